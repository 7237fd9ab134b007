"""The paper's Table 6 (four robots, 60 Mbit/s, nine steps) and a runner that puts each step
through the mission-state priorities and the allocator, for the test and the experiments.

Steps 1-5: every robot inspecting (priority 1). Then the aerial robot, Scout, the legged robot and
Jackal finish, in that order (the paper's section 5), and drop to the minimum rate.
"""

from typing import Callable, Dict, List, Tuple, Union

from cps_bw_manager.allocation import Allocation, allocate_frequencies
from cps_bw_manager.priorities import PriorityBook

# Our fleet's names for Table 6's Scout, Jackal, Legged and Aerial.
TABLE6_ROBOTS = ("scout", "jackal", "champ", "iris")
# (Hz, MB/s) per robot (TABLE6_ROBOTS order) and step.
PAPER_TABLE6 = (
    ((30.0, 1.01), (13.15, 1.87), (30.0, 1.81), (28.02, 1.87)),
    ((30.0, 1.00), (13.49, 1.87), (29.52, 1.87), (27.73, 1.87)),
    ((30.0, 1.45), (25.11, 1.87), (30.0, 1.87), (22.07, 1.87)),
    ((30.0, 1.63), (23.42, 1.87), (30.0, 0.66), (28.15, 1.87)),
    ((30.0, 1.40), (26.31, 1.87), (30.0, 1.73), (25.06, 1.87)),
    ((30.0, 1.50), (30.0, 1.70), (30.0, 1.35), (1.0, 0.05)),
    ((1.0, 0.04), (30.0, 1.48), (30.0, 1.31), (1.0, 0.06)),
    ((1.0, 0.04), (30.0, 2.09), (1.0, 0.03), (1.0, 0.06)),
    ((1.0, 0.04), (1.0, 0.08), (1.0, 0.03), (1.0, 0.06)),
)
TABLE6_FINISHED_BY_STEP = {
    step: frozenset(done)
    for step, done in (
        (1, ()),
        (2, ()),
        (3, ()),
        (4, ()),
        (5, ()),
        (6, ("iris",)),
        (7, ("iris", "scout")),
        (8, ("iris", "scout", "champ")),
        (9, ("iris", "scout", "champ", "jackal")),
    )
}
TABLE6_AVAILABLE_MBPS = 60.0


def paper_message_bytes(step, robot):
    """The message size Table 6 implies for `robot` at `step`: its MB/s / Hz, in bytes."""
    hz, mbytes = PAPER_TABLE6[step - 1][TABLE6_ROBOTS.index(robot)]
    return mbytes / hz * 1e6


def run_table6_steps(
    message_bytes: Callable[[int, str], float],
    budget_mbytes_per_s: float,
    min_rate_hz: float = 1.0,
    max_rate_hz: Union[float, Dict[str, float]] = 30.0,
) -> List[Tuple[int, frozenset, Allocation]]:
    """(step, finished robots, Allocation) for the nine steps; `max_rate_hz` may be per robot
    (e.g. capped by each sensor's rate)."""
    book = PriorityBook(TABLE6_ROBOTS, pin_done=True)  # the paper's finished robots, "reduced to 1 Hz"
    steps = []
    for step in range(1, len(PAPER_TABLE6) + 1):
        done = TABLE6_FINISHED_BY_STEP[step]
        for robot in TABLE6_ROBOTS:
            book.set_mission_state(robot, "done" if robot in done else "inspecting")
        demands = [
            book.demand(
                robot,
                message_bytes(step, robot),
                min_rate_hz,
                max_rate_hz[robot] if isinstance(max_rate_hz, dict) else max_rate_hz,
            )
            for robot in TABLE6_ROBOTS
        ]
        steps.append((step, done, allocate_frequencies(demands, budget_mbytes_per_s)))
    return steps


def format_table6(steps):
    """Our rates beside the paper's, one line per step."""
    lines = ["step | " + " | ".join(f"{r:>6}: paper Hz  MB/s -> ours Hz  MB/s  share%" for r in TABLE6_ROBOTS)]
    for step, _, result in steps:
        cells = [
            f"{r:>6}: {hz:8.2f} {mb:5.2f} -> {a.rate_hz:7.2f} {a.bandwidth_mbytes_per_s:5.2f} {a.share_percent:6.2f}"
            for r, (hz, mb), a in zip(TABLE6_ROBOTS, PAPER_TABLE6[step - 1], result.robots)
        ]
        lines.append(f"{step:4d} | " + " | ".join(cells) + f" | total {result.allocated_mbytes_per_s:.2f} MB/s")
    return "\n".join(lines)
