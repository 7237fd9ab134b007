"""The bridge's part of the per-cloud ledger (cps_ros.cloud_ledger): per robot's cloud route, what
this side received, missed (sequence gaps before it), passed on and dropped by cause, reported on
/diagnostics on a DropReporter named after the route's topic on this side.

Robots' side (stage bridge_out), per managed cloud: received from the rate limiter (gaps in the
limiter's header.seq: lost in this bridge's subscriber queue), put on the link, or not because the
link was down (kept as a backfill keyframe, or dropped), and the keyframes' fate (evicted from a full
store, sent after recovery). Twin side (stage bridge_in), per cloud route (managed and backfill):
frames received (gaps in the robots' bridge's frame numbers: lost on the link, or withheld by the
robots' bridge while the link was down), dropped by the receive path's kind, published (numbered
by this bridge, as a typed publisher would, so the decoder can count what it misses).
"""

from cps_fleet import names
from cps_ros import cloud_ledger
from cps_ros.cloud_ledger import header_seq, with_header_seq


def is_cloud_route(route) -> bool:
    """A robot's managed cloud or its backfill keyframes (by the topic names of the contract)."""
    return route.topic.endswith("/" + names.POINTS_MANAGED) or route.to.endswith("/" + names.POINTS_BACKFILL_DRACO)


class RouteLedger:
    """The ledger of one bridge side's cloud routes. `reporter(topic)` makes the DropReporter a
    route's counters go out on (cps_ros.diagnostics.DropReporter in the node; a fake in tests)."""

    def __init__(self, routes, stage, reporter):
        self.stage = stage
        self.reports = {r.to: reporter(r.topic if stage == cloud_ledger.BRIDGE_OUT else r.to) for r in routes}
        self.sequences = {to: cloud_ledger.SequenceGaps() for to in self.reports}
        self.published = dict.fromkeys(self.reports, 0)

    def __contains__(self, route_to):
        return route_to in self.reports

    def count(self, route_to, what, n=1):
        if route_to in self.reports and n:
            self.reports[route_to].count(**{cloud_ledger.key(self.stage, what): n})

    def received(self, route_to, source, seq):
        """One message (or frame) of `source` numbered `seq` (None: not numbered) on the route."""
        if route_to not in self.reports:
            return
        missed = 0 if seq is None else self.sequences[route_to].note(source, seq)
        self.count(route_to, cloud_ledger.RECEIVED)
        self.count(route_to, cloud_ledger.MISSED, missed)

    def dropped(self, route_to, cause):
        self.count(route_to, cloud_ledger.DROPPED + cause)

    def out(self, route_to):
        self.count(route_to, cloud_ledger.OUT)

    def renumbered(self, route_to, body):
        """`body` numbered as this side's next output of the route (the twin's bridge republishes)."""
        if route_to not in self.reports or header_seq(body) is None:
            return body
        self.published[route_to] += 1
        return with_header_seq(body, self.published[route_to])

    def gauge(self, route_to, **values):
        if route_to in self.reports:
            self.reports[route_to].gauge(**{cloud_ledger.key(self.stage, k): v for k, v in values.items()})
