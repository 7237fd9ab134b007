"""What the Zenoh bridge puts on the wire, and the receiving side's bookkeeping (ROS-free).

A frame is one serialized ROS message, unchanged, behind a small header: session id (which run
of the sending bridge), sequence number per (topic, source publisher), the message's header
stamp (NaN when its type has none), CRC-32 of the body, type, md5 and source. So any message
type crosses without per-type code, corruption is detected, and a restarted bridge delivers
nothing twice.
"""
import dataclasses
import math
import struct
import zlib

MAGIC = b"CPSZ"
VERSION = 1
_FIXED = struct.Struct("!4sB16sQdI")
_LEN = struct.Struct("!H")
_ROS_STAMP = struct.Struct("<III")  # std_msgs/Header: seq, stamp.secs, stamp.nsecs


class WireError(ValueError):
    """A payload that is not a bridge frame, or is damaged; the message says how."""


@dataclasses.dataclass(frozen=True)
class Frame:
    session: bytes
    seq: int
    stamp_s: float
    msg_type: str
    md5: str
    source: str
    body: bytes


def header_stamp_s(body):
    """The header stamp of a serialized message whose type starts with a std_msgs/Header."""
    if len(body) < _ROS_STAMP.size:
        raise WireError(f"message of {len(body)} bytes is too short for a std_msgs/Header")
    _, secs, nsecs = _ROS_STAMP.unpack_from(body)
    return secs + nsecs * 1e-9


def header_frame_id(body):
    """The header frame_id of a serialized message whose type starts with a std_msgs/Header."""
    if len(body) < 16:
        raise WireError(f"message of {len(body)} bytes is too short for a std_msgs/Header")
    (n,) = struct.unpack_from("<I", body, 12)
    if 16 + n > len(body):
        raise WireError("header frame_id runs past the message")
    return bytes(body[16:16 + n]).decode(errors="replace")


def encode(frame: Frame) -> bytes:
    if len(frame.session) != 16:
        raise ValueError("session id must be 16 bytes")
    parts = [_FIXED.pack(MAGIC, VERSION, frame.session, frame.seq, frame.stamp_s, zlib.crc32(frame.body))]
    for text in (frame.msg_type, frame.md5, frame.source):
        data = text.encode()
        parts += [_LEN.pack(len(data)), data]
    parts.append(frame.body)
    return b"".join(parts)


def decode(payload) -> Frame:
    """The frame in `payload`; WireError for anything that is not one, or is damaged."""
    view = memoryview(payload)
    if len(view) < _FIXED.size:
        raise WireError(f"payload of {len(view)} bytes is shorter than a frame header")
    magic, version, session, seq, stamp_s, crc = _FIXED.unpack_from(view)
    if magic != MAGIC:
        raise WireError("not a bridge frame (bad magic)")
    if version != VERSION:
        raise WireError(f"frame version {version}, this bridge reads {VERSION}")
    offset, texts = _FIXED.size, []
    for _ in range(3):
        if offset + _LEN.size > len(view):
            raise WireError("frame header truncated")
        (n,) = _LEN.unpack_from(view, offset)
        offset += _LEN.size
        if offset + n > len(view):
            raise WireError("frame header truncated")
        try:
            texts.append(bytes(view[offset:offset + n]).decode())
        except UnicodeDecodeError as exc:
            raise WireError(f"frame header is not text: {exc}") from exc
        offset += n
    body = bytes(view[offset:])
    if zlib.crc32(body) != crc:
        raise WireError("body CRC mismatch (corrupt payload)")
    return Frame(bytes(session), seq, stamp_s, texts[0], texts[1], texts[2], body)


class Deduplicator:
    """Accepts each (session, topic, source, seq) once: a bridge that re-sends after an outage or a
    restarted receiver never delivers a message twice, a restarted sender (new session) starts afresh."""

    def __init__(self):
        self._last = {}

    def accept(self, topic, frame: Frame):
        key = (topic, frame.source)
        last = self._last.get(key)
        if last is not None and last[0] == frame.session and frame.seq <= last[1]:
            return False
        self._last[key] = (frame.session, frame.seq)
        return True


def is_stale(frame: Frame, now_s, max_age_s):
    """True when the message's stamp is older than max_age_s (never for messages without a stamp)."""
    return max_age_s is not None and not math.isnan(frame.stamp_s) and now_s - frame.stamp_s > max_age_s
