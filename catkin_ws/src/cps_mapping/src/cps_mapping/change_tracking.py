"""Persistence of the live change detection (no rospy): a change is reported only after it was
found in `min_cycles` consecutive detection cycles, and withdrawn as soon as a cycle no longer
finds it (later evidence contradicts it: the place was seen occupied again, or its cluster fell
apart). Dynablox and DUFOMap both wait for repeated evidence before they call space free or
dynamic (docs/monitoring.md).

The same change in two cycles: same kind, box centres within `same_change_m` horizontally. Its
first view is the earliest any cycle found (the stamp of the first cloud that saw its place): the
change grows as more of it is seen, and a later cycle's cluster may start from a later cloud.
"""

import dataclasses
import math
from typing import List, Optional

MIN_CYCLES = 2
SAME_CHANGE_M = 0.5


@dataclasses.dataclass
class TrackedChange:
    change: object  # cps_mapping.change_detection.Change, the latest cycle's
    first_seen_s: float  # the first cycle that found it
    cycles: int  # consecutive cycles that found it
    reported_s: Optional[float] = None  # when it was first reported (min_cycles reached)
    first_view_s: Optional[float] = None  # the first cloud that saw its place (its stamp), if known


def _place(change):
    return ((change.min_m[0] + change.max_m[0]) / 2, (change.min_m[1] + change.max_m[1]) / 2)


class ChangeTracker:
    def __init__(self, min_cycles=MIN_CYCLES, same_change_m=SAME_CHANGE_M):
        if min_cycles < 1 or not same_change_m > 0:
            raise ValueError("min_cycles must be >= 1 and same_change_m positive")
        self.min_cycles, self.same_change_m = min_cycles, same_change_m
        self.tracked: List[TrackedChange] = []
        self.withdrawn: List[TrackedChange] = []  # reported once, contradicted later

    def _match(self, change, pool):
        x, y = _place(change)
        best = None
        for t in pool:
            tx, ty = _place(t.change)
            d = math.hypot(x - tx, y - ty)
            if t.change.kind == change.kind and d <= self.same_change_m and (best is None or d < best[0]):
                best = (d, t)
        return best[1] if best else None

    def update(self, changes, now_s) -> List[TrackedChange]:
        """Feed one cycle's changes; returns the reported ones (persisted `min_cycles` cycles)."""
        pool, kept = list(self.tracked), []
        for change in changes:
            t = self._match(change, pool)
            if t is None:
                t = TrackedChange(change, now_s, 0)
            else:
                pool.remove(t)
            t.change, t.cycles = change, t.cycles + 1
            views = [v for v in (t.first_view_s, getattr(change, "first_view_s", None)) if v is not None]
            t.first_view_s = min(views) if views else None
            if t.reported_s is None and t.cycles >= self.min_cycles:
                t.reported_s = now_s
            kept.append(t)
        self.withdrawn += [t for t in pool if t.reported_s is not None]
        self.tracked = kept
        return self.reported()

    def reported(self) -> List[TrackedChange]:
        return [t for t in self.tracked if t.reported_s is not None]

    def candidates(self) -> List[TrackedChange]:
        """Every change the last cycle found, reported or still being confirmed."""
        return list(self.tracked)
