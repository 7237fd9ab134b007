"""Link scenario files: the shipped ones parse into the timelines they describe; bad files fail
with file:line and what is wrong."""

import pytest

from cps_fleet.config import ConfigError
from cps_link.scenario import available_scenarios, load_scenario


def _write(folder, name, text):
    path = folder / f"{name}.yaml"
    path.write_text(text)
    return path


def _timeline(scenario):
    return [(e.at_s, e.kind, e.shaping.rate_mbps) for e in scenario.events()]


def test_the_shipped_scenarios_parse():
    assert {"wifi_good", "wifi_degraded", "outage", "shared_medium", "demo"} <= set(available_scenarios())
    for name in available_scenarios():
        load_scenario(name)
    degraded = load_scenario("wifi_degraded")
    assert (degraded.initial.delay_ms, degraded.initial.jitter_ms, degraded.initial.loss_pct) == (20, 10, 2)
    assert _timeline(degraded) == [(20, "shape", 20), (40, "shape", 5), (60, "shape", 60)]
    assert load_scenario("shared_medium").topology == "shared"
    # Wi-Fi is one medium both ways: the degraded scenarios too (teleop shares the shaper, issue 35)
    assert degraded.topology == "shared" and load_scenario("degraded_with_outage").topology == "shared"
    assert _timeline(load_scenario("demo")) == [
        (25, "cut", 60),
        (35, "restore", 60),
        (60, "shape", 10),
        (80, "shape", 60),
    ]


def test_an_include_merges_steps_and_an_outage_restores_the_shaping_in_force(tmp_path):
    _write(
        tmp_path,
        "steps",
        "initial: {rate_mbps: 60, delay_ms: 10}\nsteps:\n  - {at_s: 5, rate_mbps: 20}\n  - {at_s: 12, rate_mbps: 60}\n",
    )
    combo = load_scenario(str(_write(tmp_path, "combo", "include: [steps]\nsteps:\n  - {at_s: 8, outage_s: 10}\n")))
    assert _timeline(combo) == [(5, "shape", 20), (8, "cut", 20), (12, "shape", 60), (18, "restore", 60)]
    assert combo.initial.delay_ms == 10
    assert combo.events()[-1].shaping.delay_ms == 10


@pytest.mark.parametrize(
    "text,line,message",
    [
        ("initial: {rate_mbps: 60}\nsteps:\n  - {at_s: 5, rate_mbps: -3}\n", 3, "rate_mbps: -3.0 is outside"),
        ("initial: {rate_mbps: 60}\nsteps:\n  - {rate_mbps: 5}\n", 3, "missing key 'at_s'"),
        ("initial: {rate_mbps: 60}\nsteps:\n  - {at_s: 5}\n", 3, "needs outage_s or one of"),
        ("initial: {rate_mbps: 60}\nsteps:\n  - {at_s: 5, speed: 3}\n", 3, "speed: unknown key"),
        ("initial: {rate_mbps: 60}\nsteps:\n  - {at_s: 1, outage_s: 10}\n  - {at_s: 5, outage_s: 2}\n", 4, "overlaps"),
        ("initial: {delay_ms: 5}\n", 1, "missing initial rate_mbps"),
        ("initial: {rate_mbps: 60}\ntopology: mesh\n", 2, "must be duplex or shared"),
        ("initial: {rate_mbps: 60}\ninclude: [nowhere]\n", 2, "no scenario 'nowhere'"),
        ("initial: {rate_mbps: 60}\ninclude: [bad]\n", 2, "includes itself"),
        ("initial: {rate_mbps: 60, delay_ms: 5, jitter_ms: 9}\n", 1, "jitter_ms (9.0) > delay_ms"),
        ("initial: {rate_mbps: 60}\nsteps: [\n", 3, "YAML syntax error"),
        ("initial: {rate_mbps: 60}\nwhen: now\n", 2, "when: unknown key"),
    ],
)
def test_a_bad_file_names_its_line_and_the_problem(tmp_path, text, line, message):
    path = _write(tmp_path, "bad", text)
    with pytest.raises(ConfigError) as err:
        load_scenario(str(path))
    assert f"{path}:{line}" in str(err.value) and message in str(err.value), str(err.value)


def test_an_unknown_name_lists_the_known_ones():
    with pytest.raises(ConfigError, match="no scenario 'nosuch' \\(known: .*wifi_good"):
        load_scenario("nosuch")


def test_the_runner_announces_the_initial_rate_and_never_a_step_it_could_not_apply(tmp_path):
    """on_rate hears the rate at start; a rate step that failed (here: no such link) and an
    outage are not announced: an outage is not a capacity of 0."""
    from cps_link.scenario import ScenarioRunner

    path = _write(
        tmp_path,
        "steps",
        "initial: {rate_mbps: 60}\nsteps:\n  - {at_s: 0, rate_mbps: 5}\n  - {at_s: 0, outage_s: 0.01}\n",
    )
    announced, lines = [], []
    runner = ScenarioRunner(
        "nosuchlink", load_scenario(str(path)), log=lines.append, netem=False, on_rate=lambda t, r: announced.append(r)
    )
    runner.start()
    runner._thread.join(10.0)  # every event is at 0-0.01 s: the thread ends by itself
    runner.stop()
    assert announced == [60.0]
    assert [kind for _, kind, _, _ in runner.applied] == ["start", "shape", "cut", "restore"]
    assert len(runner.errors) == 3 and all("nosuchlink" in e for e in runner.errors), runner.errors


def test_each_event_row_says_when_its_commands_began_and_when_they_had_run(tmp_path):
    """A step's tc commands took 0.8-1.6 s on a loaded host while the link changed among the
    first: the judge starts the phase at `began_wall_time_s`, not at `wall_time_s`."""
    import csv
    import time

    from cps_fleet.csv_log import CsvLog
    from cps_link.scenario import LINK_EVENTS_COLUMNS, ScenarioRunner

    path = _write(tmp_path, "step", "initial: {rate_mbps: 60}\nsteps:\n  - {at_s: 0, rate_mbps: 10}\n")
    csv_path = str(tmp_path / "link_events.csv")
    with CsvLog(csv_path, LINK_EVENTS_COLUMNS) as log:
        runner = ScenarioRunner("nosuchlink", load_scenario(str(path)), csv_log=log, log=lambda line: None, netem=False)
        runner.apply = lambda event: time.sleep(0.3) or ""  # slow commands
        runner.start()
        runner._thread.join(10.0)
        runner.stop()
    start, step = list(csv.DictReader(open(csv_path)))
    assert step["event"] == "shape" and step["rate_mbps"] == "10"
    assert float(step["wall_time_s"]) - float(step["began_wall_time_s"]) >= 0.29
    assert abs(float(start["wall_time_s"]) - float(start["began_wall_time_s"])) < 0.01  # the start runs nothing


def test_a_failing_announcement_is_logged_and_the_scenario_goes_on(tmp_path):
    from cps_link.scenario import ScenarioRunner

    path = _write(tmp_path, "flat", "initial: {rate_mbps: 20}\n")

    def broken(mission_s, rate_mbps):
        raise RuntimeError("publisher gone")

    lines = []
    runner = ScenarioRunner("nosuchlink", load_scenario(str(path)), log=lines.append, netem=False, on_rate=broken)
    runner.start()
    runner.stop()
    assert runner.errors == ["announcing 20 Mbit/s failed: publisher gone"]
    assert any("announcing 20 Mbit/s failed" in line for line in lines)
