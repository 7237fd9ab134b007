"""The latest data of the fleet, written by ROS callbacks and read by the GUI on a timer.

Callbacks only store what arrived (under one lock, no Qt, no waiting on anything), so a slow
or cut link can never block the GUI thread: the GUI reads a consistent copy at its own pace and
shows how old every value is. Values older than `stale_after_s` are stale and drawn in red.

No rospy here: the ROS side (cps_gui.ros_io) converts messages to plain values first, so the
store is tested with a fake clock.
"""

import collections
import dataclasses
import math
import threading
import time
from typing import Dict, List, Optional, Tuple

LOW_BATTERY_FRACTION = 0.2
# A managed stream whose end-to-end latency exceeds this is shown as a slow link.
SLOW_LINK_LATENCY_MS = 1000.0
# Clouds dropped by the map server within this window raise an alarm.
DROP_ALARM_WINDOW_S = 10.0
# A robot's video status comes at 1 Hz: older than this, its video counts as 0 MB/s in the plot.
VIDEO_STATUS_MAX_AGE_S = 3.0


@dataclasses.dataclass(frozen=True)
class TopicFigures:
    """What the stats monitor reports for one topic (cps_msgs/TopicStats, the fields we show)."""

    topic: str
    robot: str
    managed: bool
    rate_hz: float
    bandwidth_mbytes_per_s: float
    latency_avg_ms: float
    age_s: float


@dataclasses.dataclass(frozen=True)
class RobotAllocation:
    robot: str
    priority: int
    rate_hz: float
    bandwidth_mbytes_per_s: float
    share_percent: float
    degraded: bool
    # Which of the robot's managed streams ("cloud" or "video") and its level (index, name).
    stream: str = "cloud"
    level: int = 0
    level_name: str = ""


# The managed streams, stacked in this order in the bandwidth plot.
STREAMS = ("cloud", "video")


@dataclasses.dataclass(frozen=True)
class VideoStatus:
    """What a camera robot's video pipeline last said (<robot>/video_throttle/status)."""

    level: int
    level_name: str
    set_rate_hz: float
    output_rate_hz: float
    mean_message_bytes: float

    @property
    def bandwidth_mbytes_per_s(self):
        size = self.mean_message_bytes if math.isfinite(self.mean_message_bytes) else 0.0
        return self.output_rate_hz * size / 1e6


@dataclasses.dataclass(frozen=True)
class Allocation:
    budget_mbytes_per_s: float
    allocated_mbytes_per_s: float
    available_mbps: float
    feasible: bool
    robots: Tuple[RobotAllocation, ...]


@dataclasses.dataclass(frozen=True)
class LinkHealth:
    """What /tissue/link_state last said: `down_since_s` is on the store's clock (NaN while up)."""

    up: bool
    down_since_s: float
    outages: int
    last_outage_s: float
    peer: str


@dataclasses.dataclass(frozen=True)
class RobotMapFigures:
    robot: str
    occupied_voxels_contributed: int
    clouds_dropped: int


@dataclasses.dataclass(frozen=True)
class MapChange:
    """One change the twin found against the baseline map: kind ("appeared"/"disappeared"/"moved"),
    the centre and size (x, y, z) of its box in `map` (a move: where the item stands now), metres;
    a move's `from_m`: the centre of the box it left."""

    kind: str
    center_m: Tuple[float, float, float]
    size_m: Tuple[float, float, float]
    from_m: Optional[Tuple[float, float, float]] = None

    @property
    def volume_m3(self):
        return self.size_m[0] * self.size_m[1] * self.size_m[2]


@dataclasses.dataclass(frozen=True)
class Pose:
    """A robot's pose in `map` (x, y, z in m, yaw in rad) and its speed over ground in m/s."""

    x: float
    y: float
    z: float
    yaw_rad: float
    speed_mps: float


@dataclasses.dataclass(frozen=True)
class HealthRow:
    """One line of the fleet health table. `*_stale` flags mark values to draw in red."""

    robot: str
    robot_type: str
    mode: str
    mission_state: str
    battery_percent: float
    battery_stale: bool
    heartbeat_age_s: float
    heartbeat_stale: bool
    link_state: str
    map_voxels: int
    clouds_dropped: int
    priority: Optional[int]
    alarms: Tuple[str, ...]


@dataclasses.dataclass
class ImageFrame:
    """The newest frame of an image topic: raw pixels as they came (conversion happens on display).
    A JPEG frame arrives already decoded to rgb8 on the ROS thread; `transport` says "jpeg" and
    `wire_bytes` is the compressed size, which the rate meter counts."""

    topic: str
    width: int
    height: int
    encoding: str
    step: int
    data: bytes
    stamp_s: float
    received_s: float
    transport: str = "raw"
    wire_bytes: Optional[int] = None


class RateMeter:
    """Messages per second and MB/s over a sliding window of arrival times and sizes."""

    def __init__(self, window_s=2.0):
        self.window_s = window_s
        self._arrivals = collections.deque()

    def add(self, t_s, size_bytes):
        self._arrivals.append((t_s, size_bytes))
        self._trim(t_s)

    def _trim(self, now_s):
        while self._arrivals and now_s - self._arrivals[0][0] > self.window_s:
            self._arrivals.popleft()

    def figures(self, now_s):
        """(rate_hz, mbytes_per_s) over the window ending at `now_s`; zeros with < 2 messages."""
        self._trim(now_s)
        if len(self._arrivals) < 2:
            return 0.0, 0.0
        span = self._arrivals[-1][0] - self._arrivals[0][0]
        if span <= 0:
            return 0.0, 0.0
        count = len(self._arrivals) - 1
        size = sum(s for _, s in list(self._arrivals)[1:])
        return count / span, size / span / 1e6


@dataclasses.dataclass(frozen=True)
class LinkEstimateFigures:
    """What the GUI shows of cps_msgs/LinkEstimate, Mbit/s."""

    capacity_mbps: float
    estimate_mbps: float
    mode: str
    true_capacity_mbps: float  # the test bed's oracle; NaN when unknown
    ratio: float

    def text(self):
        """One line: the estimate, its mode, and beside it the true capacity with the ratio."""
        out = f"estimate {self.estimate_mbps:.1f} Mbit/s ({self.mode})"
        if math.isfinite(self.true_capacity_mbps):
            out += f", true {self.true_capacity_mbps:.1f} Mbit/s (oracle)"
        if math.isfinite(self.ratio):
            out += f", ratio {self.ratio:.2f}"
        return out


class _Series:
    """A bounded history of (t, value) samples for a plot."""

    def __init__(self, maxlen):
        self.t = collections.deque(maxlen=maxlen)
        self.v = collections.deque(maxlen=maxlen)

    def add(self, t_s, value):
        self.t.append(t_s)
        self.v.append(value)

    def copy(self):
        return list(self.t), list(self.v)


@dataclasses.dataclass
class _Robot:
    name: str
    robot_type: str
    pose: Optional[Pose] = None
    pose_received_s: float = -math.inf
    battery_fraction: float = math.nan
    battery_received_s: float = -math.inf
    mode: str = "?"
    mission_state: str = "?"
    map_voxels: int = 0
    clouds_dropped: int = 0
    drop_times: collections.deque = dataclasses.field(default_factory=lambda: collections.deque(maxlen=64))
    battery_series: Optional[_Series] = None
    bandwidth_series: Optional[_Series] = None
    rate_series: Optional[_Series] = None
    latency_series: Optional[_Series] = None
    allocated_series: Optional[_Series] = None


class FleetState:
    """Thread-safe store of the fleet's latest data; `clock` is monotonic seconds (injectable)."""

    def __init__(self, robots, clock=time.monotonic, stale_after_s=2.0, history_len=600, log_len=500):
        """robots: iterable of (name, robot_type)."""
        if stale_after_s <= 0:
            raise ValueError(f"stale_after_s must be positive, got {stale_after_s}")
        self.clock = clock
        self.stale_after_s = stale_after_s
        self._lock = threading.Lock()
        self._robots: Dict[str, _Robot] = {}
        for name, robot_type in robots:
            robot = _Robot(name, robot_type)
            for series in ("battery_series", "bandwidth_series", "rate_series", "latency_series", "allocated_series"):
                setattr(robot, series, _Series(history_len))
            self._robots[name] = robot
        self._start_s = clock()
        self._stats: Tuple[TopicFigures, ...] = ()
        self._stats_received_s = -math.inf
        self._allocation: Optional[Allocation] = None
        self._allocation_received_s = -math.inf
        self._budget_series = _Series(history_len)
        # Measured bandwidth per (robot, stream), sampled together at each /tissue/stats.
        self._stream_series = {(n, s): _Series(history_len) for n in self._robots for s in STREAMS}
        self._video_status: Dict[str, Tuple[VideoStatus, float]] = {}
        self._map_changes: Tuple[MapChange, ...] = ()
        self._map_changes_version = 0
        self._available_mbps = math.nan
        # The manager's link estimate and the test bed's true capacity (an oracle), MB/s histories.
        self._estimate_series = _Series(history_len)
        self._true_capacity_series = _Series(history_len)
        self._link_estimate: Optional[LinkEstimateFigures] = None
        self._map = None
        self._map_version = 0
        self._map_received_s = -math.inf
        self._images: Dict[str, ImageFrame] = {}
        self._image_meters: Dict[str, RateMeter] = {}
        self._log = collections.deque(maxlen=log_len)
        self._log_version = 0
        self._link = LinkHealth(True, math.nan, 0, 0.0, "")
        self.ignored_messages = 0

    @property
    def robot_names(self):
        return list(self._robots)

    def _robot(self, name):
        robot = self._robots.get(name)
        if robot is None:
            self.ignored_messages += 1
        return robot

    def _t(self):
        return self.clock() - self._start_s

    # Writers: called from ROS callback threads.

    def set_pose(self, robot, pose: Pose):
        with self._lock:
            r = self._robot(robot)
            if r:
                r.pose, r.pose_received_s = pose, self.clock()

    def set_battery(self, robot, fraction):
        with self._lock:
            r = self._robot(robot)
            if r:
                r.battery_fraction, r.battery_received_s = fraction, self.clock()
                r.battery_series.add(self._t(), fraction * 100.0)

    def set_mode(self, robot, mode):
        with self._lock:
            r = self._robot(robot)
            if r:
                r.mode = mode

    def set_mission_state(self, robot, state):
        with self._lock:
            r = self._robot(robot)
            if r:
                r.mission_state = state

    def set_tissue_stats(self, topics):
        """A whole /tissue/stats message: a sequence of TopicFigures."""
        topics = tuple(topics)
        with self._lock:
            now = self.clock()
            t = self._t()
            self._stats, self._stats_received_s = topics, now
            for name, r in self._robots.items():
                mine = [f for f in topics if f.robot == name]
                # Every robot's streams at every sample, so the layers stack instant by instant.
                video, received_s = self._video_status.get(name, (None, -math.inf))
                fresh = video is not None and now - received_s <= max(self.stale_after_s, VIDEO_STATUS_MAX_AGE_S)
                cloud = sum(f.bandwidth_mbytes_per_s for f in mine if f.managed)
                self._stream_series[(name, "cloud")].add(t, cloud)
                self._stream_series[(name, "video")].add(t, video.bandwidth_mbytes_per_s if fresh else 0.0)
                if not mine:
                    continue
                managed = [f for f in mine if f.managed] or mine
                r.bandwidth_series.add(t, sum(f.bandwidth_mbytes_per_s for f in mine))
                r.rate_series.add(t, managed[0].rate_hz)
                r.latency_series.add(t, managed[0].latency_avg_ms)

    def set_allocation(self, allocation: Allocation):
        with self._lock:
            self._allocation, self._allocation_received_s = allocation, self.clock()
            t = self._t()
            self._budget_series.add(t, allocation.budget_mbytes_per_s)
            per_robot = collections.defaultdict(float)
            for a in allocation.robots:
                per_robot[a.robot] += a.bandwidth_mbytes_per_s
            for name, mbytes in per_robot.items():
                r = self._robots.get(name)
                if r:
                    r.allocated_series.add(t, mbytes)

    def set_video_status(self, robot, status: VideoStatus):
        with self._lock:
            if self._robot(robot):
                self._video_status[robot] = (status, self.clock())

    def video_status(self, robot):
        """(VideoStatus or None, seconds since it arrived) of a camera robot's video."""
        with self._lock:
            status, received_s = self._video_status.get(robot, (None, -math.inf))
            return status, self.clock() - received_s

    def stream_series(self):
        """[(robot, stream, t list, MB/s list)] in stacking order (robot by robot, cloud then video),
        every series sampled at the same /tissue/stats instants."""
        with self._lock:
            return [(n, s, *self._stream_series[(n, s)].copy()) for n in self._robots for s in STREAMS]

    def set_available_bandwidth(self, mbps):
        with self._lock:
            self._available_mbps = mbps

    def set_link_estimate(self, figures: "LinkEstimateFigures"):
        """A /tissue/link_estimate: its estimate and (when known) the true capacity join the plot."""
        with self._lock:
            self._link_estimate = figures
            t = self._t()
            if math.isfinite(figures.estimate_mbps):
                self._estimate_series.add(t, figures.estimate_mbps / 8.0)
            if math.isfinite(figures.true_capacity_mbps):
                self._true_capacity_series.add(t, figures.true_capacity_mbps / 8.0)

    def link_estimate(self):
        """(the last LinkEstimateFigures or None, estimate (t, MB/s), true capacity (t, MB/s))."""
        with self._lock:
            return self._link_estimate, self._estimate_series.copy(), self._true_capacity_series.copy()

    def set_link_state(self, up, down_for_s, outages, last_outage_s, peer):
        """A /tissue/link_state message; `down_for_s`: how long the link has been down when it arrived."""
        with self._lock:
            since = self.clock() - max(0.0, down_for_s) if not up else math.nan
            if not up and not self._link.up:
                since = self._link.down_since_s
            self._link = LinkHealth(bool(up), since, int(outages), float(last_outage_s), str(peer))

    def link_lost_text(self):
        """The banner while the link is down ("" while it is up or nothing said otherwise)."""
        with self._lock:
            link, now = self._link, self.clock()
        if link.up:
            return ""
        peer = f" to {link.peer}" if link.peer else ""
        return (
            f"LINK LOST{peer} for {now - link.down_since_s:.0f} s (outage {link.outages}): "
            f"robot data below is from before the outage"
        )

    def set_map_stats(self, robots):
        """A /twin/map_stats message: a sequence of RobotMapFigures."""
        with self._lock:
            now = self.clock()
            for figures in robots:
                r = self._robots.get(figures.robot)
                if not r:
                    continue
                if figures.clouds_dropped > r.clouds_dropped:
                    r.drop_times.append(now)
                r.map_voxels = figures.occupied_voxels_contributed
                r.clouds_dropped = figures.clouds_dropped

    def set_projected_map(self, grid):
        """Any object the top view can draw (cps_gui.topview.OccupancyImage); replaces the last."""
        with self._lock:
            self._map, self._map_received_s = grid, self.clock()
            self._map_version += 1

    def add_image(self, frame: ImageFrame):
        with self._lock:
            self._images[frame.topic] = frame
            meter = self._image_meters.setdefault(frame.topic, RateMeter())
            meter.add(frame.received_s, len(frame.data) if frame.wire_bytes is None else frame.wire_bytes)

    def add_log(self, wall_time_s, level, node, text):
        with self._lock:
            self._log.append((wall_time_s, level, node, text))
            self._log_version += 1

    # Readers: called from the GUI thread.

    def age_s(self, received_s, now_s=None):
        now_s = self.clock() if now_s is None else now_s
        return now_s - received_s

    def is_stale(self, age_s):
        return not age_s < self.stale_after_s

    def health_rows(self) -> List[HealthRow]:
        with self._lock:
            now = self.clock()
            allocations = (
                {a.robot: a for a in self._allocation.robots if a.stream == "cloud"} if self._allocation else {}
            )
            stats_by_robot = {}
            for f in self._stats:
                if f.managed:
                    stats_by_robot[f.robot] = f
            rows = []
            for r in self._robots.values():
                heartbeat = max(r.pose_received_s, r.battery_received_s)
                heartbeat_age = now - heartbeat
                battery_age = now - r.battery_received_s
                alloc = allocations.get(r.name)
                link = self._link_state(heartbeat_age, alloc, stats_by_robot.get(r.name))
                link_lost = not self._link.up
                alarms = []
                if link_lost:
                    link = "link lost"
                    alarms.append("link lost")
                if r.battery_fraction < LOW_BATTERY_FRACTION:
                    alarms.append("battery low")
                if math.isfinite(heartbeat_age) and self.is_stale(heartbeat_age):
                    alarms.append("no heartbeat")
                if link == "degraded":
                    alarms.append("below minimum rate")
                if r.drop_times and now - r.drop_times[-1] < DROP_ALARM_WINDOW_S:
                    alarms.append("dropping clouds")
                rows.append(
                    HealthRow(
                        robot=r.name,
                        robot_type=r.robot_type,
                        mode=r.mode,
                        mission_state=r.mission_state,
                        battery_percent=r.battery_fraction * 100.0,
                        battery_stale=self.is_stale(battery_age),
                        heartbeat_age_s=heartbeat_age,
                        heartbeat_stale=link_lost or self.is_stale(heartbeat_age),
                        link_state=link,
                        map_voxels=r.map_voxels,
                        clouds_dropped=r.clouds_dropped,
                        priority=alloc.priority if alloc else None,
                        alarms=tuple(alarms),
                    )
                )
            return rows

    def _link_state(self, heartbeat_age, alloc, managed_stats):
        if not math.isfinite(heartbeat_age):
            return "no data"
        if self.is_stale(heartbeat_age):
            return "lost"
        if alloc is not None and alloc.degraded:
            return "degraded"
        if managed_stats is not None and managed_stats.latency_avg_ms > SLOW_LINK_LATENCY_MS:
            return "slow"
        return "ok"

    def poses(self):
        """{robot: (Pose, stale)} of the robots whose pose has arrived."""
        with self._lock:
            now = self.clock()
            return {n: (r.pose, self.is_stale(now - r.pose_received_s)) for n, r in self._robots.items() if r.pose}

    def speed_mps(self, robot):
        with self._lock:
            r = self._robots.get(robot)
            return r.pose.speed_mps if r and r.pose else math.nan

    def plot_series(self):
        """Histories for the plots: {robot: {'bandwidth'|'rate'|'latency'|'battery'|'allocated': (t, v)}},
        the budget line (t, v), and the seconds since the last /tissue/stats."""
        with self._lock:
            per_robot = {
                n: {
                    "bandwidth": r.bandwidth_series.copy(),
                    "rate": r.rate_series.copy(),
                    "latency": r.latency_series.copy(),
                    "battery": r.battery_series.copy(),
                    "allocated": r.allocated_series.copy(),
                }
                for n, r in self._robots.items()
            }
            return per_robot, self._budget_series.copy(), self.clock() - self._stats_received_s

    def link_summary(self):
        """(available Mbit/s, the last Allocation or None, seconds since it arrived)."""
        with self._lock:
            return self._available_mbps, self._allocation, self.clock() - self._allocation_received_s

    def projected_map(self):
        """(map, version, age_s); the version changes whenever a new map arrives."""
        with self._lock:
            return self._map, self._map_version, self.clock() - self._map_received_s

    def image_topics(self):
        with self._lock:
            return sorted(self._images)

    def image(self, topic):
        """(ImageFrame or None, rate_hz, mbytes_per_s, age_s) of one image topic."""
        with self._lock:
            frame = self._images.get(topic)
            if frame is None:
                return None, 0.0, 0.0, math.inf
            now = self.clock()
            rate, mbytes = self._image_meters[topic].figures(now)
            return frame, rate, mbytes, now - frame.received_s

    def log_entries(self):
        """(version, entries); entries are (wall_time_s, level, node, text), oldest first."""
        with self._lock:
            return self._log_version, list(self._log)

    def set_map_changes(self, changes):
        """The twin's latest list of MapChange (replaces the last)."""
        with self._lock:
            self._map_changes = tuple(changes)
            self._map_changes_version += 1

    def map_changes(self):
        """(version, changes); the version changes whenever a new list arrives."""
        with self._lock:
            return self._map_changes_version, self._map_changes
