"""The per-robot names every package shares: the REP 105 frames of the graph contract and
`<robot>/<name>`, relative, which resolves to /<robot>/<name> from the root namespace."""

MAP_FRAME = "map"


def robot_topic(robot, topic):
    return f"{robot}/{topic}"


def odom_frame(robot):
    return f"{robot}/odom"


def base_frame(robot):
    return f"{robot}/base_link"
