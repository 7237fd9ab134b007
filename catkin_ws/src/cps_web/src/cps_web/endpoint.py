"""The Foxglove WebSocket endpoint: the foxglove-sdk server, its channels, and a bounded queue.

Knows nothing of rospy. The node offers each received message with a function that converts it
(cps_web.convert); the offer is dropped at once when no viewer subscribes to its channel (nothing
is converted), and otherwise queued. One worker thread converts and logs. The queue is bounded: a
full queue drops the offer and counts it, so a slow viewer never holds back the ROS callbacks
that feed the map server's graph. Past the queue the SDK keeps at most `backlog` messages per
viewer and drops its oldest (its own bound), so a stalled viewer costs a fixed amount of memory.
Conversion errors (bad input) are counted per channel and logged, never raised into the node.

A viewer that does not read costs no conversion either. The SDK does not say how far behind a
viewer is, but the kernel does: the bytes its socket holds unsent or unacknowledged (`ss`'s
Send-Q, SIOCOUTQ on the endpoint's own descriptors). While every viewer's socket holds
`stalled_bytes` or more, nothing is converted (the offer is counted `stalled`), so a stalled
viewer's socket fills once and then costs nothing, and a slow one is converted for at about the
rate it drains. When a viewer takes data again, the latched channels' latest is sent at once.
The gate is the endpoint's, not each viewer's (the SDK does not say which socket is whose): while
one viewer reads, what a stalled one subscribed is converted too, and the SDK drops it for it.
"""

import dataclasses
import fcntl
import logging
import os
import queue
import socket
import stat
import struct
import termios
import threading
import time
from typing import Callable, Dict, List, Optional

import foxglove
from foxglove import channels as fx_channels
from foxglove.websocket import Capability, ServerListener

from cps_ros import sockets
from cps_web.convert import ENDPOINT_SCHEMA, HEALTH_SCHEMA, LINK_SCHEMA

LOG = logging.getLogger("cps_web.endpoint")

# Channel kinds: the foxglove-sdk typed channel (protobuf schema) or a JSON schema.
POINT_CLOUD, FRAME_TRANSFORMS, SCENE_UPDATE, POSE_IN_FRAME, COMPRESSED_IMAGE = (
    "PointCloud",
    "FrameTransforms",
    "SceneUpdate",
    "PoseInFrame",
    "CompressedImage",
)
HEALTH_JSON, LINK_JSON, ENDPOINT_JSON = "health", "link", "endpoint"
_TYPED = {
    POINT_CLOUD: fx_channels.PointCloudChannel,
    FRAME_TRANSFORMS: fx_channels.FrameTransformsChannel,
    SCENE_UPDATE: fx_channels.SceneUpdateChannel,
    POSE_IN_FRAME: fx_channels.PoseInFrameChannel,
    COMPRESSED_IMAGE: fx_channels.CompressedImageChannel,
}
_JSON = {HEALTH_JSON: HEALTH_SCHEMA, LINK_JSON: LINK_SCHEMA, ENDPOINT_JSON: ENDPOINT_SCHEMA}

DEFAULT_HOST = "127.0.0.1"  # the twin's host only
DEFAULT_PORT = 8765  # Foxglove's usual port
DEFAULT_QUEUE = 64  # offers waiting for the worker
DEFAULT_BACKLOG = 32  # messages the SDK holds per viewer before it drops its oldest
# Unsent bytes towards a viewer from which it counts as not reading: a reading viewer's socket on
# the twin's host holds ~0 (a 55 000-point map is ~0.9 MB and drains in milliseconds), a stalled
# one's fills to its buffers (several MB).
DEFAULT_STALLED_BYTES = 256 * 1024
CHECK_PERIOD_S = 0.1  # how often the viewers' sockets are looked at (an ioctl each)
SCAN_PERIOD_S = 1.0  # how often the endpoint's descriptors are listed for new viewers' sockets (~0.3 ms)
# After this long with no viewer taking data, the node drops its ROS inputs that only viewers need.
DEFAULT_STALL_HOLD_S = 2.0


class SocketQueues:
    """The unsent or unacknowledged bytes of each connection to a local TCP port of this process
    (ioctl SIOCOUTQ on its own descriptors: what `ss` shows as Send-Q). Reading /proc/net/tcp would
    list every socket of the host, over a thousand on a running twin, at ~0.1 s of CPU a read. The
    descriptors are listed again every SCAN_PERIOD_S, or at once after `rescan` (a new viewer)."""

    def __init__(self, port: Callable[[], int]):
        self.port = port
        self._ours: Dict[int, int] = {}  # socket inode -> descriptor, of each connection to the port
        self._others = set()  # inodes of every other socket (the listener, ROS, the master)
        self._scanned_at = -float("inf")

    def rescan(self):
        self._scanned_at = -float("inf")

    def __call__(self) -> Optional[List[int]]:
        """The bytes each connection holds; None when this process's descriptors cannot be listed."""
        now = time.monotonic()
        if now - self._scanned_at >= SCAN_PERIOD_S:
            try:
                self._scan()
            except OSError:
                return None
            self._scanned_at = now
        out = []
        for inode, fd in list(self._ours.items()):
            try:
                if os.fstat(fd).st_ino != inode:  # closed, and the descriptor reused
                    raise OSError
                out.append(struct.unpack("i", fcntl.ioctl(fd, termios.TIOCOUTQ, b"\0" * 4))[0])
            except OSError:  # closed meanwhile
                self._ours.pop(inode, None)
        return out

    def _scan(self):
        ours, seen = {}, set()
        for name in os.listdir("/proc/self/fd"):
            fd = int(name)
            try:
                status = os.fstat(fd)
            except OSError:  # closed meanwhile (or the listing's own descriptor)
                continue
            if not stat.S_ISSOCK(status.st_mode):
                continue
            seen.add(status.st_ino)
            if status.st_ino in self._others:
                continue
            if status.st_ino in self._ours or self._is_connection(fd):
                ours[status.st_ino] = fd
            else:
                self._others.add(status.st_ino)
        self._ours = ours
        self._others &= seen

    def _is_connection(self, fd) -> bool:
        """Whether descriptor `fd` is a TCP connection to the port (asked of the kernel directly:
        cps_ros.sockets says why)."""
        return (
            sockets.socket_type(fd) == socket.SOCK_STREAM
            and sockets.inet_port(fd, peer=True) is not None  # a listener has no peer
            and sockets.inet_port(fd) == self.port()
        )


def parse_listen(text: str):
    """`host:port` (port 0: any free one) as (host, port); ValueError saying what is wrong."""
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        raise ValueError(f"listen address {text!r}: expected host:port, e.g. {DEFAULT_HOST}:{DEFAULT_PORT}")
    try:
        number = int(port)
    except ValueError:
        raise ValueError(f"listen address {text!r}: port {port!r} is not a number") from None
    if not 0 <= number <= 65535:
        raise ValueError(f"listen address {text!r}: port {number} out of 0..65535")
    return host.strip("[]"), number


class ListenError(RuntimeError):
    """The server could not listen where asked (port in use, address not on this host)."""


@dataclasses.dataclass
class Counters:
    """What happened to offers since the start, in all and per channel."""

    queued: int = 0
    dropped: int = 0  # the queue was full
    stalled: int = 0  # no viewer took data (every viewer's socket was full): not converted
    bad: int = 0  # the conversion refused the message (bad input)
    failed: int = 0  # the conversion raised anything else: a defect, logged with its traceback
    logged: int = 0
    by_channel: Dict[str, Dict[str, int]] = dataclasses.field(default_factory=dict)

    def count(self, topic, what):
        setattr(self, what, getattr(self, what) + 1)
        row = self.by_channel.setdefault(topic, dict.fromkeys(_COUNTED, 0))
        row[what] += 1


_COUNTED = ("queued", "dropped", "stalled", "bad", "failed", "logged")


class _Listener(ServerListener):
    """Re-sends a latched channel's latest message to a viewer that subscribes to it."""

    def __init__(self, endpoint):
        self.endpoint = endpoint

    def on_subscribe(self, client, channel):
        self.endpoint._viewer_subscribed()
        self.endpoint._resend_latched(channel.topic)


class Endpoint:
    """The server and its channels; `offer` from any thread, `close` at the end."""

    def __init__(
        self,
        channels: Dict[str, str],
        latched=(),
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        queue_size: int = DEFAULT_QUEUE,
        backlog: int = DEFAULT_BACKLOG,
        name: str = "cps twin",
        clock: Callable[[], float] = time.time,
        services=(),
        stalled_bytes: int = DEFAULT_STALLED_BYTES,
        stall_hold_s: float = DEFAULT_STALL_HOLD_S,
        send_queues: Optional[Callable[[], Optional[List[int]]]] = None,
        monotonic: Callable[[], float] = time.monotonic,
    ):
        """`channels`: Foxglove topic -> kind (one of the kinds above); `latched`: topics whose latest
        message a new subscriber gets at once (the map, the changes, static tf); `send_queues`: the
        viewers' unsent bytes (default: the kernel's, SocketQueues of the server's port); `monotonic`:
        the clock of the socket checks and the stall hold."""
        self.context = foxglove.Context()
        self.channels = {}
        for topic, kind in channels.items():
            if kind in _TYPED:
                self.channels[topic] = _TYPED[kind](topic, context=self.context)
            elif kind in _JSON:
                self.channels[topic] = foxglove.Channel(topic, schema=_JSON[kind], context=self.context)
            else:
                raise ValueError(f"channel {topic}: unknown kind {kind!r}")
        self.latched = set(latched)
        self.counters = Counters()
        self.clock = clock
        self._queue = queue.Queue(maxsize=queue_size)
        self._latest: Dict[str, tuple] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.stalled_bytes = stalled_bytes
        self.stall_hold_s = stall_hold_s
        self._send_queues = send_queues or SocketQueues(lambda: self.port)
        self._monotonic = monotonic
        self._checked_at = -float("inf")
        self._accepting = True
        self._blocked_since: Optional[float] = None
        self._viewers = (0, 0)  # (connections, stalled ones) when last looked at
        try:
            self.server = foxglove.start_server(
                name=name,
                host=host,
                port=port,
                server_listener=_Listener(self),
                message_backlog_size=backlog,
                context=self.context,
                capabilities=[Capability.Services] if services else None,
                supported_encodings=["json"] if services else None,
                services=list(services) or None,
            )
        except Exception as exc:  # the SDK's FoxgloveError: a port in use, an address not here
            raise ListenError(f"the Foxglove endpoint cannot listen on {host}:{port}: {exc}") from exc
        self._worker = threading.Thread(target=self._work, name="foxglove_endpoint", daemon=True)
        self._worker.start()

    @property
    def port(self) -> int:
        return self.server.port

    def watched(self, topic: str) -> bool:
        """Whether some viewer subscribes to `topic` now."""
        return self.channels[topic].has_sinks()

    def accepting(self) -> bool:
        """Whether some viewer takes data now: a connection holding fewer than `stalled_bytes`
        unsent (looked at every CHECK_PERIOD_S at most). True while no connection is seen or the
        sockets cannot be read: then the SDK's backlog is the only bound."""
        now = self._monotonic()
        with self._lock:
            if now - self._checked_at < CHECK_PERIOD_S:
                return self._accepting
            self._checked_at = now
        queues = self._send_queues()
        accepting = not queues or any(q < self.stalled_bytes for q in queues)
        with self._lock:
            resumed = accepting and not self._accepting
            self._accepting = accepting
            if accepting:
                self._blocked_since = None
            elif self._blocked_since is None:
                self._blocked_since = now
            self._viewers = (len(queues or ()), sum(q >= self.stalled_bytes for q in queues or ()))
        if resumed:  # the latched channels' latest, which the viewer missed while it was behind
            for topic in self.latched:
                if self.watched(topic):
                    self._resend_latched(topic)
        return accepting

    def stalled_s(self) -> float:
        """How long no viewer has taken data (0 while one does)."""
        if self.accepting():
            return 0.0
        with self._lock:
            return self._monotonic() - self._blocked_since if self._blocked_since is not None else 0.0

    def wanted(self, topic: str) -> bool:
        """Whether what feeds `topic` is worth receiving: a viewer subscribes to it, and some viewer
        took data within the last `stall_hold_s`."""
        return self.watched(topic) and self.stalled_s() < self.stall_hold_s

    def offer(self, topic: str, make: Callable[[], object], log_time_ns: Optional[int] = None) -> bool:
        """Queue `make()` (the converted message) for `topic` if a viewer subscribes to it and some
        viewer takes data; a latched topic's offer is also kept for the next subscriber. False when
        dropped, not watched, or stalled (counted)."""
        if topic in self.latched:
            with self._lock:
                self._latest[topic] = (make, log_time_ns)
        if not self.watched(topic):
            return False
        if not self.accepting():
            with self._lock:
                self.counters.count(topic, "stalled")
            return False
        return self._put(topic, make, log_time_ns)

    def _put(self, topic, make, log_time_ns) -> bool:
        try:
            self._queue.put_nowait((topic, make, log_time_ns))
        except queue.Full:
            with self._lock:
                self.counters.count(topic, "dropped")
            return False
        with self._lock:
            self.counters.count(topic, "queued")
        return True

    def _viewer_subscribed(self):
        """A viewer, maybe a new one, subscribed: its socket is looked at before the next offer."""
        rescan = getattr(self._send_queues, "rescan", None)
        if rescan:
            rescan()
        with self._lock:
            self._checked_at = -float("inf")

    def _resend_latched(self, topic):
        with self._lock:
            latest = self._latest.get(topic)
        if latest is not None:
            self._put(topic, *latest)

    def _work(self):
        while not self._stop.is_set():
            try:
                item = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                self._handle(*item)
            finally:
                self._queue.task_done()

    def _handle(self, topic, make, log_time_ns):
        if not self.accepting():  # every viewer fell behind since the offer was queued
            with self._lock:
                self.counters.count(topic, "stalled")
            return
        try:
            message = make()
        except (ValueError, TypeError, AttributeError) as exc:
            with self._lock:
                self.counters.count(topic, "bad")
                bad = self.counters.by_channel[topic]["bad"]
            if bad <= 3 or bad % 100 == 0:
                LOG.warning("%s: message refused (%d so far): %s", topic, bad, exc)
            return
        except Exception:  # a defect of ours: said loudly, counted, and the worker goes on
            with self._lock:
                self.counters.count(topic, "failed")
            LOG.exception("%s: conversion failed", topic)
            return
        self.channels[topic].log(message, log_time=log_time_ns)
        with self._lock:
            self.counters.count(topic, "logged")

    def snapshot(self) -> dict:
        """The counters as the endpoint's JSON row."""
        self.accepting()  # the viewers as they are now
        with self._lock:
            c = self.counters
            return {
                **{what: getattr(c, what) for what in _COUNTED},
                "queue_length": self._queue.qsize(),
                "viewers": self._viewers[0],
                "stalled_viewers": self._viewers[1],
                "by_channel": {k: dict(v) for k, v in c.by_channel.items()},
            }

    def wait_idle(self, timeout_s: float = 5.0) -> bool:
        """Until every queued offer was converted and logged (tests); False on timeout."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self._queue.unfinished_tasks == 0:
                return True
            time.sleep(0.01)
        return False

    def close(self):
        self._stop.set()
        self._worker.join(timeout=5.0)
        self.server.stop()
        for channel in self.channels.values():
            channel.close()
