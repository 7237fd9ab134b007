"""Each robot's priority and rate bounds from its mission state and the operator, without ROS.

The paper (2.4.4, Table 6): priorities start at 0, become 1 (high) while a robot inspects, and go
back to 0 when its route is done, at which point its rate drops to the minimum (1 Hz) while the
others share the rest. Mapping used here:

| mission_state             | priority | rate bounds             |
|---------------------------|----------|-------------------------|
| (none yet), idle, transit | 0        | [min, max]              |
| inspecting                | 1        | [min, max]              |
| done                      | 0        | [min, max], finished    |

A finished robot keeps the rate its stream can sustain while the link has room and yields first
when it does not (the manager gives it a lower weight: ManagerSettings.done_weight); nothing is
pinned without a reason (issue 36). The paper pins it at the minimum (Table 6 steps 6-9: "reduced
to 1 Hz"): `PriorityBook(robots, pin_done=True)`, [min, min], which table6 uses to reproduce them.

An operator priority (`/tissue/set_priority`) overrides the automatic one until the robot's mission
state changes again. A done robot set to 1 by the operator is no longer finished (nor pinned).
"""

import dataclasses
from typing import Dict, Iterable, Optional

from cps_bw_manager.allocation import RobotDemand

MISSION_STATES = ("idle", "transit", "inspecting", "done")
PRIORITIES = (0, 1)


@dataclasses.dataclass
class _RobotState:
    mission_state: str = "idle"
    operator_priority: Optional[int] = None


class PriorityBook:
    """Automatic priorities from mission states plus operator overrides, for a fixed set of robots."""

    def __init__(self, robots: Iterable[str], pin_done: bool = False):
        self._robots: Dict[str, _RobotState] = {name: _RobotState() for name in robots}
        self.pin_done = bool(pin_done)

    @property
    def robots(self):
        return list(self._robots)

    def set_mission_state(self, robot, state):
        """Record a mission state; returns True if the robot's effective demand changed.

        Raises KeyError for an unknown robot and ValueError for an unknown state.
        """
        entry = self._entry(robot)
        if state not in MISSION_STATES:
            raise ValueError(f"robot '{robot}': unknown mission state '{state}' (known: {', '.join(MISSION_STATES)})")
        if state == entry.mission_state:
            return False
        before = self.effective(robot)
        entry.mission_state = state
        entry.operator_priority = None
        return self.effective(robot) != before

    def set_operator_priority(self, robot, priority):
        """The operator's priority, kept until the mission state changes; KeyError/ValueError on bad input."""
        entry = self._entry(robot)
        if isinstance(priority, bool) or priority not in PRIORITIES:
            raise ValueError(f"priority must be 0 (normal) or 1 (high), got {priority!r}")
        before = self.effective(robot)
        entry.operator_priority = int(priority)
        return self.effective(robot) != before

    def mission_state(self, robot):
        return self._entry(robot).mission_state

    def priority(self, robot):
        entry = self._entry(robot)
        if entry.operator_priority is not None:
            return entry.operator_priority
        return 1 if entry.mission_state == "inspecting" else 0

    def finished(self, robot):
        """A robot whose route is done and whom the operator did not raise to 1."""
        return self._entry(robot).mission_state == "done" and self.priority(robot) == 0

    def pinned_to_minimum(self, robot):
        """The paper's policy (pin_done): a finished robot needs no more than the minimum rate."""
        return self.pin_done and self.finished(robot)

    def effective(self, robot):
        return self.priority(robot), self.finished(robot)

    def demand(self, robot, message_bytes, min_rate_hz, max_rate_hz):
        """The allocator's input for `robot`: priority and bounds from its state and the operator."""
        return RobotDemand(
            name=robot,
            message_bytes=message_bytes,
            priority=self.priority(robot),
            min_rate_hz=min_rate_hz,
            max_rate_hz=min_rate_hz if self.pinned_to_minimum(robot) else max_rate_hz,
        )

    def _entry(self, robot):
        try:
            return self._robots[robot]
        except KeyError:
            raise KeyError(f"unknown robot '{robot}' (managed: {', '.join(self._robots)})") from None
