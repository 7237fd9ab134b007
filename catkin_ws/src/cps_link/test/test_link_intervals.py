"""The link report's parts (cps_link.link_report), no ROS: the twin's intervals from the robots'
cumulative counters, bad and out-of-order reports refused and counted, round trips, socket queues."""

import json
import math

import pytest

from cps_harness.testing import wait_for
from cps_link.link_report import (
    BAD_REPORT,
    COUNTER_BACKWARDS,
    FIRST_OF_RUN,
    OLD_REPORT,
    RECEIVER_BEHIND_BYTES,
    ReportComposer,
    RoundTrips,
    SenderReport,
    decode_sender_report,
)


def _report(seq, t_s, sent, offered=None, session="run1", **extra):
    fields = dict(superseded=0, expired=0, app_limited=False)
    fields.update(extra)
    return SenderReport(session, seq, t_s, offered if offered is not None else sent, sent, **fields).encode()


def test_an_interval_is_the_difference_of_two_reports_each_side_on_its_own_clock():
    c = ReportComposer()
    assert c.on_report(_report(1, 100.0, 1000), 5000.0) == (None, FIRST_OF_RUN)
    c.received(40_000, managed=True)
    c.received(2_000, managed=False)
    interval, why = c.on_report(
        _report(2, 100.5, 51_000, offered=60_000, superseded=3, rtt_s=[0.01, 0.02], blocked_s=0.3), 5000.6
    )
    assert why is None
    assert interval.interval_s == pytest.approx(0.6) and interval.sender_interval_s == pytest.approx(0.5)
    assert (interval.delivered_bytes, interval.unmanaged_bytes) == (42_000, 2_000)
    assert (interval.sent_bytes, interval.offered_bytes, interval.superseded) == (50_000, 59_000, 3)
    assert interval.rtt_s == (0.01, 0.02) and not interval.receiver_behind and interval.sender_blocked_s == 0.3


def test_an_interval_says_which_trains_the_twin_refused_and_why():
    c = ReportComposer()
    c.on_report(_report(1, 100.0, 1000), 5000.0)
    for why in ("receiver_late", "out_of_order", "receiver_late"):
        c.train_refused(why)
    interval, _ = c.on_report(_report(2, 100.5, 2000), 5000.5)
    assert interval.probe_refused == "out_of_order:1,receiver_late:2"
    interval, _ = c.on_report(_report(3, 101.0, 3000), 5001.0)
    assert interval.probe_refused == ""  # the next interval starts from none


def test_an_interval_over_a_reconnection_carries_no_link_bytes():
    """Live beside busy loops (2026-11-30) the robots' bridge found its new link socket late: one
    interval read 0 acked bytes, the next twice the 20 Mbit/s link's rate, taken for its capacity
    (38 Mbit/s). An interval in which either side's link socket changed says its link bytes are not
    known (0), and the manager counts the frames; the next one is the link's again."""

    def report(seq, t_s, acked, sockets):
        return _report(seq, t_s, 1000 * seq, link_sent_bytes=acked, link_acked_bytes=acked, link_sockets=sockets)

    c = ReportComposer()
    c.on_report(report(1, 100.0, 1_000_000, 1), 5000.0, 2_000_000, 1)
    steady, _ = c.on_report(report(2, 100.5, 2_200_000, 1), 5000.5, 3_200_000, 1)
    assert (steady.acked_link_bytes, steady.sent_link_bytes, steady.delivered_link_bytes) == (1_200_000,) * 3
    robots_new, _ = c.on_report(report(3, 101.0, 4_600_000, 2), 5001.0, 4_400_000, 1)
    assert (robots_new.acked_link_bytes, robots_new.sent_link_bytes, robots_new.delivered_link_bytes) == (0, 0, 0)
    twin_new, _ = c.on_report(report(4, 101.5, 5_800_000, 2), 5001.5, 5_600_000, 2)
    assert (twin_new.acked_link_bytes, twin_new.delivered_link_bytes) == (0, 0)
    again, _ = c.on_report(report(5, 102.0, 7_000_000, 2), 5002.0, 6_800_000, 2)
    assert (again.acked_link_bytes, again.delivered_link_bytes) == (1_200_000, 1_200_000)


def test_a_lost_report_makes_the_next_interval_longer_not_wrong():
    c = ReportComposer()
    c.on_report(_report(1, 0.0, 0), 10.0)
    c.received(10_000, managed=True)
    # report 2 lost on the way
    c.received(10_000, managed=True)
    interval, _ = c.on_report(_report(3, 1.0, 20_000), 11.0)
    assert (interval.sent_bytes, interval.delivered_bytes, interval.sender_interval_s) == (20_000, 20_000, 1.0)


def test_duplicated_reordered_bad_and_backwards_reports_are_refused_and_counted():
    c = ReportComposer()
    c.on_report(_report(1, 0.0, 0), 10.0)
    assert c.on_report(_report(2, 0.5, 100), 10.5)[1] is None
    assert c.on_report(_report(2, 0.5, 100), 10.6) == (None, OLD_REPORT)  # duplicated
    assert c.on_report(_report(1, 0.0, 0), 10.7) == (None, OLD_REPORT)  # reordered
    for bad in (
        b"not json",
        b"[]",
        json.dumps({"v": 1, "session": "run1", "seq": 3}).encode(),  # fields missing
        _report(3, float("nan"), 10),
        _report(3, 1.0, -5),
        json.dumps({"v": 99}).encode(),
    ):
        assert c.on_report(bad, 11.0) == (None, BAD_REPORT), bad
    # a counter going down within a run: refused, and the intervals restart from it
    assert c.on_report(_report(3, 1.0, 50), 11.0) == (None, COUNTER_BACKWARDS)
    assert c.on_report(_report(4, 1.5, 150), 11.5)[0].sent_bytes == 100
    # the robots' bridge restarted: a new run starts the intervals again
    assert c.on_report(_report(1, 0.0, 0, session="run2"), 12.0) == (None, FIRST_OF_RUN)
    # a silent far side: the next report after more than MAX_INTERVAL_S restarts the intervals
    assert c.on_report(_report(2, 60.0, 10, session="run2"), 72.0) == (None, FIRST_OF_RUN)
    assert c.refused == {BAD_REPORT: 6, OLD_REPORT: 2, FIRST_OF_RUN: 3, COUNTER_BACKWARDS: 1}


def test_the_decoder_names_what_is_wrong():
    decoded = decode_sender_report(_report(7, 1.5, 10, rtt_s=[0.1]))
    assert (decoded.seq, decoded.t_s, decoded.rtt_s) == (7, 1.5, (0.1,))
    for payload, word in (
        (_report(7, 1.5, 10, rtt_s=["x"]), "rtt_s"),
        (_report(7, 1.5, 10, superseded=-1), "superseded"),
        (_report(7, 1.5, 10, pacing_mbps=float("inf")), "pacing_mbps"),
    ):
        try:
            decode_sender_report(payload)
        except ValueError as exc:
            assert word in str(exc)
        else:
            raise AssertionError(f"{payload!r} decoded")


def test_the_receiver_is_behind_only_when_its_socket_queue_stays_high():
    c = ReportComposer()
    c.on_report(_report(1, 0.0, 0), 0.0)
    c.sample_receive_queue(RECEIVER_BEHIND_BYTES + 1)  # one burst: not behind
    c.sample_receive_queue(0)
    c.sample_receive_queue(None)  # no socket found
    interval, _ = c.on_report(_report(2, 0.5, 0), 0.5)
    assert not interval.receiver_behind and interval.receive_queue_max_bytes == RECEIVER_BEHIND_BYTES + 1
    c.sample_receive_queue(RECEIVER_BEHIND_BYTES)
    c.sample_receive_queue(2 * RECEIVER_BEHIND_BYTES)
    assert c.on_report(_report(3, 1.0, 0), 1.0)[0].receiver_behind
    assert not c.on_report(_report(4, 1.5, 0), 1.5)[0].receiver_behind  # each interval on its own


def test_round_trips_count_each_echo_once():
    rt = RoundTrips(keep=4)
    first = rt.heartbeat(1_000_000_000)
    second = rt.heartbeat(1_100_000_000)
    assert rt.echo(second, 1_130_000_000) == pytest.approx(0.03)
    assert rt.echo(second, 1_140_000_000) is None  # a repeated echo
    assert rt.echo(b"junk", 1_140_000_000) is None
    assert rt.echo(first, 1_200_000_000) == pytest.approx(0.2)
    for i in range(5):
        rt.heartbeat(2_000_000_000 + i)
    assert rt.take() == pytest.approx([0.03, 0.2]) and rt.take() == []


def _server_on_a_port_no_socket_here_uses():
    """A listening socket on a port that no established socket of this process has at either end.
    LinkSockets, like the bridge, finds its sockets by port among the process's own, and a pytest
    worker holds others: final37's receiver found five with the test's local port, four of them
    loopback connections of the worker (its ROS node's, active 0.3 s before) that had that port as
    theirs; how bind(0) came to give it out as well is not traced. The bridges' ports (7447, 7448)
    are below the ephemeral range, where no connection takes its port by itself."""
    import socket

    from cps_link.link_report import LinkSockets

    for _ in range(20):
        server = socket.socket()
        server.bind(("127.0.0.1", 0))
        port = server.getsockname()[1]
        if not LinkSockets(remote_port=port).read() and not LinkSockets(local_port=port).read():
            server.listen()
            return server
        server.close()
    raise AssertionError("20 ports in a row already in use by this process's sockets")


def test_link_sockets_give_each_sockets_queues():
    """The send queue (unacked and unsent bytes) and the receive queue (unread) of the link sockets,
    as /proc/net/tcp's tx_queue and rx_queue say them."""
    import socket

    from cps_link.link_report import LinkSockets

    with _server_on_a_port_no_socket_here_uses() as server:
        port = server.getsockname()[1]
        with socket.create_connection(("127.0.0.1", port)) as client, server.accept()[0]:
            client.setblocking(False)
            sent = 0
            try:  # the receiver never reads: its window fills, then the sender's buffer
                while True:
                    sent += client.send(b"x" * 65536)
            except BlockingIOError:
                pass
            sender, receiver = LinkSockets(remote_port=port), LinkSockets(local_port=port)

            def queues():
                (out,), (inbound,) = sender.read(), receiver.read()
                return out.send_queue_bytes, inbound.receive_queue_bytes

            # every byte sent waits in one of the two (once the ACKs in flight are back)
            assert wait_for(lambda: sum(queues()) == sent, 5.0), (queues(), sent)
            assert min(queues()) > 0


def test_link_sockets_set_the_kernels_user_timeout_on_each_link_socket_once():
    """bridge.yaml tcp_user_timeout_ms: the kernel ends a link connection whose data stays
    unacknowledged that long, so Zenoh's close of a cut transport does not wait for the restore."""
    import socket

    from cps_link.link_report import LinkSockets

    with _server_on_a_port_no_socket_here_uses() as server:
        port = server.getsockname()[1]
        with socket.create_connection(("127.0.0.1", port)) as client, server.accept()[0] as accepted:
            untouched = LinkSockets(remote_port=port)
            assert len(untouched.read()) == 1
            assert client.getsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT) == 0
            sender, receiver = (
                LinkSockets(remote_port=port, user_timeout_ms=1000),
                LinkSockets(local_port=port, user_timeout_ms=1500),
            )
            assert len(sender.read()) == 1 and len(receiver.read()) == 1
            assert client.getsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT) == 1000
            assert accepted.getsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT) == 1500
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT, 7)
            sender.read()  # set once per socket, not at every read
            assert client.getsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT) == 7
            assert sender.user_timeout_refused == receiver.user_timeout_refused == 0
            refused = LinkSockets(remote_port=port, user_timeout_ms=-5)  # the kernel says EINVAL
            assert len(refused.read()) == 1 and refused.user_timeout_refused == 1


def test_link_sockets_end_their_connections_and_the_peer_sees_the_end():
    """A session reopened because Zenoh no longer holds its transport: the bridge ends that
    transport's connection itself (closing the session does not), and the peer reads its end."""
    import socket

    from cps_link.link_report import LinkSockets

    with _server_on_a_port_no_socket_here_uses() as server:
        port = server.getsockname()[1]
        with socket.create_connection(("127.0.0.1", port)) as client, server.accept()[0] as accepted:
            accepted.settimeout(5.0)
            client.sendall(b"z")
            assert accepted.recv(1) == b"z"
            assert LinkSockets(remote_port=port).end_connections() == 1
            assert accepted.recv(1) == b""  # the end of the connection, not a timeout
            with pytest.raises(OSError):
                client.sendall(b"z")
        assert LinkSockets(remote_port=port).end_connections() == 0  # none left


def test_link_sockets_look_for_new_sockets_only_when_one_closed_or_after_the_rescan_period():
    import socket

    from cps_link.link_report import LinkSockets

    with _server_on_a_port_no_socket_here_uses() as server:
        port = server.getsockname()[1]
        sender = LinkSockets(remote_port=port, rescan_s=3600.0)
        first = socket.create_connection(("127.0.0.1", port))
        assert len(sender.read()) == 1
        with socket.create_connection(("127.0.0.1", port)) as second:
            assert len(sender.read()) == 1  # the second is not looked for while the first is open
            first.close()
            (info,) = sender.read()  # the first closed: looked again, the second found
            second.sendall(b"y" * 1000)
            assert wait_for(lambda: sender.read()[0].bytes_acked >= 1000, 5.0)
        server.accept()[0].close()


def test_the_link_sockets_tcp_payload_counts_and_rtt_from_tcp_info_stay_monotone_across_a_reconnection():
    """The bridge reads its own (Zenoh's) link socket: found by port in /proc/net/tcp and by inode
    among this process's descriptors; TCP_INFO's bytes count every byte the link carried."""
    import socket
    import time

    from cps_link.link_report import LinkSockets

    server = _server_on_a_port_no_socket_here_uses()
    port = server.getsockname()[1]
    sender, receiver = LinkSockets(remote_port=port), LinkSockets(local_port=port)
    assert math.isnan(sender.read_s)  # no read yet: no instant its counters are true of
    totals = []
    for _ in range(2):  # a connection, then a reconnection
        client = socket.create_connection(("127.0.0.1", port))
        accepted, _ = server.accept()
        client.sendall(b"x" * 50_000)
        got = 0
        while got < 50_000:
            got += len(accepted.recv(65536))
        assert wait_for(lambda: any(i.bytes_acked >= 50_000 for i in sender.read()), 5.0)  # the ACKs are back
        before_s = time.monotonic()
        infos = sender.read()
        # the instant of TCP_INFO's counters, which the robots' report is stamped with
        assert before_s <= sender.read_s <= time.monotonic()
        assert len(infos) == 1 and infos[0].rtt_us > 0 and infos[0].bytes_acked >= 50_000
        receiver.read()
        totals.append((sender.totals()["bytes_new"], receiver.totals()["bytes_received"]))
        client.close()
        accepted.close()
    sender.read(), receiver.read()
    assert totals[0] == (50_000, 50_000) and totals[1] == (100_000, 100_000)
    assert (sender.sockets_found, receiver.sockets_found) == (2, 2)  # the reconnection counted
    assert sender.totals()["bytes_new"] == 100_000 and sender.read() == []  # closed: still counted
    server.close()


def test_a_read_is_stamped_when_the_kernel_gave_its_counters_not_after_the_queues(monkeypatch):
    """The byte counters are true of the getsockopt's instant: the queues' ioctls and the dup's close
    after it may let another thread hold the GIL for its 5 ms switch interval, and a probe train's
    span measured between two late stamps reads the link fast or slow."""
    import socket
    import time

    from cps_link import link_report
    from cps_link.link_report import LinkSockets

    ioctls_began = []
    real_ioctl = link_report.fcntl.ioctl

    def slow_ioctl(*args):
        ioctls_began.append(time.monotonic())
        time.sleep(0.01)
        return real_ioctl(*args)

    with _server_on_a_port_no_socket_here_uses() as server:
        port = server.getsockname()[1]
        with socket.create_connection(("127.0.0.1", port)), server.accept()[0]:
            sockets = LinkSockets(remote_port=port)
            monkeypatch.setattr(link_report.fcntl, "ioctl", slow_ioctl)
            (info,) = sockets.read()
    assert len(ioctls_began) == 2
    assert sockets.read_s == info.read_s <= ioctls_began[0]


def test_an_interval_carries_the_link_sockets_bytes_beside_the_frames():
    c = ReportComposer()
    c.on_report(_report(1, 0.0, 0, link_sent_bytes=1_000), 10.0, link_received_bytes=900)
    c.received(40_000, managed=True)
    interval, _ = c.on_report(_report(2, 0.5, 40_000, link_sent_bytes=45_000), 10.5, link_received_bytes=42_000)
    assert (interval.sent_link_bytes, interval.delivered_link_bytes) == (44_000, 41_100)
    # not readable (0) on either side: no link bytes, the frames stand
    interval, _ = c.on_report(_report(3, 1.0, 80_000), 11.0, link_received_bytes=0)
    assert (interval.sent_link_bytes, interval.delivered_link_bytes) == (0, 0)
