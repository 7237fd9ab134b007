"""Which of the allocation's levels and rates are worth sending to the robots (issue 36), no ROS.

The allocator answers at every update (2 Hz, and on every input that may change it); most answers
differ from the last one by noise (a size measured 3 % larger, an input rate 1.6 Hz instead of
1.5 Hz). Every setpoint crosses the link, wakes the robot's encoder and is echoed by its status,
on the robots' saturated CPU: so a stream's setpoint is sent only when it matters.

- a stream's first setpoint, a coarser level, a video turned off or on, and a rate below what the
  stream's rules guarantee (an operator's video, a floor) go out at once;
- a finer level waits `min_interval_s` after the stream's last level change, unless a rule needs
  it now (its rate in force is below what its rules guarantee, or it is the operator's video): the
  allocator's choice of detail follows a noisy CPU estimate, and live at 16 robots a cloud flipped
  between two leaves three times in 200 ms. Shedding detail is never delayed;
- the operator's video (its guarantee kept) takes a higher rate beyond the deadband at once: held
  5 s, its rate cut for a moment's CPU shortage came back late (fig13_live, 16 robots: 18 Hz for 5 s
  after the target was 30 again, the watched video's slowest 10 s window 21.9 fps against 28 without
  the manager);
- otherwise a rate goes out only if it left the deadband around the rate in force
  (|target - sent| > `rate_deadband` x sent: hysteresis, both taken no higher than what the stream
  can send: a cloud limiter's slack above its sensor's rate changes nothing), and at most once per `min_interval_s`
  per stream; while the link is idle (no stream's rate is held back by the budget) a lower rate
  is not sent at all: nobody needs what it frees, and a cloud's target follows its noisy input
  rate (+10 %) there;
- whatever was held back, the rates in force must fit the link: if they do not (the budget fell,
  or a size grew), every stream whose target is below its rate in force gets it at once;
- while the link's estimator probes (issue 35), a higher rate goes out at once: a probe measures
  nothing unless the fleet fills it within its 1.5 s, and held 5 s per stream no probe was ever
  filled live (a 20 -> 60 Mbit/s step went unseen). Probes come at most every 1.5 s, backing off
  to 3 s while refused, and only while the fleet wants more than it is given.

- a stream whose encoder's status, `ECHO_GRACE_S` or more after the last setpoint, reports
  another rate or level than the one in force gets it again (at most once per `min_interval_s`):
  a setpoint can be lost (a latched topic reconnecting, an encoder restarted, a race), and the
  deadband would otherwise never resend it.

Decisions are batched per robot: one call decides every stream, and the node sends a robot's
changes together.
"""

import dataclasses
import math
from typing import Dict, List, Mapping, Optional, Tuple

from cps_bw_manager.level_allocation import OPERATOR_VIDEO

DEFAULT_RATE_DEADBAND = 0.2
DEFAULT_MIN_INTERVAL_S = 5.0
# An encoder's status this long after a setpoint shows it (its status period is 1 s), s.
ECHO_GRACE_S = 2.0
# An echoed rate within this fraction of the one sent is the one sent (the message's float).
ECHO_RATE_TOLERANCE = 1e-3
FIRST, LEVEL, ON_OFF, RULE, CHANGE, BUDGET, PROBE, ECHO, OPERATOR = (
    "first",
    "level",
    "on/off",
    "rule",
    "change",
    "budget",
    "probe",
    "echo",
    "operator",
)


@dataclasses.dataclass(frozen=True)
class Target:
    """What the allocator wants for one stream."""

    level: int
    rate_hz: float  # 0: off
    min_rate_hz: float = 0.0  # what the stream's kept rules guarantee
    message_bytes: float = 0.0  # its size at `level` (the budget check)
    # The most it can send whatever its rate (a cloud: its sensor's input rate + 10 %); a limiter
    # set above it (slack on an idle link) counts only this much against the budget.
    usable_hz: float = math.inf
    operator: bool = False  # the operator's video, its guarantee kept: its level goes at once


@dataclasses.dataclass(frozen=True)
class Change:
    """A setpoint to send: the stream's level and rate now in force, and why."""

    key: Tuple[str, str]  # (robot, stream)
    level: int
    rate_hz: float
    level_changed: bool
    rate_changed: bool
    reason: str


class SetpointFilter:
    def __init__(self, rate_deadband=DEFAULT_RATE_DEADBAND, min_interval_s=DEFAULT_MIN_INTERVAL_S):
        if not (math.isfinite(rate_deadband) and 0 <= rate_deadband < 1):
            raise ValueError(f"rate_deadband must be in [0, 1), got {rate_deadband!r}")
        if not (math.isfinite(min_interval_s) and min_interval_s >= 0):
            raise ValueError(f"min_interval_s must be >= 0 s, got {min_interval_s!r}")
        self.rate_deadband = float(rate_deadband)
        self.min_interval_s = float(min_interval_s)
        self._sent: Dict[Tuple[str, str], Tuple[int, float, float]] = {}  # key -> (level, rate, at s)
        self._level_at: Dict[Tuple[str, str], float] = {}  # key -> when its level last changed, s
        self._resend: set = set()  # keys whose encoder echoed something else than in force
        self._echo_resent_at: Dict[Tuple[str, str], float] = {}
        self.sent_count = 0

    def in_force(self, key) -> Optional[Tuple[int, float]]:
        """(level, rate) last sent for the stream (None: nothing sent yet)."""
        entry = self._sent.get(key)
        return None if entry is None else entry[:2]

    def forget(self, key):
        """Send the stream's next setpoint as its first (its encoder restarted)."""
        self._sent.pop(key, None)
        self._level_at.pop(key, None)
        self._resend.discard(key)

    def echo(self, key, rate_hz, level, status_s):
        """An encoder's status: the rate (and level; None: it has none) it runs at, received at
        `status_s`. True when it is not what was sent ECHO_GRACE_S or more before: the stream's
        next decision resends what is in force (at most once per `min_interval_s`)."""
        sent = self._sent.get(key)
        if sent is None or not math.isfinite(rate_hz) or not math.isfinite(status_s):
            return False
        sent_level, sent_rate, sent_at = sent
        if status_s < sent_at + ECHO_GRACE_S:
            return False
        same_rate = abs(rate_hz - sent_rate) <= ECHO_RATE_TOLERANCE * max(sent_rate, 1.0)
        if same_rate and (level is None or level == sent_level):
            return False
        if status_s - self._echo_resent_at.get(key, -math.inf) < self.min_interval_s:
            return False
        self._resend.add(key)
        return True

    def decide(
        self,
        now_s,
        targets: Mapping[Tuple[str, str], Target],
        budget_mbytes_per_s=math.inf,
        link_idle=False,
        probing=False,
    ):
        """The setpoints to send now, per robot: {robot: [Change, ...]} (robots with none absent).
        `budget_mbytes_per_s`: what the rates in force must fit (sum of rate x message_bytes);
        `link_idle`: the allocation held no rate back for the link (its lower rates wait);
        `probing`: the link's estimator probes above its capacity (higher rates go at once)."""
        if not math.isfinite(now_s):
            raise ValueError(f"time {now_s!r} is not a time")
        changes: Dict[Tuple[str, str], Change] = {}
        for key, t in targets.items():
            reason = self._reason(key, t, now_s, link_idle, probing)
            if reason:
                changes[key] = self._change(key, t, reason)
        # The rates in force (after the changes above) must fit the link.
        total = 0.0
        for key, t in targets.items():
            rate = changes[key].rate_hz if key in changes else self._sent.get(key, (0, t.rate_hz, 0))[1]
            total += min(rate, t.usable_hz) * t.message_bytes / 1e6
        if total > budget_mbytes_per_s * (1 + 1e-9):
            for key, t in targets.items():
                if key not in changes and t.rate_hz < self._sent[key][1] and t.rate_hz < t.usable_hz:
                    changes[key] = self._change(key, t, BUDGET)
        out: Dict[str, List[Change]] = {}
        for key, change in changes.items():
            if key in self._resend:
                self._resend.discard(key)
                self._echo_resent_at[key] = float(now_s)
            previous = self._sent.get(key)
            self._sent[key] = (change.level, change.rate_hz, float(now_s))
            if previous is None or previous[0] != change.level:
                self._level_at[key] = float(now_s)
            self.sent_count += 1
            out.setdefault(key[0], []).append(change)
        return out

    def _reason(self, key, t: Target, now_s, link_idle=False, probing=False):
        sent = self._sent.get(key)
        if sent is None:
            return FIRST
        level, rate, at_s = sent
        if key in self._resend:
            return ECHO
        broken_rule = rate < t.min_rate_hz * (1 - 1e-9)
        if t.level > level or (t.level < level and (broken_rule or t.operator or self._level_settled(key, now_s))):
            return LEVEL
        if (rate == 0.0) != (t.rate_hz == 0.0):
            return ON_OFF
        if broken_rule:
            return RULE
        if link_idle and t.rate_hz < rate:
            return ""
        # A rate above what the stream can send (a cloud limiter's slack above its sensor's rate)
        # changes nothing the stream does: rates are compared up to `usable_hz`. Live at 16 robots
        # on an idle link, the clouds' slack rose 7.8 -> 10.4 -> 16.8 -> 30 Hz in 5 s steps while
        # they sent ~2.5 Hz, one setpoint each, and a level shed often fell within 5 s of one.
        have, want = min(rate, t.usable_hz), min(t.rate_hz, t.usable_hz)
        if probing and want > have * (1 + 1e-9):
            return PROBE
        if t.operator and want > (1 + self.rate_deadband) * have:
            return OPERATOR
        if abs(want - have) > self.rate_deadband * have and now_s - at_s >= self.min_interval_s:
            return CHANGE
        return ""

    def _level_settled(self, key, now_s):
        """True when the stream's level last changed at least `min_interval_s` ago."""
        return now_s - self._level_at.get(key, -math.inf) >= self.min_interval_s

    def _change(self, key, t: Target, reason):
        sent = self._sent.get(key)
        if reason != LEVEL and sent is not None and t.level < sent[0]:
            t = dataclasses.replace(t, level=sent[0])  # a finer level still waits (see _reason)
        again = sent is None or reason == ECHO  # both fields, whether or not they changed
        return Change(
            key=key,
            level=t.level,
            rate_hz=t.rate_hz,
            level_changed=again or sent[0] != t.level,
            rate_changed=again or sent[1] != t.rate_hz,
            reason=reason,
        )


def targets_of(result, demands, rates=None):
    """{key: Target} of a LevelAllocation, sizes from its `demands` ({key: StreamDemand}); `rates`
    {key: Hz} replaces some rates (a cloud limiter's slack: ManagerCore.limiter_rates). A cloud
    can send no more than its allocation's maximum (its input rate + 10 %)."""
    out = {}
    rates = rates or {}
    for a in result.streams:
        d = demands.get(a.key)
        size = d.level_bytes[a.level] if d is not None else a.message_bytes
        usable = a.max_rate_hz if a.stream == "cloud" else math.inf
        operator = d is not None and d.guarantee == OPERATOR_VIDEO and a.guarantee_kept
        out[a.key] = Target(
            a.level, rates.get(a.key, a.rate_hz), a.min_rate_hz, size, max(usable, a.rate_hz), operator=operator
        )
    return out


def in_force_allocation(result, demands, setpoints: SetpointFilter, copies=1):
    """The LevelAllocation as the robots run it: each stream with a setpoint in force at its level
    and rate (bandwidth and share at that level's size, every copy counted; a cloud's no more than
    its maximum: a limiter's slack above what its sensor produces is not use, and the backfill
    takes what the allocation leaves), the others as allocated."""
    budget = result.budget_mbytes_per_s
    streams = []
    for a in result.streams:
        held = setpoints.in_force(a.key)
        d = demands.get(a.key)
        if held is None or d is None or held == (a.level, a.rate_hz):
            streams.append(a)
            continue
        level, rate = held
        names = d.level_names or tuple(str(k) for k in range(len(d.level_bytes)))
        size = d.level_bytes[level]
        usable = max(a.max_rate_hz, a.rate_hz) if a.stream == "cloud" else math.inf  # a limiter's slack is not use
        bandwidth = copies * min(rate, usable) * size / 1e6
        streams.append(
            dataclasses.replace(
                a,
                level=level,
                level_name=names[level],
                rate_hz=rate,
                message_bytes=size,
                bandwidth_mbytes_per_s=bandwidth,
                share_percent=100.0 * bandwidth / budget,
            )
        )
    total = sum(a.bandwidth_mbytes_per_s for a in streams)
    return dataclasses.replace(result, streams=tuple(streams), allocated_mbytes_per_s=total)
