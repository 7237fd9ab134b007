"""The map server's insertion budget and the InsertCapacity it publishes, measured in the insertion
thread's CPU time; the map's snapshots and saves are built outside the map lock."""

import time

import genpy
import numpy as np
import pytest
import test_map_server_library as library
from test_map_server_library import _cloud, _server

from cps_mapping.insert_capacity import InsertionBudget, InsertionMeter
from cps_msgs.srv import SaveMapRequest


@pytest.fixture(scope="module")
def jackal_points():
    return library.jackal_points.__wrapped__()


def _stamped(points, secs):
    msg = _cloud(points)
    msg.header.stamp = genpy.Time(secs, 0)
    return msg


def test_a_newer_cloud_supersedes_the_waiting_one_and_the_capacity_counts_the_insertion(jackal_points):
    """Three clouds of jackal wait as one (the newest), two are superseded, none is lost; the
    capacity message counts the insertion, its points and voxel updates, in CPU seconds."""
    server, published = _server(robots=("jackal",))
    for secs in (100, 101, 102):
        server.receive_cloud("jackal", _stamped(jackal_points, secs))
    assert server.waiting("jackal") == 1
    assert server.insert_pending(timeout_s=0) == 1
    c = server.robot_counters("jackal")
    assert (c.clouds_received, c.clouds_inserted, c.clouds_superseded, c.clouds_dropped_queue) == (3, 1, 2, 0)
    assert c.newest_inserted_stamp_s == 102.0
    server.publish_capacity(genpy.Time(200, 0))
    (capacity,) = published["capacity"]
    assert (capacity.clouds_inserted, capacity.superseded, capacity.dropped) == (1, 2, 0)
    assert capacity.busy_s > 0 and capacity.window_s == server.options.capacity_window_s
    budget = server.options.insertion_budget_fraction
    assert capacity.clouds_per_s == pytest.approx(budget / capacity.busy_s)
    assert capacity.points_per_s == pytest.approx(budget * c.points_inserted / capacity.busy_s)
    # Every inserted point walks at least its own voxel.
    assert capacity.voxel_updates_per_s >= capacity.points_per_s > 0


def test_the_capacity_is_cpu_time_waiting_is_not_work(jackal_points):
    """A transform lookup that sleeps (as a waiting thread does for the GIL, the core or tf) costs
    wall time, not CPU: the busy time and so the capacity do not count it."""
    wait_s = 0.3

    def slow_transform(frame, stamp):
        time.sleep(wait_s)
        return library._transform_of(frame, stamp)

    server, published = _server(robots=("jackal",))
    server.admission.transform_of = slow_transform
    server.receive_cloud("jackal", _stamped(jackal_points, 100))
    wall_start = time.perf_counter()
    assert server.insert_pending(timeout_s=0) == 1
    assert time.perf_counter() - wall_start >= wait_s
    server.publish_capacity(genpy.Time(200, 0))
    (capacity,) = published["capacity"]
    assert 0 < capacity.busy_s < wait_s / 2, capacity.busy_s
    assert server.robot_counters("jackal").insertion_ms_max < wait_s / 2 * 1e3


def test_lost_clouds_are_counted_as_dropped_not_superseded(jackal_points):
    server, published = _server(tf_timeout_s=0.0)
    server.receive_cloud("scout", _cloud(jackal_points, frame="scout/lidar"))  # no transform: lost
    server.insert_pending(timeout_s=0)
    server.receive_cloud("jackal", _cloud(np.full((10, 3), np.nan)))  # placed, then refused by the insertion
    server.insert_pending(timeout_s=0)
    server.publish_capacity(genpy.Time(200, 0))
    assert (published["capacity"][0].dropped, published["capacity"][0].superseded) == (2, 0)
    assert published["capacity"][0].busy_s > 0, "what a cloud the insertion refused cost counts in the busy time"


def test_the_meter_forgets_what_left_its_window():
    now = [0.0]
    superseded = [0]
    meter = InsertionMeter(window_s=10.0, budget_fraction=0.5, clock=lambda: now[0], totals=lambda: (superseded[0], 0))
    meter.inserted(clouds=2, points=1000, voxel_updates=50_000, cpu_s=0.08)
    meter.spent(0.02)  # a cloud that could not be inserted
    superseded[0] = 3
    now[0] = 1.0
    figures = meter.figures()
    assert figures["clouds_per_s"] == pytest.approx(10.0) and figures["voxel_updates_per_s"] == pytest.approx(250_000)
    assert figures["superseded"] == 3 and figures["busy_s"] == pytest.approx(0.1)
    now[0] = 11.5  # the insertions at 0 s and the supersessions seen at 1 s are older than the window
    assert meter.figures()["clouds_inserted"] == 0 and meter.figures()["clouds_per_s"] == 0.0
    assert meter.figures()["superseded"] == 0


def test_snapshots_and_saves_are_built_outside_the_map_lock(jackal_points, tmp_path, monkeypatch):
    """Only the copy is taken under the lock: while the map message and the saved file are being
    written, the insertion can take the lock."""
    import threading

    from cps_mapping import map_server
    from cps_mapping.fused_map import FusedLogOddsMap

    server, published = _server(tmp_path, robots=("jackal",))
    server.receive_cloud("jackal", _stamped(jackal_points, 100))
    server.insert_pending(timeout_s=0)
    lock_free = []

    def probe():
        lock_free.append(server._map_lock.acquire(timeout=5.0))
        if lock_free[-1]:
            server._map_lock.release()

    real_fields, real_save = map_server.message_fields, FusedLogOddsMap.save

    def fields_probing(fused, binary=True):
        thread = threading.Thread(target=probe)
        thread.start()
        thread.join()
        return real_fields(fused, binary)

    def save_probing(fused, path):
        probe()
        return real_save(fused, path)

    monkeypatch.setattr(map_server, "message_fields", fields_probing)
    monkeypatch.setattr(FusedLogOddsMap, "save", save_probing)
    server.publish_map(genpy.Time(101, 0))
    assert server.on_save(SaveMapRequest(path="")).success
    assert len(lock_free) == 3 and all(lock_free) and len(published["octomap"]) == 1  # binary, full, save


def test_the_budget_pauses_the_insertion_for_the_rest_of_its_cycle():
    now = [0.0]
    budget = InsertionBudget(0.8, cycle_s=1.0, clock=lambda: now[0])
    assert budget.wait_s() == 0.0
    now[0] = 0.5
    budget.spend(0.5)  # 0.5 s of 0.8 s spent in the cycle that began at 0.0
    assert budget.wait_s() == 0.0
    now[0] = 0.85
    budget.spend(0.35)
    assert budget.wait_s() == pytest.approx(0.15)
    now[0] = 1.0
    assert budget.wait_s() == 0.0
    with pytest.raises(ValueError):
        InsertionBudget(1.5)


def test_voxel_updates_count_the_ray_casters_steps():
    import numpy as np

    from cps_fleet.fleet import load_fleet
    from cps_mapping.fused_map import FusedLogOddsMap
    from cps_mapping.insert_capacity import voxel_updates_of

    fused = FusedLogOddsMap.from_mapping_config(load_fleet().mapping)
    assert voxel_updates_of(fused) == 0
    fused.insert_cloud(np.array([[2.0, 0.0, 1.0]]), np.array([0.0, 0.0, 1.0]))
    walked = voxel_updates_of(fused)
    resolution = load_fleet().mapping.resolution_m
    assert 2.0 / resolution - 2 <= walked <= 2.0 / resolution + 2  # one ray of 2 m, a step per voxel
    assert voxel_updates_of(object()) is None  # a map that does not count them
