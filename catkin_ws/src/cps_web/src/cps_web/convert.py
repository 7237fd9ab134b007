"""Our ROS messages as Foxglove's schemas: pure functions of the messages' fields (no rospy).

Each takes a ROS message (any object with its fields, e.g. a genpy message) and returns a
`foxglove.messages` object or a JSON dict for the endpoint to log. Bad input (a cloud whose data
does not fit its layout, a non-finite pose) raises ValueError with what is wrong; the endpoint
counts it and goes on.
"""

import collections
import math
import threading
from typing import Dict, Iterable, Optional, Sequence, Tuple

from foxglove.messages import (
    ArrowPrimitive,
    Color,
    CompressedImage,
    CubePrimitive,
    FrameTransform,
    FrameTransforms,
    LinePrimitive,
    LinePrimitiveLineType,
    PackedElementField,
    PackedElementFieldNumericType,
    Point3,
    PointCloud,
    Pose,
    PoseInFrame,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    TextPrimitive,
    Timestamp,
    Vector3,
)

from cps_gui.colours import robot_colour
from cps_gui.topview import CHANGE_RGB

# sensor_msgs/PointField datatypes -> Foxglove's packed element types.
_FIELD_TYPES = {
    1: PackedElementFieldNumericType.Int8,
    2: PackedElementFieldNumericType.Uint8,
    3: PackedElementFieldNumericType.Int16,
    4: PackedElementFieldNumericType.Uint16,
    5: PackedElementFieldNumericType.Int32,
    6: PackedElementFieldNumericType.Uint32,
    7: PackedElementFieldNumericType.Float32,
    8: PackedElementFieldNumericType.Float64,
}
# A change's box is drawn see-through so the map inside it stays visible.
CHANGE_ALPHA = 0.6
# The trail keeps a point once the robot moved this far from the last one, and at most this many.
TRAIL_STEP_M = 0.1
TRAIL_MAX_POINTS = 2000


def timestamp(stamp) -> Timestamp:
    """A ROS time (secs, nsecs) as Foxglove's Timestamp."""
    return Timestamp(int(stamp.secs), int(stamp.nsecs))


def stamp_ns(stamp) -> int:
    return int(stamp.secs) * 1_000_000_000 + int(stamp.nsecs)


def q_identity() -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)


def _identity() -> Pose:
    return Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))


def _finite(*values) -> bool:
    return all(math.isfinite(v) for v in values)


def _pose(p, q, what) -> Pose:
    if not _finite(p.x, p.y, p.z, q.x, q.y, q.z, q.w):
        raise ValueError(f"{what}: non-finite pose")
    return Pose(position=Vector3(x=p.x, y=p.y, z=p.z), orientation=Quaternion(x=q.x, y=q.y, z=q.z, w=q.w))


def point_cloud(msg) -> PointCloud:
    """A sensor_msgs/PointCloud2 (the map's voxel centres) as foxglove.PointCloud, its bytes as they
    are: the same packed layout, one row after another without row padding."""
    data = bytes(msg.data)
    if int(msg.row_step) * int(msg.height) != len(data) or int(msg.row_step) < int(msg.point_step) * int(msg.width):
        raise ValueError(
            f"cloud {msg.header.frame_id!r}: {len(data)} bytes for {msg.height} rows of {msg.row_step} "
            f"(point_step {msg.point_step} x width {msg.width})"
        )
    if int(msg.row_step) != int(msg.point_step) * int(msg.width):  # padded rows: keep each row's points
        row, used = int(msg.row_step), int(msg.point_step) * int(msg.width)
        data = b"".join(data[r * row : r * row + used] for r in range(int(msg.height)))
    fields = []
    for f in msg.fields:
        kind = _FIELD_TYPES.get(int(f.datatype))
        if kind is None:
            raise ValueError(f"cloud field {f.name!r}: unknown datatype {f.datatype}")
        if int(f.count) != 1:
            continue  # Foxglove's packed fields are scalars; e.g. our leaf_size_m is one
        fields.append(PackedElementField(name=f.name, offset=int(f.offset), type=kind))
    return PointCloud(
        timestamp=timestamp(msg.header.stamp),
        frame_id=msg.header.frame_id,
        pose=_identity(),
        point_stride=int(msg.point_step),
        fields=fields,
        data=data,
    )


def pose_in_frame(odom) -> PoseInFrame:
    """A nav_msgs/Odometry's pose in its frame (`<robot>/odom`) as foxglove.PoseInFrame."""
    p = odom.pose.pose
    return PoseInFrame(
        timestamp=timestamp(odom.header.stamp),
        frame_id=odom.header.frame_id,
        pose=_pose(p.position, p.orientation, f"odometry in {odom.header.frame_id!r}"),
    )


def compressed_image(msg) -> CompressedImage:
    """A sensor_msgs/CompressedImage (the managed video, JPEG at the allocated level) as
    foxglove.CompressedImage; its format said the way Foxglove reads it ("jpeg" or "png")."""
    fmt = msg.format.lower()
    kind = "png" if "png" in fmt else "jpeg" if ("jpeg" in fmt or "jpg" in fmt) else None
    if kind is None:
        raise ValueError(f"image format {msg.format!r}: neither jpeg nor png")
    return CompressedImage(
        timestamp=timestamp(msg.header.stamp), frame_id=msg.header.frame_id, data=bytes(msg.data), format=kind
    )


def frame_transforms(tf_msg) -> FrameTransforms:
    """A tf2_msgs/TFMessage as foxglove.FrameTransforms (non-finite transforms raise)."""
    out = []
    for t in tf_msg.transforms:
        tr, rot = t.transform.translation, t.transform.rotation
        if not _finite(tr.x, tr.y, tr.z, rot.x, rot.y, rot.z, rot.w):
            raise ValueError(f"tf {t.header.frame_id} -> {t.child_frame_id}: non-finite transform")
        out.append(
            FrameTransform(
                timestamp=timestamp(t.header.stamp),
                parent_frame_id=t.header.frame_id.lstrip("/"),
                child_frame_id=t.child_frame_id.lstrip("/"),
                translation=Vector3(x=tr.x, y=tr.y, z=tr.z),
                rotation=Quaternion(x=rot.x, y=rot.y, z=rot.z, w=rot.w),
            )
        )
    return FrameTransforms(transforms=out)


def _colour(rgb, alpha=1.0) -> Color:
    return Color(r=rgb[0] / 255.0, g=rgb[1] / 255.0, b=rgb[2] / 255.0, a=alpha)


# visualization_msgs/Marker's CUBE and ADD.
_CUBE, _ADD = 1, 0


def change_scene(markers) -> SceneUpdate:
    """The map server's /twin/map_changes (visualization_msgs/MarkerArray: a CUBE per change whose
    `text` is its kind) as a SceneUpdate that replaces every earlier change: a box per change in
    the GUI's colours (appeared green, disappeared red) and its kind written above it."""
    entities = []
    for m in markers.markers:
        if m.type != _CUBE or m.action != _ADD or m.text not in CHANGE_RGB:
            continue
        p, s = m.pose.position, m.scale
        q = m.pose.orientation
        pose = _pose(p, q, f"change {m.id}")
        label = Pose(position=Vector3(x=p.x, y=p.y, z=p.z + s.z / 2 + 0.3), orientation=q_identity())
        entities.append(
            SceneEntity(
                timestamp=timestamp(m.header.stamp),
                frame_id=m.header.frame_id,
                id=f"change_{m.id}",
                cubes=[
                    CubePrimitive(
                        pose=pose, size=Vector3(x=s.x, y=s.y, z=s.z), color=_colour(CHANGE_RGB[m.text], CHANGE_ALPHA)
                    )
                ],
                texts=[TextPrimitive(pose=label, billboard=True, font_size=14.0, scale_invariant=True, text=m.text)],
            )
        )
    return SceneUpdate(deletions=[SceneEntityDeletion(type=SceneEntityDeletionType.All)], entities=entities)


class Trails:
    """Each robot's recent path in its odom frame and its latest pose, for the fleet's scene."""

    def __init__(self, robots: Sequence[str], step_m: float = TRAIL_STEP_M, max_points: int = TRAIL_MAX_POINTS):
        self.robots = list(robots)
        self.step_m = step_m
        self._points: Dict[str, collections.deque] = {r: collections.deque(maxlen=max_points) for r in robots}
        self._latest: Dict[str, Tuple[str, object, object]] = {}
        self._lock = threading.Lock()  # `add` on ROS threads, `scene` on the endpoint's worker

    def add(self, robot: str, odom) -> bool:
        """Take the robot's odometry; False (and nothing kept) for an unknown robot or a non-finite pose."""
        if robot not in self._points:
            return False
        p, q = odom.pose.pose.position, odom.pose.pose.orientation
        if not _finite(p.x, p.y, p.z, q.x, q.y, q.z, q.w):
            return False
        with self._lock:
            self._latest[robot] = (odom.header.frame_id, p, q, odom.header.stamp)
            points = self._points[robot]
            if not points or math.dist(points[-1], (p.x, p.y, p.z)) >= self.step_m:
                points.append((p.x, p.y, p.z))
        return True

    def scene(self) -> SceneUpdate:
        """A SceneUpdate with one entity per robot seen: an arrow at its pose and its trail, both
        in its GUI colour (cps_gui.colours, by its index in the fleet)."""
        with self._lock:
            latest = dict(self._latest)
            trails = {r: list(points) for r, points in self._points.items()}
        entities = []
        for index, robot in enumerate(self.robots):
            if robot not in latest:
                continue
            frame, p, q, stamp = latest[robot]
            colour = _colour(robot_colour(index))
            entities.append(
                SceneEntity(
                    timestamp=timestamp(stamp),
                    frame_id=frame,
                    id=robot,
                    arrows=[
                        ArrowPrimitive(
                            pose=_pose(p, q, robot),
                            shaft_length=0.5,
                            shaft_diameter=0.1,
                            head_length=0.3,
                            head_diameter=0.25,
                            color=colour,
                        )
                    ],
                    lines=[
                        LinePrimitive(
                            type=LinePrimitiveLineType.LineStrip,
                            pose=_identity(),
                            thickness=0.05,
                            points=[Point3(x=x, y=y, z=z) for x, y, z in trails[robot]],
                            color=colour,
                        )
                    ],
                    texts=[
                        TextPrimitive(
                            pose=Pose(position=Vector3(x=p.x, y=p.y, z=p.z + 0.8), orientation=q_identity()),
                            billboard=True,
                            font_size=14.0,
                            scale_invariant=True,
                            text=robot,
                            color=colour,
                        )
                    ],
                )
            )
        return SceneUpdate(entities=entities)


# --- JSON channels: plots of fleet health and the link ----------------------------------------------

HEALTH_SCHEMA = {
    "type": "object",
    "description": "Per robot: battery (percent), mission state, control mode and the age of its last pose (s).",
    "properties": {
        "stamp_s": {"type": "number"},
        "robots": {
            "type": "object",
            "additionalProperties": {
                "type": "object",
                "properties": {
                    "battery_percent": {"type": ["number", "null"]},
                    "mission_state": {"type": "string"},
                    "control_mode": {"type": "string"},
                    "pose_age_s": {"type": ["number", "null"]},
                },
            },
        },
    },
}

LINK_SCHEMA = {
    "type": "object",
    "description": "The link's capacity, the manager's budget and what it allocated (Mbit/s), and per robot stream the allocated level and rate.",
    "properties": {
        "stamp_s": {"type": "number"},
        "link_up": {"type": ["boolean", "null"]},
        "outages": {"type": ["integer", "null"]},
        "capacity_mbps": {"type": ["number", "null"]},
        "capacity_source": {"type": "string"},
        "available_mbps": {"type": ["number", "null"]},
        "budget_mbps": {"type": ["number", "null"]},
        "allocated_mbps": {"type": ["number", "null"]},
        "feasible": {"type": ["boolean", "null"]},
        "streams": {
            "type": "object",
            "additionalProperties": {
                "type": "object",
                "properties": {
                    "level": {"type": "integer"},
                    "level_name": {"type": "string"},
                    "rate_hz": {"type": "number"},
                    "mbps": {"type": "number"},
                    "degraded": {"type": "boolean"},
                },
            },
        },
    },
}

ENDPOINT_SCHEMA = {
    "type": "object",
    "description": "The endpoint's own counters since it started: messages queued, dropped (queue full), stalled (no viewer took data: not converted), bad (conversion refused), logged; the viewers connected now, and how many of them are stalled.",
    "properties": {
        "queued": {"type": "integer"},
        "dropped": {"type": "integer"},
        "stalled": {"type": "integer"},
        "bad": {"type": "integer"},
        "failed": {"type": "integer"},
        "logged": {"type": "integer"},
        "queue_length": {"type": "integer"},
        "viewers": {"type": "integer"},
        "stalled_viewers": {"type": "integer"},
        "by_channel": {"type": "object"},
    },
}


def _number(value) -> Optional[float]:
    return float(value) if value is not None and math.isfinite(value) else None


class FleetHealth:
    """The latest battery, mission state, control mode and pose time of each robot (the GUI's
    health table), as a JSON row."""

    def __init__(self, robots: Iterable[str]):
        self.robots = list(robots)
        self._battery: Dict[str, float] = {}
        self._mission: Dict[str, str] = {}
        self._mode: Dict[str, str] = {}
        self._pose_s: Dict[str, float] = {}

    def battery(self, robot, msg):
        """A sensor_msgs/BatteryState; its percentage in [0, 1] (NaN when the driver does not know)."""
        if math.isfinite(msg.percentage):
            self._battery[robot] = 100.0 * msg.percentage

    def mission_state(self, robot, text):
        self._mission[robot] = text

    def control_mode(self, robot, text):
        self._mode[robot] = text

    def pose(self, robot, now_s):
        self._pose_s[robot] = now_s

    def row(self, now_s) -> dict:
        robots = {}
        for r in self.robots:
            seen = self._pose_s.get(r)
            robots[r] = {
                "battery_percent": _number(self._battery.get(r)),
                "mission_state": self._mission.get(r, ""),
                "control_mode": self._mode.get(r, ""),
                "pose_age_s": None if seen is None else round(now_s - seen, 3),
            }
        return {"stamp_s": now_s, "robots": robots}


class LinkFigures:
    """The link's state and capacity and the manager's latest allocation, as a JSON row."""

    def __init__(self):
        self._state = None
        self._capacity = None
        self._allocation = None

    def link_state(self, msg):
        self._state = msg

    def link_capacity(self, msg):
        self._capacity = msg

    def allocation(self, msg):
        self._allocation = msg

    def row(self, now_s) -> dict:
        a, c, s = self._allocation, self._capacity, self._state
        streams = {}
        for x in a.allocations if a is not None else ():
            streams[f"{x.robot}/{x.stream}"] = {
                "level": int(x.level),
                "level_name": x.level_name,
                "rate_hz": float(x.rate_hz),
                "mbps": 8.0 * float(x.bandwidth_mbytes_per_s),
                "degraded": bool(x.degraded),
            }
        return {
            "stamp_s": now_s,
            "link_up": None if s is None else bool(s.up),
            "outages": None if s is None else int(s.outages),
            "capacity_mbps": None if c is None else _number(c.capacity_mbps),
            "capacity_source": "" if c is None else c.source,
            "available_mbps": None if a is None else _number(a.available_mbps),
            "budget_mbps": None if a is None else _number(8.0 * a.budget_mbytes_per_s),
            "allocated_mbps": None if a is None else _number(8.0 * a.allocated_mbytes_per_s),
            "feasible": None if a is None else bool(a.feasible),
            "streams": streams,
        }
