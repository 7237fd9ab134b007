"""A ROS 1 MCAP played into the graph as `rosbag play --clock` plays a bag (rospy-free: the node publishes).

Any MCAP of the `ros1` profile (cps_web's recorder's, or a bag converted by the mcap tools): each
message is published as it is stored (its bytes, its recorded header seq), on a publisher whose
type, md5sum and definition come from the channel's stored `ros1msg` schema, paced by its log time
(what rosbag record stores as the receive time), and /clock follows the log time, so every node on
/use_sim_time runs on the recording's clock.

`read_summary` reads what a replay check needs (topics, types and counts, the first cloud's frame
per cloud topic, the child frames tf carries, the span) and says why a file cannot be played.
"""

import dataclasses
import os
import time
from typing import Callable, Dict, Iterable, Optional, Tuple

import genpy
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap_ros1.decoder import DecoderFactory

# An MCAP file starts and ends with this magic; a writer that did not finish left no closing one.
MCAP_MAGIC = b"\x89MCAP0\r\n"
ROS1_PROFILE = "ros1"
TF_STATIC = "/tf_static"  # latched by convention (tf2's static broadcaster)
# tf messages read for the child frames it carries (the static ones come first).
TF_MESSAGES_READ = 500


class ReplayError(ValueError):
    """The MCAP cannot be played; the message says why."""


def is_mcap_file(path: str) -> bool:
    """True if the file at `path` starts with the MCAP magic (False if unreadable)."""
    try:
        with open(path, "rb") as stream:
            return stream.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    except OSError:
        return False


@dataclasses.dataclass(frozen=True)
class McapSummary:
    """topic -> (ROS type, messages); the first cloud frame per cloud topic; tf's child frames;
    first to last log time, s; the last log time, s (the clock a replay publishes ends there)."""

    topics: Dict[str, Tuple[str, int]]
    cloud_frames: Dict[str, str]
    tf_child_frames: Tuple[str, ...]
    duration_s: float
    end_s: float


def _open_checked(path, stream):
    """The reader of a finished ros1-profile MCAP, else ReplayError."""
    head = stream.read(len(MCAP_MAGIC))
    stream.seek(max(0, os.path.getsize(path) - len(MCAP_MAGIC)))
    tail = stream.read()
    stream.seek(0)
    if head != MCAP_MAGIC:
        raise ReplayError(f"{path}: not an MCAP file (no MCAP magic at its start)")
    if tail != MCAP_MAGIC:
        raise ReplayError(
            f"{path} was not finished by its writer (no closing MCAP magic: its last chunk and its index are "
            f"missing); `mcap recover` may rebuild it"
        )
    reader = make_reader(stream, decoder_factories=[DecoderFactory()])
    profile = reader.get_header().profile
    if profile != ROS1_PROFILE:
        raise ReplayError(
            f"{path} holds '{profile or 'no'}' profile messages, not ROS 1 ('{ROS1_PROFILE}'): "
            f"a replay plays ROS 1 messages into the ROS 1 graph"
        )
    return reader


def read_summary(path: str, cloud_topics: Iterable[str] = (), tf_topics: Iterable[str] = ()) -> McapSummary:
    """What `path` holds (ReplayError if it is not a finished, readable ROS 1 MCAP)."""
    cloud_topics, tf_topics = list(cloud_topics), list(tf_topics)
    try:
        with open(path, "rb") as stream:
            reader = _open_checked(path, stream)
            summary = reader.get_summary()
            topics: Dict[str, Tuple[str, int]] = {}
            if summary is not None and summary.statistics is not None:
                stats = summary.statistics
                for channel_id, count in stats.channel_message_counts.items():
                    channel = summary.channels[channel_id]
                    schema = summary.schemas.get(channel.schema_id)
                    kind = schema.name if schema else ""
                    topics[channel.topic] = (kind, topics.get(channel.topic, (kind, 0))[1] + count)
                start, end = stats.message_start_time, stats.message_end_time
            else:  # no statistics (optional in MCAP): count by reading every message
                start = end = None
                for schema, channel, message in reader.iter_messages(log_time_order=False):
                    kind = schema.name if schema else ""
                    topics[channel.topic] = (kind, topics.get(channel.topic, (kind, 0))[1] + 1)
                    start = message.log_time if start is None else min(start, message.log_time)
                    end = message.log_time if end is None else max(end, message.log_time)
            frames = {}
            wanted = [t for t in cloud_topics if t in topics]
            for _schema, channel, _message, cloud in reader.iter_decoded_messages(topics=wanted) if wanted else ():
                frames.setdefault(channel.topic, cloud.header.frame_id)
                if len(frames) == len(wanted):
                    break
            children = set()
            present = [t for t in tf_topics if t in topics]
            decoded = reader.iter_decoded_messages(topics=present) if present else ()
            for count, (_schema, _channel, _message, tf) in enumerate(decoded):
                children.update(t.child_frame_id.lstrip("/") for t in tf.transforms)
                if count >= TF_MESSAGES_READ:
                    break
    except ReplayError:
        raise
    except (McapError, OSError, ValueError, KeyError, AttributeError) as exc:
        raise ReplayError(f"{path}: not a readable ROS 1 MCAP ({type(exc).__name__}: {exc})") from exc
    duration = (end - start) / 1e9 if topics and start is not None else 0.0
    end_s = end / 1e9 if topics and end is not None else 0.0
    return McapSummary(topics, frames, tuple(sorted(children)), duration, end_s)


class RawMessage(genpy.Message):
    """Base of the classes `raw_class` makes: a stored message published as it is (rospy writes
    `serialize`'s bytes); no header, so rospy does not renumber the recorded seq."""

    __slots__ = ("_buff",)
    _has_header = False

    def __init__(self, buff: bytes = b""):
        self._buff = buff

    def serialize(self, buff):
        buff.write(self._buff)


def raw_class(type_name: str, definition: str, base=RawMessage):
    """A publishable class for `type_name` from its stored definition: its md5sum is computed from
    the definition (as rosbag does for a type it has no class of), so subscribers accept it."""
    from genpy import dynamic

    generated = dynamic.generate_dynamic(type_name, definition)[type_name]
    return type(
        f"Raw_{type_name.replace('/', '_')}",
        (base,),
        {"__slots__": (), "_type": type_name, "_md5sum": generated._md5sum, "_full_text": definition},
    )


@dataclasses.dataclass
class Channel:
    """One channel the player publishes: topic, type, definition, latched."""

    topic: str
    type_name: str
    definition: str
    latched: bool


def channels_of(path: str, topics: Optional[Iterable[str]] = None) -> Dict[int, Channel]:
    """channel id -> Channel of each ros1 channel on `topics` (all if None) in the MCAP at `path`."""
    wanted = None if topics is None else set(topics)
    with open(path, "rb") as stream:
        reader = _open_checked(path, stream)
        summary = reader.get_summary()
        if summary is None:
            raise ReplayError(f"{path} has no summary section (the channels' index): `mcap recover` may rebuild it")
        out = {}
        for channel_id, channel in summary.channels.items():
            if wanted is not None and channel.topic not in wanted:
                continue
            schema = summary.schemas.get(channel.schema_id)
            if channel.message_encoding != "ros1" or schema is None or schema.encoding != "ros1msg":
                raise ReplayError(
                    f"{path}: {channel.topic} is encoded as '{channel.message_encoding}' "
                    f"({schema.encoding if schema else 'no'} schema), not ros1"
                )
            latched = channel.topic == TF_STATIC or channel.metadata.get("latching") == "1"
            out[channel_id] = Channel(channel.topic, schema.name, schema.data.decode(), latched)
    return out


class Player:
    """Plays the messages of `path` on `topics` in log-time order at their recorded pace, after
    `delay_s` (subscribers connect first, as `rosbag play -d`): `publish(channel_id, data)` for each
    message, `publish_clock(ns)` at its log time before it and every `clock_period_s` while no
    message comes (rosbag play's --clock at 100 Hz). The clock only moves forward: a time already
    published is not published again (messages recorded at one log time share one), and a wait
    shorter than `clock_period_s` publishes none in between. `stopped()` True ends it early.
    `keep_alive` (rosbag play -k): after the last message the clock runs on until `stopped()`, so
    that what the publishers still queue for slow subscribers reaches them (a player that exits drops
    it). Returns the messages published."""

    def __init__(
        self,
        path: str,
        topics: Optional[Iterable[str]] = None,
        delay_s: float = 0.0,
        clock_period_s=0.01,
        keep_alive: bool = False,
    ):
        self.path = path
        self.topics = None if topics is None else list(topics)
        self.delay_s = delay_s
        self.clock_period_s = clock_period_s
        self.keep_alive = keep_alive
        self.published = 0
        self.clocks_published = 0

    def run(
        self,
        publish: Callable[[int, bytes], None],
        publish_clock: Callable[[int], None],
        stopped: Callable[[], bool] = lambda: False,
        monotonic: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> int:
        start_wall = monotonic() + self.delay_s
        while monotonic() < start_wall and not stopped():
            sleep(min(0.05, max(0.0, start_wall - monotonic())))
        first_ns = last_clock_ns = None
        next_clock_wall = 0.0  # when the clock is due again if no message moves it first

        def clock_at(ns, now):
            # Every node on /use_sim_time takes each /clock message. One before every message and
            # one more per wait cost each of the reference mission's ~15 rospy nodes 1-1.5 CPU-s
            # more in its MCAP's replay than in its bag's under rosbag play (2026-11-29).
            nonlocal last_clock_ns, next_clock_wall
            if last_clock_ns is None or ns > last_clock_ns:
                publish_clock(ns)
                last_clock_ns = ns
                self.clocks_published += 1
            next_clock_wall = now + self.clock_period_s

        with open(self.path, "rb") as stream:
            reader = _open_checked(self.path, stream)
            for _schema, channel, message in reader.iter_messages(topics=self.topics, log_time_order=True):
                if first_ns is None:
                    first_ns, start_wall = message.log_time, monotonic()
                due = start_wall + (message.log_time - first_ns) / 1e9
                while not stopped():
                    now = monotonic()
                    if now >= due:
                        break
                    if now >= next_clock_wall:
                        clock_at(first_ns + int((now - start_wall) * 1e9), now)
                    sleep(min(next_clock_wall, due) - now)
                if stopped():
                    break
                clock_at(message.log_time, monotonic())
                publish(channel.id, message.data)
                self.published += 1
        while self.keep_alive and not stopped():
            if first_ns is None:  # nothing played: no clock to run on
                sleep(self.clock_period_s)
                continue
            now = monotonic()
            if now >= next_clock_wall:
                clock_at(first_ns + int((now - start_wall) * 1e9), now)
            sleep(max(0.0, next_clock_wall - monotonic()))
        return self.published
