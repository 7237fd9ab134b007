"""The endpoint against a viewer no one here wrote (the npm @foxglove/ws-protocol client, run with
node): channels advertised, every message decoded with its advertised schema, nothing converted
for a channel nobody watches, the latest latched message to a late subscriber, a full queue's
offers dropped and counted, a stalled viewer holding back nothing and costing no conversion."""

import os
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
from cps_web.endpoint import CHECK_PERIOD_S, DEFAULT_STALLED_BYTES, Endpoint, parse_listen
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


def test_an_empty_map_decodes_as_a_cloud_of_no_points(view, npm_client):
    """The map server's first map, before any cloud, has no points: its protobuf message has no
    `data` on the wire. The viewer decoded it with its fields' defaults left out and read
    `data.length` of undefined (pkg-alone run 2026-11-30: the reference mission's viewer, subscribed
    at the mission's start)."""
    view.on_map(_map_cloud(0))
    report = foxglove_probe.probe(view.url, 2.0, [MAP], modules=npm_client)
    assert report["decode_errors"] == {} and report["errors"] == [], report
    assert report["messages"].get(MAP, 0) >= 1 and report["samples"][MAP]["points"] == 0, report


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
        assert snap["by_channel"][MAP] == {"queued": 1, "dropped": 0, "stalled": 0, "bad": 1, "failed": 0, "logged": 0}
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
        row = snap["by_channel"][MAP]
        assert row["logged"] + row["dropped"] + row["stalled"] == 200
        assert row["logged"] >= 1
    finally:
        stalled.kill()
        stalled.wait()


def _counting(make, calls):
    def counted():
        calls.append(1)
        return make()

    return counted


def test_nothing_is_converted_while_no_viewer_takes_data():
    """The viewers' sockets as the kernel would report them: while every one holds
    DEFAULT_STALLED_BYTES unsent, an offer is not converted (counted stalled), not even one queued
    before the stall; one reading viewer beside a stalled one gets everything; when a viewer reads
    again, the latched map's latest is sent at once."""
    queues = [[DEFAULT_STALLED_BYTES]]  # one viewer, its socket full
    now_s = [0.0]  # the endpoint's clock of socket checks and the stall hold, moved by hand
    gate = threading.Event()
    endpoint = Endpoint(
        {MAP: "PointCloud", HEALTH: "health"},
        latched=(MAP,),
        host="127.0.0.1",
        port=0,
        stall_hold_s=0.3,
        send_queues=lambda: queues[0],
        monotonic=lambda: now_s[0],
    )
    endpoint.watched = lambda topic: True  # as if the viewers subscribed every channel
    calls = []
    row = _counting(lambda: {"stamp_s": 0.0}, calls)
    cloud = _map_cloud(1000)
    try:
        for _ in range(20):
            assert not endpoint.offer(HEALTH, row)
            assert not endpoint.offer(MAP, _counting(lambda: convert.point_cloud(cloud), calls))
        assert endpoint.wait_idle()
        snap = endpoint.snapshot()
        assert calls == [] and snap["stalled"] == 40 and snap["queued"] == 0, snap
        assert (snap["viewers"], snap["stalled_viewers"]) == (1, 1)
        now_s[0] += 0.3
        assert not endpoint.wanted(MAP)  # stalled for stall_hold_s: the node drops the ROS inputs

        queues[0] = [10 * DEFAULT_STALLED_BYTES, 0]  # a reading viewer joins the stalled one
        now_s[0] += 2 * CHECK_PERIOD_S  # past the next check (a float sum of one period can fall short)
        assert endpoint.offer(HEALTH, row)
        assert endpoint.wait_idle()
        assert len(calls) == 2  # the offer, and the latched map's latest, re-sent on resuming
        assert endpoint.snapshot()["by_channel"][MAP]["logged"] == 1
        assert endpoint.wanted(MAP)

        assert endpoint.offer(HEALTH, lambda: gate.wait() and {"stamp_s": 1.0})  # the worker waits on it
        assert wait_for(lambda: endpoint.snapshot()["queue_length"] == 0, 5.0)
        assert endpoint.offer(HEALTH, row)  # queued while the reading viewer reads ...
        queues[0] = [DEFAULT_STALLED_BYTES]  # ... which leaves before the worker gets to it
        now_s[0] += 2 * CHECK_PERIOD_S  # past the next check (a float sum of one period can fall short)
        gate.set()
        assert endpoint.wait_idle()
        assert len(calls) == 2, "converted for viewers that take nothing"
        assert endpoint.snapshot()["by_channel"][HEALTH]["stalled"] == 21
    finally:
        gate.set()
        endpoint.close()


def test_a_viewer_that_reads_nothing_costs_no_conversion(view, npm_client):
    """The npm client subscribes every channel and stops reading: its socket fills once (a few
    maps), after which nothing is converted for it however much is offered; a reading viewer
    connecting beside it gets the map."""
    stalled = foxglove_probe.stalled_viewer(view.url, 30.0, modules=npm_client)
    calls = []
    big = _map_cloud(50_000)  # 600 kB a message
    try:
        assert wait_for(lambda: view.endpoint.watched(MAP), 5.0), "the stalled viewer never subscribed"
        assert foxglove_probe.wait_paused(stalled), "the stalled viewer never said it stopped reading"
        for filled in range(1, 101):
            view.endpoint.offer(MAP, _counting(lambda: convert.point_cloud(big), calls))
            assert view.endpoint.wait_idle(timeout_s=10.0)
            # the kernel's count, read again once CHECK_PERIOD_S has passed
            if wait_for(lambda: not view.endpoint.accepting(), timeout_s=1.5 * CHECK_PERIOD_S, poll_s=0.02):
                break
        snap = view.endpoint.snapshot()
        print(f"stalled after {filled} maps offered, {len(calls)} converted: {snap}")
        assert snap["stalled_viewers"] == 1, f"100 maps (60 MB) did not fill the stalled viewer's socket: {snap}"
        before = len(calls)
        stop = threading.Event()
        feeder = threading.Thread(target=_feed, args=(view, stop), daemon=True)
        feeder.start()
        try:
            for _ in range(100):
                view.endpoint.offer(MAP, _counting(lambda: convert.point_cloud(big), calls))
            assert view.endpoint.wait_idle()
            assert len(calls) == before, "a map was converted for a viewer that reads nothing"
            after = view.endpoint.snapshot()
            assert after["logged"] == snap["logged"], (snap, after)  # nothing of the feed either
            assert after["by_channel"][MAP]["stalled"] >= 100
            view.endpoint.offer(MAP, lambda: convert.point_cloud(_map_cloud(100)))  # latched: the next viewer's
            report = foxglove_probe.probe(view.url, 3.0, [MAP], modules=npm_client)
        finally:
            stop.set()
            feeder.join()
        assert report["messages"].get(MAP, 0) >= 1 and report["decode_errors"] == {}, report
    finally:
        stalled.kill()
        stalled.wait()


def _listening():
    """A TCP socket listening on a free loopback port."""
    import socket

    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen()
    return sock


def test_socket_queues_are_the_kernels_for_the_port_only():
    """SocketQueues reads the unsent bytes of this process's connections to the port (a socket
    written to while its peer reads nothing holds MBs), not the listener's, not other sockets';
    a closed connection leaves, a new one is seen after `rescan`."""
    import socket

    from cps_web.endpoint import SocketQueues

    with _listening() as listener, _listening() as elsewhere:
        port = listener.getsockname()[1]
        peers = [socket.create_connection(("127.0.0.1", port)) for _ in range(2)]
        peers.append(socket.create_connection(elsewhere.getsockname()))
        accepted = [listener.accept()[0] for _ in range(2)] + [elsewhere.accept()[0]]
        try:
            queues = SocketQueues(lambda: port)
            assert queues() == [0, 0]
            for conn in (accepted[0], accepted[2]):  # nobody reads at the other end
                conn.setblocking(False)
                with pytest.raises(BlockingIOError):
                    while True:
                        conn.send(b"\0" * 65536)
            full = queues()
            assert sorted(full)[0] == 0 and sorted(full)[1] > DEFAULT_STALLED_BYTES, full
            accepted.pop(1).close()
            assert len(queues()) == 1
            peers.append(socket.create_connection(("127.0.0.1", port)))
            accepted.append(listener.accept()[0])
            queues.rescan()
            assert len(queues()) == 2
        finally:
            for s in peers + accepted:
                s.close()


def test_socket_queues_leave_every_socket_of_the_process_as_it_was():
    """rospy sets Python's default socket timeout (60 s, when a subscriber connects), and a socket
    object made on a descriptor then puts its file non-blocking: looking at the process's sockets
    made rospy's TCPROS listener non-blocking, its accept thread died on EAGAIN, and nothing could
    connect to the node's publishers or services any more (test_endpoint_node after this file)."""
    import socket

    from cps_web.endpoint import SocketQueues

    before = socket.getdefaulttimeout()
    socket.setdefaulttimeout(None)  # the sockets below made blocking (rospy may have set one already)
    try:
        with _listening() as listener, _listening() as other:
            port = listener.getsockname()[1]
            with socket.create_connection(("127.0.0.1", port)) as peer, listener.accept()[0] as conn:
                conn.setblocking(True)
                socket.setdefaulttimeout(60.0)  # as rospy sets it
                assert SocketQueues(lambda: port)() == [0]
                for sock in (listener, other, conn, peer):
                    assert os.get_blocking(sock.fileno()), sock
    finally:
        socket.setdefaulttimeout(before)
