"""The bandwidth manager's state and decisions, without ROS: what the node feeds it and asks it.

It keeps per robot the measured message size and input rate (from the rate limiter's status),
the per-level sizes of every managed stream (cloud, and video for camera robots), the priority
book (mission state + operator), the operator's selected robot and the robots in teleop, the
twin's insertion capacity and the available bandwidth (configured, or the online estimate), and
turns them into a `LevelAllocation` (`allocate_streams`; `allocate` is its clouds, in the old
`Allocation` form). The node only wires topics to it.
"""

import collections
import dataclasses
import math
from typing import Dict, Optional

import numpy as np

from cps_bw_manager.allocation import (
    DEFAULT_ASSUMED_MESSAGE_BYTES,
    DEFAULT_FLOOR_RATE_HZ,
    DEFAULT_PRIORITY_WEIGHTS,
    Allocation,
    RobotAllocation,
    managed_budget_mbytes_per_s,
    water_fill,
)
from cps_bw_manager.estimation import DeliveryRateEstimator, LinkReport
from cps_bw_manager.level_allocation import (
    CLOUD,
    INSPECTION_DETAIL,
    OPERATOR_VIDEO,
    VIDEO,
    LevelAllocation,
    ResourceUse,
    StreamDemand,
    allocate_levels,
    cloud_detail_bits,
    video_detail_bits,
)
from cps_bw_manager.level_sizes import LevelSizes
from cps_bw_manager.priorities import PriorityBook

# An input rate is allowed this much headroom before it caps the robot's maximum rate.
INPUT_RATE_HEADROOM = 1.1
# A size change smaller than this fraction does not count as a change worth an immediate update.
SIZE_CHANGE_FRACTION = 0.1
# How long a robot keeps its input-rate cap while its limiter reports no input rate. A limiter
# measures over a 2 s window and needs two messages in it, so a sensor at 0.7 Hz reads 0 for runs
# of up to ~9 s (1 Hz: ~3 s); 10 s covers that. Longer silences fall back to max_rate_hz.
DEFAULT_INPUT_RATE_HOLD_S = 10.0
# The twin's insertion capacity counts this long after its last report (the map server publishes
# it every window; a silent map server no longer bounds the clouds).
INSERT_CAPACITY_HOLD_S = 10.0
TELEOP_MODE = "teleop"  # cps_sim's control modes: auto, teleop
# The unmanaged traffic kept out of the budget is its mean over this many seconds of link reports
# (odometry, tf and the rest come in bursts; the twin's link bytes less its managed frames is noisy
# per interval: the largest read up to 5 Mbit/s live on a link carrying 1-2 of it).
UNMANAGED_WINDOW_S = 2.0
# The robots' link socket was full in at least this fraction of its samples (or, without TCP_INFO,
# its sender waited for Zenoh this fraction of its interval): the link kept busy.
LINK_LIMITED_FRACTION = 0.5
# ... and in at least this fraction: the link was the limit over the whole interval, so what it
# delivered is the link's rate (a step). A socket full in 80 % of its samples read 23 % low live
# (15.45 Mbit/s on a 20 Mbit/s link): the interval's acked rate counts its empty part too.
LINK_FULL_STEP_FRACTION = 0.95
# A link report whose interval is outside this is not taken for the unmanaged traffic, s.
REPORT_INTERVAL_BOUNDS_S = (0.05, 5.0)

# Compute is a resource (issue 36). A stream that delivers less than (1 - COMPUTE_SHORTFALL) of the
# rate set on it, over COMPUTE_WINDOW_S in which the link never bound, is compute-bound (its
# producer, not the link, limits it: BBR's app-limited): no level finer than its own is bought for
# it until it has delivered its rate again for COMPUTE_CLEAR_S. The window is long because a cloud
# at ~1 Hz gives its limiter two or three messages per 2 s window.
COMPUTE_WINDOW_S = 10.0
COMPUTE_SHORTFALL = 0.2
COMPUTE_CLEAR_S = 30.0
# A host's idle CPU: the least its flowing encoders reported over the last HOST_WINDOW_S (BBR's
# windowed filters; a host is bought for only if it stayed idle that long, so a transient, e.g.
# the simulator not yet at full speed, buys nothing), and stale without a report for HOST_STALE_S.
HOST_WINDOW_S = 10.0
HOST_STALE_S = 10.0
# After the allocation buys on a host, what it bought is held for HOST_SETTLE_S, and only idle
# measured after that counts: the new work must show in the host's idle share first.
HOST_SETTLE_S = 3.0
# An encoder that forwarded this many messages without naming their level knows no levels.
LEVELLESS_AFTER = 3
# While the estimator cruises, the robots' bridge paces at this x its estimate, so that a fleet
# that fills the link waits in the bridge's own queue (priority first, newest only) and not in the
# kernel's: the capacity comes from the trains' fastest spans, a few per cent above the payload
# rate the link acknowledges (live, link_thesis at 5 Mbit/s: 4.6-4.7 against 4.50-4.59 acked
# with the robots' socket full), and paced at it the kernel's 64 kB unsent bound stayed full,
# ~110 ms of queue in front of the operator's video (its p50 ~150 ms for 6 s). BBR's pacing drains
# the queue its probes leave (gain 0.75 one phase in 8); here the margin is constant. A probe
# (x 1.2) and a drain keep their own gains.
CRUISE_PACING_GAIN = 0.9
# Resource names of the allocator's rows beside the link.
TWIN_POINTS = "twin points"


def cpu_resource(host):
    """The allocator's name of a robots' host's CPU (cores)."""
    return f"cpu {host}"


@dataclasses.dataclass(frozen=True)
class ManagerSettings:
    available_mbps: float
    reserve_fraction: float
    min_rate_hz: float
    max_rate_hz: float
    high_priority_weight: float = DEFAULT_PRIORITY_WEIGHTS[1]
    floor_rate_hz: float = DEFAULT_FLOOR_RATE_HZ
    assumed_message_bytes: float = DEFAULT_ASSUMED_MESSAGE_BYTES
    # Eq. 1 holds on average; for it to hold in every `window_s` window the budget keeps room for
    # `headroom_messages` extra messages per robot per window (rate limiters release whole messages).
    window_s: float = 1.0
    headroom_messages: float = 1.0
    # TCPROS sends one copy of a message per subscriber: every digital-twin node subscribed to a
    # managed topic (the Draco decoder, a stats monitor, ...) is one more copy on the link.
    copies_on_link: int = 1
    # A status without an input rate (0 or NaN: fewer than two messages in the limiter's window)
    # keeps the robot's last input-rate cap this long before it falls back to max_rate_hz.
    input_rate_hold_s: float = DEFAULT_INPUT_RATE_HOLD_S
    # A finished robot's bandwidth weight (issue 36: it keeps the rate its stream sustains while the
    # link has room, and yields first when it binds); the paper pins it at min_rate_hz: pin_done.
    done_weight: float = 0.25
    pin_done: bool = False
    # The share of each robots' host's cores kept idle (control loops, teleop, the bridges): the
    # allocation adds CPU work on a host only within its idle share above this.
    cpu_idle_reserve: float = 0.15
    # A level finer than the one in force must fit the link with this fraction of its cost to spare.
    upgrade_margin: float = 0.1

    def validate(self):
        """ValueError naming the parameter that is wrong."""
        managed_budget_mbytes_per_s(self.available_mbps, self.reserve_fraction)
        if (
            isinstance(self.copies_on_link, bool)
            or not isinstance(self.copies_on_link, int)
            or not 1 <= self.copies_on_link <= 100
        ):
            raise ValueError(f"copies_on_link must be an integer in [1, 100], got {self.copies_on_link!r}")
        if not isinstance(self.headroom_messages, (int, float)) or not 0 <= self.headroom_messages <= 10:
            raise ValueError(f"headroom_messages must be in [0, 10], got {self.headroom_messages!r}")
        if (
            not _finite(self.input_rate_hold_s)
            or isinstance(self.input_rate_hold_s, bool)
            or not 0 <= self.input_rate_hold_s <= 3600
        ):
            raise ValueError(f"input_rate_hold_s must be in [0, 3600] s, got {self.input_rate_hold_s!r}")
        for name in ("cpu_idle_reserve", "upgrade_margin"):
            value = getattr(self, name)
            if isinstance(value, bool) or not _finite(value) or not 0 <= value <= 1:
                raise ValueError(f"{name} must be in [0, 1], got {value!r}")
        if not isinstance(self.pin_done, bool):
            raise ValueError(f"pin_done must be true or false, got {self.pin_done!r}")
        for name in (
            "done_weight",
            "min_rate_hz",
            "max_rate_hz",
            "high_priority_weight",
            "floor_rate_hz",
            "assumed_message_bytes",
            "window_s",
        ):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if self.min_rate_hz > self.max_rate_hz:
            raise ValueError(f"min_rate_hz ({self.min_rate_hz}) > max_rate_hz ({self.max_rate_hz})")
        return self


@dataclasses.dataclass(frozen=True)
class LinkHealth:
    """The last cps_msgs/LinkState heard (up until one says otherwise)."""

    up: bool = True
    since_s: float = math.nan
    outages: int = 0
    last_outage_s: float = 0.0
    peer: str = ""


@dataclasses.dataclass(frozen=True)
class EncoderReport:
    """What a stream's encoder says beside its sizes (cps_msgs/RateLimiterStatus, issue 36)."""

    set_rate_hz: float = math.nan  # the rate in force on the robots' side (0: a video turned off)
    forwarded: Optional[int] = None  # messages sent so far (a counter)
    level_mean_cpu_s: float = math.nan  # CPU seconds per message at the level reported
    level_mean_points: float = math.nan  # points per message at that level (clouds)
    host: str = ""  # the computer and CPUs the encoder runs on
    host_cpus: float = math.nan  # cores of that host
    host_idle_fraction: float = math.nan  # their idle share over the status's window

    def validate(self, who):
        """ValueError naming the field that is not a value (NaN, 0 and "" mean: not reported)."""
        for name in ("set_rate_hz", "level_mean_cpu_s", "level_mean_points", "host_cpus"):
            value = getattr(self, name)
            if not (math.isnan(value) or (_finite(value) and value >= 0)):
                raise ValueError(f"{who}: {name} {value!r} is not NaN or finite and >= 0")
        if not (math.isnan(self.host_idle_fraction) or 0.0 <= self.host_idle_fraction <= 1.0):
            raise ValueError(f"{who}: host_idle_fraction {self.host_idle_fraction!r} outside [0, 1]")
        if self.forwarded is not None and (isinstance(self.forwarded, bool) or int(self.forwarded) < 0):
            raise ValueError(f"{who}: forwarded {self.forwarded!r} is not a count")


@dataclasses.dataclass
class _StreamState:
    """What the manager knows of one stream from its encoder (issue 36)."""

    cpu_s: LevelSizes  # CPU seconds per message per level, learned like the sizes
    points: Optional[LevelSizes]  # points per message per level (clouds)
    reported: bool = False  # an encoder status arrived
    level: Optional[int] = None  # the level its encoder runs at (None: it does not say)
    level_since_s: float = -math.inf
    set_rate_hz: float = math.nan
    host: str = ""
    # (time, forwarded counter, rate set) of its statuses, for the compute-bound judgement
    history: collections.deque = dataclasses.field(default_factory=collections.deque)
    compute_bound: bool = False
    delivering_since_s: float = math.nan
    forwarded: int = 0  # the encoder's counter
    # What the encoder runs when nobody tells it: the level and rate of its first report (its
    # configured level; the camera's default). Taking no more than that needs no spare CPU.
    baseline_level: Optional[int] = None
    baseline_rate_hz: float = math.nan


@dataclasses.dataclass
class _Measured:
    message_bytes: float = math.nan
    # The last input rate > 0 and when it was reported; NaN: never measured, or held too long.
    input_rate_hz: float = math.nan
    input_rate_at_s: float = math.nan
    output_rate_hz: float = math.nan


class ManagerCore:
    """`streams`: fleet.yaml's StreamsConfig (the levels; None: one cloud level of unknown detail
    and no video, the allocation before issue 24); `camera_robots`: the robots with a video."""

    def __init__(
        self,
        robots,
        settings: ManagerSettings,
        estimator: Optional[DeliveryRateEstimator] = None,
        streams=None,
        camera_robots=(),
    ):
        self.settings = settings.validate()
        self.robots = list(robots)
        if not self.robots:
            raise ValueError("no robots to manage")
        self.book = PriorityBook(self.robots, pin_done=settings.pin_done)
        self.estimator = estimator
        self.measured: Dict[str, _Measured] = {r: _Measured() for r in self.robots}
        self.invalid_inputs = 0
        self.weights = {0: DEFAULT_PRIORITY_WEIGHTS[0], 1: float(settings.high_priority_weight)}
        self.link = LinkHealth()
        self._last_stats_s = math.nan
        self.streams = streams
        if streams is None:
            self.cloud_levels = (("managed",), (0.0,), (settings.assumed_message_bytes,))
            self.video_levels = None
            self.camera_robots = []
        else:
            self.cloud_levels = (
                tuple(lvl.name for lvl in streams.cloud_levels),
                cloud_detail_bits([lvl.voxel_leaf_m for lvl in streams.cloud_levels]),
                tuple(lvl.bytes_prior for lvl in streams.cloud_levels),
            )
            self.video_levels = (
                tuple(lvl.name for lvl in streams.video_levels),
                video_detail_bits([lvl.width * lvl.height for lvl in streams.video_levels]),
                tuple(lvl.bytes_prior for lvl in streams.video_levels),
            )
            self.camera_robots = [r for r in self.robots if r in set(camera_robots)]
        self.sizes: Dict[tuple, LevelSizes] = {(r, CLOUD): LevelSizes(self.cloud_levels[2]) for r in self.robots}
        self.video_measured: Dict[str, _Measured] = {}
        for r in self.camera_robots:
            self.sizes[(r, VIDEO)] = LevelSizes(self.video_levels[2])
            self.video_measured[r] = _Measured()
        # The level each stream was last allocated (what its encoder produces once it follows).
        self.level_in_force = {key: sizes.levels - 1 for key, sizes in self.sizes.items()}
        # Issue 36: each stream's CPU and points per level, level and rate in force, host, and
        # whether it is compute-bound; each robots' host's idle cores (idle, cores, at s).
        self.state: Dict[tuple, _StreamState] = {
            key: _StreamState(
                cpu_s=LevelSizes(sizes.priors), points=LevelSizes(sizes.priors) if key[1] == CLOUD else None
            )
            for key, sizes in self.sizes.items()
        }
        self.hosts: Dict[str, tuple] = {}  # host -> (cores, last report s)
        self._idle: Dict[str, collections.deque] = {}  # host -> (s, idle cores) of its flowing encoders
        self._settling: Dict[str, tuple] = {}  # host -> (until s, what was bought above the baselines)
        self._points_capacity = (math.nan, -math.inf)  # (points/s, reported at s)
        self._link_bound_s = -math.inf  # the last allocation in which the link's budget bound
        self.selected_robot = ""
        self.teleop = set()
        self._capacity = (math.nan, -math.inf)  # (clouds/s, reported at s)
        # The link capacity announced by who knows it (Mbit/s, NaN: none) and who; it replaces
        # settings.available_mbps as the budget's basis (set_capacity_mbps).
        self.announced_mbps = math.nan
        self.announced_source = ""
        self._now_s = -math.inf
        self.last_demands: Dict[tuple, StreamDemand] = {}
        self.last_allocation: Optional[LevelAllocation] = None
        # the robots' bridge reports the link (on_bridge_report), so it paces at pacing_mbps
        self.bridge_paces = False
        # (report s, Mbit/s) of traffic outside the managed streams, from the bridge's link reports
        self._unmanaged = []
        # what the robots' bridge's probe trains cost the link now (its last link report), Mbit/s
        self._probe_cost_mbps = 0.0
        self.last_spare: Dict[str, float] = {}
        # The rate the last allocation gave each stream (before any limiter slack): what a stream
        # must deliver not to be judged compute-bound.
        self.allocated_rate_hz: Dict[tuple, float] = {}

    @property
    def paused(self):
        """True while the link is down: no new allocation (the limiters keep their rates)."""
        return not self.link.up

    def on_link_state(self, up, since_s, outages=0, last_outage_s=0.0, peer=""):
        """/tissue/link_state as plain values; returns True when the link changed state. While it
        is down the estimator is not fed (an outage says nothing about the capacity); when it
        comes back the estimator resumes from the estimate it had."""
        changed = bool(up) != self.link.up
        self.link = LinkHealth(bool(up), float(since_s), int(outages), float(last_outage_s), str(peer))
        if changed and up and self.estimator:
            self.estimator.resume(since_s)
        return changed

    def pause_status(self, now_s):
        """Why the allocation is paused ("" when it is not)."""
        if not self.paused:
            return ""
        peer = f" to {self.link.peer}" if self.link.peer else ""
        return (
            f"paused: link{peer} down for {max(0.0, now_s - self.link.since_s):.1f} s; rates held, "
            f"resuming from {self.available_mbps:.1f} Mbit/s when it is back"
        )

    @property
    def available_mbps(self):
        """The capacity the budget is made from: the estimate (if on; the capacity while a queue
        drains, where the robots' bridge paces), else the announced capacity, else the configured
        one."""
        if self.estimator:
            # a drain is the robots' bridge's pacer's where it reports the link (and so paces at
            # pacing_mbps); without it (over TCPROS) only the fleet's rates can drain a queue
            return self.estimator.allocation_mbps if self.bridge_paces else self.estimator.estimate_mbps
        return self.announced_mbps if _positive(self.announced_mbps) else self.settings.available_mbps

    @property
    def probing(self):
        """True while the link's estimator probes above its capacity (its raises must reach the fleet)."""
        return bool(self.estimator) and self.estimator.mode == "probe"

    @property
    def pacing_mbps(self):
        """The rate the robots' bridge paces what it sends at: the estimate (below the capacity
        while a queue drains, above it while probing; CRUISE_PACING_GAIN x it while cruising), else
        available_mbps."""
        if not self.estimator:
            return self.available_mbps
        gain = CRUISE_PACING_GAIN if self.estimator.mode == "cruise" else 1.0
        return gain * self.estimator.estimate_mbps

    @property
    def capacity_source(self):
        """Where available_mbps comes from, in words."""
        announced = f"announced by {self.announced_source or 'an unnamed source'}"
        if self.estimator:
            return "estimated online" + (
                f", at most the capacity {announced}" if _positive(self.announced_mbps) else ""
            )
        return announced if _positive(self.announced_mbps) else "configured"

    def set_capacity_mbps(self, capacity_mbps, source="", now_s=None):
        """The link's capacity announced by who knows it (cps_msgs/LinkCapacity): from the next
        allocation the budget is made from it (reserve and headroom as before) instead of the
        configured capacity. With the estimator on it becomes the estimator's ceiling and new prior
        (DeliveryRateEstimator.announce). NaN, infinite or <= 0 is refused (ValueError, counted)
        and the last good one kept: a capacity of 0 is an outage, /tissue/link_state's to report.
        Returns True if the capacity changed."""
        try:
            value = float(capacity_mbps)
        except (TypeError, ValueError):
            value = math.nan
        if isinstance(capacity_mbps, bool) or not _positive(value):
            self.invalid_inputs += 1
            kept = f"{self.announced_mbps:g} Mbit/s announced" if _positive(self.announced_mbps) else "the configured"
            raise ValueError(
                f"announced link capacity {capacity_mbps!r} Mbit/s from {source or 'an unnamed source'} is not a "
                f"capacity (finite and > 0); keeping {kept} capacity"
            )
        changed = value != self.announced_mbps
        self.announced_mbps, self.announced_source = value, str(source)
        if self.estimator and changed:
            self.estimator.announce(value, now_s)
        return changed

    def on_limiter_status(
        self,
        robot,
        mean_message_bytes,
        input_rate_hz,
        output_rate_hz=math.nan,
        *,
        now_s,
        level=None,
        level_mean_message_bytes=math.nan,
        encoder: Optional[EncoderReport] = None,
    ):
        """A rate limiter's status received at `now_s` (s, any monotonic clock); returns True if the
        size (of any level) changed enough to re-allocate now. `level`, `level_mean_message_bytes`:
        the level the clouds were produced at and their size (RateLimiterStatus); without them the
        mean size counts as the size of the level in force. `encoder`: the rest of the status
        (rate set, counter, CPU and points per message, host; issue 36).

        Raises KeyError for an unknown robot. A size of 0 or NaN (nothing received yet) keeps the
        old size; a negative or infinite size is counted and refused (ValueError). An input rate
        > 0 replaces the robot's input-rate cap at once; 0 or NaN (fewer than two messages in the
        limiter's window) keeps the last one for `input_rate_hold_s` after it was reported, then
        drops it (the robot may use max_rate_hz again, as a robot never measured does).
        """
        entry = self.measured[self._known(robot)]
        if not _finite(now_s):
            self.invalid_inputs += 1
            raise ValueError(f"robot '{robot}': status time {now_s!r} is not a time")
        self._check_encoder((robot, CLOUD), encoder)
        entry.output_rate_hz = float(output_rate_hz) if _finite(output_rate_hz) and output_rate_hz >= 0 else math.nan
        if not _positive(mean_message_bytes) and not (mean_message_bytes == 0 or math.isnan(mean_message_bytes)):
            self.invalid_inputs += 1
            raise ValueError(f"robot '{robot}': mean_message_bytes {mean_message_bytes!r} is not a size")
        if _positive(input_rate_hz):
            entry.input_rate_hz, entry.input_rate_at_s = float(input_rate_hz), float(now_s)
        elif not 0.0 <= now_s - entry.input_rate_at_s <= self.settings.input_rate_hold_s:
            entry.input_rate_hz = entry.input_rate_at_s = math.nan  # held too long (or the clock went back)
        self._now_s = max(self._now_s, float(now_s))
        level_changed = self._learn((robot, CLOUD), level, level_mean_message_bytes, mean_message_bytes, now_s)
        self._take_encoder((robot, CLOUD), level if _positive(level_mean_message_bytes) else None, encoder, now_s)
        if not _positive(mean_message_bytes):
            return level_changed
        old = entry.message_bytes
        entry.message_bytes = float(mean_message_bytes)
        return level_changed or not _positive(old) or abs(mean_message_bytes - old) > SIZE_CHANGE_FRACTION * old

    def _learn(self, key, level, level_mean_bytes, mean_bytes, now_s):
        """Feed the stream's level sizes: the level's own mean if the encoder gave one, else the
        overall mean as the size of the level in force (an encoder that knows no levels)."""
        sizes = self.sizes[key]
        if _positive(level_mean_bytes) and level is not None:
            if isinstance(level, bool) or not isinstance(level, int) or not 0 <= level < sizes.levels:
                self.invalid_inputs += 1
                raise ValueError(f"{key[0]}/{key[1]}: level {level!r} outside the {sizes.levels} levels")
            return sizes.report(level, float(level_mean_bytes), float(now_s))
        if _positive(mean_bytes):
            return sizes.report(self.level_in_force[key], float(mean_bytes), float(now_s))
        return False

    def on_video_status(
        self,
        robot,
        level,
        level_mean_message_bytes,
        mean_message_bytes=math.nan,
        output_rate_hz=math.nan,
        *,
        now_s,
        encoder: Optional[EncoderReport] = None,
    ):
        """A camera robot's video status (cps_msgs/RateLimiterStatus from its video pipeline);
        returns True if a level's size moved enough to re-allocate now. KeyError for a robot
        without managed video, ValueError (counted) for a bad level, size, time or `encoder` field."""
        if robot not in self.video_measured:
            raise KeyError(f"robot '{robot}' has no managed video (camera robots: {', '.join(self.camera_robots)})")
        if not _finite(now_s):
            self.invalid_inputs += 1
            raise ValueError(f"robot '{robot}': status time {now_s!r} is not a time")
        self._check_encoder((robot, VIDEO), encoder)
        for value in (level_mean_message_bytes, mean_message_bytes):
            if not _positive(value) and not (value == 0 or math.isnan(value)):
                self.invalid_inputs += 1
                raise ValueError(f"robot '{robot}': video size {value!r} is not a size")
        self._now_s = max(self._now_s, float(now_s))
        entry = self.video_measured[robot]
        entry.output_rate_hz = float(output_rate_hz) if _finite(output_rate_hz) and output_rate_hz >= 0 else math.nan
        if _positive(mean_message_bytes):
            entry.message_bytes = float(mean_message_bytes)
        changed = self._learn((robot, VIDEO), level, level_mean_message_bytes, mean_message_bytes, now_s)
        self._take_encoder((robot, VIDEO), level, encoder, now_s)
        return changed

    def _check_encoder(self, key, encoder):
        if encoder is None:
            return
        try:
            encoder.validate(f"{key[0]}/{key[1]}")
        except ValueError:
            self.invalid_inputs += 1
            raise

    def _take_encoder(self, key, level, encoder, now_s):
        """The encoder's level, rate set, costs and host (issue 36); judges compute-boundness."""
        st = self.state[key]
        st.reported = True
        if level is not None and 0 <= level < self.sizes[key].levels:
            if st.level != level:
                st.level, st.level_since_s = int(level), float(now_s)
            if st.baseline_level is None:
                st.baseline_level = int(level)
        if encoder is None:
            return
        if _finite(encoder.set_rate_hz):
            st.set_rate_hz = float(encoder.set_rate_hz)
            if math.isnan(st.baseline_rate_hz):
                st.baseline_rate_hz = st.set_rate_hz
        if st.level is not None:
            if _positive(encoder.level_mean_cpu_s):
                st.cpu_s.report(st.level, float(encoder.level_mean_cpu_s), float(now_s))
            if st.points is not None and _positive(encoder.level_mean_points):
                st.points.report(st.level, float(encoder.level_mean_points), float(now_s))
        if encoder.forwarded is not None:
            st.forwarded = int(encoder.forwarded)
        if encoder.host:
            st.host = encoder.host
            if _positive(encoder.host_cpus) and _finite(encoder.host_idle_fraction):
                cpus = float(encoder.host_cpus)
                self.hosts[encoder.host] = (cpus, float(now_s))
                if st.forwarded > 0:  # the host's idle share while its streams flow
                    idle = self._idle.setdefault(encoder.host, collections.deque())
                    if idle and now_s < idle[-1][0]:
                        idle.clear()
                    idle.append((float(now_s), encoder.host_idle_fraction * cpus))
                    while idle and idle[0][0] < now_s - HOST_WINDOW_S - HOST_STALE_S:
                        idle.popleft()
        if encoder.forwarded is not None:
            # A cloud's rate is set from its input rate (+10 %) once that is known; before, at the
            # maximum, which a sensor slower than it would "fail" to deliver.
            known = key[1] != CLOUD or _positive(self.measured[key[0]].input_rate_hz)
            allocated = self.allocated_rate_hz.get(key, math.nan)
            if _finite(encoder.set_rate_hz) and known and _finite(allocated):
                # the rate it was allowed: the allocation's (a cloud's limiter may be set above it
                # on an idle link: limiter_rates), or less while the setpoint filter holds it
                rate = min(float(encoder.set_rate_hz), allocated)
                self._judge_compute(st, st.forwarded, rate, float(now_s))
            elif not known:
                st.history.clear()

    def _judge_compute(self, st, forwarded, set_rate_hz, now_s):
        """Compute-bound: over the last COMPUTE_WINDOW_S, in which the link never bound (nor went
        down), the stream delivered less than (1 - COMPUTE_SHORTFALL) of the mean rate set on it."""
        history = st.history
        if history and (forwarded < history[-1][1] or now_s < history[-1][0]):
            history.clear()  # the encoder restarted, or the clock went back: start again
        history.append((now_s, forwarded, set_rate_hz))
        while len(history) > 2 and history[1][0] <= now_s - COMPUTE_WINDOW_S:
            history.popleft()
        start_s, start_count, _ = history[0]
        if now_s - start_s < COMPUTE_WINDOW_S or self._link_bound_s >= start_s or self.paused:
            return
        allocated = sum(rate for _, _, rate in history) / len(history)
        if allocated <= 0:
            return
        delivered = (forwarded - start_count) / (now_s - start_s)
        if delivered < (1.0 - COMPUTE_SHORTFALL) * allocated:
            st.compute_bound, st.delivering_since_s = True, math.nan
        elif st.compute_bound:
            if math.isnan(st.delivering_since_s):
                st.delivering_since_s = now_s
            elif now_s - st.delivering_since_s >= COMPUTE_CLEAR_S:
                st.compute_bound, st.delivering_since_s = False, math.nan

    def cpu_spare_by_stream(self):
        """{(robot, stream): the spare cores of its host in the last allocation} (where known)."""
        spare = self.last_spare
        return {
            key: spare[cpu_resource(st.host)]
            for key, st in self.state.items()
            if st.host and cpu_resource(st.host) in spare
        }

    def compute_bound_streams(self):
        """The (robot, stream) keys judged compute-bound now."""
        return tuple(key for key, st in self.state.items() if st.compute_bound)

    def compute_bound(self, robot, stream):
        """True while the stream is judged compute-bound (no finer level is bought for it)."""
        return self.state[(robot, stream)].compute_bound

    def encoder_level(self, robot, stream) -> Optional[int]:
        """The level the stream's encoder last said it runs at (None: it has not said, or has none)."""
        return self.state[(robot, stream)].level

    def reported(self, robot, stream):
        """True once the stream's encoder has said what it runs: its level, and what that costs if
        it reports its host's CPU; or it forwarded LEVELLESS_AFTER messages without naming a level
        (an encoder that knows no levels, e.g. a plain rate_limiter). Before that no setpoint is
        sent: it runs at its own configured level and initial rate, and the manager, not knowing
        what a finer level would cost, would buy the finest everywhere at start."""
        st = self.state[(robot, stream)]
        if not st.reported:
            return False
        if st.level is None:
            return st.forwarded >= LEVELLESS_AFTER
        return not st.host or st.cpu_s.reference_level is not None

    def on_selected_robot(self, robot):
        """The operator's selected robot ("" for none; a robot not managed here selects none of
        ours). Returns True if the allocation's rules changed."""
        robot = str(robot).strip()
        before = self._operators()
        self.selected_robot = robot
        return self._operators() != before

    def on_control_mode(self, robot, mode):
        """A robot's control mode in force (velocity_mux's control_mode/active). Returns True if
        the allocation's rules changed. KeyError for an unknown robot."""
        self._known(robot)
        before = self._operators()
        if str(mode).strip() == TELEOP_MODE:
            self.teleop.add(robot)
        else:
            self.teleop.discard(robot)
        return self._operators() != before

    def _operators(self):
        """The camera robots whose video gets operator quality: the selected one and every teleoperated one."""
        return {r for r in self.camera_robots if r == self.selected_robot or r in self.teleop}

    def on_insert_capacity(self, clouds_per_s, now_s, points_per_s=math.nan):
        """The map server's insertion capacity (cps_msgs/InsertCapacity.clouds_per_s, and
        points_per_s: the finer levels' points are bought within it, issue 36). 0 or NaN (nothing
        measured in its window) clears it; negative or infinite is refused (ValueError, counted).
        Returns True if the clouds/s bound moved by more than 10 % (or appeared, or went)."""
        if not _finite(now_s):
            self.invalid_inputs += 1
            raise ValueError(f"insert capacity time {now_s!r} is not a time")
        for value, unit in ((clouds_per_s, "clouds/s"), (points_per_s, "points/s")):
            if not (_positive(value) or value == 0 or math.isnan(value)):
                self.invalid_inputs += 1
                raise ValueError(f"insert capacity {value!r} {unit} is not a capacity")
        self._points_capacity = (float(points_per_s) if _positive(points_per_s) else math.nan, float(now_s))
        before = self.insert_capacity_clouds_per_s(now_s)
        self._capacity = (float(clouds_per_s) if _positive(clouds_per_s) else math.nan, float(now_s))
        self._now_s = max(self._now_s, float(now_s))
        after = self.insert_capacity_clouds_per_s(now_s)
        if (before is None) != (after is None):
            return True
        return before is not None and abs(after - before) > SIZE_CHANGE_FRACTION * before

    def insert_capacity_clouds_per_s(self, now_s=None):
        """The twin's insertion capacity in force (None: none reported in the last INSERT_CAPACITY_HOLD_S)."""
        return self._capacity_in_force(self._capacity, now_s)

    def insert_capacity_points_per_s(self, now_s=None):
        """The twin's insertion capacity in points/s in force (None: none reported lately)."""
        return self._capacity_in_force(self._points_capacity, now_s)

    def _capacity_in_force(self, reported, now_s):
        now_s = self._now_s if now_s is None else now_s
        value, at_s = reported
        if not _positive(value) or not 0.0 <= now_s - at_s <= INSERT_CAPACITY_HOLD_S:
            return None
        return value

    def spare(self, now_s=None):
        """Per resource beside the link, how much of it the allocation may take above the streams'
        baselines (issue 36). A robots' host: what its streams take above their baselines now,
        plus its idle cores above `cpu_idle_reserve` (the least over HOST_WINDOW_S of flowing
        streams), or minus the shortfall when that least is below half the reserve (the host is
        short: the extra detail is shed); between the two, what they take now (hysteresis). Held
        at what was bought for HOST_SETTLE_S after a purchase; what is taken now, for a host an
        encoder names whose idle share is not known over a whole window. The twin's points: its
        insertion capacity minus the clouds' baselines (absent until the map server reports it)."""
        now_s = self._now_s if now_s is None else now_s
        out = {}
        reserve = self.settings.cpu_idle_reserve
        named = {st.host for st in self.state.values() if st.host}
        for host in named:
            resource = cpu_resource(host)
            taken = sum(self._above_baseline(key, resource, now_s) for key, st in self.state.items() if st.host == host)
            until_s, bought = self._settling.get(host, (-math.inf, 0.0))
            if now_s < until_s:
                out[resource] = max(bought, taken)
                continue
            cores, at_s = self.hosts.get(host, (math.nan, -math.inf))
            window = [idle for t, idle in self._idle.get(host, ()) if t >= max(until_s, now_s - HOST_WINDOW_S)]
            samples = [t for t, _ in self._idle.get(host, ()) if t >= until_s]
            whole = samples and now_s - samples[0] >= HOST_WINDOW_S and 0.0 <= now_s - at_s <= HOST_STALE_S
            if not whole or not window:
                out[resource] = taken
                continue
            least = min(window)
            if least >= reserve * cores:
                out[resource] = taken + least - reserve * cores
            elif least < 0.5 * reserve * cores:
                out[resource] = max(0.0, taken - (0.5 * reserve * cores - least))
            else:
                out[resource] = taken
        capacity = self.insert_capacity_points_per_s(now_s)
        if capacity is not None:
            baselines = 0.0
            for robot in self.robots:
                use = next((u for u in self._uses((robot, CLOUD), now_s) if u.resource == TWIN_POINTS), None)
                baselines += use.baseline_per_s if use else 0.0
            out[TWIN_POINTS] = max(0.0, capacity - baselines)
        return out

    def _above_baseline(self, key, resource, now_s):
        """What the stream takes of `resource` above its baseline now (at its level and rate in force)."""
        st = self.state[key]
        use = next((u for u in self._uses(key, now_s) if u.resource == resource), None)
        if use is None or st.level is None:
            return 0.0
        rate = st.set_rate_hz if math.isnan(use.produced_hz) else use.produced_hz
        return use.increase(st.level, rate) if _finite(rate) else 0.0

    def _uses(self, key, now_s):
        """What the stream takes of the resources beside the link (ResourceUse), where known."""
        st = self.state[key]
        if st.level is None or st.baseline_level is None:
            return ()
        base = st.baseline_level
        uses = []
        if st.host and st.cpu_s.reference_level is not None:
            per = st.cpu_s.estimate(now_s)
            if key[1] == CLOUD:  # encoded at the sensor's rate, before its limiter
                produced = self.measured[key[0]].input_rate_hz
                if _positive(produced):
                    uses.append(ResourceUse(cpu_resource(st.host), per, per[base] * produced, produced))
            elif _finite(st.baseline_rate_hz):  # rendered and encoded at the rate set only
                uses.append(ResourceUse(cpu_resource(st.host), per, per[base] * st.baseline_rate_hz))
        if st.points is not None and st.points.reference_level is not None:
            # at most what the sensor produces reaches the twin (the limiter's rate is set above it
            # while the link has room, and only then are finer levels bought)
            per = st.points.estimate(now_s)
            produced = self.measured[key[0]].input_rate_hz
            if _positive(produced):
                uses.append(ResourceUse(TWIN_POINTS, per, per[base] * produced, produced))
        return tuple(uses)

    def _finest_level(self, key, now_s, uses=()):
        """No level finer than the one in force while the stream is compute-bound, or while what
        it costs its host cannot be priced (its encoder names a host but its cost, or a cloud's
        input rate, is not known yet)."""
        st = self.state[key]
        if st.level is None:
            return 0
        unpriced = st.host and not any(u.resource == cpu_resource(st.host) for u in uses)
        return st.level if st.compute_bound or unpriced else 0

    def on_mission_state(self, robot, state):
        return self.book.set_mission_state(self._known(robot), state)

    def set_priority(self, robot, priority):
        """(success, message) for the operator's request; never raises."""
        try:
            changed = self.book.set_operator_priority(robot, priority)
        except (KeyError, ValueError) as exc:
            self.invalid_inputs += 1
            return False, str(exc).strip("'\"")
        return True, (
            f"{robot}: priority {priority} until its mission state changes" + ("" if changed else " (unchanged)")
        )

    def sent_mbps(self):
        """What the rate limiters forward onto the link, Mbit/s (NaN until every one reported)."""
        total = 0.0
        for m in self.measured.values():
            if not (_finite(m.output_rate_hz) and _positive(m.message_bytes)):
                return math.nan
            total += m.output_rate_hz * m.message_bytes * 8e-6
        for m in self.video_measured.values():  # a video not reporting yet sends nothing we know of
            if _finite(m.output_rate_hz) and _positive(m.message_bytes):
                total += m.output_rate_hz * m.message_bytes * 8e-6
        return total

    def offered_mbps(self):
        """What the fleet produces before the rate limiters (their input rates x sizes), Mbit/s
        (NaN until every one reported both): the demand the estimator probes for."""
        total = 0.0
        for m in self.measured.values():
            if not (_positive(m.input_rate_hz) and _positive(m.message_bytes)):
                return math.nan
            total += m.input_rate_hz * m.message_bytes * 8e-6
        return total

    def on_link_report(self, report: LinkReport):
        """Feed the estimator (if on) one full link report (the bridge's telemetry; see
        docs/bandwidth_manager.md); returns True if the available bandwidth or the pacing rate
        moved by > 5 %.
        Not fed while the link is down: an outage says nothing about the capacity."""
        if not self.estimator or self.paused:
            return False
        before = (self.available_mbps, self.pacing_mbps)
        self.estimator.update(report)
        after = (self.available_mbps, self.pacing_mbps)
        return any(abs(a - b) > 0.05 * b for a, b in zip(after, before))

    def allocation_binds(self):
        """True when the last allocation held some stream below what it wants (a rate under its
        maximum, a coarser level than its finest, or off): the fleet would send more if allowed,
        so it is not app-limited whatever the bridge's queue says (False before any allocation)."""
        a = self.last_allocation
        return a is not None and any(s.rate_hz < 0.98 * s.max_rate_hz or s.level > 0 for s in a.streams)

    def unmanaged_mbps(self, now_s=None):
        """The traffic outside the managed streams the link carried lately (its mean over the last
        UNMANAGED_WINDOW_S of link reports), Mbit/s; NaN before the first report."""
        now_s = self._now_s if now_s is None else now_s
        recent = [(mbps, i) for t, mbps, i in self._unmanaged if t > now_s - UNMANAGED_WINDOW_S]
        return sum(m * i for m, i in recent) / sum(i for _, i in recent) if recent else math.nan

    def probe_mbps(self):
        """What the robots' bridge's probe trains cost the link on average now, Mbit/s (its last link
        report: their bytes over their period at the capacity it was told; 0 without trains)."""
        return self._probe_cost_mbps

    def budget_mbytes_per_s(self, now_s=None):
        """The managed streams' budget: the capacity less the reserve, and less the unmanaged
        traffic measured on the link where that is more than the reserve (issue 35: at 5 Mbit/s
        odometry, tf and the rest took 18 % of the link, the reserve 4 %)."""
        s = self.settings
        available = self.available_mbps
        budget = managed_budget_mbytes_per_s(available, s.reserve_fraction)
        unmanaged = self.unmanaged_mbps(now_s)
        if _finite(unmanaged):
            outside = unmanaged + self.probe_mbps()
            budget = min(budget, max(0.0, (available - outside) / 8.0))
        return budget

    def on_bridge_report(
        self,
        now_s,
        interval_s,
        sender_interval_s,
        delivered_bytes,
        unmanaged_bytes,
        sent_bytes,
        app_limited,
        rtt_s=(),
        receiver_behind=False,
        offered_bytes=math.nan,
        sender_blocked_s=0.0,
        delivered_link_bytes=0,
        sent_link_bytes=0,
        acked_link_bytes=0,
        sender_socket_full=math.nan,
        probe_bytes=0,
        probe_sent_bytes=0,
        probe_train_bytes=0,
        probe_train_spread_s=0.0,
        probe_train_sent_mbps=0.0,
        probe_train_receiver_wait_s=math.nan,
        probe_cost_mbps=0.0,
        send_queue_max_bytes=math.nan,
    ):
        """One cps_msgs/LinkReport of the bridges as plain values. Where the robots' link socket's
        TCP payload counts are there (`sent_link_bytes`, `acked_link_bytes` > 0: every byte the link
        carried, framing included) the estimator takes what was sent and what the twin acknowledged,
        both over the robots' interval on its clock (BBR's delivery rate; two clocks' intervals
        misalign by a frame or more); else the frames, delivered over the twin's interval and sent
        over the robots'. The unmanaged traffic is all the twin's socket received but the managed
        frames (or the unmanaged frames). App-limited only when the allocation does not bind either;
        link-limited when the robots' socket was full in nearly all its samples (else, without
        them, when its sender waited for Zenoh half of its interval). The probe trains' frames
        (`probe_bytes`, in delivered and unmanaged) are their own part of the budget (their mean cost
        at the robots' bridge's period now, `probe_cost_mbps`), and the last train's measure (`probe_train_bytes` over
        `probe_train_spread_s`, sent at `probe_train_sent_mbps`, the twin's reads late by up to
        `probe_train_receiver_wait_s`) is a capacity sample of its own. `send_queue_max_bytes`: the
        robots' link socket's largest kernel send queue in the interval (a standing queue's bytes).
        Returns True if the available bandwidth moved by > 5 %."""
        probe_bytes = probe_bytes if _finite(probe_bytes) and probe_bytes > 0 else 0
        if _positive(delivered_link_bytes):
            unmanaged_bytes = max(0, delivered_link_bytes - (delivered_bytes - unmanaged_bytes))
        # the frames' path: the robots' bridge counts no probe frame in what it sent (they bypass its
        # queue), the twin counts them in what it received
        if probe_bytes:
            unmanaged_bytes = max(0, unmanaged_bytes - probe_bytes)
            delivered_bytes = max(0, delivered_bytes - probe_bytes)
        if _positive(acked_link_bytes) and _positive(sent_link_bytes):
            delivered_bytes, sent_bytes = acked_link_bytes, sent_link_bytes
            delivered_interval_s = sender_interval_s
        else:
            delivered_interval_s = interval_s
        socket_full = _finite(sender_socket_full) and sender_socket_full >= LINK_LIMITED_FRACTION
        train_on_link = bool(probe_bytes) or (_finite(probe_sent_bytes) and probe_sent_bytes > 0)
        if _finite(sender_socket_full):
            link_limited = sender_socket_full >= LINK_FULL_STEP_FRACTION
        else:
            # a train's frames are taken out of the frames' delivered bytes above: without the
            # socket's counters a train's interval says nothing of a full link
            link_limited = (
                not train_on_link
                and _finite(sender_blocked_s)
                and _positive(sender_interval_s)
                and sender_blocked_s >= LINK_LIMITED_FRACTION * sender_interval_s
            )

        def mbps(n_bytes, seconds):
            # a bad interval gives a bad rate, which the estimator refuses and counts by kind
            return n_bytes * 8e-6 / seconds if _finite(n_bytes) and _finite(seconds) and seconds != 0 else math.nan

        self._now_s = max(self._now_s, now_s) if _finite(now_s) else self._now_s
        self.bridge_paces = True
        unmanaged = mbps(unmanaged_bytes, interval_s)
        low, high = REPORT_INTERVAL_BOUNDS_S
        if _finite(unmanaged) and unmanaged >= 0 and _finite(interval_s) and low <= interval_s <= high:
            self._unmanaged = [(t, v, i) for t, v, i in self._unmanaged if t > now_s - UNMANAGED_WINDOW_S]
            self._unmanaged.append((now_s, unmanaged, interval_s))
        if _finite(probe_cost_mbps) and probe_cost_mbps >= 0:
            self._probe_cost_mbps = float(probe_cost_mbps)
        has_train = _positive(probe_train_bytes) and _positive(probe_train_spread_s)
        return self.on_link_report(
            LinkReport(
                now_s=now_s,
                interval_s=interval_s,
                delivered_mbps=mbps(delivered_bytes, delivered_interval_s),
                sent_mbps=mbps(sent_bytes, sender_interval_s),
                offered_mbps=mbps(offered_bytes, sender_interval_s),
                app_limited=bool(app_limited) and not self.allocation_binds(),
                rtt_s=tuple(rtt_s),
                receiver_behind=bool(receiver_behind),
                # busy: the bridge's queue never ran empty, or its link socket stayed full (the
                # queue can be empty at a report while the sender waits for the link)
                link_busy=not app_limited or socket_full,
                link_limited=link_limited,
                link_mostly_full=socket_full if _finite(sender_socket_full) else None,
                train_mbps=mbps(probe_train_bytes, probe_train_spread_s) if has_train else math.nan,
                train_sent_mbps=float(probe_train_sent_mbps) if has_train else math.nan,
                train_receiver_wait_fraction=(
                    float(probe_train_receiver_wait_s) / float(probe_train_spread_s) if has_train else math.nan
                ),
                train_on_link=train_on_link,
                sender_queue_mbit=send_queue_max_bytes * 8e-6 if _finite(send_queue_max_bytes) else math.nan,
            )
        )

    def on_link_stats(self, now_s, delivered_mbps):
        """What exists today: the twin side's delivered Mbit/s (`/tissue/stats`) with the limiters'
        sent and offered rates; no RTT, app-limited or receiver-behind signal yet (the bridge must
        report those). Returns True if the available bandwidth moved by > 5 %."""
        last, self._last_stats_s = self._last_stats_s, now_s
        interval_s = now_s - last if math.isfinite(last) and 0 < now_s - last <= 5.0 else 0.5
        return self.on_link_report(
            LinkReport(
                now_s=now_s,
                interval_s=interval_s,
                delivered_mbps=delivered_mbps,
                sent_mbps=self.sent_mbps(),
                offered_mbps=self.offered_mbps(),
            )
        )

    def input_rate_cap_hz(self, robot):
        """The robot's maximum rate from its input: INPUT_RATE_HEADROOM x the last input rate, in
        [min_rate_hz, max_rate_hz]; max_rate_hz when none is known (never measured, or held out)."""
        s = self.settings
        rate = self.measured[self._known(robot)].input_rate_hz
        if not _positive(rate):
            return s.max_rate_hz
        return min(s.max_rate_hz, max(s.min_rate_hz, INPUT_RATE_HEADROOM * rate))

    def demands(self):
        s = self.settings
        out = []
        for robot in self.robots:
            out.append(
                self.book.demand(
                    robot, self.measured[robot].message_bytes, s.min_rate_hz, self.input_rate_cap_hz(robot)
                )
            )
        return out

    def headroom_mbytes_per_s(self, demands, budget):
        """Room for whole-message bursts inside a window, at most a quarter of the budget."""
        s = self.settings
        sizes = sum(d.message_bytes if _positive(d.message_bytes) else s.assumed_message_bytes for d in demands)
        return min(0.25 * budget, s.headroom_messages * sizes / 1e6 / s.window_s)

    def stream_demands(self, now_s=None):
        """The level allocator's input: every robot's cloud and every camera robot's video."""
        s = self.settings
        now_s = self._now_s if now_s is None else now_s
        operators = self._operators()
        out = []
        names, bits, _ = self.cloud_levels
        for robot in self.robots:
            d = self.book.demand(robot, math.nan, s.min_rate_hz, self.input_rate_cap_hz(robot))
            sizes = self.sizes[(robot, CLOUD)]
            detail = d.priority == 1 and len(names) > 1
            finished = self.book.finished(robot) and not self.book.pinned_to_minimum(robot)
            out.append(
                StreamDemand(
                    robot,
                    CLOUD,
                    sizes.estimate(now_s),
                    bits,
                    names,
                    weight=s.done_weight if finished else self.weights[d.priority],
                    priority=d.priority,
                    floor_rate_hz=d.min_rate_hz,
                    max_rate_hz=d.max_rate_hz,
                    guarantee=INSPECTION_DETAIL if detail else "",
                    guarantee_level=0,
                    guarantee_rate_hz=d.min_rate_hz,
                    size_measured=sizes.measured(now_s),
                    uses=(uses := self._uses((robot, CLOUD), now_s)),
                    finest_level=self._finest_level((robot, CLOUD), now_s, uses),
                    level_in_force=self.state[(robot, CLOUD)].level,
                )
            )
        if self.video_levels:
            names, bits, _ = self.video_levels
            st = self.streams
            for robot in self.camera_robots:
                operator = robot in operators
                sizes = self.sizes[(robot, VIDEO)]
                out.append(
                    StreamDemand(
                        robot,
                        VIDEO,
                        sizes.estimate(now_s),
                        bits,
                        names,
                        weight=self.weights[1 if operator else 0],
                        priority=int(operator),
                        floor_rate_hz=st.video_min_rate_hz,
                        max_rate_hz=st.video_max_rate_hz,
                        may_go_off=True,
                        guarantee=OPERATOR_VIDEO if operator else "",
                        guarantee_level=st.operator_video_level,
                        guarantee_rate_hz=st.operator_video_rate_hz,
                        size_measured=sizes.measured(now_s),
                        uses=(uses := self._uses((robot, VIDEO), now_s)),
                        finest_level=self._finest_level((robot, VIDEO), now_s, uses),
                        level_in_force=self.state[(robot, VIDEO)].level,
                    )
                )
        return out

    def allocate_streams(self, now_s=None) -> LevelAllocation:
        """Every stream's level and rate within (budget - headroom) / copies_on_link; bandwidths
        and shares count every copy on the link, and `budget_mbytes_per_s` stays the full budget.
        The headroom is one message per stream per window at the levels in force; if the levels
        chosen need more, the allocation is made again with that (never less than it needs)."""
        s = self.settings
        now_s = self._now_s if now_s is None else now_s
        budget = self.budget_mbytes_per_s(now_s)
        demands = self.stream_demands(now_s)
        copies = s.copies_on_link
        capacity = self.insert_capacity_clouds_per_s(now_s)

        def headroom(levels):
            sizes = sum(d.level_bytes[levels[d.key]] for d in demands)
            return min(0.25 * budget, s.headroom_messages * sizes / 1e6 / s.window_s)

        spare = self.spare(now_s)
        self.last_spare = spare

        def solve(room):
            return allocate_levels(
                demands,
                (budget - room) / copies,
                max_clouds_per_s=capacity,
                floor_rate_hz=s.floor_rate_hz,
                priority_weights=self.weights,
                spare=spare,
                upgrade_margin=s.upgrade_margin,
            )

        room = headroom(self.level_in_force)
        result = solve(room)
        chosen = {a.key: a.level for a in result.streams}
        if headroom(chosen) > room * (1 + 1e-9):
            result = solve(headroom(chosen))
            chosen = {a.key: a.level for a in result.streams}
        self.level_in_force.update(chosen)
        self.last_demands = {d.key: d for d in demands}
        self.last_allocation = result
        self.allocated_rate_hz = {a.key: a.rate_hz for a in result.streams}
        if result.link_binds:
            self._link_bound_s = max(self._link_bound_s, float(now_s))
        for resource, above in result.resource_increase:
            host = resource[len(cpu_resource("")) :] if resource.startswith(cpu_resource("")) else None
            if host is None or now_s < self._settling.get(host, (-math.inf, 0.0))[0]:
                continue
            taken = sum(self._above_baseline(k, resource, now_s) for k, st in self.state.items() if st.host == host)
            if above > taken * (1 + 1e-9) + 1e-12:  # a purchase: hold it until the host shows it
                self._settling[host] = (float(now_s) + HOST_SETTLE_S, above)
        streams = tuple(
            dataclasses.replace(
                a,
                bandwidth_mbytes_per_s=copies * a.bandwidth_mbytes_per_s,
                share_percent=100.0 * copies * a.bandwidth_mbytes_per_s / budget,
            )
            for a in result.streams
        )
        return dataclasses.replace(
            result,
            streams=streams,
            budget_mbytes_per_s=budget,
            allocated_mbytes_per_s=copies * result.allocated_mbytes_per_s,
        )

    def limiter_rates(self, result: LevelAllocation):
        """{key: rate} to set on the clouds' rate limiters. On a link that binds, the allocation's.
        On an idle one (every stream at its maximum, budget left), what the allocation leaves is
        shared among the clouds by weight as slack up to max_rate_hz: a cloud is encoded before
        its limiter whatever its rate, so slack costs nothing, and a limiter set at its sensor's
        input rate + 10 % drops clouds whenever the sensor speeds up (the input rate is a 2 s
        mean, and the setpoint filter holds a rise for up to 5 s). Bandwidth is what the
        allocation counts: slack is only used when the link has room, and it is taken back at
        once when the link binds (the filter sends decreases as soon as the rates in force would
        overrun the budget)."""
        rates = {a.key: a.rate_hz for a in result.streams if a.stream == CLOUD}
        if result.link_binds or not rates:
            return rates
        clouds = [a for a in result.streams if a.stream == CLOUD and a.rate_hz > 0]
        top = np.array(
            [
                self.settings.min_rate_hz if self.book.pinned_to_minimum(a.robot) else self.settings.max_rate_hz
                for a in clouds
            ]
        )
        size = np.array([a.message_bytes / 1e6 for a in clouds])
        lo = np.array([a.rate_hz for a in clouds]) * size
        hi = np.maximum(top * size, lo)
        copies = self.settings.copies_on_link
        budget = result.budget_mbytes_per_s / copies
        other = result.allocated_mbytes_per_s / copies - lo.sum()
        headroom = self.headroom_mbytes_per_s_at(result)
        room = budget - headroom - other
        if room <= lo.sum():
            return rates
        weight = np.array([max(a.weight, 1e-9) for a in clouds])
        b = water_fill(weight, lo, hi, room)
        raised = b / size
        capacity = self.insert_capacity_clouds_per_s()
        if capacity is not None and raised.sum() > capacity:  # nor beyond the twin's clouds/s
            allocated = lo / size
            raised = water_fill(weight, allocated, raised, max(capacity, allocated.sum()))
        rates.update({a.key: float(x) for a, x in zip(clouds, raised)})
        return rates

    def headroom_mbytes_per_s_at(self, result: LevelAllocation):
        """The per-window headroom at the levels of `result` (as allocate_streams keeps it)."""
        s = self.settings
        sizes = sum(a.message_bytes for a in result.streams)
        return min(0.25 * result.budget_mbytes_per_s, s.headroom_messages * sizes / 1e6 / s.window_s)

    def allocate(self, now_s=None) -> Allocation:
        """The clouds of `allocate_streams` as the allocation before levels (`Allocation`, one
        RobotAllocation per robot); with `streams=None` it is that allocation exactly."""
        return clouds_allocation(self.allocate_streams(now_s), self.last_demands)

    def _known(self, robot):
        if robot not in self.measured:
            raise KeyError(f"unknown robot '{robot}' (managed: {', '.join(self.robots)})")
        return robot


def _positive(value):
    try:
        return math.isfinite(float(value)) and float(value) > 0
    except (TypeError, ValueError):
        return False


def link_totals(topics):
    """(delivered Mbit/s over every topic, worst mean latency in ms over managed topics) from
    TopicStats-like records; NaN where nothing was measured."""
    delivered = sum(t.bandwidth_mbytes_per_s for t in topics if _finite(t.bandwidth_mbytes_per_s)) * 8.0
    latencies = [t.latency_avg_ms for t in topics if t.managed and t.messages > 0 and _finite(t.latency_avg_ms)]
    if not any(_finite(t.bandwidth_mbytes_per_s) for t in topics):
        delivered = math.nan
    return delivered, (max(latencies) if latencies else math.nan)


def _finite(value):
    try:
        return math.isfinite(float(value))
    except (TypeError, ValueError):
        return False


ALLOCATION_CSV_COLUMNS = (
    "stamp_s",
    "available_mbps",
    "budget_mbytes_per_s",
    "feasible",
    "robot",
    "priority",
    "mission_state",
    "rate_hz",
    "message_bytes",
    "bandwidth_mbytes_per_s",
    "share_percent",
    "degraded",
    # issue 24: one row per stream; readers of the rows before it take stream "cloud"
    "stream",
    "level",
    "level_name",
    # issue 36: level and rate_hz above are the ones in force (sent to the robots); the allocator's
    # own answer, which the setpoint filter may have held back, and whether the stream is
    # compute-bound
    "target_level",
    "target_rate_hz",
    "compute_bound",
    # the spare CPU (cores) of the host the stream's encoder runs on, as this allocation saw it
    "cpu_spare_cores",
)


LINK_STATE_CSV_COLUMNS = ("stamp_s", "up", "since_s", "outages", "last_outage_s", "peer", "available_mbps")


def link_state_csv_row(stamp_s, link: LinkHealth, available_mbps):
    """One row of link_state.csv (LINK_STATE_CSV_COLUMNS), written at every transition."""
    return (
        f"{stamp_s:.3f}",
        int(link.up),
        f"{link.since_s:.3f}",
        link.outages,
        f"{link.last_outage_s:.3f}",
        link.peer,
        f"{available_mbps:.3f}",
    )


def clouds_allocation(result: LevelAllocation, demands) -> Allocation:
    """The clouds of a LevelAllocation as an `Allocation` (rate bounds from their demands)."""
    robots = []
    for a in result.streams:
        if a.stream != CLOUD:
            continue
        d = demands[a.key]
        robots.append(
            RobotAllocation(
                name=a.robot,
                priority=a.priority,
                rate_hz=a.rate_hz,
                min_rate_hz=d.floor_rate_hz,
                max_rate_hz=a.max_rate_hz,
                message_bytes=a.message_bytes,
                bandwidth_mbytes_per_s=a.bandwidth_mbytes_per_s,
                share_percent=a.share_percent,
                degraded=a.degraded,
                size_measured=a.size_measured,
            )
        )
    allocated = sum(r.bandwidth_mbytes_per_s for r in robots)
    return Allocation(tuple(robots), result.budget_mbytes_per_s, allocated, result.feasible, result.status)


def allocation_csv_rows(stamp_s, available_mbps, result, mission_states, target=None, compute_bound=(), cpu_spare=None):
    """One row of allocation.csv per stream of `result` (ALLOCATION_CSV_COLUMNS): a LevelAllocation
    (cloud and video rows, with their levels) or an Allocation (cloud rows, no level). `target`:
    the allocator's LevelAllocation when `result` is what is in force (default: the same);
    `compute_bound`: the (robot, stream) keys judged compute-bound; `cpu_spare`: {key: cores}."""
    cpu_spare = cpu_spare or {}

    def spare(key):
        value = cpu_spare.get(key, math.nan)
        return "" if math.isnan(value) else f"{value:.3f}"

    if isinstance(result, LevelAllocation):
        wanted = (target or result).by_key()
        items = [
            (a.robot, a.priority, a.rate_hz, a.message_bytes, a.bandwidth_mbytes_per_s, a.share_percent, a.degraded)
            + (a.stream, a.level, a.level_name)
            + (
                wanted[a.key].level if a.key in wanted else "",
                f"{wanted[a.key].rate_hz:.3f}" if a.key in wanted else "",
                int(a.key in set(compute_bound)),
                spare(a.key),
            )
            for a in result.streams
        ]
    else:
        items = [
            (a.name, a.priority, a.rate_hz, a.message_bytes, a.bandwidth_mbytes_per_s, a.share_percent, a.degraded)
            + (CLOUD, "", "", "", f"{a.rate_hz:.3f}", 0, spare((a.name, CLOUD)))
            for a in result.robots
        ]
    return [
        (
            f"{stamp_s:.3f}",
            f"{available_mbps:.3f}",
            f"{result.budget_mbytes_per_s:.4f}",
            int(result.feasible),
            robot,
            priority,
            mission_states[robot],
            f"{rate:.3f}",
            f"{size:.0f}",
            f"{bandwidth:.4f}",
            f"{share:.2f}",
            int(degraded),
            *stream_level_target_bound_cpu,
        )
        for (robot, priority, rate, size, bandwidth, share, degraded, *stream_level_target_bound_cpu) in items
    ]
