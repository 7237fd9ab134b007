"""Online estimate of the link's capacity from what the link delivers (issue 23), no ROS.

Fed one `LinkReport` per measurement interval (the manager's 0.5 s): what the far side received,
what the sender put on the link, what the fleet wanted to send, whether the sender was
app-limited, heartbeat RTT samples and whether the receiver's processing (the twin's CPU) is
behind. Where each rule comes from (details in docs/bandwidth_manager.md):

- BBR: the capacity `capacity_mbps` is the maximum of delivery-rate samples taken while the
  sender is not app-limited (a sample is min(delivered, sent), BBR's guard against ACK
  compression: a backlog that arrives in a burst is not capacity). BBR ages its max filter over
  ~10 round trips; here it restarts at every overuse instead, because a fleet held back by its
  own allocation delivers less than the link could and would age a right estimate down (only an
  overuse is evidence of a lower capacity). The minimum RTT is the
  propagation floor; the allocation target probes above the capacity (gain 1.2, BBR's 1.25 kept inside the
  +-15 % band, for `probe_s`)
  only when demand exceeds it, and doubles per successful probe (BBR's STARTUP) so an up step is
  found in a few intervals.
- Google Congestion Control: overuse is a queue building, seen as delivered < sent over a merged
  window of `merge_window_s` (bursts of arrivals are merged, not read as queueing) or as the
  trendline of the RTT's queueing delay above an adaptive threshold (not absolute delay). On
  overuse caused by the link the capacity becomes what was delivered (the link was full, so that
  is its rate) and the allocation target is cut to 0.85 x it until the queue has drained.
- TCP_INFO: `rwnd_limited` (receiver not draining: its CPU) is kept apart from `app_limited`
  (the sender had nothing more to send). A receiver that is behind is recorded as
  `twin_capacity_mbps` and never lowers the link's capacity; an app-limited sender never lowers it.

Bad input (NaN, negative, a delivery rate above the line rate, time going backwards or repeating)
is counted in `ignored` by reason and ignored. No report holds the estimate (a silent far side);
`resume(now_s)` after an outage keeps the pre-outage capacity and restarts the per-interval state.

Two outputs, as BBR separates its bottleneck bandwidth from its pacing rate:
`capacity_mbps` (the link's capacity; what the accuracy targets judge) and `estimate_mbps` (the
rate the manager allocates from: the capacity, x the probe gain while probing, x the drain
factor while a queue drains). Time is passed in.
"""

import collections
import dataclasses
import math
from typing import Optional, Sequence

DRAIN_FACTOR = 0.85  # GCC's cut on overuse, x the acknowledged (delivered) rate
# With deficit_reports > 1 a deficit is overuse once it holds on that many reports in a row, or at
# once when it is this fraction of what was sent.
LARGE_DEFICIT_FRACTION = 0.4
# ... and a confirmed deficit of a busy sender whose window delivered below this x the capacity.
STEP_FRACTION = 0.7
# RTT samples of one interval from which its smallest says whether the queue emptied inside it.
WHOLE_INTERVAL_RTT_SAMPLES = 3
# A queue that stood all interval (its smallest RTT sample queueing) is the link's only if the
# sender's socket held at least this fraction of the bytes that delay means at what the link
# delivered: heartbeats delayed by a loaded host, not by a queue, come with an empty socket.
STANDING_QUEUE_BYTES_FRACTION = 0.5
# BBR's ProbeBW up gain is 1.25; 1.2 keeps a probe's allocation (96 % of it: 1.15 x the capacity)
# inside the +-15 % band the estimate is held to
PROBE_GAIN = 1.2
STARTUP_GAIN = 2.0  # BBR's STARTUP roughly doubles per round while delivery keeps up
# A probe adds the gap between the estimate and what the fleet sends, up to this fraction of its
# target (the manager's reserve and per-message headroom are a few per cent).
PROBE_GAP_FRACTION = 0.1


# Probe trains (cps_link.probe_train; libwebrtc's probe_bitrate_estimator.cc): a train received
# faster than this x its send rate was bunched on its way (the sender's batches, a shaper's burst)
# and measured no bottleneck; libwebrtc drops it. Here it counts as a train received at its pace
# does: the link carried its measured part no slower than it was sent, a lower bound at the send
# rate. Live (link_thesis, 5 -> 60 Mbit/s) the first train after the rise read 36.8 sent at 14.5,
# was dropped, and the capacity stayed 4.7 for 2.6 s more (settled 8.1 s after the rise).
TRAIN_MAX_VALID_RATIO = 2.0
# ... one received at least this x its send rate found no bottleneck: the link carries at least
# that much (a lower bound); one received slower came out at the bottleneck's rate.
TRAIN_UNSATURATED_RATIO = 0.9
TRAIN_BOTTLENECK = "bottleneck"
TRAIN_LOWER_BOUND = "lower_bound"
# A bottleneck below the capacity but above this x it is taken only when the next train confirms it
# (the larger of the two: the link carried that much): on a 60 Mbit/s link single trains read
# 36-81 Mbit/s (live, make demo on a loaded 2-core machine), a step down reads far below.
TRAIN_STEP_FRACTION = 0.7
# After a train's step down, the next train reading at least this x the capacity before the step
# refutes it (the band the estimate is held to): the step was the outlier.
STEP_REFUTED_FRACTION = 0.85
# After a step, trains are taken at once until two in a row read within this fraction of each other
# (the link's new rate, read twice), or max_drain_s has passed.
STEP_SETTLED_FRACTION = 0.1
# A bottleneck above the capacity is taken at once only above this x it, else when the next train
# confirms it (the smaller of the two). A receiver descheduled under load reads a train's bytes late
# and in a burst, which only ever reads fast (live, test_over_link beside busy loops: 26.2 Mbit/s on
# a 20 Mbit/s link); so does a burst a shaper (or Wi-Fi's aggregation) passes at the sender's pace
# after the link's queue ran empty under the train (its sender descheduled, or its TCP window shut
# after a loss): live 30.3 on the same link (1.58 x; 1 train in 100 over four runs, the others of
# that phase 19.1-20.2 but one at 10.7). In cps_link's token-bucket simulation (test_probe_train) a 10-50 ms gap
# in the sender's puts reads up to 1.3 x at 20 Mbit/s, and up to 4 x at 10 Mbit/s where a whole
# span fits in one burst. So 2 x is not a bound on such readings: it is where one reading is taken
# as a step up (20 -> 60 reads 3 x) at the cost of waiting a train for rises below it.
TRAIN_RISE_AT_ONCE = 2.0
TRAIN_HELD = "bottleneck_held"  # such a reading, waiting for the next train
# A bottleneck below what its own report interval delivered: raised to that (the link carried it).
TRAIN_BELOW_DELIVERED = "bottleneck_below_delivered"
# A train that came out slower than sent while the twin's receiving thread waited (for a CPU, or
# for its bridge's lock) more than this fraction of its measured part says only that the link
# carried at least that much: its reads came late, and a late read only ever slows a train. On the
# reference mission's saturated twin core (2026-11-30) the four trains that read a 60 Mbit/s link
# under 0.7 x (16-39 Mbit/s, each taken as a step down at once) had waited for a CPU 0.37-0.85 of
# their spans, trains read on time 0.01-0.27 (others up to 0.95 read 58-176 Mbit/s); counting the
# lock's waits too, link_thesis's shared_medium mission had 3 reports under 0.7 x the capacity
# against 34 with the CPU's alone.
TRAIN_RECEIVER_STARVED_FRACTION = 0.3
TRAIN_RECEIVER_STARVED = "receiver_starved_lower_bound"
# While a train was measured this recently the estimator does not probe by raising the allocation:
# the trains measure the link, up steps included (a train at 4 x the capacity). s.
TRAIN_FRESH_S = 12.0


def train_sample(arrival_mbps, sent_mbps, line_rate_mbps, receiver_wait_fraction=math.nan):
    """(kind, Mbit/s) of one probe train received at `arrival_mbps` that was sent at `sent_mbps`:
    (TRAIN_BOTTLENECK, the link's capacity) when it came out slower than sent,
    (TRAIN_LOWER_BOUND, what the link carried at least: the slower of the two) when it arrived at
    the rate sent or faster (more than TRAIN_MAX_VALID_RATIO x: at the rate sent), or (why it says
    nothing, NaN): train_not_finite, train_not_positive, train_above_line_rate (a bottleneck more
    than 2 x the line's rate); (TRAIN_RECEIVER_STARVED, a lower bound) for one slower than sent whose receiver
    waited (for a CPU or its lock) more than TRAIN_RECEIVER_STARVED_FRACTION of it
    (`receiver_wait_fraction`). A bottleneck above the line rate is the line rate. A lower bound
    above it is the estimator's to clip: a 60 Mbit/s link's trains read 60-220 Mbit/s over their
    25 ms halves (live), and after a false low reading such a train is what restores the capacity."""
    values = (arrival_mbps, sent_mbps)
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values):
        return "train_not_finite", math.nan
    if arrival_mbps <= 0 or sent_mbps <= 0:
        return "train_not_positive", math.nan
    if arrival_mbps >= TRAIN_UNSATURATED_RATIO * sent_mbps:
        return TRAIN_LOWER_BOUND, min(arrival_mbps, sent_mbps)
    if arrival_mbps > TRAIN_MAX_VALID_RATIO * line_rate_mbps:
        return "train_above_line_rate", math.nan
    if receiver_wait_fraction > TRAIN_RECEIVER_STARVED_FRACTION:  # False for NaN (unknown)
        return TRAIN_RECEIVER_STARVED, min(arrival_mbps, line_rate_mbps)
    # slower than sent but faster than the line: no bottleneck below the line (a shaper's burst or a
    # late read made it fast); live, two trains read a 60 Mbit/s line at 63.0 and were ignored while
    # the capacity stayed 22.5 for 8 s after the link came back (test_over_link)
    return TRAIN_BOTTLENECK, min(arrival_mbps, line_rate_mbps)


# The estimator's options when fed the bridges' link reports (issue 35, from the live runs): their
# two sides' intervals are measured on two clocks (a small deficit must hold on two reports), a
# 0.5 s interval moves by 40 % at 5 Mbit/s with one shaper burst or one large frame (samples over a
# second), a step's queue drains at 0.6 x, a refused probe's at 0.85 x (and the next waits up to 3 s),
# and a probe the fleet has not filled yet (it follows an allocation in ~1 s) lasts up to 1.5 s.
LINK_REPORT_OPTIONS = dict(
    deficit_min_mbps=0.5,
    deficit_reports=2,
    sample_window_s=1.0,
    step_drain_factor=0.6,
    drain_after_probe=True,
    probe_max_s=1.5,
    probe_backoff_max_s=3.0,
)


@dataclasses.dataclass(frozen=True)
class LinkReport:
    """One measurement interval of the link, as the manager receives it.

    `now_s`: when it was received (manager's clock); `interval_s`: the far side's measurement
    window. Rates in Mbit/s over that window. NaN / None: not known (today's manager has no RTT,
    app-limited or receiver-behind signal; see docs/bandwidth_manager.md for what the bridge must
    report)."""

    now_s: float
    interval_s: float
    delivered_mbps: float  # bytes the far side actually received
    sent_mbps: float = math.nan  # bytes the sender put on the link
    offered_mbps: float = math.nan  # what the fleet produced (demand before the rate limiters)
    app_limited: Optional[bool] = None  # the sender's queue ran empty (it had nothing more to send)
    rtt_s: Sequence[float] = ()  # heartbeat echo round-trip times measured in the interval
    receiver_behind: Optional[bool] = None  # the far side's processing is behind (CPU; TCP rwnd_limited)
    # the sender spent most of the interval waiting for the link to take what it sent (its queue
    # backlogged, its writes blocked): what was delivered is what the link carries
    link_limited: Optional[bool] = None
    # ... or the sender's socket was full in most of its samples (the link kept busy most of the
    # interval; its delivered rate can read low by the empty part)
    link_mostly_full: Optional[bool] = None
    # the sender's queue stayed backlogged (it never ran empty in the interval): the link was busy
    # with what it sent, so a rising RTT is its queue (None: taken as not app_limited)
    link_busy: Optional[bool] = None
    # a probe train measured in the interval (cps_link.probe_train): its arrival rate over its
    # measured part and the rate it was sent at (NaN: no train)
    train_mbps: float = math.nan
    train_sent_mbps: float = math.nan
    # of the train's measured part, the fraction its receiving thread waited for a CPU or its bridge's
    # lock (NaN: unknown)
    train_receiver_wait_fraction: float = math.nan
    # a probe train was on the link in the interval (sent or received): its deficit or surplus is
    # the train's queue, not the fleet's, and the train's own measure is the interval's
    train_on_link: bool = False
    # the largest kernel send queue (unacked + unsent) of the sender's link socket in the interval,
    # Mbit (NaN: not known)
    sender_queue_mbit: float = math.nan


class _Trendline:
    """GCC's delay-gradient detector: least-squares slope of the (smoothed) queueing delay over the
    last `window` samples, compared with a threshold that adapts to the slope's own size."""

    def __init__(self, window=8, smoothing=0.6, threshold_ms=25.0, k_up=0.0087, k_down=0.039):
        self.window, self.smoothing = window, smoothing
        self.threshold_ms, self.k_up, self.k_down = threshold_ms, k_up, k_down
        self.samples = collections.deque(maxlen=window)
        self.smoothed_ms = math.nan
        self.modified_trend = 0.0

    def reset(self):
        self.samples.clear()
        self.smoothed_ms = math.nan
        self.modified_trend = 0.0

    def update(self, now_s, queue_delay_ms, dt_s):
        """True when the delay gradient says a queue is building (overuse)."""
        s = (
            queue_delay_ms
            if math.isnan(self.smoothed_ms)
            else self.smoothing * self.smoothed_ms + (1 - self.smoothing) * queue_delay_ms
        )
        self.smoothed_ms = s
        self.samples.append((now_s, s))
        if len(self.samples) < 3:
            return False
        n = len(self.samples)
        mean_t = sum(t for t, _ in self.samples) / n
        mean_d = sum(d for _, d in self.samples) / n
        var = sum((t - mean_t) ** 2 for t, _ in self.samples)
        slope_ms_per_s = 0.0 if var <= 0 else sum((t - mean_t) * (d - mean_d) for t, d in self.samples) / var
        # GCC compares slope x samples x gain per packet group; over our 0.5 s intervals the
        # equivalent is the delay the slope adds across the window, in ms.
        span_s = self.samples[-1][0] - self.samples[0][0]
        self.modified_trend = slope_ms_per_s * span_s
        k = self.k_down if abs(self.modified_trend) < self.threshold_ms else self.k_up
        if abs(self.modified_trend) < self.threshold_ms + 15.0:  # GCC skips adapting on big spikes
            # GCC's k are per ms between packet groups; per 0.5 s report they would overshoot, so
            # they are applied per 100 ms: one report moves the threshold by 4-20 % of the gap
            self.threshold_ms += k * (abs(self.modified_trend) - self.threshold_ms) * dt_s * 1000.0 / 100.0
            self.threshold_ms = min(600.0, max(15.0, self.threshold_ms))
        return self.modified_trend > self.threshold_ms


class DeliveryRateEstimator:
    """The link's capacity from delivery rates (BBR) with GCC's overuse cut; see the module doc.

    `initial_mbps`: the prior (configured capacity); `line_rate_mbps`: the interface's rate, the
    ceiling of the estimate and above which a report is absurd; `min_mbps`: the floor."""

    def __init__(
        self,
        initial_mbps,
        line_rate_mbps=None,
        min_mbps=1.0,
        min_rtt_window_s=10.0,
        merge_window_s=1.0,
        deficit_fraction=0.05,
        deficit_min_mbps=0.3,
        probe_every_s=1.5,
        probe_s=0.5,
        max_drain_s=4.0,
        queue_delay_threshold_s=0.03,
        measure_window_s=0.0,
        deficit_reports=1,
        sample_window_s=0.0,
        step_drain_factor=None,
        drain_after_probe=False,
        probe_max_s=None,
        probe_backoff_max_s=None,
    ):
        for name, value in (
            ("initial_mbps", initial_mbps),
            ("min_mbps", min_mbps),
            ("min_rtt_window_s", min_rtt_window_s),
            ("merge_window_s", merge_window_s),
            ("probe_every_s", probe_every_s),
            ("probe_s", probe_s),
        ):
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        self.line_rate_mbps = float(initial_mbps if line_rate_mbps is None else line_rate_mbps)
        if not math.isfinite(self.line_rate_mbps) or self.line_rate_mbps < min_mbps:
            raise ValueError(f"line_rate_mbps ({self.line_rate_mbps}) must be finite and >= min_mbps ({min_mbps})")
        self.min_mbps = float(min_mbps)
        self.min_rtt_window_s = float(min_rtt_window_s)
        self.merge_window_s = float(merge_window_s)
        self.deficit_fraction = float(deficit_fraction)
        self.deficit_min_mbps = float(deficit_min_mbps)
        # reports in a row a small deficit must hold on (the bridges' two clocks: 2; one: 1)
        self.deficit_reports = max(1, int(deficit_reports))
        # delivery-rate samples (and an overuse's measure of the link) over this much of the last
        # reports, not one interval: a shaper's burst or one large frame moves a 0.5 s interval by
        # 40 % at 5 Mbit/s (live, issue 35); 0: per report
        self.sample_window_s = max(0.0, float(sample_window_s))
        self._samples = collections.deque()  # (now_s, interval_s, delivered, sent)
        # After a step (a large deficit, a blocked sender) the target drains at this x the new
        # capacity until the queue is gone (BBR drains its startup queue at 1/2.89): a shaper's
        # queue after 20 -> 5 Mbit/s held commands 150-200 ms for 3 s (live, issue 35). None: 0.85.
        self.step_drain_factor = DRAIN_FACTOR if step_drain_factor is None else float(step_drain_factor)
        # After a probe that found nothing, drain at 0.85 x for as long as the probe (BBR's
        # ProbeBW 0.75 phase): the probe's queue otherwise waits for the fleet to send less.
        self.drain_after_probe = bool(drain_after_probe)
        # A probe the fleet has not filled yet (it sent no more than before: it follows an
        # allocation in about a second) goes on up to this long (None: probe_s): one that ended
        # before the fleet followed found nothing, and live after 5 -> 60 Mbit/s no probe ever did.
        self.probe_max_s = probe_max_s
        # Each refused probe doubles the wait before the next, up to this (None: no backoff): at 5
        # Mbit/s the fleet always wants more, and a probe every 1.5 s queued 100 ms in the shaper
        # each time (live, issue 35). A probe that was not refused resets it.
        self.probe_backoff_max_s = probe_backoff_max_s
        self.probe_every_s = float(probe_every_s)
        if self.probe_backoff_max_s is None:
            self.probe_backoff_max_s = self.probe_every_s
        self._probe_wait_s = self.probe_every_s
        # how long a probe is held: one report interval when the reports are per interval; as long
        # as the measurement window when they are sliding averages (today's /tissue/stats: 2 s)
        self.probe_s = float(probe_s)
        self.probe_max_s = max(self.probe_s, self.probe_s if self.probe_max_s is None else float(self.probe_max_s))
        self.max_drain_s = float(max_drain_s)
        # the reports' rates are sliding averages over this window (0: per interval, as the
        # bridge's report; 2: today's /tissue/stats and limiter status)
        self.measure_window_s = max(0.0, float(measure_window_s))
        self._resumed_s = -math.inf
        self.queue_delay_threshold_s = float(queue_delay_threshold_s)
        self.capacity_mbps = self._clip(float(initial_mbps))
        self.estimate_mbps = self.capacity_mbps
        self.twin_capacity_mbps = math.nan  # what a behind receiver processed (the twin's, not the link's)
        self.receiver_behind = False
        self.congested = False
        self.mode = "cruise"  # cruise | probe | drain
        self.ignored = collections.Counter()  # reason -> reports ignored
        self.overuses = 0
        self.overuse_reasons = collections.Counter()  # deficit | rtt | link_full -> overuses
        # bottleneck | bottleneck_held | bottleneck_below_delivered | lower_bound |
        # receiver_starved_lower_bound -> trains
        self.trains = collections.Counter()
        self._train_s = -math.inf  # the last valid train's report
        # a small bottleneck reading waiting for the next train, and the capacity it was held against
        self._train_held = (math.nan, math.nan)
        self.last_overuse = ""  # the reason of the last overuse
        self.last_refused = ""  # why the last report was refused as a whole ("" it was taken)
        self._deficit_reports = 0  # consecutive reports whose merged window showed a deficit
        self._small_full_reports = 0  # consecutive reports of a full link a little below the capacity
        self._bw_max_mbps = self.capacity_mbps  # max delivery-rate sample since the last overuse (or the prior)
        self._unrefuted_mbps = self.capacity_mbps  # highest allocation target run without an overuse since
        self._rtt_samples = collections.deque()  # (now_s, smallest rtt_s, median rtt_s) per interval
        self._merged = collections.deque()  # (now_s, interval_s, delivered_mbps, sent_mbps)
        self._trend = _Trendline()
        self._last_now_s = None
        self._mode_since_s = -math.inf
        self._last_probe_s = -math.inf
        self._capacity_before_probe_mbps = math.nan
        self._drain_checked = False  # the drain's one correction of the capacity was made
        # The last step taken on one reading (an overuse's cut, a train's step down or rise taken at
        # once), the capacity it left (of cuts no train saw, the first one's), its direction and
        # whether a train took it.
        self._step_s = -math.inf
        self._before_step_mbps = math.inf
        self._step_up = False
        self._step_by_train = False
        self._step_settled = True  # two trains after the last step agreed (or none came in time)
        self._step_reading = math.nan  # the last train reading taken since that step
        # the most an interval with the link socket full throughout delivered since that step (Mbit/s)
        self._full_since_step_mbps = 0.0
        self._gain = PROBE_GAIN

    @property
    def allocation_mbps(self):
        """The rate the fleet is allotted from: the estimate, but the capacity while a queue drains.
        A drain is the pacer's (BBR lowers its pacing gain, not what the application may send):
        sent to the robots' rate limiters as setpoints, whose raises wait out a hold (issue 36:
        5 s per stream), a 1 s drain kept the fleet far below the link for 5 s and more, left
        every probe unfilled and hid a 20 -> 60 Mbit/s step (live, test_over_link)."""
        return max(self.estimate_mbps, self.capacity_mbps) if self.mode == "drain" else self.estimate_mbps

    @property
    def ignored_samples(self):
        """Reports ignored for any reason (bad values, clock steps)."""
        return sum(self.ignored.values())

    @property
    def min_rtt_s(self):
        """BBR's propagation floor: the smallest RTT sample of the last `min_rtt_window_s`."""
        return min(r for _, r, _ in self._rtt_samples) if self._rtt_samples else math.nan

    def _clip(self, mbps):
        return min(max(mbps, self.min_mbps), self.line_rate_mbps)

    def resume(self, now_s):
        """The link is back after an outage: the capacity measured before it is kept (an outage
        says nothing about the capacity), the per-interval state restarts at `now_s`."""
        self._last_now_s = now_s
        self._resumed_s = now_s
        self._merged.clear()
        self._samples.clear()
        self._deficit_reports = 0
        self._small_full_reports = 0
        self._trend.reset()
        self._rtt_samples.clear()
        self._set_mode("cruise", now_s)
        self.estimate_mbps = self.capacity_mbps
        self.congested = self.receiver_behind = False

    def announce(self, capacity_mbps, now_s=None):
        """Who knows the link's capacity announced it: it becomes the ceiling (the line rate) and
        the new prior, so the estimate follows a step at once in either direction and goes below
        it only on evidence (an overuse: cross traffic the announcement does not know of). The
        per-interval state restarts as after an outage (`now_s`: None keeps the last report's time)."""
        mbps = float(capacity_mbps)
        if not math.isfinite(mbps) or mbps <= 0:
            raise ValueError(f"announced capacity must be a finite number > 0 Mbit/s, got {capacity_mbps!r}")
        self.line_rate_mbps = mbps
        self.min_mbps = min(self.min_mbps, mbps)
        self.capacity_mbps = self._bw_max_mbps = self._unrefuted_mbps = mbps
        now_s = self._last_now_s if now_s is None else now_s
        if now_s is None:  # no report yet: nothing per interval to restart
            self.estimate_mbps = self.capacity_mbps
        else:
            self.resume(now_s)

    def _reject(self, r):
        """The reason a report is unusable, or None."""
        values = (r.now_s, r.interval_s, r.delivered_mbps)
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            return "not_finite"
        if r.interval_s <= 0 or r.delivered_mbps < 0:
            return "negative"
        for v in (r.sent_mbps, r.offered_mbps):
            if not (isinstance(v, (int, float)) and (math.isnan(v) or (math.isfinite(v) and v >= 0))):
                return "negative"
        if r.delivered_mbps > 1.05 * self.line_rate_mbps:
            return "above_line_rate"
        if self._last_now_s is not None and r.now_s <= self._last_now_s + 0.25 * r.interval_s:
            return "clock_step"  # backwards, or a repeat of the interval just counted
        return None

    def _refuse(self, reason):
        """The report is not used at all: counted in `ignored`, named in `last_refused`."""
        self.ignored[reason] += 1
        self.last_refused = reason
        return self.estimate_mbps

    def _in_step_drain(self, now_s):
        """Is `now_s` within max_drain_s of the last step taken on one reading?"""
        return now_s - self._step_s <= self.max_drain_s

    def _step_unseen(self, now_s):
        """No train has come since the last step taken on one reading, made within max_drain_s of `now_s`."""
        return self._train_s <= self._step_s and self._in_step_drain(now_s)

    def _reads_past_the_step(self, measured):
        """Is a train's `measured`, the first after a step, taken at once (see `_take_train`)?"""
        if not self._step_by_train or self._step_up or measured <= self.capacity_mbps:
            return True
        return measured >= STEP_REFUTED_FRACTION * self._before_step_mbps

    def _step_open(self, now_s):
        """Since the last step taken on one reading, no two trains have agreed, within max_drain_s."""
        return not self._step_settled and self._in_step_drain(now_s)

    def _mark_step(self, now_s, up, by_train, reading=math.nan):
        """A step taken on one reading (`reading`: a train's): the trains after it are taken at once
        until two agree (`_take_train`)."""
        if by_train or self._step_by_train or not self._step_unseen(now_s):
            self._before_step_mbps = self.capacity_mbps  # (a cut soon after one no train saw keeps its origin)
        self._step_s, self._step_up, self._step_by_train = now_s, up, by_train
        self._step_settled, self._step_reading = False, reading
        self._full_since_step_mbps = 0.0

    def _note_step_reading(self, reading):
        """A train reading taken while a step is open: two in a row within STEP_SETTLED_FRACTION settle it."""
        previous = self._step_reading
        if math.isfinite(previous) and abs(reading - previous) <= STEP_SETTLED_FRACTION * previous:
            self._step_settled = True
        self._step_reading = reading

    def _set_mode(self, mode, now_s):
        if mode != self.mode:
            self.mode, self._mode_since_s = mode, now_s

    def update(self, report: LinkReport):
        """Feed one interval; returns the allocation target `estimate_mbps` (Mbit/s)."""
        estimate = self._update(report)
        if not self.last_refused and not self.receiver_behind and self._socket_full_throughout(report):
            # what the link carried while full throughout, since the last step (`_link_full`)
            self._full_since_step_mbps = max(self._full_since_step_mbps, report.delivered_mbps)
        return estimate

    @staticmethod
    def _socket_full_throughout(report):
        """Where the report counts the link socket's own bytes: was that socket full all interval?"""
        return bool(report.link_limited) and bool(report.link_mostly_full)

    def _update(self, report):
        self.last_refused = ""
        reason = self._reject(report)
        if reason:
            return self._refuse(reason)
        if report.now_s < self._resumed_s + self.measure_window_s - 1e-6:
            # sliding averages still hold the outage (sent, nothing delivered): not a measurement
            self._last_now_s = report.now_s
            return self._refuse("window_holds_outage")
        now = report.now_s
        dt = report.interval_s if self._last_now_s is None else min(report.interval_s, now - self._last_now_s)
        self._last_now_s = now
        delivered, sent = report.delivered_mbps, report.sent_mbps
        self.receiver_behind = bool(report.receiver_behind)
        if self.receiver_behind:
            # rwnd-limited: the twin's CPU, not the link. Its rate is the twin's capacity. The
            # deficit and the RTT rise it causes are not the link's: forget them.
            self.twin_capacity_mbps = delivered
            if not (isinstance(report.train_mbps, float) and math.isnan(report.train_mbps)):
                self.ignored["train_receiver_behind"] += 1  # its arrival was the twin's pace
            self.congested = False
            self._merged.clear()
            self._deficit_reports = 0
            self._trend.reset()
            return self.estimate_mbps
        if not math.isnan(sent) and sent > 0 and delivered == 0:
            # Nothing arrived although the sender sent: an outage in the making (liveliness decides).
            return self._refuse("stalled")
        train_read_mbps = self._take_train(report)
        if report.train_on_link:
            # a train's queue is no overuse (live, it read as a deficit and cut a 10 Mbit/s link's
            # capacity to the 7.9 Mbit/s its 0.5 s interval delivered): the interval is the train's
            self.trains["interval"] += 1
            self._merged.clear()
            self._samples.clear()
            self._deficit_reports = 0
            full = self._link_full(report, delivered)
            far_below = delivered < STEP_FRACTION * self.capacity_mbps
            step = full and far_below and not train_read_mbps >= STEP_FRACTION * self.capacity_mbps
            # ... unless the link was full all along and far below the capacity (a step): then
            # what it delivered, the train's frames included, is its rate. A train waits behind
            # every data frame, so on a full link it trickles through interval after interval:
            # live after a 60 -> 20 Mbit/s step, 8 intervals in a row held a train's bytes
            # (socket full in every sample, the sender's queue never empty) and the capacity
            # stayed 58 for 4 s (test_over_link, 2026-11-29). A small shortfall is the train's
            # own cost: sent at 4 x into the link's queue it can cost a packet, and TCP then
            # sends below the link for an interval with its socket full (live beside busy loops,
            # 2026-11-30: 16.0 delivered on a 20 Mbit/s link that the same interval's train read
            # at 19.2, cut to 16.2; twice in four runs). A train read in this interval near the
            # capacity says the link is no step below it: live (final93, 2026-12-01) 1.8 s after
            # a 60 -> 20 step's cut to 19.1 an interval delivered 13.0, its socket full 60 % of
            # the time and its own train reading 19.1; cut to 13.3 for 1 s (the sender short of
            # a CPU: the next interval sent 9.5, neither app-limited nor its socket full).
            # ... and an interval full throughout that carried only the tail of a train (its
            # bytes trickling through the full link, its reading in another interval) counts
            # towards the run a small shortfall needs, as an interval without a train does: the
            # train's cost is a train's own interval's. Live (c26e, 2026-12-01) the first train
            # after a 60 -> 20 Mbit/s step read 24.6; the intervals after it delivered 19.1
            # with the socket full throughout, all but one holding a train's tail, and 24.6
            # (+23 %) stood 2 s.
            tail_short = full and math.isnan(report.train_mbps) and self._socket_full_throughout(report)
            if tail_short:
                self._small_full_reports += 1
            if step or (tail_short and self._small_full_reports >= self.deficit_reports):
                self._overuse("link_full")
                self._on_overuse(now, delivered, sent, self.step_drain_factor)
                return self.estimate_mbps
            self.congested = False
            self.capacity_mbps = self._clip(self._bw_max_mbps)
            return self.estimate_mbps
        self._merged.append((now, report.interval_s, delivered, sent))
        while self._merged and self._merged[0][0] <= now - self.merge_window_s:
            self._merged.popleft()
        rtt_overuse, queue_delay_s, least_queue_delay_s = self._rtt(now, report.rtt_s, dt)

        # a small deficit must hold on two reports in a row: the two sides' intervals are measured on
        # two clocks, and one large frame sent at the end of one interval arrives in the next; a
        # large one (LARGE_DEFICIT_FRACTION of what was sent) is no such accident. A report counts
        # towards the run only if its own interval's queue grew too (by half the deficit's bar): the
        # merged window holds one interval's deficit on two reports, and live (test_over_link,
        # final29) one large frame written at an interval's end, then an interval sent and acked
        # alike, "held" on two and cut a 19.3 Mbit/s link's capacity to 16.4 for 3 s
        grew = not math.isnan(sent) and sent - delivered > 0.5 * max(
            self.deficit_fraction * sent, self.deficit_min_mbps
        )
        self._deficit_reports = self._deficit_reports + 1 if grew and self._deficit() else 0
        large = self._deficit_reports >= 1 and self._deficit(LARGE_DEFICIT_FRACTION, 2.0 * self.deficit_min_mbps)
        deficit = self._deficit_reports >= self.deficit_reports or large
        # a link-limited interval that delivered clearly less than the capacity believed: the link
        # is full at what it delivered (the sender's blocked writes kept it from showing a deficit)
        # (while draining too: a cut from a window straddling a step can leave the capacity far
        # above what the link now takes, live 48.9 Mbit/s for 4 s on a 5 Mbit/s link)
        full = self._link_full(report, delivered)
        # ... at once if far below (a step), else once it holds on deficit_reports reports in a row:
        # one interval a little below is TCP recovering from a lost packet with its socket full
        # (live, final76: the interval after a train read the 20 Mbit/s link at 16.4, 0.85 x, and
        # cut the capacity for one report; the next train read 19.3). Train intervals, which have
        # their own rule above, neither count nor break the run.
        self._small_full_reports = self._small_full_reports + 1 if full else 0
        if full and delivered >= STEP_FRACTION * self.capacity_mbps:
            full = self._small_full_reports >= self.deficit_reports
        app_limited = report.app_limited
        if app_limited is None:
            # inferred (BBR: in flight below what the pacing allowed): the sender used clearly less
            # than its allocation, everything offered was sent, and it all arrived
            app_limited = (
                not deficit
                and not rtt_overuse
                and (math.isnan(sent) or sent < 0.9 * self.estimate_mbps)
                and (math.isnan(report.offered_mbps) or math.isnan(sent) or report.offered_mbps <= 1.02 * sent)
            )
        # A queue building is overuse whether or not the sender's own queue ran empty: app-limited
        # marks the delivery-rate samples (too low to lower the capacity), not the link's deficit
        # (issue 35: a bridge whose queue emptied between frames sent 14 Mbit/s into a 5 Mbit/s link).
        # A rising RTT is our queue only while the sender kept the link busy: heartbeat echoes through
        # loaded processes jitter by tens of ms, and read as overuse on an idle link they cut the
        # capacity to what an app-limited fleet happened to send (issue 35, live).
        busy = report.link_busy if report.link_busy is not None else not app_limited
        # ... or the bottleneck's queue stood all interval although the sender's own queue ran empty
        # between frames: every heartbeat waited behind it (the interval's smallest RTT queueing) and
        # the sender's socket held those bytes. Live (link_thesis, a 20 -> 5 Mbit/s step with the
        # fleet offering ~5 Mbit/s): RTT 2 -> 115-139 ms and 195-298 kB in the socket for 1.5 s, no
        # overuse (app-limited, the socket not full; both trains refused for packets out of order),
        # the step seen 2.7 s late and the operator's video p95 267 ms.
        standing = self._standing_queue(report, delivered, least_queue_delay_s)
        busy = busy or standing
        self.congested = deficit or full or (rtt_overuse and busy)
        if self.congested:
            self._overuse("deficit" if deficit else "link_full" if full else "rtt")
        window_delivered, window_sent = self._window(now, report.interval_s, delivered, sent)
        if self.congested:
            # a step (a large deficit, a sender blocked by the link): this interval is the new link;
            # otherwise the window's average, not one interval's noise
            # ... or a confirmed deficit while the sender kept the link busy, its window far below
            # the capacity (an app-limited fleet's window says nothing about the link: live, such a
            # "step" set a 60 Mbit/s link's capacity to the 2.4 Mbit/s it was sending)
            # ... or a standing queue while the link delivered far below the capacity: the link was
            # busy all interval, so what it delivered is its rate
            step = (
                large
                or full
                or (deficit and busy and window_delivered < STEP_FRACTION * self.capacity_mbps)
                or (rtt_overuse and standing and delivered < STEP_FRACTION * self.capacity_mbps)
            )
            if step or self.sample_window_s <= 0:
                self._on_overuse(now, delivered, sent, self.step_drain_factor if step else DRAIN_FACTOR)
            else:
                # GCC's multiplicative decrease bounds what one small overuse takes off the capacity
                self._on_overuse(now, max(window_delivered, DRAIN_FACTOR * self.capacity_mbps), window_sent)
            return self.estimate_mbps

        sample = window_delivered if math.isnan(window_sent) else min(window_delivered, window_sent)
        if not app_limited or sample > self._bw_max_mbps:
            # BBR: app-limited samples only count when they exceed the current estimate.
            self._bw_max_mbps = max(self._bw_max_mbps, sample)

        if (
            self.mode == "drain"
            and not self._drain_checked
            and not math.isnan(sent)
            and now - self._mode_since_s >= (1 if self.sample_window_s > 0 else 2) * report.interval_s - 1e-6
        ):
            # The first whole interval after the cut (the report at the cut covered the step; with
            # reports of the sender's interval, the next one is after it; a sliding window's later): if the queue the overuse left was still
            # served all along (more delivered than sent; by the RTT, still queueing), the link ran
            # full and what it delivered is its rate (GCC's acknowledged bitrate). This corrects a
            # cut measured over an interval that straddled the step. Once only: later the queue
            # may empty inside an interval.
            self._drain_checked = True
            queueing = math.isnan(queue_delay_s) or queue_delay_s > self.queue_delay_threshold_s
            # ... or still filling (less delivered than sent, by the RTT still queueing: a cut
            # measured before the step's interval was over): the link ran full, so what it
            # delivered is its rate
            still_full = (
                self.sample_window_s > 0
                and sent >= 1.05 * delivered
                and not math.isnan(queue_delay_s)
                and queue_delay_s > self.queue_delay_threshold_s
            )
            # ... and only if the link was full over the whole interval where the sender says so
            # (its socket full in nearly every sample): a queue that emptied inside the interval
            # left part of it idle, and its delivered rate is below the link's
            # ... or where even the interval's smallest RTT sample was queueing: the queue never
            # emptied, so the link was busy all along though the draining sender's socket was not
            # full (live, under a loaded machine, a 60 -> 20 Mbit/s step's straddling interval left
            # the capacity at 23.5 for 2.5 s because that socket was not full; 2026-11-28)
            whole = (
                report.link_limited is None
                or bool(report.link_limited)
                or least_queue_delay_s > self.queue_delay_threshold_s
            )
            # ... or, where the report counts the link socket's own bytes, that socket full all
            # interval: the queue stood in the sender's kernel, the link carried all it could, and
            # what was acknowledged is its rate; sent and acknowledged bytes are then alike, and
            # the heartbeats, which do not wait in that socket, see no queue. Live (test_over_link,
            # 2026-12-01) a 60 -> 20 Mbit/s step's straddling interval cut to 25.4; the next two
            # intervals had the socket full throughout and delivered 19.1 at an RTT of 2 ms, and
            # the capacity stayed 25.4 until an interval with its socket 60 % full cut it to 16.9.
            socket_full_all_along = self._socket_full_throughout(report)
            if ((delivered >= 1.02 * sent or still_full) and queueing and whole) or socket_full_all_along:
                self.capacity_mbps = self._bw_max_mbps = self._unrefuted_mbps = self._clip(delivered)
                self.estimate_mbps = self._clip(DRAIN_FACTOR * self.capacity_mbps)
        if self.mode == "drain":
            # Without RTT: the link no longer delivers more than is sent (its queue is empty), seen
            # in a report that began after the cut took effect (the first one mixes both rates).
            drained = (
                (not math.isnan(queue_delay_s) and queue_delay_s < self.queue_delay_threshold_s)
                or (
                    math.isnan(queue_delay_s)
                    and not math.isnan(sent)
                    and delivered <= 1.02 * sent
                    and now - self._mode_since_s >= 2 * report.interval_s - 1e-6
                )
                or now - self._mode_since_s >= self.max_drain_s
            )
            if drained:
                self._set_mode("cruise", now)
        kept_up = False
        if self.mode == "probe":
            # The link carried clearly more than the capacity believed (10 %: more than the
            # measurement noise) and all that was sent: BBR's STARTUP, double next time, at once.
            # That can show before `probe_s` is over (a sliding window rises early); a refusal
            # can only be trusted once the window holds the whole probe.
            kept_up = (
                not math.isnan(sent)
                and delivered >= 1.1 * self._capacity_before_probe_mbps
                and delivered >= 0.97 * sent
            )
        probed_s = now - self._mode_since_s
        # Undecided: the fleet has not filled the probe yet, or it sends more and the link carried
        # all of it but not yet 1.1 x (the fleet is still ramping up: live after 20 -> 60 Mbit/s a
        # probe ended on its first interval at 1.07 x, refusing nothing and proving nothing, three
        # times in a row). It goes on until kept, refused or probe_max_s.
        undecided = not math.isnan(sent) and (
            sent < 1.05 * self._capacity_before_probe_mbps or delivered >= 0.97 * sent
        )
        if (
            self.mode == "probe"
            and (kept_up or probed_s >= self.probe_s - 1e-6)
            and (kept_up or not undecided or probed_s >= self.probe_max_s - 1e-6)
        ):
            self._gain = STARTUP_GAIN if kept_up else PROBE_GAIN
            if kept_up or app_limited:
                # Nothing refused the probe's rate and the fleet got all it wanted at it: it may
                # keep that rate (BBR keeps pacing at the last rate the path accepted), though the
                # capacity only rises by what was measured.
                self._unrefuted_mbps = max(self._unrefuted_mbps, self.estimate_mbps)
            self._last_probe_s = now
            # refused: the link did not carry all that was sent (a fleet that sent no more than the
            # capacity, or got all of it through, refused nothing: it may simply not need more)
            refused = not (kept_up or app_limited) and not math.isnan(sent) and delivered < 0.97 * sent
            self._probe_wait_s = (
                min(self.probe_backoff_max_s, 2.0 * self._probe_wait_s) if refused else self.probe_every_s
            )
            if refused:
                # The probe's queue is acted upon here (its deficit says the link is below the
                # probe's rate, not below the capacity measured before it): the next deficit must
                # be new, as after an overuse. Live, the probe's own deficit, still in the merged
                # window on the next report, cut a 19.1 Mbit/s capacity to 16.3 (0.85 x).
                self._merged.clear()
                self._deficit_reports = 0
                self._trend.reset()
            if self.drain_after_probe and refused:
                # the link took no more: empty what the probe queued before cruising again
                self._set_mode("drain", now)
                self._drain_checked = True
                self.estimate_mbps = self._clip(DRAIN_FACTOR * self.capacity_mbps)
            else:
                self._set_mode("cruise", now)
        self.capacity_mbps = self._clip(self._bw_max_mbps)

        demand_exceeds = not app_limited
        # no probe while a queue drains (more delivered than sent): the link is full already
        surplus = not math.isnan(sent) and delivered - sent > max(self.deficit_fraction * sent, self.deficit_min_mbps)
        can_probe = self.capacity_mbps < self.line_rate_mbps and not surplus
        quick = self._gain == STARTUP_GAIN
        if (
            self.mode == "cruise"
            and demand_exceeds
            and can_probe
            and (quick or now - self._last_probe_s >= self._probe_wait_s)
            and now - self._train_s >= TRAIN_FRESH_S
        ):
            self._set_mode("probe", now)
            self._capacity_before_probe_mbps = self.capacity_mbps
            # The manager keeps a reserve and per-message headroom below the target, so the fleet
            # sends less than it: the probe adds that gap, for the *sent* rate to reach gain x.
            # The gap is bounded: after a drain the fleet may still send far below the estimate
            # (its rates were cut), and an unbounded gap took a 20 Mbit/s link's estimate to 28
            # Mbit/s live (test_over_link); at most PROBE_GAP_FRACTION of the probe's own target.
            gap = max(0.0, self.estimate_mbps - sent) if not math.isnan(sent) else 0.0
            # from the level kept by the last unrefused probe (the fleet may not have filled it yet)
            target = self._gain * self.capacity_mbps
            self.estimate_mbps = self._clip(target + min(gap, PROBE_GAP_FRACTION * target))
        elif self.mode == "cruise":
            self._gain = PROBE_GAIN if not demand_exceeds else self._gain
            self.estimate_mbps = self._clip(max(self.capacity_mbps, self._unrefuted_mbps))
        return self.estimate_mbps

    def _take_train(self, report):
        """A probe train's sample (train_sample): a bottleneck measured is the link's capacity, in
        either direction (the fleet sends too little for its own samples to say), at once when it
        is below TRAIN_STEP_FRACTION of the capacity or above TRAIN_RISE_AT_ONCE x it (or below
        the capacity an overuse's cut set, the first train within max_drain_s of it), else once the
        next train confirms it; a lower bound (a receiver-starved reading is one) only raises it;
        a bottleneck more than STEP_SETTLED_FRACTION below what its own interval delivered changes
        nothing (that interval's delivery sample counts as any); one less below reads as that
        interval. Bad samples are counted by kind in `ignored` and change
        nothing. Returns what the link carried by the train's reading (Mbit/s; NaN without a
        valid train)."""
        if isinstance(report.train_mbps, float) and math.isnan(report.train_mbps):
            return math.nan  # no train in this interval
        kind, mbps = train_sample(
            report.train_mbps, report.train_sent_mbps, self.line_rate_mbps, report.train_receiver_wait_fraction
        )
        if math.isnan(mbps):
            self.ignored[kind] += 1
            return math.nan
        step_open = self._step_open(report.now_s)
        self._train_s = report.now_s
        if kind == TRAIN_BOTTLENECK and mbps < report.delivered_mbps:
            # The link delivered more over the train's interval than the train says it can: its
            # own interval refutes the reading, which measured no bottleneck (the link carried at
            # least what the interval delivered; that sample counts as any other). Live
            # (test_over_link, 2026-11-30) a train read a 20 Mbit/s link at 11.7 in an interval that
            # delivered 15.6, taken at once as a step down; raised to 15.6 and still taken as a
            # bottleneck, one read 10.2 where 14.0 was delivered 1.9 s after the 60 -> 20 step's
            # cut (final92, 2026-12-01) and was taken at once as the shortfall after a cut: 14.0 on
            # the 20 Mbit/s link for 1 s. Within STEP_SETTLED_FRACTION of it, the two agree: the
            # reading is what the interval delivered (live, c25g 2026-12-01: the first train after a
            # 60 -> 20 step's cut to 26.1 read 19.1 in an interval that delivered a little more;
            # refuted, the cut's 26.1 stood for 3.5 s).
            self.trains[TRAIN_BELOW_DELIVERED] += 1
            if mbps < (1.0 - STEP_SETTLED_FRACTION) * report.delivered_mbps:
                return report.delivered_mbps
            mbps = report.delivered_mbps
        measured = self._clip(mbps)
        # a held reading counts only against the capacity it was held against: live (test_over_link)
        # one held on the 60 Mbit/s link "confirmed" a 19 Mbit/s reading after the 60 -> 20 step
        (held, held_against), self._train_held = self._train_held, (math.nan, math.nan)
        if held_against != self.capacity_mbps:
            held = math.nan
        # a step on this one reading: taken at once, and the trains after it too until two agree
        step = not TRAIN_STEP_FRACTION * self.capacity_mbps <= measured <= TRAIN_RISE_AT_ONCE * self.capacity_mbps
        if kind in (TRAIN_LOWER_BOUND, TRAIN_RECEIVER_STARVED):
            self.trains[kind] += 1
            if measured <= self.capacity_mbps:
                return measured
        elif step_open and not step and self._reads_past_the_step(measured):
            # The trains after a step taken on one reading read the link itself: at once, either
            # way, back across the step no further than where it started, until two of them agree
            # (within max_drain_s). Live (test_over_link, session 21) the first train after a cut
            # read a 20 Mbit/s link at 24.3 (sent at 230 for the old capacity) and the next one's
            # 19.5 was held as a small shortfall: 24.3 for over 2 s. Why at once:
            # - after an overuse's cut, a shortfall: the cut was the step's first reading (an
            #   interval that straddled it, so above the new link). Live (test_over_link, final62) a
            #   60 -> 20 Mbit/s step cut to 24.7; held, the train's 19.1 waited 2.5 s for the next;
            # - after a cut, a rise: the cut read one interval (live beside busy loops, a train's loss
            #   left TCP below a 20 Mbit/s link with its socket full: cut to 16.9, the next train's
            #   19.3 held, the one after it under-read: 16.9 for 2.5 s);
            # - after a train's step down, a further shortfall, or a reading back where the capacity
            #   was before it (the step was the outlier): live (link_thesis, 60 Mbit/s) one train sent
            #   by a stalled sender read 36.1 and the next one's 56.3 was held: 36.1 for 5.5 s. A
            #   rise part of the way back is held as any (a receiver read late reads fast);
            # - after a train's rise: the link may have risen further. Live (link_thesis, 5 -> 60)
            #   the rise went 4.7 -> 18.8 -> 44.8 on two lower bounds, and the first bottleneck
            #   reading, 56.1, waited for the next train: 3.5 s in all.
            # - but a shortfall against a train already read since the step, the two disagreeing,
            #   takes their mean: one of them is off, and a train read by a sender or receiver short
            #   of a CPU reads low. Live (test_over_link, 2026-12-01) the first train after a 60 -> 20
            #   step's cut read 19.2, the next 15.2 (taken at once: -24 % for 1 s), the next 19.4.
            previous = self._step_reading
            self._note_step_reading(measured)
            if math.isfinite(previous) and measured < previous and not self._step_settled:
                measured = 0.5 * (measured + previous)
            if self._step_up and measured < self.capacity_mbps:
                measured = max(measured, self._before_step_mbps)
            elif not self._step_up and measured > self.capacity_mbps:
                measured = min(measured, self._before_step_mbps)
            self.trains[kind] += 1
        elif measured != self.capacity_mbps and not step:
            rise = measured > self.capacity_mbps
            if math.isnan(held) or (held > self.capacity_mbps) != rise:
                self._train_held = (measured, self.capacity_mbps)
                self.trains[TRAIN_HELD] += 1
                return measured
            # a shortfall confirmed: the link carried the larger; a rise confirmed: at least the smaller
            measured = min(measured, held) if rise else max(measured, held)
            self.trains[kind] += 1
        else:
            self.trains[kind] += 1
        if step:
            self._mark_step(report.now_s, up=measured > self.capacity_mbps, by_train=True, reading=measured)
        if abs(measured - self.capacity_mbps) > self.deficit_fraction * self.capacity_mbps:
            # the link changed: samples from before are not its rate
            self._samples.clear()
            self._merged.clear()
            self._deficit_reports = 0
            self._small_full_reports = 0
        self.capacity_mbps = self._bw_max_mbps = self._unrefuted_mbps = measured
        if self.mode == "drain":
            self.estimate_mbps = min(self.estimate_mbps, measured)
        else:
            self._set_mode("cruise", report.now_s)
            self.estimate_mbps = measured
        return measured

    def _standing_queue(self, report, delivered, least_queue_delay_s):
        """Did the link's queue stand all interval: the smallest of its RTT samples queueing, and the
        sender's socket holding at least STANDING_QUEUE_BYTES_FRACTION of the bytes that delay means?"""
        if math.isnan(least_queue_delay_s) or least_queue_delay_s <= self.queue_delay_threshold_s:
            return False
        queued = report.sender_queue_mbit
        return math.isfinite(queued) and queued >= STANDING_QUEUE_BYTES_FRACTION * least_queue_delay_s * delivered

    def _link_full(self, report, delivered):
        """A link-limited interval that delivered clearly less than the capacity believed, or one whose
        socket was full in most of its samples that delivered far below it (a step). Live beside busy
        loops (session 21): the first interval after a 60 -> 20 Mbit/s step whose report was not
        refused had its socket full in 80 % of its samples and delivered 19.4; waiting for a wholly
        full one took 3.4 s. Such an interval can read low by its empty part (a socket full 80 % of
        the time read 23 % low, live): the first train after the cut takes that back. Within
        max_drain_s of a step, after an interval with the socket full throughout that delivered
        STEP_FRACTION of the capacity or more, a mostly full one far below is no second step: its
        empty part is the sender's, short of a CPU. Live (test_over_link, 2026-12-01) after a
        60 -> 20 Mbit/s step's cuts to 19.1, two such intervals delivered 18.8 and 19.6, then one
        with its socket 60 % full delivered 12.2 (the next one 7.5 with its socket empty, not
        app-limited): cut to 12.6 for 2 s."""
        if bool(report.link_limited):
            return delivered < (1.0 - self.deficit_fraction) * self.capacity_mbps - self.deficit_min_mbps
        if not (bool(report.link_mostly_full) and delivered < STEP_FRACTION * self.capacity_mbps):
            return False
        full_since_step = self._full_since_step_mbps >= STEP_FRACTION * self.capacity_mbps
        return not (self._in_step_drain(report.now_s) and full_since_step)

    def _overuse(self, reason):
        self.congested = True
        self.last_overuse = reason
        self.overuse_reasons[reason] += 1

    def _on_overuse(self, now, delivered, sent, drain_factor=DRAIN_FACTOR):
        """GCC: the link is full, so what it delivered is its rate; cut the target to 0.85 x it
        (`drain_factor`) until the queue has drained."""
        self.overuses += 1
        measured = self._clip(delivered)
        self._bw_max_mbps = self._unrefuted_mbps = measured
        self._gain = PROBE_GAIN
        self._merged.clear()  # this deficit is acted upon; the next one must be new
        self._samples.clear()  # the link changed: samples from before the overuse are not its rate
        self._deficit_reports = 0
        self._small_full_reports = 0
        self._mark_step(now, up=False, by_train=False)
        self.capacity_mbps = measured
        self.estimate_mbps = self._clip(drain_factor * measured)
        self.mode, self._mode_since_s = "drain", now  # a new overuse restarts the drain
        self._drain_checked = False
        self._trend.reset()  # the rise is acted upon; the next overuse must be a new rise

    def _window(self, now, interval_s, delivered, sent):
        """(delivered, sent) over the last sample_window_s of reports, this one included."""
        if self.sample_window_s <= 0:
            return delivered, sent
        self._samples.append((now, interval_s, delivered, sent))
        while self._samples and self._samples[0][0] <= now - self.sample_window_s:
            self._samples.popleft()
        span = sum(i for _, i, _, _ in self._samples)
        known = [(i, s) for _, i, _, s in self._samples if not math.isnan(s)]
        return (
            sum(i * d for _, i, d, _ in self._samples) / span,
            sum(i * s for i, s in known) / sum(i for i, _ in known) if known else math.nan,
        )

    def _deficit(self, fraction=None, min_mbps=None):
        """Over the merged window, did the link deliver clearly less than was sent (a queue building)?
        Clearly: by more than `fraction` of what was sent and `min_mbps` (default: the estimator's)."""
        fraction = self.deficit_fraction if fraction is None else fraction
        min_mbps = self.deficit_min_mbps if min_mbps is None else min_mbps
        known = [(i, d, s) for _, i, d, s in self._merged if not math.isnan(s)]
        if not known:
            return False
        span = sum(i for i, _, _ in known)
        delivered = sum(i * d for i, d, _ in known) / span
        sent = sum(i * s for i, _, s in known) / span
        return sent - delivered > max(fraction * sent, min_mbps)

    def _rtt(self, now, rtt_samples, dt):
        """(GCC trendline says overuse, queueing delay s over the min-RTT floor, and that of the
        interval's smallest sample) from this interval (NaN delays without a sample)."""
        good = sorted(r for r in rtt_samples if isinstance(r, (int, float)) and math.isfinite(r) and 0 < r < 60)
        if len(good) < len(tuple(rtt_samples)):
            self.ignored["bad_rtt_sample"] += len(tuple(rtt_samples)) - len(good)
        if not good:
            return False, math.nan, math.nan
        rtt = good[len(good) // 2]  # median: a burst of late echoes is one interval's worth, not many
        self._rtt_samples.append((now, good[0], rtt))
        while self._rtt_samples and self._rtt_samples[0][0] < now - self.min_rtt_window_s:
            self._rtt_samples.popleft()
        # queueing delay against the floor of the interval medians, so jitter is not queueing
        floor = min(m for _, _, m in self._rtt_samples)
        queue_delay_s = max(0.0, rtt - floor)
        overuse = self._trend.update(now, 1000.0 * queue_delay_s, dt)
        # the smallest sample says the queue never emptied only if there are a few (a report
        # carries one per heartbeat: five in 0.5 s)
        least = max(0.0, good[0] - floor) if len(good) >= WHOLE_INTERVAL_RTT_SAMPLES else math.nan
        return overuse and queue_delay_s > self.queue_delay_threshold_s, queue_delay_s, least
