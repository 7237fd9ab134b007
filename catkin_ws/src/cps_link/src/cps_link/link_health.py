"""The link's health as one bridge sees it: the other side's liveliness tokens come and go (ROS-free)."""
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

    def __post_init__(self):
        if self.since_s is None:
            self.since_s = self.started_s

    @property
    def up(self):
        return bool(self.peers)

    def peer_alive(self, name, now_s):
        """A peer's token appeared; True when the link changed to up."""
        was_up = self.up
        self.peers.add(name)
        if was_up:
            return False
        if self.ever_up:
            self.last_outage_s = now_s - self.since_s
        self.ever_up = True
        self.since_s = now_s
        return True

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
