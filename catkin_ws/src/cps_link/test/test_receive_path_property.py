"""Property test of the bridge's frame paths (issue 22), ROS-free: a robots' side sender (SendPath)
and the twin's ReceivePath driven through random interleavings of link cuts and returns, latched
re-sends, backfill, live frames of several robots and sources, duplicates, misrouted samples
(a frame at another route's subscriber, under that route's key or its own), a restarted sender
(new session), frames of another type, and corrupt or truncated payloads.

Every message published is on the topic it was sent for, with that topic's type; nothing is
published twice within a session; every drop is counted with its kind, and the kind says why;
an intact, in-order, fresh frame of the sender's current run that reaches its own route is
published (the checks do not over-drop)."""

import collections
import math
import struct

import roslib.message
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cps_fleet import names
from cps_link.bridge_config import load_bridge_table
from cps_link.bridge_wire import decode, encode, is_stale, new_session_id
from cps_link.receive_path import DROP_KINDS, SESSION_HOLD_S, WIRE_KINDS, ReceivePath, SendPath

ROBOTS = ("scout", "jackal")
TABLE = load_bridge_table(robots=ROBOTS)
TOPICS = (
    names.TF,
    names.absolute(names.robot_topic("scout", names.ODOM)),
    names.absolute(names.robot_topic("jackal", names.ODOM)),
    names.absolute(names.robot_topic("scout", names.CONTROL_MODE_ACTIVE)),
    names.absolute(names.robot_topic("jackal", names.MISSION_STATE)),
    names.absolute(names.managed_cloud_at_twin("scout")),
    names.absolute(names.robot_topic("scout", names.CAMERA_INFO)),
)
BACKFILL = {
    "scout": (
        names.absolute(names.in_twin(names.robot_topic("scout", names.POINTS_BACKFILL_POSE))),
        names.absolute(names.in_twin(names.robot_topic("scout", names.POINTS_BACKFILL_DRACO))),
    )
}
ROUTES = {r.to: r for r in TABLE.incoming("twin")}
SOURCES = ("/fleet_sim", "/robot_state_publisher")
# A type that is a real type of this side but no topic's below (an intruder's or a stray publisher's).
OTHER_TYPES = ("std_msgs/Bool", "sensor_msgs/JointState")
T0_S = 1_700_000_000.0
# What the robots' bridge seeds its SendPath with (zenoh_bridge does the same).
SEND_TYPES = {r.to: r.msg_type for r in TABLE.outgoing("robots") if r.msg_type}


def md5_of(msg_type):
    try:
        cls = roslib.message.get_message_class(msg_type)
    except Exception:
        return None
    return cls._md5sum if cls is not None else None


def _key(to):
    return ROUTES[to].key(TABLE.key_prefix)


class World:
    """The sender, the link, what is in flight, and what the receiver published or dropped."""

    def __init__(self):
        self.now_s = T0_S
        self.run_ns = 1
        self.sender = SendPath(new_session_id(self.run_ns), SEND_TYPES)
        self.up = True
        self.in_flight = []  # (route it is for, payload)
        self.latched = {}  # (topic, source) -> payload, re-sent when the link returns
        self.backfill = []
        self.receiver = ReceivePath(TABLE.incoming("twin"), TABLE.key_prefix, md5_of)
        self.truth = {}  # body -> (topic, type) it was sent as
        self.published = set()  # (session, topic, source, seq)
        self.max_seq = {}  # (session, topic, source) -> highest seq published
        self.newest = {}  # (topic, source) -> (session, when) of the newest run published
        self.drops = collections.Counter()
        self.next_id = 0

    def _body(self, topic, msg_type):
        self.next_id += 1
        body = struct.pack("<III", 0, int(self.now_s), int((self.now_s % 1) * 1e9)) + struct.pack("<Q", self.next_id)
        self.truth[body] = (topic, msg_type)
        return body

    def send(self, topic, source, msg_type=None):
        msg_type = msg_type or ROUTES[topic].msg_type
        frame = self.sender.frame(topic, source, msg_type, md5_of(msg_type), self.now_s, self._body(topic, msg_type))
        if frame is None:  # the sender refused a second type: never on the wire
            assert msg_type != ROUTES[topic].msg_type
            return
        payload = encode(frame)
        if ROUTES[topic].latched:
            self.latched[(topic, source)] = payload
        if self.up:
            self.in_flight.append((topic, payload))
        elif topic == names.absolute(names.managed_cloud_at_twin("scout")):
            # A keyframe: its pose, then the cloud, on the backfill routes.
            for to, msg_type in zip(BACKFILL["scout"], ("geometry_msgs/TransformStamped", ROUTES[topic].msg_type)):
                f = self.sender.frame(
                    to, "/zenoh_bridge_robots", msg_type, md5_of(msg_type), self.now_s, self._body(to, msg_type)
                )
                self.backfill.append((to, encode(f)))

    def restore(self):
        self.up = True
        self.in_flight += [(topic, p) for (topic, _), p in self.latched.items()]
        self.in_flight += self.backfill
        self.backfill = []

    def restart_sender(self):
        """A new run of the robots' bridge: new session; ROS latched publishers hand it their last."""
        self.run_ns += 1
        self.sender = SendPath(new_session_id(self.run_ns), SEND_TYPES)
        old = list(self.latched)
        self.latched = {}
        for topic, source in old:
            self.send(topic, source)

    def deliver(self, route_to, key, payload, expect=None):
        """One sample at route_to's subscriber; checks the verdict against what was sent."""
        verdict = self.receiver.receive(route_to, key, payload, self.now_s)
        if verdict.drop is not None:
            assert verdict.drop in DROP_KINDS, verdict
            self.drops[verdict.drop] += 1
            if expect is not None:
                assert verdict.drop in expect, (verdict, expect)
            return verdict
        assert expect is None, (verdict, expect)
        frame = verdict.frame
        # Published on the topic it was sent for, with its type, which is the table's type.
        assert self.truth[frame.body] == (route_to, frame.msg_type) == (frame.topic, ROUTES[route_to].msg_type)
        assert (frame.msg_type, frame.md5) == self.receiver.topic_type(route_to)
        ident = (frame.session, frame.topic, frame.source, frame.seq)
        assert ident not in self.published, ident
        self.published.add(ident)
        # Never an older run's message while a newer run was heard lately (a latched value would go back).
        newest = self.newest.get((frame.topic, frame.source))
        if newest is not None and frame.session < newest[0]:
            assert self.now_s - newest[1] >= SESSION_HOLD_S, (frame, newest)
        if newest is None or frame.session >= newest[0]:
            self.newest[(frame.topic, frame.source)] = (frame.session, self.now_s)
        key3 = ident[:3]
        self.max_seq[key3] = max(self.max_seq.get(key3, 0), frame.seq)
        return verdict

    def deliver_own(self, index):
        route_to, payload = self.in_flight.pop(index % len(self.in_flight))
        frame = decode(payload)
        fresh = frame.seq > self.max_seq.get((frame.session, frame.topic, frame.source), 0)
        current = frame.session == self.sender.session
        verdict = self.deliver(route_to, _key(route_to), payload)
        if fresh and current and not is_stale(frame, self.now_s, ROUTES[route_to].traffic.max_age_s):
            assert verdict.drop is None, verdict  # not over-dropped

    def check_counts(self):
        assert self.receiver.counts == self.drops
        counters = self.receiver.counters()
        assert all(counters[f"drop_{k}"] == self.drops[k] for k in DROP_KINDS)


INDEX = st.integers(0, 1000)
# (weight, step): sends and deliveries most often, so runs are long enough to hit the rare orders.
WEIGHTED = (
    (8, st.tuples(st.just("send"), st.sampled_from(TOPICS), st.sampled_from(SOURCES))),
    (8, st.tuples(st.just("deliver"), INDEX)),
    (1, st.tuples(st.just("send_other_type"), st.sampled_from(TOPICS), st.sampled_from(OTHER_TYPES))),
    (2, st.tuples(st.just("duplicate"), INDEX)),
    (2, st.tuples(st.just("misroute"), INDEX, st.sampled_from(TOPICS + BACKFILL["scout"]), st.booleans())),
    (2, st.tuples(st.just("corrupt"), INDEX, st.integers(0, 200), st.booleans())),
    (1, st.tuples(st.just("intruder"), st.sampled_from(TOPICS), st.sampled_from(OTHER_TYPES))),
    (1, st.tuples(st.just("cut"))),
    (2, st.tuples(st.just("restore"))),
    (1, st.tuples(st.just("restart_sender"))),
    (2, st.tuples(st.just("wait"), st.floats(0.0, 2.0))),
)
STEP = st.sampled_from([s for weight, s in WEIGHTED for _ in range(weight)]).flatmap(lambda s: s)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(STEP, min_size=20, max_size=150))
def test_every_published_message_is_on_its_topic_with_its_type_once(steps):
    world = World()
    for step in steps:
        kind, args = step[0], step[1:]
        if kind == "send":
            world.send(*args)
        elif kind == "send_other_type":
            world.send(args[0], SOURCES[0], args[1])
        elif kind == "deliver" and world.in_flight:
            world.deliver_own(args[0])
        elif kind == "duplicate" and world.in_flight:
            route_to, payload = world.in_flight[args[0] % len(world.in_flight)]
            world.in_flight.append((route_to, payload))
        elif kind == "misroute" and world.in_flight:
            route_to, payload = world.in_flight.pop(args[0] % len(world.in_flight))
            other, under_its_own_key = args[1], args[2]
            if other == route_to:
                continue
            if under_its_own_key:  # the sample's key is right, the subscriber is not
                world.deliver(other, _key(route_to), payload, expect={"key_mismatch"})
            else:  # the key was resolved wrong too
                world.deliver(other, _key(other), payload, expect={"wrong_topic"})
        elif kind == "corrupt" and world.in_flight:
            route_to, payload = world.in_flight.pop(args[0] % len(world.in_flight))
            at, truncate = args[1] % len(payload), args[2]
            if truncate:
                damaged = payload[:at]
            else:
                damaged = bytearray(payload)
                damaged[at] ^= 0x5A
                damaged = bytes(damaged)
            world.deliver(route_to, _key(route_to), damaged, expect=set(WIRE_KINDS))
        elif kind == "intruder":
            topic, msg_type = args
            body = world._body(topic, msg_type)
            f = SendPath(new_session_id(10**18)).frame(topic, "/intruder", msg_type, md5_of(msg_type), math.nan, body)
            world.deliver(topic, _key(topic), encode(f), expect={"topic_type_mismatch"})
        elif kind == "cut":
            world.up = False
            world.in_flight.clear()  # what was on the way is lost with the link
        elif kind == "restore" and not world.up:
            world.restore()
        elif kind == "restart_sender":
            world.restart_sender()
        elif kind == "wait":
            world.now_s += args[0]
        world.check_counts()
    # Whatever is still in flight arrives, in any order: the invariants still hold.
    while world.in_flight:
        world.deliver_own(0)
    world.check_counts()
