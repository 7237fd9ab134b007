"""One level and one rate for every managed stream (issue 24), without ROS.

Every robot has a managed cloud (levels: the voxel grid's leaf) and every camera robot a video
(levels: resolution and JPEG quality), fleet.yaml `streams:`. For each stream s the allocator
chooses a level l_s and a rate f_s so that the link holds (Eq. 1 with levels):

    sum_s size_{s, l_s} * f_s <= B        (B: the managed budget, (1 - reserve) x available)

and, if the twin reports its insertion capacity, sum_{clouds} f_s <= C (clouds/s).

The objective is lexicographic, most important first (docs/bandwidth_manager.md):

1. Rules, kept in this precedence order (each rule's stream is kept iff it still fits after the
   rules before it; that greedy order is exactly the lexicographic optimum, and the tests check
   it against every subset):
   a. every robot's cloud at >= its floor rate (link.min_rate_hz, 1 Hz) at its cheapest level
      (the coarsest); if even these do not fit the clouds degrade as allocation.py's do
      (priority classes below the minimum first, down to floor_rate_hz, then one scale factor)
      and every video is off;
   b. operator video: the selected robot's and every teleoperated robot's video at level <=
      operator_video_level and >= operator_video_rate_hz;
   c. inspection detail: a high-priority robot's cloud (near a detected site change) at the
      finest level, at >= its floor rate;
   d. every other video at >= video_min_rate_hz at its cheapest level; a video that does not fit
      is off (rate 0) rather than taking the clouds' floors.
2. Rates at each stream's base level (the cheapest level its rules allow): weighted proportional
   fairness, max sum_s w_s log f_s, which for one budget is allocation.py's weighted max-min
   water-filling on bandwidth (b_s = clip(w_s lambda, lo_s, hi_s)).
3. Detail: only when every stream runs at its maximum rate is there budget left, and it buys
   finer levels at the maximum rate: max sum_s w_s (bits(l_s) - bits(base_s)) with
   sum_s (size_{s,l_s} - size_{s,base_s}) fmax_s <= leftover, a multiple-choice knapsack solved
   exactly (dynamic programming on its Pareto frontier; scipy.optimize.milp past a size limit). bits(l) = log2 of the level's detail over the
   coarsest (points per area 1/leaf^2 for clouds, pixels for video).

Rates first, then detail, except where a rule (b, c) asks for detail first: that is the
issue's operator-first and inspection-first policy; every other stream degrades in detail
before it degrades in rate, and never below its floor while the floors fit.
"""

import dataclasses
import math
from typing import Dict, Mapping, Optional, Sequence, Tuple

import numpy as np

from cps_bw_manager.allocation import DEFAULT_FLOOR_RATE_HZ, _degrade, water_fill

CLOUD = "cloud"
VIDEO = "video"
STREAMS = (CLOUD, VIDEO)
OPERATOR_VIDEO = "operator_video"
INSPECTION_DETAIL = "inspection_detail"
GUARANTEES = (OPERATOR_VIDEO, INSPECTION_DETAIL)  # precedence order of rule 1b, 1c
# The operator's video (rule 1b) may run this much above its guaranteed rate without CPU to spare,
# where the link has room: the guarantee is a rate the operator must *see* in every window, and a
# camera told exactly that rate on a saturated host delivers a frame or two fewer in some 10 s
# windows (link_thesis at 5 Mbit/s: 15.0 fps allotted, lowest 10 s windows 15.0 and 14.5 fps).
OPERATOR_VIDEO_RATE_HEADROOM = 1.2
_BYTES_PER_MB = 1e6
# A rule that fits within this fraction of the budget fits (float rounding of sums of products).
_SLACK = 1e-12


@dataclasses.dataclass(frozen=True)
class ResourceUse:
    """What one stream takes of a resource beside the link: the CPU of the robots' host its encoder
    runs on (cores), or the twin's insertion (points/s). Issue 36: compute is a resource."""

    resource: str  # the resource's name: a host ("cpu <host>") or the twin ("twin points")
    per_message: Tuple[float, ...]  # amount per message at each level (finest first); inf: not known
    # What the stream may take without any spare: its baseline, what it runs when nobody tells it
    # (its encoder's configured level; the camera's default level and rate).
    baseline_per_s: float
    # Messages per second it is produced at whatever its allocated rate (a cloud is encoded before
    # its rate limiter drops it: the sensor's rate); NaN: at the allocated rate (video is rendered
    # and encoded only at the rate set).
    produced_hz: float = math.nan

    def per_s(self, level, rate_hz):
        """What the stream takes at `level` and `rate_hz`."""
        rate = self.produced_hz if math.isfinite(self.produced_hz) else rate_hz
        return self.per_message[level] * rate if rate > 0 else 0.0

    def increase(self, level, rate_hz):
        """What it takes at `level` and `rate_hz` beyond its baseline (never < 0)."""
        return max(0.0, self.per_s(level, rate_hz) - self.baseline_per_s)


@dataclasses.dataclass(frozen=True)
class StreamDemand:
    """What the allocator knows about one stream. Levels are finest first."""

    robot: str
    stream: str
    level_bytes: Tuple[float, ...]  # estimated size per message at each level, bytes (> 0)
    detail_bits: Tuple[float, ...]  # log2(detail / coarsest level's), nonincreasing
    level_names: Tuple[str, ...] = ()
    weight: float = 1.0
    priority: int = 0
    floor_rate_hz: float = 1.0
    max_rate_hz: float = 30.0
    may_go_off: bool = False  # rule 1d's streams (video); False: rule 1a's (cloud)
    guarantee: str = ""  # "", OPERATOR_VIDEO or INSPECTION_DETAIL
    guarantee_level: int = 0  # at this level or finer ...
    guarantee_rate_hz: float = 0.0  # ... at least this rate
    size_measured: Tuple[bool, ...] = ()
    # Issue 36. Resources beside the link (a host's CPU, the twin's insertion) and what this stream
    # takes of them; a resource with a finite spare in allocate_levels(spare=...) bounds what the
    # allocation may add to the stream's use beyond what it takes now.
    uses: Tuple[ResourceUse, ...] = ()
    # No level finer than this is bought with spare budget (stage 3): a compute-bound stream's
    # level in force. Rules 1b/1c are not bound by it.
    finest_level: int = 0
    # The level its encoder runs at now (None: not known); a finer level must fit the link with
    # allocate_levels' `upgrade_margin` to spare (hysteresis against levels flapping).
    level_in_force: Optional[int] = None

    @property
    def key(self):
        return (self.robot, self.stream)


@dataclasses.dataclass(frozen=True)
class StreamAllocation:
    robot: str
    stream: str
    level: int
    level_name: str
    rate_hz: float
    message_bytes: float
    bandwidth_mbytes_per_s: float
    share_percent: float
    weight: float
    priority: int
    min_rate_hz: float  # the rate its kept rules guarantee (0 when off)
    max_rate_hz: float
    degraded: bool  # below its floor rate, off, or its guarantee broken
    guarantee_kept: bool
    size_measured: bool

    @property
    def off(self):
        return self.rate_hz == 0.0

    @property
    def key(self):
        return (self.robot, self.stream)


@dataclasses.dataclass(frozen=True)
class LevelAllocation:
    streams: Tuple[StreamAllocation, ...]
    budget_mbytes_per_s: float
    allocated_mbytes_per_s: float
    feasible: bool  # every floor and every guarantee kept
    status: str
    broken: Tuple[str, ...]  # "<robot>/<stream>: <rule>" for every rule that did not fit
    detail_value: float  # the objective of stage 3 (sum of w x bits above the base levels)
    # True when the link's budget shares the rates (stage 2 binds); False when every stream runs
    # at its maximum rate and budget is left (the link is idle: stage 3).
    link_binds: bool = True
    # Per resource with a finite spare: what the allocation adds to its use beyond what is in force.
    resource_increase: Tuple[Tuple[str, float], ...] = ()

    def by_key(self) -> Dict[Tuple[str, str], StreamAllocation]:
        return {(a.robot, a.stream): a for a in self.streams}


def cloud_detail_bits(leaves_m):
    """log2 of points per area relative to the coarsest leaf: (coarsest / leaf)^2."""
    coarsest = leaves_m[-1]
    return tuple(2.0 * math.log2(coarsest / leaf) for leaf in leaves_m)


def video_detail_bits(pixels):
    """log2 of pixels relative to the coarsest level."""
    coarsest = pixels[-1]
    return tuple(math.log2(p / coarsest) for p in pixels)


def validate_stream(d: StreamDemand):
    """ValueError naming the stream and the field if `d` cannot be allocated."""
    n = len(d.level_bytes)
    try:  # the common case at once (the allocator validates every stream at every update)
        if (
            n
            and len(d.detail_bits) == n
            and all(0 < b < math.inf for b in d.level_bytes)
            and all(math.isfinite(x) for x in d.detail_bits)
            and 0 < d.weight < math.inf
            and 0 < d.floor_rate_hz <= d.max_rate_hz < math.inf
            and not d.guarantee
            and not d.uses
            and d.finest_level == 0
            and d.level_in_force is None
        ):
            return
    except TypeError:
        pass
    who = f"{d.robot}/{d.stream}"
    if n == 0 or len(d.detail_bits) != n:
        raise ValueError(f"{who}: needs one size and one detail per level, got {n} and {len(d.detail_bits)}")
    if any(not _finite(b) or b <= 0 for b in d.level_bytes):
        raise ValueError(f"{who}: level sizes must be finite and > 0 bytes, got {d.level_bytes}")
    if any(not _finite(x) for x in d.detail_bits):
        raise ValueError(f"{who}: detail bits must be finite, got {d.detail_bits}")
    for field in ("weight", "floor_rate_hz", "max_rate_hz"):
        value = getattr(d, field)
        if not _finite(value) or value <= 0:
            raise ValueError(f"{who}: {field} must be finite and > 0, got {value!r}")
    if d.floor_rate_hz > d.max_rate_hz:
        raise ValueError(f"{who}: floor_rate_hz ({d.floor_rate_hz}) > max_rate_hz ({d.max_rate_hz})")
    if d.guarantee:
        if d.guarantee not in GUARANTEES:
            raise ValueError(f"{who}: unknown guarantee {d.guarantee!r} (known: {', '.join(GUARANTEES)})")
        if not 0 <= d.guarantee_level < n:
            raise ValueError(f"{who}: guarantee_level {d.guarantee_level} outside the {n} levels")
        if not _finite(d.guarantee_rate_hz) or not d.floor_rate_hz <= d.guarantee_rate_hz <= d.max_rate_hz:
            raise ValueError(f"{who}: guarantee_rate_hz {d.guarantee_rate_hz!r} outside [floor, max] rate")
    if isinstance(d.finest_level, bool) or not isinstance(d.finest_level, int) or not 0 <= d.finest_level < n:
        raise ValueError(f"{who}: finest_level {d.finest_level!r} outside the {n} levels")
    if d.level_in_force is not None and (
        isinstance(d.level_in_force, bool) or not isinstance(d.level_in_force, int) or not 0 <= d.level_in_force < n
    ):
        raise ValueError(f"{who}: level_in_force {d.level_in_force!r} outside the {n} levels")
    resources = [u.resource for u in d.uses]
    if len(set(resources)) != len(resources):
        raise ValueError(f"{who}: one use per resource, got {resources}")
    for u in d.uses:
        if len(u.per_message) != n or any(not (x >= 0) for x in u.per_message):  # inf allowed, NaN not
            raise ValueError(f"{who}: {u.resource}: one amount >= 0 per level, got {u.per_message}")
        if not (_finite(u.baseline_per_s) and u.baseline_per_s >= 0):
            raise ValueError(f"{who}: {u.resource}: baseline_per_s must be finite and >= 0, got {u.baseline_per_s!r}")
        if not (math.isnan(u.produced_hz) or (_finite(u.produced_hz) and u.produced_hz >= 0)):
            raise ValueError(f"{who}: {u.resource}: produced_hz must be NaN or finite and >= 0, got {u.produced_hz!r}")


def allocate_levels(
    demands: Sequence[StreamDemand],
    budget_mbytes_per_s: float,
    *,
    max_clouds_per_s: Optional[float] = None,
    floor_rate_hz: float = DEFAULT_FLOOR_RATE_HZ,
    priority_weights=None,
    spare: Optional[Mapping[str, float]] = None,
    upgrade_margin: float = 0.0,
) -> LevelAllocation:
    """Level and rate for every stream (module docstring). ValueError for bad input.

    `max_clouds_per_s`: the twin's insertion capacity; the clouds' maximum rates are then its
    weighted water-filling share (never below their floors: a capacity below the floors is
    reported in `broken` and the floors hold). `floor_rate_hz`, `priority_weights`: rule 1a's
    degradation, as allocation.allocate_frequencies.

    `spare` (issue 36): per resource beside the link (the streams' `uses`), how much of it the
    allocation may take above the streams' baselines (from a host's idle CPU, the twin's
    insertion capacity); absent or inf: not bounded. Within it the rates above the rules' are
    shared by weight (before the link's budget, as the insertion capacity), finer levels are bought
    only if they fit it as well as the link, and an inspection's detail (rule 1c) is kept only if
    it fits; what the other rules need is never refused for it (it is counted).
    `upgrade_margin`: a level finer than a stream's `level_in_force` must fit the link with this
    fraction of its cost to spare (hysteresis).
    """
    if not _finite(budget_mbytes_per_s) or budget_mbytes_per_s <= 0:
        raise ValueError(f"budget must be > 0 MB/s, got {budget_mbytes_per_s!r}")
    if not _finite(upgrade_margin) or not 0 <= upgrade_margin <= 1:
        raise ValueError(f"upgrade_margin must be in [0, 1], got {upgrade_margin!r}")
    bounded = {}
    for name, value in (spare or {}).items():
        if not (value >= 0):  # NaN or negative
            raise ValueError(f"spare {name!r} must be >= 0 (inf: not bounded), got {value!r}")
        if math.isfinite(value):
            bounded[name] = float(value)
    if max_clouds_per_s is not None and (not _finite(max_clouds_per_s) or max_clouds_per_s < 0):
        raise ValueError(f"max_clouds_per_s must be finite and >= 0, got {max_clouds_per_s!r}")
    keys = [d.key for d in demands]
    if len(set(keys)) != len(keys):
        raise ValueError(f"streams must be unique per robot, got {keys}")
    for d in demands:
        validate_stream(d)
    budget = float(budget_mbytes_per_s)
    if not demands:
        return LevelAllocation((), budget, 0.0, True, "no managed streams", (), 0.0)

    n = len(demands)
    sizes = [np.asarray(d.level_bytes, dtype=float) / _BYTES_PER_MB for d in demands]
    bits = [np.asarray(d.detail_bits, dtype=float) for d in demands]
    weight = np.array([d.weight for d in demands], dtype=float)
    fmax = np.array([d.max_rate_hz for d in demands], dtype=float)
    floor = np.array([d.floor_rate_hz for d in demands], dtype=float)
    broken = []

    # The twin's insertion capacity caps the clouds' maximum rates (its share by weight).
    clouds = [i for i, d in enumerate(demands) if not d.may_go_off]
    if max_clouds_per_s is not None and clouds:
        low = floor[clouds]
        if low.sum() > max_clouds_per_s:
            broken.append(
                f"twin insertion capacity {max_clouds_per_s:.2f} clouds/s < the clouds' floors {low.sum():.2f}/s"
            )
            fmax[clouds] = low
        else:
            fmax[clouds] = water_fill(weight[clouds], low, fmax[clouds], max_clouds_per_s)

    # Rule 1a: the clouds' floors at their cheapest level.
    base = [_cheapest(s, range(len(s))) for s in sizes]
    floor_cost = np.array([sizes[i][base[i]] * floor[i] for i in range(n)])
    total_1a = floor_cost[clouds].sum()
    if total_1a > budget:
        return _clouds_degraded(demands, sizes, base, floor, fmax, weight, budget, floor_rate_hz, priority_weights)

    # Rules 1b, 1c (per stream, in precedence order) and 1d.
    remaining = budget - total_1a
    kept_guarantee = [False] * n
    required = floor.copy()
    active = np.array([not d.may_go_off for d in demands])
    rules_use = {r: 0.0 for r in bounded}  # what the kept guarantees take above their baselines
    for rule in GUARANTEES:
        for i, d in enumerate(demands):
            if d.guarantee != rule:
                continue
            lvl = _cheapest(sizes[i], range(d.guarantee_level + 1))
            extra = sizes[i][lvl] * d.guarantee_rate_hz - (floor_cost[i] if active[i] else 0.0)
            need = {u.resource: u.increase(lvl, d.guarantee_rate_hz) for u in d.uses if u.resource in bounded}
            # Inspection detail is bought with spare like any detail; the operator's video is not refused.
            fits = rule != INSPECTION_DETAIL or all(
                rules_use[r] + v <= _resource_slack(bounded[r]) for r, v in need.items()
            )
            if extra <= remaining + _SLACK * budget and fits:
                remaining -= extra
                kept_guarantee[i], active[i] = True, True
                base[i], required[i] = lvl, d.guarantee_rate_hz
                for r, v in need.items():
                    rules_use[r] += v
            else:
                broken.append(f"{d.robot}/{d.stream}: {rule}" + ("" if fits else " (no CPU or insertion to spare)"))
    for i, d in enumerate(demands):
        if d.may_go_off and not active[i]:
            if floor_cost[i] <= remaining + _SLACK * budget:
                remaining -= floor_cost[i]
                active[i] = True
            else:
                broken.append(f"{d.robot}/{d.stream}: floor {d.floor_rate_hz:g} Hz (off)")

    # Stage 2: rates at the base levels.
    size_base = np.array([sizes[i][base[i]] for i in range(n)])
    cap = np.maximum(fmax, required)
    if bounded:
        at_least = np.array(
            [
                required[i]
                * (OPERATOR_VIDEO_RATE_HEADROOM if kept_guarantee[i] and d.guarantee == OPERATOR_VIDEO else 1.0)
                for i, d in enumerate(demands)
            ]
        )
        cap = _cap_by_resources(demands, active, base, required, cap, weight, bounded, at_least)
    lo = np.where(active, size_base * required, 0.0)
    hi = np.where(active, size_base * cap, 0.0)
    level = list(base)
    on = np.flatnonzero(active)
    b = np.zeros(n)
    b[on] = water_fill(weight[on], lo[on], hi[on], budget)
    rate = np.where(active, b / size_base, 0.0)
    detail_value = 0.0

    # Stage 3: finer levels at the maximum rate, with what every stream at its maximum leaves.
    leftover = budget - hi.sum()
    if leftover > 0:
        resource_left = {
            r: bounded[r] - sum(u.increase(base[i], cap[i]) for i in on for u in demands[i].uses if u.resource == r)
            for r in bounded
        }
        options = []
        for i in on:
            d = demands[i]
            top = d.guarantee_level if kept_guarantee[i] else len(sizes[i]) - 1
            allowed = range(min(top, len(sizes[i]) - 1) + 1) if kept_guarantee[i] else range(len(sizes[i]))
            for lvl in allowed:
                gain = weight[i] * (bits[i][lvl] - bits[i][base[i]])
                if lvl == base[i] or gain <= 0 or lvl < d.finest_level:
                    continue
                cost = (sizes[i][lvl] - size_base[i]) * cap[i]
                if d.level_in_force is not None and lvl < d.level_in_force:
                    cost *= 1.0 + upgrade_margin
                extra = {
                    u.resource: u.increase(lvl, cap[i]) - u.increase(base[i], cap[i])
                    for u in d.uses
                    if u.resource in bounded
                }
                if all(math.isfinite(v) for v in extra.values()):
                    options.append((i, lvl, cost, gain, extra))
        choice, detail_value = choose_levels_within(options, leftover + _SLACK * budget, resource_left)
        for i, lvl in choice.items():
            level[i] = lvl
        rate = np.where(active, cap, 0.0)

    size_chosen = np.array([sizes[i][level[i]] for i in range(n)])
    b = rate * size_chosen
    if b.sum() > budget:  # floating-point excess only
        rate *= budget / b.sum() * (1 - 1e-12)
        b = rate * size_chosen
    status = "every floor and guarantee kept"
    if broken:
        status = "degraded: " + "; ".join(broken)
    elif leftover > 0:
        status += "; every stream at its maximum rate, finer levels with the rest"
    else:
        status += "; rates shared by priority-weighted max-min fairness at the base levels"
    streams = tuple(
        _result(
            d,
            level[i],
            rate[i],
            size_chosen[i],
            b[i],
            budget,
            required[i] if active[i] else 0.0,
            cap[i],
            degraded=not active[i] or bool(d.guarantee and not kept_guarantee[i]) or rate[i] < floor[i] * (1 - 1e-9),
            kept=kept_guarantee[i],
        )
        for i, d in enumerate(demands)
    )
    feasible = not broken
    increase = tuple(
        (r, float(sum(u.increase(level[i], rate[i]) for i in on for u in demands[i].uses if u.resource == r)))
        for r in sorted(bounded)
    )
    return LevelAllocation(
        streams,
        budget,
        float(b.sum()),
        feasible,
        status,
        tuple(broken),
        float(detail_value),
        link_binds=not leftover > 0,
        resource_increase=increase,
    )


def _cap_by_resources(demands, active, base, required, cap, weight, bounded, at_least):
    """The streams' maximum rates within each bounded resource's spare (issue 36): a stream whose
    use grows with its rate (a video rendered at the rate set) may add to what it takes now its
    weighted water-filling share of the spare, at its base level; never below its rules' rate
    (`required`), nor below `at_least` (the operator's video: its rate with headroom).
    A stream produced at a fixed rate (a cloud encoded before its limiter) takes what its level
    costs whatever its rate: its increase at the base level comes off the spare first."""
    cap = cap.copy()
    for r, spare in bounded.items():
        members = [(i, u) for i, d in enumerate(demands) if active[i] for u in d.uses if u.resource == r]
        left = spare - sum(u.increase(base[i], 0.0) for i, u in members if math.isfinite(u.produced_hz))
        scaled = [(i, u) for i, u in members if not math.isfinite(u.produced_hz) and u.per_message[base[i]] > 0]
        if not scaled:
            continue
        lo = np.array([u.increase(base[i], required[i]) for i, u in scaled])
        hi = np.array([u.increase(base[i], cap[i]) for i, u in scaled])
        if not np.all(np.isfinite(hi)):  # a cost not known: no more than the rules' rate or what is in force
            hi = np.where(np.isfinite(hi), hi, lo)
        if hi.sum() <= left:
            continue
        w = np.array([weight[i] for i, _ in scaled])
        grant = water_fill(w, lo, np.maximum(hi, lo), max(left, 0.0))
        for (i, u), g in zip(scaled, grant):
            per = u.per_message[base[i]]
            rate = (u.baseline_per_s + g) / per if math.isfinite(per) else 0.0
            cap[i] = min(cap[i], max(at_least[i], rate))
    return cap


def choose_levels_within(options, leftover, resource_left):
    """choose_levels with resources beside the link: options are (stream, level, link cost, gain,
    {resource: cost}) and every resource's total cost must stay within resource_left[resource].
    Exact: options that alone exceed a resource are dropped; if no option left costs any bounded
    resource it is choose_levels' knapsack, else scipy's milp with one row per resource."""
    rows = sorted(resource_left)
    kept = []
    for i, lvl, cost, gain, extra in options:
        costs = [max(0.0, extra.get(r, 0.0)) for r in rows]
        if all(c <= _resource_slack(resource_left[r]) for c, r in zip(costs, rows)):
            kept.append((i, lvl, cost, gain, costs))
    if not any(c > 0 for *_, costs in kept for c in costs):
        return choose_levels([(i, lvl, cost, gain) for i, lvl, cost, gain, _ in kept], leftover)
    limits = np.array([leftover] + [_resource_slack(resource_left[r]) for r in rows])
    best = {}
    for i, lvl, cost, gain, costs in kept:
        if gain > 0 and (i not in best or gain > best[i][3]):
            best[i] = (i, lvl, cost, gain, costs)
    totals = np.sum([[o[2]] + list(o[4]) for o in best.values()], axis=0) if best else np.zeros(len(limits))
    if np.all(totals <= limits):  # every stream's best fits
        return {i: o[1] for i, o in best.items()}, float(sum(o[3] for o in best.values()))
    return _choose_levels_milp_rows(
        [(i, lvl, [cost] + list(costs), gain) for i, lvl, cost, gain, costs in kept], limits
    )


def _resource_slack(left):
    """A resource's leftover with float rounding allowed for (never below 0)."""
    return max(0.0, left) * (1 + 1e-12) + 1e-15


def choose_levels(options, leftover):
    """Exact multiple-choice knapsack: at most one option (stream i, level, cost, gain) per stream,
    total cost <= leftover, maximum total gain. Returns ({stream: level}, gain).

    Dynamic programming over the streams on the Pareto frontier of (cost, gain): after each
    stream only the partial choices that no cheaper one matches in gain are kept, which is exact
    and stays small because the gains (weight x bits) take few distinct sums. Past
    FRONTIER_LIMIT states it hands the problem to scipy's milp (HiGHS)."""
    groups = {}
    for i, lvl, cost, gain in options:
        if gain > 0 and cost <= leftover:
            groups.setdefault(i, []).append((float(cost), float(gain), lvl))
    if not groups:
        return {}, 0.0
    finest = {i: max(opts, key=lambda o: o[1]) for i, opts in groups.items()}
    if sum(o[0] for o in finest.values()) <= leftover:  # every stream's best fits
        return {i: o[2] for i, o in finest.items()}, float(sum(o[1] for o in finest.values()))
    costs, gains = np.zeros(1), np.zeros(1)
    history = []
    for opts in groups.values():
        option_cost = np.array([0.0] + [o[0] for o in opts])
        option_gain = np.array([0.0] + [o[1] for o in opts])
        c = (costs[:, None] + option_cost[None, :]).ravel()
        g = (gains[:, None] + option_gain[None, :]).ravel()
        flat = np.flatnonzero(c <= leftover)
        flat = flat[np.lexsort((-g[flat], c[flat]))]  # cheapest first, on equal cost the larger gain first
        g_sorted = g[flat]
        best_before = np.maximum.accumulate(g_sorted)
        keep = np.empty(len(flat), dtype=bool)  # more gain than every cheaper (or equally cheap) state
        keep[0] = True
        keep[1:] = g_sorted[1:] > best_before[:-1]
        flat = flat[keep]
        costs, gains = c[flat], g[flat]
        history.append(np.divmod(flat, len(option_cost)))  # (parent state, option) per state
        if len(costs) > FRONTIER_LIMIT:
            return _choose_levels_milp(options, leftover)
    state = int(np.argmax(gains))
    value = float(gains[state])
    picked = {}
    for (i, opts), (parent, pick) in zip(reversed(list(groups.items())), reversed(history)):
        if pick[state] > 0:
            picked[i] = opts[pick[state] - 1][2]
        state = int(parent[state])
    return picked, value


# Pareto states before the knapsack goes to milp (16 robots x 2 streams x 3 levels keep ~100).
FRONTIER_LIMIT = 20000


def _choose_levels_milp(options, leftover):
    """The same knapsack by scipy.optimize.milp (HiGHS)."""
    return _choose_levels_milp_rows([(i, lvl, [cost], gain) for i, lvl, cost, gain in options], np.array([leftover]))


def _choose_levels_milp_rows(options, limits):
    """The knapsack with one row per resource: options (stream, level, [cost per row], gain),
    row k's total cost <= limits[k], at most one option per stream; milp (HiGHS)."""
    from scipy.optimize import Bounds, LinearConstraint, milp

    options = [o for o in options if o[3] > 0]
    if not options:
        return {}, 0.0
    limits = np.asarray(limits, dtype=float)
    costs = np.array([o[2] for o in options], dtype=float).T  # rows x options
    gains = np.array([o[3] for o in options])
    streams = sorted({o[0] for o in options})
    one_per_stream = np.zeros((len(streams), len(options)))
    for k, o in enumerate(options):
        one_per_stream[streams.index(o[0]), k] = 1.0
    # Each row scaled to a leftover of 1 and the gains to a largest of 1 (sizes in MB x rates give
    # costs of 1e-6); a row with nothing left admits only options that cost it nothing.
    free = limits <= 0
    if np.any(free):
        usable = ~np.any(costs[free] > 0, axis=0)
        if not usable.any():
            return {}, 0.0
        options = [o for o, ok in zip(options, usable) if ok]
        return _choose_levels_milp_rows(options, np.where(free, 1.0, limits))
    result = milp(
        -gains / gains.max(),
        integrality=np.ones(len(options)),
        bounds=Bounds(0, 1),
        constraints=[
            LinearConstraint(costs / limits[:, None], -np.inf, 1.0),
            LinearConstraint(one_per_stream, -np.inf, 1.0),
        ],
        # HiGHS' presolve loses an option whose cost is ~1e-6 of the leftover (returns "optimal"
        # with nothing chosen); the problem is small enough to need none.
        options={"presolve": False},
    )
    if result.x is None:  # cannot happen (all zeros is feasible); keep the base levels
        return {}, 0.0
    chosen = [k for k in range(len(options)) if result.x[k] > 0.5]
    if np.any(costs[:, chosen].sum(axis=1) > limits):  # solver tolerance: the base levels rather than overrun
        return {}, 0.0
    return {options[k][0]: options[k][1] for k in chosen}, float(gains[chosen].sum())


def _cheapest(size, allowed):
    """The cheapest allowed level; on a tie the finer one."""
    allowed = list(allowed)
    return min(allowed, key=lambda lvl: (size[lvl], lvl))


def _result(d, level, rate, size_mb, b, budget, required, cap, *, degraded, kept):
    names = d.level_names or tuple(str(k) for k in range(len(d.level_bytes)))
    measured = d.size_measured[level] if d.size_measured else False
    return StreamAllocation(
        robot=d.robot,
        stream=d.stream,
        level=int(level),
        level_name=names[level],
        rate_hz=float(rate),
        message_bytes=float(size_mb * _BYTES_PER_MB),
        bandwidth_mbytes_per_s=float(b),
        share_percent=float(100.0 * b / budget),
        weight=float(d.weight),
        priority=int(d.priority),
        min_rate_hz=float(required),
        max_rate_hz=float(cap),
        degraded=bool(degraded),
        guarantee_kept=bool(kept),
        size_measured=bool(measured),
    )


def _clouds_degraded(demands, sizes, base, floor, fmax, weight, budget, floor_rate_hz, priority_weights):
    """Rule 1a does not fit: the clouds degrade as allocation.py's robots do, every video is off."""
    from cps_bw_manager.allocation import DEFAULT_PRIORITY_WEIGHTS

    weights = DEFAULT_PRIORITY_WEIGHTS if priority_weights is None else priority_weights
    clouds = [i for i, d in enumerate(demands) if not d.may_go_off]
    size_mb = np.array([sizes[i][base[i]] for i in clouds])
    fmin = floor[clouds]
    priority = np.array([demands[i].priority for i in clouds])
    w = np.array([weights.get(int(p), 1.0) for p in priority], dtype=float)
    b_clouds, why = _degrade(size_mb, fmin, priority, w, size_mb * fmin, budget, floor_rate_hz)
    b = np.zeros(len(demands))
    b[clouds] = b_clouds
    rate = np.zeros(len(demands))
    rate[clouds] = b_clouds / size_mb
    broken = [f"{demands[i].robot}/{demands[i].stream}: floor {floor[i]:g} Hz" for i in clouds if rate[i] < floor[i]]
    broken += [f"{d.robot}/{d.stream}: off (the clouds' floors do not fit)" for d in demands if d.may_go_off]
    streams = []
    for i, d in enumerate(demands):
        below = bool(d.may_go_off or rate[i] < floor[i] * (1 - 1e-9))
        required = 0.0 if below else floor[i]
        streams.append(
            _result(d, base[i], rate[i], sizes[i][base[i]], b[i], budget, required, fmax[i], degraded=below, kept=False)
        )
    streams = tuple(streams)
    return LevelAllocation(streams, budget, float(b.sum()), False, why + "; every video off", tuple(broken), 0.0)


def _finite(value):
    try:
        return math.isfinite(float(value))
    except (TypeError, ValueError):
        return False
