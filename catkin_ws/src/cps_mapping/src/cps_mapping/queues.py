"""Admission before work: one latest-only slot per robot, holding each cloud as it arrived.

The map server's subscriber callbacks `put` what arrived (the serialized message, still Draco
compressed: nothing decoded, transformed or checked); the insertion thread `take`s one cloud at a
time and only then pays for it. A newer cloud of the same robot replaces the waiting one, which
is superseded (counted, not lost information: the newer view replaces it) and cost one pointer
swap, as roscpp's lazy deserialisation gives voxblox and octomap_server.

Service order: the robot whose map is oldest first (the smallest stamp of its newest inserted
cloud; never inserted first of all; ties: the cloud that waited longest). Under more load than the
insertion can serve, every robot is then served in turn and the map ages grow alike: freshness
degrades in proportion, no robot starves.

A cloud whose transform is not known yet is `defer`red into its robot's second slot, for a cloud
waiting for its transform (not ready before a time), where a newer cloud does not supersede it: the
newer one waits in the live slot. With one slot a newer cloud superseded the waiting one, so while
the robot's transforms came later than its clouds (live: tf 0.3-0.6 s behind on a busy link, the
clouds 0.1-0.3 s) every cloud was superseded before its transform came, and three robots' maps
stood still for 3 s in one demo (tf2's MessageFilter keeps a queue for the same reason). The
waiting cloud is served first once its transform is known, and superseded when a newer cloud of its
robot is inserted before it. Keyframes sent after a link outage (`backfill`) wait
in a bounded FIFO per robot, each one a different place, and are served only when no live cloud
is ready: background priority, as the link sends them within its unused budget.

What admission counts (received, superseded, missed: gaps in a sender's sequence numbers, and
keyframes beyond the FIFO) is counted here, under the slots' one lock: a received cloud takes one
lock and no other work in the receiving thread (with a hundred robots' receive threads in one
process, every further lock per message formed convoys that left the core idle; issue 37).
"""

import collections
import dataclasses
import math
import threading
import time
from typing import Callable, Dict, List, Optional, Tuple

# Backfill keyframes kept per robot; beyond, the oldest is dropped (counted as a queue drop).
BACKFILL_KEPT = 50


@dataclasses.dataclass
class AdmissionCounters:
    """One robot's admission counts (cps_msgs/RobotMapStats fields of the same names)."""

    clouds_received: int = 0
    clouds_superseded: int = 0
    clouds_missed_upstream: int = 0  # never received: gaps in the sender's sequence numbers
    clouds_dropped_queue: int = 0  # backfill keyframes beyond the FIFO's bound
    clouds_dropped_tf: int = 0  # no transform within the admission's timeout
    clouds_dropped_decoder: int = 0  # bytes that are not a cloud message
    clouds_dropped_invalid: int = 0  # no frame_id
    clouds_placed: int = 0  # handed to the insertion, placed (its ends are the insertion's counts)


@dataclasses.dataclass
class Arrival:
    """A cloud as it arrived: `message` is a rospy.AnyMsg (serialized bytes), a
    cps_msgs/CompressedPointCloud2 or a sensor_msgs/PointCloud2, untouched until taken."""

    robot: str
    message: object
    arrived_s: float  # monotonic
    backfill: bool = False
    not_before_s: float = -math.inf  # deferred until then (its transform was not known yet)
    opened: object = None  # what the inserter read of it before deferring it (not read twice)


class RobotSlots:
    """One latest-only slot, one slot for a cloud waiting for its transform and one backfill FIFO
    per robot, served oldest map first; thread-safe."""

    def __init__(self, robots: List[str], backfill_kept: int = BACKFILL_KEPT, clock: Callable = time.monotonic):
        if backfill_kept < 1:
            raise ValueError(f"backfill_kept must be >= 1, got {backfill_kept}")
        self.robots = list(robots)
        self.backfill_kept = backfill_kept
        self.clock = clock
        self._live: Dict[str, Optional[Arrival]] = {r: None for r in self.robots}
        self._waiting_tf: Dict[str, Optional[Arrival]] = {r: None for r in self.robots}
        self._backfill: Dict[str, collections.deque] = {r: collections.deque() for r in self.robots}
        self._newest_stamp_s: Dict[str, float] = {r: -math.inf for r in self.robots}
        self._counts: Dict[str, AdmissionCounters] = {r: AdmissionCounters() for r in self.robots}
        self._sequences: Dict[tuple, int] = {}  # (robot, backfill, sender) -> last number received
        self._cond = threading.Condition()
        self._closed = False

    def put(self, arrival: Arrival, sequence: Optional[Tuple[str, int]] = None) -> Optional[Arrival]:
        """Hold `arrival` (with its sender's (name, sequence number), if it carries one) and count
        it; returns what it displaced: the robot's waiting live cloud (superseded) or, for a
        keyframe, the oldest one beyond the FIFO's bound (dropped); else None."""
        with self._cond:
            counts = self._counts[arrival.robot]
            counts.clouds_received += 1
            if sequence is not None:
                key = (arrival.robot, arrival.backfill, sequence[0])
                last = self._sequences.get(key)
                self._sequences[key] = sequence[1]
                if last is not None and sequence[1] > last + 1:  # lower or equal: the sender restarted
                    counts.clouds_missed_upstream += sequence[1] - last - 1
            if arrival.backfill:
                fifo = self._backfill[arrival.robot]
                fifo.append(arrival)
                displaced = fifo.popleft() if len(fifo) > self.backfill_kept else None
                counts.clouds_dropped_queue += displaced is not None
            else:
                displaced, self._live[arrival.robot] = self._live[arrival.robot], arrival
                counts.clouds_superseded += displaced is not None
            self._cond.notify()
            return displaced

    def _ready(self, now_s):
        """The next cloud to serve (not removed) and when the first deferred one is due: a live
        cloud first, the robot whose map is oldest; a backfill keyframe only when no live one is
        ready."""
        live, due_live = self._oldest_first(
            ((r, a) for slot in (self._waiting_tf, self._live) for r, a in slot.items() if a is not None), now_s
        )
        if live is not None:
            return live, due_live
        keyframe, due_backfill = self._oldest_first(((r, f[0]) for r, f in self._backfill.items() if f), now_s)
        return keyframe, min(due_live, due_backfill)

    def _oldest_first(self, candidates, now_s):
        """(the ready arrival of the robot whose newest inserted stamp is oldest, the earliest time
        a deferred one is due) among (robot, arrival) `candidates`."""
        best, best_key, due_s = None, None, math.inf
        for robot, arrival in candidates:
            if arrival.not_before_s > now_s:
                due_s = min(due_s, arrival.not_before_s)
                continue
            key = (self._newest_stamp_s[robot], arrival.arrived_s)
            if best_key is None or key < best_key:
                best, best_key = arrival, key
        return best, due_s

    def take(self, timeout_s: Optional[float] = None) -> Optional[Arrival]:
        """The next cloud to insert (removed from its slot), waiting up to `timeout_s` (None:
        forever) for one; None on timeout or once closed."""
        deadline = None if timeout_s is None else self.clock() + timeout_s
        with self._cond:
            while not self._closed:
                now = self.clock()
                arrival, due_s = self._ready(now)
                if arrival is not None:
                    if arrival.backfill:
                        self._backfill[arrival.robot].popleft()
                    elif self._waiting_tf[arrival.robot] is arrival:
                        self._waiting_tf[arrival.robot] = None
                    else:
                        self._live[arrival.robot] = None
                    return arrival
                wake_s = min(due_s, deadline if deadline is not None else math.inf)
                if wake_s <= now:
                    return None
                self._cond.wait(None if math.isinf(wake_s) else wake_s - now)
            return None

    def defer(self, arrival: Arrival, retry_s: float) -> bool:
        """Put a taken cloud back, not ready for `retry_s`, to wait for its transform: in its robot's
        waiting slot, or, while an older cloud waits there, in the live slot unless a newer cloud
        arrived meanwhile; False (not put back: counted as superseded) in that case."""
        with self._cond:
            arrival.not_before_s = self.clock() + retry_s
            robot = arrival.robot
            if arrival.backfill:
                self._backfill[robot].appendleft(arrival)
            elif self._waiting_tf[robot] is None:
                self._waiting_tf[robot] = arrival
            elif self._live[robot] is not None:
                self._counts[robot].clouds_superseded += 1
                return False
            else:
                self._live[robot] = arrival
            self._cond.notify()
            return True

    def served(self, robot: str, stamp_s: float):
        """The robot's map now holds a cloud stamped `stamp_s` (its map age falls)."""
        with self._cond:
            self._newest_stamp_s[robot] = max(self._newest_stamp_s[robot], stamp_s)
            waiting = self._waiting_tf[robot]
            if waiting is not None and waiting.opened is not None and waiting.opened.header.stamp.to_sec() < stamp_s:
                self._waiting_tf[robot] = None  # the map has a newer view of this robot
                self._counts[robot].clouds_superseded += 1

    def count(self, robot: str, **amounts):
        """Add to the robot's admission counts (a cloud admission dropped, by cause)."""
        with self._cond:
            counts = self._counts[robot]
            for field, amount in amounts.items():
                setattr(counts, field, getattr(counts, field) + amount)

    def counts(self, robot: str) -> AdmissionCounters:
        """A copy of the robot's admission counts."""
        with self._cond:
            return dataclasses.replace(self._counts[robot])

    def state(self, robot: str) -> Tuple[AdmissionCounters, int]:
        """(a copy of the robot's admission counts, its clouds waiting), read at one instant: a cloud
        taken between two reads would be in neither."""
        with self._cond:
            return dataclasses.replace(self._counts[robot]), self.length(robot)

    def superseded_total(self) -> int:
        with self._cond:
            return sum(c.clouds_superseded for c in self._counts.values())

    def length(self, robot: str) -> int:
        """Clouds of `robot` waiting: its live and waiting-for-transform slots (0 or 1 each) and its
        backfill keyframes."""
        with self._cond:
            return (self._live[robot] is not None) + (self._waiting_tf[robot] is not None) + len(self._backfill[robot])

    def clear(self) -> List[Arrival]:
        """Empty every slot; returns what was waiting (the caller counts it)."""
        with self._cond:
            dropped = [a for slot in (self._live, self._waiting_tf) for a in slot.values() if a is not None]
            dropped += [a for fifo in self._backfill.values() for a in fifo]
            self._live = {r: None for r in self.robots}
            self._waiting_tf = {r: None for r in self.robots}
            for fifo in self._backfill.values():
                fifo.clear()
            return dropped

    def close(self):
        with self._cond:
            self._closed = True
            self._cond.notify_all()
