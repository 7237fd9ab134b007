"""An MCAP we write, read back by the PyPI mcap reader and mcap-ros1-support's decoder (classes
built from the definitions stored in the file): every channel decodes; what is dropped is counted
in the file; a message without its definition is refused."""

import io

import pytest
from mcap.reader import make_reader
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from cps_fleet import names
from cps_harness.mcap_check import read_ros1_mcap
from cps_web.mcap_recording import ClockGate, McapRecording, RecordingError, link_topics


def _raw(msg):
    buff = io.BytesIO()
    msg.serialize(buff)
    return buff.getvalue()


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_every_channel_decodes_with_its_stored_definition(tmp_path, compression):
    path = str(tmp_path / "m.mcap")
    recording = McapRecording(path, chunk_bytes=4096, compression=compression)
    odom_topic = names.absolute(names.robot_topic("jackal", names.ODOM))
    cloud_topic = names.absolute(names.managed_cloud_at_twin("jackal"))
    for i in range(50):
        odom = Odometry(header=Header(seq=i, frame_id=names.odom_frame("jackal")))
        odom.pose.pose.position.x = float(i)
        recording.write(odom_topic, odom._type, Odometry._full_text, _raw(odom), log_time_ns=1_000 + i)
        cloud = PointCloud2(header=Header(seq=i), width=i, data=bytes(i))
        recording.write(cloud_topic, cloud._type, PointCloud2._full_text, _raw(cloud), log_time_ns=1_000 + i)
    recording.close()
    contents = read_ros1_mcap(path)
    assert contents.profile == "ros1" and contents.errors == []
    assert contents.types == {odom_topic: "nav_msgs/Odometry", cloud_topic: "sensor_msgs/PointCloud2"}
    assert [m.pose.pose.position.x for m in contents.messages[odom_topic]] == [float(i) for i in range(50)]
    assert [m.width for m in contents.messages[cloud_topic]] == list(range(50))
    with open(path, "rb") as stream:
        metadata = {m.name: m.metadata for m in make_reader(stream).iter_metadata()}
    assert metadata["cps_recording"] == {"messages": "100", "refused": "0", "dropped": "{}"}


def test_a_full_backlog_drops_and_the_file_says_so(tmp_path):
    path = str(tmp_path / "m.mcap")
    recording = McapRecording(path, backlog_bytes=10)  # less than one message
    odom = Odometry()
    for _ in range(3):
        recording.write("/x", odom._type, Odometry._full_text, _raw(odom))
    recording.close()
    assert recording.dropped == {"/x": 3} and recording.messages == 0
    with open(path, "rb") as stream:
        metadata = {m.name: m.metadata for m in make_reader(stream).iter_metadata()}
    assert metadata["cps_recording"]["dropped"] == '{"/x": 3}'


def test_a_message_without_definition_is_refused(tmp_path):
    recording = McapRecording(str(tmp_path / "m.mcap"))
    with pytest.raises(RecordingError, match="without its type or definition"):
        recording.write("/x", "nav_msgs/Odometry", "", b"")
    recording.close()
    assert recording.refused == 1
    with pytest.raises(ValueError, match="compression 'gzip'"):
        McapRecording(str(tmp_path / "n.mcap"), compression="gzip")


def test_link_topics_are_what_crosses_the_link():
    topics = link_topics(["scout", "jackal"], ["jackal"])
    assert names.absolute(names.managed_cloud_at_twin("scout")) in topics
    assert names.absolute(names.robot_topic("jackal", names.CAMERA_IMAGE_COMPRESSED)) in topics
    assert names.absolute(names.robot_topic("scout", names.CAMERA_IMAGE_COMPRESSED)) not in topics
    assert {names.TF, names.TF_STATIC} <= set(topics)


def test_foxglove_npm_readers_decode_every_channel_and_catch_a_wrong_definition(tmp_path):
    """Read by the npm libraries Foxglove and Lichtblick read MCAP with (no code shared with our
    writer): every message decodes with its stored definition, every byte accounted for; a message
    stored under another type's definition is an error."""
    from std_msgs.msg import String
    from tf2_msgs.msg import TFMessage

    from cps_harness.mcap_check import npm_read

    path = str(tmp_path / "m.mcap")
    recording = McapRecording(path, chunk_bytes=4096)
    cloud_topic = names.absolute(names.robot_topic("jackal", names.POINTS))
    for i in range(20):
        cloud = PointCloud2(header=Header(seq=i, frame_id="jackal/camera"), width=i, height=1, row_step=12 * i)
        cloud.data = bytes(12 * i)
        recording.write(cloud_topic, cloud._type, PointCloud2._full_text, _raw(cloud), log_time_ns=1_000 + i)
    recording.write(names.TF_STATIC, TFMessage._type, TFMessage._full_text, _raw(TFMessage()), log_time_ns=999)
    recording.close()
    report = npm_read(path)
    assert report["profile"] == "ros1" and report["decode_errors"] == 0, report["errors"]
    assert report["message_count"] == 21
    cloud_row = report["topics"][cloud_topic]
    assert (cloud_row["type"], cloud_row["messages"], cloud_row["decoded"]) == ("sensor_msgs/PointCloud2", 20, 20)
    assert cloud_row["first"] == {"frame_id": "jackal/camera", "stamp": 0, "points": 0, "data_adds_up": True}

    wrong = str(tmp_path / "wrong.mcap")
    recording = McapRecording(wrong)
    recording.write("/x", String._type, String._full_text, _raw(Odometry(child_frame_id="a")), log_time_ns=1)
    recording.close()
    report = npm_read(wrong)
    assert report["decode_errors"] == 1 and report["topics"]["/x"]["decoded"] == 0, report


def test_what_arrives_before_a_replayed_clock_runs_is_kept_and_logged_at_its_first_time(tmp_path):
    """The recorder subscribes before the player's first message (final69's MCAP of a replay
    lacked scout's first second: subscribed once the clock ran). What comes while the clock says 0
    (a latched /tf_static, the first odometry) is held and logged at the clock's first time; a
    clock that never starts leaves it at 0, never lost."""
    path = str(tmp_path / "m.mcap")
    recording = McapRecording(path)
    gate = ClockGate(recording)
    odom = Odometry()
    for i in range(3):
        gate.write("/early", odom._type, Odometry._full_text, _raw(odom), 0)
    with pytest.raises(RecordingError):
        gate.write("/bad", odom._type, "", b"", 0)
    gate.write("/late", odom._type, Odometry._full_text, _raw(odom), 7_000_000_000)
    gate.write("/late", odom._type, Odometry._full_text, _raw(odom), 7_100_000_000)
    gate.close()
    with open(path, "rb") as stream:
        logged = [(c.topic, m.log_time) for _, c, m in make_reader(stream).iter_messages()]
    assert logged == [("/early", 7_000_000_000)] * 3 + [("/late", 7_000_000_000), ("/late", 7_100_000_000)]
    assert recording.refused == 1

    never = McapRecording(str(tmp_path / "n.mcap"))
    gate = ClockGate(never)
    gate.write(names.TF_STATIC, odom._type, Odometry._full_text, _raw(odom), 0)
    gate.close()
    assert never.messages == 1
