#!/usr/bin/env python3
"""Link benchmark: the paper's single master over TCPROS against two masters joined by cps_link's
Zenoh bridges (mutual TLS), in one run, on the same tc-shaped veth link and the same load.

    source ci/env.sh && python bench/link_bench.py [--rate 60mbit] [--cut-s 10] [--phase-s 15]   (root)

Per transport: (1) staleness of the live clouds the twin receives after a cut of the link (veth
down), max and p95 of receive - capture stamp; (2) teleop latency twin -> robot (p50/p95) while
the robots -> twin direction is saturated (clouds offered at ~2.4x the link); and, for Zenoh, (3)
the bridges' CPU seconds per MB carried and (4) their throughput ceiling over an unshaped link.
Results go to stdout and docs/benchmarks/link.md's figures are from it. The machine is shared and
has 2 cores; the load generator and recorders run on them too.
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from cps_fleet import names
from cps_harness.cut_analysis import ages_after, read_watch
from cps_harness.transport_compare import (
    FIXTURES,
    LIVE,
    Graphs,
    bridge_pids,
    cpu_s,
    start_load,
    teleop_under_saturation,
)
from cps_link.netns_link import PHYS_IP, TWIN_IP, ShapedLink, namespace
from cps_link.zenoh_session import MAKE_CERTS

LINK_NAME = "cpszl"


def _set_link(up):
    subprocess.run(
        ["ip", "-n", namespace(LINK_NAME, "phys"), "link", "set", f"{LINK_NAME}_p", "up" if up else "down"], check=True
    )


def run(transport, args, cert_dir, tmp):
    out = {}
    with ShapedLink(LINK_NAME, rate=args.rate) as link:
        graphs = Graphs(link, transport, cert_dir)
        try:
            watch = os.path.join(tmp, f"{transport}_watch.txt")
            graphs.start(
                "twin",
                [
                    sys.executable,
                    os.path.join(FIXTURES, "link_watch.py"),
                    watch,
                    *[graphs.managed_topic_on_twin(r) for r in LIVE],
                ],
                "watch",
            )
            load = start_load(graphs, LIVE, "load")
            time.sleep(args.phase_s)
            if transport == "zenoh":
                cpu0, t0 = cpu_s(bridge_pids(graphs)), time.time()
                time.sleep(args.phase_s)
                cpu1, t1 = cpu_s(bridge_pids(graphs)), time.time()
                rows = [r for msgs in read_watch(watch).messages.values() for r in msgs]
                carried = sum(b for recv, _, b in rows if t0 <= recv < t1)
                out["cpu_s_per_mb"] = (cpu1 - cpu0) / (carried / 1e6)
                out["carried_mbytes_per_s"] = carried / 1e6 / (t1 - t0)
            # (1) a cut
            _set_link(up=False)
            time.sleep(args.cut_s)
            restore = time.time()
            _set_link(up=True)
            time.sleep(args.phase_s)
            ages = ages_after(read_watch(watch), restore, [graphs.managed_topic_on_twin(r) for r in LIVE])
            ages = ages if len(ages) else np.array([np.nan])
            out["stale_max_s"], out["stale_p95_s"] = float(np.max(ages)), float(np.percentile(ages, 95))
            out["after_cut_messages"] = int(len(ages))
            graphs.stop("phys", load)
            # (2) teleop under saturation
            lat = teleop_under_saturation(graphs, os.path.join(tmp, f"{transport}_teleop.txt"), args.phase_s)
            out["teleop_p50_ms"], out["teleop_p95_ms"] = float(np.percentile(lat, 50)), float(np.percentile(lat, 95))
            out["teleop_commands"] = int(len(lat))
        finally:
            graphs.close()
    return out


def ceiling(cert_dir, tmp, seconds):
    """Zenoh bridges over an unshaped veth: 100 kB clouds offered as fast as the load generator can."""
    with ShapedLink(LINK_NAME, rate="10gbit") as link:
        graphs = Graphs(link, "zenoh", cert_dir)
        try:
            watch = os.path.join(tmp, "ceiling_watch.txt")
            graphs.start(
                "twin",
                [
                    sys.executable,
                    os.path.join(FIXTURES, "link_watch.py"),
                    watch,
                    names.absolute(names.managed_cloud_at_twin("scout")),
                ],
                "watch",
            )
            time.sleep(3.0)
            start_load(graphs, {"scout": (100000, 1000.0)}, "load")
            time.sleep(4.0)
            t0 = time.time()
            time.sleep(seconds)
            rows = read_watch(watch).messages.get(names.absolute(names.managed_cloud_at_twin("scout")), [])
            carried = sum(b for recv, _, b in rows if t0 <= recv < t0 + seconds)
            return carried / 1e6 / seconds
        finally:
            graphs.close()


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rate", default="60mbit")
    parser.add_argument("--cut-s", type=float, default=10.0)
    parser.add_argument("--phase-s", type=float, default=15.0)
    args = parser.parse_args()
    if os.geteuid() != 0:
        print("link_bench: needs root (network namespaces and tc); skipped")
        return 0
    with tempfile.TemporaryDirectory(prefix="cps-link-bench-") as tmp:
        cert_dir = os.path.join(tmp, "certs")
        subprocess.run([MAKE_CERTS, cert_dir], check=True, capture_output=True)
        results = {t: run(t, args, cert_dir, tmp) for t in ("tcpros", "zenoh")}
        results["zenoh"]["ceiling_mbytes_per_s"] = ceiling(cert_dir, tmp, seconds=8.0)
    print(
        f"link {args.rate} (tc tbf veth, {PHYS_IP} <-> {TWIN_IP}), cut {args.cut_s:.0f} s, phases {args.phase_s:.0f} s"
    )
    print(f"{'':34s} {'tcpros':>10s} {'zenoh':>10s}")
    rows = [
        ("stale after cut: max (s)", "stale_max_s", "{:.2f}"),
        ("stale after cut: p95 (s)", "stale_p95_s", "{:.2f}"),
        ("clouds received after cut", "after_cut_messages", "{:d}"),
        ("teleop under saturation p50 (ms)", "teleop_p50_ms", "{:.1f}"),
        ("teleop under saturation p95 (ms)", "teleop_p95_ms", "{:.1f}"),
        ("teleop commands", "teleop_commands", "{:d}"),
    ]
    for label, key, fmt in rows:
        print(f"{label:34s} " + " ".join(f"{fmt.format(results[t][key]):>10s}" for t in ("tcpros", "zenoh")))
    z = results["zenoh"]
    print(
        f"zenoh bridges: {z['cpu_s_per_mb']:.3f} CPU s per MB carried (both sides, at "
        f"{z['carried_mbytes_per_s']:.2f} MB/s); throughput ceiling {z['ceiling_mbytes_per_s']:.1f} MB/s "
        f"(100 kB clouds, unshaped veth)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
