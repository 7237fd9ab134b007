"""Where the map's sensors looked from (no rospy): the sensor pose of every cloud the map actually
inserted, with its robot's field of view, so that change detection counts as a viewpoint of a place
only a cloud that was in the map and had the place in view.

The robots' trails (cps_mapping.robot_bodies) keep every cloud's pose as it arrives, for the volume
their bodies swept; a cloud superseded in the map server's queue (issue 37: under load) or dropped
never reached the map, and a camera looking the other way saw nothing of a place. Both counted as
viewpoints before: a place a drone flew over with its camera ahead, or whose clouds were dropped,
passed the viewpoint rule on the strength of clouds that never showed it.

The map server tells `SensorViews` each cloud's pose when it arrives (`received`) and which clouds
went into the map (`inserted`, by stamp); the inserted poses are thinned like the trails (every
`KEEP_EVERY_M` or `KEEP_EVERY_DEG`) and saved in the map's sidecar.
"""

import collections
import dataclasses
import math
import threading
from typing import Dict, Optional

import numpy as np

from cps_mapping.robot_bodies import KEEP_EVERY_DEG, KEEP_EVERY_M

# Poses received and not yet inserted, per robot (a queue of a few clouds waits at most this many).
PENDING_MAX = 256


@dataclasses.dataclass(frozen=True)
class FieldOfView:
    """A sensor's field of view in its own frame: a lidar (x ahead, z up: all around, within
    +-half_vertical_rad of the horizon) or a depth camera (optical frame: z ahead, x right, y down;
    within +-half_horizontal_rad and +-half_vertical_rad)."""

    kind: str  # "lidar" or "depth"
    half_horizontal_rad: float
    half_vertical_rad: float

    def sees(self, local):
        """Mask of the (N, 3) points in the sensor frame inside the field of view."""
        local = np.asarray(local, dtype=np.float64).reshape(-1, 3)
        if self.kind == "lidar":
            return np.abs(np.arctan2(local[:, 2], np.hypot(local[:, 0], local[:, 1]))) <= self.half_vertical_rad
        ahead = local[:, 2] > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            return (
                ahead
                & (np.abs(np.arctan2(local[:, 0], local[:, 2])) <= self.half_horizontal_rad)
                & (np.abs(np.arctan2(local[:, 1], local[:, 2])) <= self.half_vertical_rad)
            )

    def as_json(self):
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, doc):
        fov = cls(str(doc["kind"]), float(doc["half_horizontal_rad"]), float(doc["half_vertical_rad"]))
        if fov.kind not in ("lidar", "depth") or not (fov.half_horizontal_rad > 0 and fov.half_vertical_rad > 0):
            raise ValueError(f"a field of view is a lidar or depth one with positive half angles, got {doc}")
        return fov


def field_of_view(fleet, robot_type) -> FieldOfView:
    """The field of view of a cps_fleet RobotType under the fleet's sensor profile."""
    if robot_type.sensor == "lidar":
        half_v = math.radians(fleet.profile.lidar.vertical_fov_deg) / 2
        return FieldOfView("lidar", math.pi, half_v)
    cam = fleet.profile.depth_camera
    half_h = math.radians(cam.hfov_deg) / 2
    return FieldOfView("depth", half_h, math.atan(math.tan(half_h) * cam.height / cam.width))


def fleet_fields_of_view(fleet, names=None) -> Dict[str, FieldOfView]:
    """{robot: FieldOfView} of a FleetConfig's robots (those in `names`, if given)."""
    return {
        r.name: field_of_view(fleet, fleet.robot_types[r.type])
        for r in fleet.robots
        if names is None or r.name in names
    }


class SensorViews:
    """Per robot: the sensor poses (4x4 in the map frame) of the inserted clouds, thinned, and its
    field of view."""

    def __init__(self, fields_of_view: Dict[str, FieldOfView]):
        self.fields_of_view = dict(fields_of_view)
        self.poses: Dict[str, list] = {name: [] for name in fields_of_view}
        self._pending = {name: collections.OrderedDict() for name in fields_of_view}
        self._lock = threading.Lock()

    def received(self, robot, stamp_s, rotation, translation):
        """A cloud's sensor pose as it arrives (kept until it is inserted or pushed out)."""
        pending = self._pending.get(robot)
        if pending is None:
            return
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rotation, translation
        with self._lock:
            pending[float(stamp_s)] = pose
            while len(pending) > PENDING_MAX:
                pending.popitem(last=False)

    def inserted(self, robot, stamps_s):
        """The clouds of `robot` with these stamps went into the map: keep their poses (thinned);
        forget the ones received before them that never did (superseded or dropped)."""
        pending = self._pending.get(robot)
        if pending is None or not len(stamps_s):
            return
        newest = max(stamps_s)
        with self._lock:
            for stamp in sorted(float(s) for s in stamps_s):
                pose = pending.pop(stamp, None)
                if pose is not None:
                    self._keep(robot, pose)
            for stamp in [s for s in pending if s <= newest]:
                del pending[stamp]

    def _keep(self, robot, pose):
        kept = self.poses[robot]
        if kept:
            last = kept[-1]
            moved = np.linalg.norm(pose[:3, 3] - last[:3, 3]) >= KEEP_EVERY_M
            turned = np.min(np.sum(pose[:3, :3] * last[:3, :3], axis=0)) < math.cos(math.radians(KEEP_EVERY_DEG))
            if not (moved or turned):
                return
        kept.append(pose)

    def count(self):
        with self._lock:
            return sum(len(p) for p in self.poses.values())

    def positions_seeing(self, target_m, max_range_m) -> np.ndarray:
        """(N, 3) sensor positions of the inserted clouds that had `target_m` in their field of view
        within `max_range_m` (line of sight not checked here)."""
        target = np.asarray(target_m, dtype=np.float64).reshape(3)
        out = []
        with self._lock:
            snapshot = {robot: list(poses) for robot, poses in self.poses.items()}
        for robot, poses in snapshot.items():
            if not poses:
                continue
            stack = np.asarray(poses)
            offset = target - stack[:, :3, 3]
            near = np.linalg.norm(offset, axis=1) <= max_range_m
            local = np.einsum("pji,pj->pi", stack[:, :3, :3], offset)  # R^T (target - t)
            seen = near & self.fields_of_view[robot].sees(local)
            out.append(stack[seen, :3, 3])
        return np.vstack(out) if out else np.zeros((0, 3))

    def as_json(self):
        with self._lock:
            return {
                robot: {
                    "field_of_view": self.fields_of_view[robot].as_json(),
                    "poses": [np.round(p[:3, :4], 5).ravel().tolist() for p in poses],
                }
                for robot, poses in sorted(self.poses.items())
            }

    @classmethod
    def from_json(cls, doc):
        views = cls({str(robot): FieldOfView.from_json(entry["field_of_view"]) for robot, entry in doc.items()})
        for robot, entry in doc.items():
            for row in entry["poses"]:
                if len(row) != 12:
                    raise ValueError(f"a pose is the 12 numbers of R|t, got {len(row)} numbers")
                views.poses[str(robot)].append(
                    np.vstack([np.asarray(row, dtype=np.float64).reshape(3, 4), [0, 0, 0, 1]])
                )
        return views

    def extend(self, other: Optional["SensorViews"]):
        """Add another map's views (a resumed map's) before this one's."""
        if other is None:
            return
        with self._lock:
            for robot, poses in other.poses.items():
                self.fields_of_view.setdefault(robot, other.fields_of_view[robot])
                self.poses[robot] = list(poses) + self.poses.get(robot, [])
                self._pending.setdefault(robot, collections.OrderedDict())
