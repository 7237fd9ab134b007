"""Where a test run's time went: a pytest plugin (loaded by catkin_ws/src/conftest.py) that adds up
every test's set-up, call and tear-down per package, file and test, and writes the durations
table (`--durations-table PATH`, markdown) when the run ends. With pytest-xdist it runs on the
controller, which sees every worker's reports; the sum of the tests' durations is then more than
the wall time, and the table gives both.

And the machine's: every CPU's busy time over the run, from /proc/stat (`machine_busy`), whoever
used it (processes no test reaped, a mission's orphans, anything else running). Beside the tests'
CPU it says how much of the run's cost the per-test figures see, and whether the run was bound by
the CPU (busy near 100 %: only less work makes it faster) or by waiting.

Beside the wall time, each test's CPU time (`cpu_s` in its report's user properties, hence in
junit.xml): its worker's own plus that of every child process the test reaped (the nodes and
missions it started), from set-up to tear-down. On two shared cores the wall time says how long a
test waited; the CPU time says what it cost the others (the reference mission's is its first
test's set-up).

And its worker's memory: the resident size after the test and how much it grew in it (`rss_mb`,
`rss_growth_mb`), with the tests it grew most in. A worker past MEMORY_GUARD_MB writes every
thread's stack and the running test to the report folder and exits: final9's worker grew to 23.8 GB
and the kernel's OOM killer took it, naming no test."""

import collections
import faulthandler
import os
import resource
import threading
import time

import pytest

TOP_TESTS = 40


def pytest_addoption(parser):
    parser.addoption("--durations-table", default=None, metavar="PATH", help="write where the time went (markdown)")


class Durations:
    def __init__(self, path):
        self.path = path
        self.started = time.monotonic()
        self.seconds = collections.Counter()  # nodeid -> s (set-up + call + tear-down)
        self.outcome = {}
        self.worker = {}
        self.cpu_s = collections.Counter()  # nodeid -> CPU s (the worker's and its reaped children's)
        self.rss = {}  # nodeid -> (its worker's resident MB after it, MB grown in it)
        self.machine_start = machine_cpu_s()

    @pytest.hookimpl
    def pytest_runtest_logreport(self, report):
        self.seconds[report.nodeid] += report.duration
        properties = dict(report.user_properties)
        self.cpu_s[report.nodeid] += properties.get(CPU_PROPERTY, 0.0)
        if RSS_PROPERTY in properties:
            self.rss[report.nodeid] = (properties[RSS_PROPERTY], properties.get(RSS_GROWTH_PROPERTY, 0.0))
        if report.when == "call" or report.outcome != "passed":
            self.outcome[report.nodeid] = report.outcome
        node = getattr(report, "node", None)
        if node is not None:
            self.worker[report.nodeid] = node.gateway.id

    @pytest.hookimpl
    def pytest_sessionfinish(self, session):
        wall_s = time.monotonic() - self.started
        os.makedirs(os.path.dirname(os.path.abspath(self.path)), exist_ok=True)
        with open(self.path, "w") as stream:
            busy = machine_busy(self.machine_start, machine_cpu_s())
            stream.write(table(self.seconds, self.outcome, self.worker, wall_s, self.cpu_s, self.rss, busy))


def _package(nodeid):
    parts = nodeid.split("/")
    return parts[2] if len(parts) > 3 and parts[0] == "catkin_ws" else parts[0]


def _file(nodeid):
    return nodeid.split("::", 1)[0]


def machine_cpu_s():
    """(busy, all) CPU time of every CPU since boot, from /proc/stat's first line (busy: all but idle
    and iowait), in clock ticks (`machine_busy` turns two readings into seconds), or None where it
    cannot be read."""
    try:
        with open("/proc/stat") as stream:
            fields = [int(v) for v in stream.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    # user nice system idle iowait irq softirq steal (guest time is inside user already)
    every = sum(fields[:8])
    return every - fields[3] - fields[4], every


def machine_busy(start, end):
    """(busy CPU s, available CPU s) between two `machine_cpu_s` readings, or None. In whole ticks
    until the difference: seconds since boot as floats lost the last bits, and a fully busy
    interval read busy 3.650000000008731 s of 3.6499999999941792 available."""
    if start is None or end is None:
        return None
    ticks = os.sysconf("SC_CLK_TCK")
    return (end[0] - start[0]) / ticks, (end[1] - start[1]) / ticks


def table(seconds, outcome, worker, wall_s, cpu_s=None, rss=None, machine=None):
    """The markdown table of a run: per package, per file, the slowest tests, per worker (wall s and
    CPU s), and the tests their worker's memory grew most in (rss: nodeid -> (MB after, MB grown));
    `machine`: (busy, available) CPU s of the whole machine over the run."""
    seconds, cpu_s = collections.Counter(seconds), collections.Counter(cpu_s or {})
    total, total_cpu = sum(seconds.values()), sum(cpu_s.values())
    lines = [
        "# Where the test run's time went",
        "",
        f"Wall time of the pytest run: **{wall_s:.0f} s**; the tests' own time (set-up + call + tear-down, "
        f"summed over every worker): {total:.0f} s over {len(seconds)} tests; their CPU time (each worker's "
        f"and the processes its tests reaped): {total_cpu:.0f} s.",
        "",
    ]
    if machine is not None and machine[1] > 0:
        lines[-1:-1] = [
            "",
            f"The machine's CPUs over the run (/proc/stat, every process): {machine[0]:.0f} s busy of "
            f"{machine[1]:.0f} s ({machine[0] / machine[1]:.0%}); the tests' CPU above is "
            f"{total_cpu / machine[0]:.0%} of that busy time."
            if machine[0] > 0
            else "The machine's CPUs over the run: none busy.",
        ]

    def section(title, key, limit=None):
        sums, cpus, counts = collections.Counter(), collections.Counter(), collections.Counter()
        for nodeid, s in seconds.items():
            sums[key(nodeid)] += s
            cpus[key(nodeid)] += cpu_s.get(nodeid, 0.0)
            counts[key(nodeid)] += 1
        rows = sums.most_common(limit)
        lines.extend([f"## {title}", "", "| | tests | s | share | CPU s |", "|---|---|---|---|---|"])
        lines.extend(f"| {k} | {counts[k]} | {s:.1f} | {s / total:.1%} | {cpus[k]:.1f} |" for k, s in rows)
        lines.append("")

    if worker:
        section("Per worker", lambda n: worker.get(n, "-"))
    section("Per package", _package)
    section("Per file", _file)
    lines.extend([f"## The {TOP_TESTS} slowest tests", "", "| test | outcome | s | CPU s |", "|---|---|---|---|"])
    lines.extend(
        f"| {n} | {outcome.get(n, '?')} | {s:.1f} | {cpu_s.get(n, 0.0):.1f} |"
        for n, s in seconds.most_common(TOP_TESTS)
    )
    lines.extend([f"## The {TOP_TESTS} costliest tests in CPU", "", "| test | s | CPU s |", "|---|---|---|"])
    lines.extend(f"| {n} | {seconds.get(n, 0.0):.1f} | {c:.1f} |" for n, c in cpu_s.most_common(TOP_TESTS))
    if rss:
        grown = sorted(rss.items(), key=lambda item: -item[1][1])[:TOP_MEMORY_TESTS]
        lines.extend(
            [
                "",
                f"## The {TOP_MEMORY_TESTS} tests their worker's memory grew most in",
                "",
                f"Largest resident size of a worker after a test: {max(after for after, _ in rss.values()):.0f} MB.",
                "",
                "| test | grew MB | resident MB after |",
                "|---|---|---|",
            ]
        )
        lines.extend(f"| {n} | {growth:.0f} | {after:.0f} |" for n, (after, growth) in grown)
    return "\n".join(lines) + "\n"


CPU_PROPERTY = "cpu_s"
RSS_PROPERTY, RSS_GROWTH_PROPERTY = "rss_mb", "rss_growth_mb"
TOP_MEMORY_TESTS = 10
# A worker this large is a leak (24 GB hold two workers and the missions' nodes): the guard stops
# it before the kernel's OOM killer takes it, or a mission's node. CPS_MEMORY_GUARD_MB overrides it.
MEMORY_GUARD_MB = 8000
MEMORY_GUARD_PERIOD_S = 0.5


def _cpu_s():
    """CPU s of this process and of every child it has reaped so far."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def _rss_mb():
    """This process's resident size, MB (0 where /proc cannot say)."""
    try:
        with open("/proc/self/statm") as stream:
            return int(stream.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6
    except (OSError, ValueError, IndexError):
        return 0.0


_running = {"test": "(between tests)"}


def _guard_memory(folder, limit_mb=MEMORY_GUARD_MB):
    """Until the process ends: past `limit_mb`, write the running test and every thread's stack to
    `folder` and exit (pytest-xdist reports the test its worker died in)."""
    while True:
        time.sleep(MEMORY_GUARD_PERIOD_S)
        rss_mb = _rss_mb()
        if rss_mb > limit_mb:
            os.makedirs(folder, exist_ok=True)
            with open(os.path.join(folder, f"memory_guard_{os.getpid()}.txt"), "w") as out:
                out.write(f"{_running['test']}: this worker reached {rss_mb:.0f} MB (guard {limit_mb:.0f} MB)\n")
                out.flush()
                faulthandler.dump_traceback(out, all_threads=True)
            os._exit(70)


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    item._cps_cpu_start_s = _cpu_s()
    item._cps_rss_start_mb = _rss_mb()
    _running["test"] = item.nodeid


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """The test's CPU s on its tear-down report (every worker runs this; the controller adds it up)."""
    outcome = yield
    start = getattr(item, "_cps_cpu_start_s", None)
    if call.when == "teardown" and start is not None:
        rss_mb = _rss_mb()
        outcome.get_result().user_properties.extend(
            [
                (CPU_PROPERTY, round(_cpu_s() - start, 2)),
                (RSS_PROPERTY, round(rss_mb, 1)),
                (RSS_GROWTH_PROPERTY, round(rss_mb - getattr(item, "_cps_rss_start_mb", rss_mb), 1)),
            ]
        )


def pytest_configure(config):
    path = config.getoption("--durations-table")
    if path:  # make test's run: every process that runs tests guards its memory
        folder = os.path.dirname(os.path.abspath(path))
        limit_mb = float(os.environ.get("CPS_MEMORY_GUARD_MB", MEMORY_GUARD_MB))
        threading.Thread(target=_guard_memory, args=(folder, limit_mb), name="cps_memory_guard", daemon=True).start()
    if path and not hasattr(config, "workerinput"):  # the controller (or a run without xdist)
        config.pluginmanager.register(Durations(path), "cps_durations_table")
