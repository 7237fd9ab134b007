"""cps_msgs types that stand in for upstream ones Debian 12 does not package have the upstream md5s,
so upstream tools and nodes (octomap_server's clients, point_cloud_transport, rosbag) accept them.
The md5s are computed here from the upstream definition texts with genmsg, not copied."""

import genmsg
import genmsg.msg_loader
import pytest

# ros-perception/point_cloud_transport msg/CompressedPointCloud2.msg (ROS 1 catkin package,
# commit 79adb04fe99fa06a39b8fdcfc221070ae59880ce).
POINT_CLOUD_TRANSPORT_COMPRESSED = """
std_msgs/Header header

uint32 height
uint32 width

sensor_msgs/PointField[] fields

bool is_bigendian

uint32 point_step

uint32 row_step

uint8[] compressed_data

bool is_dense"""

# OctoMap/octomap_msgs srv/BoundingBoxQuery.srv.
OCTOMAP_BOUNDING_BOX_QUERY = """# Clear a region specified by a global axis-aligned bounding box in stored OctoMap

# minimum corner point of axis-aligned bounding box in global frame
geometry_msgs/Point min
# maximum corner point of axis-aligned bounding box in global frame
geometry_msgs/Point max
---
"""

# OctoMap/octomap_msgs msg/Octomap.msg.
OCTOMAP = """# A 3D map in binary format, as Octree
Header header

# Flag to denote a binary (only free/occupied) or full occupancy octree (.bt/.ot file)
bool binary

# Class id of the contained octree
string id

# Resolution (in m) of the smallest octree nodes
float64 resolution

# binary serialization of octree, use conversions.h to read and write octrees
int8[] data
"""

# Debian installs the ROS 1 message definitions here.
SEARCH_PATH = {p: [f"/usr/share/{p}/msg"] for p in ("std_msgs", "sensor_msgs", "geometry_msgs")}


def _context():
    return genmsg.MsgContext.create_default()


def upstream_msg_md5(text, full_name):
    context = _context()
    spec = genmsg.msg_loader.load_msg_from_string(context, text, full_name)
    genmsg.msg_loader.load_depends(context, spec, SEARCH_PATH)
    return genmsg.compute_md5(context, spec)


def upstream_srv_md5(text, full_name):
    context = _context()
    spec = genmsg.msg_loader.load_srv_from_string(context, text, full_name)
    genmsg.msg_loader.load_depends(context, spec.request, SEARCH_PATH)
    genmsg.msg_loader.load_depends(context, spec.response, SEARCH_PATH)
    return genmsg.compute_md5(context, spec)


def test_compressed_point_cloud2_is_point_cloud_transports():
    from cps_msgs.msg import CompressedPointCloud2

    upstream = upstream_msg_md5(POINT_CLOUD_TRANSPORT_COMPRESSED, "point_cloud_transport/CompressedPointCloud2")
    assert CompressedPointCloud2._md5sum == upstream


def test_octomap_is_octomap_msgs():
    from cps_msgs.msg import Octomap

    assert Octomap._md5sum == upstream_msg_md5(OCTOMAP, "octomap_msgs/Octomap")


def test_clear_bbx_service_is_octomap_msgs_bounding_box_query():
    from cps_msgs.srv import BoundingBoxQuery

    upstream = upstream_srv_md5(OCTOMAP_BOUNDING_BOX_QUERY, "octomap_msgs/BoundingBoxQuery")
    assert BoundingBoxQuery._md5sum == upstream


def test_reset_service_is_std_srvs_empty_as_octomap_servers():
    from std_srvs.srv import Empty

    assert Empty._md5sum == upstream_srv_md5("---\n", "std_srvs/Empty")


@pytest.mark.parametrize(
    "text",
    [
        POINT_CLOUD_TRANSPORT_COMPRESSED.replace("bool is_dense", ""),
        POINT_CLOUD_TRANSPORT_COMPRESSED + "\nstring format",
    ],
)
def test_the_md5_check_can_fail(text):
    from cps_msgs.msg import CompressedPointCloud2

    assert CompressedPointCloud2._md5sum != upstream_msg_md5(text, "point_cloud_transport/CompressedPointCloud2")
