"""Two ROS masters on loopback joined only by the two Zenoh bridges (mutual TLS): clouds and
telemetry cross one way, commands the other; link health; latched re-send after a bridge restart;
bad frames from a keyed peer (corrupt, mistyped, for another topic) are counted, never delivered,
duplicates delivered once."""

import json
import math
import os
import pathlib
import re
import subprocess
import sys
import time

import pytest

from cps_fleet import names
from cps_harness.testing import TopicRecorder, wait_for
from cps_link.bridge_config import load_bridge_table, other_side
from cps_link.bridge_wire import Frame, encode
from cps_link.zenoh_session import MAKE_CERTS, bridge_argv, session_config
from cps_ros.processes import find_node, free_port

pytestmark = pytest.mark.waiting

HERE = os.path.dirname(os.path.abspath(__file__))
CLOUD_LOAD = find_node("cps_harness", "cloud_load")
ROBOT = "scout"


@pytest.fixture(scope="module")
def cert_dir(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("certs") / "certs")
    subprocess.run([MAKE_CERTS, path], check=True, capture_output=True)
    return path


def _diag_counter(recorder, key):
    """`key` in the twin bridge's newest own status (other statuses, its ledger's included, come between)."""
    with recorder._cond:
        messages = list(recorder.messages)
    for _, msg in reversed(messages):
        for status in msg.status:
            if status.name == "/zenoh_bridge_twin":
                return int({kv.key: kv.value for kv in status.values}.get(key, 0))
    return 0


@pytest.mark.timeout(120)
def test_two_masters_joined_only_by_the_bridges(rospy_node, ros, robots_graph, cert_dir, tmp_path, request):
    from diagnostic_msgs.msg import DiagnosticArray
    from std_msgs.msg import Bool
    from tf2_msgs.msg import TFMessage

    from cps_msgs.msg import CompressedPointCloud2, LinkState

    port = free_port()
    ros.popen(bridge_argv(sys.executable, "twin", "127.0.0.1", [ROBOT], cert_dir, port), name="bridge_twin")
    robots_bridge = robots_graph.popen(
        bridge_argv(sys.executable, "robots", "127.0.0.1", [ROBOT], cert_dir, port), name="bridge_robots"
    )
    link = TopicRecorder(names.absolute(names.LINK_STATE), LinkState)
    clouds = TopicRecorder(names.absolute(names.managed_cloud_at_twin(ROBOT)), CompressedPointCloud2)
    diagnostics = TopicRecorder(names.DIAGNOSTICS, DiagnosticArray)
    estop = rospy_node.Publisher(names.ESTOP, Bool, queue_size=1, latch=True)
    # This process's master serves later tests too: a latched e-stop left behind would hold their robots.
    for done in (estop.unregister, link.close, clouds.close, diagnostics.close):
        request.addfinalizer(done)
    estop.publish(Bool(True))
    link.wait(lambda m: m.up, timeout_s=20, what="the link up")

    # A cloud crosses robots -> twin, byte for byte, under the contract's twin-side name.
    robots_graph.popen(
        [
            sys.executable,
            CLOUD_LOAD,
            f"{ROBOT}:20000:5",
            f"{names.absolute(names.robot_topic(ROBOT, names.POINTS_DRACO))}:={names.absolute(names.managed_cloud(ROBOT))}",
        ],
        name="load",
    )
    cloud = clouds.wait(timeout_s=20, what="a cloud across the bridge")
    assert 18000 <= len(cloud.compressed_data) <= 22000

    # A teleop command crosses twin -> robots.
    received = str(tmp_path / "teleop.txt")
    robots_graph.popen(
        [sys.executable, find_node("cps_harness", "teleop_probe"), "recv", ROBOT, received], name="teleop_recv"
    )
    ros.popen([sys.executable, find_node("cps_harness", "teleop_probe"), "send", ROBOT, "20"], name="teleop_send")
    assert wait_for(lambda: os.path.exists(received) and os.path.getsize(received) > 0, timeout_s=20), (
        "no teleop command reached the robots' master"
    )

    # The latched e-stop reached the robots' side.
    echo = subprocess.run(
        ["rostopic", "echo", "-n", "1", names.ESTOP],
        env=robots_graph.env,
        capture_output=True,
        text=True,
        timeout=20,
    )
    assert "data: True" in echo.stdout, echo.stderr

    # The robots' bridge dies: the twin knows within a second (lease 600 ms; margin for a loaded
    # machine), by its own stamp of the change against the bridge's exit. (Timed from before the
    # stop, as it was, the bound also held the robots' bridge's own shutdown: final20 read 2.7 s.)
    t_stop = time.time()
    robots_graph.stop(robots_bridge)
    gone_s = time.time()
    down = link.wait(lambda m: not m.up, timeout_s=5, what="the link down")
    known_after_s = down.since.to_sec() - gone_s
    assert known_after_s < 1.5 and down.outages == 1, (known_after_s, f"the stop took {gone_s - t_stop:.2f} s")
    # A restarted bridge (new session) comes back, and the latched e-stop is there again at once.
    robots_graph.popen(
        bridge_argv(sys.executable, "robots", "127.0.0.1", [ROBOT], cert_dir, port), name="bridge_robots"
    )
    up = link.wait(lambda m: m.up, timeout_s=20, what="the link up again")
    assert up.last_outage_s > 0
    echo = subprocess.run(
        ["rostopic", "echo", "-n", "1", names.ESTOP],
        env=robots_graph.env,
        capture_output=True,
        text=True,
        timeout=20,
    )
    assert "data: True" in echo.stdout, echo.stderr

    # A keyed peer sends a corrupt frame, a wrong md5 and a duplicate: counted, never delivered.
    import zenoh

    table = load_bridge_table(robots=[ROBOT])
    config = session_config(table, "robots", "127.0.0.1", cert_dir)
    config["connect"]["endpoints"] = [f"tls/127.0.0.1:{port}"]
    with zenoh.open(zenoh.Config.from_json5(json.dumps(config))) as session:
        to = names.absolute(names.managed_cloud_at_twin(ROBOT))
        key = f"cps/topic{to}"

        def intact():
            """The intact frame, stamped now: a cloud's frame older than its route's max_age_s (2 s)
            is dropped as stale (final59: stamped before the corrupt frame's retries, it was, its
            copy then counted as a duplicate, and nothing was delivered)."""
            return encode(
                Frame(
                    b"i" * 16,
                    1,
                    time.time(),
                    "cps_msgs/CompressedPointCloud2",
                    CompressedPointCloud2._md5sum,
                    "/intruder",
                    bytes(cloud_bytes(cloud)),
                    topic=to,
                )
            )

        def put(payload):
            # Zenoh's put drops by default when its queue is not served within a millisecond: on a
            # loaded machine (CI, beside busy loops) the two 18 kB frames and the one after them were
            # dropped in the keyed peer itself while the 165 B one before them reached the twin (its
            # log, 3 of 8 runs). The bridges' own publishers of these routes block; so does this peer.
            session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

        # A new peer's puts reach the twin bridge only once its subscription has been matched: a
        # corrupt frame (rejected at the CRC, before any sequence state) is re-sent until counted.
        assert wait_for(
            lambda: put(intact()[:-3] + b"xyz") or _diag_counter(diagnostics, "corrupt") >= 1,
            timeout_s=20,
            poll_s=1.0,
        ), "the keyed peer's corrupt frame was never counted"
        put(
            encode(
                Frame(b"i" * 16, 2, math.nan, "cps_msgs/CompressedPointCloud2", "0" * 32, "/intruder", b"", topic=to)
            ),
        )
        good = intact()
        put(good)
        put(good)
        # A well-formed frame for another topic under the cloud's key (issue 22): never published there.
        put(
            encode(
                Frame(
                    b"i" * 16,
                    3,
                    math.nan,
                    "tf2_msgs/TFMessage",
                    TFMessage._md5sum,
                    "/intruder",
                    b"\x00\x00\x00\x00",
                    topic=names.TF,
                )
            ),
        )
        counted = ("corrupt", "type_mismatch", "duplicates", "drop_wrong_topic")
        assert wait_for(lambda: all(_diag_counter(diagnostics, k) >= 1 for k in counted), timeout_s=10), {
            k: _diag_counter(diagnostics, k) for k in counted
        }
        # The intact frame is delivered once; its duplicate, the corrupt and the mistyped one never.
        assert wait_for(lambda: _intruder_checks(clouds), timeout_s=10), (
            f"the intact frame was not delivered (stale: {_diag_counter(diagnostics, 'stale')})"
        )
    # Its duplicate was counted above (dropped, never published), so one stays one.
    assert _intruder_checks(clouds) == 1


def _intruder_checks(clouds):
    with clouds._cond:
        return sum(1 for _, m in clouds.messages if m.header.frame_id == "intruder-check")


def cloud_bytes(received):
    import copy
    import io

    cloud = copy.deepcopy(received)
    cloud.header.frame_id = "intruder-check"
    cloud.header.stamp.secs = int(time.time())
    buff = io.BytesIO()
    cloud.serialize(buff)
    return buff.getvalue()


@pytest.mark.parametrize("side", ["twin", "robots"])
@pytest.mark.timeout(90)
def test_a_session_that_carries_one_way_only_is_reopened(side, rospy_node, ros, robots_graph, cert_dir, tmp_path):
    """The state seen after outages (demo_repeat run 4, CI's link cut): the other side's token is
    there, its heartbeats never come. A peer that holds the token and sends no heartbeat makes the
    bridge close its session and open a new one (its token goes and comes back) after bridge.yaml's
    reopen_after_ms; so does, on the robots' side, a twin whose heartbeats come but that echoes
    none of the robots' (after unheard_after_ms). Once the peer's heartbeats (and echoes) come, the link is up and stays up."""
    import zenoh

    from cps_msgs.msg import LinkState

    port = free_port()
    # bridge.yaml with a 2 s deaf and 1 s unheard reopen (5 s and 2 s in the fleet's): the rules are
    # the same, the test shorter
    default = load_bridge_table(robots=[ROBOT])
    path = tmp_path / "bridge.yaml"
    text = re.sub(r"(?m)^reopen_after_ms: \d+$", "reopen_after_ms: 2000", pathlib.Path(default.path).read_text())
    path.write_text(re.sub(r"(?m)^unheard_after_ms: \d+$", "unheard_after_ms: 1000", text))
    table = load_bridge_table(str(path), robots=[ROBOT])
    assert (table.reopen_after_ms, table.unheard_after_ms) == (2000, 1000)
    graph = ros if side == "twin" else robots_graph
    argv = bridge_argv(sys.executable, side, "127.0.0.1", [ROBOT], cert_dir, port) + ["--table", str(path)]
    graph.popen(argv, name=f"bridge_{side}")
    peer = other_side(side)
    config = session_config(table, peer, "127.0.0.1", cert_dir)
    endpoint = f"tls/127.0.0.1:{port}"
    config["listen" if peer == "twin" else "connect"]["endpoints"] = [endpoint]
    tokens = []  # (monotonic s, kind) of the bridge's liveliness token, as the peer sees it
    with zenoh.open(zenoh.Config.from_json5(json.dumps(config))) as session:
        watch = session.liveliness().declare_subscriber(
            table.liveliness_key(side, side), lambda s: tokens.append((time.monotonic(), str(s.kind))), history=True
        )
        token = session.liveliness().declare_token(table.liveliness_key(peer, peer))
        assert wait_for(lambda: any("PUT" in k for _, k in tokens), timeout_s=30), "the bridge never came up"
        first_s = next(t for t, k in tokens if "PUT" in k)
        # No heartbeat from the peer: the bridge closes its session (its token goes) and opens another.
        assert wait_for(lambda: sum("PUT" in k for _, k in tokens) >= 2, timeout_s=30), f"never reopened: {tokens}"
        gone_s = next(t for t, k in tokens if "DELETE" in k)
        # (the robots' bridge, up on the twin's token, finds it unheard before it finds it deaf)
        reopen_s = (table.reopen_after_ms if side == "twin" else table.unheard_after_ms) / 1000.0
        assert reopen_s <= gone_s - first_s < reopen_s + 5.0, tokens
        heartbeat = session.declare_publisher(table.heartbeat_key(peer, peer))

        def beat_for(seconds):
            start_s = time.monotonic()
            while time.monotonic() - start_s < seconds:
                heartbeat.put(b"")
                time.sleep(table.heartbeat_ms / 1000.0)

        if side == "robots":
            # The other way round: the twin's heartbeats come, the robots' never come back as its
            # echoes (the twin does not hear them). The robots' bridge reopens too.
            seen = len(tokens)
            beat_for(reopen_s + 5.0)
            assert len(tokens) >= seen + 2, f"never reopened while unheard: {tokens[seen:]}"
            # the twin echoes every robots' heartbeat from now on, as the twin's bridge does
            echoes = {}

            def echo(sample):
                name = str(sample.key_expr).rsplit("/", 1)[-1]
                if name not in echoes:
                    echoes[name] = session.declare_publisher(table.echo_key(name))
                echoes[name].put(sample.payload.to_bytes())

            echo_sub = session.declare_subscriber(table.peer_heartbeat_keys("twin"), echo)
            beat_for(1.5)  # a reopen decided before the first echo came finishes
            assert wait_for(lambda: "PUT" in tokens[-1][1], timeout_s=10), tokens
        # The peer's heartbeats come (and its echoes): the link is up on the bridge's side and no
        # more reopens follow.
        state = []
        sub = (
            rospy_node.Subscriber(names.LINK_STATE, LinkState, lambda m: state.append(m.up)) if side == "twin" else None
        )
        seen = len(tokens)
        beat_for(reopen_s + 2.0)
        said = "\n".join(graph.output(f"bridge_{side}").splitlines()[-40:])  # the bridge's last lines
        assert len(tokens) == seen, f"reopened although heartbeats came: {tokens[seen:]}\n{said}"
        if sub is not None:
            sub.unregister()
            assert state and state[-1], f"the twin's link state is not up with the peer's heartbeats: {state}\n{said}"
        else:
            echo_sub.undeclare()
        token.undeclare()
        watch.undeclare()
