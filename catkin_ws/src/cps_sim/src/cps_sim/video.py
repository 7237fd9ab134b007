"""A camera robot's video under the bandwidth manager (numpy, no rospy).

The manager sets each camera robot's video level (fleet.yaml streams.video_levels: a resolution
and a JPEG quality) and rate. The simulated camera renders the colour image at that resolution
only, at that rate only, and every frame rendered is encoded and sent: nothing is rendered finer
than sent or encoded to be dropped. The video shares the depth camera's optics (its hfov and
aspect ratio), so a level must have the depth camera's aspect ratio.

`VideoControl` (cps_transport.video_levels) holds the level and rate a robot's camera follows (bad
settings refused, the last good kept); `LevelSizes` learns each level's mean message size from
what the encoder produced; `render_video` renders and encodes one frame.
"""

import dataclasses
import time

import numpy as np

from cps_fleet.config import ConfigError
from cps_transport.image_compression import compressed_format, encode_jpeg
from cps_transport.video_levels import (  # noqa: F401 (re-exported: the camera's control and sizes)
    DEFAULT_VIDEO_RATE_HZ,
    LEVEL_SIZE_WINDOW_FRAMES,
    LevelSizes,
    VideoControl,
    compressed_image_bytes,
)

# The simulated colour sensor's native resolution: no level may ask for more pixels than it has.
MAX_VIDEO_SIZE_PX = (1280, 960)
# Below this a frame shows nothing an operator can use (and JPEG's 16-pixel blocks dominate).
MIN_VIDEO_SIZE_PX = (32, 24)
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
