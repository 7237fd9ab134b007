"""A camera robot's video under the bandwidth manager (numpy, no rospy).

The manager sets each camera robot's video level (fleet.yaml streams.video_levels: a resolution
and a JPEG quality) and rate. The simulated camera renders the colour image at that resolution
only, at that rate only, and every frame rendered is encoded and sent: nothing is rendered finer
than sent or encoded to be dropped. The video shares the depth camera's optics (its hfov and
aspect ratio), so a level must have the depth camera's aspect ratio.

`VideoControl` holds the level and rate a robot's camera follows (bad settings refused, the last
good kept); `LevelSizes` learns each level's mean message size from what the encoder produced;
`render_video` renders and encodes one frame.
"""

import collections
import dataclasses
import math
import time

import numpy as np

from cps_fleet.config import ConfigError
from cps_transport.image_compression import compressed_format, encode_jpeg

# The simulated colour sensor's native resolution: no level may ask for more pixels than it has.
MAX_VIDEO_SIZE_PX = (1280, 960)
# Below this a frame shows nothing an operator can use (and JPEG's 16-pixel blocks dominate).
MIN_VIDEO_SIZE_PX = (32, 24)
# Until the manager speaks: the coarsest level at this rate (the old fixed 160x120 stream's rate).
DEFAULT_VIDEO_RATE_HZ = 5.0
# A level's mean size is the mean of its last this many frames.
LEVEL_SIZE_WINDOW_FRAMES = 20
# The encoding of what is rendered; the JPEG carries it in CompressedImage.format.
VIDEO_ENCODING = "rgb8"


def video_level_errors(fleet):
    """ConfigErrors (file:line of the level) for every video level the fleet's camera cannot produce."""
    camera = fleet.profile.depth_camera
    errors = []
    for index, level in enumerate(fleet.streams.video_levels):
        path, line = level.source
        where = f"streams.video_levels[{index}] ({level.name})"
        if level.width * camera.height != level.height * camera.width:
            errors.append(
                ConfigError(
                    path or fleet.path,
                    line,
                    f"{where}: {level.width}x{level.height} has not the depth camera's aspect ratio "
                    f"({camera.width}x{camera.height} in profile '{fleet.profile.name}'): the video shares "
                    "its optics (hfov), so the image would be stretched",
                )
            )
        elif level.width > MAX_VIDEO_SIZE_PX[0] or level.height > MAX_VIDEO_SIZE_PX[1]:
            errors.append(
                ConfigError(
                    path or fleet.path,
                    line,
                    f"{where}: {level.width}x{level.height} is above the colour sensor's "
                    f"{MAX_VIDEO_SIZE_PX[0]}x{MAX_VIDEO_SIZE_PX[1]}",
                )
            )
        elif level.width < MIN_VIDEO_SIZE_PX[0] or level.height < MIN_VIDEO_SIZE_PX[1]:
            errors.append(
                ConfigError(
                    path or fleet.path,
                    line,
                    f"{where}: {level.width}x{level.height} is below the smallest frame the camera "
                    f"renders ({MIN_VIDEO_SIZE_PX[0]}x{MIN_VIDEO_SIZE_PX[1]})",
                )
            )
    return errors


class VideoControl:
    """The level and rate one robot's camera follows. Until set: the coarsest level at
    DEFAULT_VIDEO_RATE_HZ (within the fleet's video rate bounds). A bad setting is refused with
    the reason and the last good one kept; a rate outside [video_min_rate_hz, video_max_rate_hz]
    is clamped to it (with a note)."""

    def __init__(self, streams):
        self.levels = streams.video_levels
        self.min_rate_hz = streams.video_min_rate_hz
        self.max_rate_hz = streams.video_max_rate_hz
        self.level_index = len(self.levels) - 1
        self.rate_hz = min(max(DEFAULT_VIDEO_RATE_HZ, self.min_rate_hz), self.max_rate_hz)

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
        if not math.isfinite(rate) or rate <= 0.0:
            return f"rate {rate_hz!r} Hz is not a positive finite number; keeping {self.rate_hz:g} Hz", None
        clamped = min(max(rate, self.min_rate_hz), self.max_rate_hz)
        self.rate_hz = clamped
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


@dataclasses.dataclass
class VideoTask:
    """A request for one video frame of `robot` at `level_index` (what a sensor worker renders)."""

    robot: str
    level_index: int
    width: int
    height: int
    jpeg_quality: int


@dataclasses.dataclass
class VideoFrame:
    """One encoded video frame and what it cost."""

    jpeg: np.ndarray  # uint8, the JPEG file
    width: int
    height: int
    level_index: int
    render_s: float  # rasterizing and reading back the colour image
    encode_s: float  # JPEG encoding

    @property
    def format(self):
        return compressed_format(VIDEO_ENCODING)


def render_video(camera, optical_in_map, task: VideoTask):
    """Render `camera`'s colour image at the task's resolution only and JPEG-encode it at its quality."""
    started = time.perf_counter()
    rgb = camera.render_colour(optical_in_map, task.width, task.height)
    rendered = time.perf_counter()
    data = encode_jpeg(rgb, task.jpeg_quality)
    encoded = time.perf_counter()
    return VideoFrame(
        jpeg=np.frombuffer(data, dtype=np.uint8),
        width=task.width,
        height=task.height,
        level_index=task.level_index,
        render_s=rendered - started,
        encode_s=encoded - rendered,
    )
