"""Which robots to give a closer look at a newly found change (the paper's "trigger or change
detection", section 5), without ROS: the robots that came within `radius_m` (horizontal) of the
change's place since the first detection cycle found it, or are there now, get high priority on
the link.

A change is reported only after it persisted some detection cycles (cps_mapping.change_tracking),
and under load that took 19 s (final36): the robot that saw it had moved on, no robot was near at
the report, and no one was raised. So the positions are kept at every detection cycle, and a change
counts every robot near its place since its first cycle. The map server attends to a change from
its first cycle, before it is reported: a closer look is what confirms it or withdraws it, and on a
loaded twin the second cycle came as the robots finished (CI, 2026-11-29: the request found the
manager gone; a cycle of 0.7 s of CPU took 12.9 s on a quiet machine, 11.6 s of it waiting for the
twin's CPU). Each robot is raised once per tracked change, by the tracker's identity, and none
after the change is reported (its place may drift as more of it is seen: in final36 a drift past
0.5 m made the same changes "new" again after the mission's end, when the manager had gone).
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
    """A found change no robot came near: the nearest robot since its first cycle, if any."""

    change: object
    nearest_robot: Optional[str]
    distance_m: float


class ChangeAttention:
    def __init__(self, radius_m=ATTENTION_RADIUS_M, history_s=POSITION_HISTORY_S):
        if not radius_m > 0 or not history_s > 0:
            raise ValueError("radius_m and history_s must be positive")
        self.radius_m, self.history_s = radius_m, history_s
        self._history = collections.deque()  # (t_s, {robot: (x, y)}), oldest first
        self._settled = []  # the reported changes attended to (by identity): none raised again
        self._raised = []  # (tracked change, robot) pairs raised

    def note_positions(self, now_s, positions_m: Dict[str, Tuple[float, float]]):
        """The robots' positions (map, m) at a detection cycle."""
        self._history.append((now_s, dict(positions_m)))
        while self._history and now_s - self._history[0][0] > self.history_s:
            self._history.popleft()

    def attend(self, found) -> Tuple[List[Attention], List[Unattended]]:
        """For every found change (cps_mapping.change_tracking.TrackedChange) not settled yet: each
        robot not raised for it yet that came within radius_m of its place at a noted cycle since its
        first one, at its nearest. A change is settled once it is reported; one no robot came near
        by then is returned as Unattended, with the nearest robot."""
        raise_them, unattended = [], []
        for tracked in found:
            if any(tracked is settled for settled in self._settled):
                continue
            x, y = tracked.change.place_m
            nearest: Dict[str, Tuple[float, float]] = {}  # robot -> (distance, when)
            for t_s, positions in self._history:
                if t_s < tracked.first_seen_s:
                    continue
                for robot, (rx, ry) in positions.items():
                    d = math.hypot(rx - x, ry - y)
                    if robot not in nearest or d < nearest[robot][0]:
                        nearest[robot] = (d, t_s)
            raised = [robot for t, robot in self._raised if t is tracked]
            near = sorted((r, d, t) for r, (d, t) in nearest.items() if d <= self.radius_m and r not in raised)
            raise_them += [Attention(r, tracked.change, d, t) for r, d, t in near]
            self._raised += [(tracked, r) for r, _, _ in near]
            if tracked.reported_s is None:
                continue
            self._settled.append(tracked)
            if not near and not raised:
                closest = min(nearest.items(), key=lambda item: item[1][0], default=None)
                unattended.append(
                    Unattended(tracked.change, closest[0], closest[1][0])
                    if closest
                    else Unattended(tracked.change, None, math.inf)
                )
        return raise_them, unattended
