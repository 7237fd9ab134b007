#!/usr/bin/env python3
"""Benchmark: does a stalled Foxglove viewer cost the twin anything? (issue 40's third test, as a figure)

Arms, each one whole `cps_bringup all` mission (the default fleet and profile, each route driven
there and back so that every robot still drives through the window; the Zenoh transport over
loopback; the endpoint on as by default), alternated so that drift hits both alike:
- `none` (the anchor): nobody connects to the endpoint;
- `stalled`: the npm `@foxglove/ws-protocol` client connects, subscribes every channel the
  endpoint advertises, then never reads its socket again (cps_harness.foxglove_probe.stalled_viewer),
  for the whole window;
- `reading` (to tell the stall's cost from a viewer's): the same client subscribed to every channel,
  reading and decoding all of it (on this machine: its own CPU competes with the mission's).
In each, from SETTLE_S after every process is up, for WINDOW_S, on the twin's master:
- the map server's insert rate: clouds and points inserted per s (its `map_stats` counters, summed
  over robots, between the window's first and last report), and what it dropped or superseded;
- the link's figures: delivered Mbit/s (the twin bridge's `link_report`: delivered frame bytes over
  the reports' intervals), sent and offered Mbit/s, the median heartbeat round trip;
- the CPU of the map server and of the endpoint (utime + stime from /proc, in cores), and of every
  process of the mission (by node name) and of the viewer, to see where CPU went;
and at the window's end the stalled socket's queue (what the kernel holds unsent towards the viewer:
proof that it stalled), and the endpoint's own counters (what its queue dropped) as it logged them
when the mission stopped.

Each figure is printed beside the anchor's (the `none` arms' mean, same run) as a ratio, with the
run-to-run spread of each arm (max - min over its missions, relative to the anchor's mean).

Run it under the heavy lock; the figures are bound to this 2-core machine:

    flock /tmp/cps-heavy.lock python bench/web_stall_bench.py [--reps 3] [--out bench/out/web_stall]
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

BENCH = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, BENCH)

WINDOW_S = 60.0  # the 60 s of a stalled viewer
SETTLE_S = 10.0  # after every process is up: the robots' clouds and the link's reports have started
# The mission's upper bound: up (~40-60 s on 2 cores), settle, window, and a margin; the bench stops it.
DURATION_S = 240.0
ARMS = ("none", "stalled", "reading")


def measure(window_s):
    """Run on the twin's master (a child process: rospy starts once per process, each mission has
    its own master): the map server's and the link's reports over `window_s`; a dict."""
    import rospy

    from cps_fleet import names
    from cps_harness.testing import TopicRecorder
    from cps_msgs.msg import LinkReport, MapStats

    rospy.init_node("web_stall_measure", anonymous=True, disable_signals=True)
    stats = TopicRecorder(names.absolute(names.in_twin(names.MAP_STATS)), MapStats)
    reports = TopicRecorder(names.absolute(names.LINK_REPORT), LinkReport)
    time.sleep(window_s)
    stats_msgs = [m for _, m in stats.messages]
    report_msgs = [m for _, m in reports.messages]
    if len(stats_msgs) < 2 or not report_msgs:
        return {"error": f"{len(stats_msgs)} map_stats and {len(report_msgs)} link_report messages in {window_s} s"}
    first, last = stats_msgs[0], stats_msgs[-1]
    span = (last.header.stamp - first.header.stamp).to_sec()

    def total(msg, field):
        return sum(getattr(r, field) for r in msg.robots)

    insert = {
        "span_s": span,
        "clouds_per_s": (total(last, "clouds_inserted") - total(first, "clouds_inserted")) / span,
        "points_per_s": (total(last, "points_inserted") - total(first, "points_inserted")) / span,
        "received_per_s": (total(last, "clouds_received") - total(first, "clouds_received")) / span,
        "superseded": total(last, "clouds_superseded") - total(first, "clouds_superseded"),
        "dropped": sum(
            total(last, f) - total(first, f)
            for f in ("clouds_dropped_queue", "clouds_dropped_tf", "clouds_dropped_invalid", "clouds_dropped_decoder")
        ),
    }
    interval = sum(r.interval_s for r in report_msgs)
    sender_interval = sum(r.sender_interval_s for r in report_msgs)
    rtts = [t for r in report_msgs for t in r.rtt_s]
    link = {
        "reports": len(report_msgs),
        "interval_s": interval,
        "delivered_mbps": sum(r.delivered_bytes for r in report_msgs) * 8 / 1e6 / interval,
        "sent_mbps": sum(r.sent_bytes for r in report_msgs) * 8 / 1e6 / sender_interval,
        "offered_mbps": sum(r.offered_bytes for r in report_msgs) * 8 / 1e6 / sender_interval,
        "rtt_median_ms": statistics.median(rtts) * 1e3 if rtts else None,
        "expired": sum(r.expired for r in report_msgs),
        "receiver_behind": sum(r.receiver_behind for r in report_msgs),
    }
    return {"insert": insert, "link": link}


def send_queue_bytes(port):
    """Bytes the kernel holds unsent or unacknowledged on the endpoint's side of each connection to
    its port (ss's Send-Q): a stalled viewer's grows to its socket buffers, a reading one's stays ~0."""
    out = subprocess.run(
        ["ss", "-tnH", "state", "established", f"( sport = :{port} )"], capture_output=True, text=True
    ).stdout
    return [int(line.split()[1]) for line in out.splitlines() if line.strip()]


def bench_fleet(folder):
    """The default fleet with each route driven there and back (about twice as long), so that no
    robot is done before the window ends; its fleet.yaml's path."""
    from cps_harness.fleets import write_fleet_with_repeated_routes

    return write_fleet_with_repeated_routes(folder, 1)


def run_arm(arm, out_dir, modules, fleet_file):
    from web_bench import cpu_in_window, pid_of

    from cps_bringup.plan import WEB_URL_FILE
    from cps_harness.foxglove_probe import probe_argv, stalled_viewer, wait_paused
    from cps_harness.mission import BRINGUP, Mission
    from cps_ros.processes import processes_named

    args = ["--fleet", fleet_file, "--duration", DURATION_S, "--web-listen", "127.0.0.1:0"]
    result = {"arm": arm}
    with Mission(out_dir, args, program=BRINGUP) as mission:
        mission.wait_until_up()
        time.sleep(SETTLE_S)
        with open(os.path.join(out_dir, WEB_URL_FILE)) as stream:
            url = stream.read().strip()
        port = int(url.rsplit(":", 1)[1].split("/")[0])
        viewer = None
        if arm == "stalled":
            viewer = stalled_viewer(url, WINDOW_S + 60.0, modules)
            if not wait_paused(viewer, timeout_s=20.0):
                viewer.kill()
                raise RuntimeError(f"the stalled viewer did not stall: {viewer.stderr.read()[-800:]}")
        elif arm == "reading":
            viewer = subprocess.Popen(
                probe_argv(url, WINDOW_S + 60.0, [], modules), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
            )
            time.sleep(3.0)  # connected and subscribed
        pids = {
            "endpoint": pid_of(out_dir, "foxglove_endpoint"),
            "map_server": pid_of(out_dir, os.path.join("cps_mapping", "nodes", "map_server")),
        }
        every = process_labels(processes_named(out_dir))
        if viewer is not None:
            every[f"viewer[{viewer.pid}]"] = viewer.pid
        measuring = mission.popen_on(
            "twin", [sys.executable, os.path.abspath(__file__), "--measure", str(WINDOW_S)], f"measure_{arm}"
        )
        cores = cpu_in_window({**pids, **every}, WINDOW_S)
        result["cores"] = {k: cores[k] for k in pids}
        result["process_cores"] = {k: round(v, 4) for k, v in cores.items() if k not in pids and v is not None}
        measuring.wait(timeout=WINDOW_S + 60)
        with open(os.path.join(os.path.dirname(mission.log_path), f"measure_{arm}.log")) as stream:
            result.update(json.loads(stream.read().strip().splitlines()[-1]))
        result["send_queue_bytes"] = send_queue_bytes(port)  # the stalled viewer is still connected
        if viewer is not None:
            viewer.kill()
            viewer.wait()
        mission.stop()
    result["endpoint_counters"] = endpoint_counters(out_dir)
    return result


def node_label(cmd):
    """A process's node name (`__name:=`), else its program's name."""
    words = cmd.split()
    for word in words:
        if word.startswith("__name:="):
            return word.split(":=", 1)[1]
    for word in words[1:] if words and os.path.basename(words[0]).startswith("python") else words:
        if not word.startswith("-"):
            return os.path.basename(word)
    return os.path.basename(words[0]) if words else "?"


def process_labels(processes):
    """{"<node>[pid]": pid} of (pid, cmd) pairs; a process started with `python -c` (a
    multiprocessing child) is named after its parent, e.g. "map_server/child[123]"."""
    cmds = dict(processes)
    out = {}
    for pid, cmd in processes:
        label = node_label(cmd)
        if " -c " in f" {cmd} ":
            try:
                with open(f"/proc/{pid}/stat") as stream:
                    ppid = int(stream.read().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError):
                ppid = None
            label = f"{node_label(cmds[ppid]) if ppid in cmds else '?'}/child"
        out[f"{label}[{pid}]"] = pid
    return out


def endpoint_counters(out_dir):
    """The endpoint's counters as it logged them when it stopped (queued, dropped, logged, ...)."""
    import ast

    marker = "counters at the end: "
    for root, _dirs, files in os.walk(out_dir):
        for name in files:
            if "foxglove_endpoint" not in name:
                continue
            with open(os.path.join(root, name), errors="replace") as stream:
                for line in stream:
                    if marker in line:
                        return ast.literal_eval(line.split(marker, 1)[1].strip())
    return None


def mean(values):
    return sum(values) / len(values) if values else float("nan")


FIGURES = (
    ("insert", "clouds_per_s", "map server: clouds inserted per s"),
    ("insert", "points_per_s", "map server: points inserted per s"),
    ("link", "delivered_mbps", "link: delivered Mbit/s"),
    ("link", "sent_mbps", "link: sent Mbit/s"),
    ("link", "rtt_median_ms", "link: median heartbeat round trip, ms"),
    ("cores", "map_server", "map server CPU, cores"),
    ("cores", "endpoint", "endpoint CPU, cores"),
)


def summarize(runs):
    """Per figure and arm: each run's value, the mean, the ratio of the mean to the anchor's (the
    `none` arms' mean) and the arm's spread (max - min) relative to the anchor's mean."""
    rows = []
    arms = [a for a in ARMS if any(r["arm"] == a for r in runs)]
    for group, key, label in FIGURES:
        row = {"figure": label}
        values = {
            arm: [r[group][key] for r in runs if r["arm"] == arm and r.get(group, {}).get(key) is not None]
            for arm in arms
        }
        anchor = mean(values.get("none", []))
        for arm in arms:
            v = values[arm]
            row[arm] = {
                "values": v,
                "mean": mean(v),
                "ratio": mean(v) / anchor if anchor else None,
                "spread": (max(v) - min(v)) / anchor if len(v) > 1 and anchor else None,
            }
        rows.append(row)
    return rows


def print_table(rows):
    arms = [a for a in ARMS if a in rows[0]]

    def fmt(v):
        return "-" if v is None else f"{v:.3g}"

    head = ["figure"]
    for arm in arms:
        head += [f"{arm}: each run", f"{arm}: mean / anchor", f"{arm}: spread / anchor"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for row in rows:
        cells = [row["figure"]]
        for arm in arms:
            a = row[arm]
            cells += [", ".join(fmt(v) for v in a["values"]), fmt(a["ratio"]), fmt(a["spread"])]
        print("| " + " | ".join(cells) + " |")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=os.path.join(BENCH, "out", "web_stall"))
    parser.add_argument("--reps", type=int, default=3, help="missions per arm (alternated)")
    parser.add_argument("--arms", default="none,stalled", help=f"comma-separated, of {', '.join(ARMS)}")
    parser.add_argument("--measure", type=float, default=None, help=argparse.SUPPRESS)  # the child on the twin
    parser.add_argument("--summarize", nargs="+", default=None, metavar="JSON", help="only the table of earlier runs")
    args = parser.parse_args()
    if args.measure is not None:
        print(json.dumps(measure(args.measure)))
        return 0
    if args.summarize:
        runs = []
        for path in args.summarize:
            with open(path) as stream:
                runs += json.load(stream)["runs"]
        print_table(summarize(runs))
        return 0
    from cps_harness.foxglove_probe import install_client

    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)
    os.chmod(out, 0o777)  # the nodes run as nobody when the bench runs as root
    modules = install_client()
    fleet_file = bench_fleet(out)
    runs = []
    started = time.monotonic()
    arms = args.arms.split(",")
    for rep in range(args.reps):
        for arm in arms if rep % 2 == 0 else reversed(arms):
            folder = os.path.join(out, f"{rep}_{arm}")
            os.makedirs(folder, exist_ok=True)
            os.chmod(folder, 0o777)
            run = run_arm(arm, folder, modules, fleet_file)
            run["rep"] = rep
            runs.append(run)
            print(json.dumps(run), flush=True)
    rows = summarize(runs)
    result = {
        "window_s": WINDOW_S,
        "settle_s": SETTLE_S,
        "runs": runs,
        "summary": rows,
        "wall_s": time.monotonic() - started,
    }
    with open(os.path.join(out, "web_stall_bench.json"), "w") as stream:
        json.dump(result, stream, indent=1)
    print_table(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
