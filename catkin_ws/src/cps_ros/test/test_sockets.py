"""cps_ros.sockets reads a descriptor's type, ports and type of service and leaves its file as it was
(blocking), even while a default socket timeout is set, as rospy sets one."""

import os
import socket

import pytest

from cps_ros import sockets

pytestmark = pytest.mark.unit


def test_a_sockets_facts_are_read_and_its_file_left_blocking():
    before = socket.getdefaulttimeout()
    socket.setdefaulttimeout(None)
    try:
        with socket.socket() as listener:
            listener.bind(("127.0.0.1", 0))
            listener.listen()
            port = listener.getsockname()[1]
            with socket.create_connection(("127.0.0.1", port)) as client, listener.accept()[0] as accepted:
                client.setsockopt(socket.IPPROTO_IP, socket.IP_TOS, 46 << 2)
                socket.setdefaulttimeout(60.0)  # as rospy sets it
                fds = listener.fileno(), client.fileno(), accepted.fileno()
                assert [sockets.socket_type(fd) for fd in fds] == [socket.SOCK_STREAM] * 3
                assert [sockets.inet_port(fd) for fd in fds] == [port, client.getsockname()[1], port]
                assert [sockets.inet_port(fd, peer=True) for fd in fds] == [None, port, client.getsockname()[1]]
                assert sockets.ip_tos(client.fileno()) == 46 << 2 and sockets.ip_tos(accepted.fileno()) == 0
                assert all(os.get_blocking(fd) for fd in fds)
        r, w = os.pipe()  # not a socket
        try:
            assert sockets.socket_type(r) is None and sockets.inet_port(r) is None and sockets.ip_tos(r) is None
        finally:
            os.close(r)
            os.close(w)
    finally:
        socket.setdefaulttimeout(before)
