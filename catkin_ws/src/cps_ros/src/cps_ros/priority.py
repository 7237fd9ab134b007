"""A thread's CPU priority (its nice value): Linux keeps one per thread, and a thread or process
inherits its creator's. Raising a nice value is always allowed; lowering it needs CAP_SYS_NICE or
an RLIMIT_NICE that reaches it (sched(7)). A warm spare (cps_ros.spare) imports in a thread at
spare.SPARE_NICE so that its imports take little CPU a node wants, while its main thread keeps the node's."""

import os
import resource
import time

NICE_MAX = 19


def thread_nice():
    """The calling thread's nice value."""
    return os.getpriority(os.PRIO_PROCESS, 0)


def set_thread_nice(nice):
    """Set the calling thread's nice value (new threads and processes it starts inherit it)."""
    os.setpriority(os.PRIO_PROCESS, 0, max(-20, min(NICE_MAX, int(nice))))


def may_lower_nice_to(nice):
    """True if this process may set a nice value as low as `nice` (root, or RLIMIT_NICE reaching it:
    a soft limit r allows down to 20 - r)."""
    if os.geteuid() == 0:
        return True
    soft, _ = resource.getrlimit(resource.RLIMIT_NICE)
    return soft == resource.RLIM_INFINITY or 20 - soft <= nice


def process_nice(pid):
    """The nice value of `pid`'s main thread (what a process it forks from there inherits)."""
    return os.getpriority(os.PRIO_PROCESS, pid)


def renice_process(pid, nice):
    """Set every thread of process `pid` to `nice`; the number set (a thread gone meanwhile is
    skipped). PermissionError where lowering is not allowed."""
    done = 0
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except OSError:
        return 0
    for tid in tids:
        try:
            os.setpriority(os.PRIO_PROCESS, tid, nice)
            done += 1
        except ProcessLookupError:
            pass
    return done


def thread_cpu_and_wait_s():
    """(CPU time, time runnable but waiting for a CPU) of the calling thread since it started, s,
    from the kernel's schedstat; the wait is None where the kernel keeps none. What a thread slower
    than its work says of its priority: a long wait is the CPU it did not get."""
    try:
        with open("/proc/thread-self/schedstat") as stream:
            on_cpu_ns, waiting_ns = (int(x) for x in stream.read().split()[:2])
        return on_cpu_ns / 1e9, waiting_ns / 1e9
    except (OSError, ValueError):
        return time.thread_time(), None
