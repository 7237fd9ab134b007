"""Per-level message size of one managed stream, learned online from what its encoder produced.

The encoder (the cloud's rate limiter, the video pipeline) reports the level its messages were
produced at and their mean size at that level alone (cps_msgs/RateLimiterStatus `level`,
`level_mean_message_bytes`). Rules:

- before any report: fleet.yaml's `bytes_prior` per level;
- the level last reported: its reported size, at once (no smoothing of ours: the encoder's window
  is the only averaging, so a tenfold jump counts from the first status that shows it);
- any other level: the last reported size scaled by the priors' ratio (prior_k / prior_ref),
  or that level's own measurement if it is younger than `stale_s` and larger (a level measured
  recently keeps its own size unless the scene has since grown: never the smaller of the two, so
  a scene change seen at one level raises every level's estimate at once).
"""

import math
from typing import Optional, Sequence

# A level's own measurement counts this long after it was reported (s).
DEFAULT_STALE_S = 10.0
# An estimate moving by more than this fraction is worth an allocation now.
SIZE_CHANGE_FRACTION = 0.1


class LevelSizes:
    def __init__(self, priors_bytes: Sequence[float], stale_s: float = DEFAULT_STALE_S):
        priors = [float(p) for p in priors_bytes]
        if not priors or any(not math.isfinite(p) or p <= 0 for p in priors):
            raise ValueError(f"priors must be finite sizes > 0 bytes, got {list(priors_bytes)}")
        if not math.isfinite(stale_s) or stale_s < 0:
            raise ValueError(f"stale_s must be >= 0 s, got {stale_s!r}")
        self.priors = tuple(priors)
        self.stale_s = float(stale_s)
        self._measured = [math.nan] * len(priors)  # last reported size per level
        self._at_s = [math.nan] * len(priors)
        self._ref: Optional[int] = None  # the level last reported
        self._now_s = -math.inf

    @property
    def levels(self):
        return len(self.priors)

    @property
    def reference_level(self):
        """The level last reported (None before the first report)."""
        return self._ref

    def report(self, level, mean_bytes, now_s) -> bool:
        """The encoder produced messages of `mean_bytes` at `level` (status received at `now_s`).
        Returns True if any level's estimate moved by more than SIZE_CHANGE_FRACTION. ValueError
        for a level outside the levels, a size that is not finite and > 0, or a time that is not."""
        if isinstance(level, bool) or not isinstance(level, int) or not 0 <= level < self.levels:
            raise ValueError(f"level {level!r} outside the {self.levels} levels")
        if not _positive(mean_bytes):
            raise ValueError(f"size {mean_bytes!r} is not a size")
        if not math.isfinite(now_s):
            raise ValueError(f"time {now_s!r} is not a time")
        before = self.estimate(now_s)
        self._measured[level], self._at_s[level], self._ref = float(mean_bytes), float(now_s), level
        self._now_s = max(self._now_s, float(now_s))
        after = self.estimate(now_s)
        return any(abs(a - b) > SIZE_CHANGE_FRACTION * b for a, b in zip(after, before))

    def estimate(self, now_s=None):
        """Estimated size per message at every level, bytes (finest first)."""
        now_s = self._now_s if now_s is None else now_s
        if self._ref is None:
            return self.priors
        ref = self._measured[self._ref]
        out = []
        for k, prior in enumerate(self.priors):
            if k == self._ref:
                out.append(ref)
                continue
            scaled = ref * prior / self.priors[self._ref]
            own = self._measured[k]
            fresh = math.isfinite(own) and 0.0 <= now_s - self._at_s[k] <= self.stale_s
            out.append(max(own, scaled) if fresh else scaled)
        return tuple(out)

    def measured(self, now_s=None):
        """Per level: is the estimate the level's own measurement (reference or fresh)?"""
        now_s = self._now_s if now_s is None else now_s
        return tuple(
            k == self._ref or (math.isfinite(self._measured[k]) and 0.0 <= now_s - self._at_s[k] <= self.stale_s)
            for k in range(self.levels)
        )


def _positive(value):
    try:
        return math.isfinite(float(value)) and float(value) > 0
    except (TypeError, ValueError):
        return False
