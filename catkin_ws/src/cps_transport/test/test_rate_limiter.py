"""The rate limiter delivers the rate it is set to (unit, with injected time) and the node holds
1, 8, 15 and 30 Hz within 5 % on a faster input, with live rate changes by service and topic."""

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from cps_fleet import names
from cps_harness.testing import wait_for
from cps_transport.rate_limiter import RATE_WINDOW_S, RateLimiter, WindowRate

pytestmark = pytest.mark.waiting


def _forwarded_rate(limiter, input_hz, duration_s, jitter_s=0.0, seed=0):
    rng = np.random.default_rng(seed)
    times = np.arange(0.0, duration_s, 1.0 / input_hz)
    times += rng.uniform(0.0, jitter_s, len(times))
    forwarded = [t for t in np.sort(times) if limiter.allow(t)]
    return (len(forwarded) - 1) / (forwarded[-1] - forwarded[0])


def _throttle_rate(rate_hz, input_hz, duration_s):
    """topic_tools throttle's rule: forward if at least 1/rate passed since the last forward."""
    last, count = -1e9, 0
    for t in np.arange(0.0, duration_s, 1.0 / input_hz):
        if t - last >= 1.0 / rate_hz:
            last, count = t, count + 1
    return count / duration_s


@pytest.mark.parametrize("rate_hz", [1.0, 8.0, 15.0, 30.0])
@pytest.mark.parametrize("input_hz", [31.0, 60.0])
def test_delivers_the_set_rate_on_any_faster_input(rate_hz, input_hz):
    assert _forwarded_rate(RateLimiter(rate_hz), input_hz, 60.0, jitter_s=0.3 / input_hz) == pytest.approx(
        rate_hz, rel=0.01
    )


def test_ten_to_eight_hz_where_throttle_gives_five():
    assert _throttle_rate(8.0, 10.0, 60.0) == pytest.approx(5.0, rel=0.02)
    assert _forwarded_rate(RateLimiter(8.0), 10.0, 60.0) == pytest.approx(8.0, rel=0.01)


@pytest.mark.parametrize("input_hz", [10.0, 12.8, 20.0])
def test_a_burst_of_one_frame_still_delivers_the_set_rate(input_hz):
    """The managed video admits frames with a burst of 1: its fraction of credit must carry over,
    or a 12.8 Hz camera asked for 8 Hz sends every second frame (6.4 Hz, as CI once measured)."""
    assert _forwarded_rate(RateLimiter(8.0, burst=1.0), input_hz, 60.0) == pytest.approx(8.0, rel=0.01)


def test_after_a_pause_no_more_than_burst_messages_pass_back_to_back():
    for burst in (1.0, 2.0):
        limiter = RateLimiter(8.0, burst=burst)
        assert limiter.allow(0.0)
        passed = [limiter.allow(10.0 + k * 1e-3) for k in range(5)]  # 10 s idle, then 5 at once
        assert sum(passed) == burst


def test_slower_input_passes_untouched():
    limiter = RateLimiter(30.0)
    assert all(limiter.allow(t) for t in np.arange(0, 10, 0.1))


def test_rate_change_takes_effect_at_once_and_counts():
    limiter = RateLimiter(30.0)
    times = np.arange(0.0, 20.0, 1 / 60)
    before = [t for t in times[times < 10] if limiter.allow(t)]
    limiter.set_rate(2.0)
    after = [t for t in times[times >= 10] if limiter.allow(t)]
    assert len(before) == pytest.approx(300, abs=2)
    assert len(after) == pytest.approx(20, abs=2)
    assert after[1] - after[0] == pytest.approx(0.5, abs=0.02)
    assert limiter.received == len(times) and limiter.forwarded == len(before) + len(after)


def test_bad_rates_are_refused():
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="rate_hz"):
            RateLimiter(bad)
    limiter = RateLimiter(5.0)
    with pytest.raises(ValueError):
        limiter.set_rate(0.0)
    assert limiter.rate_hz == 5.0


def test_window_rate_and_mean_size():
    window = WindowRate(2.0)
    for i in range(100):
        window.add(i * 0.1, 1000 + (i % 2) * 200)
    assert window.rate_hz(9.9) == pytest.approx(10.0)
    assert window.mean_bytes(9.9) == pytest.approx(1100, rel=0.01)
    assert window.rate_hz(30.0) == 0.0


# --- the node -------------------------------------------------------------------------------------

NS = "/rl_test"
MESSAGE_BYTES = 1600


@pytest.fixture
def limiter(ros, rospy_node):
    """The rate_limiter node at 30 Hz, fed at 60 Hz; its output arrival times, its statuses (with when
    each was read) and the feeder's publish times."""
    rospy = rospy_node
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Float64

    from cps_msgs.msg import RateLimiterStatus
    from cps_msgs.srv import SetRate

    ros.start_node(
        "cps_transport",
        "rate_limiter",
        name=names.CLOUD_THROTTLE,
        namespace=NS,
        params={"~rate_hz": 30.0},
        remap={"~input": f"{NS}/in", "~output": f"{NS}/out"},
    )
    ros.wait_for_service(names.robot_topic(NS, names.private(names.CLOUD_THROTTLE, names.SET_RATE)), timeout_s=20)
    state = SimpleNamespace(rospy=rospy, arrivals=[], status_reads=[], fed_s=[], lock=threading.Lock())

    def on_out(_msg):
        with state.lock:
            state.arrivals.append(time.monotonic())

    out_sub = rospy.Subscriber(f"{NS}/out", PointCloud2, on_out)

    def on_status(msg):
        state.status_reads.append((time.monotonic(), msg))  # one append: read with its status

    status_sub = rospy.Subscriber(names.robot_topic(NS, names.LIMITER_STATUS), RateLimiterStatus, on_status)
    pub = rospy.Publisher(f"{NS}/in", PointCloud2, queue_size=10)
    stop = threading.Event()
    message = PointCloud2(height=1, width=100, point_step=16, row_step=MESSAGE_BYTES, data=bytes(MESSAGE_BYTES))

    def feed(input_hz=60.0):
        period, next_t = 1.0 / input_hz, time.monotonic()
        while not stop.is_set():
            pub.publish(message)
            state.fed_s.append(time.monotonic())
            next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    state.set_rate = rospy.ServiceProxy(
        names.robot_topic(NS, names.private(names.CLOUD_THROTTLE, names.SET_RATE)), SetRate
    )
    state.rate_topic = rospy.Publisher(names.robot_topic(NS, names.LIMITER_RATE_HZ), Float64, queue_size=1, latch=True)
    try:
        ros.wait_for_topic(f"{NS}/out", timeout_s=20)
        yield state
    finally:
        stop.set()
        feeder.join(2.0)
        for handle in (out_sub, status_sub, pub, state.rate_topic):
            handle.unregister()


@pytest.mark.ros
def test_node_holds_1_8_15_30_hz_within_5_percent(limiter):
    from std_msgs.msg import Float64

    measured = {}
    for rate_hz, duration_s, via_topic in ((30.0, 3.0, False), (15.0, 3.0, True), (8.0, 3.0, False), (1.0, 5.5, False)):
        if via_topic:
            limiter.rate_topic.publish(Float64(rate_hz))
        else:
            assert limiter.set_rate(rate_hz).success
        time.sleep(0.4)  # the old rate's credit is spent; within the manager's 1 s budget
        with limiter.lock:
            limiter.arrivals.clear()
        # Measured over the messages of about `duration_s` at the set rate.
        assert wait_for(lambda: len(limiter.arrivals) > rate_hz * duration_s, 3 * duration_s), rate_hz
        with limiter.lock:
            got = list(limiter.arrivals)
        measured[rate_hz] = (len(got) - 1) / (got[-1] - got[0])
    for rate_hz, value in measured.items():
        assert value == pytest.approx(rate_hz, rel=0.05), measured


@pytest.mark.ros
def test_node_refuses_a_zero_rate_and_reports_its_input(limiter):
    assert limiter.set_rate(1.0).success
    response = limiter.set_rate(0.0)
    asked = limiter.rospy.Time.now()
    assert not response.success and response.rate_hz == 1.0
    assert wait_for(
        lambda: (
            limiter.status_reads
            and limiter.status_reads[-1][1].header.stamp > asked
            and limiter.status_reads[-1][1].input_rate_hz > 0
        ),
        5.0,
    ), "no status after the refusal"
    read_s, status = limiter.status_reads[-1]
    assert status.set_rate_hz == 1.0
    # What the feeder sent over the node's window (RATE_WINDOW_S) before the status, measured as the node does
    # ((n - 1) / span): 60 Hz on average, faster after a stall it caught up on (n3a, a loaded machine:
    # 68 Hz reported, the feeder behind and catching up).
    fed = [t for t in list(limiter.fed_s) if read_s - RATE_WINDOW_S <= t <= read_s]
    sent_hz = (len(fed) - 1) / (fed[-1] - fed[0])
    assert status.input_rate_hz == pytest.approx(sent_hz, rel=0.1), (status.input_rate_hz, sent_hz)
    assert status.mean_message_bytes == pytest.approx(MESSAGE_BYTES + 60, rel=0.1)
    assert status.received > status.forwarded > 0
    assert status.input_topic == f"{NS}/in" and status.output_topic == f"{NS}/out"
