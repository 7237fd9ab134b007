"""A mission's verdict, PASS, FAIL or INCOMPLETE, and the checks that failed, from its folder's files.

So that a report cannot say a mission worked when its own files say otherwise. ROS-free: it reads
only the mission folder (and what the caller knows of how the mission ended).

- INCOMPLETE: no check failed, but a file the mission should have written is missing, empty or
  truncated (a row with the wrong number of fields, a last line cut off), or the mission ended
  before every route was done. Each is named; no row is dropped without being counted here.
- FAIL: a check that could run found a failure (it wins over INCOMPLETE: what is missing is
  listed too):
  - *map stale*: a robot's map age (map_age.csv: now minus the stamp of the newest cloud of that
    robot inserted into the map, as the map server published it) above MAP_STALE_AFTER_S while the
    robot is not done, outside every link outage and the AFTER_OUTAGE_S after it. A robot with no
    cloud in the map yet ("inf") is judged only after MAP_START_GRACE_S of the map server's run
    (its start, and a restart: start-up loads the map and the kernels). A map server silent (no
    map_stats) for longer than MAP_START_GRACE_S fails too, counted from the mission monitor's
    start and to its end (rows marked "start"/"end" with no age); shorter silences of more than
    MAP_STATS_GAP_S (a restart) are listed as notes;
  - *map F1*: F1 within ±1 voxel (scores.json) below the floor (MAP_F1_FLOOR_WITHIN_1_VOXEL
    unless the caller gives another).
- PASS: every check ran and none failed.

Seconds in the messages are counted from the first row of map_age.csv ("record s").
"""

import csv
import dataclasses
import json
import math
import os
from collections import defaultdict
from typing import List, Optional, Sequence

from cps_bringup.mission import MAP_AGE_COLUMNS  # noqa: F401 (the mission monitor writes map_age.csv)
from cps_experiments.markdown import csv_float

PASS, FAIL, INCOMPLETE = "PASS", "FAIL", "INCOMPLETE"
EXIT_CODES = {PASS: 0, FAIL: 1, INCOMPLETE: 4}  # 2: could not start, 3: master lost (cli)
MAP_STALE_AFTER_S = 3.0
AFTER_OUTAGE_S = 3.0
MAP_START_GRACE_S = 15.0
# map_stats rows further apart than this: the map server was not publishing (noted; a failure
# past MAP_START_GRACE_S).
MAP_STATS_GAP_S = 3.0
# The floor on the whole-hall F1 within ±1 voxel; the committed four-robot demo scores 0.955.
MAP_F1_FLOOR_WITHIN_1_VOXEL = 0.9
MAP_AGE_CSV = "map_age.csv"
VERDICT_JSON = "verdict.json"
# What each mission must leave in its folder for its verdict to be judged.
DEMO_FILES = (
    "map.bt",
    "scores.json",
    "stats.csv",
    "arrivals.csv",
    "physical_stats.csv",
    "physical_arrivals.csv",
    "allocation.csv",
    MAP_AGE_CSV,
    "trajectories.csv",
)
MONITOR_FILES = ("map.bt", "stats.csv", "arrivals.csv", "physical_stats.csv", "physical_arrivals.csv", MAP_AGE_CSV)


@dataclasses.dataclass
class Verdict:
    status: str
    failures: List[str]  # why FAIL or INCOMPLETE, one line each
    notes: List[str]  # what was not judged, and why
    f1_floor_within_1_voxel: Optional[float]

    @property
    def exit_code(self):
        return EXIT_CODES[self.status]

    def lines(self):
        """The report's first lines (markdown)."""
        head = f"**{self.status}**" + (": every check passed" if self.status == PASS else "")
        floor = (
            ""
            if self.f1_floor_within_1_voxel is None
            else f"; map F1 within ±1 voxel at least {self.f1_floor_within_1_voxel:.2f}"
        )
        checked = (
            f"Checked: every mission file present and whole; each robot's map age at most "
            f"{MAP_STALE_AFTER_S:g} s while it works, outside link outages and {AFTER_OUTAGE_S:g} s after "
            f"each{floor}."
        )
        return (
            [head, ""]
            + [f"- {f}" for f in self.failures]
            + [f"- note: {n}" for n in self.notes]
            + ([""] if self.failures or self.notes else [])
            + [checked, ""]
        )

    def as_dict(self):
        return dataclasses.asdict(self)


def read_rows(path):
    """(rows as dicts, problems): the rows of a CSV, and what is wrong with the file (missing, empty,
    rows with the wrong number of fields, a last line cut off). Bad rows are kept out of the rows
    and counted in the problems, never dropped silently."""
    name = os.path.basename(path)
    if not os.path.isfile(path):
        return [], [f"{name} is missing"]
    with open(path, newline="") as stream:
        text = stream.read()
    if not text.strip():
        return [], [f"{name} is empty"]
    records = list(csv.reader(text.splitlines()))
    header, body = records[0], records[1:]
    rows, bad = [], []
    for line, record in enumerate(body, start=2):
        if len(record) != len(header):
            bad.append(line)
        else:
            rows.append(dict(zip(header, record)))
    problems = []
    if not text.endswith("\n") and body and (len(body) + 1) not in bad:
        bad.append(len(body) + 1)
        rows.pop()
    if bad:
        problems.append(
            f"{name}: {len(bad)} truncated row(s) (line {', '.join(map(str, sorted(bad)[:5]))}"
            f"{', ...' if len(bad) > 5 else ''}), not counted in the figures"
        )
    if not body:
        problems.append(f"{name} has a header and no rows")
    return rows, problems


def outage_windows(folder):
    """[(start wall s, end wall s)] of every link outage (scenario cuts and the bridge's link state),
    each extended by AFTER_OUTAGE_S; an outage still on at the end lasts forever."""
    from cps_experiments.link_report import bridge_outages, scenario_outages

    events, _ = read_rows(os.path.join(folder, "link_events.csv"))
    states, _ = read_rows(os.path.join(folder, "link_state.csv"))
    windows = [(start, start + duration) for start, _, duration in scenario_outages(events)]
    windows += [(start, start + duration) for start, duration, _ in bridge_outages(states)]
    return [
        (start, end + AFTER_OUTAGE_S if math.isfinite(end) else math.inf)
        for start, end in windows
        if math.isfinite(start)
    ]


def stale_intervals(map_age_rows, outages=()):
    """({robot: [(from s, to s, worst age s)]}, [map server silent (from s, to s)]) in record seconds:
    the runs of map_age.csv samples that judge the robot's map stale (see the module docstring).

    A map server run starts at the first row, and again where the robot's clouds_inserted counter
    goes back (the map server restarted with fresh counters)."""
    samples = sorted(
        (
            csv_float(r.get("time_s")),
            r.get("robot", ""),
            csv_float(r.get("map_age_s")),
            r.get("mission_state", ""),
            csv_float(r.get("clouds_inserted")),
        )
        for r in map_age_rows
    )
    samples = [s for s in samples if math.isfinite(s[0]) and s[1]]
    if not samples:
        return {}, []
    t0 = samples[0][0]
    times = sorted({s[0] for s in samples})
    gaps = [(before - t0, after - t0) for before, after in zip(times, times[1:]) if after - before > MAP_STATS_GAP_S]
    samples = [s for s in samples if not math.isnan(s[2])]  # the monitor's start/end marks
    stale = defaultdict(list)
    open_run, run_start, inserted_before = {}, {}, {}
    for t, robot, age, state, inserted in samples:
        restarted = inserted < inserted_before.get(robot, -math.inf)
        inserted_before[robot] = inserted
        if robot not in run_start or restarted:
            run_start[robot] = t
        excused = state == "done" or any(start <= t <= end for start, end in outages)
        if math.isinf(age):
            bad = not excused and t - run_start[robot] > MAP_START_GRACE_S
        else:
            bad = not excused and math.isfinite(age) and age > MAP_STALE_AFTER_S
        if bad:
            current = open_run.get(robot)
            if current is None:
                open_run[robot] = current = [t - t0, t - t0, age]
                stale[robot].append(current)
            current[1], current[2] = t - t0, max(current[2], age)
        else:
            open_run.pop(robot, None)
    return {robot: [tuple(run) for run in runs] for robot, runs in stale.items()}, gaps


def judge(
    folder,
    required_files: Sequence[str] = DEMO_FILES,
    ended_by: Optional[str] = None,
    f1_floor_within_1_voxel: Optional[float] = MAP_F1_FLOOR_WITHIN_1_VOXEL,
) -> Verdict:
    """The verdict of the mission whose files are in `folder`. `ended_by`: how the mission ended
    (MissionResult.ended_by; anything but "done" is INCOMPLETE); `f1_floor_within_1_voxel`: None when
    this mission's map is not scored against the ground truth (the monitoring mission)."""
    incomplete, failures, notes = [], [], []
    for name in required_files:
        if name.endswith(".csv"):
            incomplete += read_rows(os.path.join(folder, name))[1]
        elif not os.path.isfile(os.path.join(folder, name)) or os.path.getsize(os.path.join(folder, name)) == 0:
            incomplete.append(f"{name} is missing")
    if ended_by is not None and ended_by != "done":
        incomplete.append(f"the mission ended by {ended_by} before every route was done")

    map_age_rows, _ = read_rows(os.path.join(folder, MAP_AGE_CSV))
    if map_age_rows:
        stale, gaps = stale_intervals(map_age_rows, outage_windows(folder))
        for robot, runs in sorted(stale.items()):
            spans = ", ".join(
                f"{a:.0f}–{b:.0f} s (age up to {'inf' if math.isinf(age) else f'{age:.0f}'} s)" for a, b, age in runs
            )
            failures.append(
                f"map stale: {robot}'s map older than {MAP_STALE_AFTER_S:g} s outside link outages "
                f"(+{AFTER_OUTAGE_S:g} s) at record {spans}"
            )
        for a, b in gaps:
            if b - a > MAP_START_GRACE_S:
                failures.append(
                    f"map stale: the map server published no statistics from record {a:.0f} s to "
                    f"{b:.0f} s (over {MAP_START_GRACE_S:g} s)"
                )
            else:
                notes.append(
                    f"the map server published no statistics from record {a:.0f} s to {b:.0f} s "
                    f"(a restart; under {MAP_START_GRACE_S:g} s)"
                )

    if f1_floor_within_1_voxel is not None:
        scores_path = os.path.join(folder, "scores.json")
        if os.path.isfile(scores_path):
            from cps_mapping.scoring import read_scores

            try:
                with open(scores_path) as stream:
                    scores = read_scores(json.load(stream))
            except (OSError, ValueError) as exc:
                incomplete.append(f"scores.json is unreadable ({exc})")
                scores = {}
            f1 = scores.get("f1_within_1_voxel")
            if f1 is not None and f1 < f1_floor_within_1_voxel:
                failures.append(
                    f"map F1 within ±1 voxel {f1:.3f} below the floor {f1_floor_within_1_voxel:.2f} "
                    f"(voxel for voxel: {scores.get('f1_exact', math.nan):.3f})"
                )
    else:
        notes.append("map F1 not judged: this mission's map is not scored against the ground truth")

    status = FAIL if failures else INCOMPLETE if incomplete else PASS
    return Verdict(status, failures + incomplete, notes, f1_floor_within_1_voxel)


def write_verdict(folder, verdict: Verdict):
    """verdict.json next to the report, for `make demo`/`make monitor`'s exit code and for tests."""
    with open(os.path.join(folder, VERDICT_JSON), "w") as stream:
        json.dump(verdict.as_dict(), stream, indent=2)


def read_verdict(folder) -> Optional[Verdict]:
    """The verdict the report wrote, or None when there is none (the report did not get that far)."""
    try:
        with open(os.path.join(folder, VERDICT_JSON)) as stream:
            return Verdict(**json.load(stream))
    except (OSError, ValueError, TypeError):
        return None


def console_lines(prog, verdict: Optional[Verdict]) -> List[str]:
    """What `make demo`/`make monitor` print at the end: the verdict and each reason."""
    if verdict is None:
        return [f"[{prog}] verdict INCOMPLETE: the report wrote no verdict"]
    return [f"[{prog}] verdict {verdict.status}"] + [f"[{prog}]   {f}" for f in verdict.failures]


def exit_code(verdict: Optional[Verdict]) -> int:
    return EXIT_CODES[INCOMPLETE] if verdict is None else verdict.exit_code
