"""The mission report's link events: every outage (from the scenario runner's link_events.csv and,
when the bridge publishes /tissue/link_state, the manager's link_state.csv) with the clouds the
bridges counted lost, held back and kept for backfill meanwhile (the ledger's counters over time),
and every capacity step with the statistics windows around it against the capacity then in force
and the manager's budget after it. Plain rows in, markdown lines out."""

import bisect
import math

from cps_experiments.markdown import csv_float, markdown_table
from cps_ros import cloud_ledger as C

# Windows compared before and after a capacity step, s.
STEP_SPAN_S = 10.0
# After an outage ends, the twin's bridge counts the frames it never got with the first one it gets.
COUNTED_AFTER_S = 3.0
NOT_COUNTED = "not counted (no counters.csv: a mission before the ledger)"
# The manager's estimate is read this long after a step, and judged within +-ESTIMATE_BAND of the
# true capacity (issue 35: within +-15 % 2 s after every step).
ESTIMATE_TARGET_S = 2.0
ESTIMATE_BAND = 0.15
# The robots' bridge's send queue's drop rules (cps_link.send_queue): clouds withheld on purpose.
QUEUE_DROPS = ("superseded", "expired", "link_down", "put_failed")


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
    """(windows over `budget(t)` (MB/s), windows) among the stats windows with time in [t0, t1)."""
    inside = [(t, v) for t, v in zip(times, totals) if t0 <= t < t1]
    return sum(1 for t, v in inside if v > budget(t) * (1 + 1e-9)), len(inside)


def received_during(times, totals, t0, t1):
    """MB the twin received (managed streams) in [t0, t1): the 2 s sliding windows, one a second, so
    each second's MB/s counts once (a sum of MB/s over one-second steps)."""
    return sum(v for t, v in zip(times, totals) if t0 <= t < t1 and math.isfinite(v))


def outage_counts(series, start_s, end_s):
    """(lost, held back, kept for backfill) clouds the bridges counted from start_s to COUNTED_AFTER_S
    after end_s, over every robot (ledger.counter_series of the mission), or None without counters."""
    from cps_experiments.ledger import increase

    if not series:
        return None
    t1 = end_s + COUNTED_AFTER_S if math.isfinite(end_s) else math.inf
    held = increase(series, start_s, t1, C.BRIDGE_OUT, C.DROPPED + "outage") + sum(
        increase(series, start_s, t1, C.BRIDGE_OUT, C.DROPPED + rule) for rule in QUEUE_DROPS
    )
    kept = increase(series, start_s, t1, C.BRIDGE_OUT, C.BACKFILL_KEPT)
    gaps = increase(series, start_s, t1, C.BRIDGE_IN, C.MISSED)
    # The twin's gaps include what the robots' bridge withheld on purpose; the rest was lost on the link.
    return max(0, gaps - held - kept), held, kept


def _outage_cells(series, start_s, end_s):
    counts = outage_counts(series, start_s, end_s)
    if counts is None:
        return (NOT_COUNTED, NOT_COUNTED)
    lost, held, kept = counts
    return (f"{lost + held} ({lost} on the link, {held} held back without a keyframe)", f"{kept} kept")


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


def section(event_rows, state_rows, allocation_rows, times, totals, counters=None, estimate_rows=()):
    """Markdown lines of the link events; [] when the mission ran no scenario and saw no outage.
    `counters`: the mission's ledger.counter_series (for the clouds lost in each outage);
    `estimate_rows`: the manager's link_estimate.csv (its estimate against each step's capacity)."""
    from cps_experiments import judge as J

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
                *_outage_cells(counters, start, end),
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
                *_outage_cells(counters, start, end),
            )
        )
    lines += ["### Outages", ""]
    if rows:
        lines += [
            markdown_table(
                (
                    "outage",
                    "start, mission s",
                    "duration s",
                    "managed MB received meanwhile (stats windows)",
                    f"clouds lost (to {COUNTED_AFTER_S:g} s after)",
                    "keyframes for backfill",
                ),
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
    phase_list = J.phases(event_rows, max(times) if len(times) else 0.0)
    capacity = J.capacity_in_force(phase_list)

    def capacity_mbytes(t):
        return capacity(t) / 8.0

    estimate, estimate_points = estimate_at(estimate_rows)
    steps = []
    step_list = capacity_steps(event_rows)
    for k, (wall_s, mission_s, old, new) in enumerate(step_list):
        end_s = step_list[k + 1][0] if k + 1 < len(step_list) else math.inf
        settle = estimate_settles(estimate_points, wall_s, new, min(end_s, wall_s + STEP_SPAN_S))
        estimated = estimate(wall_s + ESTIMATE_TARGET_S)
        over_before, n_before = windows_over(times, totals, capacity_mbytes, wall_s - STEP_SPAN_S, wall_s)
        over_after, n_after = windows_over(times, totals, capacity_mbytes, wall_s, wall_s + STEP_SPAN_S)
        after = budget(wall_s + STEP_SPAN_S)
        soon = budget(wall_s + ESTIMATE_TARGET_S)
        steps.append(
            (
                f"{mission_s:.1f}",
                f"{old:g} → {new:g}",
                f"{over_before} of {n_before}",
                f"{over_after} of {n_after}",
                f"{new / 8.0:.3f}",
                "-" if math.isnan(after) else f"{after:.2f}" + (" (above the capacity)" if after > new / 8.0 else ""),
                _of_capacity(soon, new, "no budget logged"),
                _of_capacity(estimated / 8, new, "no estimate logged"),
                _settle_text(settle),
            )
        )
    lines += ["### Capacity steps", ""]
    if steps:
        lines += [
            f"Managed traffic at the twin in topic_stats' {2:g} s sliding windows (one a second) against the "
            f"capacity the scenario set, {STEP_SPAN_S:.0f} s before and after each step, and the budget the manager "
            f"planned with {STEP_SPAN_S:.0f} s after it. Delivered traffic cannot exceed the link: what the robots "
            "offered against the capacity, and whether the manager followed the step, are judged in the verdict.",
            "",
            markdown_table(
                (
                    "at mission s",
                    "Mbit/s",
                    "windows over the capacity before",
                    "after",
                    "capacity after, MB/s",
                    f"manager's budget {STEP_SPAN_S:.0f} s after, MB/s",
                    f"manager's budget {ESTIMATE_TARGET_S:g} s after, MB/s (of the capacity)",
                    f"manager's capacity estimate {ESTIMATE_TARGET_S:g} s after, MB/s (of the true)",
                    f"estimate within ±{ESTIMATE_BAND:.0%} of the true capacity from",
                ),
                steps,
            ),
            "",
        ]
    else:
        lines += ["- none", ""]
    return lines


def _mission_start(event_rows):
    start = next(r for r in event_rows if r["event"] == "start")
    return csv_float(start["wall_time_s"]) - csv_float(start["mission_time_s"])


def _of_capacity(mbytes_per_s, capacity_mbps, missing):
    """`x.xxx (NN%)`: MB/s and its share of the capacity (Mbit/s); `missing` when not logged."""
    if not math.isfinite(mbytes_per_s):
        return missing
    return f"{mbytes_per_s:.3f} ({mbytes_per_s / (capacity_mbps / 8.0):.0%})"


def _settle_text(settle_s):
    if math.isnan(settle_s):
        return "no estimate logged"
    return "never" if math.isinf(settle_s) else f"{settle_s:.1f} s"


def _seconds(value):
    return f"{value:.1f}" if math.isfinite(value) else "still down at the end"
