"""The standalone `cps_gui` command as a process: options, settings file, and the screenshot of
the whole GUI with rviz under Xvfb, checked by pixels in each pane."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import TEST_PREFIX

from cps_fleet import names
from cps_gui.host import SCREENSHOT_GALLIUM_DRIVER, choose_gl_driver
from cps_harness.testing import find_node

MARKER_RGB = (0, 255, 0)
IMAGE_RGB = (255, 0, 255)


@pytest.fixture
def xvfb_display():
    """A private Xvfb (it picks a free display number itself), killed afterwards."""
    read_fd, write_fd = os.pipe()
    proc = subprocess.Popen(
        ["Xvfb", "-displayfd", str(write_fd), "-screen", "0", "1600x1000x24", "-nolisten", "tcp"],
        pass_fds=(write_fd,),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    os.close(write_fd)
    try:
        with os.fdopen(read_fd) as stream:
            number = stream.readline().strip()
        if not number:
            pytest.fail(f"Xvfb did not start (exit code {proc.poll()})")
        yield f":{number}"
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def _wait_exit(ros, proc, timeout_s, publish=None):
    deadline = time.monotonic() + timeout_s
    while proc.poll() is None and time.monotonic() < deadline:
        if publish:
            publish()
        time.sleep(0.25)
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGUSR1)  # the host dumps its threads' stacks
        time.sleep(1.0)
        ros.stop(proc)
        pytest.fail(f"cps_gui did not exit within {timeout_s} s:\n{ros.output(proc.cps_name)[-8000:]}")
    return proc.returncode


def _why_it_ended(text):
    """A crashed GUI's output, its cause first: what it printed before faulthandler's dump (a Python
    exception that PyQt turned into abort(), a Qt fatal message), the dump's head, and the crashing
    thread's Python stack, or that it had none (a native thread: rviz, Ogre, Mesa). final44's
    SIGSEGV showed only other threads' stacks in the dump's head."""
    dump_at = text.find("Fatal Python error")
    if dump_at < 0:
        return text[-3000:]
    current_at = text.find("Current thread", dump_at)
    current = (
        text[current_at : current_at + 2000]
        if current_at >= 0
        else "(no 'Current thread' in the dump: the crashing thread ran no Python, a native thread)"
    )
    return f"{text[:dump_at][-3000:]}\n{text[dump_at : dump_at + 600]}\n...\n{current}"


def test_a_screenshot_renders_with_softpipe_unless_the_caller_chose_a_driver():
    environ = {}
    choose_gl_driver(environ, screenshot=True)
    assert environ == {"GALLIUM_DRIVER": SCREENSHOT_GALLIUM_DRIVER} and SCREENSHOT_GALLIUM_DRIVER == "softpipe"
    environ = {"GALLIUM_DRIVER": "llvmpipe"}
    choose_gl_driver(environ, screenshot=True)
    assert environ == {"GALLIUM_DRIVER": "llvmpipe"}
    environ = {}
    choose_gl_driver(environ, screenshot=False)  # an operator's window: Mesa's own choice
    assert environ == {}


def test_bad_options_are_refused_with_a_message(ros):
    for argv, words in (
        (["--after", "-1"], "--after must be >= 0"),
        (["--geometry", "big"], "WxH"),
        (["--stale-after", "0"], "--stale-after must be positive"),
    ):
        result = subprocess.run(
            [sys.executable, find_node("cps_gui", "cps_gui"), *argv],
            capture_output=True,
            text=True,
            env=ros.env,
            timeout=60,
        )
        assert result.returncode == 2 and words in result.stderr, result.stderr


def test_standalone_host_starts_saves_a_screenshot_and_its_settings(ros, rospy_node, test_fleet_file, tmp_path):
    png, ini = str(tmp_path / "gui.png"), str(tmp_path / "settings" / "gui.ini")
    proc = ros.start_node(
        "cps_gui",
        "cps_gui",
        name="cps_gui_offscreen",
        args=[
            "--no-rviz",
            "--fleet-file",
            test_fleet_file,
            "--settings",
            ini,
            "--screenshot",
            png,
            "--after",
            "2",
            "--geometry",
            "1200x800",
        ],
        env={"QT_QPA_PLATFORM": "offscreen"},
    )
    assert _wait_exit(ros, proc, 90) == 0, _why_it_ended(ros.output("cps_gui_offscreen"))
    from python_qt_binding.QtGui import QImage

    image = QImage(png)
    assert (image.width(), image.height()) == (1200, 800)
    with open(ini) as stream:
        settings = stream.read()
    assert f"teleop\\robot={TEST_PREFIX}scout" in settings and "[window]\ngeometry=" in settings
    panes = json.load(open(png + ".panes.json"))["panes"]
    assert set(panes) == {"video", "view3d", "topview", "status", "teleop", "changes"}


def _qimage_to_rgb(image):
    from python_qt_binding.QtGui import QImage

    image = image.convertToFormat(QImage.Format_RGB888)
    width, height = image.width(), image.height()
    buffer = image.constBits()
    buffer.setsize(image.bytesPerLine() * height)
    rows = np.frombuffer(buffer, np.uint8).reshape(height, image.bytesPerLine())
    return rows[:, : width * 3].reshape(height, width, 3).copy()


def _pane(rgb, rect):
    return rgb[rect["y"] : rect["y"] + rect["height"], rect["x"] : rect["x"] + rect["width"]].astype(int)


def _count_near(pixels, rgb, tolerance):
    return int((np.abs(pixels - np.array(rgb)).max(axis=2) <= tolerance).sum())


def _map_messages(rospy):
    from geometry_msgs.msg import Point
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import Image
    from std_msgs.msg import ColorRGBA
    from visualization_msgs.msg import Marker, MarkerArray

    marker = Marker(type=Marker.CUBE_LIST, action=Marker.ADD, ns="occupied", id=0)
    marker.header.frame_id = names.MAP_FRAME
    marker.pose.orientation.w = 1.0
    marker.scale.x = marker.scale.y = marker.scale.z = 0.2
    marker.color = ColorRGBA(MARKER_RGB[0] / 255.0, MARKER_RGB[1] / 255.0, MARKER_RGB[2] / 255.0, 1.0)
    marker.points = [Point(x * 0.2 - 6.0, y, z * 0.2) for x in range(60) for y in (-2.0, 2.0) for z in range(15)]
    markers = MarkerArray(markers=[marker])

    grid = OccupancyGrid()
    grid.header.frame_id = names.MAP_FRAME
    grid.info.width, grid.info.height, grid.info.resolution = 240, 160, 0.1
    grid.info.origin.position.x, grid.info.origin.position.y = -12.0, -8.0
    cells = np.zeros((160, 240), np.int8)
    cells[55:62, 40:200] = 100
    cells[98:105, 40:200] = 100
    grid.data = cells.ravel().tolist()

    pixels = np.zeros((240, 320, 3), np.uint8)
    pixels[:] = IMAGE_RGB
    image = Image(height=240, width=320, encoding="rgb8", step=960, data=pixels.tobytes())
    image.header.frame_id = f"{TEST_PREFIX}jackal/camera_optical_frame"
    return markers, grid, image


class _LiveFleet:
    """Odometry, battery, stats and allocation of the test fleet, changing over time."""

    def __init__(self, rospy):
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import BatteryState

        from cps_msgs.msg import BandwidthAllocationArray, TopicStatsArray

        self.rospy = rospy
        self.names = [TEST_PREFIX + n for n in ("scout", "jackal", "champ", "iris")]
        self.odom = {
            n: rospy.Publisher(names.absolute(names.robot_topic(n, names.ODOM)), Odometry, queue_size=2)
            for n in self.names
        }
        self.battery = {
            n: rospy.Publisher(names.absolute(names.robot_topic(n, names.BATTERY)), BatteryState, queue_size=2)
            for n in self.names
        }
        self.stats = rospy.Publisher(names.absolute(names.TISSUE_STATS), TopicStatsArray, queue_size=2)
        self.alloc = rospy.Publisher(names.absolute(names.ALLOCATION), BandwidthAllocationArray, queue_size=2)
        self.start = time.monotonic()

    def publish(self):
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import BatteryState

        from cps_msgs.msg import BandwidthAllocation, BandwidthAllocationArray, TopicStats, TopicStatsArray

        t = time.monotonic() - self.start
        stats = TopicStatsArray()
        alloc = BandwidthAllocationArray(
            available_mbps=60.0, reserve_fraction=0.04, budget_mbytes_per_s=7.2, feasible=True
        )
        for i, name in enumerate(self.names):
            odom = Odometry()
            odom.header.frame_id = names.MAP_FRAME  # no map -> <r>/odom tf in this test
            odom.pose.pose.position.x = 0.3 * t
            odom.pose.pose.orientation.w = 1.0
            odom.twist.twist.linear.x = 0.3
            self.odom[name].publish(odom)
            self.battery[name].publish(BatteryState(percentage=0.9 - 0.1 * i - 0.002 * t))
            mbytes = 1.0 + 0.5 * i + 0.2 * np.sin(t + i)
            stats.topics.append(
                TopicStats(
                    topic=names.absolute(names.managed_cloud(name)),
                    robot=name,
                    managed=True,
                    rate_hz=4.0 + i,
                    bandwidth_mbytes_per_s=mbytes,
                    latency_avg_ms=30.0 + 10 * i + 5 * np.cos(t),
                    age_s=0.1,
                )
            )
            alloc.allocations.append(
                BandwidthAllocation(robot=name, priority=int(i == 1), rate_hz=4.0 + i, bandwidth_mbytes_per_s=mbytes)
            )
        self.stats.publish(stats)
        self.alloc.publish(alloc)

    def close(self):
        for pub in [*self.odom.values(), *self.battery.values(), self.stats, self.alloc]:
            pub.unregister()


def test_screenshot_of_the_live_gui_shows_the_map_in_3d_and_top_view_and_a_camera_image(
    ros, rospy_node, test_fleet_file, tmp_path, xvfb_display
):
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import Image
    from visualization_msgs.msg import MarkerArray

    markers, grid, image = _map_messages(rospy_node)
    live = _LiveFleet(rospy_node)
    marker_pub = rospy_node.Publisher(
        names.absolute(names.in_twin(names.OCCUPIED_CELLS)), MarkerArray, queue_size=1, latch=True
    )
    grid_pub = rospy_node.Publisher(
        names.absolute(names.in_twin(names.PROJECTED_MAP)), OccupancyGrid, queue_size=1, latch=True
    )
    image_pub = rospy_node.Publisher(
        names.absolute(names.robot_topic(TEST_PREFIX + "jackal", names.CAMERA_IMAGE)), Image, queue_size=1
    )
    png = str(tmp_path / "fleet_gui.png")
    try:
        marker_pub.publish(markers)
        grid_pub.publish(grid)

        def publish():
            image.header.stamp = rospy_node.Time.now()
            image_pub.publish(image)
            live.publish()

        proc = ros.start_node(
            "cps_gui",
            "cps_gui",
            name="cps_gui_xvfb",
            args=[
                "--fleet-file",
                test_fleet_file,
                "--settings",
                str(tmp_path / "gui.ini"),
                "--screenshot",
                png,
                "--after",
                "12",
                "--geometry",
                "1600x1000",
            ],
            env={"DISPLAY": xvfb_display, "QT_QPA_PLATFORM": "xcb"},
        )
        assert _wait_exit(ros, proc, 60, publish) == 0, _why_it_ended(ros.output("cps_gui_xvfb"))
        # a screenshot renders with the driver the host chose (rviz names the device it got)
        assert f"OpenGL device: {SCREENSHOT_GALLIUM_DRIVER}" in ros.output("cps_gui_xvfb")
    finally:
        for pub in (marker_pub, grid_pub, image_pub):
            pub.unregister()
        live.close()
    if os.environ.get("CPS_GUI_FIGURE"):  # keep the picture, e.g. for the README
        import shutil

        shutil.copyfile(png, os.environ["CPS_GUI_FIGURE"])
    from python_qt_binding.QtGui import QImage

    rgb = _qimage_to_rgb(QImage(png))
    panes = json.load(open(png + ".panes.json"))["panes"]
    view3d, top, video = (_pane(rgb, panes[name]) for name in ("view3d", "topview", "video"))
    # rviz drew its scene (its grey background) and the map markers, lit, so only roughly green.
    assert _count_near(view3d, (48, 48, 48), 6) > 0.2 * view3d.shape[0] * view3d.shape[1]
    green = int(((view3d[:, :, 1] > 120) & (view3d[:, :, 0] < 90) & (view3d[:, :, 2] < 90)).sum())
    assert green > 1500, green
    # The top view drew the projected map's walls.
    assert _count_near(top, (20, 20, 20), 10) > 1000
    # The video pane shows the camera frame.
    assert _count_near(video, IMAGE_RGB, 10) > 10000
