"""The link's health as one bridge sees it (ROS-free): the other side's liveliness tokens come and
go, and its heartbeats stop. The token alone is not enough: a bridge whose transport is stuck
behind a full send buffer may not see the session end until the link is back. A token held while
its heartbeats stay away is a session that carries one way only (`deaf`)."""

import dataclasses


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

    def __post_init__(self):
        if self.since_s is None:
            self.since_s = self.started_s

    @property
    def up(self):
        return bool(self.peers)

    def heard(self, name, now_s):
        """A peer's heartbeat; True when the link changed to up."""
        return self.peer_alive(name, now_s)

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
        return True

    def token_put(self, name, now_s):
        """A peer's liveliness token appeared; True when the link changed to up."""
        self.tokens.add(name)
        return self.peer_alive(name, now_s)

    def token_deleted(self, name, now_s):
        """A peer's liveliness token disappeared; True when the link changed to down."""
        self.tokens.discard(name)
        return self.peer_gone(name, now_s)

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
        return True
