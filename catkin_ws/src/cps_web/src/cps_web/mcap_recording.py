"""A mission recorded as MCAP with the ROS 1 profile (no rospy): each message as it came off the
wire, its channel's schema the publisher's own message definition (`ros1msg`), written by the PyPI
`mcap-ros1-support` writer. Nothing is deserialized: a raw message is written as received.

`link_topics` names what crosses the link (the managed clouds and video, tf, odometry, battery,
joint states, mission state): what a user replays to reproduce a mission.
"""

import collections
import json
import threading
import time
from typing import Dict, List

from mcap.writer import CompressionType
from mcap_ros1.writer import Writer

from cps_fleet import names

LIBRARY = "cps_web"


class RecordingError(ValueError):
    """The message cannot be recorded (no type or definition in its connection header)."""


class _RawMessage:
    """A serialized ROS 1 message in the shape mcap_ros1's writer takes: its class carries `_type`
    and `_full_text` (the definition), `serialize` writes the bytes as they came."""

    __slots__ = ("_buff",)

    def __init__(self, buff: bytes):
        self._buff = buff

    def serialize(self, stream):
        stream.write(self._buff)


# Compression of the MCAP chunks: lz4 by default, as the mission bag's (`rosbag record --lz4`): a
# few times less CPU than zstd on the robots' host, which the recorder shares with the mission.
COMPRESSIONS = {"lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD, "none": CompressionType.NONE}
# What may wait for the writer, in bytes (raw clouds are ~1 MB each): beyond it a message is
# dropped and counted, never the receiving threads held up.
DEFAULT_BACKLOG_BYTES = 256 * 1024 * 1024


class McapRecording:
    """An open MCAP file written by its own thread: `write` from any thread (it only queues),
    `close` once (it writes what is queued, the drop counts as the file's `cps_recording` metadata,
    the index and the summary)."""

    def __init__(
        self,
        path: str,
        chunk_bytes: int = 4 * 1024 * 1024,
        compression: str = "lz4",
        backlog_bytes: int = DEFAULT_BACKLOG_BYTES,
    ):
        if compression not in COMPRESSIONS:
            raise ValueError(f"compression {compression!r}: one of {', '.join(COMPRESSIONS)}")
        self.path = path
        self._stream = open(path, "wb")
        self._writer = Writer(self._stream, chunk_size=chunk_bytes, compression=COMPRESSIONS[compression])
        self._types: Dict[str, type] = {}
        self._queue = collections.deque()
        self._queued_bytes = 0
        self._backlog_bytes = backlog_bytes
        self._cond = threading.Condition()
        self._closing = False
        self.messages = 0
        self.bytes_in = 0
        self.refused = 0  # no type or definition in the connection header
        self.dropped: Dict[str, int] = collections.Counter()  # per topic: the backlog was full
        self._thread = threading.Thread(target=self._write_queued, name="mcap_writer", daemon=True)
        self._thread.start()

    def write(self, topic: str, type_name: str, definition: str, payload: bytes, log_time_ns: int = None):
        """Queue one serialized message of `type_name` (its full definition as rosbag stores it)."""
        if not type_name or not definition:
            self.refused += 1
            raise RecordingError(f"{topic}: a message without its type or definition cannot be recorded")
        now = time.time_ns() if log_time_ns is None else log_time_ns
        with self._cond:
            if self._closing:
                return
            if self._queued_bytes + len(payload) > self._backlog_bytes:
                self.dropped[topic] += 1
                return
            self._queue.append((topic, type_name, definition, payload, now))
            self._queued_bytes += len(payload)
            self._cond.notify()

    def _write_queued(self):
        while True:
            with self._cond:
                while not self._queue and not self._closing:
                    self._cond.wait()
                if not self._queue:
                    return
                topic, type_name, definition, payload, now = self._queue.popleft()
                self._queued_bytes -= len(payload)
            kind = self._types.get(type_name)
            if kind is None:
                kind = type(f"Raw_{len(self._types)}", (_RawMessage,), {"_type": type_name, "_full_text": definition})
                self._types[type_name] = kind
            self._writer.write_message(topic, kind(bytes(payload)), log_time=now, publish_time=now)
            self.messages += 1
            self.bytes_in += len(payload)

    def close(self):
        with self._cond:
            if self._closing:
                return
            self._closing = True
            self._cond.notify()
        self._thread.join()
        self._writer.add_metadata(
            "cps_recording",
            {"messages": str(self.messages), "refused": str(self.refused), "dropped": json.dumps(dict(self.dropped))},
        )
        self._writer.finish()
        self._stream.close()


class ClockGate:
    """Writes into a McapRecording at the time a clock says, holding what arrives while that clock
    has not started (a replay's /clock: time 0) and logging it at the clock's first time. So the
    recorder subscribes at once and connects while the player waits (rosbag play -d): subscribing
    only once the clock ran, it missed the first second of a topic under load (the MCAP of the
    replay in final69 lacked 31 of scout's 1949 odometry messages and 18 of its 806 joint states).
    `write` from any thread."""

    def __init__(self, recording: McapRecording):
        self.recording = recording
        self._lock = threading.Lock()
        self._held = []  # (topic, type, definition, payload) before the clock started
        self._started = False

    def write(self, topic: str, type_name: str, definition: str, payload: bytes, clock_ns: int):
        """One message received when the clock said `clock_ns` (0: not started)."""
        if not self._started:
            with self._lock:
                if not self._started:
                    if clock_ns == 0:
                        if not type_name or not definition:  # refused and counted now, not at the release
                            self.recording.write(topic, type_name, definition, payload)
                        self._held.append((topic, type_name, definition, payload))
                        return
                    self._release(clock_ns)
        self.recording.write(topic, type_name, definition, payload, log_time_ns=clock_ns)

    def _release(self, clock_ns):
        for held in self._held:
            self.recording.write(*held, log_time_ns=clock_ns)
        self._held.clear()
        self._started = True

    def close(self):
        """Close the recording; what was held is written at time 0 if the clock never started."""
        with self._lock:
            if not self._started:
                self._release(0)
        self.recording.close()


def link_topics(robots, camera_robots) -> List[str]:
    """What crosses the link, resolved as the twin receives it: the managed clouds (as relayed at the
    twin), the managed video, tf, and each robot's light streams and mission state."""
    topics = [names.absolute(names.managed_cloud_at_twin(r)) for r in robots]
    topics += [names.absolute(names.robot_topic(r, names.CAMERA_IMAGE_COMPRESSED)) for r in camera_robots]
    for r in robots:
        topics += [names.absolute(t) for t in names.light_robot_streams(r)]
        topics.append(names.absolute(names.robot_topic(r, names.MISSION_STATE)))
    return topics + [names.TF, names.TF_STATIC]
