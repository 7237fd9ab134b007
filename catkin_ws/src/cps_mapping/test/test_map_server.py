"""The map_server node end to end: two robots' managed (Draco) clouds with different known poses
land in one map at the right places, and each inserted cloud comes out decoded on <r>/points; bad
inputs (a corrupt payload, unknown frame, no transform, absurd points, unknown robot, corrupt or
wrong-type map files) are counted by cause and never cost the map; save, load, reset, clear_bbx; a
restarted server resumes from its save. The tests share one running server, in order."""

import re
import time
import types

import numpy as np
import pytest
import synthetic_scene as sc
from fleet_model import new_map
from scipy.spatial.transform import Rotation

from cps_fleet import names
from cps_harness.testing import TopicRecorder, wait_for
from cps_mapping.fused_map import pack_index, voxel_index

pytestmark = [pytest.mark.ros, pytest.mark.waiting]
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
        t.header.frame_id, t.child_frame_id = names.MAP_FRAME, child
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
    t.header.frame_id, t.child_frame_id = names.MAP_FRAME, child
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
    return array_to_cloud(
        {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}, header=Header(stamp=stamp or rospy.Time.now(), frame_id=frame)
    )


def _compressed(points_sensor, frame, stamp=None):
    """The cloud as the link delivers it to the twin: Draco, lossless (the map test compares voxels)."""
    from cps_transport.draco import DracoEncoder

    return DracoEncoder(lossless=True).encode(_cloud(points_sensor, frame, stamp))


def _managed(robot):
    return names.absolute(names.managed_cloud_at_twin(robot))


def _stats(msg):
    return {r.robot: r for r in msg.robots}


def _accounted(row):
    """Received clouds that reached an end (cps_msgs/RobotMapStats' ledger), and the waiting ones."""
    return (
        row.clouds_inserted
        + row.clouds_superseded
        + row.clouds_dropped_queue
        + row.clouds_dropped_tf
        + row.clouds_dropped_invalid
        + row.clouds_dropped_decoder
        + row.queue_length
    )


def _centers(msg):
    from cps_transport.pointcloud import cloud_to_array, xyz_of

    return xyz_of(cloud_to_array(msg)).astype(np.float64)


@pytest.fixture(scope="module")
def scene_clouds():
    scene = sc.hall_scene()
    depth = sc.voxel_downsample(sc.depth_camera_cloud(scene, JACKAL[0], 0.0, width=320, height=240), RES)
    lidar = sc.voxel_downsample(sc.lidar_cloud(scene, SCOUT[0], 0.0), 0.01)
    return scene, sc.to_sensor_frame(depth, *JACKAL), sc.to_sensor_frame(lidar, *SCOUT)


def _start(graph, map_file, name, **extra):
    params = {
        "~robots": "jackal,scout,ghost",
        "~map_file": str(map_file),
        "~publish_period_s": 0.3,
        "~tf_timeout_s": 0.3,
        "~autosave_period_s": 0.0,
        "~max_points_range_m": 200.0,
    }
    params.update({f"~{k}": v for k, v in extra.items()})
    proc = graph.start_node(
        "cps_mapping", "map_server", name=name, namespace=names.absolute(names.TWIN_NS), params=params
    )
    graph.wait_for_service(names.absolute(names.in_twin(names.private(name, names.CLEAR_BBX))), timeout_s=30)
    return proc


def _occupied_count(path):
    """Occupied voxels of a saved map, read back here."""
    fused = new_map(RES)
    fused.load(str(path))
    return len(fused.occupied_index())


@pytest.fixture(scope="module")
def server(ros_master, rospy_node, scene_clouds, tmp_path_factory):
    """map_server_a with both robots' first clouds fused and published; stopped at the end."""
    rospy = rospy_node
    from sensor_msgs.msg import PointCloud2

    from cps_msgs.msg import CompressedPointCloud2, MapStats, Octomap

    _, depth_sensor, lidar_sensor = scene_clouds
    graph = ros_master.attach()
    tmp = tmp_path_factory.mktemp("map_server")
    s = types.SimpleNamespace(graph=graph, tmp=tmp, map_file=tmp / "twin.bt")
    s.tf_keep = _static_tf({"jackal/camera_depth_optical_frame": JACKAL, "scout/lidar": SCOUT})
    s.proc = _start(graph, s.map_file, "map_server_a")
    s.stats = TopicRecorder(names.absolute(names.in_twin(names.MAP_STATS)), MapStats)
    s.centers = TopicRecorder(names.absolute(names.in_twin(names.POINT_CLOUD_CENTERS)), PointCloud2)
    s.binary = TopicRecorder(names.absolute(names.in_twin(names.OCTOMAP_BINARY)), Octomap)
    s.pub_j = rospy.Publisher(_managed("jackal"), CompressedPointCloud2, queue_size=5)
    s.pub_s = rospy.Publisher(_managed("scout"), CompressedPointCloud2, queue_size=5)
    s.pub_ghost = rospy.Publisher(_managed("ghost"), CompressedPointCloud2, queue_size=1)
    s.decoded = TopicRecorder(names.absolute(names.twin_points("jackal")), PointCloud2)
    assert wait_for(lambda: s.pub_j.get_num_connections() and s.pub_s.get_num_connections(), timeout_s=20)
    assert wait_for(lambda: s.decoded.sub.get_num_connections(), timeout_s=20)
    try:
        # Depth clouds carry NaN (no return): the encoder strips them.
        with_nan = np.vstack([depth_sensor, np.full((500, 3), np.nan)])
        s.pub_j.publish(_compressed(with_nan, "jackal/camera_depth_optical_frame"))
        s.pub_s.publish(_compressed(lidar_sensor, "scout/lidar"))
        # Stats carry the published snapshot's figures: once both robots contribute to it, the
        # centres of that snapshot (or a later one) are out.
        first = s.stats.wait(
            lambda m: all(r.clouds_inserted >= 1 and r.occupied_voxels_contributed > 0 for r in m.robots),
            what="both robots inserted and published",
        )
        s.occ_msg = s.centers.wait(lambda m: m.width == first.occupied_voxels, what="occupied centres")
        s.occupied = _centers(s.occ_msg)
        yield s
    finally:
        graph.close()
        for recorder in (s.stats, s.centers, s.binary, s.decoded):
            recorder.close()
        for pub in (s.pub_j, s.pub_s, s.pub_ghost):
            pub.unregister()


def test_two_robots_land_in_one_map_at_the_right_places(server, scene_clouds):
    scene = scene_clouds[0]
    assert set(_stats(server.stats.latest)) == {"jackal", "scout"}, "the unknown robot in ~robots must be ignored"
    truth = set(pack_index(voxel_index(scene.occupied_voxels(RES), RES)).tolist())
    got = pack_index(voxel_index(server.occupied, RES)).tolist()
    assert sum(k in truth for k in got) / len(got) > 0.98
    for crate, robot in (("crate_a", "scout"), ("crate_b", "jackal")):
        box = next(b for b in scene.boxes if b.name == crate)
        near = np.all(
            (server.occupied >= np.asarray(box.min_m) - 0.1) & (server.occupied <= np.asarray(box.max_m) + 0.1), axis=1
        )
        assert near.sum() > 20, f"{crate} ({robot}'s view) is not in the fused map"
    assert server.stats.latest.occupied_voxels == len(server.occupied)
    assert server.binary.wait(lambda m: len(m.data) > 0).id == "OcTree"
    decoded = server.decoded.wait(lambda m: m.width > 0, what="jackal's inserted cloud, decoded")
    assert decoded.header.frame_id == "jackal/camera_depth_optical_frame"
    assert decoded.width == np.isfinite(scene_clouds[1]).all(axis=1).sum()


def test_bad_input_is_counted_and_leaves_the_map(server, rospy_node, scene_clouds):
    rospy = rospy_node
    _, depth_sensor, lidar_sensor = scene_clouds
    absurd = np.vstack([depth_sensor[:50], [[1e9, 0, 0], [0, 1e30, 0]]])
    _moving_tf("scout/moving_lidar", SCOUT)
    optical = "jackal/camera_depth_optical_frame"
    corrupt = _compressed(depth_sensor[:100], optical)
    corrupt.compressed_data = bytes(len(corrupt.compressed_data))  # zeros: not Draco
    inserted = _stats(server.stats.latest)["jackal"].clouds_inserted
    for robot, pub, msg in (
        ("jackal", server.pub_j, corrupt),
        ("scout", server.pub_s, _compressed(lidar_sensor[:100], "nowhere/lidar")),  # unknown frame
        (
            "scout",
            server.pub_s,
            _compressed(
                lidar_sensor[:100],
                "scout/moving_lidar",  # no tf at stamp
                rospy.Time.now() + rospy.Duration(60.0),
            ),
        ),
        ("jackal", server.pub_j, _compressed(absurd, optical)),  # absurd points
    ):
        received = _stats(server.stats.latest)[robot].clouds_received
        pub.publish(msg)
        # One at a time: a robot's slot keeps only its newest cloud, a newer one would supersede it.
        server.stats.wait(
            lambda m, robot=robot, received=received: (
                _stats(m)[robot].clouds_received == received + 1
                and _accounted(_stats(m)[robot]) == received + 1
                and _stats(m)[robot].queue_length == 0
            ),
            what=f"{robot}'s cloud through",
        )
    # The absurd cloud's 50 points inserted; the others dropped, each by its cause.
    latest = _stats(server.stats.latest)
    assert latest["jackal"].clouds_dropped_decoder == 1 and latest["scout"].clouds_dropped_tf == 2
    assert latest["jackal"].clouds_inserted == inserted + 1 and latest["jackal"].clouds_superseded == 0
    assert server.proc.poll() is None
    from cps_msgs.srv import SaveMap

    saved = rospy.ServiceProxy(names.absolute(names.in_twin(names.SAVE_MAP)), SaveMap)(
        str(server.tmp / "after_bad_input.bt")
    )
    assert saved.success, saved.message
    assert _occupied_count(server.tmp / "after_bad_input.bt") == len(server.occupied), "bad input changed the map"


def test_unknown_robot_is_named_and_ignored(server):
    assert "~robots names 'ghost', which is not in the fleet" in server.graph.output("map_server_a")
    unmapped = re.compile(re.escape(_managed("ghost")) + " is published but robot 'ghost' is not mapped")
    assert wait_for(lambda: unmapped.search(server.graph.output("map_server_a")), timeout_s=20), (
        "the unknown robot's topic was not reported"
    )


def test_refused_loads_leave_the_map_and_services_work(server, rospy_node, scene_clouds):
    rospy = rospy_node
    from geometry_msgs.msg import Point

    from cps_msgs.msg import Octomap
    from cps_msgs.srv import BoundingBoxQuery, LoadMap, SaveMap

    tmp, before = server.tmp, len(server.occupied)
    save = rospy.ServiceProxy(names.absolute(names.in_twin(names.SAVE_MAP)), SaveMap)
    load = rospy.ServiceProxy(names.absolute(names.in_twin(names.LOAD_MAP)), LoadMap)
    saved = save(str(tmp / "copy.ot"))
    assert saved.success, saved.message
    assert save(str(tmp / "before_loads.bt")).success
    (tmp / "corrupt.bt").write_bytes(b"# Octomap OcTree binary file\nid OcTree\nsize 99\nres 0.1\ndata\n\x01")
    (tmp / "color.ot").write_bytes(b"# Octomap OcTree file\nid ColorOcTree\nsize 1\nres 0.1\ndata\n")
    for bad in ("corrupt.bt", "color.ot", "missing.bt", "notamap.txt"):
        answer = load(str(tmp / bad))
        assert not answer.success and answer.message, bad
    assert save(str(tmp / "after_loads.bt")).success
    assert (tmp / "after_loads.bt").read_bytes() == (tmp / "before_loads.bt").read_bytes(), (
        "a refused load changed the map"
    )

    crate_a = next(b for b in scene_clouds[0].boxes if b.name == "crate_a")
    full = TopicRecorder(names.absolute(names.in_twin(names.OCTOMAP_FULL)), Octomap)
    try:
        # As octomap_server's: the full tree (log-odds of every known voxel), not the binary one.
        message = full.wait(lambda m: len(m.data) > 0, what="octomap_full")
        assert not message.binary and message.id == "OcTree" and message.resolution == pytest.approx(RES)
    finally:
        full.close()
    clear_bbx = rospy.ServiceProxy(
        names.absolute(names.in_twin(names.private("map_server_a", names.CLEAR_BBX))), BoundingBoxQuery
    )
    with pytest.raises(rospy.ServiceException, match="below min"):
        clear_bbx(Point(*crate_a.max_m), Point(*crate_a.min_m))
    clear_bbx(Point(*crate_a.min_m), Point(*crate_a.max_m))
    server.centers.wait(lambda m: m.width < before, what="clear_bbx effect")
    assert save(str(tmp / "without_crate_a.bt")).success
    assert load(str(tmp / "copy.ot")).success
    server.centers.wait(lambda m: m.width == before, what="the loaded map")
    assert save("").success, "empty path saves to ~map_file"


def test_restarted_server_resumes_and_reports_the_change(server, rospy_node, scene_clouds):
    rospy = rospy_node
    from std_srvs.srv import Empty
    from visualization_msgs.msg import Marker, MarkerArray

    server.graph.stop(server.proc)
    assert server.map_file.exists(), "the server saves on shutdown"
    tmp = server.tmp
    changes = TopicRecorder(names.absolute(names.in_twin(names.MAP_CHANGES)), MarkerArray)
    proc = _start(
        server.graph,
        server.map_file,
        "map_server_b",
        baseline_map=str(tmp / "without_crate_a.bt"),
        change_period_s=1.0,
        change_report=str(tmp / "changes.md"),
    )
    try:
        resumed = server.centers.wait(
            lambda m: m.header.stamp > server.occ_msg.header.stamp and m.width > 0, what="resumed map"
        )
        assert resumed.width == len(server.occupied)
        # a change is reported once two detection cycles found it (cps_mapping.change_tracking)
        reported = changes.wait(lambda m: any(k.type == Marker.CUBE for k in m.markers), what="map changes")
        boxes = [m for m in reported.markers if m.type == Marker.CUBE]
        assert len(boxes) == 1 and boxes[0].color.g > boxes[0].color.r, "crate_a must be the one appeared change"
        crate_a = next(b for b in scene_clouds[0].boxes if b.name == "crate_a")
        assert crate_a.min_m[0] - 0.2 < boxes[0].pose.position.x < crate_a.max_m[0] + 0.2
        assert "appeared" in (tmp / "changes.md").read_text()
        rospy.ServiceProxy(names.absolute(names.in_twin(names.private("map_server_b", names.RESET))), Empty)()
        server.centers.wait(lambda m: m.width == 0, what="reset")
    finally:
        server.graph.stop(proc)
        changes.close()
