"""Fixtures every package's tests share.

- `ros_master`: one private roscore for the whole test session (rospy can join one master per
  process); the environment points at it.
- `ros`: a RosGraph on that master that kills the processes a test started, even on failure.
- `rospy_node`: this test process as a rospy node on that master.
- `reference_mission`: the reference mission (cps_harness.reference), run once per test run and
  asserted on by many tests.

Every test is marked `ros` (it needs a master: it uses one of these fixtures, or says so with
`pytest.mark.ros`) or `unit` (everything else), so `pytest -m unit` runs without ROS and the
summary counts both kinds. A package's rostest file runs as one test marked `rostest` (and `ros`).
A test that runs a whole mission (it uses `reference_mission`, or says
so with `pytest.mark.mission`) is also `ros`.

Run in parallel (pytest-xdist, `-n 3 --dist loadgroup`, as `make test` does): every mission test
is in one group, `missions`, which starts first, on one worker (missions run one at a time: two at
once would share the two cores with each other); each module of ROS tests is a group of its own (its
module fixtures are set up once); unit tests go wherever a worker is free, but not to the third
worker, which runs the modules marked `waiting` (MissionsFirst).
"""

import collections
import os
import shutil
import tempfile

import pytest

from cps_harness.testing import RosGraph

pytest_plugins = ["cps_harness.durations"]

ROS_FIXTURES = frozenset({"ros_master", "ros", "rospy_node"})
MISSIONS = "missions"
# A group of a module marked `waiting` (it mostly waits: sleeps, timers, a ROS graph's round trips);
# with three workers or more, the last one runs only these (MissionsFirst).
WAITING_GROUP_PREFIX = "waiting:"


@pytest.hookimpl(tryfirst=True)  # before xdist's, which turns the groups into the items' node ids
def pytest_collection_modifyitems(config, items):
    for item in items:
        if "reference_mission" in item.fixturenames or item.get_closest_marker("mission") is not None:
            item.add_marker(pytest.mark.mission)
            item.add_marker(pytest.mark.ros)
            item.add_marker(pytest.mark.xdist_group(MISSIONS))
            continue
        if ROS_FIXTURES.intersection(item.fixturenames) or item.get_closest_marker("rostest") is not None:
            item.add_marker(pytest.mark.ros)
        if item.get_closest_marker("ros") is None:
            item.add_marker(pytest.mark.unit)
        else:
            waiting = item.get_closest_marker("waiting") is not None
            item.add_marker(pytest.mark.xdist_group((WAITING_GROUP_PREFIX if waiting else "") + item.module.__name__))
    # The reference mission's tests first (they wait for it), then the missions that run alone.
    items.sort(key=lambda item: 0 if "reference_mission" in item.fixturenames else 1)


class MissionsFirst:
    """xdist's loadgroup scheduler, with the missions' group sent out first: the worker that takes
    it starts the reference mission at once, while the other worker runs the other tests.

    With three workers or more, the last one runs only the waiting groups (modules marked
    `waiting`), which the others take only once their own work is gone: a module that mostly waits
    then waits beside the CPU-bound work instead of holding one of the two CPU-bound workers (on
    two workers, such modules held 424 s of wall for 95 s of CPU: final60)."""

    @staticmethod
    def pytest_xdist_make_scheduler(config, log):
        from xdist.scheduler import LoadGroupScheduling

        class Scheduling(LoadGroupScheduling):
            def _assign_work_unit(self, node):
                if MISSIONS in self.workqueue:
                    self.workqueue.move_to_end(MISSIONS, last=False)
                waiting_node = self.nodes[-1] if len(self.nodes) >= 3 else None
                if waiting_node is not None:
                    for_waiting = node is waiting_node
                    scope = next((s for s in self.workqueue if s.startswith(WAITING_GROUP_PREFIX) == for_waiting), None)
                    if scope is None and for_waiting:
                        # none left for it (and none will come): it ends once its own are done
                        if not self._pending_of(self.assigned_work.get(node, {})):
                            node.shutdown()
                        return
                    if scope is not None:
                        self.workqueue.move_to_end(scope, last=False)
                super()._assign_work_unit(node)

        return Scheduling(config, log)


def pytest_configure(config):
    if config.pluginmanager.hasplugin("xdist"):  # its hook exists only with the plugin (not with -p no:xdist)
        config.pluginmanager.register(MissionsFirst(), "cps_missions_first")


def pytest_terminal_summary(terminalreporter):
    """One line per kind, e.g. `unit: 250 passed, 0 failed, 0 skipped`: unit, ros (rostest files
    and missions included) and, of those, rostest and mission."""
    kinds = ("unit", "ros", "rostest", "mission")
    counts = {kind: collections.Counter() for kind in kinds}
    for outcome in ("passed", "failed", "skipped", "error", "xfailed", "xpassed"):
        for report in terminalreporter.stats.get(outcome, []):
            if not hasattr(report, "keywords") or (outcome == "passed" and report.when != "call"):
                continue
            for kind in kinds:
                if kind in report.keywords or (kind == "ros" and "unit" not in report.keywords):
                    counts[kind][outcome] += 1
    if not any(counts.values()):
        return
    terminalreporter.section("tests by kind")
    for kind, c in counts.items():
        terminalreporter.write_line(
            f"{kind}: {c['passed']} passed, {c['failed'] + c['error']} failed, {c['skipped']} skipped"
            + (f", {c['xfailed'] + c['xpassed']} xfail" if c["xfailed"] + c["xpassed"] else "")
        )


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


@pytest.fixture(scope="session")
def reference_mission():
    """The reference mission (cps_harness.reference), run to its end once per test run; its
    ReferenceRun. A test that needs it calls `reference_mission.check()` first."""
    from cps_harness.reference import keep_for_reading, run_reference

    folder = _open_folder()
    try:
        run = run_reference(folder)
        yield run
    finally:
        if os.environ.get("CPS_TEST_OUT"):  # make test's report folder: what a failure needs to be read
            keep_for_reading(folder, os.path.join(os.environ["CPS_TEST_OUT"], "reference"))
        shutil.rmtree(folder, ignore_errors=True)


def _open_folder():
    folder = tempfile.mkdtemp(prefix="cps-open-")
    os.chmod(folder, 0o755)
    return folder


@pytest.fixture
def open_tmp_path():
    """A temporary folder other users can reach (pytest's tmp_path is root-only): for a bringup run
    as root, whose nodes drop to an unprivileged user."""
    import pathlib

    folder = _open_folder()
    try:
        yield pathlib.Path(folder)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
