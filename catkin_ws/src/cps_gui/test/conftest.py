"""Fixtures of the GUI tests: an offscreen QApplication, a fleet file whose robots have names of
their own (so these tests' topics cannot meet another package's), and helpers to spin Qt."""

import math
import os
import time

import pytest
import yaml

from cps_fleet import names

TEST_PREFIX = "guitest_"


@pytest.fixture(scope="session")
def qapp():
    from python_qt_binding.QtWidgets import QApplication

    # Qt reads the platform once, when the application is made; the variable is set only for that,
    # so processes that other packages' tests start (the demo's GUI under Xvfb) do not inherit it.
    previous = os.environ.get("QT_QPA_PLATFORM")
    os.environ["QT_QPA_PLATFORM"] = previous or "offscreen"
    try:
        app = QApplication.instance() or QApplication(["cps_gui_tests"])
    finally:
        if previous is None:
            del os.environ["QT_QPA_PLATFORM"]
    yield app


@pytest.fixture(scope="session")
def test_fleet_file(tmp_path_factory):
    """cps_bringup's fleet.yaml with every robot renamed guitest_<name> and absolute paths."""
    from cps_fleet.fleet import default_fleet_path

    source = default_fleet_path()
    base = os.path.dirname(source)
    with open(source) as stream:
        doc = yaml.safe_load(stream)
    doc["site"] = os.path.normpath(os.path.join(base, doc["site"]))
    for robot in doc["robots"]:
        robot["name"] = TEST_PREFIX + robot["name"]
        robot["route"] = os.path.normpath(os.path.join(base, robot["route"]))
    path = tmp_path_factory.mktemp("fleet") / "fleet.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return str(path)


def spin_until(app, predicate, timeout_s=10.0, what="condition"):
    """Process Qt events until `predicate()` is true; AssertionError naming `what` (text or a callable
    giving it) on timeout."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        app.processEvents()
        if predicate():
            return
        time.sleep(0.01)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what() if callable(what) else what}")


def spin_for(app, seconds):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        app.processEvents()
        time.sleep(0.01)


@pytest.fixture(scope="session")
def odom_frames_in_map(rospy_node, test_fleet_file):
    """This process plays fleet_sim's part for tf: the static map -> <r>/odom of every test robot
    (its initial pose), which the GUI reads to place odometry in `map`."""
    import tf2_ros
    from geometry_msgs.msg import TransformStamped

    from cps_fleet.fleet import load_fleet

    transforms = []
    for robot in load_fleet(test_fleet_file).robots:
        pose = robot.initial_pose
        t = TransformStamped()
        t.header.stamp = rospy_node.Time.now()
        t.header.frame_id, t.child_frame_id = names.MAP_FRAME, names.odom_frame(robot.name)
        t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = pose.x, pose.y, pose.z
        t.transform.rotation.z, t.transform.rotation.w = math.sin(pose.yaw_rad / 2), math.cos(pose.yaw_rad / 2)
        transforms.append(t)
    broadcaster = tf2_ros.StaticTransformBroadcaster()
    broadcaster.sendTransform(transforms)
    yield broadcaster
