"""A fault-injecting TCP proxy on loopback (ROS-free): put it between the robots' bridge and the
twin's listener and the link can be cut, stalled, throttled or reset on a schedule, without root
or network namespaces (issue 22: fault tests that run on a laptop and in CI).

  cut       both ways stop: open connections are frozen (their bytes wait in the kernel, as over a
            pulled cable that TCP later retransmits) and new connections are held, unconnected;
            cut("up") or cut("down") stops one way only (client -> target is "up")
  stall     open connections are frozen; new ones pass (a peer stuck behind a full buffer)
  restore   ends a cut or a stall: frozen connections resume, held ones are connected
  throttle  at most bytes_per_s each way (None: unlimited)
  reset     every open connection is closed with a TCP reset, both ends
"""

import select
import socket
import struct
import threading
import time

CHUNK_BYTES = 16384
POLL_S = 0.02


class FaultProxy:
    """Forwards 127.0.0.1:`port` (0: any free port) to (target_host, target_port)."""

    def __init__(self, target_port, target_host="127.0.0.1", port=0):
        self.target = (target_host, target_port)
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind(("127.0.0.1", port))
        self._listener.listen(16)
        self._listener.settimeout(POLL_S * 5)
        self.port = self._listener.getsockname()[1]
        self._lock = threading.Lock()
        self._pairs = []  # [client socket, upstream socket or None]
        self._cut = set()  # the ways cut: "up" (client -> target), "down"
        self._stalled = []  # the connections a stall froze
        self._bytes_per_s = None
        self._closed = threading.Event()
        self.accepted = self.resets = 0
        self.forwarded_bytes = {"up": 0, "down": 0}
        threading.Thread(target=self._accept_loop, name="fault_proxy", daemon=True).start()

    # --- faults -------------------------------------------------------------------------------
    def cut(self, way=None):
        with self._lock:
            self._cut |= {way} if way else {"up", "down"}

    def stall(self):
        with self._lock:
            self._stalled = list(self._pairs)

    def restore(self):
        with self._lock:
            self._cut, self._stalled = set(), []

    def throttle(self, bytes_per_s):
        with self._lock:
            self._bytes_per_s = None if bytes_per_s is None else float(bytes_per_s)

    def reset(self):
        """Close every open connection with an RST (SO_LINGER 0) on both sides; returns how many."""
        with self._lock:
            pairs, self._pairs = self._pairs, []
            self.resets += len(pairs)
        for pair in pairs:
            for sock in pair:
                _abort(sock)
        return len(pairs)

    @property
    def up(self):
        return not self._cut

    def connections(self):
        with self._lock:
            return sum(1 for _, up in self._pairs if up is not None)

    def run_schedule(self, steps):
        """Runs [(at_s, name, *args)] (seconds from now, a method's name) in a thread; returns it."""
        t0 = time.monotonic()

        def run():
            for at_s, name, *args in sorted(steps, key=lambda s: s[0]):
                if self._closed.wait(max(0.0, t0 + at_s - time.monotonic())):
                    return
                getattr(self, name)(*args)

        thread = threading.Thread(target=run, name="fault_schedule", daemon=True)
        thread.start()
        return thread

    def close(self):
        self._closed.set()
        self.reset()
        self._listener.close()

    # --- forwarding ---------------------------------------------------------------------------
    def _accept_loop(self):
        while not self._closed.is_set():
            try:
                client, _ = self._listener.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            pair = [client, None]
            with self._lock:
                self._pairs.append(pair)
                self.accepted += 1
            threading.Thread(target=self._connect, args=(pair,), daemon=True).start()

    def _alive(self, pair):
        with self._lock:
            return any(p is pair for p in self._pairs) and not self._closed.is_set()

    def _connect(self, pair):
        """Connects upstream once the link is not cut, then pumps both ways."""
        while self._alive(pair) and self._cut:
            time.sleep(POLL_S)
        if not self._alive(pair):
            return
        try:
            upstream = socket.create_connection(self.target, timeout=2.0)
        except OSError:
            self._drop(pair)
            return
        upstream.settimeout(None)
        upstream.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with self._lock:
            pair[1] = upstream
        for src, dst, way in ((pair[0], upstream, "up"), (upstream, pair[0], "down")):
            threading.Thread(target=self._pump, args=(pair, src, dst, way), daemon=True).start()

    def _frozen(self, pair, way):
        with self._lock:
            return way in self._cut or any(p is pair for p in self._stalled)

    def _pump(self, pair, src, dst, way):
        allowance_bytes, last_s = 0.0, time.monotonic()
        while self._alive(pair):
            if self._frozen(pair, way):
                time.sleep(POLL_S)
                continue
            rate = self._bytes_per_s
            chunk = CHUNK_BYTES
            if rate is not None:
                now = time.monotonic()
                allowance_bytes = min(rate * 0.1, allowance_bytes + (now - last_s) * rate)
                last_s = now
                if allowance_bytes < 1:
                    time.sleep(POLL_S)
                    continue
                chunk = max(1, min(CHUNK_BYTES, int(allowance_bytes)))
            try:
                if not select.select([src], [], [], POLL_S)[0] or self._frozen(pair, way):  # cut while waiting
                    continue
                data = src.recv(chunk)
            except (OSError, ValueError):  # reset or closed by another thread
                break
            if not data:
                break
            if rate is not None:
                allowance_bytes -= len(data)
            try:
                dst.sendall(data)
            except OSError:
                break
            with self._lock:
                self.forwarded_bytes[way] += len(data)
        self._drop(pair)

    def _drop(self, pair):
        with self._lock:
            if not any(p is pair for p in self._pairs):
                return
            self._pairs = [p for p in self._pairs if p is not pair]
        for sock in pair:
            if sock is not None:
                try:
                    sock.close()
                except OSError:
                    pass


def _abort(sock):
    if sock is None:
        return
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    except OSError:
        pass
    try:
        sock.close()
    except OSError:
        pass
