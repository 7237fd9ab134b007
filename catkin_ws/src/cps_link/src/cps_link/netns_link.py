"""A real constrained link between a physical-twin host and a digital-twin host (the paper's Fig. 8).

Two network namespaces, `<name>_phys` (10.201.0.1) and `<name>_twin` (10.201.0.2), joined by a veth
pair whose both ends are shaped with a `tc` token bucket (tbf, default fleet.yaml's
`link.available_mbps`, the paper's measured Wi-Fi) and, if asked, delay/loss with netem. ROS processes started through `ShapedLink`
get ROS_IP and ROS_MASTER_URI of their side, so TCPROS really crosses the shaped link; iperf3
measures it as the paper did. All traffic stays inside the two namespaces; `down` (and leaving the
`ShapedLink` context, even on error) removes everything. Needs root and `ip netns`.

Topology "shared" (Wi-Fi airtime: both directions share ONE capacity) puts a router namespace
`<name>_rtr` between them: a bridge joins the two veth pairs, the ingress of both bridge ports is
redirected into one IFB device, and the one tbf (and netem) on that IFB shapes both directions.
"""

import contextlib
import json
import os
import re
import shutil
import subprocess
import time

from cps_fleet.fleet import ConfigError, load_fleet

PHYS_IP = "10.201.0.1"
TWIN_IP = "10.201.0.2"
PREFIX_LEN = 30
SIDES = ("phys", "twin")
ROUTER = "rtr"
TOPOLOGIES = ("duplex", "shared")
DEFAULT_QUEUE_MS = 50.0
_NAME = re.compile(r"^[a-z][a-z0-9]{0,9}$")
_RATE = re.compile(r"^(\d+(\.\d+)?)(bit|kbit|mbit|gbit)$")
_RATE_FACTOR = {"bit": 1.0, "kbit": 1e3, "mbit": 1e6, "gbit": 1e9}
NO_LINK_HINT = "run with --link none (plain loopback) instead"


class ClosingContext:
    """A context manager whose set-up, if it fails half-way, and whose end both call `close()`."""

    def _set_up_or_close(self, set_up):
        try:
            set_up()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc):
        self.close()


class LinkError(RuntimeError):
    """The link cannot be created, changed or measured; the message says why and what to do."""


def rate_bits_per_s(rate):
    """'60mbit' -> 6e7; LinkError for anything tc would not read the same way."""
    match = _RATE.match(str(rate).strip().lower())
    if not match:
        raise LinkError(f"rate '{rate}' is not a tc rate like 60mbit, 500kbit or 1gbit")
    value = float(match.group(1)) * _RATE_FACTOR[match.group(3)]
    if value <= 0:
        raise LinkError(f"rate '{rate}' must be > 0")
    return value


def tc_rate(mbps):
    """Mbit/s -> the tc rate that says the same, e.g. 60.0 -> '60mbit', 57.5 -> '57500kbit'."""
    kbit = round(float(mbps) * 1000)
    if kbit <= 0:
        raise LinkError(f"link rate must be > 0 Mbit/s, got {mbps}")
    return f"{kbit // 1000}mbit" if kbit % 1000 == 0 else f"{kbit}kbit"


def fleet_rate(fleet_file=None):
    """The configured link as a tc rate: fleet.yaml's `link.available_mbps`, the one home of that rate."""
    try:
        return tc_rate(load_fleet(fleet_file).link.available_mbps)
    except ConfigError as exc:
        raise LinkError(f"no link rate given and none from the fleet file: {exc}") from exc


# The kernel's bound on a TCP socket's unsent bytes (tcp_notsent_lowat), per network namespace.
UNSENT_SYSCTL = "net.ipv4.tcp_notsent_lowat"


def bridge_unsent_bytes():
    """The bound the bridge table (config/bridge.yaml `kernel_unsent_bytes`) asks of every host."""
    from cps_link.bridge_config import load_bridge_table

    try:
        return load_bridge_table().kernel_unsent_bytes
    except ConfigError as exc:
        raise LinkError(f"cannot read the bridge table for kernel_unsent_bytes: {exc}") from exc


def set_unsent_limit(ns, unsent_bytes):
    """At most `unsent_bytes` not yet sent in each TCP socket of namespace `ns` (0: leave it)."""
    if unsent_bytes:
        _run(["ip", "netns", "exec", ns, "sysctl", "-q", "-w", f"{UNSENT_SYSCTL}={int(unsent_bytes)}"])


def namespace(name, side):
    if side not in SIDES:
        raise LinkError(f"side must be one of {', '.join(SIDES)}, got '{side}'")
    return f"{name}_{side}"


def side_ip(side):
    return PHYS_IP if side == "phys" else TWIN_IP


def host_of(bridge_side):
    """The namespace side ("phys" or "twin") where a bridge side ("robots" or "twin") runs."""
    from cps_link.bridge_config import TWIN

    return "twin" if bridge_side == TWIN else "phys"


def _device(name, side):
    return f"{name}_{side[0]}"  # cps_p / cps_t: at most 12 characters (IFNAMSIZ 15)


def _check_name(name):
    if not _NAME.match(name or ""):
        raise LinkError(f"link name '{name}' must be 1-10 lowercase letters/digits, starting with a letter")


def _run(argv, check=True, timeout_s=20.0):
    proc = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, timeout=timeout_s)
    if check and proc.returncode != 0:
        raise LinkError(f"`{' '.join(argv)}` failed ({proc.returncode}): {proc.stderr.strip() or proc.stdout.strip()}")
    return proc


def check_capability():
    """LinkError naming what is missing unless we are root with ip, tc and network namespaces."""
    if os.geteuid() != 0:
        raise LinkError(f"the shaped link needs root (network namespaces and tc); {NO_LINK_HINT}")
    for tool in ("ip", "tc"):
        if shutil.which(tool) is None:
            raise LinkError(f"the shaped link needs `{tool}` (Debian package iproute2); {NO_LINK_HINT}")
    probe = f"cpsprobe{os.getpid() % 100000}"
    result = _run(["ip", "netns", "add", probe], check=False)
    if result.returncode != 0:
        raise LinkError(f"cannot create network namespaces ({result.stderr.strip()}); {NO_LINK_HINT}")
    _run(["ip", "netns", "del", probe], check=False)


def capability_problem():
    """Why this process cannot create the link (not root, no netns, no tc), or None (tests skip on it)."""
    try:
        check_capability()
    except LinkError as exc:
        return str(exc)
    return None


def list_namespaces():
    out = _run(["ip", "netns", "list"], check=False).stdout
    return [line.split()[0] for line in out.splitlines() if line.strip()]


def link_exists(name):
    present = list_namespaces()
    return any(ns in present for ns in (namespace(name, "phys"), namespace(name, "twin"), namespace_of_router(name)))


def _shape_commands(name, side, rate, delay_ms, loss_pct, queue_ms, verb, jitter_ms=0.0, with_netem=False):
    return _qdisc_commands(
        namespace(name, side), _device(name, side), rate, delay_ms, loss_pct, queue_ms, verb, jitter_ms, with_netem
    )


# Wi-Fi's WMM serves its voice access category ahead of best effort (DSCP 46, EF, maps to it); the
# command lane's packets carry it (bridge.yaml command_dscp). The shaper models the two queues under
# its one token bucket: an HTB child whose classes differ only in priority (no rate of their own:
# the tbf is the link), a u32 filter sending packets with that DSCP to the first. Handles:
_VOICE_HANDLE, _BEST_EFFORT_HANDLE = "21:", "22:"
_CLASSES_HANDLE = "20:"
_VOICE_CLASS, _BEST_EFFORT_CLASS = "20:1", "20:2"
# The voice queue holds this many packets (teleop and heartbeats are small and few).
VOICE_QUEUE_PACKETS = 100


# The shaper's token bucket: SHAPER_BURST_S of the rate (a Wi-Fi transmit opportunity's frames),
# at least SHAPER_BURST_FLOOR_BYTES (eleven full frames: with GSO off every packet is one). It was
# max(128 kB, 4 ms) for 64 kB GSO packets; at 5 Mbit/s that bucket is 0.2 s of the link passed at
# the sender's pace, which the link's estimate had to probe past with 384 kB trains that queued the
# operator's video ~250 ms behind them.
SHAPER_BURST_S = 0.004
SHAPER_BURST_FLOOR_BYTES = 16384


def shaper_burst_bytes(rate_bps):
    """The tbf burst at `rate_bps`, bytes."""
    return int(max(SHAPER_BURST_FLOOR_BYTES, rate_bps / 8 * SHAPER_BURST_S))


def best_effort_queue_bytes(rate_bps, queue_ms, burst_bytes):
    """The best-effort queue's limit: what tbf's own queue held at `queue_ms` (rate x latency +
    burst), so that the link's queue in time is what it was before the voice queue."""
    return int(rate_bps / 8 * queue_ms / 1000.0 + burst_bytes)


def _qdisc_commands(ns, dev, rate, delay_ms, loss_pct, queue_ms, verb, jitter_ms=0.0, with_netem=False, dscp=None):
    """tc commands shaping one device: tbf alone, or netem (delay/jitter/loss; always with
    `with_netem`, so that a live change can add them) with tbf as its child; under the tbf the voice
    and best-effort queues (`verb` add: made; change: the best-effort limit follows the rate)."""
    rate_bps = rate_bits_per_s(rate)
    burst_bytes = shaper_burst_bytes(rate_bps)
    tbf = ["tbf", "rate", rate, "burst", str(burst_bytes), "latency", f"{queue_ms:g}ms"]
    base = ["ip", "netns", "exec", ns, "tc", "qdisc", verb, "dev", dev]
    if delay_ms or loss_pct or with_netem:
        delay = ["delay", f"{delay_ms:g}ms"] + ([f"{jitter_ms:g}ms"] if jitter_ms else []) if delay_ms else []
        netem = ["netem", "limit", "10000"] + delay + ["loss", f"{loss_pct:g}%"]
        shaping, tbf_class = (
            [base + ["root", "handle", "1:"] + netem, base + ["parent", "1:", "handle", "10:"] + tbf],
            "10:1",
        )
    else:
        shaping, tbf_class = [base + ["root", "handle", "1:"] + tbf], "1:1"
    best_effort = ["bfifo", "limit", str(best_effort_queue_bytes(rate_bps, queue_ms, burst_bytes))]
    if verb != "add":
        return shaping + [base + ["parent", _BEST_EFFORT_CLASS, "handle", _BEST_EFFORT_HANDLE] + best_effort]
    if dscp is None:
        from cps_link.bridge_config import load_bridge_table

        dscp = load_bridge_table().command_dscp
    tc = ["ip", "netns", "exec", ns, "tc"]
    unlimited = ["htb", "rate", "10gbit", "quantum", "1514"]
    return shaping + [
        base + ["parent", tbf_class, "handle", _CLASSES_HANDLE, "htb", "default", "2"],
        tc + ["class", "add", "dev", dev, "parent", _CLASSES_HANDLE, "classid", _VOICE_CLASS, *unlimited, "prio", "0"],
        tc
        + [
            "class",
            "add",
            "dev",
            dev,
            "parent",
            _CLASSES_HANDLE,
            "classid",
            _BEST_EFFORT_CLASS,
            *unlimited,
            "prio",
            "1",
        ],
        base + ["parent", _VOICE_CLASS, "handle", _VOICE_HANDLE, "pfifo", "limit", str(VOICE_QUEUE_PACKETS)],
        base + ["parent", _BEST_EFFORT_CLASS, "handle", _BEST_EFFORT_HANDLE] + best_effort,
        tc
        + ["filter", "add", "dev", dev, "parent", _CLASSES_HANDLE, "protocol", "ip", "prio", "1", "u32"]
        + ["match", "ip", "dsfield", f"{dscp << 2:#04x}", "0xfc", "flowid", _VOICE_CLASS],
    ]


def _check_shaping_args(rate, delay_ms, loss_pct, queue_ms, jitter_ms=0.0):
    rate_bits_per_s(rate)
    if not 0 <= delay_ms <= 10000:
        raise LinkError(f"delay must be in [0, 10000] ms, got {delay_ms}")
    if not 0 <= jitter_ms <= delay_ms:
        raise LinkError(f"jitter must be in [0, delay {delay_ms:g}] ms, got {jitter_ms}")
    if not 0 <= loss_pct < 100:
        raise LinkError(f"loss must be in [0, 100) %, got {loss_pct}")
    if not 1 <= queue_ms <= 10000:
        raise LinkError(f"queue must be in [1, 10000] ms, got {queue_ms}")


def link_up(
    name="cps",
    rate=None,
    delay_ms=0.0,
    loss_pct=0.0,
    queue_ms=DEFAULT_QUEUE_MS,
    jitter_ms=0.0,
    topology="duplex",
    with_netem=False,
    unsent_bytes=None,
):
    """Create both namespaces, the veth pair, addresses, loopbacks and the shaping on both ends
    (`rate` None: fleet.yaml's link rate; topology "shared": see the module), and bound every TCP
    socket's unsent bytes in both (`unsent_bytes` None: the bridge table's, 0: the kernel's
    default, unbounded). Returns the rate."""
    _check_name(name)
    rate = rate or fleet_rate()
    _check_shaping_args(rate, delay_ms, loss_pct, queue_ms, jitter_ms)
    if topology not in TOPOLOGIES:
        raise LinkError(f"topology must be one of {', '.join(TOPOLOGIES)}, got '{topology}'")
    check_capability()
    if link_exists(name):
        raise LinkError(f"link '{name}' already exists; `cps_link down --name {name}` first")
    phys, twin = namespace(name, "phys"), namespace(name, "twin")
    try:
        _run(["ip", "netns", "add", phys])
        _run(["ip", "netns", "add", twin])
        if topology == "shared":
            _shared_medium(name)
        else:
            # Created inside phys directly, so the pair never appears in the caller's namespace.
            _run(
                [
                    "ip",
                    "-n",
                    phys,
                    "link",
                    "add",
                    _device(name, "phys"),
                    "type",
                    "veth",
                    "peer",
                    "name",
                    _device(name, "twin"),
                    "netns",
                    twin,
                ]
            )
        for side in SIDES:
            ns, dev = namespace(name, side), _device(name, side)
            _run(["ip", "-n", ns, "addr", "add", f"{side_ip(side)}/{PREFIX_LEN}", "dev", dev])
            _run(["ip", "-n", ns, "link", "set", "lo", "up"])
            _run(["ip", "-n", ns, "link", "set", dev, "up"])
            # One TCP segment per packet, as a radio sends frames: with GSO a sender's 64 kB packet
            # is one unit in the shaper's queue, 100 ms of a 5 Mbit/s link that a voice packet
            # (DSCP EF, the command lane) queued behind it waits out.
            _run(["ip", "-n", ns, "link", "set", "dev", dev, "gso_max_segs", "1"])
            set_unsent_limit(ns, bridge_unsent_bytes() if unsent_bytes is None else unsent_bytes)
        for ns, dev in shaped_devices(name):
            for cmd in _qdisc_commands(ns, dev, rate, delay_ms, loss_pct, queue_ms, "add", jitter_ms, with_netem):
                result = _run(cmd, check=False)
                if result.returncode != 0:
                    if "netem" in cmd and "unknown" in result.stderr.lower():
                        raise LinkError(
                            "this kernel has no netem qdisc (sch_netem), so --delay-ms/--loss-pct "
                            "cannot be applied; use the rate alone"
                        )
                    raise LinkError(f"`{' '.join(cmd)}` failed: {result.stderr.strip()}")
        _wait_until_up(name)
    except BaseException:
        link_down(name)
        raise
    return rate


def _router_device(name, side):
    return f"{name}_r{side[0]}"


def _ifb_device(name):
    return f"{name}_ifb"


def shared_medium(name):
    """True when link `name` has the router namespace of the shared topology."""
    return namespace_of_router(name) in list_namespaces()


def namespace_of_router(name):
    return f"{name}_{ROUTER}"


def shaped_devices(name):
    """(namespace, device) of every qdisc that shapes link `name`: both veth ends, or the one IFB."""
    if shared_medium(name):
        return [(namespace_of_router(name), _ifb_device(name))]
    return [(namespace(name, side), _device(name, side)) for side in SIDES]


def _shared_medium(name):
    """phys <-> bridge in the router namespace <-> twin; the ingress of both bridge ports goes
    through one IFB, where the shaping is."""
    rtr, bridge, ifb = namespace_of_router(name), f"{name}_br", _ifb_device(name)
    _run(["ip", "netns", "add", rtr])
    _run(["ip", "-n", rtr, "link", "add", bridge, "type", "bridge"])
    _run(["ip", "-n", rtr, "link", "add", ifb, "type", "ifb"])
    for side in SIDES:
        port = _router_device(name, side)
        _run(
            [
                "ip",
                "-n",
                rtr,
                "link",
                "add",
                port,
                "type",
                "veth",
                "peer",
                "name",
                _device(name, side),
                "netns",
                namespace(name, side),
            ]
        )
        _run(["ip", "-n", rtr, "link", "set", port, "master", bridge])
    for dev in ("lo", bridge, ifb, *(_router_device(name, side) for side in SIDES)):
        _run(["ip", "-n", rtr, "link", "set", dev, "up"])
    for side in SIDES:
        port = _router_device(name, side)
        _run(["ip", "netns", "exec", rtr, "tc", "qdisc", "add", "dev", port, "handle", "ffff:", "ingress"])
        _run(
            [
                "ip",
                "netns",
                "exec",
                rtr,
                "tc",
                "filter",
                "add",
                "dev",
                port,
                "parent",
                "ffff:",
                "protocol",
                "all",
                "u32",
                "match",
                "u32",
                "0",
                "0",
                "action",
                "mirred",
                "egress",
                "redirect",
                "dev",
                ifb,
            ]
        )


def _wait_until_up(name, timeout_s=5.0):
    deadline = time.monotonic() + timeout_s
    while True:
        states = [
            _run(
                ["ip", "-n", namespace(name, side), "-br", "link", "show", "dev", _device(name, side)], check=False
            ).stdout.split()
            for side in SIDES
        ]
        if all(len(s) > 1 and s[1] == "UP" for s in states):
            return
        if time.monotonic() > deadline:
            raise LinkError(f"the veth pair of link '{name}' did not come up: {states}")
        time.sleep(0.05)


def link_set(name="cps", rate=None, delay_ms=0.0, loss_pct=0.0, queue_ms=DEFAULT_QUEUE_MS, jitter_ms=0.0):
    """Change the shaping of both ends live (e.g. 60 -> 20 -> 60 Mbit/s; `rate` None: fleet.yaml's).
    Returns the rate."""
    _check_name(name)
    rate = rate or fleet_rate()
    _check_shaping_args(rate, delay_ms, loss_pct, queue_ms, jitter_ms)
    if not link_exists(name):
        raise LinkError(f"link '{name}' does not exist; `cps_link up --name {name}` first")
    for ns, dev in shaped_devices(name):
        with_netem = _has_netem(ns, dev)
        if (delay_ms or loss_pct) and not with_netem:
            raise LinkError(f"link '{name}' was created without netem; delay/loss need it from the start")
        # `change` keeps the queued packets; `replace` would drop them all at once and send every
        # TCP connection into retransmission back-off for seconds.
        for cmd in _qdisc_commands(ns, dev, rate, delay_ms, loss_pct, queue_ms, "change", jitter_ms, with_netem):
            _run(cmd)
    return rate


def link_cut(name="cps"):
    """Cut the link, as out of radio range: the physical side's veth end goes down (its peer loses
    carrier), so every packet between the sides is lost; TCP connections survive and retransmit."""
    _check_name(name)
    _run(["ip", "-n", namespace(name, "phys"), "link", "set", "dev", _device(name, "phys"), "down"])


def link_restore(name="cps"):
    """Undo link_cut: the veth end comes up again (with its addresses, routes and shaping)."""
    _check_name(name)
    _run(["ip", "-n", namespace(name, "phys"), "link", "set", "dev", _device(name, "phys"), "up"])
    _wait_until_up(name)


def netem_available():
    """True when this kernel has the netem qdisc (delay, jitter, loss); checked in a probe namespace."""
    probe = f"cpsnetem{os.getpid() % 100000}"
    _run(["ip", "netns", "add", probe])
    try:
        return (
            _run(
                ["ip", "netns", "exec", probe, "tc", "qdisc", "add", "dev", "lo", "root", "netem", "delay", "1ms"],
                check=False,
            ).returncode
            == 0
        )
    finally:
        _run(["ip", "netns", "del", probe], check=False)


def _has_netem(ns, dev):
    out = _run(["ip", "netns", "exec", ns, "tc", "qdisc", "show", "dev", dev]).stdout
    return re.search(r"qdisc netem 1: root", out) is not None


def link_down(name="cps"):
    """Remove both namespaces (the veth pair and its qdiscs go with them). Idempotent."""
    _check_name(name)
    present = list_namespaces()
    ours = [namespace(name, side) for side in SIDES] + [namespace_of_router(name)]
    for ns in ours:
        if ns in present:
            # Processes left in the namespace would keep it alive as a mount; kill them first.
            pids = _run(["ip", "netns", "pids", ns], check=False).stdout.split()
            for pid in pids:
                with contextlib.suppress(ProcessLookupError, ValueError):
                    os.kill(int(pid), 9)
            _run(["ip", "netns", "del", ns], check=False)
    left = [ns for ns in list_namespaces() if ns in ours]
    if left:
        raise LinkError(f"could not remove namespaces {left}")


def guard_hosts(name, listen_ports, sides=SIDES):
    """Leave each host (`sides`) of link `name` reachable from the other only at its own link
    listeners, `listen_ports[side]` ("phys" or "twin" -> ports; cps_link.host_guard says how and
    why), and let it reach only the other's; undone with the namespaces."""
    from cps_link.host_guard import guard_argv

    for side in sides:
        peer = "twin" if side == "phys" else "phys"
        argv_list = guard_argv(
            namespace(name, side), listen_ports.get(side, ()), side_ip(peer), listen_ports.get(peer, ())
        )
        for argv in argv_list:
            _run(argv)


def netns_argv(name, side, argv, env=None):
    """argv that runs `argv` inside one side's namespace with `env` (e.g. ROS_IP) set."""
    assignments = [f"{k}={v}" for k, v in (env or {}).items()]
    return ["ip", "netns", "exec", namespace(name, side), "env", *assignments, *argv]


def ros_env(side, master_port):
    """ROS_IP of `side` and the master in the digital-twin namespace."""
    return {"ROS_IP": side_ip(side), "ROS_MASTER_URI": f"http://{TWIN_IP}:{master_port}"}


def measure_mbps(name="cps", seconds=3.0, reverse=False, port=5201):
    """iperf3 server in the digital twin, client in the physical twin (as the paper: one machine
    serves, the other receives); returns the received Mbit/s. `reverse` measures twin -> phys."""
    report = _iperf3(name, seconds, port, ["-R"] if reverse else [])
    return report["end"]["sum_received"]["bits_per_second"] / 1e6


def measure_bidir_mbps(name="cps", seconds=3.0, port=5202):
    """Both directions at once (iperf3 --bidir): (phys -> twin, twin -> phys) received Mbit/s."""
    end = _iperf3(name, seconds, port, ["--bidir"])["end"]
    return end["sum_received"]["bits_per_second"] / 1e6, end["sum_received_bidir_reverse"]["bits_per_second"] / 1e6


def measure_udp_mbps(name="cps", offered_mbps=8.0, seconds=3.0, port=5211):
    """UDP at `offered_mbps` from the physical twin to the digital twin (more than the link carries
    keeps its queue full whatever the senders' congestion control); returns the received Mbit/s."""
    report = _iperf3(name, seconds, port, ["-u", "-b", f"{offered_mbps:g}M"])
    return report["end"]["sum"]["bits_per_second"] / 1e6


def _iperf3(name, seconds, port, extra):
    """iperf3's JSON report of one client run phys -> twin server with `extra` options."""
    if shutil.which("iperf3") is None:
        raise LinkError("iperf3 is not installed (Debian package iperf3)")
    if not 0.5 <= seconds <= 30:
        raise LinkError(f"measurement time must be in [0.5, 30] s, got {seconds}")
    server = subprocess.Popen(
        netns_argv(name, "twin", ["iperf3", "-s", "-1", "-B", TWIN_IP, "-p", str(port)]),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        argv = ["iperf3", "-c", TWIN_IP, "-p", str(port), "-t", f"{seconds:g}", "-J"] + extra
        deadline = time.monotonic() + 5.0
        while True:
            result = _run(netns_argv(name, "phys", argv), check=False, timeout_s=seconds + 15)
            try:
                report = json.loads(result.stdout)
            except ValueError:
                report = {"error": result.stderr.strip() or result.stdout[-500:]}
            if "error" not in report or time.monotonic() > deadline:
                break
            time.sleep(0.2)  # the server may not listen yet
        if "error" in report:
            raise LinkError(f"iperf3 failed: {report['error']}")
        return report
    finally:
        server.kill()
        server.wait(5)


class ShapedLink:
    """`with ShapedLink(rate="20mbit") as link:` the link exists inside the block and never after;
    rate None is fleet.yaml's link rate."""

    def __init__(
        self,
        name="cps",
        rate=None,
        delay_ms=0.0,
        loss_pct=0.0,
        queue_ms=DEFAULT_QUEUE_MS,
        jitter_ms=0.0,
        topology="duplex",
        with_netem=False,
        unsent_bytes=None,
    ):
        self.name, self.delay_ms, self.loss_pct, self.queue_ms = name, delay_ms, loss_pct, queue_ms
        self.jitter_ms, self.topology, self.with_netem = jitter_ms, topology, with_netem
        self.unsent_bytes = unsent_bytes
        self.rate = rate or fleet_rate()

    def __enter__(self):
        link_up(
            self.name,
            self.rate,
            self.delay_ms,
            self.loss_pct,
            self.queue_ms,
            self.jitter_ms,
            self.topology,
            self.with_netem,
            self.unsent_bytes,
        )
        return self

    def __exit__(self, *exc):
        link_down(self.name)

    def set_rate(self, rate):
        link_set(self.name, rate, self.delay_ms, self.loss_pct, self.queue_ms, self.jitter_ms)
        self.rate = rate

    def measure_mbps(self, seconds=3.0, reverse=False):
        return measure_mbps(self.name, seconds, reverse)

    def argv(self, side, argv, master_port=None, env=None):
        merged = dict(ros_env(side, master_port) if master_port else {"ROS_IP": side_ip(side)})
        merged.update(env or {})
        return netns_argv(self.name, side, argv, merged)

    def _shaper_of(self, side):
        """(namespace, device) of the shaper of `side` (shared topology: of both directions)."""
        if self.topology == "shared":
            return namespace_of_router(self.name), _ifb_device(self.name)
        return namespace(self.name, side), _device(self.name, side)

    def qdisc_bytes_sent(self, side):
        """Bytes the shaping qdisc of `side` (shared topology: of both directions) has sent so far
        (for per-window link accounting)."""
        ns, dev = self._shaper_of(side)
        out = _run(["ip", "netns", "exec", ns, "tc", "-s", "qdisc", "show", "dev", dev]).stdout
        match = re.search(r"qdisc tbf .*?Sent (\d+) bytes", out, re.S)
        return int(match.group(1)) if match else 0

    def voice_packets_sent(self, side):
        """Packets the voice queue of `side`'s shaper (those marked bridge.yaml's command_dscp) has
        sent so far."""
        ns, dev = self._shaper_of(side)
        out = _run(["ip", "netns", "exec", ns, "tc", "-s", "class", "show", "dev", dev, "classid", _VOICE_CLASS]).stdout
        match = re.search(r"Sent \d+ bytes (\d+) pkt", out)
        return int(match.group(1)) if match else 0
