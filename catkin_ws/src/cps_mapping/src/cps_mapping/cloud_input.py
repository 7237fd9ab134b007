"""Checks and transforms an incoming sensor cloud before it may enter the map, at the resolution
it was produced at (docs/cloud_levels.md).

A managed cloud carries the voxel leaf it was produced at (cps_transport.cloud_levels). A cloud
at the map's resolution or finer goes in as it is: several points in one map voxel are one hit.
A coarser cloud has one point per leaf cube, the centroid of the surface within it: inserted as is
it would leave holes between its points (a 0.2 m wall in a 0.1 m map: three voxels in four
missing, and rays of later clouds clearing the space behind them). `bridge_coarse_cloud` fills
them: every two points in neighbouring leaf cubes (26-neighbourhood, keyed in the sensor's frame
as the voxel grid keyed them) are joined by a segment sampled at half the map's resolution, and
each map voxel a segment reaches that holds no point yet gets one sample. A centroid lies on its
surface patch, so on a plane the segments stay on the plane (no thickening); a segment never
leaves the two leaf cubes' box, so nothing is added beyond the leaf's own uncertainty.
"""

import dataclasses
import struct
from typing import Optional, Tuple

import numpy as np
from sensor_msgs.msg import PointCloud2

from cps_msgs.msg import CompressedPointCloud2
from cps_transport.cloud_levels import LeafError, leaf_of_points

# The largest leaf taken as one (pcl_ros's VoxelGrid takes at most 1 m); larger: a bad leaf.
MAX_LEAF_M = 1.0
# Neighbouring leaf cubes joined by bridging: half of the 26-neighbourhood (each pair once).
_HALF_NEIGHBOURS = np.array(
    [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1) if (dx, dy, dz) > (0, 0, 0)],
    dtype=np.int64,
)


class InvalidInput(ValueError):
    """A cloud the map must not take (empty, nothing finite, or every point absurdly far)."""


class UnreadableMessage(ValueError):
    """Serialized bytes that are not a cloud message of a type the map server takes."""


# The message types a map server input may carry, by the type name a publisher announces.
CLOUD_TYPES = {cls._type: cls for cls in (CompressedPointCloud2, PointCloud2)}


def _serialized(message):
    """The bytes of a rospy.AnyMsg (kept as it arrived), or None for a message object."""
    return getattr(message, "_buff", None)


def read_message(message, default_type=CompressedPointCloud2):
    """A cloud message from what a subscriber received: a rospy.AnyMsg is deserialized as the type
    its publisher announced (connection header; `default_type` without one), a message object is
    returned as it is. UnreadableMessage for another type or bytes that do not deserialize."""
    data = _serialized(message)
    if data is None:
        return message
    announced = (getattr(message, "_connection_header", None) or {}).get("type")
    cls = CLOUD_TYPES.get(announced, None if announced else default_type)
    if cls is None:
        raise UnreadableMessage(f"type {announced}, not one of {', '.join(CLOUD_TYPES)}")
    try:
        return cls().deserialize(data)
    except Exception as exc:  # genpy raises struct.error, DeserializationError, IndexError...
        raise UnreadableMessage(f"{len(data)} bytes do not deserialize as {cls._type}: {exc}") from exc


def sender_sequence(message) -> Optional[Tuple[str, int]]:
    """(publisher, header.seq) of a received cloud, read without deserializing it: rospy and roscpp
    number every message a publisher sends, so a gap is a message lost on the way. None when the
    message carries no number (a message object handed over in-process)."""
    data = _serialized(message)
    if data is None or len(data) < 4:
        return None
    publisher = (getattr(message, "_connection_header", None) or {}).get("callerid", "")
    return publisher, struct.unpack_from("<I", data, 0)[0]


@dataclasses.dataclass
class PreparedCloud:
    points_m: np.ndarray  # N x 3 in map
    origin_m: np.ndarray  # sensor origin in map
    non_finite: int  # NaN/inf points removed (normal for depth clouds: no return)
    absurd: int  # points farther than the sanity limit, removed
    bridged: int = 0  # surface samples added between the points of a cloud coarser than the map


def read_leaf(points):
    """(leaf in m or None, problem or None) of a cloud's structured points: (None, None) when it
    carries no leaf, (None, why) when its leaf is unusable (then it is inserted as it is)."""
    try:
        leaf = leaf_of_points(points)
    except LeafError as exc:
        return None, str(exc)
    if leaf is not None and leaf > MAX_LEAF_M:
        return None, f"leaf {leaf} m is over {MAX_LEAF_M} m"
    return leaf, None


def quaternion_matrix(x, y, z, w):
    """3 x 3 rotation of a unit quaternion (normalized here)."""
    q = np.array([x, y, z, w], dtype=np.float64)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm < 1e-9:
        raise InvalidInput(f"transform has an invalid rotation quaternion {q.tolist()}")
    x, y, z, w = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def coarser_than(leaf_m, resolution_m) -> bool:
    """A cloud's leaf is coarser than the map's resolution, compared in float32, the precision a
    cloud carries its leaf in: a 0.1 m leaf arrives as 0.10000000149, which is not coarser than a
    0.1 m map."""
    return bool(np.float32(leaf_m) > np.float32(resolution_m))


def prepare_cloud(xyz_sensor, rotation, translation_m, max_points_range_m, leaf_m=None, resolution_m=None):
    """Drop non-finite points and points beyond `max_points_range_m` from the sensor, then move the
    rest into map with the sensor pose (rotation 3 x 3, translation 3). InvalidInput if none is left.
    A cloud whose `leaf_m` is coarser than the map's `resolution_m` is bridged (module docstring)."""
    xyz = np.asarray(xyz_sensor, dtype=np.float64).reshape(-1, 3)
    if len(xyz) == 0:
        raise InvalidInput("empty cloud")
    finite = np.isfinite(xyz).all(axis=1)
    sane = finite.copy()
    sane[finite] = np.einsum("ij,ij->i", xyz[finite], xyz[finite]) <= max_points_range_m**2
    non_finite = int((~finite).sum())
    absurd = int((finite & ~sane).sum())
    if not sane.any():
        raise InvalidInput(
            f"no usable point among {len(xyz)} ({non_finite} non-finite, {absurd} farther than {max_points_range_m} m)"
        )
    origin = np.asarray(translation_m, dtype=np.float64).reshape(3)
    if not np.isfinite(origin).all():
        raise InvalidInput(f"transform has a non-finite translation {origin.tolist()}")
    rotation = np.asarray(rotation, dtype=np.float64)
    points = xyz[sane] @ rotation.T + origin
    bridged = 0
    if leaf_m is not None and resolution_m is not None and coarser_than(leaf_m, resolution_m):
        extra = bridge_coarse_cloud(xyz[sane], leaf_m, resolution_m, rotation, origin, points)
        bridged = len(extra)
        points = np.concatenate([points, extra]) if bridged else points
    return PreparedCloud(points, origin, non_finite, absurd, bridged)


def _map_keys(points_m, resolution_m):
    """Map voxel index as the grid computes it (float32 coordinates, floor(p * (1 / res)))."""
    return np.floor(points_m.astype(np.float32).astype(np.float64) * (1.0 / resolution_m)).astype(np.int64)


def _packed(keys, low, span):
    rel = keys - low
    return (rel[:, 2] * span[1] + rel[:, 1]) * span[0] + rel[:, 0]


def bridge_coarse_cloud(
    xyz_sensor, leaf_m, resolution_m, rotation, translation_m, points_m: Optional[np.ndarray] = None
) -> np.ndarray:
    """Surface samples (M x 3, map frame) between the points of a cloud voxelized at `leaf_m` in its
    sensor frame, one per map voxel (of `resolution_m`) that the cloud's own points (`points_m`,
    its points in map; computed if None) leave empty (see the module docstring)."""
    xyz = np.asarray(xyz_sensor, dtype=np.float64).reshape(-1, 3)
    rotation = np.asarray(rotation, dtype=np.float64)
    origin = np.asarray(translation_m, dtype=np.float64).reshape(3)
    if points_m is None:
        points_m = xyz @ rotation.T + origin
    n = len(xyz)
    if n < 2:
        return np.empty((0, 3))
    keys = np.floor(xyz * (1.0 / leaf_m)).astype(np.int64)
    low = keys.min(axis=0) - 1
    span = keys.max(axis=0) - low + 2
    linear = _packed(keys, low, span)
    order = np.argsort(linear, kind="stable")
    sorted_linear = linear[order]
    firsts, seconds = [], []
    for offset in _HALF_NEIGHBOURS:
        target = _packed(keys + offset, low, span)
        at = np.searchsorted(sorted_linear, target)
        found = at < n
        found[found] = sorted_linear[at[found]] == target[found]
        firsts.append(np.flatnonzero(found))
        seconds.append(order[at[found]])
    first, second = np.concatenate(firsts), np.concatenate(seconds)
    if len(first) == 0:
        return np.empty((0, 3))
    a, b = xyz[first], xyz[second]
    step_m = 0.5 * resolution_m
    pieces = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / step_m).astype(np.int64))
    samples = []
    for count in np.unique(pieces):  # pairs with the same number of pieces together
        if count < 2:
            continue
        sel = pieces == count
        t = (np.arange(1, count) / count)[None, :, None]
        samples.append((a[sel][:, None, :] + t * (b[sel] - a[sel])[:, None, :]).reshape(-1, 3))
    if not samples:
        return np.empty((0, 3))
    samples = np.concatenate(samples) @ rotation.T + origin
    sample_keys = _map_keys(samples, resolution_m)
    own_keys = _map_keys(np.asarray(points_m, dtype=np.float64), resolution_m)
    low = np.minimum(sample_keys.min(axis=0), own_keys.min(axis=0))
    span = np.maximum(sample_keys.max(axis=0), own_keys.max(axis=0)) - low + 1
    sample_linear = _packed(sample_keys, low, span)
    _, first_of_voxel = np.unique(sample_linear, return_index=True)
    new = ~np.isin(sample_linear[first_of_voxel], _packed(own_keys, low, span))
    return samples[first_of_voxel[new]]
