"""The robots' bridge's send queue (cps_link.send_queue), no ROS: order, pacing, drop rules, and
app-limited marking."""

import math

import pytest

from cps_link.send_queue import EXPIRED, LINK_DOWN, PACING_MIN_BURST_BYTES, SUPERSEDED, Pacer, SendQueue

RANKS = {"video": 3, "data": 4}  # bridge.yaml's data_high and data


def _queue(rate=None):
    q = SendQueue(RANKS, now_s=0.0)
    if rate is not None:
        q.set_rate(rate, 0.0)
    return q


def _drain(q, now_s):
    out = []
    while True:
        item, _ = q.take(now_s)
        if item is None:
            return out
        out.append(item)


def test_video_leaves_before_clouds_and_each_class_in_arrival_order():
    q = _queue()
    q.offer("data", ("cloud", "scout"), 100, "c1", 0.0)
    q.offer("data", ("cloud", "iris"), 100, "c2", 0.0)
    q.offer("video", ("video", "jackal"), 100, "v1", 0.0)
    assert _drain(q, 0.0) == ["v1", "c1", "c2"]


def test_a_newer_frame_of_the_same_topic_and_source_takes_the_older_ones_place():
    q = _queue()
    q.offer("data", "a", 100, "a1", 0.0)
    q.offer("data", "b", 100, "b1", 0.0)
    assert q.offer("data", "a", 300, "a2", 0.1) == SUPERSEDED
    assert _drain(q, 0.1) == ["a2", "b1"]  # a's place in line kept: a steady stream is never starved
    c = q.snapshot()
    assert c.dropped[SUPERSEDED] == 1 and c.dropped_bytes[SUPERSEDED] == 100
    assert c.offered_bytes == 500


def test_a_frame_past_its_age_is_dropped_not_sent():
    q = _queue()
    q.offer("video", "v", 1000, "old", 0.0, max_age_s=0.5)
    q.offer("data", "c", 1000, "fresh", 0.0, max_age_s=1.0)
    assert _drain(q, 0.6) == ["fresh"]
    assert q.snapshot().dropped[EXPIRED] == 1 and q.snapshot().dropped_bytes[EXPIRED] == 1000
    q.offer("video", "v", 10, "born_stale", 1.0, max_age_s=-0.1)  # older than its bound on arrival
    assert _drain(q, 1.0) == [] and q.snapshot().dropped[EXPIRED] == 2


def test_the_pacer_holds_the_average_rate_and_urgent_bytes_count_against_it():
    rate = 100_000.0  # bytes/s
    q = _queue(rate)
    sent, t = 0, 0.0
    for i in range(400):  # 20 kB frames offered far faster than the rate, for 4 s
        t = i * 0.01
        q.offer("data", ("c", i), 20_000, 20_000, t)
        for item in _drain(q, t):
            sent += item
    # 4 s at 100 kB/s, plus at most one burst and one frame of debt
    assert sent <= 4.0 * rate + PACING_MIN_BURST_BYTES + 20_000
    assert sent >= 4.0 * rate - 20_000
    # urgent frames are charged too: after 100 kB of telemetry, a frame waits about a second
    q2 = _queue(rate)
    q2.urgent(100_000, 0.0)
    q2.offer("data", "c", 1000, "c", 0.0)
    item, wait = q2.take(0.0)
    assert item is None and wait == pytest.approx(1.0, abs=0.01)
    assert q2.take(1.0)[0] == "c"
    assert q2.snapshot().sent_bytes == 100_000 and q2.snapshot().offered_bytes == 101_000


def test_unpaced_until_a_rate_is_known_and_bad_rates_refused():
    p = Pacer(0.0)
    p.charge(10**9, 0.0)
    assert p.wait_s(0.0) == 0.0 and p.burst_bytes == math.inf
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError):
            p.set_rate(bad, 0.0)
    p.set_rate(1000.0, 0.0)
    p.charge(2000, 0.0)
    assert p.wait_s(0.0) == pytest.approx(2.0) and p.wait_s(1.0) == pytest.approx(1.0)
    p.set_rate(None, 1.0)
    assert p.wait_s(1.0) == 0.0


def test_nothing_leaves_while_the_link_is_down_and_what_waited_is_dropped():
    q = _queue()
    q.offer("data", "c", 100, "c", 0.0)
    q.set_link_up(False)
    assert q.snapshot().dropped[LINK_DOWN] == 1
    q.offer("data", "d", 100, "d", 0.1)
    assert q.take(0.1) == (None, None)
    q.set_link_up(True)
    assert _drain(q, 0.2) == ["d"]


def test_app_limited_when_the_sender_finds_nothing_while_it_could_send():
    q = _queue(rate=1000.0)
    q.app_limited_since_last(0.0)
    q.offer("data", "c", 5000, "c", 0.0)
    assert q.take(0.0)[0] == "c"  # leaves on the burst, into debt
    q.offer("data", "d", 5000, "d", 0.0)
    assert q.take(0.0)[0] is None  # waits for the pacer: paced, not app-limited
    assert not q.app_limited_since_last(0.1)
    assert _drain(q, 10.0) == ["d"]
    q.take(20.0)  # found empty while the pacer would let it send
    assert q.app_limited_since_last(20.0)
    assert q.app_limited_since_last(21.0)  # still empty and allowed: an idle sender is app-limited
    assert q.waiting() == (0, 0)


def test_every_frame_a_rule_drops_is_told_with_its_rule_for_the_routes_ledger():
    told = []
    q = SendQueue(RANKS, now_s=0.0, on_drop=lambda rule, item: told.append((rule, item)))
    q.offer("data", "a", 100, "a1", 0.0)
    q.offer("data", "a", 100, "a2", 0.1)  # supersedes a1
    q.offer("video", "v", 100, "v1", 0.1, max_age_s=0.2)
    assert _drain(q, 0.5) == ["a2"]  # v1 expired
    q.offer("data", "b", 100, "b1", 0.6)
    q.set_link_up(False)
    assert told == [(SUPERSEDED, "a1"), (EXPIRED, "v1"), (LINK_DOWN, "b1")]
    c = q.snapshot()
    assert sum(c.dropped.values()) == len(told)
