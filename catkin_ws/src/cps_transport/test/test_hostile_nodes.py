"""The real encoder and decoder nodes fed a handful of hostile messages: they stay up, count every
one on /diagnostics, and the next good cloud still crosses."""

import numpy as np
import pytest

from cps_fleet import names
from cps_harness.hostile_clouds import packed_cloud, refused_clouds, wire_copy
from cps_harness.testing import TopicRecorder, wait_for
from cps_transport.draco import DracoEncoder

pytestmark = pytest.mark.ros
R = "hostile1"
FRAME = f"{R}/camera_depth_optical_frame"


def _good_cloud():
    xyz = np.random.default_rng(1).uniform(-3, 3, (500, 3)).astype(np.float32)
    return packed_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}, FRAME)


def _refused_payloads():
    from sensor_msgs.msg import PointField

    good = DracoEncoder(leaf_size_m=0.1).encode(_good_cloud())

    def changed(**changes):
        msg = wire_copy(good)
        for key, value in changes.items():
            setattr(msg, key, value)
        return msg

    return {
        "truncated payload": changed(compressed_data=bytes(good.compressed_data)[:20]),
        "random payload": changed(compressed_data=bytes(range(256)) * 2),
        "empty payload": changed(compressed_data=b""),
        "no z field": changed(
            fields=[PointField(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xy")]
        ),
        "fewer points than the payload": changed(width=3),
    }


def _invalid_count(diagnostics, node):
    count = None
    for msg in diagnostics.wait_count(1, timeout_s=5):
        for status in msg.status:
            if status.name == node:
                count = int({kv.key: kv.value for kv in status.values}["invalid_messages"])
    return count


def test_encoder_and_decoder_nodes_count_hostile_messages_and_stay_up(ros, rospy_node):
    rospy = rospy_node
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import PointCloud2

    from cps_msgs.msg import CompressedPointCloud2

    encoder = ros.start_node(
        "cps_transport",
        "draco_encoder",
        name="draco_encoder",
        namespace=names.absolute(R),
        params={"~leaf_size_m": 0.1, "~fields": "all"},
        remap={"~input": names.absolute(names.robot_topic(R, names.POINTS_FILTERED))},
    )
    decoder = ros.start_node(
        "cps_transport",
        "draco_decoder",
        name="draco_decoder",
        namespace=names.absolute(names.TWIN_NS),
        remap={
            "~input": names.absolute(names.robot_topic(R, names.POINTS_DRACO)),
            "~output": names.absolute(names.twin_points(R)),
        },
    )
    diagnostics = TopicRecorder(names.DIAGNOSTICS, DiagnosticArray)
    decoded = TopicRecorder(names.absolute(names.twin_points(R)), PointCloud2)
    raw = rospy.Publisher(names.absolute(names.robot_topic(R, names.POINTS_FILTERED)), PointCloud2, queue_size=20)
    compressed = rospy.Publisher(
        names.absolute(names.robot_topic(R, names.POINTS_DRACO)), CompressedPointCloud2, queue_size=20
    )
    try:
        assert wait_for(lambda: raw.get_num_connections() >= 1 and compressed.get_num_connections() >= 1, timeout_s=20)
        clouds, payloads = refused_clouds(FRAME), _refused_payloads()
        for msg in clouds.values():
            raw.publish(msg)
            rospy.sleep(0.05)  # the encoder's queue holds 3
        for msg in payloads.values():
            compressed.publish(msg)
            rospy.sleep(0.05)
        assert wait_for(lambda: _invalid_count(diagnostics, f"/{R}/draco_encoder") == len(clouds), timeout_s=15), (
            f"encoder counted {_invalid_count(diagnostics, f'/{R}/draco_encoder')} of {len(clouds)}"
        )
        decoder_node = names.absolute(names.in_twin("draco_decoder"))
        assert wait_for(lambda: _invalid_count(diagnostics, decoder_node) == len(payloads), timeout_s=15), (
            f"decoder counted {_invalid_count(diagnostics, decoder_node)} of {len(payloads)}"
        )
        raw.publish(_good_cloud())
        assert decoded.wait(timeout_s=15).header.frame_id == FRAME
        assert encoder.poll() is None and decoder.poll() is None
        for node in ("draco_encoder", "draco_decoder"):
            assert "Traceback" not in ros.output(node)
    finally:
        for handle in (diagnostics, decoded):
            handle.close()
        raw.unregister()
        compressed.unregister()
