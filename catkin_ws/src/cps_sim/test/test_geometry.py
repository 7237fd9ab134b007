"""A known box at a known distance shows up where it is in the depth cloud and the lidar scan,
and sensor points transformed to `map` land on it."""

import dataclasses
import math

import numpy as np
import pytest

from cps_fleet.fleet import load_fleet
from cps_fleet.site import Equipment, load_site
from cps_sim.simulation import FleetSimulation, points_in_map

BOX_CENTER_X = 3.0
BOX_HALF = 0.5


@pytest.fixture(scope="module", params=["fast", "egl", "tiny"])
def sim(request):
    site = load_site(load_fleet().site_path)
    box = Equipment(
        "test_box",
        "crate",
        BOX_CENTER_X,
        0.0,
        0.0,
        (("size_x_m", 2 * BOX_HALF), ("size_y_m", 2.0), ("size_z_m", 2.0)),
        (0.8, 0.2, 0.2),
    )
    site = dataclasses.replace(site, areas=(), equipment=(box,))
    fleet = load_fleet(profile="light").with_robots(["scout", "jackal"])
    simulation = FleetSimulation(fleet, site=site, renderer=request.param)
    assert simulation.renderer == request.param
    yield simulation
    simulation.close()


def test_box_in_depth_cloud_at_its_distance(sim):
    sim.place("jackal", 0.0, 0.0, 0.0, 0.0)
    sim.place("scout", 0.0, -6.0, 0.0, math.pi)  # out of the way
    frame = sim.capture("jackal")
    camera = sim.robots["jackal"].sensor
    cloud = frame.cloud
    # Depth of a centre-column pixel looking slightly up (the optical axis is pitched down and
    # meets the floor first) equals where its ray meets the box face x = 2.5, within a pixel.
    pitch = math.radians(sim.robots["jackal"].robot.robot_type.sensor_mount.pitch_deg)
    row, col = int(camera.cy - camera.fy * math.tan(pitch)) - 5, int(camera.cx)
    ray = np.array([(col - camera.cx) / camera.fx, (row - camera.cy) / camera.fy, 1.0])
    ray_map = frame.sensor_in_map[:3, :3] @ ray
    expected_z = (BOX_CENTER_X - BOX_HALF - frame.sensor_in_map[0, 3]) / ray_map[0]
    pixel_footprint = expected_z / camera.fx
    assert float(cloud["z"][row, col]) == pytest.approx(expected_z, abs=pixel_footprint + 0.005)
    # Every pixel that hit the box, transformed to map, lies on its face x = 2.5.
    world = points_in_map(frame)
    on_box = world[(np.abs(world[:, 1]) < 0.9) & (world[:, 2] > 0.1) & (world[:, 2] < 1.9)]
    assert len(on_box) > 1000
    np.testing.assert_allclose(on_box[:, 0], BOX_CENTER_X - BOX_HALF, atol=0.02)


def test_box_in_lidar_scan_at_its_distance(sim):
    sim.place("scout", 0.0, 0.0, 0.0, 0.0)
    sim.place("jackal", 0.0, -6.0, 0.0, math.pi)
    frame = sim.capture("scout")
    lidar = sim.robots["scout"].sensor
    points = frame.points
    expected = BOX_CENTER_X - BOX_HALF
    above_floor = points["z"] > -0.5
    front = points[(np.abs(np.arctan2(points["y"], points["x"])) < math.radians(2)) & above_floor]
    rings = np.unique(front["ring"])
    assert len(rings) >= 8  # rings whose beams reach the 2 m box at 2.5 m
    np.testing.assert_allclose(front["x"][front["x"] < expected + 0.5], expected, atol=0.02)
    # Beam elevation of each point matches its ring within one ring spacing.
    elevation = np.arctan2(front["z"], np.hypot(front["x"], front["y"]))
    np.testing.assert_allclose(elevation, lidar.elevations[front["ring"]], atol=lidar.ring_spacing_rad)
    world = points_in_map(frame)
    on_box = world[(np.abs(world[:, 1]) < 0.9) & (world[:, 2] > 0.05) & (world[:, 0] > 0) & (world[:, 0] < 5)]
    np.testing.assert_allclose(on_box[:, 0], expected, atol=0.02)


def test_auto_renderer_picks_tiny_for_small_frames_and_egl_for_large():
    from cps_sim.world import resolve_renderer

    assert resolve_renderer("auto", 320, 240) == "tiny"
    assert resolve_renderer("auto", 640, 480) == "egl"
    assert resolve_renderer("egl", 320, 240) == "egl"
    assert resolve_renderer("fast", 640, 480) == "fast"
    with pytest.raises(ValueError, match="known: fast, egl, tiny, auto"):
        resolve_renderer("vulkan", 320, 240)
