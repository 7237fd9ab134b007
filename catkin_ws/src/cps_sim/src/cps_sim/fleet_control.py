"""Every robot's velocity mux and route tracker in one process (pure Python, no rospy).

The single-robot executables (`velocity_mux`, `route_controller`) run one robot's share each;
`fleet_control` runs the whole fleet's in one process so that 16 robots cost one interpreter, not
32. Each robot keeps its own `VelocityMux` and `RouteTracker`: a bad command, a bad mode or a
failing tick of one robot never reaches another's state. `ControlLoop` runs the robots' periodic
ticks from one thread, each robot's exceptions caught and reported by robot.
"""

import math
from typing import Callable, Dict, List, Optional, Tuple

from cps_sim.controllers import RouteTracker, VelocityMux, validate_route

# The control rates and the teleop dead-man, for both layouts (nodes' ~params override them).
MUX_RATE_HZ = 20.0
ROUTE_RATE_HZ = 10.0
DEADMAN_S = 0.5


class FleetControl:
    """Per robot of `fleet`: a VelocityMux (its type's limits) and a RouteTracker (its route)."""

    def __init__(self, fleet, site, deadman_s=DEADMAN_S, clock=None):
        """Raises cps_fleet.config.ConfigError (route file:line) for a route the site rejects."""
        self.configs = {r.name: r for r in fleet.robots}
        clock_kw = {"clock": clock} if clock is not None else {}
        self.muxes: Dict[str, VelocityMux] = {}
        self.trackers: Dict[str, RouteTracker] = {}
        for robot in fleet.robots:
            route = fleet.route(robot.name)
            validate_route(route, site, robot.robot_type)
            self.muxes[robot.name] = VelocityMux(robot.robot_type, deadman_s=deadman_s, **clock_kw)
            self.trackers[robot.name] = RouteTracker(route, robot.robot_type)

    @property
    def robots(self):
        return list(self.configs)

    def mux(self, robot) -> VelocityMux:
        try:
            return self.muxes[robot]
        except KeyError:
            raise KeyError(f"no robot '{robot}' in this fleet_control (robots: {', '.join(self.configs)})") from None

    def set_estop(self, active):
        """The fleet's e-stop reaches every robot's mux."""
        for mux in self.muxes.values():
            mux.set_estop(active)


class ControlLoop:
    """Periodic per-robot ticks from one thread; a tick that raises is reported, the others run.

    `on_error(robot, task, exc)` hears every failure (e.g. to log it and stop that robot).
    """

    def __init__(self, on_error: Callable[[str, str, BaseException], None]):
        self.on_error = on_error
        self._tasks: List[Tuple[str, str, float, Callable[[], None]]] = []
        self._next: List[float] = []
        self.failures: Dict[Tuple[str, str], int] = {}

    def add(self, robot, task, rate_hz, tick, first_s):
        if not rate_hz > 0 or not math.isfinite(rate_hz):
            raise ValueError(f"{robot} {task}: rate must be a positive number, got {rate_hz!r}")
        self._tasks.append((robot, task, 1.0 / rate_hz, tick))
        self._next.append(first_s)

    def step(self, now_s) -> Optional[float]:
        """Run every due tick; the time the next one is due (None: no tasks)."""
        for i, (robot, task, period_s, tick) in enumerate(self._tasks):
            if now_s < self._next[i]:
                continue
            try:
                tick()
            except Exception as exc:  # noqa: BLE001 (one robot's failure must not stop the others)
                self.failures[(robot, task)] = self.failures.get((robot, task), 0) + 1
                self.on_error(robot, task, exc)
            self._next[i] = max(self._next[i] + period_s, now_s)
        return min(self._next) if self._next else None
