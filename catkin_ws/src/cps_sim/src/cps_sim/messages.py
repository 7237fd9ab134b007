"""ROS messages from the simulator's numpy data (message classes only; no rospy needed).

Stamps are genpy.Time built from wall-clock seconds, so these work with or without a node.
"""

import math

import genpy
import numpy as np
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import BatteryState, CameraInfo, Image, JointState, PointCloud2, PointField

_DATATYPES = {
    np.dtype("<f4"): PointField.FLOAT32,
    np.dtype("<u4"): PointField.UINT32,
    np.dtype("<u2"): PointField.UINT16,
}


def stamp(seconds):
    return genpy.Time.from_sec(float(seconds))


def point_cloud2(array, frame_id, stamp_s):
    """PointCloud2 of a structured array: 2-D arrays are organized (H x W), 1-D unorganized.

    A float rgb field is declared FLOAT32 (PCL's packed-rgb convention) though stored as uint32 bits.
    Organized clouds are never dense (pixels without a return are NaN); unorganized ones are
    dense when every point is finite.
    """
    array = np.ascontiguousarray(array)
    height, width = array.shape if array.ndim == 2 else (1, array.shape[0])
    msg = PointCloud2()
    msg.header.stamp = stamp(stamp_s)
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(height), int(width)
    fields = []
    for name in array.dtype.names:
        dtype, offset = array.dtype.fields[name][:2]
        datatype = PointField.FLOAT32 if name == "rgb" else _DATATYPES[dtype]
        fields.append(PointField(name=name, offset=offset, datatype=datatype, count=1))
    msg.fields = fields
    msg.is_bigendian = False
    msg.point_step = array.dtype.itemsize
    msg.row_step = msg.point_step * msg.width
    msg.data = array.tobytes()
    msg.is_dense = array.ndim == 1 and bool(np.isfinite(array["x"]).all())
    return msg


def cloud_to_array(msg):
    """The structured numpy array (H x W or N) of a PointCloud2 this module wrote."""
    formats = {PointField.FLOAT32: "<f4", PointField.UINT32: "<u4", PointField.UINT16: "<u2"}
    dtype = np.dtype(
        {
            "names": [f.name for f in msg.fields],
            "formats": ["<u4" if f.name == "rgb" else formats[f.datatype] for f in msg.fields],
            "offsets": [f.offset for f in msg.fields],
            "itemsize": msg.point_step,
        }
    )
    array = np.frombuffer(bytes(msg.data), dtype=dtype)
    return array.reshape(msg.height, msg.width) if msg.height > 1 else array


def image_rgb8(rgb, frame_id, stamp_s):
    msg = Image()
    msg.header.stamp = stamp(stamp_s)
    msg.header.frame_id = frame_id
    msg.height, msg.width = rgb.shape[:2]
    msg.encoding = "rgb8"
    msg.is_bigendian = 0
    msg.step = 3 * msg.width
    msg.data = np.ascontiguousarray(rgb).tobytes()
    return msg


def camera_info(camera, frame_id, stamp_s):
    msg = CameraInfo()
    msg.header.stamp = stamp(stamp_s)
    msg.header.frame_id = frame_id
    msg.height, msg.width = camera.height, camera.width
    msg.distortion_model = "plumb_bob"
    msg.D = [0.0] * 5
    msg.K = [camera.fx, 0.0, camera.cx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 1.0]
    msg.R = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    msg.P = [camera.fx, 0.0, camera.cx, 0.0, 0.0, camera.fy, camera.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return msg


def quaternion_from_matrix(m):
    """(x, y, z, w) of the rotation part of a 4x4 (or 3x3) matrix."""
    r = np.asarray(m)[:3, :3]
    w = math.sqrt(max(0.0, 1.0 + r[0, 0] + r[1, 1] + r[2, 2])) / 2.0
    x = math.sqrt(max(0.0, 1.0 + r[0, 0] - r[1, 1] - r[2, 2])) / 2.0
    y = math.sqrt(max(0.0, 1.0 - r[0, 0] + r[1, 1] - r[2, 2])) / 2.0
    z = math.sqrt(max(0.0, 1.0 - r[0, 0] - r[1, 1] + r[2, 2])) / 2.0
    x = math.copysign(x, r[2, 1] - r[1, 2])
    y = math.copysign(y, r[0, 2] - r[2, 0])
    z = math.copysign(z, r[1, 0] - r[0, 1])
    return x, y, z, w


def transform_stamped(matrix, parent, child, stamp_s):
    msg = TransformStamped()
    msg.header.stamp = stamp(stamp_s)
    msg.header.frame_id = parent
    msg.child_frame_id = child
    t = msg.transform.translation
    t.x, t.y, t.z = (float(v) for v in matrix[:3, 3])
    q = msg.transform.rotation
    q.x, q.y, q.z, q.w = quaternion_from_matrix(matrix)
    return msg


def odometry(robot, stamp_s, base_in_odom=None):
    """nav_msgs/Odometry of <r>/base_link in <r>/odom, twist in the child frame (`base_in_odom`:
    robot.base_in_odom() if the caller has it already)."""
    name = robot.name
    msg = Odometry()
    msg.header.stamp = stamp(stamp_s)
    msg.header.frame_id = f"{name}/odom"
    msg.child_frame_id = f"{name}/base_link"
    m = robot.base_in_odom() if base_in_odom is None else base_in_odom
    p = msg.pose.pose.position
    p.x, p.y, p.z = (float(v) for v in m[:3, 3])
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = quaternion_from_matrix(m)
    msg.pose.covariance = [1e-4 if i % 7 == 0 else 0.0 for i in range(36)]
    v = robot.velocity
    msg.twist.twist.linear.x, msg.twist.twist.linear.y, msg.twist.twist.linear.z = v.vx, v.vy, v.vz
    msg.twist.twist.angular.z = v.wz
    msg.twist.covariance = [1e-4 if i % 7 == 0 else 0.0 for i in range(36)]
    return msg


def joint_state(robot, stamp_s):
    msg = JointState()
    msg.header.stamp = stamp(stamp_s)
    msg.name = list(robot.spec.joint_names)
    msg.position = [float(v) for v in robot.joint_positions]
    msg.velocity = [float(v) for v in robot.joint_velocities]
    return msg


def battery_state(robot, stamp_s):
    msg = BatteryState()
    msg.header.stamp = stamp(stamp_s)
    msg.header.frame_id = f"{robot.name}/base_link"
    msg.voltage = float(robot.battery_voltage_v)
    msg.current = float(robot.battery_current_a)
    msg.charge = float("nan")
    msg.capacity = float("nan")
    msg.design_capacity = float(robot.spec.battery_capacity_wh / robot.spec.battery_nominal_v)
    msg.percentage = float(robot.battery_fraction)
    msg.power_supply_status = BatteryState.POWER_SUPPLY_STATUS_DISCHARGING
    msg.power_supply_health = BatteryState.POWER_SUPPLY_HEALTH_GOOD
    msg.power_supply_technology = BatteryState.POWER_SUPPLY_TECHNOLOGY_LION
    msg.present = True
    return msg
