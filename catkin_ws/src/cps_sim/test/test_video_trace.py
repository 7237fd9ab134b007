"""The recorded video without ROS: every camera robot's frames along its route at every level, a
trace refused (naming the file) when its levels or robots are not the fleet's, and the player's
frames at the level asked, looping over the route."""

import dataclasses
import math

import numpy as np
import pytest

from cps_fleet.fleet import load_fleet
from cps_sim.video import VideoTask
from cps_sim.video_trace import (
    SAMPLING,
    VideoTraceError,
    VideoTracePlayer,
    load_video_trace,
    record_video_trace,
    route_poses,
)
from cps_transport.image_compression import decode_jpeg

FRAMES = 4
ROBOTS = ["scout", "jackal", "iris"]  # a lidar robot (no video), a ground and an aerial camera


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    fleet = load_fleet(profile="light").with_robots(ROBOTS)
    path = str(tmp_path_factory.mktemp("trace") / "video_trace.npz")
    record_video_trace(fleet, path, frames_per_level=FRAMES, log=lambda _: None)
    return fleet, path


def _task(fleet, robot, index):
    level = fleet.streams.video_levels[index]
    return VideoTask(robot, index, level.width, level.height, level.jpeg_quality)


def test_every_camera_robot_is_recorded_at_every_level_of_the_fleet(recorded):
    fleet, path = recorded
    trace = load_video_trace(path, fleet)
    assert trace.robots == ["jackal", "iris"]  # scout has no camera
    meta = trace.meta
    assert [(lv["name"], lv["width"], lv["height"], lv["jpeg_quality"]) for lv in meta["levels"]] == [
        (lv.name, lv.width, lv.height, lv.jpeg_quality) for lv in fleet.streams.video_levels
    ]
    assert meta["frames_per_level"] == FRAMES and meta["sampling"] == SAMPLING and meta["profile"] == "light"
    for robot in trace.robots:
        sizes = []
        for index, level in enumerate(fleet.streams.video_levels):
            frames = trace.jpegs[(robot, index)]
            assert len(frames) == FRAMES and len(trace.encode_s[(robot, index)]) == FRAMES
            pixels = [decode_jpeg(f) for f in frames]
            assert all(p.shape == (level.height, level.width, 3) for p in pixels)
            # Scenes, not blank frames (a landed quadrotor's first view may be a near wall).
            assert np.median([p.std() for p in pixels]) > 5.0
            sizes.append(trace.mean_bytes(robot, index))
        assert sizes == sorted(sizes, reverse=True)  # finer levels cost more bytes
    # Along the route: the views differ from pose to pose.
    assert len(set(trace.jpegs[("jackal", 0)])) == FRAMES


def test_a_trace_of_other_levels_or_robots_is_refused_naming_the_file(recorded, tmp_path):
    fleet, path = recorded
    streams = fleet.streams
    finer = dataclasses.replace(streams.video_levels[0], jpeg_quality=95)
    other_levels = dataclasses.replace(
        fleet, streams=dataclasses.replace(streams, video_levels=(finer,) + streams.video_levels[1:])
    )
    with pytest.raises(VideoTraceError, match="video levels") as error:
        load_video_trace(path, other_levels)
    assert path in str(error.value) and "q95" in str(error.value)
    with pytest.raises(VideoTraceError, match="camera robot 'champ' is not in it") as error:
        load_video_trace(path, load_fleet(profile="light").with_robots(["jackal", "champ"]))
    assert path in str(error.value)
    # A subset of the recorded robots is fed by it.
    assert load_video_trace(path, fleet.with_robots(["iris"])).robots == ["jackal", "iris"]
    garbage = tmp_path / "not_a_trace.npz"
    garbage.write_bytes(b"not a zip")
    with pytest.raises(VideoTraceError, match="cannot read it") as error:
        load_video_trace(str(garbage), fleet)
    assert str(garbage) in str(error.value)


def test_the_player_gives_the_asked_level_walking_one_cursor_per_robot_and_looping(recorded):
    fleet, path = recorded
    trace = load_video_trace(path, fleet)
    player = VideoTracePlayer(trace)
    levels = [0, 2, 1, 0, 2, 2]  # more frames than recorded: the route loops
    for step, index in enumerate(levels):
        frame = player.frame(_task(fleet, "jackal", index))
        level = fleet.streams.video_levels[index]
        assert (frame.width, frame.height, frame.level_index) == (level.width, level.height, index)
        assert frame.jpeg.tobytes() == trace.jpegs[("jackal", index)][step % FRAMES]
        assert frame.format == "rgb8; jpeg compressed bgr8" and frame.encode_s == 0.0
    # iris has its own cursor: jackal's frames moved it not.
    assert player.frame(_task(fleet, "iris", 1)).jpeg.tobytes() == trace.jpegs[("iris", 1)][0]
    wrong = dataclasses.replace(_task(fleet, "jackal", 0), width=320, height=240)
    with pytest.raises(ValueError, match="not level 0"):
        player.frame(wrong)


def test_route_poses_are_evenly_spaced_and_face_the_way_travelled():
    square = [(0, 0, 0), (4, 0, 0), (4, 4, 0), (0, 4, 0), (0, 0, 0)]
    poses = route_poses(square, 8)
    assert [p[:2] for p in poses] == [(0, 0), (2, 0), (4, 0), (4, 2), (4, 4), (2, 4), (0, 4), (0, 2)]
    yaws = [p[3] for p in poses]
    assert np.allclose(yaws, [0, 0, math.pi / 2, math.pi / 2, math.pi, math.pi, -math.pi / 2, -math.pi / 2])
    climb = route_poses([(0, 0, 0), (0, 0, 2), (3, 0, 2)], 5, initial_yaw_rad=1.0)
    assert climb[0][3] == 1.0 and climb[1][2] == pytest.approx(1.0)  # straight up: heading kept
    assert climb[-1][3] == 0.0 and climb[-1][:3] == pytest.approx((2.0, 0.0, 2.0))
