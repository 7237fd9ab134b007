"""Which robots to give a closer look at a newly reported change (the paper's "trigger or change
detection", section 5), without ROS: the robots that came within `radius_m` (horizontal) of the
change's place while it was being confirmed, or are there now, get high priority on the link.

A change is reported only after it persisted some detection cycles (cps_mapping.change_tracking),
and under load that took 19 s (final36): the robot that saw it had moved on, no robot was near at
the report, and no one was raised. So the positions are kept at every detection cycle, and a change
counts every robot near its place since its first cycle. Each tracked change is raised once, by the
tracker's identity (its place may drift as more of it is seen: in final36 a drift past 0.5 m made
the same changes "new" again after the mission's end, when the manager had gone).
"""

import collections
import dataclasses
import math
from typing import Dict, List, Optional, Tuple

ATTENTION_RADIUS_M = 4.0
# How long the positions are kept: more than a change takes to be reported under load.
POSITION_HISTORY_S = 120.0


@dataclasses.dataclass(frozen=True)
class Attention:
    """A robot to raise for a change: how near it came to the change's place (m) and when (s)."""

    robot: str
    change: object  # cps_mapping.change_detection.Change, the reporting cycle's
    distance_m: float
    at_s: float


@dataclasses.dataclass(frozen=True)
class Unattended:
    """A reported change no robot came near: the nearest robot since its first cycle, if any."""

    change: object
    nearest_robot: Optional[str]
    distance_m: float


class ChangeAttention:
    def __init__(self, radius_m=ATTENTION_RADIUS_M, history_s=POSITION_HISTORY_S):
        if not radius_m > 0 or not history_s > 0:
            raise ValueError("radius_m and history_s must be positive")
        self.radius_m, self.history_s = radius_m, history_s
        self._history = collections.deque()  # (t_s, {robot: (x, y)}), oldest first
        self._handled = []  # the tracked changes already attended to (by identity)

    def note_positions(self, now_s, positions_m: Dict[str, Tuple[float, float]]):
        """The robots' positions (map, m) at a detection cycle."""
        self._history.append((now_s, dict(positions_m)))
        while self._history and now_s - self._history[0][0] > self.history_s:
            self._history.popleft()

    def attend(self, reported) -> Tuple[List[Attention], List[Unattended]]:
        """For every reported change (cps_mapping.change_tracking.TrackedChange) not handled yet:
        each robot that came within radius_m of its place at a noted cycle since its first one,
        at its nearest; or, if none did, the change with the nearest robot."""
        raise_them, unattended = [], []
        for tracked in reported:
            if any(tracked is handled for handled in self._handled):
                continue
            self._handled.append(tracked)
            x, y = tracked.change.place_m
            nearest: Dict[str, Tuple[float, float]] = {}  # robot -> (distance, when)
            for t_s, positions in self._history:
                if t_s < tracked.first_seen_s:
                    continue
                for robot, (rx, ry) in positions.items():
                    d = math.hypot(rx - x, ry - y)
                    if robot not in nearest or d < nearest[robot][0]:
                        nearest[robot] = (d, t_s)
            near = sorted((r, d, t) for r, (d, t) in nearest.items() if d <= self.radius_m)
            raise_them += [Attention(r, tracked.change, d, t) for r, d, t in near]
            if not near:
                closest = min(nearest.items(), key=lambda item: item[1][0], default=None)
                unattended.append(
                    Unattended(tracked.change, closest[0], closest[1][0])
                    if closest
                    else Unattended(tracked.change, None, math.inf)
                )
        return raise_them, unattended
