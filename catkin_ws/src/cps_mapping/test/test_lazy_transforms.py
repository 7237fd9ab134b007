"""The map server's lazily read transforms: /tf bytes are only queued where they arrive and read into
the tf2 buffer by the lookup, in arrival order; bytes that are not a TFMessage are counted, never
raised; a transform not known yet raises tf2's exception at once (the lookup never waits)."""

import io

import genpy
import pytest
import rospy
import tf2_py
from geometry_msgs.msg import TransformStamped
from tf2_msgs.msg import TFMessage

from cps_fleet import names
from cps_mapping.transforms import LazyTransforms

MAP, ODOM = names.MAP_FRAME, names.odom_frame("a")


def _raw(msg):
    buffer = io.BytesIO()
    msg.serialize(buffer)
    return rospy.AnyMsg().deserialize(buffer.getvalue())


def _tf(parent, child, secs, x):
    t = TransformStamped()
    t.header.frame_id, t.child_frame_id, t.header.stamp = parent, child, genpy.Time(secs)
    t.transform.translation.x, t.transform.rotation.w = x, 1.0
    return t


def test_transforms_are_read_when_looked_up_in_arrival_order():
    transforms = LazyTransforms()
    transforms.received(_raw(TFMessage([_tf(MAP, ODOM, 0, 1.0)])), static=True)
    transforms.received(_raw(TFMessage([_tf(ODOM, "a/base", 10, 0.0)])))
    transforms.received(_raw(TFMessage([_tf(ODOM, "a/base", 11, 2.0)])))
    assert transforms.read == 0, "nothing is read where it arrives"
    pose = transforms.lookup(MAP, "a/base", genpy.Time(10, 500_000_000))
    assert pose.transform.translation.x == pytest.approx(2.0) and transforms.read == 3
    with pytest.raises(tf2_py.ExtrapolationException):
        transforms.lookup(MAP, "a/base", genpy.Time(12))  # not known yet: raises at once
    transforms.received(_raw(TFMessage([_tf(ODOM, "a/base", 12, 4.0)])))
    assert transforms.lookup(MAP, "a/base", genpy.Time(12)).transform.translation.x == pytest.approx(5.0)


def test_bytes_that_are_not_transforms_are_counted_and_clear_forgets_everything():
    transforms = LazyTransforms()
    garbage = rospy.AnyMsg().deserialize(b"\x05\x00\x00\x00xy")
    transforms.received(garbage)
    transforms.received(TFMessage([_tf(MAP, "b", 1, 0.0)]))  # a message object is taken too
    transforms.catch_up()
    assert (transforms.refused, transforms.read) == (1, 1)
    transforms.clear()
    with pytest.raises(tf2_py.TransformException):
        transforms.lookup(MAP, "b", genpy.Time(1))
