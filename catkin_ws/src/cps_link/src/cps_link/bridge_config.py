"""The Zenoh bridge's table (config/bridge.yaml): which topics cross, which way, in which class.

ROS-free and Zenoh-free: the table is read and checked here (errors name file and line), `<r>`
is expanded per robot, and each class's QoS is kept as names the bridge maps onto Zenoh's enums.
"""

import dataclasses
import os
from typing import Dict, Optional, Sequence, Tuple

from cps_fleet.config import ConfigError, Reader, load_yaml_document

ROBOTS, TWIN = "robots", "twin"
SIDES = (ROBOTS, TWIN)
PRIORITIES = ("real_time", "interactive_high", "interactive_low", "data_high", "data", "data_low", "background")
CONGESTION = ("block", "drop")
ROBOT_PLACEHOLDER = "<r>"
# A bridge process carries one lane: `command` the command class alone (its own process, Zenoh
# session and TCP connection, so a command never waits behind a cloud in a queue, a thread or the
# interpreter lock), `main` every other class, `all` both in one process.
LANES = ("all", "main", "command")
COMMAND_CLASS = "command"
# Which side's bridge listens on a lane, the other connecting: the twin on the main lane (and
# `all`), the robots on the command lane, so that each host answers from outside on exactly one
# port, its own listener's (cps_link.host_guard, issue 38); the twin opens the connection that
# carries its commands.
COMMAND_LISTENER = ROBOTS
DATA_LISTENER = TWIN
# What the robots' bridge sends on a backfill pose route.
POSE_TYPE = "geometry_msgs/TransformStamped"
DEFAULT_TABLE = os.path.normpath(
    os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "config", "bridge.yaml")
)


@dataclasses.dataclass(frozen=True)
class TrafficClass:
    name: str
    priority: str
    congestion: str
    reliable: bool
    express: bool
    max_age_s: Optional[float] = None  # receiving side drops older header stamps
    # Waits in the robots' bridge's send queue (paced, newest per topic and source, expired after
    # max_age_s: cps_link.send_queue) instead of going out at once.
    paced: bool = False


@dataclasses.dataclass(frozen=True)
class Route:
    """One topic crossing: published on `source` under `topic`, republished on the far side as `to`."""

    topic: str
    to: str
    source: str
    traffic: TrafficClass
    latched: bool = False
    robot: str = ""
    # False for what the bridge itself puts on the wire (backfill): nothing to subscribe to.
    from_ros: bool = True
    # The message type, where the table names it ("" = the type of the first frame accepted).
    msg_type: str = ""
    # One of the bandwidth manager's streams (its budget covers it); the rest of what crosses is
    # counted as unmanaged traffic in the link report.
    managed: bool = False

    def key(self, prefix):
        """The Zenoh key expression this topic travels on."""
        return f"{prefix}/topic{self.to}"


@dataclasses.dataclass(frozen=True)
class Backfill:
    """Per robot: the route whose keyframes are kept and the two routes they are re-sent on."""

    source: Dict[str, str]  # robot -> the source route's far-side name
    cloud_to: Dict[str, str]
    pose_to: Dict[str, str]
    map_frame: str
    keyframe_period_s: float
    allocation_topic: str


@dataclasses.dataclass(frozen=True)
class BridgeTable:
    path: str
    endpoint_port: int
    key_prefix: str
    lease_ms: int
    keep_alive: int
    retry_max_ms: int
    heartbeat_ms: int
    heartbeat_timeout_ms: int
    classes: Dict[str, TrafficClass]
    routes: Tuple[Route, ...]
    backfill: Optional[Backfill] = None
    # Where the robots' command lane listens (the main lane and `all`: the twin at endpoint_port).
    command_port: int = 0
    lane: str = "all"
    # Zenoh's batch size on the link, bytes (a batch is written whole; smaller batches let a
    # higher-priority message in sooner at a low rate).
    batch_bytes: int = 65535
    # At most this many bytes not yet sent may wait in a host's TCP socket (net.ipv4.tcp_notsent_lowat:
    # cps_link sets it in the test bed's namespaces; on real hosts a sysctl). 0: not set.
    kernel_unsent_bytes: int = 0
    # The other side's liveliness token there, its transport talking, but none of its heartbeats for
    # this long, ms: the bridge closes its Zenoh session and opens a new one (LinkHealth.deaf).
    reopen_after_ms: int = 5000
    # The robots' main lane: the twin heard but none of this side's heartbeats echoed since the link
    # came up for this long, ms (LinkHealth.unheard): the same stall as the twin's deaf one, seen
    # sooner, so the robots' side cures it before the twin's rule fires and only one side reopens.
    unheard_after_ms: int = 2000
    # The peer heard while the session has listed no transport to it for this long, ms
    # (LinkHealth.orphaned): reopen at once.
    orphan_after_ms: int = 300
    # The kernel ends a link connection whose sent data stays unacknowledged this long, ms
    # (TCP_USER_TIMEOUT, set on the main lane's link socket; 0: the kernel's default, ~15 min).
    tcp_user_timeout_ms: int = 1000
    # The DSCP code point of the command lane's packets (its endpoints' `dscp`: Zenoh sets IP_TOS on
    # its sockets, the connecting and the accepted one):
    # 46, EF, which Wi-Fi's WMM puts in its voice queue ahead of bulk data (the test bed's shaper
    # models that queue: cps_link.netns_link). The main lane keeps 0, best effort.
    command_dscp: int = 46
    # Zenoh closes a transport whose put with congestion block has waited this long for room in
    # its queue, ms (its wait_before_close): in a cut, what ends the transport on the sending side.
    block_wait_before_close_ms: int = 500
    # The robots' bridge's link report period, ms (cps_link.link_report).
    report_ms: int = 500

    @property
    def paced_ranks(self):
        """Paced class -> its rank in the send queue (higher Zenoh priority first)."""
        paced = [c for c in self.classes.values() if c.paced]
        return {c.name: PRIORITIES.index(c.priority) for c in paced}

    def for_lane(self, lane):
        """The part of the table one lane's bridge process carries, on that lane's port."""
        if lane not in LANES:
            raise ValueError(f"lane must be one of {', '.join(LANES)}, got '{lane}'")
        if lane == "all":
            return self
        command = lane == COMMAND_CLASS
        return dataclasses.replace(
            self,
            lane=lane,
            routes=tuple(r for r in self.routes if (r.traffic.name == COMMAND_CLASS) == command),
            endpoint_port=self.command_port if command else self.endpoint_port,
            backfill=None if command else self.backfill,
        )

    @property
    def listening_side(self):
        """The side whose bridge listens on this lane's port (the other side's connects to it)."""
        return COMMAND_LISTENER if self.lane == COMMAND_CLASS else DATA_LISTENER

    def listening_ports(self, main_port=None, command_port=None):
        """Side -> the ports its bridges listen at when the main and the command lane run apart
        (each lane's listening_side; a port None: the table's)."""
        out = {}
        for lane, port in (("main", main_port), (COMMAND_CLASS, command_port)):
            lane_table = self.for_lane(lane)
            out.setdefault(lane_table.listening_side, []).append(port or lane_table.endpoint_port)
        return out

    @property
    def publishes_link_state(self):
        """Only one process per side says whether the link is up: the one carrying telemetry."""
        return self.lane != COMMAND_CLASS

    def _scope(self, side):
        return f"{side}" if self.lane == "all" else f"{self.lane}/{side}"

    def outgoing(self, side):
        return [r for r in self.routes if r.source == side]

    def route(self, to):
        return next(r for r in self.routes if r.to == to)

    def incoming(self, side):
        return [r for r in self.routes if r.source != side]

    def liveliness_key(self, side, name):
        return f"{self.key_prefix}/bridge/{self._scope(side)}/{name}"

    def peer_liveliness_keys(self, side):
        return f"{self.key_prefix}/bridge/{self._scope(other_side(side))}/**"

    def heartbeat_key(self, side, name):
        return f"{self.key_prefix}/heartbeat/{self._scope(side)}/{name}"

    def peer_heartbeat_keys(self, side):
        return f"{self.key_prefix}/heartbeat/{self._scope(other_side(side))}/**"

    def echo_key(self, robots_name):
        """Where the twin echoes the heartbeats of the robots' bridge `robots_name` (round trips)."""
        return f"{self.key_prefix}/echo/{self._scope(ROBOTS)}/{robots_name}"

    def report_key(self, robots_name):
        """Where the robots' bridge `robots_name` puts its link report counters."""
        return f"{self.key_prefix}/linkreport/{self._scope(ROBOTS)}/{robots_name}"

    def report_keys(self):
        return f"{self.key_prefix}/linkreport/{self._scope(ROBOTS)}/**"

    def probe_key(self, robots_name):
        """Where the robots' bridge `robots_name` puts its probe trains (cps_link.probe_train)."""
        return f"{self.key_prefix}/probe/{self._scope(ROBOTS)}/{robots_name}"

    def probe_keys(self):
        return f"{self.key_prefix}/probe/{self._scope(ROBOTS)}/**"


def other_side(side):
    if side not in SIDES:
        raise ValueError(f"side must be one of {', '.join(SIDES)}, got '{side}'")
    return TWIN if side == ROBOTS else ROBOTS


def _check_topic(reader, key, name):
    if not name.startswith("/") or "//" in name or name.endswith("/") or " " in name:
        raise reader.error(key, f"'{name}' is not a global ROS topic name")
    return name


def _class_of(reader, classes):
    name = reader.get("class", str)
    if name not in classes:
        raise reader.error("class", f"unknown class '{name}' (known: {', '.join(classes)})")
    return classes[name]


def load_bridge_table(path=None, robots: Sequence[str] = ()) -> BridgeTable:
    """The table with `<r>` expanded for `robots`; ConfigError (file:line) for anything wrong."""
    path = path or DEFAULT_TABLE
    doc = load_yaml_document(path)
    top = Reader(doc)
    classes = {}
    class_reader = top.child("classes")
    for name in class_reader.value:
        c = class_reader.child(name)
        priority = c.get("priority", str)
        if priority not in PRIORITIES:
            raise c.error("priority", f"unknown priority '{priority}' (known: {', '.join(PRIORITIES)})")
        congestion = c.get("congestion", str)
        if congestion not in CONGESTION:
            raise c.error("congestion", f"unknown congestion control '{congestion}' (known: block, drop)")
        classes[name] = TrafficClass(
            name,
            priority,
            congestion,
            c.get("reliable", bool),
            c.get("express", bool),
            c.number("max_age_s", default=None, low=0.0, low_open=True) if c.has("max_age_s") else None,
            c.get("paced", bool, default=False),
        )
        if classes[name].paced and (congestion != "block" or not classes[name].reliable):
            # Zenoh drops a best-effort message whatever its congestion control
            raise c.error(
                "paced",
                "a paced class needs congestion: block and reliable: true (its queue is the bridge's, not Zenoh's)",
            )
    routes, seen = [], {}
    for entry in top.items("topics"):
        topic = _check_topic(entry, "topic", entry.get("topic", str))
        to = _check_topic(entry, "to", entry.get("to", str)) if entry.has("to") else topic
        source = entry.get("from", str)
        if source not in SIDES:
            raise entry.error("from", f"must be one of {', '.join(SIDES)}, got '{source}'")
        traffic = _class_of(entry, classes)
        latched = entry.get("latched", bool, default=False)
        msg_type = entry.get("type", str, default="")
        managed = entry.get("managed", bool, default=False)
        if msg_type and msg_type.count("/") != 1:
            raise entry.error("type", f"'{msg_type}' is not a ROS message type (package/Name)")
        per_robot = ROBOT_PLACEHOLDER in topic or ROBOT_PLACEHOLDER in to
        for robot in robots if per_robot else ("",):
            route = Route(
                topic.replace(ROBOT_PLACEHOLDER, robot),
                to.replace(ROBOT_PLACEHOLDER, robot),
                source,
                traffic,
                latched,
                robot,
                msg_type=msg_type,
                managed=managed,
            )
            if route.to in seen:
                raise entry.error("topic", f"'{route.to}' crosses twice (also at line {seen[route.to]})")
            seen[route.to] = doc.line(entry.key_path)
            routes.append(route)
    backfill = _backfill(top, doc, classes, robots, routes, seen) if top.has("backfill") else None
    limits = (
        ("batch_bytes", 1024, 65535),
        ("kernel_unsent_bytes", 0, 2**31),
        ("report_ms", 100, 5000),
        ("tcp_user_timeout_ms", 0, 600_000),
        ("command_dscp", 0, 63),
    )
    for key, low, high in limits:
        if top.has(key) and not low <= top.get(key, int) <= high:
            raise top.error(key, f"must be in [{low}, {high}], got {top.get(key, int)}")
    # a reopen sooner than a heartbeat timeout reopens a session whose peer is merely late; the
    # robots' unheard rule fires before the twin's deaf one, or both sides reopen for one stall
    timeout_ms = top.get("heartbeat_timeout_ms", int)
    reopen_ms = top.get("reopen_after_ms", int, default=BridgeTable.reopen_after_ms)
    unheard_ms = top.get("unheard_after_ms", int, default=BridgeTable.unheard_after_ms)
    orphan_ms = top.get("orphan_after_ms", int, default=BridgeTable.orphan_after_ms)
    # the orphan rule needs a heartbeat after the session stopped listing the peer's transport
    beat_ms = top.get("heartbeat_ms", int)
    # a blocked put ends its transport within the lease, as the peer's lease ends the peer's: else
    # the sending side's transport outlives a short cut and its routing state goes stale (README)
    block_ms = top.get("block_wait_before_close_ms", int, default=BridgeTable.block_wait_before_close_ms)
    lease_ms = top.get("lease_ms", int)
    for key, value, low, high in (
        ("reopen_after_ms", reopen_ms, timeout_ms + 1, 600_000),
        ("unheard_after_ms", unheard_ms, timeout_ms + 1, reopen_ms - 1),
        ("orphan_after_ms", orphan_ms, 2 * beat_ms, unheard_ms - 1),
        ("block_wait_before_close_ms", block_ms, 100, lease_ms - 1),
    ):
        if not low <= value <= high:
            if top.has(key):
                raise top.error(key, f"must be in [{low}, {high}], got {value}")
            raise top.error(None, f"{key} (not set: {value} by default) must be in [{low}, {high}]")
    if top.get("command_port", int) == top.get("endpoint_port", int):
        raise top.error("command_port", "the command lane needs a port of its own (it equals endpoint_port)")
    if COMMAND_CLASS not in classes:
        raise class_reader.error(None, f"missing class '{COMMAND_CLASS}' (the command lane carries it)")
    return BridgeTable(
        path=path,
        endpoint_port=top.get("endpoint_port", int),
        command_port=top.get("command_port", int),
        key_prefix=top.get("key_prefix", str),
        lease_ms=lease_ms,
        keep_alive=top.get("keep_alive", int),
        retry_max_ms=top.get("retry_max_ms", int),
        heartbeat_ms=top.get("heartbeat_ms", int),
        heartbeat_timeout_ms=top.get("heartbeat_timeout_ms", int),
        classes=classes,
        routes=tuple(routes),
        backfill=backfill,
        batch_bytes=top.get("batch_bytes", int, default=65535),
        kernel_unsent_bytes=top.get("kernel_unsent_bytes", int, default=0),
        report_ms=top.get("report_ms", int, default=500),
        reopen_after_ms=reopen_ms,
        unheard_after_ms=unheard_ms,
        orphan_after_ms=orphan_ms,
        tcp_user_timeout_ms=top.get("tcp_user_timeout_ms", int, default=BridgeTable.tcp_user_timeout_ms),
        command_dscp=top.get("command_dscp", int, default=BridgeTable.command_dscp),
        block_wait_before_close_ms=block_ms,
    )


def _backfill(top, doc, classes, robots, routes, seen):
    """The backfill block; adds its two routes per robot to `routes`."""
    b = top.child("backfill")
    source = _check_topic(b, "source", b.get("source", str))
    traffic = _class_of(b, classes)
    names = {key: _check_topic(b, key, b.get(key, str)) for key in ("cloud_to", "pose_to")}
    by_topic = {r.topic: r for r in routes}
    sources, clouds, poses = {}, {}, {}
    for robot in robots:
        topic = source.replace(ROBOT_PLACEHOLDER, robot)
        if topic not in by_topic or by_topic[topic].source != ROBOTS:
            raise b.error("source", f"'{topic}' is not a topic that crosses from the robots")
        sources[robot] = by_topic[topic].to
        for key, out in (("cloud_to", clouds), ("pose_to", poses)):
            out[robot] = names[key].replace(ROBOT_PLACEHOLDER, robot)
            if out[robot] in seen:
                raise b.error(key, f"'{out[robot]}' crosses twice (also at line {seen[out[robot]]})")
            seen[out[robot]] = doc.line(b.key_path + (key,))
            routes.append(
                Route(
                    out[robot],
                    out[robot],
                    ROBOTS,
                    traffic,
                    robot=robot,
                    from_ros=False,
                    msg_type=POSE_TYPE if key == "pose_to" else by_topic[topic].msg_type,
                    managed=True,  # paced within the manager's unused budget
                )
            )
    return Backfill(
        sources,
        clouds,
        poses,
        b.get("map_frame", str),
        b.number("keyframe_period_s", low=0.0, low_open=True),
        _check_topic(b, "allocation", b.get("allocation", str)),
    )


__all__ = [
    "BridgeTable",
    "ConfigError",
    "Route",
    "TrafficClass",
    "load_bridge_table",
    "other_side",
    "ROBOTS",
    "TWIN",
    "SIDES",
    "PRIORITIES",
]
