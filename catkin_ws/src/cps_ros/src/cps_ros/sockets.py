"""What the kernel says of one of this process's socket descriptors, asked through libc.

Never through a Python socket object made on the descriptor: once a default socket timeout is set
(rospy sets 60 s when a subscriber connects), making one puts the descriptor's file non-blocking,
and rospy's TCPROS listener, made non-blocking so, lost its accept thread to EAGAIN: nothing more
could connect to the process's publishers or services.
"""

import ctypes
import socket
import struct
from typing import Optional

_LIBC = ctypes.CDLL(None, use_errno=True)


def _int_option(fd, level, name) -> Optional[int]:
    value = ctypes.c_int(0)
    size = ctypes.c_uint32(ctypes.sizeof(value))
    if _LIBC.getsockopt(fd, level, name, ctypes.byref(value), ctypes.byref(size)) != 0:
        return None
    return value.value


def socket_type(fd) -> Optional[int]:
    """socket.SOCK_STREAM, SOCK_DGRAM...; None if `fd` is no socket."""
    return _int_option(fd, socket.SOL_SOCKET, socket.SO_TYPE)


def ip_tos(fd) -> Optional[int]:
    """The IPv4 type of service its packets carry (the DSCP code point << 2); None if not readable."""
    return _int_option(fd, socket.IPPROTO_IP, socket.IP_TOS)


def inet_port(fd, peer=False) -> Optional[int]:
    """The local port (the peer's with `peer`) of an IPv4 or IPv6 socket; None otherwise, or when
    it has no peer (a listener)."""
    address = ctypes.create_string_buffer(128)  # a sockaddr_storage
    size = ctypes.c_uint32(len(address))
    call = _LIBC.getpeername if peer else _LIBC.getsockname
    if call(fd, address, ctypes.byref(size)) != 0:
        return None
    family = struct.unpack_from("=H", address.raw)[0]  # sa_family, then the port, big-endian
    return struct.unpack_from("!H", address.raw, 2)[0] if family in (socket.AF_INET, socket.AF_INET6) else None
