"""The bandwidth manager's rate allocation (paper section 2.4.4, Eq. 1), without ROS.

Eq. 1 asks for rates f_i with  sum_i s_i * f_i <= B  (s_i: message length, B: the managed budget,
(1 - reserve) x available). It does not say which of the many feasible rate vectors to pick.
This module picks the weighted max-min fair one on *bandwidth* b_i = s_i * f_i:

    b_i = clip(w_{p_i} * lam, s_i * fmin_i, s_i * fmax_i),  lam the largest value with sum b_i <= B

i.e. robots of equal priority get equal bandwidth shares, a robot capped at its maximum rate hands
what it cannot use to the others, a high-priority robot gets w_1/w_0 times the share of a normal
one, and the budget is used up unless every robot is at its maximum. `lam` is found exactly by
water-filling over the 2n breakpoints of the piecewise linear sum (O(n log n)); docs/
bandwidth_manager.md shows the same solution as a sequence of linear programs.

When even the minimum rates do not fit, the allocation degrades instead of freezing: the lowest
priority class goes below its minimum first (equal shares inside the class, down to
`floor_rate_hz`), then the next class, and if all floors still do not fit every rate is scaled by
the same factor. The result says so (`feasible`, `status`, per-robot `degraded`).
"""

import dataclasses
import math
from typing import Dict, Sequence, Tuple

import numpy as np

from cps_fleet.fleet import managed_budget_mbytes_per_s  # noqa: F401 (the budget, defined once)

# Bandwidth weight per priority: 0 = normal, 1 = high (inspecting).
DEFAULT_PRIORITY_WEIGHTS = {0: 1.0, 1: 4.0}
DEFAULT_FLOOR_RATE_HZ = 0.1
# Size assumed for a robot whose managed message has not been measured yet (NaN, 0, negative):
# the upper end of a Draco-compressed lidar scan, so an unmeasured robot cannot overrun the link.
DEFAULT_ASSUMED_MESSAGE_BYTES = 60000.0
_BYTES_PER_MB = 1e6


@dataclasses.dataclass(frozen=True)
class RobotDemand:
    """What the allocator knows about one robot's managed topic."""

    name: str
    message_bytes: float
    priority: int = 0
    min_rate_hz: float = 1.0
    max_rate_hz: float = 30.0


@dataclasses.dataclass(frozen=True)
class RobotAllocation:
    name: str
    priority: int
    rate_hz: float
    min_rate_hz: float
    max_rate_hz: float
    message_bytes: float
    bandwidth_mbytes_per_s: float
    share_percent: float
    degraded: bool
    size_measured: bool


@dataclasses.dataclass(frozen=True)
class Allocation:
    robots: Tuple[RobotAllocation, ...]
    budget_mbytes_per_s: float
    allocated_mbytes_per_s: float
    feasible: bool
    status: str

    def by_name(self) -> Dict[str, RobotAllocation]:
        return {r.name: r for r in self.robots}

    def rates_hz(self) -> Dict[str, float]:
        return {r.name: r.rate_hz for r in self.robots}


def _finite(value):
    try:
        return math.isfinite(float(value))
    except (TypeError, ValueError):
        return False


def validate_demand(demand: RobotDemand, priority_weights=DEFAULT_PRIORITY_WEIGHTS):
    """ValueError naming the robot and the field if `demand` cannot be allocated."""
    if demand.priority not in priority_weights:
        raise ValueError(
            f"robot '{demand.name}': priority must be one of {sorted(priority_weights)}, got {demand.priority!r}"
        )
    for field in ("min_rate_hz", "max_rate_hz"):
        value = getattr(demand, field)
        if not _finite(value) or value <= 0:
            raise ValueError(f"robot '{demand.name}': {field} must be a finite rate > 0 Hz, got {value!r}")
    if demand.min_rate_hz > demand.max_rate_hz:
        raise ValueError(
            f"robot '{demand.name}': min_rate_hz ({demand.min_rate_hz}) > max_rate_hz ({demand.max_rate_hz})"
        )


def water_fill(weights, low, high, budget):
    """Exact weighted water-filling: b = clip(w * lam, low, high) with sum(b) == budget.

    Requires sum(low) <= budget <= sum(high) and weights > 0. O(n log n) over the breakpoints
    low/w and high/w of the piecewise linear, nondecreasing g(lam) = sum clip(w * lam, low, high).
    """
    w = np.asarray(weights, dtype=float)
    lo = np.asarray(low, dtype=float)
    hi = np.asarray(high, dtype=float)
    if lo.sum() >= budget:
        return lo.copy()
    if hi.sum() <= budget:
        return hi.copy()
    a, c = lo / w, hi / w
    order_a, order_c = np.argsort(a), np.argsort(c)
    a_sorted, c_sorted = a[order_a], c[order_c]
    prefix_lo = np.concatenate(([0.0], np.cumsum(lo[order_a])))
    prefix_wa = np.concatenate(([0.0], np.cumsum(w[order_a])))
    prefix_wc = np.concatenate(([0.0], np.cumsum(w[order_c])))
    prefix_hi = np.concatenate(([0.0], np.cumsum(hi[order_c])))

    def g(lam):
        k = np.searchsorted(a_sorted, lam, side="left")
        m = np.searchsorted(c_sorted, lam, side="left")
        return (prefix_lo[-1] - prefix_lo[k]) + lam * (prefix_wa[k] - prefix_wc[m]) + prefix_hi[m]

    candidates = np.unique(np.concatenate((a, c)))
    values = g(candidates)
    j = int(np.searchsorted(values, budget, side="left"))
    j = min(max(j, 1), len(candidates) - 1)
    lam0, lam1 = candidates[j - 1], candidates[j]
    g0, g1 = values[j - 1], values[j]
    lam = lam1 if g1 == g0 else lam0 + (budget - g0) * (lam1 - lam0) / (g1 - g0)
    b = np.clip(w * lam, lo, hi)
    total = b.sum()
    if total > budget:  # floating-point excess only; take it from the robots above their floor
        slack = b - lo
        b -= slack * min(1.0, (total - budget) / max(slack.sum(), 1e-300))
    return b


def allocate_frequencies(
    demands: Sequence[RobotDemand],
    budget_mbytes_per_s: float,
    *,
    priority_weights=None,
    floor_rate_hz=DEFAULT_FLOOR_RATE_HZ,
    assumed_message_bytes=DEFAULT_ASSUMED_MESSAGE_BYTES,
) -> Allocation:
    """Rates for every robot so that sum(size x rate) <= budget (Eq. 1), fairly and by priority.

    `budget_mbytes_per_s` is the managed budget (see `managed_budget_mbytes_per_s`). Raises
    ValueError for a bad budget, bounds or priority; unmeasured sizes use `assumed_message_bytes`.
    """
    weights = dict(DEFAULT_PRIORITY_WEIGHTS if priority_weights is None else priority_weights)
    if any(not _finite(v) or v <= 0 for v in weights.values()):
        raise ValueError(f"priority weights must be > 0, got {weights}")
    if not _finite(budget_mbytes_per_s) or budget_mbytes_per_s <= 0:
        raise ValueError(f"budget must be > 0 MB/s, got {budget_mbytes_per_s!r}")
    if not _finite(floor_rate_hz) or floor_rate_hz <= 0:
        raise ValueError(f"floor_rate_hz must be > 0, got {floor_rate_hz!r}")
    if not _finite(assumed_message_bytes) or assumed_message_bytes <= 0:
        raise ValueError(f"assumed_message_bytes must be > 0, got {assumed_message_bytes!r}")
    names = [d.name for d in demands]
    if len(set(names)) != len(names):
        raise ValueError(f"robot names must be unique, got {names}")
    for demand in demands:
        validate_demand(demand, weights)
    if not demands:
        return Allocation((), float(budget_mbytes_per_s), 0.0, True, "no managed robots")

    budget = float(budget_mbytes_per_s)
    measured = np.array([_finite(d.message_bytes) and d.message_bytes > 0 for d in demands])
    size_mb = (
        np.array([float(d.message_bytes) if ok else assumed_message_bytes for d, ok in zip(demands, measured)])
        / _BYTES_PER_MB
    )
    fmin = np.array([d.min_rate_hz for d in demands], dtype=float)
    fmax = np.array([d.max_rate_hz for d in demands], dtype=float)
    priority = np.array([d.priority for d in demands])
    w = np.array([weights[p] for p in priority], dtype=float)
    lo, hi = size_mb * fmin, size_mb * fmax

    if lo.sum() <= budget:
        b = water_fill(w, lo, hi, budget)
        feasible = True
        status = (
            "every robot at its maximum rate"
            if hi.sum() <= budget
            else "budget shared by priority-weighted max-min fairness"
        )
    else:
        b, status = _degrade(size_mb, fmin, priority, w, lo, budget, floor_rate_hz)
        feasible = False

    rate = np.minimum(b / size_mb, fmax)
    b = rate * size_mb
    if b.sum() > budget:  # floating-point excess only
        rate *= budget / b.sum() * (1 - 1e-12)
        b = rate * size_mb
    unmeasured = [n for n, ok in zip(names, measured) if not ok]
    if unmeasured:
        status += f"; size not measured yet for {', '.join(unmeasured)} (assumed {assumed_message_bytes:.0f} B)"
    share = (100.0 / budget) * b
    degraded = rate < fmin * (1 - 1e-9)
    columns = zip(
        names,
        priority.tolist(),
        rate.tolist(),
        fmin.tolist(),
        fmax.tolist(),
        (size_mb * _BYTES_PER_MB).tolist(),
        b.tolist(),
        share.tolist(),
        degraded.tolist(),
        measured.tolist(),
    )
    robots = tuple(RobotAllocation(*row) for row in columns)
    return Allocation(robots, budget, float(b.sum()), feasible, status)


def _degrade(size_mb, fmin, priority, w, lo, budget, floor_rate_hz):
    """Minimum rates do not fit: lower priority classes give up bandwidth first, down to a floor."""
    floor = size_mb * np.minimum(fmin, floor_rate_hz)
    b = lo.copy()
    for level in sorted(set(priority.tolist())):
        members = priority == level
        others = b[~members].sum()
        if others + floor[members].sum() <= budget:
            b[members] = water_fill(w[members], floor[members], lo[members], budget - others)
            return b, (
                f"infeasible: minimum rates need {lo.sum():.3f} MB/s > budget {budget:.3f} MB/s; "
                f"priority-{level} robots below their minimum"
            )
        b[members] = floor[members]
    b = floor * (budget / floor.sum())
    return b, (
        f"infeasible: even the floor rates need {floor.sum():.3f} MB/s > budget {budget:.3f} MB/s; "
        f"every rate scaled by {budget / floor.sum():.3f}"
    )
