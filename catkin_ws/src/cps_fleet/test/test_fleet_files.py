"""Fleet files with a base and generated robots, and the routes generated per share of the hall:
the routes stay in the aisles, cover them, are the same every time; bad fleets fail at file:line."""

import math
import os

import numpy as np
import pytest

from cps_fleet.config import ConfigError
from cps_fleet.fleet import check_fleet_routes, default_fleet_path, load_fleet, robot_names_arg
from cps_fleet.routes import MIN_SEPARATION_M, AisleMap, generate_routes
from cps_fleet.site import load_site

CONFIG = os.path.dirname(default_fleet_path())
FLEETS = os.path.join(CONFIG, "fleets")
SIZES = (1, 2, 4, 8, 16)


@pytest.fixture(scope="module")
def site():
    return load_site(load_fleet().site_path)


@pytest.fixture(scope="module")
def aisles(site):
    return AisleMap(site)


def _clearance_problems(site, points, clearance_m):
    """Points (x, y) closer than clearance_m to a wall, a fenced area or equipment, by the site's own
    shapes (Site.inside_hall, the areas' rectangles, Primitive.contains at a ground robot's heights)."""
    points = np.asarray(points, dtype=float)
    bad = [(x, y, "wall") for x, y in points if not site.inside_hall(x, y, clearance_m)]
    for area in site.areas:
        bad += [
            (x, y, area.name)
            for x, y in points
            if area.x_min_m - clearance_m <= x <= area.x_max_m + clearance_m
            and area.y_min_m - clearance_m <= y <= area.y_max_m + clearance_m
        ]
    for z in (0.2, 0.7, 1.2):
        xyz = np.column_stack([points, np.full(len(points), z)])
        for prim in site.primitives():
            if prim.owner != "floor" and not prim.owner.startswith("wall_"):
                bad += [(x, y, prim.owner) for x, y, _ in xyz[prim.contains(xyz, clearance_m)]]
    return bad


def _legs(route, step_m=0.1):
    pts = [route.start] + [(w.x, w.y) for w in route.waypoints]
    for (ax, ay), (bx, by) in zip(pts, pts[1:]):
        n = max(int(math.hypot(bx - ax, by - ay) / step_m), 1)
        for f in np.linspace(0.0, 1.0, n + 1):
            yield (ax + f * (bx - ax), ay + f * (by - ay))


@pytest.mark.parametrize("count", SIZES)
def test_generated_routes_stay_in_the_aisles_are_closed_and_start_apart(site, aisles, count):
    routes = generate_routes(site, count, aisles=aisles)
    assert len(routes) == count
    for route in routes:
        # 0.5 m: the 0.6 m clearance less the raster's half cell that a simplified leg may cut.
        assert _clearance_problems(site, list(_legs(route)), 0.5) == []
        last = route.waypoints[-1]
        assert (last.x, last.y) == route.start, "a route ends where its robot starts"
        assert route.waypoints[0].inspect and any(not w.inspect for w in route.waypoints[1:]) or len(routes) == 1
    starts = [r.start for r in routes]
    assert (
        min((math.dist(a, b) for i, a in enumerate(starts) for b in starts[:i]), default=math.inf) >= MIN_SEPARATION_M
    )


@pytest.mark.parametrize("count", SIZES)
def test_generated_shares_cover_the_free_aisles_in_equal_parts(site, aisles, count):
    routes = generate_routes(site, count, aisles=aisles)
    # A depth camera sees 6 m; every free cell within 1.5 m of a route is seen from close by.
    assert aisles.coverage(routes, radius_m=1.5) >= 0.95
    shares = [r.share_m for r in routes]
    assert max(shares) <= 1.3 * min(shares)


def test_generation_is_deterministic(site):
    assert generate_routes(site, 16) == generate_routes(load_site(site.path), 16)
    a, b = load_fleet(os.path.join(FLEETS, "fleet16.yaml")), load_fleet(os.path.join(FLEETS, "fleet16.yaml"))
    assert [(r.initial_pose, a.route(r.name).waypoints) for r in a.robots] == [
        (r.initial_pose, b.route(r.name).waypoints) for r in b.robots
    ]


def test_shipped_fleet_files_load_with_their_robots_and_the_base_fleet_settings():
    base = load_fleet()
    check_fleet_routes(base)  # the four-robot fleet passes the checks derived fleets get at load
    for count in SIZES:
        fleet = load_fleet(os.path.join(FLEETS, f"fleet{count}.yaml"))
        assert len(fleet.robots) == count
        assert (fleet.link, fleet.mapping, fleet.limits, fleet.site_path, fleet.profile) == (
            base.link,
            base.mapping,
            base.limits,
            base.site_path,
            base.profile,
        )
        assert fleet.path == os.path.join(FLEETS, f"fleet{count}.yaml")
    fleet = load_fleet(os.path.join(FLEETS, "fleet16.yaml"), profile="paper")
    assert fleet.profile.name == "paper"
    types = [r.type for r in fleet.robots]
    assert all(types.count(t) == 4 for t in base.robot_types)
    assert fleet.robot_names[:4] == ["scout_1", "jackal_1", "champ_1", "iris_1"] and fleet.robot_names[-1] == "iris_4"
    for robot in fleet.robots:
        template = base.robot(
            {"wheeled_lidar": "scout", "wheeled_depth": "jackal", "legged_depth": "champ", "aerial_depth": "iris"}[
                robot.type
            ]
        )
        assert robot.voxel_leaf_m == template.voxel_leaf_m
        assert robot.sensor_frame == f"{robot.name}/{template.robot_type.sensor_frame}"
        route = fleet.route(robot.name)
        assert {w.z for w in route.waypoints} == ({1.5} if robot.robot_type.is_aerial else {0.0})
        assert any(w.inspect for w in route.waypoints), "the bandwidth manager's priority follows inspection"
    assert robot_names_arg(fleet, ["scout_2", "iris_4"]).robot_names == ["scout_2", "iris_4"]


def _derived(tmp_path, text, routes=None):
    """A fleet file in tmp_path with base: the shipped fleet.yaml; `routes` {file name: text}."""
    for name, body in (routes or {}).items():
        (tmp_path / name).write_text(body)
    path = tmp_path / "fleet.yaml"
    path.write_text(f"base: {default_fleet_path()}\n" + text)
    return path


def _expect(path, line, message, where=None):
    """load_fleet(path) fails at `where` (default: path), `line`, saying `message`."""
    with pytest.raises(ConfigError) as info:
        load_fleet(str(path))
    assert f"{where or path}:{line}:" in str(info.value) and message in str(info.value), str(info.value)


ROUTE_OK = "waypoints:\n  - {x: -8.5, y: -3.0, inspect: true}\n  - {x: -8.5, y: -4.0}\n"
SCOUT = "  - {{name: {name}, type: wheeled_lidar, route: ok.yaml,\n     initial_pose: {{x: {x}, y: {y}}}}}\n"


def test_explicit_robots_take_the_type_voxel_leaf_and_can_mix_with_generated_ones(tmp_path):
    path = _derived(
        tmp_path,
        "robots:\n" + SCOUT.format(name="a", x=-8.5, y=-5.0) + "generate: {count: 4, types: [wheeled_depth]}\n",
        {"ok.yaml": ROUTE_OK},
    )
    fleet = load_fleet(str(path))
    assert fleet.robot_names == ["a", "jackal_1", "jackal_2", "jackal_3", "jackal_4"]
    assert fleet.robot("a").voxel_leaf_m == load_fleet().robot("scout").voxel_leaf_m
    assert fleet.route("a").path == str(tmp_path / "ok.yaml")


def test_duplicate_robot_names_fail_at_the_second(tmp_path):
    path = _derived(
        tmp_path,
        "robots:\n" + SCOUT.format(name="a", x=-8.5, y=-5.0) + SCOUT.format(name="a", x=-8.5, y=-2.0),
        {"ok.yaml": ROUTE_OK},
    )
    _expect(path, 5, "robot 'a' is listed twice")


def test_generated_name_taken_by_a_listed_robot_fails_at_generate(tmp_path):
    path = _derived(
        tmp_path,
        "robots:\n" + SCOUT.format(name="scout_1", x=-8.5, y=-5.0) + "generate:\n  count: 2\n",
        {"ok.yaml": ROUTE_OK},
    )
    _expect(path, 6, "generated robot 'scout_1' is also listed")


def test_more_robots_than_the_hall_has_room_for_fail_at_count(tmp_path):
    path = _derived(tmp_path, "generate:\n  types: [wheeled_depth]\n  count: 100\n")
    _expect(path, 4, "100 robots do not fit")


def test_starts_too_close_fail_at_the_second_robot(tmp_path):
    path = _derived(
        tmp_path,
        "robots:\n" + SCOUT.format(name="a", x=-8.5, y=-5.0) + SCOUT.format(name="b", x=-8.5, y=-4.5),
        {"ok.yaml": ROUTE_OK},
    )
    _expect(path, 6, "robot 'b' starts 0.50 m from 'a'")


def test_start_inside_equipment_or_a_fenced_area_fails_at_its_pose(tmp_path, site):
    tank = site.item("tank_1")
    path = _derived(tmp_path, "robots:\n" + SCOUT.format(name="a", x=tank.x, y=tank.y), {"ok.yaml": ROUTE_OK})
    _expect(path, 4, "inside 'tank_1'")
    path = _derived(tmp_path, "robots:\n" + SCOUT.format(name="a", x=12.0, y=0.0), {"ok.yaml": ROUTE_OK})
    _expect(path, 4, "outside the hall")


def test_route_through_a_fenced_area_or_out_of_the_hall_fails_at_its_waypoint(tmp_path):
    crossing = "waypoints:\n  - {x: -8.5, y: -3.0}\n  - {x: -1.0, y: -3.0, inspect: true}\n"
    path = _derived(tmp_path, "robots:\n" + SCOUT.format(name="a", x=-8.5, y=-5.0), {"ok.yaml": crossing})
    _expect(
        path,
        3,
        "robot 'a' route: leg from waypoint 0 to waypoint 1 (-1, -3) passes within 0.3 m of fenced area 'tank_farm'",
        where=tmp_path / "ok.yaml",
    )
    leaving = "waypoints:\n  - {x: -8.5, y: -3.0}\n  - {x: -8.5, y: 9.0}\n"
    path = _derived(tmp_path, "robots:\n" + SCOUT.format(name="a", x=-8.5, y=-5.0), {"ok.yaml": leaving})
    _expect(path, 3, "the hall's walls", where=tmp_path / "ok.yaml")


@pytest.mark.parametrize(
    "text,line,message",
    [
        ("generate:\n  count: 4\n  types: [wheeled_lidar, tank]\n", 4, "generate.types[1]: unknown robot type 'tank'"),
        ("generate:\n  count: 4\n  routes: random\n", 4, "unknown route scheme 'random'"),
        ("generate:\n  count: 0\n", 3, "must be a positive integer"),
        ("generate:\n  cuont: 4\n", 3, "unknown key 'cuont' (did you mean 'count'?)"),
        ("generate:\n  count: 4\n  clearance_m: 4.0\n", 3, "no free aisle 4 m clear"),
        ("profile: fast\ngenerate: {count: 1}\n", 2, "unknown profile 'fast'"),
        ("robots: []\n", 1, "the fleet has no robots"),
    ],
)
def test_bad_generate_block_names_file_line_and_problem(tmp_path, text, line, message):
    _expect(_derived(tmp_path, text), line, message)


def test_a_base_must_be_a_complete_fleet_file(tmp_path):
    inner = _derived(tmp_path, "generate: {count: 1}\n")
    outer = tmp_path / "outer.yaml"
    outer.write_text(f"base: {inner}\ngenerate: {{count: 1}}\n")
    _expect(outer, 1, "has a base itself")
