"""The robots' bridge's send queue (no ROS, no Zenoh): which frame waits, in which order, at what
pace, and which is dropped by which rule. Issue 35: at 5 Mbit/s a ~1 MB standing queue in the
kernel's socket held every frame ~1.5 s, so the twin dropped two thirds of what the link delivered
as stale. Here what waits, waits in this queue, where freshness and priority are decided.

Urgent frames (the classes not paced: commands, telemetry, log, all small) never wait: the bridge
puts them at once and charges their bytes to the pacer, so the pacing rate covers every byte the
link carries. Paced frames (bridge.yaml classes with `paced: true`: the video and the clouds) wait
here, the class of higher Zenoh priority first, first come first served within a class, and leave
at the pacing rate (BBR paces at its bandwidth estimate; GCC and SCReAM pace video under theirs):
the manager's estimate of the link from /tissue/allocation, or unpaced before the first one.

Drop rules, each counted in messages and bytes:

- `superseded`: a newer frame of the same topic and source arrived while one waited; the newer
  takes the older's place in line (fresh first, and a steady stream is never starved);
- `expired`: it waited past its class's max_age_s (the twin's bridge would drop it as stale);
- `link_down`: the link went down while it waited (the backfill keeps keyframes of the outage).

The queue holds at most one frame per topic and source, so it needs no size bound.

`app_limited` (per interval, BBR's app-limited marking): the sender found the queue empty while
the pacer would have let it send.
"""

import collections
import dataclasses
import math
import threading
from typing import Dict, Hashable, Optional

SUPERSEDED, EXPIRED, LINK_DOWN = "superseded", "expired", "link_down"
DROP_RULES = (SUPERSEDED, EXPIRED, LINK_DOWN)
# The pacer's bucket: at most this long at the pacing rate in one go, and never less than this many
# bytes (one 640x480 frame must be able to leave at 5 Mbit/s without waiting a whole bucket).
PACING_BURST_S = 0.02
PACING_MIN_BURST_BYTES = 16384


@dataclasses.dataclass
class Waiting:
    """One frame in line: `item` is what the bridge puts (its payload), `size_bytes` its length,
    `expires_s` when it is too old to send (monotonic s; inf: never)."""

    key: Hashable
    rank: int
    size_bytes: int
    expires_s: float
    item: object


@dataclasses.dataclass
class QueueCounters:
    """Cumulative counters of a SendQueue (never reset: intervals are differences)."""

    offered_bytes: int = 0  # every frame handed to the bridge for the link (urgent and paced)
    sent_bytes: int = 0  # handed on to the Zenoh session
    dropped: Dict[str, int] = dataclasses.field(default_factory=lambda: dict.fromkeys(DROP_RULES, 0))
    dropped_bytes: Dict[str, int] = dataclasses.field(default_factory=lambda: dict.fromkeys(DROP_RULES, 0))


class Pacer:
    """A token bucket at `rate_bytes_per_s` (None: unpaced). A frame may leave while the bucket is
    not in debt; leaving takes its whole size (so the bucket may go below zero by one frame), and
    urgent frames are charged the same way: the average never exceeds the rate."""

    def __init__(self, now_s, rate_bytes_per_s=None):
        self.rate = None
        self.tokens = 0.0
        self.updated_s = now_s
        self.set_rate(rate_bytes_per_s, now_s)

    @property
    def burst_bytes(self):
        return math.inf if self.rate is None else max(PACING_MIN_BURST_BYTES, self.rate * PACING_BURST_S)

    def _refill(self, now_s):
        if self.rate is not None and now_s > self.updated_s:
            self.tokens = min(self.burst_bytes, self.tokens + (now_s - self.updated_s) * self.rate)
        self.updated_s = max(self.updated_s, now_s)

    def set_rate(self, rate_bytes_per_s, now_s):
        """A new pacing rate (bytes/s > 0, or None for unpaced); ValueError for anything else."""
        if rate_bytes_per_s is not None and not (math.isfinite(rate_bytes_per_s) and rate_bytes_per_s > 0):
            raise ValueError(f"pacing rate must be a finite number of bytes/s > 0 or None, got {rate_bytes_per_s!r}")
        self._refill(now_s)
        self.rate = rate_bytes_per_s
        self.tokens = min(self.tokens, self.burst_bytes)

    def charge(self, size_bytes, now_s):
        self._refill(now_s)
        if self.rate is not None:
            self.tokens -= size_bytes

    def wait_s(self, now_s):
        """How long until a frame may leave (0: now)."""
        self._refill(now_s)
        if self.rate is None or self.tokens >= 0:
            return 0.0
        return -self.tokens / self.rate


class SendQueue:
    """Thread-safe. `ranks`: class name -> rank (lower leaves first; classes not in it are urgent).
    The bridge calls `offer` (paced) or `urgent` from its ROS callbacks and `take` / `sent` from its
    one sender thread. `on_drop(rule, item)`, if given, is told of every frame a rule drops (under
    the queue's lock: keep it short), so the bridge can count it per route."""

    def __init__(self, ranks: Dict[str, int], now_s, on_drop=None):
        self.ranks = dict(ranks)
        self.on_drop = on_drop
        self.pacer = Pacer(now_s)
        self.counters = QueueCounters()
        self.cond = threading.Condition()
        self._lines = {rank: collections.OrderedDict() for rank in sorted(set(self.ranks.values()))}
        self._app_limited = False
        self.link_up = True

    def paced(self, class_name):
        return class_name in self.ranks

    def set_rate(self, rate_bytes_per_s, now_s):
        with self.cond:
            self.pacer.set_rate(rate_bytes_per_s, now_s)
            self.cond.notify()

    def urgent(self, size_bytes, now_s):
        """A frame that does not wait was put on the link: offered, sent and charged."""
        with self.cond:
            self.counters.offered_bytes += size_bytes
            self.counters.sent_bytes += size_bytes
            self.pacer.charge(size_bytes, now_s)

    def offer(self, class_name, key, size_bytes, item, now_s, max_age_s=None):
        """A paced frame joins the line (replacing the frame of the same `key` if one waits: returns
        SUPERSEDED then, else None). `max_age_s`: how much longer it is worth sending (None: always)."""
        waiting = Waiting(
            key,
            self.ranks[class_name],
            int(size_bytes),
            now_s + max_age_s if max_age_s is not None else math.inf,
            item,
        )
        with self.cond:
            self.counters.offered_bytes += waiting.size_bytes
            line = self._lines[waiting.rank]
            old = line.get(key)
            line[key] = waiting  # an existing key keeps its place in line
            if old is not None:
                self._drop(SUPERSEDED, old)
            self.cond.notify()
        return SUPERSEDED if old is not None else None

    def _drop(self, rule, waiting):
        self.counters.dropped[rule] += 1
        self.counters.dropped_bytes[rule] += waiting.size_bytes
        if self.on_drop is not None:
            self.on_drop(rule, waiting.item)

    def set_link_up(self, up):
        """While the link is down nothing leaves; what waited when it went down is dropped."""
        with self.cond:
            self.link_up = bool(up)
            if not up:
                for line in self._lines.values():
                    for waiting in line.values():
                        self._drop(LINK_DOWN, waiting)
                    line.clear()
            self.cond.notify()

    def take(self, now_s) -> tuple:
        """(the next frame's item, 0) when one may leave now (it is charged to the pacer), else
        (None, how long to wait: the pacer's wait, or None when nothing waits)."""
        with self.cond:
            self._expire(now_s)
            head = self._head()
            wait = self.pacer.wait_s(now_s)
            if head is None:
                if wait == 0.0 and self.link_up:
                    self._app_limited = True
                return None, None
            if not self.link_up:
                return None, None
            if wait > 0.0:
                return None, wait
            del self._lines[head.rank][head.key]
            self.pacer.charge(head.size_bytes, now_s)
            return head.item, 0.0

    def sent(self, size_bytes):
        """The sender handed a taken frame to the Zenoh session."""
        with self.cond:
            self.counters.sent_bytes += size_bytes

    def _head(self) -> Optional[Waiting]:
        for line in self._lines.values():
            if line:
                return next(iter(line.values()))
        return None

    def _expire(self, now_s):
        for line in self._lines.values():
            for key in [k for k, w in line.items() if w.expires_s <= now_s]:
                self._drop(EXPIRED, line.pop(key))

    def waiting(self):
        """(frames, bytes) in line."""
        with self.cond:
            frames = [w for line in self._lines.values() for w in line.values()]
        return len(frames), sum(w.size_bytes for w in frames)

    def app_limited_since_last(self, now_s):
        """True when, since the last call, the sender found nothing to send while it could have (or
        nothing waits now while it could leave: a sender asleep on an empty queue finds nothing)."""
        with self.cond:
            flag, self._app_limited = self._app_limited, False
            return flag or (self.link_up and self._head() is None and self.pacer.wait_s(now_s) == 0.0)

    def snapshot(self):
        """A copy of the cumulative counters."""
        with self.cond:
            c = self.counters
            return QueueCounters(c.offered_bytes, c.sent_bytes, dict(c.dropped), dict(c.dropped_bytes))
