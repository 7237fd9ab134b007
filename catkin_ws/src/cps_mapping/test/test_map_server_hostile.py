"""The map_server node against hostile input: a map file too large for the grid at resume is
moved aside and the node starts empty; hostile clouds (raw PointCloud2 on its input, which it
reads by the type its publisher announces) are counted in map_stats and cost nothing;
load_map of too-large maps is refused with the running map unchanged; save_map and load_map
refuse paths outside the map folder (/etc/x)."""

import os
import re

import pytest
from hostile_maps import COARSE_LEAF_BT, far_apart_bt

from cps_fleet import names
from cps_harness.hostile_clouds import packed_cloud, refused_clouds
from cps_harness.testing import TopicRecorder, wait_for

pytestmark = [pytest.mark.ros, pytest.mark.waiting]
FRAME = "jackal/camera_depth_optical_frame"


def _static_tf():
    import rospy
    import tf2_ros
    from geometry_msgs.msg import TransformStamped

    broadcaster = tf2_ros.StaticTransformBroadcaster()
    t = TransformStamped()
    t.header.stamp = rospy.Time.now()
    t.header.frame_id, t.child_frame_id = names.MAP_FRAME, FRAME
    t.transform.translation.z = 0.5
    t.transform.rotation.w = 1.0
    broadcaster.sendTransform([t])
    return broadcaster


def _jackal(msg):
    return next(r for r in msg.robots if r.robot == "jackal")


def test_map_server_survives_hostile_maps_clouds_and_paths(ros, rospy_node, tmp_path):
    rospy = rospy_node
    import numpy as np
    from sensor_msgs.msg import PointCloud2

    from cps_msgs.msg import MapStats
    from cps_msgs.srv import LoadMap, SaveMap

    mission = tmp_path / "mission"
    mission.mkdir()
    (mission / "map.bt").write_bytes(COARSE_LEAF_BT)
    tf_keep = _static_tf()
    stats = TopicRecorder(names.absolute(names.in_twin(names.MAP_STATS)), MapStats)
    proc = ros.start_node(
        "cps_mapping",
        "map_server",
        name="map_server_hostile",
        namespace=names.absolute(names.TWIN_NS),
        params={
            "~robots": "jackal",
            "~map_file": str(mission / "map.bt"),
            "~publish_period_s": 0.3,
            "~tf_timeout_s": 0.3,
            "~autosave_period_s": 0.0,
        },
    )
    points = rospy.Publisher(names.absolute(names.managed_cloud_at_twin("jackal")), PointCloud2, queue_size=20)
    try:
        ros.wait_for_service(names.absolute(names.in_twin(names.SAVE_MAP)), timeout_s=60)
        output = ros.output("map_server_hostile")
        assert re.search(r"cannot resume: .*max_grid_voxels.*moved it to .*map\.bt\.unreadable-\d+", output), output
        assert not (mission / "map.bt").exists()
        assert wait_for(lambda: points.get_num_connections() >= 1, timeout_s=20)

        xyz = np.array([[2.0, 0.0, 0.0], [0.0, 2.0, 0.0], [1.0, 1.0, 1.0]], dtype=np.float32)
        good = packed_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}, FRAME)
        good.header.stamp = rospy.Time.now()
        points.publish(good)
        stats.wait(lambda m: _jackal(m).clouds_inserted == 1 and m.occupied_voxels > 0, what="the good cloud")
        hostile = refused_clouds(FRAME)
        for count, msg in enumerate(hostile.values(), start=1):
            msg.header.stamp = rospy.Time.now()
            points.publish(msg)
            # One at a time: the robot's slot keeps only its newest cloud, a newer one would supersede it.
            stats.wait(
                lambda m, count=count: _jackal(m).clouds_received == 1 + count and _jackal(m).queue_length == 0,
                what=f"hostile cloud {count} through",
            )
        stats.wait(
            lambda m: _jackal(m).clouds_dropped_invalid == len(hostile) and _jackal(m).clouds_superseded == 0,
            timeout_s=20,
            what=f"{len(hostile)} hostile clouds counted",
        )

        save = rospy.ServiceProxy(names.absolute(names.in_twin(names.SAVE_MAP)), SaveMap)
        load = rospy.ServiceProxy(names.absolute(names.in_twin(names.LOAD_MAP)), LoadMap)
        assert save(str(mission / "before.bt")).success
        (mission / "coarse.bt").write_bytes(COARSE_LEAF_BT)
        far_apart_bt(mission / "far.bt")
        for name in ("coarse.bt", "far.bt"):
            answer = load(str(mission / name))
            assert not answer.success and "max_grid_voxels" in answer.message, answer.message
        assert save(str(mission / "after.bt")).success
        assert (mission / "after.bt").read_bytes() == (mission / "before.bt").read_bytes(), (
            "a refused load changed the map"
        )

        for path in ("/etc/x", "/etc/x.bt", str(mission / ".." / "outside.bt")):
            answer = save(path)
            assert not answer.success and "refused" in answer.message and str(mission) in answer.message, path
            assert not load(path).success
        assert not os.path.exists("/etc/x") and not os.path.exists("/etc/x.bt")
        assert not (tmp_path / "outside.bt").exists()
        assert proc.poll() is None
        assert "Traceback" not in ros.output("map_server_hostile")
    finally:
        stats.close()
        points.unregister()
        del tf_keep
