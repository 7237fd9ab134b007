#!/usr/bin/env python3
"""A seeded chaos soak against a running 4-robot mission on the shaped link (issue 38).

One mission (cps_bringup, the default fleet with each route driven many times, across a 60 Mbit/s
shaped link with the Zenoh bridges) runs while `--faults` faults drawn from `--seed`
(cps_harness.chaos.draw_faults) are injected one after another: link cuts of 0.2-20 s, capacity
steps, a node killed (map server, either bridge, the tissue's encoder or a rate limiter; the
supervisor restarts it), the twin's CPUs saturated for 10 s, a slow viewer on the twin's map.
After each fault the invariants (cps_harness.chaos) are judged from the mission's own files and
written as one row: map fresh again, every robot's clouds arriving, teleop reaching the robots,
no frame to the wrong topic or type, nothing left of a killed process. A kill never spends a
process's last restart in the supervisor's window (cps_harness.chaos.RestartBudget, from the
mission's log): its target is then the first other with one left, named in the row.

    python bench/chaos.py [--seed 1] [--faults 50] [--kinds kill,...] [--spares on|off] [--out out/chaos] [--results docs/results/chaos.md]

Needs root (the shaped link). Machine-bound (2 cores); run it alone, under the heavy lock.
"""

import argparse
import os
import signal
import sys
import time

from cps_bringup.plan import DIGITAL
from cps_fleet import names
from cps_harness import chaos
from cps_harness.fleets import write_fleet_with_repeated_routes
from cps_harness.mission import BRINGUP, Mission

# Laps of each robot's route: enough for 50 faults (each at most ~30 s with its checks).
LAPS = 20
LINK_RATE = "60mbit"
WARM_UP_S = 10.0


def inject(mission, fault, kill_target=None):
    """Inject `fault` into the running mission; returns when it is over (its end). A kill hits
    `kill_target` (`_kill_target`'s process for the fault's target)."""
    from cps_link.netns_link import link_set, tc_rate

    if fault.kind == chaos.LINK_CUT:
        mission.set_link(False)
        try:
            time.sleep(fault.duration_s)
        finally:
            mission.set_link(True)
    elif fault.kind == chaos.CAPACITY_STEP:
        link_set(mission.run_link_name(), tc_rate(fault.rate_mbps))
        try:
            time.sleep(fault.duration_s)
        finally:
            link_set(mission.run_link_name(), LINK_RATE)
    elif fault.kind == chaos.KILL:
        pids = _pids_of(mission, kill_target or fault.target)
        if not pids:
            raise RuntimeError(f"no running {fault.target} to kill")
        for pid in pids:
            os.kill(pid, signal.SIGKILL)
    elif fault.kind == chaos.TWIN_CPU_HOG:
        hogs = [
            mission.popen_on("twin", [sys.executable, "-c", "while True: pass"], f"chaos_hog_{i}") for i in range(2)
        ]
        for hog in hogs:  # on the twin's CPUs (the host split's group), as a busy twin would be
            for controller in ("cpuset", "cpu"):
                with open(f"/sys/fs/cgroup/{controller}/cpsfleet_{mission.pid}/{DIGITAL}/tasks", "w") as tasks:
                    tasks.write(str(hog.pid))
        try:
            time.sleep(fault.duration_s)
        finally:
            for hog in hogs:
                hog.kill()
                hog.wait()
    elif fault.kind == chaos.SLOW_VIEWER:
        topic = names.absolute(names.in_twin(names.OCTOMAP_BINARY))
        viewer = mission.popen_on(
            "twin", [sys.executable, "-m", "cps_harness.slow_viewer", topic, str(fault.duration_s)], "chaos_viewer"
        )
        viewer.wait(fault.duration_s + 30)
    else:
        raise ValueError(f"unknown fault {fault.kind}")


def _kill_target(mission, target):
    """The process a kill of `target` hits: its own, or in this mission's layout its host's."""
    host = chaos.KILL_HOSTS.get(target)
    return host if host and not _pids_of(mission, target) and _pids_of(mission, host) else target


def _pids_of(mission, target):
    """The pids of the mission's processes whose ROS node name is `target` (`__name:=target` on its
    command line: a wrapper has none). A substring match also took `zenoh_bridge_twin_command`
    for `zenoh_bridge_twin`: the command lane's bridge was killed with the main one, and counted
    as a second process after the restart. A waiting warm spare (cps_ros.spare) carries the node's
    command line but is not the node: left out."""
    from cps_ros.processes import processes_named
    from cps_ros.spare import is_waiting_spare

    return [
        pid
        for pid, cmd in processes_named(str(mission.out_dir))
        if f"__name:={target}" in cmd.split() and "nice" not in cmd.split()[0] and not is_waiting_spare(pid)
    ]


def _read(path):
    from cps_experiments.run_files import read_rows

    rows, _problem = read_rows(path)
    return rows or []


def write_fleet_with_spares(fleet_file, spares=True):
    """The fleet file with limits.warm_spares set (cps_ros.spare: kills restart from a warm spare;
    the default fleet's own setting is on)."""
    import yaml

    with open(fleet_file) as stream:
        doc = yaml.safe_load(stream)
    doc["limits"]["warm_spares"] = bool(spares)
    with open(fleet_file, "w") as stream:
        yaml.safe_dump(doc, stream, sort_keys=False)
    return fleet_file


def run(args):
    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)
    os.chmod(out, 0o755)
    fleet_file = write_fleet_with_spares(write_fleet_with_repeated_routes(out, LAPS), args.spares == "on")
    from cps_fleet.fleet import load_fleet

    fleet = load_fleet(fleet_file)
    robots = fleet.robot_names
    budget = chaos.RestartBudget(fleet.limits.restart_window_s)
    faults = chaos.draw_faults(args.seed, args.faults, args.kinds)
    mission_dir = os.path.join(out, "mission")
    rows = []
    argv = ["--fleet", fleet_file, "--link", LINK_RATE, "--duration", 6 * 3600]
    with Mission(mission_dir, argv, program=BRINGUP) as mission:
        mission.wait_until_up(300)
        diag = {side: os.path.join(mission_dir, f"chaos_diagnostics_{side}.jsonl") for side in ("phys", "twin")}
        for side, path in diag.items():
            mission.popen_on(side, chaos.diagnostics_recorder_argv(sys.executable, path), f"chaos_diag_{side}")
        time.sleep(WARM_UP_S)
        for i, fault in enumerate(faults, 1):
            if not mission.running():
                rows.append(chaos.Row(i, fault.describe(), time.time(), time.time(), failures=["the mission ended"]))
                break
            before = {k: v for path in diag.values() for k, v in chaos.read_mismatch_counters(path).items()}
            start = time.time()
            described = fault.describe()
            killed = error = None
            if fault.kind == chaos.KILL:
                budget.read(mission.log(), start)
                target = budget.target(fault.target, lambda name: _kill_target(mission, name), start)
                if target is None:
                    error = "not injected: no kill target has a restart left in the supervisor's window"
                else:
                    killed = _kill_target(mission, target)
                    if target != fault.target:
                        spent = _kill_target(mission, fault.target)
                        described += f" ({spent} has no restart left in the supervisor's window: {target} instead)"
                    if killed != target:
                        described += f" (runs in {killed} in this layout)"
            if error is None:
                try:
                    inject(mission, fault, killed)
                except Exception as exc:  # noqa: BLE001 - a fault that cannot be injected is a row's failure
                    error = f"not injected: {type(exc).__name__}: {exc}"
            end = time.time()
            time.sleep(chaos.RECOVERY_S + chaos.CHECK_WINDOW_S + 1.0)
            row = chaos.judge_fault(
                chaos.Row(i, described, start, end),
                robots,
                _read(os.path.join(mission_dir, "map_age.csv")),
                _read(os.path.join(mission_dir, "arrivals.csv")),
                _read(os.path.join(mission_dir, "physical_arrivals.csv")),
                lambda r: names.absolute(names.managed_cloud_at_twin(r)) if r else None,
                names.absolute(names.COMMAND_PROBE),
            )
            if error:
                row.failures.insert(0, error)
            after = {k: v for path in diag.values() for k, v in chaos.read_mismatch_counters(path).items()}
            if not after:  # a missing value fails its check: the recorders heard no counter
                row.failures.append("the bridges' mismatch counters were not recorded")
            row.mismatches = chaos.mismatch_growth(before, after)
            if row.mismatches:
                row.failures.append(f"frames to the wrong topic or type: {row.mismatches}")
            if killed:
                alive = _pids_of(mission, killed)
                if len(alive) != 1:
                    row.failures.append(f"{len(alive)} {killed} processes after the restart (1 expected)")
            rows.append(row)
            print(_line(row), flush=True)
        mission.stop()
    return faults, rows


def _line(row):
    figures = (
        f"map age max {row.map_age_max_s:.1f} s" if row.map_age_max_s is not None else "map age -",
        f"teleop p95 {row.teleop_p95_ms:.0f} ms ({row.teleop_probes})" if row.teleop_p95_ms is not None else "teleop -",
    )
    return f"| {row.index} | {row.fault} | {'held' if row.held else 'FAILED'} | {'; '.join(figures)} | {'; '.join(row.failures) or '-'} |"


def report(args, rows):
    held = sum(r.held for r in rows)
    lines = [
        "# Chaos soak (bench/chaos.py)",
        "",
        f"Seed {args.seed}, {args.faults} faults of {', '.join(args.kinds)} asked, {len(rows)} injected into one 4-robot mission (warm spares "
        f"{args.spares}) across a {LINK_RATE} shaped link (Zenoh bridges): **{held} of {len(rows)} with every invariant held.** "
        f"Invariants, {chaos.RECOVERY_S:g} s after each fault's end for {chaos.CHECK_WINDOW_S:g} s: every robot's "
        f"published map at most {chaos.MAP_FRESH_S:g} s old, every robot's clouds arriving at the twin, the command "
        f"probe reaching the robots with p95 at most {chaos.TELEOP_P95_MS:g} ms, no mismatch counter of either "
        "bridge grown, exactly one process of a killed node after its restart. Machine-bound: 2 cores.",
        "",
        "| # | fault | invariants | figures | failures |",
        "|---|---|---|---|---|",
        *(_line(r) for r in rows),
        "",
    ]
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--faults", type=int, default=50)
    parser.add_argument("--out", default="out/chaos")
    parser.add_argument("--results", default=None, help="also write the table (Markdown) here")
    parser.add_argument(
        "--kinds",
        default=",".join(chaos.KINDS),
        help=f"comma-separated fault kinds to draw from (default all: {','.join(chaos.KINDS)})",
    )
    parser.add_argument("--spares", choices=("on", "off"), default="on", help="warm spares (default on)")
    args = parser.parse_args(argv)
    args.kinds = tuple(k for k in args.kinds.split(",") if k)
    try:
        chaos.draw_faults(args.seed, 1, args.kinds)
    except ValueError as exc:
        parser.error(str(exc))
    if os.geteuid() != 0:
        parser.error("needs root (the shaped link)")
    _faults, rows = run(args)
    text = report(args, rows)
    print(text)
    if args.results:
        with open(args.results, "w") as stream:
            stream.write(text)
    return 0 if rows and all(r.held for r in rows) and len(rows) == args.faults else 1


if __name__ == "__main__":
    sys.exit(main())
