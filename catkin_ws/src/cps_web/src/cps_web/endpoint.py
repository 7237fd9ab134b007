"""The Foxglove WebSocket endpoint: the foxglove-sdk server, its channels, and a bounded queue.

Knows nothing of rospy. The node offers each received message with a function that converts it
(cps_web.convert); the offer is dropped at once when no viewer subscribes to its channel (nothing
is converted), and otherwise queued. One worker thread converts and logs. The queue is bounded: a
full queue drops the offer and counts it, so a slow viewer never holds back the ROS callbacks
that feed the map server's graph. Past the queue the SDK keeps at most `backlog` messages per
viewer and drops its oldest (its own bound), so a stalled viewer costs a fixed amount of memory.
Conversion errors (bad input) are counted per channel and logged, never raised into the node.
"""

import dataclasses
import logging
import queue
import threading
import time
from typing import Callable, Dict, Optional

import foxglove
from foxglove import channels as fx_channels
from foxglove.websocket import Capability, ServerListener

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
    bad: int = 0  # the conversion refused the message (bad input)
    failed: int = 0  # the conversion raised anything else: a defect, logged with its traceback
    logged: int = 0
    by_channel: Dict[str, Dict[str, int]] = dataclasses.field(default_factory=dict)

    def count(self, topic, what):
        setattr(self, what, getattr(self, what) + 1)
        row = self.by_channel.setdefault(topic, {"queued": 0, "dropped": 0, "bad": 0, "failed": 0, "logged": 0})
        row[what] += 1


class _Listener(ServerListener):
    """Re-sends a latched channel's latest message to a viewer that subscribes to it."""

    def __init__(self, endpoint):
        self.endpoint = endpoint

    def on_subscribe(self, client, channel):
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
    ):
        """`channels`: Foxglove topic -> kind (one of the kinds above); `latched`: topics whose latest
        message a new subscriber gets at once (the map, the changes, static tf)."""
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

    def offer(self, topic: str, make: Callable[[], object], log_time_ns: Optional[int] = None) -> bool:
        """Queue `make()` (the converted message) for `topic` if a viewer subscribes to it; a latched
        topic's offer is also kept for the next subscriber. False when dropped or not watched."""
        if topic in self.latched:
            with self._lock:
                self._latest[topic] = (make, log_time_ns)
        if not self.watched(topic):
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
        with self._lock:
            c = self.counters
            return {
                "queued": c.queued,
                "dropped": c.dropped,
                "bad": c.bad,
                "failed": c.failed,
                "logged": c.logged,
                "queue_length": self._queue.qsize(),
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
