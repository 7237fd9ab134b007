"""The teleop command stream (cps_gui.command_stream), without Qt or ROS: a steady period on its own
thread, one final zero, and nothing once the GUI thread stops renewing its lease."""

import threading

import pytest

from cps_gui.command_stream import CommandSchedule, CommandStream


def test_the_schedule_sends_at_once_then_every_period_and_does_not_make_up_missed_ticks():
    s = CommandSchedule(period_s=0.1, lease_s=0.35)
    assert s.due(0.0) == (None, None)  # not driving: nothing, wait to be told
    assert s.drive("jackal", "ahead", 10.0) == ("jackal", "ahead")
    assert s.drive("jackal", "left", 10.02) is None  # the next period sends the newest
    assert s.due(10.05) == (None, pytest.approx(0.05))
    assert s.due(10.1) == (("jackal", "left"), pytest.approx(0.1))
    s.renew(10.15)
    assert s.due(10.2) == (("jackal", "left"), pytest.approx(0.1))
    s.renew(10.45)
    what, wait_s = s.due(10.47)  # 0.17 s late: one command, not two, and the next a period on
    assert what == ("jackal", "left") and wait_s == pytest.approx(0.1)
    assert s.drive("iris", "up", 10.5) == ("iris", "up")  # another robot: at once


def test_the_schedule_stops_with_one_final_command_and_sends_nothing_after():
    s = CommandSchedule(period_s=0.1, lease_s=0.35)
    assert s.stop("zero") is None  # not driving: nothing to stop
    s.drive("scout", "ahead", 0.0)
    assert s.stop("zero") == ("scout", "zero")
    assert s.stop("zero") is None
    assert s.due(5.0) == (None, None)
    s.renew(5.0)  # a renewal while stopped starts nothing
    assert s.due(5.0) == (None, None)


def test_a_lapsed_lease_sends_nothing_until_renewed_then_at_once():
    s = CommandSchedule(period_s=0.1, lease_s=0.35)
    s.drive("scout", "ahead", 0.0)
    assert s.due(0.1)[0] == ("scout", "ahead")
    assert s.due(0.3)[0] == ("scout", "ahead")
    assert s.due(0.36) == (None, None)  # the GUI thread held off past its lease: silent
    assert s.due(2.0) == (None, None) and s.lapses == 1
    s.renew(2.0)
    assert s.due(2.0)[0] == ("scout", "ahead")  # back: at once, then every period
    assert s.due(2.05) == (None, pytest.approx(0.05))
    assert s.lapses == 1


@pytest.mark.parametrize("period_s,lease_s", [(0.0, 1.0), (0.1, -1.0), (float("nan"), 1.0)])
def test_a_schedule_without_a_positive_period_and_lease_is_refused(period_s, lease_s):
    with pytest.raises(ValueError, match="must be > 0"):
        CommandSchedule(period_s, lease_s)


def test_the_stream_sends_from_its_thread_and_nothing_after_stop_returns():
    sent, enough = [], threading.Event()

    def send(robot, command):
        sent.append((threading.current_thread().name, robot, command))
        if len(sent) >= 4:
            enough.set()

    stream = CommandStream(send, period_s=0.02, lease_s=10.0)
    try:
        stream.drive("jackal", "ahead")
        assert sent[0][1:] == ("jackal", "ahead")  # the first at once, on the caller's thread
        assert enough.wait(10.0), sent
        assert stream.stop(final="zero") and not stream.driving
        after_stop = len(sent)
        assert sent[-1][1:] == ("jackal", "zero")
        assert {name for name, _, command in sent[1:-1]} == {"teleop-commands"}
    finally:
        stream.close()
    assert len(sent) == after_stop and stream.sent == after_stop
    with pytest.raises(RuntimeError, match="closed"):
        stream.drive("jackal", "ahead")


def test_a_send_that_raises_is_counted_and_the_stream_goes_on():
    calls, twice = [], threading.Event()

    def send(robot, command):
        calls.append(command)
        if len(calls) >= 2:
            twice.set()
        raise OSError("publisher closed")

    stream = CommandStream(send, period_s=0.02, lease_s=10.0)
    try:
        stream.drive("jackal", "ahead")
        assert twice.wait(10.0)
    finally:
        stream.close(final="zero")
    assert stream.send_errors >= 2 and stream.sent == 0 and "publisher closed" in stream.last_error
