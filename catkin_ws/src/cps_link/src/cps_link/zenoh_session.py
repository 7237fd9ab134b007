"""The Zenoh session of one bridge: endpoints, mutual TLS with the fleet's certificates, a short
lease (a silent peer is gone within a second) and endless reconnection. ROS-free.

On the main lane the twin listens on its own address and the robots' side connects to it; on the
command lane the robots listen and the twin connects (bridge_config.COMMAND_LISTENER); nobody scouts.
"""

import json
import os
import subprocess

from cps_link.bridge_config import COMMAND_CLASS, ROBOTS, TWIN, BridgeTable

MAKE_CERTS = os.path.normpath(
    os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "scripts", "make_certs")
)
CERT_DIR_ENV = "CPS_CERT_DIR"


class BridgeSetupError(RuntimeError):
    """The bridge cannot start (no certificates, bad endpoint); the message says what to do."""


def default_cert_dir():
    """$CPS_CERT_DIR, else .certs at the top of the checkout (outside git)."""
    if os.environ.get(CERT_DIR_ENV):
        return os.environ[CERT_DIR_ENV]
    root = os.environ.get("CPS_ROOT") or os.path.normpath(os.path.join(os.path.dirname(MAKE_CERTS), *[".."] * 4))
    return os.path.join(root, ".certs")


def ensure_certs(cert_dir):
    """Make the fleet's CA and certificates on first use (testbed addresses); return cert_dir."""
    if not os.path.exists(os.path.join(cert_dir, "ca.pem")):
        result = subprocess.run([MAKE_CERTS, cert_dir], capture_output=True, text=True)
        if result.returncode != 0:
            raise BridgeSetupError(f"could not make certificates in {cert_dir}: {result.stderr.strip()}")
    return cert_dir


def cert_files(cert_dir, side):
    files = {
        "ca": os.path.join(cert_dir, "ca.pem"),
        "cert": os.path.join(cert_dir, f"{side}.pem"),
        "key": os.path.join(cert_dir, f"{side}.key"),
    }
    missing = [p for p in files.values() if not os.path.isfile(p)]
    if missing:
        raise BridgeSetupError(
            f"missing TLS files {', '.join(missing)}; make them with "
            f"`{MAKE_CERTS} {cert_dir}` (see the cps_link README)"
        )
    return files


def session_config(table: BridgeTable, side, twin_address, cert_dir, tls=True, robots_address=None):
    """The Zenoh configuration (a JSON-able dict) of `side`'s bridge for the table's lane: the lane's
    listening side (BridgeTable.listening_side) listens at its own address, the other connects there
    (the twin at twin_address on the main lane; on the command lane the robots at robots_address,
    which the twin may give as a comma-separated list, one robots' bridge per computer)."""
    if side not in (ROBOTS, TWIN):
        raise BridgeSetupError(f"side must be robots or twin, got '{side}'")
    listener = table.listening_side
    addresses = [
        a.strip() for a in (twin_address if listener == TWIN else robots_address or "").split(",") if a.strip()
    ]
    if not addresses:
        raise BridgeSetupError(
            f"the {table.lane} lane's listener is the {listener} bridge: its host's address is needed (--{listener}-address)"
        )
    if side == listener and len(addresses) > 1:
        raise BridgeSetupError(f"the {side} bridge listens at one address of its own, got {', '.join(addresses)}")
    proto = "tls" if tls else "tcp"
    # Zenoh marks the command lane's sockets, the listener's accepted ones too
    mark = f"#dscp={table.command_dscp << 2}" if table.lane == COMMAND_CLASS else ""
    endpoints = [f"{proto}/{f'[{a}]' if ':' in a else a}:{table.endpoint_port}{mark}" for a in addresses]
    retry = {"period_init_ms": 200, "period_max_ms": table.retry_max_ms, "period_increase_factor": 1.5}
    config = {
        "mode": "peer",
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "listen": {"endpoints": endpoints if side == listener else [], "retry": retry},
        "connect": {
            "endpoints": endpoints if side != listener else [],
            "timeout_ms": -1,
            "exit_on_failure": False,
            "retry": retry,
        },
        "transport": {
            "link": {
                "tx": {
                    "lease": table.lease_ms,
                    "keep_alive": table.keep_alive,
                    "batch_size": table.batch_bytes,
                    "queue": {
                        "congestion_control": {"block": {"wait_before_close": table.block_wait_before_close_ms * 1000}}
                    },
                }
            },
            # Zenoh moves messages > 3 kB through shared memory when both ends can map it: on the
            # test bed's one host that would carry them past the shaped link. A bridge crosses a network.
            "shared_memory": {"enabled": False},
        },
    }
    if tls:
        files = cert_files(cert_dir, side)
        config["transport"]["link"]["tls"] = {
            "root_ca_certificate": files["ca"],
            "enable_mtls": True,
            "listen_certificate": files["cert"],
            "listen_private_key": files["key"],
            "connect_certificate": files["cert"],
            "connect_private_key": files["key"],
            "verify_name_on_connect": True,
        }
    return config


def open_session(config):
    import zenoh

    try:
        return zenoh.open(zenoh.Config.from_json5(json.dumps(config)))
    except Exception as exc:  # zenoh raises its own ZError
        raise BridgeSetupError(f"cannot open the Zenoh session: {exc}") from exc


def bridge_node_name(side, lane="all"):
    """The ROS node name of one side's bridge for one lane (bridge_config.LANES): the command lane's
    is `zenoh_bridge_<side>_command`, the others' `zenoh_bridge_<side>`."""
    return f"zenoh_bridge_{side}_command" if lane == "command" else f"zenoh_bridge_{side}"


def bridge_argv(
    python,
    side,
    twin_address,
    robots,
    cert_dir=None,
    port=None,
    fleet_file=None,
    name=None,
    lane="all",
    robots_address=None,
):
    """The command line of one side's zenoh_bridge node for one lane (bringup, tests and the benchmark);
    the command lane needs robots_address, where the robots' bridge listens."""
    node = os.path.normpath(os.path.join(os.path.dirname(MAKE_CERTS), "..", "nodes", "zenoh_bridge"))
    argv = [
        python,
        node,
        "--side",
        side,
        "--twin-address",
        twin_address,
        "--robots",
        ",".join(robots),
        "--lane",
        lane,
        f"__name:={bridge_node_name(side, lane)}",
    ]
    for flag, value in (
        ("--robots-address", robots_address),
        ("--cert-dir", cert_dir),
        ("--port", port),
        ("--fleet", fleet_file),
        ("--name", name),
    ):
        if value:
            argv += [flag, str(value)]
    return argv
