"""Fleet files for tests and benchmarks, made from the default fleet.yaml: every robot copied, a
robot of a type defined only in the copy, paths made absolute so a copy works from any folder."""

import math
import os
import re
import shutil

import yaml

# How far each copy starts from its original, m, towards the hall's centre line y = 0 (the routes
# start near the walls).
COPY_OFFSET_M = 1.5


def fleet_doc_with_absolute_paths(source=None):
    """The fleet file `source` (default: cps_bringup's fleet.yaml) as a dict whose site and route
    paths are absolute, so a copy written elsewhere still finds them."""
    from cps_fleet.fleet import default_fleet_path

    source = source or default_fleet_path()
    with open(source) as stream:
        doc = yaml.safe_load(stream)
    here = os.path.dirname(os.path.abspath(source))
    doc["site"] = os.path.normpath(os.path.join(here, doc["site"]))
    for robot in doc["robots"]:
        robot["route"] = os.path.normpath(os.path.join(here, robot["route"]))
    return doc


def write_fleet_with_copies(folder, copies=1, source=None):
    """`source` (default: cps_bringup's fleet.yaml) with every robot also as `<name>2`, `<name>3`...
    (`copies` each): same type, leaf and route, initial pose offset towards y = 0; its paths made
    absolute so the file works from `folder`. Returns the new file's path."""
    doc = fleet_doc_with_absolute_paths(source)
    robots = doc["robots"]
    originals = list(robots)
    for i in range(2, copies + 2):
        for robot in originals:
            y = robot["initial_pose"]["y"]
            pose = dict(robot["initial_pose"], y=y - math.copysign(COPY_OFFSET_M * (i - 1), y))
            robots.append(dict(robot, name=f"{robot['name']}{i}", initial_pose=pose))
    path = os.path.join(folder, f"fleet{len(robots)}.yaml")
    with open(path, "w") as stream:
        yaml.safe_dump(doc, stream, sort_keys=False)
    return path


def write_fleet_with_short_routes(folder, waypoints, source=None):
    """`source` (default: cps_bringup's fleet.yaml) with each robot's route cut to its first
    `waypoints` waypoints (route files written into `folder`), so that a test sees every route run
    to `done` in seconds; paths made absolute. Returns the new file's path."""
    doc = fleet_doc_with_absolute_paths(source)
    for robot in doc["robots"]:
        with open(robot["route"]) as stream:
            route = yaml.safe_load(stream)
        route["waypoints"] = route["waypoints"][:waypoints]
        robot["route"] = os.path.join(folder, f"{robot['name']}_route.yaml")
        with open(robot["route"], "w") as stream:
            yaml.safe_dump(route, stream, sort_keys=False)
    path = os.path.join(folder, "fleet_short_routes.yaml")
    with open(path, "w") as stream:
        yaml.safe_dump(doc, stream, sort_keys=False)
    return path


# A user's robot type that only a fleet file defines (cps_fleet knows nothing of it).
NEW_TYPE = """  tracked_lidar:   # a user's robot: only data
    base: wheeled
    sensor: lidar
    cloud_topic: velodyne_points
    sensor_frame: velodyne
    max_range_m: 20.0
    limits: {max_forward_mps: 1.0, max_lateral_mps: 0.0, max_vertical_mps: 0.0, max_yaw_rate_rps: 1.0,
             max_linear_accel_mps2: 0.5, max_yaw_accel_rps2: 1.0}
    body: {half_extents_m: [0.5, 0.4, 0.2], center_z_m: 0.3}
    sensor_mount: {xyz_m: [0.1, 0.0, 0.7], pitch_deg: 0.0}
"""
NEW_TYPE_NAME = "tracked_lidar"


def site_made_absolute(text, source):
    """A fleet file's text with its `site:` path absolute (resolved from `source`'s folder), the
    line numbers unchanged."""
    here = os.path.dirname(os.path.abspath(source))
    return re.sub(
        r"^site: (\S+)$",
        lambda m: f"site: {os.path.normpath(os.path.join(here, m.group(1)))}",
        text,
        count=1,
        flags=re.M,
    )


def fleet_with_new_type(folder, robot="scout", entry=NEW_TYPE):
    """A copy of the default fleet (its whole config folder, so routes resolve) in `folder`/config
    where `robot` is of NEW_TYPE's type, defined only in this copy; its text otherwise unchanged
    (line numbers hold for error messages). Returns the new fleet.yaml's path (a pathlib.Path)."""
    import pathlib

    from cps_fleet.fleet import default_fleet_path

    source = default_fleet_path()
    config_dir = pathlib.Path(folder) / "config"
    shutil.copytree(os.path.dirname(source), config_dir)
    path = config_dir / "fleet.yaml"
    text = site_made_absolute(path.read_text(), source)
    text = text.replace("robot_types:\n", "robot_types:\n" + entry, 1)
    old = f"  - name: {robot}\n    type: "
    start = text.index(old) + len(old)
    text = text[:start] + NEW_TYPE_NAME + text[text.index("\n", start) :]
    path.write_text(text)
    return path


def write_fleet_with_repeated_routes(folder, laps, source=None):
    """`source` (default: cps_bringup's fleet.yaml) with each robot's route driven `laps` times
    (there and back along its waypoints, so a lap ends where it started), for a soak that needs the
    robots moving for many minutes; paths made absolute. Returns the new file's path."""
    if laps < 1:
        raise ValueError(f"laps must be at least 1, got {laps}")
    doc = fleet_doc_with_absolute_paths(source)
    for robot in doc["robots"]:
        with open(robot["route"]) as stream:
            route = yaml.safe_load(stream)
        there = list(route["waypoints"])
        home = {k: robot["initial_pose"][k] for k in ("x", "y")}
        if "z" in there[0]:  # a flyer: back over its start at its first waypoint's height
            home["z"] = there[0]["z"]
        route["waypoints"] = (there + there[-2::-1] + [home]) * laps
        robot["route"] = os.path.join(folder, f"{robot['name']}_route.yaml")
        with open(robot["route"], "w") as stream:
            yaml.safe_dump(route, stream, sort_keys=False)
    path = os.path.join(folder, f"fleet_{laps}_laps.yaml")
    with open(path, "w") as stream:
        yaml.safe_dump(doc, stream, sort_keys=False)
    return path
