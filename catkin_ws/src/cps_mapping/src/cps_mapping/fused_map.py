"""The fused multi-robot map: a dense log-odds grid with OctoMap's insertion and OctoMap I/O.

`FusedLogOddsMap` is what the map server holds. It knows nothing of ROS: clouds arrive as N x 3
numpy arrays in `map` with their sensor origin. Every cloud is inserted exactly as
octomap_server's `insertPointCloud(points, origin, max_range)` would insert it, one after the
other (same rays, same float32 log-odds, same clamping; see `cps_mapping.log_odds_grid`), but
the ray casting runs in a compiled kernel over a dense log-odds grid; with
`exact_free_space=False` every ray is cast back from its endpoint and stops where the cloud has
already cleared (about each voxel once per cloud; >= 99 % of the occupied voxels agree). The map
lives in the grid only: the `.bt` stream is written from it directly and an OcTree is built from
it when `tree` is read (cached until the map changes). In exact mode a map built from a batch
equals, to float rounding, the map plain sequential insertion builds.

Voxels are named by their grid index i = floor(p / resolution); the voxel centre is
(i + 0.5) * resolution, OctoMap's grid.
"""

import copy
import dataclasses
import math
import os
import tempfile
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import octomap

from cps_mapping.log_odds_grid import GRID_MARGIN_VOXELS, LogOddsGrid

BT_HEADER = b"# Octomap OcTree binary file"
OT_HEADER = b"# Octomap OcTree file"
_INDEX_BIAS = 1 << 20
_UNKNOWN_ROBOT = ""
_MAX_ROBOTS = 255


class MapFileError(ValueError):
    """A map file that cannot be saved or loaded; the message names the file and the reason."""


@dataclasses.dataclass
class InsertResult:
    clouds: int
    points_in: int
    points_inserted: int
    points_rejected: int
    groups: int
    seconds: float


@dataclasses.dataclass
class LeafArrays:
    """Every leaf of the tree at one moment: centre (m), edge (m) and log-odds."""

    centers_m: np.ndarray
    sizes_m: np.ndarray
    log_odds: np.ndarray

    @property
    def occupied(self):
        return self.log_odds > 0.0


@dataclasses.dataclass(frozen=True)
class LogOddsBox:
    """A copy of the map's log-odds at one moment: a box of `dims` voxels from grid index `lo`,
    `log_odds` its cells flattened in C order (cell of voxel i: ravel_multi_index(i - lo, dims);
    NaN: unknown)."""

    lo: np.ndarray
    dims: np.ndarray
    log_odds: np.ndarray
    first_seen_s: np.ndarray = None  # per cell, when first seen (s; NaN: not seen); None: not kept


def voxel_index(points_m, resolution_m):
    """Integer grid index floor(p / resolution) of each point (OctoMap's voxel)."""
    return np.floor(np.asarray(points_m, dtype=np.float64) / resolution_m).astype(np.int64)


def index_to_center(index, resolution_m):
    return (np.asarray(index, dtype=np.float64) + 0.5) * resolution_m


def pack_index(index):
    """One int64 per voxel index (each axis within +-2^20 voxels), for sets and dicts."""
    idx = np.asarray(index, dtype=np.int64) + _INDEX_BIAS
    return (idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2]


def unpack_index(packed):
    packed = np.asarray(packed, dtype=np.int64)
    mask = (1 << 21) - 1
    return np.stack([(packed >> 42) & mask, (packed >> 21) & mask, packed & mask], axis=1) - _INDEX_BIAS


def near_any(index, other_index, tolerance_voxels):
    """True for each voxel of `index` with a voxel of `other_index` within the Chebyshev tolerance."""
    index = np.asarray(index, dtype=np.int64).reshape(-1, 3)
    if len(index) == 0 or len(other_index) == 0:
        return np.zeros(len(index), dtype=bool)
    other = np.unique(pack_index(other_index))
    r = range(-tolerance_voxels, tolerance_voxels + 1)
    near = np.zeros(len(index), dtype=bool)
    for offset in ((i, j, k) for i in r for j in r for k in r):
        near |= np.isin(pack_index(index + np.asarray(offset, dtype=np.int64)), other, assume_unique=False)
    return near


def expand_leaves(centers_m, sizes_m, resolution_m):
    """Grid indices of the finest voxels covered by (possibly pruned) leaves."""
    centers = np.asarray(centers_m, dtype=np.float64).reshape(-1, 3)
    sizes = np.asarray(sizes_m, dtype=np.float64).ravel()
    if len(centers) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    cells = np.maximum(np.rint(sizes / resolution_m).astype(np.int64), 1)
    out = []
    for n in np.unique(cells):
        sel = cells == n
        lo = np.rint((centers[sel] - sizes[sel, None] / 2) / resolution_m).astype(np.int64)
        if n == 1:
            out.append(lo)
            continue
        offsets = np.stack(np.meshgrid(*(np.arange(n),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
        out.append((lo[:, None, :] + offsets[None, :, :]).reshape(-1, 3))
    return np.vstack(out)


def height_colors(z_m, z_min_m=None, z_max_m=None):
    """octomap_server's height colouring: hue from 0.8 (low) to 0 (high), RGB in [0, 1]."""
    z = np.asarray(z_m, dtype=np.float64)
    if len(z) == 0:
        return np.zeros((0, 3))
    lo = z.min() if z_min_m is None else z_min_m
    hi = z.max() if z_max_m is None else z_max_m
    span = max(hi - lo, 1e-9)
    h = (1.0 - np.clip((z - lo) / span, 0.0, 1.0)) * 0.8 * 6.0
    i = np.floor(h).astype(int)
    f = h - i
    f = np.where(i % 2 == 0, 1.0 - f, f)
    n = 1.0 - f  # with s = v = 1: m = 0, n = v * (1 - s * f)
    one, zero = np.ones_like(z), np.zeros_like(z)
    table = {
        0: (one, n, zero),
        1: (n, one, zero),
        2: (zero, one, n),
        3: (zero, n, one),
        4: (n, zero, one),
        5: (one, zero, n),
        6: (one, zero, n),
    }
    rgb = np.zeros((len(z), 3))
    for k, (r, g, b) in table.items():
        sel = i == k
        rgb[sel] = np.stack([r[sel], g[sel], b[sel]], axis=1)
    return rgb


def _apply_sensor_model(tree, sensor_model):
    tree.setProbHit(sensor_model.hit)
    tree.setProbMiss(sensor_model.miss)
    tree.setClampingThresMin(sensor_model.min)
    tree.setClampingThresMax(sensor_model.max)


def new_octree(resolution_m, sensor_model):
    """An empty octomap.OcTree with `sensor_model` (hit, miss, min, max probabilities)."""
    tree = octomap.OcTree(resolution_m)
    _apply_sensor_model(tree, sensor_model)
    return tree


class FusedLogOddsMap:
    """A dense log-odds grid fed by many robots as OctoMap would be, with per-robot contribution
    tracking, OctoMap persistence (.bt/.ot) and views.

    Not thread-safe: the map server serializes access with one lock.
    """

    def __init__(
        self,
        resolution_m,
        sensor_model,
        max_grid_voxels=200_000_000,
        exact_free_space=False,
        shared_ray_stop_m=0.3,
        first_seen_stamps=False,
    ):
        """`sensor_model`: hit, miss, min, max probabilities (fleet.yaml `mapping.sensor_model`).
        Every cloud is cast from its own origin. `max_grid_voxels` bounds the log-odds grid (6 bytes per voxel; default 1.2 GB): a batch that would grow it beyond is
        refused (ValueError). `exact_free_space`: True casts every ray whole, as OctoMap does
        (the map equals plain sequential insertion); False casts each ray back from its endpoint
        and stops once it has crossed `shared_ray_stop_m` (rounded up to whole voxels) of voxels
        in a row that its cloud already cleared (shared-origin casting, several times faster,
        approximate: see `cps_mapping.log_odds_grid`; 0.3 m: >= 99.7 % of plain insertion's
        occupied voxels agree on the paper fleet's clouds at 0.1 and 0.05 m; longer is more exact
        and slower). `first_seen_stamps`: keep when each voxel was first seen (the stamp of the first
        cloud that saw it, `first_seen_s`; 4 more bytes per voxel): a monitoring mission times its
        changes from them."""
        if not resolution_m > 0:
            raise ValueError(f"resolution_m must be > 0, got {resolution_m}")
        self.resolution_m = float(resolution_m)
        self.sensor_model = sensor_model
        self.max_grid_voxels = int(max_grid_voxels)
        if not shared_ray_stop_m > 0:
            raise ValueError(f"shared_ray_stop_m must be > 0, got {shared_ray_stop_m}")
        self.exact_free_space = bool(exact_free_space)
        self.shared_ray_stop_m = float(shared_ray_stop_m)
        self.first_seen_stamps = bool(first_seen_stamps)
        self._stop_run = max(1, math.ceil(self.shared_ray_stop_m / self.resolution_m - 1e-9))
        self._robots: List[str] = [_UNKNOWN_ROBOT]
        self.version = 0
        self._tree_cache = None  # (version, OcTree built from the grid)
        self._binary_cache = None  # (version, .bt bytes, node count)
        self._grid = self._new_grid()

    @classmethod
    def from_mapping_config(cls, mapping, **kwargs):
        """Build from cps_fleet.fleet.MappingConfig (fleet.yaml `mapping:`)."""
        return cls(mapping.resolution_m, mapping.sensor_model, **kwargs)

    @property
    def tree(self):
        """An OcTree holding every known voxel with its log-odds, built from the grid when read
        and cached until the map changes (tens of ms per 100 k voxels). Read only: the map is
        the grid; write through the methods (and never call its writeBinary, which turns the
        tree it writes into max likelihood: `to_bytes`/`save` write .bt from the grid)."""
        if self._tree_cache is None or self._tree_cache[0] != self.version:
            tree = self._new_tree(self.resolution_m)
            self._grid.write_into(tree)
            self._tree_cache = (self.version, tree)
        return self._tree_cache[1]

    @tree.setter
    def tree(self, tree):
        """Take over `tree`'s voxels (e.g. a tree just read); contributions are lost. MapFileError,
        and the map unchanged, if they would need a grid over `max_grid_voxels`."""
        index, log_odds = _finest_voxels(tree, self.resolution_m, self.max_grid_voxels)
        grid = self._new_grid()
        try:
            grid.load_leaves(index, log_odds)
        except MemoryError as exc:
            raise MapFileError(f"no memory for a grid of {len(index)} voxels") from exc
        self._grid = grid
        self.version += 1

    def _binary_file(self):
        """(.bt bytes, node count): the max-likelihood, pruned tree OctoMap's writeBinary would
        write for `tree`, written from the grid (cached until the map changes)."""
        if self._binary_cache is None or self._binary_cache[0] != self.version:
            data, nodes = self._grid.binary_tree_file()
            self._binary_cache = (self.version, data, nodes)
        return self._binary_cache[1], self._binary_cache[2]

    def binary_tree_nodes(self):
        """Nodes of the published tree (.bt: max likelihood, pruned)."""
        return self._binary_file()[1]

    def _new_tree(self, resolution_m):
        return new_octree(resolution_m, self.sensor_model)

    def _new_grid(self):
        tree = self._new_tree(self.resolution_m)  # OctoMap's own float32 log-odds of the model
        return LogOddsGrid(
            self.resolution_m,
            tree.getProbHitLog(),
            tree.getProbMissLog(),
            tree.getClampingThresMinLog(),
            tree.getClampingThresMaxLog(),
            first_seen=self.first_seen_stamps,
        )

    # ---- insertion -------------------------------------------------------------------------

    def insert_cloud(self, points_m, origin_m, max_range_m=-1.0, robot=_UNKNOWN_ROBOT):
        """Insert one cloud (N x 3, map frame) seen from `origin_m`."""
        return self.insert_batch([(points_m, origin_m)], max_range_m=max_range_m, robot=robot)

    def insert_batch(
        self,
        clouds: Sequence[Tuple[np.ndarray, np.ndarray]],
        max_range_m=-1.0,
        robot=_UNKNOWN_ROBOT,
        stamps_s: Optional[Sequence[float]] = None,
    ):
        """Insert consecutive clouds of one robot, in order, each as octomap_server would;
        `stamps_s` (one per cloud) are kept where a cloud is the first to see a voxel
        (`first_seen_stamps`).

        A point within `max_range_m` of its cloud's origin is a hit and clears the voxels to it;
        a point beyond clears up to max range only (<= 0: no limit). Non-finite points are
        dropped (and counted in `points_rejected`); a non-finite origin, or clouds that would grow
        the grid beyond `max_grid_voxels`, raise ValueError before anything is inserted.
        """
        import time

        start = time.perf_counter()
        grid = self._grid
        prepared = []
        points_in = 0
        for points, origin in clouds:
            origin = np.asarray(origin, dtype=np.float64).reshape(3)
            if not np.all(np.isfinite(origin)):
                raise ValueError(f"sensor origin {origin.tolist()} is not finite")
            pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
            points_in += len(pts)
            prepared.append((origin, grid.prepare(pts, origin, max_range_m)))
        inserted = sum(len(p[1][0]) for p in prepared)
        bounds = [p[1][1:] for p in prepared if len(p[1][0])]
        if bounds:
            needed = grid.voxels_to_hold(np.min([b[0] for b in bounds], axis=0), np.max([b[1] for b in bounds], axis=0))
            if needed > self.max_grid_voxels:
                raise ValueError(
                    f"these clouds would grow the map's log-odds grid to {needed} voxels "
                    f"({needed * 6 / 1e9:.1f} GB), over the limit of {self.max_grid_voxels} "
                    f"(sensor origin far from the map?); nothing inserted"
                )
        robot_id = self._robot_id(robot)
        if stamps_s is not None and len(stamps_s) != len(prepared):
            raise ValueError(f"{len(stamps_s)} stamps for {len(prepared)} clouds; nothing inserted")
        cast = 0
        for k, (origin, cloud) in enumerate(prepared):
            if len(cloud[0]) == 0:
                continue
            grid.integrate_cloud(
                cloud,
                origin,
                max_range_m,
                robot_id,
                exact=self.exact_free_space,
                stop_run=self._stop_run,
                stamp_s=math.nan if stamps_s is None else float(stamps_s[k]),
            )
            cast += 1
        if inserted:
            self.version += 1
        return InsertResult(
            clouds=len(prepared),
            points_in=points_in,
            points_inserted=inserted,
            points_rejected=points_in - inserted,
            groups=cast,
            seconds=time.perf_counter() - start,
        )

    def _robot_id(self, robot):
        if robot not in self._robots:
            if len(self._robots) > _MAX_ROBOTS:
                raise ValueError(f"more than {_MAX_ROBOTS} robots in one map")
            self._robots.append(robot)
        return self._robots.index(robot)

    def frozen_copy(self) -> "FusedLogOddsMap":
        """An independent copy of the map (its grid's arrays copied: milliseconds, 6 bytes per
        voxel, 10 with first-seen stamps) for readers that must not hold the map lock while they
        read or write it (the publisher's snapshot, a save, change detection): the live map goes on
        taking clouds meanwhile."""
        clone = copy.copy(self)
        grid = clone._grid = copy.copy(self._grid)
        grid.log_odds, grid.owner, grid.stamp = grid.log_odds.copy(), grid.owner.copy(), grid.stamp.copy()
        grid.first_seen = grid.first_seen.copy()  # empty unless kept (4 more bytes per voxel)
        grid.lo, grid.dims = grid.lo.copy(), grid.dims.copy()
        clone._robots = list(self._robots)
        clone._tree_cache = None
        return clone

    # ---- views -----------------------------------------------------------------------------

    def leaves(self) -> LeafArrays:
        """Every known finest voxel (free ones too: about a million in the hall; the publisher
        reads only the occupied ones).

        Read from the log-odds grid, not by iterating the tree's leaves in Python (0.25 s for
        200k leaves, under the map lock every publish period). They are the tree's leaves: the
        tree is updated lazily and never pruned, except one just loaded, whose pruned leaves
        appear here expanded.
        """
        flat, log_odds = self._grid.known()
        return LeafArrays(
            index_to_center(self._grid.index_of_flat(flat), self.resolution_m),
            np.full(len(flat), self.resolution_m),
            log_odds.astype(np.float64),
        )

    @property
    def voxel_updates(self) -> int:
        """Voxel steps the ray caster has walked so far (the unit of the twin's insertion capacity)."""
        return self._grid.steps

    def log_odds_copy(self) -> LogOddsBox:
        """The log-odds of every voxel in the grid's box, copied (for readers that must not hold
        the map lock while they read, change detection's FrozenMap)."""
        grid = self._grid
        seen = None
        if grid.keeps_first_seen:
            seen = grid.first_seen.astype(np.float64) + grid.epoch_s
        return LogOddsBox(grid.lo.copy(), grid.dims.copy(), grid.log_odds.copy(), seen)

    def first_seen_s(self, points_m):
        """When each point's voxel was first seen (the stamp of the first cloud whose ray crossed
        or ended in it, s); NaN where unknown, or stamps not kept (`first_seen_stamps`)."""
        grid = self._grid
        return grid.first_seen_s(grid.flat(grid.index_of(np.asarray(points_m, dtype=np.float64).reshape(-1, 3))))

    def hit_index(self):
        """Grid indices of every voxel a named robot's cloud hit since the map started (occupied
        now or not; loaded voxels and clouds of no robot have no owner): something stood there
        while this map was made, whatever the rays that crossed it later said."""
        return self._grid.index_of_flat(np.flatnonzero(self._grid.owner))

    def occupied_index(self):
        """Grid indices of every occupied finest-resolution voxel (pruned leaves expanded)."""
        return self._grid.index_of_flat(self._occupied_flat())

    def _occupied_flat(self):
        return np.flatnonzero(self._grid.log_odds > 0.0)

    def occupied_centers(self):
        return index_to_center(self.occupied_index(), self.resolution_m)

    def occupied_leaves(self):
        """(centres, sizes) of the occupied leaves (for markers; see `leaves`), read from the
        occupied voxels alone rather than from every known one."""
        centers = index_to_center(self.occupied_index(), self.resolution_m)
        return centers, np.full(len(centers), self.resolution_m)

    def contributions(self, occupied_index=None) -> Dict[str, int]:
        """Occupied voxels per robot that last hit them ('' for loaded or unattributed voxels)."""
        if occupied_index is None:
            counts = np.bincount(self._grid.owner[self._occupied_flat()], minlength=len(self._robots))
            return {robot: int(counts[rid]) for rid, robot in enumerate(self._robots) if counts[rid]}
        return {robot: len(c) for robot, c in self.contributed_index(occupied_index).items()}

    def contributed_index(self, occupied_index=None) -> Dict[str, np.ndarray]:
        index = self.occupied_index() if occupied_index is None else np.asarray(occupied_index, dtype=np.int64)
        flat = self._grid.flat(index)
        owner = np.where(flat >= 0, self._grid.owner[np.maximum(flat, 0)], 0)
        return {robot: index[owner == rid] for rid, robot in enumerate(self._robots) if (owner == rid).any()}

    def is_free(self, points_m, max_probability=0.5):
        """True where the map holds the point's voxel as known, with an occupancy probability
        at most `max_probability` (0.5: free as OctoMap says; lower asks for firmer evidence)."""
        if not 0.0 < max_probability < 1.0:
            raise ValueError(f"max_probability must be in (0, 1), got {max_probability}")
        grid = self._grid
        flat = grid.flat(grid.index_of(np.asarray(points_m, dtype=np.float64).reshape(-1, 3)))
        if not len(flat) or not grid.log_odds.size:  # no point, or a map that has nothing yet
            return np.zeros(len(flat), dtype=bool)
        log_odds = np.where(flat >= 0, grid.log_odds[np.maximum(flat, 0)], np.nan)
        with np.errstate(invalid="ignore"):
            return log_odds <= np.float32(math.log(max_probability / (1.0 - max_probability)))

    def projected_grid(self, z_min_m=-math.inf, z_max_m=math.inf):
        """octomap_server's 2D projection: (grid int8 [rows=y, cols=x], origin_xy_m).

        100 where a column holds an occupied voxel within [z_min, z_max], 0 where it holds only
        free ones, -1 unknown; the grid spans the columns that hold a known voxel in that band.
        Read from the dense log-odds grid's columns (milliseconds, not a pass over every known
        voxel, which took ~0.2 s for the hall under the map lock every publish period).
        """
        grid, res = self._grid, self.resolution_m
        empty = np.full((1, 1), -1, dtype=np.int8), np.zeros(2)
        if not grid.dims.all():
            return empty
        center_z = (np.arange(grid.dims[2]) + grid.lo[2] + 0.5) * res
        band = (center_z + res / 2 >= z_min_m) & (center_z - res / 2 <= z_max_m)
        if not band.any():
            return empty
        columns = grid.log_odds.reshape(tuple(grid.dims))[:, :, band]
        known = ~np.isnan(columns).all(axis=2)
        with np.errstate(invalid="ignore"):
            occupied = (columns > 0.0).any(axis=2)
        xs, ys = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
        if len(xs) == 0:
            return empty
        window = (slice(xs[0], xs[-1] + 1), slice(ys[0], ys[-1] + 1))
        projected = np.full((ys[-1] + 1 - ys[0], xs[-1] + 1 - xs[0]), -1, dtype=np.int8)
        projected[known[window].T] = 0
        projected[occupied[window].T] = 100
        return projected, (np.array([xs[0], ys[0]]) + grid.lo[:2]).astype(np.float64) * res

    def memory_bytes(self):
        """What the map holds in memory: the log-odds grid, plus an OcTree and .bt if one was
        asked for since the last change."""
        extra = 0
        if self._tree_cache is not None and self._tree_cache[0] == self.version:
            extra += self._tree_cache[1].memoryUsage()
        if self._binary_cache is not None and self._binary_cache[0] == self.version:
            extra += len(self._binary_cache[1])
        return int(self._grid.nbytes + extra)

    def stats(self):
        """`tree_nodes`: nodes of the published (.bt: max likelihood, pruned) tree."""
        return {
            "occupied_voxels": int(len(self.occupied_index())),
            "tree_nodes": self.binary_tree_nodes(),
            "memory_bytes": self.memory_bytes(),
            "grid_bytes": int(self._grid.nbytes),
        }

    # ---- editing ---------------------------------------------------------------------------

    def reset(self):
        self._grid = self._new_grid()
        self.version += 1

    def clear_bbx(self, min_m, max_m):
        """Set every known voxel whose centre lies in the box free (clamped), as octomap_server."""
        lo, hi = np.asarray(min_m, dtype=np.float64), np.asarray(max_m, dtype=np.float64)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise ValueError("clear_bbx: the box corners must be finite")
        if np.any(hi < lo):
            raise ValueError(f"clear_bbx: max {hi.tolist()} is below min {lo.tolist()} on some axis")
        grid = self._grid
        if not grid.dims.all():
            return 0
        first = np.maximum(np.ceil(lo / self.resolution_m - 0.5).astype(np.int64), grid.lo)
        last = np.minimum(np.floor(hi / self.resolution_m - 0.5).astype(np.int64), grid.lo + grid.dims - 1)
        if np.any(last < first):
            return 0
        box = [slice(lo, hi + 1) for lo, hi in zip(first - grid.lo, last - grid.lo)]
        axes = [np.arange(s.start, s.stop) for s in box]
        cells = np.ravel_multi_index(np.meshgrid(*axes, indexing="ij"), tuple(grid.dims)).ravel()
        cells = cells[~np.isnan(grid.log_odds[cells])]
        if len(cells):
            grid.set_values(cells, np.full(len(cells), grid.clamp_min))
            grid.owner[cells] = 0
            self.version += 1
        return int(len(cells))

    # ---- persistence -----------------------------------------------------------------------

    def to_bytes(self, binary=True):
        """The whole map as an OctoMap file (.bt when binary, else .ot), header included."""
        return self._binary_file()[0] if binary else self.tree.write()

    def save(self, path):
        """Write `.bt` (binary, occupancy only) or `.ot` (full) atomically; return the path."""
        path = os.path.abspath(os.path.expanduser(path))
        binary = _format_of(path)
        directory = os.path.dirname(path)
        try:
            os.makedirs(directory, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=os.path.splitext(path)[1], dir=directory)
            os.close(fd)
        except OSError as exc:
            raise MapFileError(f"cannot write {path}: {exc}") from exc
        try:
            if binary:
                try:
                    with open(tmp, "wb") as stream:
                        stream.write(self._binary_file()[0])
                except OSError as exc:
                    raise MapFileError(f"cannot write {path}: {exc}") from exc
                ok = True
            else:
                ok = self.tree.write(tmp.encode())
            if not ok:
                raise MapFileError(f"OctoMap could not write {path}")
            os.chmod(tmp, 0o644)
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        return path

    def load(self, path):
        """Replace the map with the file's; on any error (MapFileError, also for a map whose grid
        would exceed `max_grid_voxels`) the current map stays as it was."""
        try:
            tree = read_octree_file(path, expected_resolution_m=self.resolution_m)
        except MemoryError as exc:
            raise MapFileError(f"{os.path.abspath(path)}: too large to read into memory") from exc
        _apply_sensor_model(tree, self.sensor_model)
        try:
            self.tree = tree
        except MapFileError as exc:
            raise MapFileError(f"{os.path.abspath(path)}: {exc}") from exc
        return tree.size()


def _finest_voxels(tree, resolution_m, max_grid_voxels=None):
    """(grid index, log-odds) of every finest voxel a tree holds (pruned leaves expanded);
    MapFileError before expanding if their bounding box (with the grid's margin) holds more than
    `max_grid_voxels` voxels (a coarse pruned leaf, or voxels kilometres apart)."""
    rows = np.array(
        [(it.getX(), it.getY(), it.getZ(), it.getSize(), it.getValue()) for it in tree.begin_leafs()], dtype=np.float64
    ).reshape(-1, 5)
    cells = np.maximum(np.rint(rows[:, 3] / resolution_m).astype(np.int64), 1)
    if len(rows) and max_grid_voxels is not None:
        lo = np.rint((rows[:, :3] - rows[:, 3:4] / 2) / resolution_m).astype(np.int64)
        span = (lo + cells[:, None]).max(axis=0) - lo.min(axis=0) + 2 * GRID_MARGIN_VOXELS
        needed = int(np.prod(span.astype(np.float64)))
        if needed > max_grid_voxels:
            raise MapFileError(
                f"its {len(rows)} leaves span {' x '.join(str(int(n)) for n in span)} voxels "
                f"({needed:.3g}, {needed * 6 / 1e9:.3g} GB), over the map's limit of "
                f"{max_grid_voxels} (max_grid_voxels); not loaded"
            )
    index = expand_leaves(rows[:, :3], rows[:, 3], resolution_m)
    order = np.argsort(cells, kind="stable")  # expand_leaves groups by leaf size, in ascending order
    values = np.repeat(rows[order, 4], cells[order] ** 3)
    return index, values


def _format_of(path):
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".bt", ".ot"):
        raise MapFileError(f"{path}: unknown map format '{ext}' (use .bt or .ot)")
    return ext == ".bt"


def parse_header(data: bytes, source="map"):
    """(binary, id, size, resolution, body offset) of an OctoMap file's bytes; MapFileError if not one."""
    first, _, _ = data.partition(b"\n")
    if first.rstrip() == BT_HEADER:
        binary = True
    elif first.rstrip() == OT_HEADER:
        binary = False
    else:
        raise MapFileError(f"{source}: not an OctoMap file (first line {first[:60]!r})")
    fields, offset = {}, len(first) + 1
    while offset < len(data):
        line, _, _ = data[offset:].partition(b"\n")
        offset += len(line) + 1
        text = line.decode(errors="replace").strip()
        if text == "data":
            break
        if text.startswith("#") or not text:
            continue
        key, _, value = text.partition(" ")
        fields[key] = value.strip()
    else:
        raise MapFileError(f"{source}: OctoMap header has no 'data' line (truncated file?)")
    try:
        tree_id, size, res = fields.get("id", "OcTree"), int(fields["size"]), float(fields["res"])
    except (KeyError, ValueError) as exc:
        raise MapFileError(f"{source}: bad OctoMap header {fields}: {exc}") from exc
    if tree_id != "OcTree":
        raise MapFileError(f"{source}: tree type '{tree_id}' is not an occupancy OcTree")
    return binary, tree_id, size, res, offset


def read_octree_file(path, expected_resolution_m=None):
    """A validated octomap.OcTree from a .bt or .ot file; MapFileError says what is wrong."""
    path = os.path.abspath(os.path.expanduser(path))
    binary = _format_of(path)
    try:
        with open(path, "rb") as stream:
            data = stream.read()
    except OSError as exc:
        raise MapFileError(f"cannot read {path}: {exc.strerror or exc}") from exc
    is_binary, _, size, res, _ = parse_header(data, path)
    if is_binary != binary:
        raise MapFileError(
            f"{path}: the extension says {'.bt' if binary else '.ot'} but the content is "
            f"{'binary (.bt)' if is_binary else 'full (.ot)'}"
        )
    if expected_resolution_m is not None and not math.isclose(res, expected_resolution_m, rel_tol=1e-6):
        raise MapFileError(f"{path}: resolution {res} m differs from the map's {expected_resolution_m} m")
    tree = octree_from_bytes(data, path)
    if tree.size() != size:
        raise MapFileError(f"{path}: header says {size} nodes but {tree.size()} were read (truncated file?)")
    return tree


def octree_from_bytes(data: bytes, source="map"):
    """An octomap.OcTree from the bytes of a whole .bt or .ot file."""
    binary, _, _, res, _ = parse_header(data, source)
    if binary:
        tree = octomap.OcTree(res)
        if not tree.readBinary(data):
            raise MapFileError(f"{source}: OctoMap could not read the binary tree")
        return tree
    with tempfile.NamedTemporaryFile(suffix=".ot") as tmp:
        tmp.write(data)
        tmp.flush()
        try:
            return octomap.OcTree.read(tmp.name.encode())
        except Exception as exc:  # the binding raises a bare Exception/IOError
            raise MapFileError(f"{source}: OctoMap could not read the tree: {exc}") from exc


def message_fields(fused: FusedLogOddsMap, binary=True):
    """(binary, id, resolution, data body) as octomap_msgs/Octomap carries them (no file header)."""
    data = fused.to_bytes(binary)
    _, tree_id, _, res, offset = parse_header(data)
    return binary, tree_id, res, data[offset:]


def octree_from_message(binary, tree_id, resolution_m, body: bytes):
    """Rebuild an octomap.OcTree from a cps_msgs/Octomap's fields (the GUI's side); binary only."""
    if not binary:
        raise MapFileError("octomap message: only binary (.bt) bodies can be rebuilt without their node count")
    size = binary_body_node_count(body)
    header = (
        BT_HEADER
        + b"\n#\nid "
        + tree_id.encode()
        + b"\nsize "
        + str(size).encode()
        + b"\nres "
        + repr(float(resolution_m)).encode()
        + b"\ndata\n"
    )
    return octree_from_bytes(header + bytes(body), "octomap message")


def binary_body_node_count(body: bytes):
    """Nodes in a binary (.bt) tree body: the root plus every child marked known in the stream.

    The body is OctoMap's pre-order stream of 2 bytes per node with children, 2 bits per child
    (00 = no child), so the count needs no tree; the file header's `size` needs it.
    """
    raw = np.frombuffer(bytes(body), dtype=np.uint8)
    if raw.size == 0:
        return 0
    pairs = np.stack([(raw >> shift) & 3 for shift in (0, 2, 4, 6)])
    return 1 + int(np.count_nonzero(pairs))
