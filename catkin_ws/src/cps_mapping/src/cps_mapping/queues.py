"""Per-robot cloud slots served round-robin (as voxblox's node keeps only what it can integrate).

The map server's subscriber callbacks `put` clouds (already in `map`); one worker thread `take`s
every waiting cloud of the next robot in turn and inserts them as one batch. A robot's slot holds
at most `queue_size` clouds (default 1: only its latest); a newer cloud supersedes the oldest
waiting one, which is counted as superseded, not as lost information: the newer view of the same
robot's surroundings replaces it, and a robot never waits behind another's backlog.
"""

import collections
import dataclasses
import threading
from typing import Dict, List

import numpy as np


@dataclasses.dataclass
class QueuedCloud:
    robot: str
    points_m: np.ndarray
    origin_m: np.ndarray
    stamp_s: float


class RobotQueues:
    """One bounded slot per robot (newest clouds win), served round-robin; thread-safe."""

    def __init__(self, robots: List[str], queue_size: int):
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        self.robots = list(robots)
        self.queue_size = queue_size
        self._queues: Dict[str, collections.deque] = {r: collections.deque() for r in self.robots}
        self._cond = threading.Condition()
        self._next = 0
        self._closed = False

    def put(self, cloud: QueuedCloud):
        """Hold a cloud; returns True if it superseded the robot's oldest waiting cloud."""
        with self._cond:
            queue = self._queues[cloud.robot]
            superseded = False
            if len(queue) >= self.queue_size:
                queue.popleft()
                superseded = True
            queue.append(cloud)
            self._cond.notify()
            return superseded

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
