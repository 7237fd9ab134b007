"""route_controller's ROS side: follows the robot's route from odometry.

The pose in `map` is odometry composed with the static `map -> <r>/odom` transform from tf
(published by fleet_sim, or a real robot's localization); nothing here recomputes it. The
decisions are `cps_sim.controllers.RouteTracker`'s. `RouteControllerNode` is one robot's topics;
the `route_controller` executable runs one in `/<r>` (relative names), `fleet_control` one per
robot in a single process (`/<r>/...` names, one tf listener for all).
"""

import math

import rospy
import tf2_ros
from geometry_msgs.msg import Twist as TwistMsg
from nav_msgs.msg import Odometry
from std_msgs.msg import String

from cps_fleet import names
from cps_fleet.config import ConfigError
from cps_ros.publisher import Publisher
from cps_ros.shutdown import init_node
from cps_sim.controllers import RouteTracker, validate_route
from cps_sim.fleet_control import ROUTE_RATE_HZ
from cps_sim.node_support import fail, load_fleet_param, load_site_for, positive_param, spin_at, twist_to_msg


def yaw_of_quaternion(q):
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


class RouteControllerNode:
    """One robot's route controller: cmd_vel/auto, flight_command and latched mission_state on `tick()`.

    `topic(relative)` gives the name to use for a per-robot topic (identity in the robot's
    namespace); `tf_buffer` is filled by a TransformListener the caller owns.
    """

    def __init__(self, config, tracker: RouteTracker, tf_buffer, topic=lambda relative: relative):
        self.config = config
        self.tracker = tracker
        self.tf_buffer = tf_buffer
        self.cmd_pub = Publisher(topic(names.CMD_VEL_AUTO), TwistMsg, queue_size=5)
        self.state_pub = Publisher(topic(names.MISSION_STATE), String, queue_size=1, latch=True)
        self.flight_pub = Publisher(topic(names.FLIGHT_COMMAND), String, queue_size=5)
        self._publish_state(self.tracker.start())
        self.sub = rospy.Subscriber(topic(names.ODOM), Odometry, self._on_odom, queue_size=5)
        rospy.loginfo(
            "route_controller %s: %d waypoints from %s", config.name, len(tracker.route.waypoints), tracker.route.path
        )

    def _on_odom(self, msg):
        p = msg.pose.pose.position
        self.tracker.set_odom(p.x, p.y, p.z, yaw_of_quaternion(msg.pose.pose.orientation))

    def _lookup_odom_in_map(self):
        """The static map -> <r>/odom once tf has it (the follower starts from its origin)."""
        odom_frame = names.odom_frame(self.config.name)
        try:
            stamped = self.tf_buffer.lookup_transform(names.MAP_FRAME, odom_frame, rospy.Time(0))
        except (tf2_ros.LookupException, tf2_ros.ConnectivityException, tf2_ros.ExtrapolationException):
            rospy.loginfo_throttle_identical(
                10.0, f"route_controller {self.config.name}: waiting for tf {names.MAP_FRAME} -> {odom_frame}"
            )
            return
        t = stamped.transform.translation
        self.tracker.set_odom_in_map(t.x, t.y, t.z, yaw_of_quaternion(stamped.transform.rotation))

    def _publish_state(self, state):
        if state:
            self.state_pub.publish(String(state))
            rospy.loginfo("route_controller %s: mission %s", self.config.name, state)

    def tick(self):
        if self.tracker.odom_in_map is None:
            self._lookup_odom_in_map()
        command, flight, state = self.tracker.update()
        if flight:
            self.flight_pub.publish(String(flight))
        if command is not None:
            self.cmd_pub.publish(twist_to_msg(command))
        self._publish_state(state)


def main():
    init_node("route_controller")
    fleet = load_fleet_param()
    name = rospy.get_param("~robot", "")
    if not name:
        fail("parameter ~robot is required (the robot's name in the fleet file)")
    try:
        config = fleet.robot(name)
    except KeyError as exc:
        fail(f"parameter ~robot: {exc.args[0]}")
    site = load_site_for(fleet)
    try:
        route = fleet.route(name)
        validate_route(route, site, config.robot_type)
    except ConfigError as exc:
        fail(f"bad route file: {exc}")
    rate_hz = positive_param("~rate_hz", ROUTE_RATE_HZ)
    tf_buffer = tf2_ros.Buffer()
    tf_listener = tf2_ros.TransformListener(tf_buffer)  # noqa: F841 (fills the buffer while alive)
    node = RouteControllerNode(config, RouteTracker(route, config.robot_type), tf_buffer)
    spin_at(rate_hz, node.tick)
