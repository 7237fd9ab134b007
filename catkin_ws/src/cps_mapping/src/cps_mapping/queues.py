"""Bounded per-robot cloud queues served round-robin, and the per-robot statistics of the server.

The map server's subscriber callbacks `put` clouds (already in `map`); one worker thread `take`s
every queued cloud of the next robot in turn and inserts them as one batch. A full queue drops
its oldest cloud (the newest view of the site matters most) and counts it.
"""
import collections
import dataclasses
import math
import threading
from typing import Dict, List, Optional

import numpy as np


@dataclasses.dataclass
class QueuedCloud:
    robot: str
    points_m: np.ndarray
    origin_m: np.ndarray
    stamp_s: float


@dataclasses.dataclass
class RobotCounters:
    """What RobotMapStats reports for one robot."""
    clouds_received: int = 0
    clouds_inserted: int = 0
    clouds_dropped_queue: int = 0
    clouds_dropped_tf: int = 0
    clouds_dropped_invalid: int = 0
    points_inserted: int = 0
    points_rejected: int = 0
    batches: int = 0
    insertion_ms_total: float = 0.0
    insertion_ms_max: float = 0.0
    newest_inserted_stamp_s: Optional[float] = None

    @property
    def insertion_ms_avg(self):
        return self.insertion_ms_total / self.batches if self.batches else 0.0

    def map_age_s(self, now_s):
        if self.newest_inserted_stamp_s is None:
            return math.inf
        return max(0.0, now_s - self.newest_inserted_stamp_s)


class RobotQueues:
    """One bounded FIFO per robot, served fairly; thread-safe."""

    def __init__(self, robots: List[str], queue_size: int):
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        self.robots = list(robots)
        self.queue_size = queue_size
        self._queues: Dict[str, collections.deque] = {r: collections.deque() for r in self.robots}
        self.counters: Dict[str, RobotCounters] = {r: RobotCounters() for r in self.robots}
        self._cond = threading.Condition()
        self._next = 0
        self._closed = False

    def put(self, cloud: QueuedCloud):
        """Queue a cloud; returns True if an older one had to be dropped to make room."""
        with self._cond:
            queue = self._queues[cloud.robot]
            dropped = False
            if len(queue) >= self.queue_size:
                queue.popleft()
                self.counters[cloud.robot].clouds_dropped_queue += 1
                dropped = True
            queue.append(cloud)
            self._cond.notify()
            return dropped

    def take(self, timeout_s=None) -> List[QueuedCloud]:
        """All queued clouds of the next robot (round-robin) that has any; [] on timeout or close."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._closed or any(self._queues.values()), timeout_s):
                return []
            if self._closed:
                return []
            for step in range(len(self.robots)):
                robot = self.robots[(self._next + step) % len(self.robots)]
                if self._queues[robot]:
                    self._next = (self._next + step + 1) % len(self.robots)
                    batch = list(self._queues[robot])
                    self._queues[robot].clear()
                    return batch
            return []

    def length(self, robot):
        with self._cond:
            return len(self._queues[robot])

    def clear(self):
        with self._cond:
            for queue in self._queues.values():
                queue.clear()

    def close(self):
        with self._cond:
            self._closed = True
            self._cond.notify_all()
