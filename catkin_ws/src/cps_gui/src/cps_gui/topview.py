"""Drawing data of the secondary top view: the projected map as an image, poses in `map`, routes,
fenced areas, and the world-to-screen transform. numpy only; the widget paints what this computes.
"""

import dataclasses
import math
from typing import Optional, Sequence, Tuple

import numpy as np

from cps_fleet.site import load_site

# Colours (RGB) of the map image: free, occupied, unknown.
FREE_RGB = (235, 235, 235)
OCCUPIED_RGB = (20, 20, 20)
UNKNOWN_RGB = (150, 160, 170)
# Site changes against the baseline map: appeared green, disappeared red.
CHANGE_RGB = {"appeared": (46, 160, 67), "disappeared": (211, 47, 47), "moved": (30, 100, 230)}
# Half the side of the square the top view shows around a change the operator selected.
FOCUS_HALF_SIDE_M = 3.0
# Occupancy values (0..100) at or above this are drawn occupied.
OCCUPIED_THRESHOLD = 50


@dataclasses.dataclass(frozen=True)
class OccupancyImage:
    """A decimated, colour-coded occupancy grid. rgb[0] is the row of the largest y (top of the
    screen); the image covers x in [x_min, x_min + width_m] and y in [y_min, y_min + height_m]."""

    rgb: np.ndarray
    x_min: float
    y_min: float
    cell_m: float
    occupied_cells: int

    @property
    def width_m(self):
        return self.rgb.shape[1] * self.cell_m

    @property
    def height_m(self):
        return self.rgb.shape[0] * self.cell_m


def occupancy_image(width, height, resolution_m, origin_x, origin_y, data, max_cells=600):
    """nav_msgs/OccupancyGrid fields (row-major, row 0 at origin_y, -1 unknown) to an image whose
    larger side has at most `max_cells` pixels. Decimation keeps the highest occupancy of each
    block, so thin walls survive. ValueError for a grid whose data does not match its size.

    The grid's origin orientation is assumed to be the identity, as octomap_server publishes it.
    """
    if width <= 0 or height <= 0:
        raise ValueError(f"empty occupancy grid ({width}x{height})")
    if not resolution_m > 0:
        raise ValueError(f"occupancy grid resolution must be positive, got {resolution_m}")
    grid = np.asarray(data, dtype=np.int16)
    if grid.size != width * height:
        raise ValueError(f"occupancy grid has {grid.size} cells, expected {width}x{height}={width * height}")
    grid = grid.reshape(height, width)
    factor = max(1, int(math.ceil(max(width, height) / float(max_cells))))
    if factor > 1:
        pad_h, pad_w = (-height) % factor, (-width) % factor
        grid = np.pad(grid, ((0, pad_h), (0, pad_w)), constant_values=-1)
        grid = grid.reshape(grid.shape[0] // factor, factor, grid.shape[1] // factor, factor).max(axis=(1, 3))
    rgb = np.empty(grid.shape + (3,), dtype=np.uint8)
    rgb[:] = UNKNOWN_RGB
    rgb[(grid >= 0) & (grid < OCCUPIED_THRESHOLD)] = FREE_RGB
    occupied = grid >= OCCUPIED_THRESHOLD
    rgb[occupied] = OCCUPIED_RGB
    return OccupancyImage(
        rgb=np.ascontiguousarray(rgb[::-1]),
        x_min=origin_x,
        y_min=origin_y,
        cell_m=resolution_m * factor,
        occupied_cells=int(occupied.sum()),
    )


@dataclasses.dataclass(frozen=True)
class Pose2D:
    """A planar pose with height: x, y, z in m, yaw in rad."""

    x: float
    y: float
    z: float
    yaw_rad: float


def odom_to_map(odom_x, odom_y, odom_yaw_rad, x, y, yaw_rad):
    """A pose in `<r>/odom` to `map`, given the map -> <r>/odom transform (odom_x, odom_y, odom_yaw_rad)."""
    c, s = math.cos(odom_yaw_rad), math.sin(odom_yaw_rad)
    return odom_x + c * x - s * y, odom_y + s * x + c * y, _wrap(odom_yaw_rad + yaw_rad)


def _wrap(angle):
    return math.atan2(math.sin(angle), math.cos(angle))


def yaw_from_quaternion(x, y, z, w):
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


@dataclasses.dataclass(frozen=True)
class Bounds:
    x_min: float
    y_min: float
    x_max: float
    y_max: float

    def union(self, other: "Bounds"):
        return Bounds(
            min(self.x_min, other.x_min),
            min(self.y_min, other.y_min),
            max(self.x_max, other.x_max),
            max(self.y_max, other.y_max),
        )

    def padded(self, margin_m):
        return Bounds(self.x_min - margin_m, self.y_min - margin_m, self.x_max + margin_m, self.y_max + margin_m)


def bounds_of_points(points: Sequence[Tuple[float, float]]) -> Optional[Bounds]:
    points = [(x, y) for x, y in points if math.isfinite(x) and math.isfinite(y)]
    if not points:
        return None
    xs, ys = zip(*points)
    return Bounds(min(xs), min(ys), max(xs), max(ys))


def scene_bounds(image: Optional[OccupancyImage], point_sets, margin_m=1.0, minimum_m=4.0):
    """The area to show: the map plus every given point (routes, robots, fence corners)."""
    bounds = None
    if image is not None:
        bounds = Bounds(image.x_min, image.y_min, image.x_min + image.width_m, image.y_min + image.height_m)
    for points in point_sets:
        b = bounds_of_points(points)
        if b is not None:
            bounds = b if bounds is None else bounds.union(b)
    if bounds is None:
        bounds = Bounds(-minimum_m / 2, -minimum_m / 2, minimum_m / 2, minimum_m / 2)
    cx, cy = (bounds.x_min + bounds.x_max) / 2, (bounds.y_min + bounds.y_max) / 2
    half_w = max(bounds.x_max - bounds.x_min, minimum_m) / 2
    half_h = max(bounds.y_max - bounds.y_min, minimum_m) / 2
    return Bounds(cx - half_w, cy - half_h, cx + half_w, cy + half_h).padded(margin_m)


def focus_bounds(x, y, half_side_m=FOCUS_HALF_SIDE_M):
    """The square around (x, y) the top view shows when the operator selects a change there."""
    return Bounds(x - half_side_m, y - half_side_m, x + half_side_m, y + half_side_m)


@dataclasses.dataclass(frozen=True)
class WorldToScreen:
    """Uniform scale, y up in the world and down on the screen, scene centred in the widget."""

    scale_px_per_m: float
    offset_x_px: float
    offset_y_px: float

    @classmethod
    def fit(cls, bounds: Bounds, width_px, height_px):
        span_x, span_y = bounds.x_max - bounds.x_min, bounds.y_max - bounds.y_min
        scale = min(width_px / span_x, height_px / span_y)
        offset_x = (width_px - scale * span_x) / 2 - scale * bounds.x_min
        offset_y = (height_px - scale * span_y) / 2 + scale * bounds.y_max
        return cls(scale, offset_x, offset_y)

    def __call__(self, x, y):
        return self.offset_x_px + self.scale_px_per_m * x, self.offset_y_px - self.scale_px_per_m * y


def fence_polygons(site):
    """[(name, [(x, y), ...])] of the fenced areas of a site loaded by cps_fleet.site.load_site.

    cps_fleet.site's FencedArea is an axis-aligned box (`x_min_m`.. fields); other shapes are read too:
    a polygon (`polygon`/`corners`/`points`), `min`/`max` pairs, `x_min`.., or a centre and size. Areas it
    cannot read are skipped and counted in the second return value.
    """
    areas = _field(site, "areas", None) or _field(site, "fenced_areas", None) or []
    polygons, unreadable = [], 0
    for index, area in enumerate(areas):
        name = str(_field(area, "name", f"fence {index + 1}"))
        polygon = _polygon_of(area)
        if polygon is None:
            unreadable += 1
        else:
            polygons.append((name, polygon))
    return polygons, unreadable


def _field(obj, name, default):
    if isinstance(obj, dict):
        return obj.get(name, default)
    return getattr(obj, name, default)


def _polygon_of(area):
    try:
        for key in ("polygon", "corners", "points", "vertices"):
            points = _field(area, key, None)
            if points:
                return [(float(_xy(p)[0]), float(_xy(p)[1])) for p in points]
        lo, hi = _field(area, "min", None), _field(area, "max", None)
        if lo is not None and hi is not None:
            return _box(_xy(lo)[0], _xy(lo)[1], _xy(hi)[0], _xy(hi)[1])
        for suffix in ("_m", ""):  # cps_fleet.site.FencedArea: x_min_m, x_max_m, y_min_m, y_max_m
            if _field(area, "x_min" + suffix, None) is not None:
                return _box(
                    _field(area, "x_min" + suffix, 0),
                    _field(area, "y_min" + suffix, 0),
                    _field(area, "x_max" + suffix, 0),
                    _field(area, "y_max" + suffix, 0),
                )
        centre, size = _field(area, "center", None) or _field(area, "centre", None), _field(area, "size", None)
        if centre is not None and size is not None:
            cx, cy = _xy(centre)
            sx, sy = _xy(size)
            return _box(cx - sx / 2, cy - sy / 2, cx + sx / 2, cy + sy / 2)
    except (TypeError, ValueError, KeyError, IndexError):
        return None
    return None


def _xy(p):
    if isinstance(p, dict):
        return float(p["x"]), float(p["y"])
    if hasattr(p, "x") and hasattr(p, "y"):
        return float(p.x), float(p.y)
    return float(p[0]), float(p[1])


def _box(x0, y0, x1, y1):
    x0, y0, x1, y1 = float(x0), float(y0), float(x1), float(y1)
    return [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]


def load_fences(site_path):
    """Fenced areas of the site file through cps_fleet.site.load_site, or ([], reason) when the
    file cannot be read: the top view then draws no fences."""
    try:
        site = load_site(site_path)
    except Exception as exc:  # a ConfigError or whatever the loader raises
        return [], f"cannot read the site file {site_path}: {exc}"
    polygons, unreadable = fence_polygons(site)
    return polygons, (f"{unreadable} fenced area(s) of {site_path} have no readable outline" if unreadable else "")
