"""The map server's robot slots (newest cloud wins, served round-robin), its insertion budget and
the InsertCapacity it publishes, measured from its own insertions."""

import genpy
import pytest
import test_map_server_library as library
from test_map_server_library import _cloud, _server

from cps_mapping.insert_capacity import InsertionBudget, InsertionMeter


@pytest.fixture(scope="module")
def jackal_points():
    return library.jackal_points.__wrapped__()


def _stamped(points, secs):
    msg = _cloud(points)
    msg.header.stamp = genpy.Time(secs, 0)
    return msg


def test_a_newer_cloud_supersedes_the_waiting_one_and_robots_take_turns(jackal_points):
    """Default slot of 1: three clouds of jackal wait as one (the newest), two are superseded, none
    is lost; the capacity message counts the insertion, its points and voxel updates."""
    server, published = _server(robots=("jackal",))
    for secs in (100, 101, 102):
        server.receive_cloud("jackal", _stamped(jackal_points, secs))
    assert server.queues.length("jackal") == 1
    assert server.insert_pending(timeout_s=0) == 1
    c = server.counters["jackal"]
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


def test_lost_clouds_are_counted_as_dropped_not_superseded(jackal_points):
    server, published = _server()
    server.receive_cloud("scout", _cloud(jackal_points, frame="scout/lidar"))  # no transform: lost
    server.publish_capacity(genpy.Time(200, 0))
    assert (published["capacity"][0].dropped, published["capacity"][0].superseded) == (1, 0)


def test_the_meter_forgets_what_left_its_window():
    now = [0.0]
    meter = InsertionMeter(window_s=10.0, budget_fraction=0.5, clock=lambda: now[0])
    meter.inserted(clouds=2, points=1000, voxel_updates=50_000, seconds=0.1)
    meter.superseded(3)
    figures = meter.figures()
    assert figures["clouds_per_s"] == pytest.approx(10.0) and figures["voxel_updates_per_s"] == pytest.approx(250_000)
    assert figures["superseded"] == 3
    now[0] = 10.5
    assert meter.figures()["clouds_inserted"] == 0 and meter.figures()["clouds_per_s"] == 0.0


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
