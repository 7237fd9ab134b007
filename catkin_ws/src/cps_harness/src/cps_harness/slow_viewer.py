"""A slow viewer: a TCPROS subscriber that reads a heavy topic at a trickle (test support, issue 38).

A remote viewer on a bad connection, or one that stopped reading, is a subscriber whose socket
fills: it connects to every publisher of a topic as any ROS subscriber does (the master's system
state, `requestTopic`, the TCPROS header with md5sum `*`), then reads at most `read_bytes_per_s`
with a small receive buffer. What must hold meanwhile is that the publisher's other subscribers
(the GUI, the link) do not wait for it.

    ROS_MASTER_URI=... python -m cps_harness.slow_viewer TOPIC SECONDS [READ_BYTES_PER_S]
"""

import socket
import struct
import sys
import time
import xmlrpc.client

CALLER_ID = "/cps_slow_viewer"
RECEIVE_BUFFER_BYTES = 4096
READ_BYTES_PER_S = 4096


def tcpros_header(fields):
    """TCPROS connection header: each `k=v` with its 4-byte little-endian length, all with the total's."""
    body = b"".join(struct.pack("<I", len(f)) + f for f in (f"{k}={v}".encode() for k, v in fields.items()))
    return struct.pack("<I", len(body)) + body


def publishers_of(master_uri, topic):
    """The XML-RPC URIs of the nodes publishing `topic` on `master_uri`."""
    master = xmlrpc.client.ServerProxy(master_uri)
    code, message, (publishers, _subs, _services) = master.getSystemState(CALLER_ID)
    if code != 1:
        raise RuntimeError(f"getSystemState: {message}")
    nodes = next((nodes for name, nodes in publishers if name == topic), [])
    uris = []
    for node in nodes:
        code, message, uri = master.lookupNode(CALLER_ID, node)
        if code == 1:
            uris.append(uri)
    return uris


def connect_slowly(node_uri, topic):
    """A TCPROS connection to `topic` at the node `node_uri`, header sent, small receive buffer."""
    code, message, protocol = xmlrpc.client.ServerProxy(node_uri).requestTopic(CALLER_ID, topic, [["TCPROS"]])
    if code != 1:
        raise RuntimeError(f"requestTopic {topic} at {node_uri}: {message}")
    _, host, port = protocol
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
    sock.connect((host, port))
    sock.sendall(tcpros_header({"callerid": CALLER_ID, "topic": topic, "md5sum": "*", "type": "*"}))
    return sock


def view_slowly(master_uri, topic, seconds, read_bytes_per_s=READ_BYTES_PER_S):
    """Hold a slow subscription to every publisher of `topic` for `seconds`; bytes read in total."""
    socks = [connect_slowly(uri, topic) for uri in publishers_of(master_uri, topic)]
    if not socks:
        raise RuntimeError(f"no publisher of {topic}")
    read, deadline = 0, time.monotonic() + seconds
    try:
        while time.monotonic() < deadline:
            for sock in socks:
                sock.settimeout(0.05)
                try:
                    read += len(sock.recv(read_bytes_per_s))
                except (socket.timeout, BlockingIOError):
                    pass
            time.sleep(1.0)
    finally:
        for sock in socks:
            sock.close()
    return read


def main(argv=None):
    import os

    argv = sys.argv[1:] if argv is None else argv
    if len(argv) not in (2, 3):
        print(__doc__.strip().splitlines()[-1].strip(), file=sys.stderr)
        return 2
    rate = int(argv[2]) if len(argv) == 3 else READ_BYTES_PER_S
    read = view_slowly(os.environ["ROS_MASTER_URI"], argv[0], float(argv[1]), rate)
    print(f"read {read} bytes of {argv[0]} in {argv[1]} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
