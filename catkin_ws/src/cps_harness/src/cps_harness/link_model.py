"""A simulated constrained link for the estimator's tests and bench (never used at run time), no ROS.

Fluid model, stepped every `tick_s`:

- the sender (the rate limiters and the robots' bridge) hands min(demand, allowed) to the link,
  allowed = (1 - reserve) x the estimator's allocation target, applied `control_lag_s` after the
  estimate changed (the manager allocates, the limiters obey);
- a tbf-like bottleneck: one FIFO drained at the capacity (x (1 - loss): retransmissions, minus
  the reverse traffic of a shared medium), holding at most `queue_limit_mbit` (drops beyond);
  capacity 0 is an outage;
- the receiver (the twin) reads at most `receiver_mbps` while a `CpuHog` is on: then it is the
  bottleneck (TCP's rwnd_limited) and its echo of the heartbeat is late by `extra_delay_s`;
- every `report_s` the far side reports a `LinkReport` (delivered, sent, offered, app-limited,
  heartbeat RTTs, receiver behind). The report crosses the link: none arrives during an outage.
  The link health says down `liveliness_s` after a cut and up at the restore (as Zenoh
  liveliness does), and the subject is paused meanwhile as the manager pauses it.

The subject is anything with `update(report, latency_ms) -> allocation Mbit/s`,
`resume(now_s)`, `estimate_mbps` and `capacity_mbps` (see `NewEstimatorSubject`); the legacy
anchor is wrapped the same way in bench/estimator_bench.py. Deterministic: jitter from a seeded RNG.
"""

import collections
import dataclasses
import math
import random
from typing import Callable, List, Sequence, Tuple

from cps_bw_manager.estimation import DeliveryRateEstimator, LinkReport


@dataclasses.dataclass(frozen=True)
class CpuHog:
    """The twin's CPU is busy from `start_s` to `end_s`: it processes at most `receiver_mbps`."""

    start_s: float
    end_s: float
    receiver_mbps: float
    extra_delay_s: float = 0.3


@dataclasses.dataclass(frozen=True)
class TraceRow:
    """One report interval as the judge sees it (rates in Mbit/s averaged over the interval)."""

    t_s: float
    capacity_mbps: float  # the true capacity (tc rate); 0 during an outage
    estimate_mbps: float  # the subject's capacity estimate (what the accuracy targets judge)
    allocation_mbps: float  # the subject's allocation target (what the manager allocates from)
    allowed_mbps: float  # what the sender was allowed at the end of the interval
    ingress_mbps: float  # what entered the link
    delivered_mbps: float
    offered_mbps: float  # the fleet's demand
    queue_mbit: float
    link_up: bool  # the link health's view (the subject is paused while False)
    receiver_behind: bool
    # what the link carries this way at the report: the tc rate less the loss and, on a shared
    # medium, the other way's traffic (all a delivery-rate estimate can see); 0 during an outage
    goodput_mbps: float = math.nan


def steps_capacity(steps: Sequence[Tuple[float, float]]) -> Callable[[float], float]:
    """capacity_of(t) from [(at_s, capacity_mbps), ...] (the first applies from 0); 0 = outage."""
    ordered = sorted(steps)

    def capacity_of(t):
        value = ordered[0][1]
        for at_s, mbps in ordered:
            if t >= at_s:
                value = mbps
        return value

    return capacity_of


class NewEstimatorSubject:
    """`DeliveryRateEstimator` behind the simulator's interface; `known` says which report fields
    it gets (default all; ("delivered", "sent", "offered") is what the manager has today)."""

    def __init__(
        self,
        estimator: DeliveryRateEstimator,
        known=("delivered", "sent", "offered", "app_limited", "rtt", "receiver_behind"),
    ):
        self.estimator = estimator
        self.known = set(known)

    def update(self, report: LinkReport, latency_ms):
        k = self.known
        report = dataclasses.replace(
            report,
            sent_mbps=report.sent_mbps if "sent" in k else math.nan,
            offered_mbps=report.offered_mbps if "offered" in k else math.nan,
            app_limited=report.app_limited if "app_limited" in k else None,
            rtt_s=report.rtt_s if "rtt" in k else (),
            receiver_behind=report.receiver_behind if "receiver_behind" in k else None,
        )
        return self.estimator.update(report)

    def resume(self, now_s):
        self.estimator.resume(now_s)

    @property
    def estimate_mbps(self):
        return self.estimator.estimate_mbps

    @property
    def capacity_mbps(self):
        return self.estimator.capacity_mbps


@dataclasses.dataclass
class LinkModel:
    """The link, the sender and the receiver (module docstring); `run` drives a subject over it."""

    capacity_of: Callable[[float], float]
    demand_of: Callable[[float], float]
    base_rtt_s: float = 0.004
    jitter_s: float = 0.0  # one-way delay jitter (uniform +-)
    loss_fraction: float = 0.0
    reverse_mbps: float = 0.0  # traffic the other way on a shared medium
    queue_limit_mbit: float = 4.0  # tbf queue + the bridge's buffer
    hogs: Sequence[CpuHog] = ()
    reserve_fraction: float = 0.04
    report_s: float = 0.5
    report_offset_s: float = 0.0  # reports at offset + k x report_s (so steps need not fall on one)
    # rates in a report averaged over this sliding window (0: the report's own interval, as a
    # bridge counting bytes per interval would; 2: today's /tissue/stats and limiter status)
    measure_window_s: float = 0.0
    tick_s: float = 0.01
    control_lag_s: float = 0.1
    liveliness_s: float = 1.0
    heartbeat_s: float = 0.1
    seed: int = 1

    def _hog(self, t):
        return next((h for h in self.hogs if h.start_s <= t < h.end_s), None)

    def run(self, subject, duration_s) -> List[TraceRow]:
        rng = random.Random(self.seed)
        ticks_per_report = max(1, int(round(self.report_s / self.tick_s)))
        queue = 0.0
        allowed = (1 - self.reserve_fraction) * subject.estimate_mbps
        pending = []  # (apply_at_s, allowed) from the control lag
        up = True
        trace, acc = [], None
        tick, cut_since, last_report_s = 0, None, 0.0
        history = collections.deque()  # (t, ingress Mbit, delivered Mbit, offered Mbit) per tick
        offset_ticks = int(round(self.report_offset_s / self.tick_s)) % ticks_per_report
        while tick * self.tick_s < duration_s - 1e-9:
            if acc is None:
                acc = dict(
                    ingress=0.0,
                    delivered=0.0,
                    offered=0.0,
                    app_limited=True,
                    queue_empty=False,
                    behind=False,
                    rtt=[],
                    latency=[],
                    delivered_while_cut=False,
                    cut=False,
                )
            t = tick * self.tick_s
            while pending and pending[0][0] <= t + 1e-9:
                allowed = pending.pop(0)[1]
            capacity = self.capacity_of(t)
            demand = self.demand_of(t)
            hog = self._hog(t)
            link_rate = max(0.0, capacity * (1 - self.loss_fraction) - self.reverse_mbps) if capacity > 0 else 0.0
            drain_rate = min(link_rate, hog.receiver_mbps) if hog else link_rate
            ingress = min(demand, allowed)
            queue += ingress * self.tick_s
            out = min(queue, drain_rate * self.tick_s)
            queue = min(self.queue_limit_mbit, queue - out)
            history.append((t, ingress * self.tick_s, out, demand * self.tick_s))
            while history and history[0][0] < t + self.tick_s - self.measure_window_s - 1e-9:  # tick = [t, t+dt)
                history.popleft()
            acc["ingress"] += ingress * self.tick_s
            acc["delivered"] += out
            acc["offered"] += demand * self.tick_s
            acc["app_limited"] &= demand <= allowed
            acc["queue_empty"] |= queue <= 1e-9
            acc["behind"] |= bool(hog) and hog.receiver_mbps < link_rate and queue > 1e-9
            acc["cut"] |= capacity <= 0
            queue_delay_s = queue / drain_rate if drain_rate > 0 else math.inf
            if tick % max(1, int(round(self.heartbeat_s / self.tick_s))) == 0 and math.isfinite(queue_delay_s):
                extra = hog.extra_delay_s if hog else 0.0
                jitter = rng.uniform(-self.jitter_s, self.jitter_s) + rng.uniform(-self.jitter_s, self.jitter_s)
                acc["rtt"].append(max(1e-4, self.base_rtt_s + queue_delay_s + extra + jitter))
                acc["latency"].append(1000.0 * (self.base_rtt_s / 2 + queue_delay_s + extra))
            tick += 1
            now = tick * self.tick_s
            # link health (liveliness): down `liveliness_s` into an outage, up at its end
            cut_since = (cut_since if cut_since is not None else t) if capacity <= 0 else None
            if up and cut_since is not None and now - cut_since >= self.liveliness_s - 1e-9:
                up = False
            elif not up and cut_since is None:
                up = True
                subject.resume(now)
            if (tick - offset_ticks) % ticks_per_report:
                continue
            interval, last_report_s = now - last_report_s, now
            if self.measure_window_s > 0:
                span = min(self.measure_window_s, now)
                sent, delivered, offered = (sum(h[i] for h in history) / span for i in (1, 2, 3))
            else:
                sent, delivered, offered = (acc[k] / interval for k in ("ingress", "delivered", "offered"))
            report = LinkReport(
                now_s=now,
                interval_s=interval,
                delivered_mbps=delivered,
                sent_mbps=sent,
                offered_mbps=offered,
                app_limited=acc["app_limited"] and acc["queue_empty"],
                rtt_s=tuple(acc["rtt"]),
                receiver_behind=acc["behind"],
            )
            if up and not acc["cut"]:
                latency = acc["latency"]
                latency_ms = sorted(latency)[len(latency) // 2] if latency else math.nan
                subject.update(report, latency_ms)
                pending.append((now + self.control_lag_s, (1 - self.reserve_fraction) * subject.estimate_mbps))
            trace.append(
                TraceRow(
                    now,
                    capacity,
                    subject.capacity_mbps,
                    subject.estimate_mbps,
                    allowed,
                    acc["ingress"] / interval,
                    acc["delivered"] / interval,
                    acc["offered"] / interval,
                    queue,
                    up,
                    acc["behind"],
                    link_rate,
                )
            )
            acc = None
        return trace


def settle_time_s(trace: Sequence[TraceRow], step_s, end_s, tolerance=0.15, truth="capacity_mbps"):
    """Seconds from `step_s` to the first report from which the capacity estimate stays within
    +-tolerance of the truth (`truth`: the row's field, the tc rate by default, or `goodput_mbps`)
    up to `end_s` (rows while the link is down are not judged; a report covers the interval before
    it, so 0.5 s is the soonest); inf if it never settles."""
    rows = [r for r in trace if step_s < r.t_s <= end_s and r.link_up and r.capacity_mbps > 0]
    settled_at = math.inf
    for r in rows:  # the first report of the final stretch within the band
        true = getattr(r, truth)
        inside = abs(r.estimate_mbps - true) <= tolerance * true
        settled_at = (r.t_s if math.isinf(settled_at) else settled_at) if inside else math.inf
    return settled_at - step_s


def ingress_over_capacity_s(trace: Sequence[TraceRow], step_s, end_s, interval_s=0.5):
    """(seconds from `step_s` until ingress first fits the capacity, the longest later run of
    report intervals with ingress over it) in (step_s, end_s]."""
    rows = [r for r in trace if step_s < r.t_s <= end_s and r.capacity_mbps > 0]
    first, longest, run, started = 0.0, 0.0, 0.0, False
    for r in rows:
        over = r.ingress_mbps > r.capacity_mbps * 1.001
        if not started:
            if over:
                first = r.t_s - step_s
                continue
            started = True
        run = run + interval_s if over else 0.0
        longest = max(longest, run)
    return first, longest


def mean_abs_error(trace: Sequence[TraceRow], start_s, end_s):
    """Mean |estimate - capacity| / capacity over the judged rows in (start_s, end_s]."""
    rows = [r for r in trace if start_s < r.t_s <= end_s and r.link_up and r.capacity_mbps > 0]
    return sum(abs(r.estimate_mbps - r.capacity_mbps) / r.capacity_mbps for r in rows) / max(1, len(rows))


def held_below_offered(trace: Sequence[TraceRow], exclude=()):
    """Report intervals where the fleet offered < 85 % of the capacity but was allowed less than it
    offered (link up; `exclude`: (start_s, end_s) spans not judged, e.g. just after an up step)."""
    bad = []
    for r in trace:
        if not r.link_up or r.capacity_mbps <= 0 or any(a < r.t_s <= b for a, b in exclude):
            continue
        if r.offered_mbps < 0.85 * r.capacity_mbps and r.allowed_mbps < 0.999 * r.offered_mbps:
            bad.append(r)
    return bad
