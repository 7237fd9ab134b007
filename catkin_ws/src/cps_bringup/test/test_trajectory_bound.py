"""The mission monitor's trajectories stay bounded and evenly spread over a long mission."""

import pytest

from cps_bringup.mission import Trajectory
from cps_fleet.fleet import load_fleet


def test_a_long_mission_keeps_at_most_max_points_evenly_spread():
    trajectory = Trajectory(max_points=100)
    samples = 100_000  # ~14 h at one sample per 0.5 s
    for k in range(samples):
        trajectory.append((float(k), 0.0, 0.0))
    points = trajectory.points()
    assert 50 <= len(points) <= 100
    xs = [p[0] for p in points]
    assert xs[0] == 0.0
    assert len({b - a for a, b in zip(xs, xs[1:])}) == 1  # even spacing
    assert xs[-1] >= samples - 1 - trajectory.stride  # reaches the present
    assert trajectory.points() is points  # no copy without a change


def test_a_short_mission_keeps_every_sample_and_copies_only_after_a_change():
    trajectory = Trajectory(max_points=10)
    for k in range(10):
        trajectory.append((k, 0, 0))
    first = trajectory.points()
    assert [p[0] for p in first] == list(range(10))
    trajectory.append((10, 0, 0))
    assert trajectory.points() is not first and len(trajectory) <= 10


def test_the_bound_comes_from_fleet_yaml_and_must_hold_two_points():
    assert load_fleet().limits.trajectory_max_points >= 2
    with pytest.raises(ValueError, match="at least 2"):
        Trajectory(1)
