"""The per-cloud ledger from the nodes' counters: rows that balance, each drop with the cause the
node that saw it gave, the clouds still on their way when counting stopped, and INCOMPLETE (by how
many) when a node's counts do not add up or were never recorded."""

import pytest
from mission_files import mission

from cps_experiments.ledger import (
    AT_MAP,
    AT_TWIN,
    CAPTURED,
    INSERTED,
    SUPERSEDED,
    TO_LINK,
    cumulative,
    map_server_counters,
    node_counters,
    read_ledger,
    robot_ledger,
)
from cps_fleet import names
from cps_ros import cloud_ledger as C

pytestmark = pytest.mark.unit
R = "scout"


def _counters(**stages):
    """node_counters-like {topic: {stage: {what: n}}} for scout."""
    topics = {
        C.ENCODER: names.absolute(names.robot_topic(R, names.POINTS_FILTERED)),
        C.LIMITER: names.absolute(names.robot_topic(R, names.POINTS_DRACO)),
        C.BRIDGE_OUT: names.absolute(names.managed_cloud(R)),
        C.BRIDGE_IN: names.absolute(names.managed_cloud_at_twin(R)),
        C.DECODER: names.absolute(names.managed_cloud_at_twin(R)),
    }
    out = {}
    for stage, values in stages.items():
        out.setdefault(topics[stage], {})[stage] = values
    return out


def _chain(n, limiter_dropped=0):
    passed = n - limiter_dropped
    return dict(
        encoder={C.RECEIVED: n, C.OUT: n},
        limiter={C.RECEIVED: n, C.OUT: passed, "dropped_rate_limiter": limiter_dropped},
        bridge_out={C.RECEIVED: passed, C.OUT: passed},
        bridge_in={C.RECEIVED: passed, C.OUT: passed},
        decoder={C.RECEIVED: passed, C.OUT: passed},
    )


def test_a_mission_whose_every_cloud_is_accounted_for_balances():
    ledger = robot_ledger(
        R,
        _counters(**_chain(100, limiter_dropped=30)),
        {"clouds_received": 70, "clouds_inserted": 60, "clouds_superseded": 10, "queue_length": 0},
        duration_s=50,
    )
    assert ledger.balanced, ledger.problems
    assert ledger.stage(CAPTURED) == 100 and ledger.stage(TO_LINK) == 70 and ledger.stage(AT_MAP) == 70
    assert dict(ledger.drops) == {"rate limiter: above the rate the manager allocated": 30}
    assert dict(ledger.ends) == {INSERTED: 60, SUPERSEDED: 10}


def test_each_loss_is_counted_by_the_node_that_saw_it_with_its_cause():
    """The robots' bridge missed 3 in its subscriber queue and withheld 10 during an outage (4 kept
    as keyframes, later sent); the twin's bridge saw 15 gaps: 10 withheld, so 5 lost on the link;
    it dropped 2 as stale; the map server dropped 1 without a transform."""
    stages = _chain(100)
    stages["bridge_out"] = {
        C.RECEIVED: 97,
        C.MISSED: 3,
        C.OUT: 87,
        "dropped_outage": 6,
        C.BACKFILL_KEPT: 4,
        C.BACKFILL_SENT: 4,
    }
    stages["bridge_in"] = {C.RECEIVED: 82, C.MISSED: 15, C.OUT: 80, "dropped_stale": 2}
    stages["decoder"] = {C.RECEIVED: 80, C.OUT: 80}
    counters = _counters(**stages)
    counters[names.absolute(names.in_twin(names.robot_topic(R, names.POINTS_BACKFILL_DRACO)))] = {
        C.BRIDGE_IN: {C.RECEIVED: 4, C.OUT: 4},
        C.DECODER: {C.RECEIVED: 4, C.OUT: 4},
    }
    server = {"clouds_received": 84, "clouds_inserted": 80, "clouds_superseded": 3, "clouds_dropped_tf": 1}
    ledger = robot_ledger(R, counters, server, duration_s=50)
    assert ledger.balanced, ledger.problems
    drops = dict(ledger.drops)
    assert drops == {
        "rate limiter → robots' bridge: subscriber queue": 3,
        "link down: the robots' bridge held it back, no keyframe kept": 6,
        "link: put on the link, never received": 5,
        "twin's bridge: stale": 2,
        "map server: no transform at the cloud's stamp": 1,
    }
    assert ledger.stage(AT_TWIN) == 80 and ledger.stage(AT_MAP) == 84


def test_clouds_the_robots_send_queue_dropped_by_rule_are_withheld_not_lost_on_the_link():
    """The robots' bridge numbered 100 clouds and its send queue dropped 7 (5 superseded by a newer
    one, 2 expired): the twin's bridge's 9 gaps are those 7 and 2 lost on the link."""
    stages = _chain(100)
    stages["bridge_out"] = {C.RECEIVED: 100, C.OUT: 93, "dropped_superseded": 5, "dropped_expired": 2}
    stages["bridge_in"] = {C.RECEIVED: 91, C.MISSED: 9, C.OUT: 91}
    stages["decoder"] = {C.RECEIVED: 91, C.OUT: 91}
    server = {"clouds_received": 91, "clouds_inserted": 91}
    ledger = robot_ledger(R, _counters(**stages), server, duration_s=50)
    assert ledger.balanced, ledger.problems
    assert dict(ledger.drops) == {
        "robots' bridge's send queue: superseded": 5,
        "robots' bridge's send queue: expired": 2,
        "link: put on the link, never received": 2,
    }


def test_clouds_withheld_at_the_end_are_not_gaps_yet_and_beyond_the_allowance_are_unaccounted():
    """The robots' send queue dropped the last cloud it numbered before counting stopped: no later
    frame has shown the twin that gap yet (the reference mission of 2026-11-28 11:30: -1). Many
    more withheld than the twin's gaps is still an imbalance."""
    stages = _chain(100)
    stages["bridge_out"] = {C.RECEIVED: 100, C.OUT: 96, "dropped_superseded": 4}
    stages["bridge_in"] = {C.RECEIVED: 96, C.MISSED: 3, C.OUT: 96}
    stages["decoder"] = {C.RECEIVED: 96, C.OUT: 96}
    server = {"clouds_received": 96, "clouds_inserted": 96}
    ledger = robot_ledger(R, _counters(**stages), server, duration_s=50)
    assert ledger.balanced, ledger.problems
    assert ledger.in_flight == 1 and "link: put on the link, never received" not in dict(ledger.drops)
    stages["bridge_out"] = {C.RECEIVED: 100, C.OUT: 60, "dropped_superseded": 40}
    stages["bridge_in"] = {C.RECEIVED: 60, C.MISSED: 3, C.OUT: 60}
    stages["decoder"] = {C.RECEIVED: 60, C.OUT: 60}
    server = {"clouds_received": 60, "clouds_inserted": 60}
    ledger = robot_ledger(R, _counters(**stages), server, duration_s=50)
    assert not ledger.balanced and any("withheld clouds" in p for p in ledger.problems), ledger.problems


def test_a_map_server_that_decodes_what_it_inserts_closes_the_ledger_without_a_decoder_process():
    """Issue 37: the twin's bridge hands the map server its live clouds and the keyframes after an
    outage still compressed; the map server missed 2 in its subscriber queue and found 10 undecodable."""
    stages = _chain(100)
    del stages["decoder"]
    stages["bridge_out"] = {C.RECEIVED: 100, C.OUT: 96, C.BACKFILL_KEPT: 4, C.BACKFILL_SENT: 4}
    stages["bridge_in"] = {C.RECEIVED: 96, C.MISSED: 4, C.OUT: 96}
    counters = _counters(**stages)
    counters[names.absolute(names.in_twin(names.robot_topic(R, names.POINTS_BACKFILL_DRACO)))] = {
        C.BRIDGE_IN: {C.RECEIVED: 4, C.OUT: 4},
    }
    server = {
        "clouds_received": 98,
        "clouds_missed_upstream": 2,
        "clouds_inserted": 71,
        "clouds_superseded": 16,
        "clouds_dropped_decoder": 10,
        "queue_length": 1,
    }
    ledger = robot_ledger(R, counters, server, duration_s=50)
    assert ledger.balanced and not ledger.problems, ledger.problems
    assert dict(ledger.drops) == {
        "twin's bridge → map server: subscriber queue": 2,
        "map server: undecodable cloud": 10,
    }
    assert ledger.stage(AT_MAP) == 98
    server["clouds_dropped_decoder"] = 0  # the undecodable clouds in no counter
    assert robot_ledger(R, counters, server, duration_s=50).unaccounted == 10


def test_clouds_on_their_way_when_counting_stopped_are_in_flight_up_to_two_seconds_of_them():
    stages = _chain(100)
    stages["decoder"] = {C.RECEIVED: 97, C.OUT: 97}  # 3 still between the bridge and the decoder
    server = {"clouds_received": 97, "clouds_inserted": 97}
    ledger = robot_ledger(R, _counters(**stages), server, duration_s=50)  # 2 Hz: 4 may be on the way
    assert ledger.balanced and ledger.in_flight == 3
    stages["decoder"] = {C.RECEIVED: 80, C.OUT: 80}
    ledger = robot_ledger(R, _counters(**stages), {"clouds_received": 80, "clouds_inserted": 80}, duration_s=50)
    assert not ledger.balanced and ledger.unaccounted == 20
    assert "twin's bridge → decoder: 100 passed on, 80 received or missed" in ledger.problems[0]


def test_a_node_whose_counts_do_not_add_up_is_unaccounted():
    stages = _chain(100)
    stages["limiter"] = {C.RECEIVED: 100, C.OUT: 70}  # 30 neither forwarded nor counted as dropped
    stages.update({k: {C.RECEIVED: 70, C.OUT: 70} for k in ("bridge_out", "bridge_in", "decoder")})
    ledger = robot_ledger(R, _counters(**stages), {"clouds_received": 70, "clouds_inserted": 70}, duration_s=50)
    assert (
        ledger.unaccounted == 30 and "rate limiter: received and passed on or dropped differ by +30" in ledger.problems
    )


def test_without_node_counters_the_statistics_counts_show_what_has_no_cause():
    """The committed demo's files: only the statistics' arrivals and the map server's inserted."""
    ledger = robot_ledger(R, {}, {"clouds_inserted": 949}, duration_s=75, stats_captured=970, stats_at_twin=964)
    assert not ledger.balanced and ledger.unaccounted == 21
    assert ledger.problems[0].startswith("counters not recorded: Draco encoder, rate limiter, robots' bridge")
    assert ("received at the twin (statistics' count)", 964) in ledger.stages


def test_a_restarted_node_counts_both_runs():
    assert cumulative([1, 5, 9, 2, 4]) == 13
    rows = [
        {"time_s": "1", "node": "/n", "input_topic": "/t", "key": "ledger_decoder_received", "value": "5"},
        {"time_s": "2", "node": "/n", "input_topic": "/t", "key": "ledger_decoder_received", "value": "2"},
        {"time_s": "3", "node": "/n", "input_topic": "/t", "key": "invalid_messages", "value": "9"},
    ]
    assert node_counters(rows)["/t"]["decoder"]["received"] == 7
    waiting = [  # a gauge: what is in the backfill store now, not a running count
        {"time_s": "1", "node": "/b", "input_topic": "/m", "key": "ledger_bridge_out_backfill_waiting", "value": "7"},
        {"time_s": "2", "node": "/b", "input_topic": "/m", "key": "ledger_bridge_out_backfill_waiting", "value": "0"},
    ]
    assert node_counters(waiting)["/m"]["bridge_out"]["backfill_waiting"] == 0
    servers = map_server_counters(
        [
            {"time_s": "1", "robot": R, "clouds_inserted": "10", "clouds_received": "11", "queue_length": "1"},
            {"time_s": "2", "robot": R, "clouds_inserted": "3", "clouds_received": "3", "queue_length": "0"},
            {"time_s": "3", "robot": R, "mission_state": "end", "clouds_inserted": ""},
        ]
    )
    assert servers[R] == {"clouds_inserted": 13, "clouds_received": 14, "queue_length": 0}


def test_a_missions_files_give_its_ledger_and_its_markdown(tmp_path):
    folder = mission(tmp_path / "m", lost_in_limiter_queue=2)
    ledger = read_ledger(str(folder), ["scout", "jackal"])
    assert all(r.balanced for r in ledger.robots.values()), [r.problems for r in ledger.robots.values()]
    assert dict(ledger.robots["scout"].drops) == {"Draco encoder → rate limiter: subscriber queue": 2}
    text = "\n".join(ledger.markdown())
    assert "## Cloud ledger" in text and "| scout | 120 | 120 | 118 | 118 | 118 | 118 | 2 | 0 | 0 | balances |" in text
    assert "| Draco encoder → rate limiter: subscriber queue | 2 | 2 |" in text
