"""What the Zenoh bridge puts on the wire (ROS-free; what the receiving side makes of it is
cps_link.receive_path).

A frame is one serialized ROS message, unchanged, behind a small header: session id (which run
of the sending bridge; its first 8 bytes are the run's start time, so a newer run is known),
sequence number per (topic, source publisher), the message's header stamp (NaN when its type has
none), CRC-32 of the whole frame, length of the body, destination topic, type, md5 and source.
So any message type crosses without per-type code, corruption and truncation are detected, a
restarted bridge delivers nothing twice, and a frame that reaches the wrong topic is recognised
(version 2: the frame names its topic; version 1 did not, and a frame mis-delivered after a
reconnect was published on another topic with another type).
"""

import dataclasses
import math
import os
import struct
import time
import zlib

MAGIC = b"CPSZ"
VERSION = 2
_FIXED = struct.Struct("!4sB16sQdII")  # magic, version, session, seq, stamp, CRC-32, body length
_CRC_AT = 37  # the CRC's offset in _FIXED: it covers the whole frame with its own 4 bytes zeroed
_LEN = struct.Struct("!H")
_ROS_STAMP = struct.Struct("<III")  # std_msgs/Header: seq, stamp.secs, stamp.nsecs


# What WireError.kind says about a payload the receiving side drops (its diagnostics count each).
TRUNCATED, NOT_A_FRAME, BAD_VERSION, BAD_CRC = "truncated", "not_a_frame", "bad_version", "bad_crc"


class WireError(ValueError):
    """A payload that is not a bridge frame, or is damaged; the message says how, `kind` names it."""

    def __init__(self, message, kind=NOT_A_FRAME):
        super().__init__(message)
        self.kind = kind


@dataclasses.dataclass(frozen=True)
class Frame:
    session: bytes
    seq: int
    stamp_s: float
    msg_type: str
    md5: str
    source: str
    body: bytes
    topic: str = ""  # where the far side publishes it (the route's `to`)


def new_session_id(now_ns=None):
    """16 bytes: the run's start time (ns, big-endian, so newer runs compare greater) and 8 random."""
    return struct.pack("!Q", time.time_ns() if now_ns is None else now_ns) + os.urandom(8)


def session_started_ns(session):
    """The start time a session id carries (see new_session_id), ns."""
    return struct.unpack_from("!Q", session)[0]


def header_stamp(body):
    """(secs, nsecs): the header stamp of a serialized message whose type starts with a
    std_msgs/Header, exactly (a float of seconds since 1970 keeps only ~0.24 us)."""
    if len(body) < _ROS_STAMP.size:
        raise WireError(f"message of {len(body)} bytes is too short for a std_msgs/Header")
    _, secs, nsecs = _ROS_STAMP.unpack_from(body)
    return secs, nsecs


def header_stamp_s(body):
    """The header stamp of a serialized message whose type starts with a std_msgs/Header, s."""
    secs, nsecs = header_stamp(body)
    return secs + nsecs * 1e-9


def header_frame_id(body):
    """The header frame_id of a serialized message whose type starts with a std_msgs/Header."""
    if len(body) < 16:
        raise WireError(f"message of {len(body)} bytes is too short for a std_msgs/Header")
    (n,) = struct.unpack_from("<I", body, 12)
    if 16 + n > len(body):
        raise WireError("header frame_id runs past the message")
    return bytes(body[16 : 16 + n]).decode(errors="replace")


def encode(frame: Frame) -> bytes:
    if len(frame.session) != 16:
        raise ValueError("session id must be 16 bytes")
    parts = [_FIXED.pack(MAGIC, VERSION, frame.session, frame.seq, frame.stamp_s, 0, len(frame.body))]
    for text in (frame.topic, frame.msg_type, frame.md5, frame.source):
        data = text.encode()
        parts += [_LEN.pack(len(data)), data]
    parts.append(frame.body)
    out = bytearray(b"".join(parts))
    struct.pack_into("!I", out, _CRC_AT, zlib.crc32(out))
    return bytes(out)


def decode(payload) -> Frame:
    """The frame in `payload`; WireError (with its kind) for anything that is not one, or is damaged."""
    view = memoryview(payload)
    if len(view) >= 5 and bytes(view[:4]) == MAGIC and view[4] != VERSION:
        raise WireError(f"frame version {view[4]}, this bridge reads {VERSION}", BAD_VERSION)
    if len(view) < _FIXED.size:
        raise WireError(f"payload of {len(view)} bytes is shorter than a frame header", TRUNCATED)
    magic, version, session, seq, stamp_s, crc, body_len = _FIXED.unpack_from(view)
    if magic != MAGIC:
        raise WireError("not a bridge frame (bad magic)", NOT_A_FRAME)
    offset, texts = _FIXED.size, []
    for _ in range(4):
        if offset + _LEN.size > len(view):
            raise WireError("frame header truncated", TRUNCATED)
        (n,) = _LEN.unpack_from(view, offset)
        offset += _LEN.size
        if offset + n > len(view):
            raise WireError("frame header truncated", TRUNCATED)
        try:
            texts.append(bytes(view[offset : offset + n]).decode())
        except UnicodeDecodeError as exc:
            raise WireError(f"frame header is not text: {exc}", NOT_A_FRAME) from exc
        offset += n
    if len(view) - offset < body_len:
        raise WireError(f"body truncated: {len(view) - offset} of {body_len} bytes", TRUNCATED)
    if len(view) - offset > body_len:
        raise WireError(f"{len(view) - offset - body_len} bytes past the body", NOT_A_FRAME)
    if zlib.crc32(view[_CRC_AT + 4 :], zlib.crc32(b"\x00" * 4, zlib.crc32(view[:_CRC_AT]))) != crc:
        raise WireError("CRC mismatch (corrupt payload)", BAD_CRC)
    body = bytes(view[offset:])
    return Frame(bytes(session), seq, stamp_s, texts[1], texts[2], texts[3], body, topic=texts[0])


def is_stale(frame: Frame, now_s, max_age_s):
    """True when the message's stamp is older than max_age_s (never for messages without a stamp)."""
    return max_age_s is not None and not math.isnan(frame.stamp_s) and now_s - frame.stamp_s > max_age_s
