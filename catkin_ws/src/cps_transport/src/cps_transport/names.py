"""The topic and service names of cps_transport's nodes, in one place.

Names a user remaps per node are private (`~input`, `~output`), resolved in the robot's
namespace the node runs in. The statistics are site-wide names of the ROS graph contract
(`/tissue/stats`, `/twin/<r>/...`): absolute, so topic_stats started in any namespace reports on
the one topic everybody reads (remap `/tissue/stats:=...` for a second monitor).
"""
INPUT = "~input"
OUTPUT = "~output"
COMPRESSED_SUFFIX = "compressed"  # image_transport's compressed plugin: <image>/compressed

# rate_limiter: its rate is set through these, its state reported on STATUS.
STATUS = "~status"
SET_RATE = "~set_rate"
RATE_HZ = "~rate_hz"

STATS = "/tissue/stats"
TF = "/tf"


def managed_cloud_at_twin(robot):
    """The managed cloud as relayed on the digital-twin side (the link carries it once)."""
    return f"/twin/{robot}/points_filtered/draco/managed"


def light_robot_streams(robot):
    """The robot's unmanaged streams that cross the link whole (the 4 % reserve)."""
    return [f"/{robot}/odom", f"/{robot}/battery", f"/{robot}/joint_states"]
