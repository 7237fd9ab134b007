"""The bridge's part of the cloud ledger without ROS or Zenoh: per cloud route, received, missed
(gaps in the numbers before it), dropped by cause and put out, and the twin's republished clouds
numbered by the bridge itself."""

import collections
import struct

import pytest

from cps_fleet import names
from cps_link.bridge_config import load_bridge_table
from cps_link.route_ledger import RouteLedger, is_cloud_route
from cps_ros import cloud_ledger as C
from cps_ros.cloud_ledger import header_seq, with_header_seq

pytestmark = pytest.mark.unit


class FakeReporter:
    def __init__(self, topic):
        self.topic, self.values = topic, collections.Counter()

    def count(self, **counts):
        self.values.update(counts)

    def gauge(self, **values):
        self.values.update({k: v - self.values[k] for k, v in values.items()})


def test_only_the_cloud_routes_are_kept_and_their_counters_add_up():
    table = load_bridge_table(robots=["scout", "jackal"])
    outgoing = [r for r in table.outgoing("robots") if r.from_ros and is_cloud_route(r)]
    incoming = [r for r in table.incoming("twin") if is_cloud_route(r)]
    assert {r.robot for r in outgoing} == {"scout", "jackal"} and len(outgoing) == 2
    assert len(incoming) == 4  # each robot's managed cloud and its backfill keyframes
    sent = RouteLedger(outgoing, C.BRIDGE_OUT, FakeReporter)
    route = outgoing[0].to
    for seq in (1, 2, 4):
        sent.received(route, "/cloud_tissue", seq)
    sent.out(route)
    sent.out(route)
    sent.dropped(route, "outage")
    sent.count("/not/a/cloud", C.OUT)  # not a cloud route: ignored
    values = sent.reports[route].values
    assert sent.reports[route].topic == outgoing[0].topic
    assert values[C.key(C.BRIDGE_OUT, C.RECEIVED)] == 3 and values[C.key(C.BRIDGE_OUT, C.MISSED)] == 1
    assert values[C.key(C.BRIDGE_OUT, C.OUT)] == 2 and values[C.key(C.BRIDGE_OUT, "dropped_outage")] == 1


def test_the_twins_bridge_numbers_what_it_republishes():
    table = load_bridge_table(robots=["scout"])
    incoming = [r for r in table.incoming("twin") if is_cloud_route(r)]
    received = RouteLedger(incoming, C.BRIDGE_IN, FakeReporter)
    body = struct.pack("<I", 77) + b"rest of a cloud"
    first = received.renumbered(incoming[0].to, body)
    second = received.renumbered(incoming[0].to, body)
    assert (header_seq(first), header_seq(second)) == (1, 2) and first[4:] == body[4:]
    assert received.renumbered(names.absolute(names.robot_topic("scout", names.ODOM)), body) == body
    assert header_seq(with_header_seq(b"\0\0\0\0x", 2**32 + 5)) == 5
