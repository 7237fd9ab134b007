"""Our messages as Foxglove schemas: fields, colours, frames, and bad input refused with a reason."""

import math
import struct

import pytest
import rospy
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import BatteryState, CompressedImage, PointCloud2, PointField
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import Marker, MarkerArray

from cps_fleet import names
from cps_gui.colours import robot_colour
from cps_gui.topview import CHANGE_RGB
from cps_harness.foxglove_decode import decode
from cps_msgs.msg import BandwidthAllocation, BandwidthAllocationArray, LinkCapacity, LinkState
from cps_web import convert


def _header(frame, secs=12, nsecs=345):
    return Header(frame_id=frame, stamp=rospy.Time(secs, nsecs))


def _cloud(points, frame=names.MAP_FRAME, pad=0):
    fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate("xyz")]
    data = b"".join(struct.pack("<3f", *p) for p in points)
    return PointCloud2(
        header=_header(frame),
        height=1,
        width=len(points),
        fields=fields,
        is_bigendian=False,
        point_step=12,
        row_step=12 * len(points) + pad,
        data=data + b"\0" * pad,
        is_dense=True,
    )


def _odom(robot, x, y, z=0.0, w=1.0):
    msg = Odometry(header=_header(names.odom_frame(robot)), child_frame_id=names.base_frame(robot))
    msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z = x, y, z
    msg.pose.pose.orientation.w = w
    return msg


def test_point_cloud_keeps_layout_stamp_and_frame():
    msg = _cloud([(1.0, 2.0, 3.0), (4.0, 5.0, 6.0)])
    out = decode(convert.point_cloud(msg))
    assert out.frame_id == names.MAP_FRAME
    assert (out.timestamp.seconds, out.timestamp.nanos) == (12, 345)
    assert out.point_stride == 12
    float32 = 7  # foxglove.PackedElementField.NumericType.FLOAT32
    assert [(f.name, f.offset, f.type) for f in out.fields] == [("x", 0, float32), ("y", 4, float32), ("z", 8, float32)]
    assert struct.unpack("<6f", out.data) == (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)


def test_point_cloud_with_padded_rows_keeps_only_points():
    msg = _cloud([(1.0, 2.0, 3.0)], pad=4)
    assert struct.unpack("<3f", decode(convert.point_cloud(msg)).data) == (1.0, 2.0, 3.0)


def test_point_cloud_whose_data_does_not_fit_is_refused():
    msg = _cloud([(1.0, 2.0, 3.0), (4.0, 5.0, 6.0)])
    msg.data = msg.data[:-3]
    with pytest.raises(ValueError, match="bytes for 1 rows"):
        convert.point_cloud(msg)


def test_point_cloud_with_unknown_datatype_is_refused():
    msg = _cloud([(1.0, 2.0, 3.0)])
    msg.fields[0].datatype = 42
    with pytest.raises(ValueError, match="unknown datatype 42"):
        convert.point_cloud(msg)


def test_pose_in_frame_is_in_the_robots_odom_frame():
    out = decode(convert.pose_in_frame(_odom("scout", 1.5, -2.0)))
    assert out.frame_id == names.odom_frame("scout")
    assert (out.pose.position.x, out.pose.position.y, out.pose.orientation.w) == (1.5, -2.0, 1.0)


def test_non_finite_pose_is_refused():
    with pytest.raises(ValueError, match="non-finite"):
        convert.pose_in_frame(_odom("scout", math.nan, 0.0))


@pytest.mark.parametrize("fmt, kind", [("jpeg", "jpeg"), ("rgb8; jpeg compressed bgr8", "jpeg"), ("png", "png")])
def test_compressed_image_format_as_foxglove_reads_it(fmt, kind):
    msg = CompressedImage(header=_header("scout/camera"), format=fmt, data=b"\xff\xd8abc")
    out = decode(convert.compressed_image(msg))
    assert (out.format, out.data, out.frame_id) == (kind, b"\xff\xd8abc", "scout/camera")


def test_compressed_image_of_unknown_format_is_refused():
    with pytest.raises(ValueError, match="neither jpeg nor png"):
        convert.compressed_image(CompressedImage(header=_header("c"), format="h264", data=b"x"))


def test_frame_transforms_strip_leading_slashes_and_refuse_nan():
    t = TransformStamped(header=_header("/" + names.MAP_FRAME), child_frame_id=names.odom_frame("scout"))
    t.transform.rotation.w = 1.0
    t.transform.translation.x = 2.0
    out = decode(convert.frame_transforms(TFMessage(transforms=[t])))
    assert [(x.parent_frame_id, x.child_frame_id, x.translation.x) for x in out.transforms] == [
        (names.MAP_FRAME, names.odom_frame("scout"), 2.0)
    ]
    t.transform.rotation.w = math.inf
    with pytest.raises(ValueError, match="non-finite transform"):
        convert.frame_transforms(TFMessage(transforms=[t]))


def _change(kind, i, x):
    m = Marker(header=_header(names.MAP_FRAME), ns="map_changes", id=i, type=Marker.CUBE, action=Marker.ADD, text=kind)
    m.pose.position.x, m.pose.orientation.w = x, 1.0
    m.scale.x, m.scale.y, m.scale.z = 1.0, 0.5, 0.8
    return m


def test_change_scene_replaces_all_and_uses_the_guis_colours():
    label = Marker(header=_header(names.MAP_FRAME), id=9, type=Marker.TEXT_VIEW_FACING, action=Marker.ADD, text="x")
    clear = Marker(header=_header(names.MAP_FRAME), action=Marker.DELETEALL)
    msg = MarkerArray(markers=[clear, _change("appeared", 1, 3.0), label, _change("disappeared", 3, -1.0)])
    out = decode(convert.change_scene(msg))
    assert [d.type for d in out.deletions] == [1]  # foxglove.SceneEntityDeletion.Type.ALL
    assert [e.id for e in out.entities] == ["change_1", "change_3"]
    for entity, kind in zip(out.entities, ("appeared", "disappeared")):
        cube = entity.cubes[0]
        rgb = tuple(round(255 * c) for c in (cube.color.r, cube.color.g, cube.color.b))
        assert rgb == CHANGE_RGB[kind]
        assert (cube.size.x, cube.size.y, cube.size.z) == (1.0, 0.5, 0.8)
        assert entity.texts[0].text == kind
        assert entity.frame_id == names.MAP_FRAME


def test_trails_keep_a_point_per_step_in_the_robots_colour():
    trails = convert.Trails(["scout", "jackal"], step_m=0.5)
    for x in (0.0, 0.1, 0.6, 0.7, 1.2):
        assert trails.add("jackal", _odom("jackal", x, 0.0))
    assert not trails.add("ghost", _odom("ghost", 0.0, 0.0))
    assert not trails.add("jackal", _odom("jackal", math.nan, 0.0))
    scene = decode(trails.scene())
    assert [e.id for e in scene.entities] == ["jackal"]  # scout never seen
    entity = scene.entities[0]
    assert entity.frame_id == names.odom_frame("jackal")
    assert [p.x for p in entity.lines[0].points] == [0.0, 0.6, 1.2]
    assert entity.arrows[0].pose.position.x == 1.2
    colour = entity.lines[0].color
    assert tuple(round(255 * c) for c in (colour.r, colour.g, colour.b)) == robot_colour(1)


def test_fleet_health_row():
    health = convert.FleetHealth(["scout", "iris"])
    health.battery("scout", BatteryState(percentage=0.42))
    health.battery("iris", BatteryState(percentage=math.nan))  # unknown: not a number in a plot
    health.mission_state("scout", "running")
    health.control_mode("scout", "auto")
    health.pose("scout", 10.0)
    row = health.row(12.5)
    assert row["robots"]["scout"] == {
        "battery_percent": pytest.approx(42.0),
        "mission_state": "running",
        "control_mode": "auto",
        "pose_age_s": 2.5,
    }
    assert row["robots"]["iris"] == {
        "battery_percent": None,
        "mission_state": "",
        "control_mode": "",
        "pose_age_s": None,
    }


def test_link_figures_in_mbit_per_s():
    link = convert.LinkFigures()
    assert link.row(1.0)["budget_mbps"] is None  # nothing heard yet: null, not a made-up zero
    link.link_state(LinkState(up=True, outages=2))
    link.link_capacity(LinkCapacity(capacity_mbps=10.0, source="tc scenario demo"))
    link.allocation(
        BandwidthAllocationArray(
            available_mbps=60.0,
            budget_mbytes_per_s=7.2,
            allocated_mbytes_per_s=5.0,
            feasible=True,
            allocations=[
                BandwidthAllocation(
                    robot="scout", stream="video", level=2, level_name="low", rate_hz=5.0, bandwidth_mbytes_per_s=0.25
                )
            ],
        )
    )
    row = link.row(2.0)
    assert row["link_up"] is True and row["outages"] == 2
    assert row["capacity_mbps"] == 10.0 and row["capacity_source"] == "tc scenario demo"
    assert row["budget_mbps"] == pytest.approx(57.6) and row["allocated_mbps"] == pytest.approx(40.0)
    assert row["streams"]["scout/video"] == {
        "level": 2,
        "level_name": "low",
        "rate_hz": 5.0,
        "mbps": 2.0,
        "degraded": False,
    }
