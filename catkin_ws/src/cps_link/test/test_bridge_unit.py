"""The Zenoh bridge's parts that need no ROS master: wire frames, the table, link health."""

import dataclasses
import io
import math
import uuid

import pytest
import roslib.message
import zenoh

from cps_fleet import names
from cps_link.backfill import Keyframe, KeyframeStore, Pacer, unused_bytes_per_s
from cps_link.bridge_config import ROBOTS, TWIN, ConfigError, load_bridge_table
from cps_link.bridge_wire import Frame, WireError, decode, encode, header_stamp_s, is_stale
from cps_link.link_health import LinkHealth
from cps_link.link_report import socket_full_bytes
from cps_link.zenoh_bridge import POSE_TOLERANCE_S, keyframe_pose, zenoh_qos
from cps_link.zenoh_session import BridgeSetupError, session_config

ROBOT_NAMES = ("scout", "jackal", "champ", "iris")
# Every type bridge.yaml carries (and sensor_msgs/PointCloud2 of the backfill).
TYPES = (
    "geometry_msgs/Twist",
    "std_msgs/String",
    "std_msgs/Bool",
    "std_msgs/Float64",
    "nav_msgs/Odometry",
    "sensor_msgs/BatteryState",
    "sensor_msgs/JointState",
    "cps_msgs/RateLimiterStatus",
    "tf2_msgs/TFMessage",
    "diagnostic_msgs/DiagnosticArray",
    "cps_msgs/TopicStatsArray",
    "rosgraph_msgs/Log",
    "cps_msgs/CompressedPointCloud2",
    "sensor_msgs/CompressedImage",
    "sensor_msgs/CameraInfo",
    "cps_msgs/LinkState",
    "sensor_msgs/PointCloud2",
)


def _sample(msg_type):
    cls = roslib.message.get_message_class(msg_type)
    msg = cls()
    if cls._has_header:
        msg.header.stamp.secs, msg.header.stamp.nsecs, msg.header.frame_id = 1700000000, 250000000, "scout/lidar"
    for slot, slot_type in zip(cls.__slots__, cls._slot_types):
        if slot_type == "string":
            setattr(msg, slot, "teleop ü")
        elif slot_type == "uint8[]":
            setattr(msg, slot, bytes(range(256)) * 40)
        elif slot_type == "float64":
            setattr(msg, slot, 0.1 + 1e-12)
    return cls, msg


def _serialize(msg):
    buff = io.BytesIO()
    msg.serialize(buff)
    return buff.getvalue()


@pytest.mark.parametrize("msg_type", TYPES)
def test_every_type_crosses_byte_identical(msg_type):
    cls, msg = _sample(msg_type)
    body = _serialize(msg)
    stamp = header_stamp_s(body) if cls._has_header else math.nan
    frame = Frame(uuid.uuid4().bytes, 7, stamp, msg_type, cls._md5sum, "/fleet_sim", body)
    out = decode(encode(frame))
    assert out.body == body and (out.session, out.seq, out.msg_type, out.md5, out.source) == (
        frame.session,
        7,
        msg_type,
        cls._md5sum,
        "/fleet_sim",
    )
    assert _serialize(cls().deserialize(out.body)) == body
    if cls._has_header:
        assert out.stamp_s == pytest.approx(1700000000.25)


def test_damaged_frames_are_refused_with_a_reason():
    good = encode(
        Frame(
            b"s" * 16, 1, math.nan, "std_msgs/String", "992ce8a1687cec8c8bd883ec73ca41d1", "/gui", b"\x02\x00\x00\x00hi"
        )
    )
    flipped = bytearray(good)
    flipped[-1] ^= 0xFF
    for bad, why in (
        (good[:10], "shorter"),
        (b"XXXX" + good[4:], "magic"),
        (bytes(flipped), "CRC"),
        (good[:45], "truncated"),
        (b"", "shorter"),
    ):
        with pytest.raises(WireError, match=why):
            decode(bad)


def test_staleness_only_for_stamped_messages_past_the_bound():
    frame = Frame(b"s" * 16, 1, 100.0, "t", "m", "", b"")
    assert is_stale(frame, 101.5, 1.0) and not is_stale(frame, 100.9, 1.0) and not is_stale(frame, 1e9, None)
    assert not is_stale(Frame(b"s" * 16, 1, math.nan, "t", "m", "", b""), 1e9, 1.0)


def test_classes_map_to_their_zenoh_qos():
    table = load_bridge_table(robots=ROBOT_NAMES)

    def robot_topic(robot, name):
        return names.absolute(names.robot_topic(robot, name))

    champ_cloud = names.absolute(names.managed_cloud_at_twin("champ"))
    expected = {
        robot_topic("scout", names.CMD_VEL_TELEOP): (
            zenoh.Priority.REAL_TIME,
            zenoh.CongestionControl.BLOCK,
            True,
            True,
        ),
        names.ESTOP: (zenoh.Priority.REAL_TIME, zenoh.CongestionControl.BLOCK, True, True),
        # the manager's setpoints: off teleop's lane (issue 36), never dropped
        robot_topic("iris", names.LIMITER_RATE_HZ): (
            zenoh.Priority.INTERACTIVE_LOW,
            zenoh.CongestionControl.BLOCK,
            True,
            True,
        ),
        robot_topic("iris", names.VIDEO_LEVEL): (
            zenoh.Priority.INTERACTIVE_LOW,
            zenoh.CongestionControl.BLOCK,
            True,
            True,
        ),
        robot_topic("jackal", names.ODOM): (zenoh.Priority.INTERACTIVE_HIGH, zenoh.CongestionControl.DROP, True, True),
        names.TF_STATIC: (zenoh.Priority.INTERACTIVE_HIGH, zenoh.CongestionControl.DROP, True, True),
        names.ROSOUT: (zenoh.Priority.DATA_LOW, zenoh.CongestionControl.DROP, True, False),
        # paced: the bridge's own send queue holds the backlog, so Zenoh blocks rather than drops
        # (and reliable: Zenoh drops a best-effort message whatever its congestion control)
        champ_cloud: (zenoh.Priority.DATA, zenoh.CongestionControl.BLOCK, True, False),
        robot_topic("jackal", names.CAMERA_IMAGE_COMPRESSED): (
            zenoh.Priority.DATA_HIGH,
            zenoh.CongestionControl.BLOCK,
            True,
            True,
        ),
    }
    routes = {r.to: r for r in table.routes}
    for topic, (priority, congestion, reliable, express) in expected.items():
        qos = zenoh_qos(routes[topic].traffic)
        assert (qos["priority"], qos["congestion_control"], qos["express"]) == (priority, congestion, express), topic
        assert (qos["reliability"] == zenoh.Reliability.RELIABLE) == reliable, topic
    assert routes[champ_cloud].traffic.max_age_s == 2.0
    assert {r.to for r in table.routes if r.traffic.paced} == {
        r.to for r in table.routes if r.traffic.name in ("data", "video")
    }
    assert {r.to for r in table.routes if r.managed and r.from_ros} == {
        names.absolute(names.managed_cloud_at_twin(r)) for r in ROBOT_NAMES
    } | {robot_topic(r, names.CAMERA_IMAGE_COMPRESSED) for r in ROBOT_NAMES}
    assert table.paced_ranks["video"] < table.paced_ranks["data"]  # the video leaves first
    assert {r.to for r in table.routes if r.latched} >= {
        names.TF_STATIC,
        names.ESTOP,
        robot_topic("scout", names.CONTROL_MODE),
        robot_topic("scout", names.MISSION_STATE),
    }
    assert all(r.source == TWIN for r in table.routes if r.traffic.name == "command")
    assert all(
        r.source == ROBOTS
        for r in table.routes
        if r.traffic.name not in ("command", "setpoint") and r.to != names.absolute(names.ALLOCATION)
    )
    assert not {r.to for r in table.for_lane("command").routes} & {
        robot_topic(robot, topic)
        for robot in ROBOT_NAMES
        for topic in (names.LIMITER_RATE_HZ, names.LIMITER_LEVEL, names.VIDEO_RATE_HZ, names.VIDEO_LEVEL)
    }
    assert {r.to for r in table.routes if r.traffic.name == "backfill"} == {
        names.absolute(names.in_twin(names.robot_topic(r, kind)))
        for r in ROBOT_NAMES
        for kind in (names.POINTS_BACKFILL_DRACO, names.POINTS_BACKFILL_POSE)
    }
    iris_backfill = names.absolute(names.in_twin(names.robot_topic("iris", names.POINTS_BACKFILL_DRACO)))
    assert zenoh_qos(routes[iris_backfill].traffic)["priority"] == zenoh.Priority.BACKGROUND
    scout_cloud = names.absolute(names.managed_cloud("scout"))
    assert routes[names.absolute(names.managed_cloud_at_twin("scout"))].topic == scout_cloud


def test_bad_table_names_file_and_line(tmp_path):
    path = tmp_path / "bridge.yaml"
    base = (
        "endpoint_port: 7447\nkey_prefix: cps\nlease_ms: 600\nkeep_alive: 3\nretry_max_ms: 500\n"
        "heartbeat_ms: 100\nheartbeat_timeout_ms: 700\n"
        "classes:\n  command: {priority: real_time, congestion: block, reliable: true, express: true}\n"
    )
    for topics, message in (
        ("  - {topic: /a, from: moon, class: command}\n", "bridge.yaml:11.*from"),
        ("  - {topic: /a, from: twin, class: fast}\n", "bridge.yaml:11.*unknown class"),
        ("  - {topic: a, from: twin, class: command}\n", "not a global ROS topic"),
        ("  - {topic: /a, from: twin, class: command}\n" * 2, "bridge.yaml:12.*crosses twice"),
    ):
        path.write_text(base + "topics:\n" + topics)
        with pytest.raises(ConfigError, match=message):
            load_bridge_table(str(path), ROBOT_NAMES)
    topic = "topics:\n  - {topic: /a, from: twin, class: command}\n"
    for extra, message in (
        # a paced class must block in Zenoh, and be reliable (Zenoh drops best effort anyway)
        ("  data: {priority: data, congestion: drop, reliable: true, express: false, paced: true}\n", "paced"),
        ("  data: {priority: data, congestion: block, reliable: false, express: false, paced: true}\n", "paced"),
    ):
        path.write_text(base + extra + topic)
        with pytest.raises(ConfigError, match=message):
            load_bridge_table(str(path), ROBOT_NAMES)
    settings = (
        "batch_bytes: 100",
        "batch_bytes: 70000",
        "report_ms: 10",
        "kernel_unsent_bytes: -1",
        "tcp_user_timeout_ms: -1",
    )
    # a reopen sooner than a heartbeat timeout would reopen a session whose peer is merely late
    # and the robots' unheard rule must come before the twin's deaf one
    for setting in settings + (
        "reopen_after_ms: 500",
        "unheard_after_ms: 600",
        "unheard_after_ms: 5000",
        # the orphan rule needs two heartbeats, and comes before the unheard one
        "orphan_after_ms: 150",
        "orphan_after_ms: 2000",
        # a blocked put ends its transport within the lease, as the peer's lease ends the peer's
        "block_wait_before_close_ms: 2000",
    ):
        path.write_text(base + topic + setting + "\n")
        with pytest.raises(ConfigError, match=setting.split(":")[0]):
            load_bridge_table(str(path), ROBOT_NAMES)
    # a deaf rule shortened below the default unheard rule is refused too, naming the latter
    path.write_text(base + topic + "reopen_after_ms: 1500\n")
    with pytest.raises(ConfigError, match="unheard_after_ms"):
        load_bridge_table(str(path), ROBOT_NAMES)


def test_link_health_counts_outages_and_their_length():
    health = LinkHealth(started_s=0.0)
    assert not health.up and health.outages == 0
    assert health.peer_alive("robots", 1.0) and health.up and health.last_outage_s == 0.0
    assert not health.peer_alive("scout", 1.5)
    assert not health.peer_gone("scout", 2.0) and health.up
    assert health.peer_gone("robots", 3.0) and not health.up and health.outages == 1
    assert not health.peer_gone("robots", 3.5)
    assert health.peer_alive("robots", 13.0) and health.last_outage_s == pytest.approx(10.0)
    assert health.since_s == 13.0


def test_a_silent_peer_is_gone_after_the_heartbeat_timeout_even_with_its_token():
    health = LinkHealth(started_s=0.0)
    assert health.heard("robots", 1.0)
    assert not health.expire(1.6, timeout_s=0.7) and health.up
    assert not health.heard("robots", 1.7)
    assert health.expire(2.5, timeout_s=0.7) and not health.up and health.outages == 1
    assert not health.expire(3.0, timeout_s=0.7)
    assert health.heard("robots", 12.5) and health.last_outage_s == pytest.approx(10.0)


def test_a_token_held_without_heartbeats_is_a_deaf_session_and_closing_it_takes_every_token():
    """The half-open session seen after outages: the robots' token came back, their heartbeats did
    not. The silence counts from the token's arrival; a heartbeat clears it."""
    health = LinkHealth(started_s=0.0)
    assert health.token_put("robots", 10.0) and health.up
    assert health.deaf(12.9, after_s=3.0) == []
    assert health.expire(11.0, timeout_s=0.7) and not health.up  # the heartbeat timeout says down first
    assert health.deaf(13.1, after_s=3.0) == ["robots"]
    assert health.heard("robots", 13.2) and health.deaf(13.3, after_s=3.0) == []
    # a transport that began to talk at 15 s (a restore) counts its silence from then, not from 13.2 s
    assert health.deaf(17.0, after_s=3.0, since_s=15.0) == [] and health.deaf(18.1, after_s=3.0, since_s=15.0)
    assert health.session_closed(14.0) and not health.up and health.tokens == set()
    assert health.deaf(30.0, after_s=3.0) == [] and not health.session_closed(30.0)
    assert health.token_put("robots", 31.0) and not health.token_deleted("scout", 31.5)
    assert health.token_deleted("robots", 32.0) and health.deaf(40.0, after_s=3.0) == []


def test_a_peer_heard_that_never_echoes_this_side_is_an_unheard_session():
    """The one-way session seen from the robots' side: the twin's token and heartbeats come, its
    echoes of the robots' heartbeats do not. Echoes from before the outage do not count."""
    health = LinkHealth(started_s=0.0)
    assert health.token_put("twin", 1.0) and not health.heard_back()
    assert health.echoed(1.2) == pytest.approx(0.2) and health.heard_back()
    assert health.echoed(1.3) is None  # only the first echo of an up period is reported
    assert not health.unheard(100.0, after_s=3.0)
    assert health.token_deleted("twin", 5.0) and not health.heard_back()
    assert health.token_put("twin", 15.0) and not health.heard_back()
    assert not health.heard("twin", 15.1) and not health.unheard(17.9, after_s=3.0)  # already up
    assert health.unheard(18.1, after_s=3.0) and not health.heard_back()
    assert health.echoed(18.2) == pytest.approx(3.2) and not health.unheard(30.0, after_s=3.0)


def test_a_peer_heard_while_the_session_lists_no_transport_to_it_is_an_orphaned_session():
    """Zenoh's stale close removed the new transport: the peer's heartbeats still arrive, the
    session lists no peer. Only a heartbeat after the listing stopped counts (a peer that closed
    its transport stops being heard), and only while up."""
    health = LinkHealth(started_s=0.0)
    health.transports_listed(0, 0.5)  # down: nothing to say
    assert health.token_put("twin", 1.0) and health.unlisted_since_s is None
    health.transports_listed(1, 1.1)
    assert not health.orphaned(5.0, after_s=0.3)
    health.transports_listed(0, 2.0)  # the transport went; no heartbeat since
    assert not health.orphaned(2.5, after_s=0.3)
    assert not health.heard("twin", 2.1) and not health.orphaned(2.25, after_s=0.3)  # too soon
    assert health.orphaned(2.35, after_s=0.3)
    health.transports_listed(1, 2.4)  # a transport listed again: no longer
    assert not health.orphaned(3.0, after_s=0.3)
    health.transports_listed(0, 3.1)
    assert health.token_deleted("twin", 3.2)  # the link went down: the listing says nothing
    health.transports_listed(0, 3.3)
    assert health.unlisted_since_s is None and not health.orphaned(9.0, after_s=0.3)
    # a reopen: the closing session listed nothing while still up, and no heartbeat tick came while
    # down; the new session's first token must not find the old session's listing (test_zenoh_bridge
    # saw two reopens 1 ms apart)
    assert health.token_put("twin", 10.0)
    health.transports_listed(0, 10.5)
    assert health.session_closed(10.6) and health.token_put("twin", 11.0)
    assert not health.orphaned(11.0, after_s=0.3) and not health.orphaned(12.0, after_s=0.3)


def test_the_socket_talks_from_its_first_bytes_after_a_silence_and_the_first_heartbeat_is_timed():
    health = LinkHealth(started_s=0.0)
    assert health.socket_talking(1.0, gap_s=0.7) is None
    health.socket_bytes(100, 1.0, gap_s=0.7)
    health.socket_bytes(100, 1.5, gap_s=0.7)  # no new bytes: still talking (within the gap)
    assert health.socket_talking(1.6, gap_s=0.7) == 1.0
    assert health.socket_talking(1.8, gap_s=0.7) is None  # silent longer than the gap: a cut
    health.socket_bytes(250, 12.0, gap_s=0.7)
    health.socket_bytes(300, 12.5, gap_s=0.7)
    assert health.socket_talking(12.6, gap_s=0.7) == 12.0  # talking again since the restore
    assert health.token_put("robots", 12.1)
    assert health.first_heartbeat_after_token("robots", 12.4) == pytest.approx(0.3)
    assert health.first_heartbeat_after_token("robots", 12.5) is None


def test_session_config_listens_on_twin_connects_from_robots_over_mtls(tmp_path):
    for name in ("ca.pem", "twin.pem", "twin.key", "robots.pem", "robots.key"):
        (tmp_path / name).write_text("x")
    table = load_bridge_table(robots=ROBOT_NAMES)
    twin = session_config(table, TWIN, "10.201.0.2", str(tmp_path))
    robots = session_config(table, ROBOTS, "10.201.0.2", str(tmp_path))
    assert twin["listen"]["endpoints"] == ["tls/10.201.0.2:7447"] and twin["connect"]["endpoints"] == []
    assert robots["connect"]["endpoints"] == ["tls/10.201.0.2:7447"] and robots["listen"]["endpoints"] == []
    # the command lane the other way round: the robots listen at their own address, the twin connects
    # there, so each host answers at exactly one port (issue 38)
    command = table.for_lane("command")
    twin_command = session_config(command, TWIN, "10.201.0.2", str(tmp_path), robots_address="10.201.0.1")
    robots_command = session_config(command, ROBOTS, "10.201.0.2", str(tmp_path), robots_address="10.201.0.1")
    assert robots_command["listen"]["endpoints"] == ["tls/10.201.0.1:7448#dscp=184"]
    assert robots_command["connect"]["endpoints"] == [] and twin_command["listen"]["endpoints"] == []
    assert twin_command["connect"]["endpoints"] == ["tls/10.201.0.1:7448#dscp=184"]
    with pytest.raises(BridgeSetupError, match="--robots-address"):
        session_config(command, TWIN, "10.201.0.2", str(tmp_path))
    # one robots' bridge per robot computer: the twin connects to each, each listens at its own
    several = session_config(command, TWIN, "10.201.0.2", str(tmp_path), robots_address="10.201.0.1, 10.201.0.3")
    assert several["connect"]["endpoints"] == ["tls/10.201.0.1:7448#dscp=184", "tls/10.201.0.3:7448#dscp=184"]
    with pytest.raises(BridgeSetupError, match="listens at one address"):
        session_config(command, ROBOTS, "10.201.0.2", str(tmp_path), robots_address="10.201.0.1,10.201.0.3")
    assert robots["transport"]["link"]["tls"]["enable_mtls"] is True
    assert robots["transport"]["link"]["tls"]["connect_private_key"].endswith("robots.key")
    assert not twin["scouting"]["multicast"]["enabled"]
    # what waits below the bridge's own queue is small, and nothing bypasses the link through
    # shared memory on a one-host test bed (issue 35)
    for config in (twin, robots):
        assert config["transport"]["shared_memory"]["enabled"] is False
        assert config["transport"]["link"]["tx"]["batch_size"] == table.batch_bytes == 16384
        # a cut ends the sending side's transport after 500 ms of a blocked put, not Zenoh's 5 s:
        # within the lease, as the other side's ends
        block = config["transport"]["link"]["tx"]["queue"]["congestion_control"]["block"]
        assert block["wait_before_close"] == 1000 * table.block_wait_before_close_ms == 500_000
        assert table.block_wait_before_close_ms < table.lease_ms
    # the kernel holds at most four batches unsent (one made Zenoh's writer stall, then the
    # transport close); the socket counts as full from half of that, where the kernel wakes its writer
    assert table.kernel_unsent_bytes == 65536 == 4 * table.batch_bytes and table.report_ms == 500
    assert socket_full_bytes(table) == 32768
    assert socket_full_bytes(dataclasses.replace(table, kernel_unsent_bytes=0)) == table.batch_bytes // 2
    assert table.reopen_after_ms == 5000 > table.unheard_after_ms == 2000 > table.heartbeat_timeout_ms
    assert table.orphan_after_ms == 300 >= 2 * table.heartbeat_ms
    assert table.tcp_user_timeout_ms == 1000
    zenoh.Config.from_json5(__import__("json").dumps(twin))


def _keyframe(robot, stamp_s, size):
    return Keyframe(robot, stamp_s, (b"p" * 100, b"c" * (size - 100)))


def test_backfill_store_keeps_one_keyframe_per_period_and_drops_the_oldest_when_full():
    store = KeyframeStore(capacity_bytes=3000, period_s=1.0)
    assert store.offer(_keyframe("scout", 10.0, 1000))
    assert not store.offer(_keyframe("scout", 10.5, 1000))  # within the keyframe period
    assert store.offer(_keyframe("iris", 10.5, 1000))  # per robot
    assert store.offer(_keyframe("scout", 11.0, 1000))
    assert store.bytes == 3000 and store.evicted == 0
    assert store.offer(_keyframe("scout", 12.0, 1500))  # full: the two oldest make room
    assert store.evicted == 2 and store.bytes == 2500 and len(store) == 2
    assert not store.offer(_keyframe("iris", 20.0, 5000)) and store.refused == 1
    assert [store.pop().stamp_s for _ in range(2)] == [11.0, 12.0] and store.pop() is None
    assert store.bytes == 0 and store.kept == 4
    with pytest.raises(ValueError):
        KeyframeStore(0, 1.0)


def test_backfill_pacer_sends_only_what_the_manager_leaves_unused():
    assert unused_bytes_per_s(6.93, 6.0) == pytest.approx(0.93e6)
    assert unused_bytes_per_s(6.0, 6.5) == 0.0
    pacer = Pacer(burst_bytes=200_000, now_s=0.0)
    assert not pacer.take(100_000, 10.0)  # no allocation heard yet: nothing goes
    pacer.set_rate(100_000, 10.0)
    assert not pacer.take(100_000, 10.5)
    assert pacer.take(100_000, 11.01)
    assert not pacer.take(100_000, 11.5)
    pacer.set_rate(0.0, 11.5)
    assert not pacer.take(1, 100.0)
    # A 1 MB keyframe goes once the bucket is full, then the debt is paid first.
    pacer.set_rate(100_000, 100.0)
    assert pacer.take(1_000_000, 102.1)
    assert not pacer.take(1000, 110.0)
    assert pacer.take(1000, 112.0)


def test_header_frame_id_of_a_cloud():
    from cps_link.bridge_wire import header_frame_id

    _, msg = _sample("cps_msgs/CompressedPointCloud2")
    assert header_frame_id(_serialize(msg)) == "scout/lidar"
    with pytest.raises(WireError):
        header_frame_id(b"\x00" * 12 + b"\xff\x00\x00\x00")


def test_the_command_lane_carries_the_command_class_alone_on_its_own_port_and_keys():
    table = load_bridge_table(robots=["scout", "jackal"])
    command, main = table.for_lane("command"), table.for_lane("main")
    assert {r.traffic.name for r in command.routes} == {"command"}
    assert "command" not in {r.traffic.name for r in main.routes}
    assert sorted(r.to for r in command.routes + main.routes) == sorted(r.to for r in table.routes)  # none lost
    assert names.absolute(names.robot_topic("scout", names.CMD_VEL_TELEOP)) in {r.to for r in command.routes}
    assert (command.endpoint_port, main.endpoint_port) == (table.command_port, table.endpoint_port)
    assert command.endpoint_port != main.endpoint_port
    assert command.backfill is None and main.backfill is not None
    # Each lane knows only its own peers: the main lane's link state never counts a command bridge.
    assert command.peer_liveliness_keys(TWIN) != main.peer_liveliness_keys(TWIN)
    assert not command.publishes_link_state and main.publishes_link_state and table.publishes_link_state
    assert table.liveliness_key(ROBOTS, "robots") == "cps/bridge/robots/robots"  # one process: keys as before
    with pytest.raises(ValueError, match="lane must be one of"):
        table.for_lane("video")


def test_a_command_port_equal_to_the_main_port_is_refused_with_file_and_line(tmp_path):
    source = open(load_bridge_table().path).read()
    path = tmp_path / "bridge.yaml"
    path.write_text(source.replace("command_port: 7448", "command_port: 7447"))
    line = next(i for i, text in enumerate(path.read_text().splitlines(), 1) if text.startswith("command_port"))
    with pytest.raises(ConfigError, match=f"{path}:{line}: command_port: the command lane needs a port of its own"):
        load_bridge_table(str(path))


def _tos_of_connections(port):
    """IP_TOS of this process's TCP connections from or to `port` (cps_ros.sockets: no socket
    object is made on a descriptor, which would put rospy's listener in this process non-blocking)."""
    import os
    import socket

    from cps_ros import sockets

    found = []
    for fd in map(int, os.listdir("/proc/self/fd")):
        peer = sockets.inet_port(fd, peer=True)  # None for a listener
        if sockets.socket_type(fd) == socket.SOCK_STREAM and peer is not None and port in (sockets.inet_port(fd), peer):
            found.append(sockets.ip_tos(fd))
    return found


def test_the_command_lanes_connection_carries_its_dscp_both_ways():
    """bridge.yaml command_dscp: Zenoh marks the command lane's sockets (its endpoints' `dscp`), the
    twin's connecting one and the robots' accepted one (teleop goes twin -> robots): 46, EF, which
    Wi-Fi's WMM and the test bed's shaper serve first. The main lane's stay unmarked."""
    import dataclasses
    import json
    import time

    import zenoh

    from cps_ros.processes import free_port

    table = load_bridge_table(robots=ROBOT_NAMES)
    for lane, tos in (("command", table.command_dscp << 2), ("main", 0)):
        lane_table = dataclasses.replace(table.for_lane(lane), endpoint_port=free_port())
        sessions = []
        try:
            for side in (TWIN, ROBOTS):
                config = session_config(lane_table, side, "127.0.0.1", "", tls=False, robots_address="127.0.0.1")
                sessions.append(zenoh.open(zenoh.Config.from_json5(json.dumps(config))))
            deadline = time.monotonic() + 10.0
            while len(_tos_of_connections(lane_table.endpoint_port)) < 2 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert _tos_of_connections(lane_table.endpoint_port) == [tos, tos], lane
        finally:
            for session in sessions:
                session.close()


def test_a_link_report_is_stamped_when_its_interval_closed_not_when_it_was_published(monkeypatch):
    """Two reports' stamps are as far apart as the second's interval says, however long the first
    waited to be published: stamped at publishing, one that waited came within a quarter interval
    of the next one's stamp and the manager refused the next as a repeat (live, 1 of 4 runs)."""
    import rospy

    from cps_link.link_report import ReportComposer, SenderReport
    from cps_link.zenoh_bridge import link_report_msg

    monkeypatch.setattr(rospy.rostime, "_rostime_initialized", True)  # a clock without a node

    def at(now_s):
        monkeypatch.setattr(rospy.rostime, "_rostime_current", rospy.Time.from_sec(now_s))

    def report(seq, t_s):
        return SenderReport("run1", seq, t_s, 1000 * seq, 1000 * seq, 0, 0, False).encode()

    composer = ReportComposer()
    composer.on_report(report(1, 10.0), 500.0)
    first, _ = composer.on_report(report(2, 10.5), 500.5)  # closed at ROS time 1000.5 ...
    second, _ = composer.on_report(report(3, 11.5), 501.46)  # ... and 1001.46
    at(1001.22)  # the first published 0.72 s after it closed
    first_stamp = link_report_msg(first, 0.72).header.stamp.to_sec()
    at(1001.46)  # the second at once
    second_stamp = link_report_msg(second).header.stamp.to_sec()
    assert second_stamp - first_stamp == pytest.approx(second.interval_s)


class _Transforms:
    """tf2_ros.Buffer's lookup_transform as the robots' bridge uses it: a pose at the asked time
    (tf2 stamps an interpolated transform with the time asked), or, for a time after the newest,
    tf2's extrapolation error; the newest for time 0."""

    def __init__(self, newest):
        self.newest = newest

    def lookup_transform(self, target, source, stamp):
        import rospy
        from geometry_msgs.msg import TransformStamped

        if stamp > self.newest:
            raise RuntimeError("Lookup would require extrapolation into the future")
        pose = TransformStamped()
        pose.header.frame_id, pose.child_frame_id = target, source
        pose.header.stamp = self.newest if stamp == rospy.Time(0) else rospy.Time(stamp.secs, stamp.nsecs)
        return pose


@pytest.mark.parametrize("ahead_ns", [0, 3_000_000])
def test_a_keyframe_pose_carries_its_cloud_stamp_to_the_nanosecond(ahead_ns):
    """The twin pairs a keyframe with its pose by (frame, stamp in ns) (admission_process.BackfillPoses).
    The pose was stamped through a float of seconds (rospy.Time.from_sec): 1796068802.154 s came
    back 1796068802.154000044, and every keyframe of a demo went without its pose, placed by the
    twin's /tf interpolated across the outage (issue 39)."""
    import rospy
    from sensor_msgs.msg import PointCloud2

    cloud = PointCloud2()
    cloud.header.stamp, cloud.header.frame_id = rospy.Time(1796068802, 154000000), "champ/depth"
    stamp_ns = cloud.header.stamp.to_nsec()
    assert rospy.Time.from_sec(cloud.header.stamp.to_sec()).to_nsec() != stamp_ns  # what a float loses
    newest = rospy.Time(1796068802, 154000000 - ahead_ns)  # the cloud a few ms ahead of its tf
    assert ahead_ns * 1e-9 <= POSE_TOLERANCE_S
    pose = keyframe_pose(_Transforms(newest), names.MAP_FRAME, _serialize(cloud))
    assert pose.child_frame_id == "champ/depth"
    assert pose.header.stamp.to_nsec() == stamp_ns
