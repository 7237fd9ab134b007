"""A trace-driven fleet: one recorded mission replayed as N robots into the twin, without the simulator.

The trace is a mission bag (`cps_bringup ... --record`): each robot's managed clouds (Draco, what
crosses the link), its odometry and tf. A replay of N robots gives every copy its own name
(`<robot>` for the first copy of a recorded robot, `<robot>_c<k>` after), its own frames (every
`<robot>/...` frame renamed), an offset in space (its map -> odom transform moved by a placement
that keeps the whole recorded trajectory inside the hall, at least `step_m` from every other copy's
placement of the same robot) and an offset in time (copy k of a robot starts k/K of the way into the
trace, which loops). Everything is published at wall-clock rate, stamped with the wall time at which
it is sent, into the twin's inputs: `/twin/<copy>/points_filtered/draco/managed` (what the link
relay or bridge would deliver), `/tf`, `/tf_static` and `/<copy>/odom`.

The clouds and tf are published synchronously (rospy publishers without a queue): `publish()`
returns once the message is written to every subscriber's socket, so nothing is dropped silently
in a publisher queue; a twin that does not read its sockets holds the replay back instead, and that
shows as the replay's lateness, measured when `publish()` returns. A publish that raises is
counted as the replay's own drop.

A copy replays the recorded clouds seen from a shifted pose: it offers the twin the same load as a
robot of that type would (clouds, points, rays), not new information about the site. A request for
more robots than the hall has placements for is told what it can have and gets that, never two
copies at the same placement.

This is runtime (like rosbag play): the benchmark (bench/twin_capacity.py) and fig13's replay arm
use it, and it knows nothing of their metrics.
"""

import argparse
import copy as copying
import dataclasses
import heapq
import json
import math
import os
import sys
import threading
import time
import warnings
from typing import Dict, List, Optional, Tuple

import numpy as np
import yaml

from cps_fleet import names
from cps_fleet.fleet import FleetConfig, load_fleet

# Placements are on a grid of this pitch (m) around the recorded trajectory, and keep this margin
# (m) from the hall's walls.
PLACEMENT_STEP_M = 1.0
WALL_MARGIN_M = 0.3
MAX_PLACEMENTS_PER_ROBOT = 64
# compact_trace(busy_only): a robot sending fewer clouds per second is starting or done (a paper
# profile mission on two cores records ~1.5 clouds/s per camera: its compaction asks for less).
MIN_BUSY_HZ = 3
# A replay later than this has stalled: it resumes from the present (Player.run).
STALL_S = 0.5


class TraceError(ValueError):
    """The trace cannot be replayed; the message says why."""


@dataclasses.dataclass
class RobotTrace:
    """One recorded robot: events as (seconds since the trace's start, kind, message)."""

    name: str
    clouds: List[Tuple[float, object]]
    odom: List[Tuple[float, object]]
    tf: List[Tuple[float, object]]  # geometry_msgs/TransformStamped of this robot's frames
    tf_static: List[object]
    positions_xy: np.ndarray  # the robot's base positions in map over the trace (for placements)


@dataclasses.dataclass
class Trace:
    robots: Dict[str, RobotTrace]
    duration_s: float
    source: str


def _owner(frame, robots):
    head = frame.lstrip("/").split("/", 1)[0]
    return head if head in robots else None


def load_trace(bag_path: str, fleet: FleetConfig) -> Trace:
    """The managed clouds, odometry and tf of every fleet robot found in the bag (TraceError if none)."""
    import rosbag

    robots = set(fleet.robot_names)
    managed = {names.absolute(names.managed_cloud(r)): r for r in robots}
    odom = {names.absolute(names.robot_topic(r, names.ODOM)): r for r in robots}
    try:
        bag = rosbag.Bag(bag_path)
    except Exception as exc:
        raise TraceError(f"{bag_path}: not a readable rosbag ({exc})") from exc
    traces = {r: RobotTrace(r, [], [], [], [], np.zeros((0, 2))) for r in robots}
    with bag:
        start = bag.get_start_time()
        topics = [*managed, *odom, names.TF, names.TF_STATIC]
        for topic, msg, t in bag.read_messages(topics=topics):
            rel = t.to_sec() - start
            if topic in managed:
                traces[managed[topic]].clouds.append((rel, msg))
            elif topic in odom:
                traces[odom[topic]].odom.append((rel, msg))
            else:
                for transform in msg.transforms:
                    owner = _owner(transform.child_frame_id, robots)
                    if owner is None:
                        continue
                    if topic == names.TF_STATIC:
                        traces[owner].tf_static.append(transform)
                    else:
                        traces[owner].tf.append((rel, transform))
        duration = bag.get_end_time() - start
    found = {r: tr for r, tr in traces.items() if tr.clouds}
    if not found:
        raise TraceError(
            f"{bag_path} holds no managed clouds of the fleet's robots ({', '.join(sorted(robots))}): record a "
            f"mission with `cps_bringup all --record` (it records {names.managed_cloud('<robot>')})"
        )
    for r, tr in found.items():
        if not any(t.child_frame_id.lstrip("/") == f"{r}/odom" for t in tr.tf_static):
            raise TraceError(f"{bag_path}: no map -> {r}/odom on /tf_static: the copies could not be placed")
        tr.positions_xy = _positions(tr)
    return Trace(found, duration, bag_path)


def compact_trace(bag_path: str, fleet: FleetConfig, out_path: str, busy_only=False, min_busy_hz=MIN_BUSY_HZ) -> str:
    """A copy of the bag with only what a replay reads (managed clouds, odometry, tf): a mission bag
    also holds the raw sensor streams, ~30x larger and slow to scan. `busy_only`: only the part where
    every robot sends clouds at its working rate (from the last robot's first cloud to the first
    second in which a robot sends fewer than `min_busy_hz`), not the start-up nor the robots done;
    /tf_static is kept whole."""
    import rosbag

    clouds = [names.absolute(names.managed_cloud(r)) for r in fleet.robot_names]
    topics = clouds + [names.absolute(names.robot_topic(r, names.ODOM)) for r in fleet.robot_names]
    with rosbag.Bag(bag_path) as bag:
        start, end = -math.inf, math.inf
        if busy_only:
            stamps = {}
            for topic, _, t in bag.read_messages(topics=clouds):
                stamps.setdefault(topic, []).append(t.to_sec())
            start = max(min(s) for s in stamps.values())
            for s in stamps.values():
                s = np.asarray(s)
                for second in np.arange(start, s[-1], 1.0):
                    if np.count_nonzero((s >= second) & (s < second + 1.0)) < min_busy_hz:
                        end = min(end, second)
                        break
                else:
                    end = min(end, s[-1])
            if not end - start > 5.0:
                raise TraceError(f"{bag_path}: fewer than 5 s in which every robot sends clouds")
        with rosbag.Bag(out_path, "w") as out:
            for topic, msg, t in bag.read_messages(topics=topics + [names.TF, names.TF_STATIC]):
                if topic == names.TF_STATIC and t.to_sec() < start:
                    out.write(topic, msg, type(t).from_sec(start))  # the trace starts with it, not before
                elif topic == names.TF_STATIC or start <= t.to_sec() <= end:
                    out.write(topic, msg, t)
    return out_path


def _positions(trace: RobotTrace) -> np.ndarray:
    """The robot's positions in the map: map -> odom (static) composed with its odometry."""
    base = next(t for t in trace.tf_static if t.child_frame_id.lstrip("/") == f"{trace.name}/odom").transform
    q = base.rotation
    yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
    c, s = math.cos(yaw), math.sin(yaw)
    xy = [(m.pose.pose.position.x, m.pose.pose.position.y) for _, m in trace.odom] or [(0.0, 0.0)]
    xy = np.asarray(xy, dtype=float)
    return np.stack(
        [base.translation.x + c * xy[:, 0] - s * xy[:, 1], base.translation.y + s * xy[:, 0] + c * xy[:, 1]], 1
    )


def hall_bounds(fleet: FleetConfig) -> Tuple[float, float, float, float]:
    """(x_min, x_max, y_min, y_max) of the hall's interior, m."""
    with open(fleet.site_path) as f:
        hall = yaml.safe_load(f)["hall"]
    return hall["x_min_m"], hall["x_max_m"], hall["y_min_m"], hall["y_max_m"]


def placements(trace: RobotTrace, bounds, step_m=PLACEMENT_STEP_M, margin_m=WALL_MARGIN_M):
    """Offsets (dx, dy) on a `step_m` grid that keep the robot's whole trajectory `margin_m` inside the
    hall; (0, 0) first, then the nearest ones (at most MAX_PLACEMENTS_PER_ROBOT)."""
    x_min, x_max, y_min, y_max = bounds
    lo, hi = trace.positions_xy.min(axis=0), trace.positions_xy.max(axis=0)
    dx = np.arange(math.ceil((x_min + margin_m - lo[0]) / step_m), math.floor((x_max - margin_m - hi[0]) / step_m) + 1)
    dy = np.arange(math.ceil((y_min + margin_m - lo[1]) / step_m), math.floor((y_max - margin_m - hi[1]) / step_m) + 1)
    offsets = [(float(i * step_m), float(j * step_m)) for i in dx for j in dy]
    offsets.sort(key=lambda o: (math.hypot(*o), o))
    return offsets[:MAX_PLACEMENTS_PER_ROBOT]


@dataclasses.dataclass(frozen=True)
class Copy:
    name: str
    source: str
    offset_xy_m: Tuple[float, float]
    time_offset_s: float


def plan_copies(trace: Trace, n: int, bounds, step_m=PLACEMENT_STEP_M) -> Tuple[List[Copy], Optional[str]]:
    """N copies, taken round-robin over the recorded robots, each at its own placement; (copies,
    None) or, when the hall holds fewer, (what it holds, a sentence saying so)."""
    if n < 1:
        raise TraceError(f"robots: {n}; at least 1")
    recorded = sorted(trace.robots)
    free = {r: placements(trace.robots[r], bounds, step_m) for r in recorded}
    for r in recorded:
        if not free[r] or free[r][0] != (0.0, 0.0):
            free[r] = [(0.0, 0.0)] + [o for o in free[r] if o != (0.0, 0.0)]  # as recorded: always honest
    chosen: Dict[str, List[Tuple[float, float]]] = {r: [] for r in recorded}
    order = []
    while len(order) < n and any(free.values()):
        for r in recorded:
            if len(order) < n and free[r]:
                chosen[r].append(free[r].pop(0))
                order.append(r)
    copies, seen = [], {r: 0 for r in recorded}
    for r in order:
        k = seen[r]
        seen[r] += 1
        total = len(chosen[r])
        copies.append(Copy(r if k == 0 else f"{r}_c{k}", r, chosen[r][k], trace.duration_s * k / total))
    note = None
    if len(copies) < n:
        capacity = ", ".join(f"{r} {len(chosen[r])}" for r in recorded)
        note = (
            f"asked for {n} robots, but the trace's {len(recorded)} robots can be placed only {len(copies)} times "
            f"in the hall ({capacity}; placements {step_m:g} m apart keeping each trajectory inside): replaying "
            f"{len(copies)}"
        )
    return copies, note


def write_copies_fleet(fleet: FleetConfig, copies: List[Copy], path: str) -> str:
    """A fleet file whose robots are the copies (type, leaf and route of their source; start pose
    moved by the placement), everything else as `fleet`'s; for the twin's nodes (decoder, map server)."""
    with open(fleet.path) as f:
        doc = yaml.safe_load(f)
    if "base" in doc:
        raise TraceError(f"{fleet.path}: a derived fleet file; record with a plain fleet file")
    here = os.path.dirname(fleet.path)
    doc["site"] = os.path.abspath(os.path.join(here, doc["site"]))
    robots = []
    for c in copies:
        source = fleet.robot(c.source)
        pose = source.initial_pose
        robots.append(
            dict(
                name=c.name,
                type=source.type,
                initial_pose=dict(
                    x=pose.x + c.offset_xy_m[0], y=pose.y + c.offset_xy_m[1], z=pose.z, yaw_deg=pose.yaw_deg
                ),
                voxel_leaf_m=source.voxel_leaf_m,
                route=os.path.abspath(source.route_path),
            )
        )
    doc["robots"] = robots
    with open(path, "w") as f:
        f.write(f"# Generated by cps_bringup.trace_replay: {len(copies)} copies of the robots of {fleet.path}\n")
        yaml.safe_dump(doc, f, sort_keys=False)
    return path


def twin_specs(copies_fleet_path: str, out_dir: str, map_server_args=()):
    """The twin's cloud path for the copies: the map server as bringup plans it (no bridge, relay,
    manager or GUI: the replay feeds the map server's inputs, as the link would)."""
    from cps_bringup.plan import DIGITAL, MAP_SERVER, RunOptions, plan_nodes

    fleet = load_fleet(copies_fleet_path)
    options = RunOptions(out_dir=out_dir, map_file=os.path.join(out_dir, "map.bt"))
    keep = []
    for spec in plan_nodes(fleet, sides=(DIGITAL,), options=options):
        if spec.label == MAP_SERVER:
            spec = dataclasses.replace(spec, argv=(*spec.argv, *map_server_args))
            keep.append(dataclasses.replace(spec, after=()))
    return keep


def _rename(frame, source, target):
    bare = frame.lstrip("/")
    return target + bare[len(source) :] if bare == source or bare.startswith(source + "/") else frame


class Player:
    """Publishes the copies' events at wall-clock rate (the caller's rospy node); `stop` ends it."""

    def __init__(
        self,
        trace: Trace,
        copies: List[Copy],
        publish_cloud,
        publish_tf,
        publish_odom,
        clock=time.time,
        tf_period_s=0.0,
        odometry=True,
        time_scale=None,
    ):
        """`publish_cloud(copy_name, msg)`, `publish_tf(transforms)`, `publish_odom(copy_name, msg)`;
        `tf_period_s`: keep one recorded odom -> base transform per period of replay time (0: all);
        `odometry`: False leaves odometry out (the twin's cloud path does not read it); `time_scale`:
        {recorded robot: replay seconds per recorded second} (default 1: as recorded)."""
        self.trace, self.copies = trace, copies
        self.tf_period_s, self.odometry = tf_period_s, odometry
        self.time_scale = dict(time_scale or {})
        self.cloud_lateness_s: List[float] = []  # when publish() returned, after the cloud was due
        self.stalls_s: List[float] = []
        self.publish_cloud, self.publish_tf, self.publish_odom = publish_cloud, publish_tf, publish_odom
        self.clock = clock
        self._stop = threading.Event()
        self.sent_clouds = {c.name: 0 for c in copies}
        # the stamps of each copy's first and last cloud sent (s): a copy says nothing of the twin
        # before its first or after its last
        self.first_cloud_stamp_s: Dict[str, float] = {}
        self.last_cloud_stamp_s: Dict[str, float] = {}
        self.dropped_clouds = {c.name: 0 for c in copies}  # publish() raised
        self.publish_errors: List[str] = []

    def static_transforms(self, stamp):
        """Every copy's static tf (map -> odom moved by its placement, its sensor mounts), renamed."""
        out = []
        for c in self.copies:
            for t in self.trace.robots[c.source].tf_static:
                t = copying.deepcopy(t)
                t.header.stamp = stamp
                t.header.frame_id = _rename(t.header.frame_id, c.source, c.name)
                t.child_frame_id = _rename(t.child_frame_id, c.source, c.name)
                if t.child_frame_id == f"{c.name}/odom":
                    t.transform.translation.x += c.offset_xy_m[0]
                    t.transform.translation.y += c.offset_xy_m[1]
                out.append(t)
        return out

    def _events(self, c: Copy):
        """(seconds after the replay's start, kind, message) of one copy, looping the trace (its
        time stretched by the robot's `time_scale`)."""
        robot = self.trace.robots[c.source]
        scale = self.time_scale.get(c.source, 1.0)
        tf, last = [], {}
        for t, m in robot.tf:
            if t * scale - last.get(m.child_frame_id, -math.inf) >= self.tf_period_s:
                last[m.child_frame_id] = t * scale
                tf.append((t * scale, 0, "tf", m))
        odom = [(t * scale, 1, "odom", m) for t, m in robot.odom] if self.odometry else []
        clouds = [(t * scale, 2, "cloud", m) for t, m in robot.clouds]
        events = sorted(tf + odom + clouds, key=lambda e: (e[0], e[1]))
        offset_s = c.time_offset_s * scale
        # At its start a copy first sends each frame's transform nearest its time offset, so that its
        # first clouds find tf (the trace's order resumes after).
        nearest = {}
        for t, _, _, m in tf:
            best = nearest.get(m.child_frame_id)
            if best is None or abs(t - offset_s) < abs(best[0] - offset_s):
                nearest[m.child_frame_id] = (t, m)
        period = max(self.trace.duration_s * scale, 1e-3)
        # by time and kind only (stable: messages recorded at the same instant keep their order; they
        # do not compare, and a recording with two odometry messages of one stamp stopped the replay)
        shifted = sorted(
            (((t - offset_s) % period, order, kind, m) for t, order, kind, m in events), key=lambda e: e[:2]
        )
        for _, m in nearest.values():
            yield 0.0, "tf", m
        loop = 0
        while True:
            for t, _, kind, m in shifted:
                yield loop * period + t, kind, m
            loop += 1

    def run(self, duration_s, stamp_of):
        """Play for `duration_s` of wall time; `stamp_of(wall_s)` makes a header stamp (rospy.Time)."""
        start = self.clock()
        streams = {c.name: self._events(c) for c in self.copies}
        by_name = {c.name: c for c in self.copies}
        heap, count = [], 0  # count: a unique tie-breaker (messages do not compare)
        for name, stream in streams.items():
            t, kind, m = next(stream)
            heapq.heappush(heap, (t, count, name, kind, m))
            count += 1
        while heap and not self._stop.is_set():
            t, _, name, kind, m = heapq.heappop(heap)
            if t > duration_s:
                break
            delay = start + t - self.clock()
            if delay < -STALL_S:
                # The replay stalled (its CPU taken): resume from now rather than send the missed
                # seconds in a burst of old stamps; counted, so that the run can be judged.
                self.stalls_s.append(-delay)
                start -= delay
                delay = 0.0
            if delay > 0 and self._stop.wait(delay):
                break
            if self._send(by_name[name], kind, m, stamp_of(start + t)) and kind == "cloud":
                self.cloud_lateness_s.append(max(0.0, self.clock() - (start + t)))
                self.first_cloud_stamp_s.setdefault(name, start + t)
                self.last_cloud_stamp_s[name] = start + t
            nt, nkind, nm = next(streams[name])
            heapq.heappush(heap, (nt, count, name, nkind, nm))
            count += 1

    def _send(self, c: Copy, kind, msg, stamp):
        """Publish one event of copy `c` (restamped, renamed); False for a cloud whose publish raised."""
        msg = copying.copy(msg)  # a shallow copy: the payload is shared, the header is new
        if kind == "tf":
            msg.header = copying.copy(msg.header)
            msg.header.stamp = stamp
            msg.header.frame_id = _rename(msg.header.frame_id, c.source, c.name)
            msg.child_frame_id = _rename(msg.child_frame_id, c.source, c.name)
            self.publish_tf([msg])
            return True
        msg.header = copying.copy(msg.header)
        msg.header.stamp = stamp
        msg.header.frame_id = _rename(msg.header.frame_id, c.source, c.name)
        if kind == "odom":
            msg.child_frame_id = _rename(msg.child_frame_id, c.source, c.name)
            self.publish_odom(c.name, msg)
            return True
        try:
            self.publish_cloud(c.name, msg)
        except Exception as exc:  # rospy raises ROSException / ROSSerializationException on a closed link
            self.dropped_clouds[c.name] += 1
            if len(self.publish_errors) < 10:
                self.publish_errors.append(f"{c.name}: {type(exc).__name__}: {exc}")
            return False
        self.sent_clouds[c.name] += 1
        return True

    def stop(self):
        self._stop.set()


def profile_time_scales(trace: Trace, fleet: FleetConfig, profile: str) -> Dict[str, float]:
    """{recorded robot: time scale} that plays each robot's clouds at its sensor's rate in `profile`
    (fleet.yaml's profiles): a simulator that could not keep the paper profile's rates on two cores
    recorded its clouds slower; stretching the robot's whole trace (clouds, tf, odometry alike)
    keeps every cloud at the pose it was taken from. TraceError for an unknown profile."""
    try:
        rates = fleet.with_profile(profile).profile
    except KeyError as exc:
        raise TraceError(str(exc)) from exc
    scales = {}
    for name, robot in trace.robots.items():
        recorded_hz = len(robot.clouds) / max(trace.duration_s, 1e-3)
        target_hz = rates.lidar.rate_hz if fleet.robot(name).has_lidar else rates.depth_camera.rate_hz
        scales[name] = recorded_hz / target_hz
    return scales


def build_parser():
    parser = argparse.ArgumentParser(prog="trace_replay", description=__doc__.split("\n\n")[0])
    parser.add_argument("bag", help="a mission bag (cps_bringup ... --record)")
    parser.add_argument("--robots", type=int, required=True, help="how many robots to replay")
    parser.add_argument("--fleet", default=None, help="the fleet file the bag was recorded with")
    parser.add_argument("--duration", type=float, required=True, metavar="S", help="wall seconds to play")
    parser.add_argument("--copies-fleet", required=True, help="write the copies' fleet file here (for the twin)")
    parser.add_argument("--plan-only", action="store_true", help="write the copies' fleet file and exit")
    parser.add_argument(
        "--tf-rate", type=float, default=0.0, metavar="HZ", help="odom -> base transforms per second (0: as recorded)"
    )
    parser.add_argument(
        "--shard",
        default="0/1",
        metavar="I/K",
        help="play only copies I, I+K, I+2K... of the plan (K processes share a large replay)",
    )
    parser.add_argument(
        "--wait-for-subscribers",
        type=float,
        default=0.0,
        metavar="S",
        help="wait up to S seconds for a subscriber on every cloud topic and /tf before playing (as rosbag play's)",
    )
    parser.add_argument(
        "--no-odom", action="store_true", help="leave odometry out (the twin's cloud path needs tf only)"
    )
    parser.add_argument("--step", type=float, default=PLACEMENT_STEP_M, metavar="M", help="placement grid pitch")
    parser.add_argument(
        "--profile-rates",
        default=None,
        metavar="PROFILE",
        help="play each robot's clouds at its sensor's rate in this fleet profile (e.g. paper), the robot's "
        "trace stretched in time (default: as recorded)",
    )
    return parser


def main(argv=None, log=print):
    """The node: plan the copies, write their fleet file, then (unless --plan-only) play them."""
    args = build_parser().parse_args(argv)
    fleet = load_fleet(args.fleet)
    try:
        trace = load_trace(args.bag, fleet)
        copies, note = plan_copies(trace, args.robots, hall_bounds(fleet), args.step)
        shard, shards = (int(x) for x in args.shard.split("/"))
        if not 0 <= shard < shards:
            raise TraceError(f"--shard {args.shard}: I/K with 0 <= I < K")
        time_scale = profile_time_scales(trace, fleet, args.profile_rates) if args.profile_rates else {}
    except TraceError as exc:
        print(f"trace_replay: error: {exc}", file=sys.stderr)
        return 2
    if note:
        log(f"[trace_replay] {note}")
    write_copies_fleet(fleet, copies, args.copies_fleet)
    log(
        f"[trace_replay] {len(copies)} robots from {len(trace.robots)} recorded over {trace.duration_s:.1f} s: "
        + ", ".join(
            f"{c.name}<-{c.source}@({c.offset_xy_m[0]:+g},{c.offset_xy_m[1]:+g}) m,+{c.time_offset_s:.1f} s"
            for c in copies
        )
    )
    if args.plan_only:
        return 0
    copies = copies[shard::shards]
    import rospy
    from nav_msgs.msg import Odometry
    from tf2_msgs.msg import TFMessage

    from cps_msgs.msg import CompressedPointCloud2
    from cps_ros.publisher import Publisher

    # One node name per shard: a second node of the same name would shut the first one down.
    rospy.init_node("trace_replay" if shards == 1 else f"trace_replay_{shard}_of_{shards}", disable_signals=True)
    # queue_size None: synchronous, nothing dropped unseen in a publisher queue (module docstring);
    # rospy warns that it is meant for few publishers, and that is the point here.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SyntaxWarning)
        cloud_pubs = {
            c.name: Publisher(
                names.absolute(names.managed_cloud_at_twin(c.name)), CompressedPointCloud2, queue_size=None
            )
            for c in copies
        }
        tf_pub = Publisher(names.TF, TFMessage, queue_size=None)
    odom_pubs = {
        c.name: Publisher(names.absolute(names.robot_topic(c.name, names.ODOM)), Odometry, queue_size=5) for c in copies
    }
    static_pub = Publisher(names.TF_STATIC, TFMessage, queue_size=1, latch=True)
    player = Player(
        trace,
        copies,
        lambda name, m: cloud_pubs[name].publish(m),
        lambda transforms: tf_pub.publish(TFMessage(transforms=transforms)),
        lambda name, m: odom_pubs[name].publish(m),
        tf_period_s=1.0 / args.tf_rate if args.tf_rate > 0 else 0.0,
        odometry=not args.no_odom,
        time_scale=time_scale,
    )
    if args.wait_for_subscribers > 0:
        deadline = time.monotonic() + args.wait_for_subscribers
        waiting = [*cloud_pubs.values(), tf_pub]
        while waiting and time.monotonic() < deadline:
            waiting = [p for p in waiting if p.get_num_connections() == 0]
            time.sleep(0.05)
        if waiting:
            names_waiting = ", ".join(p.name for p in waiting)
            log(
                f"[trace_replay] no subscriber after {args.wait_for_subscribers:g} s on {names_waiting}; playing anyway"
            )
    static_pub.publish(TFMessage(transforms=player.static_transforms(rospy.Time.from_sec(time.time()))))
    try:
        player.run(args.duration, rospy.Time.from_sec)
    except KeyboardInterrupt:
        pass
    late = sorted(player.cloud_lateness_s) or [0.0]
    summary = dict(
        sent=player.sent_clouds,
        first_cloud_stamp_s=player.first_cloud_stamp_s,
        last_cloud_stamp_s=player.last_cloud_stamp_s,
        dropped=player.dropped_clouds,
        publish_errors=player.publish_errors,
        late_p95_s=late[int(0.95 * (len(late) - 1))],
        late_max_s=late[-1],
        stalls_s=[round(x, 3) for x in player.stalls_s],
    )
    # The replay's own lateness: clouds are stamped when they were due, so a late replay ages the map.
    log(f"[trace_replay] sent clouds: {sum(player.sent_clouds.values())} {json.dumps(summary)}", flush=True)
    rospy.signal_shutdown("done")
    return 0
