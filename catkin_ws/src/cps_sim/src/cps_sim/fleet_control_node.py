"""fleet_control's ROS side: every robot's velocity mux and route controller in one process.

The same `VelocityMuxNode` and `RouteControllerNode` as the single-robot executables, one pair per
robot of the fleet with `/<r>/...` names (the graph is the same as with a process per robot),
one tf listener, ticked from one thread by `cps_sim.fleet_control.ControlLoop`.
"""

import time

import rospy
import tf2_ros
from std_msgs.msg import Bool

from cps_fleet import names
from cps_fleet.config import ConfigError
from cps_ros.shutdown import init_node
from cps_sim.fleet_control import DEADMAN_S, MUX_RATE_HZ, ROUTE_RATE_HZ, ControlLoop, FleetControl
from cps_sim.node_support import WARN_PERIOD_S, ThrottledLog, fail, load_fleet_param, load_site_for, positive_param
from cps_sim.realtime import run_realtime
from cps_sim.route_controller_node import RouteControllerNode
from cps_sim.velocity_mux_node import VelocityMuxNode

MUX, ROUTE = "velocity_mux", "route_controller"


class FleetControlNode:
    def __init__(self, fleet, mux_rate_hz=MUX_RATE_HZ, route_rate_hz=ROUTE_RATE_HZ, deadman_s=DEADMAN_S):
        site = load_site_for(fleet)
        try:
            self.control = FleetControl(fleet, site, deadman_s=deadman_s)
        except ConfigError as exc:
            fail(f"bad route file: {exc}")
        self.tf_buffer = tf2_ros.Buffer()
        self.tf_listener = tf2_ros.TransformListener(self.tf_buffer)
        self.muxes, self.routes, self.errors = {}, {}, {}
        self.loop = ControlLoop(self._on_error)
        now = time.time()
        for i, robot in enumerate(fleet.robots):
            r = robot.name

            def topic(relative, r=r):
                return "/" + names.robot_topic(r, relative)

            self.muxes[r] = VelocityMuxNode(robot, self.control.muxes[r], topic, subscribe_estop=False)
            self.routes[r] = RouteControllerNode(robot, self.control.trackers[r], self.tf_buffer, topic)
            self.errors[r] = ThrottledLog(rospy.logerr, WARN_PERIOD_S)
            # Staggered so the robots' publications do not all fall in the same instant.
            offset_s = i / (len(fleet.robots) * mux_rate_hz)
            self.loop.add(r, MUX, mux_rate_hz, self.muxes[r].tick, now + offset_s)
            self.loop.add(r, ROUTE, route_rate_hz, self.routes[r].tick, now + offset_s)
        # One subscriber for the fleet: the latched state must reach every robot's mux.
        self.estop_sub = rospy.Subscriber(names.ESTOP, Bool, self._on_estop, queue_size=5)
        self.period_s = 1.0 / max(mux_rate_hz, route_rate_hz)
        rospy.loginfo(
            "fleet_control: velocity mux (%.0f Hz) and route controller (%.0f Hz) for %s",
            mux_rate_hz,
            route_rate_hz,
            ", ".join(self.muxes),
        )

    def _on_estop(self, msg):
        for mux in self.muxes.values():
            mux.on_estop(msg)

    def _on_error(self, robot, task, exc):
        """One robot's tick failed: say so and hold that robot (zero), the others carry on."""
        self.errors[robot](
            f"fleet_control {robot}: {task} failed: {type(exc).__name__}: {exc}; "
            f"{robot} holds ({self.loop.failures[(robot, task)]} failures so far)"
        )
        try:
            self.muxes[robot].stop()
        except Exception as stop_exc:  # noqa: BLE001
            rospy.logerr(f"fleet_control {robot}: could not send zero: {stop_exc}")

    def spin(self):
        run_realtime(self.loop.step, self.period_s, time.time, time.sleep, rospy.is_shutdown)


def main():
    init_node("fleet_control")
    fleet = load_fleet_param()
    node = FleetControlNode(
        fleet,
        mux_rate_hz=positive_param("~mux_rate_hz", MUX_RATE_HZ),
        route_rate_hz=positive_param("~route_rate_hz", ROUTE_RATE_HZ),
        deadman_s=positive_param("~deadman_s", DEADMAN_S),
    )
    node.spin()
