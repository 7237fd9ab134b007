"""What the endpoint shows of the twin: handlers for the ROS messages the node subscribes, and
which Foxglove channel each feeds (no rospy: the node wires topics to these methods).

Each handler does the least on the ROS callback thread: it keeps what the periodic rows need and
offers a conversion to the endpoint, which runs it on its own worker only if a viewer watches.
"""

from typing import Callable, Dict, Optional, Tuple

from cps_fleet import names
from cps_web import convert
from cps_web.endpoint import (
    COMPRESSED_IMAGE,
    ENDPOINT_JSON,
    FRAME_TRANSFORMS,
    HEALTH_JSON,
    LINK_JSON,
    POINT_CLOUD,
    POSE_IN_FRAME,
    SCENE_UPDATE,
    Endpoint,
    parse_listen,
)


def channel(name: str) -> str:
    """A WEB_* name as the Foxglove topic a viewer sees (`/twin/web/map`)."""
    return names.absolute(names.in_twin(name))


MAP, TF, FLEET, CHANGES, VIDEO = (
    channel(n) for n in (names.WEB_MAP, names.WEB_TF, names.WEB_FLEET, names.WEB_CHANGES, names.WEB_VIDEO)
)
HEALTH, LINK, COUNTERS = (channel(n) for n in (names.WEB_HEALTH, names.WEB_LINK, names.WEB_ENDPOINT))


def pose_channel(robot: str) -> str:
    return channel(names.web_pose(robot))


def channels_of(robots):
    """Foxglove topic -> kind of every channel the endpoint offers for `robots`."""
    out = {
        MAP: POINT_CLOUD,
        TF: FRAME_TRANSFORMS,
        FLEET: SCENE_UPDATE,
        CHANGES: SCENE_UPDATE,
        VIDEO: COMPRESSED_IMAGE,
        HEALTH: HEALTH_JSON,
        LINK: LINK_JSON,
        COUNTERS: ENDPOINT_JSON,
    }
    out.update({pose_channel(r): POSE_IN_FRAME for r in robots})
    return out


def _ns(stamp) -> int:
    return convert.stamp_ns(stamp)


class TwinView:
    """The endpoint for `robots` (names), fed by the node's subscriptions."""

    def __init__(self, robots, camera_robots, options, now_s: Callable[[], float], commands=None):
        """`commands`: the viewer's operator commands (cps_web.commands.OperatorCommands) or None."""
        host, port = parse_listen(options.listen)
        self.robots = list(robots)
        self.camera_robots = [r for r in self.robots if r in set(camera_robots)]
        self.now_s = now_s
        self.endpoint = Endpoint(
            channels_of(self.robots),
            latched=(MAP, CHANGES),
            host=host,
            port=port,
            queue_size=options.queue_size,
            backlog=options.backlog,
            services=commands.services() if commands else (),
            stalled_bytes=options.stalled_bytes,
            stall_hold_s=options.stall_hold_s,
        )
        self.url = f"ws://{host}:{self.endpoint.port}"
        self.trails = convert.Trails(self.robots)
        self.health = convert.FleetHealth(self.robots)
        self.link = convert.LinkFigures()
        self.selected_robot = ""
        self._static_tf = {}

    # --- handlers (ROS callback threads) ---------------------------------------------------------
    def on_map(self, msg):
        self.endpoint.offer(MAP, lambda: convert.point_cloud(msg), _ns(msg.header.stamp))

    def on_changes(self, msg):
        self.endpoint.offer(CHANGES, lambda: convert.change_scene(msg))

    def on_tf(self, msg):
        self.endpoint.offer(TF, lambda: convert.frame_transforms(msg))

    def on_tf_static(self, msg):
        """Static transforms accumulate (each latched publisher sends its own); all are re-sent."""
        for t in msg.transforms:
            self._static_tf[t.child_frame_id] = t
        static = _Transforms(list(self._static_tf.values()))  # taken here: the worker converts later
        self.endpoint.offer(TF, lambda: convert.frame_transforms(static))

    def on_odom(self, robot, msg):
        if self.trails.add(robot, msg):
            self.health.pose(robot, self.now_s())
        self.endpoint.offer(pose_channel(robot), lambda: convert.pose_in_frame(msg), _ns(msg.header.stamp))

    def on_battery(self, robot, msg):
        self.health.battery(robot, msg)

    def on_mission_state(self, robot, msg):
        self.health.mission_state(robot, msg.data)

    def on_control_mode(self, robot, msg):
        self.health.control_mode(robot, msg.data)

    def on_selected_robot(self, msg):
        self.selected_robot = msg.data

    def on_video(self, msg):
        self.endpoint.offer(VIDEO, lambda: convert.compressed_image(msg), _ns(msg.header.stamp))

    def on_allocation(self, msg):
        self.link.allocation(msg)

    def on_link_capacity(self, msg):
        self.link.link_capacity(msg)

    def on_link_state(self, msg):
        self.link.link_state(msg)

    # --- periodic (the node's timers) ---------------------------------------------------------------
    def send_scene(self):
        self.endpoint.offer(FLEET, self.trails.scene)

    def send_status(self):
        now = self.now_s()
        self.endpoint.offer(HEALTH, lambda: self.health.row(now))
        self.endpoint.offer(LINK, lambda: self.link.row(now))
        self.endpoint.offer(COUNTERS, self.endpoint.snapshot)

    def watched_inputs(self) -> Dict[str, Optional[Tuple[str, str, Callable]]]:
        """The inputs subscribed only while a viewer watches what they feed and some viewer takes
        data (Endpoint.wanted): key -> (topic, message type, handler), None when not wanted now. The
        map, changes and static tf are latched: a new subscription gets their latest at once.
        Relative topics resolve in the twin's namespace."""
        video = self.video_robot()
        wanted = {
            "map": (names.POINT_CLOUD_CENTERS, "sensor_msgs/PointCloud2", self.on_map, MAP),
            "changes": (names.MAP_CHANGES, "visualization_msgs/MarkerArray", self.on_changes, CHANGES),
            "tf": (names.TF, "tf2_msgs/TFMessage", self.on_tf, TF),
            "tf_static": (names.TF_STATIC, "tf2_msgs/TFMessage", self.on_tf_static, TF),
        }
        out = {
            key: (topic, kind, handler) if self.endpoint.wanted(ch) else None
            for key, (topic, kind, handler, ch) in wanted.items()
        }
        out["video"] = (
            None
            if video is None
            else (
                names.absolute(names.robot_topic(video, names.CAMERA_IMAGE_COMPRESSED)),
                "sensor_msgs/CompressedImage",
                self.on_video,
            )
        )
        return out

    def video_robot(self) -> Optional[str]:
        """Whose video to subscribe now: the operator's selected robot (the GUI's choice, which the
        manager gives operator-quality video), else the first camera robot; None while no viewer
        watches the video, or none takes data (then nothing of it is pulled across the link for the
        endpoint)."""
        if not self.endpoint.wanted(VIDEO):
            return None
        if self.selected_robot in self.camera_robots:
            return self.selected_robot
        return self.camera_robots[0] if self.camera_robots else None

    def close(self):
        self.endpoint.close()


class _Transforms:
    """A TFMessage-like holder of transforms (what convert.frame_transforms reads)."""

    def __init__(self, transforms):
        self.transforms = transforms
