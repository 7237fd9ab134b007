"""What the map server can insert, measured in CPU time of its own insertion thread (cps_msgs/InsertCapacity).

Every cloud the insertion thread takes is timed with the thread's CPU clock (`time.thread_time`:
the CPU it used, not the wall time it waited for the GIL, the core or a transform), from taking
it out of its slot to the end of its insertion: deserialising, Draco decoding, the transform,
preparation and the ray casting. Clouds that fail (no transform, undecodable, invalid) cost CPU
too and count in the busy time. Over the last `window_s` the capacity at the insertion budget is

    clouds_per_s = budget_fraction * clouds inserted / CPU seconds      (likewise points, voxel updates)

i.e. what the insertion thread inserts when it gets `budget_fraction` of a core, at the cost per
cloud it just measured. Measured in CPU time it does not fall as the load rises (in wall time,
waiting counted as work: 321 -> 58 -> 37 clouds/s from 8 to 32 replayed robots, issue 37).
Superseded clouds (a robot's waiting cloud replaced by its newer one) and dropped clouds (lost: no
transform, undecodable, invalid, insertion failed) are counted apart.

The insertion budget is also enforced (`InsertionBudget`, in the same CPU seconds): within each
cycle of `cycle_s` the insertion thread uses at most `budget_fraction * cycle_s` of CPU, then
waits for the next cycle, so that publishing, services and the subscribers keep their share of
the twin's core; the robots' slots meanwhile keep only their newest cloud.
"""

import collections
import threading
import time
from typing import Optional

from std_msgs.msg import Header

from cps_msgs.msg import InsertCapacity

CAPACITY_WINDOW_S = 10.0


def voxel_updates_of(fused_map) -> Optional[int]:
    """Voxel steps the map's ray caster has walked so far (None if this map does not count them)."""
    return getattr(fused_map, "voxel_updates", None)


class InsertionMeter:
    """Insertions, superseded and dropped clouds over a sliding window; thread-safe."""

    def __init__(self, window_s=CAPACITY_WINDOW_S, budget_fraction=1.0, clock=time.monotonic, totals=None):
        """`totals()`: (clouds superseded, clouds dropped) so far, counted where they happen (the
        receive side, the insertion); the window's share is read from them at each `figures`."""
        if window_s <= 0 or not 0 < budget_fraction <= 1:
            raise ValueError(f"window_s {window_s} must be > 0 and budget_fraction {budget_fraction} in (0, 1]")
        self.window_s, self.budget_fraction, self.clock = window_s, budget_fraction, clock
        self._insertions = collections.deque()  # (t, clouds, points, voxel_updates, cpu_s)
        self._totals = totals or (lambda: (0, 0))
        self._samples = collections.deque([(clock(), 0, 0)])  # (t, superseded, dropped so far), one per figures()
        self._lock = threading.Lock()

    def inserted(self, clouds, points, voxel_updates, cpu_s):
        """`clouds` inserted with `points` and `voxel_updates`, in `cpu_s` of the thread's CPU."""
        with self._lock:
            self._insertions.append((self.clock(), clouds, points, voxel_updates, cpu_s))

    def spent(self, cpu_s):
        """CPU the insertion thread spent on a cloud it did not insert (it failed, or waits for its
        transform): part of the cost of what it inserts."""
        self.inserted(0, 0, 0, cpu_s)

    def _trim(self, now):
        while self._insertions and self._insertions[0][0] < now - self.window_s:
            self._insertions.popleft()
        while len(self._samples) > 1 and self._samples[1][0] <= now - self.window_s:
            self._samples.popleft()  # the oldest totals left are the window's start

    def figures(self):
        """The window's InsertCapacity fields (capacity 0 before the first insertion)."""
        superseded_total, dropped_total = self._totals()
        with self._lock:
            now = self.clock()
            self._samples.append((now, superseded_total, dropped_total))
            self._trim(now)
            clouds = sum(i[1] for i in self._insertions)
            points = sum(i[2] for i in self._insertions)
            updates = sum(i[3] for i in self._insertions)
            busy_s = sum(i[4] for i in self._insertions)
            superseded = superseded_total - self._samples[0][1]
            dropped = dropped_total - self._samples[0][2]
        rate = self.budget_fraction / busy_s if busy_s > 0 else 0.0
        return dict(
            window_s=self.window_s,
            clouds_inserted=clouds,
            busy_s=busy_s,
            clouds_per_s=clouds * rate,
            points_per_s=points * rate,
            voxel_updates_per_s=updates * rate,
            superseded=superseded,
            dropped=dropped,
        )

    def message(self, stamp, frame_id) -> InsertCapacity:
        return InsertCapacity(header=Header(stamp=stamp, frame_id=frame_id), **self.figures())


class InsertionBudget:
    """At most `fraction * cycle_s` of insertion in each cycle of `cycle_s`; thread-safe enough for
    one insertion thread (the only caller of `spend` and `wait_s`)."""

    def __init__(self, fraction, cycle_s=1.0, clock=time.monotonic):
        if not 0 < fraction <= 1 or cycle_s <= 0:
            raise ValueError(f"fraction {fraction} must be in (0, 1] and cycle_s {cycle_s} > 0")
        self.fraction, self.cycle_s, self.clock = fraction, cycle_s, clock
        self._cycle_start = None
        self._spent_s = 0.0

    def _roll(self, now):
        if self._cycle_start is None or now - self._cycle_start >= self.cycle_s:
            self._cycle_start, self._spent_s = now, 0.0

    def spend(self, cpu_s):
        """The insertion thread used `cpu_s` of CPU in this cycle."""
        self._roll(self.clock())
        self._spent_s += cpu_s

    def wait_s(self):
        """How long the insertion must pause before its next cloud (0: budget left in this cycle)."""
        if self.fraction >= 1.0:
            return 0.0
        now = self.clock()
        self._roll(now)
        if self._spent_s < self.fraction * self.cycle_s:
            return 0.0
        return max(0.0, self._cycle_start + self.cycle_s - now)
