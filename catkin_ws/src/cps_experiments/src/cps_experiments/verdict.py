"""A mission's verdict, PASS, FAIL or INCOMPLETE, from its folder's files: what a user would feel.

So that a report cannot say a mission worked when its own files say otherwise. ROS-free: it reads
only the mission folder (and what the caller knows of how the mission ended), and judges with
`cps_experiments.judge` (covering windows, a missing or NaN value fails its check).

The checks (each FAIL names the check, the robot and the mission second; times are seconds from
the mission's start: link_events.csv's start, else the mission monitor's first row):

- **map published and fresh**, per robot: the age of that robot's newest cloud in the map as the map
  server last *published* it (map_age.csv `published_map_age_s`; not the insertion stamps, which a
  map server that inserts but stops publishing keeps fresh) at most MAP_STALE_AFTER_S while the
  robot works, outside link outages (the scenario's cuts when it ran one: `outage_windows`) and
  AFTER_OUTAGE_S after each, from MAP_START_GRACE_S after the monitoring started (a map server
  restart gets the grace again). Not recorded: FAIL.
- **map server heard**: no silence of its statistics longer than MAP_STATS_GAP_S (a restart, a hang),
  and the first within MAP_START_GRACE_S of the monitoring's start.
- **clouds arriving**, per robot: its managed clouds at the twin (arrivals.csv) at least MIN_CLOUD_HZ
  in every CLOUD_WINDOW_S window while it works, outside outages.
- **budget within the capacity**: after every capacity step of the scenario (link_events.csv) and
  STEP_SETTLE_S for the manager to follow, the manager's budget (allocation.csv) at most the
  capacity then in force; and what the robots offered the link (physical_stats.csv, managed clouds
  and video) in no statistics window above it.
- **operator video**, per robot whose video the manager allocated or the twin received: frames at
  least MIN_VIDEO_FPS in every CLOUD_WINDOW_S window outside outages.
- **teleop**: the command probe's latency p95 outside outages at most TELEOP_P95_MS.
- **map F1**, both ways (scores.json): within ±1 voxel at least the floor, voxel for voxel at least
  its floor; NaN or missing fails.
- **ledger** (cps_experiments.ledger): every robot's clouds accounted for, from capture to the map;
  when the rows do not balance, or a stage's counters were not recorded, the mission is INCOMPLETE
  by that many clouds.

INCOMPLETE: no check failed, but a file the mission should have written is missing, empty or
truncated, the ledger does not balance, or the mission ended before every route was done. FAIL
wins over INCOMPLETE (what is missing is listed too). PASS: every check ran and none failed.
"""

import dataclasses
import json
import math
import os
from collections import defaultdict
from typing import List, Optional, Sequence

import numpy as np

from cps_bringup.mission import MAP_AGE_COLUMNS  # noqa: F401 (the mission monitor writes map_age.csv)
from cps_experiments import judge as J
from cps_experiments.markdown import csv_float
from cps_experiments.run_files import read_rows
from cps_fleet import names

PASS, FAIL, INCOMPLETE = "PASS", "FAIL", "INCOMPLETE"
EXIT_CODES = {PASS: 0, FAIL: 1, INCOMPLETE: 4}  # 2: could not start, 3: master lost (cli)
MAP_STALE_AFTER_S = 3.0
AFTER_OUTAGE_S = 3.0
MAP_START_GRACE_S = 15.0
# The map server's statistics come every second: a gap longer than this is a silence (a FAIL).
MAP_STATS_GAP_S = 3.0
# "Every robot's clouds at >= 1 Hz in every 10 s window" (the bar of link_thesis and fig13_live).
CLOUD_WINDOW_S = 10.0
MIN_CLOUD_HZ = 1.0
# A video below one frame a second in a whole window is frozen to its operator.
MIN_VIDEO_FPS = 1.0
TELEOP_P95_MS = 50.0
# After a capacity step the manager has this long to bring its budget within the new capacity: the
# scenario's announcement reaches it within a second, and the rates it sets take a second to show.
STEP_SETTLE_S = 5.0
# The floors on the whole-hall F1; the committed four-robot demo scored 0.966 within ±1 voxel and
# 0.701 voxel for voxel.
MAP_F1_FLOOR_WITHIN_1_VOXEL = 0.9
MAP_F1_FLOOR_EXACT = 0.6
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
STATS_WINDOW_S = 2.0  # topic_stats' sliding window (cps_transport.topic_stats.DEFAULT_WINDOW_S)


@dataclasses.dataclass
class Verdict:
    status: str
    failures: List[str]  # why FAIL or INCOMPLETE, one line each
    notes: List[str]  # what was not judged, and why
    f1_floor_within_1_voxel: Optional[float]
    checks: List[dict] = dataclasses.field(default_factory=list)  # every judge.Check, as dicts
    f1_floor_exact: Optional[float] = None

    @property
    def exit_code(self):
        return EXIT_CODES[self.status]

    def lines(self):
        """The report's first lines (markdown): the status, every failure, the notes, what was checked."""
        head = f"**{self.status}**" + (": every check passed" if self.status == PASS else "")
        return (
            [head, ""]
            + [f"- {f}" for f in self.failures]
            + [f"- note: {n}" for n in self.notes]
            + ([""] if self.failures or self.notes else [])
            + [self.checked_text(), ""]
        )

    def checked_text(self):
        floors = (
            ""
            if self.f1_floor_within_1_voxel is None
            else f"; map F1 at least {self.f1_floor_within_1_voxel:.2f} within ±1 voxel and "
            f"{self.f1_floor_exact if self.f1_floor_exact is not None else MAP_F1_FLOOR_EXACT:.2f} voxel for voxel"
        )
        return (
            "Checked: every mission file present and whole; each robot's map, as the map server published it, "
            f"at most {MAP_STALE_AFTER_S:g} s old while the robot works (outside link outages and "
            f"{AFTER_OUTAGE_S:g} s after each); the map server's statistics never silent over {MAP_STATS_GAP_S:g} s; "
            f"each robot's clouds at the twin at ≥ {MIN_CLOUD_HZ:g} Hz in every {CLOUD_WINDOW_S:g} s window while it "
            f"works; after each capacity step (+{STEP_SETTLE_S:g} s) the manager's budget and the offered load "
            f"within the capacity in force; each video at ≥ {MIN_VIDEO_FPS:g} fps in every {CLOUD_WINDOW_S:g} s "
            f"window; teleop p95 ≤ {TELEOP_P95_MS:g} ms{floors}; every robot's clouds accounted for in the ledger. "
            "Outside outages throughout; a value not measured fails its check."
        )

    def as_dict(self):
        return dataclasses.asdict(self)


def outage_windows(folder):
    """[(start wall s, end wall s)] of the link outages the checks excuse, each extended by
    AFTER_OUTAGE_S; an outage still on at the end lasts forever. A mission that ran a link scenario
    (link_events.csv starts) is excused its scenario's cuts only: an outage its bridges report
    outside them (a link that did not come back) is the operator's to feel, and judged. Without a
    scenario (a real link) the bridges' link state is all there is to know of outages."""
    from cps_experiments.link_report import bridge_outages, scenario_outages

    events, _ = read_rows(os.path.join(folder, "link_events.csv"))
    if any(r.get("event") == "start" for r in events):
        windows = [(start, start + duration) for start, _, duration in scenario_outages(events)]
    else:
        states, _ = read_rows(os.path.join(folder, "link_state.csv"))
        windows = [(start, start + duration) for start, duration, _ in bridge_outages(states)]
    return [
        (start, end + AFTER_OUTAGE_S if math.isfinite(end) else math.inf)
        for start, end in windows
        if math.isfinite(start)
    ]


@dataclasses.dataclass
class MissionFiles:
    """What the checks read, once: rows of each CSV, the mission's origin and end (wall s), outages."""

    folder: str
    map_age: list
    events: list
    allocation: list
    arrivals: list
    physical_arrivals: list
    physical_stats: list
    origin_s: float
    end_s: float
    outages: list

    def mission_s(self, wall_s):
        return wall_s - self.origin_s

    @classmethod
    def read(cls, folder):
        rows = {n: read_rows(os.path.join(folder, n))[0] for n in _READ}
        events = rows["link_events.csv"]
        start = next((r for r in events if r.get("event") == "start"), None)
        map_times = [csv_float(r.get("time_s")) for r in rows[MAP_AGE_CSV]]
        map_times = [t for t in map_times if math.isfinite(t)]
        origin = (
            csv_float(start["wall_time_s"]) - csv_float(start["mission_time_s"])
            if start
            else (min(map_times) if map_times else math.nan)
        )
        end = max(map_times) if map_times else math.nan
        return cls(
            folder,
            rows[MAP_AGE_CSV],
            events,
            rows["allocation.csv"],
            rows["arrivals.csv"],
            rows["physical_arrivals.csv"],
            rows["physical_stats.csv"],
            origin,
            end,
            outage_windows(folder),
        )


_READ = (
    MAP_AGE_CSV,
    "link_events.csv",
    "allocation.csv",
    "arrivals.csv",
    "physical_arrivals.csv",
    "physical_stats.csv",
)


def _spans(bad_times, step_s=1.5):
    """Runs of consecutive failing sample times [(first, last)] (samples about a second apart)."""
    out = []
    for t in sorted(bad_times):
        if out and t - out[-1][1] <= step_s:
            out[-1][1] = t
        else:
            out.append([t, t])
    return [tuple(s) for s in out]


def _map_samples(files: MissionFiles):
    """{robot: [(wall s, published age, insertion age, state, inserted)]} and the monitor's start and
    end marks (wall s)."""
    per_robot, marks = defaultdict(list), []
    for r in files.map_age:
        t = csv_float(r.get("time_s"))
        if not math.isfinite(t) or not r.get("robot"):
            continue
        if r.get("mission_state") in ("start", "end") and math.isnan(csv_float(r.get("map_age_s"))):
            marks.append(t)
            continue
        published = csv_float(r["published_map_age_s"]) if "published_map_age_s" in r else None
        per_robot[r["robot"]].append(
            (
                t,
                published,
                csv_float(r.get("map_age_s")),
                r.get("mission_state", ""),
                csv_float(r.get("clouds_inserted")),
            )
        )
    return per_robot, marks


def check_map(files: MissionFiles, robots) -> List[J.Check]:
    """map published and fresh (per robot) and map server heard (the fleet)."""
    name, checks = "map published and fresh", []
    per_robot, marks = _map_samples(files)
    stats_times = sorted({t for samples in per_robot.values() for t, *_ in samples})
    monitor_start = min(marks + stats_times) if marks or stats_times else math.nan
    monitor_end = max(marks + stats_times) if marks or stats_times else math.nan
    for robot in robots:
        samples = sorted(per_robot.get(robot, []))
        if not samples:
            checks.append(J.check(name, None, robot, None, "no map statistics for this robot (counts as a failure)"))
            continue
        if samples[0][1] is None:
            checks.append(
                J.check(
                    name,
                    None,
                    robot,
                    None,
                    "map_age.csv has no published_map_age_s: when the map was last published is not recorded "
                    "(insertion stamps alone would pass a map server that stopped publishing)",
                )
            )
            continue
        bad, worst, run_start, inserted_before = [], {}, monitor_start, -math.inf
        for t, published, _, state, inserted in samples:
            if inserted < inserted_before:  # counters went back: the map server restarted
                run_start = t
            inserted_before = inserted if math.isfinite(inserted) else inserted_before
            excused = state == "done" or J.overlaps(t, t, files.outages) or t - run_start <= MAP_START_GRACE_S
            if excused:
                continue
            if J.missing(published) or published > MAP_STALE_AFTER_S:
                bad.append(t)
                worst[t] = published
        if not bad:
            checks.append(J.check(name, True, robot, None, f"at most {MAP_STALE_AFTER_S:g} s old"))
        for a, b in _spans(bad):
            ages = [worst[t] for t in bad if a <= t <= b]
            top = "NaN" if any(J.missing(v) for v in ages) else f"{max(ages):.1f} s"
            checks.append(
                J.check(
                    name,
                    False,
                    robot,
                    files.mission_s(a),
                    f"published map older than {MAP_STALE_AFTER_S:g} s from {files.mission_s(a):.0f} to "
                    f"{files.mission_s(b):.0f} s (up to {top})",
                )
            )
    heard = "map server heard"
    if not stats_times:
        checks.append(J.check(heard, None, "", None, "no map statistics at all (counts as a failure)"))
        return checks
    if stats_times[0] - monitor_start > MAP_START_GRACE_S:
        checks.append(
            J.check(
                heard,
                False,
                "",
                files.mission_s(monitor_start),
                f"first map statistics {stats_times[0] - monitor_start:.1f} s after the monitoring started "
                f"(over {MAP_START_GRACE_S:g} s)",
            )
        )
    gaps = J.silences(stats_times, stats_times[0], monitor_end, MAP_STATS_GAP_S)
    for a, b in gaps:
        checks.append(
            J.check(
                heard,
                False,
                "",
                files.mission_s(a),
                f"no map statistics from {files.mission_s(a):.1f} to {files.mission_s(b):.1f} s "
                f"({b - a:.1f} s, over {MAP_STATS_GAP_S:g} s)",
            )
        )
    if not any(c.name == heard for c in checks):
        checks.append(J.check(heard, True, "", None, f"no silence over {MAP_STATS_GAP_S:g} s"))
    return checks


def _done_at(files: MissionFiles):
    """{robot: wall s it was first seen done} from map_age.csv's mission_state."""
    out = {}
    for r in files.map_age:
        t = csv_float(r.get("time_s"))
        if r.get("mission_state") == "done" and math.isfinite(t):
            out[r["robot"]] = min(out.get(r["robot"], math.inf), t)
    return out


def _arrivals(rows, suffix):
    """{robot: sorted receive times} of the arrival rows whose topic ends with `suffix`."""
    out = defaultdict(list)
    for r in rows:
        t = csv_float(r.get("receive_s"))
        if r.get("robot") and r.get("topic", "").endswith(suffix) and math.isfinite(t):
            out[r["robot"]].append(t)
    return {k: sorted(v) for k, v in out.items()}


def _rate_checks(name, per_robot, robots, files, start_s, end_of, floor, unit):
    checks = []
    for robot in robots:
        end = end_of(robot)
        times = per_robot.get(robot, [])
        found = J.windows(times, start_s, end, CLOUD_WINDOW_S, exclude=files.outages)
        if not found:
            checks.append(
                J.check(name, True, robot, None, "no window outside outages while it worked")
                if end - start_s <= 0
                else J.check(
                    name, None, robot, None, "every window touches an outage: not judged (counts as a failure)"
                )
            )
            continue
        low = min(found, key=lambda w: (w.rate_hz, w.start_s))
        checks.append(
            J.at_least(
                name,
                low.rate_hz,
                floor,
                robot,
                files.mission_s(low.start_s),
                unit,
                what=f"lowest {CLOUD_WINDOW_S:g} s window{' (partial)' if low.partial else ''} "
                f"{files.mission_s(low.start_s):.0f}-{files.mission_s(low.end_s):.0f} s:",
            )
        )
    return checks


def check_streams(files: MissionFiles, robots) -> List[J.Check]:
    """clouds arriving (per robot) and operator video (per robot with video)."""
    clouds = _arrivals(files.arrivals, "/" + names.POINTS_MANAGED)
    video = _arrivals(files.arrivals, "/" + names.CAMERA_IMAGE_COMPRESSED)
    everything = [t for v in clouds.values() for t in v]
    if not math.isfinite(files.end_s):
        return [J.check("clouds arriving", None, "", None, "the mission's span is not known (no map_age.csv)")]
    # The fleet's clouds begin with the first one at the twin, or the start grace, whichever is first.
    start = min([files.origin_s + MAP_START_GRACE_S] + everything[:1])
    done = _done_at(files)
    checks = _rate_checks(
        "clouds arriving",
        clouds,
        robots,
        files,
        start,
        lambda r: min(done.get(r, math.inf), files.end_s),
        MIN_CLOUD_HZ,
        " Hz",
    )
    video_robots = sorted(set(video) | {r.get("robot") for r in files.allocation if r.get("stream") == "video"})
    checks += _rate_checks(
        "operator video",
        video,
        [r for r in video_robots if r],
        files,
        start,
        lambda r: files.end_s,
        MIN_VIDEO_FPS,
        " fps",
    )
    return checks


def check_teleop(files: MissionFiles) -> List[J.Check]:
    probe = [
        (csv_float(r.get("receive_s")), (csv_float(r.get("receive_s")) - csv_float(r.get("stamp_ns")) * 1e-9) * 1e3)
        for r in files.physical_arrivals
        if r.get("topic") == names.absolute(names.COMMAND_PROBE)
    ]
    kept = [ms for t, ms in probe if math.isfinite(ms) and not J.overlaps(t, t, files.outages)]
    p95 = float(np.percentile(kept, 95)) if kept else math.nan
    return [J.at_most("teleop", p95, TELEOP_P95_MS, "", None, " ms", what=f"command probe p95 over {len(kept)} probes")]


def check_capacity(files: MissionFiles) -> List[J.Check]:
    """budget within the capacity, after every step of the scenario (none ran: one note-like PASS)."""
    name = "budget within the capacity"
    phase_list = J.phases(files.events, files.end_s if math.isfinite(files.end_s) else 0.0)
    if not phase_list:
        return []
    capacity = J.capacity_in_force(phase_list)
    settled = [(p.start_s, p.start_s + STEP_SETTLE_S) for p in phase_list]
    checks = []
    budgets = sorted((csv_float(r.get("stamp_s")), csv_float(r.get("budget_mbytes_per_s"))) for r in files.allocation)
    over = [
        (t, b, capacity(t) / 8.0)
        for t, b in budgets
        if math.isfinite(t) and not J.overlaps(t, t, settled) and (J.missing(b) or b > capacity(t) / 8.0 * (1 + 1e-9))
    ]
    if files.allocation and not over:
        checks.append(J.check(name, True, "", None, "the manager's budget within every phase's capacity"))
    elif not files.allocation:
        checks.append(J.check(name, None, "", None, "no allocation.csv: the manager's budget is not known"))
    for a, b in _spans([t for t, *_ in over], step_s=2.0):
        worst = max((x for x in over if a <= x[0] <= b), key=lambda x: x[1] - x[2])
        checks.append(
            J.check(
                name,
                False,
                "",
                files.mission_s(a),
                f"the manager's budget {worst[1]:.2f} MB/s above the {worst[2]:.3f} MB/s the link carried "
                f"({capacity(a):g} Mbit/s) from {files.mission_s(a):.0f} to {files.mission_s(b):.0f} s: "
                "planned on a capacity the link no longer had",
            )
        )
    offered = J.stats_window_volumes(
        files.physical_stats, lambda r: r.get("managed") == "True" and _link_stream(r.get("topic", "")), STATS_WINDOW_S
    )
    # A window (t - STATS_WINDOW_S, t] is judged when it lies in one phase, past its settling time.
    bad = [
        (t, v, capacity(t) / 8.0)
        for t, v in offered
        if not any(p.start_s <= t and t - STATS_WINDOW_S < p.start_s + STEP_SETTLE_S for p in phase_list)
        and not J.overlaps(t - STATS_WINDOW_S, t, files.outages)
        and t - STATS_WINDOW_S >= phase_list[0].start_s
        and (J.missing(v) or v > capacity(t) / 8.0)
    ]
    offered_name = "offered load within the capacity"
    if offered and not bad:
        checks.append(
            J.check(offered_name, True, "", None, "no statistics window of the robots' offer above the capacity")
        )
    elif not offered:
        checks.append(J.check(offered_name, None, "", None, "physical_stats.csv measured no managed stream"))
    for a, b in _spans([t for t, *_ in bad], step_s=2.0):
        worst = max((x for x in bad if a <= x[0] <= b), key=lambda x: x[1] if math.isfinite(x[1]) else math.inf)
        checks.append(
            J.check(
                offered_name,
                False,
                "",
                files.mission_s(a),
                f"the robots offered {worst[1]:.2f} MB/s against {worst[2]:.3f} MB/s of capacity in the "
                f"{STATS_WINDOW_S:g} s windows ending {files.mission_s(a):.0f}-{files.mission_s(b):.0f} s",
            )
        )
    return checks


def _link_stream(topic):
    return topic.endswith(("/" + names.POINTS_MANAGED, "/" + names.CAMERA_IMAGE_COMPRESSED))


def check_f1(folder, floor_tolerant, floor_exact) -> List[J.Check]:
    from cps_mapping.scoring import read_scores

    scores = {}
    try:
        with open(os.path.join(folder, "scores.json")) as stream:
            scores = read_scores(json.load(stream))
    except (OSError, ValueError):
        pass
    return [
        J.at_least("map F1", scores.get("f1_within_1_voxel"), floor_tolerant, what="within ±1 voxel"),
        J.at_least("map F1", scores.get("f1_exact"), floor_exact, what="voxel for voxel"),
    ]


def judge(
    folder,
    required_files: Sequence[str] = DEMO_FILES,
    ended_by: Optional[str] = None,
    f1_floor_within_1_voxel: Optional[float] = MAP_F1_FLOOR_WITHIN_1_VOXEL,
    f1_floor_exact: Optional[float] = MAP_F1_FLOOR_EXACT,
    robots: Optional[Sequence[str]] = None,
) -> Verdict:
    """The verdict of the mission whose files are in `folder`. `ended_by`: how the mission ended
    (MissionResult.ended_by; anything but "done" is INCOMPLETE); `f1_floor_within_1_voxel`: None when
    this mission's map is not scored against the ground truth (the monitoring mission); `robots`:
    the mission's robots (default: every robot its files name)."""
    from cps_experiments.ledger import read_ledger

    incomplete, notes = [], []
    for name in required_files:
        if name.endswith(".csv"):
            incomplete += read_rows(os.path.join(folder, name))[1]
        elif not os.path.isfile(os.path.join(folder, name)) or os.path.getsize(os.path.join(folder, name)) == 0:
            incomplete.append(f"{name} is missing")
    if ended_by is not None and ended_by != "done":
        incomplete.append(f"the mission ended by {ended_by} before every route was done")
    files = MissionFiles.read(folder)
    if robots is None:
        robots = sorted({r["robot"] for r in files.map_age if r.get("robot")})
    checks = check_map(files, robots) + check_streams(files, robots) + check_teleop(files) + check_capacity(files)
    if f1_floor_within_1_voxel is not None:
        checks += check_f1(
            folder, f1_floor_within_1_voxel, MAP_F1_FLOOR_EXACT if f1_floor_exact is None else f1_floor_exact
        )
    else:
        notes.append("map F1 not judged: this mission's map is not scored against the ground truth")
    ledger = read_ledger(folder, robots)
    incomplete += ledger.incomplete_lines()
    failures = [c.line() for c in checks if c.failed]
    status = FAIL if failures else INCOMPLETE if incomplete else PASS
    return Verdict(
        status,
        failures + incomplete,
        notes,
        f1_floor_within_1_voxel,
        [dataclasses.asdict(c) for c in checks],
        f1_floor_exact if f1_floor_within_1_voxel is not None else None,
    )


def checks_table(verdict: Verdict) -> List[str]:
    """The report's table of every check (markdown lines)."""
    from cps_experiments.markdown import markdown_table

    rows = [
        (
            c["name"],
            c["robot"] or "fleet",
            c["status"],
            "whole mission" if c["at_s"] is None else f"{c['at_s']:.1f}",
            c["detail"],
        )
        for c in verdict.checks
    ]
    return [markdown_table(("check", "robot", "status", "mission s", "detail"), rows)] if rows else []


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
