"""The bridge's frame paths without ROS or Zenoh: what a received payload becomes (publish on which
topic with which type, or drop with a reason), and the sequence numbers of what is sent.

The invariant the receiving side keeps, on both sides: a message is published only on the topic
its sender put it on (the frame names it; the Zenoh key it came under must be that topic's key)
and only with the one type that topic has (the table's, else the first accepted frame's). A frame
that breaks it is dropped and counted by kind; nothing re-types a topic. Issue 22: after a link
cut, the twin's bridge published frames on another route's topic with their own type (the cause
was not reproduced; docs/reliability.md, "Frames on the wrong topic").
"""

import collections
import dataclasses
import threading
from typing import Callable, Dict, Iterable, Optional

from cps_link.bridge_config import Route
from cps_link.bridge_wire import (
    BAD_CRC,
    BAD_VERSION,
    NOT_A_FRAME,
    TRUNCATED,
    Frame,
    WireError,
    decode,
    is_stale,
    new_session_id,
    session_started_ns,
)

# Drop kinds beyond WireError's (truncated, not_a_frame, bad_version, bad_crc).
KEY_MISMATCH = "key_mismatch"  # the sample's key is not the key of the route that received it
WRONG_TOPIC = "wrong_topic"  # the frame is for another listed topic than the route's
UNLISTED_TOPIC = "unlisted_topic"  # the frame is for a topic this side's table does not receive
UNKNOWN_TYPE = "unknown_type"  # this side has no such message type
MD5_MISMATCH = "md5_mismatch"  # this side's definition of the type differs
TOPIC_TYPE_MISMATCH = "topic_type_mismatch"  # the topic has another type (table, or first frame)
OLD_SESSION = "old_session"  # from a sender's run older than the one heard lately
DUPLICATE = "duplicates"
STALE = "stale"
# The bridge's own counters of a type mismatch outside the receive path's verdicts: a ROS message
# of another type than its route's on the way out, a frame for a publisher of another type on the
# way in (never: the receive path keeps one type per topic).
SEND_TOPIC_TYPE_MISMATCH = "send_topic_type_mismatch"
PUBLISHER_TYPE_MISMATCH = "publisher_type_mismatch"
WIRE_KINDS = (TRUNCATED, NOT_A_FRAME, BAD_VERSION, BAD_CRC)
DROP_KINDS = WIRE_KINDS + (
    KEY_MISMATCH,
    WRONG_TOPIC,
    UNLISTED_TOPIC,
    UNKNOWN_TYPE,
    MD5_MISMATCH,
    TOPIC_TYPE_MISMATCH,
    OLD_SESSION,
    DUPLICATE,
    STALE,
)
# The older counters the diagnostics kept (and dashboards read): sums of the kinds above.
AGGREGATE = {"corrupt": WIRE_KINDS, "type_mismatch": (UNKNOWN_TYPE, MD5_MISMATCH, TOPIC_TYPE_MISMATCH)}
# A frame from an older run of a sender is dropped while the newer run was heard this recently, s;
# past that the older run is taken back (a sender whose clock stepped back is not shut out forever).
SESSION_HOLD_S = 5.0
# Sessions remembered per (topic, source) for duplicates.
SESSIONS_KEPT = 4


@dataclasses.dataclass(frozen=True)
class Verdict:
    """What to do with one payload: publish `frame` on frame.topic (drop is None) or drop it."""

    frame: Optional[Frame]
    drop: Optional[str] = None
    detail: str = ""


class _Source:
    """One (topic, source publisher): its current session, when it was heard, seqs per session."""

    def __init__(self):
        self.session = None
        self.heard_s = 0.0
        self.last_seq = collections.OrderedDict()


class ReceivePath:
    """Decides, for each (route, key, payload), publish or drop; counts drops by kind. Thread-safe.

    `routes` are the routes this side receives, `md5_of(msg_type)` this side's md5 of a type (None
    when it has no such type)."""

    def __init__(
        self, routes: Iterable[Route], key_prefix, md5_of: Callable[[str], Optional[str]], hold_s=SESSION_HOLD_S
    ):
        self.routes = {r.to: r for r in routes}
        self.keys = {to: r.key(key_prefix) for to, r in self.routes.items()}
        self.md5_of = md5_of
        self.hold_s = hold_s
        # topic -> (type, md5): from the table where it names the type, else the first accepted frame.
        self.types: Dict[str, tuple] = {}
        for to, r in self.routes.items():
            if r.msg_type and md5_of(r.msg_type):
                self.types[to] = (r.msg_type, md5_of(r.msg_type))
        self.counts = collections.Counter()
        self._sources = {}
        self._lock = threading.Lock()

    def topic_type(self, topic):
        """(type, md5) the topic is published with, or None before its first accepted frame."""
        with self._lock:
            return self.types.get(topic)

    def _drop(self, kind, detail, frame=None):
        self.counts[kind] += 1
        return Verdict(frame, kind, detail)

    def receive(self, route_to, key, payload, now_s) -> Verdict:
        """The verdict on `payload`, received by the subscriber of route `route_to` under `key`
        (None: not known, not checked)."""
        try:
            frame = decode(payload)
        except WireError as exc:
            with self._lock:
                return self._drop(exc.kind, str(exc))
        with self._lock:
            return self._check(route_to, key, frame, now_s)

    def _check(self, route_to, key, frame, now_s):
        route = self.routes.get(route_to)
        if route is None:
            return self._drop(UNLISTED_TOPIC, f"no route {route_to} on this side", frame)
        if key is not None and key != self.keys[route_to]:
            return self._drop(KEY_MISMATCH, f"sample under {key} reached {route_to}'s subscriber", frame)
        if frame.topic not in self.routes:
            return self._drop(UNLISTED_TOPIC, f"frame for {frame.topic!r}, not a topic this side receives", frame)
        if frame.topic != route_to:
            return self._drop(WRONG_TOPIC, f"frame for {frame.topic} reached {route_to}", frame)
        md5 = self.md5_of(frame.msg_type)
        if md5 is None:
            return self._drop(UNKNOWN_TYPE, f"{frame.msg_type!r} is not a type this side knows", frame)
        if md5 != frame.md5:
            return self._drop(MD5_MISMATCH, f"{frame.msg_type}: md5 {frame.md5} != this side's {md5}", frame)
        known = self.types.get(route_to)
        if known is not None and known != (frame.msg_type, frame.md5):
            return self._drop(TOPIC_TYPE_MISMATCH, f"{frame.msg_type} on {route_to}, which is {known[0]}", frame)
        source = self._sources.setdefault((route_to, frame.source), _Source())
        if source.session is not None and frame.session != source.session:
            newer = session_started_ns(frame.session) > session_started_ns(source.session)
            if not newer and now_s - source.heard_s < self.hold_s:
                return self._drop(OLD_SESSION, f"{frame.source} on {route_to}: an older run of its sender", frame)
        last = source.last_seq.get(frame.session)
        if last is not None and frame.seq <= last:
            return self._drop(DUPLICATE, "", frame)
        source.session, source.heard_s = frame.session, now_s
        source.last_seq[frame.session] = frame.seq
        source.last_seq.move_to_end(frame.session)
        while len(source.last_seq) > SESSIONS_KEPT:
            source.last_seq.popitem(last=False)
        if is_stale(frame, now_s, route.traffic.max_age_s):
            return self._drop(STALE, f"stamp {now_s - frame.stamp_s:.2f} s old", frame)
        self.types.setdefault(route_to, (frame.msg_type, frame.md5))
        return Verdict(frame)

    def counters(self):
        """Drops per kind (every kind, zeros included) and the aggregate counters."""
        with self._lock:
            out = {f"drop_{kind}": self.counts[kind] for kind in DROP_KINDS}
            out.update({name: sum(self.counts[k] for k in kinds) for name, kinds in AGGREGATE.items()})
            out.update({DUPLICATE: self.counts[DUPLICATE], STALE: self.counts[STALE]})
        return out


class SendPath:
    """The sending side's frames: one session per bridge run, a sequence number per (topic, source),
    and one type per topic (an AnyMsg subscriber takes any publisher's type: a second type on a
    topic is refused, counted, never sent)."""

    def __init__(self, session=None, table_types=None):
        self.session = session or new_session_id()
        self.table_types = dict(table_types or {})  # topic -> type name, where the table names it
        self.types = {}
        self.counts = collections.Counter()
        self._seq = {}
        self._lock = threading.Lock()

    def frame(self, topic, source, msg_type, md5, stamp_s, body) -> Optional[Frame]:
        """The next frame of `source` on `topic`, or None (counted) when the topic has another type."""
        with self._lock:
            if self.table_types.get(topic, msg_type) != msg_type or self.types.setdefault(topic, (msg_type, md5)) != (
                msg_type,
                md5,
            ):
                self.counts[TOPIC_TYPE_MISMATCH] += 1
                return None
            key = (topic, source)
            self._seq[key] = self._seq.get(key, 0) + 1
            seq = self._seq[key]
        return Frame(self.session, seq, stamp_s, msg_type, md5, source, bytes(body), topic=topic)
