"""velocity_mux's ROS side (in /<r>): cmd_vel/auto or cmd_vel/teleop by control_mode -> cmd_vel,
with dead-man and e-stop. The decisions are `cps_sim.controllers.VelocityMux`'s."""
import threading

import rospy
from geometry_msgs.msg import Twist as TwistMsg
from std_msgs.msg import Bool, String

from cps_sim import names
from cps_sim.controllers import VelocityMux
from cps_sim.node_support import fail, load_fleet_param, positive_param, spin_at, twist_from_msg, twist_to_msg


class VelocityMuxNode:
    """cmd_vel/auto or cmd_vel/teleop by control_mode -> cmd_vel, with dead-man and e-stop (in /<r>)."""

    def __init__(self):
        fleet = load_fleet_param()
        name = rospy.get_param("~robot", "") or rospy.get_namespace().strip("/")
        try:
            self.config = fleet.robot(name)
        except KeyError as exc:
            fail(f"parameter ~robot: {exc.args[0]}")
        self.rate_hz = positive_param("~rate_hz", 20.0)
        deadman = positive_param("~deadman_s", 0.5)
        # Stopped until the latched e-stop state and a fresh command arrive (a restart knows neither).
        self.mux = VelocityMux(self.config.robot_type, deadman_s=deadman)
        self.lock = threading.Lock()
        self.pub = rospy.Publisher(names.CMD_VEL, TwistMsg, queue_size=5)
        # The mode in force (yocs_cmd_vel_mux's `active`): control_mode is only what was asked.
        self.active_pub = rospy.Publisher(names.CONTROL_MODE_ACTIVE, String, queue_size=1, latch=True)
        self.active_pub.publish(String(data=self.mux.mode))
        rospy.Subscriber(names.CMD_VEL_AUTO, TwistMsg, self._on_cmd, callback_args=names.CMD_VEL_AUTO, queue_size=5)
        rospy.Subscriber(names.CMD_VEL_TELEOP, TwistMsg, self._on_cmd, callback_args=names.CMD_VEL_TELEOP,
                         queue_size=5)
        rospy.Subscriber(names.CONTROL_MODE, String, self._on_mode, queue_size=5)
        rospy.Subscriber(names.ESTOP, Bool, self._on_estop, queue_size=5)

    def _on_cmd(self, msg, topic):
        with self.lock:
            handler = self.mux.on_auto if topic == names.CMD_VEL_AUTO else self.mux.on_teleop
            reason = handler(twist_from_msg(msg))
        if reason:
            rospy.logwarn_throttle(2.0, f"{rospy.resolve_name(topic)}: dropped {reason}; holding "
                                        f"({self.mux.dropped} dropped so far)")

    def _on_mode(self, msg):
        try:
            with self.lock:
                self.mux.set_mode(msg.data.strip())
            self.active_pub.publish(String(data=self.mux.mode))
            rospy.loginfo("velocity_mux %s: control mode %s", self.config.name, self.mux.mode)
        except ValueError as exc:
            rospy.logwarn_throttle(2.0, f"{rospy.resolve_name(names.CONTROL_MODE)}: {exc}; staying in {self.mux.mode}")

    def _on_estop(self, msg):
        with self.lock:
            first = self.mux.estop is None
            self.mux.set_estop(msg.data)
        if first:
            rospy.loginfo("velocity_mux %s: e-stop state heard (%s)", self.config.name, "on" if msg.data else "off")

    def _publish(self):
        with self.lock:
            out = self.mux.update()
        self.pub.publish(twist_to_msg(out))

    def spin(self):
        spin_at(self.rate_hz, self._publish)


def main():
    rospy.init_node("velocity_mux")
    VelocityMuxNode().spin()
