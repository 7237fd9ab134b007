"""LevelSizes: priors first, the encoder's per-level sizes at once, the others by the priors' ratio."""

import math

import pytest

from cps_bw_manager.level_sizes import LevelSizes

PRIORS = (12000.0, 3600.0, 1200.0)


def test_priors_before_the_first_report():
    sizes = LevelSizes(PRIORS)
    assert sizes.estimate(0.0) == PRIORS
    assert sizes.measured(0.0) == (False, False, False)


def test_one_measured_level_scales_the_unmeasured_ones_by_the_priors_ratio():
    sizes = LevelSizes(PRIORS)
    assert sizes.report(2, 2400.0, now_s=0.0)  # the scene is twice the prior's
    assert sizes.estimate(0.0) == pytest.approx((24000.0, 7200.0, 2400.0))
    assert sizes.measured(0.0) == (False, False, True)


def test_a_tenfold_jump_is_learned_from_the_first_status_that_shows_it_at_every_level():
    sizes = LevelSizes(PRIORS)
    sizes.report(0, 12000.0, now_s=0.0)
    sizes.report(2, 1200.0, now_s=1.0)
    assert sizes.estimate(1.0) == pytest.approx(PRIORS)
    assert sizes.report(2, 12000.0, now_s=1.5)  # the scene changed: x10 at the level in force
    assert sizes.estimate(1.5) == pytest.approx((120000.0, 36000.0, 12000.0))


def test_a_recent_own_measurement_is_kept_when_the_scene_shrinks_until_it_is_stale():
    sizes = LevelSizes(PRIORS, stale_s=10.0)
    sizes.report(0, 12000.0, now_s=0.0)
    sizes.report(2, 600.0, now_s=1.0)  # half the prior at the coarse level
    assert sizes.estimate(1.0)[0] == pytest.approx(12000.0)  # never the smaller of the two
    assert sizes.estimate(1.0)[2] == pytest.approx(600.0)
    assert sizes.estimate(10.5)[0] == pytest.approx(6000.0)  # level 0's own size is 10.5 s old
    assert sizes.measured(10.5) == (False, False, True)


def test_small_changes_do_not_ask_for_an_allocation():
    sizes = LevelSizes(PRIORS)
    assert sizes.report(1, 3600.0, now_s=0.0) is False  # the prior itself
    assert sizes.report(1, 3900.0, now_s=0.5) is False  # < 10 %
    assert sizes.report(1, 4400.0, now_s=1.0) is True


@pytest.mark.parametrize(
    "level, size, now, match",
    [
        (3, 1000.0, 0.0, "outside the 3 levels"),
        (-1, 1000.0, 0.0, "outside"),
        (True, 1000.0, 0.0, "outside"),
        (0, 0.0, 0.0, "not a size"),
        (0, math.nan, 0.0, "not a size"),
        (0, -5.0, 0.0, "not a size"),
        (0, math.inf, 0.0, "not a size"),
        (0, 1000.0, math.nan, "not a time"),
    ],
)
def test_bad_reports_are_refused_and_change_nothing(level, size, now, match):
    sizes = LevelSizes(PRIORS)
    sizes.report(1, 3000.0, now_s=0.0)
    before = sizes.estimate(0.0)
    with pytest.raises(ValueError, match=match):
        sizes.report(level, size, now)
    assert sizes.estimate(0.0) == before


@pytest.mark.parametrize("priors", [(), (1.0, 0.0), (1.0, math.nan)])
def test_bad_priors_are_clear_errors(priors):
    with pytest.raises(ValueError, match="priors"):
        LevelSizes(priors)
