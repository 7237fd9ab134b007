"""The industrial hall (a site file such as cps_sim/config/hall.yaml) as plain dataclasses and primitives.

Pure Python + numpy (no pybullet, no rospy), so the GUI, the mapping scorer and the
change-detection tests can read the site too. `Site.primitives()` expands the hall into boxes
and cylinders in `map`; the simulator, the ground-truth export and the waypoint checks all use
that one expansion, so they cannot disagree.
"""

import dataclasses
import functools
import math
import os
from typing import Optional, Tuple

import numpy as np

from cps_fleet.config import Reader, load_yaml_document

EQUIPMENT_TYPES = ("tank", "vertical_cylinder", "drum", "crate", "shelving", "pipe_run")
_SIZE_KEYS = {
    "tank": ("radius_m", "height_m"),
    "vertical_cylinder": ("radius_m", "height_m"),
    "drum": ("radius_m", "height_m"),
    "crate": ("size_x_m", "size_y_m", "size_z_m"),
    "shelving": ("size_x_m", "size_y_m", "size_z_m", "levels"),
    "pipe_run": ("length_m", "pipe_radius_m", "elevation_m", "count", "spacing_m"),
}


@dataclasses.dataclass(frozen=True)
class Primitive:
    """A box (half_extents) or a cylinder (radius, half_length along `axis`) in `map`.

    The shape is rotated by `yaw_rad` about z; a cylinder's axis is 'z' (vertical) or 'x'
    (horizontal, along the rotated x axis).
    """

    kind: str
    center: Tuple[float, float, float]
    yaw_rad: float
    rgba: Tuple[float, float, float, float]
    owner: str
    half_extents: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float = 0.0
    half_length: float = 0.0
    axis: str = "z"

    def aabb(self):
        """(min xyz, max xyz) of the primitive, as numpy arrays."""
        c, s = abs(math.cos(self.yaw_rad)), abs(math.sin(self.yaw_rad))
        if self.kind == "box":
            hx, hy, hz = self.half_extents
        elif self.axis == "z":
            hx = hy = self.radius
            hz = self.half_length
            c, s = 1.0, 0.0
        else:
            hx, hy, hz = self.half_length, self.radius, self.radius
        ex = np.array([c * hx + s * hy, s * hx + c * hy, hz])
        center = np.asarray(self.center, dtype=float)
        return center - ex, center + ex

    def contains(self, points, margin_m=0.0):
        """Boolean mask of the (N, 3) points inside the primitive grown by `margin_m`."""
        p = np.atleast_2d(np.asarray(points, dtype=float)) - np.asarray(self.center)
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        local = np.stack([c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1], p[:, 2]], axis=1)
        if self.kind == "box":
            return np.all(np.abs(local) <= np.asarray(self.half_extents) + margin_m, axis=1)
        if self.axis == "z":
            radial, along = np.hypot(local[:, 0], local[:, 1]), local[:, 2]
        else:
            radial, along = np.hypot(local[:, 1], local[:, 2]), local[:, 0]
        return (radial <= self.radius + margin_m) & (np.abs(along) <= self.half_length + margin_m)


@dataclasses.dataclass(frozen=True)
class Hall:
    x_min_m: float
    x_max_m: float
    y_min_m: float
    y_max_m: float
    wall_height_m: float
    wall_thickness_m: float
    floor_rgb: Tuple[float, float, float]
    wall_rgb: Tuple[float, float, float]


@dataclasses.dataclass(frozen=True)
class Fence:
    post_spacing_m: float
    post_size_m: float
    rail_size_m: float
    rgb: Tuple[float, float, float]


@dataclasses.dataclass(frozen=True)
class FencedArea:
    name: str
    x_min_m: float
    x_max_m: float
    y_min_m: float
    y_max_m: float
    fence_height_m: float

    @property
    def rectangle(self):
        """(x_min, y_min, x_max, y_max) in `map`, metres."""
        return (self.x_min_m, self.y_min_m, self.x_max_m, self.y_max_m)

    @property
    def center(self):
        return ((self.x_min_m + self.x_max_m) / 2.0, (self.y_min_m + self.y_max_m) / 2.0)

    def contains_xy(self, x, y):
        return self.x_min_m <= x <= self.x_max_m and self.y_min_m <= y <= self.y_max_m


@dataclasses.dataclass(frozen=True)
class Equipment:
    name: str
    type: str
    x: float
    y: float
    yaw_deg: float
    size: Tuple[Tuple[str, float], ...]
    rgb: Tuple[float, float, float]
    line: int = 0

    def dim(self, key):
        return dict(self.size)[key]

    def primitives(self):
        """The boxes and cylinders this item is made of, in `map`."""
        yaw = math.radians(self.yaw_deg)
        rgba = tuple(self.rgb) + (1.0,)
        c, s = math.cos(yaw), math.sin(yaw)

        def at(lx, ly, z):
            return (self.x + c * lx - s * ly, self.y + s * lx + c * ly, z)

        if self.type in ("tank", "vertical_cylinder", "drum"):
            h = self.dim("height_m")
            return [
                Primitive(
                    "cylinder",
                    (self.x, self.y, h / 2.0),
                    yaw,
                    rgba,
                    self.name,
                    radius=self.dim("radius_m"),
                    half_length=h / 2.0,
                    axis="z",
                )
            ]
        if self.type == "crate":
            hx, hy, hz = self.dim("size_x_m") / 2, self.dim("size_y_m") / 2, self.dim("size_z_m") / 2
            return [Primitive("box", (self.x, self.y, hz), yaw, rgba, self.name, half_extents=(hx, hy, hz))]
        if self.type == "shelving":
            sx, sy, sz = self.dim("size_x_m"), self.dim("size_y_m"), self.dim("size_z_m")
            levels = int(self.dim("levels"))
            post = 0.05
            out = []
            for px in (-1, 1):
                for py in (-1, 1):
                    out.append(
                        Primitive(
                            "box",
                            at(px * (sx / 2 - post / 2), py * (sy / 2 - post / 2), sz / 2),
                            yaw,
                            rgba,
                            self.name,
                            half_extents=(post / 2, post / 2, sz / 2),
                        )
                    )
            shelf_rgba = (0.6, 0.6, 0.6, 1.0)
            for k in range(levels):
                z = 0.15 + k * (sz - 0.2) / max(levels - 1, 1)
                out.append(
                    Primitive("box", at(0.0, 0.0, z), yaw, shelf_rgba, self.name, half_extents=(sx / 2, sy / 2, 0.02))
                )
            return out
        if self.type == "pipe_run":
            length, r = self.dim("length_m"), self.dim("pipe_radius_m")
            elev, count, spacing = self.dim("elevation_m"), int(self.dim("count")), self.dim("spacing_m")
            width = (count - 1) * spacing
            out = [
                Primitive(
                    "cylinder",
                    at(0.0, -width / 2 + k * spacing, elev),
                    yaw,
                    rgba,
                    self.name,
                    radius=r,
                    half_length=length / 2,
                    axis="x",
                )
                for k in range(count)
            ]
            support_rgba = (0.45, 0.45, 0.45, 1.0)
            for end in (-1, 1):
                lx = end * (length / 2 - 0.1)
                top = elev - r
                out.append(
                    Primitive(
                        "box", at(lx, 0.0, top / 2), yaw, support_rgba, self.name, half_extents=(0.04, 0.04, top / 2)
                    )
                )
                out.append(
                    Primitive(
                        "box",
                        at(lx, 0.0, top - 0.03),
                        yaw,
                        support_rgba,
                        self.name,
                        half_extents=(0.05, width / 2 + r + 0.05, 0.03),
                    )
                )
            return out
        raise ValueError(f"unknown equipment type {self.type}")

    @functools.cached_property
    def footprint(self):
        """Axis-aligned (x_min, y_min, x_max, y_max) of the item on the floor, metres. Computed once
        per item (the item is frozen): the site change generator asks it ~200 000 times a run."""
        lows, highs = zip(*(p.aabb() for p in self.primitives()))
        low, high = np.min(lows, axis=0), np.max(highs, axis=0)
        return (float(low[0]), float(low[1]), float(high[0]), float(high[1]))

    @property
    def top_z(self):
        return float(max(p.aabb()[1][2] for p in self.primitives()))


@dataclasses.dataclass(frozen=True)
class Site:
    path: str
    seed: int
    hall: Hall
    fence: Fence
    areas: Tuple[FencedArea, ...]
    equipment: Tuple[Equipment, ...]

    def item(self, name):
        for item in self.equipment:
            if item.name == name:
                return item
        raise KeyError(f"no equipment named '{name}' (known: {', '.join(e.name for e in self.equipment)})")

    def without(self, name):
        """The same hall with equipment `name` removed (for change detection)."""
        self.item(name)
        return dataclasses.replace(self, equipment=tuple(e for e in self.equipment if e.name != name))

    def moved(self, name, dx_m, dy_m, dyaw_deg=0.0):
        """The same hall with equipment `name` shifted by (dx_m, dy_m) and turned by dyaw_deg."""
        self.item(name)
        return dataclasses.replace(
            self,
            equipment=tuple(
                dataclasses.replace(e, x=e.x + dx_m, y=e.y + dy_m, yaw_deg=e.yaw_deg + dyaw_deg)
                if e.name == name
                else e
                for e in self.equipment
            ),
        )

    def area(self, name):
        for area in self.areas:
            if area.name == name:
                return area
        raise KeyError(f"no fenced area named '{name}'")

    def structure_primitives(self):
        """Floor (a slab whose top is z = 0), the four walls and the fences."""
        h = self.hall
        floor_rgba = tuple(h.floor_rgb) + (1.0,)
        wall_rgba = tuple(h.wall_rgb) + (1.0,)
        t = h.wall_thickness_m
        cx, cy = (h.x_min_m + h.x_max_m) / 2, (h.y_min_m + h.y_max_m) / 2
        sx, sy = (h.x_max_m - h.x_min_m) / 2, (h.y_max_m - h.y_min_m) / 2
        wz = h.wall_height_m / 2
        out = [Primitive("box", (cx, cy, -0.05), 0.0, floor_rgba, "floor", half_extents=(sx + t, sy + t, 0.05))]
        out.append(
            Primitive("box", (h.x_min_m - t / 2, cy, wz), 0.0, wall_rgba, "wall_west", half_extents=(t / 2, sy + t, wz))
        )
        out.append(
            Primitive("box", (h.x_max_m + t / 2, cy, wz), 0.0, wall_rgba, "wall_east", half_extents=(t / 2, sy + t, wz))
        )
        out.append(
            Primitive("box", (cx, h.y_min_m - t / 2, wz), 0.0, wall_rgba, "wall_south", half_extents=(sx, t / 2, wz))
        )
        out.append(
            Primitive("box", (cx, h.y_max_m + t / 2, wz), 0.0, wall_rgba, "wall_north", half_extents=(sx, t / 2, wz))
        )
        fence_rgba = tuple(self.fence.rgb) + (1.0,)
        post, rail = self.fence.post_size_m / 2, self.fence.rail_size_m / 2
        for area in self.areas:
            owner = f"fence_{area.name}"
            fh = area.fence_height_m
            corners = [
                (area.x_min_m, area.y_min_m),
                (area.x_max_m, area.y_min_m),
                (area.x_max_m, area.y_max_m),
                (area.x_min_m, area.y_max_m),
            ]
            for (x0, y0), (x1, y1) in zip(corners, corners[1:] + corners[:1]):
                length = math.hypot(x1 - x0, y1 - y0)
                yaw = math.atan2(y1 - y0, x1 - x0)
                n_posts = max(int(round(length / self.fence.post_spacing_m)), 1)
                for k in range(n_posts):
                    f = k / n_posts
                    out.append(
                        Primitive(
                            "box",
                            (x0 + f * (x1 - x0), y0 + f * (y1 - y0), fh / 2),
                            yaw,
                            fence_rgba,
                            owner,
                            half_extents=(post, post, fh / 2),
                        )
                    )
                mid = ((x0 + x1) / 2, (y0 + y1) / 2)
                for z in (fh - rail, 0.1, fh / 2):
                    out.append(
                        Primitive(
                            "box", (mid[0], mid[1], z), yaw, fence_rgba, owner, half_extents=(length / 2, rail, rail)
                        )
                    )
        return out

    def primitives(self):
        """Everything solid in the hall: structure, then equipment, with a seeded colour jitter."""
        rng = np.random.default_rng(self.seed)
        out = self.structure_primitives()
        for item in self.equipment:
            jitter = rng.uniform(-0.04, 0.04)
            for prim in item.primitives():
                rgba = tuple(float(np.clip(c + jitter, 0.0, 1.0)) for c in prim.rgba[:3]) + (1.0,)
                out.append(dataclasses.replace(prim, rgba=rgba))
        return out

    def inside_hall(self, x, y, margin_m=0.0):
        h = self.hall
        return (h.x_min_m + margin_m <= x <= h.x_max_m - margin_m) and (
            h.y_min_m + margin_m <= y <= h.y_max_m - margin_m
        )

    def blocking_item(self, x, y, z, margin_m=0.3):
        """Name of the equipment or fence whose volume (grown by margin_m) holds (x, y, z), or None."""
        point = np.array([[x, y, z]])
        for prim in self.structure_primitives():
            if prim.owner.startswith("fence_") and prim.contains(point, margin_m)[0]:
                return prim.owner
        for item in self.equipment:
            for prim in item.primitives():
                if prim.contains(point, margin_m)[0]:
                    return item.name
        return None


def _rgb(reader, key):
    value = reader.get(key, list)
    if len(value) != 3 or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and 0.0 <= v <= 1.0 for v in value
    ):
        raise reader.error(key, f"must be three numbers in [0, 1], got {value!r}")
    return tuple(float(v) for v in value)


def load_site(path):
    """Read and validate a site file (the fleet's `site_path`); errors (ConfigError) name the file,
    the line and the problem."""
    doc = load_yaml_document(path)
    top = Reader(doc).known_keys("seed", "hall", "fence", "fenced_areas", "equipment")
    seed = top.get("seed", int, default=0)
    hr = top.child("hall").known_keys(
        "x_min_m", "x_max_m", "y_min_m", "y_max_m", "wall_height_m", "wall_thickness_m", "floor_colour", "wall_colour"
    )
    hall = Hall(
        x_min_m=hr.number("x_min_m"),
        x_max_m=hr.number("x_max_m"),
        y_min_m=hr.number("y_min_m"),
        y_max_m=hr.number("y_max_m"),
        wall_height_m=hr.number("wall_height_m", low=0.0, low_open=True),
        wall_thickness_m=hr.number("wall_thickness_m", low=0.0, low_open=True),
        floor_rgb=_rgb(hr, "floor_colour"),
        wall_rgb=_rgb(hr, "wall_colour"),
    )
    if hall.x_max_m <= hall.x_min_m or hall.y_max_m <= hall.y_min_m:
        raise hr.error(None, "x_max_m/y_max_m must be greater than x_min_m/y_min_m")
    fr = top.child("fence").known_keys("post_spacing_m", "post_size_m", "rail_size_m", "colour")
    fence = Fence(
        fr.number("post_spacing_m", low=0.0, low_open=True),
        fr.number("post_size_m", low=0.0, low_open=True),
        fr.number("rail_size_m", low=0.0, low_open=True),
        _rgb(fr, "colour"),
    )

    areas = []
    for ar in top.items("fenced_areas"):
        ar.known_keys("name", "x_min_m", "x_max_m", "y_min_m", "y_max_m", "fence_height_m")
        area = FencedArea(
            ar.get("name", str),
            ar.number("x_min_m"),
            ar.number("x_max_m"),
            ar.number("y_min_m"),
            ar.number("y_max_m"),
            ar.number("fence_height_m", low=0.0, low_open=True),
        )
        if area.x_max_m <= area.x_min_m or area.y_max_m <= area.y_min_m:
            raise ar.error(None, f"fenced area '{area.name}' is empty (max must exceed min)")
        if not (
            hall.x_min_m <= area.x_min_m
            and area.x_max_m <= hall.x_max_m
            and hall.y_min_m <= area.y_min_m
            and area.y_max_m <= hall.y_max_m
        ):
            raise ar.error(None, f"fenced area '{area.name}' is not inside the hall")
        if area.name in (a.name for a in areas):
            raise ar.error("name", f"fenced area '{area.name}' is listed twice")
        areas.append(area)

    equipment = []
    for er in top.items("equipment"):
        name = er.get("name", str)
        if name in (e.name for e in equipment):
            raise er.error("name", f"equipment name '{name}' is used twice (names must be unique)")
        kind = er.get("type", str)
        if kind not in EQUIPMENT_TYPES:
            raise er.error("type", f"unknown equipment type '{kind}' (known: {', '.join(EQUIPMENT_TYPES)})")
        er.known_keys("name", "type", "x", "y", "yaw_deg", "colour", *_SIZE_KEYS[kind])
        size = []
        for key in _SIZE_KEYS[kind]:
            if key in ("levels", "count"):
                value = er.get(key, int)
                if value < 1:
                    raise er.error(key, f"must be at least 1, got {value}")
            else:
                value = er.number(key, low=0.0, low_open=True)
            size.append((key, float(value)))
        item = Equipment(
            name,
            kind,
            er.number("x"),
            er.number("y"),
            er.number("yaw_deg", default=0.0),
            tuple(size),
            _rgb(er, "colour"),
            line=doc.line(er.key_path),
        )
        x0, y0, x1, y1 = item.footprint
        if not (hall.x_min_m <= x0 and x1 <= hall.x_max_m and hall.y_min_m <= y0 and y1 <= hall.y_max_m):
            raise er.error(
                None, f"equipment '{name}' is not inside the hall (footprint {x0:.2f},{y0:.2f}..{x1:.2f},{y1:.2f})"
            )
        equipment.append(item)

    return Site(
        path=os.path.abspath(path), seed=seed, hall=hall, fence=fence, areas=tuple(areas), equipment=tuple(equipment)
    )


def check_waypoint(site: Site, x, y, z, robot_type, margin_m=0.3) -> Optional[str]:
    """Why a waypoint is not reachable for a robot of `robot_type` (a RobotType: aerial robots fly over
    equipment) at (x, y, z): outside the hall, inside equipment or a fence; None if it is."""
    if not site.inside_hall(x, y, margin_m):
        h = site.hall
        return (
            f"({x}, {y}) is outside the hall (x in [{h.x_min_m}, {h.x_max_m}], "
            f"y in [{h.y_min_m}, {h.y_max_m}], keeping {margin_m} m from the walls)"
        )
    aerial = robot_type.is_aerial
    probe_z = z if aerial else 0.2
    blocker = site.blocking_item(x, y, probe_z, margin_m)
    if blocker is not None:
        return f"({x}, {y}, {z}) is inside '{blocker}' (or within {margin_m} m of it)"
    if aerial and z > 0.0 and z < 0.3:
        return f"z = {z} m is below the 0.3 m minimum flight altitude"
    return None
