"""Ground truth for map scoring: the hall's occupied voxels on OctoMap's grid.

A voxel is occupied when the surface of a solid (floor top, walls, fences, equipment) passes
through it; voxel centres are (floor(p / res) + 0.5) * res in `map`, as OctoMap keys them.
The floor is included: its top surface z = 0 lies in the voxel layer just below z = 0
(centres at z = -res / 2), because the floor slab is the solid below that plane.
"""

import numpy as np

from cps_sim.geometry import surface_points
from cps_sim.line_of_sight import march_is_clear


def occupied_voxels(site, resolution_m, include_floor=True):
    """(N, 3) float64 centres of the occupied surface voxels of `site`, sorted, unique."""
    if not resolution_m > 0:
        raise ValueError(f"resolution_m must be positive, got {resolution_m}")
    spacing = resolution_m / 3.0
    keys = []
    for prim in site.primitives():
        if prim.owner == "floor":
            if not include_floor:
                continue
            h = site.hall
            xs = np.arange(h.x_min_m, h.x_max_m, spacing)
            ys = np.arange(h.y_min_m, h.y_max_m, spacing)
            gx, gy = np.meshgrid(xs, ys, indexing="ij")
            pts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, -1e-6)], axis=1)
        else:
            pts = surface_points(prim, spacing)
        keys.append(np.unique(np.floor(pts / resolution_m).astype(np.int64), axis=0))
    unique = np.unique(np.vstack(keys), axis=0)
    return (unique.astype(np.float64) + 0.5) * resolution_m


def save_ground_truth(path, site, resolution_m, include_floor=True):
    """Write `path` (.npz): resolution_m, occupied_centers_m (N x 3, map), includes_floor."""
    centers = occupied_voxels(site, resolution_m, include_floor)
    np.savez_compressed(
        path,
        resolution_m=float(resolution_m),
        occupied_centers_m=centers,
        includes_floor=bool(include_floor),
        site_path=str(site.path),
    )
    return centers


def positions_every(positions_m, spacing_m):
    """The positions of a path at least `spacing_m` apart (the first always kept): ray-casting from
    every 0.5 s sample of a slow robot adds little but time."""
    pts = np.asarray(positions_m, dtype=np.float64).reshape(-1, 3)
    kept = []
    for p in pts[np.isfinite(pts).all(axis=1)]:
        if not kept or np.linalg.norm(p - kept[-1]) >= spacing_m:
            kept.append(p)
    return np.array(kept).reshape(-1, 3)


def observable_from_positions(truth_centers_m, resolution_m, sensor_positions_m, max_range_m):
    """The truth voxels in line of sight of at least one sensor position, within `max_range_m`.

    The simulator's ground truth ray-cast from where the sensors actually were, so the observable
    surface does not depend on the map being scored. Per position and truth voxel within range, a
    ray from the sensor to the voxel's nearest point is marched in half-voxel steps through the
    truth grid; the voxel is visible when no other truth voxel lies on the way. The sensor's field
    of view is not modelled (any direction counts): this surface is a superset of what a camera
    facing the direction it was facing could see, so coverage against it errs low, never high.
    """
    truth = np.asarray(truth_centers_m, dtype=np.float64).reshape(-1, 3)
    positions = np.asarray(sensor_positions_m, dtype=np.float64).reshape(-1, 3)
    if len(truth) == 0 or len(positions) == 0:
        return truth[:0]
    res = float(resolution_m)
    index = np.floor(truth / res).astype(np.int64)
    lo = index.min(axis=0) - 1
    dims = index.max(axis=0) - lo + 2
    occupied = np.zeros(tuple(dims), dtype=bool)
    occupied[tuple((index - lo).T)] = True
    seen = np.zeros(len(truth), dtype=bool)
    step_m = res / 2.0
    for origin in positions:
        # A sensor inside a truth voxel (on the floor, in a wall) sees nothing from there.
        start_cell = np.floor(origin / res).astype(np.int64) - lo
        if ((start_cell >= 0) & (start_cell < dims)).all() and occupied[tuple(start_cell)]:
            continue
        todo = np.flatnonzero(~seen & (np.linalg.norm(truth - origin, axis=1) <= max_range_m))
        # The voxel's point nearest the sensor: a ray to its centre would graze its neighbours.
        target = np.clip(origin, truth[todo] - res / 2, truth[todo] + res / 2)
        length = np.linalg.norm(target - origin, axis=1)
        seen[todo[march_is_clear(origin, target, length, occupied, lo, res, step_m)]] = True
    return truth[seen]
