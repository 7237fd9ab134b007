"""Link scenarios: named YAML files of timed steps (capacity, delay/jitter/loss, outages) that a
runner applies to a live cps_link link during a mission, logging every step to a CSV.

    topology: shared            # optional: duplex (default) or shared (one capacity both ways)
    include: [outage]           # optional: other scenarios of the same folder, steps merged
    initial: {rate_mbps: 60}    # the link at the start (included files' initial values first)
    steps:
      - {at_s: 20, rate_mbps: 20, delay_ms: 20, jitter_ms: 10, loss_pct: 2}
      - {at_s: 25, outage_s: 10}   # cut at 25 s, restored at 35 s

A step changes only the values it names; the others keep their last value. Times are seconds
from the start of the mission.
"""

import dataclasses
import os
import threading
import time
from typing import Optional, Tuple

from cps_fleet.config import ConfigError, Reader, load_yaml_document

SCENARIO_DIR = os.path.normpath(
    os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "config", "scenarios")
)
SHAPING_KEYS = ("rate_mbps", "delay_ms", "jitter_ms", "loss_pct")
LINK_EVENTS_COLUMNS = (
    "mission_time_s",
    "wall_time_s",
    "event",
    "rate_mbps",
    "delay_ms",
    "jitter_ms",
    "loss_pct",
    "note",
    # when the event's commands began, wall s: `wall_time_s` is when they had all run, which on a
    # loaded host was 0.8-1.6 s later (a step's tc commands, both ends), while the robots' end's
    # shaper changes among the first
    "began_wall_time_s",
)
_LIMITS = {
    "rate_mbps": (0.0, 10000.0, True),
    "delay_ms": (0.0, 10000.0, False),
    "jitter_ms": (0.0, 10000.0, False),
    "loss_pct": (0.0, 99.0, False),
}


@dataclasses.dataclass(frozen=True)
class Shaping:
    rate_mbps: float
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    loss_pct: float = 0.0

    @property
    def impaired(self):
        return bool(self.delay_ms or self.jitter_ms or self.loss_pct)


@dataclasses.dataclass(frozen=True)
class Step:
    at_s: float
    changes: Tuple[Tuple[str, float], ...]  # (key of SHAPING_KEYS, value)
    outage_s: Optional[float]
    where: str  # file:line, for messages


@dataclasses.dataclass(frozen=True)
class LinkEvent:
    """What the runner does at `at_s`: "shape" (set `shaping`), "cut" or "restore"."""

    at_s: float
    kind: str
    shaping: Shaping
    where: str


@dataclasses.dataclass(frozen=True)
class Scenario:
    name: str
    path: str
    topology: str
    initial: Shaping
    steps: Tuple[Step, ...]

    def events(self):
        """The timeline in time order: each shaping step with the link as it becomes, each outage
        as a cut and a restore."""
        events, shaping = [], self.initial
        for step in sorted(self.steps, key=lambda s: s.at_s):
            if step.changes:
                shaping = dataclasses.replace(shaping, **dict(step.changes))
                events.append(LinkEvent(step.at_s, "shape", shaping, step.where))
            if step.outage_s is not None:
                events.append(LinkEvent(step.at_s, "cut", shaping, step.where))
                events.append(LinkEvent(step.at_s + step.outage_s, "restore", shaping, step.where))
        events.sort(key=lambda e: (e.at_s, e.kind != "restore"))
        # a restore carries the shaping in force when it happens
        current, fixed = self.initial, []
        for e in events:
            current = e.shaping if e.kind == "shape" else current
            fixed.append(dataclasses.replace(e, shaping=current))
        return fixed


def scenario_path(name_or_path, folder=SCENARIO_DIR):
    """A scenario name (file `<folder>/<name>.yaml`) or a path to a YAML file."""
    if name_or_path.endswith((".yaml", ".yml")) or os.sep in name_or_path:
        return os.path.abspath(name_or_path)
    return os.path.normpath(os.path.join(folder, f"{name_or_path}.yaml"))


def available_scenarios(folder=SCENARIO_DIR):
    return sorted(f[:-5] for f in os.listdir(folder) if f.endswith(".yaml"))


def load_scenario(name_or_path, folder=SCENARIO_DIR):
    """Parse a scenario (and what it includes); ConfigError with file:line for anything wrong."""
    path = scenario_path(name_or_path, folder)
    if not os.path.exists(path):
        raise ConfigError(path, None, f"no scenario '{name_or_path}' (known: {', '.join(available_scenarios(folder))})")
    return _load(path, os.path.dirname(path), ())


def _load(path, folder, including):
    doc = load_yaml_document(path)
    top = Reader(doc)
    for key in top.value:
        if key not in ("description", "topology", "include", "initial", "steps"):
            raise top.error(key, "unknown key (known: description, topology, include, initial, steps)")
    name = os.path.splitext(os.path.basename(path))[0]
    topology = top.get("topology", str, default="duplex")
    if topology not in ("duplex", "shared"):
        raise top.error("topology", f"must be duplex or shared, got '{topology}'")
    initial, steps = {}, []
    for index, included in enumerate(top.get("include", list, default=[])):
        where = (("include", index),)
        if not isinstance(included, str) or not included:
            raise doc.error(*where, f"must be a scenario name, got {included!r}")
        child_path = scenario_path(included, folder)
        if child_path in including + (path,):
            raise doc.error(*where, f"includes itself through '{included}'")
        if not os.path.exists(child_path):
            raise doc.error(*where, f"no scenario '{included}' in {folder}")
        child = _load(child_path, folder, including + (path,))
        initial.update(dataclasses.asdict(child.initial))
        steps.extend(child.steps)
        if child.topology == "shared" and not top.has("topology"):
            topology = "shared"
    if top.has("initial"):
        initial.update(_changes(top.child("initial")))
    if "rate_mbps" not in initial:
        raise top.error("initial" if top.has("initial") else None, "missing initial rate_mbps (here or in an include)")
    for reader in top.items("steps") if top.has("steps") else []:
        steps.append(_step(reader))
    scenario = Scenario(name, path, topology, _shaping(top, Shaping(**initial)), tuple(steps))
    _check_outages(scenario)
    return scenario


def _changes(reader):
    out = {}
    for key in reader.value:
        if key not in SHAPING_KEYS and key not in ("at_s", "outage_s"):
            raise reader.error(key, f"unknown key (known: at_s, outage_s, {', '.join(SHAPING_KEYS)})")
        if key in SHAPING_KEYS:
            low, high, low_open = _LIMITS[key]
            out[key] = reader.number(key, low=low, high=high, low_open=low_open)
    return out


def _step(reader):
    where = f"{reader.doc.path}:{reader.doc.line(reader.key_path)}"
    at_s = reader.number("at_s", low=0.0, high=86400.0)
    changes = _changes(reader)
    outage_s = reader.number("outage_s", low=0.0, high=86400.0, low_open=True) if reader.has("outage_s") else None
    if not changes and outage_s is None:
        raise reader.error(None, f"a step needs outage_s or one of {', '.join(SHAPING_KEYS)}")
    return Step(at_s, tuple(sorted(changes.items())), outage_s, where)


def _shaping(top, shaping):
    if shaping.jitter_ms > shaping.delay_ms:
        raise top.error("initial", f"jitter_ms ({shaping.jitter_ms}) > delay_ms ({shaping.delay_ms})")
    return shaping


def _check_outages(scenario):
    cut_until, cut_where = -1.0, None
    for event in scenario.events():
        if event.shaping.jitter_ms > event.shaping.delay_ms:
            raise _at(event.where, f"jitter_ms ({event.shaping.jitter_ms}) > delay_ms ({event.shaping.delay_ms})")
        if event.kind == "cut":
            if event.at_s < cut_until:
                raise _at(event.where, f"outage at {event.at_s:g} s overlaps the one from {cut_where}")
            cut_until = next(
                e.at_s
                for e in scenario.events()
                if e.kind == "restore" and e.at_s > event.at_s and e.where == event.where
            )
            cut_where = event.where


def _at(where, message):
    path, _, line = where.rpartition(":")
    return ConfigError(path, int(line), message)


# The events that set the link's rate: what an announced capacity follows. A cut is not a rate of
# 0 (the bridges' link_state reports an outage) and a restore brings back the rate in force.
RATE_EVENTS = ("start", "shape")


class ScenarioRunner:
    """Applies a scenario's events to link `link_name` at their mission times, in a thread; each
    applied event is logged and written to `csv_log` (a cps_fleet CsvLog of LINK_EVENTS_COLUMNS).
    `on_rate(mission_s, rate_mbps)`: called with the rate at start and after each rate step that
    was applied (not after a failed one, a cut or a restore); an exception in it is logged and
    counted in `errors`, and the scenario goes on."""

    def __init__(self, link_name, scenario, csv_log=None, log=print, netem=None, on_rate=None):
        from cps_link import netns_link

        self.link_name, self.scenario, self.csv_log, self.log = link_name, scenario, csv_log, log
        self.on_rate = on_rate
        self._announced_mbps = None  # the last rate given to on_rate
        self.netem = netns_link.netem_available() if netem is None else netem
        self.applied = []  # (mission_time_s, LinkEvent, note)
        self.errors = []
        self._stop = threading.Event()
        self._thread = None
        self._t0 = None

    def start(self, t0_monotonic=None):
        self._t0 = time.monotonic() if t0_monotonic is None else t0_monotonic
        self._write(0.0, "start", self.scenario.initial, f"scenario {self.scenario.name} ({self.scenario.topology})")
        self._thread = threading.Thread(target=self._run, name="link-scenario", daemon=True)
        self._thread.start()

    def stop(self):
        self._stop.set()
        if self._thread:
            self._thread.join(30.0)

    def _run(self):
        for event in self.scenario.events():
            if self._stop.wait(max(0.0, self._t0 + event.at_s - time.monotonic())):
                return
            began_wall_s = time.time()
            try:
                note = self.apply(event)
            except Exception as exc:  # a failed step is logged and the mission goes on
                note = f"FAILED: {exc}"
                self.errors.append(note)
            self._write(time.monotonic() - self._t0, event.kind, event.shaping, note, began_wall_s)

    def apply(self, event):
        """Apply one event to the link; returns a note on what could not be applied."""
        from cps_link import netns_link

        if event.kind == "cut":
            netns_link.link_cut(self.link_name)
            return ""
        if event.kind == "restore":
            netns_link.link_restore(self.link_name)
        s = event.shaping
        if self.netem:
            netns_link.link_set(
                self.link_name, netns_link.tc_rate(s.rate_mbps), s.delay_ms, s.loss_pct, jitter_ms=s.jitter_ms
            )
            return ""
        netns_link.link_set(self.link_name, netns_link.tc_rate(s.rate_mbps))
        return "delay/jitter/loss not applied: this kernel has no sch_netem" if s.impaired else ""

    def _write(self, mission_s, kind, s, note, began_wall_s=None):
        now_wall_s = time.time()
        began_wall_s = now_wall_s if began_wall_s is None else began_wall_s
        self.applied.append((mission_s, kind, s, note))
        self.log(
            f"[link] {mission_s:6.1f} s {kind}: {s.rate_mbps:g} Mbit/s, delay {s.delay_ms:g}+-{s.jitter_ms:g} ms, "
            f"loss {s.loss_pct:g} %" + (f" ({note})" if note else "")
        )
        if self.csv_log:
            self.csv_log.write(
                (
                    f"{mission_s:.3f}",
                    f"{now_wall_s:.3f}",
                    kind,
                    f"{s.rate_mbps:g}",
                    f"{s.delay_ms:g}",
                    f"{s.jitter_ms:g}",
                    f"{s.loss_pct:g}",
                    note,
                    f"{began_wall_s:.3f}",
                )
            )
        self._announce(mission_s, kind, s, note)

    def _announce(self, mission_s, kind, s, note):
        if self.on_rate is None or kind not in RATE_EVENTS or note.startswith("FAILED"):
            return
        if s.rate_mbps == self._announced_mbps:
            return  # a step of delay, jitter or loss only: the capacity did not change
        try:
            self.on_rate(mission_s, s.rate_mbps)
            self._announced_mbps = s.rate_mbps
        except Exception as exc:  # the link's steps go on without the announcement
            self.errors.append(f"announcing {s.rate_mbps:g} Mbit/s failed: {exc}")
            self.log(f"[link] {mission_s:6.1f} s: announcing {s.rate_mbps:g} Mbit/s failed: {exc}")
