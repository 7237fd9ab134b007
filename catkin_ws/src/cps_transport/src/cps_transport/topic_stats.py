"""Live topic statistics: what `rostopic hz` and `rostopic bw` show, plus end-to-end latency,
over a sliding window (time injected, no ROS), reading header.stamp from serialized bytes, and a
per-message arrival log (stamp, receive time) for joining one cloud's arrivals at two places."""

import collections
import math
import struct

import numpy as np

_STAMP = struct.Struct("<II")


def has_header_first(message_definition):
    """True when the first field of a message definition is a std_msgs/Header."""
    for line in message_definition.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith("=" * 10):
            return False
        parts = line.split()
        return len(parts) >= 2 and parts[0] in ("Header", "std_msgs/Header") and "=" not in line
    return False


def stamp_ns_from_serialized(buffer):
    """header.stamp in integer nanoseconds (exact: a join key) of a serialized message that starts
    with a Header, or None."""
    if len(buffer) < 12:
        return None
    secs, nsecs = _STAMP.unpack_from(buffer, 4)
    if nsecs >= 1_000_000_000:
        return None
    return secs * 1_000_000_000 + nsecs


# One row per stamped message (cps_fleet.csv_log.CsvLog): the same capture stamp travels through
# voxel grid, Draco and the rate limiter, so the robots' side's rows and the twin's join per cloud
# (cps_experiments.report.latency_split).
# bytes: the serialized message; width, height: a sensor_msgs/CompressedImage's JPEG as delivered
# (empty for anything else), so a video's resolution is judged as the operator gets it.
ARRIVAL_COLUMNS = ("topic", "robot", "stamp_ns", "receive_s", "bytes", "width", "height")
COMPRESSED_IMAGE_TYPE = "sensor_msgs/CompressedImage"


def compressed_image_dimensions(buffer):
    """(width, height) of the JPEG in a serialized sensor_msgs/CompressedImage (header, format,
    data), or None when it is not one."""
    from cps_transport.image_compression import jpeg_dimensions

    view = memoryview(buffer)
    try:
        offset = 12  # header: seq, stamp
        for _ in range(2):  # header.frame_id, format
            (n,) = struct.unpack_from("<I", view, offset)
            offset += 4 + n
        (n,) = struct.unpack_from("<I", view, offset)
    except struct.error:
        return None
    offset += 4
    if offset + n > len(view):
        return None
    return jpeg_dimensions(view[offset : offset + n])


# counters.csv / physical_counters.csv: a node's per-cloud ledger counter (cps_ros.cloud_ledger), from
# its /diagnostics status, each time it changed (cps_experiments.ledger reads them back).
COUNTER_COLUMNS = ("time_s", "node", "input_topic", "key", "value")


# topic_stats' sliding window, s (its ~window_s).
DEFAULT_WINDOW_S = 2.0


class TopicWindow:
    """Receive time, serialized size and latency of the messages of one topic in the last window."""

    def __init__(self, window_s=2.0):
        if not window_s > 0:
            raise ValueError(f"window_s must be > 0, got {window_s}")
        self.window_s = float(window_s)
        self._events = collections.deque()  # (receive_s, size_bytes, latency_s or nan)
        self.total_messages = 0
        self.last_receive_s = None
        self.invalid_messages = 0

    def add(self, receive_s, size_bytes, stamp_s=None):
        latency = receive_s - stamp_s if stamp_s is not None and stamp_s > 0 else math.nan
        self._events.append((receive_s, size_bytes, latency))
        self.total_messages += 1
        self.last_receive_s = receive_s
        self._expire(receive_s)

    def _expire(self, now_s):
        while self._events and self._events[0][0] < now_s - self.window_s:
            self._events.popleft()

    def snapshot(self, now_s):
        """Statistics over (now - window, now]: rate as rostopic hz ((n-1)/span), MB/s = rate x mean
        size (rostopic bw's bytes over time), latency avg/max/std/p95 in ms (NaN without stamps)."""
        self._expire(now_s)
        n = len(self._events)
        stats = dict(
            window_s=self.window_s,
            messages=n,
            rate_hz=0.0,
            bandwidth_mbytes_per_s=0.0,
            mean_message_bytes=0.0,
            latency_avg_ms=math.nan,
            latency_max_ms=math.nan,
            latency_std_ms=math.nan,
            latency_p95_ms=math.nan,
            age_s=math.inf if self.last_receive_s is None else now_s - self.last_receive_s,
            invalid_messages=self.invalid_messages,
        )
        if n == 0:
            return stats
        events = np.array(self._events, dtype=np.float64)
        stats["mean_message_bytes"] = float(events[:, 1].mean())
        span = events[-1, 0] - events[0, 0]
        if n >= 2 and span > 0:
            stats["rate_hz"] = (n - 1) / span
        stats["bandwidth_mbytes_per_s"] = stats["rate_hz"] * stats["mean_message_bytes"] / 1e6
        latencies = events[:, 2][~np.isnan(events[:, 2])] * 1e3
        if len(latencies):
            stats.update(
                latency_avg_ms=float(latencies.mean()),
                latency_max_ms=float(latencies.max()),
                latency_std_ms=float(latencies.std()),
                latency_p95_ms=float(np.percentile(latencies, 95)),
            )
        return stats
