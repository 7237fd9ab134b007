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
  volume (voxels x resolution^3);
- a disappeared and an appeared cluster that are one item moved become one *moved* change
  (`pair_moves`): the horizontal shift that lays the baseline's voxels around the disappeared
  cluster onto the new map's around the appeared one, found by correlation, explains both;
- with the new map's first-seen stamps (`seen_s`), each change says when the first cloud that
  saw its place was taken (`first_view_s`).
"""

import dataclasses
import functools
import json
import math
import os
import zipfile
from typing import Callable, List, Optional

import numpy as np
from scipy import ndimage

from cps_mapping.atomic_file import write_atomically
from cps_mapping.fused_map import index_to_center, pack_index, voxel_index
from cps_mapping.fused_map import near_any as _sparse_near_any


@dataclasses.dataclass
class Change:
    kind: str  # "appeared", "disappeared" or "moved"
    voxels: int
    centroid_m: tuple
    size_m: tuple  # extent along x, y, z
    volume_m3: float
    min_m: tuple
    max_m: tuple
    # When the first cloud that saw the change's place was taken (s, the clouds' clock), if known.
    first_view_s: Optional[float] = None
    # A move: the box is the item where it stands now; it was displaced by this (m) from `from_m`
    # (the centre of its box before).
    displacement_m: Optional[tuple] = None
    from_m: Optional[tuple] = None

    @property
    def place_m(self):
        """(x, y) of the change: the centre of its box (a surface seen from one side pulls the
        voxels' mean toward that side)."""
        return ((self.min_m[0] + self.max_m[0]) / 2, (self.min_m[1] + self.max_m[1]) / 2)

    @classmethod
    def from_dict(cls, doc):
        """A change as `dataclasses.asdict` wrote it (a report's .json), other keys ignored."""
        fields = {f.name for f in dataclasses.fields(cls)}
        kept = {k: tuple(v) if isinstance(v, list) else v for k, v in doc.items() if k in fields}
        return cls(**kept)


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


def _box_gap(lo, hi, a, b):
    """Empty voxels between the boxes of labels a and b along the axis where they are farthest apart
    (<= 0: they touch or overlap)."""
    return int(np.max(np.maximum(lo[a] - hi[b], lo[b] - hi[a]))) - 1


def _connected_through(support, a_members, b_members, floor_z, margin_voxels=2):
    """True if two clusters' voxels are one 26-connected piece of `support` (the occupied voxels of
    the map that holds them) above the floor, within their joint box grown by `margin_voxels`: one
    item of that map (two faces of it, or a sliver and the rest of it), not two items side by side.
    The floor (its layer and the one above, as in a move's correlation) joins everything and is left out."""
    both = np.vstack([a_members, b_members])
    lo, hi = both.min(axis=0) - margin_voxels, both.max(axis=0) + margin_voxels
    lo[2] = max(lo[2], floor_z + _FLOOR_LAYERS + 1)
    if np.any(hi < lo):
        return False
    a_members = a_members[a_members[:, 2] >= lo[2]]
    b_members = b_members[b_members[:, 2] >= lo[2]]
    if not len(a_members) or not len(b_members):
        return False
    region = np.vstack([_region(support, lo, hi), a_members, b_members]) - lo
    grid = np.zeros(tuple(hi - lo + 1), dtype=bool)
    grid[region[:, 0], region[:, 1], region[:, 2]] = True
    labels, _ = ndimage.label(grid, structure=np.ones((3, 3, 3), dtype=bool))
    a_labels = labels[tuple((a_members - lo).T)]
    b_labels = labels[tuple((b_members - lo).T)]
    return bool(np.intersect1d(a_labels, b_labels).size)


def _merge_boxes(index, labels, count, gap_voxels, support=None, floor_z=0, min_voxels=1, item_gap_voxels=0):
    """Relabel so that clusters that are one item share a label: clusters whose voxel boxes are at
    most `gap_voxels` apart, and, if one of them holds at least `min_voxels`, at most
    `item_gap_voxels` apart; with `support` (the occupied voxels of the map that holds the clusters)
    only if their voxels are connected through it (`_connected_through`).

    Without that test two items side by side were one change: seed 5077's fleet_1 had drum_3
    (removed) and tank_2 (moved) 0.2 m apart, their disappeared clusters' boxes within the gap, and
    reported them as one, the drum missed. With it, slivers of one item farther apart are one change:
    the second slivers of crate_2's new place (pair_2), of new_box_1 (fleet_1) and a board of moved
    shelving_2 (fleet_2) were each reported as a false 'appeared'."""
    lo = np.full((count + 1, 3), np.iinfo(np.int64).max)
    hi = np.full((count + 1, 3), np.iinfo(np.int64).min)
    np.minimum.at(lo, labels, index)
    np.maximum.at(hi, labels, index)
    sizes = np.bincount(labels, minlength=count + 1)
    parent = list(range(count + 1))
    members = {}

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    def of(label):
        if label not in members:
            members[label] = index[labels == label]
        return members[label]

    for a in range(1, count + 1):
        for b in range(a + 1, count + 1):
            if not sizes[a] or not sizes[b] or root(a) == root(b):
                continue
            gap = _box_gap(lo, hi, a, b)
            near = gap <= gap_voxels or (max(sizes[a], sizes[b]) >= min_voxels and gap <= item_gap_voxels)
            if not near:
                continue
            if support is None or _connected_through(support, of(a), of(b), floor_z):
                parent[root(b)] = root(a)
    return np.array([root(label) for label in range(count + 1)])[labels]


def _change_of(kind, members, resolution_m, **extra):
    """The Change of a cluster of voxel indices."""
    centers = index_to_center(members, resolution_m)
    lo_m = members.min(axis=0) * resolution_m
    hi_m = (members.max(axis=0) + 1) * resolution_m
    return Change(
        kind=kind,
        voxels=int(len(members)),
        centroid_m=tuple(np.round(centers.mean(axis=0), 4).tolist()),
        size_m=tuple(np.round(hi_m - lo_m, 4).tolist()),
        volume_m3=float(len(members) * resolution_m**3),
        min_m=tuple(np.round(lo_m, 4).tolist()),
        max_m=tuple(np.round(hi_m, 4).tolist()),
        **extra,
    )


def _clusters(index, kind, resolution_m, min_cluster_voxels, merge_gap_voxels=0, support=None, floor_z=0):
    """[(Change, its voxel indices)]: 26-connected clusters of voxels; with `merge_gap_voxels` g,
    clusters at most 2 g empty voxels apart are one (an item's surface cut in two by the tolerance
    around something next to it), and so are clusters whose boxes come within 2 g voxels, or within
    ITEM_GAP_M of a cluster of at least `min_cluster_voxels`, if `support` (the occupied voxel
    indices of the map that holds them) connects them above the floor (`floor_z`, its voxel layer):
    `_merge_boxes`."""
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
        item_gap = int(round(ITEM_GAP_M / resolution_m)) if support is not None else 0
        voxel_labels = _merge_boxes(
            index, voxel_labels, count, 2 * merge_gap_voxels, support, floor_z, min_cluster_voxels, item_gap
        )
    out = []
    for label in range(1, count + 1):
        members = index[voxel_labels == label]
        if not len(members):
            continue
        if len(members) < min_cluster_voxels:
            continue
        out.append((_change_of(kind, members, resolution_m), members))
    return sorted(out, key=lambda cm: -cm[0].voxels)


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
    - `sheet_min_incidence_deg`: a change that is a thin sheet (`sheet_axis`: a shelf board, a
      patch of floor) needs its `min_viewpoints` from lines of sight that meet its plane at least
      this steeply, in the map that says it is not there (the new mission's for a disappeared
      sheet, the baseline mission's for an appeared one): rays at a grazing angle cross the voxels
      of a thin surface without touching it, and carve it out of one mission's map and not the
      other's (docs/monitoring.md; 0: not checked).
    - `move_radius_m`: a disappeared and an appeared cluster this near (box centres) that one
      horizontal shift explains (at least `move_min_explained` of each) are one moved item
      (`pair_moves`; 0: never paired).
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
    move_radius_m: float = 0.0
    move_min_explained: float = 0.6
    sheet_min_incidence_deg: float = 0.0

    def __post_init__(self):
        if self.tolerance_voxels < 0 or self.min_cluster_voxels < 1 or self.disappeared_min_misses < 1:
            raise ValueError("tolerance_voxels must be >= 0, min_cluster_voxels and disappeared_min_misses >= 1")
        if not 0.0 < self.appeared_free_max_probability < 0.5:
            raise ValueError("appeared_free_max_probability must be in (0, 0.5)")


# Clusters of one kind whose boxes are at most this far apart, one of them a change's size, are one
# change when the map that holds them connects them above the floor (`_merge_boxes`): the slivers of
# one item (a 3 m shelving's boards, a moved crate's sides), not two items (the generator keeps them
# 0.2 m apart, and the map's free space between them).
ITEM_GAP_M = 1.5

# How far apart (box centres) a move's two halves may be: the longest item of the hall (a 4 m pipe
# run) moved by its own length leaves slivers 4 m apart.
MOVE_RADIUS_M = 5.0

# A moved item is at most this long along x or y (`_whole_item`): the hall's longest (a 4 m pipe run)
# and a voxel each end; what reaches further is structure (a wall, the fence), not an item moved.
ITEM_MAX_M = 4.2

# A thin surface seen at incidence theta: each ray crosses ~1/tan(theta) voxels of the surface's
# layer and meets the surface in one of them, the others get a miss. With OctoMap's hit 0.7 / miss
# 0.4 (log-odds +0.85 / -0.41) a surface still there stays occupied while 1/tan(theta) - 1 < 2.1
# (theta > 18 deg) and is carved free below; 30 deg (0.7 misses per hit) keeps a margin. A lidar
# (+-15 deg) never sees a horizontal sheet that steeply: only a view from above or below does.
SHEET_MIN_INCIDENCE_DEG = 30.0
# An appeared sheet: the baseline saw its place free from at least this many steep viewpoints (a
# disappeared one needs `min_viewpoints` of the new mission, issue 25's rule for every disappearance).
APPEARED_SHEET_VIEWPOINTS = 1
# A sheet: at most this many voxels thick, at least SHEET_ASPECT times longer along both other axes.
SHEET_MAX_VOXELS = 2
SHEET_ASPECT = 3
# The viewpoint rule draws lines of sight to at most this many of a cluster's voxels (spread over
# it): a position sees the cluster if one of them is clear.
MAX_SIGHT_TARGETS = 64

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
    move_radius_m=MOVE_RADIUS_M,
    sheet_min_incidence_deg=SHEET_MIN_INCIDENCE_DEG,
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
    appeared_cluster_ok: Optional[Callable] = None,
    merge_gap_voxels=0,
    min_known_neighbours=6,
    baseline_firm: Optional[Callable] = None,
    current_firm: Optional[Callable] = None,
    seen_s: Optional[Callable] = None,
    move_radius_m=0.0,
    move_min_explained=0.6,
    baseline_hit_index=None,
    current_hit_index=None,
) -> List[Change]:
    """Clusters of voxels that appeared or disappeared between two maps (see the module docstring).
    `excluded(index)`: True for voxels no change may hold (the robots' swept volume);
    `baseline_known`/`current_known(points)`: known free there (the neighbourhood rule);
    `disappeared_cluster_ok(change, members_m)`, `appeared_cluster_ok(change, members_m)`: a last test of
    each cluster, given its voxels' centres (the viewpoints);
    `baseline_firm`/`current_firm(points)`: the voxel was seen occupied firmly enough to count as gone/new;
    `seen_s(points)`: when the new map first saw each point's voxel (each change's first view);
    `move_radius_m` > 0: pair moves within it (`pair_moves`, with `move_min_explained`);
    `baseline_hit_index`/`current_hit_index`: the voxels each map's robots ever hit (FusedLogOddsMap.hit_index):
    nothing appeared (disappeared) within the tolerance of a voxel the baseline (new) mission ever hit."""
    if tolerance_voxels < 0 or min_cluster_voxels < 1:
        raise ValueError("tolerance_voxels must be >= 0 and min_cluster_voxels >= 1")
    base = _index(baseline_centers_m, resolution_m)
    cur = _index(current_centers_m, resolution_m)
    if excluded is not None:
        base, cur = base[~excluded(base)], cur[~excluded(cur)]
    appeared = cur[~near_any(cur, base, tolerance_voxels)]
    disappeared = base[~near_any(base, cur, tolerance_voxels)]
    # A voxel a mission's sensor ever hit held something during that mission: the rays that crossed
    # it later may have passed beside a thin surface inside it (DUFOMap: void only where never hit).
    if baseline_hit_index is not None and len(appeared):
        appeared = appeared[~near_any(appeared, baseline_hit_index, tolerance_voxels)]
    if current_hit_index is not None and len(disappeared):
        disappeared = disappeared[~near_any(disappeared, current_hit_index, tolerance_voxels)]
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
    floor_z = _floor_layer(base, cur) if merge_gap_voxels > 0 else 0
    gone = _clusters(disappeared, "disappeared", resolution_m, min_cluster_voxels, merge_gap_voxels, base, floor_z)
    if disappeared_cluster_ok is not None:
        gone = [(c, m) for c, m in gone if disappeared_cluster_ok(c, index_to_center(m, resolution_m))]
    new = _clusters(appeared, "appeared", resolution_m, min_cluster_voxels, merge_gap_voxels, cur, floor_z)
    if appeared_cluster_ok is not None:
        new = [(c, m) for c, m in new if appeared_cluster_ok(c, index_to_center(m, resolution_m))]
    if seen_s is not None:
        for change, members in new + gone:
            change.first_view_s = _earliest(seen_s(index_to_center(members, resolution_m)))
    if move_radius_m > 0:
        first_view = None
        if seen_s is not None:
            first_view = lambda members: _earliest(seen_s(index_to_center(members, resolution_m)))  # noqa: E731
        return pair_moves(
            new, gone, base, cur, resolution_m, move_radius_m, move_min_explained, min_cluster_voxels, first_view
        )
    return [c for c, _ in new + gone]


def _earliest(stamps):
    stamps = np.asarray(stamps, dtype=np.float64)
    stamps = stamps[np.isfinite(stamps)]
    return round(float(stamps.min()), 3) if len(stamps) else None


# Voxels at or below this layer above the floor are left out of a move's correlation: the floor is
# in both maps under every item and would pull the shift toward none.
_FLOOR_LAYERS = 1


def _region(index, lo, hi):
    return index[np.all((index >= lo) & (index <= hi), axis=1)]


def _layer_votes(votes, before, after):
    """Adds to `votes` ((dx, dy) -> count) each shift that lays a voxel of `before` onto one of
    `after` in the same layer."""
    for z in np.intersect1d(before[:, 2], after[:, 2]):
        b, a = before[before[:, 2] == z][:, :2], after[after[:, 2] == z][:, :2]
        d = (a[None, :, :] - b[:, None, :]).reshape(-1, 2)
        keys, counts = np.unique(d, axis=0, return_counts=True)
        for k, c in zip(map(tuple, keys), counts):
            votes[k] = votes.get(k, 0) + int(c)


def _best_shift(before, after, min_shift_voxels):
    """(shift (dx, dy) in voxels, sub-voxel refined, float; votes) that lays most of what moved onto
    the other map, in the same layer, at least `min_shift_voxels` long; None if none. What moved:
    `before`'s voxels that `after` has no longer (within a voxel), laid onto `after`, and `after`'s
    new voxels laid back onto `before`. What stood still casts no vote: seed 42507's pair_0 had a
    drum moved 1.8 m beside a 1.4 m tank, whose wall laid onto itself 2 voxels along won the
    correlation of the whole boxes (123 votes against the drum's), and the move was two changes."""
    gone = before[~near_any(before, after, 1)]
    new = after[~near_any(after, before, 1)]
    votes = {}
    _layer_votes(votes, gone, after)
    _layer_votes(votes, before, new)
    candidates = [(c, k) for k, c in votes.items() if max(abs(k[0]), abs(k[1])) >= min_shift_voxels]
    if not candidates:
        return None
    count, (dx, dy) = max(candidates)
    # the votes' mean over the peak's 3 x 3 neighbourhood: the shift between voxel steps
    near = [((dx + i, dy + j), votes.get((dx + i, dy + j), 0)) for i in (-1, 0, 1) for j in (-1, 0, 1)]
    weight = sum(w for _, w in near)
    refined = (sum(k[0] * w for k, w in near) / weight, sum(k[1] * w for k, w in near) / weight)
    return refined, (dx, dy), count


def _explained(index, shift, other, tolerance_voxels=1):
    """Fraction of `index`'s voxels that, shifted by `shift` (dx, dy), lie within the tolerance of `other`."""
    if not len(index) or not len(other):
        return 0.0
    moved = index + np.array([shift[0], shift[1], 0])
    return float(near_any(moved, other, tolerance_voxels).mean())


def pair_moves(
    appeared, disappeared, base, cur, resolution_m, radius_m, min_explained, min_cluster_voxels=1, first_view=None
):
    """The changes, with each disappeared and appeared cluster that are one item moved replaced by
    one "moved" change. `appeared`/`disappeared`: [(Change, voxel indices)]; `base`/`cur`: the
    two maps' occupied voxel indices (robots' volume left out); `first_view(members)`: the first
    view of a change split off a cluster (None: its cluster's).

    A pair within `radius_m` (box centres, horizontally) is a move when one horizontal shift, found
    by correlating what moved between the two maps over both clusters' boxes (one voxel around; the
    floor and shifts under 2 voxels left out: `_best_shift`), lays at least `min_explained` of the
    moved item's pieces of the disappeared cluster onto the new map and of the appeared one, shifted
    back, onto the baseline, and as much of one of the two whole clusters.
    A move shorter than the item leaves only slivers (the side it left and the side it took); the
    correlation still finds the whole item's shift, and the item's other slivers that the shift
    explains join the move (`_slivers_of`). A cluster's pieces that the shift does not explain are
    other items the grouping joined to it (`_other_items`): the size rule reads the moved item's
    pieces only, and the others stay changes of their own (at least `min_cluster_voxels`). Whether
    the move took the item clear of its old place reads the whole item (`_whole_item`: what the
    disappeared cluster is connected to and moved with it), not the slivers. Best pairs first."""
    appeared, disappeared = list(appeared), list(disappeared)  # paired clusters are replaced by their item's part
    floor_z = None
    candidates = []
    for i, (a, a_members) in enumerate(appeared):
        for j, (d, d_members) in enumerate(disappeared):
            if math.dist(a.place_m, d.place_m) > radius_m:
                continue
            if floor_z is None:
                floor_z = _floor_layer(base, cur)
            lo = np.minimum(a_members.min(axis=0), d_members.min(axis=0)) - 1
            hi = np.maximum(a_members.max(axis=0), d_members.max(axis=0)) + 1
            lo[2] = max(lo[2], floor_z + _FLOOR_LAYERS + 1)
            before, after = _region(base, lo, hi), _region(cur, lo, hi)
            if not len(before) or not len(after):
                continue
            shift = _best_shift(before, after, 2)
            if shift is None:
                continue
            refined, step, votes = shift
            a_item, a_others = _other_items(a_members, (-step[0], -step[1]), base, min_explained)
            d_item, d_others = _other_items(d_members, step, cur, min_explained)
            if not len(a_item) or not len(d_item):
                continue
            item = np.vstack([d_item, before[near_any(before + [step[0], step[1], 0], after, 1)]])

            def item_of(d_item=d_item, step=step, item=item):
                whole = _whole_item(d_item, base, cur, step, floor_z, int(round(ITEM_MAX_M / resolution_m)))
                return item if whole is None else whole

            if not _same_size(a_item, d_item, item_of, step, floor_z):
                continue
            back = (-step[0], -step[1])
            gone_ok, new_ok = _explained(d_members, step, cur), _explained(a_members, back, base)
            # The shift explains the moved item's pieces on both sides and one side's whole cluster:
            # the other may also hold an item added (or removed) beside the move. Seed 17645's pair_1
            # moved a crate and added a drum 0.3 m from its new side, as large in the map as the
            # crate's new faces: the 'appeared' cluster over both was half explained, the crate's
            # old place whole, and the move was two changes.
            items_ok = min(_explained(d_item, step, cur), _explained(a_item, back, base))
            if items_ok >= min_explained and max(gone_ok, new_ok) >= min_explained:
                split = ((a_item, a_others), (d_item, d_others))
                candidates.append((min(gone_ok, new_ok), votes, i, j, refined, step, before, after, split))
    used_a, used_d, pairs, split_off = set(), set(), [], []
    for _, _, i, j, refined, step, before, after, split in sorted(candidates, key=lambda c: (-c[0], -c[1])):
        if i in used_a or j in used_d:
            continue
        used_a.add(i)
        used_d.add(j)
        (a_item, a_others), (d_item, d_others) = split
        appeared[i] = _part_of(appeared[i][0], a_item, resolution_m, first_view)
        disappeared[j] = _part_of(disappeared[j][0], d_item, resolution_m, first_view)
        for parent, others in ((appeared[i][0], a_others), (disappeared[j][0], d_others)):
            for change, members in _clusters(others, parent.kind, resolution_m, min_cluster_voxels):
                change.first_view_s = first_view(members) if first_view else parent.first_view_s
                split_off.append(change)
        item = np.vstack([d_item, before[near_any(before + [step[0], step[1], 0], after, 1)]])
        pairs.append(([i], [j], refined, step, np.unique(item, axis=0)))
    for a_of, d_of, _, step, item in pairs:
        shift = np.array([step[0], step[1], 0])
        a_of += _slivers_of(appeared, used_a, item + shift, base, -shift, min_explained)
        d_of += _slivers_of(disappeared, used_d, item, cur, shift, min_explained)
    moves = [
        _move([appeared[i][0] for i in a_of], [disappeared[j][0] for j in d_of], refined, step, item, resolution_m)
        for a_of, d_of, refined, step, item in pairs
    ]
    rest = [c for k, (c, _) in enumerate(appeared) if k not in used_a]
    rest += [c for k, (c, _) in enumerate(disappeared) if k not in used_d]
    return moves + rest + split_off


def _whole_item(members, base, cur, step, floor_z, max_voxels):
    """The baseline's voxels of the whole item a disappeared cluster (`members`) is part of, moved by
    `step` (dx, dy voxels): its 26-connected component above the floor among the baseline's voxels
    that the shift lays onto the new map, within `max_voxels` of the cluster; None if that reaches
    further than `max_voxels` along x or y (structure, not an item). Seed 45756's fleet_1 moved a 3 m
    pipe run 0.67 m along its length: only its end posts changed, each clear of its old place, and
    the size rule of a clear move compared the two posts as whole items (one seen with its
    crossbar, one without) and refused the pair; the pipes the posts carry say the move is short."""
    lo, hi = members.min(axis=0) - max_voxels, members.max(axis=0) + max_voxels
    lo[2] = max(lo[2], floor_z + _FLOOR_LAYERS + 1)
    near = _region(base, lo, hi)
    carried = near[near_any(near + np.array([step[0], step[1], 0]), cur, 1)]
    voxels = np.unique(np.vstack([carried, members]), axis=0)
    origin = voxels.min(axis=0)
    local = voxels - origin
    grid = np.zeros(tuple(local.max(axis=0) + 1), dtype=bool)
    grid[tuple(local.T)] = True
    labels, _ = ndimage.label(grid, structure=np.ones((3, 3, 3), dtype=bool))
    ids = np.unique(labels[tuple((members - origin).T)])
    item = voxels[np.isin(labels[tuple(local.T)], ids[ids > 0])]
    extent = item.max(axis=0) - item.min(axis=0) + 1
    return None if max(extent[0], extent[1]) > max_voxels else item


def _other_items(members, shift, other, min_explained):
    """(the voxels of a cluster that are one moved item, the rest): its 26-connected pieces that
    `shift` (dx, dy) lays onto `other` (the other map) for at least `min_explained` of their voxels,
    and the pieces it does not (other items the grouping joined to it). Seed 51999's fleet_0 moved
    tank_4 and added a drum 0.3 m from its new side: the two were one 'appeared' cluster 2.4 m long,
    which the size rule of a clear move refused to pair with the tank's 1.6 m old place; the move and
    the drum were reported as a false 'appeared' and a false 'disappeared'."""
    if not len(members):
        return members, members
    lo = members.min(axis=0)
    local = members - lo
    grid = np.zeros(tuple(local.max(axis=0) + 1), dtype=bool)
    grid[tuple(local.T)] = True
    labels, count = ndimage.label(grid, structure=np.ones((3, 3, 3), dtype=bool))
    piece = labels[tuple(local.T)]
    laid = near_any(members + np.array([shift[0], shift[1], 0]), other, 1)
    explained = np.bincount(piece, weights=laid, minlength=count + 1) / np.maximum(
        np.bincount(piece, minlength=count + 1), 1
    )
    keep = explained[piece] >= min_explained
    return members[keep], members[~keep]


def _part_of(change, members, resolution_m, first_view):
    """(Change, members) of the part `members` of `change`'s cluster (all of it: `change` itself)."""
    if len(members) == change.voxels:
        return change, members
    part = _change_of(change.kind, members, resolution_m)
    part.first_view_s = first_view(members) if first_view else change.first_view_s
    return part, members


# A moved item's other slivers lie within its box (before or after the move) grown by this many voxels.
SLIVER_MARGIN_VOXELS = 2


def _slivers_of(clusters, used, item, other, shift, min_explained):
    """Indices of the clusters not in `used` (added to it) that are more slivers of one moved item:
    inside the box of `item` (its voxels where the cluster's map has it) grown by
    SLIVER_MARGIN_VOXELS, and laid by `shift` onto `other` (the other map) for at least
    `min_explained` of their voxels. Seed 42507's pair_4 moved shelving_1 0.5 m: its new front was
    two appeared clusters (its top board's voxels between them not in the new map), one was paired
    and the other reported as a false 'appeared'."""
    lo, hi = item.min(axis=0) - SLIVER_MARGIN_VOXELS, item.max(axis=0) + SLIVER_MARGIN_VOXELS
    out = []
    for k, (_, members) in enumerate(clusters):
        if k in used or not np.all((members >= lo) & (members <= hi)):
            continue
        if _explained(members, shift[:2], other) >= min_explained:
            used.add(k)
            out.append(k)
    return out


# A move that takes an item clear of its old place (the shift along some axis at least both clusters'
# extent) leaves two whole items: their tops within MOVE_TOP_VOXELS layers, their extents along x and
# y within MOVE_SIZE_VOXELS plus MOVE_SIZE_FRACTION of the larger (a surface's one-voxel jitter on
# either side).
MOVE_TOP_VOXELS = 1
MOVE_SIZE_VOXELS = 2
MOVE_SIZE_FRACTION = 0.15


def _same_size(a_members, d_members, item_of, step, floor_z):
    """True if an appeared and a disappeared cluster can be one item moved by `step` (dx, dy voxels);
    `item_of()`: the baseline's voxels of the item (asked only when the shift takes both clusters
    clear of themselves: `_whole_item` reads a region of the map). When the shift takes the item clear of where it stood, the two are the whole item before and
    after: the same height (their tops within MOVE_TOP_VOXELS layers) and the same extent along x
    and y. A shorter move leaves slivers (the side it left, the side it took), whose sizes are the
    move's and the views', not the item's: they are not compared. Seed 5077's fleet_5 paired
    crate_2 (1.0 x 1.0 x 1.0 m, removed) with a 0.77 x 0.92 x 1.15 m box added 4.2 m away: one
    shift explained 60 % of each within the one-voxel tolerance."""
    extent_a = a_members.max(axis=0) - a_members.min(axis=0) + 1
    extent_d = d_members.max(axis=0) - d_members.min(axis=0) + 1
    if not any(abs(step[k]) >= max(extent_a[k], extent_d[k]) for k in (0, 1)):
        return True
    item = item_of()
    extent_item = item.max(axis=0) - item.min(axis=0) + 1
    if not any(abs(step[k]) >= max(extent_a[k], extent_d[k], extent_item[k]) for k in (0, 1)):
        return True
    top_a, top_d = int(a_members[:, 2].max()) - floor_z, int(d_members[:, 2].max()) - floor_z
    if abs(top_a - top_d) > MOVE_TOP_VOXELS:
        return False
    for axis in (0, 1):
        larger = max(extent_a[axis], extent_d[axis])
        if abs(int(extent_a[axis]) - int(extent_d[axis])) > MOVE_SIZE_VOXELS + MOVE_SIZE_FRACTION * larger:
            return False
    return True


def _floor_layer(base, cur):
    """The floor's voxel layer: the lowest layer that holds many voxels of either map."""
    both = np.concatenate([base[:, 2], cur[:, 2]])
    if not len(both):
        return 0
    layers, counts = np.unique(both, return_counts=True)
    return int(layers[np.argmax(counts >= 0.5 * counts.max())])


def _move(appeared, disappeared, shift_voxels, step, item, resolution_m):
    """One "moved" change from its appeared and disappeared clusters (Changes): the item (its
    baseline voxels `item`: the disappeared clusters and what moved with them) now, displaced by
    `shift_voxels` (`step` rounded) from where it was."""
    now = _change_of("moved", item + [step[0], step[1], 0], resolution_m)
    displacement = np.array([shift_voxels[0], shift_voxels[1], 0.0]) * resolution_m
    old_box = _change_of("moved", item, resolution_m)
    now.voxels = sum(c.voxels for c in appeared + disappeared)
    now.volume_m3 = float(now.voxels * resolution_m**3)
    now.displacement_m = tuple(np.round(displacement, 4).tolist())
    now.from_m = tuple(np.round((np.asarray(old_box.min_m) + old_box.max_m) / 2, 4).tolist())
    views = [c.first_view_s for c in appeared + disappeared if c.first_view_s is not None]
    now.first_view_s = min(views) if views else None
    return now


def _seen_through(sources, fused, rules, resolution_m, every_cluster, min_viewpoints):
    """cluster -> True if `min_viewpoints` viewpoints saw it through `fused`'s known free space (a
    sheet only from steep enough: `rules.sheet_min_incidence_deg`); with `every_cluster` False a
    cluster that is no sheet passes untested. `sources`: a mission's
    SensorViews (the inserted clouds that had the cluster in view) or, for a map saved without them,
    its RobotTrails (every pose, wherever it looked)."""
    views = sources if hasattr(sources, "positions_seeing") else None
    positions = None if views is not None else sensor_positions(sources, rules.viewpoint_separation_m)
    known = functools.partial(fused.is_free, max_probability=0.5)

    def ok(change, members_m=None):
        if not every_cluster and sheet_axis(change, resolution_m) is None:
            return True
        here = positions
        if views is not None:
            target = (np.asarray(change.min_m) + change.max_m) / 2
            here = distinct_positions(
                views.positions_seeing(target, rules.max_view_range_m), rules.viewpoint_separation_m
            )
        seen = viewpoints_of(
            change, here, known, resolution_m, rules.max_view_range_m, rules.sheet_min_incidence_deg, members_m
        )
        return seen >= min_viewpoints

    return ok


def distinct_positions(points, separation_m):
    """One of the points per `separation_m` cell they fall in (the first): each a distinct
    viewpoint, where a sensor was (not the cell's centre, up to 0.87 cell away from any)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not len(points):
        return points
    _, first = np.unique(np.floor(points / separation_m).astype(np.int64), axis=0, return_index=True)
    return points[np.sort(first)]


def sensor_positions(trails, separation_m):
    """The sensor positions of the robots' trails (cps_mapping.robot_bodies.RobotTrails), one per
    `separation_m` cell: each one a distinct viewpoint."""
    if trails is None:
        return np.zeros((0, 3))
    points = [p[:3, 3] for trail in trails.trails.values() for p in trail.snapshot()[1]]
    return distinct_positions(points, separation_m)


def sheet_axis(change, resolution_m):
    """The axis (0, 1, 2) a change's box is thin along if it is a sheet (at most SHEET_MAX_VOXELS
    thick and at least SHEET_ASPECT times that along both other axes: a shelf board, a patch of
    floor, one face of an item), else None."""
    extent = np.round(np.asarray(change.size_m) / resolution_m).astype(int)
    axis = int(np.argmin(extent))
    others = np.delete(extent, axis)
    if extent[axis] <= SHEET_MAX_VOXELS and np.all(others >= SHEET_ASPECT * extent[axis]):
        return axis
    return None


def sight_targets(members_m, limit=MAX_SIGHT_TARGETS):
    """At most `limit` of a cluster's voxel centres (N, 3), spread over it: what the viewpoint rule
    draws lines of sight to."""
    members_m = np.asarray(members_m, dtype=np.float64).reshape(-1, 3)
    if len(members_m) <= limit:
        return members_m
    return members_m[np.unique(np.linspace(0, len(members_m) - 1, limit).round().astype(int))]


def viewpoints_of(
    change, positions, known_free, resolution_m, max_range_m, sheet_min_incidence_deg=0.0, members_m=None
):
    """How many of `positions` see the change through known free space within range: a segment from
    the sensor, sampled every half voxel, is free in the map that says the thing is gone, to the
    box centre stopped one voxel diagonal and half the box's largest side short of it (the box's own
    surface), or to one of the change's voxels (`members_m`, at most MAX_SIGHT_TARGETS of them:
    `sight_targets`) stopped one voxel diagonal short; a position counts if one of its segments is
    free. One free-space query per target for all positions. A sheet
    (`sheet_axis`) counts only segments that meet its plane at `sheet_min_incidence_deg` or more: a
    ray at a grazing angle passes through the voxels of a thin surface without touching it.

    Lines to the voxels, not only to the box centre: a sensor at the height of a thin rail between it and
    the change (a lidar at 0.7 m behind the storage fence's 0.6 m rail) had its one line to the
    centre run inside the rail's voxel layer, blocked by the 4 cm rail its own rays passed over; how
    many positions passed then depended on which of the rail's voxels the mission had hit (issue 39:
    crate_2's removal missed in a full test run, seen through the fence from 5 of 15 positions of one
    run and 3 of 12 of another)."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if not len(positions):
        return 0
    diagonal = math.sqrt(3) * resolution_m
    centre = (np.asarray(change.min_m) + change.max_m) / 2
    targets = [(centre, diagonal + max(change.size_m) / 2)]
    if members_m is not None:
        targets += [(voxel, diagonal) for voxel in sight_targets(members_m)]
    axis = sheet_axis(change, resolution_m) if sheet_min_incidence_deg > 0 else None
    seen = np.zeros(len(positions), dtype=bool)
    for target, short_m in targets:
        unseen = ~seen
        seen[unseen] = _clear_sight(
            positions[unseen], target, short_m, known_free, resolution_m, max_range_m, axis, sheet_min_incidence_deg
        )
        if seen.all():
            break
    return int(seen.sum())


def _clear_sight(positions, target, short_m, known_free, resolution_m, max_range_m, axis, min_incidence_deg):
    """Per position: the segment to `target`, stopped `short_m` short of it, is within range, steep
    enough on a sheet's plane (`axis`), and known free at every half-voxel sample."""
    offset = target - positions
    distance = np.linalg.norm(offset, axis=1)
    stop = distance - short_m
    usable = (distance <= max_range_m) & (stop > 0)
    if axis is not None:
        with np.errstate(invalid="ignore", divide="ignore"):
            usable &= np.abs(offset[:, axis]) >= math.sin(math.radians(min_incidence_deg)) * distance
    if not usable.any():
        return usable
    step = resolution_m / 2
    n = int(np.ceil(stop[usable].max() / step))
    t = resolution_m + step * np.arange(n)  # distance along each segment
    unit = offset[usable] / distance[usable, None]
    samples = positions[usable, None, :] + t[None, :, None] * unit[:, None, :]
    valid = t[None, :] < stop[usable, None]
    free = np.ones(valid.shape, dtype=bool)
    free[valid] = known_free(samples[valid])
    usable[usable] = free.all(axis=1)
    return usable


class FrozenMap:
    """What change detection reads of a FusedLogOddsMap (its occupied voxels and free-space
    queries, as FusedLogOddsMap.is_free answers them), copied under the map lock in milliseconds so
    that the detection runs without it: run under the lock it took seconds on the loaded 2-core
    machine, and insertion waited (the maps went stale every detection period). Reads the map's
    log-odds as they are at the copy (FusedLogOddsMap.log_odds_copy)."""

    def __init__(self, fused):
        self.resolution_m, self.sensor_model = fused.resolution_m, fused.sensor_model
        self._occupied = fused.occupied_centers()
        self._hit_index = fused.hit_index()
        box = fused.log_odds_copy()
        self._lo, self._dims, self._log_odds = box.lo, box.dims, box.log_odds
        self._first_seen = box.first_seen_s

    def occupied_centers(self):
        return self._occupied

    def hit_index(self):
        """FusedLogOddsMap.hit_index as at the copy."""
        return self._hit_index

    def hit_levels(self):
        """(voxel index, level) of every occupied voxel: the net hits its log-odds stand for
        (level k if log-odds >= (k - 0.5) hit log-odds, capped at MAX_HIT_LEVEL)."""
        index = voxel_index(self._occupied, self.resolution_m)
        rel = index - self._lo
        log_odds = self._log_odds[np.ravel_multi_index(rel.T, self._dims)] if len(rel) else np.zeros(0, np.float32)
        hit = math.log(self.sensor_model.hit / (1.0 - self.sensor_model.hit))
        level = np.clip(np.floor(log_odds / hit + 0.5), 0, MAX_HIT_LEVEL).astype(np.uint8)
        return index, level

    def _cells(self, points_m):
        """(flat cell, inside the box) of each point's voxel."""
        pts = np.asarray(points_m, dtype=np.float32).astype(np.float64).reshape(-1, 3)
        rel = np.floor(pts * (1.0 / self.resolution_m)).astype(np.int64) - self._lo
        inside = np.all((rel >= 0) & (rel < self._dims), axis=1)
        flat = np.zeros(len(pts), dtype=np.int64)
        if inside.any():
            flat[inside] = np.ravel_multi_index(rel[inside].T, self._dims)
        return flat, inside

    def first_seen_s(self, points_m):
        """When each point's voxel was first seen (FusedLogOddsMap.first_seen_s), as at the copy."""
        flat, inside = self._cells(points_m)
        out = np.full(len(flat), np.nan)
        if self._first_seen is not None:
            out[inside] = self._first_seen[flat[inside]]
        return out

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


# zlib level of the saved level tables: 1 compresses a reference mission's (50 k voxels) in 21 ms of
# CPU to 336 kB, numpy's savez_compressed (level 6) in 95 ms to 270 kB; the map server writes them at
# every autosave (2 s in the reference fleet) on the twin's CPU that inserts the clouds.
LEVELS_ZLIB_LEVEL = 1


def savez_fast(stream, **arrays):
    """np.savez_compressed's .npz (np.load reads it) at LEVELS_ZLIB_LEVEL."""
    with zipfile.ZipFile(stream, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=LEVELS_ZLIB_LEVEL) as archive:
        for name, array in arrays.items():
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=False)


def write_hit_levels(map_path, frozen):
    """Beside a saved map (`<map>.hits.npz`): how firmly each occupied voxel was seen (FrozenMap.hit_levels)
    and every voxel ever hit (`ever_hit`, FrozenMap.hit_index); a .bt keeps only occupied/free, and
    a surface seen in one or two clouds (e.g. the floor seen with a lagging pose) must not count as
    firmly as one seen all mission long."""
    index, level = frozen.hit_levels()
    ever = frozen.hit_index()
    return write_atomically(
        hit_levels_path(map_path),
        lambda stream: savez_fast(stream, index=index.astype(np.int32), level=level, ever_hit=ever.astype(np.int32)),
    )


def read_ever_hit(map_path):
    """The voxels a saved map's robots ever hit (write_hit_levels), or None if not saved."""
    path = hit_levels_path(map_path)
    if not os.path.exists(path):
        return None
    with np.load(path) as data:
        return data["ever_hit"].astype(np.int64) if "ever_hit" in data.files else None


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
        lambda stream: savez_fast(stream, index=index.astype(np.int32), level=level),
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
    baseline_trails=None,
    baseline_ever_hit=None,
    current_ever_hit=None,
    current_views=None,
    baseline_views=None,
    **kwargs,
) -> List[Change]:
    """detect_changes for two FusedLogOddsMaps under `rules` (ChangeRules; keyword arguments
    override its fields): `swept` (robot_bodies.SweptVolume) is excluded, `current_trails` give the
    viewpoints of the monitoring mission; `current_misses` (VoxelLevels of miss levels) stands for the current map's
    log-odds at the baseline's voxels when the current map was read from a .bt; `baseline_hits`,
    `current_hits` (VoxelLevels) how firmly each map's occupied voxels were seen (the current one's
    from its own log-odds when it is a FrozenMap); `baseline_trails` the baseline mission's
    viewpoints (the sheet rule of an appeared cluster); `current_views`, `baseline_views`
    (sensor_views.SensorViews) the viewpoints of the clouds each map inserted, with their fields of
    view, used instead of the trails when given; `baseline_ever_hit`, `current_ever_hit` the
    voxels each map's robots ever hit (read_ever_hit; the current one's from the map itself when it
    is a FrozenMap or a live map)."""
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
    cluster_ok = appeared_ok = None
    current_sources = current_views if current_views is not None else current_trails
    baseline_sources = baseline_views if baseline_views is not None else baseline_trails
    if rules.min_viewpoints > 0 and current_sources is not None:
        cluster_ok = _seen_through(current_sources, current_map, rules, res, True, rules.min_viewpoints)
    if rules.sheet_min_incidence_deg > 0 and baseline_sources is not None:
        appeared_ok = _seen_through(baseline_sources, baseline_map, rules, res, False, APPEARED_SHEET_VIEWPOINTS)

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
        appeared_cluster_ok=appeared_ok,
        merge_gap_voxels=rules.merge_gap_voxels,
        seen_s=getattr(current_map, "first_seen_s", None),
        baseline_hit_index=baseline_ever_hit,
        current_hit_index=current_ever_hit if current_ever_hit is not None else _hit_index_of(current_map),
        move_radius_m=rules.move_radius_m,
        move_min_explained=rules.move_min_explained,
    )


def _hit_index_of(fused):
    """A live map's (or FrozenMap's) ever-hit voxels; None for a map read from a file (no owners)."""
    if isinstance(fused, FrozenMap) or getattr(fused, "hit_index", None) is not None and len(fused.hit_index()):
        return fused.hit_index()
    return None


def write_report(changes: List[Change], path, baseline_name="baseline", current_name="current", tracker=None):
    """A Markdown report (and a .json twin) of the changes; returns the Markdown path. With a
    `tracker` (change_tracking.ChangeTracker) the .json also holds when each change was first found
    and reported (s, the map server's clock), and the withdrawn ones."""
    lines = [
        f"# Site changes: {current_name} against {baseline_name}",
        "",
        f"{sum(c.kind == 'appeared' for c in changes)} appeared, "
        f"{sum(c.kind == 'disappeared' for c in changes)} disappeared, "
        f"{sum(c.kind == 'moved' for c in changes)} moved.",
        "",
        "| # | change | centroid x, y, z (m) | size x, y, z (m) | volume (m³) | voxels | moved by x, y (m) |",
        "|---|---|---|---|---|---|---|",
    ]
    for i, c in enumerate(changes, 1):
        moved = f"{c.displacement_m[0]:+.2f}, {c.displacement_m[1]:+.2f}" if c.displacement_m else "—"
        lines.append(
            f"| {i} | {c.kind} | {', '.join(f'{v:.2f}' for v in c.centroid_m)} | "
            f"{', '.join(f'{v:.2f}' for v in c.size_m)} | {c.volume_m3:.3f} | {c.voxels} | {moved} |"
        )
    # Each file replaced atomically: the map server rewrites them every detection cycle, and a
    # mission that ended while it wrote (seed 70615's fleet_4) left an empty .json, its report lost.
    write_atomically(str(path), lambda stream: stream.write("\n".join(lines) + "\n"), binary=False)
    rows = [dataclasses.asdict(c) for c in changes]
    if tracker is not None:
        for row, t in zip(rows, tracker.reported()):
            row.update(first_seen_s=t.first_seen_s, reported_s=t.reported_s, cycles=t.cycles)
            row["first_view_s"] = t.first_view_s
        rows += [
            {
                **dataclasses.asdict(t.change),
                "withdrawn": True,
                "first_seen_s": t.first_seen_s,
                "reported_s": t.reported_s,
                "first_view_s": t.first_view_s,
            }
            for t in tracker.withdrawn
        ]
    write_atomically(
        str(path).rsplit(".", 1)[0] + ".json", lambda stream: json.dump(rows, stream, indent=1), binary=False
    )
    return path
