"""route_controller's ROS side (in /<r>): follows the robot's route from odometry.

The pose in `map` is odometry composed with the static `map -> <r>/odom` transform from tf
(published by fleet_sim, or a real robot's localization); nothing here recomputes it.
"""
import math

import rospy
import tf2_ros
from geometry_msgs.msg import Twist as TwistMsg
from nav_msgs.msg import Odometry
from std_msgs.msg import String

from cps_fleet.config import ConfigError
from cps_sim import names
from cps_sim.controllers import RouteFollower, validate_route
from cps_sim.node_support import fail, load_fleet_param, load_site_for, positive_param, spin_at, twist_to_msg
from cps_sim.robots import pose_matrix


def yaw_of_quaternion(q):
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def matrix_of_transform(transform):
    """4x4 of a geometry_msgs/Transform whose rotation is a yaw (as map -> odom is)."""
    t = transform.translation
    return pose_matrix(t.x, t.y, t.z, yaw_of_quaternion(transform.rotation))


class RouteControllerNode:
    """Follows the robot's route from its odometry and tf's map -> <r>/odom (in /<r>)."""

    def __init__(self):
        fleet = load_fleet_param()
        name = rospy.get_param("~robot", "")
        if not name:
            fail("parameter ~robot is required (the robot's name in the fleet file)")
        try:
            self.config = fleet.robot(name)
        except KeyError as exc:
            fail(f"parameter ~robot: {exc.args[0]}")
        site = load_site_for(fleet)
        try:
            self.route = fleet.route(name)
            validate_route(self.route, site, self.config.robot_type)
        except ConfigError as exc:
            fail(f"bad route file: {exc}")
        self.rate_hz = positive_param("~rate_hz", 10.0)
        self.tf_buffer = tf2_ros.Buffer()
        self.tf_listener = tf2_ros.TransformListener(self.tf_buffer)
        self.odom_in_map = None
        self.follower = None
        self.cmd_pub = rospy.Publisher(names.CMD_VEL_AUTO, TwistMsg, queue_size=5)
        self.state_pub = rospy.Publisher(names.MISSION_STATE, String, queue_size=1, latch=True)
        self.flight_pub = rospy.Publisher(names.FLIGHT_COMMAND, String, queue_size=5)
        self.odom_pose = None
        self.last_state = None
        self._publish_state("idle")
        rospy.Subscriber(names.ODOM, Odometry, self._on_odom, queue_size=5)
        rospy.loginfo("route_controller %s: %d waypoints from %s", name, len(self.route.waypoints), self.route.path)

    def _on_odom(self, msg):
        p = msg.pose.pose.position
        self.odom_pose = pose_matrix(p.x, p.y, p.z, yaw_of_quaternion(msg.pose.pose.orientation))

    def _lookup_odom_in_map(self):
        """The static map -> <r>/odom once tf has it (the follower starts from its origin)."""
        try:
            stamped = self.tf_buffer.lookup_transform(names.MAP_FRAME, names.odom_frame(self.config.name),
                                                      rospy.Time(0))
        except (tf2_ros.LookupException, tf2_ros.ConnectivityException, tf2_ros.ExtrapolationException):
            rospy.loginfo_throttle(10.0, f"route_controller {self.config.name}: waiting for tf "
                                         f"{names.MAP_FRAME} -> {names.odom_frame(self.config.name)}")
            return
        self.odom_in_map = matrix_of_transform(stamped.transform)
        start_xy = (self.odom_in_map[0, 3], self.odom_in_map[1, 3])
        self.follower = RouteFollower(self.route, self.config.robot_type, start_xy=start_xy)

    def _pose_in_map(self):
        m = self.odom_in_map @ self.odom_pose
        return m[0, 3], m[1, 3], m[2, 3], math.atan2(m[1, 0], m[0, 0])

    def _publish_state(self, state):
        if state != self.last_state:
            self.state_pub.publish(String(state))
            rospy.loginfo("route_controller %s: mission %s", self.config.name, state)
            self.last_state = state

    def _update(self):
        if self.odom_in_map is None:
            self._lookup_odom_in_map()
        if self.follower is None or self.odom_pose is None:
            return
        twist, flight = self.follower.update(*self._pose_in_map())
        if flight:
            self.flight_pub.publish(String(flight))
        if not self.follower.finished or self.last_state != "done":
            self.cmd_pub.publish(twist_to_msg(twist))
        self._publish_state(self.follower.state)

    def spin(self):
        spin_at(self.rate_hz, self._update)


def main():
    rospy.init_node("route_controller")
    RouteControllerNode().spin()
