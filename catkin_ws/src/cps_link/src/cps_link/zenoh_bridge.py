"""One side's bridge between its ROS graph and the Zenoh session to the other side.

Outgoing topics (bridge.yaml, `from` this side) are read as rospy.AnyMsg and put on Zenoh
unchanged with their class's priority, congestion control and reliability; incoming frames are
checked (CRC, type and md5 against this side's message definitions, duplicates, stale stamps for
classes with max_age_s, and that the frame is for the topic whose route received it, in that topic's
one type: cps_link.receive_path), then republished under the contract's names. Latched topics keep every
source's last message for late subscribers and are re-sent when the link comes back. Liveliness
tokens tell each side within a lease whether the other is there: /tissue/link_state.
"""

import dataclasses
import io
import math
import threading
import time

import roslib.message
import rospy

from cps_fleet import names
from cps_link.backfill import Keyframe, KeyframeStore, Pacer, unused_bytes_per_s
from cps_link.bridge_config import ROBOTS, TWIN, BridgeTable, Route, other_side
from cps_link.bridge_wire import Frame, WireError, encode, header_frame_id, header_stamp, header_stamp_s
from cps_link.link_health import LinkHealth
from cps_link.link_report import (
    LinkSockets,
    ReportComposer,
    RoundTrips,
    SenderReport,
    socket_full_bytes,
)
from cps_link.probe_train import TrainArrivals, TrainSchedule
from cps_link.receive_path import (
    PUBLISHER_TYPE_MISMATCH,
    SEND_TOPIC_TYPE_MISMATCH,
    TOPIC_TYPE_MISMATCH,
    ReceivePath,
    SendPath,
)
from cps_link.route_ledger import RouteLedger, is_cloud_route
from cps_link.send_queue import DROP_RULES, EXPIRED, SUPERSEDED, SendQueue
from cps_msgs.msg import LinkReport, LinkState
from cps_ros import cloud_ledger
from cps_ros.diagnostics import DropReporter
from cps_ros.priority import thread_cpu_and_wait_s
from cps_ros.publisher import Publisher

LINK_STATE_PERIOD_S = 1.0
# How long to stay quiet before saying the other side has not come up yet, s.
NOT_UP_WARN_AFTER_S = 5.0
# rospy subscriber queues: the data class keeps only the newest message (fresh first).
QUEUE_SIZE = {"data": 1, "backfill": 50}
# How long a new publisher of a never-dropped topic waits for the subscribers the master knows of
# before its first message (rospy drops what is published before a subscriber has connected).
SUBSCRIBER_WAIT_S = 2.0
DEFAULT_QUEUE_SIZE = 20
# The backfill's token bucket: at most this much in one go, bytes; its send loop's period, s.
BACKFILL_BURST_BYTES = 300_000
BACKFILL_POLL_S = 0.02
# How far back the robots' bridge keeps transforms for keyframe poses, s.
TF_CACHE_S = 60.0
# A keyframe may take the newest transform when it is at most this far from its capture, s.
POSE_TOLERANCE_S = 0.1
# The transforms the robots' bridge forwards anyway; it keeps them for keyframe poses (one
# subscription per topic and process in rospy: a tf2 listener beside the AnyMsg one would clash).
TF_TOPICS = {names.TF: False, names.TF_STATIC: True}
# The sender thread looks at its queue at least this often, s (a new frame wakes it at once).
SENDER_POLL_S = 0.2
# The robots' bridge looks this often whether a probe train is due, s (cps_link.probe_train).
PROBE_POLL_S = 0.05
# The host's bound on a TCP socket's unsent bytes (cps_link.netns_link.UNSENT_SYSCTL).
UNSENT_SYSCTL_PATH = "/proc/sys/net/ipv4/tcp_notsent_lowat"


def zenoh_qos_priority(name):
    import zenoh

    return getattr(zenoh.Priority, name.upper())


def zenoh_congestion(name):
    import zenoh

    return getattr(zenoh.CongestionControl, name.upper())


def zenoh_qos(traffic):
    """The declare_publisher keyword arguments of a traffic class."""
    import zenoh

    return {
        "priority": zenoh_qos_priority(traffic.priority),
        "congestion_control": zenoh_congestion(traffic.congestion),
        "reliability": zenoh.Reliability.RELIABLE if traffic.reliable else zenoh.Reliability.BEST_EFFORT,
        "express": traffic.express,
    }


def keyframe_pose(tf_buffer, map_frame, cloud_body):
    """geometry_msgs/TransformStamped map <- the cloud's frame at its capture, stamped exactly as the
    cloud's header (secs, nsecs): the twin pairs a keyframe with its pose by (frame, stamp in ns)
    (cps_mapping.admission_process.BackfillPoses). The newest transform if the cloud is a few ms
    ahead of the tf it is captured with (tf arrives after the cloud).

    Stamped through a float of seconds, as before (rospy.Time.from_sec), the pose's stamp missed the
    cloud's by up to ~0.1 us in all of a demo's 36 keyframes: the twin found no pose for any of
    them and placed each with its own /tf at the stamp, interpolated across the outage's gaps where
    no /tf had crossed: most of them metres off the robot's path. Their hits stood in free space (issue 39: the
    baseline's ever-hit voxels in columns no robot passed, which hid new items from the never-hit
    rule)."""
    frame = header_frame_id(cloud_body)
    stamp = rospy.Time(*header_stamp(cloud_body))
    try:
        pose = tf_buffer.lookup_transform(map_frame, frame, stamp)
    except Exception:  # tf2's extrapolation: look at the newest one
        pose = tf_buffer.lookup_transform(map_frame, frame, rospy.Time(0))
        if abs((pose.header.stamp - stamp).to_sec()) > POSE_TOLERANCE_S:
            raise
    pose.header.stamp = stamp
    return pose


class _LatchedReplay(rospy.SubscribeListener):
    """Sends every source's last message of a latched topic to each new subscriber."""

    def __init__(self):
        self.messages = {}
        self.lock = threading.Lock()

    def peer_subscribe(self, topic_name, topic_publish, peer_publish):
        with self.lock:
            stored = list(self.messages.values())
        for msg in stored:
            peer_publish(msg)


@dataclasses.dataclass
class _Declared:
    """What the bridge declared on one Zenoh session, closed with it. Its puts count a failure
    (the session closed under them while it is reopened) instead of raising."""

    session: object
    pubs: dict = dataclasses.field(default_factory=dict)  # outgoing route's `to` -> publisher
    subs: list = dataclasses.field(default_factory=list)
    token: object = None
    heartbeat_pub: object = None
    heartbeat_matching: object = None  # the listener of whether the peer subscribes to our heartbeats
    report_pub: object = None
    probe_pub: object = None
    echo_pubs: dict = dataclasses.field(default_factory=dict)  # key -> publisher

    def put(self, to, payload, reporter):
        """Put on route `to`'s publisher; False (counted) when Zenoh refused it."""
        return self._put(self.pubs[to], payload, reporter, to)

    def put_own(self, kind, payload, reporter):
        """Put on the bridge's own publisher of `kind` (heartbeat, link report, probe train)."""
        pub = {"heartbeat": self.heartbeat_pub, "link report": self.report_pub, "probe train": self.probe_pub}[kind]
        return self._put(pub, payload, reporter, kind)

    def echo(self, key, payload, reporter):
        """Send a heartbeat straight back on `key` (declared on first use)."""
        try:
            if key not in self.echo_pubs:
                self.echo_pubs[key] = self.session.declare_publisher(
                    key,
                    priority=zenoh_qos_priority("real_time"),
                    express=True,
                    congestion_control=zenoh_congestion("drop"),
                )
        except Exception as exc:  # zenoh's ZError on a closed session
            reporter.drop(f"heartbeat echo: {exc}")
            return False
        return self._put(self.echo_pubs[key], payload, reporter, "heartbeat echo")

    @staticmethod
    def _put(pub, payload, reporter, what):
        try:
            pub.put(payload)
            return True
        except Exception as exc:  # zenoh's ZError on a closed session
            reporter.drop(f"{what}: put failed: {exc}")
            return False


class ZenohBridge:
    """Carries `table`'s topics between this side's ROS master and `session` (an open Zenoh session);
    `session_factory()` opens another when that one carries one way only (None: never reopened)."""

    def __init__(
        self, table: BridgeTable, side, session, name, endpoint="", backfill_store_bytes=None, session_factory=None
    ):
        self.table, self.side, self.name = table, side, name
        self.peer_side = other_side(side)
        self.endpoint = endpoint
        self.lock = threading.Lock()
        self.latched_frames = {}
        self.classes = {}
        self.send_path = SendPath(table_types={r.to: r.msg_type for r in table.outgoing(side) if r.msg_type})
        self.session_id = self.send_path.session
        self.receive_path = ReceivePath(table.incoming(side), table.key_prefix, self._md5_of)
        self.started_s = time.time()
        self.health = LinkHealth(started_s=self.started_s)
        self.reporter = DropReporter("zenoh_bridge_command" if table.lane == "command" else "zenoh_bridge")

        # The per-cloud ledger of this side's cloud routes (cps_link.route_ledger).
        def ledger_reporter(topic):  # a status of its own name: the bridge's own status stays one per node
            return DropReporter(topic, name=rospy.get_name() + "/ledger")

        self.sent_ledger = RouteLedger(
            [r for r in table.outgoing(side) if r.from_ros and is_cloud_route(r)],
            cloud_ledger.BRIDGE_OUT,
            ledger_reporter,
        )
        self.received_ledger = RouteLedger(
            [r for r in table.incoming(side) if is_cloud_route(r)], cloud_ledger.BRIDGE_IN, ledger_reporter
        )
        self.link_pub = (
            Publisher(names.LINK_STATE, LinkState, queue_size=5, latch=True) if table.publishes_link_state else None
        )
        self.store = None
        if side == ROBOTS and table.backfill and backfill_store_bytes:
            self._start_backfill(backfill_store_bytes)
        # The link report (cps_link.link_report): the robots' main lane queues, paces and counts
        # what it sends and measures round trips; the twin's counts what it receives.
        self.main_lane = table.publishes_link_state
        self.queue = (
            SendQueue(table.paced_ranks, time.monotonic(), on_drop=self._queue_dropped)
            if side == ROBOTS and self.main_lane
            else None
        )
        self.round_trips = RoundTrips() if self.queue is not None else None
        self.composer = ReportComposer() if side == TWIN and self.main_lane else None
        # probe trains while the fleet sends too little to fill the link (cps_link.probe_train)
        self.trains = TrainSchedule() if self.queue is not None else None
        self.train_arrivals = (
            TrainArrivals(on_refused=self.composer.train_refused) if self.composer is not None else None
        )
        self._probe_lock_wait_s = 0.0  # the probe callback's waits for self.lock, cumulative
        self._probe_sent_bytes = 0
        self._send_queue_max, self._report_seq, self._closing = 0, 0, False
        self._blocked_s = 0.0  # the sender thread's time inside Zenoh's put since the last report
        # this process's own link socket (Zenoh's): TCP_INFO for the bytes the link carried and its RTT
        port = table.endpoint_port
        self.link_sockets = (
            LinkSockets(
                **({"remote_port": port} if self.queue is not None else {"local_port": port}),
                user_timeout_ms=table.tcp_user_timeout_ms,
            )
            if self.main_lane
            else None
        )
        self._tcp_rtts = []  # the robots' link socket's smoothed RTT at each heartbeat since the last report
        self._socket_samples = [0, 0]  # heartbeat samples of the link socket since the last report, of them full
        self._socket_full_bytes = socket_full_bytes(table)
        self.publishers, self.replays, self.ros_subs = {}, {}, []
        self._publisher_ready = {}  # route.to -> Event: its publisher's subscribers connected (or waited for)
        # Every typed topic this side republishes is advertised before its first frame, its
        # subscribers awaited all at once beside the Zenoh session's start. Made on each route's
        # first frame, a restarted twin bridge had each robot's first cloud wait for the map server
        # to connect, one robot after another in Zenoh's callback (issue 38's kills: 3.5-6.4 s to a
        # fresh map, the robots fresh one after another).
        threading.Thread(target=self._advertise, name="advertise", daemon=True).start()
        self.session_factory = session_factory
        self._reopening = False
        self.z = self._declare(session)
        for route in table.outgoing(side):
            if not route.from_ros:
                continue
            self.ros_subs.append(
                rospy.Subscriber(
                    route.topic,
                    rospy.AnyMsg,
                    self._send,
                    callback_args=route,
                    queue_size=QUEUE_SIZE.get(route.traffic.name, DEFAULT_QUEUE_SIZE),
                    buff_size=2**24,
                    tcp_nodelay=True,
                )
            )
        self.report_timer = self.link_report_pub = None
        if self.queue is not None:
            threading.Thread(target=self._sender_loop, name="sender", daemon=True).start()
            threading.Thread(target=self._probe_loop, name="probe", daemon=True).start()
            self.report_timer = rospy.Timer(rospy.Duration(table.report_ms / 1000.0), self._report)
        if self.composer is not None:
            self.link_report_pub = Publisher(names.LINK_REPORT, LinkReport, queue_size=10)
        if self.main_lane:
            _warn_unsent_limit(table.kernel_unsent_bytes)
        self._publish_link_state()
        self.timer = rospy.Timer(rospy.Duration(LINK_STATE_PERIOD_S), self._tick)
        self.heartbeat_timer = rospy.Timer(rospy.Duration(table.heartbeat_ms / 1000.0), self._heartbeat)

    def _declare(self, session):
        """Declare on `session` everything this bridge carries: one _Declared, closed together."""
        table, side = self.table, self.side
        z = _Declared(session=session)
        for route in table.incoming(side):
            z.subs.append(
                session.declare_subscriber(
                    route.key(table.key_prefix), lambda sample, r=route: self._receive(sample, r)
                )
            )
        for route in table.outgoing(side):
            z.pubs[route.to] = session.declare_publisher(route.key(table.key_prefix), **zenoh_qos(route.traffic))
        z.token = session.liveliness().declare_token(table.liveliness_key(side, self.name))
        z.subs.append(
            session.liveliness().declare_subscriber(table.peer_liveliness_keys(side), self._on_liveliness, history=True)
        )
        z.heartbeat_pub = session.declare_publisher(
            table.heartbeat_key(side, self.name),
            priority=zenoh_qos_priority("real_time"),
            express=True,
            congestion_control=zenoh_congestion("drop"),
        )
        z.heartbeat_matching = z.heartbeat_pub.declare_matching_listener(self._on_heartbeat_matching)
        z.subs.append(session.declare_subscriber(table.peer_heartbeat_keys(side), self._on_heartbeat))
        if self.queue is not None:
            z.subs.append(session.declare_subscriber(table.echo_key(self.name), self._on_echo))
            # real_time, with the heartbeats: on interactive_high, behind the telemetry, Zenoh dropped
            # reports for 2.7 s after a 20 -> 5 Mbit/s step (its queue congested), just when they count
            z.report_pub = session.declare_publisher(
                table.report_key(self.name),
                priority=zenoh_qos_priority("real_time"),
                express=True,
                congestion_control=zenoh_congestion("drop"),
            )
            # the lowest priority: every data frame goes first; blocked, not dropped, so a train
            # is whole (its own thread waits, not the data's sender)
            z.probe_pub = session.declare_publisher(
                table.probe_key(self.name),
                priority=zenoh_qos_priority("background"),
                congestion_control=zenoh_congestion("block"),
            )
        if self.composer is not None:
            z.subs.append(session.declare_subscriber(table.report_keys(), self._on_report))
            z.subs.append(session.declare_subscriber(table.probe_keys(), self._on_probe))
        return z

    # --- the session: reopened when it carries one way only ----------------------------------
    def _watch_session(self, now_s):
        """Reopen the session (on a thread of its own) when it carries the other side's way only.
        Three rules, the first that holds:
        - orphaned (bridge.yaml orphan_after_ms, any lane, either side): the peer is heard but the
          session lists no transport to it. Zenoh 1.10.2's close of the transport from before an
          outage can finish after the new one to the same peer opened (the old link's close waits
          on the cut link; the restore lets it finish) and then removes the new one from its
          transport manager by the peer's id: what arrives is still delivered, what this side puts
          finds no transport (the Zenoh debug log of a stalled restore, cps_link README).
        - unheard (unheard_after_ms, the robots' main lane, whose heartbeats the twin echoes): the
          twin is heard but has echoed none of this side's heartbeats since the link came up; sooner
          than the twin's deaf rule for the same stall, so that one side reopens.
        - deaf (reopen_after_ms): the other side's token is there and its transport is talking, but
          its heartbeats do not come. The transport talks while the link socket receives bytes
          without a gap of a heartbeat timeout (its keep-alives at least), and the silence counts
          from when it began to: in a cut the robots' bridge keeps the twin's token until the link
          is back and hears nothing, and at the restore its socket talks before the twin's
          heartbeats come. A lane without a link socket read (the command lane) leaves it to the
          twin's side, which drops a cut peer's token within the lease."""
        if self.session_factory is None or self._reopening:
            return
        after_s = self.table.reopen_after_ms / 1000.0
        gap_s = self.table.heartbeat_timeout_ms / 1000.0
        with self.lock:
            orphaned = self.health.orphaned(now_s, self.table.orphan_after_ms / 1000.0)
            if self.link_sockets is not None:
                since_s = self.health.socket_talking(now_s, gap_s)  # a restore: heartbeats have had no time yet
            else:
                since_s = -math.inf if self.side == TWIN else None
            # None: the transport is not talking (a cut), or a robots' lane without a socket read
            talking = since_s is not None
            deaf = self.health.deaf(now_s, after_s, since_s) if talking else []
            unheard = (
                talking
                and self.round_trips is not None
                and self.health.unheard(now_s, self.table.unheard_after_ms / 1000.0)
            )
        if orphaned:
            why = (
                f"{self.peer_side} bridge is heard but the Zenoh session has listed no transport to it "
                f"for {self.table.orphan_after_ms} ms"
            )
        elif unheard:
            why = f"{self.peer_side} bridge is heard but echoed none of this side's heartbeats for {self.table.unheard_after_ms} ms"
        elif deaf:
            why = (
                f"{self.peer_side} bridge {', '.join(map(repr, deaf))} holds its liveliness token but sent "
                f"no heartbeat for {self.table.reopen_after_ms} ms"
            )
        else:
            return
        self._reopening = True
        threading.Thread(target=self._reopen, args=(why,), name="reopen", daemon=True).start()

    def _reopen(self, why):
        rospy.logwarn(f"{rospy.get_name()}: {why}: reopening the Zenoh session")
        old = self.z
        try:
            old.session.close()
        except Exception as exc:  # zenoh's ZError: the old session is dropped either way
            rospy.logwarn(f"{rospy.get_name()}: closing the Zenoh session: {exc}")
        if self.link_sockets is not None:
            # an orphaned transport is not the session's to close: its connection, left open, is
            # ended here. After the close, not before: a peer whose connection ended while the old
            # session still listened reconnected to it and stayed with its orphaned transport.
            with self.lock:
                ended = self.link_sockets.end_connections()
            if ended:
                rospy.logwarn(f"{rospy.get_name()}: ended {ended} link connection(s) the closed session left open")
        with self.lock:
            down = self.health.session_closed(time.time())
        self._link_changed(False, down, "", "this side reopens its session")
        self.reporter.count(sessions_reopened=1)
        delay_s = self.table.heartbeat_ms / 1000.0
        while not rospy.is_shutdown() and not self._closing:
            try:
                self.z = self._declare(self.session_factory())
                break
            except Exception as exc:  # the port not yet free, a bad certificate: said, tried again
                rospy.logwarn_throttle(5.0, f"{rospy.get_name()}: reopening the Zenoh session: {exc}; trying again")
                time.sleep(delay_s)
                delay_s = min(2 * delay_s, self.table.retry_max_ms / 1000.0)
        self._reopening = False

    # --- outgoing ---------------------------------------------------------------------------
    def _message_class(self, msg_type):
        if msg_type not in self.classes:
            try:
                self.classes[msg_type] = roslib.message.get_message_class(msg_type)
            except Exception:  # a type name roslib cannot even parse: not a type of this side
                self.classes[msg_type] = None
        return self.classes[msg_type]

    def _md5_of(self, msg_type):
        cls = self._message_class(msg_type)
        return cls._md5sum if cls is not None else None

    def frame_of(self, route: Route, msg):
        """The frame of one rospy.AnyMsg received on `route` (next sequence number of its source), or
        None (counted) when it is not of the type the route's topic has."""
        header = getattr(msg, "_connection_header", None) or {}
        msg_type, md5 = header.get("type", ""), header.get("md5sum", "")
        source = header.get("callerid", "")
        cls = self._message_class(msg_type)
        stamp = float("nan")
        if cls is not None and cls._has_header:
            try:
                stamp = header_stamp_s(msg._buff)
            except WireError:
                pass
        frame = self.send_path.frame(route.to, source, msg_type, md5, stamp, msg._buff)
        if frame is None:
            self.reporter.count(**{SEND_TOPIC_TYPE_MISMATCH: 1})
            self.reporter.drop(f"{route.topic}: {msg_type} from {source} is not the topic's type")
        return (route.to, source), frame

    def _keep_transforms(self, topic, body):
        from tf2_msgs.msg import TFMessage

        static = TF_TOPICS[topic]
        for transform in TFMessage().deserialize(body).transforms:
            if static:
                self.tf_buffer.set_transform_static(transform, "zenoh_bridge")
            else:
                self.tf_buffer.set_transform(transform, "zenoh_bridge")

    def _send(self, msg, route: Route):
        if self.store is not None and route.topic in TF_TOPICS:
            self._keep_transforms(route.topic, msg._buff)
        if route.to in self.sent_ledger:
            self.sent_ledger.received(
                route.to,
                (getattr(msg, "_connection_header", None) or {}).get("callerid", ""),
                cloud_ledger.header_seq(msg._buff),
            )
        key, frame = self.frame_of(route, msg)
        if frame is None:
            self.sent_ledger.dropped(route.to, "type")
            return
        if self.store is not None and not self._carries() and route.to in self.backfill_robot:
            kept = self._keep_keyframe(self.backfill_robot[route.to], frame)
            if kept:
                self.sent_ledger.count(route.to, cloud_ledger.BACKFILL_KEPT)
            else:
                self.sent_ledger.dropped(route.to, "outage")
            return
        payload = encode(frame)
        if route.latched:
            with self.lock:
                self.latched_frames[key] = payload
        if self.queue is not None and route.traffic.paced:
            self._queue_frame(route, frame, payload)
            return
        self._put_now(route.to, payload)
        self.reporter.count(sent=1, sent_bytes=len(payload))
        self.sent_ledger.out(route.to)

    def _put_now(self, to, payload):
        """Put a frame that does not wait (charged to the pacer: the pace covers every byte)."""
        if not self.z.put(to, payload, self.reporter):
            return
        if self.queue is not None:
            self.queue.urgent(len(payload), time.monotonic())

    def _queue_frame(self, route, frame, payload):
        """A paced frame joins the send queue for what is left of its class's max_age_s (by its
        header stamp: the time it took to get here counts)."""
        max_age = route.traffic.max_age_s
        if max_age is not None and math.isfinite(frame.stamp_s):
            max_age -= max(0.0, time.time() - frame.stamp_s)
        self.queue.offer(
            route.traffic.name, (route.to, frame.source), len(payload), (route.to, payload), time.monotonic(), max_age
        )

    def _sender_loop(self):
        """The one thread that hands paced frames to Zenoh, as the queue and its pacer let them go.
        Their classes block in Zenoh when its queue is full, so the backlog stays in ours."""
        q = self.queue
        while not rospy.is_shutdown() and not self._closing:
            with q.cond:
                item, wait = q.take(time.monotonic())
                if item is None:
                    q.cond.wait(SENDER_POLL_S if wait is None else min(wait, SENDER_POLL_S))
                    continue
            to, payload = item
            started = time.monotonic()
            put = self.z.put(to, payload, self.reporter)
            with self.lock:
                self._blocked_s += time.monotonic() - started
            if not put:
                continue
            q.sent(len(payload))
            self.reporter.count(sent=1, sent_bytes=len(payload))
            self.sent_ledger.out(to)

    def _queue_dropped(self, rule, item):
        """The send queue dropped a frame by `rule`: a cloud's is counted in its route's ledger."""
        to, _payload = item
        self.sent_ledger.dropped(to, rule)

    def resend_latched(self):
        """Put every latched topic's last message again (the far side drops what it already has)."""
        with self.lock:
            frames = [(to, payload) for (to, _), payload in self.latched_frames.items()]
        for to, payload in frames:
            self._put_now(to, payload)

    # --- incoming ---------------------------------------------------------------------------
    def _receive(self, sample, route: Route):
        try:
            payload = sample.payload.to_bytes()
            if self.composer is not None:
                with self.lock:
                    self.composer.received(len(payload), route.managed)
            self.deliver(route, payload, str(sample.key_expr))
        except Exception as exc:  # a zenoh callback must never die
            self.reporter.drop(f"{route.to}: {exc}")

    def deliver(self, route: Route, payload, key=None):
        """Check one frame received by `route`'s subscriber (under `key`) and republish it; returns
        the kind of drop (counted in the diagnostics), or None when published."""
        verdict = self.receive_path.receive(route.to, key, payload, time.time())
        if route.to in self.received_ledger:
            frame = verdict.frame
            self.received_ledger.received(
                route.to, None if frame is None else (frame.source, frame.session), None if frame is None else frame.seq
            )
        if verdict.drop is not None:
            if verdict.drop not in ("duplicates", "stale"):
                self.reporter.drop(f"{route.to}: {verdict.drop}: {verdict.detail}")
            self.reporter.gauge(**self.receive_path.counters())
            self.received_ledger.dropped(route.to, verdict.drop)
            return verdict.drop
        frame = verdict.frame
        cls = self._message_class(frame.msg_type)
        pub = self._publisher(route, cls)
        if (pub.type, pub.md5sum) != (frame.msg_type, frame.md5):  # never: the receive path keeps one type
            self.reporter.count(**{PUBLISHER_TYPE_MISMATCH: 1})
            self.reporter.drop(f"{route.to}: {frame.msg_type} for a publisher of {pub.type}")
            return TOPIC_TYPE_MISMATCH
        if self.queue is not None and route.to == names.absolute(names.ALLOCATION):
            self._on_allocation(cls().deserialize(frame.body))
        msg = rospy.AnyMsg()
        msg._buff = self.received_ledger.renumbered(route.to, frame.body)
        if route.latched:
            replay = self.replays[route.to]
            with replay.lock:
                replay.messages[frame.source] = msg
        pub.publish(msg)
        self.reporter.ok(received_bytes=len(frame.body))
        self.received_ledger.out(route.to)
        return None

    def _publisher(self, route, cls):
        """`route`'s publisher, made if it has none yet; returns once its subscribers are connected
        (those of a never-dropped topic, up to SUBSCRIBER_WAIT_S)."""
        pub, new = self._make_publisher(route, cls)
        if new:
            self._await_subscribers([(route, pub)])
        else:
            self._publisher_ready[route.to].wait(SUBSCRIBER_WAIT_S)
        return pub

    def _make_publisher(self, route, cls):
        """(`route`'s publisher, True if made now)."""
        with self.lock:
            pub = self.publishers.get(route.to)
            if pub is not None:
                return pub, False
            listener = None
            if route.latched:
                listener = self.replays[route.to] = _LatchedReplay()
            self._publisher_ready[route.to] = threading.Event()
            pub = self.publishers[route.to] = Publisher(
                route.to,
                cls,
                queue_size=QUEUE_SIZE.get(route.traffic.name, DEFAULT_QUEUE_SIZE),
                subscriber_listener=listener,
                tcp_nodelay=True,
            )
            return pub, True

    def _advertise(self):
        """Make the publisher of every route whose type the table names (the managed streams first)
        and wait for their subscribers together."""
        routes = sorted((r for r in self.table.incoming(self.side) if r.msg_type), key=lambda r: not r.managed)
        made = []
        for route in routes:
            cls = self._message_class(route.msg_type)
            if cls is None or rospy.is_shutdown():
                continue
            try:
                pub, new = self._make_publisher(route, cls)
            except Exception as exc:  # a node shutting down: a first frame makes the rest, as before
                rospy.logdebug(f"{rospy.get_name()}: advertising {route.to}: {exc}")
                break
            if new:
                made.append((route, pub))
        self._await_subscribers(made)

    def _await_subscribers(self, made):
        """Wait (up to SUBSCRIBER_WAIT_S) until each publisher of a never-dropped topic in `made`
        [(route, publisher)] is connected to every subscriber of its topic the master knows (rospy
        drops what is published before a subscriber has connected), then mark each ready."""
        waiting = []
        for route, pub in made:
            if route.traffic.congestion == "block" and not route.latched:
                waiting.append((route, pub))
            else:
                self._publisher_ready[route.to].set()
        if not waiting:
            return
        expected = _subscriber_counts()
        deadline = time.monotonic() + SUBSCRIBER_WAIT_S
        while waiting and not rospy.is_shutdown():
            still = []
            for route, pub in waiting:
                if pub.get_num_connections() >= expected.get(route.to, 0):
                    self._publisher_ready[route.to].set()
                else:
                    still.append((route, pub))
            waiting = still
            if waiting and time.monotonic() >= deadline:
                break
            if waiting:
                time.sleep(0.01)
        for route, _ in waiting:
            self._publisher_ready[route.to].set()

    # --- backfill (robots' side) --------------------------------------------------------------
    def _start_backfill(self, capacity_bytes):
        import tf2_ros  # tf2's buffer alone: see TF_TOPICS

        backfill = self.table.backfill
        self.store = KeyframeStore(capacity_bytes, backfill.keyframe_period_s)
        self.pacer = Pacer(BACKFILL_BURST_BYTES, time.monotonic())
        self.backfill_robot = {to: robot for robot, to in backfill.source.items()}
        self.tf_buffer = tf2_ros.Buffer(rospy.Duration(TF_CACHE_S))
        missing = [t for t in TF_TOPICS if t not in {r.topic for r in self.table.outgoing(ROBOTS)}]
        if missing:
            rospy.logwarn(f"{rospy.get_name()}: {', '.join(missing)} do not cross; keyframes may lack poses")
        threading.Thread(target=self._backfill_loop, name="backfill", daemon=True).start()

    def _keep_keyframe(self, robot, cloud: Frame):
        """Keep a cloud captured during an outage as a keyframe, with its sensor's pose in the map;
        True when the store kept it."""
        from geometry_msgs.msg import TransformStamped

        if not self.store.wants(robot, cloud.stamp_s):
            return False
        try:
            pose = keyframe_pose(self.tf_buffer, self.table.backfill.map_frame, cloud.body)
        except Exception as exc:  # tf2's exceptions and a cloud without a header
            self.reporter.count(backfill_no_pose=1)
            rospy.logwarn_throttle(5.0, f"{rospy.get_name()}: keyframe of {robot} without a pose: {exc}")
            return False
        backfill = self.table.backfill
        pose_route = self.table.route(backfill.pose_to[robot])
        cloud_route = self.table.route(backfill.cloud_to[robot])
        pose_msg = rospy.AnyMsg()
        buff = io.BytesIO()
        pose.serialize(buff)
        pose_msg._buff = buff.getvalue()
        pose_msg._connection_header = {
            "type": TransformStamped._type,
            "md5sum": TransformStamped._md5sum,
            "callerid": rospy.get_name(),
        }
        cloud_msg = rospy.AnyMsg()
        cloud_msg._buff = cloud.body
        cloud_msg._connection_header = {"type": cloud.msg_type, "md5sum": cloud.md5, "callerid": cloud.source}
        frames = [self.frame_of(r, m)[1] for r, m in ((pose_route, pose_msg), (cloud_route, cloud_msg))]
        if None in frames:  # counted by frame_of
            return False
        payloads = tuple(encode(f) for f in frames)
        return self.store.offer(Keyframe(robot, cloud.stamp_s, payloads))

    def _on_allocation(self, allocation):
        """The manager's allocation: the send queue paces at its pacing rate (its estimate of the
        link: every byte counts; below the capacity it allocates from while a queue drains), else
        at that capacity; the backfill at what it leaves unused."""
        now = time.monotonic()
        with self.lock:
            self.trains.set_capacity(allocation.available_mbps)
        pacing = allocation.pacing_mbps
        mbps = pacing if math.isfinite(pacing) and pacing > 0 else allocation.available_mbps
        self.queue.set_rate(mbps * 1e6 / 8.0 if math.isfinite(mbps) and mbps > 0 else None, now)
        if self.store is not None:
            self.pacer.set_rate(
                unused_bytes_per_s(allocation.budget_mbytes_per_s, allocation.allocated_mbytes_per_s), now
            )

    def _backfill_loop(self):
        backfill = self.table.backfill
        while not rospy.is_shutdown():
            time.sleep(BACKFILL_POLL_S)
            keyframe = self.store.peek() if self._carries() else None
            if keyframe is None or not self.pacer.take(keyframe.size_bytes, time.monotonic()):
                continue
            keyframe = self.store.pop()
            for to, payload in zip(
                (backfill.pose_to[keyframe.robot], backfill.cloud_to[keyframe.robot]), keyframe.payloads
            ):
                self._put_now(to, payload)
            self.reporter.count(backfill_sent=1, backfill_sent_bytes=keyframe.size_bytes)
            self.sent_ledger.count(backfill.source[keyframe.robot], cloud_ledger.BACKFILL_SENT)

    def backfill_counters(self):
        s = self.store
        return (
            {
                "backfill_kept": s.kept,
                "backfill_evicted": s.evicted,
                "backfill_refused": s.refused,
                "backfill_stored": len(s),
                "backfill_stored_bytes": s.bytes,
            }
            if s
            else {}
        )

    # --- link health ------------------------------------------------------------------------
    def _on_liveliness(self, sample):
        import zenoh

        peer = str(sample.key_expr).rsplit("/", 1)[-1]
        with self.lock:
            if sample.kind == zenoh.SampleKind.PUT:
                up = self.health.token_put(peer, time.time())
                down = False
            else:
                up, down = False, self.health.token_deleted(peer, time.time())
        self._link_changed(up, down, peer, "its liveliness token")

    def _on_heartbeat(self, sample):
        peer = str(sample.key_expr).rsplit("/", 1)[-1]
        if self.composer is not None:
            # the robots' heartbeat goes straight back: their round trip over the link
            payload = sample.payload.to_bytes()
            self.z.echo(self.table.echo_key(peer), payload, self.reporter)
            with self.lock:
                self.composer.received(len(payload), managed=False)
        now_s = time.time()
        with self.lock:
            up = self.health.heard(peer, now_s)
            after_token_s = self.health.first_heartbeat_after_token(peer, now_s)
        if after_token_s is not None:
            rospy.loginfo(
                f"{rospy.get_name()}: {self.peer_side} bridge '{peer}': its first heartbeat "
                f"{after_token_s * 1000:.0f} ms after its token"
            )
        self._link_changed(up, False, peer, "its heartbeat")

    def _on_heartbeat_matching(self, status):
        """Zenoh's own view of whether the peer subscribes to this side's heartbeats: a transport
        whose peer's declarations were lost sends nothing while both sides hold each other's token."""
        rospy.loginfo(
            f"{rospy.get_name()}: the {self.peer_side} side "
            f"{'subscribes' if status.matching else 'no longer subscribes'} to this side's heartbeats"
        )

    def _on_echo(self, sample):
        with self.lock:
            self.round_trips.echo(sample.payload.to_bytes(), time.monotonic_ns())
            first_after_s = self.health.echoed(time.time())
        if first_after_s is not None:
            rospy.loginfo(
                f"{rospy.get_name()}: the {self.peer_side} bridge hears this side: its first echo "
                f"{first_after_s * 1000:.0f} ms after the link came up"
            )

    def _carries(self):
        """The link carries this side's messages: up, and where the twin echoes this side's
        heartbeats, heard back since (a session that carries only the twin's way does not: a
        keyframe sent into it is lost, one kept waits for the reopen)."""
        with self.lock:
            return self.health.heard_back() if self.round_trips is not None else self.health.up

    def _heartbeat(self, _event=None):
        if self.round_trips is not None:
            with self.lock:
                payload = self.round_trips.heartbeat(time.monotonic_ns())
            self._put_heartbeat(payload)
            with self.lock:
                infos = self.link_sockets.read()
                self._send_queue_max = max([self._send_queue_max, *(i.send_queue_bytes for i in infos)])
                self._tcp_rtts += [i.rtt_us * 1e-6 for i in infos if i.rtt_us > 0]
                if infos:
                    self._socket_samples[0] += 1
                    self._socket_samples[1] += any(i.notsent_bytes >= self._socket_full_bytes for i in infos)
        else:
            self._put_heartbeat(b"")
        if self.composer is not None:
            with self.lock:
                sizes = [i.receive_queue_bytes for i in self.link_sockets.read()]
                self.composer.sample_receive_queue(max(sizes) if sizes else None)
        listed = self._transports_listed()
        now_s = time.time()
        with self.lock:
            if listed is not None:
                self.health.transports_listed(listed, now_s)
            if self.link_sockets is not None:
                received = self.link_sockets.totals()["bytes_received"]
                self.health.socket_bytes(received, now_s, self.table.heartbeat_timeout_ms / 1000.0)
                refused = self.link_sockets.user_timeout_refused
            down = self.health.expire(now_s, self.table.heartbeat_timeout_ms / 1000.0)
        self._link_changed(False, down, "", f"no heartbeat for {self.table.heartbeat_timeout_ms} ms")
        if self.link_sockets is not None and refused:
            rospy.logwarn_once(
                f"{rospy.get_name()}: the kernel refused TCP_USER_TIMEOUT on the link socket: a cut connection "
                "lingers until Zenoh's own close (bridge.yaml tcp_user_timeout_ms)"
            )
        self._watch_session(now_s)

    def _transports_listed(self):
        """How many transports to peers the Zenoh session lists (None: closed under a reopen)."""
        try:
            return len(list(self.z.session.info.peers_zid()))
        except Exception:  # zenoh's ZError: the session closed while it is reopened
            return None

    def _put_heartbeat(self, payload):
        self.z.put_own("heartbeat", payload, self.reporter)
        if self.queue is not None:
            self.queue.urgent(len(payload), time.monotonic())

    # --- the link report (cps_link.link_report) ----------------------------------------------
    def _report(self, _event=None):
        """The robots' side: its cumulative counters, round trips and queue since the last report."""
        with self.lock:
            echoes = self.round_trips.take()
            # the kernel's smoothed RTT of the link socket (no Python scheduling in it) where it is
            # readable, else the heartbeat echoes
            rtts, self._tcp_rtts = (self._tcp_rtts or echoes), []
            read = self.link_sockets.read()
            link = self.link_sockets.totals()
            queue_max, self._send_queue_max = self._send_queue_max, 0
            (samples, full), self._socket_samples = self._socket_samples, [0, 0]
            blocked_s, self._blocked_s = self._blocked_s, 0.0
            self._report_seq += 1
            seq = self._report_seq
        # The report is of the instant its socket counters were read (the interval's acked bytes
        # are over it); the frames' counters are taken next to it. Stamped before taking the
        # bridge's lock it was 12-19 ms early (median), up to 38 ms (live, test_over_link): up to
        # 7 % of a 0.5 s interval's rate, moved from one interval to the next.
        now = self.link_sockets.read_s if read else time.monotonic()
        counters = self.queue.snapshot()
        rate = self.queue.pacer.rate
        report = SenderReport(
            session=self.session_id.hex(),
            seq=seq,
            t_s=now,
            offered_bytes=counters.offered_bytes,
            sent_bytes=counters.sent_bytes,
            superseded=counters.dropped[SUPERSEDED],
            expired=counters.dropped[EXPIRED],
            app_limited=self.queue.app_limited_since_last(now),
            rtt_s=rtts,
            blocked_s=blocked_s,
            link_sent_bytes=link["bytes_new"],
            link_acked_bytes=link["bytes_acked"],
            socket_samples=samples,
            socket_full_samples=full,
            link_sockets=self.link_sockets.sockets_found,
            send_queue_max_bytes=queue_max,
            pacing_mbps=rate * 8e-6 if rate else 0.0,
            peer=self.name,
            probe_sent_bytes=self._probe_sent_bytes,
            probe_cost_mbps=self.trains.cost_mbps(),
        )
        with self.lock:
            self.trains.note_interval(report.app_limited, samples, full)
        payload = report.encode()
        self.z.put_own("link report", payload, self.reporter)
        self.queue.urgent(len(payload), now)
        self.reporter.gauge(
            **{f"queue_{rule}": counters.dropped[rule] for rule in DROP_RULES},
            **{f"queue_{rule}_bytes": counters.dropped_bytes[rule] for rule in DROP_RULES},
            queue_waiting=self.queue.waiting()[0],
            pacing_mbps=round(rate * 8e-6, 3) if rate else 0.0,
        )

    def _on_report(self, sample):
        """The twin's side: one robots' report closes an interval of what arrived; publish it."""
        try:
            payload = sample.payload.to_bytes()
            with self.lock:
                self.composer.received(len(payload), managed=False)
                self.link_sockets.read()
                received = self.link_sockets.totals()["bytes_received"]
                closed_s = time.monotonic()
                self.train_arrivals.expire(closed_s)
                interval, _ = self.composer.on_report(payload, closed_s, received, self.link_sockets.sockets_found)
                refused = dict(self.composer.refused)
            self.reporter.gauge(**{f"report_{why}": n for why, n in refused.items()})
            if interval is not None:
                self.link_report_pub.publish(link_report_msg(interval, time.monotonic() - closed_s))
        except Exception as exc:  # a zenoh callback must never die
            self.reporter.drop(f"link report: {exc}")

    # --- probe trains (cps_link.probe_train) ---------------------------------------------------
    def _probe_loop(self):
        """The robots' side: a train when one is due (app-limited, link up, its period passed)."""
        while not rospy.is_shutdown() and not self._closing:
            time.sleep(PROBE_POLL_S)
            with self.lock:
                plan = self.trains.start(time.monotonic()) if self.trains.due(time.monotonic()) else None
            if plan is not None:
                self._send_train(plan)

    def _send_train(self, plan):
        """Put the train's messages at its pace (its own thread: a blocked put holds no data)."""
        sent = 0
        for index in range(plan.count):
            if index:
                wait = plan.started_s + plan.due_s(index) - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            payload = plan.message(index, time.monotonic())
            started, wait_before = time.monotonic(), thread_cpu_and_wait_s()[1]
            put = self.z.put_own("probe train", payload, self.reporter)
            wait_after = thread_cpu_and_wait_s()[1]  # the put's time waiting for a CPU is not the link's
            plan.put_took(
                time.monotonic() - started, 0.0 if None in (wait_before, wait_after) else wait_after - wait_before
            )
            if not put:
                break
            sent += len(payload)
            with self.lock:
                self._probe_sent_bytes += len(payload)
        self.reporter.count(probe_trains_sent=1, probe_sent_bytes=sent)

    def _on_probe(self, sample):
        """The twin's side: one probe message, timed with the link's bytes received then."""
        try:
            payload = sample.payload.to_bytes()
            asked_s = time.monotonic()
            with self.lock:
                self._probe_lock_wait_s += time.monotonic() - asked_s
                self.composer.received(len(payload), managed=False, probe=True)
                read = self.link_sockets.read()
                if read:
                    totals = self.link_sockets.totals()
                    now, link_bytes, out_of_order = (
                        self.link_sockets.read_s,
                        totals["bytes_received"],
                        totals["rcv_ooopack"],
                    )
                    idle_s = min(i.last_data_recv_ms for i in read) * 1e-3
                else:  # no TCP_INFO: the frames this bridge received
                    now, link_bytes, idle_s, out_of_order = time.monotonic(), self.composer.delivered_bytes, 0.0, 0
                # how late this thread's reads may be: its waits for a CPU and for the lock
                cpu_wait_s = thread_cpu_and_wait_s()[1]
                wait_s = math.nan if cpu_wait_s is None else cpu_wait_s + self._probe_lock_wait_s
                measure = self.train_arrivals.arrival(payload, now, link_bytes, idle_s, wait_s, out_of_order)
                if measure is not None:
                    self.composer.train_measured(measure)
                refused = dict(self.train_arrivals.refused)
                measured = self.train_arrivals.measured
            self.reporter.gauge(probe_trains_measured=measured, **{f"probe_{why}": n for why, n in refused.items()})
        except Exception as exc:  # a zenoh callback must never die
            self.reporter.drop(f"probe train: {exc}")

    def _link_changed(self, up, down, peer, why):
        if self.queue is not None and (up or down):
            self.queue.set_link_up(self.health.up)
            with self.lock:
                self.trains.link_up = self.health.up
        if up:
            rospy.loginfo(f"{rospy.get_name()}: link up: {self.peer_side} bridge '{peer}' is there ({why})")
            self.resend_latched()
            threading.Timer(0.5, self.resend_latched).start()
        if down:
            rospy.logwarn(
                f"{rospy.get_name()}: link down: {self.peer_side} bridge {peer and repr(peer) + ' '}"
                f"is gone ({why}; outage {self.health.outages})"
            )
        if up or down:
            self._publish_link_state()

    def _tick(self, _event=None):
        self.reporter.gauge(**self.backfill_counters(), **self.receive_path.counters())
        if self.store is not None:
            for robot, to in self.table.backfill.source.items():
                self.sent_ledger.gauge(
                    to,
                    **{
                        cloud_ledger.BACKFILL_EVICTED: self.store.evicted_of(robot),
                        cloud_ledger.BACKFILL_WAITING: self.store.waiting_of(robot),
                    },
                )
        if self.health.up:
            # A latched message lost on its way (its class may drop, or the far side's subscriber
            # was not there yet) is otherwise never sent again: a map server without /tf_static
            # inserts nothing. The far side drops the copies it already has.
            self.resend_latched()
        if not self.health.ever_up and time.time() - self.started_s > NOT_UP_WARN_AFTER_S:
            rospy.logwarn_throttle(
                10.0,
                f"{rospy.get_name()}: no {self.peer_side} bridge has come up yet "
                f"({self.endpoint or 'listening'}); still trying",
            )
        self._publish_link_state()

    def link_state(self):
        h = self.health
        return LinkState(
            up=h.up,
            since=rospy.Time.from_sec(h.since_s),
            outages=h.outages,
            last_outage_s=h.last_outage_s,
            peer=",".join(sorted(h.peers)) or self.peer_side,
        )

    def _publish_link_state(self):
        if self.link_pub is None:
            return
        msg = self.link_state()
        msg.header.stamp = rospy.Time.from_sec(time.time())
        self.link_pub.publish(msg)

    def close(self):
        """Stop the timers and ROS subscriptions, take the token back and close the session (once)."""
        with self.lock:
            if self._closing:
                return
            self._closing = True
        self.timer.shutdown()
        self.heartbeat_timer.shutdown()
        if self.report_timer is not None:
            self.report_timer.shutdown()
        for sub in self.ros_subs:
            sub.unregister()
        z = self.z
        for step in (z.token.undeclare, z.session.close):
            try:
                step()
            except Exception as exc:  # zenoh's ZError: closed already, by a reopen under way
                rospy.logdebug(f"{rospy.get_name()}: closing: {exc}")


def _subscriber_counts():
    """Topic -> how many subscribers the master knows of ({} without a master)."""
    import rosgraph

    try:
        _, subscribers, _ = rosgraph.Master(rospy.get_name()).getSystemState()
    except Exception:  # no master: nothing to wait for
        return {}
    return {name: len(nodes) for name, nodes in subscribers}


def link_report_msg(interval, closed_s_ago=0.0) -> LinkReport:
    """cps_msgs/LinkReport of one cps_link.link_report.Interval, stamped when it closed
    (`closed_s_ago` s before now): on the same clock reading as its interval_s, so that two reports'
    stamps are as far apart as the second's interval says. Stamped at publishing, a report whose
    publishing waited (the bridge's lock, its CPU) came within a quarter interval of the next one's
    stamp, and the manager refused the next as a repeat (live beside busy loops, 1 of 4 runs)."""
    msg = LinkReport(
        seq=interval.seq,
        interval_s=interval.interval_s,
        sender_interval_s=interval.sender_interval_s,
        delivered_bytes=interval.delivered_bytes,
        unmanaged_bytes=interval.unmanaged_bytes,
        sent_bytes=interval.sent_bytes,
        offered_bytes=interval.offered_bytes,
        app_limited=interval.app_limited,
        rtt_s=list(interval.rtt_s),
        receiver_behind=interval.receiver_behind,
        sender_blocked_s=interval.sender_blocked_s,
        delivered_link_bytes=interval.delivered_link_bytes,
        sent_link_bytes=interval.sent_link_bytes,
        acked_link_bytes=interval.acked_link_bytes,
        sender_socket_full=interval.sender_socket_full,
        receive_queue_max_bytes=min(interval.receive_queue_max_bytes, 2**32 - 1),
        send_queue_max_bytes=min(interval.send_queue_max_bytes, 2**32 - 1),
        superseded=min(interval.superseded, 2**32 - 1),
        expired=min(interval.expired, 2**32 - 1),
        pacing_mbps=interval.pacing_mbps,
        peer=interval.peer,
        probe_bytes=interval.probe_bytes,
        probe_sent_bytes=interval.probe_sent_bytes,
        probe_trains=interval.probe_trains,
        probe_train_bytes=interval.probe_train_bytes,
        probe_train_spread_s=interval.probe_train_spread_s,
        probe_train_sent_mbps=interval.probe_train_sent_mbps,
        probe_train_receiver_wait_s=interval.probe_train_receiver_wait_s,
        probe_cost_mbps=interval.probe_cost_mbps,
        probe_refused=interval.probe_refused,
    )
    msg.header.stamp = rospy.Time.now() - rospy.Duration.from_sec(max(0.0, closed_s_ago))
    return msg


def _warn_unsent_limit(wanted_bytes):
    """Warn when this host lets more than bridge.yaml's kernel_unsent_bytes wait in a TCP socket:
    a queue there is beyond the bridge's send queue and its drop rules (issue 35)."""
    if not wanted_bytes:
        return
    try:
        with open(UNSENT_SYSCTL_PATH) as stream:
            have = int(stream.read().strip())
    except (OSError, ValueError):
        return
    if have > wanted_bytes:
        rospy.logwarn(
            f"{rospy.get_name()}: this host lets {have} unsent bytes wait in a TCP socket; the bridge table "
            f"asks for {wanted_bytes} (sysctl -w net.ipv4.tcp_notsent_lowat={wanted_bytes}): a slow link will "
            "hold a queue the bridge cannot see or drop from"
        )
