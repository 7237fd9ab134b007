"""The ledger's counter names and sequence gaps, without ROS."""

import pytest

from cps_ros import cloud_ledger as C

pytestmark = pytest.mark.unit


def test_a_gap_in_a_sources_numbers_is_what_was_missed_and_a_restart_is_no_gap():
    gaps = C.SequenceGaps()
    assert [gaps.note("/a", s) for s in (1, 2, 5, 6)] == [0, 0, 2, 0]
    assert gaps.note("/b", 10) == 0  # another source: its own numbers
    assert gaps.note("/a", 1) == 0 and gaps.note("/a", 3) == 1  # /a restarted: counted from its new run
    assert (gaps.received, gaps.missed) == (7, 3)


def test_keys_name_their_stage_and_parse_back():
    key = C.key(C.BRIDGE_OUT, C.DROPPED + "outage")
    assert key == "ledger_bridge_out_dropped_outage"
    assert C.parse_key(key) == (C.BRIDGE_OUT, "dropped_outage")
    assert C.parse_key("ledger_limiter_received") == (C.LIMITER, "received")
    assert C.parse_key("invalid_messages") is None and C.parse_key("ledger_nowhere_x") is None
