"""A synthetic mission folder with every file a mission writes, for the verdict's and the ledger's
tests: two robots, clouds at 2 Hz, jackal's video at 10 fps, the command probe at 10 Hz, a map
server that inserts and publishes every second, and every node's ledger counters balanced. Each
argument changes one thing, so that a test shows what one fault does to the verdict."""

import csv
import json

from cps_bringup.mission import MAP_AGE_COLUMNS, MAP_SERVER_COUNTERS
from cps_fleet import names
from cps_ros import cloud_ledger as C
from cps_transport.topic_stats import COUNTER_COLUMNS

T0 = 1000.0  # wall time of mission second 0
ROBOTS = ("scout", "jackal")
CLOUD_HZ = 2.0
EVENT_COLUMNS = ("mission_time_s", "wall_time_s", "event", "rate_mbps", "delay_ms", "jitter_ms", "loss_pct", "note")


def write_csv(path, columns, rows):
    with open(path, "w", newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(columns)
        writer.writerows(rows)


def event(mission_s, kind, rate_mbps):
    return (mission_s, T0 + mission_s, kind, rate_mbps, 0, 0, 0, "scenario test" if kind == "start" else "")


def mission(
    folder,
    duration_s=60,
    events=None,
    published_age=lambda robot, t: 0.6,
    inserted_age=lambda robot, t: 0.5,
    state=lambda robot, t: "inspecting",
    stats_times=None,
    cloud_times=None,
    budget=lambda t: 6.9,
    f1=(0.7, 0.95),
    counters=True,
    lost_in_limiter_queue=0,
    link_down=(),
):
    """Write the mission into `folder` (a pathlib.Path); returns it. Times are mission seconds;
    link_down: (from, to) of each outage the twin's bridge reported (link_state.csv)."""
    folder.mkdir(parents=True, exist_ok=True)
    events = events if events is not None else [event(0, "start", 60)]
    write_csv(folder / "link_events.csv", EVENT_COLUMNS, events)
    stats_times = stats_times if stats_times is not None else list(range(duration_s))
    cloud_times = cloud_times or (lambda robot: [k / CLOUD_HZ for k in range(int(duration_s * CLOUD_HZ))])
    clouds = {r: [t for t in cloud_times(r) if t < duration_s] for r in ROBOTS}
    rows = [(f"{T0 - 1:.3f}", r, "nan", "start") + ("",) * (len(MAP_AGE_COLUMNS) - 4) for r in ROBOTS]
    for t in stats_times:
        for r in ROBOTS:
            inserted = sum(1 for c in clouds[r] if c < t)
            rows.append(
                (f"{T0 + t:.3f}", r, inserted_age(r, t), state(r, t), inserted, published_age(r, t))
                + (inserted,)  # clouds_received; every other counter 0
                + (0,) * (len(MAP_SERVER_COUNTERS) - 1)
            )
    rows += [(f"{T0 + duration_s:.3f}", r, "nan", "end") + ("",) * (len(MAP_AGE_COLUMNS) - 4) for r in ROBOTS]
    write_csv(folder / "map_age.csv", MAP_AGE_COLUMNS, rows)
    arrivals = [
        ("/" + names.managed_cloud_at_twin(r), r, int((T0 + t - 0.05) * 1e9), f"{T0 + t:.6f}")
        for r in ROBOTS
        for t in clouds[r]
    ]
    video = names.absolute(names.robot_topic("jackal", names.CAMERA_IMAGE_COMPRESSED))
    arrivals += [
        (video, "jackal", int((T0 + k / 10 - 0.03) * 1e9), f"{T0 + k / 10:.6f}") for k in range(duration_s * 10)
    ]
    write_csv(folder / "arrivals.csv", ("topic", "robot", "stamp_ns", "receive_s"), arrivals)
    probe = names.absolute(names.COMMAND_PROBE)
    physical = [(probe, "", int((T0 + k / 10 - 0.01) * 1e9), f"{T0 + k / 10:.6f}") for k in range(duration_s * 10)]
    physical += [
        (
            names.absolute(names.robot_topic(r, names.POINTS_FILTERED)),
            r,
            int((T0 + t - 0.1) * 1e9),
            f"{T0 + t - 0.09:.6f}",
        )
        for r in ROBOTS
        for t in clouds[r]
    ]
    write_csv(folder / "physical_arrivals.csv", ("topic", "robot", "stamp_ns", "receive_s"), physical)
    stats_columns = ("time_s", "topic", "robot", "managed", "messages", "mean_message_bytes")
    offered = [
        (T0 + s, "/" + names.managed_cloud(r), r, "True", 4, 20000) for s in range(1, duration_s) for r in ROBOTS
    ]
    offered += [(T0 + s, video, "jackal", "True", 20, 5000) for s in range(1, duration_s)]
    write_csv(folder / "physical_stats.csv", stats_columns, offered)
    write_csv(
        folder / "stats.csv",
        stats_columns,
        [(T0 + s, "/" + names.managed_cloud_at_twin("scout"), "scout", "True", 4, 20000) for s in range(duration_s)],
    )
    write_csv(
        folder / "allocation.csv",
        ("stamp_s", "budget_mbytes_per_s", "robot", "stream", "rate_hz"),
        [(T0 + s + 0.5, budget(s + 0.5), r, "cloud", 2.0) for s in range(duration_s) for r in ROBOTS]
        + [(T0 + s + 0.5, budget(s + 0.5), "jackal", "video", 10.0) for s in range(duration_s)],
    )
    states = [(T0, 1, T0, 0, 0.0, "robots", 60.0)]
    for k, (down_s, up_s) in enumerate(link_down):
        states.append((T0 + down_s, 0, T0 + down_s, k + 1, 0.0, "robots", 60.0))
        states.append((T0 + up_s, 1, T0 + up_s, k + 1, up_s - down_s, "robots", 60.0))
    write_csv(
        folder / "link_state.csv",
        ("stamp_s", "up", "since_s", "outages", "last_outage_s", "peer", "available_mbps"),
        [s for s in states if s[0] < T0 + duration_s],
    )
    write_csv(folder / "trajectories.csv", ("robot", "sample", "x_m", "y_m", "z_m"), [("scout", 0, 0, 0, 0)])
    (folder / "map.bt").write_bytes(b"# Octomap OcTree binary file\n")
    (folder / "scores.json").write_text(json.dumps({"f1_exact": f1[0], "f1_within_1_voxel": f1[1]}))
    if counters:
        write_counters(folder, {r: len(clouds[r]) for r in ROBOTS}, stats_times, lost_in_limiter_queue)
    return folder


def write_counters(folder, captured, stats_times, lost_in_limiter_queue=0):
    """Every node's ledger counters at the end, balanced: each robot's clouds all inserted (the map
    server's received and inserted in map_age.csv's last row are set to them too)."""
    physical, twin = [], []
    t = f"{T0 + max(stats_times, default=0):.3f}"
    for r, n in captured.items():
        lost = lost_in_limiter_queue
        stages = [
            (
                physical,
                "/cloud_tissue",
                names.absolute(names.robot_topic(r, names.POINTS_FILTERED)),
                C.ENCODER,
                {C.RECEIVED: n, C.OUT: n},
            ),
            (
                physical,
                "/cloud_tissue",
                names.absolute(names.robot_topic(r, names.POINTS_DRACO)),
                C.LIMITER,
                {C.RECEIVED: n - lost, C.MISSED: lost, C.OUT: n - lost},
            ),
            (
                physical,
                "/zenoh_bridge",
                names.absolute(names.managed_cloud(r)),
                C.BRIDGE_OUT,
                {C.RECEIVED: n - lost, C.OUT: n - lost},
            ),
            (
                twin,
                "/zenoh_bridge",
                names.absolute(names.managed_cloud_at_twin(r)),
                C.BRIDGE_IN,
                {C.RECEIVED: n - lost, C.OUT: n - lost},
            ),
        ]
        for rows, node, topic, stage, values in stages:
            rows += [(t, node, topic, C.key(stage, what), v) for what, v in values.items()]
    write_csv(folder / "physical_counters.csv", COUNTER_COLUMNS, physical)
    write_csv(folder / "counters.csv", COUNTER_COLUMNS, twin)
    # The map server received and inserted every cloud that reached it.
    with open(folder / "map_age.csv", newline="") as stream:
        rows = list(csv.reader(stream))
    last = {}
    for i, row in enumerate(rows[1:], start=1):
        if row[3] not in ("start", "end"):
            last[row[1]] = i
    for r, i in last.items():
        reached = captured[r] - lost_in_limiter_queue
        rows[i][4] = str(reached)
        rows[i][MAP_AGE_COLUMNS.index("clouds_received")] = str(reached)
    write_csv(folder / "map_age.csv", rows[0], rows[1:])
