#!/usr/bin/env python3
"""Benchmark of the map server's warm-up: process start to ready, and the first cloud's insertion.

Each run copies the cps_mapping package (nodes and Python, no cache) to a fresh temporary folder
(another checkout) and starts its map_server node on a private master, in two modes, in the same run:
- cold: no usable kernel cache (what an older checkout had after another checkout's build, issue
  29): the node compiles its numba kernels at its start;
- built: the kernels built first as `make setup` builds them (`python -m cps_mapping.build_kernels`,
  timed apart), keyed by the source's content: the node only loads them.

Measured per run and mode: start to ready (Popen to the latched `~ready` arriving here, and the
node's own `ready_after_s`), the first cloud's insertion latency when it is sent as soon as the
node subscribes (during its warm-up: as the clouds of a mission that does not wait), and a cloud
sent once it is ready (what bringup now does). Inserted = the first `octomap_binary` that
follows it (published every 0.05 s on change). Medians over `--runs`; two shared cores are noisy.

    python bench/warmup_bench.py [--runs 3]
"""

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

from cps_fleet import names
from cps_harness.warm_start import (
    checkout_env,
    copy_checkout,
    managed_cloud_topic,
    managed_wall_cloud,
    static_sensor_transform,
)

PACKAGE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "catkin_ws", "src", "cps_mapping")
SENSOR_FRAME = "jackal/camera_depth_optical_frame"
MODES = ("cold", "built")


def inserted_after(octomap, sent_at_s, timeout_s=180.0):
    """Arrival (monotonic s) of the first non-empty map published after `sent_at_s`."""
    octomap.wait(
        lambda m: len(m.data) > 0 and octomap.messages[-1][0] >= sent_at_s,
        timeout_s=timeout_s,
        what="the cloud in the map",
    )
    return next(t for t, m in octomap.messages if t >= sent_at_s and len(m.data) > 0)


def one_start(graph, rospy, mode, run, tmp):
    """Start a map server from a fresh checkout in `mode`; its figures."""
    from diagnostic_msgs.msg import DiagnosticStatus

    from cps_harness.testing import TopicRecorder, wait_for
    from cps_msgs.msg import CompressedPointCloud2, Octomap

    checkout = copy_checkout(PACKAGE, os.path.join(tmp, f"{mode}_{run}", "cps_mapping"))
    env = checkout_env(checkout)
    build_s = None
    if mode == "built":
        t0 = time.monotonic()
        subprocess.run([sys.executable, "-m", "cps_mapping.build_kernels"], env=env, check=True, capture_output=True)
        build_s = time.monotonic() - t0
    name = f"map_server_{mode}_{run}"
    ready = TopicRecorder(names.absolute(names.in_twin(names.private(name, names.READY))), DiagnosticStatus)
    octomap = TopicRecorder(names.absolute(names.in_twin(names.private(name, names.OCTOMAP_BINARY))), Octomap)
    publisher = rospy.Publisher(managed_cloud_topic("jackal"), CompressedPointCloud2, queue_size=1)
    try:
        started_at = time.monotonic()
        proc = graph.popen(
            [
                sys.executable,
                os.path.join(checkout, "nodes", "map_server"),
                f"__ns:={names.absolute(names.TWIN_NS)}",
                f"__name:={name}",
                f"{names.OCTOMAP_BINARY}:={names.absolute(names.in_twin(names.private(name, names.OCTOMAP_BINARY)))}",
                "_robots:=jackal",
                f"_map_file:={os.path.join(tmp, name + '.bt')}",
                "_publish_period_s:=0.05",
                "_autosave_period_s:=0.0",
            ],
            name=name,
            env=env,
        )
        assert wait_for(lambda: publisher.get_num_connections(), timeout_s=60), f"{name} did not subscribe"
        early_sent_at = time.monotonic()
        publisher.publish(managed_wall_cloud(rospy, SENSOR_FRAME, 0.0))
        status = ready.wait(timeout_s=300, what=f"{name} ready")
        ready_at = ready.messages[0][0]
        early_inserted_at = inserted_after(octomap, early_sent_at)
        late_sent_at = time.monotonic()
        publisher.publish(managed_wall_cloud(rospy, SENSOR_FRAME, 5.0))
        late_inserted_at = inserted_after(octomap, late_sent_at)
        values = {kv.key: kv.value for kv in status.values}
        graph.stop(proc)
    finally:
        ready.close()
        octomap.close()
        publisher.unregister()
    return {
        "build_s": build_s,
        "start_to_ready_s": ready_at - started_at,
        "node_ready_after_s": float(values["ready_after_s"]),
        "kernel_load_s": float(values["kernel_load_s"]),
        "compiled": values["kernels_compiled"] or "-",
        "early_cloud_s": early_inserted_at - early_sent_at,
        "ready_cloud_s": late_inserted_at - late_sent_at,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()

    from cps_ros.processes import RosGraph

    tmp = tempfile.mkdtemp(prefix="cps-warmup-bench-")
    graph = RosGraph(log_dir=tmp)
    graph.start()
    graph.point_this_process_here()
    import rospy

    rospy.init_node("warmup_bench", anonymous=True, disable_signals=True)
    keep_tf = static_sensor_transform(rospy, SENSOR_FRAME)
    results = {mode: [] for mode in MODES}
    try:
        for run in range(args.runs):
            for mode in MODES:
                figures = one_start(graph, rospy, mode, run, tmp)
                results[mode].append(figures)
                print(
                    f"run {run + 1} {mode:5s}: "
                    + ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in figures.items()),
                    flush=True,
                )
    finally:
        graph.close()
        shutil.rmtree(tmp, ignore_errors=True)
        del keep_tf

    def median(mode, key):
        return statistics.median(r[key] for r in results[mode])

    print(f"\nmedians of {args.runs} runs (s)")
    print(
        "| mode | kernels compiled at start | start -> ready (here) | node's ready_after_s | kernel load | "
        "first cloud, sent at subscription, inserted after | cloud sent once ready, inserted after |"
    )
    print("|---|---|---|---|---|---|---|")
    for mode in MODES:
        print(
            f"| {mode} | {results[mode][0]['compiled']} | {median(mode, 'start_to_ready_s'):.2f} | "
            f"{median(mode, 'node_ready_after_s'):.2f} | {median(mode, 'kernel_load_s'):.2f} | "
            f"{median(mode, 'early_cloud_s'):.2f} | {median(mode, 'ready_cloud_s'):.3f} |"
        )
    print(
        f"\nbuild step (make setup's `python -m cps_mapping.build_kernels`, once per source): "
        f"{median('built', 'build_s'):.1f} s"
    )
    for key, what in (("start_to_ready_s", "start -> ready"), ("early_cloud_s", "first cloud (sent at subscription)")):
        print(f"ratio cold / built, {what}: {median('cold', key) / median('built', key):.1f}x")


if __name__ == "__main__":
    main()
