"""The durations plugin: a run's table gives each test's wall and CPU time, the CPU of the child
processes a test reaped included, with and without xdist workers; junit.xml keeps the CPU time.
Each test's memory growth is in the table, and a worker past the memory guard stops naming its test."""

import re
import subprocess
import sys
import time
import xml.etree.ElementTree as ET

import pytest

from cps_harness.durations import table

BUSY_CHILD_S = 0.6
TESTS = f"""
import subprocess, sys, time

def test_child_burns_cpu():
    subprocess.run([sys.executable, "-c", "import time\\nt = time.process_time()\\nwhile time.process_time() - t < {BUSY_CHILD_S}: pass"], check=True)

def test_sleeps():
    time.sleep(0.3)
"""


@pytest.mark.parametrize("workers", [[], ["-n", "2"]])
def test_a_childs_cpu_is_its_tests_and_a_sleep_costs_none(tmp_path, workers):
    junit = tmp_path / "junit.xml"
    result, out = _run(tmp_path, TESTS, *workers, f"--junitxml={junit}")
    assert result.returncode == 0, result.stdout + result.stderr
    rows = {m.group(1): (float(m.group(2)), float(m.group(3))) for m in _slowest_rows(out.read_text())}
    child_s, child_cpu = rows["test_sample.py::test_child_burns_cpu"]
    sleep_s, sleep_cpu = rows["test_sample.py::test_sleeps"]
    assert child_cpu >= BUSY_CHILD_S * 0.9, rows
    assert sleep_s >= 0.3 and sleep_cpu < 0.2, rows
    properties = {
        case.get("name"): float(prop.get("value"))
        for case in ET.parse(junit).iter("testcase")
        for prop in case.iter("property")
        if prop.get("name") == "cpu_s"
    }
    assert properties["test_child_burns_cpu"] >= BUSY_CHILD_S * 0.9, properties


def _slowest_rows(text):
    section = text.split("slowest tests", 1)[1].split("##", 1)[0]
    return re.finditer(r"^\| (\S+) \| \w+ \| ([\d.]+) \| ([\d.]+) \|$", section, re.M)


def test_the_table_without_cpu_figures_reads_zero():
    text = table({"a/b.py::t": 2.0}, {"a/b.py::t": "passed"}, {}, 3.0)
    assert "| a/b.py::t | passed | 2.0 | 0.0 |" in text and "their CPU time" in text


GROW_MB = 300
MEMORY_TESTS = f"""
import os, time

held = []

def test_small():
    pass

def test_grows():
    held.append(bytearray({GROW_MB} * 1000 * 1000))
    if os.environ.get("CPS_MEMORY_GUARD_MB"):
        time.sleep(10)  # held long enough for the guard's sampling
"""


def _run(tmp_path, tests, *options, env=None):
    import os

    (tmp_path / "test_sample.py").write_text(tests)
    out = tmp_path / "report" / "durations.md"
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "cps_harness.durations", *options]
        + [f"--rootdir={tmp_path}", f"--durations-table={out}", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
        env={**os.environ, **(env or {})},
    )
    return result, out


def test_the_test_that_grew_its_worker_heads_the_memory_table(tmp_path):
    result, out = _run(tmp_path, MEMORY_TESTS)
    assert result.returncode == 0, result.stdout + result.stderr
    section = out.read_text().split("memory grew most in", 1)[1]
    rows = re.findall(r"^\| (\S+) \| (\d+) \| (\d+) \|$", section, re.M)
    assert rows[0][0] == "test_sample.py::test_grows" and int(rows[0][1]) >= GROW_MB * 0.95, rows


@pytest.mark.parametrize("workers", [[], ["-n", "2", "--max-worker-restart", "0"]])
def test_a_worker_past_the_memory_guard_stops_and_names_its_test(tmp_path, workers):
    result, out = _run(tmp_path, MEMORY_TESTS, *workers, env={"CPS_MEMORY_GUARD_MB": str(GROW_MB)})
    assert result.returncode != 0, result.stdout + result.stderr
    (guard,) = (tmp_path / "report").glob("memory_guard_*.txt")
    text = guard.read_text()
    assert text.startswith("test_sample.py::test_grows: this worker reached") and "test_grows" in text, text


def test_the_machines_busy_share_is_given_beside_the_tests_cpu():
    text = table({"a/b.py::t": 2.0}, {"a/b.py::t": "passed"}, {}, 3.0, {"a/b.py::t": 1.5}, machine=(5.0, 6.0))
    assert "5 s busy of 6 s (83%); the tests' CPU above is 30% of that busy time." in text


def test_the_machines_cpu_counts_a_busy_loop():
    from cps_harness.durations import machine_busy, machine_cpu_s

    start = machine_cpu_s()
    t_end = time.process_time() + 0.3
    while time.process_time() < t_end:
        pass
    busy, available = machine_busy(start, machine_cpu_s())
    assert busy >= 0.25 and available >= busy


def test_a_fully_busy_interval_is_never_busier_than_the_machine():
    """n3a (2026-11-30): seconds since boot as floats read a fully busy interval as 3.650000000008731 s
    busy of 3.6499999999941792 available; the readings are whole ticks until their difference."""
    import os

    from cps_harness.durations import machine_busy

    ticks = os.sysconf("SC_CLK_TCK")
    start, end = (123456789012, 234567890123), (123456789012 + 365, 234567890123 + 365)
    busy, available = machine_busy(start, end)
    assert busy == available == 365 / ticks
