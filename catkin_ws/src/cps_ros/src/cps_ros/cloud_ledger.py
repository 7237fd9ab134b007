"""The per-cloud ledger's counters, as the nodes report them on /diagnostics (ROS-free).

Each node on a managed cloud's path counts, per robot, what it received, what it passed on and what
it dropped by cause, under keys `ledger_<stage>_<what>` in its DropReporter's values (the key names
are here, once, for the nodes and for the report that reads them back: cps_experiments.ledger).
`missed` is what the node can tell it never got: gaps in the sequence numbers of the stage before
(`SequenceGaps`: header.seq, which every rospy and roscpp publisher numbers per topic, or the bridge's
frame numbers), so a cloud lost in a subscriber queue or on the link is counted by the node after
it, by cause, and not worked out from two other counters.
"""

import struct
import threading

LEDGER_PREFIX = "ledger_"
# The stages, in the order a managed cloud meets them.
ENCODER = "encoder"  # Draco encoder: voxel grid output in, encoded out
LIMITER = "limiter"  # rate limiter: encoded in, forwarded out (re-numbered)
BRIDGE_OUT = "bridge_out"  # the robots' bridge: managed clouds in, put on the link out
BRIDGE_IN = "bridge_in"  # the twin's bridge: frames in, published out (re-numbered)
DECODER = "decoder"  # the twin's Draco decoder: compressed in, decoded out
STAGES = (ENCODER, LIMITER, BRIDGE_OUT, BRIDGE_IN, DECODER)
RECEIVED, MISSED, OUT = "received", "missed", "out"
DROPPED = "dropped_"  # + cause
# The robots' bridge, per robot: clouds it did not put on the link because it saw the link down
# (kept as a backfill keyframe, or not), and the keyframes' fate.
BACKFILL_KEPT, BACKFILL_EVICTED, BACKFILL_SENT = "backfill_kept", "backfill_evicted", "backfill_sent"
BACKFILL_WAITING = "backfill_waiting"  # a gauge: its keyframes in the store now


def key(stage, what):
    """The diagnostics key of one counter: `ledger_<stage>_<what>`."""
    return f"{LEDGER_PREFIX}{stage}_{what}"


def parse_key(name):
    """(stage, what) of a ledger key, or None for any other key."""
    if not name.startswith(LEDGER_PREFIX):
        return None
    rest = name[len(LEDGER_PREFIX) :]
    for stage in sorted(STAGES, key=len, reverse=True):
        if rest.startswith(stage + "_"):
            return stage, rest[len(stage) + 1 :]
    return None


_SEQ = struct.Struct("<I")


def header_seq(buff):
    """header.seq of a serialized message that starts with a std_msgs/Header (None if too short)."""
    return _SEQ.unpack_from(buff, 0)[0] if len(buff) >= _SEQ.size else None


def with_header_seq(buff, seq):
    """The serialized message with its header.seq set to `seq` (the rest unchanged): a relay numbers
    what it passes on as a typed publisher would, so the next stage can count what it misses."""
    return _SEQ.pack(seq & 0xFFFFFFFF) + bytes(buff[_SEQ.size :])


class SequenceGaps:
    """Sequence numbers of one input, per source (a publisher, a bridge session): how many were
    received and how many are missing between consecutive ones (lost before this node). A number at
    or below the last one starts a new run of that source (it restarted), counting no gap."""

    def __init__(self):
        self.received = 0
        self.missed = 0
        self._last = {}
        self._lock = threading.Lock()

    def note(self, source, seq):
        """One message numbered `seq` from `source`; returns how many were missed just before it."""
        with self._lock:
            self.received += 1
            last = self._last.get(source)
            self._last[source] = seq
            gap = seq - last - 1 if last is not None and seq > last else 0
            self.missed += gap
            return gap
