"""Online estimate of the link's available bandwidth from what it delivers (delay-based), no ROS.

The paper assumes the available bandwidth is known in advance (section 5). Here the digital twin
side's statistics (`/tissue/stats`: delivered MB/s and latency) drive an estimator in the style of
delay-based congestion control:

- the latency baseline is the smallest latency seen over the last `baseline_window_s`;
- queueing delay = latency - baseline. Above `queue_threshold_ms` the link is saturated, so what
  it delivers is its capacity: the estimate becomes delivered x a factor below 1 so the queue
  drains within about `drain_time_s` (at most `drain_factor`, at least 0.5), never more than it was;
- otherwise the estimate grows by `increase_per_s` (multiplicative, per second) up to
  `max_mbps`, and never stays below what was just delivered.

Time is passed in, so the estimator is unit-tested against a simulated queue.
"""
import collections
import math


class BandwidthEstimator:
    def __init__(self, initial_mbps, max_mbps=None, min_mbps=1.0, queue_threshold_ms=25.0,
                 increase_per_s=0.25, drain_factor=0.9, drain_time_s=2.0, baseline_window_s=10.0):
        for name, value in (("initial_mbps", initial_mbps), ("min_mbps", min_mbps),
                            ("queue_threshold_ms", queue_threshold_ms), ("increase_per_s", increase_per_s),
                            ("drain_time_s", drain_time_s), ("baseline_window_s", baseline_window_s)):
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
        self.drain_factor = float(drain_factor)
        self.drain_time_s = float(drain_time_s)
        self.baseline_window_s = float(baseline_window_s)
        self.estimate_mbps = min(max(float(initial_mbps), self.min_mbps), self.max_mbps)
        self.congested = False
        self.ignored_samples = 0
        self._latencies = collections.deque()
        self._last_time_s = None

    @property
    def baseline_ms(self):
        return min(v for _, v in self._latencies) if self._latencies else math.nan

    def update(self, now_s, delivered_mbps, latency_ms):
        """Feed one measurement window; returns the new estimate in Mbit/s.

        NaN, infinite or negative inputs (e.g. no message in the window) are counted and ignored.
        """
        if not all(math.isfinite(v) for v in (now_s, delivered_mbps, latency_ms)) \
                or delivered_mbps < 0 or latency_ms < 0:
            self.ignored_samples += 1
            return self.estimate_mbps
        dt = 0.0 if self._last_time_s is None else max(0.0, now_s - self._last_time_s)
        self._last_time_s = now_s
        self._latencies.append((now_s, latency_ms))
        while self._latencies and self._latencies[0][0] < now_s - self.baseline_window_s:
            self._latencies.popleft()
        queueing_ms = latency_ms - self.baseline_ms
        self.congested = queueing_ms > self.queue_threshold_ms
        if self.congested:
            factor = min(self.drain_factor, max(0.5, 1.0 - queueing_ms / (1000.0 * self.drain_time_s)))
            estimate = min(self.estimate_mbps, factor * delivered_mbps)
        else:
            estimate = max(self.estimate_mbps * (1.0 + self.increase_per_s) ** dt, delivered_mbps)
        self.estimate_mbps = min(max(estimate, self.min_mbps), self.max_mbps)
        return self.estimate_mbps
