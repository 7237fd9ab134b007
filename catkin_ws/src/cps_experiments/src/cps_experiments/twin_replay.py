"""The twin alone under a replayed fleet: one trial replays a recorded mission as N robots
(cps_bringup.trace_replay) into the twin's map server and returns what the twin did with the clouds,
every one accounted for by cause, its throughput, its map ages and its CPU. `holds` judges a trial.

The ledger of a trial, from the nodes' own counters (the replay's summary and the map server's last
MapStats, read after the replay ended and the twin drained):

    sent (the replay's publish() returned) = inserted + superseded + waiting
        + dropped: queue (the map server's backfill FIFO, and gaps in the senders' sequence numbers:
          lost between publish() and the map server), decoder, tf, map server (its checks)
        + unaccounted (sent, never received, no gap to show it: still in flight, or lost at the end)

and the replay's own drops (publish() raised) are counted beside `sent`. Throughput is measured over
the steady window (from WARMUP_S after the first insertion to the replay's end): inserted clouds and
points per second from the counters' growth; map age p95 over every robot's 1 Hz map_age_s in that
window, per robot too (the oldest robot's p95 against the median robot's: no robot starves).

Used by bench/twin_capacity.py (the sweep N = 8 ... 128) and by fig13_live's replay rows (N = 32
and 64). The caller owns the ROS master, the host split and this process's rospy node.
"""

import json
import math
import os
import subprocess
import sys
import threading
import time
from contextlib import contextmanager

import numpy as np

from cps_ros.processes import descendants, process_cpu_s

REPLAY = "trace_replay"  # cps_bringup's node script
WARMUP_S = 8.0
MAX_DROPPED = 0.01
# Superseded in a robot's slot: the newer cloud is inserted instead. A few percent come from clouds
# arriving together (8 and 16 replayed robots: 4-11 %); past a quarter the twin inserts a fraction
# of what it is sent, and that is not holding the fleet (issue 34: 24 robots "held" at 63 %).
MAX_SUPERSEDED = 0.25
MAX_AGE_P95_S = 1.0
DRAIN_S = 3.0
# Beyond its capacity the twin's map age p95 should stay within this many times N / inserted per s
# (each robot served in turn: N / rate between its insertions; issue 37).
AGE_BAR_FACTOR = 1.5
# Issue 37's other bars on a sweep: inserted clouds/s never falls more than this below its highest
# at a smaller N (no cliff), and the oldest robot's map age p95 stays within this many times the
# median robot's (no robot starves).
MAX_FALL = 0.10
MAX_OLDEST_OVER_MEDIAN = 2.0
# The replay keeps at least 20 odom -> base transforms per second per copy (recorded: ~50) and no
# odometry: the twin's cloud path needs tf at the clouds' stamps only, and one Python replay must
# keep up. A cloud waits in the map server for the first transform after its stamp, and a newer
# cloud of its robot supersedes it there: tf at TF_PER_CLOUD times the fastest cloud rate keeps
# that wait within half a cloud period (`replay_tf_rate_hz`).
TF_RATE_HZ = 20.0
TF_PER_CLOUD = 2.0
# A replay whose clouds leave later than this (p95, when publish() returned) limits the trial, not
# the twin: marked so.
MAX_REPLAY_LATE_S = 0.1
# Robots per replay process (one Python process keeps time for ~16: 0.02 s late p95 at 16, 0.7 s at 32).
ROBOTS_PER_REPLAY = 8
# The drop causes of a row, in the ledger's order (sent = the sum of these).
CAUSES = ("inserted", "superseded", "waiting", "queue", "decoder", "tf", "map_server", "unaccounted")


def replay_tf_rate_hz(profile):
    """The odom -> base transforms per second a replay of `profile` (fleet.yaml's profiles) sends per
    copy: TF_PER_CLOUD times its fastest sensor's cloud rate, at least TF_RATE_HZ, at most what the
    simulator publishes (cps_sim's odom rate). Light: 20 Hz; paper: 50 Hz (its 30 Hz camera clouds
    against 20 Hz tf: 33 % of the clouds superseded at 8 robots with the twin's CPU half idle, 18 %
    at 50 Hz, session 22)."""
    from cps_fleet.fleet import load_fleet
    from cps_sim.fleet_sim_node import FleetSimOptions

    rates = load_fleet().with_profile(profile).profile
    fastest_hz = max(rates.depth_camera.rate_hz, rates.lidar.rate_hz)
    return min(FleetSimOptions().odom_rate_hz, max(TF_RATE_HZ, TF_PER_CLOUD * fastest_hz))


def _replay_script():
    from cps_ros.processes import find_node

    return find_node("cps_bringup", REPLAY)


class Watch:
    """The twin's MapStats and InsertCapacity, as they arrive (this process's rospy node). The map
    server decodes what it inserts (no decoder process on the twin): its counters hold every cause."""

    def __init__(self):
        import rospy

        from cps_fleet import names
        from cps_msgs.msg import InsertCapacity, MapStats

        self.lock = threading.Lock()
        self.stats, self.capacity = [], []
        rospy.Subscriber(names.absolute(names.in_twin(names.MAP_STATS)), MapStats, self._on_stats, queue_size=20)
        rospy.Subscriber(
            names.absolute(names.in_twin(names.INSERT_CAPACITY)), InsertCapacity, self._on_capacity, queue_size=20
        )

    def _on_stats(self, msg):
        with self.lock:
            self.stats.append((time.monotonic(), msg))

    def _on_capacity(self, msg):
        with self.lock:
            self.capacity.append((time.monotonic(), msg))

    def clear(self):
        with self.lock:
            self.stats, self.capacity = [], []


def map_ages(stats, robots, played, warmup_s=WARMUP_S):
    """{robot: its map ages, s} from MapStats messages, each robot's from `warmup_s` after the stamp of
    the first cloud its replay sent to the stamp of its last (`played`: {robot: (first s, last s)};
    a robot without them: every message). The replays' shards start and end apart (at 128 robots on
    one twin CPU up to ~1 s; on two CPUs shared with the twin 7 of 16 shards began after the others'
    warm-up, and their copies' ages were infinite in the window): before its replay, and after it,
    a copy's map age grows with nothing for the twin to insert (at 128 robots the tail made the
    pooled p95 2.3 s while every robot was served at least every 0.95 s)."""
    ages = {r: [] for r in robots}
    for msg in stats:
        stamp_s = msg.header.stamp.to_sec()
        for row in msg.robots:
            if row.robot not in ages:
                continue
            first_s, last_s = played.get(row.robot, (-math.inf, math.inf))
            if first_s + warmup_s <= stamp_s <= last_s:
                ages[row.robot].append(row.map_age_s)
    return ages


def ledger(sent, replay_dropped, rows):
    """{cause: clouds} of a trial from the replay's sent count and the map server's RobotMapStats
    of the copies (module docstring); the causes sum to `sent`."""

    def total(field):
        return sum(getattr(r, field) for r in rows)

    counts = dict(
        inserted=total("clouds_inserted"),
        superseded=total("clouds_superseded"),
        waiting=total("queue_length"),
        queue=total("clouds_dropped_queue") + total("clouds_missed_upstream"),
        decoder=total("clouds_dropped_decoder"),
        tf=total("clouds_dropped_tf"),
        map_server=total("clouds_dropped_invalid"),
    )
    # Sent but neither received nor missed (lost where no counter sees it), or received and in no
    # counter (a map server bug): `unaccounted`, never hidden. The second part alone, for the report:
    counts["unaccounted"] = sent - sum(counts.values())
    counts["received_not_ended"] = (
        total("clouds_received")
        - sum(counts[c] for c in ("inserted", "superseded", "waiting", "decoder", "tf", "map_server"))
        - total("clouds_dropped_queue")
    )
    counts["replay_dropped"] = replay_dropped
    return counts


def _window_rate(stats, robots, field, start, end):
    """Growth per second of a RobotMapStats field summed over `robots`, between the samples nearest
    `start` and `end` (monotonic s)."""
    inside = [(t, m) for t, m in stats if start <= t <= end]
    if len(inside) < 2:
        return 0.0
    (t0, m0), (t1, m1) = inside[0], inside[-1]

    def total(msg):
        return sum(getattr(r, field) for r in msg.robots if r.robot in robots)

    return (total(m1) - total(m0)) / (t1 - t0) if t1 > t0 else 0.0


def cpu_ticks(cpus):
    """(busy, total) jiffies of `cpus` so far, from /proc/stat: what every process on them used."""
    busy = total = 0
    with open("/proc/stat") as stream:
        for line in stream:
            name, *fields = line.split()
            if name.startswith("cpu") and name[3:].isdigit() and int(name[3:]) in cpus:
                ticks = [int(x) for x in fields[:8]]
                idle = ticks[3] + ticks[4]  # idle, iowait
                busy, total = busy + sum(ticks) - idle, total + sum(ticks)
    return busy, total


class CpuSampler:
    """Once a second: the twin's processes' CPU (the map server, and its receive process apart) and
    how busy the twin's CPUs were with anything, so that the figures cover the steady window only."""

    def __init__(self, map_server_pid, cpus, period_s=1.0):
        self.pids = [map_server_pid, *descendants(map_server_pid)]
        self.cpus, self.period_s = tuple(cpus), period_s
        self.samples = []  # (monotonic s, twin CPU s, receive CPU s, busy ticks, total ticks)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="cpu_sampler", daemon=True)
        self._thread.start()

    def _sample(self):
        twin = sum(process_cpu_s(p) for p in self.pids)
        receive = sum(process_cpu_s(p) for p in self.pids[1:])
        self.samples.append((time.monotonic(), twin, receive, *cpu_ticks(self.cpus)))

    def _run(self):
        while True:
            self._sample()
            if self._stop.wait(self.period_s):
                return

    def stop(self):
        self._stop.set()
        self._thread.join()

    def over(self, start, end):
        """(twin CPU s/s, receive CPU s/s, twin CPUs busy) between the samples nearest `start`, `end`."""
        inside = [s for s in self.samples if start <= s[0] <= end] or self.samples
        if len(inside) < 2:
            return 0.0, 0.0, 0.0
        first, last = inside[0], inside[-1]
        wall = last[0] - first[0]
        busy = (last[3] - first[3]) / max(1, last[4] - first[4])
        return (last[1] - first[1]) / wall, (last[2] - first[2]) / wall, busy


def _percentile(values, q):
    return float(np.percentile(values, q)) if len(values) else math.inf


def trial(
    graph,
    watch,
    split,
    bag,
    n,
    duration_s,
    out_dir,
    label="",
    replay_args=(),
    map_server_args=(),
    tf_rate_hz=TF_RATE_HZ,
):
    """One replay of `n` robots (`map_server_args`: the map server's extra arguments, such as
    private parameters; `tf_rate_hz`: transforms per second per copy); the figures of the run (a
    dict, JSON-ready)."""
    from cps_bringup.plan import DIGITAL, PHYSICAL
    from cps_bringup.supervisor import Supervisor
    from cps_bringup.trace_replay import twin_specs
    from cps_fleet.fleet import load_fleet

    folder = os.path.join(out_dir, f"{label or 'replay'}_{n}")
    os.makedirs(folder, exist_ok=True)
    copies_fleet = os.path.join(folder, "copies.yaml")
    plan = subprocess.run(
        [sys.executable, _replay_script(), bag, "--robots", str(n), "--duration", "1", "--copies-fleet", copies_fleet]
        + ["--plan-only", *replay_args],
        capture_output=True,
        text=True,
        check=True,
    )
    robots = load_fleet(copies_fleet).robot_names
    note = next((line for line in plan.stdout.splitlines() if "asked for" in line), "")
    supervisor = Supervisor(
        twin_specs(copies_fleet, folder, map_server_args),
        graph,
        log=lambda _m: None,
        spec_prefix=lambda spec: split.prefix(DIGITAL),
    )
    sampler = None
    shards = math.ceil(n / ROBOTS_PER_REPLAY)
    tag = f"replay_{label}_{n}_{time.monotonic_ns()}"
    try:
        supervisor.start_all(timeout_s=180)
        sampler = CpuSampler(supervisor.pid_of(supervisor.specs[0].label), split.cpus.get(DIGITAL, ()))
        watch.clear()
        replays = [
            graph.popen(
                [*split.prefix(PHYSICAL), sys.executable, _replay_script(), bag, "--robots", str(n)]
                + ["--duration", str(duration_s), "--copies-fleet", copies_fleet, "--no-odom"]
                + ["--tf-rate", str(tf_rate_hz), "--wait-for-subscribers", "30", "--shard", f"{i}/{shards}"]
                + list(replay_args),
                name=f"{tag}_{i}",
            )
            for i in range(shards)
        ]
        for replay in replays:
            replay.wait(timeout=duration_s + 120)
        end = time.monotonic()
        time.sleep(DRAIN_S)  # the last clouds through the slots, and one more MapStats after them
    finally:
        if sampler is not None:
            sampler.stop()
        supervisor.stop_all()
    sent, played, replay_dropped, late, stalls, errors = {}, {}, 0, [], [], []
    for i in range(shards):
        output = graph.output(f"{tag}_{i}")
        sent_line = next((line for line in reversed(output.splitlines()) if "sent clouds:" in line), None)
        if sent_line is None:
            raise RuntimeError(f"the replay of {n} (shard {i}) did not finish: {output[-2000:]}")
        summary = json.loads(sent_line[sent_line.index("{") :])
        sent.update(summary["sent"])
        for robot, last_s in summary.get("last_cloud_stamp_s", {}).items():
            played[robot] = (summary["first_cloud_stamp_s"][robot], last_s)
        replay_dropped += sum(summary.get("dropped", {}).values())
        late.append(summary["late_p95_s"])
        stalls += summary.get("stalls_s", [])
        errors += summary.get("publish_errors", [])
    with watch.lock:
        stats, capacity = list(watch.stats), list(watch.capacity)
    if not stats:
        raise RuntimeError("no map_stats from the map server")
    last = {r.robot: r for r in stats[-1][1].robots if r.robot in robots}
    total_sent = sum(sent.values())
    counts = ledger(total_sent, replay_dropped, list(last.values()))
    # The steady window starts WARMUP_S after the first copy's first insertion (the replay reads its trace first).
    first = next((t for t, msg in stats if any(r.clouds_inserted for r in msg.robots if r.robot in robots)), end)
    start = first + WARMUP_S
    window = [(t, m) for t, m in stats if start <= t <= end]
    ages = map_ages([m for _, m in window], robots, played)
    pooled = [a for values in ages.values() for a in values]
    per_robot_p95 = [_percentile(v, 95) for v in ages.values() if v]
    median_p95 = float(np.median(per_robot_p95)) if per_robot_p95 else math.inf
    oldest_p95 = max(per_robot_p95) if per_robot_p95 else math.inf
    inserted_per_s = _window_rate(stats, robots, "clouds_inserted", start, end)
    steady = [m for t, m in capacity if start <= t <= end]
    cap = steady[-1] if steady else (capacity[-1][1] if capacity else None)
    lost = sum(counts[c] for c in ("queue", "decoder", "tf", "map_server", "unaccounted")) + replay_dropped
    twin_cpu, receive_cpu, cpus_busy = sampler.over(start, end)
    row = dict(
        label=label,
        asked=n,
        robots=len(robots),
        note=note,
        duration_s=duration_s,
        tf_rate_hz=tf_rate_hz,
        window_s=max(0.0, end - start),
        sent=total_sent,
        offered_clouds_per_s=total_sent / duration_s if duration_s else 0.0,
        received=sum(r.clouds_received for r in last.values()),
        **{f"clouds_{cause}": counts[cause] for cause in CAUSES},
        received_not_ended=counts["received_not_ended"],
        replay_dropped=replay_dropped,
        replay_errors=errors,
        inserted=counts["inserted"],
        superseded=counts["superseded"],
        dropped=lost,
        dropped_pct=100.0 * lost / total_sent if total_sent else 100.0,
        superseded_pct=100.0 * counts["superseded"] / total_sent if total_sent else 0.0,
        inserted_clouds_per_s=inserted_per_s,
        inserted_points_per_s=_window_rate(stats, robots, "points_inserted", start, end),
        age_p95_s=_percentile(pooled, 95),
        age_p50_s=_percentile(pooled, 50),
        oldest_robot_age_p95_s=oldest_p95,
        median_robot_age_p95_s=median_p95,
        oldest_over_median=oldest_p95 / median_p95 if median_p95 > 0 else math.inf,
        robot_age_p95_s={r: _percentile(v, 95) for r, v in ages.items() if v},
        age_bar_s=AGE_BAR_FACTOR * len(robots) / inserted_per_s if inserted_per_s > 0 else math.inf,
        twin_cpu_s_per_s=twin_cpu,
        receive_cpu_s_per_s=receive_cpu,
        twin_cpus_busy=cpus_busy,  # by anything: the twin, or other work on a shared machine
        insertion_cpu_s_per_s=(cap.busy_s / cap.window_s) if cap and cap.window_s else 0.0,
        counted_by="the nodes' counters (the replay's, the map server's)",
        busy_s=cap.busy_s if cap else 0.0,
        capacity_window_s=cap.window_s if cap else 0.0,
        clouds_per_s_capacity=cap.clouds_per_s if cap else 0.0,
        points_per_s_capacity=cap.points_per_s if cap else 0.0,
        voxel_updates_per_s_capacity=cap.voxel_updates_per_s if cap else 0.0,
        insertion_ms_avg=float(np.mean([r.insertion_ms_avg for r in last.values() if r.clouds_inserted] or [0.0])),
    )
    row["replay_late_p95_s"] = max(late)
    row["replay_stalls_s"] = stalls
    row["replay_limited"] = row["replay_late_p95_s"] > MAX_REPLAY_LATE_S or bool(stalls)
    row["ledger_balances"] = counts["unaccounted"] == 0 and counts["received_not_ended"] == 0
    row["holds"] = holds(row)
    return row


def holds(row):
    """N holds when at most MAX_DROPPED of the clouds sent were lost (dropped or unaccounted), at
    most MAX_SUPERSEDED were superseded (the twin inserts what it is sent, not a fraction of it) and
    every robot's map age p95 is at most MAX_AGE_P95_S (the oldest robot's; the pooled p95 for a row
    without it); a figure not measured (NaN) does not hold."""
    age = row.get("oldest_robot_age_p95_s", row.get("age_p95_s"))
    figures = (row.get("dropped_pct"), row.get("superseded_pct"), age)
    if any(v is None or not math.isfinite(v) for v in figures):
        return False
    return (
        row["dropped_pct"] <= 100 * MAX_DROPPED
        and row["superseded_pct"] <= 100 * MAX_SUPERSEDED
        and age <= MAX_AGE_P95_S
    )


def judge_sweep(rows):
    """Issue 37's bars on one sweep's rows (trial's dicts): the capacity (the largest N that holds,
    measured), the worst fall of inserted clouds/s from the capacity on, freshness in proportion and
    no robot starving beyond it, and every cloud accounted for at every N."""
    rows = sorted(rows, key=lambda r: r["robots"])
    capacity = max((r["robots"] for r in rows if holds(r)), default=0)
    worst_fall, peak = 0.0, 0.0
    for r in rows:
        if r["robots"] >= capacity:
            peak = max(peak, r["inserted_clouds_per_s"])
            worst_fall = max(worst_fall, 1.0 - r["inserted_clouds_per_s"] / peak if peak else 0.0)
    beyond = [r for r in rows if r["robots"] > capacity]
    fresh = [r for r in rows if r["oldest_robot_age_p95_s"] <= MAX_AGE_P95_S and r["dropped_pct"] <= 100 * MAX_DROPPED]
    return dict(
        capacity=capacity,
        # Issue 37's words alone: every robot's map age p95 <= MAX_AGE_P95_S, <= MAX_DROPPED lost
        # (superseded not judged); beside `capacity`, never instead of it.
        fresh_capacity=max((r["robots"] for r in fresh), default=0),
        worst_fall=worst_fall,
        no_cliff=worst_fall <= MAX_FALL,
        fresh_beyond=all(r["age_p95_s"] <= r["age_bar_s"] for r in beyond),
        no_starving=all(r["oldest_over_median"] <= MAX_OLDEST_OVER_MEDIAN for r in beyond),
        ledger=all(r["clouds_unaccounted"] == 0 for r in rows),
    )


# The columns of a trial's row written as CSV (fig13_live's replay rows), in order.
CSV_COLUMNS = (
    "label",
    "robots",
    "duration_s",
    "sent",
    "offered_clouds_per_s",
    *(f"clouds_{cause}" for cause in CAUSES),
    "replay_dropped",
    "superseded_pct",
    "dropped_pct",
    "inserted_clouds_per_s",
    "inserted_points_per_s",
    "age_p50_s",
    "age_p95_s",
    "oldest_robot_age_p95_s",
    "median_robot_age_p95_s",
    "oldest_over_median",
    "age_bar_s",
    "twin_cpu_s_per_s",
    "receive_cpu_s_per_s",
    "insertion_cpu_s_per_s",
    "twin_cpus_busy",
    "clouds_per_s_capacity",
    "points_per_s_capacity",
    "insertion_ms_avg",
    "replay_late_p95_s",
    "replay_limited",
    "ledger_balances",
    "holds",
)


@contextmanager
def replay_bench(out_dir, twin_cpus=None, twin_shares=16384, replay_shares=16384, name="cps_twin_replay"):
    """A private master, the twin on `twin_cpus` (default: the last CPU) and the replays on the
    others (on every CPU when the twin has them all), and this process's rospy node watching the
    twin; yields (run(n, bag, duration_s, label="", replay_args=(), map_server_args=(), tf_rate_hz=TF_RATE_HZ),
    the split's description).
    Everything is stopped and removed on exit."""
    from cps_bringup.host_split import HostSplit, online_cpus
    from cps_bringup.plan import DIGITAL, PHYSICAL
    from cps_ros.processes import RosGraph, free_port

    os.makedirs(os.path.join(out_dir, "logs"), exist_ok=True)
    cpus = online_cpus()
    twin = tuple(twin_cpus) if twin_cpus else (cpus[-1],)
    robots_side = tuple(c for c in cpus if c not in twin) or cpus
    split = HostSplit.choose(
        {PHYSICAL: robots_side, DIGITAL: twin},
        name=f"{name}_{os.getpid()}",
        shares={DIGITAL: twin_shares, PHYSICAL: replay_shares},
    )
    with split, RosGraph(port=free_port(), log_dir=os.path.join(out_dir, "logs")) as graph:
        import rospy

        graph.point_this_process_here()
        rospy.init_node("twin_replay", anonymous=True, disable_signals=True)
        watch = Watch()
        try:
            yield (
                lambda n, bag, duration_s, label="", replay_args=(), map_server_args=(), tf_rate_hz=TF_RATE_HZ: trial(
                    graph, watch, split, bag, n, duration_s, out_dir, label, replay_args, map_server_args, tf_rate_hz
                ),
                split.describe(),
            )
        finally:
            rospy.signal_shutdown("done")
