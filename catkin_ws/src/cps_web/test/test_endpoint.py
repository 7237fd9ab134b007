"""The endpoint against a viewer no one here wrote (the npm @foxglove/ws-protocol client, run with
node): channels advertised, every message decoded with its advertised schema, nothing converted
for a channel nobody watches, the latest latched message to a late subscriber, a full queue's
offers dropped and counted, a stalled viewer holding back nothing."""

import threading
import time

import pytest
import rospy
from sensor_msgs.msg import CompressedImage, PointCloud2
from std_msgs.msg import Header

from cps_fleet import names
from cps_harness import foxglove_probe
from cps_harness.synthetic_clouds import xyz_cloud
from cps_harness.testing import wait_for
from cps_web import convert
from cps_web.endpoint import Endpoint, parse_listen
from cps_web.options import EndpointOptions
from cps_web.twin_view import CHANGES, FLEET, HEALTH, LINK, MAP, VIDEO, TwinView, channels_of, pose_channel

ROBOTS = ["scout", "jackal"]


@pytest.fixture(scope="module")
def npm_client():
    try:
        return foxglove_probe.install_client()
    except foxglove_probe.ClientMissing as exc:
        pytest.fail(f"the npm Foxglove client could not be installed: {exc}")


@pytest.fixture
def view():
    options = EndpointOptions(listen="127.0.0.1:0", queue_size=16)
    v = TwinView(ROBOTS, ["scout"], options, now_s=time.time)
    try:
        yield v
    finally:
        v.close()


def _map_cloud(n):
    return xyz_cloud([(i, 0.5 * i, 1.0) for i in range(n)], names.MAP_FRAME, rospy.Time(5, 0))


def _feed(view, stop):
    """What the twin's topics would give the view, a few times a second, until `stop`."""
    from nav_msgs.msg import Odometry

    jpeg = b"\xff\xd8\xff\xe0" + b"\0" * 200 + b"\xff\xd9"
    i = 0
    while not stop.is_set():
        for r in ROBOTS:
            odom = Odometry(header=Header(frame_id=names.odom_frame(r), stamp=rospy.Time(5, i)))
            odom.pose.pose.position.x, odom.pose.pose.orientation.w = 0.2 * i, 1.0
            view.on_odom(r, odom)
        view.on_video(
            CompressedImage(header=Header(frame_id="scout/camera", stamp=rospy.Time(5, i)), format="jpeg", data=jpeg)
        )
        view.send_scene()
        view.send_status()
        i += 1
        stop.wait(0.1)  # 10 Hz, and ends at once when told


def test_listen_address_is_checked():
    assert parse_listen("127.0.0.1:0") == ("127.0.0.1", 0)
    assert parse_listen("[::1]:8765") == ("::1", 8765)
    for bad in ("8765", "host:port", "h:70000", ":1"):
        with pytest.raises(ValueError, match="listen address"):
            parse_listen(bad)


def test_npm_client_decodes_every_channel_with_its_advertised_schema(view, npm_client):
    view.on_map(_map_cloud(100))  # latched, before anyone connects: a late viewer still gets it
    stop = threading.Event()
    feeder = threading.Thread(target=_feed, args=(view, stop), daemon=True)
    feeder.start()
    try:
        report = foxglove_probe.probe(view.url, 4.0, [], modules=npm_client)
    finally:
        stop.set()
        feeder.join()
    advertised = {c["topic"]: c["schemaName"] for c in report["channels"]}
    assert set(advertised) == set(channels_of(ROBOTS)), report["channels"]
    assert advertised[MAP] == "foxglove.PointCloud" and advertised[VIDEO] == "foxglove.CompressedImage"
    assert report["decode_errors"] == {} and report["errors"] == []
    for topic in (MAP, FLEET, VIDEO, HEALTH, LINK, pose_channel("scout"), pose_channel("jackal")):
        assert report["messages"].get(topic, 0) >= 1, (topic, report["messages"])
    assert report["samples"][MAP] == {
        "frame_id": names.MAP_FRAME,
        "points": 100,
        "whole": True,
        "fields": ["x", "y", "z"],
    }
    assert report["samples"][VIDEO]["jpeg_soi"] and report["samples"][VIDEO]["format"] == "jpeg"
    assert sorted(report["samples"][FLEET]["entities"]) == sorted(ROBOTS)
    assert report["samples"][pose_channel("jackal")]["frame_id"] == names.odom_frame("jackal")
    assert view.endpoint.snapshot()["bad"] == 0


def test_nothing_is_converted_for_a_channel_nobody_watches(view):
    calls = []
    assert not view.endpoint.offer(CHANGES, lambda: calls.append(1))
    view.endpoint.wait_idle()
    assert calls == [] and view.endpoint.snapshot()["queued"] == 0
    assert view.video_robot() is None  # no viewer of the video: nothing of it is subscribed


def test_full_queue_drops_and_counts_and_bad_input_is_counted():
    gate = threading.Event()
    endpoint = Endpoint({MAP: "PointCloud", HEALTH: "health"}, host="127.0.0.1", port=0, queue_size=2)
    endpoint.watched = lambda topic: True  # as if a viewer subscribed: the queue is what is tested
    try:
        assert endpoint.offer(HEALTH, lambda: gate.wait() and {"stamp_s": 0.0})  # the worker blocks on it
        assert wait_for(lambda: endpoint.snapshot()["queue_length"] == 0, 5.0)  # the worker took it, and waits
        accepted = [endpoint.offer(HEALTH, lambda: {"stamp_s": 1.0}) for _ in range(5)]
        assert accepted == [True, True, False, False, False]
        gate.set()
        assert endpoint.wait_idle()
        endpoint.offer(MAP, lambda: convert.point_cloud(PointCloud2(point_step=12, width=2, height=1, row_step=24)))
        assert endpoint.wait_idle()
        snap = endpoint.snapshot()
        assert (snap["dropped"], snap["bad"], snap["logged"]) == (3, 1, 3)
        assert snap["by_channel"][MAP] == {"queued": 1, "dropped": 0, "bad": 1, "failed": 0, "logged": 0}
        endpoint.offer(HEALTH, lambda: 1 / 0)  # a defect: counted, and the worker goes on
        endpoint.offer(HEALTH, lambda: {"stamp_s": 2.0})
        assert endpoint.wait_idle()
        assert endpoint.snapshot()["by_channel"][HEALTH]["failed"] == 1
        assert endpoint.snapshot()["by_channel"][HEALTH]["logged"] == 4
    finally:
        endpoint.close()


def test_a_stalled_viewer_holds_back_no_offer(view, npm_client):
    """A viewer that subscribed and never reads: every offer returns (none waits for room), and the
    worker still logs everything queued: the SDK's per-viewer backlog drops for that viewer."""
    stalled = foxglove_probe.stalled_viewer(view.url, 6.0, modules=npm_client)
    try:
        assert wait_for(lambda: view.endpoint.watched(MAP), 5.0), "the stalled viewer never subscribed"
        assert foxglove_probe.wait_paused(stalled), "the stalled viewer never said it stopped reading"
        big = _map_cloud(50_000)  # 600 kB a message
        for _ in range(200):
            view.on_map(big)
        assert view.endpoint.wait_idle(timeout_s=30.0), "the worker was held back by the stalled viewer"
        snap = view.endpoint.snapshot()
        print(f"stalled viewer, 200 offers of a 600 kB map: {snap}")
        assert snap["by_channel"][MAP]["logged"] + snap["by_channel"][MAP]["dropped"] == 200
        assert snap["by_channel"][MAP]["logged"] >= 1
    finally:
        stalled.kill()
        stalled.wait()
