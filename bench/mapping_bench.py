#!/usr/bin/env python3
"""Benchmark of the multi-robot map server's insertion (cps_mapping) on cps_sim clouds.

Anchor, measured in the same run: plain sequential OctoMap insertion, what octomap_server does
per cloud (insertPointCloud of every point, its own origin, max range, no discretization,
inner nodes updated per cloud). Ours: FusedLogOddsMap.insert_batch (ray casting and log-odds per
cloud in a compiled kernel over a dense grid) in both free-space modes: exact (OctoMap's rays,
the same map) and shared-origin casting (the map server's default: rays cast back from their
endpoints, stopping where the cloud already cleared).

1. Throughput at 0.1 m and 0.05 m: clouds/s and points/s of plain and of both modes on the same
   cloud stream, timed in the same runs (median of `--runs` runs; ours includes writing the .bt
   map message once per second of stream time, as the node's publisher does), how the maps agree
   (occupied and known voxels, log-odds) and F1 against the ground truth.
2. Keeping up: the four robots replayed at the bandwidth manager's typical rates (`--depth-hz`,
   `--lidar-hz`) for `--keep-up-s` seconds (the rendered clouds looped); a discrete-event run of
   the server (bounded drop-oldest queues served round-robin, one worker; every second the
   publisher's snapshot under the map lock) in which every insertion and snapshot really runs and
   takes the time it takes; map age p95 and drops.

The clouds: every robot moves along its route at `--speed` m/s and captures at its sensor rate,
voxelized as the digital tissue does (fleet.yaml voxel_leaf_m). Timings on a shared 2-core
machine are noisy.

    python bench/mapping_bench.py [--profile paper] [--seconds 1] [--runs 3] [--cache clouds.pkl]
"""

import argparse
import math
import os
import pickle
import time

import numpy as np

from cps_fleet.fleet import load_fleet
from cps_mapping.fused_map import (
    FusedLogOddsMap,
    _finest_voxels,
    index_to_center,
    message_fields,
    new_octree,
    pack_index,
)
from cps_mapping.log_odds_grid import warm_up
from cps_mapping.scoring import score_map
from cps_transport.voxel import voxel_downsample


def route_polyline(fleet, name):
    start = fleet.robot(name).initial_pose
    pts = [(start.x, start.y, start.z)] + [(w.x, w.y, w.z) for w in fleet.route(name).waypoints]
    return np.array(pts, dtype=float)


def pose_at(polyline, distance_m):
    seg = np.linalg.norm(np.diff(polyline[:, :2], axis=0), axis=1)
    for i, length in enumerate(seg):
        if distance_m <= length or i == len(seg) - 1:
            f = min(distance_m / length, 1.0) if length > 0 else 0.0
            p = polyline[i] + f * (polyline[i + 1] - polyline[i])
            yaw = math.atan2(polyline[i + 1][1] - polyline[i][1], polyline[i + 1][0] - polyline[i][0])
            return p, yaw
        distance_m -= length
    raise AssertionError("unreachable")


def render_stream(profile, seconds, speed_mps, start_fraction=0.3):
    """[(stamp_s, robot, points_map voxelized, origin_m, rate_hz)] sorted by stamp."""
    from cps_sim.simulation import build_fleet_simulation, points_in_map

    sim = build_fleet_simulation(None, profile, None, "egl")
    fleet = sim.fleet
    stream = []
    try:
        for name, robot in sim.robots.items():
            cfg = fleet.robot(name)
            rate = fleet.profile.lidar.rate_hz if cfg.has_lidar else fleet.profile.depth_camera.rate_hz
            line = route_polyline(fleet, name)
            total = np.linalg.norm(np.diff(line[:, :2], axis=0), axis=1).sum()
            for k in range(int(seconds * rate)):
                t = k / rate
                p, yaw = pose_at(line, start_fraction * total + speed_mps * t)
                sim.place(name, p[0], p[1], p[2], yaw)
                frame = sim.capture(name)
                pts = voxel_downsample(points_in_map(frame), cfg.voxel_leaf_m)
                stream.append((t, name, np.asarray(pts, dtype=np.float64), frame.sensor_in_map[:3, 3].copy(), rate))
    finally:
        sim.close()
    return fleet, sorted(stream, key=lambda c: (c[0], c[1]))


def occupied_of_tree(fleet, tree, resolution_m):
    fused = FusedLogOddsMap(resolution_m, fleet.mapping.sensor_model)
    fused.tree = tree
    return fused.occupied_index()


def batches_of(stream, batch):
    """Consecutive clouds of each robot in groups of `batch`, in arrival order of the group's last cloud."""
    pending, out = {}, []
    for cloud in stream:
        pending.setdefault(cloud[1], []).append(cloud)
        if len(pending[cloud[1]]) == batch:
            out.append(pending.pop(cloud[1]))
    out.extend(v for v in pending.values() if v)
    return out


def run_plain(fleet, stream, resolution_m):
    ranges = {r.name: fleet.mapping.max_range_m[r.type] for r in fleet.robots}
    tree = new_octree(resolution_m, fleet.mapping.sensor_model)
    start = time.perf_counter()
    for _, robot, pts, origin, _ in stream:
        tree.insertPointCloud(pts, origin, maxrange=ranges[robot])
    return time.perf_counter() - start, tree


def new_map(fleet, resolution_m, exact):
    return FusedLogOddsMap(resolution_m, fleet.mapping.sensor_model, exact_free_space=exact)


def run_ours(fleet, stream, resolution_m, batch, exact):
    """insert_batch per batch; the .bt map message written after every second of stream time."""
    ranges = {r.name: fleet.mapping.max_range_m[r.type] for r in fleet.robots}
    fused = new_map(fleet, resolution_m, exact)
    next_read = 1.0
    start = time.perf_counter()
    for group in batches_of(stream, batch):
        fused.insert_batch([(c[2], c[3]) for c in group], max_range_m=ranges[group[0][1]], robot=group[0][1])
        if group[-1][0] >= next_read:
            fused.to_bytes(binary=True)
            next_read += 1.0
    fused.to_bytes(binary=True)
    return time.perf_counter() - start, fused


MODES = (("exact", True), ("shared-origin", False))


def throughput(fleet, stream, resolution_m, batch, truth, runs):
    """One row per mode; plain and both modes timed in the same runs, one after the other."""
    points = sum(len(c[2]) for c in stream)
    plain_times, ours_times, maps = [], {m: [] for m, _ in MODES}, {}
    for _ in range(runs):
        seconds, tree = run_plain(fleet, stream, resolution_m)
        plain_times.append(seconds)
        for mode, exact in MODES:
            seconds, maps[mode] = run_ours(fleet, stream, resolution_m, batch, exact)
            ours_times[mode].append(seconds)
    plain_s = float(np.median(plain_times))
    plain_occ = occupied_of_tree(fleet, tree, resolution_m)
    plain_idx, plain_val = _finest_voxels(tree, resolution_m)
    plain_map = dict(zip(pack_index(plain_idx).tolist(), plain_val.tolist()))
    plain_keys = set(pack_index(plain_occ).tolist())
    gt = None
    if truth is not None:
        from cps_sim.ground_truth import occupied_voxels

        gt = occupied_voxels(truth, resolution_m)
    rows = []
    for mode, _ in MODES:
        fused = maps[mode]
        ours_s = float(np.median(ours_times[mode]))
        ours_occ = fused.occupied_index()
        flat, values = fused._grid.known()
        ours_map = dict(zip(pack_index(fused._grid.index_of_flat(flat)).tolist(), values.astype(np.float64).tolist()))
        common = plain_map.keys() & ours_map.keys()
        max_dl = max((abs(plain_map[k] - ours_map[k]) for k in common), default=0.0)
        ours_keys = set(pack_index(ours_occ).tolist())
        both = len(plain_keys & ours_keys)
        row = dict(
            mode=mode,
            resolution_m=resolution_m,
            batch=batch,
            clouds=len(stream),
            points=points,
            runs=runs,
            plain_s=plain_times,
            ours_s=ours_times[mode],
            plain_clouds_per_s=len(stream) / plain_s,
            plain_points_per_s=points / plain_s,
            ours_clouds_per_s=len(stream) / ours_s,
            ours_points_per_s=points / ours_s,
            speedup=plain_s / ours_s,
            plain_occupied=len(plain_keys),
            ours_occupied=len(ours_keys),
            plain_in_ours=both / max(len(plain_keys), 1),
            ours_in_plain=both / max(len(ours_keys), 1),
            jaccard=both / max(len(plain_keys | ours_keys), 1),
            known_jaccard=len(common) / max(len(plain_map.keys() | ours_map.keys()), 1),
            max_log_odds_difference=max_dl,
            steps_per_cloud=fused._grid.steps / len(stream),
            ours_memory_mb=fused.memory_bytes() / 1e6,
            ours_grid_mb=fused.stats()["grid_bytes"] / 1e6,
            grid_voxels=tuple(fused._grid.dims.tolist()),
            plain_memory_mb=tree.memoryUsage() / 1e6,
        )
        if gt is not None:
            for name, occ in (("plain", plain_occ), ("ours", ours_occ)):
                s = score_map(index_to_center(occ, resolution_m), gt, resolution_m)
                for label, match in (("exact", s.exact), ("within_1_voxel", s.tolerant)):
                    row[f"{name}_precision_{label}"], row[f"{name}_recall_{label}"] = match.precision, match.recall
                    row[f"{name}_f1_{label}"] = match.f1
        rows.append(row)
    return rows


def replay(stream, depth_hz, lidar_hz, seconds, fleet):
    """The rendered stream thinned to the managed rates and looped to `seconds`."""
    lidar = {r.name for r in fleet.robots if fleet.robot(r.name).has_lidar}
    length = max(c[0] for c in stream) + min(1.0 / c[4] for c in stream)
    out = []
    for t, robot, pts, origin, rate in stream:
        want = lidar_hz if robot in lidar else depth_hz
        every = max(int(round(rate / want)), 1)
        if round(t * rate) % every:
            continue
        loop = 0
        while t + loop * length < seconds:
            out.append((t + loop * length, robot, pts, origin, rate / every))
            loop += 1
    return sorted(out, key=lambda c: (c[0], c[1]))


def snapshot(fused):
    """What map_server's publisher does under the map lock once per period."""
    occupied = fused.occupied_index()
    fused.occupied_leaves()
    fused.projected_grid(0.1, 2.0)
    message_fields(fused, binary=True)
    fused.contributions(occupied)
    fused.binary_tree_nodes()
    fused.memory_bytes()


def keep_up(fleet, stream, queue_size, plain=False, publish_period_s=1.0, exact=False):
    """Discrete-event run of the server: arrivals at their stamps, one worker, real insertion times."""
    ranges = {r.name: fleet.mapping.max_range_m[r.type] for r in fleet.robots}
    robots = sorted({c[1] for c in stream})
    queues = {r: [] for r in robots}
    dropped = {r: 0 for r in robots}
    newest = {r: None for r in robots}
    ages = {r: [] for r in robots}
    fused = new_map(fleet, fleet.mapping.resolution_m, exact)
    tree = new_octree(fleet.mapping.resolution_m, fleet.mapping.sensor_model)
    clock, i, turn = 0.0, 0, 0
    end = stream[-1][0] + 1.0
    next_sample, next_publish = 0.0, publish_period_s
    busy = 0.0

    def sample_until(t):
        nonlocal next_sample
        while next_sample <= t:
            if next_sample >= 1.0:  # after the first second, every robot has had a chance
                for r in robots:
                    ages[r].append(next_sample - newest[r] if newest[r] is not None else math.inf)
            next_sample += 0.1

    while clock < end:
        while i < len(stream) and stream[i][0] <= clock:
            q = queues[stream[i][1]]
            if len(q) >= queue_size:
                q.pop(0)
                dropped[stream[i][1]] += 1
            q.append(stream[i])
            i += 1
        if clock >= next_publish and not plain:
            start = time.perf_counter()
            snapshot(fused)
            spent = time.perf_counter() - start
            clock += spent
            busy += spent
            next_publish += publish_period_s
            sample_until(clock)
            continue
        ready = [r for r in robots[turn:] + robots[:turn] if queues[r]]
        if not ready:
            nxt = stream[i][0] if i < len(stream) else end
            nxt = min(nxt, next_publish) if not plain else nxt
            sample_until(nxt)
            clock = max(nxt, clock)
            continue
        robot = ready[0]
        turn = (robots.index(robot) + 1) % len(robots)
        if plain:
            batch = [queues[robot].pop(0)]
            start = time.perf_counter()
            tree.insertPointCloud(batch[0][2], batch[0][3], maxrange=ranges[robot])
        else:
            batch, queues[robot] = queues[robot], []
            start = time.perf_counter()
            fused.insert_batch([(c[2], c[3]) for c in batch], max_range_m=ranges[robot], robot=robot)
        spent = time.perf_counter() - start
        clock += spent
        busy += spent
        sample_until(clock)
        newest[robot] = max(c[0] for c in batch)
    return {
        r: dict(
            p95_age_s=float(np.percentile(ages[r], 95)) if ages[r] else math.inf,
            dropped=dropped[r],
            clouds=sum(c[1] == r for c in stream),
            busy=busy / end,
        )
        for r in robots
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--profile", default="paper")
    parser.add_argument("--seconds", type=float, default=1.0, help="stream length per robot, s")
    parser.add_argument("--speed", type=float, default=0.5, help="robot speed along its route, m/s")
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 3], help="clouds per insert_batch call")
    parser.add_argument("--resolutions", type=float, nargs="+", default=[0.1, 0.05])
    parser.add_argument("--runs", type=int, default=3, help="timed runs per row (median reported)")
    parser.add_argument("--queue-size", type=int, default=3)
    parser.add_argument("--depth-hz", type=float, nargs="+", default=[10.0, 30.0], help="managed depth rates to replay")
    parser.add_argument("--lidar-hz", type=float, default=10.0)
    parser.add_argument("--keep-up-s", type=float, default=20.0)
    parser.add_argument("--cache", help="pickle of the rendered stream: read if present, else written")
    args = parser.parse_args()

    t0 = time.perf_counter()
    if args.cache and os.path.exists(args.cache):
        with open(args.cache, "rb") as f:
            stream = pickle.load(f)
        fleet = load_fleet(profile=args.profile)
    else:
        fleet, stream = render_stream(args.profile, args.seconds, args.speed)
        if args.cache:
            with open(args.cache, "wb") as f:
                pickle.dump(stream, f)
    stream = [c for c in stream if c[0] < args.seconds]
    from cps_fleet.site import load_site

    site = load_site(fleet.site_path)
    per_robot = {}
    for c in stream:
        per_robot.setdefault(c[1], []).append(len(c[2]))
    print(
        f"# {len(stream)} clouds ready in {time.perf_counter() - t0:.1f} s (profile {args.profile}, "
        f"{args.seconds} s per robot at {args.speed} m/s); load average {os.getloadavg()[0]:.1f} on "
        f"{os.cpu_count()} cores"
    )
    for robot, sizes in per_robot.items():
        print(f"#   {robot}: {len(sizes)} clouds, {np.mean(sizes):.0f} points/cloud after the tissue's voxel grid")
    warm_up()  # load (or compile) the kernels outside the timing

    print(f"\n## Throughput (ours vs plain sequential OctoMap insertion, same clouds, median of {args.runs} runs)")
    print(
        "| res m | batch | ours: free space | plain clouds/s | plain points/s | ours clouds/s | ours points/s | "
        "speed-up | plain occ. in ours | ours occ. in plain | Jaccard occ. | Jaccard known | max abs log-odds diff | "
        "voxel steps/cloud | F1 exact plain | F1 exact ours | F1 within ±1 voxel plain | F1 within ±1 voxel ours | plain s (runs) | ours s (runs) | plain tree MB | "
        "ours grid MB (voxels) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for res in args.resolutions:
        for batch in args.batch:
            for r in throughput(fleet, stream, res, batch, site, args.runs):
                print(
                    f"| {res} | {batch} | {r['mode']} | {r['plain_clouds_per_s']:.1f} | {r['plain_points_per_s']:.0f} | "
                    f"{r['ours_clouds_per_s']:.1f} | {r['ours_points_per_s']:.0f} | {r['speedup']:.1f}x | "
                    f"{r['plain_in_ours']:.4f} | {r['ours_in_plain']:.4f} | {r['jaccard']:.4f} | "
                    f"{r['known_jaccard']:.4f} | {r['max_log_odds_difference']:.1e} | {r['steps_per_cloud']:.0f} | "
                    f"{r['plain_f1_exact']:.3f} | {r['ours_f1_exact']:.3f} | "
                    f"{r['plain_f1_within_1_voxel']:.3f} | {r['ours_f1_within_1_voxel']:.3f} | "
                    f"{' '.join(f'{x:.2f}' for x in r['plain_s'])} | {' '.join(f'{x:.3f}' for x in r['ours_s'])} | "
                    f"{r['plain_memory_mb']:.0f} | {r['ours_grid_mb']:.0f} ({'x'.join(map(str, r['grid_voxels']))}) |",
                    flush=True,
                )
            print(f"<!-- load average {os.getloadavg()[0]:.1f} after {res} m batch {batch} -->", flush=True)

    print(
        f"\n## Keeping up: four robots at managed rates for {args.keep_up_s:g} s, queue {args.queue_size} per robot, "
        f"{fleet.mapping.resolution_m} m (fleet.yaml), publisher snapshot every 1 s"
    )
    print("| ours: free space | depth Hz | lidar Hz | robot | clouds | dropped | map age p95 s | worker busy |")
    print("|---|---|---|---|---|---|---|---|")
    for mode, exact in (("shared-origin", False), ("exact", True)):
        for depth_hz in args.depth_hz:
            replayed = replay(stream, depth_hz, args.lidar_hz, args.keep_up_s, fleet)
            for robot, r in keep_up(fleet, replayed, args.queue_size, exact=exact).items():
                print(
                    f"| {mode} | {depth_hz:g} | {args.lidar_hz:g} | {robot} | {r['clouds']} | {r['dropped']} | "
                    f"{r['p95_age_s']:.2f} | {r['busy']:.0%} |",
                    flush=True,
                )
    print(f"<!-- load average {os.getloadavg()[0]:.1f} at the end -->")


if __name__ == "__main__":
    main()
