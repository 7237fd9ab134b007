"""Robot types as data (fleet.yaml robot_types): sensible values, file:line errors, new types."""

import pytest

from cps_fleet.config import ConfigError
from cps_fleet.fleet import ROBOT_TYPES, load_fleet
from cps_harness.fleets import NEW_TYPE, fleet_with_new_type


def test_the_default_fleet_defines_the_four_types():
    assert set(load_fleet().robot_types) == set(ROBOT_TYPES)


@pytest.mark.parametrize("robot_type", ROBOT_TYPES)
def test_limits_are_non_negative_and_every_type_drives_and_turns(robot_type):
    limits = load_fleet().robot_types[robot_type].limits
    assert limits.max_forward_mps > 0 and limits.max_yaw_rate_rps > 0
    assert limits.max_linear_accel_mps2 > 0 and limits.max_yaw_accel_rps2 > 0
    assert limits.max_lateral_mps >= 0 and limits.max_vertical_mps >= 0


def test_only_the_quadrotor_climbs():
    types = load_fleet().robot_types
    assert [name for name, t in types.items() if t.limits.can_climb] == ["aerial_depth"]


def test_sensor_frame_and_max_range_come_from_the_type():
    fleet = load_fleet()
    assert fleet.robot("scout").sensor_frame == "scout/lidar"
    assert fleet.robot("jackal").sensor_frame == "jackal/camera_depth_optical_frame"
    assert fleet.mapping.max_range_m == {
        "wheeled_lidar": 12.0,
        "wheeled_depth": 6.0,
        "legged_depth": 6.0,
        "aerial_depth": 6.0,
    }


def test_a_new_type_is_only_data(tmp_path):
    fleet = load_fleet(str(fleet_with_new_type(tmp_path)))
    scout = fleet.robot("scout")
    assert scout.type == "tracked_lidar" and scout.has_lidar
    assert scout.cloud_topic == "velodyne_points" and scout.sensor_frame == "scout/velodyne"
    assert fleet.mapping.max_range_m["tracked_lidar"] == 20.0
    assert fleet.robot_types["tracked_lidar"].limits.max_forward_mps == 1.0
    assert fleet.robot_types["tracked_lidar"].body.half_extents_m == (0.5, 0.4, 0.2)
    assert fleet.robot_types["tracked_lidar"].sensor_mount.xyz_m == (0.1, 0.0, 0.7)


@pytest.mark.parametrize(
    "key", ["base", "sensor", "cloud_topic", "sensor_frame", "max_range_m", "limits", "body", "sensor_mount"]
)
def test_a_type_missing_a_key_names_file_line_and_key(tmp_path, key):
    drop = (f"{key}:",) + (("max_linear",) if key == "limits" else ())  # limits spans two lines
    entry = "".join(line + "\n" for line in NEW_TYPE.splitlines() if not line.strip().startswith(drop))
    path = fleet_with_new_type(tmp_path, entry=entry)
    line = path.read_text().splitlines().index("  tracked_lidar:   # a user's robot: only data") + 1
    with pytest.raises(ConfigError) as error:
        load_fleet(str(path))
    assert f"{path}:{line}: robot_types.tracked_lidar: missing key '{key}'" in str(error.value)


def test_an_unknown_sensor_kind_is_refused(tmp_path):
    path = fleet_with_new_type(tmp_path, entry=NEW_TYPE.replace("sensor: lidar", "sensor: sonar"))
    with pytest.raises(
        ConfigError,
        match=r"fleet.yaml:\d+: robot_types.tracked_lidar.sensor: unknown sensor kind "
        r"'sonar' \(known: lidar, depth\)",
    ):
        load_fleet(str(path))


@pytest.mark.parametrize(
    "body, words",
    [
        ("[0.5, 0.0, 0.2]", r"body.half_extents_m: must be three positive numbers \(x, y, z\), got \[0.5, 0.0, 0.2\]"),
        ("[0.5, -0.4, 0.2]", r"body.half_extents_m: must be three positive numbers"),
        ("[0.5, 0.4]", r"body.half_extents_m: must be three positive numbers"),
        ("0.5", r"body.half_extents_m: must be a list"),
    ],
)
def test_a_body_without_three_positive_half_extents_is_refused_naming_the_file(tmp_path, body, words):
    path = fleet_with_new_type(tmp_path, entry=NEW_TYPE.replace("[0.5, 0.4, 0.2]", body))
    line = next(i for i, text in enumerate(path.read_text().splitlines(), 1) if "center_z_m: 0.3" in text)
    with pytest.raises(ConfigError, match=rf"{path}:{line}: robot_types.tracked_lidar.{words}"):
        load_fleet(str(path))


def test_a_body_missing_its_height_or_a_mount_out_of_range_is_refused(tmp_path):
    path = fleet_with_new_type(tmp_path, entry=NEW_TYPE.replace(", center_z_m: 0.3", ""))
    with pytest.raises(ConfigError, match=r"fleet.yaml:\d+: robot_types.tracked_lidar.body: missing key 'center_z_m'"):
        load_fleet(str(path))
    path = fleet_with_new_type(tmp_path / "pitch", entry=NEW_TYPE.replace("pitch_deg: 0.0", "pitch_deg: 120.0"))
    with pytest.raises(ConfigError, match=r"sensor_mount.pitch_deg: 120.0 is outside \[-90.0, 90.0\]"):
        load_fleet(str(path))
