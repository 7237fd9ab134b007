"""Sharing one simulator thread fairly between the fleet's sensors (pure Python).

`SensorScheduler` runs the sensor whose capture is most overdue (earliest deadline first). A
sensor that falls more than one period behind skips the missed captures instead of bursting,
so when the machine cannot keep every nominal rate each sensor gets a share in proportion to
its rate and none starves. `RateMeter` measures what was achieved.
"""

import collections


class RateMeter:
    """Events per second over the last `window_s` seconds."""

    def __init__(self, window_s=5.0):
        self.window_s = window_s
        self._times = collections.deque()

    def tick(self, now_s):
        self._times.append(now_s)
        self._trim(now_s)

    def _trim(self, now_s):
        while self._times and self._times[0] < now_s - self.window_s:
            self._times.popleft()

    def rate_hz(self, now_s):
        self._trim(now_s)
        if len(self._times) < 2:
            return 0.0
        span = max(now_s - self._times[0], self._times[-1] - self._times[0])
        return (len(self._times) - 1) / span if span > 0 else 0.0


class SensorScheduler:
    """Earliest-deadline-first over periodic tasks keyed by name, with achieved-rate meters."""

    def __init__(self, rates_hz, now_s, window_s=5.0):
        for name, rate in rates_hz.items():
            if not rate > 0:
                raise ValueError(f"sensor '{name}': rate must be positive, got {rate}")
        self.periods = {name: 1.0 / rate for name, rate in rates_hz.items()}
        # Stagger the first captures so the sensors do not all fire in the same instant.
        count = max(len(rates_hz), 1)
        self.due = {name: now_s + i * min(self.periods.values()) / count for i, name in enumerate(rates_hz)}
        self.meters = {name: RateMeter(window_s) for name in rates_hz}
        self.runs = {name: 0 for name in rates_hz}
        self.skipped = {name: 0 for name in rates_hz}

    def set_rate(self, name, rate_hz, now_s):
        """Run `name` at `rate_hz` from now on; a faster rate takes effect at once."""
        if not rate_hz > 0:
            raise ValueError(f"sensor '{name}': rate must be positive, got {rate_hz}")
        self.periods[name] = 1.0 / rate_hz
        self.due[name] = min(self.due[name], now_s + self.periods[name])

    def next(self, exclude=()):
        """(name, due time) of the task to run next (not in `exclude`), or (None, inf) if none."""
        candidates = [n for n in self.due if n not in exclude]
        if not candidates:
            return None, float("inf")
        name = min(candidates, key=self.due.get)
        return name, self.due[name]

    def done(self, name, started_s, finished_s):
        """Record a run of `name` that began at started_s and schedule its next one."""
        self.meters[name].tick(started_s)
        self.runs[name] += 1
        period = self.periods[name]
        due = self.due[name] + period
        if due < finished_s - period:
            self.skipped[name] += int((finished_s - due) / period)
            due = finished_s
        self.due[name] = due

    def achieved_hz(self, name, now_s):
        return self.meters[name].rate_hz(now_s)


class StepTimer:
    """Mean and longest duration of a loop's passes since the last `reset` (for diagnostics)."""

    def __init__(self):
        self.reset()

    def reset(self):
        self.count, self.total_s, self.longest_s = 0, 0.0, 0.0

    def add(self, seconds):
        self.count += 1
        self.total_s += seconds
        self.longest_s = max(self.longest_s, seconds)

    @property
    def mean_ms(self):
        return 1000.0 * self.total_s / self.count if self.count else 0.0

    @property
    def max_ms(self):
        return 1000.0 * self.longest_s
