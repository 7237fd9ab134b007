"""Where a test run's time went: a pytest plugin (loaded by catkin_ws/src/conftest.py) that adds up
every test's set-up, call and tear-down per package, file and test, and writes the durations
table (`--durations-table PATH`, markdown) when the run ends. With pytest-xdist it runs on the
controller, which sees every worker's reports; the sum of the tests' durations is then more than
the wall time, and the table gives both."""

import collections
import os
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

    @pytest.hookimpl
    def pytest_runtest_logreport(self, report):
        self.seconds[report.nodeid] += report.duration
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
            stream.write(table(self.seconds, self.outcome, self.worker, wall_s))


def _package(nodeid):
    parts = nodeid.split("/")
    return parts[2] if len(parts) > 3 and parts[0] == "catkin_ws" else parts[0]


def _file(nodeid):
    return nodeid.split("::", 1)[0]


def table(seconds, outcome, worker, wall_s):
    """The markdown table of a run: per package, per file, the slowest tests, per worker."""
    total = sum(seconds.values())
    lines = [
        "# Where the test run's time went",
        "",
        f"Wall time of the pytest run: **{wall_s:.0f} s**; the tests' own time (set-up + call + tear-down, "
        f"summed over every worker): {total:.0f} s over {len(seconds)} tests.",
        "",
    ]

    def section(title, key, limit=None):
        sums, counts = collections.Counter(), collections.Counter()
        for nodeid, s in seconds.items():
            sums[key(nodeid)] += s
            counts[key(nodeid)] += 1
        rows = sums.most_common(limit)
        lines.extend([f"## {title}", "", "| | tests | s | share |", "|---|---|---|---|"])
        lines.extend(f"| {k} | {counts[k]} | {s:.1f} | {s / total:.1%} |" for k, s in rows)
        lines.append("")

    if worker:
        section("Per worker", lambda n: worker.get(n, "-"))
    section("Per package", _package)
    section("Per file", _file)
    lines.extend([f"## The {TOP_TESTS} slowest tests", "", "| test | outcome | s |", "|---|---|---|"])
    lines.extend(f"| {n} | {outcome.get(n, '?')} | {s:.1f} |" for n, s in seconds.most_common(TOP_TESTS))
    return "\n".join(lines) + "\n"


def pytest_configure(config):
    path = config.getoption("--durations-table")
    if path and not hasattr(config, "workerinput"):  # the controller (or a run without xdist)
        config.pluginmanager.register(Durations(path), "cps_durations_table")
