"""Views of the simulated hall (cps_sim) from chosen poses, as (points in map, sensor origin)."""

import math

import numpy as np


def capture_views(poses, site=None, robots=("jackal",), profile="light"):
    """robot -> [(points_map, origin_m)] for each (x, y, z, yaw_deg) in `poses[robot]`."""
    from cps_sim.simulation import build_fleet_simulation, points_in_map

    sim = build_fleet_simulation(None, profile, list(robots), "egl", site=site)
    try:
        out = {}
        for robot in robots:
            out[robot] = []
            for x, y, z, yaw_deg in poses[robot]:
                sim.place(robot, x, y, z, math.radians(yaw_deg))
                frame = sim.capture(robot)
                out[robot].append((points_in_map(frame), np.asarray(frame.sensor_in_map[:3, 3], dtype=np.float64)))
        return out
    finally:
        sim.close()
