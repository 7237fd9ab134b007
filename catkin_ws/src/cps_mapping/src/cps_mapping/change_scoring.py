"""Detected site changes scored against the simulator's list of what it changed (no rospy).

A detected change is placed at the centre of its box (the extent of its voxels): a surface seen
from one side pulls the voxels' mean toward that side, while the box of a top seen with a side
spans the item. It matches an expected change of the same kind (appeared/disappeared/moved) whose
footprint, grown by `match_margin_m`, holds that place (a move: where the item stands now, and
where it stood holds the detected move's origin); each is matched at most once, nearest first. A
move reported as a disappeared and an appeared change matches nothing: a move is one change.
Precision is matched detections over detections, recall matched expectations over expectations.
The position error of a match is the horizontal distance between the detected place and the
centre of the changed item's footprint; of a move, the error of its displacement (how far the
detected shift is from the item's).
"""

import dataclasses
import math
from typing import List, Optional, Sequence, Tuple

MATCH_MARGIN_M = 0.5


@dataclasses.dataclass(frozen=True)
class ChangeMatch:
    expected_index: int
    detected_index: int
    position_error_m: float


@dataclasses.dataclass(frozen=True)
class ChangeScore:
    matches: Tuple[ChangeMatch, ...]
    detected: int
    expected: int

    @property
    def precision(self):
        return len(self.matches) / self.detected if self.detected else math.nan

    @property
    def recall(self):
        return len(self.matches) / self.expected if self.expected else math.nan

    def match_of_expected(self, index) -> Optional[ChangeMatch]:
        return next((m for m in self.matches if m.expected_index == index), None)

    def match_of_detected(self, index) -> Optional[ChangeMatch]:
        return next((m for m in self.matches if m.detected_index == index), None)

    def as_dict(self):
        return {
            "precision": self.precision,
            "recall": self.recall,
            "detected": self.detected,
            "expected": self.expected,
            "matches": [dataclasses.asdict(m) for m in self.matches],
        }


def detected_place(change):
    """(x, y) of a detected change: the centre of its box."""
    return ((change.min_m[0] + change.max_m[0]) / 2, (change.min_m[1] + change.max_m[1]) / 2)


def _inside(place, centre, size, margin_m):
    return all(abs(place[k] - centre[k]) <= size[k] / 2 + margin_m for k in (0, 1))


def _error(detected, expected, margin_m):
    """The position error of `detected` as `expected`, or None if they do not match."""
    if detected.kind != expected.kind:
        return None
    place = detected_place(detected)
    if not _inside(place, expected.centroid_m, expected.size_m, margin_m):
        return None
    if expected.kind != "moved":
        return math.hypot(place[0] - expected.centroid_m[0], place[1] - expected.centroid_m[1])
    shift, origin = getattr(detected, "displacement_m", None), getattr(detected, "from_m", None)
    if shift is None or origin is None:
        return None
    if not _inside(origin, expected.from_centroid_m, expected.from_size_m, margin_m):
        return None
    return math.hypot(shift[0] - expected.displacement_m[0], shift[1] - expected.displacement_m[1])


def score_changes(detected: Sequence, expected: Sequence, match_margin_m=MATCH_MARGIN_M) -> ChangeScore:
    """`detected`: change_detection.Change; `expected`: cps_sim.site_changes.ExpectedChange (or
    anything with kind, centroid_m, size_m, and for a move displacement_m, from_centroid_m, from_size_m)."""
    pairs = []
    for i, e in enumerate(expected):
        for j, d in enumerate(detected):
            error = _error(d, e, match_margin_m)
            if error is not None:
                pairs.append((error, i, j))
    matches: List[ChangeMatch] = []
    used_e, used_d = set(), set()
    for error, i, j in sorted(pairs):
        if i not in used_e and j not in used_d:
            used_e.add(i)
            used_d.add(j)
            matches.append(ChangeMatch(i, j, round(error, 4)))
    return ChangeScore(tuple(sorted(matches, key=lambda m: m.expected_index)), len(detected), len(expected))
