"""host_cpu: the idle share of a process's CPUs from /proc/stat."""

import math

import pytest

from cps_transport.host_cpu import HostCpu, cpu_list_text, read_cpu_jiffies

STAT = """cpu  300 0 100 600 0 0 0 0 0 0
cpu0 100 0 50 300 0 0 0 0 0 0
cpu1 200 0 50 300 0 0 0 0 0 0
intr 1 2 3
"""


def _stat(tmp_path, text):
    path = tmp_path / "stat"
    path.write_text(text)
    return str(path)


def test_cpu_lists_are_written_as_ranges():
    assert cpu_list_text({0, 1, 2, 5}) == "0-2,5" and cpu_list_text({3}) == "3"


def test_only_the_processes_cpus_count(tmp_path):
    path = _stat(tmp_path, STAT)
    assert read_cpu_jiffies({0}, path) == (300, 450)
    assert read_cpu_jiffies({0, 1}, path) == (600, 1000)
    with pytest.raises(ValueError, match="cpu 2"):
        read_cpu_jiffies({2}, path)


def test_the_idle_share_is_over_the_last_interval_and_read_at_most_once_per_interval(tmp_path):
    clock = [0.0]
    path = _stat(tmp_path, STAT)
    meter = HostCpu(cpus={1}, stat_path=path, clock=lambda: clock[0], min_interval_s=1.0)
    assert "cpus 1" in meter.host and meter.cores == 1.0
    assert math.isnan(meter.idle_fraction())  # one reading: no interval yet
    # cpu1: +100 busy, +300 idle, +100 iowait (idle too)
    (tmp_path / "stat").write_text(STAT.replace("cpu1 200 0 50 300 0", "cpu1 300 0 50 600 100"))
    clock[0] = 0.5
    assert math.isnan(meter.idle_fraction())  # within the interval: the last figure
    clock[0] = 1.0
    assert meter.idle_fraction() == pytest.approx(400 / 500)


def test_an_unreadable_stat_is_counted_not_raised(tmp_path):
    meter = HostCpu(cpus={0}, stat_path=str(tmp_path / "missing"))
    assert math.isnan(meter.idle_fraction()) and meter.errors == 1
