"""ManagerCore during an outage: paused while /tissue/link_state says down, the estimator not fed
(an outage is no capacity measurement), and resuming from the online estimate when it is back."""

import pytest

from cps_bw_manager.estimation import DeliveryRateEstimator
from cps_bw_manager.manager import LINK_STATE_CSV_COLUMNS, ManagerCore, ManagerSettings, link_state_csv_row

SETTINGS = ManagerSettings(available_mbps=60.0, reserve_fraction=0.04, min_rate_hz=1.0, max_rate_hz=30.0)


def _core():
    core = ManagerCore(["a", "b"], SETTINGS, DeliveryRateEstimator(initial_mbps=60.0, line_rate_mbps=60.0))
    for robot in ("a", "b"):
        core.on_limiter_status(robot, 100000.0, 30.0, 30.0, now_s=0.0)
    return core


def test_down_pauses_and_says_so_up_resumes():
    core = _core()
    assert not core.paused and core.pause_status(0.0) == ""
    assert core.on_link_state(False, since_s=10.0, outages=1, peer="robots")
    assert core.paused
    status = core.pause_status(14.0)
    assert status.startswith("paused: link to robots down for 4.0 s") and "60.0 Mbit/s" in status
    assert not core.on_link_state(False, since_s=10.0, outages=1, peer="robots")  # no change
    assert core.on_link_state(True, since_s=20.0, outages=1, last_outage_s=10.0, peer="robots")
    assert not core.paused and core.pause_status(21.0) == ""


def test_an_outage_does_not_collapse_the_estimate_and_it_resumes_from_it():
    core = _core()  # the limiters send 2 x 30 Hz x 100 kB = 48 Mbit/s
    # Saturated at 20 Mbit/s: the capacity comes down to that.
    for t in range(1, 8):
        core.on_link_stats(0.5 * t, 20.0)
    before = core.estimator.capacity_mbps
    assert before == pytest.approx(20.0)
    core.on_link_state(False, since_s=8.0)
    # Nothing arrives while the physical side sends: an outage is no capacity measurement.
    for t in range(8, 18):
        assert not core.on_link_stats(float(t), 0.0)
    assert core.estimator.capacity_mbps == before
    core.on_link_state(True, since_s=18.0, last_outage_s=10.0)
    assert core.available_mbps == before
    assert core.allocate().budget_mbytes_per_s == pytest.approx(0.96 * before / 8.0)
    # After the outage it tracks again from there.
    core.on_link_stats(18.5, 20.0)
    assert core.estimator.capacity_mbps == pytest.approx(20.0)


def test_link_state_rows_match_the_columns():
    core = _core()
    core.on_link_state(False, since_s=3.5, outages=2, last_outage_s=1.25, peer="twin")
    row = link_state_csv_row(4.0, core.link, core.available_mbps)
    assert len(row) == len(LINK_STATE_CSV_COLUMNS)
    assert dict(zip(LINK_STATE_CSV_COLUMNS, row)) == {
        "stamp_s": "4.000",
        "up": 0,
        "since_s": "3.500",
        "outages": 2,
        "last_outage_s": "1.250",
        "peer": "twin",
        "available_mbps": "60.000",
    }
