#!/usr/bin/env python3
"""Benchmark of the multi-robot map server's insertion (cps_mapping) on cps_sim clouds.

Anchor, measured in the same run: plain sequential OctoMap insertion, what octomap_server does
per cloud (insertPointCloud of every point, its own origin, max range, no discretization,
inner nodes updated per cloud). Ours: FusedOctoMap.insert_batch (batches of consecutive
clouds of one robot, discretized in numpy, lazy inner-node update).

1. Throughput at 0.1 m and 0.05 m: clouds/s and points/s of both on the same cloud stream,
   and how their maps agree (occupied voxels) and score against the ground truth.
2. Keeping up: the four-robot fleet streams at its sensor rates (the managed rates are at most
   these); a discrete-event run of the server's queues (bounded, drop-oldest, round-robin) in
   which every insertion really runs and takes the time it takes; map age p95 and drops.

The clouds: every robot moves along its route at `--speed` m/s and captures at its sensor rate,
voxelized as the digital tissue does (fleet.yaml voxel_leaf_m). Timings on a shared 2-core
machine are noisy.

    python bench/mapping_bench.py [--profile paper] [--seconds 3] [--batch 3]
"""
import argparse
import math
import time

import numpy as np
import octomap

from cps_mapping.octree_map import FusedOctoMap, index_to_center, near_any, pack_index, voxel_index
from cps_mapping.scoring import score_map
from cps_msgs.fleet import load_fleet
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


def plain_tree(resolution_m, model):
    tree = octomap.OcTree(resolution_m)
    tree.setProbHit(model.hit)
    tree.setProbMiss(model.miss)
    tree.setClampingThresMin(model.min)
    tree.setClampingThresMax(model.max)
    return tree


def occupied_of_tree(tree, resolution_m):
    fused = FusedOctoMap(resolution_m)
    fused.tree = tree
    fused.version += 1
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


def throughput(fleet, stream, resolution_m, batch, truth):
    model = fleet.mapping.sensor_model
    ranges = {r.name: fleet.mapping.max_range_m[r.type] for r in fleet.robots}
    points = sum(len(c[2]) for c in stream)

    tree = plain_tree(resolution_m, model)
    start = time.perf_counter()
    for _, robot, pts, origin, _ in stream:
        tree.insertPointCloud(pts, origin, maxrange=ranges[robot])
    plain_s = time.perf_counter() - start
    plain_occ = occupied_of_tree(tree, resolution_m)

    fused = FusedOctoMap.from_mapping_config(fleet.mapping)
    fused.resolution_m = resolution_m
    fused.reset()
    start = time.perf_counter()
    for group in batches_of(stream, batch):
        fused.insert_batch([(c[2], c[3]) for c in group], max_range_m=ranges[group[0][1]], robot=group[0][1])
    ours_s = time.perf_counter() - start
    ours_occ = fused.occupied_index()

    plain_keys, ours_keys = set(pack_index(plain_occ).tolist()), set(pack_index(ours_occ).tolist())
    both = len(plain_keys & ours_keys)
    row = dict(resolution_m=resolution_m, batch=batch, clouds=len(stream), points=points,
               plain_clouds_per_s=len(stream) / plain_s, plain_points_per_s=points / plain_s,
               ours_clouds_per_s=len(stream) / ours_s, ours_points_per_s=points / ours_s,
               speedup=plain_s / ours_s, plain_occupied=len(plain_keys), ours_occupied=len(ours_keys),
               plain_in_ours=both / max(len(plain_keys), 1), ours_in_plain=both / max(len(ours_keys), 1),
               jaccard=both / max(len(plain_keys | ours_keys), 1),
               plain_in_ours_tol1=float(near_any(plain_occ, ours_occ, 1).mean()) if len(plain_occ) else 0.0)
    if truth is not None:
        from cps_sim.ground_truth import occupied_voxels

        gt = occupied_voxels(truth, resolution_m)
        for name, occ in (("plain", plain_occ), ("ours", ours_occ)):
            s = score_map(index_to_center(occ, resolution_m), gt, resolution_m)
            row[f"{name}_precision"], row[f"{name}_recall"], row[f"{name}_f1"] = s.precision, s.recall, s.f1
    return row


def keep_up(fleet, stream, queue_size, plain=False):
    """Discrete-event run of the server: arrivals at their stamps, one worker, real insertion times."""
    ranges = {r.name: fleet.mapping.max_range_m[r.type] for r in fleet.robots}
    robots = sorted({c[1] for c in stream})
    queues = {r: [] for r in robots}
    dropped = {r: 0 for r in robots}
    newest = {r: None for r in robots}
    ages = {r: [] for r in robots}
    fused = FusedOctoMap.from_mapping_config(fleet.mapping)
    tree = plain_tree(fleet.mapping.resolution_m, fleet.mapping.sensor_model)
    clock, i, turn = 0.0, 0, 0
    end = stream[-1][0] + 1.0
    next_sample = 0.0

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
        ready = [r for r in robots[turn:] + robots[:turn] if queues[r]]
        if not ready:
            nxt = stream[i][0] if i < len(stream) else end
            sample_until(nxt)
            clock = nxt
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
        clock += time.perf_counter() - start
        sample_until(clock)
        newest[robot] = max(c[0] for c in batch)
    return {r: dict(p95_age_s=float(np.percentile(ages[r], 95)) if ages[r] else math.inf,
                    dropped=dropped[r], clouds=sum(c[1] == r for c in stream)) for r in robots}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--profile", default="paper")
    parser.add_argument("--seconds", type=float, default=3.0, help="stream length per robot, s")
    parser.add_argument("--speed", type=float, default=0.5, help="robot speed along its route, m/s")
    parser.add_argument("--batch", type=int, nargs="+", default=[3, 10], help="clouds per batch in the throughput run")
    parser.add_argument("--queue-size", type=int, default=3)
    args = parser.parse_args()

    t0 = time.perf_counter()
    fleet, stream = render_stream(args.profile, args.seconds, args.speed)
    from cps_sim.site import load_site

    site = load_site(fleet.site_path)
    per_robot = {}
    for c in stream:
        per_robot.setdefault(c[1], []).append(len(c[2]))
    print(f"# {len(stream)} clouds rendered in {time.perf_counter() - t0:.1f} s (profile {args.profile}, "
          f"{args.seconds} s per robot at {args.speed} m/s)")
    for robot, sizes in per_robot.items():
        print(f"#   {robot}: {len(sizes)} clouds, {np.mean(sizes):.0f} points/cloud after the tissue's voxel grid")

    print("\n## Throughput (ours vs plain sequential OctoMap insertion, same clouds)")
    print("| res m | batch | plain clouds/s | plain points/s | ours clouds/s | ours points/s | speed-up | "
          "plain occ. in ours | ours occ. in plain | Jaccard | plain in ours ±1 voxel | F1 plain | F1 ours |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for res in (0.1, 0.05):
        for batch in args.batch:
            r = throughput(fleet, stream, res, batch, site)
            print(f"| {res} | {batch} | {r['plain_clouds_per_s']:.1f} | {r['plain_points_per_s']:.0f} | "
                  f"{r['ours_clouds_per_s']:.1f} | {r['ours_points_per_s']:.0f} | {r['speedup']:.1f}x | "
                  f"{r['plain_in_ours']:.3f} | {r['ours_in_plain']:.3f} | {r['jaccard']:.3f} | "
                  f"{r['plain_in_ours_tol1']:.3f} | {r['plain_f1']:.3f} | {r['ours_f1']:.3f} |", flush=True)

    print(f"\n## Keeping up: the fleet at its {args.profile} sensor rates, queue {args.queue_size} per robot, "
          f"0.1 m (fleet.yaml)")
    print("| server | robot | clouds | dropped | map age p95 s |")
    print("|---|---|---|---|---|")
    for label, plain in (("plain sequential", True), ("ours", False)):
        for robot, r in keep_up(fleet, stream, args.queue_size, plain).items():
            print(f"| {label} | {robot} | {r['clouds']} | {r['dropped']} | {r['p95_age_s']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
