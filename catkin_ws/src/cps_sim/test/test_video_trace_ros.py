"""fleet_sim with ~video_trace on a real master: the camera plays its recorded frames (not rendered
ones) at the level and rate the manager's topics set, says so in its log, and refuses a trace that
does not match the fleet before publishing anything."""

import os

import pytest
from video_sim import RATE_TOLERANCE, ROBOT, WINDOW_S, dimensions, frames_at, video_sim

pytestmark = [pytest.mark.ros, pytest.mark.waiting]

FRAMES = 6


@pytest.fixture(scope="module")
def trace_path(tmp_path_factory):
    from cps_fleet.fleet import load_fleet
    from cps_sim.video_trace import record_video_trace

    path = str(tmp_path_factory.mktemp("video_trace") / "jackal.npz")
    record_video_trace(load_fleet(profile="light").with_robots([ROBOT]), path, FRAMES, log=lambda _: None)
    return path


@pytest.fixture(scope="module")
def sim(ros_master, rospy_node, trace_path):
    with video_sim(ros_master, rospy_node, name="fleet_sim_trace", video_trace=trace_path) as running:
        yield running


@pytest.mark.parametrize("level_index, size, rate_hz", [(0, (640, 480), 12.0), (2, (160, 120), 4.0)])
def test_the_camera_plays_the_recorded_level_at_the_rate_it_is_told(sim, trace_path, level_index, size, rate_hz):
    from std_msgs.msg import Float64, UInt8

    from cps_fleet.fleet import load_fleet
    from cps_sim.video_trace import load_video_trace

    graph, level, rate, images, status = sim
    trace = load_video_trace(trace_path, load_fleet(profile="light").with_robots([ROBOT]))
    recorded = set(trace.jpegs[(ROBOT, level_index)])
    level.publish(UInt8(level_index))
    rate.publish(Float64(rate_hz))
    frames = frames_at(images, size[0], WINDOW_S + (2.0 if rate_hz < 5 else 0.0))
    assert frames and all(dimensions(m) == size for m in frames)
    # The recorded frames, not rendered ones (the robot stands still; the trace walks its route).
    assert all(bytes(m.data) in recorded for m in frames)
    assert len({bytes(m.data) for m in frames}) == min(len(frames), FRAMES)
    stamps = [m.header.stamp.to_sec() for m in frames]
    measured = (len(stamps) - 1) / (stamps[-1] - stamps[0])
    assert abs(measured - rate_hz) <= RATE_TOLERANCE * rate_hz, f"{measured:.2f} Hz for {rate_hz} Hz"
    report = status.wait(lambda s: s.level == level_index and s.set_rate_hz == rate_hz, timeout_s=5)
    # The level's size is learned from the recorded frames (the status: the last 20 sent, with header).
    assert report.level_mean_message_bytes == pytest.approx(trace.mean_bytes(ROBOT, level_index), rel=0.25)
    assert (
        f"video: recorded frames of each camera robot's route at each video level ({os.path.basename(trace_path)}:"
        in graph.output("fleet_sim_trace")
    )


def test_a_trace_without_one_of_the_fleets_cameras_stops_fleet_sim_naming_it(ros, trace_path):
    proc = ros.start_node(
        "cps_sim",
        "fleet_sim",
        name="fleet_sim_bad_trace",
        params={"~profile": "light", "~robots": f"{ROBOT},champ", "~video_trace": trace_path},
    )
    assert proc.wait(timeout=60) != 0
    output = ros.output("fleet_sim_bad_trace")
    assert trace_path in output and "camera robot 'champ' is not in it" in output, output[-2000:]
