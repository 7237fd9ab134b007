"""The simulated link and its judges (what the estimator's tests and bench rely on)."""

import math

import pytest

from cps_harness.link_model import (
    CpuHog,
    LinkModel,
    TraceRow,
    held_below_offered,
    ingress_over_capacity_s,
    settle_time_s,
    steps_capacity,
)


class _Fixed:
    """A subject that never changes its estimate."""

    def __init__(self, mbps):
        self.estimate_mbps = self.capacity_mbps = mbps
        self.resumed = []

    def update(self, report, latency_ms):
        return self.estimate_mbps

    def resume(self, now_s):
        self.resumed.append(now_s)


def _row(t, capacity, estimate, ingress=0.0, offered=0.0, allowed=0.0, up=True):
    return TraceRow(t, capacity, estimate, estimate, allowed, ingress, ingress, offered, 0.0, up, False)


def test_the_queue_delivers_the_capacity_and_drops_beyond_its_limit():
    trace = LinkModel(steps_capacity([(0, 10)]), lambda t: 30.0, queue_limit_mbit=4.0).run(_Fixed(60.0), 5.0)
    assert all(r.delivered_mbps == pytest.approx(10.0) for r in trace)
    assert all(r.ingress_mbps == pytest.approx(30.0) for r in trace)
    assert trace[-1].queue_mbit == pytest.approx(4.0)


def test_an_outage_sends_no_report_and_the_link_health_follows_liveliness():
    subject = _Fixed(60.0)
    trace = LinkModel(steps_capacity([(0, 20), (5, 0), (10, 20)]), lambda t: 5.0).run(subject, 15.0)
    down = [r.t_s for r in trace if not r.link_up]
    assert down[0] == pytest.approx(6.0) and down[-1] == pytest.approx(10.0)
    assert subject.resumed == [pytest.approx(10.0, abs=0.02)]  # at the first tick the link carries again


def test_a_cpu_hog_caps_what_the_receiver_takes_and_says_it_is_behind():
    hog = CpuHog(2.0, 4.0, receiver_mbps=1.0)
    trace = LinkModel(steps_capacity([(0, 60)]), lambda t: 5.0, hogs=[hog]).run(_Fixed(60.0), 6.0)
    during = [r for r in trace if 2.5 <= r.t_s <= 4.0]
    assert all(r.delivered_mbps == pytest.approx(1.0) and r.receiver_behind for r in during)


def test_sliding_measurement_windows_lag_a_step():
    model = LinkModel(steps_capacity([(0, 60), (5, 10)]), lambda t: 30.0, measure_window_s=2.0)
    reports = []

    class Recorder(_Fixed):
        def update(self, report, latency_ms):
            reports.append(report)
            return self.estimate_mbps

    model.run(Recorder(60.0), 8.0)
    at = {round(r.now_s, 2): r.delivered_mbps for r in reports}
    assert at[5.0] == pytest.approx(30.0) and at[6.0] == pytest.approx(20.0) and at[7.0] == pytest.approx(10.0)


def test_settle_time_is_from_the_first_report_of_the_final_in_band_stretch():
    trace = [_row(0.5, 10, 60), _row(1.0, 10, 11), _row(1.5, 10, 13), _row(2.0, 10, 10), _row(2.5, 10, 10)]
    assert settle_time_s(trace, 0.0, 2.5) == pytest.approx(2.0)
    assert math.isinf(settle_time_s(trace[:3], 0.0, 1.5))


def test_the_goodput_is_the_rate_less_loss_and_the_other_way_and_can_be_the_judges_truth():
    """A shared medium at 5 Mbit/s with 2 % loss and 1 Mbit/s the other way carries 3.9 this way:
    a delivery-rate estimate at 3.9 is 22 % off the tc rate and right on what the link carries."""
    trace = LinkModel(steps_capacity([(0, 5)]), lambda t: 30.0, loss_fraction=0.02, reverse_mbps=1.0).run(
        _Fixed(3.9), 3.0
    )
    assert all(r.goodput_mbps == pytest.approx(3.9) for r in trace)
    assert math.isinf(settle_time_s(trace, 0.0, 3.0))
    assert settle_time_s(trace, 0.0, 3.0, truth="goodput_mbps") == pytest.approx(0.5)


def test_ingress_over_capacity_first_and_longest_runs():
    trace = [
        _row(0.5, 10, 10, ingress=30),
        _row(1.0, 10, 10, ingress=12),
        _row(1.5, 10, 10, ingress=9),
        _row(2.0, 10, 10, ingress=11),
        _row(2.5, 10, 10, ingress=9),
    ]
    assert ingress_over_capacity_s(trace, 0.0, 2.5) == (1.0, 0.5)


def test_held_below_offered_only_counts_loads_under_85_percent():
    trace = [
        _row(0.5, 10, 10, offered=8.0, allowed=7.0),
        _row(1.0, 10, 10, offered=9.0, allowed=7.0),
        _row(1.5, 10, 10, offered=8.0, allowed=9.6),
        _row(2.0, 10, 10, offered=8.0, allowed=1.0, up=False),
    ]
    assert [r.t_s for r in held_below_offered(trace)] == [0.5]
