"""Larger fleets for tests and benchmarks: the default fleet.yaml with every robot copied."""

import math
import os

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
