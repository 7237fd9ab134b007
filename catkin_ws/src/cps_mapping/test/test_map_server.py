"""The map_server node: two robots with different known poses land in one map at the right
places; bad inputs (NaN, unknown frame, no transform, empty, absurd points, unknown robot,
corrupt or wrong-type map files) are counted and never cost the map; save, load, reset,
clear_bbx; a restarted server resumes from its save."""
import threading
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cps_mapping.fused_map import pack_index, voxel_index
import synthetic_scene as sc

pytestmark = pytest.mark.ros
RES = 0.1
# Sensor poses in map: (origin, rotation of the sensor frame in map).
JACKAL = (np.array([-1.0, 2.0, 0.5]), sc.rotation_z(0.0) @ sc.OPTICAL_TO_BODY)
SCOUT = (np.array([-5.0, -1.5, 0.6]), sc.rotation_z(0.0))


def _static_tf(frames):
    import rospy
    import tf2_ros
    from geometry_msgs.msg import TransformStamped

    broadcaster = tf2_ros.StaticTransformBroadcaster()
    msgs = []
    for child, (origin, rotation) in frames.items():
        t = TransformStamped()
        t.header.stamp = rospy.Time.now()
        t.header.frame_id, t.child_frame_id = "map", child
        t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = origin.tolist()
        x, y, z, w = Rotation.from_matrix(rotation).as_quat()
        t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z, t.transform.rotation.w = x, y, z, w
        msgs.append(t)
    broadcaster.sendTransform(msgs)
    return broadcaster


def _moving_tf(child, pose):
    """A transform known only at one instant (as odometry), so later stamps cannot be resolved."""
    import rospy
    import tf2_ros
    from geometry_msgs.msg import TransformStamped

    broadcaster = tf2_ros.TransformBroadcaster()
    t = TransformStamped()
    t.header.stamp = rospy.Time.now()
    t.header.frame_id, t.child_frame_id = "map", child
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = pose[0].tolist()
    t.transform.rotation.w = 1.0
    for _ in range(3):
        broadcaster.sendTransform(t)
        time.sleep(0.1)


def _cloud(points_sensor, frame, stamp=None):
    import rospy
    from std_msgs.msg import Header

    from cps_transport.pointcloud import array_to_cloud

    pts = np.asarray(points_sensor, dtype=np.float32).reshape(-1, 3)
    return array_to_cloud({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]},
                          header=Header(stamp=stamp or rospy.Time.now(), frame_id=frame))


class Latest:
    """The newest message of a topic, waited for with a predicate."""

    def __init__(self, topic, msg_type):
        import rospy

        self.msg, self.cond = None, threading.Condition()
        self.sub = rospy.Subscriber(topic, msg_type, self._cb, queue_size=1, buff_size=2 ** 26)

    def _cb(self, msg):
        with self.cond:
            self.msg = msg
            self.cond.notify_all()

    def wait(self, predicate=lambda m: True, timeout_s=20.0, what="message"):
        with self.cond:
            if not self.cond.wait_for(lambda: self.msg is not None and predicate(self.msg), timeout_s):
                raise AssertionError(f"timed out waiting for {what}; last: {self.msg}")
            return self.msg


def _stats(msg):
    return {r.robot: r for r in msg.robots}


def _centers(msg):
    from cps_transport.pointcloud import cloud_to_array, xyz_of

    return xyz_of(cloud_to_array(msg)).astype(np.float64)


@pytest.fixture(scope="module")
def scene_clouds():
    scene = sc.hall_scene()
    depth = sc.voxel_downsample(sc.depth_camera_cloud(scene, JACKAL[0], 0.0, width=320, height=240), RES)
    lidar = sc.voxel_downsample(sc.lidar_cloud(scene, SCOUT[0], 0.0), 0.01)
    return scene, sc.to_sensor_frame(depth, *JACKAL), sc.to_sensor_frame(lidar, *SCOUT)


def _start(ros, map_file, name, **extra):
    params = {"~robots": "jackal,scout,ghost", "~map_file": str(map_file), "~publish_period_s": 0.3,
              "~tf_timeout_s": 0.3, "~autosave_period_s": 0.0, "~max_points_range_m": 200.0}
    params.update({f"~{k}": v for k, v in extra.items()})
    proc = ros.start_node("cps_mapping", "map_server", name=name, params=params)
    ros.wait_for_service("/twin/clear_bbx", timeout_s=30)
    return proc


def test_map_server_end_to_end(ros, rospy_node, scene_clouds, tmp_path):
    rospy = rospy_node
    from geometry_msgs.msg import Point
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Empty

    from cps_msgs.msg import MapStats, Octomap
    from cps_msgs.srv import ClearBBX, SaveMap

    scene, depth_sensor, lidar_sensor = scene_clouds
    map_file = tmp_path / "twin.bt"
    tf_keep = _static_tf({"jackal/camera_depth_optical_frame": JACKAL, "scout/lidar": SCOUT})
    proc = _start(ros, map_file, "map_server_a")
    stats = Latest("/twin/map_stats", MapStats)
    centers = Latest("/twin/octomap_point_cloud_centers", PointCloud2)
    binary = Latest("/twin/octomap_binary", Octomap)
    pub_j = rospy.Publisher("/twin/jackal/points", PointCloud2, queue_size=5)
    pub_s = rospy.Publisher("/twin/scout/points", PointCloud2, queue_size=5)
    pub_ghost = rospy.Publisher("/twin/ghost/points", PointCloud2, queue_size=1)
    time.sleep(1.0)
    try:
        # Depth clouds carry NaN (no return) as the decoder delivers them.
        with_nan = np.vstack([depth_sensor, np.full((500, 3), np.nan)])
        pub_j.publish(_cloud(with_nan, "jackal/camera_depth_optical_frame"))
        pub_s.publish(_cloud(lidar_sensor, "scout/lidar"))
        # Stats carry the published snapshot's figures: once both robots contribute to it, the
        # centres of that snapshot (or a later one) are out.
        s = stats.wait(lambda m: all(r.clouds_inserted >= 1 and r.occupied_voxels_contributed > 0 for r in m.robots),
                       what="both robots inserted and published")
        assert set(_stats(s)) == {"jackal", "scout"}, "the unknown robot in ~robots must be ignored"
        occ_msg = centers.wait(lambda m: m.width == s.occupied_voxels, what="occupied centres after insertion")
        occupied = _centers(occ_msg)
        truth = set(pack_index(voxel_index(scene.occupied_voxels(RES), RES)).tolist())
        got = pack_index(voxel_index(occupied, RES)).tolist()
        assert sum(k in truth for k in got) / len(got) > 0.98
        for crate, robot in (("crate_a", "scout"), ("crate_b", "jackal")):
            box = next(b for b in scene.boxes if b.name == crate)
            near = np.all((occupied >= np.asarray(box.min_m) - 0.1) & (occupied <= np.asarray(box.max_m) + 0.1), axis=1)
            assert near.sum() > 20, f"{crate} ({robot}'s view) is not in the fused map"
        s = stats.wait(lambda m: all(r.occupied_voxels_contributed > 0 for r in m.robots), what="contributions")
        assert s.occupied_voxels == len(occupied)
        assert binary.wait(lambda m: len(m.data) > 0).id == "OcTree"
        before = len(occupied)

        # Bad input: every one is counted, none changes the map.
        absurd = np.vstack([depth_sensor[:50], [[1e9, 0, 0], [0, 1e30, 0]]])
        _moving_tf("scout/moving_lidar", SCOUT)
        for pub, msg in (
                (pub_j, _cloud(np.full((100, 3), np.nan), "jackal/camera_depth_optical_frame")),  # all NaN
                (pub_j, _cloud(np.zeros((0, 3)), "jackal/camera_depth_optical_frame")),           # empty
                (pub_s, _cloud(lidar_sensor[:100], "nowhere/lidar")),                             # unknown frame
                (pub_s, _cloud(lidar_sensor[:100], "scout/moving_lidar",                          # no tf at stamp
                               rospy.Time.now() + rospy.Duration(60.0))),
                (pub_j, _cloud(absurd, "jackal/camera_depth_optical_frame")),                     # absurd points
                (pub_ghost, _cloud(depth_sensor[:10], "ghost/lidar"))):                           # unknown robot
            pub.publish(msg)
            time.sleep(0.5)  # the subscriber waits up to tf_timeout_s per cloud
        s = stats.wait(lambda m: _stats(m)["jackal"].clouds_dropped_invalid >= 2 and
                       _stats(m)["scout"].clouds_dropped_tf >= 2 and _stats(m)["jackal"].clouds_inserted >= 2,
                       what="bad inputs counted")
        assert proc.poll() is None
        time.sleep(0.7)  # > 2 publish periods: the map after the absurd cloud's 50 valid points is out
        assert centers.msg.width == before, "bad input changed the map"

        # Services: save, load a bad file (refused), clear_bbx, load the save back, reset.
        save = rospy.ServiceProxy("/twin/save_map", SaveMap)
        load = rospy.ServiceProxy("/twin/load_map", SaveMap)
        saved = save(str(tmp_path / "copy.ot"))
        assert saved.success, saved.message
        (tmp_path / "corrupt.bt").write_bytes(b"# Octomap OcTree binary file\nid OcTree\nsize 99\nres 0.1\ndata\n\x01")
        (tmp_path / "color.ot").write_bytes(b"# Octomap OcTree file\nid ColorOcTree\nsize 1\nres 0.1\ndata\n")
        for bad in ("corrupt.bt", "color.ot", "missing.bt", "notamap.txt"):
            answer = load(str(tmp_path / bad))
            assert not answer.success and answer.message, bad
        time.sleep(0.7)
        assert centers.msg.width == before, "a refused load changed the map"
        crate_a = next(b for b in scene.boxes if b.name == "crate_a")
        assert rospy.ServiceProxy("/twin/clear_bbx", ClearBBX)(Point(*crate_a.min_m), Point(*crate_a.max_m)).success
        centers.wait(lambda m: m.width < before, what="clear_bbx effect")
        assert save(str(tmp_path / "without_crate_a.bt")).success
        assert load(str(tmp_path / "copy.ot")).success
        centers.wait(lambda m: m.width == before, what="the loaded map")
        assert save("").success, "empty path saves to ~map_file"
    finally:
        ros.stop(proc)
    assert map_file.exists(), "the server saves on shutdown"

    # A restarted server resumes from its save; against a baseline without crate_a, it reports
    # crate_a as the one change.
    from visualization_msgs.msg import Marker, MarkerArray

    changes = Latest("/twin/map_changes", MarkerArray)
    proc = _start(ros, map_file, "map_server_b", baseline_map=str(tmp_path / "without_crate_a.bt"),
                  change_period_s=1.0, change_report=str(tmp_path / "changes.md"))
    try:
        resumed = centers.wait(lambda m: m.header.stamp > occ_msg.header.stamp and m.width > 0, what="resumed map")
        assert resumed.width == before
        boxes = [m for m in changes.wait(what="map changes").markers if m.type == Marker.CUBE]
        assert len(boxes) == 1 and boxes[0].color.g > boxes[0].color.r, "crate_a must be the one appeared change"
        crate_a = next(b for b in scene.boxes if b.name == "crate_a")
        assert crate_a.min_m[0] - 0.2 < boxes[0].pose.position.x < crate_a.max_m[0] + 0.2
        assert "appeared" in (tmp_path / "changes.md").read_text()
        rospy.ServiceProxy("/twin/reset", Empty)()
        centers.wait(lambda m: m.width == 0, what="reset")
    finally:
        ros.stop(proc)
        for sub in (stats, centers, binary, changes):
            sub.sub.unregister()
        for pub in (pub_j, pub_s, pub_ghost):
            pub.unregister()
    assert "not mapped" in ros.output("map_server_a") or "ghost" in ros.output("map_server_a")
