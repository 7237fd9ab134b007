"""The LEGACY delay-based estimator (the bench's anchor) against a simulated bottleneck queue whose capacity goes 60 -> 20 -> 60
Mbit/s, with the sender obeying the estimate (as the manager's allocation does)."""

import math

import pytest

from cps_harness.legacy_estimation import LegacyDelayEstimator as BandwidthEstimator


def _simulate(capacity_of, duration_s=40.0, dt=0.5, demand_mbps=80.0, reserve=0.04, base_ms=2.0):
    """Fluid queue: offered = min(demand, budget from the estimate); queue grows at offered - capacity."""
    est = BandwidthEstimator(initial_mbps=60.0, max_mbps=60.0)
    queue_mbit, t, trace = 0.0, 0.0, []
    while t < duration_s:
        capacity = capacity_of(t)
        offered = min(demand_mbps, (1 - reserve) * est.estimate_mbps)
        delivered = min(capacity, offered + queue_mbit / dt)
        queue_mbit = max(0.0, queue_mbit + (offered - capacity) * dt)
        latency_ms = base_ms + 1000.0 * queue_mbit / capacity
        t += dt
        est.update(t, delivered, latency_ms, sent_mbps=offered)
        trace.append((t, capacity, est.estimate_mbps, latency_ms))
    return trace


def _capacity(t):
    return 20.0 if 10.0 <= t < 25.0 else 60.0


def test_estimate_tracks_60_20_60_within_a_few_seconds():
    trace = _simulate(_capacity)
    for t, capacity, estimate, latency in trace:
        settled = (3.0 <= t < 10.0) or (14.0 <= t < 25.0) or (32.0 <= t)
        if settled:
            # The estimate probes up to ~30 % above the capacity (one second of growth), like a
            # congestion controller, and comes back down at once.
            assert 0.6 * capacity <= estimate <= 1.3 * capacity, (t, capacity, estimate)
    # The queue built by the drop drains within 6 s; afterwards probing costs short latency spikes
    # (< 200 ms) while the median stays near the baseline.
    after = sorted(lat for t, _, _, lat in trace if 16.5 <= t < 25.0)
    assert after[-1] < 200.0 and after[len(after) // 2] < 30.0
    # The drop is detected within 2 s.
    assert min(est for t, _, est, _ in trace if 10.0 <= t <= 12.0) <= 22.0


def test_latency_without_a_building_queue_holds_the_estimate():
    """A busy receiver (latency up, but everything sent arrives) must not collapse the estimate."""
    est = BandwidthEstimator(initial_mbps=60.0)
    for i in range(10):
        est.update(i * 0.5, 50.0, 10.0, sent_mbps=50.0)
    for i in range(10, 30):
        est.update(i * 0.5, 48.0, 200.0, sent_mbps=50.0)
    assert est.estimate_mbps == 60.0
    # With the same latency and a queue building (sent well above delivered), it drops.
    est.update(15.0, 20.0, 400.0, sent_mbps=50.0)
    assert est.estimate_mbps <= 30.0


def test_a_stalled_link_halves_the_estimate_once_per_second():
    est = BandwidthEstimator(initial_mbps=60.0)
    est.update(0.0, 40.0, 5.0, sent_mbps=40.0)
    for i in range(1, 5):  # nothing arrives for 2 s while 40 Mbit/s are sent
        est.update(i * 0.5, 0.0, math.nan, sent_mbps=40.0)
    assert est.estimate_mbps == 15.0
    # Nothing sent and nothing received is not a stall.
    idle = BandwidthEstimator(initial_mbps=60.0)
    idle.update(0.0, 0.0, math.nan, sent_mbps=0.0)
    assert idle.estimate_mbps == 60.0 and idle.ignored_samples == 1


def test_estimate_never_exceeds_the_ceiling_and_ignores_bad_samples():
    est = BandwidthEstimator(initial_mbps=60.0, max_mbps=60.0)
    for i in range(20):
        est.update(i * 0.5, 500.0, 1.0)
    assert est.estimate_mbps == 60.0
    before = est.estimate_mbps
    for bad in ((11.0, math.nan, 1.0), (11.5, 10.0, math.inf), (12.0, -1.0, 1.0), (12.5, 10.0, -3.0)):
        assert est.update(*bad) == before
    assert est.ignored_samples == 4


def test_estimate_has_a_floor():
    est = BandwidthEstimator(initial_mbps=60.0, min_mbps=2.0)
    est.update(0.0, 10.0, 1.0)
    for i in range(1, 10):
        est.update(0.5 * i, 0.0, 500.0)
    assert est.estimate_mbps == 2.0


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(initial_mbps=0.0),
        dict(initial_mbps=-5.0),
        dict(initial_mbps=math.nan),
        dict(initial_mbps=10.0, drain_factor=1.5),
        dict(initial_mbps=10.0, max_mbps=0.5),
    ],
)
def test_bad_parameters_are_clear_errors(kwargs):
    with pytest.raises(ValueError):
        BandwidthEstimator(**kwargs)
