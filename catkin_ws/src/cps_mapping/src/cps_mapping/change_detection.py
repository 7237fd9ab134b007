"""Monitoring (the paper's second phase, Fig. 1): what changed on a site between two missions.

`detect_changes(baseline, current, resolution_m)` compares the occupied voxels of a baseline map
with a new map of the same site:
- a voxel *appeared* if it is occupied now and no baseline voxel lies within
  `tolerance_voxels` of it (Chebyshev distance), and it *disappeared* the other way round; the
  tolerance absorbs the one-voxel jitter of surfaces seen from other viewpoints;
- where the other map's free space is given (`baseline_is_free`, `current_is_free`), a voxel
  only counts if the other map saw that place free: a surface seen for the first time is not a
  change, and neither is one the new mission did not look at. Between two OctoMaps "free" means
  firmly free (`free_max_probability`, default 0.25: with OctoMap's miss probability 0.4 at
  least three clouds' rays more than hits): a curved or slanted surface seen at a grazing angle
  is crossed by the rays of one or two clouds aimed past it and left weakly free, and when the
  next mission sees it face on (because what hid it moved) it must not count as appeared;
- changed voxels are grouped into 26-connected clusters; clusters smaller than
  `min_cluster_voxels` are noise. Each cluster has a centroid, an axis-aligned size and a
  volume (voxels x resolution^3).
"""

import dataclasses
import functools
import json
from typing import Callable, List, Optional

import numpy as np
from scipy import ndimage

from cps_mapping.fused_map import index_to_center, near_any, voxel_index


@dataclasses.dataclass
class Change:
    kind: str  # "appeared" or "disappeared"
    voxels: int
    centroid_m: tuple
    size_m: tuple  # extent along x, y, z
    volume_m3: float
    min_m: tuple
    max_m: tuple


def _index(centers, resolution_m):
    pts = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    return np.unique(voxel_index(pts, resolution_m), axis=0) if len(pts) else np.zeros((0, 3), np.int64)


def _clusters(index, kind, resolution_m, min_cluster_voxels):
    if len(index) == 0:
        return []
    lo = index.min(axis=0)
    grid = np.zeros(tuple(index.max(axis=0) - lo + 1), dtype=bool)
    local = index - lo
    grid[local[:, 0], local[:, 1], local[:, 2]] = True
    labels, count = ndimage.label(grid, structure=np.ones((3, 3, 3), dtype=bool))
    voxel_labels = labels[local[:, 0], local[:, 1], local[:, 2]]
    out = []
    for label in range(1, count + 1):
        members = index[voxel_labels == label]
        if len(members) < min_cluster_voxels:
            continue
        centers = index_to_center(members, resolution_m)
        lo_m = members.min(axis=0) * resolution_m
        hi_m = (members.max(axis=0) + 1) * resolution_m
        out.append(
            Change(
                kind=kind,
                voxels=int(len(members)),
                centroid_m=tuple(np.round(centers.mean(axis=0), 4).tolist()),
                size_m=tuple(np.round(hi_m - lo_m, 4).tolist()),
                volume_m3=float(len(members) * resolution_m**3),
                min_m=tuple(np.round(lo_m, 4).tolist()),
                max_m=tuple(np.round(hi_m, 4).tolist()),
            )
        )
    return sorted(out, key=lambda c: -c.voxels)


def detect_changes(
    baseline_centers_m,
    current_centers_m,
    resolution_m,
    tolerance_voxels=1,
    min_cluster_voxels=8,
    baseline_is_free: Optional[Callable] = None,
    current_is_free: Optional[Callable] = None,
) -> List[Change]:
    """Clusters of voxels that appeared or disappeared between two maps (see the module docstring)."""
    if tolerance_voxels < 0 or min_cluster_voxels < 1:
        raise ValueError("tolerance_voxels must be >= 0 and min_cluster_voxels >= 1")
    base = _index(baseline_centers_m, resolution_m)
    cur = _index(current_centers_m, resolution_m)
    appeared = cur[~near_any(cur, base, tolerance_voxels)]
    disappeared = base[~near_any(base, cur, tolerance_voxels)]
    if baseline_is_free is not None and len(appeared):
        appeared = appeared[baseline_is_free(index_to_center(appeared, resolution_m))]
    if current_is_free is not None and len(disappeared):
        disappeared = disappeared[current_is_free(index_to_center(disappeared, resolution_m))]
    return _clusters(appeared, "appeared", resolution_m, min_cluster_voxels) + _clusters(
        disappeared, "disappeared", resolution_m, min_cluster_voxels
    )


def detect_map_changes(baseline_map, current_map, free_max_probability=0.25, **kwargs) -> List[Change]:
    """detect_changes for two FusedLogOddsMaps, each one's firm free space (occupancy probability at
    most `free_max_probability`) vouching for the other's changes."""
    if abs(baseline_map.resolution_m - current_map.resolution_m) > 1e-9:
        raise ValueError("the two maps have different resolutions")
    return detect_changes(
        baseline_map.occupied_centers(),
        current_map.occupied_centers(),
        current_map.resolution_m,
        baseline_is_free=functools.partial(baseline_map.is_free, max_probability=free_max_probability),
        current_is_free=functools.partial(current_map.is_free, max_probability=free_max_probability),
        **kwargs,
    )


def write_report(changes: List[Change], path, baseline_name="baseline", current_name="current"):
    """A Markdown report (and a .json twin) of the changes; returns the Markdown path."""
    lines = [
        f"# Site changes: {current_name} against {baseline_name}",
        "",
        f"{sum(c.kind == 'appeared' for c in changes)} appeared, "
        f"{sum(c.kind == 'disappeared' for c in changes)} disappeared.",
        "",
        "| # | change | centroid x, y, z (m) | size x, y, z (m) | volume (m³) | voxels |",
        "|---|---|---|---|---|---|",
    ]
    for i, c in enumerate(changes, 1):
        lines.append(
            f"| {i} | {c.kind} | {', '.join(f'{v:.2f}' for v in c.centroid_m)} | "
            f"{', '.join(f'{v:.2f}' for v in c.size_m)} | {c.volume_m3:.3f} | {c.voxels} |"
        )
    with open(path, "w") as stream:
        stream.write("\n".join(lines) + "\n")
    with open(str(path).rsplit(".", 1)[0] + ".json", "w") as stream:
        json.dump([dataclasses.asdict(c) for c in changes], stream, indent=1)
    return path
