"""`make monitor`: the monitoring mission (the paper's second phase) after `make demo`'s
characterization: the fleet goes back to a site the simulator has changed (equipment removed,
moved, added: a changes file), the twin compares its new map with the saved one as it grows,
and the report scores what it found against what the simulator changed.
Writes into --out: map.bt, map_changes.md/.json (live), gui.png, changes.json, topdown.png, report.md.
"""

import argparse
import os
import sys
import time

from cps_bringup.cli import mission_args
from cps_experiments.demo import choose_link, report_verdict, run_and_report
from cps_fleet.fleet import PROFILES

DEFAULT_BASELINE = "out/demo/map.bt"
DEFAULT_CHANGES_FILE = "config/site_changes.yaml"  # in cps_bringup, found through rospkg
# The robots of the storage area, where the example changes are: a shorter mission than the demo's.
DEFAULT_ROBOTS = "champ,iris"
SCREENSHOT_AFTER_S = 60.0


def default_changes_file():
    """cps_bringup's example changes file (one crate removed, one moved 1 m), found through rospkg."""
    import rospkg

    return os.path.join(rospkg.RosPack().get_path("cps_bringup"), DEFAULT_CHANGES_FILE)


def parse_args(argv):
    parser = argparse.ArgumentParser(prog="monitor", description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline", default=DEFAULT_BASELINE, help=f"the earlier map (default {DEFAULT_BASELINE})")
    parser.add_argument(
        "--site-changes",
        default=None,
        help=f"what the simulator changes (YAML; default cps_bringup's {DEFAULT_CHANGES_FILE})",
    )
    parser.add_argument("--out", default="out/monitor")
    parser.add_argument("--link", default="auto", help="auto (fleet.yaml's link rate when root), none, or a rate")
    parser.add_argument("--profile", default=None, choices=PROFILES)
    parser.add_argument("--robots", default=DEFAULT_ROBOTS, help=f"who goes back (default {DEFAULT_ROBOTS})")
    parser.add_argument("--duration", type=float, default=300.0, metavar="S", help="upper bound on the mission")
    parser.add_argument("--screenshot-after", type=float, default=SCREENSHOT_AFTER_S, metavar="S")
    return parser.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    t0 = time.monotonic()
    if args.site_changes is None:
        args.site_changes = default_changes_file()
    if not os.path.isfile(args.baseline):
        print(
            f"monitor: error: no baseline map at {args.baseline}: run `make demo` first (it saves the "
            f"characterization map there), or pass --baseline MAP.bt",
            file=sys.stderr,
        )
        return 2
    mission = mission_args(
        "all",
        baseline=args.baseline,
        site_changes=args.site_changes,
        out=args.out,
        link=choose_link(args.link),
        duration=args.duration,
        robots=args.robots,
        screenshot=True,
        screenshot_after=args.screenshot_after,
        profile=args.profile,
    )
    from cps_experiments.monitor_report import write_monitor_report

    if not run_and_report("monitor", mission, write_monitor_report, t0):
        return 2
    return report_verdict("monitor", os.path.abspath(args.out))
