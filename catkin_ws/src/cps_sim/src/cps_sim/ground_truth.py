"""Ground truth for map scoring: the hall's occupied voxels on OctoMap's grid.

A voxel is occupied when the surface of a solid (floor top, walls, fences, equipment) passes
through it; voxel centres are (floor(p / res) + 0.5) * res in `map`, as OctoMap keys them.
The floor is included: its top surface z = 0 lies in the voxel layer just below z = 0
(centres at z = -res / 2), because the floor slab is the solid below that plane.
"""
import numpy as np

from cps_sim.geometry import surface_points


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
    np.savez_compressed(path, resolution_m=float(resolution_m), occupied_centers_m=centers,
                        includes_floor=bool(include_floor), site_path=str(site.path))
    return centers
