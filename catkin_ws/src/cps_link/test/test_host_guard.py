"""The host guard: from the other host only a host's own link listener answers (the twin's main
lane, the robots' command lane) and each reaches the other's only, over a real link's two
namespaces; its rules and its refusals."""

import json
import socket
import subprocess
import sys

import pytest

from cps_harness.port_scan import scan_argv
from cps_harness.testing import link_name
from cps_link import netns_link
from cps_link.host_guard import GUARD_PRIORITY, guard_argv, guard_rules
from cps_link.netns_link import PHYS_IP, TWIN_IP, ShapedLink, guard_hosts, namespace, netns_argv

MAIN_PORT, COMMAND_PORT = 7447, 7448  # the twin listens at the first, the robots at the second
LISTEN = {"twin": (MAIN_PORT,), "phys": (COMMAND_PORT,)}
OTHER_PORT = 41035  # a roscpp XML-RPC server's kind of port, on 0.0.0.0


def test_a_host_answers_from_its_listener_and_reaches_only_the_others():
    twin = guard_rules([MAIN_PORT, MAIN_PORT], PHYS_IP, [COMMAND_PORT])
    allow = ["priority", str(GUARD_PRIORITY)]
    assert twin[:2] == [
        [*allow, "ipproto", "tcp", "sport", "7447", "lookup", "main"],
        [*allow, "to", f"{PHYS_IP}/32", "ipproto", "tcp", "dport", "7448", "lookup", "main"],
    ]
    robots = guard_rules([COMMAND_PORT], TWIN_IP, [MAIN_PORT])
    assert robots[:2] == [
        [*allow, "ipproto", "tcp", "sport", "7448", "lookup", "main"],
        [*allow, "to", f"{TWIN_IP}/32", "ipproto", "tcp", "dport", "7447", "lookup", "main"],
    ]
    # a host with no listener of its own (one lane, the twin listening) only connects
    assert guard_rules([], TWIN_IP, [MAIN_PORT])[0] == [
        *allow,
        "to",
        f"{TWIN_IP}/32",
        "ipproto",
        "tcp",
        "dport",
        "7447",
    ] + [
        "lookup",
        "main",
    ]
    for rules in (twin, robots):  # then every other TCP and UDP packet leaving the host
        assert rules[-2:] == [
            ["priority", str(GUARD_PRIORITY + 1), "ipproto", "tcp", "prohibit"],
            ["priority", str(GUARD_PRIORITY + 1), "ipproto", "udp", "prohibit"],
        ]


@pytest.mark.parametrize(
    "listen, peer, match",
    [
        ([], [], "needs a link port"),
        ([0], [MAIN_PORT], "listening ports"),
        ([MAIN_PORT], [70000], "the peer's ports"),
    ],
)
def test_bad_guard_arguments_are_refused(listen, peer, match):
    with pytest.raises(ValueError, match=match):
        guard_rules(listen, TWIN_IP, peer)


def _listen(name, side, ports):
    """A process in `side`'s namespace listening on `ports` on every address until killed."""
    code = (
        "import socket, sys, time\n"
        "held = []\n"
        "for p in sys.argv[1:]:\n"
        "    s = socket.socket(); s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)\n"
        "    s.bind(('0.0.0.0', int(p))); s.listen(8); held.append(s)\n"
        "print('up', flush=True)\n"
        "import signal\n"
        "signal.pause()  # until the test kills it\n"
    )
    proc = subprocess.Popen(
        netns_argv(name, side, [sys.executable, "-c", code, *map(str, ports)]), stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout.readline().strip() == "up"
    return proc


def _open_from(name, side, host, ports):
    out = subprocess.run(
        netns_argv(name, side, scan_argv(sys.executable, host, ports)), check=True, capture_output=True, text=True
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


@pytest.mark.skipif(netns_link.capability_problem() is not None, reason=f"{netns_link.capability_problem()}")
def test_guarded_hosts_answer_each_other_only_at_their_listeners():
    name = link_name("hg")
    with ShapedLink(name, rate="60mbit"):
        twin = _listen(name, "twin", (MAIN_PORT, OTHER_PORT))
        robots = _listen(name, "phys", (COMMAND_PORT, OTHER_PORT))
        try:
            # Unguarded, each host reaches every listener of the other.
            assert _open_from(name, "phys", TWIN_IP, (MAIN_PORT, OTHER_PORT)) == [MAIN_PORT, OTHER_PORT]
            assert _open_from(name, "twin", PHYS_IP, (COMMAND_PORT, OTHER_PORT)) == [COMMAND_PORT, OTHER_PORT]
            # The twin guarded alone: it answers the (unguarded) robots' host at its listener only,
            # and still reaches the robots' listener.
            for argv in guard_argv(namespace(name, "twin"), LISTEN["twin"], PHYS_IP, LISTEN["phys"]):
                subprocess.run(argv, check=True)
            assert _open_from(name, "phys", TWIN_IP, (MAIN_PORT, OTHER_PORT)) == [MAIN_PORT]
            assert _open_from(name, "twin", PHYS_IP, (COMMAND_PORT, OTHER_PORT)) == [COMMAND_PORT]
            # Both guarded (as bringup does): each answers at its own listener and reaches the other's.
            guard_hosts(name, LISTEN, sides=("phys",))
            assert _open_from(name, "twin", PHYS_IP, (COMMAND_PORT, OTHER_PORT)) == [COMMAND_PORT]
            assert _open_from(name, "phys", TWIN_IP, (MAIN_PORT, OTHER_PORT)) == [MAIN_PORT]
            # Loopback inside each host is untouched (each side's ROS graph lives there).
            assert _open_from(name, "twin", "127.0.0.1", (OTHER_PORT,)) == [OTHER_PORT]
            assert _open_from(name, "phys", "127.0.0.1", (OTHER_PORT,)) == [OTHER_PORT]
        finally:
            for proc in (twin, robots):
                proc.kill()
                proc.wait()
    assert not [ns for ns in netns_link.list_namespaces() if ns.startswith(f"{name}_")]


def test_the_scan_tells_open_from_closed():
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    port = server.getsockname()[1]
    closed = socket.socket()
    closed.bind(("127.0.0.1", 0))
    try:
        from cps_harness.port_scan import open_ports

        assert open_ports("127.0.0.1", [port, closed.getsockname()[1]]) == [port]
    finally:
        server.close()
        closed.close()
