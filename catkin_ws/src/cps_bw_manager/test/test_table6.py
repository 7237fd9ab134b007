"""The paper's Table 6 (four robots, 60 Mbit/s, nine steps) through the mission-state mapping and
the allocator. Message sizes per step are the paper's bandwidth / frequency. Run with -s to see
our rates beside the paper's."""

import math

import pytest

from cps_bw_manager.allocation import managed_budget_mbytes_per_s
from cps_bw_manager.priorities import PriorityBook
from cps_bw_manager.table6 import PAPER_TABLE6, format_table6, paper_message_bytes, run_table6_steps
from cps_bw_manager.table6 import TABLE6_ROBOTS as ROBOTS


def test_table6_pattern_is_reproduced():
    budget = managed_budget_mbytes_per_s(60.0, 0.04)
    steps = run_table6_steps(paper_message_bytes, budget, 1.0, 30.0)
    print(
        f"\nTable 6, 60 Mbit/s, 4 % reserve -> managed budget {budget:.2f} MB/s "
        f"(the paper's shares are of 7.50 MB/s)\n" + format_table6(steps)
    )
    assert [done for _, done, _ in steps][5:] == [{"iris"}, {"iris", "scout"}, {"iris", "scout", "champ"}, set(ROBOTS)]
    for step, done, result in steps:
        paper_row = PAPER_TABLE6[step - 1]
        assert result.feasible
        assert result.allocated_mbytes_per_s <= budget * (1 + 1e-9)
        active = []
        for robot, (paper_hz, _), a in zip(ROBOTS, paper_row, result.robots):
            if robot in done:
                assert a.priority == 0 and math.isclose(a.rate_hz, 1.0), (step, robot, a)
                continue
            assert a.priority == 1
            # Where the paper is capped at 30 Hz we are too; elsewhere we give at least the paper's
            # rate, since what a capped robot cannot use is handed to the others.
            assert a.rate_hz <= 30.0 * (1 + 1e-9)
            assert a.rate_hz >= min(paper_hz, 30.0) * (1 - 1e-6), (step, robot, a.rate_hz, paper_hz)
            active.append(a)
        uncapped = [a for a in active if a.rate_hz < 30.0 * (1 - 1e-9)]
        if uncapped:
            # Equal priority, equal bandwidth share, and the budget is used up.
            shares = [a.bandwidth_mbytes_per_s for a in uncapped]
            assert max(shares) - min(shares) <= 1e-9 * max(shares)
            assert math.isclose(result.allocated_mbytes_per_s, budget, rel_tol=1e-9)
        if step >= 6:
            # Steps 6-8: the remaining robots run at the maximum, as in the paper.
            assert all(math.isclose(a.rate_hz, 30.0) for a in active)


def test_per_robot_maximum_caps_a_slow_sensor():
    budget = managed_budget_mbytes_per_s(60.0, 0.04)
    steps = run_table6_steps(
        paper_message_bytes, budget, 1.0, {"scout": 10.0, "jackal": 30.0, "champ": 30.0, "iris": 30.0}
    )
    assert all(result.by_name()["scout"].rate_hz <= 10.0 + 1e-9 for _, _, result in steps)


def test_operator_raises_a_finished_robot_back():
    book = PriorityBook(ROBOTS, pin_done=True)  # the paper's policy
    for robot in ROBOTS:
        book.set_mission_state(robot, "inspecting")
    book.set_mission_state("iris", "done")
    assert book.demand("iris", 50000.0, 1.0, 30.0).max_rate_hz == 1.0 and book.finished("iris")
    assert book.set_operator_priority("iris", 1)
    demand = book.demand("iris", 50000.0, 1.0, 30.0)
    assert demand.priority == 1 and demand.max_rate_hz == 30.0 and not book.finished("iris")
    # The override lasts until the mission state changes again.
    book.set_mission_state("iris", "transit")
    assert book.priority("iris") == 0


@pytest.mark.parametrize(
    "robot, priority, error",
    [
        ("nobody", 1, KeyError),
        ("iris", 2, ValueError),
        ("iris", -1, ValueError),
        ("iris", True, ValueError),
    ],
)
def test_bad_operator_priority_is_a_clear_error(robot, priority, error):
    with pytest.raises(error):
        PriorityBook(ROBOTS).set_operator_priority(robot, priority)


def test_unknown_mission_state_is_a_clear_error():
    with pytest.raises(ValueError, match="mission state"):
        PriorityBook(ROBOTS).set_mission_state("iris", "flying")


def test_a_finished_robot_is_not_pinned_unless_the_paper_policy_is_asked():
    book = PriorityBook(ROBOTS)
    book.set_mission_state("iris", "done")
    demand = book.demand("iris", 50000.0, 1.0, 30.0)
    assert book.finished("iris") and not book.pinned_to_minimum("iris")
    assert demand.priority == 0 and demand.max_rate_hz == 30.0
