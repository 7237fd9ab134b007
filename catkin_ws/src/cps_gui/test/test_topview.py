"""Top-view drawing data, the video frame conversion and the shipped rviz config."""

import math
import os

import numpy as np
import pytest

from cps_fleet import names
from cps_gui import rviz_config, topview


def test_occupancy_image_colours_and_orientation():
    # 3 x 2 grid, row 0 at the origin (bottom): one occupied cell at x=2, y=0.
    data = [0, -1, 100, 0, 0, 0]
    image = topview.occupancy_image(3, 2, 0.5, -1.0, 2.0, data)
    assert image.rgb.shape == (2, 3, 3) and image.occupied_cells == 1
    assert tuple(image.rgb[1, 2]) == topview.OCCUPIED_RGB  # bottom row on screen is row 0
    assert tuple(image.rgb[1, 1]) == topview.UNKNOWN_RGB
    assert tuple(image.rgb[0, 0]) == topview.FREE_RGB
    assert (image.x_min, image.y_min, image.width_m, image.height_m) == (-1.0, 2.0, 1.5, 1.0)


def test_large_grids_are_decimated_keeping_thin_walls():
    width = height = 2000
    data = np.zeros((height, width), dtype=np.int8)
    data[1000, :] = 100  # a one-cell wall
    image = topview.occupancy_image(width, height, 0.05, 0.0, 0.0, data.ravel(), max_cells=500)
    assert image.rgb.shape == (500, 500, 3) and image.cell_m == pytest.approx(0.2)
    assert image.occupied_cells == 500


@pytest.mark.parametrize(
    "args,match",
    [
        ((0, 2, 0.1, 0, 0, []), "empty"),
        ((2, 2, 0.0, 0, 0, [0] * 4), "resolution"),
        ((2, 2, 0.1, 0, 0, [0] * 3), "3 cells"),
    ],
)
def test_bad_grids_are_rejected(args, match):
    with pytest.raises(ValueError, match=match):
        topview.occupancy_image(*args)


def test_odom_to_map_applies_the_map_to_odom_transform():
    x, y, yaw = topview.odom_to_map(-8.0, -6.0, math.radians(90), 1.0, 0.0, 0.0)
    assert (x, y, yaw) == pytest.approx((-8.0, -5.0, math.radians(90)))
    assert topview.yaw_from_quaternion(0, 0, math.sin(0.4), math.cos(0.4)) == pytest.approx(0.8)


def test_world_to_screen_fits_and_keeps_aspect():
    bounds = topview.Bounds(-10, -5, 10, 5)
    to_screen = topview.WorldToScreen.fit(bounds, 400, 400)
    assert to_screen(-10, 5) == pytest.approx((0, 100))
    assert to_screen(10, -5) == pytest.approx((400, 300))


def test_scene_bounds_cover_map_and_points_with_margin():
    image = topview.occupancy_image(10, 10, 1.0, 0.0, 0.0, [0] * 100)
    bounds = topview.scene_bounds(image, [[(20.0, -3.0)], []], margin_m=1.0)
    assert (bounds.x_min, bounds.y_min, bounds.x_max, bounds.y_max) == (-1.0, -4.0, 21.0, 11.0)
    empty = topview.scene_bounds(None, [], margin_m=0.0, minimum_m=4.0)
    assert (empty.x_max - empty.x_min, empty.y_max - empty.y_min) == (4.0, 4.0)


def test_fence_polygons_read_the_shapes_a_site_may_use():
    class Area:
        def __init__(self, **kw):
            self.__dict__.update(kw)

    site = {
        "fenced_areas": [
            {"name": "a", "polygon": [[0, 0], [1, 0], [1, 1]]},
            Area(name="b", min=(0, 0), max=(2, 1)),
            {"name": "c", "x_min": 0, "y_min": 0, "x_max": 1, "y_max": 3},
            Area(name="m", x_min_m=0, y_min_m=0, x_max_m=1, y_max_m=2),
            {"name": "d", "center": {"x": 1, "y": 1}, "size": [2, 4]},
            {"name": "broken", "polygon": [["x", 0]]},
            {"name": "shapeless"},
        ]
    }
    polygons, unreadable = topview.fence_polygons(site)
    assert [name for name, _ in polygons] == ["a", "b", "c", "m", "d"] and unreadable == 2
    assert dict(polygons)["d"] == [(0, -1), (2, -1), (2, 3), (0, 3)]


def test_the_fenced_areas_of_the_shipped_hall_are_drawn():
    from cps_fleet.fleet import load_fleet

    fences, problem = topview.load_fences(load_fleet().site_path)
    assert fences and problem == ""
    for _, polygon in fences:
        assert len(polygon) == 4 and polygon[0][0] < polygon[1][0] and polygon[1][1] < polygon[2][1]


def test_load_fences_explains_a_missing_site_file(tmp_path):
    fences, problem = topview.load_fences(str(tmp_path / "nope.yaml"))
    assert fences == [] and problem


def test_shipped_rviz_config_is_the_generated_one_for_the_default_fleet():
    from cps_fleet.fleet import load_fleet

    path = os.path.join(os.path.dirname(__file__), "..", "config", "fleet.rviz")
    with open(path) as stream:
        shipped = stream.read()
    fleet = load_fleet()
    assert shipped == rviz_config.dump(rviz_config.fleet_rviz_config(fleet))
    for robot in fleet.robots:
        assert (
            names.absolute(names.twin_points(robot.name)) in shipped
            and names.absolute(names.robot_topic(robot.name, names.ODOM)) in shipped
        )
    assert f"Fixed Frame: {names.MAP_FRAME}" in shipped and names.in_twin(names.OCCUPIED_CELLS) in shipped


def _frame(encoding, width, height, data, step=0):
    from cps_gui.fleet_state import ImageFrame

    return ImageFrame("/cam", width, height, encoding, step, bytes(data), 0.0, 0.0)


def test_video_frames_convert_from_the_common_encodings(qapp):
    from cps_gui.widgets.video import frame_to_rgb

    rgb = frame_to_rgb(_frame("rgb8", 2, 1, [1, 2, 3, 4, 5, 6]))
    assert rgb.tolist() == [[[1, 2, 3], [4, 5, 6]]]
    assert frame_to_rgb(_frame("bgr8", 1, 1, [1, 2, 3])).tolist() == [[[3, 2, 1]]]
    assert frame_to_rgb(_frame("mono8", 1, 1, [7])).tolist() == [[[7, 7, 7]]]
    padded = frame_to_rgb(_frame("rgb8", 1, 2, [1, 2, 3, 0, 4, 5, 6, 0], step=4))
    assert padded.tolist() == [[[1, 2, 3]], [[4, 5, 6]]]
    big = frame_to_rgb(_frame("rgb8", 1280, 960, np.zeros(1280 * 960 * 3, np.uint8)), max_side_px=640)
    assert big.shape == (480, 640, 3)


@pytest.mark.parametrize(
    "frame,match",
    [
        (("32FC1", 1, 1, [0] * 4), "unsupported image encoding"),
        (("rgb8", 2, 2, [0] * 6), "expected 2 rows"),
        (("rgb8", 0, 0, []), "empty"),
    ],
)
def test_bad_video_frames_are_rejected(qapp, frame, match):
    from cps_gui.widgets.video import frame_to_rgb

    with pytest.raises(ValueError, match=match):
        frame_to_rgb(_frame(*frame))
