"""The multi-robot map server (paper 2.3.1, Fig. 6) without the ROS plumbing.

Admission before work (issue 37): the receive side (`cps_mapping.admission`: in the node its own
process) only counts a robot's cloud and holds it as it arrived (still Draco-compressed, even still
serialized) in the robot's latest-only slot; a newer cloud supersedes it at the cost of a pointer
swap. Whoever calls `insert_pending` (the node's insertion thread) takes one cloud at a time, the
robot whose map is oldest first, placed by the admission's transform lookup (which never waits),
and only then pays for it: Draco decoding, checks, preparation and insertion into one
FusedLogOddsMap, timed in the thread's CPU time. Every cloud ends in exactly one counter: inserted,
superseded, or dropped by cause (decoder, tf, invalid, queue), or it still waits; gaps in a
sender's sequence numbers count the clouds lost before they arrived. `publish_*` build the messages from a copy of the map taken in milliseconds
under the map lock (insertion goes on while they are built) and hand them to injected publish
callables; the `on_*` service handlers take and return cps_msgs/std_srvs types. The node wires
this to rospy; the tests drive it directly.
"""

import dataclasses
import logging
import math
import os
import threading
import time
from typing import Callable, Dict, Optional, Sequence, Tuple

import numpy as np
from std_msgs.msg import Header
from std_srvs.srv import EmptyResponse

from cps_fleet import names
from cps_mapping import map_messages
from cps_mapping.admission import Admission, PlacedCloud, TransformUnavailable, merged_counts
from cps_mapping.baseline import BaselineError, load_baseline, read_map_trails, read_map_views, write_map_metadata
from cps_mapping.change_attention import ATTENTION_RADIUS_M
from cps_mapping.change_detection import (
    TRUSTED_RULES,
    FrozenMap,
    VoxelLevels,
    detect_map_changes,
    read_ever_hit,
    write_hit_levels,
    write_miss_levels,
    write_report,
)
from cps_mapping.change_tracking import ChangeTracker
from cps_mapping.cloud_input import InvalidInput, prepare_cloud, read_leaf
from cps_mapping.fused_map import FusedLogOddsMap, MapFileError, message_fields
from cps_mapping.insert_capacity import InsertionBudget, InsertionMeter, voxel_updates_of
from cps_mapping.markers import occupied_cells_markers
from cps_mapping.robot_bodies import RobotTrails, SweptVolume, fleet_bodies
from cps_mapping.sensor_views import SensorViews, fleet_fields_of_view
from cps_mapping.throttled_log import ThrottledLog
from cps_msgs.msg import CompressedPointCloud2
from cps_msgs.srv import BoundingBoxQueryResponse, LoadMapResponse, SaveMapResponse
from cps_transport.draco import DracoDecoder, DracoError
from cps_transport.pointcloud import InvalidCloud, cloud_to_array, xyz_of

_WARN_EVERY_S = 5.0
_FRAME_WARN_EVERY_S = 30.0
_LEAF_WARN_EVERY_S = 300.0  # every cloud of a fleet without levels: not a line per robot every 5 s
__all__ = ["MapOutputs", "MapServer", "MapServerOptions", "RobotCounters", "TransformUnavailable"]


def _option(default, meaning, unit="", **bounds):
    return dataclasses.field(default=default, metadata=dict(meaning=meaning, unit=unit, bounds=bounds))


@dataclasses.dataclass(frozen=True)
class MapServerOptions:
    """The map server's settings, one per private parameter of the node (same name)."""

    fleet_file: str = _option(
        "", "fleet.yaml: robots, resolution, sensor model, max ranges, autosave period (empty: cps_bringup's)", "path"
    )
    robots: Tuple[str, ...] = _option(
        (),
        "robots to map (list or comma string; empty: the whole fleet); names not in the fleet are logged and ignored",
    )
    frame_id: str = _option("map", "fixed frame")
    tf_timeout_s: float = _option(
        0.5,
        "a cloud whose transform is still unknown this long after it arrived is dropped (the insertion "
        "never waits for one: it serves other robots meanwhile)",
        "s",
        low=0.0,
    )
    receive_nice: int = _option(
        5,
        "nice of the receive process (its subscribers, transforms and slots), above the map server's: "
        "at 5 (CFS weight 335 against 1024) the insertion gets about three quarters of a core both want",
        "",
        low=0,
        high=19,
    )
    insertion_budget_fraction: float = _option(
        0.8,
        "CPU share of each second the insertion thread may use (the rest: publishing, services, "
        "subscribers); InsertCapacity's capacity is at this share",
        "",
        low=0.0,
        low_open=True,
        high=1.0,
    )
    capacity_window_s: float = _option(
        10.0, "InsertCapacity's window of measured insertions", "s", low=0.0, low_open=True
    )
    publish_period_s: float = _option(
        1.0, "map, markers, centres and projected map (if the map changed)", "s", low=0.0, low_open=True
    )
    map_file: str = _option("", "autosave target (.bt or .ot), saved on shutdown, resumed at start", "path")
    map_folder: str = _option(
        "",
        "save_map and load_map accept only paths inside this folder, symlinks and .. "
        "resolved (empty: the folder of ~map_file; neither: only ~map_file itself)",
        "path",
    )
    autosave_period_s: Optional[float] = _option(
        None, "0: only on shutdown and on request (default: fleet.yaml mapping.autosave_period_s)", "s", low=0.0
    )
    max_points_range_m: float = _option(
        200.0, "points farther from the sensor are absurd: removed, counted", "m", low=0.0, low_open=True
    )
    exact_free_space: bool = _option(
        False, "true: every ray cast whole (plain OctoMap insertion); false: shared-origin casting"
    )
    shared_ray_stop_m: float = _option(
        0.3,
        "shared-origin casting: a ray stops after this length of voxels its cloud already cleared",
        "m",
        low=0.0,
        low_open=True,
    )
    projected_min_z_m: float = _option(0.1, "lower bound of the projected map's height band", "m")
    projected_max_z_m: float = _option(2.0, "upper bound of the projected map's height band", "m")
    baseline_map: str = _option("", "baseline map of the same site for map_changes", "path")
    change_period_s: float = _option(5.0, "change detection period", "s", low=0.0, low_open=True)
    change_report: str = _option("", "Markdown (+ .json) report written at each change detection", "path")
    change_tolerance_voxels: int = _option(
        TRUSTED_RULES.tolerance_voxels,
        "a voxel changed if no voxel of the other map lies this near: absorbs "
        "thin structures (fence rails) seen from other viewpoints",
        "voxels",
        low=0,
    )
    change_min_cluster_voxels: int = _option(
        TRUSTED_RULES.min_cluster_voxels, "smaller clusters of changed voxels are noise", "voxels", low=1
    )
    change_attention_radius_m: float = _option(
        ATTENTION_RADIUS_M,
        "a robot this near a newly found change (from its first cycle) gets high link priority (0: never)",
        "m",
        low=0.0,
    )


@dataclasses.dataclass
class RobotCounters:
    """What RobotMapStats reports for one robot (`MapServer.robot_counters`: the admission counts,
    kept by the slots, with what the insertion counted)."""

    clouds_received: int = 0
    clouds_inserted: int = 0
    clouds_dropped_queue: int = 0  # backfill keyframes beyond their FIFO's bound
    clouds_superseded: int = 0  # replaced in the slot by a newer cloud before insertion
    clouds_dropped_tf: int = 0
    clouds_dropped_invalid: int = 0  # the map server's own checks, or the insertion failed
    clouds_dropped_decoder: int = 0  # not deserializable or not Draco-decodable
    clouds_placed: int = 0  # handed by the admission to the insertion
    clouds_without_leaf: int = 0  # inserted as they are (docs/cloud_levels.md)
    clouds_bad_leaf: int = 0  # leaf unreadable: inserted as they are
    points_bridged: int = 0  # surface samples added to clouds coarser than the map
    points_inserted: int = 0
    points_rejected: int = 0
    batches: int = 0  # insertions (one cloud each)
    insertion_ms_total: float = 0.0  # CPU ms of the insertion thread per inserted cloud, summed
    insertion_ms_max: float = 0.0
    newest_inserted_stamp_s: Optional[float] = None
    # Never received: gaps in the sender's header.seq (the twin's bridge numbers what it relays:
    # lost in the subscriber queue), for the per-cloud ledger.
    clouds_missed_upstream: int = 0
    # The stamp of this robot's newest cloud in the map as last published (None before).
    newest_published_stamp_s: Optional[float] = None

    @property
    def insertion_ms_avg(self):
        return self.insertion_ms_total / self.batches if self.batches else 0.0

    @property
    def clouds_dropped(self):
        """Lost, every cause (superseded is not lost; missed never arrived)."""
        return (
            self.clouds_dropped_queue
            + self.clouds_dropped_tf
            + self.clouds_dropped_invalid
            + self.clouds_dropped_decoder
        )

    @property
    def clouds_accounted(self):
        """Received clouds that reached an end (inserted, superseded or dropped by a cause)."""
        return (
            self.clouds_inserted
            + self.clouds_superseded
            + self.clouds_dropped_queue
            + self.clouds_dropped_tf
            + self.clouds_dropped_invalid
            + self.clouds_dropped_decoder
        )

    def map_age_s(self, now_s):
        if self.newest_inserted_stamp_s is None:
            return math.inf
        return max(0.0, now_s - self.newest_inserted_stamp_s)

    def published_map_age_s(self, now_s):
        """What a subscriber of the map sees: now - the stamp of this robot's newest cloud in the map as
        last published (inf before), which keeps growing when the map stops being published."""
        if self.newest_published_stamp_s is None:
            return math.inf
        return max(0.0, now_s - self.newest_published_stamp_s)


def _merged_counters(insertion: RobotCounters, admitted) -> RobotCounters:
    """The insertion's counters (a copy) with the admission's AdmissionCounters, a cause both count summed."""
    both = merged_counts(admitted, **{f: getattr(insertion, f) for f in vars(admitted) if hasattr(insertion, f)})
    return dataclasses.replace(insertion, **both)


def _waiting(insertion: RobotCounters, admitted) -> int:
    """Clouds received and not ended: in the slot, or placed and not yet ended by the insertion.
    `admitted` is the admission's (AdmissionCounters, clouds in the slot), read after `insertion`."""
    counts, in_slot = admitted
    ended = insertion.clouds_inserted + insertion.clouds_dropped_decoder + insertion.clouds_dropped_invalid
    return in_slot + counts.clouds_placed - ended


@dataclasses.dataclass(frozen=True)
class MapSnapshot:
    """What the publishers send for one map version, built from a copy of the map taken under the
    map lock (in milliseconds) and read outside it."""

    version: int
    leaf_centers_m: np.ndarray
    leaf_sizes_m: np.ndarray
    grid: np.ndarray
    grid_origin_m: np.ndarray
    octomap_fields: tuple
    contributions: Dict[str, int]
    tree_nodes: int
    memory_bytes: int


@dataclasses.dataclass(frozen=True)
class MapOutputs:
    """One publish callable per output topic (a rospy Publisher's `publish`; a list's `append` in tests)."""

    octomap: Callable
    markers: Callable
    centers: Callable
    projected_map: Callable
    stats: Callable
    changes: Callable
    # octomap_full (log-odds .ot body), built only while `full_wanted()` (it costs a tree walk).
    octomap_full: Optional[Callable] = None
    full_wanted: Callable = lambda: True
    # cps_msgs/InsertCapacity (insert_capacity.py), once a second.
    capacity: Optional[Callable] = None
    # points(robot, PointCloud2): each inserted cloud as decoded (sensor frame), for displays.
    points: Optional[Callable] = None


class MapServer:
    """The fused map, the per-robot queues and counters, and what the node's callbacks do."""

    def __init__(
        self,
        fleet,
        options: MapServerOptions,
        outputs: MapOutputs,
        transform_of: Optional[Callable],
        log: logging.Logger = logging.getLogger(__name__),
        admission: Optional[Callable] = None,
    ):
        """`fleet`: cps_fleet's FleetConfig. `transform_of(frame, stamp)` -> (3x3 rotation, translation)
        of `frame` in `options.frame_id`, or raises TransformUnavailable, never waiting: the lookup
        of the receive side made here (`admission` None). `admission(robots)`: makes a receive side
        of the same interface that runs elsewhere (the node's receive process,
        cps_mapping.admission_process). ValueError for bad options."""
        self.options, self.outputs, self.log = options, outputs, log
        self._transform_of = transform_of
        if options.map_file and os.path.splitext(options.map_file)[1].lower() not in (".bt", ".ot"):
            raise ValueError(f"map_file: '{options.map_file}' must end in .bt or .ot")
        self.robots = self._select_robots(fleet, options.robots)
        folder = options.map_folder or (os.path.dirname(os.path.abspath(options.map_file)) if options.map_file else "")
        self.map_folder = os.path.realpath(folder) if folder else ""
        mapped = [r for r in fleet.robots if r.name in self.robots]
        self.max_range_m = {r.name: fleet.mapping.max_range_m.get(r.type, -1.0) for r in mapped}
        self.sensor_frames = {r.name: r.sensor_frame for r in mapped}
        self.map = FusedLogOddsMap.from_mapping_config(
            fleet.mapping,
            exact_free_space=options.exact_free_space,
            shared_ray_stop_m=options.shared_ray_stop_m,
            first_seen_stamps=bool(options.baseline_map),  # a change is timed from the cloud that first saw it
        )
        self.baseline = None
        # The robots' sensor poses and bodies, saved with the map: change detection ignores robots.
        self.trails = RobotTrails(fleet_bodies(fleet, self.robots))
        # Where the inserted clouds were taken from and what they could see: change detection's viewpoints.
        self.views = SensorViews(fleet_fields_of_view(fleet, self.robots))
        self.baseline_trails = self.baseline_views = self.baseline_ever_hit = None
        if options.baseline_map:
            try:
                self.baseline = load_baseline(options.baseline_map, fleet.mapping, options.frame_id)
                self.baseline_trails = read_map_trails(options.baseline_map)
                self.baseline_views = read_map_views(options.baseline_map)
                self.baseline_ever_hit = read_ever_hit(options.baseline_map)
            except BaselineError as exc:
                raise ValueError(f"baseline_map: {exc}") from exc
            self.swept = SweptVolume(self.map.resolution_m).add(self.baseline_trails)
            self.baseline_hits = VoxelLevels.of_map(options.baseline_map)
            self.tracker = ChangeTracker()
        self._map_lock = threading.Lock()
        self._save_lock = threading.Lock()  # one save (map and sidecars) at a time
        self._counters_lock = threading.Lock()
        self._publish_lock = threading.Lock()  # the map timer's and the insertion thread's publications
        self.counters = {r: RobotCounters() for r in self.robots}  # the insertion's; the admission's apart
        # a robot's cloud is in the map and none of its clouds yet in a published one (first_unpublished)
        self._unpublished_first = False
        # robots whose next inserted cloud is their first since the link came back (link_restored)
        self._resumed_robots = set()
        self.admission = (
            admission(self.robots)
            if admission is not None
            else Admission(self.robots, transform_of, options.tf_timeout_s, options.frame_id, log)
        )
        self.decoder = DracoDecoder()  # the insertion thread's: only it decodes
        self.latest_poses = {}  # sensor frame -> (rotation, translation) of its robot's last inserted cloud
        self.meter = InsertionMeter(options.capacity_window_s, options.insertion_budget_fraction, totals=self._totals)
        self.budget = InsertionBudget(options.insertion_budget_fraction)
        self.snapshot: Optional[MapSnapshot] = None
        self._full_version = None  # the map version octomap_full last carried
        self.unknown_robots = set()
        self._throttled = ThrottledLog(log)
        self._resume()

    def _select_robots(self, fleet, wanted: Sequence[str]):
        if not wanted:
            return list(fleet.robot_names)
        for name in wanted:
            if name not in fleet.robot_names:
                self.log.error(
                    f"map_server: ~robots names '{name}', which is not in the fleet "
                    f"({', '.join(fleet.robot_names)}); ignoring it"
                )
        known = [w for w in wanted if w in fleet.robot_names]
        if not known:
            raise ValueError(f"robots: none of {list(wanted)} is in the fleet")
        return known

    def describe(self):
        o = self.options
        free = "exact" if o.exact_free_space else f"shared-origin casting (stop {o.shared_ray_stop_m} m)"
        return (
            f"map_server: robots {', '.join(self.robots)}; resolution {self.map.resolution_m} m; "
            f"max range {self.max_range_m}; latest-only slots, oldest map first; map file '{o.map_file or '(none)'}'; "
            f"free space {free}"
        )

    def _warn(self, key, period_s, message, level=logging.WARNING):
        """Log `message` unless the same `key` was logged within `period_s`."""
        self._throttled.warn(key, message, period_s, level)

    def _counts_in_order(self):
        """({robot: a copy of the insertion's counters}, the admission's snapshot), read in that
        order. The admission counts a cloud placed before the insertion can end it, so every cloud
        the first read counts as ended the second counts as placed, and a robot's waiting count is
        never negative. Read the other way round, a cloud received and inserted between the two
        reads made it -1, which a uint32 field cannot carry: /twin/map_stats failed to serialize."""
        with self._counters_lock:
            insertion = {r: dataclasses.replace(c) for r, c in self.counters.items()}
        return insertion, self.admission.snapshot()

    def robot_counters(self, robot) -> RobotCounters:
        """A copy of the robot's counters: the admission's and the insertion's, a cause both count summed."""
        insertion, admitted = self._counts_in_order()
        return _merged_counters(insertion[robot], admitted[robot][0])

    def waiting(self, robot) -> int:
        """The robot's clouds received and not ended yet: in its slot, or placed and on their way to
        the insertion (the receive process hands them over in batches)."""
        insertion, admitted = self._counts_in_order()
        return _waiting(insertion[robot], admitted[robot])

    def _totals(self):
        """(superseded, dropped) so far, every robot and both sides (InsertCapacity's window)."""
        insertion, admitted = self._counts_in_order()
        rows = [_merged_counters(insertion[r], admitted[r][0]) for r in self.robots]
        return sum(c.clouds_superseded for c in rows), sum(c.clouds_dropped for c in rows)

    def _count(self, robot, **amounts):
        with self._counters_lock:
            counters = self.counters[robot]
            for field, amount in amounts.items():
                setattr(counters, field, getattr(counters, field) + amount)

    # ---- persistence ---------------------------------------------------------------------------

    def _resume(self):
        path = self.options.map_file
        if not path or not os.path.exists(path):
            return
        try:
            nodes = self.map.load(path)
            self.log.info(f"map_server: resumed from {path} ({nodes} nodes)")
            self.trails.extend(read_map_trails(path) or RobotTrails({}))
            self.views.extend(read_map_views(path))
        except Exception as exc:  # any bad map file: moved aside, never a crash loop at start-up
            aside = f"{path}.unreadable-{int(time.time())}"
            try:
                os.replace(path, aside)
            except OSError as move_error:
                aside = f"nowhere ({move_error.strerror}), it stays"
            self.log.error(f"map_server: cannot resume: {exc}; moved it to {aside} and started an empty map")

    def _save(self, path):
        """The map and its sidecars, one save at a time (the autosave timer and a save request must
        not interleave their files); MapFileError for any of them that cannot be written. The map
        is copied under the map lock (milliseconds) and written from the copy: insertion goes on."""
        with self._save_lock:
            with self._map_lock:
                frozen = self.map.frozen_copy()
            saved = frozen.save(path)
            write_map_metadata(saved, self.options.frame_id, frozen.resolution_m, self.trails, self.views)
            try:
                write_hit_levels(saved, FrozenMap(frozen))  # how firmly each voxel was seen, for change detection
            except OSError as exc:
                raise MapFileError(f"cannot write the hit levels beside {saved}: {exc}") from exc
            return saved

    def autosave(self):
        try:
            self._save(self.options.map_file)
        except MapFileError as exc:
            self._warn("autosave", 30.0, f"map_server: autosave failed: {exc}", logging.ERROR)

    def shutdown(self):
        """Stop the insertion and save to `map_file`, if set."""
        self.admission.close()
        if self.options.map_file:
            try:
                path = self._save(self.options.map_file)
                self.log.info(f"map_server: saved the map to {path} on shutdown")
            except MapFileError as exc:
                self.log.error(f"map_server: could not save on shutdown: {exc}")

    # ---- input ---------------------------------------------------------------------------------

    def receive_cloud(self, robot, msg, backfill=False):
        """Admission (in this process): hold a robot's cloud as it arrived (a rospy.AnyMsg of a
        CompressedPointCloud2 or PointCloud2, or such a message) in its slot; nothing is decoded
        or checked here. A cloud it replaces is counted superseded; a gap in the sender's sequence
        numbers, as missed. `backfill`: a keyframe sent after a link outage (its own FIFO, served
        when no live cloud is ready). Never raises."""
        self.admission.receive(robot, msg, backfill)

    def notice_topics(self, topics: Sequence[str], namespace: str):
        """Warn once per robot whose managed cloud (`<namespace>/<robot>/points_filtered/draco/managed`)
        is among `topics` but is not mapped."""
        for topic in topics:
            robot = names.robot_of_topic(topic, names.POINTS_MANAGED, namespace)
            if robot and robot not in self.robots and robot not in self.unknown_robots:
                self.unknown_robots.add(robot)
                self.log.warning(
                    f"map_server: {topic} is published but robot '{robot}' is not mapped "
                    f"(fleet/~robots: {', '.join(self.robots)}); its clouds are ignored "
                    f"({len(self.unknown_robots)} unknown robot(s) seen)"
                )

    def insert_pending(self, timeout_s=0.5):
        """Take the next cloud (the robot whose map is oldest; waiting up to `timeout_s` for one,
        and first for the next budget cycle if this one's CPU budget is spent) and insert it; the
        number of clouds inserted (0 or 1). Its whole cost, in the thread's CPU time, is measured."""
        pause_s = self.budget.wait_s()
        if pause_s > 0:
            time.sleep(pause_s)  # the insertion thread yields its core for the rest of the cycle
        cpu_start = time.thread_time()  # waiting below costs no CPU; placing a cloud here does
        placed = self.admission.next_cloud(timeout_s=timeout_s)
        if placed is None:
            return 0
        try:
            inserted = self._insert(placed)
        except Exception as exc:  # a bug here must not stop the map; say it loudly
            inserted = None
            self._count(placed.robot, clouds_dropped_invalid=1)
            self._warn(
                ("unexpected", placed.robot),
                _WARN_EVERY_S,
                f"map_server: {placed.robot}: cloud dropped, unexpected {type(exc).__name__}: {exc}",
                logging.ERROR,
            )
        cpu_s = time.thread_time() - cpu_start
        self.budget.spend(cpu_s)
        if inserted is None:
            self.meter.spent(cpu_s)
            return 0
        points, updates, stamp_s = inserted
        self.meter.inserted(1, points, updates, cpu_s)
        with self._counters_lock:
            c = self.counters[placed.robot]
            c.clouds_inserted += 1
            c.points_inserted += points
            c.batches += 1
            c.insertion_ms_total += cpu_s * 1e3
            c.insertion_ms_max = max(c.insertion_ms_max, cpu_s * 1e3)
            c.newest_inserted_stamp_s = max(stamp_s, c.newest_inserted_stamp_s or stamp_s)
            if c.newest_published_stamp_s is None or placed.robot in self._resumed_robots:
                self._resumed_robots.discard(placed.robot)
                self._unpublished_first = True
        return 1

    def link_restored(self):
        """The link to the robots is back after an outage (or a bridge's restart): each robot's first
        cloud inserted after it asks for a publication at once (`first_unpublished`), as a restarted
        server's first clouds do, rather than waiting for the period. Chaos seed 2 (2026-12-01, fault
        26): the robots' bridge killed, every robot's clouds inserted again 2.9-3.1 s after, champ's
        map published 0.1 s later by the timer: 3.3 s old 3 s after the kill, against a 3 s bar."""
        with self._counters_lock:
            self._resumed_robots = set(self.robots)

    def first_unpublished(self):
        """True (once) when a robot's first cloud since this process started (or since the link came
        back: `link_restored`) was inserted and no map holding it was published yet: the insertion
        publishes at once rather than a period later. After
        a map server kill one robot's first cloud was placed just after the first publication (its
        transforms not yet in the new process's buffer) and waited a whole period: its map was not
        fresh 3 s after the kill (issue 38's chaos soak, seed 1, fault 42). Asked after every
        insertion: the lock only when the flag is set."""
        if not self._unpublished_first:
            return False
        with self._counters_lock:
            due, self._unpublished_first = self._unpublished_first, False
        return due

    def _drop(self, robot, cause, key, message, level=logging.WARNING):
        self._count(robot, **{cause: 1})
        self._warn((key, robot), _WARN_EVERY_S, f"map_server: {robot}: {message}", level)

    def _insert(self, placed: PlacedCloud):
        """Decode, check and insert one placed cloud: (points inserted, voxel updates, stamp s), or
        None when it was dropped (counted by cause)."""
        robot, msg = placed.robot, placed.message
        frame = msg.header.frame_id.lstrip("/")
        rotation, translation = placed.rotation, placed.translation_m
        if isinstance(msg, CompressedPointCloud2):
            try:
                msg = self.decoder.decode(msg)
            except (DracoError, InvalidCloud) as exc:
                return self._drop(robot, "clouds_dropped_decoder", "draco", f"undecodable cloud dropped: {exc}")
        try:
            points = cloud_to_array(msg)
            xyz = xyz_of(points)
        except InvalidCloud as exc:
            return self._drop(robot, "clouds_dropped_invalid", "malformed", f"malformed cloud dropped: {exc}")
        stamp_s = msg.header.stamp.to_sec()
        self.trails.record(robot, stamp_s, rotation, translation)
        self.views.received(robot, stamp_s, rotation, translation)
        if frame != self.sensor_frames[robot]:
            self._warn(
                ("unexpected frame", robot),
                _FRAME_WARN_EVERY_S,
                f"map_server: {robot}: cloud in frame '{frame}', expected '{self.sensor_frames[robot]}'; "
                f"inserted with its own transform",
            )
        leaf, leaf_problem = read_leaf(points)
        if leaf is None:
            self._count(robot, **{"clouds_bad_leaf" if leaf_problem else "clouds_without_leaf": 1})
            self._warn(
                ("leaf", robot),
                _LEAF_WARN_EVERY_S,
                f"map_server: {robot}: cloud {'with a bad leaf (' + leaf_problem + ')' if leaf_problem else 'without a leaf'}"
                f" inserted at the map's resolution as it is",
            )
        try:
            cloud = prepare_cloud(
                xyz, rotation, translation, self.options.max_points_range_m, leaf, self.map.resolution_m
            )
        except InvalidInput as exc:
            return self._drop(robot, "clouds_dropped_invalid", "invalid", f"cloud dropped: {exc}")
        if cloud.bridged:
            self._count(robot, points_bridged=cloud.bridged)
        if cloud.absurd:
            self._count(robot, points_rejected=cloud.absurd)
            self._warn(
                ("absurd", robot),
                _WARN_EVERY_S,
                f"map_server: {robot}: {cloud.absurd} points farther than {self.options.max_points_range_m} m "
                f"(~max_points_range_m) removed",
            )
        try:
            with self._map_lock:
                updates_before = voxel_updates_of(self.map)
                result = self.map.insert_batch(
                    [(cloud.points_m, cloud.origin_m)],
                    max_range_m=self.max_range_m[robot],
                    robot=robot,
                    stamps_s=[stamp_s],
                )
                updates_after = voxel_updates_of(self.map)
        except ValueError as exc:  # a cloud that would grow the grid beyond its bound
            return self._drop(robot, "clouds_dropped_invalid", "insertion", f"cloud not inserted: {exc}", logging.ERROR)
        self.views.inserted(robot, [stamp_s])  # viewpoints: only clouds in the map
        self.latest_poses[frame] = (rotation, translation)
        if self.outputs.points is not None:
            try:
                self.outputs.points(robot, msg)
            except Exception as exc:  # a display's topic must not cost the map its cloud
                self._warn(("points", robot), _WARN_EVERY_S, f"map_server: {robot}: decoded cloud not published: {exc}")
        updates = updates_after - updates_before if None not in (updates_before, updates_after) else 0
        return result.points_inserted, max(0, updates), stamp_s

    # ---- output --------------------------------------------------------------------------------

    def take_snapshot(self):
        """(snapshot of the current map version, whether it is new). Only the copy is made under
        the map lock; the views are read from the copy."""
        with self._map_lock:
            if self.snapshot is not None and self.snapshot.version == self.map.version:
                return self.snapshot, False
            frozen = self.map.frozen_copy()
        centers, sizes = frozen.occupied_leaves()
        grid, origin = frozen.projected_grid(self.options.projected_min_z_m, self.options.projected_max_z_m)
        snapshot = MapSnapshot(
            version=frozen.version,
            leaf_centers_m=centers,
            leaf_sizes_m=sizes,
            grid=grid,
            grid_origin_m=origin,
            octomap_fields=message_fields(frozen, binary=True),
            contributions=frozen.contributions(),
            tree_nodes=frozen.binary_tree_nodes(),
            memory_bytes=frozen.memory_bytes(),  # the grid and the .bt, as the map holds them
        )
        self.snapshot = snapshot
        return snapshot, True

    def _header(self, stamp):
        return Header(stamp=stamp, frame_id=self.options.frame_id)

    def publish_map(self, stamp):
        """The map, markers, centres and projected map, if the map changed since the last call (one
        publication at a time, whichever thread calls)."""
        with self._publish_lock:
            self._publish_map(stamp)

    def _publish_map(self, stamp):
        self._publish_full(stamp)
        with self._counters_lock:  # read before the snapshot: the snapshot holds at least these clouds
            newest = {r: c.newest_inserted_stamp_s for r, c in self.counters.items()}
        snap, changed = self.take_snapshot()
        if not changed:
            return
        out = self.outputs
        out.octomap(map_messages.octomap_message(snap.octomap_fields, self._header(stamp)))
        with self._counters_lock:
            for robot, stamp_s in newest.items():
                if stamp_s is not None:
                    self.counters[robot].newest_published_stamp_s = stamp_s
        out.markers(
            occupied_cells_markers(snap.leaf_centers_m, snap.leaf_sizes_m, self.map.resolution_m, self._header(stamp))
        )
        out.centers(map_messages.centers_cloud(snap.leaf_centers_m, self._header(stamp)))
        out.projected_map(
            map_messages.projected_map(snap.grid, snap.grid_origin_m, self.map.resolution_m, self._header(stamp))
        )

    def _publish_full(self, stamp):
        """octomap_full, once per map version and only while someone listens."""
        out = self.outputs
        if out.octomap_full is None or not out.full_wanted() or self._full_version == self.map.version:
            return
        with self._map_lock:
            frozen = self.map.frozen_copy()
        self._full_version, fields = frozen.version, message_fields(frozen, binary=False)
        out.octomap_full(map_messages.octomap_message(fields, self._header(stamp)))

    def publish_stats(self, stamp):
        """MapStats: the published snapshot's figures and every robot's counters at `stamp`."""
        snap = self.snapshot
        contributions = snap.contributions if snap is not None else {}
        insertion, admitted = self._counts_in_order()
        robots = [
            map_messages.robot_map_stats(
                r,
                _merged_counters(insertion[r], admitted[r][0]),
                _waiting(insertion[r], admitted[r]),
                stamp.to_sec(),
                contributions.get(r, 0),
            )
            for r in self.robots
        ]
        self.outputs.stats(map_messages.map_stats(self._header(stamp), self.map.resolution_m, snap, robots))

    def publish_capacity(self, stamp):
        """InsertCapacity over the last window (to the manager: the fleet's cloud load must fit in it)."""
        if self.outputs.capacity is not None:
            self.outputs.capacity(self.meter.message(stamp, self.options.frame_id))

    def publish_changes(self, stamp):
        """What appeared or disappeared against the baseline map, as markers (and the report); returns
        the changes."""
        with self._map_lock:  # a copy in milliseconds: insertion goes on while the detection runs
            frozen = self.map.frozen_copy()
        current = FrozenMap(frozen)  # its scans (occupied, ever hit) read the copy, off the lock
        changes = detect_map_changes(
            self.baseline,
            current,
            rules=TRUSTED_RULES,
            swept=self.swept.add(self.trails),
            current_trails=self.trails,
            current_views=self.views,
            baseline_trails=self.baseline_trails,
            baseline_views=self.baseline_views,
            baseline_ever_hit=self.baseline_ever_hit,
            baseline_hits=self.baseline_hits,
            tolerance_voxels=self.options.change_tolerance_voxels,
            min_cluster_voxels=self.options.change_min_cluster_voxels,
        )
        if self.options.change_report:  # how often the new mission saw each baseline voxel free
            write_miss_levels(self.options.change_report, self.baseline, current)
        tracked = self.tracker.update(changes, stamp.to_sec())  # reported after 2 cycles, withdrawn when contradicted
        changes = [t.change for t in tracked]
        array = map_messages.change_markers(changes, self._header(stamp))
        if self.options.change_report:  # before the markers, so that whoever sees them finds the report
            write_report(
                changes, self.options.change_report, self.options.baseline_map, "live map", tracker=self.tracker
            )
        self.outputs.changes(array)
        return changes

    # ---- services ------------------------------------------------------------------------------

    def _service_path(self, path):
        """The file a save/load request names (empty: ~map_file), symlinks and .. resolved;
        MapFileError for a path outside the map folder."""
        path = os.path.expanduser(path.strip()) if path else self.options.map_file
        if not path:
            raise MapFileError("no path given and ~map_file is empty")
        real = os.path.realpath(path)
        if self.map_folder and os.path.commonpath([real, self.map_folder]) == self.map_folder:
            return real
        if not self.map_folder and self.options.map_file and real == os.path.realpath(self.options.map_file):
            return real
        raise MapFileError(
            f"{path}: refused, map files are read and written only inside "
            f"{self.map_folder or '(no folder: set ~map_folder or ~map_file)'} (~map_folder)"
        )

    def on_save(self, req):
        try:
            path = self._save(self._service_path(req.path))
            return SaveMapResponse(success=True, message=f"saved {path}", path=path)
        except MapFileError as exc:
            self.log.error(f"map_server: save failed: {exc}")
            return SaveMapResponse(success=False, message=str(exc), path=req.path)

    def on_load(self, req):
        try:
            path = self._service_path(req.path)
            with self._map_lock:
                nodes = self.map.load(path)
            return LoadMapResponse(success=True, message=f"loaded {path} ({nodes} nodes)", path=path)
        except MapFileError as exc:
            self.log.error(f"map_server: load refused, the running map is unchanged: {exc}")
            return LoadMapResponse(success=False, message=str(exc), path=req.path)

    def on_reset(self, _req):
        with self._map_lock:
            self.map.reset()
        self.log.info("map_server: map reset")
        return EmptyResponse()

    def on_clear_bbx(self, req):
        """octomap_server's clear_bbx; a bad box raises ValueError (rospy fails the call with its text)."""
        lo = (req.min.x, req.min.y, req.min.z)
        hi = (req.max.x, req.max.y, req.max.z)
        with self._map_lock:
            cleared = self.map.clear_bbx(lo, hi)
        self.log.info(f"map_server: clear_bbx {lo} .. {hi}: {cleared} voxels cleared")
        return BoundingBoxQueryResponse()
