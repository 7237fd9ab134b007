"""LEGACY: the delay-based estimator the manager used until issue 23; kept only as the anchor of
`bench/estimator_bench.py` (not imported by the manager or its node; `estimation` replaced it).

It read a busy CPU as congestion (57.8 -> 7.2 Mbit/s on an idle 60 Mbit/s link) and could not
lower the estimate when the link shrank under a small load. What it did:

The paper assumes the available bandwidth is known in advance (section 5). Here the digital twin
side's statistics (`/tissue/stats`: delivered MB/s and latency) drive an estimator in the style of
delay-based congestion control:

- the latency baseline is the smallest latency seen over the last `baseline_window_s`;
- queueing delay = latency - baseline. Above `queue_threshold_ms` *and* with the link delivering
  clearly less than the physical side sends (`delivered < backlog_ratio x sent`) or the latency
  rising by more than `rise_ms` for three updates in a row (a queue is building), the link is saturated, so what it delivers is its capacity: the estimate becomes
  delivered x a factor below 1 so the queue drains within about `drain_time_s` (at most
  `drain_factor`), never less than half the old estimate and at most once per `holdoff_s`
  (the effect of a decrease shows only one statistics window later);
- high latency without a building queue (a busy CPU, or a queue that is already draining), or
  queueing above half the threshold, holds the estimate;
- otherwise the estimate grows by `increase_per_s` (multiplicative, per second; at least
  `increase_min_mbps_per_s`), faster the longer the latency has stayed low (x(1 + quiet s / 5),
  at most x3, convex like CUBIC away from its last maximum), up to `max_mbps`, and never stays below what was just delivered;
  within +-10 % of the rate delivered at the last saturation, and for `slow_probe_s` after it, it
  probes five times slower, so the queue it builds while probing stays small (as CUBIC does near
  its last maximum) without getting stuck at a saturation point measured while a queue drained.

The default threshold (60 ms of queueing) sits below the paper's 100 ms latency bound and above
the latency noise of a busy 2-core machine.

Without `sent` (unknown), high latency alone counts as saturation. A window in which nothing
arrives although the physical side sends (a stalled link) halves the estimate.

Time is passed in, so the estimator is unit-tested against a simulated queue.
"""

import collections
import math


class LegacyDelayEstimator:
    """The old hand-tuned queueing-delay rule (see the module docstring); bench anchor only."""

    def __init__(
        self,
        initial_mbps,
        max_mbps=None,
        min_mbps=1.0,
        queue_threshold_ms=60.0,
        increase_per_s=0.25,
        increase_min_mbps_per_s=4.0,
        drain_factor=0.9,
        drain_time_s=2.0,
        baseline_window_s=10.0,
        backlog_ratio=0.85,
        holdoff_s=1.0,
        rise_ms=5.0,
        slow_probe_s=5.0,
    ):
        for name, value in (
            ("initial_mbps", initial_mbps),
            ("min_mbps", min_mbps),
            ("queue_threshold_ms", queue_threshold_ms),
            ("increase_per_s", increase_per_s),
            ("drain_time_s", drain_time_s),
            ("baseline_window_s", baseline_window_s),
        ):
            if not math.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be > 0, got {value!r}")
        if not 0 < drain_factor <= 1:
            raise ValueError(f"drain_factor must be in (0, 1], got {drain_factor!r}")
        self.max_mbps = float(initial_mbps if max_mbps is None else max_mbps)
        if self.max_mbps < min_mbps:
            raise ValueError(f"max_mbps ({self.max_mbps}) < min_mbps ({min_mbps})")
        self.min_mbps = float(min_mbps)
        self.queue_threshold_ms = float(queue_threshold_ms)
        self.increase_per_s = float(increase_per_s)
        self.increase_min_mbps_per_s = max(0.0, float(increase_min_mbps_per_s))
        self.drain_factor = float(drain_factor)
        self.drain_time_s = float(drain_time_s)
        if not 0 < backlog_ratio <= 1:
            raise ValueError(f"backlog_ratio must be in (0, 1], got {backlog_ratio!r}")
        self.backlog_ratio = float(backlog_ratio)
        self.holdoff_s = max(0.0, float(holdoff_s))
        self.rise_ms = float(rise_ms)
        self.slow_probe_s = float(slow_probe_s)
        self._last_decrease_s = -math.inf
        self._saturation_mbps = math.nan
        self._quiet_since_s = math.nan
        self.baseline_window_s = float(baseline_window_s)
        self.estimate_mbps = min(max(float(initial_mbps), self.min_mbps), self.max_mbps)
        self.congested = False
        self.ignored_samples = 0
        self._latencies = collections.deque()
        self._last_time_s = None
        self._last_latency_ms = math.nan
        self._rising = 0

    def _stalled(self, now_s):
        """Nothing arrives although the physical side sends: back off (halve, once per holdoff)."""
        self.congested = True
        self._last_time_s = now_s
        if now_s - self._last_decrease_s >= self.holdoff_s:
            self._last_decrease_s = now_s
            self.estimate_mbps = max(self.min_mbps, 0.5 * self.estimate_mbps)
        return self.estimate_mbps

    def resume(self, now_s):
        """The link is back after an outage: the next update grows from `now_s`, not from before
        the outage (the estimate itself is kept: the allocation resumes from it)."""
        self._last_time_s = now_s
        self._quiet_since_s = now_s
        self._rising = 0
        self._last_latency_ms = math.nan

    @property
    def baseline_ms(self):
        return min(v for _, v in self._latencies) if self._latencies else math.nan

    def update(self, now_s, delivered_mbps, latency_ms, sent_mbps=None):
        """Feed one measurement window (`sent_mbps`: what the physical side sent in it, if known);
        returns the new estimate in Mbit/s.

        NaN, infinite or negative inputs (e.g. no message in the window) are counted and ignored.
        """
        known_sent = sent_mbps is not None and math.isfinite(sent_mbps) and sent_mbps >= 0
        stalled = (
            known_sent
            and sent_mbps > self.min_mbps
            and delivered_mbps == 0
            and math.isfinite(now_s)
            and not math.isfinite(latency_ms)
        )
        if stalled:
            return self._stalled(now_s)
        if (
            not all(math.isfinite(v) for v in (now_s, delivered_mbps, latency_ms))
            or delivered_mbps < 0
            or latency_ms < 0
        ):
            self.ignored_samples += 1
            return self.estimate_mbps
        dt = 0.0 if self._last_time_s is None else max(0.0, now_s - self._last_time_s)
        self._last_time_s = now_s
        self._latencies.append((now_s, latency_ms))
        while self._latencies and self._latencies[0][0] < now_s - self.baseline_window_s:
            self._latencies.popleft()
        queueing_ms = latency_ms - self.baseline_ms
        delayed = queueing_ms > self.queue_threshold_ms
        self._rising = self._rising + 1 if latency_ms > self._last_latency_ms + self.rise_ms else 0
        self._last_latency_ms = latency_ms
        building = not known_sent or delivered_mbps < self.backlog_ratio * sent_mbps or self._rising >= 3
        self.congested = delayed and building
        if self.congested:
            self._quiet_since_s = now_s
        if self.congested and now_s - self._last_decrease_s < self.holdoff_s:
            estimate = self.estimate_mbps
        elif self.congested:
            self._last_decrease_s = now_s
            self._saturation_mbps = delivered_mbps
            factor = min(self.drain_factor, max(0.5, 1.0 - queueing_ms / (1000.0 * self.drain_time_s)))
            estimate = min(self.estimate_mbps, max(0.5 * self.estimate_mbps, factor * delivered_mbps))
        elif delayed or queueing_ms > 0.5 * self.queue_threshold_ms:
            estimate = self.estimate_mbps
            self._quiet_since_s = now_s
        else:
            near = 0.9 * self._saturation_mbps <= self.estimate_mbps <= 1.1 * self._saturation_mbps
            if near and now_s - self._last_decrease_s < self.slow_probe_s:
                grown = self.estimate_mbps * (1.0 + self.increase_per_s / 5.0) ** dt
            else:
                if math.isnan(self._quiet_since_s):
                    self._quiet_since_s = now_s
                boost = min(3.0, 1.0 + (now_s - self._quiet_since_s) / 5.0)
                grown = max(
                    self.estimate_mbps * (1.0 + boost * self.increase_per_s) ** dt,
                    self.estimate_mbps + self.increase_min_mbps_per_s * dt,
                )
            estimate = max(grown, delivered_mbps)
        self.estimate_mbps = min(max(estimate, self.min_mbps), self.max_mbps)
        return self.estimate_mbps
