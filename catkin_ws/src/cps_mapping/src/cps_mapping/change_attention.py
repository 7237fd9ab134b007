"""Which robots to give a closer look at a newly found change (the paper's "trigger or change
detection", section 5), without ROS: a robot within `radius_m` (horizontal) of a change that
was not there at the previous detection gets high priority on the link.
"""

import math
from typing import Callable, Dict, List, Sequence, Tuple

ATTENTION_RADIUS_M = 4.0
# A change whose centroid stays within this of one already seen is the same change.
SAME_CHANGE_M = 0.5


class ChangeAttention:
    def __init__(self, radius_m=ATTENTION_RADIUS_M, same_change_m=SAME_CHANGE_M):
        if not radius_m > 0 or not same_change_m > 0:
            raise ValueError("radius_m and same_change_m must be positive")
        self.radius_m, self.same_change_m = radius_m, same_change_m
        self._seen: List[Tuple[str, float, float]] = []

    def _is_new(self, change):
        x, y = change.centroid_m[0], change.centroid_m[1]
        return not any(
            kind == change.kind and math.hypot(x - sx, y - sy) <= self.same_change_m for kind, sx, sy in self._seen
        )

    def robots_to_raise(self, changes: Sequence, positions_m: Callable[[], Dict[str, Tuple[float, float]]]):
        """[(robot, change)] for every change new since the last call and each robot near it;
        `positions_m()` (robot -> (x, y) in map) is asked only when there is a new change."""
        out, positions = [], None
        for change in changes:
            if not self._is_new(change):
                continue
            self._seen.append((change.kind, change.centroid_m[0], change.centroid_m[1]))
            positions = positions_m() if positions is None else positions
            for robot, (x, y) in sorted(positions.items()):
                if math.hypot(x - change.centroid_m[0], y - change.centroid_m[1]) <= self.radius_m:
                    out.append((robot, change))
        return out
