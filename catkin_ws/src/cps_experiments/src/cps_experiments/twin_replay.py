"""The twin alone under a replayed fleet: one trial replays a recorded mission as N robots
(cps_bringup.trace_replay) into the twin's decoder(s) and map server, and returns what the twin did
with the clouds, from the nodes' own counters (the decoder's ledger, the map server's inserted,
superseded and dropped by cause), its map age and its CPU share (from just before the replay to the
end of the drain, over that span). `holds` judges a trial.

Used by bench/twin_capacity.py (the largest N one twin core holds) and by fig13_live's replay rows
(N = 32 and 64). The caller owns the ROS master, the host split and this process's rospy node.
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

from cps_ros.processes import process_cpu_s

REPLAY = "trace_replay"  # cps_bringup's node script
WARMUP_S = 8.0
MAX_DROPPED = 0.01
# Superseded in a robot's slot: the newer cloud is inserted instead. A few percent come from clouds
# arriving together (8 and 16 replayed robots: 4-11 %); past a quarter the twin inserts a fraction
# of what it is sent, and that is not holding the fleet (issue 34: 24 robots "held" at 63 %).
MAX_SUPERSEDED = 0.25
MAX_AGE_P95_S = 1.0
DRAIN_S = 3.0
# The replay keeps 20 odom -> base transforms per second per copy (recorded: ~50) and no odometry:
# the twin's cloud path needs tf at the clouds' stamps only, and one Python replay must keep up.
TF_RATE_HZ = 20.0
# A replay whose clouds leave later than this (p95) limits the trial, not the twin: marked so.
MAX_REPLAY_LATE_S = 0.1
# Robots per replay process (one Python process keeps time for ~16: 0.02 s late p95 at 16, 0.7 s at 32).
ROBOTS_PER_REPLAY = 8


def _replay_script():
    from cps_ros.processes import find_node

    return find_node("cps_bringup", REPLAY)


class Watch:
    """The twin's MapStats, InsertCapacity and the decoders' ledger counters (cps_ros.cloud_ledger on
    /diagnostics), as they arrive (this process's rospy node)."""

    def __init__(self):
        import rospy
        from diagnostic_msgs.msg import DiagnosticArray

        from cps_fleet import names
        from cps_msgs.msg import InsertCapacity, MapStats

        self.lock = threading.Lock()
        self.stats, self.capacity = [], []
        self.decoders = {}  # (node, input topic) -> {ledger key: value}, the newest
        rospy.Subscriber("/" + names.in_twin(names.MAP_STATS), MapStats, self._on_stats, queue_size=20)
        rospy.Subscriber("/" + names.in_twin(names.INSERT_CAPACITY), InsertCapacity, self._on_capacity, queue_size=20)
        rospy.Subscriber(names.absolute(names.DIAGNOSTICS), DiagnosticArray, self._on_diagnostics, queue_size=100)

    def _on_diagnostics(self, array):
        from cps_ros.cloud_ledger import LEDGER_PREFIX

        with self.lock:
            for status in array.status:
                values = {kv.key: kv.value for kv in status.values if kv.key.startswith(LEDGER_PREFIX)}
                if values:
                    topic = next((kv.value for kv in status.values if kv.key == "input_topic"), status.hardware_id)
                    self.decoders[(status.name, topic)] = values

    def _on_stats(self, msg):
        with self.lock:
            self.stats.append((time.monotonic(), msg))

    def _on_capacity(self, msg):
        with self.lock:
            self.capacity.append((time.monotonic(), msg))

    def clear(self):
        with self.lock:
            self.stats, self.capacity, self.decoders = [], [], {}

    def decoder_counts(self, robots):
        """{what: total} of the decoders' ledger counters (stage decoder) over `robots`' inputs."""
        from cps_fleet import names
        from cps_ros import cloud_ledger

        topics = {names.absolute(names.managed_cloud_at_twin(r)) for r in robots}
        out = {}
        with self.lock:
            for (_, topic), values in self.decoders.items():
                if topic not in topics:
                    continue
                for key, value in values.items():
                    parsed = cloud_ledger.parse_key(key)
                    if parsed and parsed[0] == cloud_ledger.DECODER:
                        out[parsed[1]] = out.get(parsed[1], 0) + int(float(value))
        return out


def trial(graph, watch, split, bag, n, layout, duration_s, out_dir):
    """One replay of `n` robots; the figures of the run."""
    from cps_bringup.plan import DIGITAL, PHYSICAL
    from cps_bringup.supervisor import Supervisor
    from cps_bringup.trace_replay import twin_specs
    from cps_fleet.fleet import load_fleet

    folder = os.path.join(out_dir, f"{layout}_{n}")
    os.makedirs(folder, exist_ok=True)
    copies_fleet = os.path.join(folder, "copies.yaml")
    plan = subprocess.run(
        [sys.executable, _replay_script(), bag, "--robots", str(n), "--duration", "1", "--copies-fleet", copies_fleet]
        + ["--plan-only"],
        capture_output=True,
        text=True,
        check=True,
    )
    robots = load_fleet(copies_fleet).robot_names
    note = next((line for line in plan.stdout.splitlines() if "asked for" in line), "")
    supervisor = Supervisor(
        twin_specs(copies_fleet, folder, layout),
        graph,
        log=lambda _m: None,
        spec_prefix=lambda spec: split.prefix(DIGITAL),
    )
    twin_pids = []
    try:
        supervisor.start_all(timeout_s=180)
        twin_pids = [supervisor.pid_of(s.label) for s in supervisor.specs]
        cpu0 = sum(process_cpu_s(p, waited_children=True) for p in twin_pids)
        watch.clear()
        replay_start = time.monotonic()  # the twin's CPU is measured from here: its share over the same span
        shards = math.ceil(n / ROBOTS_PER_REPLAY)
        replays = [
            graph.popen(
                [
                    *split.prefix(PHYSICAL),
                    sys.executable,
                    _replay_script(),
                    bag,
                    "--robots",
                    str(n),
                    "--duration",
                    str(duration_s),
                ]
                + ["--copies-fleet", copies_fleet, "--no-odom", "--tf-rate", str(TF_RATE_HZ)]
                + ["--wait-for-subscribers", "30", "--shard", f"{i}/{shards}"],
                name=f"replay_{layout}_{n}_{i}",
            )
            for i in range(shards)
        ]
        for replay in replays:
            replay.wait(timeout=duration_s + 120)
        end = time.monotonic()
        time.sleep(DRAIN_S)  # the last clouds through the decoder and the slots
        cpu_s = sum(process_cpu_s(p, waited_children=True) for p in twin_pids) - cpu0
    finally:
        supervisor.stop_all()
    sent, late, stalls = {}, [], []
    for i in range(shards):
        output = graph.output(f"replay_{layout}_{n}_{i}")
        sent_line = next((line for line in reversed(output.splitlines()) if "sent clouds:" in line), None)
        if sent_line is None:
            raise RuntimeError(f"the replay of {n} (shard {i}) did not finish: {output[-2000:]}")
        summary = json.loads(sent_line[sent_line.index("{") :])
        sent.update(summary["sent"])
        late.append(summary["late_p95_s"])
        stalls += summary.get("stalls_s", [])
    summary = dict(late_p95_s=max(late), stalls_s=stalls)
    with watch.lock:
        stats, capacity = list(watch.stats), list(watch.capacity)
    if not stats:
        raise RuntimeError("no map_stats from the map server")
    last = {r.robot: r for r in stats[-1][1].robots}
    # The map age's window starts WARMUP_S after the first copy's first insertion (the replay reads its
    # trace first).
    first = next((t for t, msg in stats if any(r.clouds_inserted for r in msg.robots if r.robot in robots)), end)
    start = first
    ages = [r.map_age_s for t, msg in stats if first + WARMUP_S <= t <= end for r in msg.robots if r.robot in robots]

    def total(field):
        return sum(getattr(last[r], field) for r in robots if r in last)

    # Every cloud by what the nodes counted (the ledger): the decoder's received and the replay's
    # clouds it never got (gaps in the publishers' numbers), its drops; the map server's received,
    # the decoder's clouds it never got, inserted, superseded (its own counter), dropped, waiting.
    decoder = watch.decoder_counts(robots)
    inserted, received, superseded = total("clouds_inserted"), total("clouds_received"), total("clouds_superseded")
    waiting = total("queue_length")
    by_cause = {
        "replay → decoder (queues)": decoder.get("missed", 0),
        "decoder: damaged payload": decoder.get("dropped_decoder", 0),
        "decoder → map server (queues)": total("clouds_missed_upstream"),
        "map server: no transform": total("clouds_dropped_tf"),
        "map server: invalid": total("clouds_dropped_invalid"),
        "map server: queue": total("clouds_dropped_queue"),
    }
    total_sent = sum(sent.values())
    dropped = sum(by_cause.values())
    unaccounted = total_sent - inserted - superseded - waiting - dropped
    steady = [m for t, m in capacity if t >= start + WARMUP_S]
    cap = steady[-1] if steady else (capacity[-1][1] if capacity else None)
    age_p95 = float(np.percentile(ages, 95)) if ages else math.inf
    row = dict(
        layout=layout,
        asked=n,
        robots=len(robots),
        note=note,
        sent=total_sent,
        received=received,
        inserted=inserted,
        superseded=superseded,
        dropped=dropped,
        dropped_by_cause=by_cause,
        unaccounted=unaccounted,
        decoder_received=decoder.get("received", 0),
        dropped_pct=100.0 * (dropped + max(unaccounted, 0)) / total_sent if total_sent else 100.0,
        superseded_pct=100.0 * superseded / total_sent if total_sent else 0.0,
        age_p95_s=age_p95,
        # CPU from just before the replays started to the end of the drain, over that same span.
        twin_cpu_s_per_s=cpu_s / max(end + DRAIN_S - replay_start, 1e-9),
        counted_by="the nodes' counters (decoder ledger, map server)",
        busy_s=cap.busy_s if cap else 0.0,
        window_s=cap.window_s if cap else 0.0,
        clouds_per_s_capacity=cap.clouds_per_s if cap else 0.0,
        voxel_updates_per_s_capacity=cap.voxel_updates_per_s if cap else 0.0,
        insertion_voxel_updates_per_busy_s=(cap.voxel_updates_per_s / 0.8) if cap else 0.0,
    )
    row["replay_late_p95_s"] = summary["late_p95_s"]
    row["replay_stalls_s"] = summary["stalls_s"]
    row["replay_limited"] = summary["late_p95_s"] > MAX_REPLAY_LATE_S or bool(summary["stalls_s"])
    row["holds"] = holds(row)
    return row


def holds(row):
    """N holds when at most MAX_DROPPED of the clouds sent were lost (dropped or unaccounted), at
    most MAX_SUPERSEDED were superseded (the twin inserts what it is sent, not a fraction of it) and
    the map age p95 is at most MAX_AGE_P95_S; a figure not measured (NaN) does not hold."""
    figures = (row.get("dropped_pct"), row.get("superseded_pct"), row.get("age_p95_s"))
    if any(v is None or not math.isfinite(v) for v in figures):
        return False
    return (
        row["dropped_pct"] <= 100 * MAX_DROPPED
        and row["superseded_pct"] <= 100 * MAX_SUPERSEDED
        and row["age_p95_s"] <= MAX_AGE_P95_S
    )


@contextmanager
def replay_bench(out_dir, twin_cpu=None, twin_shares=16384, replay_shares=16384, name="cps_twin_replay"):
    """A private master, the twin on one CPU (`twin_cpu`, default the last) and the replays on the
    others, and this process's rospy node watching the twin; yields (run(n, layout, bag, duration_s),
    the split's description). Everything is stopped and removed on exit."""
    from cps_bringup.host_split import HostSplit, online_cpus
    from cps_bringup.plan import DIGITAL, PHYSICAL
    from cps_ros.processes import RosGraph, free_port

    os.makedirs(os.path.join(out_dir, "logs"), exist_ok=True)
    cpus = online_cpus()
    twin = twin_cpu if twin_cpu is not None else cpus[-1]
    robots_side = tuple(c for c in cpus if c != twin) or cpus
    split = HostSplit.choose(
        {PHYSICAL: robots_side, DIGITAL: (twin,)},
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
                lambda n, layout, bag, duration_s: trial(graph, watch, split, bag, n, layout, duration_s, out_dir),
                split.describe(),
            )
        finally:
            rospy.signal_shutdown("done")
