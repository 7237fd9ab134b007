"""A ROS 1 MCAP read for a replay (what it holds, or why it cannot be played) and played at its
recorded pace with /clock at the log time, on a fake clock."""

import io

import pytest
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from cps_fleet import names
from cps_web.mcap_recording import McapRecording
from cps_web.mcap_replay import Player, ReplayError, channels_of, is_mcap_file, raw_class, read_summary

T0 = 1_700_000_000_000_000_000  # ns: a log time as a wall-clock recording has it
ODOM = names.absolute(names.robot_topic("jackal", names.ODOM))
CLOUD = names.absolute(names.robot_topic("jackal", names.POINTS))


def _raw(msg):
    buff = io.BytesIO()
    msg.serialize(buff)
    return buff.getvalue()


def _write(path, log_times_s=(0.0, 0.5, 1.0)):
    recording = McapRecording(str(path), chunk_bytes=1024)
    for i, t in enumerate(log_times_s):
        odom = Odometry(header=Header(seq=100 + i, frame_id=names.robot_topic("jackal", names.ODOM)))
        recording.write(ODOM, odom._type, Odometry._full_text, _raw(odom), log_time_ns=T0 + int(t * 1e9))
    cloud = PointCloud2(header=Header(frame_id="jackal/camera_depth_optical_frame"), width=3, data=bytes(3))
    recording.write(CLOUD, cloud._type, PointCloud2._full_text, _raw(cloud), log_time_ns=T0 + 200_000_000)
    recording.close()
    return str(path)


def test_summary_gives_topics_counts_frames_and_span(tmp_path):
    path = _write(tmp_path / "m.mcap")
    assert is_mcap_file(path) and not is_mcap_file(str(tmp_path / "absent.mcap"))
    summary = read_summary(path, cloud_topics=[CLOUD, names.absolute(names.robot_topic("scout", names.POINTS))])
    assert summary.topics == {ODOM: ("nav_msgs/Odometry", 3), CLOUD: ("sensor_msgs/PointCloud2", 1)}
    assert summary.cloud_frames == {CLOUD: "jackal/camera_depth_optical_frame"}
    assert summary.duration_s == pytest.approx(1.0)


def test_unfinished_other_profile_and_junk_are_refused_with_the_reason(tmp_path):
    path = _write(tmp_path / "m.mcap")
    data = open(path, "rb").read()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    with pytest.raises(ReplayError, match="not finished by its writer"):
        read_summary(str(tmp_path / "cut.mcap"))
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap at all")
    with pytest.raises(ReplayError, match="not an MCAP file"):
        read_summary(str(tmp_path / "junk.mcap"))
    from mcap.writer import Writer

    with open(tmp_path / "ros2.mcap", "wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2", library="test")
        writer.finish()
    with pytest.raises(ReplayError, match="'ros2' profile messages, not ROS 1"):
        read_summary(str(tmp_path / "ros2.mcap"))


def test_a_raw_class_publishes_the_stored_bytes_with_the_types_md5():
    kind = raw_class("nav_msgs/Odometry", Odometry._full_text)
    assert (kind._type, kind._md5sum) == ("nav_msgs/Odometry", Odometry._md5sum)
    buff = io.BytesIO()
    kind(b"\x01\x02").serialize(buff)
    assert buff.getvalue() == b"\x01\x02" and not kind._has_header  # rospy leaves the seq as recorded


class FakeClock:
    def __init__(self):
        self.now = 0.0

    def monotonic(self):
        return self.now

    def sleep(self, seconds):
        self.now += seconds


def test_player_keeps_the_recorded_pace_and_clock_after_its_delay(tmp_path):
    path = _write(tmp_path / "m.mcap")
    channels = channels_of(path)
    clock, published, clocks = FakeClock(), [], []
    player = Player(path, topics=[ODOM, CLOUD], delay_s=2.0, clock_period_s=0.01)

    played = player.run(
        lambda channel, data: published.append((clock.now, channels[channel].topic, data)),
        clocks.append,
        monotonic=clock.monotonic,
        sleep=clock.sleep,
    )

    assert played == 4
    assert [(round(t, 6), topic) for t, topic, _ in published] == [
        (2.0, ODOM),
        (2.2, CLOUD),
        (2.5, ODOM),
        (3.0, ODOM),
    ]
    odom = Odometry()
    odom.deserialize(published[-1][2])
    assert odom.header.seq == 102  # as recorded
    assert clocks == sorted(clocks) and clocks[0] == T0 and clocks[-1] == T0 + 1_000_000_000
    assert len(clocks) >= 100  # ~100 Hz between messages, as rosbag play --clock


def test_player_sends_each_clock_time_once_and_no_tick_between_close_messages(tmp_path):
    """Every node on /use_sim_time takes every /clock message: dense messages (odometry every 2 ms,
    two at each log time, as a recording of a replay holds them) bring one clock per log time,
    ahead of its messages, and none in between; a longer gap still ticks at the clock period."""
    times = [i * 0.002 for i in range(200) for _ in (0, 1)] + [1.0]  # 0.4 s dense, then a 0.6 s gap
    path = _write(tmp_path / "dense.mcap", log_times_s=times)
    clock, events = FakeClock(), []
    player = Player(path, topics=[ODOM], clock_period_s=0.01)

    played = player.run(
        lambda channel, data: events.append(("message", data)),
        lambda ns: events.append(("clock", ns)),
        monotonic=clock.monotonic,
        sleep=clock.sleep,
    )

    assert played == len(times)
    clocks = [ns for kind, ns in events if kind == "clock"]
    assert clocks == sorted(set(clocks)) and player.clocks_published == len(clocks)
    last_clock = None
    for kind, value in events:  # each message after a clock at (or past) its log time
        if kind == "clock":
            last_clock = value
        else:
            odom = Odometry()
            odom.deserialize(value)
            assert last_clock >= T0 + int(times[odom.header.seq - 100] * 1e9)
    dense = [ns for ns in clocks if ns < T0 + 400_000_000]
    assert len(dense) == 200  # one per log time, none between messages 2 ms apart
    gap = [ns for ns in clocks if T0 + 400_000_000 < ns < T0 + 1_000_000_000]
    assert 50 <= len(gap) <= 61  # 0.6 s at 100 Hz


def test_player_kept_alive_runs_the_clock_on_after_the_last_message_until_stopped(tmp_path):
    """As rosbag play -k: the process stays up (a publisher's queue to a slow subscriber is lost
    when its process exits) and the clock moves on past the recording's end, at the clock period."""
    path = _write(tmp_path / "m.mcap")
    clock, clocks = FakeClock(), []
    player = Player(path, topics=[ODOM, CLOUD], clock_period_s=0.01, keep_alive=True)

    played = player.run(
        lambda c, d: None, clocks.append, stopped=lambda: clock.now >= 5.0, monotonic=clock.monotonic, sleep=clock.sleep
    )

    assert played == 4
    end_ns = T0 + 1_000_000_000
    after = [ns for ns in clocks if ns > end_ns]
    assert clocks == sorted(set(clocks)) and after and after[-1] >= T0 + 4_900_000_000
    assert 380 <= len(after) <= 401  # 4 s at 100 Hz
    idle, sleeps = FakeClock(), []  # kept alive with nothing to play: it waits, a clock period at a time

    def idle_sleep(seconds):
        assert seconds > 0, "a busy wait"  # before: sleep(0) over and over, a core spent
        sleeps.append(seconds)
        idle.sleep(seconds)

    empty = Player(path, topics=["/no_such_topic"], clock_period_s=0.01, keep_alive=True)
    assert empty.run(lambda c, d: None, clocks.append, lambda: idle.now >= 1.0, idle.monotonic, idle_sleep) == 0
    assert 95 <= len(sleeps) <= 101
    other = FakeClock()  # not kept alive: returns at the last message
    assert Player(path).run(lambda c, d: None, lambda ns: None, monotonic=other.monotonic, sleep=other.sleep) == 4
    assert other.now < 1.1


def test_player_plays_only_the_topics_asked_and_stops_when_told(tmp_path):
    path = _write(tmp_path / "m.mcap")
    assert {c.topic for c in channels_of(path, [ODOM]).values()} == {ODOM}
    clock, published = FakeClock(), []
    player = Player(path, topics=[ODOM])
    player.run(lambda c, d: published.append(c), lambda ns: None, monotonic=clock.monotonic, sleep=clock.sleep)
    assert len(published) == 3
    stopped = Player(path).run(
        lambda c, d: None, lambda ns: None, stopped=lambda: True, monotonic=clock.monotonic, sleep=clock.sleep
    )
    assert stopped == 0
