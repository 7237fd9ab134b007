"""The primary 3D view's rviz configuration, generated from the fleet so that robot names live
only in fleet.yaml. `config/fleet.rviz` is this generator's output for the default fleet
(`python -m cps_gui.rviz_config > config/fleet.rviz`; a test keeps the two equal), so plain
`rviz -d config/fleet.rviz` shows the same scene.
"""

import sys

import yaml

from cps_fleet import names
from cps_gui.colours import robot_colour


def fleet_rviz_config(fleet, frame_rate_hz=10):
    """The rviz config (a dict in rviz's YAML schema): the fused map as markers, TF, and per robot
    its odometry with a trail of past poses and its latest decoded cloud, in the `map` frame."""
    displays = [
        {
            "Class": "rviz/Grid",
            "Name": "Grid",
            "Enabled": True,
            "Cell Size": 1,
            "Plane Cell Count": 40,
            "Reference Frame": "<Fixed Frame>",
            "Color": "160; 160; 164",
            "Alpha": 0.5,
        },
        {
            "Class": "rviz/MarkerArray",
            "Name": "Fused map",
            "Enabled": True,
            "Marker Topic": names.in_twin(names.OCCUPIED_CELLS),
            "Queue Size": 2,
            "Namespaces": {},
        },
        {
            "Class": "rviz/MarkerArray",
            "Name": "Map changes",
            "Enabled": True,
            "Marker Topic": names.in_twin(names.MAP_CHANGES),
            "Queue Size": 2,
            "Namespaces": {},
        },
        {
            "Class": "rviz/TF",
            "Name": "TF",
            "Enabled": True,
            "Show Names": False,
            "Show Axes": True,
            "Show Arrows": False,
            "Marker Scale": 1,
            "Update Interval": 0.2,
            "Frame Timeout": 15,
        },
    ]
    for index, robot in enumerate(fleet.robots):
        colour = "%d; %d; %d" % robot_colour(index)
        displays.append(
            {
                "Class": "rviz/Group",
                "Name": robot.name,
                "Enabled": True,
                "Displays": [
                    {
                        "Class": "rviz/Odometry",
                        "Name": "pose and trail",
                        "Enabled": True,
                        "Topic": names.absolute(names.robot_topic(robot.name, names.ODOM)),
                        "Queue Size": 2,
                        "Keep": 200,
                        "Position Tolerance": 0.2,
                        "Angle Tolerance": 0.3,
                        "Shape": {
                            "Value": "Arrow",
                            "Color": colour,
                            "Alpha": 1,
                            "Shaft Length": 0.6,
                            "Shaft Radius": 0.08,
                            "Head Length": 0.3,
                            "Head Radius": 0.15,
                        },
                        "Covariance": {"Value": False},
                    },
                    {
                        "Class": "rviz/PointCloud2",
                        "Name": "latest cloud",
                        "Enabled": True,
                        "Topic": names.absolute(names.twin_points(robot.name)),
                        "Queue Size": 1,
                        "Style": "Points",
                        "Size (Pixels)": 2,
                        "Alpha": 0.8,
                        "Decay Time": 0,
                        "Color Transformer": "FlatColor",
                        "Color": colour,
                        "Selectable": False,
                        "Use Fixed Frame": True,
                        "Unreliable": True,
                    },
                ],
            }
        )
    return {
        "Panels": [],
        "Visualization Manager": {
            "Class": "",
            "Displays": displays,
            "Enabled": True,
            "Global Options": {
                "Fixed Frame": "map",
                "Background Color": "48; 48; 48",
                "Frame Rate": frame_rate_hz,
                "Default Light": True,
            },
            "Name": "root",
            "Tools": [
                {"Class": "rviz/Interact", "Hide Inactive Objects": True},
                {"Class": "rviz/MoveCamera"},
                {"Class": "rviz/FocusCamera"},
            ],
            "Value": True,
            "Views": {
                "Current": {
                    "Class": "rviz/Orbit",
                    "Name": "Current View",
                    "Target Frame": "<Fixed Frame>",
                    "Distance": 32,
                    "Focal Point": {"X": 0, "Y": 0, "Z": 0},
                    "Pitch": 0.85,
                    "Yaw": 4.2,
                    "Field of View": 0.785,
                    "Near Clip Distance": 0.01,
                },
                "Saved": None,
            },
        },
        "Window Geometry": {"Hide Left Dock": True, "Hide Right Dock": True},
    }


def dump(config):
    return (
        "# Generated by `python -m cps_gui.rviz_config` from the default fleet.yaml; do not edit.\n"
        + yaml.safe_dump(config, sort_keys=False, default_flow_style=False)
    )


def main():
    from cps_fleet.fleet import load_fleet

    sys.stdout.write(dump(fleet_rviz_config(load_fleet(sys.argv[1] if len(sys.argv) > 1 else None))))


if __name__ == "__main__":
    main()
