"""Robots are not the site: the volume the robots' bodies swept during a mission, from the sensor
pose of each cloud the twin inserted (tf at the cloud's stamp) and each robot type's body (no rospy).

A robot sees the others (and a lidar sees its own mast), so a map holds robots; compared with a map
of another mission they come out as changes (issue 25: a robot at about (1.3, 3.5, 0.35) m in
every run). The map server keeps a `PoseTrail` per robot (a pose kept each time the sensor moved
`KEEP_EVERY_M` or turned `KEEP_EVERY_DEG`), saves the trails with the map (its sidecar
`<map>.json`, cps_mapping.baseline), and change detection ignores voxels inside the bodies' swept
volume, grown by `BODY_MARGIN_M`, of both missions. Items on the site cannot stand where a robot
drove, so the swept volume holds no real change (the scenario generator keeps its changes off the
routes, cps_sim.site_change_generator).

The body is the fleet contract's (fleet.yaml robot_types: each type's `body` box and
`sensor_mount`, as the simulator uses them too), stored with each trail so that a map stays
cleanable without the fleet file.
"""

import dataclasses
import math
import threading
from typing import Dict, List, Optional, Sequence

import numpy as np

from cps_fleet.transforms import body_in_base, rigid_inverse, sensor_in_base
from cps_mapping.fused_map import pack_index, voxel_index

KEEP_EVERY_M = 0.05
KEEP_EVERY_DEG = 5.0
# A body's sensed surface lies up to one voxel outside its box (voxel rounding) plus the sensor's
# noise: 0.1 m around the box (one voxel of the default 0.1 m map).
BODY_MARGIN_M = 0.1
POSES_PER_CHUNK = 256


@dataclasses.dataclass(frozen=True)
class RobotBody:
    """A robot's body box in its sensor frame: half extents and the box's 4x4 pose in the sensor frame."""

    robot_type: str
    half_extents_m: tuple
    box_in_sensor: tuple  # 4x4, row-major, nested tuples

    def as_json(self):
        return {
            "robot_type": self.robot_type,
            "half_extents_m": list(self.half_extents_m),
            "box_in_sensor": [list(r) for r in self.box_in_sensor],
        }

    @classmethod
    def from_json(cls, doc):
        half = tuple(float(v) for v in doc["half_extents_m"])
        box = np.asarray(doc["box_in_sensor"], dtype=np.float64)
        if len(half) != 3 or box.shape != (4, 4) or not all(h > 0 for h in half):
            raise ValueError("a body needs 3 positive half extents and a 4x4 box_in_sensor")
        return cls(str(doc["robot_type"]), half, tuple(map(tuple, box.tolist())))


def body_of_type(robot_type) -> RobotBody:
    """The body of a cps_fleet RobotType (its `body` box and `sensor_mount`), in its sensor frame."""
    box_in_sensor = rigid_inverse(sensor_in_base(robot_type)) @ body_in_base(robot_type)
    return RobotBody(robot_type.name, tuple(robot_type.body.half_extents_m), tuple(map(tuple, box_in_sensor.tolist())))


def fleet_bodies(fleet, names=None) -> Dict[str, RobotBody]:
    """{robot name: body} for a cps_fleet FleetConfig's robots (those in `names`, if given)."""
    return {r.name: body_of_type(fleet.robot_types[r.type]) for r in fleet.robots if names is None or r.name in names}


class PoseTrail:
    """One robot's sensor poses in the map frame (stamp, 3x3 rotation, translation), thinned."""

    def __init__(self, body: RobotBody, keep_every_m=KEEP_EVERY_M, keep_every_deg=KEEP_EVERY_DEG):
        self.body = body
        self.keep_every_m, self.keep_cos = keep_every_m, math.cos(math.radians(keep_every_deg))
        self.stamps_s: List[float] = []
        self.poses: List[np.ndarray] = []  # 4x4
        self._lock = threading.Lock()

    def record(self, stamp_s, rotation, translation):
        """Keep the pose if it moved or turned enough since the last kept one; True if kept."""
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rotation, translation
        with self._lock:
            if self.poses:
                last = self.poses[-1]
                moved = np.linalg.norm(pose[:3, 3] - last[:3, 3]) >= self.keep_every_m
                # the smallest cosine between the two frames' axes: 1 when they agree
                turned = np.min(np.sum(pose[:3, :3] * last[:3, :3], axis=0)) < self.keep_cos
                if not (moved or turned):
                    return False
            self.stamps_s.append(float(stamp_s))
            self.poses.append(pose)
            return True

    def snapshot(self):
        with self._lock:
            return list(self.stamps_s), list(self.poses)

    def as_json(self):
        stamps, poses = self.snapshot()
        return {
            "body": self.body.as_json(),
            # stamp s, then the 3x4 [R | t] row-major, millimetre/1e-5 precision
            "poses": [[round(s, 3)] + np.round(p[:3, :4], 5).ravel().tolist() for s, p in zip(stamps, poses)],
        }

    @classmethod
    def from_json(cls, doc):
        trail = cls(RobotBody.from_json(doc["body"]))
        for row in doc["poses"]:
            if len(row) != 13:
                raise ValueError(f"a pose is [stamp, 12 numbers of R|t], got {len(row)} numbers")
            m = np.asarray(row[1:], dtype=np.float64).reshape(3, 4)
            trail.stamps_s.append(float(row[0]))
            trail.poses.append(np.vstack([m, [0.0, 0.0, 0.0, 1.0]]))
        return trail


class RobotTrails:
    """Every robot's PoseTrail (the map server's), saved in the map's sidecar."""

    def __init__(self, bodies: Dict[str, RobotBody]):
        self.trails = {name: PoseTrail(body) for name, body in bodies.items()}

    def record(self, robot, stamp_s, rotation, translation):
        trail = self.trails.get(robot)
        return trail.record(stamp_s, rotation, translation) if trail else False

    def as_json(self):
        return {name: trail.as_json() for name, trail in sorted(self.trails.items())}

    @classmethod
    def from_json(cls, doc):
        out = cls({})
        out.trails = {str(name): PoseTrail.from_json(entry) for name, entry in doc.items()}
        return out

    def pose_count(self):
        return sum(len(t.poses) for t in self.trails.values())

    def extend(self, other: "RobotTrails"):
        """Add another mission's trails (a resumed map's) before this one's poses."""
        for name, trail in other.trails.items():
            mine = self.trails.setdefault(name, PoseTrail(trail.body))
            stamps, poses = trail.snapshot()
            with mine._lock:
                mine.stamps_s[:0], mine.poses[:0] = stamps, poses


def _box_samples(half_extents_m, margin_m, step_m):
    """Points filling a box grown by `margin_m`, `step_m` apart (faces included), in the box frame."""
    axes = [
        np.linspace(-(h + margin_m), h + margin_m, max(2, int(math.ceil(2 * (h + margin_m) / step_m)) + 1))
        for h in half_extents_m
    ]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return np.hstack([grid, np.ones((len(grid), 1))])


class SweptVolume:
    """The packed voxel indices inside any robot's body at any kept pose, grown incrementally
    (the live detection adds the poses kept since its last cycle)."""

    def __init__(self, resolution_m, margin_m=BODY_MARGIN_M):
        self.resolution_m, self.margin_m = resolution_m, margin_m
        self._packed = np.zeros(0, dtype=np.int64)
        self._done: Dict[int, int] = {}  # id(trail) -> poses already added

    def add(self, trails: Optional[RobotTrails]):
        if trails is None:
            return self
        new = []
        for trail in trails.trails.values():
            _, poses = trail.snapshot()
            start = self._done.get(id(trail), 0)
            if start >= len(poses):
                continue
            self._done[id(trail)] = len(poses)
            body = trail.body
            box = np.asarray(body.box_in_sensor)
            samples = _box_samples(body.half_extents_m, self.margin_m, self.resolution_m / 2)
            for lo in range(start, len(poses), POSES_PER_CHUNK):  # bounded memory: ~1e6 points a chunk
                stack = np.asarray(poses[lo : lo + POSES_PER_CHUNK]) @ box  # (P, 4, 4): box in map
                points = np.einsum("pij,nj->pni", stack[:, :3, :], samples).reshape(-1, 3)
                new.append(np.unique(pack_index(voxel_index(points, self.resolution_m))))
        if new:
            self._packed = np.unique(np.concatenate([self._packed] + new))
        return self

    def __len__(self):
        return len(self._packed)

    def contains(self, index: Sequence) -> np.ndarray:
        """True for each voxel index (N, 3) inside the swept volume."""
        index = np.asarray(index, dtype=np.int64).reshape(-1, 3)
        if not len(index) or not len(self._packed):
            return np.zeros(len(index), dtype=bool)
        return np.isin(pack_index(index), self._packed)
