"""Properties of allocate_frequencies over many random fleets, and its bad-input handling."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog

from cps_bw_manager.allocation import (
    DEFAULT_PRIORITY_WEIGHTS,
    RobotDemand,
    allocate_frequencies,
    managed_budget_mbytes_per_s,
    water_fill,
)

REL = 1e-7


@st.composite
def fleets(draw, min_robots=1, max_robots=12):
    n = draw(st.integers(min_robots, max_robots))
    demands = []
    for i in range(n):
        fmin = draw(st.floats(0.2, 5.0))
        fmax = draw(st.floats(fmin, 40.0))
        demands.append(
            RobotDemand(
                name=f"r{i}",
                message_bytes=draw(st.floats(500.0, 300000.0)),
                priority=draw(st.sampled_from([0, 1])),
                min_rate_hz=fmin,
                max_rate_hz=fmax,
            )
        )
    budget = draw(st.floats(0.005, 20.0))
    return demands, budget


def _bw(result):
    return np.array([r.bandwidth_mbytes_per_s for r in result.robots])


@settings(max_examples=400, deadline=None)
@given(fleets())
def test_budget_never_exceeded_and_bounds_respected(case):
    demands, budget = case
    result = allocate_frequencies(demands, budget)
    assert result.allocated_mbytes_per_s <= budget * (1 + REL)
    assert _bw(result).sum() <= budget * (1 + REL)
    for d, r in zip(demands, result.robots):
        assert 0 < r.rate_hz <= d.max_rate_hz * (1 + REL)
        assert math.isclose(r.bandwidth_mbytes_per_s, r.rate_hz * d.message_bytes / 1e6, rel_tol=1e-9)
        if result.feasible:
            assert r.rate_hz >= d.min_rate_hz * (1 - REL)
            assert not r.degraded


@settings(max_examples=400, deadline=None)
@given(fleets())
def test_budget_used_up_unless_everyone_is_at_maximum(case):
    demands, budget = case
    result = allocate_frequencies(demands, budget)
    all_max = sum(d.message_bytes * d.max_rate_hz for d in demands) / 1e6
    if all_max <= budget:
        assert all(math.isclose(r.rate_hz, d.max_rate_hz, rel_tol=1e-9) for d, r in zip(demands, result.robots))
    else:
        assert math.isclose(result.allocated_mbytes_per_s, budget, rel_tol=1e-6)


@settings(max_examples=400, deadline=None)
@given(fleets(min_robots=2))
def test_weighted_max_min_fairness(case):
    """Robots strictly inside their bounds get bandwidth proportional to their priority's weight;
    a robot at its maximum gets no more than that level, one at its minimum no less."""
    demands, budget = case
    result = allocate_frequencies(demands, budget)
    if not result.feasible:
        return
    levels = []
    for d, r in zip(demands, result.robots):
        level = r.bandwidth_mbytes_per_s / DEFAULT_PRIORITY_WEIGHTS[d.priority]
        at_min = r.rate_hz <= d.min_rate_hz * (1 + 1e-6)
        at_max = r.rate_hz >= d.max_rate_hz * (1 - 1e-6)
        levels.append((level, at_min, at_max))
    free = [lvl for lvl, at_min, at_max in levels if not at_min and not at_max]
    if free:
        lam = free[0]
        assert all(math.isclose(lvl, lam, rel_tol=1e-6) for lvl in free)
        for lvl, at_min, at_max in levels:
            if at_max and not at_min:
                assert lvl <= lam * (1 + 1e-6)
            if at_min and not at_max:
                assert lvl >= lam * (1 - 1e-6)


@settings(max_examples=200, deadline=None)
@given(st.integers(2, 10), st.floats(1000.0, 200000.0), st.floats(0.01, 10.0))
def test_equal_priority_equal_size_gives_equal_rates(n, size, budget):
    demands = [RobotDemand(f"r{i}", size, 1, 1.0, 30.0) for i in range(n)]
    rates = [r.rate_hz for r in allocate_frequencies(demands, budget).robots]
    assert max(rates) - min(rates) <= 1e-9 * max(rates)


@settings(max_examples=400, deadline=None)
@given(fleets(), st.data())
def test_monotone_in_priority(case, data):
    demands, budget = case
    i = data.draw(st.integers(0, len(demands) - 1))
    low = [
        d if k != i else RobotDemand(d.name, d.message_bytes, 0, d.min_rate_hz, d.max_rate_hz)
        for k, d in enumerate(demands)
    ]
    high = [
        d if k != i else RobotDemand(d.name, d.message_bytes, 1, d.min_rate_hz, d.max_rate_hz)
        for k, d in enumerate(demands)
    ]
    rate_low = allocate_frequencies(low, budget).robots[i].rate_hz
    rate_high = allocate_frequencies(high, budget).robots[i].rate_hz
    assert rate_high >= rate_low * (1 - 1e-7)


@settings(max_examples=400, deadline=None)
@given(fleets())
def test_graceful_when_minimum_rates_do_not_fit(case):
    demands, budget = case
    need = sum(d.message_bytes * d.min_rate_hz for d in demands) / 1e6
    result = allocate_frequencies(demands, budget)
    assert result.feasible == (need <= budget)
    if result.feasible:
        return
    assert "infeasible" in result.status
    assert math.isclose(result.allocated_mbytes_per_s, budget, rel_tol=1e-6)
    robots = list(zip(demands, result.robots))
    assert any(r.degraded for _, r in robots)
    # Low priority degrades first: while a high-priority robot is below its minimum, every
    # low-priority robot is at the floor (0.1 Hz or its own minimum if lower) or below.
    if any(d.priority == 1 and r.degraded for d, r in robots):
        for d, r in robots:
            if d.priority == 0:
                assert r.rate_hz <= min(d.min_rate_hz, 0.1) * (1 + 1e-6)


@settings(max_examples=100, deadline=None)
@given(fleets())
def test_total_matches_the_eq1_linear_program(case):
    """The LP of Eq. 1 (maximize sum s_i f_i, s.t. sum s_i f_i <= B, fmin <= f <= fmax, HiGHS)
    uses the same total bandwidth as the water-filling whenever the minimum rates fit."""
    demands, budget = case
    result = allocate_frequencies(demands, budget)
    if not result.feasible:
        return
    size = np.array([d.message_bytes for d in demands]) / 1e6
    lp = linprog(
        -size, A_ub=[size], b_ub=[budget], bounds=[(d.min_rate_hz, d.max_rate_hz) for d in demands], method="highs"
    )
    assert lp.status == 0
    assert math.isclose(-lp.fun, result.allocated_mbytes_per_s, rel_tol=1e-6)


def test_water_fill_hits_the_budget_exactly():
    b = water_fill([1.0, 1.0, 4.0], [0.1, 0.1, 0.1], [0.5, 10.0, 10.0], 3.0)
    assert np.allclose(b, [0.5, 0.5, 2.0])


def test_high_priority_gets_its_weight_times_the_share():
    demands = [RobotDemand("a", 50000, 0), RobotDemand("b", 50000, 1)]
    result = allocate_frequencies(demands, 1.0)
    a, b = result.robots
    assert math.isclose(b.bandwidth_mbytes_per_s / a.bandwidth_mbytes_per_s, 4.0, rel_tol=1e-9)


def test_unmeasured_size_uses_the_conservative_default():
    for size in (0.0, float("nan"), -5.0, None):
        result = allocate_frequencies([RobotDemand("a", size), RobotDemand("b", 20000.0)], 1.0)
        a = result.by_name()["a"]
        assert not a.size_measured and a.message_bytes == 60000.0
        assert "not measured" in result.status
        assert result.allocated_mbytes_per_s <= 1.0 * (1 + REL)


@pytest.mark.parametrize(
    "available, reserve", [(0.0, 0.04), (-10.0, 0.04), (float("nan"), 0.04), (60.0, 1.0), (60.0, -0.1), (60.0, 1.5)]
)
def test_bad_link_numbers_are_clear_errors(available, reserve):
    with pytest.raises(ValueError, match="available|reserve"):
        managed_budget_mbytes_per_s(available, reserve)


def test_reserve_is_taken_off_the_link():
    assert math.isclose(managed_budget_mbytes_per_s(60.0, 0.04), 7.2)


@pytest.mark.parametrize("budget", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_budget_is_a_clear_error(budget):
    with pytest.raises(ValueError, match="budget"):
        allocate_frequencies([RobotDemand("a", 1000.0)], budget)


@pytest.mark.parametrize(
    "demand, match",
    [
        (RobotDemand("a", 1000.0, 0, 5.0, 1.0), "min_rate_hz .* > max_rate_hz"),
        (RobotDemand("a", 1000.0, 2), "priority"),
        (RobotDemand("a", 1000.0, -1), "priority"),
        (RobotDemand("a", 1000.0, 0, 0.0, 1.0), "min_rate_hz"),
        (RobotDemand("a", 1000.0, 0, 1.0, float("nan")), "max_rate_hz"),
    ],
)
def test_bad_demand_is_a_clear_error(demand, match):
    with pytest.raises(ValueError, match=match):
        allocate_frequencies([demand], 1.0)


def test_duplicate_robot_is_an_error_and_no_robots_is_fine():
    with pytest.raises(ValueError, match="unique"):
        allocate_frequencies([RobotDemand("a", 1.0), RobotDemand("a", 1.0)], 1.0)
    assert allocate_frequencies([], 1.0).robots == ()
