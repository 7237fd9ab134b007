"""ManagerCore with fleet.yaml's stream levels: the operator's selection and teleop, inspection
detail, per-level sizes from the encoders, the twin's insertion capacity and the CSV rows."""

import dataclasses
import math

import pytest

from cps_bw_manager.manager import (
    ALLOCATION_CSV_COLUMNS,
    INSERT_CAPACITY_HOLD_S,
    ManagerCore,
    ManagerSettings,
    allocation_csv_rows,
)
from cps_fleet.fleet import load_fleet

FLEET = load_fleet()
STREAMS = FLEET.streams
CAMERAS = [r.name for r in FLEET.robots if r.has_depth_camera]
ROBOTS = FLEET.robot_names
SETTINGS = ManagerSettings(available_mbps=4.0, reserve_fraction=0.04, min_rate_hz=1.0, max_rate_hz=30.0)


def _core(settings=SETTINGS):
    return ManagerCore(ROBOTS, settings, streams=STREAMS, camera_robots=CAMERAS)


def _by(result):
    return {(a.robot, a.stream): a for a in result.streams}


def _operator_quality(a):
    return a.level <= STREAMS.operator_video_level and a.rate_hz >= STREAMS.operator_video_rate_hz - 1e-9


def test_the_fleets_camera_robots_have_a_video_and_every_robot_a_cloud():
    result = _core().allocate_streams(now_s=0.0)
    keys = {(a.robot, a.stream) for a in result.streams}
    assert keys == {(r, "cloud") for r in ROBOTS} | {(r, "video") for r in CAMERAS}
    assert "scout" not in CAMERAS and CAMERAS  # the lidar robot has no camera


def test_selecting_a_robot_gives_it_operator_video_and_selecting_another_moves_it():
    core = _core()
    before = _by(core.allocate_streams(now_s=0.0))
    assert not any(_operator_quality(before[(r, "video")]) for r in CAMERAS)
    assert core.on_selected_robot("jackal")
    after = _by(core.allocate_streams(now_s=0.0))
    assert _operator_quality(after[("jackal", "video")])
    assert after[("jackal", "video")].guarantee_kept
    assert core.on_selected_robot("iris")
    moved = _by(core.allocate_streams(now_s=0.0))
    assert _operator_quality(moved[("iris", "video")]) and not moved[("jackal", "video")].guarantee_kept
    assert not core.on_selected_robot("iris")  # unchanged
    assert core.on_selected_robot("")  # none selected
    assert not core.on_selected_robot("scout")  # no camera: nothing to raise


def test_a_robot_in_teleop_gets_operator_video_too():
    # 5 Mbit/s: two operator videos (2 x 320x240 x 15 Hz at the priors) beside every cloud's floor;
    # at 4 Mbit/s they no longer fit with the clouds' measured priors and the second is degraded.
    core = _core(dataclasses.replace(SETTINGS, available_mbps=5.0))
    core.on_selected_robot("jackal")
    assert core.on_control_mode("champ", "teleop")
    result = _by(core.allocate_streams(now_s=0.0))
    assert _operator_quality(result[("champ", "video")]) and _operator_quality(result[("jackal", "video")])
    assert core.on_control_mode("champ", "auto")
    assert not _by(core.allocate_streams(now_s=0.0))[("champ", "video")].guarantee_kept
    with pytest.raises(KeyError):
        core.on_control_mode("nobody", "teleop")


def test_an_inspecting_robot_gets_the_finest_leaf_and_the_others_keep_their_floor():
    core = _core()
    core.on_mission_state("champ", "inspecting")
    result = _by(core.allocate_streams(now_s=0.0))
    assert result[("champ", "cloud")].level == 0 and result[("champ", "cloud")].guarantee_kept
    assert all(result[(r, "cloud")].rate_hz >= 1.0 for r in ROBOTS)


def test_budget_held_at_every_level_the_encoders_report_and_a_tenfold_jump_is_held_at_the_next_allocation():
    core = _core(dataclasses.replace(SETTINGS, headroom_messages=0.0))
    core.on_selected_robot("jackal")
    first = core.allocate_streams(now_s=0.0)
    for a in first.streams:  # the encoders follow and report sizes at the priors
        if a.stream == "cloud":
            core.on_limiter_status(
                a.robot, a.message_bytes, 10.0, now_s=0.5, level=a.level, level_mean_message_bytes=a.message_bytes
            )
        else:
            core.on_video_status(a.robot, a.level, a.message_bytes, now_s=0.5)
    # The scene changes: every cloud ten times larger at the level in force.
    truth = {}
    changed = False
    for r in ROBOTS:
        level = core.level_in_force[(r, "cloud")]
        truth[r] = [10 * s for s in core.sizes[(r, "cloud")].estimate(0.5)]
        size = truth[r][level]
        changed |= core.on_limiter_status(r, size, 10.0, now_s=1.0, level=level, level_mean_message_bytes=size)
    assert changed  # the node re-allocates at once
    after = core.allocate_streams(now_s=1.0)
    used = sum(
        a.rate_hz * (truth[a.robot][a.level] if a.stream == "cloud" else a.message_bytes) / 1e6 for a in after.streams
    )
    assert used <= after.budget_mbytes_per_s * (1 + 1e-9)


def test_a_lower_insertion_capacity_lowers_the_clouds_rates_and_a_silent_map_server_no_longer_bounds_them():
    core = _core(dataclasses.replace(SETTINGS, available_mbps=60.0))
    free = sum(a.rate_hz for a in core.allocate_streams(now_s=0.0).streams if a.stream == "cloud")
    assert core.on_insert_capacity(8.0, now_s=0.0)
    held = sum(a.rate_hz for a in core.allocate_streams(now_s=0.0).streams if a.stream == "cloud")
    assert held == pytest.approx(8.0) and free > 8.0
    assert not core.on_insert_capacity(8.2, now_s=1.0)  # < 10 %
    assert core.insert_capacity_clouds_per_s(1.0 + INSERT_CAPACITY_HOLD_S + 0.1) is None
    later = core.allocate_streams(now_s=1.0 + INSERT_CAPACITY_HOLD_S + 0.1)
    assert sum(a.rate_hz for a in later.streams if a.stream == "cloud") == pytest.approx(free)
    for bad in (-1.0, math.inf):
        with pytest.raises(ValueError, match="not a capacity"):
            core.on_insert_capacity(bad, now_s=2.0)


def test_bad_video_and_level_reports_are_refused_and_counted():
    core = _core()
    with pytest.raises(KeyError, match="no managed video"):
        core.on_video_status("scout", 0, 1000.0, now_s=0.0)
    with pytest.raises(ValueError, match="outside the 3 levels"):
        core.on_video_status("jackal", 7, 1000.0, now_s=0.0)
    with pytest.raises(ValueError, match="not a size"):
        core.on_video_status("jackal", 0, -4.0, now_s=0.0)
    with pytest.raises(ValueError, match="outside the 3 levels"):
        core.on_limiter_status("scout", 1000.0, 10.0, now_s=0.0, level=3, level_mean_message_bytes=1000.0)
    assert core.invalid_inputs == 3  # the unknown robot is a KeyError, as for the clouds


def test_csv_rows_per_stream_with_the_level():
    core = _core()
    core.on_selected_robot("jackal")
    result = core.allocate_streams(now_s=0.0)
    rows = allocation_csv_rows(3.0, 4.0, result, {r: "idle" for r in ROBOTS})
    assert all(len(row) == len(ALLOCATION_CSV_COLUMNS) for row in rows)
    column = ALLOCATION_CSV_COLUMNS.index
    jackal_video = next(r for r in rows if r[column("robot")] == "jackal" and r[column("stream")] == "video")
    assert jackal_video[column("level_name")] in [lvl.name for lvl in STREAMS.video_levels]
    assert len(rows) == len(ROBOTS) + len(CAMERAS)
