"""Fixtures every package's tests share.

- `ros_master`: one private roscore for the whole test session (rospy can join one master per
  process); the environment points at it.
- `ros`: a RosGraph on that master that kills the processes a test started, even on failure.
- `rospy_node`: this test process as a rospy node on that master.

Every test is marked `ros` (it needs a master: it uses one of these fixtures, or says so with
`pytest.mark.ros`) or `unit` (everything else), so `pytest -m unit` runs without ROS and the
summary counts both kinds.
"""

import collections
import os
import shutil
import tempfile

import pytest

from cps_harness.testing import RosGraph

ROS_FIXTURES = frozenset({"ros_master", "ros", "rospy_node"})


def pytest_collection_modifyitems(config, items):
    for item in items:
        if ROS_FIXTURES.intersection(item.fixturenames):
            item.add_marker(pytest.mark.ros)
        if item.get_closest_marker("ros") is None:
            item.add_marker(pytest.mark.unit)


def pytest_terminal_summary(terminalreporter):
    """One line per kind, e.g. `unit: 250 passed, 0 failed, 1 skipped`."""
    counts = {"unit": collections.Counter(), "ros": collections.Counter()}
    for outcome in ("passed", "failed", "skipped", "error"):
        for report in terminalreporter.stats.get(outcome, []):
            if not hasattr(report, "keywords") or (outcome == "passed" and report.when != "call"):
                continue
            counts["ros" if "ros" in report.keywords else "unit"][outcome] += 1
    # ci/run_tests.sh runs the rostest .test files first and leaves their count in this file.
    rostest_summary = os.environ.get("CPS_ROSTEST_SUMMARY")
    rostest_line = None
    if rostest_summary and os.path.exists(rostest_summary):
        with open(rostest_summary) as stream:
            rostest_line = stream.read().strip()
    if not any(counts.values()) and not rostest_line:
        return
    terminalreporter.section("tests by kind")
    for kind, c in counts.items():
        terminalreporter.write_line(
            f"{kind}: {c['passed']} passed, {c['failed'] + c['error']} failed, {c['skipped']} skipped"
        )
    if rostest_line:
        terminalreporter.write_line(rostest_line)


@pytest.fixture(scope="session")
def ros_master():
    graph = RosGraph()
    graph.start()
    graph.point_this_process_here()
    os.environ["ROS_HOME"] = graph.home
    try:
        yield graph
    finally:
        graph.close()


@pytest.fixture
def ros(ros_master):
    graph = ros_master.attach()
    try:
        yield graph
    finally:
        graph.close()


@pytest.fixture(scope="session")
def rospy_node(ros_master):
    import rospy

    rospy.init_node("cps_pytest", anonymous=True, disable_signals=True)
    yield rospy
    rospy.signal_shutdown("tests done")


@pytest.fixture
def open_tmp_path():
    """A temporary folder other users can reach (pytest's tmp_path is root-only): for a bringup run
    as root, whose nodes drop to an unprivileged user."""
    import pathlib

    folder = tempfile.mkdtemp(prefix="cps-open-")
    os.chmod(folder, 0o755)
    try:
        yield pathlib.Path(folder)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
