"""The link's health as one bridge sees it (ROS-free): the other side's liveliness tokens come and
go, and its heartbeats stop. The token alone is not enough: a bridge whose transport is stuck
behind a full send buffer may not see the session end until the link is back. A token held while
its heartbeats stay away is a session that carries one way only (`deaf`); so is a peer heard while
its echoes of this side's heartbeats never come back (`unheard`, where the peer echoes them), and
so is a peer heard while the session lists no transport to it (`orphaned`: Zenoh's close of the
transport before an outage, finishing after the new one opened, removed the new one)."""

import dataclasses
import math


@dataclasses.dataclass
class LinkHealth:
    """Up while at least one of the peer side's bridges holds its liveliness token."""

    started_s: float
    peers: set = dataclasses.field(default_factory=set)
    since_s: float = None
    outages: int = 0
    last_outage_s: float = 0.0
    ever_up: bool = False
    last_heard: dict = dataclasses.field(default_factory=dict)
    tokens: set = dataclasses.field(default_factory=set)  # the peers whose liveliness tokens are there
    # when the peer last echoed one of this side's heartbeats (the side that asks for echoes)
    last_echo_s: float = -math.inf
    # the link socket: its received bytes, when they last grew, and since when they have grown
    # without a gap longer than the caller's (the transport talks)
    socket_received: int = 0
    socket_heard_s: float = -math.inf
    socket_talking_since_s: float = -math.inf
    # the peers whose token came and that were not heard since: when it came
    token_unheard_since: dict = dataclasses.field(default_factory=dict)
    # since when the Zenoh session has listed no transport to a peer while the link was up (None:
    # it lists one, or the link is down)
    unlisted_since_s: float = None

    def __post_init__(self):
        if self.since_s is None:
            self.since_s = self.started_s

    @property
    def up(self):
        return bool(self.peers)

    def heard(self, name, now_s):
        """A peer's heartbeat; True when the link changed to up."""
        return self.peer_alive(name, now_s)

    def first_heartbeat_after_token(self, name, now_s):
        """Seconds from the peer's token to this, its first heartbeat after it (None if not the first)."""
        since_s = self.token_unheard_since.pop(name, None)
        return None if since_s is None else now_s - since_s

    def echoed(self, now_s):
        """The peer echoed one of this side's heartbeats; seconds since the link came up when this is
        the first echo of this up period (None otherwise)."""
        first = self.up and self.last_echo_s < self.since_s
        self.last_echo_s = now_s
        return now_s - self.since_s if first else None

    def heard_back(self):
        """Up, and the peer has echoed this side's heartbeats since: it hears this side."""
        return self.up and self.last_echo_s >= self.since_s

    def unheard(self, now_s, after_s):
        """Up for more than after_s without one echo: the peer is heard, this side is not (a session
        that carries the peer's way only)."""
        return self.up and self.last_echo_s < self.since_s and now_s - self.since_s > after_s

    def socket_bytes(self, received, now_s, gap_s):
        """The link socket's received byte count at now_s (`gap_s`: the longest silence that still
        counts as talking)."""
        if received != self.socket_received:
            if now_s - self.socket_heard_s > gap_s:
                self.socket_talking_since_s = now_s
            self.socket_received, self.socket_heard_s = received, now_s

    def socket_talking(self, now_s, gap_s):
        """Since when the link socket has been receiving bytes without a gap longer than gap_s (None:
        it is silent now, as in a cut)."""
        return None if now_s - self.socket_heard_s > gap_s else self.socket_talking_since_s

    def expire(self, now_s, timeout_s):
        """Peers not heard for timeout_s are gone; True when the link changed to down."""
        silent = [n for n in self.peers if now_s - self.last_heard.get(n, now_s) > timeout_s]
        return any([self.peer_gone(n, now_s) for n in silent])

    def peer_alive(self, name, now_s):
        """A peer's token appeared (or it was heard); True when the link changed to up."""
        self.last_heard[name] = now_s
        was_up = self.up
        self.peers.add(name)
        if was_up:
            return False
        if self.ever_up:
            self.last_outage_s = now_s - self.since_s
        self.ever_up = True
        self.since_s = now_s
        self.unlisted_since_s = None  # a new up period: what the old session listed says nothing
        return True

    def token_put(self, name, now_s):
        """A peer's liveliness token appeared; True when the link changed to up."""
        self.tokens.add(name)
        self.token_unheard_since[name] = now_s
        return self.peer_alive(name, now_s)

    def token_deleted(self, name, now_s):
        """A peer's liveliness token disappeared; True when the link changed to down."""
        self.tokens.discard(name)
        self.token_unheard_since.pop(name, None)
        return self.peer_gone(name, now_s)

    def transports_listed(self, count, now_s):
        """How many transports to peers the Zenoh session listed at now_s."""
        if count or not self.up:
            self.unlisted_since_s = None
        elif self.unlisted_since_s is None:
            self.unlisted_since_s = now_s

    def orphaned(self, now_s, after_s):
        """Up, the session has listed no transport to the peer for after_s, and the peer was heard
        after it stopped listing one: the transport still receives, but Zenoh's transport manager no
        longer holds it, so nothing this side puts goes out (a session that carries the peer's way
        only, seen from this side at once)."""
        since_s = self.unlisted_since_s
        if since_s is None or now_s - since_s < after_s:
            return False
        return max(self.last_heard.values(), default=-math.inf) > since_s

    def deaf(self, now_s, after_s, since_s=float("-inf")):
        """The peers whose token is there but that were not heard for after_s, counted from their
        token's coming or their last heartbeat, and from `since_s` at the earliest (since when the
        transport has been talking): their session carries this side's way only."""
        return sorted(n for n in self.tokens if now_s - max(self.last_heard.get(n, now_s), since_s) > after_s)

    def session_closed(self, now_s):
        """This side closed its session: every token goes with it; True when the link changed to down."""
        return any([self.token_deleted(n, now_s) for n in sorted(self.tokens)])

    def peer_gone(self, name, now_s):
        """A peer's token disappeared; True when the link changed to down (one more outage)."""
        if name not in self.peers:
            return False
        self.peers.discard(name)
        if self.up:
            return False
        self.outages += 1
        self.since_s = now_s
        self.unlisted_since_s = None
        return True
