"""OctoMap cloud insertion in a dense log-odds grid (numba); the OcTree and its .bt built from it.

`LogOddsGrid.integrate_cloud(..., exact=True)` does what OctoMap's `insertPointCloud(points,
origin, maxrange)` does to the finest voxels, with the same arithmetic:
- rays are cast with OctoMap's `computeRayKeys` (Amanatides-Woo, float32 points, the same
  stopping rule), every voxel a ray crosses gets one miss per cloud;
- an endpoint within max range gets one hit, and a voxel both crossed and hit in one cloud is
  only hit (OctoMap's "occupied wins"); a point beyond max range clears up to max range only;
- log-odds are float32, added and clamped as `updateNodeLogOdds`.
So a sequence of clouds gives the finest-voxel log-odds of plain sequential insertion.

`exact=False` (shared-origin casting): the rays of one cloud share its origin, so every ray is
cast from its endpoint back toward the origin and stops once it has crossed `stop_run` voxels in
a row that this cloud already cleared; the origin side of the cloud, crossed by thousands of
rays, is then walked about once instead of once per ray. Approximate: two traversals that meet in
a voxel may part again nearer the origin (they enter it at different points), and the voxels the
later ray would have crossed there stay as they were; the reverse traversal may also pick the
other voxel at exact corner ties. On the paper fleet's clouds (bench/mapping_bench.py) stopping
after 1 voxel leaves 1-3 % of the occupied voxels that exact insertion clears, after 0.3 m of
voxels 0.3 % (and walks 8x (0.1 m) / 3.5x (0.05 m) fewer voxels than exact casting).

Asked for (`first_seen=True`, a monitoring mission's map), the grid also keeps when each voxel
was first seen: the stamp of the first cloud whose ray crossed or ended in it (float32 seconds
from the grid's epoch, its first stamped cloud; NaN: not seen by a stamped cloud), so that a
change is timed from the cloud that first saw its place, not from an estimate of who could have.

Nothing else is kept per voxel: there is no OcTree to keep in step. `binary_tree_bytes` writes
OctoMap's binary (.bt) stream straight from the grid (max likelihood, pruned, byte for byte what
`writeBinary` of the same tree writes) and `full_tree` builds an OcTree with every voxel's
log-odds when one is asked for. Memory: 6 bytes per voxel (float32 log-odds, a one-byte stamp of
the last cloud that cleared or hit it, the last robot that hit it) of the bounding box of
everything seen (0.05 m over a 21 x 16 x 3.5 m hall: about 56 MB).
"""

import dataclasses
import math
import time
from typing import Tuple

import numpy as np

from cps_mapping import kernel_cache

GRID_MARGIN_VOXELS = 8
_TREE_DEPTH = 16
_TREE_MAX_VAL = 1 << 15


@kernel_cache.njit(nogil=True, inline="always")
def _key(coord, res_factor):
    return np.int64(math.floor(res_factor * np.float64(coord)))


@kernel_cache.njit(nogil=True, inline="always")
def _add(log_odds, flat, delta, clamp_min, clamp_max):
    old = log_odds[flat]
    base = np.float32(0.0) if math.isnan(old) else old
    new = np.float32(base + delta)
    if new < clamp_min:
        new = clamp_min
    elif new > clamp_max:
        new = clamp_max
    log_odds[flat] = new


@kernel_cache.njit(nogil=True, inline="always")
def _seen(first_seen, log_odds, flat, t):
    """A voxel not yet known is seen now, by the cloud of stamp `t` (only if the grid keeps stamps)."""
    if first_seen.shape[0] > 0 and math.isnan(log_odds[flat]):
        first_seen[flat] = t


@kernel_cache.njit(nogil=True)
def _prepare(points, origin, max_range, res_factor):
    """Finite points as float32 (N x 3) and the (lo, hi) voxel indices the cloud's rays can touch
    (a point beyond max range: up to max range only), with two voxels to spare."""
    n = points.shape[0]
    out = np.empty((n, 3), dtype=np.float32)
    o = np.empty(3, dtype=np.float64)
    for a in range(3):
        o[a] = np.float64(origin[a])
    mn = o.copy()
    mx = o.copy()
    m = 0
    for i in range(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            continue
        out[m, 0], out[m, 1], out[m, 2] = x, y, z
        for a in range(3):
            c = np.float64(out[m, a])
            if max_range > 0.0:
                c = min(max(c, o[a] - max_range), o[a] + max_range)
            if c < mn[a]:
                mn[a] = c
            if c > mx[a]:
                mx[a] = c
        m += 1
    lo = np.empty(3, dtype=np.int64)
    hi = np.empty(3, dtype=np.int64)
    for a in range(3):
        lo[a] = np.int64(math.floor(mn[a] * res_factor)) - 2
        hi[a] = np.int64(math.floor(mx[a] * res_factor)) + 2
    return out[:m], lo, hi


@kernel_cache.njit(nogil=True)
def _integrate(
    points,
    origin,
    max_range,
    resolution,
    lo,
    dims,
    log_odds,
    stamp,
    owner,
    free_code,
    hit_code,
    robot_id,
    hit,
    miss,
    clamp_min,
    clamp_max,
    exact,
    stop_run,
    first_seen,
    t,
):
    """One cloud into the grid (see the module docstring); returns the voxel steps walked.
    exact: OctoMap's computeRayKeys from the origin; else back from each endpoint, stopping after
    `stop_run` consecutive voxels this cloud already cleared. `first_seen` (empty: not kept) gets
    `t` at every voxel this cloud is the first to see."""
    res_factor = 1.0 / resolution
    n = points.shape[0]
    ends = np.empty((n, 3), dtype=np.float32)
    ox, oy, oz = origin[0], origin[1], origin[2]
    lx, ly, lz = lo[0], lo[1], lo[2]
    sy, sz = dims[1] * dims[2], dims[2]
    # endpoints: occupied within max range (first, so that rays never clear them)
    for i in range(n):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        dx = np.float32(px - ox)
        dy = np.float32(py - oy)
        dz = np.float32(pz - oz)
        norm = math.sqrt(np.float64(np.float32(np.float32(dx * dx + dy * dy) + dz * dz)))
        if max_range < 0.0 or norm <= max_range:
            ends[i, 0], ends[i, 1], ends[i, 2] = px, py, pz
            flat = (_key(px, res_factor) - lx) * sy + (_key(py, res_factor) - ly) * sz + (_key(pz, res_factor) - lz)
            if stamp[flat] != hit_code:
                stamp[flat] = hit_code
                owner[flat] = robot_id
                _seen(first_seen, log_odds, flat, t)
                _add(log_odds, flat, hit, clamp_min, clamp_max)
        else:
            f = np.float32(norm)
            r = np.float32(max_range)
            ends[i, 0] = np.float32(ox + np.float32(np.float32(dx / f) * r))
            ends[i, 1] = np.float32(oy + np.float32(np.float32(dy / f) * r))
            ends[i, 2] = np.float32(oz + np.float32(np.float32(dz / f) * r))
    kox, koy, koz = _key(ox, res_factor), _key(oy, res_factor), _key(oz, res_factor)
    big = np.finfo(np.float64).max
    steps = 0
    for i in range(n):
        ex, ey, ez = ends[i, 0], ends[i, 1], ends[i, 2]
        kex, key_, kez = _key(ex, res_factor), _key(ey, res_factor), _key(ez, res_factor)
        if kox == kex and koy == key_ and koz == kez:
            continue
        # exact: from the origin to the endpoint (OctoMap's computeRayKeys); else back from the endpoint
        if exact:
            sx, sy_, sz_ = ox, oy, oz
            cx, cy, cz = kox, koy, koz
            tx, ty, tz = kex, key_, kez
            ddx, ddy, ddz = np.float32(ex - ox), np.float32(ey - oy), np.float32(ez - oz)
        else:
            sx, sy_, sz_ = ex, ey, ez
            cx, cy, cz = kex, key_, kez
            tx, ty, tz = kox, koy, koz
            ddx, ddy, ddz = np.float32(ox - ex), np.float32(oy - ey), np.float32(oz - ez)
        length = np.float32(math.sqrt(np.float64(np.float32(np.float32(ddx * ddx + ddy * ddy) + ddz * ddz))))
        ddx, ddy, ddz = np.float32(ddx / length), np.float32(ddy / length), np.float32(ddz / length)
        stx = 1 if ddx > 0.0 else (-1 if ddx < 0.0 else 0)
        sty = 1 if ddy > 0.0 else (-1 if ddy < 0.0 else 0)
        stz = 1 if ddz > 0.0 else (-1 if ddz < 0.0 else 0)
        if stx != 0:
            border = (np.float64(cx) + 0.5) * resolution + np.float64(np.float32(stx * resolution * 0.5))
            tmx = (border - np.float64(sx)) / np.float64(ddx)
            tdx = resolution / abs(np.float64(ddx))
        else:
            tmx, tdx = big, big
        if sty != 0:
            border = (np.float64(cy) + 0.5) * resolution + np.float64(np.float32(sty * resolution * 0.5))
            tmy = (border - np.float64(sy_)) / np.float64(ddy)
            tdy = resolution / abs(np.float64(ddy))
        else:
            tmy, tdy = big, big
        if stz != 0:
            border = (np.float64(cz) + 0.5) * resolution + np.float64(np.float32(stz * resolution * 0.5))
            tmz = (border - np.float64(sz_)) / np.float64(ddz)
            tdz = resolution / abs(np.float64(ddz))
        else:
            tmz, tdz = big, big
        run = 0
        if exact:  # the origin's voxel first
            flat = (cx - lx) * sy + (cy - ly) * sz + (cz - lz)
            s = stamp[flat]
            if s != free_code and s != hit_code:
                stamp[flat] = free_code
                _seen(first_seen, log_odds, flat, t)
                _add(log_odds, flat, miss, clamp_min, clamp_max)
        while True:
            if tmx < tmy:
                if tmx < tmz:
                    cx += stx
                    tmx += tdx
                else:
                    cz += stz
                    tmz += tdz
            else:
                if tmy < tmz:
                    cy += sty
                    tmy += tdy
                else:
                    cz += stz
                    tmz += tdz
            at_target = cx == tx and cy == ty and cz == tz
            if exact and at_target:
                break
            if min(tmx, tmy, tmz) > length and not at_target:
                break
            steps += 1
            flat = (cx - lx) * sy + (cy - ly) * sz + (cz - lz)
            s = stamp[flat]
            if s == free_code:
                run += 1
                if not exact and run >= stop_run:
                    break  # this cloud cleared these: the rest of the way to the origin is (about) cleared
            elif s != hit_code:
                run = 0
                stamp[flat] = free_code
                _seen(first_seen, log_odds, flat, t)
                _add(log_odds, flat, miss, clamp_min, clamp_max)
            if at_target:
                break
    return steps


# ---- OctoMap's binary stream from the grid --------------------------------------------------------


@kernel_cache.njit(nogil=True)
def _finest_states(log_odds, occ_threshold):
    """Each finest voxel's state as a child: 0 unknown, 1 free, 2 occupied (max likelihood)."""
    states = np.zeros(log_odds.shape[0], dtype=np.uint8)
    for i in range(log_odds.shape[0]):
        v = log_odds[i]
        if not math.isnan(v):
            states[i] = 2 if v >= occ_threshold else 1
    return states


@kernel_cache.njit(nogil=True, inline="always")
def _state_of(code):
    if code == 0:
        return 0
    if code == 0x5555:
        return 1  # eight free leaves: pruned to one free leaf
    if code == 0xAAAA:
        return 2
    return 3


@kernel_cache.njit(nogil=True)
def _level_states(codes):
    """Each node's state as a child of the level above: `_state_of` its child code."""
    states = np.empty(codes.shape[0], dtype=np.uint8)
    for i in range(codes.shape[0]):
        states[i] = _state_of(codes[i])
    return states


@kernel_cache.njit(nogil=True)
def _parent_codes(states, clo, cd):
    """The level above a box of nodes with these states (lowest key `clo`, dims `cd`): for each
    parent its 16-bit child code, 2 bits per child in OctoMap's child order x + 2y + 4z
    (00 unknown, 01 free, 10 occupied, 11 inner node)."""
    plo = clo >> 1
    phi = (clo + cd - 1) >> 1
    pd = phi - plo + 1
    out = np.zeros(pd[0] * pd[1] * pd[2], dtype=np.uint16)
    for x in range(cd[0]):
        kx = clo[0] + x
        px = (kx >> 1) - plo[0]
        bx = kx & 1
        for y in range(cd[1]):
            ky = clo[1] + y
            py = (ky >> 1) - plo[1]
            by = ky & 1
            base = (x * cd[1] + y) * cd[2]
            prow = (px * pd[1] + py) * pd[2]
            for z in range(cd[2]):
                state = states[base + z]
                if state == 0:
                    continue
                kz = clo[2] + z
                child = bx + 2 * by + 4 * (kz & 1)
                out[prow + (kz >> 1) - plo[2]] |= np.uint16(state << (2 * child))
    return out, plo, pd


@kernel_cache.njit(nogil=True)
def _write_preorder(codes, offsets, los, ds):
    """OctoMap's writeBinaryNode from the root down: 2 bytes per inner node, children in order.
    Level lv's child codes are codes[offsets[lv]:offsets[lv + 1]], its box (los[lv], ds[lv]): flat
    arrays rather than numba typed lists, whose own functions numba compiles in every process."""
    top = offsets.shape[0] - 2
    n_inner = 0
    for lv in range(top + 1):
        for i in range(offsets[lv], offsets[lv + 1]):
            c = codes[i]
            if _state_of(c) == 3 or (lv == top and c != 0):
                n_inner += 1
    out = np.empty(2 * n_inner, dtype=np.uint8)
    if n_inner == 0:
        return out, 0
    stack_l = np.empty(8 * (top + 2), dtype=np.int64)
    stack_k = np.empty((8 * (top + 2), 3), dtype=np.int64)
    sp = 0
    stack_l[0] = top
    stack_k[0, 0], stack_k[0, 1], stack_k[0, 2] = los[top][0], los[top][1], los[top][2]
    sp = 1
    w = 0
    nodes = 1
    while sp > 0:
        sp -= 1
        lv = stack_l[sp]
        kx, ky, kz = stack_k[sp, 0], stack_k[sp, 1], stack_k[sp, 2]
        lo, d = los[lv], ds[lv]
        code = codes[offsets[lv] + ((kx - lo[0]) * d[1] + (ky - lo[1])) * d[2] + (kz - lo[2])]
        out[w] = np.uint8(code & 0xFF)
        out[w + 1] = np.uint8(code >> 8)
        w += 2
        for child in range(7, -1, -1):
            s = (code >> (2 * child)) & 3
            if s == 0:
                continue
            nodes += 1
            if s == 3 and lv > 0:
                stack_l[sp] = lv - 1
                stack_k[sp, 0] = 2 * kx + (child & 1)
                stack_k[sp, 1] = 2 * ky + ((child >> 1) & 1)
                stack_k[sp, 2] = 2 * kz + ((child >> 2) & 1)
                sp += 1
    return out[:w], nodes


def binary_tree_body(log_odds, lo, dims, occ_threshold=0.0):
    """(body bytes, node count) of OctoMap's binary stream for the finest voxels of a grid.

    What `writeBinary` writes for an OcTree holding these voxels: the tree turned into max
    likelihood (a voxel is occupied at log-odds >= `occ_threshold`, OctoMap's isNodeOccupied)
    and pruned (eight equal leaves become their parent), then written depth first. Built level by
    level over the grid's box, never as a tree: about 10 ms for 7 M voxels.
    """
    dims = np.asarray(dims, dtype=np.int64)
    if not dims.all() or not np.any(~np.isnan(log_odds)):
        return b"", 0
    klo = np.asarray(lo, dtype=np.int64) + _TREE_MAX_VAL
    codes, clo, cd = _parent_codes(_finest_states(log_odds, np.float32(occ_threshold)), klo, dims)
    levels, los, ds = [codes], [clo], [cd]
    for _ in range(_TREE_DEPTH - 1):
        codes, clo, cd = _parent_codes(_level_states(codes), clo, cd)
        levels.append(codes)
        los.append(clo)
        ds.append(cd)
    # levels[i] holds the nodes of depth 15 - i; the last is the root (depth 0)
    offsets = np.cumsum([0] + [len(level) for level in levels]).astype(np.int64)
    body, nodes = _write_preorder(
        np.concatenate(levels), offsets, np.stack(los).astype(np.int64), np.stack(ds).astype(np.int64)
    )
    return body.tobytes(), int(nodes)


def binary_tree_file(log_odds, lo, dims, resolution_m, occ_threshold=0.0):
    """(whole .bt file bytes, node count), header as OctoMap's writeBinary writes it."""
    body, nodes = binary_tree_body(log_odds, lo, dims, occ_threshold)
    header = (
        "# Octomap OcTree binary file\n"
        "# (feel free to add / change comments, but leave the first line as it is!)\n#\n"
        f"id OcTree\nsize {nodes}\nres {resolution_m:g}\ndata\n"
    ).encode()
    return header + body, nodes


# ---- Z order, for writing voxels into an OcTree --------------------------------------------------


def _spread_bits(v):
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    return (v | (v << 2)) & 0x1249249249249249


def morton_code(index):
    """Z-order of voxel indices (x in the lowest bit, as OctoMap numbers children); writing voxels
    in this order walks the tree depth-first, which halves the cost of updateNodes."""
    key = (np.asarray(index, dtype=np.int64) + (1 << 15)) & 0xFFFF
    return _spread_bits(key[:, 0]) | (_spread_bits(key[:, 1]) << 1) | (_spread_bits(key[:, 2]) << 2)


def _origin32(origin_m):
    return np.ascontiguousarray(origin_m, dtype=np.float32).reshape(3)


def _max_range_arg(max_range_m):
    """The kernels' max range: metres, or -1 for none (None or <= 0, as OctoMap's maxrange)."""
    return float(max_range_m) if max_range_m is not None and max_range_m > 0 else -1.0


class LogOddsGrid:
    """Finest-voxel log-odds (float32, NaN = unknown) and last-hitting robot over a growing box;
    with `first_seen`, when each voxel was first seen (see the module docstring).

    Voxel i (grid index floor(p / resolution) as OctoMap computes it) is cell i - lo.
    """

    def __init__(self, resolution_m, hit_log, miss_log, clamp_min_log, clamp_max_log, first_seen=False):
        self.resolution_m = float(resolution_m)
        self.keeps_first_seen = bool(first_seen)
        self.epoch_s = math.nan  # the stamp first_seen counts from: the first stamped cloud's
        self.hit, self.miss = np.float32(hit_log), np.float32(miss_log)
        self.clamp_min, self.clamp_max = np.float32(clamp_min_log), np.float32(clamp_max_log)
        self.lo = np.zeros(3, dtype=np.int64)
        self.dims = np.zeros(3, dtype=np.int64)
        self._allocate(self.lo, self.dims)
        self._cloud_id = 0
        self.steps = 0

    def _allocate(self, lo, dims):
        size = int(np.prod(dims))
        self.log_odds = np.full(size, np.nan, dtype=np.float32)
        self.owner = np.zeros(size, dtype=np.uint8)
        self.stamp = np.zeros(size, dtype=np.uint8)  # 2 c: cleared by cloud c, 2 c + 1: hit by it
        self.first_seen = np.full(size if self.keeps_first_seen else 0, np.nan, dtype=np.float32)
        self.lo, self.dims = lo.astype(np.int64), dims.astype(np.int64)

    # ---- indexing ------------------------------------------------------------------------

    def index_of(self, points_m):
        """OctoMap's voxel index of each point (floor(p * (1 / resolution)), as coordToKey)."""
        pts = np.asarray(points_m, dtype=np.float32).astype(np.float64)
        return np.floor(pts * (1.0 / self.resolution_m)).astype(np.int64)

    def flat(self, index):
        """Flat cell of each voxel index; -1 for voxels outside the box."""
        rel = np.asarray(index, dtype=np.int64).reshape(-1, 3) - self.lo
        inside = np.all((rel >= 0) & (rel < self.dims), axis=1)
        flat = np.full(len(rel), -1, dtype=np.int64)
        flat[inside] = np.ravel_multi_index(rel[inside].T, self.dims) if inside.any() else flat[inside]
        return flat

    def index_of_flat(self, flat):
        return np.stack(np.unravel_index(np.asarray(flat, dtype=np.int64), self.dims), axis=1) + self.lo

    def _grown(self, lo_index, hi_index):
        """(lo, hi) of the box that holds the current one and [lo_index, hi_index]; None if it does."""
        lo_index, hi_index = np.asarray(lo_index, dtype=np.int64), np.asarray(hi_index, dtype=np.int64)
        if self.dims.all() and np.all(lo_index >= self.lo) and np.all(hi_index < self.lo + self.dims):
            return None
        if self.dims.all():
            return (
                np.minimum(self.lo, lo_index - GRID_MARGIN_VOXELS),
                np.maximum(self.lo + self.dims, hi_index + 1 + GRID_MARGIN_VOXELS),
            )
        return lo_index - GRID_MARGIN_VOXELS, hi_index + 1 + GRID_MARGIN_VOXELS

    def voxels_to_hold(self, lo_index, hi_index):
        """Voxels the box would have once it holds [lo_index, hi_index]."""
        grown = self._grown(lo_index, hi_index)
        return int(np.prod(self.dims)) if grown is None else int(np.prod(grown[1] - grown[0]))

    def prepare(self, points_m, origin_m, max_range_m):
        """(finite points as float32, lo, hi): the cloud as `integrate_cloud` takes it and the
        voxel indices its rays can touch (a point beyond max range: up to max range only), so
        that a caller can bound the grid's growth before inserting anything."""
        points = np.ascontiguousarray(np.asarray(points_m, dtype=np.float64).reshape(-1, 3))
        return _prepare(points, _origin32(origin_m), _max_range_arg(max_range_m), 1.0 / self.resolution_m)

    def ensure(self, lo_index, hi_index):
        """Grow the box to hold [lo_index, hi_index]."""
        grown = self._grown(lo_index, hi_index)
        if grown is None:
            return
        new_lo, new_hi = grown
        old = (self.log_odds, self.owner, self.lo, self.dims, self.first_seen)
        self._allocate(new_lo, new_hi - new_lo)
        if old[3].all():
            offset = old[2] - self.lo
            sl = tuple(slice(o, o + d) for o, d in zip(offset, old[3]))
            self.log_odds.reshape(tuple(self.dims))[sl] = old[0].reshape(tuple(old[3]))
            self.owner.reshape(tuple(self.dims))[sl] = old[1].reshape(tuple(old[3]))
            if self.keeps_first_seen:
                self.first_seen.reshape(tuple(self.dims))[sl] = old[4].reshape(tuple(old[3]))

    # ---- insertion -----------------------------------------------------------------------

    def integrate_cloud(self, prepared, origin_m, max_range_m, robot_id, exact=True, stop_run=1, stamp_s=math.nan):
        """Insert one cloud, as `prepare` returned it (map frame): exact as OctoMap's
        insertPointCloud, or with shared-origin casting (`exact=False`, see the module docstring).
        `stamp_s`: the cloud's stamp, kept where it is the first to see a voxel (with first_seen)."""
        points, lo, hi = prepared
        if len(points) == 0:
            return
        t = math.nan
        if self.keeps_first_seen and math.isfinite(stamp_s):
            if math.isnan(self.epoch_s):
                self.epoch_s = float(stamp_s)
            t = stamp_s - self.epoch_s
        self.ensure(lo, hi)
        self._cloud_id += 1
        if self._cloud_id > 127:  # one byte of stamp per voxel: start over every 127 clouds
            self.stamp[:] = 0
            self._cloud_id = 1
        self.steps += _integrate(
            points,
            _origin32(origin_m),
            _max_range_arg(max_range_m),
            self.resolution_m,
            self.lo,
            self.dims,
            self.log_odds,
            self.stamp,
            self.owner,
            np.uint8(2 * self._cloud_id),
            np.uint8(2 * self._cloud_id + 1),
            np.uint8(robot_id),
            self.hit,
            self.miss,
            self.clamp_min,
            self.clamp_max,
            bool(exact),
            np.int64(stop_run),
            self.first_seen,
            np.float32(t),
        )

    @property
    def nbytes(self):
        """Memory of the grid's arrays (6 bytes per voxel of the box; 10 with first_seen)."""
        return int(self.log_odds.nbytes + self.owner.nbytes + self.stamp.nbytes + self.first_seen.nbytes)

    def first_seen_s(self, flat):
        """The stamp (s) of the first cloud that saw each cell (`flat`, -1: outside); NaN where
        not kept, not seen, or seen by a cloud without a stamp."""
        flat = np.asarray(flat, dtype=np.int64)
        out = np.full(len(flat), np.nan)
        if self.keeps_first_seen and len(flat):
            inside = flat >= 0
            out[inside] = self.first_seen[flat[inside]].astype(np.float64) + self.epoch_s
        return out

    def set_values(self, flat, values):
        """Set voxels (e.g. clear_bbx)."""
        self.log_odds[np.asarray(flat, dtype=np.int64)] = np.asarray(values, dtype=np.float32)

    def known(self):
        """(flat cells, log-odds) of every known voxel."""
        flat = np.flatnonzero(~np.isnan(self.log_odds))
        return flat, self.log_odds[flat]

    def binary_tree_file(self, occ_threshold=0.0):
        """The .bt file (max likelihood, pruned, as OctoMap's writeBinary) and its node count."""
        return binary_tree_file(self.log_odds, self.lo, self.dims, self.resolution_m, occ_threshold)

    def write_into(self, tree):
        """Write every known voxel's log-odds into an empty OcTree (one lazy updateNodes per
        distinct value, in Z order; a new node starts at 0, so it takes the value exactly)."""
        flat, values = self.known()
        if len(flat) == 0:
            return
        voxels = self.index_of_flat(flat)
        centers = (voxels.astype(np.float64) + 0.5) * self.resolution_m
        order = np.lexsort((morton_code(voxels), values))
        distinct, starts = np.unique(values[order], return_index=True)
        bounds = list(starts) + [len(order)]
        for k, value in enumerate(distinct):
            rows = order[bounds[k] : bounds[k + 1]]
            tree.updateNodes(centers[rows].tolist(), float(value), True)
        tree.updateInnerOccupancy()

    def load_leaves(self, index, log_odds):
        """Replace everything by finest voxels `index` with `log_odds` (a tree just read)."""
        if len(index) == 0:
            self._allocate(np.zeros(3, dtype=np.int64), np.zeros(3, dtype=np.int64))
            return
        lo, hi = index.min(axis=0), index.max(axis=0)
        self._allocate(lo - GRID_MARGIN_VOXELS, hi + 1 + GRID_MARGIN_VOXELS - (lo - GRID_MARGIN_VOXELS))
        self.log_odds[self.flat(index)] = np.asarray(log_odds, dtype=np.float32)


@dataclasses.dataclass(frozen=True)
class WarmUp:
    """What `warm_up` measured."""

    load_s: float  # first call of every kernel: loaded from the build-time cache (or compiled)
    insertion_ms: float  # one cloud inserted after that: the speed the first real cloud gets
    compiled: Tuple[str, ...]  # kernels this process compiled; () when the cache held them all
    cache_dir: str  # where they were looked for (kernel_cache: keyed by this source's content)


# The warm-up cloud: a ring of points around the origin, as a scan of a small room.
WARMUP_POINTS = 2000


def warm_up():
    """Load every kernel with the argument types the map server passes (compiling what the cache
    lacks), then time one more insertion: after this the first cloud is inserted at full speed."""
    t0 = time.monotonic()
    grid = LogOddsGrid(0.1, 0.85, -0.4, -2.0, 3.5)
    cloud = grid.prepare(np.array([[1.0, 0.0, 0.0], [9.0, 0.0, 0.0]]), np.zeros(3), 5.0)
    for exact in (True, False):
        grid.integrate_cloud(cloud, np.zeros(3), 5.0, 0, exact=exact)
    seen = LogOddsGrid(0.1, 0.85, -0.4, -2.0, 3.5, first_seen=True)  # the same kernel, stamps kept
    seen.integrate_cloud(seen.prepare(np.array([[1.0, 0.0, 0.0]]), np.zeros(3), 5.0), np.zeros(3), 5.0, 0, stamp_s=1.0)
    grid.binary_tree_file()
    load_s = time.monotonic() - t0
    angles = np.linspace(0.0, 2.0 * np.pi, WARMUP_POINTS, endpoint=False)
    ring = np.stack([4.0 * np.cos(angles), 4.0 * np.sin(angles), np.linspace(-1.0, 1.0, WARMUP_POINTS)], axis=1)
    t1 = time.monotonic()
    grid.integrate_cloud(grid.prepare(ring, np.zeros(3), 5.0), np.zeros(3), 5.0, 1, exact=False)
    insertion_ms = (time.monotonic() - t1) * 1e3
    return WarmUp(load_s, insertion_ms, kernel_cache.compiled_kernels(), kernel_cache.cache_dir(__file__))
