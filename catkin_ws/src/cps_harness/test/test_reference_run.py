"""ReferenceRun's checks: a mission that ran and judged itself FAIL still serves the tests that
read its files; only `check_passed` (the verdict's one test) fails on it."""

import pytest

from cps_experiments.verdict import FAIL, PASS, Verdict, write_verdict
from cps_harness.reference import ReferenceRun

pytestmark = pytest.mark.unit


def _run(tmp_path, returncode, status=None):
    if status is not None:
        write_verdict(str(tmp_path), Verdict(status, ["map published and fresh: FAIL"] * (status == FAIL), [], 0.9))
    return ReferenceRun(out=tmp_path, fleet_file="", bag="", returncode=returncode, log="the log's tail")


def test_a_passed_mission_passes_both_checks(tmp_path):
    run = _run(tmp_path, 0, PASS)
    run.check()
    run.check_passed()


def test_a_failed_verdict_fails_only_check_passed(tmp_path):
    run = _run(tmp_path, 1, FAIL)
    run.check()
    with pytest.raises(AssertionError, match="verdict FAILED"):
        run.check_passed()


@pytest.mark.parametrize(
    "returncode, status",
    [(1, None), (1, PASS), (0, FAIL), (4, None), (2, None), (None, PASS)],
    ids=[
        "crashed without a verdict",
        "crashed after a PASS",
        "exit 0 on FAIL",
        "incomplete",
        "did not start",
        "never ended",
    ],
)
def test_a_mission_that_did_not_judge_itself_fails_check(tmp_path, returncode, status):
    run = _run(tmp_path, returncode, status)
    with pytest.raises(AssertionError, match="the reference mission ended with"):
        run.check()


def test_a_mission_that_could_not_run_fails_check_with_its_error(tmp_path):
    run = _run(tmp_path, None)
    run.error = "the reference mission failed: TimeoutError"
    with pytest.raises(AssertionError, match="TimeoutError"):
        run.check()
