"""The link report's parts without ROS or Zenoh (issue 35; docs/bandwidth_manager.md specifies the
message): what the robots' bridge sends every 0.5 s, how the twin's bridge makes one interval of
it with what it received, heartbeat echoes for round trips, and the kernel's socket queues.

The robots' bridge sends cumulative counters (offered, sent, its queue's drops) with its report's
sequence number and its monotonic time; the twin's bridge keeps cumulative counts of what it
received and takes the differences between two consecutive reports of one robots' bridge run. So
a lost report only makes the next interval longer, a duplicated or older one is refused, and the
two sides' clocks are never compared: each side's interval is measured on its own clock (the
robots' between sending two reports, the twin's between receiving them). The report rides a
higher Zenoh priority than the data, so the twin's interval is a delivery-rate sample of the link
over that time, not a count of the same bytes.
"""

import collections
import dataclasses
import fcntl
import json
import math
import os
import socket
import struct
import termios
import time
from typing import List, NamedTuple, Optional, Sequence

REPORT_VERSION = 1
# Why the twin's bridge does not make an interval of a robots' report (each counted).
BAD_REPORT = "bad_report"  # not a report, or a field missing / negative / not finite
OLD_REPORT = "old_report"  # its sequence number is not newer than the last one of its run
FIRST_OF_RUN = "first_of_run"  # the first report of a robots' bridge run: the start of intervals
COUNTER_BACKWARDS = "counter_backwards"  # a cumulative counter went down within one run
REPORT_REFUSALS = (BAD_REPORT, OLD_REPORT, FIRST_OF_RUN, COUNTER_BACKWARDS)
# An interval longer than this is not one (an outage, a stopped bridge): it restarts the intervals.
MAX_INTERVAL_S = 5.0
HEARTBEAT = struct.Struct("!QQ")  # sequence number, the sender's monotonic clock in ns
# The twin's bridge is behind when its link socket's receive queue holds at least this much in at
# least RECEIVER_BEHIND_SAMPLES of the samples of one interval (sampled at every heartbeat).
RECEIVER_BEHIND_BYTES = 131072
RECEIVER_BEHIND_SAMPLES = 2


def socket_full_bytes(table):
    """The robots' link socket is full (the link, not the sender, is the limit) when at least this
    much waits in it not yet sent: half of bridge.yaml's kernel_unsent_bytes, which TCP_NOTSENT_LOWAT
    keeps it between only while the link is slower than the sender (the kernel wakes the writer
    below half); half a Zenoh batch where the kernel's bound is not set."""
    return max(table.kernel_unsent_bytes, table.batch_bytes) // 2


@dataclasses.dataclass(frozen=True)
class SenderReport:
    """What the robots' bridge sends: cumulative counters of its run at its monotonic time `t_s`."""

    session: str  # the robots' bridge run (its frames' session id, hex)
    seq: int
    t_s: float
    offered_bytes: int
    sent_bytes: int
    superseded: int
    expired: int
    app_limited: bool  # since the previous report
    rtt_s: Sequence[float] = ()
    blocked_s: float = 0.0  # since the previous report: how long its sender waited for the link
    # its link socket's TCP payload bytes sent for the first time and acked, cumulative (TCP_INFO:
    # every byte the link carries, framing included, but the TCP/IP headers); 0: not readable
    link_sent_bytes: int = 0
    link_acked_bytes: int = 0
    # heartbeat samples since the previous report, and of them those whose link socket held at least
    # socket_full_bytes() not yet sent (the link, not the sender, was the limit then)
    socket_samples: int = 0
    socket_full_samples: int = 0  # heartbeat round trips completed since the previous report
    send_queue_max_bytes: int = 0  # since the previous report
    pacing_mbps: float = 0.0
    peer: str = ""
    # probe trains' bytes put on the link, cumulative, and their mean cost now (cps_link.probe_train)
    probe_sent_bytes: int = 0
    probe_cost_mbps: float = 0.0
    # link sockets this bridge has read so far (LinkSockets.sockets_found): one more is a reconnection,
    # and its byte counters over the interval that holds it are not the link's
    link_sockets: int = 0

    def encode(self) -> bytes:
        return json.dumps({"v": REPORT_VERSION, **dataclasses.asdict(self), "rtt_s": list(self.rtt_s)}).encode()


class ReportError(ValueError):
    pass


def decode_sender_report(payload) -> SenderReport:
    """The SenderReport in `payload`; ReportError for anything else (a bad field says which)."""
    try:
        doc = json.loads(bytes(payload).decode())
    except (UnicodeDecodeError, ValueError) as exc:
        raise ReportError(f"not a link report: {exc}") from exc
    if not isinstance(doc, dict) or doc.get("v") != REPORT_VERSION:
        raise ReportError(f"not a version {REPORT_VERSION} link report")
    fields = {f.name: f for f in dataclasses.fields(SenderReport)}
    missing = [n for n in ("session", "seq", "t_s", "offered_bytes", "sent_bytes") if n not in doc]
    if missing:
        raise ReportError(f"link report without {', '.join(missing)}")
    values = {k: v for k, v in doc.items() if k in fields}
    for name in (
        "seq",
        "offered_bytes",
        "sent_bytes",
        "superseded",
        "expired",
        "send_queue_max_bytes",
        "link_sent_bytes",
        "link_acked_bytes",
        "socket_samples",
        "socket_full_samples",
        "probe_sent_bytes",
        "link_sockets",
    ):
        v = values.get(name, 0)
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ReportError(f"link report field {name} = {v!r} is not a count")
    for name in ("t_s", "pacing_mbps", "blocked_s", "probe_cost_mbps"):
        v = values.get(name, 0.0)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise ReportError(f"link report field {name} = {v!r} is not a finite number >= 0")
    rtts = values.get("rtt_s", [])
    if not isinstance(rtts, list) or not all(isinstance(r, (int, float)) and not isinstance(r, bool) for r in rtts):
        raise ReportError("link report field rtt_s is not a list of numbers")
    values["rtt_s"] = tuple(float(r) for r in rtts)
    values["app_limited"] = bool(values.get("app_limited", False))
    values["session"], values["peer"] = str(values["session"]), str(values.get("peer", ""))
    return SenderReport(**values)


@dataclasses.dataclass(frozen=True)
class Interval:
    """One interval of the link, as cps_msgs/LinkReport carries it."""

    seq: int
    interval_s: float
    sender_interval_s: float
    delivered_bytes: int
    unmanaged_bytes: int
    sent_bytes: int
    offered_bytes: int
    app_limited: bool
    rtt_s: tuple
    receiver_behind: bool
    sender_blocked_s: float
    # TCP payload bytes (framing included) received by the twin's link socket and sent by the
    # robots' over the two intervals (0: not readable)
    delivered_link_bytes: int
    sent_link_bytes: int
    acked_link_bytes: int  # the robots' link socket's, over sender_interval_s (its clock, as sent)
    sender_socket_full: float  # fraction of the robots' samples with its link socket full
    receive_queue_max_bytes: int
    send_queue_max_bytes: int
    superseded: int
    expired: int
    pacing_mbps: float
    peer: str
    # probe trains (cps_link.probe_train): their frames the twin received in the interval (in
    # delivered_bytes and unmanaged_bytes too) and the robots' bridge sent over its interval
    probe_bytes: int = 0
    probe_sent_bytes: int = 0
    # trains measured in the interval, and the last one's measured part: the link bytes that
    # arrived after its first message, over how long, the rate it was sent at (0: none) and how long
    # of it the twin's receiving thread waited for a CPU or the bridge's lock (NaN: not known)
    probe_trains: int = 0
    probe_train_bytes: int = 0
    probe_train_spread_s: float = 0.0
    probe_train_sent_mbps: float = 0.0
    probe_train_receiver_wait_s: float = math.nan
    probe_cost_mbps: float = 0.0  # the trains' mean cost at the robots' bridge's period now
    # trains the twin refused in the interval, by reason (cps_link.probe_train.PROBE_REFUSALS), e.g.
    # "receiver_late:2,out_of_order:1" ("" none): a rise seen late with no train measured says why
    probe_refused: str = ""


class _Mark(NamedTuple):
    """What closed an interval: the robots' report and the twin's counters when it came."""

    report: SenderReport
    now_s: float  # the twin's monotonic s
    delivered_bytes: int
    unmanaged_bytes: int
    link_received_bytes: int  # the twin's link socket's (0: not readable)
    probe_bytes: int
    link_sockets: int  # link sockets the twin had read so far


class ReportComposer:
    """The twin's side: counts what it receives (`received`), samples its socket's receive queue
    (`sample_receive_queue`) and makes an Interval of each robots' report (`on_report`). Not
    thread-safe: the bridge calls it under its lock."""

    def __init__(self, behind_bytes=RECEIVER_BEHIND_BYTES, behind_samples=RECEIVER_BEHIND_SAMPLES):
        self.delivered_bytes = 0
        self.unmanaged_bytes = 0
        self.behind_bytes, self.behind_samples = behind_bytes, behind_samples
        self.refused = dict.fromkeys(REPORT_REFUSALS, 0)
        self._last: Optional[_Mark] = None  # what closed the last interval
        self._queue_max = 0
        self._queue_high = 0
        self.probe_bytes = 0  # cumulative
        self._trains = []  # TrainMeasure of the interval
        self._refused_trains = collections.Counter()  # why -> trains refused in the interval

    def received(self, size_bytes, managed, probe=False):
        self.delivered_bytes += size_bytes
        if not managed:
            self.unmanaged_bytes += size_bytes
        if probe:
            self.probe_bytes += size_bytes

    def train_measured(self, measure):
        """A probe train measured (cps_link.probe_train.TrainMeasure): the interval reports the last."""
        self._trains.append(measure)

    def train_refused(self, why):
        """A probe train the twin could not measure (`why`: one of probe_train.PROBE_REFUSALS)."""
        self._refused_trains[why] += 1

    def sample_receive_queue(self, queue_bytes):
        """One sample of the link socket's receive queue (None: no socket found)."""
        if queue_bytes is None:
            return
        self._queue_max = max(self._queue_max, queue_bytes)
        self._queue_high += queue_bytes >= self.behind_bytes

    def on_report(self, payload, now_s, link_received_bytes=0, link_sockets=0) -> tuple:
        """(Interval, None) for a robots' report received at `now_s` (the twin's monotonic s), with
        the twin's link socket's cumulative TCP payload bytes received then (0: not readable) and
        how many link sockets the twin has read so far, or (None, why not: one of REPORT_REFUSALS,
        counted). An interval in which either side's link socket changed (a reconnection) carries
        no link bytes (0: not known): live, a robots' socket found late read 0 acked bytes for one
        interval and twice the link's rate for the next, and the manager took 38 Mbit/s for the
        20 Mbit/s link's capacity (test_over_link beside busy loops, 2026-11-30)."""
        try:
            report = decode_sender_report(payload)
        except ReportError:
            return self._refuse(BAD_REPORT)
        here = _Mark(
            report,
            now_s,
            self.delivered_bytes,
            self.unmanaged_bytes,
            link_received_bytes,
            self.probe_bytes,
            link_sockets,
        )
        last = self._last
        if last is None or last.report.session != report.session:
            self._start(here)
            return self._refuse(FIRST_OF_RUN)
        before = last.report
        if report.seq <= before.seq:
            return self._refuse(OLD_REPORT)
        counters = ("offered_bytes", "sent_bytes", "superseded", "expired")
        if (
            any(getattr(report, c) < getattr(before, c) for c in counters)
            or report.t_s <= before.t_s
            or 0 < link_received_bytes < last.link_received_bytes  # 0: not readable now, not a counter going down
            or 0 < report.link_sent_bytes < before.link_sent_bytes
            or 0 < report.link_acked_bytes < before.link_acked_bytes
            or report.probe_sent_bytes < before.probe_sent_bytes
        ):
            self._start(here)
            return self._refuse(COUNTER_BACKWARDS)
        interval_s, sender_interval_s = now_s - last.now_s, report.t_s - before.t_s
        if not (0 < interval_s <= MAX_INTERVAL_S and 0 < sender_interval_s <= MAX_INTERVAL_S):
            self._start(here)
            return self._refuse(FIRST_OF_RUN)
        behind = self._queue_high >= self.behind_samples
        train = self._trains[-1] if self._trains else None
        same_sockets = (report.link_sockets, link_sockets) == (before.link_sockets, last.link_sockets)

        def link_bytes(now, then):
            # a socket's counter over the interval: 0 (not known) where either end was not readable
            # or a link socket changed in between
            return now - then if now and then and same_sockets else 0

        interval = Interval(
            seq=report.seq,
            interval_s=interval_s,
            sender_interval_s=sender_interval_s,
            delivered_bytes=self.delivered_bytes - last.delivered_bytes,
            unmanaged_bytes=self.unmanaged_bytes - last.unmanaged_bytes,
            sent_bytes=report.sent_bytes - before.sent_bytes,
            offered_bytes=report.offered_bytes - before.offered_bytes,
            app_limited=report.app_limited,
            rtt_s=tuple(report.rtt_s),
            receiver_behind=behind,
            sender_blocked_s=report.blocked_s,
            delivered_link_bytes=link_bytes(link_received_bytes, last.link_received_bytes),
            sent_link_bytes=link_bytes(report.link_sent_bytes, before.link_sent_bytes),
            acked_link_bytes=link_bytes(report.link_acked_bytes, before.link_acked_bytes),
            sender_socket_full=report.socket_full_samples / report.socket_samples if report.socket_samples else 0.0,
            receive_queue_max_bytes=self._queue_max,
            send_queue_max_bytes=report.send_queue_max_bytes,
            superseded=report.superseded - before.superseded,
            expired=report.expired - before.expired,
            pacing_mbps=report.pacing_mbps,
            peer=report.peer,
            probe_bytes=self.probe_bytes - last.probe_bytes,
            probe_sent_bytes=report.probe_sent_bytes - before.probe_sent_bytes,
            probe_trains=len(self._trains),
            probe_train_bytes=train.bytes if train else 0,
            probe_train_spread_s=train.spread_s if train else 0.0,
            probe_train_sent_mbps=train.sent_mbps if train else 0.0,
            probe_train_receiver_wait_s=train.receiver_wait_s if train else math.nan,
            probe_cost_mbps=report.probe_cost_mbps,
            probe_refused=",".join(f"{why}:{n}" for why, n in sorted(self._refused_trains.items())),
        )
        self._start(here)
        return interval, None

    def _start(self, here):
        self._last = here
        self._queue_max = self._queue_high = 0
        self._trains = []
        self._refused_trains = collections.Counter()

    def _refuse(self, why):
        self.refused[why] += 1
        return None, why


class RoundTrips:
    """The robots' side of heartbeat round trips: each heartbeat carries (seq, send time); the twin
    echoes it at once; an echo's round trip is counted once, an unknown or repeated echo never."""

    def __init__(self, keep=64):
        self.keep = keep
        self._sent = {}
        self._seq = 0
        self.completed: List[float] = []

    def heartbeat(self, now_ns) -> bytes:
        self._seq += 1
        self._sent[self._seq] = now_ns
        for old in [s for s in self._sent if s <= self._seq - self.keep]:
            del self._sent[old]
        return HEARTBEAT.pack(self._seq, now_ns)

    def echo(self, payload, now_ns) -> Optional[float]:
        """The round trip of an echoed heartbeat (s), or None when it is not one we are waiting for."""
        if len(payload) != HEARTBEAT.size:
            return None
        seq, sent_ns = HEARTBEAT.unpack(bytes(payload))
        if self._sent.get(seq) != sent_ns:
            return None
        del self._sent[seq]
        rtt = (now_ns - sent_ns) * 1e-9
        self.completed.append(rtt)
        return rtt

    def take(self):
        """The round trips completed since the last call."""
        out, self.completed = self.completed, []
        return out


def _hex_port(address):
    return int(address.rsplit(":", 1)[1], 16)


def _tcp_sockets(local_port, remote_port, proc_root):
    """[(tx_queue, rx_queue, inode)] of the established sockets with that local / remote port."""
    out = []
    for name in ("tcp", "tcp6"):
        try:
            with open(f"{proc_root}/{name}") as stream:
                lines = stream.read().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            parts = line.split()
            if len(parts) < 5 or parts[3] != "01":  # 01: ESTABLISHED
                continue
            try:
                local, remote = _hex_port(parts[1]), _hex_port(parts[2])
                tx, rx = (int(v, 16) for v in parts[4].split(":"))
                inode = int(parts[9]) if len(parts) > 9 else 0
            except ValueError:
                continue
            if (local_port is None or local == local_port) and (remote_port is None or remote == remote_port):
                out.append((tx, rx, inode))
    return out


# struct tcp_info (linux/tcp.h), the fields read: srtt and min RTT (us), bytes acked, received and
# sent (the TCP payload: TLS, Zenoh and the bridge's frames, every byte the link carries but the
# TCP/IP headers), bytes not yet sent, the time limited by the receiver's window (us), and how long
# ago data last arrived (ms: a probe train's end, cps_link.probe_train), and the packets received
# out of order (bytes_received counts in-order bytes only: it jumps when a lost packet's
# retransmission fills the hole, which a probe train must not take for the link's pace).
_TCP_INFO_LEN = 232
_TCP_INFO_FIELDS = {
    "rtt_us": ("I", 68),
    "bytes_acked": ("Q", 120),
    "bytes_received": ("Q", 128),
    "notsent_bytes": ("I", 144),
    "min_rtt_us": ("I", 148),
    "rwnd_limited_us": ("Q", 176),
    "bytes_sent": ("Q", 200),
    "bytes_retrans": ("Q", 208),
    "last_data_recv_ms": ("I", 52),
    "rcv_ooopack": ("I", 224),
}


@dataclasses.dataclass(frozen=True)
class TcpInfo:
    rtt_us: int
    bytes_acked: int
    bytes_received: int
    notsent_bytes: int
    min_rtt_us: int
    rwnd_limited_us: int
    bytes_sent: int  # retransmissions included
    bytes_retrans: int
    # The socket's queues (ioctl SIOCOUTQ / SIOCINQ, /proc/net/tcp's tx_queue and rx_queue): bytes
    # unacked or not yet sent, and received but not yet read by the application.
    send_queue_bytes: int = 0
    receive_queue_bytes: int = 0
    last_data_recv_ms: int = 0  # how long ago the socket last received data (the kernel's, ms)
    rcv_ooopack: int = 0  # packets received out of order (a loss or reordering before them), cumulative
    # the monotonic s right after the kernel gave these counters (NaN: not read from a socket)
    read_s: float = math.nan

    @property
    def bytes_new(self):
        """Bytes sent for the first time (what the sender put on the link, retransmissions aside)."""
        return self.bytes_sent - self.bytes_retrans


def parse_tcp_info(raw) -> Optional[TcpInfo]:
    """The fields above from getsockopt(TCP_INFO)'s bytes (None when too short: an older kernel)."""
    if len(raw) < _TCP_INFO_LEN:
        return None
    return TcpInfo(
        **{name: struct.unpack_from("=" + kind, raw, at)[0] for name, (kind, at) in _TCP_INFO_FIELDS.items()}
    )


# How often LinkSockets looks in /proc/net/tcp for a new link socket while its known ones stay open.
# Parsing every socket of the namespace at each 10 Hz heartbeat (9.4 ms of CPU a scan here) was half
# of each bridge's CPU in test_zenoh_bridge (2026-11-28); a closed one is noticed at the next read.
LINK_SOCKET_RESCAN_S = 1.0


class LinkSockets:
    """TCP_INFO and queues of this process's own link sockets (Zenoh's, found by their port in
    /proc/net/tcp and their inode among /proc/self/fd), with cumulative byte counters that stay
    monotone across a reconnection (a new socket's counters start from the old ones' total).
    Not thread-safe."""

    def __init__(
        self,
        local_port=None,
        remote_port=None,
        proc_root="/proc/net",
        fd_root="/proc/self/fd",
        rescan_s=LINK_SOCKET_RESCAN_S,
        user_timeout_ms=0,
    ):
        self.local_port, self.remote_port = local_port, remote_port
        # TCP_USER_TIMEOUT set on each link socket found (0: left as it is), and the inodes set
        self.user_timeout_ms = user_timeout_ms
        self._timed = set()
        self.user_timeout_refused = 0  # sockets the kernel refused it for
        self.proc_root, self.fd_root = proc_root, fd_root
        self.rescan_s = rescan_s
        self._scanned_s = -math.inf  # monotonic s of the last look in /proc/net/tcp
        self._inodes = []  # the link sockets' inodes it found there
        self._fds = {}  # inode -> fd in this process
        self._last = {}  # inode -> TcpInfo at the last read
        self.sockets_found = 0  # link sockets read so far (one more: a reconnection)
        self._base = {"bytes_new": 0, "bytes_acked": 0, "bytes_received": 0, "rcv_ooopack": 0}
        # the monotonic s at which the last read's TCP_INFO were taken (NaN before one): the
        # instant its byte counters are true of, so an interval between two reads is measured
        # from these, not from when the caller began (the robots' report was stamped before it
        # took the bridge's lock: up to 38 ms early live). Taken right after getsockopt, not after
        # the queues' ioctls and the dup's close, which lets another thread take the GIL for up
        # to its 5 ms switch interval: a probe train's span measured between two late stamps.
        self.read_s = math.nan

    def _fd_of(self, inode):
        if inode in self._fds:
            return self._fds[inode]
        try:
            for name in os.listdir(self.fd_root):
                try:
                    if os.readlink(f"{self.fd_root}/{name}") == f"socket:[{inode}]":
                        self._fds[inode] = int(name)
                        return int(name)
                except OSError:
                    continue
        except OSError:
            pass
        return None

    def _still_open(self, inode):
        fd = self._fds.get(inode)
        try:
            return fd is not None and os.readlink(f"{self.fd_root}/{fd}") == f"socket:[{inode}]"
        except OSError:
            return False

    def _link_inodes(self):
        now = time.monotonic()
        if now - self._scanned_s >= self.rescan_s or not all(self._still_open(i) for i in self._inodes):
            self._scanned_s = now
            # this process's own only: another's socket on the port has no descriptor here, and
            # kept, it would read as closed at every read and bring the scan back each time
            found = _tcp_sockets(self.local_port, self.remote_port, self.proc_root)
            self._inodes = [i for _, _, i in found if i and self._fd_of(i) is not None]
        return self._inodes

    def read(self):
        """[TcpInfo] of the link sockets now ([] when none is ours or TCP_INFO is not readable)."""
        out, seen = [], set()
        for inode in self._link_inodes():
            fd = self._fd_of(inode)
            if fd is not None and self.user_timeout_ms and inode not in self._timed:
                self._timed.add(inode)
                self.user_timeout_refused += not _set_user_timeout(fd, self.user_timeout_ms)
            info = _tcp_info_of(fd) if fd is not None else None
            if info is None:
                continue
            self.read_s = info.read_s if math.isfinite(info.read_s) else time.monotonic()
            seen.add(inode)
            out.append(info)
            self.sockets_found += inode not in self._last
            self._last[inode] = info
        for inode in [i for i in self._last if i not in seen]:  # a closed socket: its bytes stay counted
            gone = self._last.pop(inode)
            for name in self._base:
                self._base[name] += getattr(gone, name)
            self._fds.pop(inode, None)
        return out

    def end_connections(self):
        """Shut down this process's link sockets (both ways; their owner sees the end of its
        connection and closes it); how many. For a session closed to be reopened: a transport Zenoh
        no longer held is not closed with it, and its connection would outlive it, the peer still
        holding the old session's token and subscriptions."""
        ended = 0
        for inode in self._link_inodes():
            fd = self._fd_of(inode)
            try:
                with _dup_socket(fd) as sock:
                    sock.shutdown(socket.SHUT_RDWR)
                ended += 1
            except (OSError, TypeError):  # closed meanwhile (TypeError: no descriptor left)
                continue
        return ended

    def totals(self):
        """{bytes_new (sent, retransmissions aside), bytes_acked, bytes_received, rcv_ooopack (packets
        received out of order)}: cumulative over every link socket so far."""
        return {name: base + sum(getattr(i, name) for i in self._last.values()) for name, base in self._base.items()}


_SIOCINQ, _SIOCOUTQ = termios.FIONREAD, termios.TIOCOUTQ  # linux/sockios.h: the same numbers


def _set_user_timeout(fd, timeout_ms):
    """TCP_USER_TIMEOUT of file descriptor `fd` of this process (the socket keeps the option);
    False when it cannot be set."""
    try:
        with _dup_socket(fd) as sock:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT, int(timeout_ms))
        return True
    except OSError:
        return False


def _dup_socket(fd):
    """A socket object on a dup of file descriptor `fd` of this process (closing it closes the dup
    only; options and shutdowns reach the socket itself). While a default socket timeout is set
    (rospy's 60 s) it puts the shared file non-blocking: harmless for Zenoh's link sockets, which
    are already (on another process's sockets it is not: cps_web.endpoint.SocketQueues)."""
    dup = os.dup(fd)
    try:
        return socket.socket(fileno=dup)
    except OSError:
        os.close(dup)
        raise


def _tcp_info_of(fd):
    """TCP_INFO of file descriptor `fd` of this process (a dup is read and closed; the socket stays)."""
    try:
        with _dup_socket(fd) as sock:
            raw = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, _TCP_INFO_LEN)
            read_s = time.monotonic()
            info = parse_tcp_info(raw)
            if info is None:
                return None
            send, receive = (
                struct.unpack("i", fcntl.ioctl(sock.fileno(), op, b"\0" * 4))[0] for op in (_SIOCOUTQ, _SIOCINQ)
            )
            return dataclasses.replace(info, send_queue_bytes=send, receive_queue_bytes=receive, read_s=read_s)
    except OSError:
        return None
