"""The managed video's level and rate, ROS-free and camera-free: what a robot's video follows
(fleet.yaml `streams.video_levels`, set by the bandwidth manager on <robot>/video_throttle/level and
rate_hz) and what it learns of each level's size. Used by the simulated camera (cps_sim.video) and
by `ManagedVideoCompressor` (cps_transport.tissue) for a camera that only gives raw images.
"""

import collections
import math

import numpy as np

# Until the manager speaks: the coarsest level at this rate (the old fixed 160x120 stream's rate).
DEFAULT_VIDEO_RATE_HZ = 5.0
# A level's mean size is the mean of its last this many frames.
LEVEL_SIZE_WINDOW_FRAMES = 20


class VideoControl:
    """The level and rate one robot's camera follows. Until set: the coarsest level at
    DEFAULT_VIDEO_RATE_HZ (within the fleet's video rate bounds). A bad setting is refused with
    the reason and the last good one kept; a rate outside [video_min_rate_hz, video_max_rate_hz]
    is clamped to it (with a note); rate 0 turns the video off (the allocator's "no room")."""

    @property
    def set_rate_hz(self):
        """The rate in force: 0 while off."""
        return 0.0 if self.off else self.rate_hz

    def __init__(self, streams):
        self.levels = streams.video_levels
        self.min_rate_hz = streams.video_min_rate_hz
        self.max_rate_hz = streams.video_max_rate_hz
        self.level_index = len(self.levels) - 1
        self.rate_hz = min(max(DEFAULT_VIDEO_RATE_HZ, self.min_rate_hz), self.max_rate_hz)
        # Rate 0 from the manager: the link has no room for this video; nothing is rendered or sent
        # until a positive rate comes (rate_hz keeps the last one, for the schedule).
        self.off = False

    @property
    def level(self):
        return self.levels[self.level_index]

    @property
    def period_s(self):
        return 1.0 / self.rate_hz

    def set_level(self, index):
        """None when applied, else why it was refused (the level stays)."""
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)):
            return f"level {index!r} is not an integer index"
        if not 0 <= index < len(self.levels):
            known = ", ".join(f"{i}={lvl.name}" for i, lvl in enumerate(self.levels))
            return f"unknown video level {index} (levels: {known}); keeping {self.level_index} ({self.level.name})"
        self.level_index = int(index)
        return None

    def set_rate(self, rate_hz):
        """(error, note): error when refused (the rate stays), note when clamped to the bounds."""
        try:
            rate = float(rate_hz)
        except (TypeError, ValueError):
            return f"rate {rate_hz!r} is not a number; keeping {self.rate_hz:g} Hz", None
        if rate == 0.0:
            self.off = True
            return None, None
        if not math.isfinite(rate) or rate < 0.0:
            return f"rate {rate_hz!r} Hz is not 0 (off) or a positive finite number; keeping {self.rate_hz:g} Hz", None
        clamped = min(max(rate, self.min_rate_hz), self.max_rate_hz)
        self.rate_hz, self.off = clamped, False
        if clamped != rate:
            return None, f"rate {rate:g} Hz clamped to {clamped:g} Hz (video_min/max_rate_hz)"
        return None, None


class LevelSizes:
    """Per level, the mean serialized size of its last LEVEL_SIZE_WINDOW_FRAMES messages."""

    def __init__(self, levels, window=LEVEL_SIZE_WINDOW_FRAMES):
        self.sizes = [collections.deque(maxlen=window) for _ in levels]

    def add(self, level_index, message_bytes):
        self.sizes[level_index].append(float(message_bytes))

    def mean(self, level_index):
        """Mean size at `level_index`, bytes; NaN before its first frame."""
        sizes = self.sizes[level_index]
        return sum(sizes) / len(sizes) if sizes else math.nan


def compressed_image_bytes(frame_id, fmt, data_len):
    """The serialized size of a sensor_msgs/CompressedImage (what crosses the link), bytes:
    header (seq, stamp, frame_id), format and data, each string/array with its 4-byte length."""
    return 4 + 8 + 4 + len(frame_id.encode()) + 4 + len(fmt.encode()) + 4 + int(data_len)
