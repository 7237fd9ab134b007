"""Fig. 14: the top-down view of the fused map with every robot's trajectory and route.

Used by the demo's report and by `make experiments`. Occupied voxels are drawn as a height map
(the highest occupied voxel per column) over the observed floor in grey, fenced areas as outlines,
routes dashed.
"""

import numpy as np

# The paper's colours (Fig. 14): legged yellow, scout green, Jackal red, UAV purple.
# Voxels below this height are the floor: drawn grey, not as obstacles.
FLOOR_TOP_M = 0.15
ROBOT_COLOURS = {
    "wheeled_lidar": "tab:green",
    "wheeled_depth": "tab:red",
    "legged_depth": "gold",
    "aerial_depth": "tab:purple",
}
# A type only a user's fleet file defines gets these, in the fleet's order.
OTHER_COLOURS = ("tab:blue", "tab:orange", "tab:brown", "tab:pink", "tab:olive", "tab:cyan")


def robot_colours(fleet):
    """{robot: colour}: the paper's colour of its type, or one of OTHER_COLOURS for a user's type."""
    others = iter(OTHER_COLOURS * (1 + len(fleet.robots) // len(OTHER_COLOURS)))
    return {r.name: ROBOT_COLOURS.get(r.type) or next(others) for r in fleet.robots}


def height_image(occupied_centers_m, resolution_m, x_range, y_range):
    """2D array of the highest occupied z per (x, y) column (NaN where nothing is occupied)."""
    nx = int(np.ceil((x_range[1] - x_range[0]) / resolution_m))
    ny = int(np.ceil((y_range[1] - y_range[0]) / resolution_m))
    image = np.full((ny, nx), np.nan)
    if len(occupied_centers_m):
        pts = np.asarray(occupied_centers_m)
        ix = np.floor((pts[:, 0] - x_range[0]) / resolution_m).astype(int)
        iy = np.floor((pts[:, 1] - y_range[0]) / resolution_m).astype(int)
        inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        order = np.argsort(pts[inside, 2])
        image[iy[inside][order], ix[inside][order]] = pts[inside, 2][order]
    return image


def plot_topdown(occupied_centers_m, trajectories, fleet, png_path, title=None, overlay=None):
    """Write the top-down PNG. `trajectories`: robot → list of (x, y, z) in map; `overlay(ax)` draws
    more on the axes (e.g. the monitoring report's changes)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from cps_fleet.site import load_site

    site = load_site(fleet.site_path)
    hall = site.hall
    margin = 0.5
    x_range = (hall.x_min_m - margin, hall.x_max_m + margin)
    y_range = (hall.y_min_m - margin, hall.y_max_m + margin)
    res = fleet.mapping.resolution_m
    centers = np.asarray(occupied_centers_m).reshape(-1, 3)
    on_floor = centers[:, 2] < FLOOR_TOP_M
    floor = np.isfinite(height_image(centers[on_floor], res, x_range, y_range))
    image = height_image(centers[~on_floor], res, x_range, y_range)
    fig, ax = plt.subplots(figsize=(11, 8.5))
    ax.imshow(np.where(floor, 0.85, np.nan), origin="lower", extent=(*x_range, *y_range), cmap="gray", vmin=0, vmax=1)
    shown = ax.imshow(
        image,
        origin="lower",
        extent=(*x_range, *y_range),
        cmap="viridis",
        vmin=0.0,
        vmax=max(2.0, float(np.nanmax(image)) if np.isfinite(image).any() else 2.0),
    )
    fig.colorbar(shown, ax=ax, fraction=0.03, label="highest occupied voxel, m")
    for area in site.areas:
        x0, y0, x1, y1 = area.rectangle
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="0.4", ls=":", lw=1.2))
        ax.text(x0 + 0.1, y1 - 0.35, area.name, fontsize=8, color="0.3")
    colours = robot_colours(fleet)
    for robot in fleet.robots:
        colour = colours[robot.name]
        route = fleet.route(robot.name)
        ax.plot([w.x for w in route.waypoints], [w.y for w in route.waypoints], ls="--", color=colour, lw=1, alpha=0.7)
        path = np.asarray(trajectories.get(robot.name) or np.empty((0, 3)))
        if len(path):
            ax.plot(path[:, 0], path[:, 1], color=colour, lw=2.2, label=f"{robot.name} ({robot.type})")
            ax.plot(path[0, 0], path[0, 1], "o", color=colour, ms=6)
            ax.plot(path[-1, 0], path[-1, 1], "s", color=colour, ms=6)
        else:
            ax.plot([], [], color=colour, lw=2.2, label=f"{robot.name} (no trajectory)")
    if overlay is not None:
        overlay(ax)
    ax.set_xlim(*x_range)
    ax.set_ylim(*y_range)
    ax.set_aspect("equal")
    ax.set_xlabel("x, m (map)")
    ax.set_ylabel("y, m (map)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title or f"Fused OctoMap, top-down ({res} m voxels), trajectories solid, routes dashed")
    fig.tight_layout()
    fig.savefig(png_path, dpi=110)
    plt.close(fig)
    return png_path
