"""What the warm-up test and bench share: a fresh copy of a package's checkout (with or without its
kernel cache), an environment that imports it first, a wall cloud and the static transform it
needs. Test and bench support only (the runtime never imports it)."""

import os
import shutil

import numpy as np

from cps_fleet import names


def copy_checkout(package_dir, target_dir, with_cache=False):
    """The package's nodes and Python at `target_dir`, with or without its caches (__pycache__)."""
    ignore = None if with_cache else shutil.ignore_patterns("__pycache__")
    for part in ("nodes", "src"):
        shutil.copytree(os.path.join(package_dir, part), os.path.join(target_dir, part), ignore=ignore)
    return target_dir


def checkout_env(checkout_dir):
    """This environment with `checkout_dir`'s Python first on the path."""
    return {**os.environ, "PYTHONPATH": os.pathsep.join([os.path.join(checkout_dir, "src"), os.environ["PYTHONPATH"]])}


def wall_cloud(rospy, frame_id, offset_m=0.0):
    """A 4 x 3 m wall of 80 x 60 points 3 m in front of the sensor (its optical z axis), `offset_m`
    sideways (a new map version each)."""
    from sensor_msgs import point_cloud2
    from std_msgs.msg import Header

    u, v = np.meshgrid(np.linspace(-2.0, 2.0, 80), np.linspace(-1.5, 1.5, 60))
    pts = np.stack([u.ravel() + offset_m, v.ravel(), np.full(u.size, 3.0)], axis=1).astype(np.float32)
    return point_cloud2.create_cloud_xyz32(Header(stamp=rospy.Time.now(), frame_id=frame_id), pts)


def managed_wall_cloud(rospy, frame_id, offset_m=0.0):
    """`wall_cloud` as the link delivers it to the map server: Draco-compressed (cps_msgs/
    CompressedPointCloud2, for `managed_cloud_topic`)."""
    from cps_transport.draco import DracoEncoder

    return DracoEncoder(lossless=True).encode(wall_cloud(rospy, frame_id, offset_m))


def managed_cloud_topic(robot):
    """Where the map server takes a robot's clouds: the managed cloud as relayed at the twin."""
    return names.absolute(names.managed_cloud_at_twin(robot))


def static_sensor_transform(rospy, frame_id, height_m=0.5):
    """map -> `frame_id`, `height_m` up, latched on /tf_static; keep the returned broadcaster."""
    import tf2_ros
    from geometry_msgs.msg import TransformStamped

    broadcaster = tf2_ros.StaticTransformBroadcaster()
    t = TransformStamped()
    t.header.stamp = rospy.Time.now()
    t.header.frame_id, t.child_frame_id = names.MAP_FRAME, frame_id
    t.transform.translation.z = height_m
    t.transform.rotation.w = 1.0
    broadcaster.sendTransform(t)
    return broadcaster
