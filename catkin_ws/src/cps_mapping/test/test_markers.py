"""occupied_cells_markers: the bytes on the wire are the MarkerArray genpy would write."""

import io

import numpy as np
import rospy
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from cps_fleet import names
from cps_mapping.fused_map import height_colors
from cps_mapping.markers import occupied_cells_markers

RES = 0.1


def _genpy_markers(centers, sizes, header):
    """The same message built object by object, as the map server did before."""
    array = MarkerArray()
    colors = height_colors(centers[:, 2]) if len(centers) else np.zeros((0, 3))
    levels = np.round(sizes / RES).astype(int)
    for marker_id, level in enumerate(sorted(set(levels.tolist()) | {1})):
        sel = levels == level
        m = Marker(
            header=header,
            ns="map",
            id=marker_id,
            type=Marker.CUBE_LIST,
            action=Marker.ADD if sel.any() else Marker.DELETE,
        )
        m.scale.x = m.scale.y = m.scale.z = level * RES
        m.pose.orientation.w = 1.0
        m.color.a = 1.0
        m.points = [Point(*p) for p in centers[sel].tolist()]
        m.colors = [ColorRGBA(r, g, b, 1.0) for r, g, b in colors[sel].tolist()]
        array.markers.append(m)
    return array


def _bytes(msg):
    buff = io.BytesIO()
    msg.serialize(buff)
    return buff.getvalue()


def test_serialized_markers_are_the_bytes_genpy_writes_and_read_back():
    rng = np.random.default_rng(3)
    centers = rng.uniform([-10, -7, 0], [10, 7, 3], size=(500, 3))
    sizes = rng.choice([RES, 2 * RES, 8 * RES], size=500)
    header = Header(seq=0, stamp=rospy.Time(1795434700, 123), frame_id=names.MAP_FRAME)
    ours = occupied_cells_markers(centers, sizes, RES, header)
    assert _bytes(ours) == _bytes(_genpy_markers(centers, sizes, header))
    back = MarkerArray().deserialize(_bytes(ours))
    assert [m.id for m in back.markers] == [0, 1, 2] and back.markers[2].scale.x == 8 * RES
    finest = back.markers[0]
    np.testing.assert_allclose([(p.x, p.y, p.z) for p in finest.points], centers[np.isclose(sizes, RES)])
    assert len(finest.colors) == len(finest.points) and finest.colors[0].a == 1.0


def test_an_empty_map_publishes_one_delete_marker():
    header = Header(frame_id=names.MAP_FRAME)
    ours = occupied_cells_markers(np.zeros((0, 3)), np.zeros(0), RES, header)
    assert _bytes(ours) == _bytes(_genpy_markers(np.zeros((0, 3)), np.zeros(0), header))
    back = MarkerArray().deserialize(_bytes(ours))
    assert len(back.markers) == 1 and back.markers[0].action == Marker.DELETE and back.markers[0].points == []
