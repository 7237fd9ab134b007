"""The tissue's per-robot parts as rospy objects, and every robot's parts in one process.

The one-process-per-node executables (`draco_encoder`, `rate_limiter`, `image_compressor`,
`draco_decoder`) and the shared ones (`cloud_tissue`, `cloud_decoder`) build the same classes
here, so both layouts behave alike topic for topic; the shared ones just make one per robot.
Each robot's parts have their own subscribers (rospy gives each its own thread), encoder, limiter
and drop counters: a malformed cloud of one robot is dropped and counted there and nothing else.
`robot_tissue_configs` (no ROS) says which topics and numbers each robot gets from the fleet file.
"""

import collections
import dataclasses
import math
import struct
import threading
import time
from typing import List, Optional, Tuple

import rospy
from rosgraph.names import ns_join
from sensor_msgs.msg import CompressedImage, Image, PointCloud2
from std_msgs.msg import Float64, UInt8

from cps_fleet import names
from cps_msgs.msg import CompressedPointCloud2, RateLimiterStatus
from cps_msgs.srv import SetRate, SetRateResponse
from cps_ros import cloud_ledger
from cps_ros.diagnostics import DropReporter
from cps_ros.publisher import Publisher
from cps_ros.relay import relay_class, relay_message
from cps_ros.timers import guarded_timer
from cps_transport import host_cpu
from cps_transport.cloud_levels import (
    LeafLedger,
    LeafTracker,
    cloud_level_leaves,
    header_key,
    level_of_leaf,
    nearest_level,
    position_tolerance_m,
    serialized_header_key,
)
from cps_transport.draco import DracoEncoder, carried_leaf_m, leaf_of_compressed
from cps_transport.draco_transport import DracoPublisher, DracoSubscriber
from cps_transport.image_compression import InvalidImage, compress_image, compressed_format
from cps_transport.pointcloud import InvalidCloud, cloud_to_array, xyz_of
from cps_transport.rate_limiter import RateLimiter, WindowRate
from cps_transport.topic_stats import has_header_first

# Clouds waiting for the link per subscriber of the managed topic.
LIMITER_OUTPUT_QUEUE_SIZE = 5
# A level's mean size in the limiter's status: over its last this many forwarded messages.
LEVEL_MEAN_MESSAGES = 10


class LevelCosts:
    """Per level, what the encoder's last LEVEL_MEAN_MESSAGES messages cost the robots' side (CPU
    seconds) and held (points): what the status reports (issue 36). Thread-safe."""

    def __init__(self):
        self._lock = threading.Lock()
        self._costs = collections.defaultdict(lambda: collections.deque(maxlen=LEVEL_MEAN_MESSAGES))

    def add(self, level, cpu_s, points=math.nan):
        with self._lock:
            self._costs[level].append((float(cpu_s), float(points)))

    def mean(self, level):
        """(CPU s, points) per message at `level` (NaN, NaN before its first)."""
        with self._lock:
            costs = list(self._costs.get(level, ()))
        if not costs:
            return math.nan, math.nan
        return sum(c for c, _ in costs) / len(costs), sum(p for _, p in costs) / len(costs)


# How long a level change waits for the voxel grid's dynamic_reconfigure service.
VOXEL_GRID_RECONFIGURE_TIMEOUT_S = 5.0


@dataclasses.dataclass(frozen=True)
class RobotTissueConfig:
    """One robot's topics and numbers in the tissue (docs/ros-graph.md)."""

    robot: str
    filtered: str  # /<r>/points_filtered, the voxel grid's output
    draco: str  # /<r>/points_filtered/draco
    managed: str  # /<r>/points_filtered/draco/managed
    throttle_node: str  # /<r>/cloud_throttle: its status, rate_hz and set_rate
    leaf_size_m: float  # the voxel leaf at start: the cloud level nearest the robot's voxel_leaf_m
    rate_hz: float  # the managed rate until the bandwidth manager sets one
    cloud_levels_m: Tuple[float, ...] = ()  # fleet.yaml streams.cloud_levels' leaves, finest first
    initial_level: int = 0  # the level until the manager publishes one (the leaf above)
    level_topic: Optional[str] = None  # /<r>/cloud_throttle/level (std_msgs/UInt8, from the manager)
    voxel_grid: Optional[str] = None  # /<r>/voxel_grid, whose leaf a level change sets
    map_resolution_m: float = math.inf  # sets Draco's tolerance (cloud_levels.position_tolerance_m)


def _rt(robot, name):
    """A robot's topic, fully qualified: cloud_tissue serves every robot from one node."""
    return names.absolute(names.robot_topic(robot, name))


def robot_tissue_configs(fleet, robots=None, initial_rate_hz=None) -> List[RobotTissueConfig]:
    """The tissue of `robots` (default: the whole fleet), everything from the fleet file (the
    limiters start at `initial_rate_hz`, default the link's min_rate_hz); an unknown robot raises
    KeyError naming the fleet's."""
    from cps_transport.voxel_grid_command import voxel_nodelet_name

    out = []
    leaves = cloud_level_leaves(fleet)
    for name in robots or fleet.robot_names:
        robot = fleet.robot(name)
        level = nearest_level(leaves, robot.voxel_leaf_m)
        out.append(
            RobotTissueConfig(
                robot=name,
                filtered=_rt(name, names.POINTS_FILTERED),
                draco=_rt(name, names.POINTS_DRACO),
                managed=_rt(name, names.POINTS_MANAGED),
                throttle_node=_rt(name, names.CLOUD_THROTTLE),
                leaf_size_m=leaves[level],
                cloud_levels_m=leaves,
                initial_level=level,
                level_topic=_rt(name, names.LIMITER_LEVEL),
                voxel_grid=voxel_nodelet_name(robot),
                map_resolution_m=float(fleet.mapping.resolution_m),
                rate_hz=float(fleet.link.min_rate_hz if initial_rate_hz is None else initial_rate_hz),
            )
        )
    return out


def twin_cloud_topics(robot, backfill):
    """(input, output) pairs the twin's decoder serves for `robot`: the managed cloud as relayed,
    and with `backfill` (Zenoh transport) the keyframes kept during an outage."""
    pairs = [(names.absolute(names.managed_cloud_at_twin(robot)), names.absolute(names.twin_points(robot)))]
    if backfill:
        pairs.append(
            tuple(
                names.absolute(names.in_twin(names.robot_topic(robot, t)))
                for t in (names.POINTS_BACKFILL_DRACO, names.POINTS_BACKFILL)
            )
        )
    return pairs


def parse_robot_list(text):
    """`a,b,c` (or a YAML list) -> names; empty -> None (the whole fleet)."""
    if isinstance(text, (list, tuple)):
        names = [str(n).strip() for n in text]
    else:
        names = [n.strip() for n in str(text or "").split(",")]
    names = [n for n in names if n]
    return names or None


class ManagedRateLimiter:
    """Any message type: `input_topic` -> `output_topic` at the set rate (token bucket), relayed
    without deserializing. `node_name` (e.g. /<r>/cloud_throttle) owns `<node>/set_rate`
    (cps_msgs/SetRate), `<node>/rate_hz` (std_msgs/Float64) and `<node>/status`
    (cps_msgs/RateLimiterStatus, 1 Hz and right after every change). With `cloud_levels_m` (the
    managed cloud's level leaves) the status also gives the level of the clouds it forwards (from
    the leaf each carries) and that level's mean size over its last LEVEL_MEAN_MESSAGES forwarded
    clouds (NaN before the first); a forwarded cloud without a readable level leaf is counted on
    /diagnostics and leaves both as they were. With `ledger` (a LeafLedger its process's encoder
    notes) a cloud this node published is looked up there; only the others are decoded for it."""

    def __init__(
        self,
        input_topic,
        output_topic,
        node_name,
        rate_hz,
        burst=2.0,
        window_s=2.0,
        cloud_levels_m=(),
        level=0,
        ledger: Optional[LeafLedger] = None,
        costs: Optional[LevelCosts] = None,
    ):
        self.limiter = RateLimiter(rate_hz, burst=burst, window_s=window_s)
        self.costs = costs  # the encoder's cost per level (its process's encoder; None: not known)
        self.host_cpu = host_cpu.shared()
        self.node_name = node_name
        self.lock = threading.Lock()
        self.input_topic = input_topic
        self.output_topic = output_topic
        self.publisher = None
        self.relay_cls = None
        # Managed clouds (`cloud_levels_m`, the levels' leaves): the level of each forwarded cloud,
        # read from the leaf it carries, and each level's last sizes.
        self.cloud_levels_m = tuple(cloud_levels_m)
        self.level = int(level)
        self.level_sizes = collections.defaultdict(lambda: collections.deque(maxlen=LEVEL_MEAN_MESSAGES))
        self.level_report = DropReporter(ns_join(node_name, "level")) if self.cloud_levels_m else None
        self.ledger = ledger
        # The per-cloud ledger: what came in (and the encoder's numbers it never got), what went out
        # (numbered by this limiter, so the next stage can count what it misses) and what it held back.
        self.sequence = cloud_ledger.SequenceGaps()
        self.forward_seq = 0
        self.header_first = None
        self.ledger_report = DropReporter(input_topic, name=ns_join(node_name, "ledger"))

        def private(name):
            return ns_join(node_name, name.lstrip("~"))

        self.status_pub = Publisher(private(names.STATUS), RateLimiterStatus, queue_size=5, latch=True)
        self.service = rospy.Service(private(names.SET_RATE), SetRate, self.on_set_rate)
        self.rate_sub = rospy.Subscriber(private(names.RATE_HZ), Float64, lambda msg: self.set_rate(msg.data))
        self.input_sub = rospy.Subscriber(input_topic, rospy.AnyMsg, self.on_message, queue_size=5, buff_size=1 << 24)
        self.status_timer = guarded_timer(1.0, lambda _event: self.publish_status(), f"status {node_name}")
        self.publish_status()

    def set_rate(self, rate_hz):
        """The status is echoed only when the rate changed (issue 36: a setpoint repeated is not news)."""
        try:
            with self.lock:
                before = self.limiter.rate_hz
                self.limiter.set_rate(rate_hz)
                changed = self.limiter.rate_hz != before
        except ValueError as exc:
            rospy.logwarn(f"{self.node_name}: rate not changed: {exc}")
            return False, str(exc)
        if changed:
            self.publish_status()
        return True, f"rate set to {self.limiter.rate_hz} Hz"

    def on_set_rate(self, request):
        success, message = self.set_rate(request.rate_hz)
        return SetRateResponse(success=success, message=message, rate_hz=self.limiter.rate_hz)

    def on_message(self, msg):
        if self.header_first is None:
            self.header_first = has_header_first(msg._connection_header.get("message_definition", ""))
        seq = cloud_ledger.header_seq(msg._buff) if self.header_first else None
        with self.lock:
            missed = 0 if seq is None else self.sequence.note(msg._connection_header.get("callerid", ""), seq)
            forward = self.limiter.allow(time.monotonic(), len(msg._buff))
            if forward and self.publisher is None:
                self.relay_cls = relay_class(msg._connection_header)
                self.publisher = Publisher(self.output_topic, self.relay_cls, queue_size=LIMITER_OUTPUT_QUEUE_SIZE)
            if forward:
                self.forward_seq += 1
                out = relay_message(self.relay_cls, msg)
                if seq is not None:  # numbered as this limiter's output, as a typed publisher would
                    out._buff = cloud_ledger.with_header_seq(msg._buff, self.forward_seq)
        self.ledger_report.count(
            **{
                cloud_ledger.key(cloud_ledger.LIMITER, cloud_ledger.RECEIVED): 1,
                cloud_ledger.key(cloud_ledger.LIMITER, cloud_ledger.MISSED): missed,
                cloud_ledger.key(
                    cloud_ledger.LIMITER, cloud_ledger.OUT if forward else cloud_ledger.DROPPED + "rate_limiter"
                ): 1,
            }
        )
        if forward:
            self.publisher.publish(out)
            if self.cloud_levels_m:
                self._note_level(msg)

    def _note_level(self, msg):
        """The forwarded cloud's level (from its leaf) and size; a status right away on a change."""
        leaf = self._noted_leaf(msg)
        if leaf is None:
            try:
                leaf = leaf_of_compressed(CompressedPointCloud2().deserialize(msg._buff))
            except Exception as exc:  # DracoError, or genpy's DeserializationError for a foreign message
                self.level_report.drop(f"level of a forwarded cloud unreadable: {exc}")
                return
        level = None if leaf is None else level_of_leaf(self.cloud_levels_m, leaf)
        if level is None:
            self.level_report.drop(
                f"forwarded cloud carries leaf {leaf!r} m, not one of the levels {list(self.cloud_levels_m)}"
            )
            return
        self.level_report.ok()
        with self.lock:
            changed = level != self.level
            self.level = level
            self.level_sizes[level].append(len(msg._buff))
        if changed:
            self.publish_status()

    def _noted_leaf(self, msg):
        """The leaf the ledger has for a cloud this node published; None: decode it."""
        if self.ledger is None or msg._connection_header.get("callerid") != rospy.get_name():
            return None
        try:
            return self.ledger.leaf_of(serialized_header_key(msg._buff))
        except struct.error:  # shorter than a header: the decode reports it
            return None

    def publish_status(self):
        now = time.monotonic()
        idle = self.host_cpu.idle_fraction()
        with self.lock:
            cpu_s, points = self.costs.mean(self.level) if self.costs is not None else (math.nan, math.nan)
            status = RateLimiterStatus(
                input_topic=self.input_topic,
                output_topic=self.output_topic,
                set_rate_hz=self.limiter.rate_hz,
                input_rate_hz=self.limiter.input.rate_hz(now),
                output_rate_hz=self.limiter.output.rate_hz(now),
                mean_message_bytes=self.limiter.input.mean_bytes(now),
                received=self.limiter.received,
                forwarded=self.limiter.forwarded,
                level=self.level,
                level_mean_message_bytes=self._level_mean_bytes(),
                level_mean_cpu_s=cpu_s,
                level_mean_points=points,
                host=self.host_cpu.host,
                host_cpus=self.host_cpu.cores,
                host_idle_fraction=idle,
            )
        status.header.stamp = rospy.Time.now()
        self.status_pub.publish(status)

    def _level_mean_bytes(self):
        sizes = self.level_sizes.get(self.level)
        return sum(sizes) / len(sizes) if sizes else math.nan


class ImageCompressor:
    """sensor_msgs/Image (rgb8, bgr8, mono8) -> sensor_msgs/CompressedImage JPEG, only while the
    output has subscribers and at most `max_rate_hz` (0: every image); other encodings and
    malformed images are dropped, counted and reported on /diagnostics.

    For a camera that only gives raw images (the `image_compressor` executable). The fleet's
    managed video is not this: the simulated camera renders and encodes each robot's video at the
    manager's level and rate (cps_sim.video), so the tissue no longer compresses camera images."""

    def __init__(self, input_topic, output_topic, quality=75, max_rate_hz=0.0):
        self.quality = quality
        self.limiter = RateLimiter(max_rate_hz, burst=1.0) if max_rate_hz > 0 else None
        self.report = DropReporter(input_topic)
        self.publisher = Publisher(output_topic, CompressedImage, queue_size=2)
        self.subscriber = rospy.Subscriber(input_topic, Image, self.on_image, queue_size=1, buff_size=1 << 24)

    def on_image(self, msg):
        if self.publisher.get_num_connections() == 0:
            self.report.count(skipped_no_subscriber=1)
            return
        if self.limiter is not None and not self.limiter.allow(rospy.get_time()):
            self.report.count(skipped_rate=1)
            return
        try:
            fmt, data = compress_image(msg.encoding, msg.width, msg.height, msg.step, msg.data, self.quality)
        except InvalidImage as exc:
            self.report.drop(exc)
            return
        self.report.ok(raw_bytes=len(msg.data), compressed_bytes=len(data))
        self.publisher.publish(CompressedImage(header=msg.header, format=fmt, data=data))


class ManagedVideoCompressor:
    """A raw-only camera's managed video: `<robot>/camera/image_raw` (rgb8, bgr8, mono8) ->
    `<robot>/camera/image_raw/compressed` at the level and rate the bandwidth manager sets on
    `<robot>/video_throttle/level` and `rate_hz` (the simulated camera renders at the level instead;
    this is for cameras that cannot be told). A frame is admitted at the set rate first (token
    bucket, one frame of burst), and only then shrunk to the level's size and encoded at its
    quality: nothing is encoded to be dropped. A camera whose aspect ratio is not the level's is
    refused frame by frame (an error, throttled, and counted). Publishes
    `<robot>/video_throttle/status` (1 Hz and on change) like the simulated camera."""

    def __init__(self, robot, streams):
        from cps_transport.video_follower import VideoFollower
        from cps_transport.video_levels import LevelSizes

        def topic(relative):
            return _rt(robot, relative)

        self.robot = robot
        self.lock = threading.Lock()
        self.follower = VideoFollower(robot, streams, self._on_setting, lock=self.lock)
        self.control = self.follower.control
        self.sizes = LevelSizes(streams.video_levels)
        self.cpu_s = LevelSizes(streams.video_levels)  # per level: seconds to shrink, encode and publish a frame
        self.host_cpu = host_cpu.shared()
        self.limiter = RateLimiter(self.control.rate_hz, burst=1.0)
        self.sent_meter = WindowRate()  # frames sent per second
        self.rendered = self.sent = 0
        self.mean_bytes = float("nan")
        self.input_topic, self.output_topic = topic(names.CAMERA_IMAGE), topic(names.CAMERA_IMAGE_COMPRESSED)
        self.report = DropReporter(self.input_topic)
        self.publisher = Publisher(self.output_topic, CompressedImage, queue_size=2)
        self.status_pub = Publisher(topic(names.VIDEO_STATUS), RateLimiterStatus, queue_size=5, latch=True)
        self.subscriber = rospy.Subscriber(self.input_topic, Image, self.on_image, queue_size=1, buff_size=1 << 24)
        self.status_timer = guarded_timer(1.0, lambda _event: self.publish_status(), f"status {robot} video")
        self.publish_status()

    def _on_setting(self, rate_changed):
        if rate_changed:
            with self.lock:
                self.limiter.set_rate(self.control.rate_hz)
        self.publish_status()

    def on_image(self, msg):
        from cps_transport.image_compression import encode_jpeg, image_pixels, resize_pixels
        from cps_transport.video_levels import compressed_image_bytes

        if self.publisher.get_num_connections() == 0:
            self.report.count(skipped_no_subscriber=1)
            return
        now = time.monotonic()
        with self.lock:
            if self.control.off or not self.limiter.allow(now):
                self.report.count(skipped_rate=1)
                return
            index, level = self.control.level_index, self.control.level
        if msg.width * level.height != msg.height * level.width:
            self.report.drop(InvalidImage(f"{msg.width}x{msg.height} has not the aspect ratio of level {level.name}"))
            rospy.logerr_throttle(
                10.0,
                f"{self.input_topic}: {msg.width}x{msg.height} cannot give video level {level.name} (aspect ratio)",
            )
            return
        started = time.thread_time()
        try:
            pixels = resize_pixels(
                image_pixels(msg.encoding, msg.width, msg.height, msg.step, msg.data), level.width, level.height
            )
            data = encode_jpeg(pixels, level.jpeg_quality)
        except InvalidImage as exc:
            self.report.drop(exc)
            return
        out = CompressedImage(header=msg.header, format=compressed_format(msg.encoding), data=data)
        self.publisher.publish(out)
        cpu_s = time.thread_time() - started
        size = compressed_image_bytes(msg.header.frame_id, out.format, len(data))
        self.report.ok(raw_bytes=len(msg.data), compressed_bytes=len(data))
        with self.lock:
            self.rendered += 1
            self.sent += 1
            self.sizes.add(index, size)
            self.cpu_s.add(index, cpu_s)
            self.mean_bytes = size if self.mean_bytes != self.mean_bytes else 0.9 * self.mean_bytes + 0.1 * size
            self.sent_meter.add(now, size)

    def publish_status(self):
        now = time.monotonic()
        idle = self.host_cpu.idle_fraction()
        with self.lock:
            index = self.control.level_index
            status = RateLimiterStatus(
                input_topic=self.input_topic,
                output_topic=self.output_topic,
                set_rate_hz=self.control.set_rate_hz,
                input_rate_hz=self.limiter.input.rate_hz(now),
                output_rate_hz=self.sent_meter.rate_hz(now),
                mean_message_bytes=self.mean_bytes,
                received=self.limiter.received,
                forwarded=self.sent,
                level=index,
                level_mean_message_bytes=self.sizes.mean(index),
                level_mean_cpu_s=self.cpu_s.mean(index),
                level_mean_points=math.nan,
                host=self.host_cpu.host,
                host_cpus=self.host_cpu.cores,
                host_idle_fraction=idle,
            )
        status.header.stamp = rospy.Time.now()
        self.status_pub.publish(status)


class DracoEncoderPart:
    """Subscribes a sensor_msgs/PointCloud2 topic and publishes it Draco-encoded (DracoPublisher:
    bad clouds dropped and counted). With `leaves` (a LeafTracker) each cloud carries the leaf the
    voxel grid produced it at, and Draco's position tolerance is `cloud_levels.position_tolerance_m`
    of that leaf and `map_resolution_m`; with `ledger` too, each cloud's leaf is noted there before
    it is published (for the rate limiter of this process)."""

    def __init__(
        self,
        input_topic,
        output_topic,
        encoder,
        leaves: Optional[LeafTracker] = None,
        map_resolution_m=math.inf,
        ledger: Optional[LeafLedger] = None,
        costs: Optional[LevelCosts] = None,
        levels_m=(),
    ):
        self.publisher = DracoPublisher(input_topic, encoder, topic=output_topic)
        self.leaves = leaves
        self.ledger = ledger
        # With `costs` and the levels' leaves: each cloud's CPU time and points, noted per level.
        self.costs = costs
        self.levels_m = tuple(levels_m)
        self.map_resolution_m = map_resolution_m
        self.lock = threading.Lock()
        self.sequence = cloud_ledger.SequenceGaps()  # the voxel grid's numbers: what this queue lost
        self.subscriber = rospy.Subscriber(input_topic, PointCloud2, self.on_message, queue_size=3, buff_size=1 << 24)

    def on_message(self, cloud):
        """Counts the cloud in the ledger (and the voxel grid's clouds missed before it), then encodes it."""
        callerid = getattr(cloud, "_connection_header", {}).get("callerid", "")
        missed = self.sequence.note(callerid, cloud.header.seq)
        encoded = self.publisher.publish(cloud) if self.leaves is None else self.on_cloud(cloud)
        self.publisher.report.count(
            **{
                cloud_ledger.key(cloud_ledger.ENCODER, cloud_ledger.RECEIVED): 1,
                cloud_ledger.key(cloud_ledger.ENCODER, cloud_ledger.MISSED): missed,
                cloud_ledger.key(
                    cloud_ledger.ENCODER, cloud_ledger.OUT if encoded is not None else cloud_ledger.DROPPED + "encoder"
                ): 1,
            }
        )

    def switch_leaf(self, leaf_m):
        """The voxel grid now produces `leaf_m`: the next clouds carry it (see LeafTracker)."""
        with self.lock:
            self.leaves.switch(leaf_m)

    def on_cloud(self, cloud):
        """Encodes and publishes one cloud at its leaf; the CompressedPointCloud2, or None when dropped."""
        started = time.thread_time()
        with self.lock:
            if self.leaves.switching:
                try:
                    leaf = self.leaves.leaf_of(xyz_of(cloud_to_array(cloud)))
                except InvalidCloud as exc:
                    self.publisher.report.drop(exc)
                    return None
            else:
                leaf = self.leaves.leaf_m
        self.publisher.encoder.position_tolerance_m = position_tolerance_m(leaf, self.map_resolution_m)
        if self.ledger is not None:
            self.ledger.note(header_key(cloud.header), carried_leaf_m(leaf))
        sent = self.publisher.publish(cloud, leaf_size_m=leaf)
        if sent is not None and self.costs is not None:
            level = level_of_leaf(self.levels_m, leaf)
            if level is not None:
                self.costs.add(level, time.thread_time() - started, cloud.width * cloud.height)
        return sent


class CloudLevelSwitch:
    """Follows the manager's level for one robot's cloud: on `level_topic` (std_msgs/UInt8, the
    index into `leaves_m`) sets the voxel grid `voxel_grid`'s leaf through its dynamic_reconfigure
    service (pcl_ros's VoxelGrid takes it between two clouds) and, once it answers with the new
    leaf, tells the encoder (`on_leaf(leaf_m)`). An index past the levels or a voxel grid that does
    not take the leaf is logged and counted on /diagnostics; the previous level stays. The voxel
    grid's latched `parameter_updates` says which leaf it runs at: one that comes up after the level
    was published (the service was not there yet), or comes back at its initial leaf (its manager
    restarted), is given the level then, and the clouds in between carry the leaf it really used."""

    def __init__(self, level_topic, voxel_grid, leaves_m, on_leaf, timeout_s=VOXEL_GRID_RECONFIGURE_TIMEOUT_S):
        from dynamic_reconfigure.msg import Config
        from dynamic_reconfigure.srv import Reconfigure

        self.leaves_m = tuple(leaves_m)
        self.on_leaf = on_leaf
        self.timeout_s = timeout_s
        self.service_name = ns_join(voxel_grid, "set_parameters")
        self.proxy = rospy.ServiceProxy(self.service_name, Reconfigure)
        self.report = DropReporter(level_topic)
        self.wanted = None  # the manager's last valid level
        self.level = None  # the level the voxel grid confirmed
        self.restored = 0
        self.lock = threading.Lock()
        self.subscriber = rospy.Subscriber(level_topic, UInt8, self.on_level, queue_size=1)
        self.updates = rospy.Subscriber(ns_join(voxel_grid, "parameter_updates"), Config, self.on_parameters)

    def on_level(self, msg):
        with self.lock:  # one change at a time, in order
            level = int(msg.data)
            if not 0 <= level < len(self.leaves_m):
                self._failed(f"level {level} is not one of the {len(self.leaves_m)} cloud levels (0 = finest)")
                return
            self.wanted = level
            try:
                self.apply(level)
            except ValueError as exc:
                self._failed(exc)
            else:
                self.report.ok()

    def on_parameters(self, config):
        """The voxel grid's configuration in force: if it is not the wanted level's leaf, set it."""
        leaf = {p.name: p.value for p in config.doubles}.get("leaf_size")
        with self.lock:
            if self.wanted is None or leaf is None or abs(leaf - self.leaves_m[self.wanted]) <= 1e-9:
                return
            rospy.logwarn(
                f"{self.service_name}: the voxel grid runs at {leaf} m, not level {self.wanted}'s "
                f"{self.leaves_m[self.wanted]} m (started late or restarted): setting it"
            )
            if self.level is not None:  # the encoder believed the level's leaf: it is this one
                self.on_leaf(leaf)
                self.level = None
            try:
                self.apply(self.wanted)
            except ValueError as exc:
                self._failed(exc)
            else:
                self.restored += 1

    def _failed(self, reason):
        self.report.drop(reason)
        rospy.logerr_throttle(10.0, f"{self.subscriber.name}: {reason}")

    def apply(self, level):
        from dynamic_reconfigure.msg import Config, DoubleParameter

        if level == self.level:
            return
        leaf = self.leaves_m[level]
        try:
            self.proxy.wait_for_service(timeout=self.timeout_s)
            answer = self.proxy(Config(doubles=[DoubleParameter(name="leaf_size", value=leaf)]))
        except (rospy.ServiceException, rospy.ROSException, OSError) as exc:
            raise ValueError(f"{self.service_name} did not take leaf {leaf} m (level {level}): {exc}") from exc
        taken = {p.name: p.value for p in answer.config.doubles}.get("leaf_size")
        if taken is None or abs(taken - leaf) > 1e-9:
            raise ValueError(f"{self.service_name} answered leaf_size {taken} for {leaf} m (level {level})")
        self.level = level
        self.on_leaf(leaf)
        rospy.loginfo(f"{self.service_name}: cloud level {level}, leaf {leaf} m")


class DracoDecoderPart:
    """Subscribes a cps_msgs/CompressedPointCloud2 topic and publishes the decoded
    sensor_msgs/PointCloud2, header kept (DracoSubscriber: damaged payloads dropped and counted)."""

    def __init__(self, input_topic, output_topic):
        self.publisher = Publisher(output_topic, PointCloud2, queue_size=2)
        self.subscriber = DracoSubscriber(
            None, self.publisher.publish, topic=input_topic, ledger_stage=cloud_ledger.DECODER
        )


class RobotTissue:
    """One robot's cloud tissue on its side: Draco encoder, rate limiter and the cloud level's
    follower, with the same topics, defaults and queue sizes as the single-node executables; the
    encoder tells the limiter each cloud's leaf (a LeafLedger), so the limiter need not decode the
    clouds it forwards to read it. (The camera's JPEG video comes from the camera itself at the
    manager's level and rate: cps_sim.video.)"""

    def __init__(self, config: RobotTissueConfig):
        self.config = config
        levels = bool(config.cloud_levels_m)
        ledger = LeafLedger() if levels else None
        costs = LevelCosts() if levels else None
        self.encoder = DracoEncoderPart(
            config.filtered,
            config.draco,
            DracoEncoder(leaf_size_m=config.leaf_size_m),
            leaves=LeafTracker(config.leaf_size_m) if levels else None,
            map_resolution_m=config.map_resolution_m,
            ledger=ledger,
            costs=costs,
            levels_m=config.cloud_levels_m,
        )
        self.limiter = ManagedRateLimiter(
            config.draco,
            config.managed,
            config.throttle_node,
            config.rate_hz,
            cloud_levels_m=config.cloud_levels_m,
            level=config.initial_level,
            ledger=ledger,
            costs=costs,
        )
        self.levels = (
            CloudLevelSwitch(config.level_topic, config.voxel_grid, config.cloud_levels_m, self.encoder.switch_leaf)
            if levels and config.level_topic and config.voxel_grid
            else None
        )


class CloudTissue:
    """Every robot's RobotTissue in one process (the robots' side of the shared layout)."""

    def __init__(self, configs):
        self.robots = {c.robot: RobotTissue(c) for c in configs}


class CloudDecoders:
    """Every robot's twin-side decoders in one process: managed clouds and (with `backfill`) the
    keyframes sent after an outage."""

    def __init__(self, robots, backfill):
        self.parts = {
            (r, i): DracoDecoderPart(src, dst)
            for r in robots
            for i, (src, dst) in enumerate(twin_cloud_topics(r, backfill))
        }
