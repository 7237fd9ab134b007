"""Checks and transforms an incoming sensor cloud before it may enter the map."""

import dataclasses

import numpy as np


class InvalidInput(ValueError):
    """A cloud the map must not take (empty, nothing finite, or every point absurdly far)."""


@dataclasses.dataclass
class PreparedCloud:
    points_m: np.ndarray  # N x 3 in map
    origin_m: np.ndarray  # sensor origin in map
    non_finite: int  # NaN/inf points removed (normal for depth clouds: no return)
    absurd: int  # points farther than the sanity limit, removed


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


def prepare_cloud(xyz_sensor, rotation, translation_m, max_points_range_m):
    """Drop non-finite points and points beyond `max_points_range_m` from the sensor, then move the
    rest into map with the sensor pose (rotation 3 x 3, translation 3). InvalidInput if none is left."""
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
    points = xyz[sane] @ np.asarray(rotation, dtype=np.float64).T + origin
    return PreparedCloud(points, origin, non_finite, absurd)
