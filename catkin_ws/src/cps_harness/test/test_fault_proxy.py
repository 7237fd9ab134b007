"""The fault-injecting proxy (ROS-free) against an echo server on loopback: it forwards, and a cut,
a stall, a throttle and a reset each do what the link tests rely on."""

import socket
import threading
import time

import pytest

from cps_harness.fault_proxy import FaultProxy
from cps_harness.testing import wait_for

WAIT_S = 5.0


@pytest.fixture
def echo_port():
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)
    stop = threading.Event()

    def serve(conn):
        with conn:
            while True:
                try:
                    data = conn.recv(65536)
                except OSError:
                    return
                if not data:
                    return
                conn.sendall(data)

    def accept():
        server.settimeout(0.1)
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except socket.timeout:
                continue
            except OSError:  # closed at the end of the test
                return
            conn.settimeout(None)
            threading.Thread(target=serve, args=(conn,), daemon=True).start()

    threading.Thread(target=accept, daemon=True).start()
    yield server.getsockname()[1]
    stop.set()
    server.close()


@pytest.fixture
def proxy(echo_port):
    p = FaultProxy(echo_port)
    yield p
    p.close()


def _client(proxy):
    c = socket.create_connection(("127.0.0.1", proxy.port), timeout=WAIT_S)
    c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return c


def _echo(conn, data, timeout_s=WAIT_S):
    """Sends data and reads its echo back (socket.timeout when it does not come within timeout_s)."""
    conn.settimeout(timeout_s)
    conn.sendall(data)
    got = b""
    while len(got) < len(data):
        chunk = conn.recv(65536)
        if not chunk:
            raise ConnectionError("closed")
        got += chunk
    return got


def test_it_forwards_both_ways(proxy):
    with _client(proxy) as c:
        assert _echo(c, b"hello" * 1000) == b"hello" * 1000
    # The counter moves after the bytes are handed on: the echo may be read before it does.
    assert wait_for(
        lambda: proxy.forwarded_bytes["up"] >= 5000 and proxy.forwarded_bytes["down"] >= 5000, timeout_s=WAIT_S
    ), proxy.forwarded_bytes


def test_a_cut_freezes_open_connections_and_holds_new_ones_until_restored(proxy):
    with _client(proxy) as c:
        assert _echo(c, b"a") == b"a"
        proxy.cut()
        with pytest.raises(socket.timeout):
            _echo(c, b"b", timeout_s=0.3)
        late = _client(proxy)  # accepted, held
        with pytest.raises(socket.timeout):
            _echo(late, b"c", timeout_s=0.3)
        proxy.restore()
        # What was sent during the cut arrives after it, as TCP retransmits over a returned cable.
        c.settimeout(WAIT_S)
        assert c.recv(10) == b"b"
        late.settimeout(WAIT_S)
        assert late.recv(10) == b"c"
        late.close()


def test_a_stall_freezes_open_connections_only(proxy):
    with _client(proxy) as c:
        assert _echo(c, b"a") == b"a"
        proxy.stall()
        with pytest.raises(socket.timeout):
            _echo(c, b"b", timeout_s=0.3)
        with _client(proxy) as fresh:
            assert _echo(fresh, b"new") == b"new"
        proxy.restore()
        c.settimeout(WAIT_S)
        assert c.recv(10) == b"b"


def test_a_reset_closes_every_connection_with_an_rst(proxy):
    c = _client(proxy)
    assert _echo(c, b"a") == b"a"
    assert proxy.reset() == 1
    c.settimeout(WAIT_S)
    with pytest.raises((ConnectionResetError, ConnectionError)):
        _echo(c, b"b")
        _echo(c, b"b")  # the first send may still be taken before the RST is seen
    c.close()
    with _client(proxy) as again:  # the link itself is still there
        assert _echo(again, b"c") == b"c"


def test_a_throttle_bounds_the_rate(proxy):
    rate_bytes_per_s = 100_000
    proxy.throttle(rate_bytes_per_s)
    data = b"x" * 150_000
    with _client(proxy) as c:
        t0 = time.monotonic()
        assert _echo(c, data, timeout_s=10) == data
        elapsed_s = time.monotonic() - t0
    # 150 kB each way at 100 kB/s (each way has its own bucket, with a 0.1 s burst): ~1.4-1.5 s.
    assert 1.2 <= elapsed_s <= 4.0, elapsed_s
    proxy.throttle(None)
    with _client(proxy) as c:
        t0 = time.monotonic()
        assert _echo(c, data) == data
        assert time.monotonic() - t0 < 1.0


def test_a_schedule_runs_faults_in_order(proxy):
    proxy.run_schedule([(0.2, "restore"), (0.0, "cut")]).join(timeout=WAIT_S)
    assert proxy.up
    with _client(proxy) as c:
        assert _echo(c, b"ok") == b"ok"


def test_a_one_way_cut_stops_only_that_way(proxy):
    with _client(proxy) as c:
        assert _echo(c, b"a") == b"a"
        proxy.cut("down")  # the echo server still gets our bytes; its answers wait
        with pytest.raises(socket.timeout):
            _echo(c, b"b", timeout_s=0.3)
        assert wait_for(lambda: proxy.forwarded_bytes["up"] >= 2, timeout_s=WAIT_S)
        proxy.restore()
        c.settimeout(WAIT_S)
        assert c.recv(10) == b"b"
