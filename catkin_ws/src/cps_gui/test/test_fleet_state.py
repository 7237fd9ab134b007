"""The latest-data store: health rows, alarms, staleness and plot histories, on a fake clock."""

import math
import threading

import pytest

from cps_fleet import names
from cps_gui.fleet_state import (
    Allocation,
    FleetState,
    ImageFrame,
    Pose,
    RateMeter,
    RobotAllocation,
    RobotMapFigures,
    TopicFigures,
)


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


@pytest.fixture
def clock():
    return FakeClock()


@pytest.fixture
def state(clock):
    return FleetState([("scout", "wheeled_lidar"), ("iris", "aerial_depth")], clock=clock, stale_after_s=2.0)


def rows(state):
    return {r.robot: r for r in state.health_rows()}


def test_no_data_is_reported_as_such(state):
    row = rows(state)["scout"]
    assert row.link_state == "no data" and row.heartbeat_stale and row.battery_stale
    assert math.isnan(row.battery_percent) and row.alarms == ()


def test_health_row_from_fresh_data(state, clock):
    state.set_pose("scout", Pose(1, 2, 0, 0.5, 0.3))
    state.set_battery("scout", 0.8)
    state.set_mode("scout", "teleop")
    state.set_mission_state("scout", "inspecting")
    state.set_map_stats([RobotMapFigures("scout", 1234, 0)])
    clock.t += 0.5
    row = rows(state)["scout"]
    assert (row.mode, row.mission_state, row.battery_percent, row.map_voxels) == ("teleop", "inspecting", 80.0, 1234)
    assert row.heartbeat_age_s == pytest.approx(0.5) and not row.heartbeat_stale and row.link_state == "ok"
    assert row.alarms == ()


def test_data_turns_stale_when_publishing_stops(state, clock):
    state.set_pose("scout", Pose(0, 0, 0, 0, 0))
    state.set_battery("scout", 0.9)
    clock.t += 2.5
    row = rows(state)["scout"]
    assert row.heartbeat_stale and row.battery_stale and row.link_state == "lost"
    assert "no heartbeat" in row.alarms
    assert state.poses()["scout"][1] is True


def test_alarms_for_low_battery_degraded_link_slow_link_and_dropped_clouds(state, clock):
    state.set_pose("iris", Pose(0, 0, 1, 0, 0))
    state.set_battery("iris", 0.1)
    state.set_allocation(Allocation(1.0, 1.2, 8.0, False, (RobotAllocation("iris", 1, 1.0, 1.2, 100.0, True),)))
    state.set_map_stats([RobotMapFigures("iris", 10, 0)])
    state.set_map_stats([RobotMapFigures("iris", 12, 3)])
    row = rows(state)["iris"]
    assert set(row.alarms) == {"battery low", "below minimum rate", "dropping clouds"}
    assert row.link_state == "degraded" and row.priority == 1 and row.clouds_dropped == 3
    clock.t += 1.0
    state.set_pose("iris", Pose(0, 0, 1, 0, 0))
    state.set_allocation(Allocation(1.0, 0.5, 8.0, True, (RobotAllocation("iris", 0, 5.0, 0.5, 50.0, False),)))
    state.set_tissue_stats(
        [TopicFigures(names.absolute(names.managed_cloud("iris")), "iris", True, 5.0, 0.5, 1500.0, 0.1)]
    )
    assert rows(state)["iris"].link_state == "slow"
    clock.t += 10.0
    state.set_pose("iris", Pose(0, 0, 1, 0, 0))
    assert "dropping clouds" not in rows(state)["iris"].alarms


def test_plot_series_from_stats_and_allocation(state, clock):
    stats = [
        TopicFigures(names.absolute(names.managed_cloud("scout")), "scout", True, 4.0, 0.6, 35.0, 0.1),
        TopicFigures(names.absolute(names.robot_topic("scout", names.ODOM)), "scout", False, 20.0, 0.01, 2.0, 0.05),
        TopicFigures(names.TF, "", False, 100.0, 0.05, math.nan, 0.0),
    ]
    state.set_tissue_stats(stats)
    state.set_allocation(Allocation(6.9, 0.6, 60.0, True, (RobotAllocation("scout", 0, 4.0, 0.6, 100.0, False),)))
    clock.t += 1.0
    state.set_tissue_stats(stats)
    per_robot, budget, stats_age = state.plot_series()
    t, bandwidth = per_robot["scout"]["bandwidth"]
    assert bandwidth == pytest.approx([0.61, 0.61]) and t[1] - t[0] == pytest.approx(1.0)
    assert per_robot["scout"]["rate"][1] == [4.0, 4.0]
    assert per_robot["scout"]["latency"][1] == [35.0, 35.0]
    assert per_robot["iris"]["bandwidth"] == ([], [])
    assert budget[1] == [6.9] and stats_age == pytest.approx(0.0)


def test_unknown_robots_are_counted_and_change_nothing(state):
    state.set_battery("tank", 0.5)
    state.set_pose("tank", Pose(0, 0, 0, 0, 0))
    assert state.ignored_messages == 2 and set(rows(state)) == {"scout", "iris"}


def test_images_keep_the_newest_frame_with_rate_and_bandwidth(state, clock):
    for i in range(11):
        state.add_image(ImageFrame("/cam", 2, 1, "rgb8", 6, bytes(6 * 1000), 0.0, clock.t))
        clock.t += 0.1
    frame, rate, mbytes, age = state.image("/cam")
    assert rate == pytest.approx(10.0) and mbytes == pytest.approx(0.06) and age == pytest.approx(0.1)
    assert state.image("/other") == (None, 0.0, 0.0, math.inf)


def test_rate_meter_forgets_old_messages():
    meter = RateMeter(window_s=1.0)
    meter.add(0.0, 100)
    meter.add(0.5, 100)
    assert meter.figures(0.6)[0] == pytest.approx(2.0)
    assert meter.figures(5.0) == (0.0, 0.0)


def test_log_keeps_the_newest_entries(clock):
    state = FleetState([], clock=clock, log_len=3)
    for i in range(5):
        state.add_log(float(i), "INFO", "/n", f"m{i}")
    version, entries = state.log_entries()
    assert version == 5 and [e[3] for e in entries] == ["m2", "m3", "m4"]


def test_concurrent_writers_and_reader(state):
    def write(name):
        for i in range(2000):
            state.set_battery(name, i / 2000.0)
            state.set_tissue_stats([TopicFigures("/t", name, True, 1.0, 1.0, 1.0, 0.0)])

    threads = [threading.Thread(target=write, args=(n,)) for n in ("scout", "iris")]
    for t in threads:
        t.start()
    for _ in range(200):
        state.health_rows()
        state.plot_series()
    for t in threads:
        t.join()
    assert rows(state)["scout"].battery_percent == pytest.approx(1999 / 20.0)


def test_stale_threshold_must_be_positive():
    with pytest.raises(ValueError, match="stale_after_s"):
        FleetState([], stale_after_s=0)


def test_link_lost_marks_every_robot_and_its_data_age_red_until_the_link_is_back(state, clock):
    state.set_pose("scout", Pose(1, 2, 0, 0.5, 0.3))
    state.set_battery("scout", 0.9)
    assert state.link_lost_text() == ""
    state.set_link_state(False, 1.5, 3, 0.0, "robots")
    clock.t += 1.0  # data still fresh by age, but from before the outage
    row = rows(state)["scout"]
    assert row.link_state == "link lost" and "link lost" in row.alarms and row.heartbeat_stale
    assert state.link_lost_text().startswith("LINK LOST to robots for 2 s (outage 3)")
    state.set_link_state(False, 9.0, 3, 0.0, "robots")  # a repeat keeps the first start
    assert "for 2 s" in state.link_lost_text()
    state.set_link_state(True, 0.0, 3, 2.5, "robots")
    state.set_pose("scout", Pose(1, 2, 0, 0.5, 0.3))
    row = rows(state)["scout"]
    assert state.link_lost_text() == "" and row.link_state == "ok" and not row.heartbeat_stale
