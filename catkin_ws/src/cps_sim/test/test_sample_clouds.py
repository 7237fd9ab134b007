"""The sample clouds other packages benchmark with have the layouts the contract fixes."""

import numpy as np

from cps_fleet.fleet import load_fleet
from cps_sim.messages import cloud_to_array
from cps_sim.sample_clouds import render_mission_clouds, render_sample_frames


def test_sample_clouds_have_the_sensor_layouts():
    frames = render_sample_frames("paper")
    assert set(frames) == {"scout", "jackal", "champ", "iris"}
    for name in ("jackal", "champ", "iris"):
        cloud = frames[name].cloud
        assert (cloud.height, cloud.width, cloud.point_step) == (480, 640, 32)
        assert [f.name for f in cloud.fields] == ["x", "y", "z", "rgb"]
        assert cloud.header.frame_id == f"{name}/camera_depth_optical_frame"
        assert not cloud.is_dense
        points = cloud_to_array(cloud)
        valid = np.isfinite(points["z"])
        assert 0.3 < valid.mean() <= 1.0, name
        assert np.all(points["z"][valid] >= 0.05) and np.all(points["z"][valid] <= 18.0)
        assert frames[name].sensor_pose_in_map.shape == (4, 4)
    scan = frames["scout"].cloud
    assert scan.height == 1 and scan.header.frame_id == "scout/lidar"
    assert [f.name for f in scan.fields] == ["x", "y", "z", "intensity", "ring", "time"]
    points = cloud_to_array(scan)
    assert 10000 < len(points) <= 16 * 1875
    assert set(np.unique(points["ring"])) <= set(range(16))
    assert np.all(np.isfinite(points["x"]))


def test_mission_clouds_follow_the_route():
    clouds = render_mission_clouds("light", robots=["jackal"], frames_per_robot=3)
    poses = [s.sensor_pose_in_map[:3, 3] for s in clouds["jackal"]]
    assert len(poses) == 3
    assert np.linalg.norm(poses[0] - poses[2]) > 1.0
    assert clouds["jackal"][0].cloud.width == load_fleet(profile="light").profile.depth_camera.width
