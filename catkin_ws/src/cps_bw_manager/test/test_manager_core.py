"""ManagerCore: measured sizes and input rates, mission states, operator priorities and bad input."""

import math
from types import SimpleNamespace

import pytest

from cps_bw_manager.estimation import DeliveryRateEstimator
from cps_bw_manager.manager import (
    ALLOCATION_CSV_COLUMNS,
    ManagerCore,
    ManagerSettings,
    allocation_csv_rows,
    link_totals,
)

SETTINGS = ManagerSettings(
    available_mbps=60.0, reserve_fraction=0.04, min_rate_hz=1.0, max_rate_hz=30.0, headroom_messages=0.0
)


def _core(**kwargs):
    return ManagerCore(["a", "b"], SETTINGS, **kwargs)


def test_measured_sizes_drive_the_allocation():
    core = _core()
    assert core.on_limiter_status("a", 200000.0, 50.0, now_s=0.0)
    assert core.on_limiter_status("b", 200000.0, 50.0, now_s=0.0)
    assert not core.on_limiter_status("a", 210000.0, 50.0, now_s=0.0)  # < 10 %: no immediate update needed
    result = core.allocate()
    assert result.allocated_mbytes_per_s == pytest.approx(7.2)
    assert all(r.size_measured for r in result.robots)


def test_headroom_keeps_room_for_one_message_per_robot_per_window():
    import dataclasses

    core = ManagerCore(["a", "b"], dataclasses.replace(SETTINGS, headroom_messages=1.0))
    core.on_limiter_status("a", 200000.0, 50.0, now_s=0.0)
    core.on_limiter_status("b", 200000.0, 50.0, now_s=0.0)
    result = core.allocate()
    assert result.budget_mbytes_per_s == pytest.approx(7.2)
    assert result.allocated_mbytes_per_s == pytest.approx(7.2 - 0.4)
    assert sum(r.share_percent for r in result.robots) == pytest.approx(100 * 6.8 / 7.2)


def test_two_subscribers_across_the_link_halve_the_rates():
    import dataclasses

    one = ManagerCore(["a", "b"], SETTINGS)
    two = ManagerCore(["a", "b"], dataclasses.replace(SETTINGS, copies_on_link=2))
    for core in (one, two):
        core.on_limiter_status("a", 300000.0, 50.0, now_s=0.0)
        core.on_limiter_status("b", 300000.0, 50.0, now_s=0.0)
    assert two.allocate().rates_hz()["a"] == pytest.approx(one.allocate().rates_hz()["a"] / 2)
    assert two.allocate().allocated_mbytes_per_s == pytest.approx(7.2)


def test_input_rate_caps_the_maximum_and_frees_bandwidth_for_the_others():
    core = _core()
    core.on_limiter_status("a", 300000.0, 5.0, now_s=0.0)  # a only produces 5 Hz
    core.on_limiter_status("b", 300000.0, 50.0, now_s=0.0)
    rates = core.allocate().rates_hz()
    assert rates["a"] == pytest.approx(5.5)
    assert rates["b"] == pytest.approx((7.2 - 5.5 * 0.3) / 0.3)


def test_a_done_robot_yields_first_when_the_link_binds_and_the_operator_can_raise_it():
    core = _core()
    for r in "ab":
        core.on_limiter_status(r, 300000.0, 50.0, now_s=0.0)
        core.on_mission_state(r, "inspecting")
    assert core.on_mission_state("a", "done")
    rates = core.allocate().rates_hz()
    # 7.2 MB/s of 0.3 MB clouds: 24 Hz shared by weight, the finished robot's 0.25 against 4.
    assert rates["a"] == pytest.approx(24.0 * 0.25 / 4.25) and rates["b"] == pytest.approx(24.0 * 4.0 / 4.25)
    ok, message = core.set_priority("a", 1)
    assert ok and "until its mission state changes" in message
    rates = core.allocate().rates_hz()
    assert rates["a"] == pytest.approx(rates["b"])


def test_a_done_robot_keeps_the_rate_its_stream_sustains_while_the_link_has_room():
    """Issue 36: nothing pinned without a reason (it was pinned at 1 Hz, capping the fleet's
    slowest window); the paper's pin is still there as pin_done."""
    core = _core()
    for r in "ab":
        core.on_limiter_status(r, 30000.0, 5.0, now_s=0.0)  # 5 Hz sensors, 0.15 MB/s each: room
    core.on_mission_state("a", "done")
    assert core.allocate().rates_hz()["a"] == pytest.approx(5.5)  # its input rate + 10 %
    import dataclasses

    paper = ManagerCore(["a", "b"], dataclasses.replace(SETTINGS, pin_done=True))
    paper.on_limiter_status("a", 30000.0, 5.0, now_s=0.0)
    paper.on_mission_state("a", "done")
    assert paper.allocate().rates_hz()["a"] == pytest.approx(1.0)


@pytest.mark.parametrize("robot, priority", [("nobody", 1), ("a", 2), ("a", 255)])
def test_bad_set_priority_is_refused_with_a_message(robot, priority):
    core = _core()
    ok, message = core.set_priority(robot, priority)
    assert not ok and ("unknown robot" in message or "priority must be" in message)
    assert core.invalid_inputs == 1


def test_unmeasured_sizes_are_safe_and_bad_sizes_are_refused():
    core = _core()
    assert not core.on_limiter_status("a", 0.0, 0.0, now_s=0.0)
    assert not core.on_limiter_status("a", math.nan, 0.0, now_s=0.0)
    with pytest.raises(ValueError, match="not a size"):
        core.on_limiter_status("a", -3.0, 10.0, now_s=0.0)
    with pytest.raises(ValueError, match="not a size"):
        core.on_limiter_status("a", math.inf, 10.0, now_s=0.0)
    with pytest.raises(KeyError):
        core.on_limiter_status("nobody", 1000.0, 10.0, now_s=0.0)
    result = core.allocate()
    assert not any(r.size_measured for r in result.robots)
    assert result.allocated_mbytes_per_s <= 7.2 + 1e-9


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(available_mbps=0.0), "available"),
        (dict(available_mbps=-60.0), "available"),
        (dict(reserve_fraction=1.0), "reserve"),
        (dict(reserve_fraction=-0.5), "reserve"),
        (dict(min_rate_hz=40.0), "min_rate_hz"),
        (dict(max_rate_hz=math.nan), "max_rate_hz"),
        (dict(high_priority_weight=0.0), "high_priority_weight"),
        (dict(headroom_messages=-1.0), "headroom_messages"),
        (dict(window_s=0.0), "window_s"),
        (dict(copies_on_link=0), "copies_on_link"),
        (dict(copies_on_link=1.5), "copies_on_link"),
        (dict(input_rate_hold_s=-1.0), "input_rate_hold_s"),
        (dict(input_rate_hold_s=math.nan), "input_rate_hold_s"),
    ],
)
def test_bad_settings_name_the_parameter(change, match):
    import dataclasses

    with pytest.raises(ValueError, match=match):
        ManagerCore(["a"], dataclasses.replace(SETTINGS, **change))


def test_an_announced_capacity_replaces_the_configured_one_as_the_budgets_basis():
    core = _core()
    for r in "ab":
        core.on_limiter_status(r, 200000.0, 50.0, now_s=0.0)
    assert core.allocate().budget_mbytes_per_s == pytest.approx(0.96 * 60.0 / 8)
    assert core.capacity_source == "configured"
    assert core.set_capacity_mbps(5.0, "tc scenario wifi_degraded")
    assert core.available_mbps == 5.0
    assert core.capacity_source == "announced by tc scenario wifi_degraded"
    result = core.allocate()
    assert result.budget_mbytes_per_s == pytest.approx(0.96 * 5.0 / 8)  # the reserve applied as before
    assert result.allocated_mbytes_per_s <= result.budget_mbytes_per_s * (1 + 1e-9)
    assert not core.set_capacity_mbps(5.0, "tc scenario wifi_degraded")  # the same: nothing changed
    assert core.set_capacity_mbps(60.0, "tc scenario wifi_degraded")  # back up
    assert core.allocate().budget_mbytes_per_s == pytest.approx(0.96 * 60.0 / 8)


@pytest.mark.parametrize("bad", [math.nan, 0.0, -5.0, math.inf, -math.inf, None, "fast", True])
def test_a_bad_announced_capacity_is_refused_and_the_last_good_one_kept(bad):
    core = _core()
    with pytest.raises(ValueError, match="not a capacity.*keeping the configured"):
        core.set_capacity_mbps(bad, "modem")
    assert core.available_mbps == 60.0 and core.invalid_inputs == 1
    core.set_capacity_mbps(20.0, "modem")
    with pytest.raises(ValueError, match="keeping 20 Mbit/s announced"):
        core.set_capacity_mbps(bad, "modem")
    assert core.available_mbps == 20.0 and core.invalid_inputs == 2
    assert core.allocate().budget_mbytes_per_s == pytest.approx(0.96 * 20.0 / 8)


def test_an_announced_capacity_bounds_the_estimator_and_restarts_it_there():
    """With the estimator on, the announcement is its ceiling and new prior: a step down is
    followed at once, a step up too (not probed up for), and no estimate goes above it."""
    core = _core(estimator=DeliveryRateEstimator(initial_mbps=60.0))
    for r in "ab":  # 15 Hz x 200 kB = 24 Mbit/s each forwarded, 160 Mbit/s offered
        core.on_limiter_status(r, 200000.0, 50.0, 15.0, now_s=0.0)
    core.on_link_stats(0.0, 48.0)
    assert core.set_capacity_mbps(5.0, "tc", now_s=0.5)
    assert core.available_mbps == 5.0 and core.estimator.line_rate_mbps == 5.0
    assert core.capacity_source == "estimated online, at most the capacity announced by tc"
    for i in range(2, 40):  # the link delivers all it can: nothing says it is wider
        core.on_link_stats(0.5 * i, 5.0)
        assert core.available_mbps <= 5.0 * (1 + 1e-9)
    assert core.set_capacity_mbps(60.0, "tc", now_s=20.0)
    assert core.available_mbps == 60.0
    assert core.allocate().budget_mbytes_per_s == pytest.approx(0.96 * 60.0 / 8)


def test_an_announcement_before_any_link_report_sets_the_estimators_prior():
    core = _core(estimator=DeliveryRateEstimator(initial_mbps=60.0, min_mbps=1.0))
    assert core.set_capacity_mbps(0.5, "modem")  # below the estimator's floor: the floor follows
    assert core.available_mbps == 0.5 and core.estimator.min_mbps == 0.5


def test_estimator_lowers_the_budget_when_the_link_saturates():
    core = _core(estimator=DeliveryRateEstimator(initial_mbps=60.0))
    for r in "ab":  # the limiters forward 15 Hz x 200 kB = 24 Mbit/s each, of 50 Hz offered
        core.on_limiter_status(r, 200000.0, 50.0, 15.0, now_s=0.0)
    assert core.sent_mbps() == pytest.approx(48.0)
    assert core.offered_mbps() == pytest.approx(160.0)
    assert not core.on_link_stats(0.0, 48.0)
    # The link delivers 20 of the 48 Mbit/s sent: it is full at 20, the target is cut to 0.85 x 20.
    assert core.on_link_stats(0.5, 20.0)
    assert core.estimator.capacity_mbps == pytest.approx(20.0)
    assert core.available_mbps == pytest.approx(17.0)
    assert core.allocate().budget_mbytes_per_s == pytest.approx(0.96 * core.available_mbps / 8)


def test_estimator_is_not_lowered_by_an_app_limited_fleet():
    """The fleet offers 8 Mbit/s and all of it arrives: nothing says the link is narrower."""
    core = _core(estimator=DeliveryRateEstimator(initial_mbps=60.0))
    for r in "ab":
        core.on_limiter_status(r, 50000.0, 10.0, 10.0, now_s=0.0)
    for i in range(20):
        core.on_link_stats(0.5 * i, 8.0)
    assert core.available_mbps == 60.0


def test_a_full_link_report_keeps_a_busy_twin_apart_from_the_link():
    """With the bridge's report (receiver behind, RTT), a twin that drains 2 of 48 Mbit/s is the
    twin's capacity; the link's estimate and the budget stay."""
    from cps_bw_manager.estimation import LinkReport

    core = _core(estimator=DeliveryRateEstimator(initial_mbps=60.0))
    for i in range(1, 10):
        core.on_link_report(
            LinkReport(
                now_s=0.5 * i,
                interval_s=0.5,
                delivered_mbps=2.0,
                sent_mbps=48.0,
                offered_mbps=48.0,
                app_limited=False,
                rtt_s=(0.05 + 0.1 * i,),
                receiver_behind=True,
            )
        )
    assert core.available_mbps == 60.0 and core.estimator.twin_capacity_mbps == 2.0
    core.on_link_state(False, since_s=5.0)  # while down, not fed
    assert not core.on_link_report(LinkReport(now_s=5.5, interval_s=0.5, delivered_mbps=1.0, sent_mbps=48.0))


def test_link_totals_from_topic_stats():
    topics = [
        SimpleNamespace(managed=True, messages=10, bandwidth_mbytes_per_s=1.0, latency_avg_ms=5.0),
        SimpleNamespace(managed=True, messages=0, bandwidth_mbytes_per_s=0.0, latency_avg_ms=math.nan),
        SimpleNamespace(managed=False, messages=50, bandwidth_mbytes_per_s=0.25, latency_avg_ms=500.0),
    ]
    delivered, latency = link_totals(topics)
    assert delivered == pytest.approx(10.0) and latency == 5.0
    assert all(math.isnan(v) for v in link_totals([]))


def test_one_allocation_csv_row_per_robot_with_every_column():
    core = _core()
    core.on_limiter_status("a", 200000.0, 50.0, now_s=0.0)
    rows = allocation_csv_rows(12.5, 60.0, core.allocate(), {"a": "inspecting", "b": "idle"})
    assert [row[4] for row in rows] == ["a", "b"]
    assert all(len(row) == len(ALLOCATION_CSV_COLUMNS) for row in rows)
    assert rows[0][:4] == ("12.500", "60.000", "7.2000", 1) and rows[0][6] == "inspecting"
