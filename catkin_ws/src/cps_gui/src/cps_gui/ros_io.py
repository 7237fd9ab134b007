"""The GUI's ROS side: subscribers that turn messages into plain values in a FleetState, and the
command publishers and service calls of the teleoperation pane.

Callbacks run on rospy's threads and only convert and store; anything that talks to the master
or a service (topic discovery, /tissue/set_priority) runs on a worker thread and reports back
through a callback, so the GUI thread never waits on the network.
"""

import dataclasses
import math
import threading

import rospy
import tf2_ros
from geometry_msgs.msg import Twist
from nav_msgs.msg import OccupancyGrid, Odometry
from rosgraph_msgs.msg import Log
from sensor_msgs.msg import BatteryState, CompressedImage, Image
from std_msgs.msg import Bool, Float64, String
from visualization_msgs.msg import Marker, MarkerArray

from cps_fleet import names
from cps_gui import topview
from cps_gui.fleet_state import (
    Allocation,
    ImageFrame,
    LinkEstimateFigures,
    MapChange,
    Pose,
    RobotAllocation,
    RobotMapFigures,
    TopicFigures,
    VideoStatus,
)
from cps_msgs.msg import (
    BandwidthAllocationArray,
    LinkEstimate,
    LinkState,
    MapStats,
    RateLimiterStatus,
    TopicStatsArray,
)
from cps_msgs.srv import SetPriority, SetPriorityRequest
from cps_ros.publisher import Publisher
from cps_ros.timers import guarded_timer
from cps_transport.image_compression import InvalidImage, decode_jpeg

IMAGE_TYPE = "sensor_msgs/Image"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/CompressedImage"
MODES = ("auto", "teleop")
FLIGHT_COMMANDS = ("takeoff", "land")
FLIGHT_COMMAND_QUEUE = 10  # flight commands an operator can click before the first has gone
LOG_LEVELS = {Log.DEBUG: "DEBUG", Log.INFO: "INFO", Log.WARN: "WARN", Log.ERROR: "ERROR", Log.FATAL: "FATAL"}


def map_changes_of(msg):
    """The MapChanges of a /twin/map_changes MarkerArray: its boxes, whose `text` is the kind; a
    move's arrow ("moved from", after its box) says where the item stood."""
    out = []
    for marker in msg.markers:
        if marker.action != Marker.ADD:
            continue
        if marker.type == Marker.CUBE and marker.text in ("appeared", "disappeared", "moved"):
            p, s = marker.pose.position, marker.scale
            out.append(MapChange(marker.text, (p.x, p.y, p.z), (s.x, s.y, s.z)))
        elif marker.type == Marker.ARROW and marker.text == "moved from" and out and len(marker.points) == 2:
            p = marker.points[0]
            out[-1] = dataclasses.replace(out[-1], from_m=(p.x, p.y, p.z))
    return out


class FleetRosIO:
    """Subscriptions feeding `state` and the command side for every robot of `fleet`."""

    def __init__(self, fleet, state, discovery_period_s=2.0, service_timeout_s=3.0):
        self.fleet = fleet
        self.state = state
        self.service_timeout_s = service_timeout_s
        self._subscribers = []
        self._image_sub = None
        self._image_topic = ""
        self._image_lock = threading.Lock()
        self._image_topics = {}  # topic -> IMAGE_TYPE or COMPRESSED_IMAGE_TYPE
        self.invalid_images = 0
        self._closed = False
        self.teleop_pubs, self.mode_pubs, self.flight_pubs = {}, {}, {}
        # map -> <r>/odom comes from tf (fleet_sim or the robots publish it), cached once heard.
        self.tf_buffer = tf2_ros.Buffer()
        self._tf_listener = tf2_ros.TransformListener(self.tf_buffer)
        self._odom_in_map = {}
        for robot in fleet.robots:
            self._robot_io(robot)
        sub = self._subscribe
        sub(names.TISSUE_STATS, TopicStatsArray, self._on_stats)
        sub(names.ALLOCATION, BandwidthAllocationArray, self._on_allocation)
        sub(names.AVAILABLE_BANDWIDTH, Float64, lambda m: state.set_available_bandwidth(m.data))
        sub(names.in_twin(names.MAP_STATS), MapStats, self._on_map_stats)
        sub(names.LINK_STATE, LinkState, self._on_link_state, queue_size=10)
        sub(
            names.LINK_ESTIMATE,
            LinkEstimate,
            lambda m: state.set_link_estimate(
                LinkEstimateFigures(m.capacity_mbps, m.estimate_mbps, m.mode, m.true_capacity_mbps, m.ratio)
            ),
            queue_size=5,
        )
        sub(names.in_twin(names.PROJECTED_MAP), OccupancyGrid, self._on_projected_map, buff_size=2**24)
        sub(names.ROSOUT_AGG, Log, self._on_log, queue_size=100)
        sub(
            names.in_twin(names.MAP_CHANGES),
            MarkerArray,
            lambda m: state.set_map_changes(map_changes_of(m)),
            buff_size=2**20,
        )
        self.estop_pub = Publisher(names.ESTOP, Bool, queue_size=1, latch=True)
        # The robot whose video the operator watches: the manager gives it operator-quality video.
        self.selected_pub = Publisher(names.SELECTED_ROBOT, String, queue_size=1, latch=True)
        self.selected_robot = None
        self._discovery = guarded_timer(discovery_period_s, self._discover_images, "image discovery")
        threading.Thread(target=self._discover_images, args=(None,), daemon=True).start()

    def _subscribe(self, topic, msg_type, callback, queue_size=1, buff_size=65536):
        self._subscribers.append(
            rospy.Subscriber(topic, msg_type, callback, queue_size=queue_size, buff_size=buff_size)
        )

    def _robot_io(self, robot):
        name, state = robot.name, self.state

        def topic(relative):
            return names.robot_topic(name, relative)

        def on_odom(msg):
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            if not all(math.isfinite(v) for v in (p.x, p.y, p.z, q.x, q.y, q.z, q.w)):
                rospy.logwarn_throttle(
                    10.0,
                    f"cps_gui: {names.absolute(names.robot_topic(name, names.ODOM))} with a non-finite pose, ignored",
                )
                return
            origin = self._odom_origin(name)
            if origin is None:
                rospy.logwarn_throttle(
                    10.0,
                    f"cps_gui: no tf {names.MAP_FRAME} -> {names.odom_frame(name)} yet; "
                    f"{names.absolute(names.robot_topic(name, names.ODOM))} not shown",
                )
                return
            yaw = topview.yaw_from_quaternion(q.x, q.y, q.z, q.w)
            x, y, yaw_map = topview.odom_to_map(origin.x, origin.y, origin.yaw_rad, p.x, p.y, yaw)
            v = msg.twist.twist.linear
            state.set_pose(name, Pose(x, y, origin.z + p.z, yaw_map, math.hypot(v.x, v.y)))

        def on_battery(msg):
            if not math.isfinite(msg.percentage):
                rospy.logwarn_throttle(
                    10.0,
                    f"cps_gui: {names.absolute(names.robot_topic(name, names.BATTERY))} without a percentage, ignored",
                )
                return
            state.set_battery(name, msg.percentage)

        self._subscribe(topic(names.ODOM), Odometry, on_odom)
        self._subscribe(topic(names.BATTERY), BatteryState, on_battery)
        self._subscribe(topic(names.CONTROL_MODE_ACTIVE), String, lambda m: state.set_mode(name, m.data))
        self._subscribe(topic(names.MISSION_STATE), String, lambda m: state.set_mission_state(name, m.data))
        if robot.has_depth_camera:
            self._subscribe(topic(names.VIDEO_STATUS), RateLimiterStatus, lambda m: self._on_video_status(name, m))
        self.teleop_pubs[name] = Publisher(topic(names.CMD_VEL_TELEOP), Twist, queue_size=1)
        self.mode_pubs[name] = Publisher(topic(names.CONTROL_MODE), String, queue_size=1, latch=True)
        if robot.robot_type.is_aerial:
            # Each takeoff or land is an event, not a state: a queue of one dropped a takeoff that a land
            # followed within the writer's turn (test_gui_ros, final6); none is lost behind another.
            self.flight_pubs[name] = Publisher(topic(names.FLIGHT_COMMAND), String, queue_size=FLIGHT_COMMAND_QUEUE)

    def _odom_origin(self, robot):
        """The static map -> <r>/odom as a topview.Pose2D, or None until tf has it."""
        origin = self._odom_in_map.get(robot)
        if origin is None:
            try:
                t = self.tf_buffer.lookup_transform(names.MAP_FRAME, names.odom_frame(robot), rospy.Time(0)).transform
            except (tf2_ros.LookupException, tf2_ros.ConnectivityException, tf2_ros.ExtrapolationException):
                return None
            q = t.rotation
            origin = topview.Pose2D(
                t.translation.x, t.translation.y, t.translation.z, topview.yaw_from_quaternion(q.x, q.y, q.z, q.w)
            )
            self._odom_in_map[robot] = origin
        return origin

    # Incoming.

    def _on_stats(self, msg):
        self.state.set_tissue_stats(
            TopicFigures(t.topic, t.robot, t.managed, t.rate_hz, t.bandwidth_mbytes_per_s, t.latency_avg_ms, t.age_s)
            for t in msg.topics
        )

    def _on_allocation(self, msg):
        self.state.set_allocation(
            Allocation(
                budget_mbytes_per_s=msg.budget_mbytes_per_s,
                allocated_mbytes_per_s=msg.allocated_mbytes_per_s,
                available_mbps=msg.available_mbps,
                feasible=msg.feasible,
                robots=tuple(
                    RobotAllocation(
                        a.robot,
                        a.priority,
                        a.rate_hz,
                        a.bandwidth_mbytes_per_s,
                        a.share_percent,
                        a.degraded,
                        a.stream or "cloud",
                        a.level,
                        a.level_name,
                    )
                    for a in msg.allocations
                ),
            )
        )

    def _on_video_status(self, robot, msg):
        levels = self.fleet.streams.video_levels
        level_name = levels[msg.level].name if msg.level < len(levels) else f"level {msg.level}?"
        size = msg.level_mean_message_bytes if math.isfinite(msg.level_mean_message_bytes) else msg.mean_message_bytes
        self.state.set_video_status(
            robot, VideoStatus(msg.level, level_name, msg.set_rate_hz, msg.output_rate_hz, size)
        )

    def _on_link_state(self, msg):
        down_for_s = (rospy.Time.now() - msg.since).to_sec() if not msg.since.is_zero() else 0.0
        self.state.set_link_state(msg.up, down_for_s, msg.outages, msg.last_outage_s, msg.peer)

    def _on_map_stats(self, msg):
        self.state.set_map_stats(
            RobotMapFigures(
                r.robot,
                r.occupied_voxels_contributed,
                r.clouds_dropped_queue + r.clouds_dropped_tf + r.clouds_dropped_invalid,
            )
            for r in msg.robots
        )

    def _on_projected_map(self, msg):
        info = msg.info
        try:
            image = topview.occupancy_image(
                info.width, info.height, info.resolution, info.origin.position.x, info.origin.position.y, msg.data
            )
        except ValueError as exc:
            rospy.logwarn_throttle(10.0, f"cps_gui: {names.in_twin(names.PROJECTED_MAP)} ignored: {exc}")
            return
        self.state.set_projected_map(image)

    def _on_log(self, msg):
        self.state.add_log(msg.header.stamp.to_sec(), LOG_LEVELS.get(msg.level, str(msg.level)), msg.name, msg.msg)

    def _on_image(self, msg):
        self.state.add_image(
            ImageFrame(
                topic=self._image_topic,
                width=msg.width,
                height=msg.height,
                encoding=msg.encoding,
                step=msg.step,
                data=bytes(msg.data),
                stamp_s=msg.header.stamp.to_sec(),
                received_s=self.state.clock(),
            )
        )

    def _on_compressed_image(self, msg, topic):
        """Decodes the JPEG here, on rospy's thread, so the GUI thread only scales a pixmap."""
        try:
            rgb = decode_jpeg(msg.data)
        except InvalidImage as exc:
            self.invalid_images += 1
            rospy.logwarn_throttle(
                10.0, f"cps_gui: frame on {topic} ({msg.format!r}) not shown ({self.invalid_images} so far): {exc}"
            )
            return
        height, width, _ = rgb.shape
        self.state.add_image(
            ImageFrame(
                topic=topic,
                width=width,
                height=height,
                encoding="rgb8",
                step=3 * width,
                data=rgb.tobytes(),
                stamp_s=msg.header.stamp.to_sec(),
                received_s=self.state.clock(),
                transport="jpeg",
                wire_bytes=len(msg.data),
            )
        )

    # Image topics: raw and compressed, found by type, one subscribed at a time (the one on screen).

    def _discover_images(self, _event):
        if self._closed:
            return
        try:
            topics = rospy.get_published_topics()
        except Exception as exc:  # master unreachable: keep the last list
            rospy.logwarn_throttle(30.0, f"cps_gui: cannot list topics: {exc}")
            return
        self._image_topics = {t: kind for t, kind in topics if kind in (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE)}

    @property
    def image_topics(self):
        """Every advertised sensor_msgs/Image and sensor_msgs/CompressedImage topic, sorted."""
        return sorted(self._image_topics)

    def image_topic_type(self, topic):
        """The advertised type of an image topic; before it is advertised, guessed from the name
        (image_transport's `<base>/compressed`)."""
        kind = self._image_topics.get(topic)
        if kind:
            return kind
        return COMPRESSED_IMAGE_TYPE if topic.endswith("/" + names.COMPRESSED_SUFFIX) else IMAGE_TYPE

    def select_image_topic(self, topic):
        """Subscribe to `topic` (empty: none), dropping the previous image subscription."""
        with self._image_lock:
            if topic == self._image_topic:
                return
            if self._image_sub is not None:
                self._image_sub.unregister()
                self._image_sub = None
            self._image_topic = topic
            if topic and self.image_topic_type(topic) == COMPRESSED_IMAGE_TYPE:
                self._image_sub = rospy.Subscriber(
                    topic,
                    CompressedImage,
                    self._on_compressed_image,
                    callback_args=topic,
                    queue_size=1,
                    buff_size=2**22,
                )
            elif topic:
                self._image_sub = rospy.Subscriber(topic, Image, self._on_image, queue_size=1, buff_size=2**24)

    # Outgoing.

    def publish_velocity(self, robot, command):
        twist = Twist()
        twist.linear.x, twist.linear.y, twist.linear.z = command.linear_x, command.linear_y, command.linear_z
        twist.angular.z = command.angular_z
        self.teleop_pubs[robot].publish(twist)

    def set_mode(self, robot, mode):
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got '{mode}'")
        self.mode_pubs[robot].publish(String(data=mode))

    def flight_command(self, robot, command):
        if command not in FLIGHT_COMMANDS:
            raise ValueError(f"flight command must be one of {FLIGHT_COMMANDS}, got '{command}'")
        if robot not in self.flight_pubs:
            raise ValueError(f"robot '{robot}' does not fly")
        self.flight_pubs[robot].publish(String(data=command))

    def select_robot(self, robot):
        """The operator watches `robot` ("" for none): say so on /tissue/selected_robot (latched)."""
        if robot != self.selected_robot:
            self.selected_robot = robot
            self.selected_pub.publish(String(data=robot))

    def set_estop(self, stop):
        self.estop_pub.publish(Bool(data=bool(stop)))

    def set_priority(self, robot, priority, done):
        """Call /tissue/set_priority on a worker thread; `done(ok, text)` runs on that thread."""

        def call():
            try:
                rospy.wait_for_service(names.SET_PRIORITY, timeout=self.service_timeout_s)
                proxy = rospy.ServiceProxy(names.SET_PRIORITY, SetPriority)
                reply = proxy(SetPriorityRequest(robot=robot, priority=priority))
                done(reply.success, reply.message)
            except (rospy.ROSException, rospy.ServiceException) as exc:
                done(False, f"{names.SET_PRIORITY} failed: {exc}")

        threading.Thread(target=call, name=f"set_priority_{robot}", daemon=True).start()

    def close(self):
        self._closed = True
        self._discovery.shutdown()
        self._tf_listener.unregister()
        for sub in self._subscribers:
            sub.unregister()
        self.select_image_topic("")
        for pubs in (self.teleop_pubs, self.mode_pubs, self.flight_pubs):
            for pub in pubs.values():
                pub.unregister()
        self.estop_pub.unregister()
        self.selected_pub.unregister()
