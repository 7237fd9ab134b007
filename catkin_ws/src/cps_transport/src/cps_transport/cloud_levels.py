"""The managed cloud's detail levels and the leaf each cloud carries (no ROS; docs/cloud_levels.md).

Every managed cloud carries the voxel leaf it was produced at as a per-point FLOAT32 field named
`leaf_size_m` (LEAF_FIELD), the same value on every point. The encoder adds it without copying the
cloud (`DracoEncoder.encode(cloud, leaf_size_m=...)`): Draco carries it as one constant GENERIC
attribute (about 45 bytes per cloud), the compressed message's `fields` name it, and the unchanged
decoder gives it back as an ordinary field of the twin's PointCloud2, which the map server reads.

A level change reaches the voxel grid before the clouds it already filtered have all reached the
encoder, so `LeafTracker` labels the clouds of a switch by what they are: a voxel grid's output
has one point per voxel of its leaf (each centroid lies in its own voxel), and a cloud filtered at
a finer leaf almost always has several points in some voxel of the coarser one.

`LeafLedger` lets a rate limiter in the encoder's process know a forwarded cloud's leaf from the
encoder instead of decoding the payload again.
"""

import collections
import math
import struct
import threading
from typing import Optional, Sequence, Tuple

import numpy as np

LEAF_FIELD = "leaf_size_m"
# Draco's largest position error on a managed cloud, as a fraction of the map's resolution (and
# never over half the leaf). At half the leaf (0.05 m for a 0.1 m cloud) quantization snaps a
# surface to a lattice one map voxel apart whose origin differs per cloud: two views of a room put
# the same wall in neighbouring voxels, and 0.1 m clouds filled 53 % of its 0.1 m voxels with 37 %
# cleared, against 95 % and 4 % unquantized; at 1/8 of the map's resolution every level is within
# 0.1 point of its unquantized map (docs/cloud_levels.md), for 1.3-1.6x the bytes.
MAP_QUANTIZATION_FRACTION = 0.125
# Two leaves within this relative difference are the same level (float32 round trips of 0.05 m).
LEAF_RELATIVE_TOLERANCE = 1e-4
# The clouds a LeafLedger remembers: far more than can be between the encoder and the limiter
# (the encoder's publisher queues 2, the limiter's subscriber 5).
LEAF_LEDGER_CLOUDS = 64


class LeafError(ValueError):
    """A cloud's leaf field that cannot be read as one leaf (not constant, not finite, <= 0)."""


def position_tolerance_m(leaf_m, map_resolution_m=math.inf):
    """Draco's position tolerance for a cloud of `leaf_m` going into a map of `map_resolution_m`."""
    return min(0.5 * leaf_m, MAP_QUANTIZATION_FRACTION * map_resolution_m)


def level_of_leaf(leaves_m: Sequence[float], leaf_m: float) -> Optional[int]:
    """Index of the level whose leaf is `leaf_m` (within LEAF_RELATIVE_TOLERANCE), else None."""
    for index, level_leaf in enumerate(leaves_m):
        if abs(leaf_m - level_leaf) <= LEAF_RELATIVE_TOLERANCE * level_leaf:
            return index
    return None


def nearest_level(leaves_m: Sequence[float], leaf_m: float) -> int:
    """Index of the level nearest `leaf_m` by ratio (0.01 m -> the 0.05 m level; ties: finer)."""
    if not leaves_m:
        raise ValueError("no levels")
    if not leaf_m > 0:
        raise ValueError(f"leaf must be > 0 m, got {leaf_m}")
    return min(range(len(leaves_m)), key=lambda i: (abs(math.log(leaves_m[i] / leaf_m)), i))


def cloud_level_leaves(fleet) -> Tuple[float, ...]:
    """The managed cloud's level leaves (fleet.yaml streams.cloud_levels), finest first."""
    return tuple(float(level.voxel_leaf_m) for level in fleet.streams.cloud_levels)


def initial_leaf_m(fleet, robot_config) -> float:
    """The leaf a robot's voxel grid starts at, until the manager publishes a level: the level
    nearest the robot's voxel_leaf_m (one of the levels, so the manager always knows the size)."""
    leaves = cloud_level_leaves(fleet)
    return leaves[nearest_level(leaves, robot_config.voxel_leaf_m)]


def leaf_of_points(points) -> Optional[float]:
    """The leaf a structured point array carries in LEAF_FIELD; None when it has no such field;
    LeafError when the values are not one finite leaf > 0."""
    names = points.dtype.names or ()
    if LEAF_FIELD not in names:
        return None
    values = np.asarray(points[LEAF_FIELD], dtype=np.float64).reshape(-1)
    if len(values) == 0:
        raise LeafError("no points to read the leaf from")
    first = values[0]
    if not (math.isfinite(first) and first > 0):
        raise LeafError(f"{LEAF_FIELD} is {first!r}, not a leaf > 0 m")
    if not np.all(values == first):
        low, high = float(np.nanmin(values)), float(np.nanmax(values))
        raise LeafError(f"{LEAF_FIELD} varies within the cloud ({low!r} .. {high!r}); one leaf per cloud")
    return float(first)


def one_point_per_voxel(xyz, leaf_m) -> bool:
    """True when no two of the finite points (N x 3) share a voxel of edge `leaf_m`, keyed as
    pcl::VoxelGrid keys them (floor(p * (1 / leaf)) in float32): what a voxel grid at that leaf
    (or finer) emits."""
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    if len(xyz) < 2:
        return True
    keys = np.floor(xyz * (np.float32(1.0) / np.float32(leaf_m))).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    flat = (keys[:, 2] * span[1] + keys[:, 1]) * span[0] + keys[:, 0]
    return len(np.unique(flat)) == len(flat)


class LeafTracker:
    """The leaf of each cloud coming out of a voxel grid whose leaf is switched at runtime.

    `switch(new_leaf)` once the voxel grid has taken the new leaf; `leaf_of(xyz)` for each cloud
    after it, in order. Until the first cloud that shows the newest leaf, each cloud is the
    coarsest of the leaves set since the last confirmed one for which it has one point per voxel;
    from then on every cloud is the newest leaf. A sparse cloud of a finer leaf can pass for a
    coarser one during a switch (then it is inserted as the coarser: gaps up to it bridged)."""

    def __init__(self, leaf_m):
        self.pending = [float(leaf_m)]  # leaves set since the last confirmed one, newest last
        self.switches = 0

    @property
    def leaf_m(self):
        """The newest leaf set (what the voxel grid produces now)."""
        return self.pending[-1]

    @property
    def switching(self):
        return len(self.pending) > 1

    def switch(self, new_leaf_m):
        new_leaf_m = float(new_leaf_m)
        if new_leaf_m == self.pending[-1]:
            return
        self.pending = [leaf for leaf in self.pending if leaf != new_leaf_m] + [new_leaf_m]
        self.switches += 1

    def leaf_of(self, xyz) -> float:
        if not self.switching:
            return self.pending[0]
        candidates = sorted(self.pending, reverse=True)
        leaf = next((c for c in candidates[:-1] if one_point_per_voxel(xyz, c)), candidates[-1])
        # clouds come in order: the leaves set before this one's are over
        self.pending = self.pending[self.pending.index(leaf) :]
        return leaf


def header_key(header):
    """A cloud's key in a LeafLedger: (stamp secs, stamp nsecs, frame_id as bytes)."""
    return header.stamp.secs, header.stamp.nsecs, header.frame_id.encode()


def serialized_header_key(buff):
    """header_key of a serialized message whose first field is a std_msgs/Header (seq, stamp,
    frame_id), read without deserializing it; struct.error for a buffer shorter than a header."""
    secs, nsecs, length = struct.unpack_from("<3I", buff, 4)
    return secs, nsecs, bytes(buff[16 : 16 + length])


class LeafLedger:
    """The leaves an encoder gave the clouds it publishes, for the rate limiter of the same process
    that relays them as raw bytes: it looks a forwarded cloud's leaf up by its header_key instead of
    decoding the payload (cps_transport.draco.leaf_of_compressed) again. `note(key, leaf_m)` before
    publishing, with the leaf as carried (draco.carried_leaf_m); `leaf_of(key)`: that leaf, or None
    when the key is unknown (not noted, or over LEAF_LEDGER_CLOUDS ago) or ambiguous (clouds noted
    with it carried different leaves), where the caller must decode. Thread-safe."""

    def __init__(self, clouds=LEAF_LEDGER_CLOUDS):
        self.clouds = int(clouds)
        self.leaves = collections.OrderedDict()  # key -> leaf, None once ambiguous; oldest first
        self.lock = threading.Lock()

    def note(self, key, leaf_m):
        with self.lock:
            known = self.leaves.pop(key, leaf_m)
            self.leaves[key] = leaf_m if known == leaf_m else None
            while len(self.leaves) > self.clouds:
                self.leaves.popitem(last=False)

    def leaf_of(self, key) -> Optional[float]:
        with self.lock:
            return self.leaves.get(key)
