"""The durations plugin: a run's table gives each test's wall and CPU time, the CPU of the child
processes a test reaped included, with and without xdist workers; junit.xml keeps the CPU time."""

import re
import subprocess
import sys
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
    (tmp_path / "test_sample.py").write_text(TESTS)
    out, junit = tmp_path / "durations.md", tmp_path / "junit.xml"
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "cps_harness.durations", *workers]
        + [f"--rootdir={tmp_path}", f"--durations-table={out}", f"--junitxml={junit}", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
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
