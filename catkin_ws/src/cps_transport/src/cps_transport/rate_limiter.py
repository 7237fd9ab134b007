"""A rate limiter that delivers the rate it is set to (time injected, no ROS).

topic_tools' throttle forwards a message only if 1/rate has passed since the last one, so an
input of 10 Hz asked for 8 Hz gives 5 Hz (every second message is 0.1 s < 0.125 s early).
Here every message earns `rate x dt` credit and costs 1, with at most `burst` whole credits
banked (plus the fraction): the fractional credit always carries over, so whenever the input is
faster than the set rate the output averages exactly the set rate (10 Hz -> 8 Hz forwards 4 of every 5).
"""

import collections

# The window of a limiter's input and output rates (its status's input_rate_hz), s.
RATE_WINDOW_S = 2.0


class WindowRate:
    """Messages per second and mean size over the last `window_s` seconds of arrivals."""

    def __init__(self, window_s=RATE_WINDOW_S):
        if not window_s > 0:
            raise ValueError(f"window_s must be > 0, got {window_s}")
        self.window_s = window_s
        self._events = collections.deque()  # (time_s, size_bytes)
        self._bytes = 0

    def add(self, now_s, size_bytes=0):
        self._events.append((now_s, size_bytes))
        self._bytes += size_bytes
        self._expire(now_s)

    def _expire(self, now_s):
        while self._events and self._events[0][0] < now_s - self.window_s:
            self._bytes -= self._events.popleft()[1]

    def rate_hz(self, now_s):
        """(n - 1) / (last - first) over the window (as rostopic hz), 0 with fewer than two."""
        self._expire(now_s)
        if len(self._events) < 2:
            return 0.0
        span = self._events[-1][0] - self._events[0][0]
        return (len(self._events) - 1) / span if span > 0 else 0.0

    def mean_bytes(self, now_s):
        self._expire(now_s)
        return self._bytes / len(self._events) if self._events else 0.0


class RateLimiter:
    """Token bucket: `allow(now_s)` says whether the message arriving now is forwarded."""

    def __init__(self, rate_hz, burst=2.0, window_s=RATE_WINDOW_S):
        self.burst = float(burst)
        if self.burst < 1.0:
            raise ValueError(f"burst must be >= 1 message, got {burst}")
        self.rate_hz = self._checked(rate_hz)
        self._credit = 1.0
        self._last_s = None
        self.received = 0
        self.forwarded = 0
        self.input = WindowRate(window_s)
        self.output = WindowRate(window_s)

    @staticmethod
    def _checked(rate_hz):
        rate_hz = float(rate_hz)
        if not rate_hz > 0 or rate_hz != rate_hz or rate_hz == float("inf"):
            raise ValueError(f"rate_hz must be a finite number > 0, got {rate_hz}")
        return rate_hz

    def set_rate(self, rate_hz):
        """Change the rate; credit earned so far stays (capped), so the change is immediate."""
        self.rate_hz = self._checked(rate_hz)

    def allow(self, now_s, size_bytes=0):
        self.received += 1
        self.input.add(now_s, size_bytes)
        if self._last_s is not None:
            elapsed = max(0.0, now_s - self._last_s)
            credit = self._credit + elapsed * self.rate_hz
            # At most `burst` whole messages banked, but the fraction always carries over: a cap of
            # exactly `burst` would drop it and, at burst 1, alias like topic_tools' throttle.
            self._credit = min(credit, self.burst + credit % 1.0)
        self._last_s = now_s
        if self._credit >= 1.0:
            self._credit -= 1.0
            self.forwarded += 1
            self.output.add(now_s, size_bytes)
            return True
        return False
