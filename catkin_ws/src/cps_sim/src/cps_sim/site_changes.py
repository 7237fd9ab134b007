"""Equipment removed from, moved in or added to the hall, for monitoring missions (no rospy).

A changes file (e.g. cps_bringup/config/site_changes.yaml) lists them by equipment name:

    removed: [crate_2]
    moved:   [{name: crate_4, dx_m: 0.0, dy_m: 1.0}]
    added:   [{name: new_box, shape: box, x: 0.0, y: 0.0, size_x_m: 0.6, size_y_m: 0.6, size_z_m: 0.8},
              {name: new_drum, shape: cylinder, x: 1.0, y: 0.0, radius_m: 0.3, height_m: 0.9}]

`load_site_changes` checks it against the site (ConfigError with file:line); `expected_changes`
is the simulator's truth of what a change detector should find.
"""

import dataclasses
from typing import Optional, Sequence, Tuple

import numpy as np

from cps_fleet.config import Reader, load_yaml_document
from cps_fleet.site import Equipment

ADDED_SHAPES = {"box": ("crate", ("size_x_m", "size_y_m", "size_z_m")), "cylinder": ("drum", ("radius_m", "height_m"))}
ADDED_RGB = (0.85, 0.20, 0.60)


@dataclasses.dataclass(frozen=True)
class SiteMove:
    """Shift equipment item `name` by (dx_m, dy_m) in map."""

    name: str
    dx_m: float
    dy_m: float

    @classmethod
    def parse(cls, text):
        """From `name:dx_m:dy_m`; ValueError says what is wrong."""
        parts = text.split(":")
        if len(parts) != 3:
            raise ValueError(f"'{text}' is not name:dx_m:dy_m")
        return cls(parts[0], float(parts[1]), float(parts[2]))


@dataclasses.dataclass(frozen=True)
class SiteChanges:
    """What a monitoring mission finds changed: removed names, moves, new items."""

    removed: Tuple[str, ...] = ()
    moved: Tuple[SiteMove, ...] = ()
    added: Tuple[Equipment, ...] = ()
    path: str = ""

    def apply(self, site):
        site = apply_site_changes(site, self.removed, self.moved)
        return dataclasses.replace(site, equipment=site.equipment + tuple(self.added))

    def describe(self):
        parts = [
            f"removed {', '.join(self.removed)}" if self.removed else "",
            "moved " + ", ".join(f"{m.name} by ({m.dx_m:+.2f}, {m.dy_m:+.2f}) m" for m in self.moved)
            if self.moved
            else "",
            f"added {', '.join(a.name for a in self.added)}" if self.added else "",
        ]
        return "; ".join(p for p in parts if p) or "no changes"


def apply_site_changes(site, without: Sequence[str] = (), moves: Sequence[SiteMove] = ()):
    """The site without the named items and with the moves applied; KeyError names the known items."""
    for name in without:
        site = site.without(name)
    for move in moves:
        site = site.moved(move.name, move.dx_m, move.dy_m)
    return site


def _known(reader, key, site):
    name = reader.get(key, str)
    if name not in (e.name for e in site.equipment):
        raise reader.error(
            key, f"no equipment named '{name}' in {site.path} (known: {', '.join(e.name for e in site.equipment)})"
        )
    return name


def _check_inside(reader, site, item, what):
    x0, y0, x1, y1 = item.footprint
    if not all(site.inside_hall(x, y) for x, y in ((x0, y0), (x1, y1))):
        h = site.hall
        raise reader.error(
            None,
            f"{what} '{item.name}' would leave the hall: footprint x {x0:.2f}..{x1:.2f}, "
            f"y {y0:.2f}..{y1:.2f} (hall x {h.x_min_m}..{h.x_max_m}, y {h.y_min_m}..{h.y_max_m})",
        )


def load_site_changes(path, site) -> SiteChanges:
    """Read a changes file against `site` (cps_fleet.site.Site); ConfigError names file:line."""
    doc = load_yaml_document(path)
    top = Reader(doc)
    unknown = set(doc.data) - {"removed", "moved", "added"}
    if unknown:
        raise top.error(sorted(unknown)[0], "unknown key (known: removed, moved, added)")
    removed = []
    for i, name in enumerate(top.get("removed", list, default=[])):
        if not isinstance(name, str) or name not in (e.name for e in site.equipment):
            raise doc.error(
                ("removed", i),
                f"no equipment named {name!r} in {site.path} (known: {', '.join(e.name for e in site.equipment)})",
            )
        removed.append(name)
    moved = []
    for reader in top.items("moved") if top.has("moved") else []:
        name = _known(reader, "name", site)
        if name in removed:
            raise reader.error("name", f"'{name}' is also listed as removed")
        move = SiteMove(name, reader.number("dx_m", default=0.0), reader.number("dy_m", default=0.0))
        _check_inside(reader, site, site.moved(name, move.dx_m, move.dy_m).item(name), "moved equipment")
        moved.append(move)
    added = []
    for reader in top.items("added") if top.has("added") else []:
        name = reader.get("name", str)
        if name in (e.name for e in site.equipment) or name in (a.name for a in added):
            raise reader.error("name", f"equipment name '{name}' is already used")
        shape = reader.get("shape", str)
        if shape not in ADDED_SHAPES:
            raise reader.error("shape", f"unknown shape '{shape}' (known: {', '.join(ADDED_SHAPES)})")
        kind, keys = ADDED_SHAPES[shape]
        size = tuple((key, reader.number(key, low=0.0, low_open=True)) for key in keys)
        item = Equipment(
            name,
            kind,
            reader.number("x"),
            reader.number("y"),
            reader.number("yaw_deg", default=0.0),
            size,
            ADDED_RGB,
            line=doc.line(reader.key_path),
        )
        _check_inside(reader, site, item, "added equipment")
        added.append(item)
    return SiteChanges(tuple(removed), tuple(moved), tuple(added), path=str(path))


@dataclasses.dataclass(frozen=True)
class ExpectedChange:
    """One change the simulator made: which item, appeared, disappeared or moved, where (its solid's
    axis-aligned box in map; a moved item's where it stands now, with the box it left)."""

    name: str
    kind: str
    centroid_m: Tuple[float, float, float]
    size_m: Tuple[float, float, float]
    displacement_m: Optional[Tuple[float, float, float]] = None  # a move: by how much (m)
    from_centroid_m: Optional[Tuple[float, float, float]] = None  # a move: the box it left
    from_size_m: Optional[Tuple[float, float, float]] = None


def _box(item):
    lows, highs = zip(*(p.aabb() for p in item.primitives()))
    lo, hi = np.min(lows, axis=0), np.max(highs, axis=0)
    return tuple(np.round((lo + hi) / 2, 4).tolist()), tuple(np.round(hi - lo, 4).tolist())


def _expected(item, kind):
    return ExpectedChange(item.name, kind, *_box(item))


def expected_changes(site, changes: SiteChanges):
    """What a detector comparing maps of `site` before and after `changes` should find: a removed
    item disappeared, an added one appeared, a moved one moved (one change: where it went, from
    where, by how much)."""
    after = changes.apply(site)
    out = [_expected(site.item(name), "disappeared") for name in changes.removed]
    for move in changes.moved:
        before = _box(site.item(move.name))
        out.append(
            ExpectedChange(
                move.name,
                "moved",
                *_box(after.item(move.name)),
                displacement_m=(move.dx_m, move.dy_m, 0.0),
                from_centroid_m=before[0],
                from_size_m=before[1],
            )
        )
    out += [_expected(item, "appeared") for item in changes.added]
    return out
