"""The top-down picture (the paper's Fig. 14) of any fleet: the paper's colours for its four robot
types, others for a type only a user's fleet file defines (the demo's report draws it for every
mission)."""

import numpy as np

from cps_experiments.topdown_map import OTHER_COLOURS, ROBOT_COLOURS, plot_topdown, robot_colours
from cps_fleet.fleet import load_fleet
from cps_harness.fleets import fleet_with_new_type


def test_a_users_robot_type_is_drawn_in_a_colour_of_its_own(tmp_path):
    fleet = load_fleet(str(fleet_with_new_type(tmp_path, robot="scout")))
    colours = robot_colours(fleet)
    assert colours["scout"] == OTHER_COLOURS[0] and colours["jackal"] == ROBOT_COLOURS["wheeled_depth"]
    trajectories = {"scout": [(-8.0, -6.0, 0.5), (-8.0, -4.0, 0.5)], "jackal": []}
    png = plot_topdown(np.array([[0.0, 0.0, 1.0], [1.0, 1.0, 0.5]]), trajectories, fleet, str(tmp_path / "top.png"))
    assert (tmp_path / "top.png").stat().st_size > 10_000 and png == str(tmp_path / "top.png")
