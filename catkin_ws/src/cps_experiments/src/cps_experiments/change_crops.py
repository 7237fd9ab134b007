"""What an inspector attaches to a work order: for one detected change, a small picture of the
place in the baseline beside the same place now, top-down and from the side, the change's box
outlined (no rospy; matplotlib Agg).

Each panel shows the occupied voxels of one map within the change's box grown by `CROP_MARGIN_M`:
top-down as the columns' highest voxel (colour = height), side as the voxels within the change's
own y extent (grown by `SLAB_M`) seen along y (colour = depth). The outline is the change's box: green appeared, red disappeared.
"""

import numpy as np

CROP_MARGIN_M = 0.8
SLAB_M = 0.1  # the side view shows the voxels within the change's y extent grown by this
APPEARED_COLOUR, DISAPPEARED_COLOUR = "tab:green", "tab:red"


def _inside(centers, lo, hi):
    return centers[np.all((centers >= lo) & (centers <= hi), axis=1)]


def draw_change_crop(path, change, baseline_centers_m, current_centers_m, resolution_m, title=""):
    """Write a 2 x 2 PNG (rows: top-down, side; columns: baseline, now) of `change` to `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    lo = np.asarray(change.min_m) - CROP_MARGIN_M
    hi = np.asarray(change.max_m) + CROP_MARGIN_M
    lo[2] = max(lo[2], -resolution_m)
    colour = APPEARED_COLOUR if change.kind == "appeared" else DISAPPEARED_COLOUR
    fig, axes = plt.subplots(2, 2, figsize=(5.6, 5.0))
    for col, (label, centers) in enumerate((("baseline", baseline_centers_m), ("now", current_centers_m))):
        pts = _inside(np.asarray(centers, dtype=float).reshape(-1, 3), lo, hi)
        for row, (ax_i, ax_j, ax_c, names) in enumerate(((0, 1, 2, ("x m", "y m")), (0, 2, 1, ("x m", "z m")))):
            ax = axes[row, col]
            if row == 1:  # the side view: only the slab of the change's own y extent
                pts = pts[(pts[:, 1] >= change.min_m[1] - SLAB_M) & (pts[:, 1] <= change.max_m[1] + SLAB_M)]
            if len(pts):
                order = np.argsort(pts[:, ax_c]) if row == 0 else np.argsort(-pts[:, ax_c])
                ax.scatter(
                    pts[order, ax_i], pts[order, ax_j], c=pts[order, ax_c], s=6, marker="s", cmap="viridis",
                    vmin=lo[ax_c], vmax=hi[ax_c], linewidths=0,
                )  # fmt: skip
            ax.add_patch(
                Rectangle(
                    (change.min_m[ax_i], change.min_m[ax_j]),
                    change.max_m[ax_i] - change.min_m[ax_i],
                    change.max_m[ax_j] - change.min_m[ax_j],
                    fill=False,
                    ec=colour,
                    lw=1.8,
                )  # fmt: skip
            )
            ax.set_xlim(lo[ax_i], hi[ax_i])
            ax.set_ylim(lo[ax_j], hi[ax_j])
            ax.set_aspect("equal")
            ax.tick_params(labelsize=6)
            ax.set_xlabel(names[0], fontsize=7)
            ax.set_ylabel(names[1], fontsize=7)
            ax.set_title(f"{label}, {'top-down' if row == 0 else 'side (from -y)'}", fontsize=8)
    fig.suptitle(title or f"{change.kind}, {change.voxels} voxels", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
