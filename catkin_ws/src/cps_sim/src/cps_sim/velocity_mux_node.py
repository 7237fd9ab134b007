"""velocity_mux's ROS side: cmd_vel/auto or cmd_vel/teleop by control_mode -> cmd_vel, with
dead-man and e-stop. The decisions are `cps_sim.controllers.VelocityMux`'s.

`VelocityMuxNode` is one robot's topics; the `velocity_mux` executable runs one in `/<r>`
(relative names), `fleet_control` one per robot in a single process (`/<r>/...` names).
"""

import threading

import rospy
from geometry_msgs.msg import Twist as TwistMsg
from std_msgs.msg import Bool, String

from cps_fleet import names
from cps_ros.publisher import Publisher
from cps_ros.shutdown import init_node
from cps_sim.controllers import VelocityMux
from cps_sim.fleet_control import DEADMAN_S, MUX_RATE_HZ
from cps_sim.node_support import (
    WARN_PERIOD_S,
    ThrottledLog,
    fail,
    load_fleet_param,
    positive_param,
    spin_at,
    twist_from_msg,
    twist_to_msg,
)


class VelocityMuxNode:
    """One robot's mux: cmd_vel/auto or cmd_vel/teleop by control_mode -> cmd_vel on `tick()`.

    `topic(relative)` gives the name to use for a per-robot topic (identity in the robot's
    namespace). Stopped until the latched e-stop state and a fresh command arrive (a restart
    knows neither). `subscribe_estop=False`: the caller calls `on_estop` (rospy delivers a
    latched message to only some of several same-topic subscribers in one process when they are
    added while it arrives, so fleet_control subscribes once for the fleet).
    """

    def __init__(self, config, mux: VelocityMux, topic=lambda relative: relative, subscribe_estop=True):
        self.config = config
        self.mux = mux
        self.lock = threading.Lock()
        # Per robot: rospy's own throttle is per line of code, so one robot's warnings would hide another's.
        self.warn = ThrottledLog(rospy.logwarn, WARN_PERIOD_S)
        self.cmd_vel_auto, self.cmd_vel_teleop = topic(names.CMD_VEL_AUTO), topic(names.CMD_VEL_TELEOP)
        self.pub = Publisher(topic(names.CMD_VEL), TwistMsg, queue_size=5)
        # The mode in force (yocs_cmd_vel_mux's `active`): control_mode is only what was asked.
        self.active_pub = Publisher(topic(names.CONTROL_MODE_ACTIVE), String, queue_size=1, latch=True)
        self.active_pub.publish(String(data=self.mux.mode))
        self.mode_topic = topic(names.CONTROL_MODE)
        self.subs = [
            rospy.Subscriber(self.cmd_vel_auto, TwistMsg, self._on_cmd, callback_args=self.cmd_vel_auto, queue_size=5),
            rospy.Subscriber(
                self.cmd_vel_teleop, TwistMsg, self._on_cmd, callback_args=self.cmd_vel_teleop, queue_size=5
            ),
            rospy.Subscriber(self.mode_topic, String, self._on_mode, queue_size=5),
        ]
        if subscribe_estop:
            self.subs.append(rospy.Subscriber(names.ESTOP, Bool, self.on_estop, queue_size=5))

    def _on_cmd(self, msg, topic):
        with self.lock:
            handler = self.mux.on_auto if topic == self.cmd_vel_auto else self.mux.on_teleop
            reason = handler(twist_from_msg(msg))
            dropped = self.mux.dropped
        if reason:
            self.warn(f"{rospy.resolve_name(topic)}: dropped {reason}; holding ({dropped} dropped so far)")

    def _on_mode(self, msg):
        try:
            with self.lock:
                self.mux.set_mode(msg.data.strip())
                mode = self.mux.mode
            self.active_pub.publish(String(data=mode))
            rospy.loginfo("velocity_mux %s: control mode %s", self.config.name, mode)
        except ValueError as exc:
            self.warn(f"{rospy.resolve_name(self.mode_topic)}: {exc}; staying in {self.mux.mode}")

    def on_estop(self, msg):
        with self.lock:
            first = self.mux.estop is None
            self.mux.set_estop(msg.data)
        if first:
            rospy.loginfo("velocity_mux %s: e-stop state heard (%s)", self.config.name, "on" if msg.data else "off")

    def tick(self):
        with self.lock:
            out = self.mux.update()
        self.pub.publish(twist_to_msg(out))

    def stop(self):
        """Publish zero (this robot's tick failed: it must not keep its last command)."""
        self.pub.publish(TwistMsg())


def main():
    init_node("velocity_mux")
    fleet = load_fleet_param()
    name = rospy.get_param("~robot", "") or rospy.get_namespace().strip("/")
    try:
        config = fleet.robot(name)
    except KeyError as exc:
        fail(f"parameter ~robot: {exc.args[0]}")
    rate_hz = positive_param("~rate_hz", MUX_RATE_HZ)
    deadman = positive_param("~deadman_s", DEADMAN_S)
    node = VelocityMuxNode(config, VelocityMux(config.robot_type, deadman_s=deadman))
    spin_at(rate_hz, node.tick)
