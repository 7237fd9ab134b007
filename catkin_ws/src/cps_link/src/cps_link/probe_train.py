"""Probe trains: the link's capacity measured while the fleet leaves it room (issue 35), no ROS, no
Zenoh.

A fleet that offers 3 Mbit/s never fills a 10 Mbit/s link, so nothing it sends says the link went
from 60 to 10 Mbit/s. The robots' bridge then sends, now and then, a short train of padding on a
probe route of its own (Zenoh's lowest priority: data always goes first), paced at 4 x the
capacity it believes; the twin's bridge times the train's arrival. Mirrored from libwebrtc's
application-limited (ALR) probing: `bitrate_prober.cc` sends a cluster of packets at a target
rate, `probe_bitrate_estimator.cc` takes the receive rate over the cluster (the first packet's
size left out, as it arrived before the interval began) and compares it with the send rate: a
cluster received at less than 0.9 x its send rate found the bottleneck; one received at its send
rate proves only that the link carries that much. Ours differ where the link differs:

- the receive side counts every byte its link socket received while the train arrived (TCP_INFO's
  bytes_received read at each probe message, or the bridge's frames where that is not readable):
  the fleet's own frames overtake the train in Zenoh's priorities and share the link with it;
- the rate is taken over the train's second half (from the arrival of the message that completes
  half its bytes to the last): a token-bucket shaper (the test bed's tc tbf, burst max(16 kB,
  4 ms): cps_link.netns_link) and Wi-Fi's aggregation pass a train's head at the sender's rate;
  the second half is served at the bottleneck once the head has used up the burst;
- a train is sized by the capacity believed: PROBE_TRAIN_S of it (libwebrtc's clusters are
  bounded by duration and a packet count), at least PROBE_MIN_TRAIN_BYTES, so that at 5 Mbit/s a
  train is ~100 ms of the link, not the 0.6 s of the fixed 384 kB trains made for a 128 kB shaper
  burst, which queued the operator's video ~250 ms behind them in the link's one bulk queue;
- the train's cost is bounded by the capacity believed: its period is the train's bytes over
  PROBE_COST_FRACTION of it, so a train costs that fraction of the link on average, and a high
  capacity (where a step down matters most) is probed often. libwebrtc probes in ALR every 5 s;
  issue 35's bar (the estimate within 2 s of a 60 -> 10 Mbit/s step) needs about 1 s at 60 Mbit/s;
- the train is paced at 4 x, not libwebrtc's 2 x, and the send rate compared with is that of the
  measured part (a sender that stalled there sent it slowly: its arrival is no bottleneck).
"""

import dataclasses
import math
import struct
from typing import Optional

# A train is PROBE_TRAIN_S of the capacity believed, within [PROBE_MIN_TRAIN_BYTES,
# PROBE_MAX_TRAIN_BYTES], in about PROBE_TRAIN_MESSAGES messages of [PROBE_MIN_MESSAGE_BYTES,
# PROBE_MAX_MESSAGE_BYTES] (a Zenoh batch of the bridge table's 16 kB holds one; the twin's bridge
# takes each in Python, so at 60 Mbit/s they stay 16 kB, one per 2 ms). A token bucket of burst B
# passes the first B x S / (S - R) bytes of a train sent at S into a link of R at the sender's
# pace; the second half is measured after it only if that is less than half the train: at S = 4 R
# and the test bed's 16 kB floor, 21 kB, so 64 kB.
PROBE_TRAIN_S = 0.05
PROBE_MIN_TRAIN_BYTES = 64000
PROBE_MAX_TRAIN_BYTES = 384000
PROBE_TRAIN_MESSAGES = 16
PROBE_MIN_MESSAGE_BYTES = 4000
PROBE_MAX_MESSAGE_BYTES = 16000
# The train is paced at this x the capacity believed (libwebrtc's ALR probes go at 2 x its
# estimate; 4 x here, for the shaper's burst above): a link that kept its capacity comes out slower
# than sent (its capacity measured); one that grew by 4 x carries it all (a lower bound).
PROBE_SEND_GAIN = 4.0
# On average a train costs at most this fraction of the capacity believed (its period follows).
PROBE_COST_FRACTION = 0.05
# ... but the trains are at least this far apart, and at most this far (at 5 Mbit/s a 64 kB train
# at 5 % is one per 2 s; at 1 Mbit/s the 10 s bound, 5.1 %), s.
PROBE_MIN_PERIOD_S = 0.5
PROBE_MAX_PERIOD_S = 10.0
# A capacity raised to at least this x the one the last train was sized and paced for (a step up
# found: the link may carry more still) makes the next train due PROBE_MIN_PERIOD_S after that one:
# libwebrtc's ProbeController probes further at once when a probe's result comes near its target.
# Live (link_thesis, 5 -> 60 Mbit/s) each step of the rise waited a period of the capacity before
# it (2 s at 5 Mbit/s) for the train that could read more.
PROBE_FURTHER_RISE = 2.0
# A report interval whose robots' link socket was full in under this fraction of its samples left
# the link room: the sender's queue, if it backlogged, was held by its pacer (below the estimate
# while the manager cruises), not by the link, and a train can measure the link beside it.
ROOM_SOCKET_FULL_FRACTION = 0.5
# The twin gives up a train whose last message has not come this long after its first, s
# (libwebrtc's kMaxProbeInterval is 1 s); its messages are counted, its rate is not measured.
PROBE_TRAIN_TIMEOUT_S = 2.0
# A train is measured from at least this fraction of its messages (libwebrtc: 0.8).
PROBE_MIN_RECEIVED_FRACTION = 0.8

# version, train id, message index, messages in the train, train bytes, the rate it is paced at
# (Mbit/s), and on each message the sender's spread so far (from the first message's put to this
# one's, s) and how much of it the sender spent blocked in Zenoh's puts (the link held it back).
_HEADER = struct.Struct("!BIHHIddd")
PROBE_VERSION = 1

# Why the twin does not measure a train (each counted).
BAD_PROBE = "bad_probe"  # not a probe message, or a field out of range
INCOMPLETE = "incomplete"  # fewer than PROBE_MIN_RECEIVED_FRACTION of its messages came in time
TOO_SHORT = "too_short"  # its measured part arrived in no time (one read of the socket)
# most of its measured part's frames had arrived before the twin's bridge took its first message
# (the link moved less than RECEIVER_LATE_FRACTION of them after it): the twin's pace, not the
# link's. (Some may have: a shaper's burst can carry the head past the train's half.)
RECEIVER_LATE = "receiver_late"
RECEIVER_LATE_FRACTION = 0.5
# the twin's link socket received packets out of order while the train arrived (TCP_INFO's
# rcv_ooopack): a packet was lost or reordered, and the in-order byte count the train is timed by
# jumps when its retransmission fills the hole, so a span across the jump reads the link fast. The
# suspected cause, not a traced one, of a live over-reading (test_over_link beside busy loops: a 20
# Mbit/s link read 30.2 by a train the twin's thread took on time, sent at 4 x into a queue the
# fleet's frames already held); in simulation such a jump reads 1.25 x and more
OUT_OF_ORDER = "out_of_order"
# The measured part's rate is its fastest span's among those that carry at least this fraction of
# its link bytes. Each (read time, link bytes) pair is what the kernel had received when the twin
# read it, however late the read, so a span's rate is what the link delivered over it, and a late
# read only slows the spans that end on it: final52 (2026-11-29) read a 20 Mbit/s link as 8.4 when
# the twin took a train's last message ~30 ms late while the fleet's frames kept the link's
# last-receive time at the read.
FASTEST_SPAN_FRACTION = 0.5
# The kernel keeps a socket's last receive in jiffies (TCP_INFO's last_data_recv: Debian's amd64
# kernels tick at 250 Hz, 4 ms), so "silent for idle_s" means the data came between idle_s - tick
# and idle_s + tick before the read. The train's end is put at the latest of those: taken at its
# face value, an end a tick too early made a 20 Mbit/s link read 24.5 (CI, 2026-11-30) and up to
# 1.6 x in simulation; the latest end can only slow the reading, by at most a tick.
LAST_RECEIVE_TICK_S = 0.004
PROBE_REFUSALS = (BAD_PROBE, INCOMPLETE, TOO_SHORT, RECEIVER_LATE, OUT_OF_ORDER)


@dataclasses.dataclass(frozen=True)
class ProbeHeader:
    train: int
    index: int
    count: int
    train_bytes: int
    target_mbps: float
    sent_spread_s: float  # from the first message's put to this one's
    sent_blocked_s: float  # of that, the time the sender waited inside earlier puts (Zenoh's queue full)

    def encode(self, size_bytes) -> bytes:
        head = _HEADER.pack(
            PROBE_VERSION,
            self.train,
            self.index,
            self.count,
            self.train_bytes,
            self.target_mbps,
            self.sent_spread_s,
            self.sent_blocked_s,
        )
        return head + bytes(max(0, size_bytes - len(head)))


class ProbeError(ValueError):
    pass


def decode_probe(payload) -> ProbeHeader:
    """The header of one probe message; ProbeError for anything else."""
    raw = bytes(payload)
    if len(raw) < _HEADER.size:
        raise ProbeError(f"a probe message of {len(raw)} bytes is shorter than its header")
    version, train, index, count, train_bytes, target, spread, blocked = _HEADER.unpack_from(raw)
    if version != PROBE_VERSION:
        raise ProbeError(f"probe version {version}, not {PROBE_VERSION}")
    if not 0 <= index < count or train_bytes <= 0:
        raise ProbeError(f"probe message {index} of {count} in a train of {train_bytes} bytes")
    for name, v in (("target_mbps", target), ("sent_spread_s", spread), ("sent_blocked_s", blocked)):
        if not math.isfinite(v) or v < 0:
            raise ProbeError(f"probe field {name} = {v!r} is not a finite number >= 0")
    if target <= 0:
        raise ProbeError("probe target rate 0")
    return ProbeHeader(train, index, count, train_bytes, target, spread, blocked)


def train_shape(capacity_mbps):
    """(messages, bytes per message) of a train at `capacity_mbps` believed (the least train while
    nothing is believed)."""
    wanted = PROBE_MIN_TRAIN_BYTES
    if math.isfinite(capacity_mbps) and capacity_mbps > 0:
        wanted = min(PROBE_MAX_TRAIN_BYTES, max(PROBE_MIN_TRAIN_BYTES, capacity_mbps * PROBE_TRAIN_S / 8e-6))
    message = min(PROBE_MAX_MESSAGE_BYTES, max(PROBE_MIN_MESSAGE_BYTES, wanted / PROBE_TRAIN_MESSAGES))
    message = int(math.ceil(message / 1000.0) * 1000)
    return int(math.ceil(wanted / message)), message


def train_bytes_for(capacity_mbps):
    """A train's bytes at `capacity_mbps` believed (train_shape)."""
    count, message = train_shape(capacity_mbps)
    return count * message


def train_period_s(capacity_mbps, train_bytes=None, cost_fraction=PROBE_COST_FRACTION):
    """How far apart trains go so that they cost `cost_fraction` of `capacity_mbps` on average, s
    (`train_bytes` None: the train sized for that capacity)."""
    if not (math.isfinite(capacity_mbps) and capacity_mbps > 0):
        return PROBE_MAX_PERIOD_S
    if train_bytes is None:
        train_bytes = train_bytes_for(capacity_mbps)
    period = train_bytes * 8e-6 / (cost_fraction * capacity_mbps)
    return min(PROBE_MAX_PERIOD_S, max(PROBE_MIN_PERIOD_S, period))


def probe_cost_fraction(link_mbps, capacity_mbps, train_bytes=None):
    """What the trains cost of a `link_mbps` link while the sender believes `capacity_mbps`."""
    if train_bytes is None:
        train_bytes = train_bytes_for(capacity_mbps)
    return train_bytes * 8e-6 / train_period_s(capacity_mbps, train_bytes) / link_mbps


class TrainSchedule:
    """The robots' side: when a train is due (the link had room in the last report interval, the
    link up, a period of the capacity believed since the last one) and what it is (train_shape of
    the capacity believed). Not thread-safe."""

    def __init__(self, gain=PROBE_SEND_GAIN):
        if not (math.isfinite(gain) and gain > 1):
            raise ValueError(f"a train paced at {gain!r} x the capacity believed measures nothing")
        self.gain = float(gain)
        self.capacity_mbps = math.nan
        self.link_has_room = False  # the last report interval left the link room (note_interval)
        self.link_up = True
        self.last_train_s = -math.inf
        self.last_train_capacity_mbps = math.nan  # the capacity the last train was sized and paced for
        self.further = False  # the capacity rose far above it: the next train soon
        self.trains = 0

    @property
    def train_bytes(self):
        """The next train's bytes."""
        return train_bytes_for(self.capacity_mbps)

    def set_capacity(self, capacity_mbps):
        if math.isfinite(capacity_mbps) and capacity_mbps > 0:
            if capacity_mbps >= PROBE_FURTHER_RISE * self.last_train_capacity_mbps:
                self.further = True
            self.capacity_mbps = float(capacity_mbps)

    def note_interval(self, app_limited, socket_samples, socket_full_samples):
        """The last report interval: the sender app-limited (its queue ran empty), and in how many of
        the robots' link socket's samples it was full. The link had room if the sender was
        app-limited, or if its socket was full in under ROOM_SOCKET_FULL_FRACTION of the samples
        (its queue held by the pacer, not the link: paced at 0.9 x the estimate while the manager
        cruises, a fleet that fills the link is never app-limited, and on that alone no train would
        see a 5 -> 60 Mbit/s rise)."""
        full_fraction = socket_full_samples / socket_samples if socket_samples > 0 else 1.0
        self.link_has_room = bool(app_limited) or full_fraction < ROOM_SOCKET_FULL_FRACTION

    def due(self, now_s) -> bool:
        period_s = PROBE_MIN_PERIOD_S if self.further else train_period_s(self.capacity_mbps)
        return (
            self.link_has_room
            and self.link_up
            and math.isfinite(self.capacity_mbps)
            and now_s - self.last_train_s >= period_s
        )

    def cost_mbps(self):
        """What the trains cost the link on average at the capacity believed now, Mbit/s (0 before one
        is known): the budget keeps it out of the managed streams' share."""
        if not math.isfinite(self.capacity_mbps):
            return 0.0
        return self.train_bytes * 8e-6 / train_period_s(self.capacity_mbps)

    def start(self, now_s) -> "TrainPlan":
        """The next train (its id, sizes and pace), started at `now_s`."""
        self.trains += 1
        self.last_train_s = now_s
        self.last_train_capacity_mbps = self.capacity_mbps
        self.further = False
        count, message_bytes = train_shape(self.capacity_mbps)
        return TrainPlan(self.trains & 0xFFFFFFFF, count, message_bytes, self.gain * self.capacity_mbps)


@dataclasses.dataclass
class TrainPlan:
    """One train as the sender paces it: message k is due `due_s(k)` after the first."""

    train: int
    count: int
    message_bytes: int
    target_mbps: float
    blocked_s: float = 0.0
    started_s: float = math.nan

    @property
    def train_bytes(self):
        return self.count * self.message_bytes

    def due_s(self, index):
        return index * self.message_bytes * 8e-6 / self.target_mbps

    def message(self, index, now_s) -> bytes:
        """Message `index` as put at `now_s` (the first one starts the train's clock)."""
        if index == 0:
            self.started_s = now_s
        header = ProbeHeader(
            self.train,
            index,
            self.count,
            self.train_bytes,
            self.target_mbps,
            max(0.0, now_s - self.started_s),
            self.blocked_s,
        )
        return header.encode(self.message_bytes)

    def put_took(self, seconds, cpu_wait_s=0.0):
        """One put's time, of which `cpu_wait_s` runnable but waiting for a CPU (the thread's
        schedstat): the rest, when more than a millisecond, is the sender held back by Zenoh's full
        queue. The wait is the sender's own slowness, not the link's: on the reference mission's
        saturated robots' core a train's puts took 51-111 ms instead of 13, were counted as held
        back, and the train read as sent at its 231 Mbit/s target and received at 25-31: a
        "bottleneck" far under the link's 60 (2026-11-30)."""
        held_s = seconds - max(0.0, cpu_wait_s)
        if held_s > 1e-3:
            self.blocked_s += held_s


@dataclasses.dataclass(frozen=True)
class TrainMeasure:
    """One train as the twin measured it: `bytes` arrived over the link in `spread_s` over the fastest
    span of its measured part (the second half: FASTEST_SPAN_FRACTION), against the rate its
    messages over that span were sent at."""

    train: int
    messages: int
    bytes: int
    spread_s: float
    sent_mbps: float
    whole_bytes: int  # the same over the whole train, first to last message (for the record)
    whole_spread_s: float
    # how long the twin's receiving thread waited over the span, runnable but without a CPU (its
    # schedstat) or for its bridge's lock, s: its reads were late by up to that much, which only ever
    # slows a train; NaN where the kernel keeps no schedstat
    receiver_wait_s: float = math.nan

    @property
    def arrival_mbps(self):
        return self.bytes * 8e-6 / self.spread_s


def sent_rate_mbps(since: ProbeHeader, last: ProbeHeader, message_bytes):
    """The rate the messages from `since` to `last` were handed to the link: the train's target
    unless its sender could not keep it for its own reasons (a starved CPU, not the link holding
    it back in Zenoh's puts). Over the same part of the train as its arrival is measured: a sender
    that stalled in the second half sent it slowly, and its slow arrival is no bottleneck. The
    last message's size is left out (it was put at the end of the spread), as libwebrtc does."""
    spread_s = last.sent_spread_s - since.sent_spread_s
    free_s = spread_s - (last.sent_blocked_s - since.sent_blocked_s)
    if last.index <= since.index or free_s <= 0:
        return last.target_mbps
    return min(last.target_mbps, (last.index - since.index) * message_bytes * 8e-6 / free_s)


class TrainArrivals:
    """The twin's side: `arrival` per probe message with the link's cumulative received bytes then;
    a train's last message gives its TrainMeasure or a refusal counted in `refused`; a train cut
    short (a later train's first message, or `expire`) is counted incomplete. Not thread-safe: the
    bridge calls it under its lock."""

    def __init__(self, timeout_s=PROBE_TRAIN_TIMEOUT_S, min_fraction=PROBE_MIN_RECEIVED_FRACTION, on_refused=None):
        self.timeout_s, self.min_fraction = timeout_s, min_fraction
        self.on_refused = on_refused  # called with the reason of each train refused (the link report's)
        self.refused = dict.fromkeys(PROBE_REFUSALS, 0)
        self.measured = 0
        self.received_bytes = 0  # every probe message's bytes, measured or not
        # (header of the first message seen,
        #  [(t, link bytes, train bytes so far, header, idle s, wait s, packets out of order)])
        self._train = None

    def arrival(
        self, payload, now_s, link_bytes, idle_s=0.0, wait_s=math.nan, out_of_order=0
    ) -> Optional[TrainMeasure]:
        """One probe message taken at `now_s` (monotonic s) when the link had delivered `link_bytes`
        in all (cumulative, the message included) and had been silent for `idle_s` (the kernel's
        last_data_recv: a message taken after the train's end says when the end came), the taking
        thread having waited `wait_s` for a CPU or its lock so far (cumulative; NaN: unknown), and
        the link socket having received `out_of_order` packets out of order so far (cumulative).
        Returns the measure of a train this message completes, else None."""
        size = len(payload)
        self.received_bytes += size
        try:
            header = decode_probe(payload)
        except ProbeError:
            self._refuse(BAD_PROBE)
            return None
        train = self._train
        if train is not None and (train[0].train != header.train or now_s - train[1][0][0] > self.timeout_s):
            self._give_up()
            train = None
        if train is None:
            train = self._train = (header, [])
        samples = train[1]
        so_far = (samples[-1][2] if samples else 0) + size
        samples.append((now_s, link_bytes, so_far, header, max(0.0, idle_s), wait_s, out_of_order))
        if header.index == header.count - 1:
            self._train = None
            return self._measure(samples)
        return None

    def expire(self, now_s):
        """Give up a train whose last message is overdue (the bridge calls it now and then)."""
        if self._train is not None and now_s - self._train[1][0][0] > self.timeout_s:
            self._give_up()

    def _refuse(self, why):
        self.refused[why] += 1
        if self.on_refused is not None:
            self.on_refused(why)

    def _give_up(self):
        self._train = None
        self._refuse(INCOMPLETE)

    def _measure(self, samples) -> Optional[TrainMeasure]:
        last = samples[-1][3]
        if len(samples) < self.min_fraction * last.count:
            self._refuse(INCOMPLETE)
            return None
        measure = measure_train(samples, last.train_bytes // last.count)
        if not isinstance(measure, TrainMeasure):
            self._refuse(measure)
            return None
        self.measured += 1
        return measure


def measure_train(samples, message_bytes):
    """The TrainMeasure of one train's arrivals [(t, link bytes, train bytes so far, header, idle s,
    the receiving thread's wait for a CPU or its lock so far s, packets out of order so far)], or
    why not (TOO_SHORT, RECEIVER_LATE, OUT_OF_ORDER). The measured part starts at the message that completes half the train's bytes
    (the head may have passed a shaper's burst at the sender's rate) and ends when the link last
    received data before the last message was taken (the latest the kernel's tick allows:
    LAST_RECEIVE_TICK_S); its rate is that of its fastest span
    (FASTEST_SPAN_FRACTION), with the receiver's wait over that span."""
    if len(samples) < 2:
        return TOO_SHORT
    if samples[-1][6] != samples[0][6]:
        return OUT_OF_ORDER
    total = samples[-1][2]
    mid = next(i for i, s in enumerate(samples) if s[2] >= total / 2.0)
    mid = min(mid, len(samples) - 2)
    first, half, last = samples[0], samples[mid], samples[-1]
    end_s = max(last[0] - max(0.0, last[4] - LAST_RECEIVE_TICK_S), half[0])
    moved = last[1] - half[1]
    if end_s - half[0] <= 0 or moved <= 0:
        return TOO_SHORT
    if moved < RECEIVER_LATE_FRACTION * (total - half[2]):
        return RECEIVER_LATE
    # (read time, link bytes then, header, the receiver's wait then) over the measured part, in time;
    # the last message's at the link's last receive before it was read
    points = sorted(
        [(s[0], s[1], s[3], s[5]) for s in samples[mid:-1]] + [(end_s, last[1], last[3], last[5])],
        key=lambda p: p[0],
    )
    best = None  # (rate, bytes, spread s, header at its start, header at its end, receiver's wait s)
    for i, (t0, b0, h0, w0) in enumerate(points):
        for t1, b1, h1, w1 in points[i + 1 :]:
            if t1 > t0 and b1 - b0 >= FASTEST_SPAN_FRACTION * moved:
                rate = (b1 - b0) / (t1 - t0)
                if best is None or rate > best[0]:
                    best = (rate, b1 - b0, t1 - t0, h0, h1, w1 - w0)
    if best is None:
        return TOO_SHORT
    _, span_bytes, span_s, since, until, wait_s = best
    return TrainMeasure(
        train=last[3].train,
        messages=len(samples),
        bytes=int(span_bytes),
        spread_s=span_s,
        sent_mbps=sent_rate_mbps(since, until, message_bytes),
        whole_bytes=int(last[1] - first[1]),
        whole_spread_s=end_s - first[0],
        receiver_wait_s=wait_s,
    )
