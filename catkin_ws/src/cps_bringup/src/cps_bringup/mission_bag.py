"""Which topics a mission bag holds, and whether a bag fits a fleet (before replaying it).

A mission bag (`cps_bringup ... --record`) holds the physical side's sensor, odometry and tf
topics and the twin's managed inputs. `--replay` plays only the physical topics, under the bag's
own clock (`rosbag play --clock`, every node with /use_sim_time): the clouds keep their recorded
stamps, tf is looked up at those stamps and the tissue's latency is measured against the replayed
clock, so replay latency is the tissue's own, not the time since the recording.

A mission recorded as MCAP (`--record FILE.mcap`, or any ROS 1 MCAP) is checked and replayed the
same way, by cps_web's MCAP player in place of rosbag play; which one a file is, its first bytes say.
"""

import dataclasses
from typing import Dict, List, Tuple

from cps_fleet import names
from cps_fleet.fleet import FleetConfig

TF, TF_STATIC = names.TF, names.TF_STATIC
# Per robot, relative to /<r>: what the robot's side publishes and the replay feeds to the tissue.
PHYSICAL_TOPICS = (names.ODOM, names.JOINT_STATES, names.BATTERY)


class BagError(ValueError):
    """The bag cannot be replayed for this fleet; the message says why."""


def _rt(robot, name):
    return names.absolute(names.robot_topic(robot, name))


def cloud_topic(fleet: FleetConfig, robot: str) -> str:
    return _rt(robot, fleet.robot(robot).cloud_topic)


def replay_topics(fleet: FleetConfig) -> List[str]:
    """The physical side's topics: what `rosbag play` publishes in place of the robots."""
    topics = []
    for robot in fleet.robot_names:
        topics.append(cloud_topic(fleet, robot))
        topics += [_rt(robot, t) for t in PHYSICAL_TOPICS]
    return topics + [TF, TF_STATIC]


def record_topics(fleet: FleetConfig) -> List[str]:
    """The physical topics plus the managed clouds the twin receives (for inspection, not replayed)."""
    return replay_topics(fleet) + [names.absolute(names.managed_cloud(r)) for r in fleet.robot_names]


def required_topics(fleet: FleetConfig) -> List[str]:
    """What a replay cannot do without: each robot's cloud and odometry, and tf."""
    return [t for r in fleet.robot_names for t in (cloud_topic(fleet, r), _rt(r, names.ODOM))] + [TF]


@dataclasses.dataclass(frozen=True)
class BagContents:
    """What check_bag read: topic -> (type, message count), the first cloud frame per cloud topic,
    the child frames tf carries, the bag's duration and its last message's time (s, the bag's clock)."""

    topics: Dict[str, Tuple[str, int]]
    cloud_frames: Dict[str, str]
    tf_child_frames: Tuple[str, ...]
    duration_s: float
    end_s: float


def is_mcap_recording(path: str) -> bool:
    """True for an MCAP file (its magic) or a name ending in .mcap; else a rosbag."""
    from cps_web.mcap_replay import is_mcap_file

    return path.lower().endswith(".mcap") or is_mcap_file(path)


def read_bag(path: str, cloud_topics) -> BagContents:
    """Topics, first cloud frames and tf child frames of the bag or ROS 1 MCAP at `path` (BagError
    if unreadable)."""
    if is_mcap_recording(path):
        return _read_mcap(path, cloud_topics)
    import rosbag

    try:
        bag = rosbag.Bag(path)
    except Exception as exc:  # rosbag raises ROSBagException, OSError, ...
        raise BagError(f"{path}: not a readable rosbag ({exc})") from exc
    with bag:
        info = bag.get_type_and_topic_info().topics
        topics = {name: (t.msg_type, t.message_count) for name, t in info.items()}
        frames = {}
        wanted = [t for t in cloud_topics if t in topics]
        # read_messages(topics=[]) would read every topic.
        for topic, msg, _ in bag.read_messages(topics=wanted) if wanted else ():
            frames.setdefault(topic, msg.header.frame_id)
            if len(frames) == len(wanted):
                break
        children = set()
        tf_topics = [t for t in (TF, TF_STATIC) if t in topics]
        for count, (_, msg, _) in enumerate(bag.read_messages(topics=tf_topics) if tf_topics else ()):
            children.update(t.child_frame_id.lstrip("/") for t in msg.transforms)
            if count > 500:
                break
        duration = bag.get_end_time() - bag.get_start_time() if topics else 0.0
        end_s = bag.get_end_time() if topics else 0.0
    return BagContents(topics, frames, tuple(sorted(children)), duration, end_s)


def _read_mcap(path, cloud_topics) -> BagContents:
    from cps_web.mcap_replay import ReplayError, read_summary

    try:
        summary = read_summary(path, cloud_topics, (TF, TF_STATIC))
    except ReplayError as exc:
        raise BagError(str(exc)) from exc
    return BagContents(summary.topics, summary.cloud_frames, summary.tf_child_frames, summary.duration_s, summary.end_s)


def check_bag(path: str, fleet: FleetConfig) -> BagContents:
    """The bag's contents if it can feed `fleet`'s tissue and twin; else BagError naming what is
    missing or why the bag belongs to another fleet (other robots, other sensor frames)."""
    clouds = {cloud_topic(fleet, r): r for r in fleet.robot_names}
    contents = read_bag(path, clouds)
    problems = []
    recorded_robots = sorted(
        {t.split("/")[1] for t in contents.topics if t.count("/") >= 2 and t.endswith("/" + names.ODOM)}
    )
    ours = set(fleet.robot_names)
    if recorded_robots and not ours & set(recorded_robots):
        raise BagError(
            f"{path} was recorded for another fleet: it holds robots {', '.join(recorded_robots)}, "
            f"the fleet ({fleet.path}) has {', '.join(fleet.robot_names)}"
        )
    missing = [t for t in required_topics(fleet) if t not in contents.topics]
    if missing:
        problems.append(f"missing topics: {', '.join(missing)}")
        if any(names.absolute(names.managed_cloud_at_twin(r)) in contents.topics for r in fleet.robot_names):
            problems.append(
                "it holds the clouds as the twin received them: a --record-link-only recording (what crossed "
                "the link) cannot stand in for the robots' sensors"
            )
    for topic, robot in clouds.items():
        kind = contents.topics.get(topic, (None,))[0]
        if kind and kind != "sensor_msgs/PointCloud2":
            problems.append(f"{topic} is {kind}, not sensor_msgs/PointCloud2")
        frame = contents.cloud_frames.get(topic)
        expected = fleet.robot(robot).sensor_frame
        if frame is not None and frame.lstrip("/") != expected:
            problems.append(
                f"{topic} is in frame '{frame}', the fleet's {robot} senses in '{expected}' "
                f"(recorded for another fleet or robot type?)"
            )
    if contents.tf_child_frames:
        absent = [f"{r}/odom" for r in fleet.robot_names if f"{r}/odom" not in contents.tf_child_frames]
        if absent:
            problems.append(f"tf has no {', '.join(absent)} (map -> <robot>/odom on /tf_static)")
    if problems:
        raise BagError(f"{path} cannot be replayed for the fleet {fleet.path}:\n  " + "\n  ".join(problems))
    return contents


def finish_recording(path: str, recorder_log: str = None) -> str:
    """Make sure the mission's bag exists at `path` once the recorder has stopped.

    rosbag record writes `<path>.active` and renames it when it closes cleanly. A recorder that was
    killed (a slow disk, a stop timeout) leaves an unindexed `.active` file: it is reindexed
    (`rosbag reindex`) and moved into place, so the recorded messages are not lost. Returns what was
    done; BagError if there is no bag at all, with the recorder's last log lines.
    """
    import os
    import subprocess

    if path.lower().endswith(".mcap"):
        return _finished_mcap(path, recorder_log)
    if os.path.exists(path):
        return f"recorded {path}"
    active = path + ".active"
    if os.path.exists(active):
        result = subprocess.run(["rosbag", "reindex", "--quiet", active], capture_output=True, text=True)
        if result.returncode != 0:
            raise BagError(
                f"{active} was left unclosed by the recorder and could not be reindexed: "
                f"{(result.stderr or result.stdout).strip()[-500:]}"
            )
        os.replace(active, path)
        backup = os.path.splitext(active)[0] + ".orig.active"
        if os.path.exists(backup):
            os.remove(backup)
        return f"the recorder did not close {path}; reindexed it from {active}"
    tail = ""
    if recorder_log and os.path.exists(recorder_log):
        with open(recorder_log, errors="replace") as log:
            tail = "".join(log.readlines()[-8:])
    raise BagError(
        f"no bag was written to {path} (nor {active}); the recorder's log {recorder_log or '(none)'} ends:\n{tail}"
    )


def _log_tail(recorder_log):
    import os

    if recorder_log and os.path.exists(recorder_log):
        with open(recorder_log, errors="replace") as log:
            return "".join(log.readlines()[-8:])
    return ""


def _finished_mcap(path: str, recorder_log: str = None) -> str:
    """The MCAP at `path` if its recorder finished it (summary and closing magic written), else
    BagError with the recorder's last log lines: a recorder killed mid-chunk loses that chunk."""
    import os

    from cps_web.mcap_replay import MCAP_MAGIC

    if not os.path.exists(path):
        raise BagError(f"no MCAP was written to {path}; the recorder's log ends:\n{_log_tail(recorder_log)}")
    with open(path, "rb") as stream:
        head = stream.read(len(MCAP_MAGIC))
        stream.seek(max(0, os.path.getsize(path) - len(MCAP_MAGIC)))
        tail = stream.read()
    if head != MCAP_MAGIC or tail != MCAP_MAGIC:
        raise BagError(
            f"{path} was not finished by its recorder (no closing MCAP magic: its last chunk is lost and it "
            f"has no index); the recorder's log ends:\n{_log_tail(recorder_log)}"
        )
    return f"recorded {path} ({os.path.getsize(path) / 1e6:.1f} MB, MCAP)"
