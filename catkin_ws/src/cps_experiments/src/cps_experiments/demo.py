"""`make demo`: the whole mission headless, then everything a user needs to judge it in one folder.

The fleet follows its routes (fleet.yaml's sensor profile unless --profile) with voxel grid + Draco + bandwidth manager, the
map is fused at the digital twin and the GUI is rendered offscreen. Across a tc-shaped 60 Mbit/s
link between two network namespaces when root, over loopback otherwise (and it says which).
Writes: map.bt, ground_truth.npz, scores.json, gui.png, stats.csv, allocation.csv, plots, report.md.
"""

import argparse
import json
import os
import sys
import time

from cps_bringup.cli import mission_args, run_mission
from cps_bringup.supervisor import BringupError
from cps_fleet.fleet import PROFILES


def choose_link(requested, log=print, fleet_file=None):
    """'auto' → the fleet file's link rate when this process may create network namespaces, else
    loopback (says why)."""
    if requested != "auto":
        return requested
    from cps_bringup.link import link_unavailable_reason

    reason = link_unavailable_reason()
    if reason:
        log(f"[demo] no shaped link: {reason}; running over loopback instead")
        return "none"
    from cps_link.netns_link import fleet_rate

    return fleet_rate(fleet_file)


def parse_args(argv):
    parser = argparse.ArgumentParser(prog="demo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="out/demo")
    parser.add_argument("--fleet", default=None, help="fleet.yaml (default: cps_bringup/config/fleet.yaml)")
    parser.add_argument("--port", type=int, default=None, help="the twin's roscore port (default: a free one)")
    parser.add_argument("--record", default=None, metavar="BAG", help="also record the mission (cps_bringup --record)")
    parser.add_argument(
        "--link", default="auto", help="auto (fleet.yaml's link rate when root), none, or a rate like 20mbit"
    )
    parser.add_argument(
        "--link-scenario",
        default="demo",
        metavar="NAME",
        help="cps_link scenario on the shaped link (default demo: a 10 s outage at 25 s, then "
        "60 -> 10 -> 60 Mbit/s); 'none' for a constant link",
    )
    parser.add_argument("--profile", default=None, choices=PROFILES, help="sensor profile (default: fleet.yaml's)")
    parser.add_argument("--robots", default=None, help="subset, e.g. scout,jackal (default: the whole fleet)")
    parser.add_argument(
        "--duration",
        type=float,
        default=420.0,
        metavar="S",
        help="upper bound on the mission (it normally ends when every route is done)",
    )
    parser.add_argument(
        "--screenshot-after",
        type=float,
        default=DEMO_SCREENSHOT_AFTER_S,
        metavar="S",
        help="when the GUI screenshot is taken, seconds after start (during the mission)",
    )
    parser.add_argument(
        "--map-f1-floor",
        type=float,
        default=None,
        metavar="F1",
        help="the verdict's floor on map F1 within ±1 voxel (default: cps_experiments.verdict's "
        "MAP_F1_FLOOR_WITHIN_1_VOXEL, for the whole fleet)",
    )
    parser.add_argument(
        "--map-f1-floor-exact",
        type=float,
        default=None,
        metavar="F1",
        help="the verdict's floor on map F1 voxel for voxel (default: cps_experiments.verdict's "
        "MAP_F1_FLOOR_EXACT, for the whole fleet)",
    )
    parser.add_argument(
        "--web-listen",
        default=None,
        metavar="HOST:PORT",
        help="where the twin's Foxglove endpoint listens (cps_bringup --web-listen; default its own)",
    )
    parser.add_argument(
        "--kill-map-server-at",
        type=float,
        default=None,
        metavar="S",
        help="fault injection: kill the map server mid-mission (it must resume from autosave)",
    )
    return parser.parse_args(argv)


# After the demo scenario's 10 s outage (at 25 s), before its capacity step (60 s): the screenshot
# shows the operator's live video at its level, not the outage's frozen frame.
DEMO_SCREENSHOT_AFTER_S = 45.0


def main(argv=None):
    args = parse_args(argv)
    t0 = time.monotonic()
    out_dir = os.path.abspath(args.out)
    link = choose_link(args.link, fleet_file=args.fleet)
    scenario = args.link_scenario if link != "none" and args.link_scenario != "none" else None
    mission = mission_args(
        "all",
        fleet=args.fleet,
        port=args.port,
        record=args.record,
        profile=args.profile,
        out=out_dir,
        link=link,
        duration=args.duration,
        screenshot=True,
        screenshot_after=args.screenshot_after,
        link_scenario=scenario,
        robots=args.robots,
        kill_map_server_at=args.kill_map_server_at,
        **({"web_listen": args.web_listen} if args.web_listen else {}),
    )
    mission.map_f1_floor = args.map_f1_floor
    mission.map_f1_floor_exact = args.map_f1_floor_exact
    from cps_experiments.report import write_mission_report

    result = run_and_report("demo", mission, write_mission_report, t0)
    if result is None:
        return 2
    print(json.dumps({"ended_by": result.ended_by, "link": result.link, "out": out_dir}, indent=None))
    return report_verdict("demo", out_dir)


def report_verdict(prog, out_dir):
    """Print the verdict the report wrote and each reason; the exit code (0 only on PASS)."""
    from cps_experiments.verdict import console_lines, exit_code, read_verdict

    verdict = read_verdict(out_dir)
    for line in console_lines(prog, verdict):
        print(line, file=sys.stderr if verdict is None or verdict.status != "PASS" else sys.stdout)
    return exit_code(verdict)


def run_and_report(prog, mission, write_report, t0):
    """Run the mission and `write_report(result, mission, wall_time_s)`; the MissionResult, or None
    after printing why the mission could not start."""
    try:
        result = run_mission(mission)
    except BringupError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return None
    report = write_report(result, mission, wall_time_s=time.monotonic() - t0)
    print(f"[{prog}] wrote {report}")
    return result
