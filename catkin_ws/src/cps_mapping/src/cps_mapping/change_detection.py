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
import math
import os
from typing import Callable, List, Optional

import numpy as np
from scipy import ndimage

from cps_mapping.atomic_file import write_atomically
from cps_mapping.fused_map import index_to_center, pack_index, voxel_index
from cps_mapping.fused_map import near_any as _sparse_near_any


@dataclasses.dataclass
class Change:
    kind: str  # "appeared" or "disappeared"
    voxels: int
    centroid_m: tuple
    size_m: tuple  # extent along x, y, z
    volume_m3: float
    min_m: tuple
    max_m: tuple


def near_any(index, other_index, tolerance_voxels):
    """fused_map.near_any (a voxel of `other_index` within the Chebyshev tolerance of each of
    `index`) on a dense grid over both: one dilation instead of (2 t + 1)^3 set lookups (2 s for
    t = 2 on the hall's maps, 0.05 s this way)."""
    index = np.asarray(index, dtype=np.int64).reshape(-1, 3)
    other = np.asarray(other_index, dtype=np.int64).reshape(-1, 3)
    if not len(index) or not len(other):
        return np.zeros(len(index), dtype=bool)
    lo = np.minimum(index.min(axis=0), other.min(axis=0)) - tolerance_voxels
    hi = np.maximum(index.max(axis=0), other.max(axis=0)) + tolerance_voxels
    if np.prod(hi - lo + 1) > 50_000_000:  # maps far apart: the set lookups bound memory
        return _sparse_near_any(index, other, tolerance_voxels)
    grid = np.zeros(tuple(hi - lo + 1), dtype=bool)
    o = other - lo
    grid[o[:, 0], o[:, 1], o[:, 2]] = True
    if tolerance_voxels > 0:
        grid = ndimage.maximum_filter(grid, size=2 * tolerance_voxels + 1, mode="constant")
    i = index - lo
    return grid[i[:, 0], i[:, 1], i[:, 2]]


def _index(centers, resolution_m):
    pts = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    return np.unique(voxel_index(pts, resolution_m), axis=0) if len(pts) else np.zeros((0, 3), np.int64)


def _merge_boxes(index, labels, count, gap_voxels):
    """Relabel so that clusters whose voxel boxes are at most `gap_voxels` apart share a label."""
    lo = np.full((count + 1, 3), np.iinfo(np.int64).max)
    hi = np.full((count + 1, 3), np.iinfo(np.int64).min)
    np.minimum.at(lo, labels, index)
    np.maximum.at(hi, labels, index)
    parent = list(range(count + 1))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a in range(1, count + 1):
        for b in range(a + 1, count + 1):
            if np.all(lo[a] <= hi[b] + gap_voxels + 1) and np.all(lo[b] <= hi[a] + gap_voxels + 1):
                parent[root(b)] = root(a)
    return np.array([root(label) for label in range(count + 1)])[labels]


def _clusters(index, kind, resolution_m, min_cluster_voxels, merge_gap_voxels=0):
    """26-connected clusters of voxels; with `merge_gap_voxels` g, clusters at most 2 g empty voxels
    apart are one (an item's surface cut in two by the tolerance around something next to it)."""
    if len(index) == 0:
        return []
    lo = index.min(axis=0) - merge_gap_voxels
    grid = np.zeros(tuple(index.max(axis=0) - lo + 1 + merge_gap_voxels), dtype=bool)
    local = index - lo
    grid[local[:, 0], local[:, 1], local[:, 2]] = True
    cube = np.ones((3, 3, 3), dtype=bool)
    if merge_gap_voxels > 0:
        grid = ndimage.binary_dilation(grid, structure=cube, iterations=merge_gap_voxels)
    labels, count = ndimage.label(grid, structure=cube)
    voxel_labels = labels[local[:, 0], local[:, 1], local[:, 2]]
    if merge_gap_voxels > 0:  # and clusters whose boxes come within the gap: one item's faces
        voxel_labels = _merge_boxes(index, voxel_labels, count, 2 * merge_gap_voxels)
    out = []
    for label in range(1, count + 1):
        members = index[voxel_labels == label]
        if not len(members):
            continue
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


@dataclasses.dataclass(frozen=True)
class ChangeRules:
    """The evidence a change needs (docs/monitoring.md says which anchor each rule comes from).

    - `tolerance_voxels`: a voxel changed only if no voxel of the other map lies this near
      (Chebyshev); 1 voxel absorbs the jitter of a surface seen from another viewpoint.
    - `appeared_free_max_probability`: a voxel appeared only where the baseline saw firm free space
      (occupancy probability at most this; unknown never counts).
    - `disappeared_min_misses`: a baseline voxel disappeared only where the new mission's rays
      passed through it at least this many times net of hits (its log-odds at or below this many
      misses of the sensor model; 5 reaches OctoMap's free clamp 0.12 with miss 0.4).
    - `min_known_neighbours`: the other map must know (free, or occupied in both maps) at least
      this many of the 6 face neighbours of a changed voxel (DUFOMap's neighbourhood rule against
      single rays grazing past; 5, not 6: the neighbour inside a new item is often hidden from the
      baseline by the item's own front, as from every viewpoint of a map made from one side).
    - `min_viewpoints`: a disappeared cluster must be in line of sight through known free space, and
      within `max_view_range_m`, of sensor poses at least `viewpoint_separation_m` apart, this many
      (needs the mission's robot trails; not checked without them).
    - `min_cluster_voxels`: smaller clusters are noise (docs/monitoring.md derives the default).
    - `min_hits`: a changed voxel must have been seen occupied this many times net of misses in the
      map that holds it (OctoMap's log-odds; 1: any occupied voxel): a surface seen in one or two
      clouds, e.g. the floor seen with a lagging pose, is no equipment.
    - `merge_gap_voxels`: clusters of one kind at most twice this many empty voxels apart are one
      change (one item's surface, cut by the tolerance around what stands next to it).
    - `min_height_voxels`: a change must span at least this many voxels in height. The ground
      robots' lidars (+-15 deg) meet a horizontal surface thinner than a voxel (a 4 cm shelf board
      in a 10 cm voxel, a fence rail, a patch of floor) at a grazing angle: its voxel is both hit
      and passed through, and which way it ends depends on where the sensors stood, so a flat
      sheet one mission kept and the other carved free is no evidence (1: not checked; a change
      of something that thin is beyond what the grid can attest).
    """

    tolerance_voxels: int = 1
    min_cluster_voxels: int = 8
    appeared_free_max_probability: float = 0.25
    disappeared_min_misses: int = 3
    min_known_neighbours: int = 0
    min_viewpoints: int = 0
    merge_gap_voxels: int = 0
    min_hits: int = 1
    viewpoint_separation_m: float = 1.0
    max_view_range_m: float = 8.0
    min_height_voxels: int = 1

    def __post_init__(self):
        if self.tolerance_voxels < 0 or self.min_cluster_voxels < 1 or self.disappeared_min_misses < 1:
            raise ValueError("tolerance_voxels must be >= 0, min_cluster_voxels and disappeared_min_misses >= 1")
        if self.min_height_voxels < 1:
            raise ValueError("min_height_voxels must be >= 1")
        if not 0.0 < self.appeared_free_max_probability < 0.5:
            raise ValueError("appeared_free_max_probability must be in (0, 0.5)")


# What the twin reports by default: the strict rules of issue 25 (docs/monitoring.md).
TRUSTED_RULES = ChangeRules(
    tolerance_voxels=2,
    min_cluster_voxels=16,
    appeared_free_max_probability=0.25,
    disappeared_min_misses=3,
    min_known_neighbours=5,
    min_viewpoints=2,
    merge_gap_voxels=1,
    min_hits=3,
    min_height_voxels=2,
)


def misses_probability(misses, miss_probability):
    """The occupancy probability a fresh voxel has after `misses` net misses, less half a miss of
    slack (float32 log-odds and clamping): a voxel with at most this probability was missed that often."""
    logit = (misses - 0.5) * math.log(miss_probability / (1.0 - miss_probability))
    return 1.0 / (1.0 + math.exp(-logit))


_FACES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.int64)


def _neighbours_known(index, resolution_m, known_free, occupied_both, min_known):
    """True where at least `min_known` face neighbours of a voxel are known free in the other map or
    occupied in both."""
    if not len(index):
        return np.zeros(0, dtype=bool)
    known = np.zeros(len(index), dtype=np.int64)
    for face in _FACES:
        n = index + face
        known += known_free(index_to_center(n, resolution_m)) | near_any(n, occupied_both, 0)
    return known >= min_known


def detect_changes(
    baseline_centers_m,
    current_centers_m,
    resolution_m,
    tolerance_voxels=1,
    min_cluster_voxels=8,
    baseline_is_free: Optional[Callable] = None,
    current_is_free: Optional[Callable] = None,
    excluded: Optional[Callable] = None,
    baseline_known: Optional[Callable] = None,
    current_known: Optional[Callable] = None,
    disappeared_cluster_ok: Optional[Callable] = None,
    merge_gap_voxels=0,
    min_known_neighbours=6,
    baseline_firm: Optional[Callable] = None,
    current_firm: Optional[Callable] = None,
    min_height_voxels=1,
) -> List[Change]:
    """Clusters of voxels that appeared or disappeared between two maps (see the module docstring).
    `excluded(index)`: True for voxels no change may hold (the robots' swept volume);
    `baseline_known`/`current_known(points)`: known free there (the neighbourhood rule);
    `disappeared_cluster_ok(change)`: a last test of each disappeared cluster (the viewpoints);
    `baseline_firm`/`current_firm(points)`: the voxel was seen occupied firmly enough to count as gone/new;
    `min_height_voxels`: flatter clusters are dropped (ChangeRules says why)."""
    if tolerance_voxels < 0 or min_cluster_voxels < 1 or min_height_voxels < 1:
        raise ValueError("tolerance_voxels must be >= 0, min_cluster_voxels and min_height_voxels >= 1")
    base = _index(baseline_centers_m, resolution_m)
    cur = _index(current_centers_m, resolution_m)
    if excluded is not None:
        base, cur = base[~excluded(base)], cur[~excluded(cur)]
    appeared = cur[~near_any(cur, base, tolerance_voxels)]
    disappeared = base[~near_any(base, cur, tolerance_voxels)]
    if current_firm is not None and len(appeared):
        appeared = appeared[current_firm(index_to_center(appeared, resolution_m))]
    if baseline_firm is not None and len(disappeared):
        disappeared = disappeared[baseline_firm(index_to_center(disappeared, resolution_m))]
    if baseline_is_free is not None and len(appeared):
        appeared = appeared[baseline_is_free(index_to_center(appeared, resolution_m))]
    if current_is_free is not None and len(disappeared):
        disappeared = disappeared[current_is_free(index_to_center(disappeared, resolution_m))]
    if baseline_known is not None or current_known is not None:
        both = base[near_any(base, cur, 0)]
        if baseline_known is not None and len(appeared):
            appeared = appeared[_neighbours_known(appeared, resolution_m, baseline_known, both, min_known_neighbours)]
        if current_known is not None and len(disappeared):
            disappeared = disappeared[
                _neighbours_known(disappeared, resolution_m, current_known, both, min_known_neighbours)
            ]
    gone = _clusters(disappeared, "disappeared", resolution_m, min_cluster_voxels, merge_gap_voxels)
    if disappeared_cluster_ok is not None:
        gone = [c for c in gone if disappeared_cluster_ok(c)]
    found = _clusters(appeared, "appeared", resolution_m, min_cluster_voxels, merge_gap_voxels) + gone
    return [c for c in found if c.size_m[2] >= (min_height_voxels - 0.5) * resolution_m]


def sensor_positions(trails, separation_m):
    """The sensor positions of the robots' trails (cps_mapping.robot_bodies.RobotTrails), thinned
    greedily so that no two kept ones are closer than `separation_m`: each one a distinct viewpoint."""
    if trails is None:
        return np.zeros((0, 3))
    points = [p[:3, 3] for trail in trails.trails.values() for p in trail.snapshot()[1]]
    if not points:
        return np.zeros((0, 3))
    cells = np.unique(np.floor(np.asarray(points) / separation_m).astype(np.int64), axis=0)
    return (cells + 0.5) * separation_m  # one viewpoint per separation-sized cell


def viewpoints_of(change, positions, known_free, resolution_m, max_range_m):
    """How many of `positions` see the change's box centre through known free space within range:
    the segment from the sensor to the centre, stopped one voxel diagonal plus half the box's
    largest side short of it (the box's own surface), sampled every half voxel, must be free in the
    map that says the thing is gone. One free-space query for all positions."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if not len(positions):
        return 0
    target = (np.asarray(change.min_m) + change.max_m) / 2
    offset = target - positions
    distance = np.linalg.norm(offset, axis=1)
    stop = distance - math.sqrt(3) * resolution_m - max(change.size_m) / 2
    usable = (distance <= max_range_m) & (stop > 0)
    if not usable.any():
        return 0
    step = resolution_m / 2
    n = int(np.ceil(stop[usable].max() / step))
    t = resolution_m + step * np.arange(n)  # distance along each segment
    unit = offset[usable] / distance[usable, None]
    samples = positions[usable, None, :] + t[None, :, None] * unit[:, None, :]
    valid = t[None, :] < stop[usable, None]
    free = np.ones(valid.shape, dtype=bool)
    free[valid] = known_free(samples[valid])
    return int(np.sum(free.all(axis=1)))


class FrozenMap:
    """What change detection reads of a FusedLogOddsMap (its occupied voxels and free-space
    queries, as FusedLogOddsMap.is_free answers them), copied under the map lock in milliseconds so
    that the detection runs without it: run under the lock it took seconds on the loaded 2-core
    machine, and insertion waited (the maps went stale every detection period). Reads the map's
    log-odds as they are at the copy (FusedLogOddsMap.log_odds_copy)."""

    def __init__(self, fused):
        self.resolution_m, self.sensor_model = fused.resolution_m, fused.sensor_model
        self._occupied = fused.occupied_centers()
        box = fused.log_odds_copy()
        self._lo, self._dims, self._log_odds = box.lo, box.dims, box.log_odds

    def occupied_centers(self):
        return self._occupied

    def hit_levels(self):
        """(voxel index, level) of every occupied voxel: the net hits its log-odds stand for
        (level k if log-odds >= (k - 0.5) hit log-odds, capped at MAX_HIT_LEVEL)."""
        index = voxel_index(self._occupied, self.resolution_m)
        rel = index - self._lo
        log_odds = self._log_odds[np.ravel_multi_index(rel.T, self._dims)] if len(rel) else np.zeros(0, np.float32)
        hit = math.log(self.sensor_model.hit / (1.0 - self.sensor_model.hit))
        level = np.clip(np.floor(log_odds / hit + 0.5), 0, MAX_HIT_LEVEL).astype(np.uint8)
        return index, level

    def is_free(self, points_m, max_probability=0.5):
        if not 0.0 < max_probability < 1.0:
            raise ValueError(f"max_probability must be in (0, 1), got {max_probability}")
        pts = np.asarray(points_m, dtype=np.float32).astype(np.float64).reshape(-1, 3)
        rel = np.floor(pts * (1.0 / self.resolution_m)).astype(np.int64) - self._lo
        inside = np.all((rel >= 0) & (rel < self._dims), axis=1)
        out = np.zeros(len(pts), dtype=bool)
        if not inside.any() or not self._log_odds.size:
            return out
        log_odds = self._log_odds[np.ravel_multi_index(rel[inside].T, self._dims)]
        with np.errstate(invalid="ignore"):
            out[inside] = log_odds <= np.float32(math.log(max_probability / (1.0 - max_probability)))
        return out


MAX_MISS_LEVEL = 6
# OctoMap's clamp 0.97 with hit 0.7 stands for 4.1 net hits: 5 levels tell a saturated voxel.
MAX_HIT_LEVEL = 5


def hit_levels_path(map_path):
    return f"{map_path}.hits.npz"


def write_hit_levels(map_path, frozen):
    """Beside a saved map (`<map>.hits.npz`): how firmly each occupied voxel was seen (FrozenMap.hit_levels);
    a .bt keeps only occupied/free, and a surface seen in one or two clouds (e.g. the floor seen
    with a lagging pose) must not count as firmly as one seen all mission long."""
    index, level = frozen.hit_levels()
    return write_atomically(
        hit_levels_path(map_path),
        lambda stream: np.savez_compressed(stream, index=index.astype(np.int32), level=level),
    )


class VoxelLevels:
    """A saved (voxel index, level) table (hit or miss levels): `at_least(points, level)`."""

    def __init__(self, index, level):
        packed = pack_index(np.asarray(index, dtype=np.int64).reshape(-1, 3))
        order = np.argsort(packed)
        self.packed, self.level = packed[order], np.asarray(level)[order]

    @classmethod
    def load(cls, path):
        with np.load(path) as data:
            return cls(data["index"], data["level"])

    def at_least(self, points, resolution_m, level):
        packed = pack_index(voxel_index(np.asarray(points).reshape(-1, 3), resolution_m))
        if not len(self.packed):
            return np.zeros(len(packed), dtype=bool)
        at = np.clip(np.searchsorted(self.packed, packed), 0, len(self.packed) - 1)
        return (self.packed[at] == packed) & (self.level[at] >= level)

    @classmethod
    def of_map(cls, map_path):
        """The hit levels saved beside a map, or None (a map saved before they were kept)."""
        path = hit_levels_path(map_path)
        return cls.load(path) if os.path.exists(path) else None


def miss_levels(baseline_map, current_map):
    """(voxel index (N, 3), level uint8) for every occupied voxel of the baseline: the largest number
    of net misses k <= MAX_MISS_LEVEL (0 if none) the current map's log-odds there stand for. A saved
    .bt keeps only occupied/free, so this is what the evidence rule needs of a finished mission."""
    centers = baseline_map.occupied_centers()
    index = _index(centers, baseline_map.resolution_m)
    points = index_to_center(index, baseline_map.resolution_m)
    level = np.zeros(len(index), dtype=np.uint8)
    for k in range(1, MAX_MISS_LEVEL + 1):
        p = misses_probability(k, current_map.sensor_model.miss)
        level[current_map.is_free(points, max_probability=p)] = k
    return index, level


def miss_levels_path(report_path):
    return str(report_path).rsplit(".", 1)[0] + "_miss_levels.npz"


def write_miss_levels(report_path, baseline_map, current_map):
    """miss_levels beside the live report (`<report>_miss_levels.npz`), replaced atomically."""
    index, level = miss_levels(baseline_map, current_map)
    return write_atomically(
        miss_levels_path(report_path),
        lambda stream: np.savez_compressed(stream, index=index.astype(np.int32), level=level),
    )


def _firm(fused, levels, min_hits):
    """points -> occupied with at least `min_hits` net hits, from saved levels or a FrozenMap; None
    (no test) for min_hits <= 1 or a map without either."""
    if min_hits <= 1:
        return None
    if levels is not None:
        return functools.partial(levels.at_least, resolution_m=fused.resolution_m, level=min_hits)
    if isinstance(fused, FrozenMap):
        levels = VoxelLevels(*fused.hit_levels())
        return functools.partial(levels.at_least, resolution_m=fused.resolution_m, level=min_hits)
    return None


def detect_map_changes(
    baseline_map,
    current_map,
    free_max_probability=None,
    rules: Optional[ChangeRules] = None,
    swept=None,
    current_trails=None,
    current_misses=None,
    baseline_hits=None,
    current_hits=None,
    **kwargs,
) -> List[Change]:
    """detect_changes for two FusedLogOddsMaps under `rules` (ChangeRules; keyword arguments
    override its fields): `swept` (robot_bodies.SweptVolume) is excluded, `current_trails` give the
    viewpoints of the monitoring mission; `current_misses` (VoxelLevels of miss levels) stands for the current map's
    log-odds at the baseline's voxels when the current map was read from a .bt; `baseline_hits`,
    `current_hits` (VoxelLevels) how firmly each map's occupied voxels were seen (the current one's
    from its own log-odds when it is a FrozenMap)."""
    if abs(baseline_map.resolution_m - current_map.resolution_m) > 1e-9:
        raise ValueError("the two maps have different resolutions")
    rules = dataclasses.replace(rules or ChangeRules(), **kwargs)
    if free_max_probability is not None:
        rules = dataclasses.replace(rules, appeared_free_max_probability=free_max_probability)
    res = current_map.resolution_m
    miss = current_map.sensor_model.miss if hasattr(current_map, "sensor_model") else 0.4
    gone_probability = min(rules.appeared_free_max_probability, misses_probability(rules.disappeared_min_misses, miss))
    if free_max_probability is not None:
        gone_probability = free_max_probability
    cluster_ok = None
    if rules.min_viewpoints > 0 and current_trails is not None:
        positions = sensor_positions(current_trails, rules.viewpoint_separation_m)
        known = functools.partial(current_map.is_free, max_probability=0.5)

        def cluster_ok(change):
            return viewpoints_of(change, positions, known, res, rules.max_view_range_m) >= rules.min_viewpoints

    return detect_changes(
        baseline_map.occupied_centers(),
        current_map.occupied_centers(),
        res,
        tolerance_voxels=rules.tolerance_voxels,
        min_cluster_voxels=rules.min_cluster_voxels,
        baseline_is_free=functools.partial(baseline_map.is_free, max_probability=rules.appeared_free_max_probability),
        current_is_free=functools.partial(current_map.is_free, max_probability=gone_probability)
        if current_misses is None
        else functools.partial(current_misses.at_least, resolution_m=res, level=rules.disappeared_min_misses),
        baseline_firm=_firm(baseline_map, baseline_hits, rules.min_hits),
        current_firm=_firm(current_map, current_hits, rules.min_hits),
        excluded=swept.contains if swept is not None and len(swept) else None,
        baseline_known=functools.partial(baseline_map.is_free, max_probability=0.5)
        if rules.min_known_neighbours
        else None,
        current_known=functools.partial(current_map.is_free, max_probability=0.5)
        if rules.min_known_neighbours
        else None,
        min_known_neighbours=rules.min_known_neighbours,
        disappeared_cluster_ok=cluster_ok,
        merge_gap_voxels=rules.merge_gap_voxels,
        min_height_voxels=rules.min_height_voxels,
    )


def write_report(changes: List[Change], path, baseline_name="baseline", current_name="current", tracker=None):
    """A Markdown report (and a .json twin) of the changes; returns the Markdown path. With a
    `tracker` (change_tracking.ChangeTracker) the .json also holds when each change was first found
    and reported (s, the map server's clock), and the withdrawn ones."""
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
    rows = [dataclasses.asdict(c) for c in changes]
    if tracker is not None:
        for row, t in zip(rows, tracker.reported()):
            row.update(first_seen_s=t.first_seen_s, reported_s=t.reported_s, cycles=t.cycles)
        rows += [
            {
                **dataclasses.asdict(t.change),
                "withdrawn": True,
                "first_seen_s": t.first_seen_s,
                "reported_s": t.reported_s,
            }
            for t in tracker.withdrawn
        ]
    with open(str(path).rsplit(".", 1)[0] + ".json", "w") as stream:
        json.dump(rows, stream, indent=1)
    return path
