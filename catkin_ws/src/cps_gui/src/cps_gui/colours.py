"""One colour per robot (by its index in the fleet), shared by the plots, top view and rviz."""

ROBOT_COLOURS = [
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
]


def robot_colour(index):
    return ROBOT_COLOURS[index % len(ROBOT_COLOURS)]
