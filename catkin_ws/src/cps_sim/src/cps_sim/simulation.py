"""The fleet in one PyBullet world: robots, their sensors and kinematics (no rospy).

`FleetSimulation` is what the fleet_sim node, the sample-cloud renderer and the tests drive.
"""
import dataclasses
from typing import Dict

import numpy as np

from cps_sim.robots import Robot
from cps_sim.sensors import DepthCamera, Lidar
from cps_sim.site import load_site
from cps_sim.world import SimWorld


@dataclasses.dataclass
class SimulatedRobot:
    robot: Robot
    sensor: object          # DepthCamera or Lidar
    rate_hz: float
    config: object          # cps_msgs.fleet.RobotConfig

    @property
    def name(self):
        return self.robot.name

    @property
    def sensor_frame(self):
        return self.config.sensor_frame


class FleetSimulation:
    """One world, the fleet's robots in it at their initial poses, one sensor per robot."""

    def __init__(self, fleet, site=None, renderer="egl"):
        self.fleet = fleet
        self.site = site if site is not None else load_site(fleet.site_path)
        self.world = SimWorld(self.site, renderer)
        self.robots: Dict[str, SimulatedRobot] = {}
        profile = fleet.profile
        for cfg in fleet.robots:
            robot = Robot(cfg.name, cfg.type, cfg.initial_pose)
            body = self.world.add_robot(robot)
            if cfg.has_lidar:
                lp = profile.lidar
                sensor = Lidar(self.world, lp.rings, lp.samples_per_ring, lp.vertical_fov_deg, lp.max_range_m,
                               ignore_body=body)
                rate = lp.rate_hz
            else:
                cp = profile.depth_camera
                sensor = DepthCamera(self.world, cp.width, cp.height, cp.hfov_deg, cp.near_m, cp.far_m)
                rate = cp.rate_hz
            self.robots[cfg.name] = SimulatedRobot(robot, sensor, rate, cfg)

    @property
    def renderer(self):
        return self.world.renderer

    def step(self, dt_s):
        for sim in self.robots.values():
            sim.robot.step(dt_s)
            self.world.sync_robot(sim.robot)

    def place(self, name, x, y, z, yaw):
        sim = self.robots[name]
        sim.robot.set_pose(x, y, z, yaw)
        self.world.sync_robot(sim.robot)

    def capture(self, name):
        """A DepthFrame or LidarScan of robot `name` at its current pose."""
        sim = self.robots[name]
        return sim.sensor.capture(sim.robot.sensor_in_map())

    def close(self):
        self.world.close()


def sensor_points(frame):
    """The structured points (H x W depth cloud or N lidar points) of a capture."""
    return frame.cloud if hasattr(frame, "cloud") else frame.points


def points_in_map(frame) -> np.ndarray:
    """(N, 3) finite points of a capture transformed to `map`."""
    pts = sensor_points(frame).reshape(-1)
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], axis=1).astype(np.float64)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    m = frame.sensor_in_map
    return xyz @ m[:3, :3].T + m[:3, 3]


def build_fleet_simulation(fleet_file=None, profile=None, robots=None, renderer="egl", site=None):
    """Load fleet.yaml (optionally a profile and a robot subset) and build the simulation."""
    from cps_msgs.fleet import load_fleet, robot_names_arg

    fleet = load_fleet(fleet_file, profile)
    fleet = robot_names_arg(fleet, robots)
    return FleetSimulation(fleet, site=site, renderer=renderer)

