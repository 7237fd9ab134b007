"""SetpointFilter: hysteresis, the minimum interval, what goes out at once, and the budget."""

import math
import random

import pytest

from cps_bw_manager.setpoints import (
    BUDGET,
    CHANGE,
    ECHO,
    ECHO_GRACE_S,
    FIRST,
    LEVEL,
    ON_OFF,
    OPERATOR,
    PROBE,
    RULE,
    SetpointFilter,
    Target,
)

CLOUD = ("a", "cloud")
VIDEO = ("a", "video")
OTHER = ("b", "cloud")


def _sent(out):
    return {c.key: c for changes in out.values() for c in changes}


def test_the_first_setpoint_goes_out_and_is_batched_per_robot():
    f = SetpointFilter()
    out = f.decide(0.0, {CLOUD: Target(1, 5.0), VIDEO: Target(2, 5.0), OTHER: Target(1, 3.0)})
    assert set(out) == {"a", "b"} and len(out["a"]) == 2
    assert all(c.reason == FIRST and c.level_changed and c.rate_changed for c in _sent(out).values())
    assert f.in_force(CLOUD) == (1, 5.0) and f.sent_count == 3


def test_noise_inside_the_deadband_sends_nothing_however_long_it_lasts():
    f = SetpointFilter(rate_deadband=0.2, min_interval_s=5.0)
    f.decide(0.0, {CLOUD: Target(1, 5.0)})
    rng = random.Random(3)
    for k in range(1, 2000):  # 1000 s of updates at 2 Hz, the target wandering +-19 %
        assert not f.decide(k * 0.5, {CLOUD: Target(1, 5.0 * (1 + rng.uniform(-0.19, 0.19)))})
    assert f.sent_count == 1


def test_a_material_rate_change_waits_for_the_minimum_interval():
    f = SetpointFilter(rate_deadband=0.2, min_interval_s=5.0)
    f.decide(0.0, {CLOUD: Target(1, 5.0)})
    assert not f.decide(1.0, {CLOUD: Target(1, 8.0)})  # material, but 1 s after the last
    assert not f.decide(4.9, {CLOUD: Target(1, 8.0)})
    change = _sent(f.decide(5.0, {CLOUD: Target(1, 8.0)}))[CLOUD]
    assert change.reason == CHANGE and change.rate_hz == 8.0 and not change.level_changed


def test_at_most_one_setpoint_per_stream_per_interval_under_any_rate_noise():
    f = SetpointFilter(rate_deadband=0.2, min_interval_s=5.0)
    rng = random.Random(7)
    times = {}
    for k in range(4000):
        now = k * 0.25
        for key, changes in _sent(f.decide(now, {CLOUD: Target(1, rng.uniform(0.5, 30.0))})).items():
            times.setdefault(key, []).append(now)
    gaps = [b - a for a, b in zip(times[CLOUD], times[CLOUD][1:])]
    assert gaps and min(gaps) >= 5.0


def test_a_coarser_level_an_off_video_and_a_broken_rule_go_out_at_once():
    f = SetpointFilter(min_interval_s=5.0)
    f.decide(0.0, {CLOUD: Target(1, 5.0), VIDEO: Target(2, 5.0)})
    out = _sent(f.decide(0.5, {CLOUD: Target(2, 5.0), VIDEO: Target(2, 0.0)}))
    assert out[CLOUD].reason == LEVEL and out[CLOUD].level_changed and not out[CLOUD].rate_changed
    assert out[VIDEO].reason == ON_OFF and out[VIDEO].rate_hz == 0.0
    # the operator selects the robot: 15 Hz guaranteed, 0.5 s later
    out = _sent(f.decide(1.0, {VIDEO: Target(2, 15.0, min_rate_hz=15.0)}))
    assert out[VIDEO].reason == ON_OFF
    f.decide(10.0, {VIDEO: Target(2, 5.0)})  # after the interval: down to 5 Hz
    out = _sent(f.decide(10.5, {VIDEO: Target(1, 15.0, min_rate_hz=15.0)}))
    assert out[VIDEO].reason == LEVEL
    f.decide(20.0, {VIDEO: Target(1, 5.0)})
    assert _sent(f.decide(20.5, {VIDEO: Target(1, 15.0, min_rate_hz=15.0)}))[VIDEO].reason == RULE


def test_held_decreases_go_out_as_soon_as_the_rates_in_force_overrun_the_budget():
    f = SetpointFilter(rate_deadband=0.2, min_interval_s=5.0)
    targets = {CLOUD: Target(1, 10.0, message_bytes=100000.0), OTHER: Target(1, 10.0, message_bytes=100000.0)}
    f.decide(0.0, targets, budget_mbytes_per_s=2.0)
    # The budget drops by 10 %: each target 9 Hz, inside the deadband, but 20 Hz x 0.1 MB > 1.8 MB/s.
    lower = {k: Target(1, 9.0, message_bytes=100000.0) for k in targets}
    out = _sent(f.decide(1.0, lower, budget_mbytes_per_s=1.8))
    assert {c.reason for c in out.values()} == {BUDGET} and all(c.rate_hz == 9.0 for c in out.values())
    # Within the budget a held decrease stays held.
    assert not f.decide(2.0, {k: Target(1, 8.0, message_bytes=100000.0) for k in targets}, budget_mbytes_per_s=1.8)


def test_bad_settings_and_times_are_refused():
    with pytest.raises(ValueError):
        SetpointFilter(rate_deadband=1.0)
    with pytest.raises(ValueError):
        SetpointFilter(min_interval_s=-1.0)
    with pytest.raises(ValueError):
        SetpointFilter().decide(math.nan, {})


def test_while_the_link_is_idle_a_lower_rate_waits_and_a_higher_one_goes():
    f = SetpointFilter(rate_deadband=0.2, min_interval_s=5.0)
    f.decide(0.0, {CLOUD: Target(1, 1.5)})
    assert not f.decide(10.0, {CLOUD: Target(1, 0.6)}, link_idle=True)  # nobody needs what it frees
    assert _sent(f.decide(20.0, {CLOUD: Target(1, 2.0)}, link_idle=True))[CLOUD].rate_hz == 2.0
    assert _sent(f.decide(30.0, {CLOUD: Target(1, 0.6)}, link_idle=False))[CLOUD].reason == CHANGE


def test_a_clouds_limiter_slack_above_what_it_can_send_moves_without_a_setpoint():
    """Live (fig13_live, 16 robots, 60 Mbit/s, session 20): on the idle link each cloud's limiter
    slack rose 7.8 -> 10.4 -> 16.8 -> 30 Hz, one setpoint every 5 s, while the cloud sent ~2.5 Hz
    (its usable rate): the rate it runs at never changed. Rates are compared up to what the
    stream can send; a stream held below that still gets its rise."""
    f = SetpointFilter(rate_deadband=0.2, min_interval_s=5.0)
    f.decide(0.0, {CLOUD: Target(0, 7.8, usable_hz=2.5)}, link_idle=True)
    for k, slack_hz in enumerate((10.4, 16.8, 30.0, 12.0), start=1):
        assert not f.decide(5.0 * k, {CLOUD: Target(0, slack_hz, usable_hz=2.5)}, link_idle=True)
        assert not f.decide(5.0 * k, {CLOUD: Target(0, slack_hz, usable_hz=2.6)}, link_idle=False, probing=True)
    # its sensor sped up past the limiter: the rise goes (the whole slack) once the interval passed
    change = _sent(f.decide(30.0, {CLOUD: Target(0, 16.8, usable_hz=9.9)}, link_idle=True))[CLOUD]
    assert change.reason == CHANGE and change.rate_hz == 16.8
    # a video has no such bound: its rate is what it renders
    f.decide(0.0, {VIDEO: Target(2, 8.0)})
    assert _sent(f.decide(5.0, {VIDEO: Target(2, 12.0)}))[VIDEO].reason == CHANGE


def test_a_finer_level_waits_the_interval_after_the_last_level_change_and_never_flaps():
    """Live at 16 robots a cloud went 1, 0, 1, 0, 1 within 10 s (three changes in 200 ms): shedding
    detail goes out at once, buying it back waits min_interval_s after the stream's last level change."""
    f = SetpointFilter(min_interval_s=5.0)
    f.decide(0.0, {CLOUD: Target(1, 5.0)})
    assert not f.decide(1.0, {CLOUD: Target(0, 5.0)})  # finer, 1 s after the first setpoint
    assert _sent(f.decide(3.0, {CLOUD: Target(2, 5.0)}))[CLOUD].reason == LEVEL  # coarser: at once
    levels = []
    for k in range(40):  # 20 s of a target flipping between two leaves at every update
        out = _sent(f.decide(3.5 + 0.5 * k, {CLOUD: Target(1 + k % 2, 5.0)}))
        levels += [(3.5 + 0.5 * k, out[CLOUD].level)] if CLOUD in out else []
    finer = [t for (t, level), (_, before) in zip(levels, [(3.0, 2)] + levels) if level < before]
    assert finer and min(b - a for a, b in zip([3.0] + finer, finer)) >= 5.0
    assert f.in_force(CLOUD)[0] in (1, 2)
    # a broken rule takes the finer level at once
    g = SetpointFilter(rate_deadband=0.2, min_interval_s=5.0)
    g.decide(0.0, {CLOUD: Target(1, 5.0)})
    g.decide(5.0, {CLOUD: Target(2, 5.0)})
    change = _sent(g.decide(6.0, {CLOUD: Target(1, 5.0, min_rate_hz=8.0)}))[CLOUD]
    assert change.reason == LEVEL and change.level == 1  # a rule needs it: at once
    g.decide(7.0, {VIDEO: Target(2, 5.0)})  # the video's first setpoint
    assert not g.decide(7.5, {VIDEO: Target(1, 5.0)})  # finer: waits
    assert _sent(g.decide(8.0, {VIDEO: Target(1, 5.0, operator=True)}))[VIDEO].reason == LEVEL  # selected: at once
    # the operator's video back up to its rate at once (fig13_live: held 5 s at 18 Hz after a moment's
    # CPU shortage); another stream's rise waits its 5 s; within the deadband nothing goes out
    assert _sent(g.decide(8.5, {VIDEO: Target(1, 18.0, operator=True), CLOUD: Target(1, 5.0)}))[VIDEO].rate_hz == 18.0
    out = _sent(g.decide(9.0, {VIDEO: Target(1, 30.0, operator=True), CLOUD: Target(1, 9.0)}))
    assert out[VIDEO].reason == OPERATOR and out[VIDEO].rate_hz == 30.0 and CLOUD not in out
    assert not g.decide(9.5, {VIDEO: Target(1, 33.0, operator=True), CLOUD: Target(1, 9.0)})
    h = SetpointFilter(min_interval_s=5.0)
    h.decide(0.0, {VIDEO: Target(1, 5.0)})
    h.decide(8.0, {VIDEO: Target(2, 5.0)})
    change = _sent(h.decide(10.0, {VIDEO: Target(1, 0.0)}))[VIDEO]  # turned off while a finer level waits
    assert change.reason == ON_OFF and change.level == 2 and not change.level_changed


def test_while_the_estimator_probes_a_higher_rate_goes_at_once_and_a_lower_one_still_waits():
    """Issue 35: a probe measures nothing unless the fleet fills it within its 1.5 s."""
    f = SetpointFilter(rate_deadband=0.2, min_interval_s=5.0)
    f.decide(0.0, {CLOUD: Target(1, 5.0)})
    assert not f.decide(1.0, {CLOUD: Target(1, 5.5)})  # not probing: held
    change = _sent(f.decide(1.0, {CLOUD: Target(1, 5.5)}, probing=True))[CLOUD]
    assert change.reason == PROBE and change.rate_hz == 5.5
    assert not f.decide(1.5, {CLOUD: Target(1, 5.0)}, probing=True)  # a lower one is no probe


def test_a_lost_setpoint_is_sent_again_once_the_encoder_echoes_another_rate():
    """Live (CI, TCPROS over the shaped link): two decisions published out of order left a limiter
    at 24.7 Hz while the filter held 16.1 Hz in force, inside the deadband of every later target."""
    f = SetpointFilter(rate_deadband=0.2, min_interval_s=5.0)
    f.decide(0.0, {CLOUD: Target(2, 16.0)})
    assert not f.echo(CLOUD, 16.0, 2, 3.0)  # the one in force
    assert not f.decide(3.0, {CLOUD: Target(2, 15.0)})  # inside the deadband: nothing
    assert not f.echo(CLOUD, 24.7, 2, ECHO_GRACE_S - 0.1)
    assert f.echo(CLOUD, 24.7, 2, 3.5)
    change = _sent(f.decide(3.6, {CLOUD: Target(2, 15.0)}))[CLOUD]
    # both fields again, the target now (within the deadband of the one in force)
    assert change.reason == ECHO and change.level_changed and change.rate_changed and change.rate_hz == 15.0
    assert f.in_force(CLOUD) == (2, 15.0)
    assert not f.decide(4.1, {CLOUD: Target(2, 15.0)})  # sent once


def test_an_echoed_level_counts_and_an_encoder_that_never_agrees_gets_one_resend_per_interval():
    f = SetpointFilter(rate_deadband=0.2, min_interval_s=5.0)
    f.decide(0.0, {CLOUD: Target(1, 5.0), OTHER: Target(1, 5.0)})
    assert not f.echo(OTHER, 5.0, None, 3.0)  # an encoder without levels: its rate alone
    assert not f.echo(OTHER, 5.0 * (1 + 1e-5), 1, 3.0)  # a float's rounding is the same rate
    resent = []
    for k in range(3, 40):  # an encoder that keeps level 0 (a clamp, a bug): 1 s statuses
        if f.echo(CLOUD, 5.0, 0, float(k)):
            changes = _sent(f.decide(float(k), {CLOUD: Target(1, 5.0), OTHER: Target(1, 5.0)}))
            assert set(changes) == {CLOUD} and changes[CLOUD].reason == ECHO
            resent.append(k)
    assert resent == [3, 8, 13, 18, 23, 28, 33, 38]
    assert not f.echo(("c", "cloud"), 1.0, None, 10.0)  # nothing sent yet: nothing to compare
    assert not f.echo(OTHER, math.nan, None, 10.0)  # an encoder that does not say
    f.forget(CLOUD)
    assert _sent(f.decide(40.0, {CLOUD: Target(1, 5.0)}))[CLOUD].reason == FIRST
