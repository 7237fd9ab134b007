"""The whole system, for real: the reference mission (cps_harness.reference; three robots of the
light profile fly their routes through the tissue, across the shaped link when root) writes a map
that scores against ground truth, a report with its verdict and a screenshot whose panes show the
map, the top view and a camera image. Afterwards no process and no network namespace of the run is
left. (The map server killed mid-mission and resuming from its autosave: test_link_cut.)"""

import json
import re

import numpy as np

from cps_bringup.link import link_unavailable_reason
from cps_harness.reference import MAP_F1_FLOOR


def _pane(image, panes, name):
    box = panes["panes"][name]
    return image[box["y"] : box["y"] + box["height"], box["x"] : box["x"] + box["width"]]


def test_the_reference_mission_ends_with_a_scored_map_a_report_and_its_verdict(reference_mission):
    reference_mission.check_passed()
    out, log = reference_mission.out, reference_mission.log
    assert "every robot finished its route" in log, log[-3000:]
    assert "[demo] verdict PASS" in log, log[-3000:]  # the demo exits 0 only on PASS (check_passed above)
    # The supervisor's events are in the report as in the log (a killed map server's restart there:
    # test_link_cut, in the bringup's log).
    report = (out / "report.md").read_text()
    assert "## Supervisor events" in report and re.search(r"^- \d+ s all: \d+ processes up$", report, re.M), report

    scores = json.loads((out / "scores.json").read_text())
    # MAP_F1_FLOOR is a within-±1-voxel figure (the only one there was when it was set).
    assert scores["f1_within_1_voxel"] >= MAP_F1_FLOOR, scores
    assert scores["precision_within_1_voxel"] > 0.9, scores
    assert (out / "map.bt").stat().st_size > 10_000


def test_the_screenshot_shows_a_camera_image_the_map_in_3d_and_the_top_view(reference_mission):
    reference_mission.check()
    from PIL import Image

    out = reference_mission.out
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


def test_nothing_of_the_run_is_left(reference_mission):
    reference_mission.check()
    assert not reference_mission.leftovers, reference_mission.leftovers
    if link_unavailable_reason() is None:  # the run had its own shaped link: none of it may be left
        assert reference_mission.mission.run_link_name(), "the log does not name the run's link"
