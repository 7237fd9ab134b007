"""The tissue's per-robot parts as rospy objects, and every robot's parts in one process.

The one-process-per-node executables (`draco_encoder`, `rate_limiter`, `image_compressor`,
`draco_decoder`) and the shared ones (`cloud_tissue`, `cloud_decoder`) build the same classes
here, so both layouts behave alike topic for topic; the shared ones just make one per robot.
Each robot's parts have their own subscribers (rospy gives each its own thread), encoder, limiter
and drop counters: a malformed cloud of one robot is dropped and counted there and nothing else.
`robot_tissue_configs` (no ROS) says which topics and numbers each robot gets from the fleet file.
"""

import dataclasses
import threading
import time
from typing import List

import rospy
from rosgraph.names import ns_join
from sensor_msgs.msg import CompressedImage, Image, PointCloud2
from std_msgs.msg import Float64, UInt8

from cps_fleet import names
from cps_msgs.msg import RateLimiterStatus
from cps_msgs.srv import SetRate, SetRateResponse
from cps_ros.diagnostics import DropReporter
from cps_ros.relay import relay_class, relay_message
from cps_ros.timers import guarded_timer
from cps_transport.draco import DracoEncoder
from cps_transport.draco_transport import DracoPublisher, DracoSubscriber
from cps_transport.image_compression import InvalidImage, compress_image, compressed_format
from cps_transport.rate_limiter import RateLimiter, WindowRate

# Clouds waiting for the link per subscriber of the managed topic.
LIMITER_OUTPUT_QUEUE_SIZE = 5


@dataclasses.dataclass(frozen=True)
class RobotTissueConfig:
    """One robot's topics and numbers in the tissue (docs/ros-graph.md)."""

    robot: str
    filtered: str  # /<r>/points_filtered, the voxel grid's output
    draco: str  # /<r>/points_filtered/draco
    managed: str  # /<r>/points_filtered/draco/managed
    throttle_node: str  # /<r>/cloud_throttle: its status, rate_hz and set_rate
    leaf_size_m: float  # the voxel leaf: sets Draco's quantization
    rate_hz: float  # the managed rate until the bandwidth manager sets one


def _rt(robot, name):
    """A robot's topic, fully qualified: cloud_tissue serves every robot from one node."""
    return names.absolute(names.robot_topic(robot, name))


def robot_tissue_configs(fleet, robots=None, initial_rate_hz=None) -> List[RobotTissueConfig]:
    """The tissue of `robots` (default: the whole fleet), everything from the fleet file (the
    limiters start at `initial_rate_hz`, default the link's min_rate_hz); an unknown robot raises
    KeyError naming the fleet's."""
    out = []
    for name in robots or fleet.robot_names:
        robot = fleet.robot(name)
        out.append(
            RobotTissueConfig(
                robot=name,
                filtered=_rt(name, names.POINTS_FILTERED),
                draco=_rt(name, names.POINTS_DRACO),
                managed=_rt(name, names.POINTS_MANAGED),
                throttle_node=_rt(name, names.CLOUD_THROTTLE),
                leaf_size_m=float(robot.voxel_leaf_m),
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
    (cps_msgs/RateLimiterStatus, 1 Hz and right after every change)."""

    def __init__(self, input_topic, output_topic, node_name, rate_hz, burst=2.0, window_s=2.0):
        self.limiter = RateLimiter(rate_hz, burst=burst, window_s=window_s)
        self.node_name = node_name
        self.lock = threading.Lock()
        self.input_topic = input_topic
        self.output_topic = output_topic
        self.publisher = None
        self.relay_cls = None

        def private(name):
            return ns_join(node_name, name.lstrip("~"))

        self.status_pub = rospy.Publisher(private(names.STATUS), RateLimiterStatus, queue_size=5, latch=True)
        self.service = rospy.Service(private(names.SET_RATE), SetRate, self.on_set_rate)
        self.rate_sub = rospy.Subscriber(private(names.RATE_HZ), Float64, lambda msg: self.set_rate(msg.data))
        self.input_sub = rospy.Subscriber(input_topic, rospy.AnyMsg, self.on_message, queue_size=5, buff_size=1 << 24)
        self.status_timer = guarded_timer(1.0, lambda _event: self.publish_status(), f"status {node_name}")
        self.publish_status()

    def set_rate(self, rate_hz):
        try:
            with self.lock:
                self.limiter.set_rate(rate_hz)
        except ValueError as exc:
            rospy.logwarn(f"{self.node_name}: rate not changed: {exc}")
            return False, str(exc)
        self.publish_status()
        return True, f"rate set to {self.limiter.rate_hz} Hz"

    def on_set_rate(self, request):
        success, message = self.set_rate(request.rate_hz)
        return SetRateResponse(success=success, message=message, rate_hz=self.limiter.rate_hz)

    def on_message(self, msg):
        with self.lock:
            forward = self.limiter.allow(time.monotonic(), len(msg._buff))
            if forward and self.publisher is None:
                self.relay_cls = relay_class(msg._connection_header)
                self.publisher = rospy.Publisher(
                    self.output_topic, self.relay_cls, queue_size=LIMITER_OUTPUT_QUEUE_SIZE
                )
        if forward:
            self.publisher.publish(relay_message(self.relay_cls, msg))

    def publish_status(self):
        now = time.monotonic()
        with self.lock:
            status = RateLimiterStatus(
                input_topic=self.input_topic,
                output_topic=self.output_topic,
                set_rate_hz=self.limiter.rate_hz,
                input_rate_hz=self.limiter.input.rate_hz(now),
                output_rate_hz=self.limiter.output.rate_hz(now),
                mean_message_bytes=self.limiter.input.mean_bytes(now),
                received=self.limiter.received,
                forwarded=self.limiter.forwarded,
            )
        status.header.stamp = rospy.Time.now()
        self.status_pub.publish(status)


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
        self.publisher = rospy.Publisher(output_topic, CompressedImage, queue_size=2)
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
        from cps_transport.video_levels import LevelSizes, VideoControl

        def topic(relative):
            return _rt(robot, relative)

        self.robot = robot
        self.lock = threading.Lock()
        self.control = VideoControl(streams)
        self.sizes = LevelSizes(streams.video_levels)
        self.limiter = RateLimiter(self.control.rate_hz, burst=1.0)
        self.sent_meter = WindowRate()  # frames sent per second
        self.rendered = self.sent = 0
        self.mean_bytes = float("nan")
        self.input_topic, self.output_topic = topic(names.CAMERA_IMAGE), topic(names.CAMERA_IMAGE_COMPRESSED)
        self.level_topic, self.rate_topic = topic(names.VIDEO_LEVEL), topic(names.VIDEO_RATE_HZ)
        self.report = DropReporter(self.input_topic)
        self.publisher = rospy.Publisher(self.output_topic, CompressedImage, queue_size=2)
        self.status_pub = rospy.Publisher(topic(names.VIDEO_STATUS), RateLimiterStatus, queue_size=5, latch=True)
        self.level_sub = rospy.Subscriber(self.level_topic, UInt8, self._on_level, queue_size=5)
        self.rate_sub = rospy.Subscriber(self.rate_topic, Float64, self._on_rate, queue_size=5)
        self.subscriber = rospy.Subscriber(self.input_topic, Image, self.on_image, queue_size=1, buff_size=1 << 24)
        self.status_timer = guarded_timer(1.0, lambda _event: self.publish_status(), f"status {robot} video")
        self.publish_status()

    def _on_level(self, msg):
        with self.lock:
            error = self.control.set_level(msg.data)
        if error:
            rospy.logerr(f"{self.level_topic}: {error}")
            return
        self.publish_status()

    def _on_rate(self, msg):
        with self.lock:
            error, note = self.control.set_rate(msg.data)
            if not error:
                self.limiter.set_rate(self.control.rate_hz)
        if error:
            rospy.logerr(f"{self.rate_topic}: {error}")
            return
        if note:
            rospy.logwarn_throttle(10.0, f"{self.rate_topic}: {note}")
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
        size = compressed_image_bytes(msg.header.frame_id, out.format, len(data))
        self.report.ok(raw_bytes=len(msg.data), compressed_bytes=len(data))
        with self.lock:
            self.rendered += 1
            self.sent += 1
            self.sizes.add(index, size)
            self.mean_bytes = size if self.mean_bytes != self.mean_bytes else 0.9 * self.mean_bytes + 0.1 * size
            self.sent_meter.add(now, size)

    def publish_status(self):
        now = time.monotonic()
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
            )
        status.header.stamp = rospy.Time.now()
        self.status_pub.publish(status)


class DracoEncoderPart:
    """Subscribes a sensor_msgs/PointCloud2 topic and publishes it Draco-encoded (DracoPublisher:
    bad clouds dropped and counted)."""

    def __init__(self, input_topic, output_topic, encoder):
        self.publisher = DracoPublisher(input_topic, encoder, topic=output_topic)
        self.subscriber = rospy.Subscriber(
            input_topic, PointCloud2, self.publisher.publish, queue_size=3, buff_size=1 << 24
        )


class DracoDecoderPart:
    """Subscribes a cps_msgs/CompressedPointCloud2 topic and publishes the decoded
    sensor_msgs/PointCloud2, header kept (DracoSubscriber: damaged payloads dropped and counted)."""

    def __init__(self, input_topic, output_topic):
        self.publisher = rospy.Publisher(output_topic, PointCloud2, queue_size=2)
        self.subscriber = DracoSubscriber(None, self.publisher.publish, topic=input_topic)


class RobotTissue:
    """One robot's cloud tissue on its side: Draco encoder and rate limiter, with the same topics,
    defaults and queue sizes as the single-node executables. (The camera's JPEG video comes from
    the camera itself at the manager's level and rate: cps_sim.video.)"""

    def __init__(self, config: RobotTissueConfig):
        self.config = config
        self.encoder = DracoEncoderPart(config.filtered, config.draco, DracoEncoder(leaf_size_m=config.leaf_size_m))
        self.limiter = ManagedRateLimiter(config.draco, config.managed, config.throttle_node, config.rate_hz)


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
