"""The e-stop holds at the robot and the dead-man runs on a monotonic clock, on a real master:
fleet_sim ignores /<r>/cmd_vel during STOP ALL, a mux restarted after the GUI has gone starts
stopped, and a mux whose wall clock steps by 30 s stops teleop within its dead-man and never
stops spuriously while commands flow."""

import os
import sys
import time

import pytest

from cps_fleet import names
from cps_harness.testing import TopicRecorder, wait_for

pytestmark = [pytest.mark.ros, pytest.mark.waiting]

HERE = os.path.dirname(os.path.abspath(__file__))
# A GUI stand-in in its own process: publishes the e-stop state latched, then dies when killed.
GUI = (
    "import sys, rospy; from std_msgs.msg import Bool; from cps_fleet import names; "
    "rospy.init_node('gui', anonymous=True); p = rospy.Publisher(names.ESTOP, Bool, queue_size=1, latch=True); "
    "p.publish(Bool(sys.argv[1] == 'on')); rospy.spin()"
)


# What a mux logs once, when it first hears the e-stop state (off).
HEARD_OFF = "e-stop state heard (off)"


def _twist(vx):
    from geometry_msgs.msg import Twist

    msg = Twist()
    msg.linear.x = vx
    return msg


def _publish_for(pub, msg, seconds, rate_hz=20.0):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pub.publish(msg)
        time.sleep(1.0 / rate_hz)


def _publish_until(pub, msg, done, timeout_s, rate_hz=20.0):
    """Publish `msg` at `rate_hz` until `done()` (True) or until `timeout_s` has passed (False):
    commands that must be obeyed within `timeout_s`, stopped at the first sign that they are."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        pub.publish(msg)
        time.sleep(1.0 / rate_hz)
        if done():
            return True
    return False


def _start_mux(graph, env=None):
    return graph.start_node(
        "cps_sim",
        "velocity_mux",
        name="velocity_mux",
        namespace=names.absolute("jackal"),
        params={"~robot": "jackal"},
        env=env,
    )


def _start_gui(graph, state):
    return graph.popen([sys.executable, "-c", GUI, state], name="gui")


@pytest.fixture(scope="module")
def sim(ros_master, rospy_node):
    graph = ros_master.attach()
    try:
        graph.start_node(
            "cps_sim",
            "fleet_sim",
            name="fleet_sim_jackal",
            params={"~profile": "light", "~robots": "jackal", "~sensor_workers": 0},
        )
        graph.wait_for_topic(names.absolute(names.robot_topic("jackal", names.ODOM)), timeout_s=90)
        yield graph
    finally:
        graph.close()


def _position(odom):
    p = odom.wait(timeout_s=10).pose.pose.position
    return p.x, p.y


def test_stop_all_cannot_be_bypassed_by_publishing_cmd_vel_directly(sim, rospy_node):
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry

    gui = _start_gui(sim, "on")
    odom = TopicRecorder(names.absolute(names.robot_topic("jackal", names.ODOM)), Odometry)
    direct = rospy_node.Publisher(names.absolute(names.robot_topic("jackal", names.CMD_VEL)), Twist, queue_size=5)
    try:
        assert wait_for(lambda: "e-stop state heard (on)" in sim.output("fleet_sim_jackal"), 20)
        before = _position(odom)
        _publish_for(direct, _twist(0.5), seconds=3.0)
        after = _position(odom)
        assert abs(after[0] - before[0]) < 1e-3 and abs(after[1] - before[1]) < 1e-3, (before, after)
        assert all(abs(m.twist.twist.linear.x) < 1e-6 for _, m in odom.messages[-20:])
        sim.stop(gui)
        gui = _start_gui(sim, "off")  # released: the same commands now drive it
        assert wait_for(lambda: _moves(direct, odom), 20), "released: the same commands drive it"
    finally:
        sim.stop(gui)
        direct.unregister()
        odom.close()


def _moves(direct, odom):
    before = _position(odom)
    _publish_for(direct, _twist(0.5), seconds=1.0)
    after = _position(odom)
    return abs(after[0] - before[0]) + abs(after[1] - before[1]) > 0.05


def test_a_mux_restarted_after_the_gui_has_gone_starts_stopped(sim, rospy_node):
    from geometry_msgs.msg import Twist

    executed = TopicRecorder(names.absolute(names.robot_topic("jackal", names.CMD_VEL)), Twist)
    auto = rospy_node.Publisher(names.absolute(names.robot_topic("jackal", names.CMD_VEL_AUTO)), Twist, queue_size=5)
    gui = _start_gui(sim, "off")
    mux = _start_mux(sim)
    try:
        sim.wait_for_topic(names.absolute(names.robot_topic("jackal", names.CMD_VEL)), timeout_s=30)
        assert wait_for(lambda: HEARD_OFF in sim.output_of(mux), 20)
        assert _publish_until(
            auto, _twist(0.3), lambda: executed.latest is not None and executed.latest.linear.x > 0.0, 6.0
        ), "the mux, e-stop off, never drove"
        sim.stop(gui)  # the GUI dies, then the mux
        sim.stop(mux)
        executed.take()
        mux = _start_mux(sim)
        assert wait_for(lambda: executed.count > 20, 30), "the restarted mux publishes cmd_vel"
        _publish_for(auto, _twist(0.3), seconds=2.0)
        outputs = [m.linear.x for _, m in executed.take()]
        assert outputs and all(vx == 0.0 for vx in outputs), outputs
        gui = _start_gui(sim, "off")  # the state heard again: the route's commands drive
        # The GUI's process takes its own time to come up (1-3 s on the loaded machine): commands
        # published before the restarted mux has heard it are rightly not executed.
        assert wait_for(lambda: HEARD_OFF in sim.output_of(mux), 30), sim.output_of(mux)
        assert _publish_until(auto, _twist(0.3), lambda: any(m.linear.x > 0.0 for _, m in executed.messages), 2.0), (
            "the state heard again, the commands did not drive within 2 s"
        )
    finally:
        sim.stop(gui)
        sim.stop(mux)
        auto.unregister()
        executed.close()


def test_the_mux_deadman_survives_its_wall_clock_stepping_back_30_s(sim, rospy_node, tmp_path):
    from geometry_msgs.msg import Twist
    from std_msgs.msg import String

    step_file = tmp_path / "clock_stepped"
    env = {
        "PYTHONPATH": os.path.join(HERE, "clock_step") + os.pathsep + os.environ.get("PYTHONPATH", ""),
        "CPS_TEST_CLOCK_STEP_FILE": str(step_file),
        "CPS_TEST_CLOCK_STEP_S": "-30",
    }
    executed = TopicRecorder(names.absolute(names.robot_topic("jackal", names.CMD_VEL)), Twist)
    teleop = rospy_node.Publisher(
        names.absolute(names.robot_topic("jackal", names.CMD_VEL_TELEOP)), Twist, queue_size=5
    )
    mode = rospy_node.Publisher(
        names.absolute(names.robot_topic("jackal", names.CONTROL_MODE)), String, queue_size=1, latch=True
    )
    gui = _start_gui(sim, "off")
    mux = _start_mux(sim, env=env)
    try:
        assert wait_for(lambda: HEARD_OFF in sim.output_of(mux), 30), sim.output_of(mux)
        mode.publish(String("teleop"))
        assert wait_for(lambda: "control mode teleop" in sim.output_of(mux), 10), sim.output_of(mux)
        # 5 Hz commands, well inside the 0.5 s dead-man: a mux on the wall clock would drop to zero
        # between commands after each step (age < 0 after a step back, > 30 s after a step forward).
        assert _publish_until(
            teleop, _twist(0.3), lambda: executed.latest is not None and executed.latest.linear.x > 0.0, 1.0, 5.0
        ), "teleop commands not obeyed within 1 s"
        executed.take()
        for _ in range(3):
            for step in (step_file.write_text, lambda _: step_file.unlink()):
                teleop.publish(_twist(0.3))
                time.sleep(0.1)
                step("")  # mid-way between two commands
                time.sleep(0.1)
                _publish_for(teleop, _twist(0.3), seconds=0.6, rate_hz=5.0)
        # The last command went at most 0.2 s before this; what the mux sent after it may be its
        # dead-man's zero, rightly, once this process is slow to read it (final103, a full run:
        # "zero at [4.8] s", the sequence's end).
        commands_end_s = time.monotonic()
        taken = [(t, m) for t, m in executed.take() if t <= commands_end_s]
        # When a zero came (s after the first output), to tell a late command from a missed step.
        zeros = [round(t - taken[0][0], 2) for t, m in taken if not m.linear.x > 0.0]
        assert len(taken) > 60 and not zeros, f"{len(taken)} outputs, zero at {zeros} s after the first"
        step_file.write_text("")  # the operator link goes; the wall clock steps back
        stepped_at = time.monotonic()
        assert wait_for(lambda: executed.latest is not None and executed.latest.linear.x == 0.0, 5)
        stopped_after_s = time.monotonic() - stepped_at
        assert stopped_after_s < 2.0, stopped_after_s  # dead-man 0.5 s; a wall-clock mux: ~30 s
        executed.take()
        time.sleep(1.0)
        outputs = [m.linear.x for _, m in executed.take()]
        assert len(outputs) > 5 and all(vx == 0.0 for vx in outputs)  # alive, and stays stopped
        assert mux.poll() is None
    finally:
        sim.stop(gui)
        sim.stop(mux)
        teleop.unregister()
        mode.unregister()
        executed.close()
