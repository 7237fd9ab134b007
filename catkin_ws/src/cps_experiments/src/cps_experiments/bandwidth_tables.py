"""Tables 2/3/4 and Figs. 11/12: raw, voxel-filtered and Draco-compressed MB/s per robot.

Clouds: cps_sim's renderer with the paper's sensor profile (640x480 depth cameras at 30 Hz, a
16x1875 lidar at 10 Hz) at poses spread evenly along each robot's route, so min/max are over a
mission. Sizes per stage come from cps_transport.stream_sizes (what pcl_ros's VoxelGrid and our
encoder node send); MB/s = bytes x the nominal rate (10^6 B/s).
"""

import dataclasses
import os
from typing import Dict

import numpy as np

from cps_experiments import paper
from cps_experiments.markdown import fmt, markdown_table, write_csv, write_markdown
from cps_fleet.fleet import load_fleet

LEAF_SIZES_M = (0.01, 0.02, 0.05, 0.10, 0.20, 0.50)
PAPER_LEAF_M = 0.10
STAGES = ("raw", "filtered", "compressed")


@dataclasses.dataclass
class MissionSizes:
    """Bytes per stage of every rendered cloud: sizes[robot][leaf] = [StageSizes per frame]."""

    fleet: object
    frames_per_robot: int
    sizes: Dict[str, Dict[float, list]]
    rates_hz: Dict[str, float]
    fleet_leaf_m: Dict[str, float]
    clouds: Dict[str, list]  # robot -> [cps_sim SampleCloud], kept for the replay experiments

    def mbytes_per_s(self, robot, leaf, stage):
        """MB/s of every frame at the robot's nominal rate."""
        return np.array([getattr(s, f"{stage}_bytes") * self.rates_hz[robot] / 1e6 for s in self.sizes[robot][leaf]])

    def compressed_bytes(self, robot, leaf=None):
        leaf = self.fleet_leaf_m[robot] if leaf is None else leaf
        return np.array([s.compressed_bytes for s in self.sizes[robot][leaf]], dtype=float)


def measure_mission_sizes(frames_per_robot=10, leaf_sizes=LEAF_SIZES_M, log=print) -> MissionSizes:
    """Render `frames_per_robot` paper-profile clouds along each route and size every stage."""
    from cps_sim.sample_clouds import render_mission_clouds
    from cps_transport.stream_sizes import stage_sizes

    fleet = load_fleet(profile="paper")
    rates = {
        r.name: (fleet.profile.lidar.rate_hz if r.has_lidar else fleet.profile.depth_camera.rate_hz)
        for r in fleet.robots
    }
    fleet_leaf = {r.name: r.voxel_leaf_m for r in fleet.robots}
    leaves = sorted(set(leaf_sizes) | set(fleet_leaf.values()) | {PAPER_LEAF_M})
    log(f"[experiments] rendering {frames_per_robot} paper-profile cloud(s) per robot along the routes")
    clouds = render_mission_clouds("paper", frames_per_robot=frames_per_robot)
    sizes = {}
    for robot, samples in clouds.items():
        sizes[robot] = {leaf: [stage_sizes(s.cloud, leaf) for s in samples] for leaf in leaves}
        log(f"[experiments] {robot}: sized {len(samples)} cloud(s) at {len(leaves)} leaf sizes")
    return MissionSizes(fleet, frames_per_robot, sizes, rates, fleet_leaf, clouds)


def _min_max(values):
    return float(np.min(values)), float(np.max(values))


def table4_rows(mission: MissionSizes, leaf_of):
    """Per robot and the total: Hz and (min, max) MB/s per stage at leaf_of(robot)."""
    rows, totals = [], np.zeros((3, 2))
    for robot in mission.sizes:
        leaf = leaf_of(robot)
        cells = [_min_max(mission.mbytes_per_s(robot, leaf, stage)) for stage in STAGES]
        totals += np.array(cells)
        rows.append((robot, leaf, mission.rates_hz[robot], cells))
    return rows, [tuple(t) for t in totals]


def _paper_range(pair):
    return f"{pair[0]:g}–{pair[1]:g}"


def write_table4(mission: MissionSizes, out_dir):
    """table4.csv and table4.md: the fleet's leaf sizes (scout 1 cm) and every robot at 10 cm."""
    headers = (
        ["robot", "leaf_m", "rate_hz"]
        + [f"{stage}_{m}_mbytes_per_s" for stage in STAGES for m in ("min", "max")]
        + [f"paper_{stage}_{m}" for stage in STAGES for m in ("min", "max")]
    )
    csv_rows, sections = [], []
    variants = (
        (
            "fleet.yaml leaf sizes (scout 0.01 m, the others 0.10 m; the paper's text)",
            "fleet",
            lambda r: mission.fleet_leaf_m[r],
        ),
        ("every robot at 0.10 m (the caption of the paper's Table 4)", "0.10", lambda r: PAPER_LEAF_M),
    )
    summary = {}
    for title, key, leaf_of in variants:
        rows, totals = table4_rows(mission, leaf_of)
        md_rows = []
        for robot, leaf, rate, cells in rows:
            p = paper.TABLE4[robot]
            csv_rows.append(
                [robot, leaf, rate] + [round(v, 4) for c in cells for v in c] + [v for stage in p[:3] for v in stage]
            )
            md_rows.append(
                [robot, f"{leaf:g}", f"{rate:g}"]
                + [f"{fmt(c[0], 3)}–{fmt(c[1], 3)} ({_paper_range(ps)})" for c, ps in zip(cells, p[:3])]
            )
        csv_rows.append(
            [f"total ({key})", "", ""]
            + [round(v, 4) for t in totals for v in t]
            + [v for stage in paper.TABLE4_TOTAL for v in stage]
        )
        md_rows.append(
            ["**total**", "", ""]
            + [f"**{fmt(t[0], 3)}–{fmt(t[1], 3)}** ({_paper_range(pt)})" for t, pt in zip(totals, paper.TABLE4_TOTAL)]
        )
        sections += [
            f"## {title}",
            markdown_table(
                [
                    "robot",
                    "leaf m",
                    "Hz",
                    "raw MB/s min–max (paper)",
                    "filtered MB/s (paper)",
                    "compressed MB/s (paper)",
                ],
                md_rows,
            ),
        ]
        summary[key] = totals
    write_csv(os.path.join(out_dir, "table4.csv"), headers, csv_rows)

    fleet_totals, ten_cm = summary["fleet"], summary["0.10"]
    lidar_robot = next(r.name for r in mission.fleet.robots if r.has_lidar)
    lidar = mission.sizes[lidar_robot][PAPER_LEAF_M][0]
    lidar_step = mission.clouds[lidar_robot][0].cloud.point_step
    means = {
        stage: sum(float(np.mean(mission.mbytes_per_s(r, mission.fleet_leaf_m[r], stage))) for r in mission.sizes)
        for stage in STAGES
    }
    text = [
        f"Clouds: cps_sim, paper profile, {mission.frames_per_robot} poses evenly along each robot's route "
        f"(min/max over those). MB/s = bytes per cloud × nominal rate (depth 30 Hz, lidar 10 Hz); filtered = "
        f"voxels × the input's point_step (as pcl_ros's VoxelGrid sends it); compressed = our encoder node "
        f"(x,y,z, error ≤ leaf/2). The paper's numbers are in parentheses.",
        f"Fleet mean, fleet.yaml leaf sizes: raw **{means['raw']:.2f}** → filtered **{means['filtered']:.2f}** → "
        f"compressed **{means['compressed']:.3f} MB/s** (paper, section 5: {paper.FLEET_RAW_MBYTES_PER_S} → "
        f"{paper.FLEET_FILTERED_MBYTES_PER_S} → {paper.FLEET_COMPRESSED_MBYTES_PER_S} MB/s); reduction "
        f"{100 * (1 - means['compressed'] / means['raw']):.2f} % (paper 99.0 %).",
        "### Differences",
        f"- Raw: depth clouds are 640×480 × 32 B = 9.83 MB (x,y,z,rgb with PCL's padding, as "
        f"depth_image_proc publishes) × 30 Hz = 294.9 MB/s, within 2 % of the paper's 280–290; the paper's "
        f"Table 2 counts 28 B/point. Scout's lidar ({lidar.points} points × {lidar_step} B = {lidar.raw_bytes / 1e3:.0f} kB "
        f"at 10 Hz) is above the paper's 2.85–4.50 MB/s: our scan carries x,y,z,intensity,ring,time for every "
        f"ray that hits (Velodyne-like, 16 × 1875).",
        f"- Filtered: our hall is emptier and smaller than the paper's Gazebo world, so a 10 cm grid keeps "
        f"fewer voxels per depth frame; the fleet's filtered total at 10 cm is {ten_cm[1][0]:.2f}–{ten_cm[1][1]:.2f} MB/s "
        f"against the paper's 45.09–50.37 MB/s. With Scout at 1 cm (fleet.yaml) the lidar keeps most of its points, "
        f"which the paper's Scout row (2.1–2.69 MB/s) also shows.",
        f"- Compressed: {fleet_totals[2][0]:.3f}–{fleet_totals[2][1]:.3f} MB/s against 8.01–10.07 MB/s: besides the "
        f"fewer voxels, our encoder quantizes positions to the leaf's half-size (6–8 bits at 10 cm instead of "
        f"point_cloud_transport's 14) and sends x,y,z only; with point_cloud_transport's defaults the same clouds "
        f"are 5–10× larger (docs/benchmarks/transport.md).",
    ]
    write_markdown(
        os.path.join(out_dir, "table4.md"),
        "Tables 2/3/4: raw, filtered and compressed point clouds",
        text[:2] + sections + text[2:],
    )
    return {"fleet": fleet_totals, "0.10": ten_cm, "means": means}


def fleet_curve(mission: MissionSizes, stage):
    """Fleet MB/s (sum over robots of the mean over frames) at every leaf size measured."""
    leaves = sorted(next(iter(mission.sizes.values())))
    return np.array(leaves), np.array(
        [sum(float(np.mean(mission.mbytes_per_s(r, leaf, stage))) for r in mission.sizes) for leaf in leaves]
    )


def write_figs_11_12(mission: MissionSizes, out_dir):
    """fig11.png (voxel size vs filtered MB/s), fig12.png (filtered vs compressed), fig11_12.csv."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    leaves, raw = fleet_curve(mission, "raw")
    _, filtered = fleet_curve(mission, "filtered")
    _, compressed = fleet_curve(mission, "compressed")
    per_robot = {
        r: fleet_curve(dataclasses.replace(mission, sizes={r: mission.sizes[r]}), "filtered")[1] for r in mission.sizes
    }
    write_csv(
        os.path.join(out_dir, "fig11_12.csv"),
        ["leaf_m", "raw_mbytes_per_s", "filtered_mbytes_per_s", "compressed_mbytes_per_s"]
        + [f"filtered_{r}_mbytes_per_s" for r in per_robot],
        [
            [leaf, round(a, 4), round(b, 4), round(c, 5)] + [round(per_robot[r][i], 4) for r in per_robot]
            for i, (leaf, a, b, c) in enumerate(zip(leaves, raw, filtered, compressed))
        ],
    )

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    ax.plot(leaves * 100, filtered, "o-", color="tab:blue", label="filtered, fleet (ours)")
    for robot, values in per_robot.items():
        ax.plot(leaves * 100, values, ".:", alpha=0.7, label=f"filtered, {robot}")
    ax.axhline(raw[0], color="grey", ls="--", label=f"raw, fleet ({raw[0]:.0f} MB/s)")
    ax.plot([10], [paper.FLEET_FILTERED_MBYTES_PER_S], "k*", ms=12, label="paper: 44.55 MB/s at 10 cm")
    ax.axhline(paper.FLEET_RAW_MBYTES_PER_S, color="k", ls=":", lw=0.8, label="paper raw 874.5 MB/s")
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="voxel size (cm)",
        ylabel="MB/s at nominal rates",
        title="Fig. 11: voxel size vs consumed bandwidth (4 robots)",
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "fig11.png"), dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    ax.plot(leaves * 100, filtered, "o-", label="filtered (ours)")
    ax.plot(leaves * 100, compressed, "^-", label="filtered + Draco (ours)")
    ax.plot([10], [paper.FLEET_FILTERED_MBYTES_PER_S], "k*", ms=12, label="paper filtered, 10 cm")
    ax.plot([10], [paper.FLEET_COMPRESSED_MBYTES_PER_S], "kP", ms=10, label="paper compressed, 10 cm (8.71)")
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="voxel size (cm)",
        ylabel="fleet MB/s at nominal rates",
        title="Fig. 12: filtered vs compressed point-cloud streams",
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "fig12.png"), dpi=120)
    plt.close(fig)
    return {"leaves": leaves, "raw": raw, "filtered": filtered, "compressed": compressed}


def run(out_dir, mission: MissionSizes):
    totals = write_table4(mission, out_dir)
    curves = write_figs_11_12(mission, out_dir)
    return {"table4": totals, "fig11_12": curves}
