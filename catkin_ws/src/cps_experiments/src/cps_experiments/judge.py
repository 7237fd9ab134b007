"""One judge for every report: windows, rates, phases and checks from plain numbers (no ROS, no files).

The mission verdict, link_thesis, fig13_live, the twin's capacity and Table 5 all judge with these,
so that no report can flatter itself with its own arithmetic:

- **Windows overlap and cover the whole span.** Width W, one every `step_s` from the span's start, and
  the last one ends at the span's end, so no second of the span goes unseen; a span shorter than W gets
  one window over all of it, marked partial. Windows that touch an excluded interval (a link outage)
  are left out, and that is said by the caller.
- **A stream's rate comes from its own arrivals:** arrivals in a window over the window's length; its
  mean over a span is its arrivals in the span over the span's length. Means and windows are taken
  from the same arrivals, so the lowest window can never exceed the mean (`impossible_minimum`
  says when a table's figures break that).
- **Phases are the scenario's own** spans of constant capacity (link_events.csv), numbered in order:
  two runs of a scenario are compared phase by phase by that number, never by a label holding a
  rounded time.
- **A NaN or missing value fails its check,** never passes.
- **Every failure names the check, the robot (or the fleet) and the time.**
"""

import bisect
import dataclasses
import math
from typing import Callable, Iterable, List, Optional, Sequence, Tuple

import numpy as np

PASS, FAIL = "PASS", "FAIL"
# A window's step when the caller gives none, s: every second, as topic_stats samples its windows.
DEFAULT_STEP_S = 1.0
# The link's scenario events that set its rate (link_events.csv `event`).
RATE_EVENTS = ("start", "shape")


def missing(value) -> bool:
    """True for None, NaN, an empty string or anything that is not a number."""
    if value is None or isinstance(value, bool):
        return value is None
    try:
        return math.isnan(float(value))
    except (TypeError, ValueError):
        return True


# --- windows -------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Window:
    """[start_s, end_s) and the arrivals in it; `partial`: shorter than the width asked for."""

    start_s: float
    end_s: float
    count: int
    partial: bool = False

    @property
    def length_s(self):
        return self.end_s - self.start_s

    @property
    def rate_hz(self):
        return self.count / self.length_s if self.length_s > 0 else math.nan


def overlaps(start_s, end_s, intervals: Iterable[Tuple[float, float]]) -> bool:
    """True when [start_s, end_s) meets any of the closed `intervals` (start, end)."""
    return any(a < end_s and start_s <= b for a, b in intervals)


def window_starts(start_s, end_s, width_s, step_s=DEFAULT_STEP_S) -> List[float]:
    """Starts of the windows that cover [start_s, end_s): every `step_s` from the start while a whole
    window fits, and one ending exactly at the end. [] for an empty span."""
    if not (width_s > 0 and step_s > 0):
        raise ValueError(f"window width and step must be > 0, got {width_s}, {step_s}")
    if not end_s > start_s:
        return []
    if end_s - start_s <= width_s:
        return [start_s]
    last = end_s - width_s
    starts = list(np.arange(start_s, last, step_s))
    if not starts or last - starts[-1] > 1e-9:
        starts.append(last)
    return [float(s) for s in starts]


def windows(arrivals_s, start_s, end_s, width_s, step_s=DEFAULT_STEP_S, exclude=()) -> List[Window]:
    """The windows covering [start_s, end_s) (see `window_starts`) with the arrivals in each; a span
    shorter than `width_s` gives one window over all of it, marked partial. Windows that touch an
    interval of `exclude` (closed (start, end) pairs: outages) are left out."""
    times = np.sort(np.asarray([t for t in arrivals_s if not missing(t)], dtype=float))
    out = []
    for a in window_starts(start_s, end_s, width_s, step_s):
        b = min(a + width_s, end_s)
        if overlaps(a, b, exclude):
            continue
        count = int(np.searchsorted(times, b, side="left") - np.searchsorted(times, a, side="left"))
        out.append(Window(a, b, count, partial=b - a < width_s - 1e-9))
    return out


def lowest_window(arrivals_s, start_s, end_s, width_s, step_s=DEFAULT_STEP_S, exclude=()) -> Optional[Window]:
    """The window with the lowest rate (the earliest of equals), or None when no window is left."""
    found = windows(arrivals_s, start_s, end_s, width_s, step_s, exclude)
    return min(found, key=lambda w: (w.rate_hz, w.start_s)) if found else None


def mean_rate_hz(arrivals_s, start_s, end_s) -> float:
    """Arrivals in [start_s, end_s) over its length (NaN for an empty span): the same arrivals the
    windows count."""
    if not end_s > start_s:
        return math.nan
    return sum(1 for t in arrivals_s if not missing(t) and start_s <= t < end_s) / (end_s - start_s)


def impossible_minimum(mean, lowest, tolerance=0.02) -> bool:
    """True when a lowest window is above the mean over the same span: impossible for windows that
    cover the span (with `window_starts`' windows the tiles from the start plus the one ending at the
    end hold every arrival, so one of them is at most the mean). A table with such a row cut its
    windows without covering the span."""
    if missing(mean) or missing(lowest):
        return False
    return float(lowest) > float(mean) * (1 + tolerance) + 1e-12


def silences(times_s, start_s, end_s, longest_s) -> List[Tuple[float, float]]:
    """[(from, to)] spans of [start_s, end_s] longer than `longest_s` without any of `times_s` (the
    span's own start and end count as its edges: nothing at all is one silence over all of it)."""
    inside = sorted(t for t in times_s if not missing(t) and start_s <= t <= end_s)
    edges = [start_s] + inside + [end_s]
    return [(a, b) for a, b in zip(edges, edges[1:]) if b - a > longest_s]


def stats_window_volumes(stats_rows, keep: Callable[[dict], bool], window_s) -> List[Tuple[float, float]]:
    """[(time s, MB/s)] per statistics publication, summed over the rows `keep` accepts: each row's
    messages x mean size over its window (topic_stats' sliding `window_s`, published every second),
    the volume received, the same for every topic set. A row without numbers adds nothing; a time
    whose every kept row lacks them is NaN (missing, never 0)."""
    totals, seen = {}, set()
    for row in stats_rows:
        if not keep(row):
            continue
        t = _float(row.get("time_s"))
        if missing(t):
            continue
        seen.add(t)
        messages, mean_bytes = _float(row.get("messages")), _float(row.get("mean_message_bytes"))
        if not (missing(messages) or missing(mean_bytes)):
            totals[t] = totals.get(t, 0.0) + messages * mean_bytes / window_s / 1e6
    return [(t, totals.get(t, math.nan)) for t in sorted(seen)]


def _float(value):
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


# --- phases --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Phase:
    """The scenario's `index`-th span of constant capacity, [start_s, end_s) in wall seconds."""

    index: int
    start_s: float
    end_s: float
    capacity_mbps: float

    @property
    def length_s(self):
        return self.end_s - self.start_s

    @property
    def capacity_mbytes_per_s(self):
        return self.capacity_mbps / 8.0

    def label(self, origin_s):
        """'5 Mbit/s, phase 3 (40.0-60.0 s)': for reading only, never for matching."""
        return (
            f"{self.capacity_mbps:g} Mbit/s, phase {self.index + 1} "
            f"({self.start_s - origin_s:.1f}-{self.end_s - origin_s:.1f} s)"
        )


def phases(event_rows, end_s) -> List[Phase]:
    """The scenario's phases from link_events.csv rows (`event` start/shape with `rate_mbps`), up
    to `end_s`: a new phase at each change of the rate, from when its commands began
    (`began_wall_time_s`; files without it: `wall_time_s`, when they had run, up to 1.6 s later
    while the link had already changed), numbered from 0. A cut does not end a phase (the capacity
    is the shaper's; the outage is judged apart)."""
    points = []
    for row in event_rows:
        if row.get("event") not in RATE_EVENTS:
            continue
        t, rate = _float(row.get("began_wall_time_s")), _float(row.get("rate_mbps"))
        if missing(t):
            t = _float(row.get("wall_time_s"))
        if missing(t) or missing(rate) or (points and points[-1][1] == rate):
            continue
        points.append((t, rate))
    out = []
    for i, (t, rate) in enumerate(points):
        end = points[i + 1][0] if i + 1 < len(points) else max(end_s, t)
        out.append(Phase(i, t, end, rate))
    return out


def capacity_in_force(phase_list: Sequence[Phase]) -> Callable[[float], float]:
    """wall s -> the capacity (Mbit/s) the scenario had set then; NaN before its start."""
    starts = [p.start_s for p in phase_list]

    def at(t):
        i = bisect.bisect_right(starts, t) - 1
        return phase_list[i].capacity_mbps if i >= 0 else math.nan

    return at


def steps(phase_list: Sequence[Phase]) -> List[Tuple[float, float, float]]:
    """[(wall s, from Mbit/s, to Mbit/s)]: every change of capacity."""
    return [(b.start_s, a.capacity_mbps, b.capacity_mbps) for a, b in zip(phase_list, phase_list[1:])]


def match_phases(ours: Sequence[Phase], theirs: Sequence[Phase]):
    """([(our phase, their phase)] paired by index, [why a pair is missing or differs]): two runs of
    one scenario compared on the scenario's own boundaries. A phase of one run without its match, or
    of another capacity, is named, never silently dropped."""
    pairs, problems = [], []
    for i in range(max(len(ours), len(theirs))):
        a = ours[i] if i < len(ours) else None
        b = theirs[i] if i < len(theirs) else None
        if a is None or b is None:
            problems.append(f"phase {i + 1} is in {'one run' if a or b else 'neither run'} only")
        elif a.capacity_mbps != b.capacity_mbps:
            problems.append(f"phase {i + 1}: {a.capacity_mbps:g} against {b.capacity_mbps:g} Mbit/s")
        else:
            pairs.append((a, b))
    return pairs, problems


# --- checks --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Check:
    """One judged condition: `name` (what a user would feel), PASS or FAIL, for `robot` ('' = the
    fleet) at `at_s` (seconds from the mission's start; None: the whole mission), and why."""

    name: str
    status: str
    robot: str = ""
    at_s: Optional[float] = None
    detail: str = ""

    @property
    def failed(self):
        return self.status == FAIL

    def line(self):
        who = self.robot or "fleet"
        when = "whole mission" if self.at_s is None else f"at {self.at_s:.1f} s"
        return f"{self.name}: {self.status}, {who}, {when}: {self.detail}".rstrip(": ")


def check(name, ok, robot="", at_s=None, detail="") -> Check:
    """PASS when `ok` is True; FAIL for False and for None (not measured fails, never passes)."""
    return Check(name, PASS if ok is True else FAIL, robot, at_s, detail)


def at_least(name, value, floor, robot="", at_s=None, unit="", what="") -> Check:
    """`value` >= `floor`; NaN or missing fails, saying so."""
    subject = f"{what} " if what else ""
    if missing(value):
        return check(name, None, robot, at_s, f"{subject}not measured (counts as a failure)")
    ok = float(value) >= floor
    return check(name, ok, robot, at_s, f"{subject}{_num(value)}{unit} {'≥' if ok else '<'} {_num(floor)}{unit}")


def at_most(name, value, ceiling, robot="", at_s=None, unit="", what="") -> Check:
    """`value` <= `ceiling`; NaN or missing fails, saying so."""
    subject = f"{what} " if what else ""
    if missing(value):
        return check(name, None, robot, at_s, f"{subject}not measured (counts as a failure)")
    ok = float(value) <= ceiling
    return check(name, ok, robot, at_s, f"{subject}{_num(value)}{unit} {'≤' if ok else '>'} {_num(ceiling)}{unit}")


# --- comparing two arms ---------------------------------------------------------------------------

# Reports print compared figures to this many significant digits (`_num`, and fig13_live's ".3g").
PRINTED_DIGITS = 3


def printed_unit(value, digits=PRINTED_DIGITS) -> float:
    """One unit of the last digit `value` is printed with (0.001 for 0.982, 1 for 115; 0 for 0 or NaN)."""
    value = abs(float(value))
    if not math.isfinite(value) or value == 0.0:
        return 0.0
    return 10.0 ** (math.floor(math.log10(value)) - digits + 1)


def printed_apart(value, bar, digits=2) -> str:
    """`value` with `digits` decimals, or as many more as it takes to print differently from `bar`
    when it differs from it: a figure that misses its bar never prints as the bar (seed 45756's
    precision 0.946 printed "0.95" against "≥ 0.95", met: no)."""
    if missing(value):
        return "—"
    value, bar = float(value), float(bar)
    while value != bar and f"{value:.{digits}f}" == f"{bar:.{digits}f}" and digits < 9:
        digits += 1
    return f"{value:.{digits}f}"


def compare(ours, theirs, larger_better, spread=math.nan) -> str:
    """'worse', 'better' or 'same' for `ours` against `theirs`: 'same' within the run-to-run `spread`
    (NaN: not measured) and within one unit of the last printed digit of the larger of the two,
    so that two figures the report prints alike are never called different (fig13_live called the
    manager worse on F1 at 0.982 against 0.983 with a spread of 0.0005, and on 0.456 against 0.457
    with none measured); 'n/a' when either is missing."""
    if missing(ours) or missing(theirs):
        return "n/a"
    gain = (ours - theirs) if larger_better else (theirs - ours)
    larger = max(abs(float(ours)), abs(float(theirs)))
    # (and float's rounding: 0.456 - 0.457 is a little more than 0.001)
    margin = max(spread if not missing(spread) else 0.0, printed_unit(larger)) + 1e-9 * larger
    return "worse" if gain < -margin else "better" if gain > margin else "same"


def _num(value):
    value = float(value)
    if math.isinf(value):
        return "inf"
    return f"{value:.3g}" if abs(value) < 100 else f"{value:.0f}"


def status_of(checks: Iterable[Check]) -> str:
    """FAIL when any check failed (an empty list is no evidence: FAIL), else PASS."""
    checks = list(checks)
    return FAIL if not checks or any(c.failed for c in checks) else PASS


def held_text(c: Optional[Check]) -> str:
    """'held' / 'NOT held (why)' / 'not measured: NOT held' for a report's bar."""
    if c is None:
        return "not measured: NOT held"
    if c.status == PASS:
        return f"held ({c.detail})" if c.detail else "held"
    return f"NOT held ({c.detail})" if c.detail else "NOT held"
