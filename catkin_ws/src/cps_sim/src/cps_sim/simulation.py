"""The fleet in one PyBullet world: robots, their sensors and kinematics (no rospy).

`FleetSimulation` is what the fleet_sim node, the sample-cloud renderer and the tests drive.
"""

import dataclasses
from typing import Dict

import numpy as np

from cps_fleet.site import load_site
from cps_sim.robots import Robot
from cps_sim.sensors import CameraModel, DepthCamera, Lidar
from cps_sim.world import DEFAULT_RENDERER, SimWorld, resolve_renderer


@dataclasses.dataclass
class SimulatedRobot:
    robot: Robot
    sensor: object  # DepthCamera or Lidar; CameraModel or None without a world
    rate_hz: float
    config: object  # cps_fleet.fleet.RobotConfig

    @property
    def name(self):
        return self.robot.name

    @property
    def sensor_frame(self):
        return self.config.sensor_frame


class FleetSimulation:
    """One world, the fleet's robots in it at their initial poses, one sensor per robot.

    With renderer=None there is no PyBullet world: only the robots' kinematics and the camera
    models (the fleet_sim node then captures in sensor worker processes).
    """

    def __init__(self, fleet, site=None, renderer=DEFAULT_RENDERER):
        self.fleet = fleet
        self.site = site if site is not None else load_site(fleet.site_path)
        self.world = None
        if renderer is not None:
            cam = fleet.profile.depth_camera
            self.world = SimWorld(
                self.site,
                resolve_renderer(renderer, cam.width, cam.height),
                fallback_renderer=resolve_renderer("auto", cam.width, cam.height),
            )
        self.robots: Dict[str, SimulatedRobot] = {}
        profile = fleet.profile
        for cfg in fleet.robots:
            robot = Robot(cfg.name, cfg.robot_type, cfg.initial_pose)
            if self.world is None:
                cp = profile.depth_camera
                sensor = CameraModel(cp.width, cp.height, cp.hfov_deg) if cfg.has_depth_camera else None
                rate = cp.rate_hz if cfg.has_depth_camera else profile.lidar.rate_hz
                self.robots[cfg.name] = SimulatedRobot(robot, sensor, rate, cfg)
                continue
            body = self.world.add_robot(robot)
            if cfg.has_lidar:
                lp = profile.lidar
                sensor = Lidar(
                    self.world, lp.rings, lp.samples_per_ring, lp.vertical_fov_deg, lp.max_range_m, ignore_body=body
                )
                rate = lp.rate_hz
            else:
                cp = profile.depth_camera
                sensor = DepthCamera(self.world, cp.width, cp.height, cp.hfov_deg, cp.near_m, cp.far_m)
                rate = cp.rate_hz
            self.robots[cfg.name] = SimulatedRobot(robot, sensor, rate, cfg)

    @property
    def renderer(self):
        return self.world.renderer if self.world is not None else None

    def step(self, dt_s):
        for sim in self.robots.values():
            sim.robot.step(dt_s)
            if self.world is not None:
                self.world.sync_robot(sim.robot)

    def place(self, name, x, y, z, yaw):
        sim = self.robots[name]
        sim.robot.set_pose(x, y, z, yaw)
        if self.world is not None:
            self.world.sync_robot(sim.robot)

    def poses(self):
        """Robot -> (x, y, z, yaw) in map, what a sensor worker needs to place the bodies."""
        return {name: (s.robot.x, s.robot.y, s.robot.z, s.robot.yaw) for name, s in self.robots.items()}

    def capture(self, name):
        """A DepthFrame or LidarScan of robot `name` at its current pose."""
        sim = self.robots[name]
        return sim.sensor.capture(sim.robot.sensor_in_map())

    def capture_video(self, task):
        """A VideoFrame of robot `task.robot`'s camera at its current pose, at the task's level only."""
        from cps_sim.video import render_video

        sim = self.robots[task.robot]
        return render_video(sim.sensor, sim.robot.sensor_in_map(), task)

    def close(self):
        if self.world is not None:
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


def build_fleet_simulation(fleet_file=None, profile=None, robots=None, renderer=DEFAULT_RENDERER, site=None):
    """Load fleet.yaml (optionally a profile and a robot subset) and build the simulation."""
    from cps_fleet.fleet import load_fleet, robot_names_arg

    fleet = load_fleet(fleet_file, profile)
    fleet = robot_names_arg(fleet, robots)
    return FleetSimulation(fleet, site=site, renderer=renderer)
