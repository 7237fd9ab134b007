"""Inspection routes generated from the site, and route checks against it (no rospy).

The hall's free floor (inside the walls, outside the fenced areas and the equipment footprints,
each grown by a clearance) is rasterised, thinned to its centre lines (the aisles' skeleton) and
walked once by a depth-first tour. That tour is cut into N arcs of equal length: robot k starts
at the head of arc k (its first waypoint), inspects along it (``inspect: true``) and comes back
to its start by the shortest way along the aisles (``inspect: false``, so the bandwidth manager's
priority, which follows the mission state, is high only on the robot's own share). Everything is
deterministic: the same site and N give the same routes in every process that loads the fleet.
"""

import dataclasses
import heapq
import math
from typing import List, Optional, Tuple

import numpy as np

from cps_fleet.site import Site

# Distance kept from walls, fences and equipment footprints by generated routes (m).
DEFAULT_CLEARANCE_M = 0.6
# Distance every route (written or generated) keeps from them; the waypoint checks' margin.
ROUTE_MARGIN_M = 0.3
# Robots may not start closer to each other than this (m).
MIN_SEPARATION_M = 1.0
# Aerial robots fly their generated routes at this height (m): over the aisles, under the walls' top.
DEFAULT_FLIGHT_ALTITUDE_M = 1.5
# Raster pitch of the free floor (m); the hall is centred on a cell so its aisles' centre lines are cells.
GRID_M = 0.25
# An arc shorter than this is no share of the hall (m).
MIN_ARC_M = 2.0
# Spacing of the points a segment is checked at (m).
_SAMPLE_M = 0.05
# Generated routes follow the aisles' centre lines to within this (m) after simplification.
_SIMPLIFY_M = 0.15


class RouteError(ValueError):
    """The generator cannot give N robots a share each, or a route is not drivable (the caller
    turns it into a ConfigError at its file and line)."""


class _Solids:
    """Primitives (cps_fleet.site.Primitive) as arrays, tested against many points at once."""

    def __init__(self, primitives, owners):
        self.owners = np.array(list(owners) + [""], dtype=object)
        self.center = np.array([p.center for p in primitives], dtype=float).reshape(-1, 3)
        self.yaw = np.array([p.yaw_rad for p in primitives], dtype=float)
        self.kind = np.array([0 if p.kind == "box" else (1 if p.axis == "z" else 2) for p in primitives], dtype=int)
        self.half = np.array([p.half_extents for p in primitives], dtype=float).reshape(-1, 3)
        self.radius = np.array([p.radius for p in primitives], dtype=float)
        self.half_length = np.array([p.half_length for p in primitives], dtype=float)

    def first_owner(self, points, margin_m, footprint):
        """Per point: the owner of the first solid holding it (grown by margin_m), or ''. With
        `footprint`, (N, 2) points are tested at each solid's own height (its shadow on the floor)."""
        points = np.atleast_2d(np.asarray(points, dtype=float))
        if len(self.kind) == 0:
            return np.full(len(points), "", dtype=object)
        rel = points[:, None, :2] - self.center[None, :, :2]
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        lx = c * rel[..., 0] + s * rel[..., 1]
        ly = -s * rel[..., 0] + c * rel[..., 1]
        lz = np.zeros_like(lx) if footprint else points[:, None, 2] - self.center[None, :, 2]
        m = margin_m
        box = (
            (np.abs(lx) <= self.half[:, 0] + m)
            & (np.abs(ly) <= self.half[:, 1] + m)
            & (np.abs(lz) <= self.half[:, 2] + m)
        )
        vertical = (np.hypot(lx, ly) <= self.radius + m) & (np.abs(lz) <= self.half_length + m)
        horizontal = (np.hypot(ly, lz) <= self.radius + m) & (np.abs(lx) <= self.half_length + m)
        hit = np.where(self.kind == 0, box, np.where(self.kind == 1, vertical, horizontal))
        first = np.where(hit.any(axis=1), hit.argmax(axis=1), len(self.kind))
        return self.owners[first]


class Floor:
    """The site's obstacles as seen by a robot: walls, fenced areas (closed to ground robots),
    equipment footprints; and, for robots flying, the fences' and equipment's volumes."""

    def __init__(self, site: Site):
        self.site = site
        self.hall = site.hall
        self.areas = np.array([a.rectangle for a in site.areas], dtype=float).reshape(-1, 4)
        equipment = [(item.name, prim) for item in site.equipment for prim in item.primitives()]
        self.equipment = _Solids([p for _, p in equipment], [n for n, _ in equipment])
        fences = [p for p in site.structure_primitives() if p.owner.startswith("fence_")]
        self.solids = _Solids(fences + [p for _, p in equipment], [p.owner for p in fences] + [n for n, _ in equipment])

    def _walls(self, xy, margin_m):
        h = self.hall
        return (
            (xy[:, 0] < h.x_min_m + margin_m)
            | (xy[:, 0] > h.x_max_m - margin_m)
            | (xy[:, 1] < h.y_min_m + margin_m)
            | (xy[:, 1] > h.y_max_m - margin_m)
        )

    def blocker_2d(self, xy, margin_m):
        """Per (N, 2) point: '' if a ground robot may stand there keeping `margin_m`, else what is in the way."""
        xy = np.atleast_2d(np.asarray(xy, dtype=float))[:, :2]
        out = self.equipment.first_owner(xy, margin_m, footprint=True)
        for area, (x0, y0, x1, y1) in zip(self.site.areas, self.areas):
            inside = (
                (xy[:, 0] >= x0 - margin_m)
                & (xy[:, 0] <= x1 + margin_m)
                & (xy[:, 1] >= y0 - margin_m)
                & (xy[:, 1] <= y1 + margin_m)
            )
            out[inside] = f"fenced area '{area.name}'"
        out[self._walls(xy, margin_m)] = "the hall's walls"
        return out

    def blocker_3d(self, xyz, margin_m):
        """Per (N, 3) point: '' if a flying robot may be there keeping `margin_m`, else what is in the way."""
        xyz = np.atleast_2d(np.asarray(xyz, dtype=float))
        out = self.solids.first_owner(xyz, margin_m, footprint=False)
        out[self._walls(xyz, margin_m)] = "the hall's walls"
        return out

    def segment_blocker(self, a, b, margin_m, aerial=False):
        """('' or what is in the way, the first blocked point) along the segment a -> b ((x, y, z) each)."""
        a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
        n = max(int(math.ceil(np.linalg.norm((b - a)[:2]) / _SAMPLE_M)), 1)
        points = a + np.linspace(0.0, 1.0, n + 1)[:, None] * (b - a)
        blocked = self.blocker_3d(points, margin_m) if aerial else self.blocker_2d(points[:, :2], margin_m)
        bad = np.flatnonzero(blocked != "")
        if len(bad) == 0:
            return "", None
        return blocked[bad[0]], tuple(float(v) for v in points[bad[0]])


def route_problem(floor: Floor, start, waypoints, aerial, margin_m=ROUTE_MARGIN_M):
    """(index of the first bad waypoint, why) for a route driven from `start` (x, y), or None.

    Ground robots: every leg from the start through the waypoints stays `margin_m` clear of walls,
    fenced areas and equipment footprints. Aerial robots: every leg between waypoints (the first is
    reached after a vertical take-off) stays `margin_m` clear of the walls and of the fences' and
    equipment's volumes at its height.
    """
    points = [(start[0], start[1], 0.0)] + [(w.x, w.y, w.z) for w in waypoints]
    for i in range(1, len(points)):
        if aerial and i == 1:
            what, at = floor.segment_blocker(points[1], points[1], margin_m, aerial=True)
        else:
            what, at = floor.segment_blocker(points[i - 1], points[i], margin_m, aerial)
        if what:
            leg = (
                "waypoint" if i == 1 and aerial else ("leg from the start" if i == 1 else f"leg from waypoint {i - 2}")
            )
            return i - 1, (
                f"{leg} to waypoint {i - 1} ({points[i][0]:g}, {points[i][1]:g}) passes within "
                f"{margin_m:g} m of {what} at ({at[0]:.2f}, {at[1]:.2f})"
            )
    return None


@dataclasses.dataclass(frozen=True)
class GeneratedWaypoint:
    x: float
    y: float
    inspect: bool


@dataclasses.dataclass(frozen=True)
class GeneratedRoute:
    """A robot's share: where it starts (x, y, yaw) and its closed route back to there."""

    start: Tuple[float, float]
    yaw_deg: float
    waypoints: Tuple[GeneratedWaypoint, ...]
    share_m: float


class AisleMap:
    """The free floor rasterised (cells keeping `clearance_m`), its centre lines and their tour."""

    def __init__(self, site: Site, clearance_m=DEFAULT_CLEARANCE_M, grid_m=GRID_M):
        self.floor = Floor(site)
        self.clearance_m = clearance_m
        self.grid_m = grid_m
        h = site.hall
        cx, cy = (h.x_min_m + h.x_max_m) / 2.0, (h.y_min_m + h.y_max_m) / 2.0
        kx, ky = int((h.x_max_m - cx) / grid_m), int((h.y_max_m - cy) / grid_m)
        self.xs = cx + grid_m * np.arange(-kx, kx + 1)
        self.ys = cy + grid_m * np.arange(-ky, ky + 1)
        gx, gy = np.meshgrid(self.xs, self.ys)
        self.free = (self.floor.blocker_2d(np.column_stack([gx.ravel(), gy.ravel()]), clearance_m) == "").reshape(
            gx.shape
        )
        skeleton = _largest_component(_thin(self.free))
        self.nodes = [tuple(rc) for rc in np.argwhere(skeleton)]
        self.skeleton = skeleton
        self.tour = self._tour()

    def xy(self, cell):
        return (float(self.xs[cell[1]]), float(self.ys[cell[0]]))

    def neighbours(self, cell):
        r, c = cell
        for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0), (1, 1), (1, -1), (-1, -1), (-1, 1)):
            rr, cc = r + dr, c + dc
            if 0 <= rr < self.skeleton.shape[0] and 0 <= cc < self.skeleton.shape[1] and self.skeleton[rr, cc]:
                yield (rr, cc), self.grid_m * math.hypot(dr, dc)

    def _tour(self):
        """A closed depth-first walk over the centre lines from their south-west-most cell."""
        if not self.nodes:
            return []
        root = min(self.nodes)
        seen, tour = {root}, [root]
        stack = [(root, self.neighbours(root))]
        while stack:
            cell, it = stack[-1]
            for nxt, _ in it:
                if nxt not in seen:
                    seen.add(nxt)
                    tour.append(nxt)
                    stack.append((nxt, self.neighbours(nxt)))
                    break
            else:
                stack.pop()
                if stack:
                    tour.append(stack[-1][0])
        return tour

    def shortest_path(self, a, b):
        """Cells from a to b along the centre lines (Dijkstra)."""
        dist, prev, heap = {a: 0.0}, {}, [(0.0, a)]
        while heap:
            d, cell = heapq.heappop(heap)
            if cell == b:
                break
            if d > dist[cell]:
                continue
            for nxt, step in self.neighbours(cell):
                if d + step < dist.get(nxt, math.inf):
                    dist[nxt], prev[nxt] = d + step, cell
                    heapq.heappush(heap, (d + step, nxt))
        path = [b]
        while path[-1] != a:
            path.append(prev[path[-1]])
        return path[::-1]

    def coverage(self, routes, radius_m):
        """Fraction of the free cells within `radius_m` of some route's legs (start included)."""
        cells = np.column_stack(
            [np.meshgrid(self.xs, self.ys)[0][self.free], np.meshgrid(self.xs, self.ys)[1][self.free]]
        )
        near = np.zeros(len(cells), dtype=bool)
        for route in routes:
            pts = [route.start] + [(w.x, w.y) for w in route.waypoints]
            for (ax, ay), (bx, by) in zip(pts, pts[1:]):
                d = np.array([bx - ax, by - ay])
                length2 = float(d @ d)
                rel = cells - (ax, ay)
                f = np.clip(rel @ d / length2, 0.0, 1.0) if length2 > 0 else np.zeros(len(cells))
                near |= np.hypot(*(rel - f[:, None] * d).T) <= radius_m
        return float(near.mean()) if len(cells) else 0.0


def generate_routes(
    site: Site,
    count,
    clearance_m=DEFAULT_CLEARANCE_M,
    min_separation_m=MIN_SEPARATION_M,
    aisles: Optional[AisleMap] = None,
) -> List[GeneratedRoute]:
    """`count` closed routes sharing the hall's aisles; RouteError if they do not fit."""
    aisles = aisles or AisleMap(site, clearance_m)
    tour = aisles.tour
    if count < 1:
        raise RouteError(f"count must be at least 1, got {count}")
    if len(tour) < 2:
        raise RouteError(f"the hall has no free aisle {clearance_m:g} m clear of walls, fences and equipment")
    xy = np.array([aisles.xy(c) for c in tour])
    cumulative = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    total = cumulative[-1]
    if total / count < MIN_ARC_M:
        raise RouteError(
            f"{count} robots do not fit: the aisles' tour is {total:.0f} m, "
            f"{total / count:.1f} m each is below the {MIN_ARC_M:g} m minimum share"
        )
    starts = []
    for k in range(count):
        i = int(np.searchsorted(cumulative, k * total / count))
        limit = int(np.searchsorted(cumulative, (k + 1) * total / count - MIN_ARC_M))
        while i <= limit and any(math.dist(xy[i], xy[j]) < min_separation_m for j in starts):
            i += 1
        if i > limit:
            raise RouteError(
                f"{count} robots do not fit: no start for robot {k + 1} at least "
                f"{min_separation_m:g} m from the others along its share of the aisles"
            )
        starts.append(i)
    routes = []
    for k, i in enumerate(starts):
        end = starts[k + 1] if k + 1 < count else len(tour) - 1
        arc = tour[i : end + 1]
        back = aisles.shortest_path(arc[-1], arc[0])
        out = _simplify(aisles, [aisles.xy(c) for c in arc])
        home = _simplify(aisles, [aisles.xy(c) for c in back])
        if len(out) < 2:
            raise RouteError(f"robot {k + 1}'s share of the aisles is empty")
        # The start is the first waypoint: the robot is on its share (inspecting) from the outset.
        waypoints = [GeneratedWaypoint(x, y, True) for x, y in out]
        waypoints += [GeneratedWaypoint(x, y, False) for x, y in home[1:]]
        start = out[0]
        yaw = math.degrees(math.atan2(out[1][1] - start[1], out[1][0] - start[0]))
        routes.append(
            GeneratedRoute(
                start=start,
                yaw_deg=round(yaw, 1),
                waypoints=tuple(waypoints),
                share_m=float(cumulative[end] - cumulative[i]),
            )
        )
    return routes


def _simplify(aisles, points):
    """Fewer points within _SIMPLIFY_M of the polyline, every new leg still clear (Douglas-Peucker)."""
    points = [p for i, p in enumerate(points) if i == 0 or p != points[i - 1]]
    if len(points) <= 2:
        return points
    keep = {0, len(points) - 1}
    stack = [(0, len(points) - 1)]
    arr = np.asarray(points)
    margin = aisles.clearance_m - aisles.grid_m / 2.0
    while stack:
        a, b = stack.pop()
        if b - a < 2:
            continue
        seg = arr[b] - arr[a]
        rel = arr[a + 1 : b] - arr[a]
        length = np.hypot(*seg)
        if length > 0:
            deviation = np.abs(seg[0] * rel[:, 1] - seg[1] * rel[:, 0]) / length
        else:
            deviation = np.hypot(rel[:, 0], rel[:, 1])
        worst = int(np.argmax(deviation))
        clear = length > 0 and not aisles.floor.segment_blocker((*arr[a], 0.0), (*arr[b], 0.0), margin)[0]
        if deviation[worst] > _SIMPLIFY_M or not clear:
            mid = a + 1 + worst
            keep.add(mid)
            stack += [(a, mid), (mid, b)]
    return [points[i] for i in sorted(keep)]


def _thin(mask):
    """Zhang-Suen thinning of a boolean raster to 8-connected one-cell-wide centre lines."""
    img = np.pad(mask.astype(np.uint8), 1)
    changed = True
    while changed:
        changed = False
        for step in (0, 1):
            p = img
            c = p[1:-1, 1:-1]
            n = [p[:-2, 1:-1], p[:-2, 2:], p[1:-1, 2:], p[2:, 2:], p[2:, 1:-1], p[2:, :-2], p[1:-1, :-2], p[:-2, :-2]]
            count = sum(v.astype(int) for v in n)
            transitions = sum(((n[i] == 0) & (n[(i + 1) % 8] == 1)).astype(int) for i in range(8))
            if step == 0:
                side = (n[0] * n[2] * n[4] == 0) & (n[2] * n[4] * n[6] == 0)
            else:
                side = (n[0] * n[2] * n[6] == 0) & (n[0] * n[4] * n[6] == 0)
            remove = (c == 1) & (count >= 2) & (count <= 6) & (transitions == 1) & side
            if remove.any():
                c[remove] = 0
                changed = True
    return img[1:-1, 1:-1].astype(bool)


def _largest_component(mask):
    """The largest 8-connected part of `mask` (ties: the one with the smallest cell)."""
    seen = np.zeros_like(mask, dtype=bool)
    best = []
    for start in map(tuple, np.argwhere(mask)):
        if seen[start]:
            continue
        part, stack = [], [start]
        seen[start] = True
        while stack:
            r, c = stack.pop()
            part.append((r, c))
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    rr, cc = r + dr, c + dc
                    if 0 <= rr < mask.shape[0] and 0 <= cc < mask.shape[1] and mask[rr, cc] and not seen[rr, cc]:
                        seen[rr, cc] = True
                        stack.append((rr, cc))
        if len(part) > len(best):
            best = part
    out = np.zeros_like(mask, dtype=bool)
    for cell in best:
        out[cell] = True
    return out
