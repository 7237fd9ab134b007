"""Robots are not the site: the robots' sensor poses are kept, saved beside the map and read back;
the volume their bodies swept holds the voxels a body leaves in a map, and change detection skips
it; a change must persist two detection cycles and is withdrawn when contradicted."""

import json
import types

import numpy as np
import pytest

from cps_fleet import names
from cps_fleet.fleet import load_fleet
from cps_mapping.baseline import BaselineError, read_map_trails, write_map_metadata
from cps_mapping.change_detection import detect_changes
from cps_mapping.change_tracking import ChangeTracker
from cps_mapping.fused_map import voxel_index
from cps_mapping.robot_bodies import RobotTrails, SweptVolume, fleet_bodies

RES = 0.1


@pytest.fixture(scope="module")
def fleet():
    return load_fleet()


def _sensor_pose(fleet, robot, x, y, yaw):
    """The sensor's (rotation, translation) in map for the robot's base at (x, y, yaw), as the
    simulator mounts it (cps_sim.robots)."""
    from cps_sim.robots import Robot

    r = fleet.robot(robot)
    sim = Robot(r.name, fleet.robot_types[r.type], r.initial_pose)
    sim.set_pose(x, y, 0.0, yaw)
    m = sim.sensor_in_map()
    return m[:3, :3], m[:3, 3]


def _body_voxels(fleet, robot, x, y, yaw):
    """The voxels of the body box of `robot` (its type's, as the simulator builds it) at that pose
    (its surface as a map holds it)."""
    body = fleet.robot(robot).robot_type.body
    hx, hy, hz = body.half_extents_m
    g = np.stack(np.meshgrid(*(np.linspace(-h, h, 9) for h in (hx, hy, hz)), indexing="ij"), -1).reshape(-1, 3)
    c, s = np.cos(yaw), np.sin(yaw)
    world = g @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) + [x, y, body.center_z_m]
    return np.unique(voxel_index(world, RES), axis=0)


def test_swept_volume_holds_every_robots_body(fleet):
    robots = ("scout", "champ", "iris")
    trails = RobotTrails(fleet_bodies(fleet, robots))
    for robot in robots:
        for k in range(20):  # a short drive, turning
            trails.record(robot, float(k), *_sensor_pose(fleet, robot, 1.0 + 0.1 * k, -2.0, 0.05 * k))
    swept = SweptVolume(RES).add(trails)
    for robot in robots:
        body = _body_voxels(fleet, robot, 1.5, -2.0, 0.25)
        assert swept.contains(body).all(), robot
    assert not swept.contains(voxel_index(np.array([[1.5, 0.0, 0.5], [5.0, -2.0, 0.3]]), RES)).any()


def test_poses_are_thinned_saved_with_the_map_and_read_back(tmp_path, fleet):
    trails = RobotTrails(fleet_bodies(fleet, ("champ",)))
    rotation, translation = _sensor_pose(fleet, "champ", 0.0, 0.0, 0.0)
    kept = [trails.record("champ", 0.1 * k, rotation, translation + [0.011 * k, 0, 0]) for k in range(11)]
    assert sum(kept) == 3, "one kept every 0.05 m"
    assert not trails.record("nobody", 0.0, rotation, translation)
    path = str(tmp_path / "map.bt")
    write_map_metadata(path, names.MAP_FRAME, RES, trails)
    back = read_map_trails(path)
    assert back.pose_count() == 3 and back.trails["champ"].body == trails.trails["champ"].body
    np.testing.assert_allclose(back.trails["champ"].poses[-1], trails.trails["champ"].poses[-1], atol=1e-5)
    write_map_metadata(path, names.MAP_FRAME, RES)  # a map saved without poses: usable, and says so
    assert read_map_trails(path) is None
    assert read_map_trails(str(tmp_path / "none.bt")) is None
    doc = json.load(open(path + ".json"))
    doc["robot_poses"] = {"champ": {"body": {"robot_type": "x"}, "poses": []}}
    json.dump(doc, open(path + ".json", "w"))
    with pytest.raises(BaselineError, match="unreadable robot poses"):
        read_map_trails(path)


def test_a_robot_in_the_baseline_is_no_change(fleet):
    floor = np.stack(np.meshgrid(np.arange(-20, 40), np.arange(-50, 0), [0], indexing="ij"), -1).reshape(-1, 3)
    floor_m = (floor + 0.5) * RES
    robot_m = (_body_voxels(fleet, "champ", 1.3, -3.5, 0.0) + 0.5) * RES
    baseline = np.vstack([floor_m, robot_m])
    assert [c.kind for c in detect_changes(baseline, floor_m, RES)] == ["disappeared"]
    trails = RobotTrails(fleet_bodies(fleet, ("champ",)))
    trails.record("champ", 0.0, *_sensor_pose(fleet, "champ", 1.3, -3.5, 0.0))
    swept = SweptVolume(RES).add(trails)
    assert detect_changes(baseline, floor_m, RES, excluded=swept.contains) == []


def _change(kind, x):
    return types.SimpleNamespace(kind=kind, min_m=(x - 0.5, 0.0, 0.0), max_m=(x + 0.5, 1.0, 1.0))


def test_a_change_is_reported_after_two_cycles_and_withdrawn_when_contradicted():
    tracker = ChangeTracker()
    assert tracker.update([_change("appeared", 1.0)], 5.0) == []
    reported = tracker.update([_change("appeared", 1.2), _change("disappeared", 4.0)], 10.0)
    assert [(t.change.kind, t.first_seen_s, t.reported_s) for t in reported] == [("appeared", 5.0, 10.0)]
    assert tracker.update([_change("disappeared", 4.1)], 15.0)[0].change.kind == "disappeared"
    assert [t.change.kind for t in tracker.withdrawn] == ["appeared"]
    assert tracker.update([_change("appeared", 1.0)], 20.0) == [], "withdrawn: it starts over"
