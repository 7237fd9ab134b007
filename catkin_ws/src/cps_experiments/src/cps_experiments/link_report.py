"""The mission report's link events: every outage (from the scenario runner's link_events.csv and,
when the bridge publishes /tissue/link_state, the manager's link_state.csv) and every capacity
step with the 1 s windows over budget around it. Plain rows in, markdown lines out."""

import bisect
import math

from cps_experiments.markdown import csv_float, markdown_table

# Windows compared before and after a capacity step, s.
STEP_SPAN_S = 10.0
# The manager's estimate is read this long after a step, and judged within +-ESTIMATE_BAND of the
# true capacity (issue 35: within +-15 % 2 s after every step).
ESTIMATE_TARGET_S = 2.0
ESTIMATE_BAND = 0.15
NOT_YET = "n/a: the bridges count these on /diagnostics; this report does not read them yet"


def scenario_outages(event_rows):
    """[(start wall s, start mission s, duration s or NaN if still cut at the end)] from link_events.csv."""
    out, cut = [], None
    for row in event_rows:
        if row["event"] == "cut":
            cut = row
        elif row["event"] == "restore" and cut is not None:
            out.append(
                (
                    csv_float(cut["wall_time_s"]),
                    csv_float(cut["mission_time_s"]),
                    csv_float(row["wall_time_s"]) - csv_float(cut["wall_time_s"]),
                )
            )
            cut = None
    if cut is not None:
        out.append((csv_float(cut["wall_time_s"]), csv_float(cut["mission_time_s"]), math.nan))
    return out


def bridge_outages(state_rows):
    """[(start wall s, duration s or NaN, peer)] from the manager's link_state.csv transitions."""
    out, down = [], None
    for row in state_rows:
        if row["up"] == "0":
            down = down or row
        elif down is not None:
            out.append(
                (csv_float(down["since_s"]), csv_float(row["since_s"]) - csv_float(down["since_s"]), row["peer"])
            )
            down = None
    if down is not None:
        out.append((csv_float(down["since_s"]), math.nan, down["peer"]))
    return out


def capacity_steps(event_rows):
    """[(wall s, mission s, from Mbit/s, to Mbit/s)] for every change of the link's rate."""
    out, rate = [], math.nan
    for row in event_rows:
        new = csv_float(row["rate_mbps"])
        if row["event"] in ("start", "shape") and math.isfinite(rate) and new != rate:
            out.append((csv_float(row["wall_time_s"]), csv_float(row["mission_time_s"]), rate, new))
        if row["event"] in ("start", "shape"):
            rate = new
    return out


def budget_at(allocation_rows):
    """A function wall s -> the manager's budget (MB/s) in force then (NaN before the first)."""
    points = sorted((csv_float(r["stamp_s"]), csv_float(r["budget_mbytes_per_s"])) for r in allocation_rows)
    times = [t for t, _ in points]

    def at(t):
        i = bisect.bisect_right(times, t) - 1
        return points[i][1] if i >= 0 else math.nan

    return at


def windows_over(times, totals, budget, t0, t1):
    """(windows over the budget in force, windows) among the stats windows with time in [t0, t1)."""
    inside = [(t, v) for t, v in zip(times, totals) if t0 <= t < t1]
    return sum(1 for t, v in inside if v > budget(t) * (1 + 1e-9)), len(inside)


def received_during(times, totals, t0, t1):
    """MB the twin received (managed clouds) in [t0, t1), from ~1 s stats windows."""
    return sum(v for t, v in zip(times, totals) if t0 <= t < t1 and math.isfinite(v))


def estimate_at(estimate_rows):
    """A function wall s -> the manager's capacity estimate (Mbit/s) in force then, from its
    link_estimate.csv (its estimate when the estimator is off; NaN before the first row)."""
    points = []
    for r in estimate_rows:
        capacity, estimate = csv_float(r.get("capacity_mbps")), csv_float(r.get("estimate_mbps"))
        points.append((csv_float(r.get("stamp_s")), capacity if math.isfinite(capacity) else estimate))
    points.sort()
    times = [t for t, _ in points]

    def at(t):
        i = bisect.bisect_right(times, t) - 1
        return points[i][1] if i >= 0 else math.nan

    return at, points


def estimate_settles(points, step_s, true_mbps, end_s, band=ESTIMATE_BAND):
    """Seconds from `step_s` after which every estimate until `end_s` is within +-band of the true
    capacity (inf: never; NaN: no estimate in the span)."""
    inside = [(t, v) for t, v in points if step_s <= t < end_s]
    if not inside:
        return math.nan
    settled = math.inf
    for t, v in reversed(inside):
        if not math.isfinite(v) or abs(v / true_mbps - 1.0) > band:
            break
        settled = t - step_s
    return settled


def section(event_rows, state_rows, allocation_rows, times, totals, estimate_rows=()):
    """Markdown lines of the link events; [] when the mission ran no scenario and saw no outage.
    `estimate_rows`: the manager's link_estimate.csv (its estimate against each step's capacity)."""
    if not event_rows and not state_rows:
        return []
    lines = ["## Link events", ""]
    scenario = next((r["note"] for r in event_rows if r["event"] == "start"), "")
    if scenario:
        lines += [
            f"The link ran {scenario}; every step the runner applied, with its time, is in `link_events.csv`.",
            "",
        ]
    notes = sorted({r["note"] for r in event_rows if r["note"] and r["event"] != "start"})
    lines += [f"- note: {n}" for n in notes] + ([""] if notes else [])
    rows = []
    for start, mission_s, duration in scenario_outages(event_rows):
        end = start + duration if math.isfinite(duration) else math.inf
        rows.append(
            (
                "link cut (scenario)",
                f"{mission_s:.1f}",
                _seconds(duration),
                f"{received_during(times, totals, start, end):.3f}",
                NOT_YET,
                NOT_YET,
            )
        )
    for start, duration, peer in bridge_outages(state_rows):
        end = start + duration if math.isfinite(duration) else math.inf
        mission_s = start - _mission_start(event_rows) if event_rows else math.nan
        rows.append(
            (
                f"bridge saw {peer or 'peer'} down",
                f"{mission_s:.1f}" if math.isfinite(mission_s) else "-",
                _seconds(duration),
                f"{received_during(times, totals, start, end):.3f}",
                NOT_YET,
                NOT_YET,
            )
        )
    lines += ["### Outages", ""]
    if rows:
        lines += [
            markdown_table(
                ("outage", "start, mission s", "duration s", "clouds received meanwhile MB", "dropped", "backfilled"),
                rows,
            ),
            "",
        ]
        if not state_rows:
            lines += [
                "No `/tissue/link_state` was heard (the Zenoh bridge does not run yet), so the manager did not "
                "pause: the outages above are the scenario's cuts.",
                "",
            ]
    else:
        lines += ["- none", ""]
    budget = budget_at(allocation_rows)
    estimate, estimate_points = estimate_at(estimate_rows)
    steps = []
    step_list = capacity_steps(event_rows)
    for k, (wall_s, mission_s, old, new) in enumerate(step_list):
        over_before, n_before = windows_over(times, totals, budget, wall_s - STEP_SPAN_S, wall_s)
        over_after, n_after = windows_over(times, totals, budget, wall_s, wall_s + STEP_SPAN_S)
        first_ok = _first_within(times, totals, budget, wall_s)
        end_s = step_list[k + 1][0] if k + 1 < len(step_list) else math.inf
        settle = estimate_settles(estimate_points, wall_s, new, min(end_s, wall_s + STEP_SPAN_S))
        after = wall_s + ESTIMATE_TARGET_S
        steps.append(
            (
                f"{mission_s:.1f}",
                f"{old:g} → {new:g}",
                f"{over_before} of {n_before}",
                f"{over_after} of {n_after}",
                first_ok,
                f"{estimate(after) / 8:.3f} of {new / 8:.3f} ({estimate(after) / new:.0%}); budget {budget(after):.3f}"
                if math.isfinite(estimate(after))
                else "no estimate logged",
                _settle_text(settle),
            )
        )
    lines += ["### Capacity steps", ""]
    if steps:
        lines += [
            f"Managed traffic at the twin per ~1 s stats window against the manager's budget in force then, "
            f"{STEP_SPAN_S:.0f} s before and after each step.",
            "",
            markdown_table(
                (
                    "at mission s",
                    "Mbit/s",
                    "windows over budget before",
                    "after",
                    "from the step until every later window of the span is within",
                    f"manager's estimate {ESTIMATE_TARGET_S:g} s after, MB/s of the true capacity (and its budget)",
                    f"estimate within ±{ESTIMATE_BAND:.0%} of the true capacity from",
                ),
                steps,
            ),
            "",
        ]
    else:
        lines += ["- none", ""]
    return lines


def _settle_text(settle_s):
    if math.isnan(settle_s):
        return "no estimate logged"
    return "never" if math.isinf(settle_s) else f"{settle_s:.1f} s"


def _first_within(times, totals, budget, step_s):
    inside = [(t, v) for t, v in zip(times, totals) if step_s <= t < step_s + STEP_SPAN_S]
    for k in range(len(inside)):
        if all(v <= budget(t) * (1 + 1e-9) for t, v in inside[k:]):
            return f"{inside[k][0] - step_s:.1f} s" if k else "0 s (never over)"
    return "not within the span"


def _mission_start(event_rows):
    start = next(r for r in event_rows if r["event"] == "start")
    return csv_float(start["wall_time_s"]) - csv_float(start["mission_time_s"])


def _seconds(value):
    return f"{value:.1f}" if math.isfinite(value) else "still down at the end"
