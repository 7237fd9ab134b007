"""Backfill: what the robots' side keeps while the link is down, and how fast it may send it after
(ROS-free). Keyframes (one cloud per robot per keyframe period, with the pose it was captured at)
go into a store bounded in bytes; when it is full the oldest go first, each counted. After
recovery they leave oldest first, paced by a token bucket at the bandwidth the manager leaves
unused (budget - allocated), so they never take live traffic's share."""

import collections
import dataclasses
import threading


@dataclasses.dataclass(frozen=True)
class Keyframe:
    robot: str
    stamp_s: float
    payloads: tuple  # what goes on the wire, in order (pose, then cloud)

    @property
    def size_bytes(self):
        return sum(len(p) for p in self.payloads)


class KeyframeStore:
    """At most `capacity_bytes` of keyframes, at most one per robot per `period_s` of capture time."""

    def __init__(self, capacity_bytes, period_s):
        if capacity_bytes <= 0 or period_s <= 0:
            raise ValueError(f"capacity ({capacity_bytes} bytes) and keyframe period ({period_s} s) must be > 0")
        self.capacity_bytes, self.period_s = int(capacity_bytes), float(period_s)
        self._frames = collections.deque()
        self._last_stamp = {}
        self._lock = threading.Lock()
        self.bytes = 0
        self.kept = 0
        self.evicted = 0  # oldest dropped to make room
        self.evicted_by_robot = collections.Counter()
        self.refused = 0  # larger than the whole store

    def __len__(self):
        return len(self._frames)

    def wants(self, robot, stamp_s):
        """True when a cloud of `robot` captured at stamp_s would be a new keyframe."""
        last = self._last_stamp.get(robot)
        return last is None or stamp_s - last >= self.period_s

    def offer(self, keyframe: Keyframe):
        """Keep it if it is a keyframe (evicting the oldest while full); True when kept."""
        with self._lock:
            if not self.wants(keyframe.robot, keyframe.stamp_s):
                return False
            if keyframe.size_bytes > self.capacity_bytes:
                self.refused += 1
                return False
            self._last_stamp[keyframe.robot] = keyframe.stamp_s
            while self.bytes + keyframe.size_bytes > self.capacity_bytes:
                evicted = self._frames.popleft()
                self.bytes -= evicted.size_bytes
                self.evicted += 1
                self.evicted_by_robot[evicted.robot] += 1
            self._frames.append(keyframe)
            self.bytes += keyframe.size_bytes
            self.kept += 1
            return True

    def evicted_of(self, robot):
        """How many of `robot`'s keyframes were evicted to make room."""
        with self._lock:
            return self.evicted_by_robot[robot]

    def waiting_of(self, robot):
        """How many of `robot`'s keyframes are in the store now."""
        with self._lock:
            return sum(1 for frame in self._frames if frame.robot == robot)

    def peek(self):
        with self._lock:
            return self._frames[0] if self._frames else None

    def pop(self):
        """The oldest keyframe (capture order), or None."""
        with self._lock:
            if not self._frames:
                return None
            frame = self._frames.popleft()
            self.bytes -= frame.size_bytes
            return frame


class Pacer:
    """A token bucket filled at `rate_bytes_per_s` (changed live), holding at most `burst_bytes`."""

    def __init__(self, burst_bytes, now_s):
        self.burst_bytes = float(burst_bytes)
        self.rate_bytes_per_s = 0.0
        self.tokens = 0.0
        self._t = now_s

    def set_rate(self, rate_bytes_per_s, now_s):
        self._refill(now_s)
        self.rate_bytes_per_s = max(0.0, float(rate_bytes_per_s))

    def _refill(self, now_s):
        self.tokens = min(self.burst_bytes, self.tokens + (now_s - self._t) * self.rate_bytes_per_s)
        self._t = now_s

    def take(self, size_bytes, now_s):
        """True (and the tokens spent) when `size_bytes` may go now; a frame larger than the burst
        may go once the bucket is full."""
        self._refill(now_s)
        if self.tokens >= min(size_bytes, self.burst_bytes) and self.rate_bytes_per_s > 0:
            self.tokens -= size_bytes
            return True
        return False


def unused_bytes_per_s(budget_mbytes_per_s, allocated_mbytes_per_s):
    """What the manager leaves of its budget, bytes/s (never negative)."""
    return max(0.0, (budget_mbytes_per_s - allocated_mbytes_per_s) * 1e6)
