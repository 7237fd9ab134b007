"""Draco point-cloud transport for any rospy node, shaped like point_cloud_transport's plugin:
a publisher created on a base topic advertises `<base>/draco` and encodes in `publish(cloud)`;
a subscriber on a base topic listens on `<base>/draco` and hands the user's callback a decoded
sensor_msgs/PointCloud2. Bad clouds and damaged payloads are counted, warned about (throttled)
and reported on /diagnostics (see `cps_ros.diagnostics.DropReporter`); they never raise into rospy."""

import rospy
from rosgraph.names import ns_join

from cps_msgs.msg import CompressedPointCloud2
from cps_ros import cloud_ledger
from cps_ros.diagnostics import DropReporter
from cps_ros.publisher import Publisher
from cps_transport.draco import DracoDecoder, DracoEncoder, DracoError
from cps_transport.pointcloud import InvalidCloud

TRANSPORT_SUFFIX = "draco"


def draco_topic(base_topic):
    """The transport topic of a base topic: `<base>/draco` (resolved in the caller's namespace)."""
    return ns_join(rospy.resolve_name(base_topic), TRANSPORT_SUFFIX)


class DracoPublisher:
    """Advertises `<base>/draco` (cps_msgs/CompressedPointCloud2); `publish(cloud)` encodes a
    sensor_msgs/PointCloud2 with `encoder` and sends it. `topic` overrides the transport topic
    (the encoder node's `~output` remap). A cloud that cannot be encoded is dropped and counted."""

    def __init__(self, base_topic, encoder=None, topic=None, queue_size=2, latch=False, **encoder_args):
        self.base_topic = rospy.resolve_name(base_topic)
        self.topic = rospy.resolve_name(topic) if topic else draco_topic(base_topic)
        self.encoder = encoder if encoder is not None else DracoEncoder(**encoder_args)
        self._publisher = Publisher(self.topic, CompressedPointCloud2, queue_size=queue_size, latch=latch)
        self.report = DropReporter(self.base_topic)

    @property
    def invalid(self):
        return self.report.invalid

    @property
    def published(self):
        return self.report.processed

    def get_num_connections(self):
        return self._publisher.get_num_connections()

    def publish(self, cloud, leaf_size_m=None):
        """Encodes and publishes `cloud` (carrying `leaf_size_m`, the leaf it was voxelized at, if
        given); returns the CompressedPointCloud2, or None when dropped."""
        try:
            compressed = self.encoder.encode(cloud, leaf_size_m=leaf_size_m)
        except (InvalidCloud, DracoError) as exc:
            self.report.drop(exc)
            return None
        except Exception as exc:  # a cloud the checks missed: still one counted drop, not a traceback
            self.report.drop(f"unexpected {type(exc).__name__}: {exc}")
            return None
        self.report.ok(nan_points_dropped=self.encoder.last_info.points_nan)
        self._publisher.publish(compressed)
        return compressed

    def unregister(self):
        self._publisher.unregister()


class DracoSubscriber:
    """Subscribes `<base>/draco` and calls `callback(cloud)` with each decoded
    sensor_msgs/PointCloud2 (header kept). `topic` overrides the transport topic (the decoder
    node subscribes `.../draco/managed`). A payload that cannot be decoded is dropped and counted.
    With `ledger_stage` (cps_ros.cloud_ledger's stage name) each payload is also counted in the
    per-cloud ledger: received, the previous stage's numbers it never got, decoded or dropped."""

    def __init__(
        self, base_topic, callback, decoder=None, topic=None, queue_size=10, buff_size=1 << 22, ledger_stage=None
    ):
        self.topic = rospy.resolve_name(topic) if topic else draco_topic(base_topic)
        self.decoder = decoder if decoder is not None else DracoDecoder()
        self.callback = callback
        self.report = DropReporter(self.topic)
        self.ledger_stage = ledger_stage
        self.sequence = cloud_ledger.SequenceGaps()
        self._subscriber = rospy.Subscriber(
            self.topic, CompressedPointCloud2, self._on_compressed, queue_size=queue_size, buff_size=buff_size
        )

    @property
    def invalid(self):
        return self.report.invalid

    @property
    def received(self):
        return self.report.processed

    def get_num_connections(self):
        return self._subscriber.get_num_connections()

    def _on_compressed(self, msg):
        if self.ledger_stage:
            callerid = getattr(msg, "_connection_header", {}).get("callerid", "")
            self._ledger(cloud_ledger.RECEIVED, missed=self.sequence.note(callerid, msg.header.seq))
        try:
            cloud = self.decoder.decode(msg)
        except (InvalidCloud, DracoError) as exc:
            self.report.drop(exc)
            self._ledger(cloud_ledger.DROPPED + "decoder")
            return
        except Exception as exc:  # a payload the checks missed: still one counted drop, not a traceback
            self.report.drop(f"unexpected {type(exc).__name__}: {exc}")
            self._ledger(cloud_ledger.DROPPED + "decoder")
            return
        self.report.ok()
        self.callback(cloud)
        self._ledger(cloud_ledger.OUT)

    def _ledger(self, what, missed=0):
        """One count of `what` (and `missed` gaps before it) in the ledger, when this subscriber keeps one."""
        if self.ledger_stage:
            counts = {cloud_ledger.key(self.ledger_stage, what): 1}
            if missed:
                counts[cloud_ledger.key(self.ledger_stage, cloud_ledger.MISSED)] = missed
            self.report.count(**counts)

    def unregister(self):
        self._subscriber.unregister()
