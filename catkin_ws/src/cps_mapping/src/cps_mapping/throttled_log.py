"""Warnings logged at most once per period and key (a robot's repeated problem: one line, not one
per cloud)."""

import logging
import math
import time

WARN_EVERY_S = 5.0


class ThrottledLog:
    """`warn(key, message)`: logs `message` unless the same `key` was logged within `period_s`."""

    def __init__(self, log, clock=time.monotonic):
        self.log, self.clock = log, clock
        self._last = {}

    def warn(self, key, message, period_s=WARN_EVERY_S, level=logging.WARNING):
        now = self.clock()
        if now - self._last.get(key, -math.inf) >= period_s:
            self._last[key] = now
            self.log.log(level, message)
