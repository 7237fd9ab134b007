#!/usr/bin/env python3
"""Benchmark of the twin's Foxglove endpoint and of MCAP recording, in one mission (issue 40).

One `cps_bringup all` mission (the default fleet and profile, the Zenoh transport over loopback,
`--record` to a ROS 1 bag as users record today). Once it is up, beside it on the same masters:
cps_web's MCAP recorder on the same topics as the bag (the robots' side), and a second one with
only what crosses the link (`--record-link-only`'s topics, on the twin's side). Then:
- the endpoint's CPU (utime + stime from /proc, in cores) for WINDOW_S with no viewer, then for
  WINDOW_S with one viewer (the npm @foxglove/ws-protocol client subscribed to every channel); the
  map server's CPU in the same windows is the anchor (the endpoint's cost as a share of it);
- bytes per minute of the bag (rosbag record --lz4, the anchor) and of both MCAP files (zstd), each
  over its own recorded span (first to last message), and their ratio.

Run it under the heavy lock; the figures are bound to this 2-core machine:

    flock /tmp/cps-heavy.lock python bench/web_bench.py [--out bench/out/web]
"""

import argparse
import json
import os
import signal
import sys
import time

from cps_bringup.mission_bag import record_topics
from cps_bringup.plan import WEB_URL_FILE
from cps_fleet.fleet import load_fleet
from cps_harness.foxglove_probe import install_client, probe_argv
from cps_harness.mcap_check import read_ros1_mcap
from cps_harness.mission import BRINGUP, Mission
from cps_ros.processes import find_node, processes_named
from cps_web.mcap_recording import link_topics

WINDOW_S = 20.0
DURATION_S = 120.0  # the mission's upper bound; the bench stops it after its windows
TICKS = os.sysconf("SC_CLK_TCK")


def cpu_s(pid):
    """utime + stime of `pid` in seconds (None once it is gone)."""
    try:
        with open(f"/proc/{pid}/stat") as stream:
            fields = stream.read().rsplit(")", 1)[1].split()
    except FileNotFoundError:
        return None
    return (int(fields[11]) + int(fields[12])) / TICKS


def pid_of(out_dir, node_path_part):
    """The mission's process whose command line holds `node_path_part`."""
    found = [pid for pid, cmd in processes_named(out_dir) if node_path_part in cmd and "xvfb" not in cmd]
    if not found:
        raise RuntimeError(f"no process of the mission runs {node_path_part}")
    return found[0]


def cpu_in_window(pids, seconds):
    """{name: cores} of each pid over `seconds` of wall time (None for a process that ended)."""
    before = {k: cpu_s(p) for k, p in pids.items()}
    t0 = time.monotonic()
    time.sleep(seconds)
    wall = time.monotonic() - t0
    after = {k: cpu_s(p) for k, p in pids.items()}
    return {k: None if before[k] is None or after[k] is None else (after[k] - before[k]) / wall for k in pids}


def mcap_span(path):
    """(bytes, recorded span in s, messages, decode errors) of an MCAP, every message decoded."""
    contents = read_ros1_mcap(path, keep=lambda topic: False)
    from mcap.reader import make_reader

    with open(path, "rb") as stream:
        stats = make_reader(stream).get_summary().statistics
    span = (stats.message_end_time - stats.message_start_time) / 1e9
    return os.path.getsize(path), span, stats.message_count, contents.errors


def bag_span(path):
    import rosbag

    with rosbag.Bag(path) as bag:
        return os.path.getsize(path), bag.get_end_time() - bag.get_start_time(), bag.get_message_count()


def counts_in_span(bag_path, mcap_path):
    """{topic: [bag's messages, MCAP's messages]} over the MCAP's recorded span (the MCAP recorder
    started later and stopped earlier than the bag's): a recorder that loses messages shows here,
    and the MCAP's own `cps_recording` metadata (its dropped counts)."""
    import rosbag
    import rospy
    from mcap.reader import make_reader

    with open(mcap_path, "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    stats = summary.statistics
    topic_of = {c.id: c.topic for c in summary.channels.values()}
    counts = {topic_of[k]: [0, v] for k, v in stats.channel_message_counts.items()}
    start, end = rospy.Time(nsecs=stats.message_start_time), rospy.Time(nsecs=stats.message_end_time)
    with rosbag.Bag(bag_path) as bag:
        for topic, _raw, _t in bag.read_messages(start_time=start, end_time=end, raw=True):
            counts.setdefault(topic, [0, 0])[0] += 1
    return counts, metadata.get("cps_recording", {})


def recorder_argv(path, topics, name):
    return [
        sys.executable,
        find_node("cps_web", "mcap_recorder"),
        f"__name:={name}",
        f"_path:={path}",
        f"_topics:={','.join(topics)}",
    ]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "out", "web"))
    args = parser.parse_args()
    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)
    os.chmod(out, 0o777)  # the nodes run as nobody when the bench runs as root
    fleet = load_fleet()
    cameras = [r.name for r in fleet.robots if r.has_depth_camera]
    modules = install_client()
    bag, full_mcap, link_mcap = (os.path.join(out, n) for n in ("mission.bag", "mission.mcap", "link.mcap"))
    for path in (bag, full_mcap, link_mcap):
        if os.path.exists(path):
            os.remove(path)
    mission_args = ["--duration", DURATION_S, "--record", bag, "--web-listen", "127.0.0.1:0"]
    result = {"window_s": WINDOW_S, "robots": fleet.robot_names}
    with Mission(out, mission_args, program=BRINGUP) as mission:
        mission.wait_until_up()
        recorders = [
            mission.popen_on("phys", recorder_argv(full_mcap, record_topics(fleet), "mcap_full"), "mcap_full"),
            mission.popen_on(
                "twin", recorder_argv(link_mcap, link_topics(fleet.robot_names, cameras), "mcap_link"), "mcap_link"
            ),
        ]
        with open(os.path.join(out, WEB_URL_FILE)) as stream:
            url = stream.read().strip()
        pids = {
            "endpoint": pid_of(out, "foxglove_endpoint"),
            "map_server": pid_of(out, os.path.join("cps_mapping", "nodes", "map_server")),
        }
        time.sleep(5.0)  # the recorders subscribed
        result["no_viewer_cores"] = cpu_in_window(pids, WINDOW_S)
        viewer = mission.popen_on("twin", probe_argv(url, WINDOW_S + 6.0, [], modules), "viewer")
        time.sleep(3.0)  # connected and subscribed
        result["one_viewer_cores"] = cpu_in_window(pids, WINDOW_S)
        viewer.wait(timeout=60)
        with open(os.path.join(os.path.dirname(mission.log_path), "viewer.log")) as stream:
            report = json.loads(stream.read().strip().splitlines()[-1])
        result["viewer_messages"] = report["messages"]
        result["viewer_decode_errors"] = report["decode_errors"]
        for proc in recorders:
            proc.send_signal(signal.SIGINT)
        for proc in recorders:
            proc.wait(timeout=60)
        mission.stop()
    result["bag"] = dict(zip(("bytes", "span_s", "messages"), bag_span(bag)))
    for key, path in (("mcap_full", full_mcap), ("mcap_link_only", link_mcap)):
        size, span, count, errors = mcap_span(path)
        result[key] = {"bytes": size, "span_s": span, "messages": count, "decode_errors": errors}
    result["full_counts_bag_vs_mcap"], result["mcap_full_metadata"] = counts_in_span(bag, full_mcap)
    result["mcap_link_metadata"] = counts_in_span(bag, link_mcap)[1]
    for key in ("bag", "mcap_full", "mcap_link_only"):
        r = result[key]
        r["mb_per_min"] = r["bytes"] / 1e6 / (r["span_s"] / 60.0)
    with open(os.path.join(out, "web_bench.json"), "w") as stream:
        json.dump(result, stream, indent=1)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
