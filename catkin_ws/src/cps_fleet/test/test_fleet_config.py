"""fleet.yaml and route files: the shipped ones load; broken ones fail naming file, line and problem."""

import os
import shutil

import pytest

from cps_fleet.config import ConfigError
from cps_fleet.fleet import ROBOT_TYPES, default_fleet_path, load_fleet, load_route, robot_names_arg


def test_shipped_fleet_loads_with_four_robots_and_both_profiles():
    fleet = load_fleet()
    assert fleet.robot_names == ["scout", "jackal", "champ", "iris"]
    assert [r.type for r in fleet.robots] == list(ROBOT_TYPES)
    assert set(fleet.profiles) >= {"paper", "light"}
    paper = fleet.with_profile("paper").profile
    assert (paper.depth_camera.width, paper.depth_camera.height, paper.depth_camera.rate_hz) == (640, 480, 30.0)
    assert (paper.lidar.rings, paper.lidar.samples_per_ring, paper.lidar.rate_hz) == (16, 1875, 10.0)
    assert fleet.link.budget_mbytes_per_s == pytest.approx(0.96 * 60 / 8)
    for robot in fleet.robots:
        assert fleet.route(robot.name).waypoints


@pytest.fixture
def fleet_copy(tmp_path):
    """A copy of the shipped fleet.yaml (with its routes) that a test may break."""
    source = default_fleet_path()
    config_dir = tmp_path / "config"
    shutil.copytree(os.path.dirname(source), config_dir)
    path = config_dir / "fleet.yaml"
    text = path.read_text()
    # The site path is relative to the original location; point it back there.
    site = os.path.normpath(os.path.join(os.path.dirname(source), "../../cps_sim/config/hall.yaml"))
    path.write_text(text.replace("site: ../../cps_sim/config/hall.yaml", f"site: {site}"))
    return path


def _line_of(path, needle):
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if needle in line:
            return number
    raise AssertionError(needle)


@pytest.mark.parametrize(
    "old,new,message",
    [
        ("type: legged_depth", "type: tank", "unknown robot type 'tank' (known: wheeled_lidar, wheeled_depth"),
        ("voxel_leaf_m: 0.01", "voxel_leaf_m: -1", "voxel_leaf_m: -1.0 is outside (0.0, 10.0]"),
        ("available_mbps: 60.0", "available_mbps: 0", "available_mbps: 0.0 is outside (0.0"),
        ("reserve_fraction: 0.04", "reserve_fraction: 1.5", "reserve_fraction: 1.5 is outside [0.0, 0.99]"),
        ("min_rate_hz: 1.0", "min_rate_hz: 40.0", "min_rate_hz (40.0) > max_rate_hz (30.0)"),
        ("route: routes/route3.yaml", "route: routes/nowhere.yaml", "does not exist"),
        ("name: jackal", "name: scout", "robot 'scout' is listed twice"),
        ("profile: light", "profile: fast", "unknown profile 'fast'"),
        ("resolution_m: 0.1", "resolution_m: .nan", "must be finite"),
        ("trajectory_max_points: 2000", "trajectory_max_points: 1", "must be at least 2"),
        ("csv_max_mbytes: 50.0", "csv_max_mbytes: 0", "csv_max_mbytes: 0.0 is outside [0.001"),
        ("node_log_max_mbytes: 20.0", "node_log_max_mbytes: -5", "node_log_max_mbytes: -5.0 is outside"),
        (
            "restart_backoff_max_s: 30.0",
            "restart_backoff_max_s: 0.1",
            "restart_backoff_max_s (0.1) < restart_backoff_s",
        ),
        ("restart_window_s: 300.0", "restart_window_s: 0", "restart_window_s: 0.0 is outside (0.0"),
        (
            "autosave_period_s: 10.0",
            "autosave_periode_s: 10.0",
            "mapping.autosave_periode_s: unknown key 'autosave_periode_s' (did you mean 'autosave_period_s'?)",
        ),
        ("link:", "links:", "links: unknown key 'links' (did you mean 'link'?)"),
        ("voxel_leaf_m: 0.01", "voxel_leaf: 0.01", "robots[0].voxel_leaf: unknown key 'voxel_leaf'"),
        ("yaw_deg: 90.0}", "yaw: 90.0}", "robots[0].initial_pose.yaw: unknown key 'yaw'"),
        ("hfov_deg: 60.0}", "hfov_deg: 60.0, fps: 30}", "profiles.paper.depth_camera.fps: unknown key 'fps'"),
        ("{hit: 0.7, miss: 0.4,", "{hti: 0.7, miss: 0.4,", "sensor_model.hti: unknown key 'hti' (did you mean 'hit'?)"),
        ("min: 0.12, max: 0.97}", "min: 0.12, max: 0.10}", "sensor_model.max: 0.1 is outside (0.5, 1.0]"),
        ("min: 0.12, max: 0.97}", "min: 0.7, max: 0.97}", "sensor_model.min: 0.7 is outside (0.0, 0.5]"),
        ("{hit: 0.7, miss: 0.4,", "{hit: 1.0, miss: 0.4,", "sensor_model.hit: 1.0 must be below 1.0"),
        ("{hit: 0.7, miss: 0.4,", "{hit: 0.7, miss: 0.5,", "sensor_model.miss: 0.5 must be below 0.5"),
        ("voxel_leaf_m: 0.20, bytes_prior", "voxel_leaf_m: 0.08, bytes_prior", "levels go from finest to coarsest"),
        (
            "voxel_leaf_m: 0.05, bytes_prior",
            "voxel_leaf_m: 0.01, bytes_prior",
            "leaf 0.01 m is finer than what robot type aerial_depth's depth resolves at 3 m, half its max_range_m "
            "(0.020 m",
        ),
        ("{name: 160x120, width: 160,", "{name: 160x120, width: 1600,", "levels go from finest to coarsest"),
        ("jpeg_quality: 90,", "jpeg_quality: 101,", "jpeg_quality: 101.0 is outside [1, 100]"),
        ("bytes_prior: 11000}", "bytes_prior: 0}", "bytes_prior: 0.0 is outside (0.0"),
        ("operator_video_level: 1", "operator_video_level: 3", "there are 3 video levels"),
        ("operator_video_rate_hz: 15.0", "operator_video_rate_hz: 45.0", "must lie within"),
    ],
)
def test_broken_fleet_file_names_file_line_and_problem(fleet_copy, old, new, message):
    line = _line_of(fleet_copy, old)
    fleet_copy.write_text(fleet_copy.read_text().replace(old, new, 1))
    with pytest.raises(ConfigError) as info:
        load_fleet(str(fleet_copy))
    text = str(info.value)
    assert message in text
    assert f"{fleet_copy}:{line}:" in text


def test_yaml_syntax_error_names_the_line(tmp_path):
    path = tmp_path / "route.yaml"
    path.write_text("waypoints:\n  - {x: 1, y: 2}\n  - {x: 3, y: [\n")
    with pytest.raises(ConfigError, match=r"route.yaml:\d+: YAML syntax error"):
        load_route(str(path))


def test_route_waypoint_needs_numbers(tmp_path):
    path = tmp_path / "route.yaml"
    path.write_text("waypoints:\n  - {x: 1, y: 2}\n  - {x: one, y: 2}\n")
    with pytest.raises(ConfigError, match=r"route.yaml:3: waypoints\[1\]\.x: must be a number, got 'one'"):
        load_route(str(path))


def test_missing_file_and_empty_route(tmp_path):
    with pytest.raises(ConfigError, match="cannot read file"):
        load_fleet(str(tmp_path / "absent.yaml"))
    path = tmp_path / "route.yaml"
    path.write_text("waypoints: []\n")
    with pytest.raises(ConfigError, match="at least one waypoint"):
        load_route(str(path))


def test_robot_subset_keeps_order_and_rejects_unknown_names():
    fleet = load_fleet()
    assert robot_names_arg(fleet, ["iris", "scout"]).robot_names == ["iris", "scout"]
    with pytest.raises(ValueError, match="unknown robot\\(s\\) tank; the fleet has scout, jackal, champ, iris"):
        robot_names_arg(fleet, ["scout", "tank"])


def test_an_unknown_key_in_a_route_or_the_site_names_file_line_and_key(tmp_path):
    from cps_fleet.site import load_site

    path = tmp_path / "route.yaml"
    path.write_text("waypoints:\n  - {x: 1, y: 2}\n  - {x: 3, y: 2, inspcet: true}\n")
    with pytest.raises(
        ConfigError,
        match=r"route.yaml:3: waypoints\[1\]\.inspcet: unknown key 'inspcet' "
        r"\(did you mean 'inspect'\?\)",
    ):
        load_route(str(path))
    path.write_text("waypoints:\n  - {x: 1, y: 2}\nloop: true\n")
    with pytest.raises(ConfigError, match=r"route.yaml:3: loop: unknown key 'loop'"):
        load_route(str(path))
    site = tmp_path / "hall.yaml"
    text = open(load_fleet().site_path).read()
    site.write_text(text.replace("  post_size_m: 0.06", "  post_size_m: 0.06\n  post_colour: [1, 0, 0]"))
    line = _line_of(site, "post_colour")
    with pytest.raises(ConfigError, match=rf"hall.yaml:{line}: fence.post_colour: unknown key 'post_colour'"):
        load_site(str(site))
    site.write_text(text.replace("radius_m: 0.8, height_m: 2.5,", "radius_m: 0.8, height_m: 2.5, size_x_m: 1.0,"))
    with pytest.raises(ConfigError, match=r"equipment\[0\]\.size_x_m: unknown key 'size_x_m'"):
        load_site(str(site))
