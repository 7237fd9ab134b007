"""Each bringup run's shaped link has its own name, and a run removes only the links of runs
that are gone: a killed run's leftovers must not stop the next one (CI failed on exactly that,
with one fixed name for every run), nor may a run remove a live one's link."""

import os

import pytest

from cps_bringup.link import link_unavailable_reason, remove_stale_run_links, run_link_name
from cps_link.netns_link import _NAME, link_down, link_exists, link_up

DEAD_PID = 4194305  # above any pid_max (2^22): no process has it


def test_run_link_names_are_per_process_and_valid_for_any_pid():
    assert run_link_name(123) == "cps123" and run_link_name() == f"cps{os.getpid()}"
    assert _NAME.match(run_link_name(DEAD_PID)), "the longest pid still makes a valid link name"


@pytest.mark.skipif(link_unavailable_reason() is not None, reason=f"{link_unavailable_reason()}")
def test_only_the_links_of_gone_runs_are_removed():
    dead, live, other = run_link_name(DEAD_PID), run_link_name(), "cpsrlother"
    try:
        for name in (dead, live, other):
            link_up(name, rate="10mbit")
        removed = remove_stale_run_links(log=lambda _line: None)
        # Other gone runs' leftovers on this machine may go too; never a live one's nor another form.
        assert dead in removed and live not in removed and other not in removed, removed
        assert not link_exists(dead)
        assert link_exists(live), "a live run's link was removed"
        assert link_exists(other), "a link not of the run form was removed"
    finally:
        for name in (dead, live, other):
            link_down(name)
