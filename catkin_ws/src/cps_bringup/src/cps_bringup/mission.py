"""What the mission is doing, for the terminal and the report: states, map size, link use.

`MissionProgress` is plain data updated by ROS callbacks (`MissionMonitor` wires them) and
formatted by `format_progress`.
"""

import dataclasses
import threading
import time
from typing import Dict, List, Optional

import numpy as np

from cps_fleet import names


@dataclasses.dataclass
class MissionProgress:
    robots: List[str]
    mission_state: Dict[str, str] = dataclasses.field(default_factory=dict)
    # When each robot was first seen done (monotonic seconds), for the report.
    done_at_s: Dict[str, float] = dataclasses.field(default_factory=dict)
    occupied_voxels: int = 0
    map_age_s: Dict[str, float] = dataclasses.field(default_factory=dict)
    clouds_inserted: Dict[str, int] = dataclasses.field(default_factory=dict)
    clouds_dropped: Dict[str, int] = dataclasses.field(default_factory=dict)
    clouds_superseded: Dict[str, int] = dataclasses.field(default_factory=dict)
    voxels_contributed: Dict[str, int] = dataclasses.field(default_factory=dict)
    rates_hz: Dict[str, float] = dataclasses.field(default_factory=dict)
    allocated_mbytes_per_s: float = 0.0
    budget_mbytes_per_s: float = 0.0
    available_mbps: float = 0.0
    managed_mbytes_per_s: float = 0.0
    managed_latency_ms: Dict[str, float] = dataclasses.field(default_factory=dict)
    # Each robot's path in `map` (x, y, z), sampled at most every 0.5 s, decimated (`Trajectory`).
    trajectories: Dict[str, tuple] = dataclasses.field(default_factory=dict)

    def all_done(self):
        return all(self.mission_state.get(r) == "done" for r in self.robots)


class Trajectory:
    """A path of at most `max_points` points: when full, every other point is dropped and from then
    on only every `stride`-th sample is kept, so the points stay evenly spread over the whole run.
    `points()` is an immutable copy, rebuilt only after a change."""

    def __init__(self, max_points):
        if max_points < 2:
            raise ValueError(f"a trajectory needs room for at least 2 points, got {max_points}")
        self.max_points = max_points
        self.stride = 1
        self._samples = 0
        self._points = []
        self._copy = ()

    def append(self, point):
        self._samples += 1
        if (self._samples - 1) % self.stride:
            return
        if len(self._points) >= self.max_points:
            self._points = self._points[::2]
            self.stride *= 2
            if (self._samples - 1) % self.stride:
                self._copy = None
                return
        self._points.append(point)
        self._copy = None

    def points(self):
        if self._copy is None:
            self._copy = tuple(self._points)
        return self._copy

    def __len__(self):
        return len(self._points)


def format_progress(progress: MissionProgress, elapsed_s: float) -> str:
    states = " ".join(
        f"{r}:{progress.mission_state.get(r, '?')}@{progress.rates_hz.get(r, 0):.0f}Hz" for r in progress.robots
    )
    return (
        f"[{elapsed_s:6.1f} s] {states} | map {progress.occupied_voxels} voxels | "
        f"link {progress.managed_mbytes_per_s:.2f}/{progress.budget_mbytes_per_s:.2f} MB/s"
    )


# map_age.csv, which the mission monitor writes and the mission verdict and its cloud ledger read
# (cps_experiments.verdict, cps_experiments.ledger): per robot, the map's age by insertion and as
# published, and the map server's counters as it published them.
MAP_SERVER_COUNTERS = (
    "clouds_received",
    "clouds_superseded",
    "clouds_dropped_queue",
    "clouds_dropped_tf",
    "clouds_dropped_invalid",
    "clouds_dropped_decoder",
    "clouds_missed_upstream",
    "queue_length",
)
MAP_AGE_COLUMNS = (
    "time_s",
    "robot",
    "map_age_s",
    "mission_state",
    "clouds_inserted",
    "published_map_age_s",
    *MAP_SERVER_COUNTERS,
)


def map_age_rows(map_stats, mission_state, now_s):
    """map_age.csv rows (MAP_AGE_COLUMNS) of one cps_msgs/MapStats message: per robot, the wall
    time, its map age, its mission state then, its inserted clouds, the published map's age and the
    map server's other counters."""
    return [
        (
            f"{now_s:.3f}",
            stats.robot,
            f"{stats.map_age_s:.3f}",
            mission_state.get(stats.robot, ""),
            stats.clouds_inserted,
            f"{stats.published_map_age_s:.3f}",
            *(getattr(stats, name) for name in MAP_SERVER_COUNTERS),
        )
        for stats in map_stats.robots
    ]


class MissionMonitor:
    """Subscribes to mission states, map stats, allocation and tissue stats (rospy must be up)."""

    def __init__(self, fleet, map_age_csv_path=None):
        """`map_age_csv_path`: where each map_stats message's per-robot map age is logged (the
        verdict's map-stale check reads it); None: not logged."""
        import rospy
        import tf2_ros
        from nav_msgs.msg import Odometry
        from std_msgs.msg import String

        from cps_msgs.msg import BandwidthAllocationArray, MapStats, TopicStatsArray

        robots = fleet.robot_names
        self.progress = MissionProgress(list(robots), trajectories={r: () for r in robots})
        self._trajectories = {r: Trajectory(fleet.limits.trajectory_max_points) for r in robots}
        # map <- <r>/odom as the robots' side publishes it on tf (static), not recomputed from config.
        self._tf = tf2_ros.Buffer()
        self._tf_listener = tf2_ros.TransformListener(self._tf)
        self._odom_in_map = {}
        self._last_sample = {}
        self._lock = threading.Lock()
        self._map_age_log = None
        if map_age_csv_path:
            from cps_fleet.csv_log import CsvLog

            self._map_age_log = CsvLog(map_age_csv_path, MAP_AGE_COLUMNS)
            self._mark_map_age_log("start")
        self._subs = [
            rospy.Subscriber(names.robot_topic(r, names.MISSION_STATE), String, self._on_state, callback_args=r)
            for r in robots
        ]
        self._subs += [
            rospy.Subscriber(names.robot_topic(r, names.ODOM), Odometry, self._on_odom, callback_args=r) for r in robots
        ]
        self._subs.append(rospy.Subscriber(names.in_twin(names.MAP_STATS), MapStats, self._on_map))
        self._subs.append(rospy.Subscriber(names.ALLOCATION, BandwidthAllocationArray, self._on_allocation))
        self._subs.append(rospy.Subscriber(names.TISSUE_STATS, TopicStatsArray, self._on_stats))

    def _on_state(self, msg, robot):
        with self._lock:
            self.progress.mission_state[robot] = msg.data
            if msg.data == "done":
                self.progress.done_at_s.setdefault(robot, time.monotonic())

    def _on_odom(self, msg, robot):
        now = time.monotonic()
        if now - self._last_sample.get(robot, 0.0) < 0.5:
            return
        odom_in_map = self._odom_in_map.get(robot) or self._lookup_odom_in_map(msg.header.frame_id)
        if odom_in_map is None:
            return
        self._odom_in_map[robot] = odom_in_map
        self._last_sample[robot] = now
        rotation, translation = odom_in_map
        p = msg.pose.pose.position
        point = tuple(float(v) for v in rotation @ (p.x, p.y, p.z) + translation)
        with self._lock:
            self._trajectories[robot].append(point)

    def _lookup_odom_in_map(self, odom_frame):
        """(rotation 3 x 3, translation 3) of `odom_frame` in map, or None while tf lacks it."""
        import rospy
        import tf2_ros

        from cps_mapping.cloud_input import quaternion_matrix

        try:
            t = self._tf.lookup_transform("map", odom_frame, rospy.Time(0)).transform
        except (tf2_ros.LookupException, tf2_ros.ConnectivityException, tf2_ros.ExtrapolationException):
            return None
        q, v = t.rotation, t.translation
        return quaternion_matrix(q.x, q.y, q.z, q.w), np.array([v.x, v.y, v.z])

    def _on_map(self, msg):
        with self._lock:
            self.progress.occupied_voxels = msg.occupied_voxels
            for stats in msg.robots:
                self.progress.map_age_s[stats.robot] = stats.map_age_s
                self.progress.clouds_inserted[stats.robot] = stats.clouds_inserted
                self.progress.clouds_dropped[stats.robot] = (
                    stats.clouds_dropped_queue + stats.clouds_dropped_tf + stats.clouds_dropped_invalid
                )
                self.progress.clouds_superseded[stats.robot] = stats.clouds_superseded
                self.progress.voxels_contributed[stats.robot] = stats.occupied_voxels_contributed
            if self._map_age_log is not None:
                for row in map_age_rows(msg, self.progress.mission_state, time.time()):
                    self._map_age_log.write(row)

    def _on_allocation(self, msg):
        with self._lock:
            self.progress.budget_mbytes_per_s = msg.budget_mbytes_per_s
            self.progress.allocated_mbytes_per_s = msg.allocated_mbytes_per_s
            self.progress.available_mbps = msg.available_mbps
            for allocation in msg.allocations:
                if allocation.stream in ("", "cloud"):  # the cloud's rate ("" from a manager without levels)
                    self.progress.rates_hz[allocation.robot] = allocation.rate_hz

    def _on_stats(self, msg):
        with self._lock:
            managed = [t for t in msg.topics if t.managed]
            self.progress.managed_mbytes_per_s = sum(t.bandwidth_mbytes_per_s for t in managed)
            for topic in managed:
                self.progress.managed_latency_ms[topic.robot] = topic.latency_avg_ms

    def snapshot(self) -> MissionProgress:
        with self._lock:
            return dataclasses.replace(
                self.progress,
                mission_state=dict(self.progress.mission_state),
                done_at_s=dict(self.progress.done_at_s),
                map_age_s=dict(self.progress.map_age_s),
                clouds_inserted=dict(self.progress.clouds_inserted),
                clouds_dropped=dict(self.progress.clouds_dropped),
                clouds_superseded=dict(self.progress.clouds_superseded),
                voxels_contributed=dict(self.progress.voxels_contributed),
                rates_hz=dict(self.progress.rates_hz),
                managed_latency_ms=dict(self.progress.managed_latency_ms),
                trajectories={r: t.points() for r, t in self._trajectories.items()},
            )

    def _mark_map_age_log(self, mark):
        """A row per robot with no age: when the monitoring started and ended, so the verdict sees a
        map server that published nothing at the start or the end of the mission."""
        for robot in self.progress.robots:
            self._map_age_log.write((f"{time.time():.3f}", robot, "nan", mark) + ("",) * (len(MAP_AGE_COLUMNS) - 4))

    def close(self):
        for sub in self._subs:
            sub.unregister()
        if self._map_age_log is not None:
            self._mark_map_age_log("end")
            self._map_age_log.close()


def wait_for_mission(
    monitor: MissionMonitor,
    supervisor,
    duration_s: Optional[float],
    print_every_s=10.0,
    log=print,
    on_tick=None,
    finished=None,
):
    """Poll until every robot is done or `duration_s` passes; the supervisor restarts what dies."""
    t0 = time.monotonic()
    last_print = -print_every_s
    while True:
        elapsed = time.monotonic() - t0
        supervisor.poll()
        if on_tick:
            on_tick(elapsed)
        progress = monitor.snapshot()
        if elapsed - last_print >= print_every_s:
            log(format_progress(progress, elapsed))
            last_print = elapsed
        if progress.all_done():
            log(format_progress(progress, elapsed))
            log("[bringup] every robot finished its route")
            return "done", elapsed
        ended_by = finished() if finished else None
        if ended_by:
            log(format_progress(progress, elapsed))
            log(f"[bringup] mission ended by {ended_by}")
            return ended_by, elapsed
        if duration_s is not None and elapsed >= duration_s:
            log(format_progress(progress, elapsed))
            log(f"[bringup] duration of {duration_s:.0f} s reached")
            return "duration", elapsed
        supervisor.wait_for_exit(0.5)
