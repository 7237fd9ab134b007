"""A seeded chaos soak's pieces (issue 38; bench/chaos.py runs them against a live mission).

`draw_faults(seed, n)` draws the faults (the same seed, the same faults). Each fault is injected
into a running mission (cps_harness.mission.Mission on a shaped link), and after it ends the
invariants are judged from the mission's own files (`judge_fault`) over the window from the
fault's end plus `RECOVERY_S` to `CHECK_WINDOW_S` later:
- the map fresh again: every robot's published map age at most `MAP_FRESH_S` (map_age.csv);
- every robot's clouds arriving at the twin (arrivals.csv);
- teleop reaching the robots: the command probe arriving on the robots' side, p95 latency;
- no frame delivered to the wrong topic or type: the bridges' mismatch counters did not grow
  (DropReporter's /diagnostics on each side, recorded by `diagnostics_recorder_argv`);
- nothing left of a killed process: no process of the killed node's name but the one the
  supervisor restarted.
"""

import dataclasses
import json
import math
import random
import re
from typing import Dict, List, Optional, Sequence

from cps_link.receive_path import (
    KEY_MISMATCH,
    MD5_MISMATCH,
    PUBLISHER_TYPE_MISMATCH,
    SEND_TOPIC_TYPE_MISMATCH,
    TOPIC_TYPE_MISMATCH,
    UNKNOWN_TYPE,
    UNLISTED_TOPIC,
    WRONG_TOPIC,
)

# The faults the soak draws from, with how long each lasts (s) where it lasts.
LINK_CUT = "link_cut"  # the veth down for 0.2-20 s
CAPACITY_STEP = "capacity_step"  # the link's rate to 5, 10 or 20 Mbit/s for 5-15 s
KILL = "kill"  # SIGKILL a node the supervisor restarts (one of KILL_TARGETS)
TWIN_CPU_HOG = "twin_cpu_hog"  # the twin's CPUs saturated for 10 s
SLOW_VIEWER = "slow_viewer"  # a subscriber on the twin reading a heavy topic at a trickle for 10 s
KINDS = (LINK_CUT, CAPACITY_STEP, KILL, TWIN_CPU_HOG, SLOW_VIEWER)
CUT_S = (0.2, 20.0)  # drawn log-uniform: short cuts as often as long ones
STEP_MBPS = (5.0, 10.0, 20.0)
STEP_S = (5.0, 15.0)
HOG_S = 10.0
VIEWER_S = 10.0
# Process-name fragments of the nodes a kill may hit (every one restarted by the supervisor).
KILL_TARGETS = ("map_server", "zenoh_bridge_twin", "zenoh_bridge_robots", "cloud_tissue", "cloud_throttle")
# Where a target runs inside another process in some tissue layout (the shared layout's cloud_tissue
# runs every robot's limiter): a kill of it kills its host. The draw stays the same for every layout.
KILL_HOSTS = {"cloud_throttle": "cloud_tissue"}

# The invariants' window: from the fault's end + RECOVERY_S, for CHECK_WINDOW_S.
RECOVERY_S = 3.0
CHECK_WINDOW_S = 5.0
MAP_FRESH_S = 3.0
TELEOP_P95_MS = 50.0
# The bridges' counters of frames that would have been delivered to the wrong topic or type, as
# their diagnostics name them: the receive path's drops (`drop_<kind>`) and the bridge's own. The
# first soak of 50 faults looked for the kinds without their prefix: it recorded nothing, and the
# invariant held on no data while the twin's log named 8 misplaced frames.
MISMATCH_KEYS = tuple(
    f"drop_{kind}"
    for kind in (KEY_MISMATCH, WRONG_TOPIC, UNLISTED_TOPIC, UNKNOWN_TYPE, MD5_MISMATCH, TOPIC_TYPE_MISMATCH)
) + (SEND_TOPIC_TYPE_MISMATCH, PUBLISHER_TYPE_MISMATCH)


@dataclasses.dataclass(frozen=True)
class Fault:
    kind: str
    duration_s: float = 0.0  # how long it lasts (0: an instant, e.g. a kill)
    rate_mbps: Optional[float] = None  # CAPACITY_STEP's rate
    target: str = ""  # KILL's node

    def describe(self):
        if self.kind == LINK_CUT:
            return f"link cut {self.duration_s:.1f} s"
        if self.kind == CAPACITY_STEP:
            return f"capacity {self.rate_mbps:g} Mbit/s for {self.duration_s:.1f} s"
        if self.kind == KILL:
            return f"kill -9 {self.target}"
        return f"{self.kind} {self.duration_s:.0f} s"


def draw_faults(seed: int, count: int, kinds: Sequence[str] = KINDS) -> List[Fault]:
    """`count` faults of `kinds` drawn from `seed` (random.Random: the same on every machine; a
    narrower `kinds` draws another sequence)."""
    if count < 1:
        raise ValueError(f"count must be at least 1, got {count}")
    unknown = [k for k in kinds if k not in KINDS]
    if unknown or not kinds:
        raise ValueError(f"kinds must be some of {', '.join(KINDS)}, got {', '.join(kinds) or 'none'}")
    rng = random.Random(seed)
    faults = []
    for _ in range(count):
        kind = rng.choice(tuple(kinds))
        if kind == LINK_CUT:
            low, high = math.log(CUT_S[0]), math.log(CUT_S[1])
            faults.append(Fault(kind, round(math.exp(rng.uniform(low, high)), 2)))
        elif kind == CAPACITY_STEP:
            faults.append(Fault(kind, round(rng.uniform(*STEP_S), 1), rate_mbps=rng.choice(STEP_MBPS)))
        elif kind == KILL:
            faults.append(Fault(kind, target=rng.choice(KILL_TARGETS)))
        else:
            faults.append(Fault(kind, HOG_S if kind == TWIN_CPU_HOG else VIEWER_S))
    return faults


# The supervisor's line for a restart it schedules (cps_bringup.supervisor: "restart n/limit").
RESTART_LINE = re.compile(r"\[bringup\] (?P<label>\S+): exited with code -?\d+; restart (?P<n>\d+)/(?P<limit>\d+)")


class RestartBudget:
    """The supervisor's restart budget of each process, as the mission's log shows it. A process
    restarted `limit` times within the window ends the mission at its next death: by design (a
    crash loop is not restarted forever), so a fourth kill of one process in 300 s tests the
    supervisor's limit, not recovery. The first seed-2 soak ended that way after 26 of its 50
    faults (cloud_tissue killed a fourth time in 300 s, three times as cloud_throttle's host)."""

    def __init__(self, window_s: float):
        self.window_s = window_s
        self.limits: Dict[str, int] = {}
        self.restarts_s: Dict[str, List[float]] = {}  # when each restart line was first read
        self._lines_read = 0

    def read(self, log_text: str, now_s: float):
        """Take the restart lines of the mission's log not read yet, as of `now_s`."""
        lines = list(RESTART_LINE.finditer(log_text))
        for match in lines[self._lines_read :]:
            label = match.group("label")
            self.limits[label] = int(match.group("limit"))
            self.restarts_s.setdefault(label, []).append(now_s)
        self._lines_read = len(lines)

    def left(self, label: str, now_s: float) -> Optional[int]:
        """Restarts `label` has left in the window (None: never restarted, its limit not known yet;
        every kill target's limit is at least 1)."""
        if label not in self.limits:
            return None
        recent = [t for t in self.restarts_s[label] if now_s - t < self.window_s]
        return self.limits[label] - len(recent)

    def target(self, drawn: str, host_of, now_s: float) -> Optional[str]:
        """The kill target for a drawn one: itself while its host has a restart left, else the first
        of KILL_TARGETS (in their order: the same run, the same choice) whose host has; None when
        none has."""
        for name in (drawn, *(t for t in KILL_TARGETS if t != drawn)):
            left = self.left(host_of(name), now_s)
            if left is None or left >= 1:
                return name
        return None


@dataclasses.dataclass
class Row:
    """One fault's line of the soak's table: what was checked, and why it failed if it did."""

    index: int
    fault: str
    start_s: float  # mission wall clock (s since the epoch) when injected
    end_s: float
    map_age_max_s: Optional[float] = None
    robots_without_clouds: List[str] = dataclasses.field(default_factory=list)
    teleop_probes: int = 0
    teleop_p95_ms: Optional[float] = None
    mismatches: Dict[str, float] = dataclasses.field(default_factory=dict)
    leftovers: List[str] = dataclasses.field(default_factory=list)
    failures: List[str] = dataclasses.field(default_factory=list)

    @property
    def held(self):
        return not self.failures


def _float(value):
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _p95(values):
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(math.ceil(0.95 * len(ordered))) - 1)] if ordered else None


def judge_fault(row: Row, robots, map_age_rows, arrival_rows, probe_rows, cloud_topic_of, probe_topic) -> Row:
    """Fill `row`'s figures and failures from the mission's CSV rows (dicts as csv.DictReader gives)
    over [end + RECOVERY_S, end + RECOVERY_S + CHECK_WINDOW_S]; a missing value is a failure."""
    lo = row.end_s + RECOVERY_S
    hi = lo + CHECK_WINDOW_S

    def inside(r, key):
        return lo <= _float(r.get(key)) <= hi

    ages = {}
    for r in map_age_rows:
        if inside(r, "time_s") and r.get("robot") in robots:
            age = _float(r.get("published_map_age_s"))
            ages[r["robot"]] = max(ages.get(r["robot"], -math.inf), age if math.isfinite(age) else math.inf)
    missing = [r for r in robots if r not in ages]
    if missing:
        row.failures.append(f"no map age recorded for {', '.join(missing)}")
    if ages:
        row.map_age_max_s = max(ages.values())
        stale = {r: a for r, a in ages.items() if a > MAP_FRESH_S}
        if stale:
            row.failures.append("map not fresh: " + ", ".join(f"{r} {a:.1f} s" for r, a in sorted(stale.items())))
    arrived = {
        r.get("robot")
        for r in arrival_rows
        if inside(r, "receive_s") and r.get("topic") == cloud_topic_of(r.get("robot"))
    }
    row.robots_without_clouds = sorted(set(robots) - arrived)
    if row.robots_without_clouds:
        row.failures.append(f"no clouds from {', '.join(row.robots_without_clouds)}")
    latencies = [
        (_float(r.get("receive_s")) - _float(r.get("stamp_ns")) * 1e-9) * 1000.0
        for r in probe_rows
        if r.get("topic") == probe_topic and inside(r, "receive_s")
    ]
    row.teleop_probes = len(latencies)
    row.teleop_p95_ms = _p95(latencies)
    if not latencies:
        row.failures.append("no teleop probe reached the robots")
    elif row.teleop_p95_ms > TELEOP_P95_MS:
        row.failures.append(f"teleop p95 {row.teleop_p95_ms:.0f} ms > {TELEOP_P95_MS:.0f} ms")
    return row


def mismatch_growth(before: Dict[str, float], after: Dict[str, float]) -> Dict[str, float]:
    """The mismatch counters that grew between two readings ({node/key: value})."""
    return {k: v - before.get(k, 0.0) for k, v in after.items() if v > before.get(k, 0.0)}


def read_mismatch_counters(path) -> Dict[str, float]:
    """The latest value of every mismatch counter in a recorder's JSON-lines file ({} if none yet)."""
    latest = {}
    try:
        with open(path) as stream:
            for line in stream:
                try:
                    entry = json.loads(line)
                except ValueError:
                    continue
                latest[f"{entry['node']}/{entry['key']}"] = float(entry["value"])
    except OSError:
        pass
    return latest


# Run against one side's master: appends every mismatch counter of /diagnostics as a JSON line.
RECORDER = """
import json, sys, rospy
from diagnostic_msgs.msg import DiagnosticArray
from cps_fleet import names
from cps_harness.chaos import MISMATCH_KEYS
out = open(sys.argv[1], "a", buffering=1)
def on_diag(array):
    for status in array.status:
        for kv in status.values:
            if kv.key in MISMATCH_KEYS:
                out.write(json.dumps({"node": status.name, "key": kv.key, "value": kv.value}) + "\\n")
rospy.init_node("chaos_mismatch_recorder", anonymous=True)
rospy.Subscriber(names.absolute(names.DIAGNOSTICS), DiagnosticArray, on_diag, queue_size=50)
rospy.spin()
"""


def diagnostics_recorder_argv(python, path):
    return [python, "-c", RECORDER, path]
