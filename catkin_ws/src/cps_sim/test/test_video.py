"""The managed video's rules without ROS: which levels the camera can produce (file:line), the
level and rate it follows (bad ones refused, the last good kept), the per-level sizes, and that a
frame is rendered and encoded at its level's size only."""

import math
import pathlib
import shutil

import numpy as np
import pytest

from cps_fleet.fleet import load_fleet
from cps_sim.video import (
    DEFAULT_VIDEO_RATE_HZ,
    LevelSizes,
    VideoControl,
    VideoTask,
    compressed_image_bytes,
    video_level_errors,
)
from cps_transport.image_compression import decode_jpeg

FLEET = pathlib.Path(__file__).resolve().parents[2] / "cps_bringup" / "config" / "fleet.yaml"
FINE_LINE = "    - {name: 640x480, width: 640, height: 480, jpeg_quality: 90, bytes_prior: 60000}\n"
MIDDLE_LINE = "    - {name: 320x240, width: 320, height: 240, jpeg_quality: 75, bytes_prior: 14000}\n"


def _fleet_with_level(tmp_path, old_line, level_line):
    """A copy of fleet.yaml (and its routes) with `old_line` replaced by `level_line`: (fleet, path, line)."""
    text = FLEET.read_text()
    assert old_line in text
    text = text.replace(old_line, level_line)
    site = FLEET.parents[2] / "cps_sim" / "config" / "hall.yaml"
    text = text.replace("site: ../../cps_sim/config/hall.yaml", f"site: {site}")
    shutil.copytree(FLEET.parent / "routes", tmp_path / "routes")
    path = tmp_path / "fleet.yaml"
    path.write_text(text)
    return load_fleet(str(path)), str(path), text[: text.index(level_line)].count("\n") + 1


def test_the_shipped_levels_are_all_producible():
    assert video_level_errors(load_fleet()) == []


@pytest.mark.parametrize(
    "old_line, level, reason",
    [
        (MIDDLE_LINE, "{name: 320x200, width: 320, height: 200, jpeg_quality: 75, bytes_prior: 14000}", "aspect ratio"),
        (FINE_LINE, "{name: 1600x1200, width: 1600, height: 1200, jpeg_quality: 75, bytes_prior: 14000}", "above"),
    ],
)
def test_a_level_the_camera_cannot_produce_is_refused_at_its_line(tmp_path, old_line, level, reason):
    fleet, path, line = _fleet_with_level(tmp_path, old_line, f"    - {level}\n")
    errors = video_level_errors(fleet)
    assert len(errors) == 1
    assert (errors[0].path, errors[0].line) == (path, line)
    assert reason in str(errors[0]) and f"{path}:{line}" in str(errors[0])


def test_control_starts_coarse_and_slow_and_keeps_the_last_good_setting():
    streams = load_fleet().streams
    control = VideoControl(streams)
    assert control.level_index == len(streams.video_levels) - 1 and control.rate_hz == DEFAULT_VIDEO_RATE_HZ
    assert control.set_level(0) is None and control.level.name == "640x480"
    assert "unknown video level 7" in control.set_level(7) and control.level_index == 0
    assert control.set_rate(12.5) == (None, None) and control.rate_hz == 12.5
    for bad in (math.nan, -3.0, math.inf, "fast"):
        error, _ = control.set_rate(bad)
        assert error and control.rate_hz == 12.5 and not control.off, bad
    error, note = control.set_rate(100.0)
    assert error is None and "clamped" in note and control.rate_hz == streams.video_max_rate_hz


def test_rate_0_from_the_allocator_turns_the_video_off_until_a_positive_rate():
    control = VideoControl(load_fleet().streams)
    assert control.set_rate(12.0) == (None, None)
    assert control.set_rate(0.0) == (None, None)
    assert control.off and control.set_rate_hz == 0.0 and control.rate_hz == 12.0
    assert control.set_rate(8.0) == (None, None)
    assert not control.off and control.set_rate_hz == 8.0


def test_level_sizes_are_per_level_means_of_the_last_frames():
    sizes = LevelSizes(range(3), window=3)
    assert math.isnan(sizes.mean(0))
    for size in (100, 200, 300, 400):
        sizes.add(0, size)
    sizes.add(2, 50)
    assert sizes.mean(0) == 300.0 and sizes.mean(2) == 50.0 and math.isnan(sizes.mean(1))


def test_compressed_image_bytes_is_the_serialized_size():
    from io import BytesIO

    from sensor_msgs.msg import CompressedImage

    msg = CompressedImage(format="rgb8; jpeg compressed bgr8", data=b"x" * 1234)
    msg.header.frame_id = "jackal/camera_depth_optical_frame"
    buffer = BytesIO()
    msg.serialize(buffer)
    assert compressed_image_bytes(msg.header.frame_id, msg.format, len(msg.data)) == len(buffer.getvalue())


@pytest.fixture(scope="module")
def simulation():
    from cps_sim.simulation import FleetSimulation

    fleet = load_fleet(profile="light")
    sim = FleetSimulation(fleet, renderer="fast")
    yield fleet, sim
    sim.close()


def test_each_level_is_rendered_and_encoded_at_its_own_size(simulation):
    fleet, sim = simulation
    sizes = []
    for index, level in enumerate(fleet.streams.video_levels):
        frame = sim.capture_video(VideoTask("jackal", index, level.width, level.height, level.jpeg_quality))
        pixels = decode_jpeg(frame.jpeg.tobytes())
        assert pixels.shape == (level.height, level.width, 3) and frame.level_index == index
        assert pixels.std() > 5.0  # a scene, not a blank frame
        sizes.append(len(frame.jpeg))
    assert sizes == sorted(sizes, reverse=True)  # finer levels cost more bytes


def test_the_video_shows_what_the_depth_camera_sees(simulation):
    """Same optics: the coarsest video level and the light profile's 160x120 depth image agree."""
    fleet, sim = simulation
    level = fleet.streams.video_levels[-1]
    depth_rgb = sim.capture("jackal").rgb
    frame = sim.capture_video(VideoTask("jackal", 2, level.width, level.height, 95))
    video = decode_jpeg(frame.jpeg.tobytes()).astype(float)
    assert video.shape == depth_rgb.shape
    assert np.abs(video - depth_rgb).mean() < 6.0  # JPEG's error at quality 95, not another view
