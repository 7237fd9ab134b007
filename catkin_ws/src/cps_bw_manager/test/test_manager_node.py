"""The bandwidth_manager node with cps_transport's real rate_limiter nodes: measured sizes, mission
states, operator priorities, bad input and the CSV log."""
import csv
import math
import threading
import time

import pytest

pytestmark = pytest.mark.ros

ROBOTS = ("scout", "jackal")
PAYLOAD_BYTES = 20000


def _wait_for(predicate, timeout_s, what):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


class _Latest:
    def __init__(self, rospy, topic, cls, key=None):
        self.msgs = {}
        self.sub = rospy.Subscriber(topic, cls, self._on)
        self.key = key

    def _on(self, msg):
        self.msgs[self.key(msg) if self.key else None] = msg


@pytest.fixture
def graph(ros, rospy_node, tmp_path):
    """Two rate limiters fed at 20 Hz with 20 kB clouds, and the manager on a 2 Mbit/s budget."""
    rospy = rospy_node
    from std_msgs.msg import String

    from cps_msgs.msg import CompressedPointCloud2

    for r in ROBOTS:
        ros.start_node("cps_transport", "rate_limiter", name="cloud_throttle", namespace=f"/{r}",
                       remap={"~input": f"/{r}/points_filtered/draco",
                              "~output": f"/{r}/points_filtered/draco/managed"})
    csv_path = tmp_path / "allocation.csv"
    ros.start_node("cps_bw_manager", "bandwidth_manager", name="bandwidth_manager",
                   params={"~robots": list(ROBOTS), "~available_mbps": 2.0, "~csv_path": str(csv_path)})
    ros.wait_for_service("/tissue/set_priority")
    pubs = {r: rospy.Publisher(f"/{r}/points_filtered/draco", CompressedPointCloud2, queue_size=2) for r in ROBOTS}
    mission = {r: rospy.Publisher(f"/{r}/mission_state", String, queue_size=1, latch=True) for r in ROBOTS}
    stop = threading.Event()

    def feed():
        msg = CompressedPointCloud2(format="draco", compressed_data=bytes(PAYLOAD_BYTES))
        while not stop.is_set():
            for pub in pubs.values():
                msg.header.stamp = rospy.Time.now()
                pub.publish(msg)
            time.sleep(0.05)

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        yield rospy, mission, csv_path
    finally:
        stop.set()
        feeder.join(2.0)
        for pub in list(pubs.values()) + list(mission.values()):
            pub.unregister()


def test_manager_sets_limiter_rates_from_sizes_states_and_operator(ros, graph):
    rospy, mission, csv_path = graph
    from std_msgs.msg import String

    from cps_msgs.msg import BandwidthAllocationArray, RateLimiterStatus
    from cps_msgs.srv import SetPriority

    alloc = _Latest(rospy, "/tissue/allocation", BandwidthAllocationArray)
    status = {r: _Latest(rospy, f"/{r}/cloud_throttle/status", RateLimiterStatus) for r in ROBOTS}

    def allocation():
        msg = alloc.msgs.get(None)
        return {a.robot: a for a in msg.allocations} if msg else {}

    def in_force(expected):
        """Every limiter runs the rate the manager last allocated, and that matches `expected`."""
        current = allocation()
        if not current:
            return False
        for r in ROBOTS:
            s = status[r].msgs.get(None)
            if s is None or not math.isclose(s.set_rate_hz, current[r].rate_hz, rel_tol=1e-6):
                return False
        return expected(current)

    from std_msgs.msg import Float64

    available = rospy.wait_for_message("/tissue/available_bandwidth", Float64, timeout=10.0)
    assert available.data == pytest.approx(2.0)
    budget = 0.96 * 2.0 / 8.0
    # Sizes measured by the limiters (serialized message, a little above the payload); equal shares.
    _wait_for(lambda: in_force(lambda a: all(PAYLOAD_BYTES < a[r].message_bytes < PAYLOAD_BYTES + 1000 for r in ROBOTS)
                               and math.isclose(a["scout"].rate_hz, a["jackal"].rate_hz, rel_tol=1e-6)),
              20.0, "equal rates from measured sizes")
    a = allocation()
    assert sum(x.bandwidth_mbytes_per_s for x in a.values()) <= budget * (1 + 1e-9)
    # Room for one extra message per robot per 1 s window is kept (~headroom_messages).
    size = a["scout"].message_bytes / 1e6
    assert a["scout"].rate_hz == pytest.approx((budget - 2 * size) / 2 / size, rel=1e-6)

    # Inspecting -> priority 1 -> 4x the bandwidth of the normal robot.
    mission["scout"].publish(String("inspecting"))
    _wait_for(lambda: in_force(lambda a: a["scout"].priority == 1 and math.isclose(
        a["scout"].bandwidth_mbytes_per_s / a["jackal"].bandwidth_mbytes_per_s, 4.0, rel_tol=1e-3)),
        5.0, "scout at priority 1")

    # Done -> the minimum rate.
    mission["jackal"].publish(String("done"))
    _wait_for(lambda: in_force(lambda a: a["jackal"].rate_hz == pytest.approx(1.0)), 5.0, "jackal at 1 Hz")

    set_priority = rospy.ServiceProxy("/tissue/set_priority", SetPriority)
    bad = set_priority(robot="nobody", priority=1)
    assert not bad.success and "unknown robot" in bad.message
    bad = set_priority(robot="jackal", priority=2)
    assert not bad.success and "priority must be 0" in bad.message
    ok = set_priority(robot="jackal", priority=1)
    assert ok.success
    _wait_for(lambda: in_force(lambda a: a["jackal"].priority == 1 and math.isclose(
        a["jackal"].rate_hz, a["scout"].rate_hz, rel_tol=0.1)), 5.0, "jackal raised by the operator")

    # Bad input on the wire does not kill the node.
    bogus = rospy.Publisher("/scout/cloud_throttle/status", RateLimiterStatus, queue_size=5)
    time.sleep(0.5)
    for size in (-5.0, math.inf):
        bogus.publish(RateLimiterStatus(mean_message_bytes=size, input_rate_hz=10.0))
    mission["scout"].publish(String("flying"))
    time.sleep(1.0)
    bogus.unregister()
    stamp = alloc.msgs[None].header.stamp
    _wait_for(lambda: alloc.msgs[None].header.stamp > stamp, 3.0, "allocations after bad input")
    log = ros.output("bandwidth_manager")
    assert "not a size" in log and "unknown mission state" in log

    with open(csv_path) as stream:
        rows = list(csv.DictReader(stream))
    assert {r["robot"] for r in rows} == set(ROBOTS)
    assert any(r["mission_state"] == "done" for r in rows)
    assert all(float(r["rate_hz"]) > 0 for r in rows)
    for sub in [alloc.sub] + [s.sub for s in status.values()]:
        sub.unregister()


@pytest.mark.parametrize("params, match", [
    ({"~available_mbps": -5.0}, "available bandwidth must be > 0"),
    ({"~available_mbps": 0.0}, "available bandwidth must be > 0"),
    ({"~reserve_fraction": 1.0}, "reserve_fraction must be in"),
    ({"~min_rate_hz": 40.0}, "min_rate_hz"),
    ({"~robots": ["scout", "nobody"]}, "unknown robot"),
    ({"~update_rate_hz": 0.5}, "update_rate_hz"),
    ({"~headroom_messages": -1.0}, "headroom_messages"),
])
def test_bad_parameters_stop_the_node_with_a_clear_message(ros, params, match):
    name = f"bad_manager_{abs(hash(match)) % 10**6}"  # private params outlive a node on the master
    proc = ros.start_node("cps_bw_manager", "bandwidth_manager", name=name, params=params)
    assert proc.wait(30) == 2
    assert match in ros.output(name)
