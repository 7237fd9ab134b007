"""The whole system, for real: two robots of the light profile fly their routes through the tissue
(across the shaped link when root), the map server is killed mid-mission and must resume from its
autosave, and the demo writes a map that scores against ground truth, a report and a screenshot.
Afterwards no process and no network namespace of the run is left."""

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from cps_bringup.link import link_unavailable_reason
from cps_ros.processes import processes_named

DEMO = os.path.join(os.path.dirname(__file__), "..", "nodes", "demo")
# Two robots of the light profile over their whole routes map well over half of what the site's
# ground truth holds within reach; a broken transform, decoder or insertion drops F1 far below.
F1_THRESHOLD = 0.6
# Two robots see less of the hall than the demo's four: voxel for voxel ~0.5 (fig13_live's 2-robot
# runs: 0.51), against the four robots' 0.70 that the verdict's default floor is set for.
F1_EXACT_THRESHOLD = 0.4


def _pane(image, panes, name):
    box = panes["panes"][name]
    return image[box["y"] : box["y"] + box["height"], box["x"] : box["x"] + box["width"]]


@pytest.mark.ros
@pytest.mark.slow
def test_two_robot_mission_end_to_end(open_tmp_path):
    out = open_tmp_path / "demo"
    result = subprocess.run(
        [
            sys.executable,
            DEMO,
            "--robots",
            "scout,jackal",
            "--out",
            str(out),
            "--duration",
            "150",
            "--screenshot-after",
            "25",
            "--kill-map-server-at",
            "24",
            "--map-f1-floor",
            str(F1_THRESHOLD),
            "--map-f1-floor-exact",
            str(F1_EXACT_THRESHOLD),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    log = result.stdout + result.stderr
    assert "every robot finished its route" in log, log[-3000:]
    # The kill is what a user feels: the map server's statistics went silent while it restarted, and the
    # verdict says so (FAIL, exit 1, at the kill); nothing else fails (the mission ends before the
    # scenario's capacity step). The ledger may be INCOMPLETE by the clouds the killed server held.
    verdict = json.loads((out / "verdict.json").read_text())
    failed = [c for c in verdict["checks"] if c["status"] == "FAIL"]
    assert result.returncode == 1 and verdict["status"] == "FAIL", log[-4000:]
    assert {c["name"] for c in failed} == {"map server heard"}, failed
    assert all(20.0 <= c["at_s"] <= 30.0 for c in failed), failed

    report = (out / "report.md").read_text()
    assert "map_server: killed by --kill-map-server-at" in report
    assert "map_server: exited with code" in report and "restart 1/3" in report
    map_server_logs = sorted((out / "logs").glob("map_server-*.log"), key=lambda p: int(p.stem.split("-")[1]))
    assert len(map_server_logs) == 2, map_server_logs
    assert "map_server: resumed from" in map_server_logs[1].read_text()

    scores = json.loads((out / "scores.json").read_text())
    # F1_THRESHOLD is a within-±1-voxel figure (the only one there was when it was set).
    assert scores["f1_within_1_voxel"] >= F1_THRESHOLD, scores
    assert scores["precision_within_1_voxel"] > 0.9, scores
    assert (out / "map.bt").stat().st_size > 10_000

    from PIL import Image

    image = np.asarray(Image.open(out / "gui.png").convert("RGB")).astype(int)
    panes = json.loads((out / "gui.png.panes.json").read_text())
    video = _pane(image, panes, "video")
    assert video.std() > 10, "the camera pane shows no image"
    # rviz colours the occupied cells by height: a live map is many strongly coloured pixels.
    view3d = _pane(image, panes, "view3d")
    colourful = (view3d.max(axis=2) - view3d.min(axis=2)) > 80
    assert colourful.mean() > 0.03, f"3D view shows no map ({colourful.mean():.3%} coloured pixels)"
    # The top view draws occupied cells of the projected map dark on a light background.
    topview = _pane(image, panes, "topview")
    dark = topview.max(axis=2) < 60
    assert dark.mean() > 0.02, f"top view shows no map ({dark.mean():.3%} dark pixels)"

    leftovers = processes_named(str(out))
    assert not leftovers, leftovers
    run_link = re.search(r"between namespaces (\w+)_phys", log)
    if link_unavailable_reason() is None:  # the run had its own shaped link: none of it may be left
        assert run_link, "the log does not name the run's link"
        namespaces = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout.split()
        assert not [ns for ns in namespaces if ns.startswith(f"{run_link.group(1)}_")], namespaces
