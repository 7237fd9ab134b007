"""The paper's Table 6 scenario (four robots, 60 Mbit/s, nine steps) for the allocator, without ROS:
the paper's rates and bandwidths per step, which robots have finished by which step, and
`run_table6_steps` that plays the steps through the mission-state priorities and
`allocate_frequencies` with any message sizes (the paper's, or ones measured on our clouds)."""
from typing import Callable, Dict, List, Sequence, Tuple

from cps_bw_manager.allocation import Allocation, allocate_frequencies
from cps_bw_manager.priorities import PriorityBook

TABLE6_ROBOTS = ("scout", "jackal", "champ", "iris")  # Table 6: Scout, Jackal, Legged, Aerial
# (Hz, MB/s) per step and robot, from Table 6.
PAPER_TABLE6 = [
    [(30.0, 1.01), (13.15, 1.87), (30.0, 1.81), (28.02, 1.87)],
    [(30.0, 1.00), (13.49, 1.87), (29.52, 1.87), (27.73, 1.87)],
    [(30.0, 1.45), (25.11, 1.87), (30.0, 1.87), (22.07, 1.87)],
    [(30.0, 1.63), (23.42, 1.87), (30.0, 0.66), (28.15, 1.87)],
    [(30.0, 1.40), (26.31, 1.87), (30.0, 1.73), (25.06, 1.87)],
    [(30.0, 1.50), (30.0, 1.70), (30.0, 1.35), (1.0, 0.05)],
    [(1.0, 0.04), (30.0, 1.48), (30.0, 1.31), (1.0, 0.06)],
    [(1.0, 0.04), (30.0, 2.09), (1.0, 0.03), (1.0, 0.06)],
    [(1.0, 0.04), (1.0, 0.08), (1.0, 0.03), (1.0, 0.06)],
]
# Steps 1-5: every robot inspecting. Then iris, scout, champ, jackal finish (the paper's text).
TABLE6_FINISHED_BY_STEP = {6: {"iris"}, 7: {"iris", "scout"}, 8: {"iris", "scout", "champ"},
                           9: {"iris", "scout", "champ", "jackal"}}


def paper_message_bytes(step, robot):
    """The message size the paper's step implies for `robot`: its MB/s / Hz."""
    hz, mbytes = PAPER_TABLE6[step - 1][TABLE6_ROBOTS.index(robot)]
    return mbytes / hz * 1e6


def run_table6_steps(message_bytes: Callable[[int, str], float], budget_mbytes_per_s: float,
                     min_rate_hz=1.0, max_rate_hz: Dict[str, float] = None,
                     robots: Sequence[str] = TABLE6_ROBOTS) -> List[Tuple[int, set, Allocation]]:
    """(step, finished robots, Allocation) for the nine steps; `message_bytes(step, robot)` gives
    the managed message size; `max_rate_hz` per robot (default 30 Hz each)."""
    book = PriorityBook(robots)
    rows = []
    for step in range(1, len(PAPER_TABLE6) + 1):
        done = TABLE6_FINISHED_BY_STEP.get(step, set())
        for robot in robots:
            book.set_mission_state(robot, "done" if robot in done else "inspecting")
        demands = [book.demand(robot, message_bytes(step, robot), min_rate_hz, (max_rate_hz or {}).get(robot, 30.0))
                   for robot in robots]
        rows.append((step, done, allocate_frequencies(demands, budget_mbytes_per_s)))
    return rows
