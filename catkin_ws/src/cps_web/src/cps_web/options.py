"""The endpoint's, the recorder's and the player's settings, one per private parameter of their nodes (same name)."""

import dataclasses

from cps_web.endpoint import (
    DEFAULT_BACKLOG,
    DEFAULT_HOST,
    DEFAULT_PORT,
    DEFAULT_QUEUE,
    DEFAULT_STALL_HOLD_S,
    DEFAULT_STALLED_BYTES,
)


def _option(default, meaning, unit="", **bounds):
    return dataclasses.field(default=default, metadata=dict(meaning=meaning, unit=unit, bounds=bounds))


@dataclasses.dataclass(frozen=True)
class EndpointOptions:
    """The Foxglove endpoint node's settings."""

    fleet_file: str = _option("", "fleet.yaml (empty: cps_bringup's)", "path")
    robots: str = _option("", "comma-separated robots to show (empty: the whole fleet)")
    listen: str = _option(f"{DEFAULT_HOST}:{DEFAULT_PORT}", "host:port the WebSocket listens on (port 0: any free one)")
    queue_size: int = _option(
        DEFAULT_QUEUE, "offers waiting for conversion; beyond it they are dropped, counted", low=1
    )
    backlog: int = _option(DEFAULT_BACKLOG, "messages the SDK holds per viewer before dropping its oldest", low=1)
    stalled_bytes: int = _option(
        DEFAULT_STALLED_BYTES,
        "unsent bytes in a viewer's socket from which it counts as not reading; while every viewer is "
        "there, nothing is converted (counted as stalled)",
        "B",
        low=1,
    )
    stall_hold_s: float = _option(
        DEFAULT_STALL_HOLD_S,
        "after this long with no viewer reading, the map, tf and video are unsubscribed until one reads again",
        "s",
        low=0.0,
    )
    nice: int = _option(
        10,
        "the node's nice, below the map server's (0) and its receive process's (5): when the twin's CPU is "
        "short, the map goes first",
        "",
        low=0,
        high=19,
    )
    scene_period_s: float = _option(0.2, "how often the robots' poses and trails are sent", "s", low=0.02)
    status_period_s: float = _option(1.0, "how often fleet health, the link and the counters are sent", "s", low=0.1)
    url_file: str = _option("", "write the endpoint's ws:// URL here once it listens (empty: none)", "path")


@dataclasses.dataclass(frozen=True)
class RecorderOptions:
    """The MCAP recorder node's settings."""

    path: str = _option("", "the MCAP file to write", "path")
    topics: str = _option("", "comma-separated resolved topics to record")
    chunk_bytes: int = _option(4 * 1024 * 1024, "MCAP chunk size before compression", "B", low=1024)
    compression: str = _option("lz4", "chunk compression: lz4, zstd or none")
    backlog_mbytes: float = _option(
        256.0, "messages waiting for the writer; beyond it they are dropped, counted", "MB", low=1.0
    )


@dataclasses.dataclass(frozen=True)
class PlayerOptions:
    """The MCAP player node's settings."""

    path: str = _option("", "the ROS 1 MCAP file to play", "path")
    topics: str = _option("", "comma-separated topics to play (empty: every topic)")
    delay_s: float = _option(
        0.0, "wait after advertising, before the first message (subscribers connect)", "s", low=0.0
    )
    clock_hz: float = _option(100.0, "how often /clock is published between messages", "Hz", low=1.0)
    queue_size: int = _option(100, "messages each publisher queues per subscriber (rosbag play's default)", low=1)
    keep_alive: bool = _option(
        False, "after the last message, run the clock on until shut down, so that slow subscribers get what is queued"
    )


def parameters(kind):
    """(name, meaning with unit and default) of each private parameter, for --help."""
    out = []
    for field in dataclasses.fields(kind):
        unit = f" [{field.metadata['unit']}]" if field.metadata["unit"] else ""
        out.append((field.name, f"{field.metadata['meaning']}{unit} (default {field.default!r})"))
    return out


def read_options(kind):
    """`kind` (a dataclass above) from the node's private parameters, range-checked."""
    from cps_ros.params import param

    values = {}
    for field in dataclasses.fields(kind):
        values[field.name] = param(f"~{field.name}", field.default, type(field.default), **field.metadata["bounds"])
    return kind(**values)
