"""Only the link's listeners answer from outside a host: policy-routing rules in place of a firewall.

Over Zenoh each side's ROS graph stays on its host's loopback (ROS_IP=127.0.0.1), and rospy nodes
and roscpp's TCPROS bind 127.0.0.1 then. roscpp's XML-RPC server does not: xmlrpcpp's
`XmlRpcSocket::bind` always binds INADDR_ANY, so the nodelet manager and rosout still accept
connections from the link's network. A host firewall closes that; this testbed's kernel has no
netfilter (no iptables or nft) and no tc actions, so the guard uses `ip rule`, which needs neither.

A packet a host sends to another host passes these rules (packets to the host's own addresses are
answered by the `local` table at priority 0 first): it is routed only if it is TCP from the host's
own link listener (the twin's main lane, the robots' command lane: bridge_config.COMMAND_LISTENER)
or TCP to the other host's address at the other host's listener (this host's bridge connecting);
every other TCP or UDP packet leaving the host is prohibited. A connection to any other port never
gets its SYN-ACK, so from the link's network each host shows its own listener and nothing else.
The same commands work on a real host; there add `to <the link's subnet>` to each rule so that
the host's other networks are untouched.
"""

from typing import List, Sequence

# Ahead of the main table's rule (32766); the allow rules first, then the prohibit rules.
GUARD_PRIORITY = 1000
BLOCKED_PROTOCOLS = ("tcp", "udp")


def _ports(ports, what):
    ports = sorted({int(p) for p in ports})
    if any(not 0 < p < 65536 for p in ports):
        raise ValueError(f"{what} must be 1..65535, got {ports}")
    return ports


def guard_rules(listen_ports: Sequence[int], peer_ip: str, peer_ports: Sequence[int]) -> List[List[str]]:
    """The `ip rule add` arguments that leave a host reachable only at `listen_ports` (its own link
    listeners) and let it reach only `peer_ip` at `peer_ports` (the other host's)."""
    listen, peer = _ports(listen_ports, "listening ports"), _ports(peer_ports, "the peer's ports")
    if not listen and not peer:
        raise ValueError("a guarded host needs a link port: one it listens on or one of its peer's")
    allowed = [["ipproto", "tcp", "sport", str(p)] for p in listen]
    allowed += [["to", f"{peer_ip}/32", "ipproto", "tcp", "dport", str(p)] for p in peer]
    rules = [["priority", str(GUARD_PRIORITY), *selector, "lookup", "main"] for selector in allowed]
    rules += [["priority", str(GUARD_PRIORITY + 1), "ipproto", proto, "prohibit"] for proto in BLOCKED_PROTOCOLS]
    return rules


def guard_argv(namespace: str, listen_ports: Sequence[int], peer_ip: str, peer_ports: Sequence[int]) -> List[List[str]]:
    """The commands that guard the host in network namespace `namespace` (removed with it)."""
    return [["ip", "-n", namespace, "rule", "add", *rule] for rule in guard_rules(listen_ports, peer_ip, peer_ports)]
