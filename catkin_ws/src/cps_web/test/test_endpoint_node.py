"""The foxglove_endpoint node on a private master, seen by the npm @foxglove/ws-protocol client:
the latched map, a robot's pose and the video it subscribes only while watched (and read), at the
nice that puts it behind the map server; a port in use refused with a clear error; the MCAP
recorder node's file read back."""

import os
import socket

import pytest

from cps_fleet import names
from cps_harness import foxglove_probe
from cps_harness.cgroups import nice_of
from cps_harness.synthetic_clouds import xyz_cloud
from cps_harness.testing import messages_received, wait_for
from cps_web.options import EndpointOptions
from cps_web.twin_view import MAP, VIDEO, pose_channel

pytestmark = [pytest.mark.ros, pytest.mark.waiting]

ROBOT = "jackal"  # a camera robot of the default fleet
SENT = 20  # messages of each topic the recorder test publishes


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _map_cloud(rospy, n):
    return xyz_cloud([(i, 0.0, 1.0) for i in range(n)], names.MAP_FRAME, rospy.Time.now())


def _start_endpoint(ros, url_file, listen="127.0.0.1:0"):
    return ros.start_node(
        "cps_web",
        "foxglove_endpoint",
        name=names.FOXGLOVE_ENDPOINT,
        namespace=names.absolute(names.TWIN_NS),
        params={"~robots": ROBOT, "~listen": listen, "~url_file": str(url_file)},
    )


def test_node_serves_map_pose_and_video_to_the_npm_client(ros, rospy_node, tmp_path):
    rospy = rospy_node
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import CompressedImage, PointCloud2
    from std_msgs.msg import Header

    map_pub = rospy.Publisher(
        names.absolute(names.in_twin(names.POINT_CLOUD_CENTERS)), PointCloud2, queue_size=1, latch=True
    )
    odom_pub = rospy.Publisher(names.absolute(names.robot_topic(ROBOT, names.ODOM)), Odometry, queue_size=5)
    video_topic = names.absolute(names.robot_topic(ROBOT, names.CAMERA_IMAGE_COMPRESSED))
    video_pub = rospy.Publisher(video_topic, CompressedImage, queue_size=2)
    map_pub.publish(_map_cloud(rospy, 500))
    url_file = tmp_path / "url.txt"
    proc = _start_endpoint(ros, url_file)
    assert wait_for(lambda: url_file.exists() and url_file.read_text().strip(), timeout_s=30.0), ros.output(
        names.FOXGLOVE_ENDPOINT
    )
    url = url_file.read_text().strip()
    # behind the map server when the CPU is short: every thread, rospy's started before the nice too
    threads = [int(t) for t in os.listdir(f"/proc/{proc.pid}/task")]
    assert nice_of(proc.pid) == EndpointOptions.nice
    assert {os.getpriority(os.PRIO_PROCESS, t) for t in threads} == {EndpointOptions.nice}, len(threads)
    assert video_pub.get_num_connections() == 0  # nobody watches: the video is not subscribed

    import threading

    stop = threading.Event()

    def feed():
        i = 0
        while not stop.is_set():
            odom = Odometry(header=Header(frame_id=names.odom_frame(ROBOT), stamp=rospy.Time.now()))
            odom.pose.pose.position.x, odom.pose.pose.orientation.w = 0.1 * i, 1.0
            odom_pub.publish(odom)
            video_pub.publish(
                CompressedImage(header=Header(stamp=rospy.Time.now()), format="jpeg", data=b"\xff\xd8" + b"\0" * 64)
            )
            i += 1
            stop.wait(0.1)  # 10 Hz, and ends at once when told

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        report = foxglove_probe.probe(url, 5.0, [MAP, VIDEO, pose_channel(ROBOT)])
    finally:
        stop.set()
        feeder.join()
    assert report["decode_errors"] == {} and report["errors"] == []
    assert report["samples"][MAP]["points"] == 500
    assert report["messages"].get(VIDEO, 0) >= 1, report["messages"]
    assert report["samples"][VIDEO]["jpeg_soi"]
    assert report["samples"][pose_channel(ROBOT)]["frame_id"] == names.odom_frame(ROBOT)
    # The viewer left: the video is unsubscribed again.
    assert wait_for(lambda: video_pub.get_num_connections() == 0, timeout_s=10.0), "the video unsubscribed"


def test_node_drops_its_inputs_while_the_only_viewer_reads_nothing(ros, rospy_node, tmp_path):
    """A viewer subscribes everything and stops reading: the map, republished as the map server does,
    fills its socket, and within the stall hold the node unsubscribes the video (and the map) again.
    (One latched 600 kB map did not always fill it: its socket's receive buffer, autotuned while it
    still read, took most of it, 1 run in 2 alone.)"""
    rospy = rospy_node
    from sensor_msgs.msg import CompressedImage, PointCloud2

    map_pub = rospy.Publisher(
        names.absolute(names.in_twin(names.POINT_CLOUD_CENTERS)), PointCloud2, queue_size=1, latch=True
    )
    video_pub = rospy.Publisher(
        names.absolute(names.robot_topic(ROBOT, names.CAMERA_IMAGE_COMPRESSED)), CompressedImage, queue_size=2
    )
    big_map = _map_cloud(rospy, 50_000)  # 600 kB
    map_pub.publish(big_map)
    republish = rospy.Timer(rospy.Duration(0.5), lambda _e: map_pub.publish(big_map))
    url_file = tmp_path / "url.txt"
    _start_endpoint(ros, url_file)
    assert wait_for(lambda: url_file.exists() and url_file.read_text().strip(), timeout_s=30.0), ros.output(
        names.FOXGLOVE_ENDPOINT
    )
    stalled = foxglove_probe.stalled_viewer(url_file.read_text().strip(), 60.0)
    try:
        assert foxglove_probe.wait_paused(stalled, timeout_s=20.0), "the stalled viewer never said it stopped reading"
        assert wait_for(lambda: video_pub.get_num_connections() == 1, timeout_s=10.0), "the video never subscribed"
        assert wait_for(lambda: map_pub.get_num_connections() == 0, timeout_s=10.0 + EndpointOptions.stall_hold_s), (
            "the map still subscribed for a viewer that reads nothing: " + ros.output(names.FOXGLOVE_ENDPOINT)[-2000:]
        )
        # the inputs are dropped one after another: each publisher hears of its own (final53 read
        # the video's count between the map's connection closing and the video's)
        assert wait_for(lambda: video_pub.get_num_connections() == 0, timeout_s=5.0), "the video still subscribed"
        assert stalled.poll() is None  # still connected: the stall, not its leaving, dropped the inputs
    finally:
        republish.shutdown()
        stalled.kill()
        stalled.wait()


def test_port_in_use_is_a_clear_error(ros, tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        proc = _start_endpoint(ros, tmp_path / "url.txt", listen=f"127.0.0.1:{port}")
        assert proc.wait(timeout=30) == 2
    assert f"{port}" in ros.output_of(proc) and not (tmp_path / "url.txt").exists()


def test_recorder_node_writes_an_mcap_every_channel_decodes(ros, rospy_node, tmp_path):
    rospy = rospy_node
    from nav_msgs.msg import Odometry
    from std_msgs.msg import Header

    from cps_harness.mcap_check import read_ros1_mcap

    topic = names.absolute(names.robot_topic(ROBOT, names.ODOM))
    cloud_topic = names.absolute(names.in_twin(names.POINT_CLOUD_CENTERS)) + "_rec"
    path = tmp_path / "mission.mcap"
    proc = ros.start_node(
        "cps_web",
        "mcap_recorder",
        name="mcap_recorder_test",
        params={"~path": str(path), "~topics": f"{topic},{cloud_topic}"},
    )
    from sensor_msgs.msg import PointCloud2

    odom_pub = rospy.Publisher(topic, Odometry, queue_size=SENT)
    cloud_pub = rospy.Publisher(cloud_topic, PointCloud2, queue_size=SENT)
    assert wait_for(lambda: odom_pub.get_num_connections() and cloud_pub.get_num_connections(), timeout_s=30.0), (
        ros.output_of(proc)
    )
    for i in range(SENT):
        odom = Odometry(header=Header(frame_id=names.odom_frame(ROBOT), seq=i), child_frame_id=names.base_frame(ROBOT))
        odom.pose.pose.position.x = float(i)
        odom_pub.publish(odom)
        cloud_pub.publish(_map_cloud(rospy, 10 + i))
    recorder = names.absolute("mcap_recorder_test")
    assert wait_for(
        lambda: min(messages_received(recorder, t) for t in (topic, cloud_topic)) >= SENT, timeout_s=20.0
    ), ros.output_of(proc)  # every message in the recorder before it is stopped
    proc.terminate()
    assert proc.wait(timeout=20) == 0, ros.output_of(proc)
    contents = read_ros1_mcap(str(path))
    assert contents.errors == []
    assert contents.types == {topic: "nav_msgs/Odometry", cloud_topic: "sensor_msgs/PointCloud2"}
    assert [m.pose.pose.position.x for m in contents.messages[topic]] == [float(i) for i in range(SENT)]
    assert [m.width for m in contents.messages[cloud_topic]] == [10 + i for i in range(SENT)]


def test_operator_commands_from_the_viewer_are_checked_and_reach_ros(ros, rospy_node, tmp_path):
    """Select a camera robot and raise a priority from the npm client: the selection is published
    latched as the GUI's is, the priority goes through the manager's service; a robot that is no
    camera robot, an unknown robot, or a request without its fields is refused with the reason."""
    rospy = rospy_node
    from std_msgs.msg import String

    from cps_harness.testing import TopicRecorder
    from cps_msgs.srv import SetPriority, SetPriorityResponse

    asked = []

    def manager(request):
        asked.append((request.robot, request.priority))
        return SetPriorityResponse(success=True, message=f"{request.robot} at {request.priority}")

    service = rospy.Service(names.absolute(names.SET_PRIORITY), SetPriority, manager)
    selected = TopicRecorder(names.absolute(names.SELECTED_ROBOT), String)
    url_file = tmp_path / "url.txt"
    proc = ros.start_node(
        "cps_web",
        "foxglove_endpoint",
        name=names.FOXGLOVE_ENDPOINT,
        namespace=names.absolute(names.TWIN_NS),
        params={"~robots": "scout,jackal", "~listen": "127.0.0.1:0", "~url_file": str(url_file)},
    )
    try:
        assert wait_for(lambda: url_file.exists() and url_file.read_text().strip(), timeout_s=30.0), ros.output_of(proc)
        select = names.absolute(names.in_twin(names.WEB_SELECT_ROBOT))
        priority = names.absolute(names.in_twin(names.WEB_SET_PRIORITY))
        calls = [
            (select, {"robot": "jackal"}),
            (select, {"robot": "scout"}),  # scout has no camera
            (priority, {"robot": "jackal", "high": True}),
            (priority, {"robot": "ghost", "high": True}),
            (priority, {"robot": "jackal"}),
        ]
        report = foxglove_probe.probe(url_file.read_text().strip(), 4.0, [], calls=calls)
    finally:
        service.shutdown()
    assert set(report["services"]) == {select, priority}, report["services"]
    results = [(c["response"], c["failure"]) for c in report["calls"]]
    assert results[0] == ({"ok": True, "message": "selected jackal"}, None)
    assert results[1][0] is None and "not a camera robot" in results[1][1]
    assert results[2] == ({"ok": True, "message": "jackal at 1"}, None)
    assert results[3][0] is None and "ghost" in results[3][1]
    assert results[4][0] is None and "lacks 'high'" in results[4][1]
    assert asked == [("jackal", 1)]
    assert wait_for(lambda: selected.latest is not None, timeout_s=5.0) and selected.latest.data == "jackal"


def test_mcap_player_node_plays_a_recording_at_its_pace_with_its_clock(ros, rospy_node, tmp_path):
    """The player publishes every stored message as recorded (header seq kept), paced by the log
    times, /clock at those times, /tf_static latched; then it exits by itself."""
    import io

    import rospy as _rospy
    from nav_msgs.msg import Odometry
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import Header
    from tf2_msgs.msg import TFMessage

    from cps_harness.testing import TopicRecorder
    from cps_web.mcap_recording import McapRecording

    robot = "mcap_player_test"
    topic = names.absolute(names.robot_topic(robot, names.ODOM))
    static = names.absolute(names.robot_topic(robot, "tf_static"))
    start_ns, step_ns = 5_000_000_000, 10**8

    def raw(msg):
        buff = io.BytesIO()
        msg.serialize(buff)
        return buff.getvalue()

    path = str(tmp_path / "played.mcap")
    recording = McapRecording(path)
    recording.write(names.TF_STATIC, TFMessage._type, TFMessage._full_text, raw(TFMessage()), log_time_ns=start_ns)
    for i in range(SENT):
        odom = Odometry(header=Header(seq=100 + i, frame_id=names.odom_frame(ROBOT)))
        odom.pose.pose.position.x = float(i)
        recording.write(topic, odom._type, Odometry._full_text, raw(odom), log_time_ns=start_ns + i * step_ns)
    recording.close()
    odoms, clocks = TopicRecorder(topic, Odometry), TopicRecorder("/clock", Clock, queue_size=1000)
    statics = TopicRecorder(static, _rospy.AnyMsg)
    proc = ros.start_node(
        "cps_web",
        "mcap_player",
        name="mcap_player_test",
        params={"~path": path, "~topics": f"{topic},{names.TF_STATIC}", "~delay_s": 1.5},
        remap={names.TF_STATIC: static},
    )
    assert proc.wait(timeout=30) == 0, ros.output_of(proc)
    assert wait_for(lambda: odoms.count >= SENT, timeout_s=5.0), ros.output_of(proc)
    received = [msg for _, msg in odoms.messages]
    assert [m.header.seq for m in received] == [100 + i for i in range(SENT)]
    assert [m.pose.pose.position.x for m in received] == [float(i) for i in range(SENT)]
    span = odoms.messages[-1][0] - odoms.messages[0][0]
    assert span >= 0.8 * (SENT - 1) * step_ns / 1e9, span  # its recorded pace, not as fast as it can
    times = [msg.clock.to_nsec() for _, msg in clocks.messages]
    assert times == sorted(times) and times[0] >= start_ns and times[-1] == start_ns + (SENT - 1) * step_ns
    assert statics.count == 1 and statics.latest._connection_header["latching"] == "1"
