"""Synthetic box scenes and exact sensor clouds for tests and benchmarks without the simulator.

A scene is a list of axis-aligned boxes (floor, walls and crates) in `map`. `depth_camera_cloud`
and `lidar_cloud` cast rays analytically against those boxes, so a test knows exactly which
surfaces a robot saw. Clouds are returned in `map`; `to_sensor_frame` gives them in the sensor
frame for ROS tests. The digital twin's real input comes from cps_sim; this module only stands
in where the simulator is not wanted (unit tests, a labelled fallback in the benchmark).
"""

import dataclasses
from typing import Dict, Tuple

import numpy as np


@dataclasses.dataclass(frozen=True)
class Box:
    name: str
    min_m: Tuple[float, float, float]
    max_m: Tuple[float, float, float]

    def moved(self, dx_m, dy_m):
        return Box(
            self.name,
            (self.min_m[0] + dx_m, self.min_m[1] + dy_m, self.min_m[2]),
            (self.max_m[0] + dx_m, self.max_m[1] + dy_m, self.max_m[2]),
        )


@dataclasses.dataclass(frozen=True)
class BoxScene:
    boxes: Tuple[Box, ...]

    def moved(self, name, dx_m, dy_m):
        return BoxScene(tuple(b.moved(dx_m, dy_m) if b.name == name else b for b in self.boxes))

    def without(self, name):
        return BoxScene(tuple(b for b in self.boxes if b.name != name))

    def occupied_voxels(self, resolution_m):
        """Centres of the voxels (OctoMap's grid) whose cell intersects the surface of any box."""
        centres = []
        for box in self.boxes:
            lo = np.floor(np.asarray(box.min_m) / resolution_m).astype(np.int64)
            hi = np.ceil(np.asarray(box.max_m) / resolution_m).astype(np.int64) - 1
            ranges = [np.arange(a, b + 1) for a, b in zip(lo, hi)]
            grid = np.stack(np.meshgrid(*ranges, indexing="ij"), axis=-1).reshape(-1, 3)
            shell = np.zeros(len(grid), dtype=bool)
            for axis in range(3):
                shell |= (grid[:, axis] == lo[axis]) | (grid[:, axis] == hi[axis])
            centres.append((grid[shell] + 0.5) * resolution_m)
        keys = np.unique(np.round(np.vstack(centres) / resolution_m - 0.5).astype(np.int64), axis=0)
        return (keys + 0.5) * resolution_m


# Faces sit this far off the 0.1 m and 0.05 m voxel borders, so that a surface point is not
# split between two voxels by rounding.
GRID_OFFSET_M = 0.013


def hall_scene(size_x_m=20.0, size_y_m=16.0, height_m=4.0, wall_m=0.2, offset_m=GRID_OFFSET_M):
    """A closed hall with a floor, four walls and three pieces of equipment (two crates, a tank)."""
    hx, hy = size_x_m / 2, size_y_m / 2
    return _shifted(
        BoxScene(
            (
                Box("floor", (-hx, -hy, -wall_m), (hx, hy, 0.0)),
                Box("wall_north", (-hx, hy, 0.0), (hx, hy + wall_m, height_m)),
                Box("wall_south", (-hx, -hy - wall_m, 0.0), (hx, -hy, height_m)),
                Box("wall_east", (hx, -hy, 0.0), (hx + wall_m, hy, height_m)),
                Box("wall_west", (-hx - wall_m, -hy, 0.0), (-hx, hy, height_m)),
                Box("crate_a", (-3.0, -2.0, 0.0), (-2.0, -1.0, 1.0)),
                Box("crate_b", (2.0, 1.5, 0.0), (3.2, 2.5, 1.2)),
                Box("tank", (-1.0, 3.0, 0.0), (1.0, 4.5, 2.0)),
            )
        ),
        offset_m,
    )


def _shifted(scene, offset_m):
    shift = np.full(3, offset_m)
    return BoxScene(
        tuple(Box(b.name, tuple(np.asarray(b.min_m) + shift), tuple(np.asarray(b.max_m) + shift)) for b in scene.boxes)
    )


def cast_rays(scene, origin_m, directions, max_range_m):
    """Distance along each unit direction to the first box surface (inf where nothing is hit).

    The slab test one axis at a time on 1-D arrays: the same arithmetic as on (N, 3) arrays, so
    the same distances, without numpy's slow reductions over a 3-wide axis."""
    origin = np.asarray(origin_m, dtype=np.float64)
    dirs = np.asarray(directions, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = [np.ascontiguousarray(1.0 / dirs[:, axis]) for axis in range(3)]
    best = np.full(len(dirs), np.inf)
    for box in scene.boxes:
        lo = np.asarray(box.min_m) - origin
        hi = np.asarray(box.max_m) - origin
        t_near, t_far = None, None
        for axis in range(3):
            with np.errstate(invalid="ignore"):
                t1, t2 = lo[axis] * inv[axis], hi[axis] * inv[axis]
            t1[np.isnan(t1)] = -np.inf
            t2[np.isnan(t2)] = np.inf
            near, far = np.minimum(t1, t2), np.maximum(t1, t2)
            t_near = near if t_near is None else np.maximum(t_near, near, out=t_near)
            t_far = far if t_far is None else np.minimum(t_far, far, out=t_far)
        inside = np.all((origin >= np.asarray(box.min_m)) & (origin <= np.asarray(box.max_m)))
        t_hit = t_far if inside else t_near
        valid = (t_far >= np.maximum(t_near, 0.0)) & (t_hit > 1e-6)
        best = np.where(valid & (t_hit < best), t_hit, best)
    best[best > max_range_m] = np.inf
    return best


def rotation_z(yaw_rad):
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# Optical frame (z forward, x right, y down) to a body frame looking along +x.
OPTICAL_TO_BODY = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def depth_camera_cloud(scene, origin_m, yaw_rad, width=640, height=480, hfov_deg=60.0, far_m=18.0):
    """Points (map frame) a pinhole depth camera at `origin_m` looking along `yaw_rad` sees."""
    f = (width / 2) / np.tan(np.radians(hfov_deg) / 2)
    u, v = np.meshgrid(np.arange(width) + 0.5 - width / 2, np.arange(height) + 0.5 - height / 2)
    optical = np.stack([u.ravel() / f, v.ravel() / f, np.ones(u.size)], axis=1)
    rot = rotation_z(yaw_rad) @ OPTICAL_TO_BODY
    rays = optical @ rot.T
    depth_along_z = cast_rays(scene, origin_m, rays, far_m * np.sqrt(1 + (u.ravel() ** 2 + v.ravel() ** 2) / f**2))
    keep = np.isfinite(depth_along_z)
    return np.asarray(origin_m) + rays[keep] * depth_along_z[keep, None]


def lidar_cloud(
    scene, origin_m, yaw_rad=0.0, rings=16, samples_per_ring=1875, vertical_fov_deg=30.0, max_range_m=100.0
):
    """Points (map frame) of a spinning multi-ring lidar at `origin_m`."""
    elev = np.radians(np.linspace(-vertical_fov_deg / 2, vertical_fov_deg / 2, rings))
    azim = np.linspace(0.0, 2 * np.pi, samples_per_ring, endpoint=False) + yaw_rad
    e, a = np.meshgrid(elev, azim, indexing="ij")
    dirs = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1).reshape(-1, 3)
    dist = cast_rays(scene, origin_m, dirs, max_range_m)
    keep = np.isfinite(dist)
    return np.asarray(origin_m) + dirs[keep] * dist[keep, None]


def voxel_downsample(points, leaf_m):
    """Centroid of the points in each leaf_m voxel, as pcl's VoxelGrid (what the tissue sends)."""
    keys = np.floor(points / leaf_m).astype(np.int64)
    # One int64 per voxel (21 bits an axis, offset to be positive) sorts as the rows do: the same
    # voxels in the same order as np.unique(keys, axis=0), which sorts structured rows slowly.
    packed = ((keys[:, 0] + _KEY_OFFSET) << 42) | ((keys[:, 1] + _KEY_OFFSET) << 21) | (keys[:, 2] + _KEY_OFFSET)
    _, inverse, counts = np.unique(packed, return_inverse=True, return_counts=True)
    # bincount adds each voxel's points in their order, as np.add.at did: the same sums
    sums = np.stack([np.bincount(inverse, weights=points[:, axis], minlength=len(counts)) for axis in range(3)], 1)
    return sums / counts[:, None]


_KEY_OFFSET = 1 << 20  # voxel indices within +-2^20 (100 km at 0.1 m)


def to_sensor_frame(points_map, origin_m, rotation):
    """Map-frame points into a sensor frame whose pose in map is (origin_m, rotation)."""
    return (np.asarray(points_map) - np.asarray(origin_m)) @ np.asarray(rotation)


def trajectory(start_m, end_m, n):
    """n poses evenly spaced on a straight line, yaw along the line."""
    start, end = np.asarray(start_m, float), np.asarray(end_m, float)
    yaw = float(np.arctan2(end[1] - start[1], end[0] - start[0]))
    return [(start + (end - start) * (i / max(n - 1, 1)), yaw) for i in range(n)]


def robot_clouds(scene, kind, poses, leaf_m) -> Dict[str, list]:
    """(points_map, origin) per pose for a 'depth' or 'lidar' robot, voxelized as the tissue does."""
    clouds = []
    for origin, yaw in poses:
        pts = depth_camera_cloud(scene, origin, yaw) if kind == "depth" else lidar_cloud(scene, origin, yaw)
        clouds.append((voxel_downsample(pts, leaf_m), np.asarray(origin, float)))
    return clouds
