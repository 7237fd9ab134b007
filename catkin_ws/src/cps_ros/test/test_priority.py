"""cps_ros.priority: a thread's nice value is its own, and who may lower one."""

import os
import resource
import threading

import pytest

from cps_ros import priority

pytestmark = pytest.mark.unit


def test_a_thread_niced_leaves_the_process_main_thread_as_it_was():
    before = priority.thread_nice()
    seen = {}

    def run():
        priority.set_thread_nice(before + 5)
        seen["thread"] = priority.thread_nice()
        inner = threading.Thread(target=lambda: seen.setdefault("child", priority.thread_nice()))
        inner.start()
        inner.join()

    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    assert seen == {"thread": min(priority.NICE_MAX, before + 5), "child": min(priority.NICE_MAX, before + 5)}
    assert priority.thread_nice() == before == os.getpriority(os.PRIO_PROCESS, os.getpid())


@pytest.mark.parametrize(
    "euid, soft, nice, allowed",
    [
        (0, 0, -5, True),
        (1000, 0, 0, False),
        (1000, 0, 19, False),
        (1000, 20, 0, True),
        (1000, 20, -1, False),
        (1000, 1, 19, True),
        (1000, resource.RLIM_INFINITY, -20, True),
    ],
)
def test_lowering_a_nice_value_needs_root_or_rlimit_nice(monkeypatch, euid, soft, nice, allowed):
    monkeypatch.setattr(os, "geteuid", lambda: euid)
    monkeypatch.setattr(resource, "getrlimit", lambda which: (soft, soft))
    assert priority.may_lower_nice_to(nice) is allowed


def test_a_threads_cpu_and_its_wait_for_a_cpu_are_read():
    """The map server's change detection says how long a slow cycle waited for a CPU (schedstat)."""
    import time

    cpu_s, waited_s = priority.thread_cpu_and_wait_s()
    t_end = time.thread_time() + 0.2
    while time.thread_time() < t_end:
        pass
    cpu_end_s, waited_end_s = priority.thread_cpu_and_wait_s()
    assert 0.15 <= cpu_end_s - cpu_s <= 1.0
    assert waited_s is not None and waited_end_s >= waited_s  # this kernel keeps schedstat
