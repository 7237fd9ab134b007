#!/usr/bin/env python3
"""Round trips of small messages on two TCP connections across a link, one marked with a DSCP code
point (both ends) and one not (test support for test_shared_medium).

  tos_pings.py serve PORT_MARKED PORT_PLAIN DSCP      echo server; prints "listening" when ready
  tos_pings.py ping HOST PORT_MARKED PORT_PLAIN DSCP DURATION_S INTERVAL_S
                                                      prints JSON {"marked": [[t_s, rtt_s], ...], "plain": [...]}
"""

import json
import socket
import struct
import sys
import threading
import time


def _connection(sock, dscp):
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    if dscp:
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_TOS, dscp << 2)
    return sock


def _echo(sock):
    with sock:
        while True:
            data = sock.recv(64)
            if not data:
                return
            sock.sendall(data)


def serve(port_marked, port_plain, dscp):
    listeners = []
    for port in (port_marked, port_plain):
        listener = socket.socket()
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("0.0.0.0", port))
        listener.listen()
        listeners.append(listener)
    print("listening", flush=True)
    threads = []
    for listener, marked in zip(listeners, (dscp, 0)):
        sock, _ = listener.accept()
        threads.append(threading.Thread(target=_echo, args=(_connection(sock, marked),), daemon=True))
        threads[-1].start()
    for thread in threads:
        thread.join()


def _round_trip(sock, index):
    sent = time.monotonic()
    sock.sendall(struct.pack("!Qd", index, sent))
    got = b""
    while len(got) < 16:
        chunk = sock.recv(16 - len(got))
        if not chunk:
            raise ConnectionError("the echo server closed")
        got += chunk
    return time.monotonic() - sent


def ping(host, port_marked, port_plain, dscp, duration_s, interval_s):
    marked = _connection(socket.create_connection((host, port_marked), timeout=10), dscp)
    plain = _connection(socket.create_connection((host, port_plain), timeout=10), 0)
    out = {"marked": [], "plain": []}
    start = time.monotonic()
    index = 0
    while time.monotonic() - start < duration_s:
        for name, sock in (("marked", marked), ("plain", plain)):
            out[name].append([time.monotonic() - start, _round_trip(sock, index)])
        index += 1
        time.sleep(max(0.0, start + index * interval_s - time.monotonic()))
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    mode, args = sys.argv[1], sys.argv[2:]
    if mode == "serve":
        serve(int(args[0]), int(args[1]), int(args[2]))
    else:
        ping(args[0], int(args[1]), int(args[2]), int(args[3]), float(args[4]), float(args[5]))
