"""The per-cloud ledger of a mission: per robot, every cloud from its capture to the map, each loss
with its cause, from the nodes' own counters (ROS-free: reads the mission folder).

The counters (cps_ros.cloud_ledger) come from the nodes on the cloud's path, recorded by each side's
topic_stats from /diagnostics into `physical_counters.csv` (Draco encoder, rate limiter, the robots'
bridge) and `counters.csv` (the twin's bridge, the decoder), and the map server's from its MapStats
in `map_age.csv`. Each node counts what it received, what it never got (gaps in the numbers of the
stage before it: a subscriber queue, the link), what it passed on and what it dropped by cause; so
a loss is counted where it is seen, never worked out as the difference of two other counters.

The rows balance when, for every node, received = passed on + dropped, and, between two nodes, what
the first passed on = what the second received or knows it missed, up to the clouds still on their
way when counting stopped (at most ALLOWED_UNSEEN_S of the robot's clouds per hop: the nodes report
once a second). Whatever does not balance, and any stage whose counters were not recorded, makes
the ledger INCOMPLETE by that many clouds, and the report says so.
"""

import dataclasses
import math
import os
from collections import defaultdict
from typing import Dict, List, Optional

from cps_bringup.mission import MAP_SERVER_COUNTERS
from cps_experiments.markdown import csv_float, markdown_table
from cps_experiments.run_files import read_rows
from cps_fleet import names
from cps_ros import cloud_ledger as C

PHYSICAL_COUNTERS_CSV = "physical_counters.csv"
COUNTERS_CSV = "counters.csv"
MAP_AGE_CSV = "map_age.csv"
# What a node reports as it is now (not a running count): its last value counts.
GAUGES = (C.BACKFILL_WAITING,)
# Counters are reported once a second: a hop may have this much of a robot's clouds on the way.
ALLOWED_UNSEEN_S = 2.0
# The map server's queue length in map_age.csv: a gauge, its last value counts.
MAP_SERVER_QUEUE = "queue_length"
# The map server's counters in map_age.csv that only grow: the clouds inserted (a column of its own
# there) and every counter but the queue's length.
MAP_SERVER_CUMULATIVE = ("clouds_inserted",) + tuple(c for c in MAP_SERVER_COUNTERS if c != MAP_SERVER_QUEUE)


def _read(path):
    return read_rows(path)[0] if os.path.isfile(path) else None


def cumulative(series):
    """The total of a counter reported over time, its restarts summed: `series` is its values in
    time order; a value below the one before starts a new run of the node."""
    total, last = 0.0, 0.0
    for value in series:
        if value < last:
            total += last
        last = value
    return total + last


def node_counters(rows) -> Dict[str, Dict[str, Dict[str, float]]]:
    """{input topic: {stage: {what: total}}} of counters.csv rows (a node's restarts summed; nodes
    reporting the same topic and stage added)."""
    series = defaultdict(list)
    for row in sorted(rows or [], key=lambda r: csv_float(r.get("time_s"))):
        parsed = C.parse_key(row.get("key", ""))
        value = csv_float(row.get("value"))
        if parsed and math.isfinite(value):
            series[(row.get("node", ""), row.get("input_topic", ""), *parsed)].append(value)
    out = defaultdict(lambda: defaultdict(dict))
    for (_, topic, stage, what), values in series.items():
        total = values[-1] if what in GAUGES else cumulative(values)
        out[topic][stage][what] = out[topic][stage].get(what, 0.0) + total
    return out


def counter_series(rows) -> Dict[tuple, List[tuple]]:
    """{(input topic, stage, what): [(time s, running total)]} of counters.csv rows, restarts summed:
    for what a counter did between two times (`increase`)."""
    raw = defaultdict(list)
    for row in sorted(rows or [], key=lambda r: csv_float(r.get("time_s"))):
        parsed = C.parse_key(row.get("key", ""))
        value, t = csv_float(row.get("value")), csv_float(row.get("time_s"))
        if parsed and math.isfinite(value) and math.isfinite(t):
            raw[(row.get("node", ""), row.get("input_topic", ""), *parsed)].append((t, value))
    out = defaultdict(list)
    for (_, topic, stage, what), points in raw.items():
        base, last = 0.0, 0.0
        for t, value in points:
            if value < last and what not in GAUGES:
                base += last
            last = value
            out[(topic, stage, what)].append((t, base + value))
    return out


def increase(series, t0_s, t1_s, stage, what, topics=None) -> int:
    """How much `what` of `stage` grew between t0_s and t1_s, summed over input topics (all, or
    those in `topics`): the counter's last value by t1_s less its last value before t0_s."""

    def at(points, t):
        before = [v for ts, v in points if ts <= t]
        return before[-1] if before else 0.0

    return int(
        round(
            sum(
                at(points, t1_s) - at(points, t0_s)
                for (topic, s, w), points in series.items()
                if s == stage and w == what and (topics is None or topic in topics)
            )
        )
    )


def read_counter_series(folder):
    """counter_series of both sides' counters files in `folder`, each side's stages from its own
    file ({} when neither was recorded)."""
    return counter_series(_side_rows(folder))


def map_server_counters(map_age_rows) -> Dict[str, Dict[str, float]]:
    """{robot: {counter: total}} from map_age.csv: the map server's counters as it published them,
    its restarts summed (clouds_inserted going back is a restart); queue_length is the last one.
    A counter the file does not have is absent (an older mission)."""
    series = defaultdict(lambda: defaultdict(list))
    for row in sorted(map_age_rows or [], key=lambda r: csv_float(r.get("time_s"))):
        if not row.get("robot") or row.get("mission_state") in ("start", "end"):
            continue
        for name in MAP_SERVER_CUMULATIVE + (MAP_SERVER_QUEUE,):
            value = csv_float(row.get(name))
            if name in row and math.isfinite(value):
                series[row["robot"]][name].append(value)
    return {
        robot: {
            name: (values[-1] if name == MAP_SERVER_QUEUE else cumulative(values)) for name, values in counters.items()
        }
        for robot, counters in series.items()
    }


@dataclasses.dataclass
class RobotLedger:
    robot: str
    stages: List[tuple] = dataclasses.field(default_factory=list)  # (label, clouds) along the path
    drops: List[tuple] = dataclasses.field(default_factory=list)  # (cause, clouds)
    ends: List[tuple] = dataclasses.field(default_factory=list)  # (what became of them, clouds)
    in_flight: int = 0
    unaccounted: int = 0
    problems: List[str] = dataclasses.field(default_factory=list)

    @property
    def balanced(self):
        return self.unaccounted == 0 and not self.problems

    @property
    def dropped(self):
        return sum(n for _, n in self.drops)

    def stage(self, label):
        return next((n for name, n in self.stages if name == label), None)


CAPTURED = "captured"
ENCODED = "encoded"
TO_LINK = "handed to the link"
AT_TWIN = "received at the twin"
DECODED = "decoded"
AT_MAP = "at the map server"
INSERTED = "inserted"
SUPERSEDED = "superseded in its slot (a newer cloud of the robot inserted instead)"
WAITING = "waiting in the map server's slot at the end"
STORED = "still in the backfill store at the end"
STAGE_COLUMNS = (CAPTURED, ENCODED, TO_LINK, AT_TWIN, DECODED, AT_MAP)


class _Builder:
    """Walks one robot's counters stage by stage, keeping every row and every imbalance."""

    def __init__(self, robot, allowed_unseen):
        self.ledger = RobotLedger(robot)
        self.allowed = allowed_unseen

    def drop(self, cause, n):
        if n:
            self.ledger.drops.append((cause, int(round(n))))

    def internal(self, where, residual):
        """Received less passed on and dropped, within one node: a few may be in the node when its
        last report was taken (up to the allowance); anything else is unaccounted."""
        if 0.5 < residual <= self.allowed:
            self.ledger.in_flight += int(round(residual))
        elif abs(residual) > 0.5:
            self.ledger.unaccounted += int(round(abs(residual)))
            self.ledger.problems.append(f"{where}: received and passed on or dropped differ by {residual:+.0f}")

    def hop(self, where, passed_on, reached):
        """Between two counted stages: what the first passed on against what the second received or
        knows it missed; the rest is on the way, or the two last reports were taken a moment apart
        (up to the allowance either way), or unaccounted."""
        unseen = passed_on - reached
        if abs(unseen) <= self.allowed:
            self.ledger.in_flight += int(round(abs(unseen)))
        else:
            self.ledger.unaccounted += int(round(abs(unseen)))
            self.ledger.problems.append(
                f"{where}: {passed_on:.0f} passed on, {reached:.0f} received or missed by the next stage "
                f"({unseen:+.0f}; at most {self.allowed:.0f} may be on the way)"
            )


def robot_ledger(robot, counters, map_server, duration_s, stats_captured=None, stats_at_twin=None) -> RobotLedger:
    """One robot's ledger from `counters` (node_counters of both sides), `map_server` (its
    map_server_counters row), the mission's `duration_s` (for the clouds a hop may have on the way),
    and the statistics' own counts of its filtered clouds and of its clouds at the twin (used only
    when the nodes counted nothing)."""
    topic = {
        "filtered": names.absolute(names.robot_topic(robot, names.POINTS_FILTERED)),
        "draco": names.absolute(names.robot_topic(robot, names.POINTS_DRACO)),
        "managed": names.absolute(names.managed_cloud(robot)),
        "at_twin": names.absolute(names.managed_cloud_at_twin(robot)),
        "backfill": names.absolute(names.in_twin(names.robot_topic(robot, names.POINTS_BACKFILL_DRACO))),
    }

    def stage(key, name):
        found = counters.get(topic[key], {}).get(name)
        return defaultdict(float, found) if found else None

    enc, lim = stage("filtered", C.ENCODER), stage("draco", C.LIMITER)
    out, inn, dec = stage("managed", C.BRIDGE_OUT), stage("at_twin", C.BRIDGE_IN), stage("at_twin", C.DECODER)
    back_in, back_dec = stage("backfill", C.BRIDGE_IN), stage("backfill", C.DECODER)
    ms = map_server or {}
    # The map server decodes what it inserts (issue 37: no decoder process on the twin) when it
    # counts undecodable clouds; then the twin's bridge hands it the clouds still compressed.
    server_decodes = "clouds_dropped_decoder" in ms
    captured_guess = enc[C.RECEIVED] + enc[C.MISSED] if enc else (stats_captured or 0)
    rate = captured_guess / duration_s if duration_s and duration_s > 0 else 0.0
    b = _Builder(robot, math.ceil(ALLOWED_UNSEEN_S * rate) if rate else 0)
    led = b.ledger
    missing = [
        label
        for label, found in (
            ("Draco encoder", enc),
            ("rate limiter", lim),
            ("robots' bridge", out),
            ("twin's bridge", inn),
            ("decoder", dec),
            ("map server", "clouds_received" in ms or None),
        )
        if not found and not (label == "decoder" and server_decodes)
    ]
    if missing:
        led.problems.append(f"counters not recorded: {', '.join(missing)}")
    if not (enc or lim or out or inn or dec) and "clouds_received" not in ms:
        inserted = ms.get("clouds_inserted")
        known = [
            (label, n) for label, n in ((CAPTURED, stats_captured), (AT_TWIN, stats_at_twin), (INSERTED, inserted)) if n
        ]
        led.stages = [(f"{label} (statistics' count)" if label != INSERTED else label, int(n)) for label, n in known]
        top = max((n for _, n in known), default=0)
        led.unaccounted = int(top - (inserted or 0))
        return led

    # previous: (where, what it passed on) of the last counted stage, to close each hop with the next.
    previous = None

    def arrive(label, counted, missed_cause):
        nonlocal previous
        if previous is not None:
            b.hop(f"{previous[0]} → {label}", previous[1], counted[C.RECEIVED] + counted[C.MISSED])
            b.drop(f"{previous[0]} → {label}: {missed_cause}", counted[C.MISSED])
        else:
            b.drop(f"before the {label}: {missed_cause}", counted[C.MISSED])

    if enc:
        led.stages.append((CAPTURED, int(enc[C.RECEIVED] + enc[C.MISSED])))
        b.drop("voxel grid → Draco encoder: subscriber queue", enc[C.MISSED])
        b.drop("Draco encoder: cloud could not be encoded", enc[C.DROPPED + "encoder"])
        b.internal("Draco encoder", enc[C.RECEIVED] - enc[C.OUT] - enc[C.DROPPED + "encoder"])
        led.stages.append((ENCODED, int(enc[C.OUT])))
        previous = ("Draco encoder", enc[C.OUT])
    elif stats_captured:
        led.stages.append((f"{CAPTURED} (statistics' count)", int(stats_captured)))
    if lim:
        arrive("rate limiter", lim, "subscriber queue")
        b.drop("rate limiter: above the rate the manager allocated", lim[C.DROPPED + "rate_limiter"])
        b.internal("rate limiter", lim[C.RECEIVED] - lim[C.OUT] - lim[C.DROPPED + "rate_limiter"])
        led.stages.append((TO_LINK, int(lim[C.OUT])))
        previous = ("rate limiter", lim[C.OUT])
    withheld, backfill_sent = 0.0, 0.0
    if out:
        arrive("robots' bridge", out, "subscriber queue")
        b.drop("link down: the robots' bridge held it back, no keyframe kept", out[C.DROPPED + "outage"])
        b.drop("robots' bridge: not of the topic's type", out[C.DROPPED + "type"])
        # Numbered, then dropped by its send queue's rules (cps_link.send_queue) or a failed put.
        queue_drops = {
            what: n
            for what, n in out.items()
            if what.startswith(C.DROPPED) and what not in (C.DROPPED + "outage", C.DROPPED + "type")
        }
        for what, n in sorted(queue_drops.items()):
            b.drop(f"robots' bridge's send queue: {what[len(C.DROPPED) :].replace('_', ' ')}", n)
        kept = out[C.BACKFILL_KEPT]
        b.internal(
            "robots' bridge",
            out[C.RECEIVED]
            - out[C.OUT]
            - out[C.DROPPED + "outage"]
            - out[C.DROPPED + "type"]
            - sum(queue_drops.values())
            - kept,
        )
        withheld = out[C.DROPPED + "outage"] + sum(queue_drops.values()) + kept
        if kept:
            evicted, backfill_sent = out[C.BACKFILL_EVICTED], out[C.BACKFILL_SENT]
            waiting = out[C.BACKFILL_WAITING]
            b.drop("backfill store full: keyframe evicted", evicted)
            if waiting:
                led.ends.append((STORED, int(waiting)))
            b.internal("backfill store", kept - evicted - backfill_sent - waiting)
        # Every cloud it received and numbered: those it put on the link and those it withheld.
        previous = ("robots' bridge", out[C.RECEIVED] - out[C.DROPPED + "type"])
    if inn:
        if previous is not None and previous[0] == "robots' bridge":
            b.hop("robots' bridge → twin's bridge", previous[1], inn[C.RECEIVED] + inn[C.MISSED])
            lost = inn[C.MISSED] - withheld  # the twin's gaps, less the frames withheld on purpose
            if lost < -b.allowed:
                b.internal("twin's bridge's sequence gaps against the robots' bridge's withheld clouds", lost)
            # A withheld frame shows at the twin as a gap only once a later frame arrives: the last
            # ones withheld before counting stopped are not gaps yet (the hop above counts them on
            # the way), up to the allowance.
            b.drop("link: put on the link, never received", max(0.0, lost))
        else:
            arrive("twin's bridge", inn, "link or subscriber queue")
        drops = {what: n for what, n in inn.items() if what.startswith(C.DROPPED)}
        for what, n in sorted(drops.items()):
            b.drop(f"twin's bridge: {what[len(C.DROPPED) :].replace('_', ' ')}", n)
        b.internal("twin's bridge", inn[C.RECEIVED] - inn[C.OUT] - sum(drops.values()))
        led.stages.append((AT_TWIN, int(inn[C.OUT])))
        previous = ("twin's bridge", inn[C.OUT])
    elif stats_at_twin:
        led.stages.append((f"{AT_TWIN} (statistics' count)", int(stats_at_twin)))
    decoded = 0.0
    if dec:
        arrive("decoder", dec, "subscriber queue" if inn else "relay, link or subscriber queue")
        b.drop("decoder: damaged payload", dec[C.DROPPED + "decoder"])
        b.internal("decoder", dec[C.RECEIVED] - dec[C.OUT] - dec[C.DROPPED + "decoder"])
        decoded = dec[C.OUT]
        previous = ("decoder", dec[C.OUT])
    if back_in or back_dec:  # the keyframes sent after an outage: a second path into the map server
        if back_in:
            b.hop("robots' bridge (backfill) → twin's bridge", backfill_sent, back_in[C.RECEIVED])
            drops = {what: n for what, n in back_in.items() if what.startswith(C.DROPPED)}
            for what, n in sorted(drops.items()):
                b.drop(f"twin's bridge (backfill): {what[len(C.DROPPED) :].replace('_', ' ')}", n)
            b.internal("twin's bridge (backfill)", back_in[C.RECEIVED] - back_in[C.OUT] - sum(drops.values()))
        if back_dec:
            if back_in:
                b.hop("twin's bridge → decoder (backfill)", back_in[C.OUT], back_dec[C.RECEIVED] + back_dec[C.MISSED])
                b.drop("twin's bridge → decoder (backfill): subscriber queue", back_dec[C.MISSED])
            b.drop("decoder (backfill): damaged payload", back_dec[C.DROPPED + "decoder"])
            b.internal("decoder (backfill)", back_dec[C.RECEIVED] - back_dec[C.OUT] - back_dec[C.DROPPED + "decoder"])
            decoded += back_dec[C.OUT]
        previous = ("decoder", decoded)
    if dec or back_dec:
        led.stages.append((DECODED, int(decoded)))
    elif server_decodes and back_in:  # both of the twin's bridge's outputs reach the map server
        previous = ("twin's bridge", (inn[C.OUT] if inn else 0.0) + back_in[C.OUT])
    if "clouds_received" in ms:
        received = ms["clouds_received"] + ms.get("clouds_missed_upstream", 0.0)
        if previous is not None:
            b.hop(f"{previous[0]} → map server", previous[1], received)
        before = previous[0] if previous else "before the map server"
        b.drop(f"{before} → map server: subscriber queue", ms.get("clouds_missed_upstream", 0))
        led.stages.append((AT_MAP, int(ms["clouds_received"])))
        b.drop("map server: no transform at the cloud's stamp", ms.get("clouds_dropped_tf", 0))
        b.drop("map server: invalid cloud", ms.get("clouds_dropped_invalid", 0))
        b.drop("map server: queue full", ms.get("clouds_dropped_queue", 0))
        b.drop("map server: undecodable cloud", ms.get("clouds_dropped_decoder", 0))
        ends = [
            (INSERTED, ms.get("clouds_inserted", 0.0)),
            (SUPERSEDED, ms.get("clouds_superseded", 0.0)),
            (WAITING, ms.get(MAP_SERVER_QUEUE, 0.0)),
        ]
        led.ends = [(what, int(n)) for what, n in ends if n or what == INSERTED] + led.ends
        b.internal(
            "map server",
            ms["clouds_received"]
            - sum(n for _, n in ends)
            - ms.get("clouds_dropped_tf", 0)
            - ms.get("clouds_dropped_invalid", 0)
            - ms.get("clouds_dropped_queue", 0)
            - ms.get("clouds_dropped_decoder", 0),
        )
    elif "clouds_inserted" in ms:
        led.ends = [(INSERTED, int(ms["clouds_inserted"]))] + led.ends
    return led


@dataclasses.dataclass
class Ledger:
    robots: Dict[str, RobotLedger]
    recorded: bool  # any node counters at all

    def incomplete_lines(self) -> List[str]:
        """One line per robot whose clouds are not all accounted for (the verdict's INCOMPLETE)."""
        return [
            f"ledger: {r.robot}'s clouds do not balance: {r.unaccounted} unaccounted"
            + (f" ({'; '.join(r.problems)})" if r.problems else "")
            for r in self.robots.values()
            if not r.balanced
        ]

    def markdown(self) -> List[str]:
        """The report's section: the path per robot, each drop by cause, what became of them."""
        lines = [
            "## Cloud ledger",
            "",
            "Every robot's clouds from capture to the map, from the nodes' own counters (`physical_counters.csv`, "
            "`counters.csv`, and the map server's in `map_age.csv`); a loss is counted by the node that saw it, with "
            f"its cause. Up to {ALLOWED_UNSEEN_S:g} s of a robot's clouds may be on their way between two nodes when "
            "counting stops (in flight); anything else that does not balance is unaccounted, and the mission is "
            "INCOMPLETE by it.",
            "",
        ]
        if not self.robots:
            return lines + ["No robot to account for.", ""]
        robots = list(self.robots.values())
        labels = []
        for r in robots:
            for label, _ in r.stages:
                if label not in labels:
                    labels.append(label)
        ends = []
        for r in robots:
            for label, _ in r.ends:
                if label not in ends:
                    ends.append(label)
        header = ["robot", *labels, *ends, "dropped", "in flight at the end", "unaccounted", "balance"]
        rows = []
        for r in robots:
            stages, finals = dict(r.stages), dict(r.ends)
            rows.append(
                [r.robot]
                + [stages.get(label, "-") for label in labels]
                + [finals.get(label, 0) for label in ends]
                + [r.dropped, r.in_flight, r.unaccounted, "balances" if r.balanced else "**INCOMPLETE**"]
            )
        lines += [markdown_table(header, rows), ""]
        causes = []
        for r in robots:
            for cause, _ in r.drops:
                if cause not in causes:
                    causes.append(cause)
        if causes:
            lines += [
                "Dropped, by cause:",
                "",
                markdown_table(
                    ["cause", *(r.robot for r in robots)],
                    [[cause, *(dict(r.drops).get(cause, 0) for r in robots)] for cause in causes],
                ),
                "",
            ]
        else:
            lines += ["Dropped: none, by any counted cause.", ""]
        problems = [f"- {r.robot}: {p}" for r in robots for p in r.problems]
        if problems:
            lines += ["Why it does not balance:", "", *problems, ""]
        return lines


# Each side's stages, read from that side's file only (a side's /diagnostics may also carry the
# other side's, relayed by the bridges, late or not at all during an outage).
PHYSICAL_STAGES = (C.ENCODER, C.LIMITER, C.BRIDGE_OUT)
TWIN_STAGES = (C.BRIDGE_IN, C.DECODER)


def _side_rows(folder):
    """counters rows of both files, each file's own side's stages only."""
    rows = []
    for name, stages in ((PHYSICAL_COUNTERS_CSV, PHYSICAL_STAGES), (COUNTERS_CSV, TWIN_STAGES)):
        for row in _read(os.path.join(folder, name)) or []:
            parsed = C.parse_key(row.get("key", ""))
            if parsed and parsed[0] in stages:
                rows.append(row)
    return rows


def read_ledger(folder, robots, duration_s=None) -> Ledger:
    """The ledger of the mission in `folder` for `robots`."""
    counters = node_counters(_side_rows(folder))
    map_age = _read(os.path.join(folder, MAP_AGE_CSV)) or []
    servers = map_server_counters(map_age)
    if duration_s is None:
        times = [csv_float(r.get("time_s")) for r in map_age]
        times = [t for t in times if math.isfinite(t)]
        duration_s = max(times) - min(times) if times else 0.0
    captured = _arrival_counts(_read(os.path.join(folder, "physical_arrivals.csv")), "/" + names.POINTS_FILTERED)
    at_twin = _arrival_counts(_read(os.path.join(folder, "arrivals.csv")), "/" + names.POINTS_MANAGED)
    return Ledger(
        {r: robot_ledger(r, counters, servers.get(r), duration_s, captured.get(r), at_twin.get(r)) for r in robots},
        recorded=bool(counters),
    )


def _arrival_counts(rows, suffix) -> Dict[str, int]:
    """Clouds per robot an arrivals file saw on topics ending with `suffix` (a statistics node's count)."""
    out = defaultdict(int)
    for row in rows or []:
        if row.get("robot") and row.get("topic", "").endswith(suffix):
            out[row["robot"]] += 1
    return out


def balanced(ledger: Optional[Ledger]) -> bool:
    return ledger is not None and all(r.balanced for r in ledger.robots.values())
