"""The bridge's receive path without ROS or Zenoh (issue 22): a frame is published only on the topic
it was sent for, in that topic's one type; every bad input is dropped and counted by its kind."""

import math
import struct

import pytest
import roslib.message

from cps_fleet import names
from cps_link.bridge_config import load_bridge_table
from cps_link.bridge_wire import Frame, decode, encode, new_session_id
from cps_link.receive_path import DROP_KINDS, ReceivePath, SendPath

ROBOTS = ("scout", "jackal")
T0_S = 1_700_000_000.0


def md5_of(msg_type):
    try:
        cls = roslib.message.get_message_class(msg_type)
    except Exception:
        return None
    return cls._md5sum if cls is not None else None


@pytest.fixture(scope="module")
def table():
    return load_bridge_table(robots=ROBOTS)


def _path(table):
    return ReceivePath(table.incoming("twin"), table.key_prefix, md5_of)


def _key(table, to):
    return table.route(to).key(table.key_prefix)


def _frame(to, msg_type, seq=1, session=b"\x00" * 8 + b"a" * 8, source="/sim", body=b"\x00" * 8, stamp_s=math.nan):
    return Frame(session, seq, stamp_s, msg_type, md5_of(msg_type) or "0" * 32, source, body, topic=to)


def _receive(path, table, to, payload, key=None, now_s=T0_S):
    return path.receive(to, _key(table, to) if key is None else key, payload, now_s)


def test_a_good_frame_is_published_on_its_topic_with_its_type(table):
    path = _path(table)
    verdict = _receive(path, table, names.TF, encode(_frame(names.TF, "tf2_msgs/TFMessage")))
    assert verdict.drop is None and verdict.frame.topic == names.TF and verdict.frame.msg_type == "tf2_msgs/TFMessage"
    assert path.topic_type(names.TF) == ("tf2_msgs/TFMessage", md5_of("tf2_msgs/TFMessage"))
    assert sum(path.counts.values()) == 0


def test_issue_22_a_tf_frame_on_the_backfill_pose_route_is_dropped_and_never_retypes_it(table):
    """The issue's run: /tf, odom and camera_info frames reached the backfill pose subscribers."""
    path = _path(table)
    pose = names.absolute(names.in_twin(names.robot_topic("scout", names.POINTS_BACKFILL_POSE)))
    for to, msg_type in (
        (names.TF, "tf2_msgs/TFMessage"),
        (names.absolute(names.robot_topic("jackal", names.ODOM)), "nav_msgs/Odometry"),
        (names.absolute(names.robot_topic("scout", names.CAMERA_INFO)), "sensor_msgs/CameraInfo"),
    ):
        # Under the pose route's key (Zenoh resolved the wrong key) and under its own (wrong callback).
        payload = encode(_frame(to, msg_type))
        assert _receive(path, table, pose, payload).drop == "wrong_topic"
        assert _receive(path, table, pose, payload, key=_key(table, to)).drop == "key_mismatch"
    assert path.counts == {"wrong_topic": 3, "key_mismatch": 3}
    # The pose topic's type is the table's; a TransformStamped still goes through.
    assert path.topic_type(pose)[0] == "geometry_msgs/TransformStamped"
    assert _receive(path, table, pose, encode(_frame(pose, "geometry_msgs/TransformStamped"))).drop is None


def test_each_bad_input_is_dropped_and_counted_by_kind(table):
    path = _path(table)
    to = names.absolute(names.robot_topic("scout", names.CONTROL_MODE_ACTIVE))
    good = encode(_frame(to, "std_msgs/String", body=b"\x04\x00\x00\x00auto"))
    flipped = bytearray(good)
    flipped[-1] ^= 0x01
    seq_flipped = bytearray(good)
    seq_flipped[30] ^= 0x01  # the CRC covers the header too: no copy with another seq gets through
    old_version = bytearray(good)
    old_version[4] = 1
    cases = [
        (good[:20], "truncated"),  # inside the fixed header
        (good[:50], "truncated"),  # inside the texts
        (good[:-2], "truncated"),  # the body cut short
        (good + b"xx", "not_a_frame"),
        (b"XXXX" + good[4:], "not_a_frame"),
        (bytes(flipped), "bad_crc"),
        (bytes(seq_flipped), "bad_crc"),
        (bytes(old_version), "bad_version"),
        (encode(_frame(to, "std_msgs/Strung")), "unknown_type"),
        (encode(_frame(to, "no type at all")), "unknown_type"),
        (encode(Frame(b"s" * 16, 1, math.nan, "std_msgs/String", "0" * 32, "/sim", b"", topic=to)), "md5_mismatch"),
        (encode(_frame(to, "std_msgs/Bool")), "topic_type_mismatch"),  # a real type, not this topic's
        (encode(_frame("/scout/not_in_the_table", "std_msgs/String")), "unlisted_topic"),
        (
            encode(_frame(names.absolute(names.robot_topic("scout", names.CMD_VEL_TELEOP)), "geometry_msgs/Twist")),
            "unlisted_topic",
        ),  # the other way
        (
            encode(_frame(names.absolute(names.robot_topic("scout", names.MISSION_STATE)), "std_msgs/String")),
            "wrong_topic",
        ),
    ]
    for payload, kind in cases:
        verdict = _receive(path, table, to, payload)
        assert verdict.drop == kind, (payload[:60], verdict)
    assert (
        _receive(
            path, table, to, good, key="cps/topic" + names.absolute(names.robot_topic("scout", names.MISSION_STATE))
        ).drop
        == "key_mismatch"
    )
    expected = {}
    for _, kind in cases:
        expected[kind] = expected.get(kind, 0) + 1
    expected["key_mismatch"] = 1
    assert dict(path.counts) == expected
    counters = path.counters()
    assert counters["corrupt"] == 8 and counters["type_mismatch"] == 4 and counters["drop_wrong_topic"] == 1
    assert set(counters) >= {f"drop_{k}" for k in DROP_KINDS}
    # None of it stopped anything: the good frame still goes through, once.
    assert _receive(path, table, to, good).drop is None
    assert _receive(path, table, to, good).drop == "duplicates"


def test_a_restarted_sender_starts_afresh_and_its_old_run_is_refused_while_the_new_one_talks(table):
    to = names.ESTOP
    path = ReceivePath(table.incoming("robots"), table.key_prefix, md5_of)
    old, new = new_session_id(1_000), new_session_id(2_000)
    key = table.route(to).key(table.key_prefix)

    def send(session, seq, now_s):
        return path.receive(to, key, encode(_frame(to, "std_msgs/Bool", seq, session, body=b"\x01")), now_s).drop

    assert send(old, 5, T0_S) is None
    assert send(new, 1, T0_S + 1) is None  # newer run: afresh
    assert send(old, 6, T0_S + 2) == "old_session"  # a late frame of the dead run
    assert send(new, 1, T0_S + 2) == "duplicates"  # its latched re-send
    assert send(new, 2, T0_S + 3) is None
    # The newer run silent for longer than the hold: the older one is taken back (a clock stepped back).
    assert send(old, 7, T0_S + 10) is None
    assert send(old, 7, T0_S + 10) == "duplicates" and send(old, 5, T0_S + 10) == "duplicates"


def test_stale_stamped_data_is_dropped_and_counted(table):
    path = _path(table)
    to = names.absolute(names.managed_cloud_at_twin("scout"))
    body = struct.pack("<III", 0, int(T0_S), 0) + b"\x00" * 40
    assert (
        _receive(
            path,
            table,
            to,
            encode(_frame(to, "cps_msgs/CompressedPointCloud2", body=body, stamp_s=T0_S)),
            now_s=T0_S + 2,
        ).drop
        == "stale"
    )
    assert path.counters()["stale"] == 1


def test_the_sender_puts_the_topic_in_every_frame_and_refuses_a_second_type():
    send = SendPath(table_types={names.TF: "tf2_msgs/TFMessage"})
    odom = names.absolute(names.robot_topic("scout", names.ODOM))
    frame = send.frame(odom, "/sim", "nav_msgs/Odometry", "m1", math.nan, b"x")
    assert decode(encode(frame)).topic == odom and frame.seq == 1
    assert send.frame(odom, "/sim", "nav_msgs/Odometry", "m1", math.nan, b"y").seq == 2
    assert send.frame(odom, "/other", "std_msgs/String", "m2", math.nan, b"z") is None
    assert send.frame(names.TF, "/sim", "tf2_msgs/TFMessage_", "m3", math.nan, b"z") is None  # not the table's
    assert send.counts["topic_type_mismatch"] == 2
