#!/usr/bin/env python3
"""Cloud levels benchmark: bytes per managed cloud at each level of fleet.yaml's streams.cloud_levels
on clouds cps_sim renders along each robot's route (the demo's profile, `light` by default), as the
robot's tissue sends them: voxel grid at the level's leaf (pcl's semantics), Draco at the tissue's
tolerance (cloud_levels.position_tolerance_m: half the leaf, at most 1/8 of the map's resolution),
the leaf carried with the cloud. Anchors in the same run: the same clouds without the leaf (the
carrier's cost), Draco at half the leaf (the tolerance before the levels), and fleet.yaml's
bytes_prior (the manager's assumption before it learns the size).

    source ci/env.sh && python bench/cloud_levels_bench.py [--frames 5] [--profile light] [--out docs/benchmarks/cloud_levels.md]
"""

import argparse
import io
import sys

import numpy as np

from cps_fleet.fleet import load_fleet
from cps_transport.cloud_levels import cloud_level_leaves, position_tolerance_m
from cps_transport.draco import DracoEncoder
from cps_transport.stream_sizes import filter_cloud


def serialized_bytes(msg):
    """What the rate limiter counts: the serialized message's length."""
    buffer = io.BytesIO()
    msg.serialize(buffer)
    return len(buffer.getvalue())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=5, help="poses along each robot's route")
    parser.add_argument("--profile", default=None, help="sensor profile (default: fleet.yaml's)")
    parser.add_argument("--out", default=None, help="write the table as markdown here")
    args = parser.parse_args(argv)

    from cps_sim.sample_clouds import render_mission_clouds

    fleet = load_fleet(profile=args.profile)
    leaves = cloud_level_leaves(fleet)
    priors = [level.bytes_prior for level in fleet.streams.cloud_levels]
    resolution = fleet.mapping.resolution_m
    clouds = render_mission_clouds(fleet.profile.name, frames_per_robot=args.frames)
    rows = []
    for robot, samples in clouds.items():
        for index, leaf in enumerate(leaves):
            encoder = DracoEncoder(position_tolerance_m=position_tolerance_m(leaf, resolution))
            half_leaf = DracoEncoder(position_tolerance_m=0.5 * leaf)
            points, labelled, plain, before = [], [], [], []
            for sample in samples:
                filtered, _ = filter_cloud(sample.cloud, leaf)
                points.append(filtered.width * filtered.height)
                labelled.append(serialized_bytes(encoder.encode(filtered, leaf_size_m=leaf)))
                plain.append(serialized_bytes(encoder.encode(filtered)))
                before.append(serialized_bytes(half_leaf.encode(filtered)))
            rows.append(
                (
                    robot,
                    index,
                    leaf,
                    np.mean(points),
                    np.mean(labelled),
                    min(labelled),
                    max(labelled),
                    np.mean(labelled) - np.mean(plain),
                    np.mean(before),
                    priors[index],
                )
            )
    header = (
        f"Bytes per managed cloud per level, {fleet.profile.name} profile, {args.frames} poses along each "
        f"robot's route (cps_sim), map resolution {resolution} m; serialized CompressedPointCloud2 as the "
        "rate limiter counts it. `leaf cost`: bytes the carried leaf adds (anchor: the same cloud without "
        "it); `half leaf`: the same cloud at Draco's tolerance before the levels (half the leaf, no leaf "
        "carried); `/ prior`: mean over fleet.yaml's bytes_prior for that level.\n\n"
        "| robot | level | leaf m | points | bytes mean | min | max | leaf cost | half leaf | mean / half leaf "
        "| bytes_prior | mean / prior |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = [
        f"| {r} | {i} | {leaf:.2f} | {pts:.0f} | {mean:.0f} | {lo} | {hi} | {cost:.0f} | {old:.0f} | {mean / old:.2f} "
        f"| {prior:.0f} | {mean / prior:.2f} |"
        for r, i, leaf, pts, mean, lo, hi, cost, old, prior in rows
    ]
    table = header + "\n".join(lines) + "\n"
    print(table)
    if args.out:
        with open(args.out, "w") as stream:
            stream.write(
                "# Cloud levels: bytes per cloud\n\n"
                + f"`python bench/cloud_levels_bench.py --frames {args.frames}`\n\n"
                + table
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
