"""Which TCP ports of a host answer from another host (test support for cps_link.host_guard).

`listening_ports(ns)`: every TCP port something listens on in network namespace `ns`, on any
address (from `ss`). `python -m cps_harness.port_scan HOST PORT...`, run inside the other host's
namespace, tries them all at once (a connect that completes within the timeout is open; refused
or unanswered is not) and prints the open ones as JSON.
"""

import errno
import json
import selectors
import socket
import subprocess
import sys
import time

CONNECT_TIMEOUT_S = 2.0


def listening_ports(namespace):
    """Ports with a listening TCP socket in `namespace` (IPv4 or IPv6, any address)."""
    out = subprocess.run(
        ["ip", "netns", "exec", namespace, "ss", "-ltnH"], check=True, capture_output=True, text=True
    ).stdout
    ports = set()
    for line in out.splitlines():
        fields = line.split()
        if len(fields) >= 4:
            ports.add(int(fields[3].rsplit(":", 1)[1]))
    return sorted(ports)


def open_ports(host, ports, timeout_s=CONNECT_TIMEOUT_S):
    """The `ports` of `host` whose TCP connect completes within `timeout_s` (all tried at once); a
    connect refused at once, by the far host or by this host's routing, is not open."""
    selector = selectors.DefaultSelector()
    for port in ports:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setblocking(False)
        if sock.connect_ex((host, port)) not in (0, errno.EINPROGRESS):  # refused on the spot (a route prohibits it)
            sock.close()
            continue
        selector.register(sock, selectors.EVENT_WRITE, port)
    found = []
    deadline = time.monotonic() + timeout_s
    while selector.get_map() and time.monotonic() < deadline:
        for key, _ in selector.select(max(0.0, deadline - time.monotonic())):
            if key.fileobj.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR) == 0:
                found.append(key.data)
            selector.unregister(key.fileobj)
            key.fileobj.close()
    for key in list(selector.get_map().values()):
        key.fileobj.close()
    selector.close()
    return sorted(found)


def scan_argv(python, host, ports):
    """argv that runs this module's scan (prefix it with the scanning host's `ip netns exec`)."""
    return [python, "-m", "cps_harness.port_scan", host, *map(str, ports)]


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) < 2:
        print("usage: python -m cps_harness.port_scan HOST PORT...", file=sys.stderr)
        return 2
    print(json.dumps(open_ports(argv[0], [int(p) for p in argv[1:]])))
    return 0


if __name__ == "__main__":
    sys.exit(main())
