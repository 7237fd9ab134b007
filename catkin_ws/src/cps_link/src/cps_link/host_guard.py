"""Only the link's listeners answer from outside a host: policy-routing rules in place of a firewall.

Over Zenoh each side's ROS graph stays on its host's loopback (ROS_IP=127.0.0.1), and rospy nodes
and roscpp's TCPROS bind 127.0.0.1 then. roscpp's XML-RPC server does not: xmlrpcpp's
`XmlRpcSocket::bind` always binds INADDR_ANY, so the nodelet manager and rosout still accept
connections from the link's network. A host firewall closes that; this testbed's kernel has no
netfilter (no iptables or nft) and no tc actions, so the guard uses `ip rule`, which needs neither.

A packet a host sends to another host passes these rules (packets to the host's own addresses are
answered by the `local` table at priority 0 first): it is routed only if it is TCP from one of the
link's listening ports (the twin, whose bridges listen) or TCP to the twin's address at one of those
ports (the robots' bridges connecting); every other TCP or UDP packet leaving the host is
prohibited. A connection to any other port never gets its SYN-ACK, so from the link's network each
host shows the link's ports and nothing else. The same commands work on a real host; there add
`to <the link's subnet>` to each rule so that the host's other networks are untouched.
"""

from typing import List, Sequence

# Ahead of the main table's rule (32766); the allow rules first, then the prohibit rules.
GUARD_PRIORITY = 1000
LISTENING_SIDE = "twin"  # bridge.yaml: the twin listens, the robots' bridges connect
CONNECTING_SIDE = "phys"
BLOCKED_PROTOCOLS = ("tcp", "udp")


def guard_rules(side: str, link_ports: Sequence[int], twin_ip: str) -> List[List[str]]:
    """The `ip rule add` arguments that leave only `link_ports` reachable on `side`'s host
    ("twin": it listens on them; "phys": it connects to `twin_ip` on them)."""
    ports = sorted({int(p) for p in link_ports})
    if not ports or any(not 0 < p < 65536 for p in ports):
        raise ValueError(f"link ports must be 1..65535, got {list(link_ports)}")
    if side == LISTENING_SIDE:
        allowed = [["ipproto", "tcp", "sport", str(p)] for p in ports]
    elif side == CONNECTING_SIDE:
        allowed = [["to", f"{twin_ip}/32", "ipproto", "tcp", "dport", str(p)] for p in ports]
    else:
        raise ValueError(f"side must be '{LISTENING_SIDE}' or '{CONNECTING_SIDE}', got '{side}'")
    rules = [["priority", str(GUARD_PRIORITY), *selector, "lookup", "main"] for selector in allowed]
    rules += [["priority", str(GUARD_PRIORITY + 1), "ipproto", proto, "prohibit"] for proto in BLOCKED_PROTOCOLS]
    return rules


def guard_argv(namespace: str, side: str, link_ports: Sequence[int], twin_ip: str) -> List[List[str]]:
    """The commands that guard the host in network namespace `namespace` (removed with it)."""
    return [["ip", "-n", namespace, "rule", "add", *rule] for rule in guard_rules(side, link_ports, twin_ip)]
