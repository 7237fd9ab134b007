"""One fleet_control process drives several robots on a real master: their routes, each robot's
teleop reaching its own cmd_vel, a NaN for one robot refused without touching the other, and the
fleet's e-stop stopping both."""

import pytest

from cps_fleet import names
from cps_harness.testing import TopicRecorder, wait_for

pytestmark = pytest.mark.ros
SIMULATED = ("jackal", "champ")
# scout and iris are not simulated: their routes wait for tf, their muxes still serve teleop.
ROBOTS = SIMULATED + ("scout", "iris")


def _twist(x):
    from geometry_msgs.msg import Twist

    msg = Twist()
    msg.linear.x = x
    return msg


@pytest.fixture
def fleet(ros, rospy_node):
    from geometry_msgs.msg import Twist
    from std_msgs.msg import Bool, String

    # Latched before the nodes start, as the bringup's keeper does: every robot must hear it.
    estop = rospy_node.Publisher(names.ESTOP, Bool, queue_size=1, latch=True)
    estop.publish(Bool(False))
    ros.start_node(
        "cps_sim",
        "fleet_sim",
        name="fleet_sim_fc",
        params={"~profile": "light", "~robots": ",".join(SIMULATED), "~sensor_workers": 0},
    )
    ros.start_node("cps_sim", "fleet_control", name="fleet_control", params={"~robots": ",".join(ROBOTS)})
    io = {
        "executed": {r: TopicRecorder(names.absolute(names.robot_topic(r, names.CMD_VEL)), Twist) for r in ROBOTS},
        "state": {r: TopicRecorder(names.absolute(names.robot_topic(r, names.MISSION_STATE)), String) for r in ROBOTS},
        "active": {
            r: TopicRecorder(names.absolute(names.robot_topic(r, names.CONTROL_MODE_ACTIVE)), String) for r in ROBOTS
        },
        "mode": {
            r: rospy_node.Publisher(
                names.absolute(names.robot_topic(r, names.CONTROL_MODE)), String, queue_size=1, latch=True
            )
            for r in ROBOTS
        },
        "teleop": {
            r: rospy_node.Publisher(names.absolute(names.robot_topic(r, names.CMD_VEL_TELEOP)), Twist, queue_size=5)
            for r in ROBOTS
        },
        "estop": estop,
    }
    try:
        yield io
    finally:
        for group in ("executed", "state", "active"):
            for recorder in io[group].values():
                recorder.close()
        for group in ("mode", "teleop"):
            for pub in io[group].values():
                pub.unregister()
        io["estop"].unregister()


def test_one_process_drives_two_robots_isolates_a_nan_and_the_estop_stops_both(fleet, ros, rospy_node):
    import rosnode
    from std_msgs.msg import Bool, String

    for r in SIMULATED:  # both routes followed from this one process
        fleet["state"][r].wait(lambda m: m.data in ("transit", "inspecting"), timeout_s=45, what=f"{r}'s route")
    for r in ROBOTS:  # the latched e-stop state reaches every robot's mux
        assert wait_for(lambda r=r: f"velocity_mux {r}: e-stop state heard (off)" in ros.output("fleet_control"), 5)
    nodes = rosnode.get_node_names()
    assert "/fleet_control" in nodes and not [n for n in nodes if "velocity_mux" in n or "route_controller" in n]

    for r in ROBOTS:
        fleet["mode"][r].publish(String("teleop"))
        fleet["active"][r].wait(lambda m: m.data == "teleop", timeout_s=10, what=f"{r}'s mux in teleop")
    speeds = {"jackal": 0.3, "champ": 0.2, "scout": 0.25, "iris": 0.35}
    rate = rospy_node.Rate(10)

    def send(overrides=None, n=10):
        for _ in range(n):
            for r in ROBOTS:
                fleet["teleop"][r].publish(_twist((overrides or {}).get(r, speeds[r])))
            rate.sleep()

    send()
    for r in ROBOTS:  # each robot's command reaches its own cmd_vel
        fleet["executed"][r].wait(
            lambda m, r=r: m.linear.x == pytest.approx(speeds[r], abs=0.02), timeout_s=2, what=f"{r}'s teleop executed"
        )

    send({"jackal": float("nan")}, n=5)
    fleet["executed"]["jackal"].wait(lambda m: m.linear.x == 0.0, timeout_s=2, what="jackal holding after a NaN")
    dropped = "{}: dropped".format
    jackal_teleop, champ_teleop = (
        names.absolute(names.robot_topic(r, names.CMD_VEL_TELEOP)) for r in ("jackal", "champ")
    )
    assert wait_for(lambda: dropped(jackal_teleop) in ros.output("fleet_control"), 5), ros.output("fleet_control")[
        -2000:
    ]
    assert dropped(champ_teleop) not in ros.output("fleet_control")
    assert fleet["executed"]["champ"].latest.linear.x == pytest.approx(speeds["champ"], abs=0.02)

    send(n=3)
    fleet["estop"].publish(Bool(True))
    send(n=5)
    for r in ROBOTS:
        fleet["executed"][r].wait(lambda m: m.linear.x == 0.0, timeout_s=2, what=f"the e-stop stopping {r}")
    fleet["estop"].publish(Bool(False))
