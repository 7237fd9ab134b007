"""The bandwidth_manager node with stream levels, on a private master: the operator's selection
raises that robot's video to operator quality within one manager period, and a lower insertion
capacity reported by the map server lowers the fleet's cloud rates."""

import time
from types import SimpleNamespace

import pytest

from cps_fleet import names
from cps_harness.testing import TopicRecorder

pytestmark = pytest.mark.ros

ROBOTS = ("scout", "jackal", "champ")  # scout: lidar, no camera
UPDATE_RATE_HZ = 1.0  # one manager period: 1 s


@pytest.fixture
def graph(ros, rospy_node):
    rospy = rospy_node
    from std_msgs.msg import Float64, String, UInt8

    from cps_msgs.msg import BandwidthAllocationArray, InsertCapacity

    ros.start_node(
        "cps_bw_manager",
        "bandwidth_manager",
        name="bandwidth_manager",
        params={"~robots": list(ROBOTS), "~available_mbps": 4.0, "~update_rate_hz": UPDATE_RATE_HZ},
    )
    ros.wait_for_service(names.absolute(names.SET_PRIORITY))
    allocation = TopicRecorder(names.absolute(names.ALLOCATION), BandwidthAllocationArray)
    video_level = TopicRecorder(names.absolute(names.robot_topic("jackal", names.VIDEO_LEVEL)), UInt8)
    video_rate = TopicRecorder(names.absolute(names.robot_topic("jackal", names.VIDEO_RATE_HZ)), Float64)
    cloud_rates = {
        r: TopicRecorder(names.absolute(names.robot_topic(r, names.LIMITER_RATE_HZ)), Float64) for r in ROBOTS
    }
    selected = rospy.Publisher(names.absolute(names.SELECTED_ROBOT), String, queue_size=1, latch=True)
    capacity = rospy.Publisher(
        names.absolute(names.in_twin(names.INSERT_CAPACITY)), InsertCapacity, queue_size=1, latch=True
    )
    recorders = [allocation, video_level, video_rate, *cloud_rates.values()]
    encoders = _Encoders(rospy, ROBOTS, ("jackal", "champ"))
    try:
        yield SimpleNamespace(
            rospy=rospy,
            allocation=allocation,
            video_level=video_level,
            video_rate=video_rate,
            cloud_rates=cloud_rates,
            selected=selected,
            capacity=capacity,
            InsertCapacity=InsertCapacity,
            String=String,
        )
    finally:
        encoders.stop()
        for recorder in recorders:
            recorder.close()
        selected.unregister()
        capacity.unregister()


class _Encoders:
    """The robots' encoders as the manager hears them: every robot's cloud at leaf 0.10 (level 1,
    11 kB) and every camera robot's video at 160x120 (level 2, 2.5 kB), statuses at 2 Hz (the
    manager sends a stream no setpoint before its encoder said what it runs)."""

    def __init__(self, rospy, robots, cameras):
        import threading

        from cps_msgs.msg import RateLimiterStatus

        self.stop_event = threading.Event()
        pubs = [
            (
                rospy.Publisher(
                    names.absolute(names.robot_topic(r, names.LIMITER_STATUS)), RateLimiterStatus, queue_size=2
                ),
                1,
                11000.0,
            )
            for r in robots
        ] + [
            (
                rospy.Publisher(
                    names.absolute(names.robot_topic(r, names.VIDEO_STATUS)), RateLimiterStatus, queue_size=2
                ),
                2,
                2500.0,
            )
            for r in cameras
        ]

        def run():
            while not self.stop_event.wait(0.5):
                for pub, level, size in pubs:
                    pub.publish(
                        RateLimiterStatus(
                            mean_message_bytes=size,
                            input_rate_hz=5.0,
                            output_rate_hz=5.0,
                            level=level,
                            level_mean_message_bytes=size,
                        )
                    )

        self.pubs = [p for p, _, _ in pubs]
        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()

    def stop(self):
        self.stop_event.set()
        self.thread.join(2.0)
        for pub in self.pubs:
            pub.unregister()


def _streams(msg):
    return {(a.robot, a.stream): a for a in msg.allocations}


def test_selecting_a_robot_raises_its_video_to_operator_quality_within_one_period(graph):
    from cps_fleet.fleet import load_fleet

    streams = load_fleet().streams
    first = graph.allocation.wait(lambda m: ("jackal", "video") in _streams(m), 20.0, "an allocation with videos")
    assert ("scout", "video") not in _streams(first)
    before = _streams(first)[("jackal", "video")]
    assert before.level > streams.operator_video_level  # unselected: not at operator quality yet
    graph.video_level.wait(timeout_s=10.0, what="the latched video level")
    graph.video_rate.wait(timeout_s=10.0, what="the latched video rate")
    assert graph.selected.get_num_connections() > 0 or _wait_connected(graph.selected)
    sent = time.monotonic()
    graph.selected.publish(graph.String("jackal"))
    level = graph.video_level.wait(lambda m: m.data <= streams.operator_video_level, 10.0, "operator level")
    rate = graph.video_rate.wait(lambda m: m.data >= streams.operator_video_rate_hz, 10.0, "operator rate")
    arrived = max(graph.video_level.messages[-1][0], graph.video_rate.messages[-1][0])
    assert arrived - sent <= 1.0 / UPDATE_RATE_HZ, f"took {arrived - sent:.3f} s (one period: {1 / UPDATE_RATE_HZ} s)"
    assert level.data <= streams.operator_video_level and rate.data >= streams.operator_video_rate_hz
    after = graph.allocation.wait(
        lambda m: _streams(m)[("jackal", "video")].level <= streams.operator_video_level, 5.0, "the allocation"
    )
    video = _streams(after)[("jackal", "video")]
    assert video.level_name == streams.video_levels[video.level].name and video.priority == 1
    assert after.allocated_mbytes_per_s <= after.budget_mbytes_per_s * (1 + 1e-9)


def _wait_connected(pub, timeout_s=10.0):
    from cps_harness.testing import wait_for

    return wait_for(lambda: pub.get_num_connections() > 0, timeout_s)


def test_a_lower_insertion_capacity_lowers_the_fleets_cloud_rates(graph):
    first = graph.allocation.wait(lambda m: len(m.allocations) > 0, 20.0, "a first allocation")
    clouds_before = sum(a.rate_hz for a in first.allocations if a.stream == "cloud")
    assert clouds_before > 6.0  # 4 Mbit/s carries the three clouds well above 2 Hz each
    assert _wait_connected(graph.capacity), (
        f"the manager never subscribed to {names.absolute(names.in_twin(names.INSERT_CAPACITY))}"
    )
    stamp = graph.rospy.Time.now()
    graph.capacity.publish(graph.InsertCapacity(window_s=2.0, clouds_per_s=6.0, points_per_s=1e6))
    held = graph.allocation.wait(
        lambda m: (
            m.header.stamp >= stamp and sum(a.rate_hz for a in m.allocations if a.stream == "cloud") <= 6.0 + 1e-6
        ),
        10.0,
        "cloud rates within the insertion capacity",
    )
    rates = {a.robot: a.rate_hz for a in held.allocations if a.stream == "cloud"}
    assert all(rate >= 1.0 for rate in rates.values())  # the floors hold
    for robot, recorder in graph.cloud_rates.items():  # and the limiters are told
        recorder.wait(lambda m, r=robot: abs(m.data - rates[r]) < 1e-6, 5.0, f"{robot}'s limiter rate")
