"""Where a test run's time went: a pytest plugin (loaded by catkin_ws/src/conftest.py) that adds up
every test's set-up, call and tear-down per package, file and test, and writes the durations
table (`--durations-table PATH`, markdown) when the run ends. With pytest-xdist it runs on the
controller, which sees every worker's reports; the sum of the tests' durations is then more than
the wall time, and the table gives both.

Beside the wall time, each test's CPU time (`cpu_s` in its report's user properties, hence in
junit.xml): its worker's own plus that of every child process the test reaped (the nodes and
missions it started), from set-up to tear-down. On two shared cores the wall time says how long a
test waited; the CPU time says what it cost the others (the reference mission's is its first
test's set-up)."""

import collections
import os
import resource
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

    @pytest.hookimpl
    def pytest_runtest_logreport(self, report):
        self.seconds[report.nodeid] += report.duration
        self.cpu_s[report.nodeid] += dict(report.user_properties).get(CPU_PROPERTY, 0.0)
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
            stream.write(table(self.seconds, self.outcome, self.worker, wall_s, self.cpu_s))


def _package(nodeid):
    parts = nodeid.split("/")
    return parts[2] if len(parts) > 3 and parts[0] == "catkin_ws" else parts[0]


def _file(nodeid):
    return nodeid.split("::", 1)[0]


def table(seconds, outcome, worker, wall_s, cpu_s=None):
    """The markdown table of a run: per package, per file, the slowest tests, per worker (wall s and
    CPU s)."""
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
    return "\n".join(lines) + "\n"


CPU_PROPERTY = "cpu_s"


def _cpu_s():
    """CPU s of this process and of every child it has reaped so far."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    item._cps_cpu_start_s = _cpu_s()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """The test's CPU s on its tear-down report (every worker runs this; the controller adds it up)."""
    outcome = yield
    start = getattr(item, "_cps_cpu_start_s", None)
    if call.when == "teardown" and start is not None:
        outcome.get_result().user_properties.append((CPU_PROPERTY, round(_cpu_s() - start, 2)))


def pytest_configure(config):
    path = config.getoption("--durations-table")
    if path and not hasattr(config, "workerinput"):  # the controller (or a run without xdist)
        config.pluginmanager.register(Durations(path), "cps_durations_table")
