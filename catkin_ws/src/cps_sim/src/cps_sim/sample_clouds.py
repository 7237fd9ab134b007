"""Clouds rendered by the simulator, for other packages' benchmarks and tests.

`render_sample_clouds` gives one cloud per robot of the default fleet from a pose in its fenced
area looking at equipment; `render_mission_clouds` gives clouds at poses spread along each
robot's route (for min/max figures over a mission). Each sample carries the sensor's pose in
`map` so that a mapping test can insert it.
"""

import dataclasses
import math
from typing import Dict, List

import numpy as np

from cps_sim import messages
from cps_sim.simulation import build_fleet_simulation, sensor_points
from cps_sim.world import DEFAULT_RENDERER

# Robot -> (x, y, z, yaw_deg) in map: inside its fenced area, facing equipment.
SAMPLE_POSES = {
    "scout": (-6.5, -2.6, 0.0, 0.0),
    "jackal": (-6.6, 1.8, 0.0, 35.0),
    "champ": (2.6, 0.8, 0.0, 20.0),
    "iris": (6.5, -5.2, 3.0, 150.0),
}


@dataclasses.dataclass
class SampleCloud:
    robot: str
    cloud: object  # sensor_msgs/PointCloud2 in the sensor frame
    sensor_pose_in_map: np.ndarray  # 4 x 4, the sensor frame in map
    frame_id: str


def _sample(sim, name, stamp_s):
    frame = sim.capture(name)
    robot = sim.robots[name]
    cloud = messages.point_cloud2(sensor_points(frame), robot.sensor_frame, stamp_s)
    return SampleCloud(name, cloud, frame.sensor_in_map.copy(), robot.sensor_frame)


def render_sample_frames(profile_name="paper", robots=None, poses=None, renderer=DEFAULT_RENDERER, fleet_file=None):
    """Robot -> SampleCloud, one frame each from `poses` (robot -> (x, y, z, yaw_deg)) or SAMPLE_POSES."""
    import time

    sim = build_fleet_simulation(fleet_file, profile_name, robots, renderer)
    try:
        out = {}
        for name in sim.robots:
            x, y, z, yaw_deg = (poses or {}).get(name) or SAMPLE_POSES.get(name) or _route_pose(sim, name, 0.5)
            sim.place(name, x, y, z, math.radians(yaw_deg))
        for name in sim.robots:
            out[name] = _sample(sim, name, time.time())
        return out
    finally:
        sim.close()


def render_sample_clouds(profile_name="paper", robots=None, poses=None, renderer=DEFAULT_RENDERER, fleet_file=None):
    """Robot -> sensor_msgs/PointCloud2 (depth: organized x,y,z,rgb, point_step 32, optical frame;
    lidar: x,y,z,intensity,ring,time, unorganized)."""
    return {
        name: s.cloud for name, s in render_sample_frames(profile_name, robots, poses, renderer, fleet_file).items()
    }


def _route_pose(sim, name, fraction):
    """(x, y, z, yaw_deg) at `fraction` of the way along the robot's route polyline."""
    cfg = sim.robots[name].config
    start = cfg.initial_pose
    pts = [(start.x, start.y, start.z)] + [(w.x, w.y, w.z) for w in sim.fleet.route(name).waypoints]
    pts = np.array(pts, dtype=float)
    seg = np.linalg.norm(np.diff(pts[:, :2], axis=0), axis=1)
    total = seg.sum()
    target = fraction * total
    for i, length in enumerate(seg):
        if target <= length or i == len(seg) - 1:
            f = min(target / length, 1.0) if length > 0 else 0.0
            p = pts[i] + f * (pts[i + 1] - pts[i])
            yaw = math.degrees(math.atan2(pts[i + 1][1] - pts[i][1], pts[i + 1][0] - pts[i][0]))
            return float(p[0]), float(p[1]), float(p[2]), yaw
        target -= length
    raise AssertionError("unreachable")


def render_mission_clouds(
    profile_name="paper", robots=None, frames_per_robot=5, renderer=DEFAULT_RENDERER, fleet_file=None
) -> Dict[str, List[SampleCloud]]:
    """Robot -> SampleClouds at `frames_per_robot` poses evenly along its route (start to end)."""
    import time

    sim = build_fleet_simulation(fleet_file, profile_name, robots, renderer)
    try:
        out = {name: [] for name in sim.robots}
        for k in range(frames_per_robot):
            fraction = (k + 0.5) / frames_per_robot
            for name in sim.robots:
                x, y, z, yaw = _route_pose(sim, name, fraction)
                sim.place(name, x, y, z, math.radians(yaw))
            for name in sim.robots:
                out[name].append(_sample(sim, name, time.time()))
        return out
    finally:
        sim.close()


__all__ = ["SAMPLE_POSES", "SampleCloud", "render_sample_clouds", "render_sample_frames", "render_mission_clouds"]
