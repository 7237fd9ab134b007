"""The topic and service names of the bandwidth manager, in one place.

All relative: started in the root namespace the node has exactly the names of the ROS graph
contract (`/tissue/allocation`, `/<r>/cloud_throttle/rate_hz`, ...); started in a namespace it
manages the fleet inside that namespace.
"""
ALLOCATION = "tissue/allocation"
AVAILABLE_BANDWIDTH = "tissue/available_bandwidth"
SET_PRIORITY = "tissue/set_priority"
STATS = "tissue/stats"
LINK_STATE = "tissue/link_state"  # cps_msgs/LinkState, published by the bridge
LIMITER = "cloud_throttle"  # the robot's rate limiter (cps_transport: in cloud_tissue, or a rate_limiter node)


def limiter_rate_hz(robot):
    return f"{robot}/{LIMITER}/rate_hz"


def limiter_status(robot):
    return f"{robot}/{LIMITER}/status"


def mission_state(robot):
    return f"{robot}/mission_state"


def managed_cloud(robot):
    """The topic the robot's limiter publishes, named in the allocation message."""
    return f"{robot}/points_filtered/draco/managed"
