"""A rogue host on the same segment as the robots and the twin, without the fleet's keys: it
cannot publish a command that a robot executes, cannot read any cloud, and cannot reach either
ROS master, while the fleet's own bridges carry clouds and commands. Over real namespaces."""

import json
import os
import subprocess
import sys
import time

import pytest

from cps_fleet import names
from cps_harness.netns_lan import SharedLan
from cps_harness.port_scan import listening_ports, scan_argv
from cps_harness.testing import link_name, wait_for
from cps_link import netns_link
from cps_link.bridge_config import load_bridge_table
from cps_link.host_guard import guard_argv
from cps_link.zenoh_session import MAKE_CERTS, bridge_argv
from cps_ros.processes import RosGraph, find_node

LINK = link_name("zr")

pytestmark = [pytest.mark.ros, pytest.mark.slow]
HERE = os.path.dirname(os.path.abspath(__file__))
CLOUD_LOAD = find_node("cps_harness", "cloud_load")
HOSTS = {"phys": "10.203.0.1", "twin": "10.203.0.2", "rogue": "10.203.0.3"}
PORTS = {"main": 7447, "command": 7448}  # each lane's port (bridge.yaml's endpoint_port, command_port)
# the host where each lane listens (bridge_config: the twin's the main lane, the robots' the command lane)
LISTENER = {lane: netns_link.host_of(load_bridge_table().for_lane(lane).listening_side) for lane in PORTS}
ROBOT = "scout"


def _scan(lan, host):
    """The listening ports of `host` that a connect from the rogue host reaches."""
    listening = listening_ports(lan.namespace(host))
    out = subprocess.run(
        lan.argv("rogue", scan_argv(sys.executable, HOSTS[host], listening)),
        check=True,
        capture_output=True,
        text=True,
        timeout=30,
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def _lines(path):
    return open(path).read().split("\n") if os.path.exists(path) else []


@pytest.mark.skipif(netns_link.capability_problem() is not None, reason=f"{netns_link.capability_problem()}")
@pytest.mark.timeout(240)
def test_a_rogue_host_gets_nothing_in_and_nothing_out(tmp_path):
    from cps_bringup.link import InNamespace

    fleet_certs, rogue_certs = str(tmp_path / "fleet"), str(tmp_path / "rogue")
    for path in (fleet_certs, rogue_certs):
        subprocess.run(
            [MAKE_CERTS, path, "--san", f"IP:{HOSTS['twin']}", "--san", f"IP:{HOSTS['phys']}"],
            check=True,
            capture_output=True,
        )
    teleop_file, cloud_file = str(tmp_path / "teleop.txt"), str(tmp_path / "clouds.txt")
    with SharedLan(LINK, HOSTS) as lan:
        robots = InNamespace(RosGraph(host_ip="127.0.0.1"), f"/var/run/netns/{lan.namespace('phys')}")
        twin = InNamespace(RosGraph(host_ip="127.0.0.1"), f"/var/run/netns/{lan.namespace('twin')}")
        try:
            robots.start()
            twin.start()
            for lane, port in PORTS.items():
                for graph, side, name in ((twin, "twin", f"bt_{lane}"), (robots, "robots", f"br_{lane}")):
                    argv = bridge_argv(
                        sys.executable,
                        side,
                        HOSTS["twin"],
                        [ROBOT],
                        fleet_certs,
                        port,
                        lane=lane,
                        robots_address=HOSTS["phys"],
                    )
                    graph.popen(argv, name=name)
            robots.popen(
                [
                    sys.executable,
                    CLOUD_LOAD,
                    f"{ROBOT}:20000:5",
                    f"{names.absolute(names.robot_topic(ROBOT, names.POINTS_DRACO))}:={names.absolute(names.managed_cloud(ROBOT))}",
                ],
                name="load",
            )
            robots.popen(
                [sys.executable, find_node("cps_harness", "teleop_probe"), "recv", ROBOT, teleop_file],
                name="teleop_recv",
            )
            twin.popen(
                [
                    sys.executable,
                    find_node("cps_harness", "link_recorder"),
                    cloud_file,
                    ROBOT,
                    f"{names.absolute(names.managed_cloud(ROBOT))}:={names.absolute(names.managed_cloud_at_twin(ROBOT))}",
                ],
                name="recorder",
            )
            sender = twin.popen(
                [sys.executable, find_node("cps_harness", "teleop_probe"), "send", ROBOT, "10"],
                name="teleop_send",
            )
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and not (len(_lines(teleop_file)) > 3 and len(_lines(cloud_file)) > 3):
                time.sleep(0.5)
            assert len(_lines(teleop_file)) > 3, (
                "the fleet's own teleop did not cross:\n" + twin.output("bt_command")[-2000:]
            )
            assert len(_lines(cloud_file)) > 3, (
                "the fleet's own clouds did not cross:\n" + robots.output("br_main")[-2000:]
            )
            twin.stop(sender)

            # Both lanes' ports at once, the command lane's above all.
            rogues = {
                lane: subprocess.Popen(
                    lan.argv(
                        "rogue",
                        [
                            sys.executable,
                            find_node("cps_harness", "rogue"),
                            HOSTS[LISTENER[lane]],
                            str(port),
                            rogue_certs,
                            os.path.join(fleet_certs, "ca.pem"),
                            f"{HOSTS['phys']}:{robots.port}",
                            f"{HOSTS['twin']}:{twin.port}",
                            f"{HOSTS['twin']}:11311",
                        ],
                    ),
                    stdout=subprocess.PIPE,
                    stderr=subprocess.PIPE,
                    text=True,
                )
                for lane, port in PORTS.items()
            }
            try:
                said = {lane: rogue.communicate(timeout=120) for lane, rogue in rogues.items()}
            finally:
                for rogue in rogues.values():
                    rogue.kill()
                    rogue.wait()
            for lane, (stdout, stderr) in said.items():
                assert rogues[lane].returncode == 0, stderr[-3000:]
                results = json.loads(stdout.strip().splitlines()[-1])
                print(lane, json.dumps(results, indent=1))
                for name in ("plain_tcp", "tls_own_ca", "tls_fleet_ca_own_cert", "tls_fleet_ca_no_cert"):
                    attempt = results[name]
                    assert attempt["read"] == 0, f"{lane} lane, {name}: the rogue read {attempt['read']} samples"
                    assert attempt.get("peers", 0) == 0, f"{lane} lane, {name}: the rogue joined the session"
                assert all(code != 0 for code in results["masters"].values()), results["masters"]
            time.sleep(1.0)
            executed = [line for line in _lines(teleop_file) if line.endswith(" 12345.000000")]
            assert not executed, f"a rogue command reached the robot: {executed}"
            # The fleet's own path still works after the attempts.
            assert len(_lines(cloud_file)) > 3

            # One open port per host (issue 38). Unguarded, the rogue reaches ports beyond the link's
            # (roscpp's XML-RPC servers bind 0.0.0.0 whatever ROS_IP says: rosout's on both hosts).
            before = {host: _scan(lan, host) for host in ("phys", "twin")}
            listens = {
                host: [port for lane, port in PORTS.items() if LISTENER[lane] == host] for host in ("phys", "twin")
            }
            assert any(set(found) - set(listens[host]) for host, found in before.items()), before
            for host, peer in (("phys", "twin"), ("twin", "phys")):
                for argv in guard_argv(lan.namespace(host), listens[host], HOSTS[peer], listens[peer]):
                    subprocess.run(argv, check=True)
            after = {host: _scan(lan, host) for host in ("phys", "twin")}
            print("open from the rogue host, unguarded:", before, "guarded:", after)
            assert after == {"phys": [PORTS["command"]], "twin": [PORTS["main"]]}, (before, after)
            # and the fleet's connections, made before the guard, still carry clouds
            carried = len(_lines(cloud_file))
            assert wait_for(lambda: len(_lines(cloud_file)) > carried, 10.0), "no cloud crossed after the guard"
        finally:
            robots.close()
            twin.close()
    assert not any(ns.startswith(f"{LINK}_") for ns in netns_link.list_namespaces())
