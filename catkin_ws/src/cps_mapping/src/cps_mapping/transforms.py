"""The map server's transforms, read lazily (issue 37).

/tf and /tf_static arrive as serialized bytes (rospy.AnyMsg): the receiving thread only appends
them to a deque, without a lock or any deserialisation. Whoever looks a transform up (the insertion
thread, before each cloud) first reads what arrived into a tf2 BufferCore, in arrival order. With
tf2_ros's listener every /tf message took its thread through deserialisation and two locks: a
hundred replayed robots' transforms (2 560 messages/s) made lock convoys that left the twin's core
idle while clouds waited for their poses.
"""

import collections
import threading

import genpy
import tf2_py
from tf2_msgs.msg import TFMessage

AUTHORITY = "map_server"
CACHE_S = 30.0


class LazyTransforms:
    """A tf2 buffer fed lazily from received /tf and /tf_static messages; thread-safe."""

    def __init__(self, cache_s=CACHE_S):
        self.buffer = tf2_py.BufferCore(genpy.Duration(cache_s))
        self._pending = collections.deque()  # (message, static), appended by the receiving threads
        self._lock = threading.Lock()  # the readers: the insertion thread, the change detection timer
        self.read = 0  # transforms read into the buffer
        self.refused = 0  # messages that did not deserialize, transforms the binding could not convert

    def received(self, message, static=False):
        """A /tf (or /tf_static) message as received: rospy.AnyMsg bytes or a TFMessage."""
        self._pending.append((message, static))

    def _read_pending(self):
        while self._pending:
            message, static = self._pending.popleft()
            data = getattr(message, "_buff", None)
            try:
                msg = TFMessage().deserialize(data) if data is not None else message
            except Exception:  # genpy raises struct.error, DeserializationError...
                self.refused += 1
                continue
            add = self.buffer.set_transform_static if static else self.buffer.set_transform
            for transform in msg.transforms:
                try:
                    add(transform, AUTHORITY)  # tf2 itself ignores (and prints) NaN and bad quaternions
                except Exception:  # a transform the binding cannot convert
                    self.refused += 1
                    continue
                self.read += 1

    def lookup(self, target_frame, source_frame, stamp):
        """geometry_msgs/TransformStamped of `source_frame` in `target_frame` at `stamp` (genpy.Time;
        0: the latest), from what has arrived so far; tf2_py.TransformException when it is not
        known (yet). Never waits."""
        with self._lock:
            self._read_pending()
            return self.buffer.lookup_transform_core(target_frame, source_frame, stamp)

    def catch_up(self):
        """Read what arrived (the insertion thread calls it when idle, so the deque stays short)."""
        with self._lock:
            self._read_pending()

    def clear(self):
        """Forget every transform (time jumped back: a replayed bag looped)."""
        with self._lock:
            self._pending.clear()
            self.buffer.clear()
