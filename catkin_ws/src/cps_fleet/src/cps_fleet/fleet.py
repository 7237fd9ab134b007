"""The fleet configuration (fleet.yaml) and route files, validated.

Every node that needs a fleet-wide number reads it through `load_fleet`, so the numbers live in
one file. Errors name the file, the line and what is wrong (`cps_fleet.config.ConfigError`).
"""

import dataclasses
import math
import os
import re
from typing import Dict, List, Optional, Tuple

from cps_fleet.config import ConfigError, Reader, load_yaml_document
from cps_fleet.robot_types import RobotType, read_robot_types

# The default fleet's four types (fleet.yaml robot_types); the simulator's bodies are modelled on them.
ROBOT_TYPES = ("wheeled_lidar", "wheeled_depth", "legged_depth", "aerial_depth")
PROFILES = ("paper", "light")
_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


# The package whose config/fleet.yaml is the default fleet (found through rospkg, devel or install space).
DEFAULT_FLEET_PACKAGE = "cps_bringup"


def default_fleet_path():
    """$CPS_FLEET_FILE, else config/fleet.yaml of DEFAULT_FLEET_PACKAGE as rospkg finds it."""
    env = os.environ.get("CPS_FLEET_FILE")
    if env:
        return env
    try:
        import rospkg

        package_dir = rospkg.RosPack().get_path(DEFAULT_FLEET_PACKAGE)
    except Exception as exc:  # rospkg raises its own ResourceNotFound
        raise ConfigError(
            "fleet.yaml",
            None,
            f"no fleet file given and {DEFAULT_FLEET_PACKAGE} not found by rospkg "
            f"({exc}); pass the fleet file or set CPS_FLEET_FILE",
        ) from exc
    return os.path.join(package_dir, "config", "fleet.yaml")


@dataclasses.dataclass(frozen=True)
class Pose2D:
    x: float
    y: float
    z: float
    yaw_deg: float

    @property
    def yaw_rad(self):
        return math.radians(self.yaw_deg)


@dataclasses.dataclass(frozen=True)
class DepthCameraProfile:
    width: int
    height: int
    rate_hz: float
    near_m: float
    far_m: float
    hfov_deg: float


@dataclasses.dataclass(frozen=True)
class LidarProfile:
    rings: int
    samples_per_ring: int
    rate_hz: float
    vertical_fov_deg: float
    max_range_m: float


@dataclasses.dataclass(frozen=True)
class SensorProfile:
    name: str
    depth_camera: DepthCameraProfile
    lidar: LidarProfile

    def point_spacing_m(self, sensor, range_m):
        """Distance between neighbouring returns `range_m` away, at the sensor's finest angular
        step (lidar: min of the azimuth step and the ring spacing; depth: one pixel's angle)."""
        if sensor == "lidar":
            lidar = self.lidar
            step = 2.0 * math.pi / lidar.samples_per_ring
            if lidar.rings > 1:
                step = min(step, math.radians(lidar.vertical_fov_deg) / (lidar.rings - 1) or step)
        else:
            step = math.radians(self.depth_camera.hfov_deg) / self.depth_camera.width
        return step * range_m


@dataclasses.dataclass(frozen=True)
class LinkConfig:
    available_mbps: float
    reserve_fraction: float
    min_rate_hz: float
    max_rate_hz: float
    estimate_bandwidth: bool
    # The robots' side Zenoh bridge keeps this many bytes of keyframes during an outage (None: none).
    backfill_store_bytes: Optional[int] = None

    @property
    def budget_mbytes_per_s(self):
        """The managed budget at the configured link rate (managed_budget_mbytes_per_s)."""
        return managed_budget_mbytes_per_s(self.available_mbps, self.reserve_fraction)


def managed_budget_mbytes_per_s(available_mbps, reserve_fraction):
    """The one formula of the managed budget: (1 - reserve) x available, from Mbit/s to MB/s
    (10^6 bytes/s); ValueError on a bad argument."""
    if not isinstance(available_mbps, (int, float)) or not math.isfinite(available_mbps) or available_mbps <= 0:
        raise ValueError(f"available bandwidth must be > 0 Mbit/s, got {available_mbps!r}")
    if (
        not isinstance(reserve_fraction, (int, float))
        or not math.isfinite(reserve_fraction)
        or not 0.0 <= reserve_fraction < 1.0
    ):
        raise ValueError(f"reserve_fraction must be in [0, 1), got {reserve_fraction!r}")
    return (1.0 - reserve_fraction) * available_mbps / 8.0


@dataclasses.dataclass(frozen=True)
class CloudLevel:
    """One detail level of a robot's managed cloud: the voxel grid's leaf."""

    name: str
    voxel_leaf_m: float
    bytes_prior: float  # size per message assumed before the encoder's first one at this level


@dataclasses.dataclass(frozen=True)
class VideoLevel:
    """One level of a camera robot's video: the resolution the camera renders and the JPEG quality."""

    name: str
    width: int
    height: int
    jpeg_quality: int
    bytes_prior: float
    # Where the level is written: its fleet file and line (for errors about what the camera can do).
    source: Tuple[str, int] = ("", 0)


@dataclasses.dataclass(frozen=True)
class StreamsConfig:
    """The managed streams' levels (fleet.yaml `streams:`); index 0 is the finest level."""

    cloud_levels: Tuple[CloudLevel, ...]
    video_levels: Tuple[VideoLevel, ...]
    video_min_rate_hz: float
    video_max_rate_hz: float
    # The selected (or teleoperated) robot's video: at this level or finer, at least this rate.
    operator_video_level: int
    operator_video_rate_hz: float


@dataclasses.dataclass(frozen=True)
class SensorModel:
    hit: float
    miss: float
    min: float
    max: float


@dataclasses.dataclass(frozen=True)
class MappingConfig:
    resolution_m: float
    sensor_model: SensorModel
    # Per robot type (robot_types[*].max_range_m).
    max_range_m: Dict[str, float]
    # The map server's autosave period (0: only on shutdown and on request).
    autosave_period_s: float


@dataclasses.dataclass(frozen=True)
class LimitsConfig:
    """Bounds on growth and on restarts (fleet.yaml `limits:`)."""

    trajectory_max_points: int
    csv_max_mbytes: float
    node_log_max_mbytes: float
    restart_backoff_s: float
    restart_backoff_max_s: float
    restart_window_s: float
    warm_spares: bool


@dataclasses.dataclass(frozen=True)
class Waypoint:
    x: float
    y: float
    z: float
    inspect: bool


@dataclasses.dataclass(frozen=True)
class Route:
    path: str
    waypoints: Tuple[Waypoint, ...]
    # Line of every waypoint in the route file, for error messages of later checks.
    lines: Tuple[int, ...]


@dataclasses.dataclass(frozen=True)
class RobotConfig:
    name: str
    type: str
    initial_pose: Pose2D
    voxel_leaf_m: float
    route_path: str
    robot_type: RobotType
    # A generated route (fleet files with `generate:`); None: the route is read from route_path.
    route: Optional[Route] = None
    # Where the robot is described: its fleet file and the line of its initial pose (or of `generate:`).
    source: Tuple[str, int] = ("", 0)

    @property
    def has_depth_camera(self):
        return self.robot_type.sensor == "depth"

    @property
    def has_lidar(self):
        return self.robot_type.sensor == "lidar"

    @property
    def cloud_topic(self):
        """The sensor's cloud topic, relative to /<name>."""
        return self.robot_type.cloud_topic

    @property
    def sensor_frame(self):
        return f"{self.name}/{self.robot_type.sensor_frame}"


@dataclasses.dataclass(frozen=True)
class FleetConfig:
    path: str
    profile: SensorProfile
    profiles: Dict[str, SensorProfile]
    site_path: str
    link: LinkConfig
    mapping: MappingConfig
    robots: Tuple[RobotConfig, ...]
    limits: LimitsConfig
    robot_types: Dict[str, RobotType]
    streams: StreamsConfig

    def robot(self, name):
        for robot in self.robots:
            if robot.name == name:
                return robot
        raise KeyError(f"robot '{name}' is not in the fleet ({', '.join(self.robot_names)})")

    @property
    def robot_names(self):
        return [r.name for r in self.robots]

    def with_robots(self, names):
        """The same fleet restricted to `names` (in the given order); unknown names raise KeyError."""
        return dataclasses.replace(self, robots=tuple(self.robot(n) for n in names))

    def with_profile(self, name):
        if name not in self.profiles:
            raise KeyError(f"unknown profile '{name}' (known: {', '.join(sorted(self.profiles))})")
        return dataclasses.replace(self, profile=self.profiles[name])

    def route(self, name):
        robot = self.robot(name)
        return robot.route if robot.route is not None else load_route(robot.route_path)


def _profile(reader, name):
    reader.known_keys("depth_camera", "lidar")
    cam = reader.child("depth_camera").known_keys("width", "height", "rate_hz", "near_m", "far_m", "hfov_deg")
    lidar = reader.child("lidar").known_keys("rings", "samples_per_ring", "rate_hz", "vertical_fov_deg", "max_range_m")
    depth = DepthCameraProfile(
        width=_positive_int(cam, "width"),
        height=_positive_int(cam, "height"),
        rate_hz=cam.number("rate_hz", low=0.0, high=1000.0, low_open=True),
        near_m=cam.number("near_m", low=0.0, low_open=True),
        far_m=cam.number("far_m", low=0.0, low_open=True),
        hfov_deg=cam.number("hfov_deg", low=1.0, high=179.0),
    )
    if depth.far_m <= depth.near_m:
        raise cam.error("far_m", f"far_m ({depth.far_m}) must be greater than near_m ({depth.near_m})")
    return SensorProfile(
        name=name,
        depth_camera=depth,
        lidar=LidarProfile(
            rings=_positive_int(lidar, "rings"),
            samples_per_ring=_positive_int(lidar, "samples_per_ring"),
            rate_hz=lidar.number("rate_hz", low=0.0, high=1000.0, low_open=True),
            vertical_fov_deg=lidar.number("vertical_fov_deg", low=0.0, high=180.0),
            max_range_m=lidar.number("max_range_m", low=0.0, low_open=True),
        ),
    )


def _positive_int(reader, key):
    value = reader.get(key, int)
    if value <= 0:
        raise reader.error(key, f"must be a positive integer, got {value}")
    return value


def load_fleet(path=None, profile=None):
    """Read and validate fleet.yaml (default: cps_bringup's); `profile` overrides the file's choice.
    A file with `base:` takes all but its robots from that fleet file (see `_load_derived`)."""
    path = path or default_fleet_path()
    doc = load_yaml_document(path)
    if "base" in doc.data:
        return _load_derived(doc, profile)
    top = Reader(doc).known_keys(
        "profile", "site", "profiles", "link", "robot_types", "mapping", "limits", "streams", "robots"
    )

    profiles_reader = top.child("profiles")
    profiles = {name: _profile(profiles_reader.child(name), name) for name in profiles_reader.value}
    for required in PROFILES:
        if required not in profiles:
            raise profiles_reader.error(None, f"missing profile '{required}'")
    chosen = profile or top.get("profile", str)
    if chosen not in profiles:
        raise ConfigError(
            doc.path,
            doc.line(("profile",)),
            f"profile: unknown profile '{chosen}' (known: {', '.join(sorted(profiles))})",
        )

    link_reader = top.child("link").known_keys(
        "available_mbps", "reserve_fraction", "min_rate_hz", "max_rate_hz", "estimate_bandwidth", "backfill_store_bytes"
    )
    link = LinkConfig(
        available_mbps=link_reader.number("available_mbps", low=0.0, low_open=True),
        reserve_fraction=link_reader.number("reserve_fraction", low=0.0, high=0.99),
        min_rate_hz=link_reader.number("min_rate_hz", low=0.0, low_open=True),
        max_rate_hz=link_reader.number("max_rate_hz", low=0.0, low_open=True),
        estimate_bandwidth=link_reader.get("estimate_bandwidth", bool, default=False),
        backfill_store_bytes=int(link_reader.number("backfill_store_bytes", low=0.0, low_open=True))
        if link_reader.has("backfill_store_bytes")
        else None,
    )
    if link.min_rate_hz > link.max_rate_hz:
        raise link_reader.error("min_rate_hz", f"min_rate_hz ({link.min_rate_hz}) > max_rate_hz ({link.max_rate_hz})")

    robot_types = read_robot_types(top.child("robot_types"))
    map_reader = top.child("mapping").known_keys("resolution_m", "sensor_model", "autosave_period_s")
    model = map_reader.child("sensor_model").known_keys("hit", "miss", "min", "max")
    mapping = MappingConfig(
        resolution_m=map_reader.number("resolution_m", low=0.001, high=10.0),
        sensor_model=_sensor_model(model),
        max_range_m={name: t.max_range_m for name, t in robot_types.items()},
        autosave_period_s=map_reader.number("autosave_period_s", low=0.0),
    )

    limits_reader = top.child("limits").known_keys(
        "trajectory_max_points",
        "csv_max_mbytes",
        "node_log_max_mbytes",
        "restart_backoff_s",
        "restart_backoff_max_s",
        "restart_window_s",
        "warm_spares",
    )
    limits = LimitsConfig(
        trajectory_max_points=_positive_int(limits_reader, "trajectory_max_points"),
        csv_max_mbytes=limits_reader.number("csv_max_mbytes", low=0.001, high=1e6),
        node_log_max_mbytes=limits_reader.number("node_log_max_mbytes", low=0.001, high=1e6),
        restart_backoff_s=limits_reader.number("restart_backoff_s", low=0.0, high=3600.0),
        restart_backoff_max_s=limits_reader.number("restart_backoff_max_s", low=0.0, high=3600.0),
        restart_window_s=limits_reader.number("restart_window_s", low=0.0, high=86400.0, low_open=True),
        warm_spares=limits_reader.get("warm_spares", bool),
    )
    if limits.trajectory_max_points < 2:
        raise limits_reader.error("trajectory_max_points", f"must be at least 2, got {limits.trajectory_max_points}")
    if limits.restart_backoff_max_s < limits.restart_backoff_s:
        raise limits_reader.error(
            "restart_backoff_max_s",
            f"restart_backoff_max_s ({limits.restart_backoff_max_s}) < restart_backoff_s ({limits.restart_backoff_s})",
        )

    streams = _streams(top.child("streams"))

    robots = []
    for item in top.items("robots"):
        robots.append(_read_robot(item, robot_types, robots))
    if not robots:
        raise top.error("robots", "the fleet has no robots")
    _check_cloud_levels(top.child("streams"), streams, profiles[chosen], robot_types, robots)

    return FleetConfig(
        path=os.path.abspath(doc.path),
        profile=profiles[chosen],
        profiles=profiles,
        site_path=top.path_of("site"),
        link=link,
        mapping=mapping,
        robots=tuple(robots),
        limits=limits,
        robot_types=robot_types,
        streams=streams,
    )


def _streams(reader):
    """fleet.yaml `streams:`: each stream's levels, finest first, and the operator's video target."""
    reader.known_keys(
        "cloud_levels",
        "video_levels",
        "video_min_rate_hz",
        "video_max_rate_hz",
        "operator_video_level",
        "operator_video_rate_hz",
    )
    cloud = []
    for item in reader.items("cloud_levels"):
        item.known_keys("name", "voxel_leaf_m", "bytes_prior")
        level = CloudLevel(
            name=item.get("name", str),
            voxel_leaf_m=item.number("voxel_leaf_m", low=0.001, high=10.0),
            bytes_prior=item.number("bytes_prior", low=0.0, low_open=True),
        )
        if cloud and level.voxel_leaf_m <= cloud[-1].voxel_leaf_m:
            raise item.error(
                "voxel_leaf_m",
                f"levels go from finest to coarsest: {level.voxel_leaf_m} m after {cloud[-1].voxel_leaf_m} m",
            )
        cloud.append(level)
    video = []
    for item in reader.items("video_levels"):
        item.known_keys("name", "width", "height", "jpeg_quality", "bytes_prior")
        level = VideoLevel(
            name=item.get("name", str),
            width=_positive_int(item, "width"),
            height=_positive_int(item, "height"),
            jpeg_quality=int(item.number("jpeg_quality", low=1, high=100)),
            bytes_prior=item.number("bytes_prior", low=0.0, low_open=True),
            source=(os.path.abspath(item.doc.path), item.doc.line(item.key_path)),
        )
        if video and level.width * level.height >= video[-1].width * video[-1].height:
            raise item.error("width", f"levels go from finest to coarsest: {level.name} after {video[-1].name}")
        video.append(level)
    for key, levels in (("cloud_levels", cloud), ("video_levels", video)):
        if not levels:
            raise reader.error(key, "needs at least one level")
        names = [level.name for level in levels]
        if len(set(names)) != len(names):
            raise reader.error(key, f"level names must be unique, got {names}")
    streams = StreamsConfig(
        cloud_levels=tuple(cloud),
        video_levels=tuple(video),
        video_min_rate_hz=reader.number("video_min_rate_hz", low=0.0, low_open=True),
        video_max_rate_hz=reader.number("video_max_rate_hz", low=0.0, low_open=True),
        operator_video_level=int(reader.number("operator_video_level", low=0)),
        operator_video_rate_hz=reader.number("operator_video_rate_hz", low=0.0, low_open=True),
    )
    if streams.video_min_rate_hz > streams.video_max_rate_hz:
        raise reader.error("video_min_rate_hz", "video_min_rate_hz > video_max_rate_hz")
    if streams.operator_video_level >= len(video):
        raise reader.error("operator_video_level", f"there are {len(video)} video levels (0 is the finest)")
    if not streams.video_min_rate_hz <= streams.operator_video_rate_hz <= streams.video_max_rate_hz:
        raise reader.error("operator_video_rate_hz", "must lie within [video_min_rate_hz, video_max_rate_hz]")
    return streams


def _check_cloud_levels(reader, streams, profile, robot_types, robots):
    """A cloud level finer than a robot's sensor resolves is refused (ConfigError at the level's
    line): its leaf must be at least the sensor's point spacing at half its type's max_range_m
    (the map inserts points up to max_range_m), else the voxel grid keeps every return of the
    farther half of that range as it is and the level costs bytes without detail the sensor has
    (docs/cloud_levels.md)."""
    used = sorted({robot.type for robot in robots})
    for item, level in zip(reader.items("cloud_levels"), streams.cloud_levels):
        for name in used:
            robot_type = robot_types[name]
            range_m = 0.5 * robot_type.max_range_m
            spacing = profile.point_spacing_m(robot_type.sensor, range_m)
            if level.voxel_leaf_m < spacing:
                raise item.error(
                    "voxel_leaf_m",
                    f"level {level.name}: leaf {level.voxel_leaf_m} m is finer than what robot type {name}'s "
                    f"{robot_type.sensor} resolves at {range_m:g} m, half its max_range_m ({spacing:.3f} m between "
                    f"neighbouring returns, profile {profile.name}); use a leaf of at least {spacing:.3f} m",
                )


def _read_robot(item, robot_types, robots, default_voxel_leaf_m=None):
    """One entry of a `robots:` list, checked against `robot_types` and the robots read before it."""
    item.known_keys("name", "type", "initial_pose", "voxel_leaf_m", "route")
    name = item.get("name", str)
    if not _NAME.match(name):
        raise item.error("name", f"'{name}' is not a valid ROS name (lowercase letters, digits, _)")
    if name in (r.name for r in robots):
        raise item.error("name", f"robot '{name}' is listed twice")
    robot_type = item.get("type", str)
    if robot_type not in robot_types:
        raise item.error("type", f"unknown robot type '{robot_type}' (known: {', '.join(robot_types)})")
    pose = item.child("initial_pose").known_keys("x", "y", "z", "yaw_deg")
    route_path = item.path_of("route")
    if not os.path.exists(route_path):
        raise item.error("route", f"route file {route_path} does not exist")
    if default_voxel_leaf_m is not None and not item.has("voxel_leaf_m"):
        voxel_leaf_m = default_voxel_leaf_m(item, robot_type)
    else:
        voxel_leaf_m = item.number("voxel_leaf_m", low=0.0, high=10.0, low_open=True)
    return RobotConfig(
        name=name,
        type=robot_type,
        initial_pose=Pose2D(
            pose.get("x", float),
            pose.get("y", float),
            pose.get("z", float, default=0.0),
            pose.get("yaw_deg", float, default=0.0),
        ),
        voxel_leaf_m=voxel_leaf_m,
        route_path=route_path,
        robot_type=robot_types[robot_type],
        source=(os.path.abspath(item.doc.path), item.doc.line(item.key_path + ("initial_pose",))),
    )


def _sensor_model(model):
    """OctoMap's probabilities, checked: miss < 0.5 < hit (a miss lowers, a hit raises the
    occupancy), and 0 < min < 0.5 < max < 1 (finite clamping log-odds on either side of unknown)."""
    sensor = SensorModel(
        hit=model.number("hit", low=0.5, high=1.0, low_open=True),
        miss=model.number("miss", low=0.0, high=0.5, low_open=True),
        min=model.number("min", low=0.0, high=0.5, low_open=True),
        max=model.number("max", low=0.5, high=1.0, low_open=True),
    )
    for key, value, limit in (
        ("hit", sensor.hit, 1.0),
        ("miss", sensor.miss, 0.5),
        ("min", sensor.min, 0.5),
        ("max", sensor.max, 1.0),
    ):
        if value == limit:
            raise model.error(
                key, f"{value} must be below {limit} (a probability of {limit} has no finite log-odds or no effect)"
            )
    return sensor


def load_route(path):
    """Read a route file: `waypoints:` a list of {x, y, z (default 0), inspect (default false)}."""
    doc = load_yaml_document(path)
    top = Reader(doc).known_keys("waypoints")
    items = top.items("waypoints")
    if not items:
        raise top.error("waypoints", "a route needs at least one waypoint")
    waypoints, lines = [], []
    for item in items:
        item.known_keys("x", "y", "z", "inspect")
        waypoints.append(
            Waypoint(
                item.get("x", float),
                item.get("y", float),
                item.get("z", float, default=0.0),
                item.get("inspect", bool, default=False),
            )
        )
        lines.append(doc.line(item.key_path))
    return Route(path=os.path.abspath(path), waypoints=tuple(waypoints), lines=tuple(lines))


def _load_derived(doc, profile):
    """A fleet file that takes everything but its robots from `base:` (another fleet file) and lists
    and/or generates its robots; every robot, start and route is checked against the site."""
    from cps_fleet import routes
    from cps_fleet.site import load_site

    top = Reader(doc).known_keys("base", "profile", "robots", "generate")
    base_path = top.path_of("base")
    if os.path.abspath(base_path) == os.path.abspath(doc.path):
        raise top.error("base", "a fleet file cannot be its own base")
    base_doc = load_yaml_document(base_path)
    if "base" in base_doc.data:
        raise top.error("base", f"{base_path} has a base itself; the base must be a complete fleet file")
    base = load_fleet(base_path, profile)
    if profile is None and top.has("profile"):
        chosen = top.get("profile", str)
        if chosen not in base.profiles:
            raise top.error("profile", f"unknown profile '{chosen}' (known: {', '.join(sorted(base.profiles))})")
        base = base.with_profile(chosen)
    templates = {}
    for robot in base.robots:
        templates.setdefault(robot.type, robot)

    def voxel_leaf_of(reader, robot_type):
        if robot_type not in templates:
            raise reader.error(
                "voxel_leaf_m", f"missing key 'voxel_leaf_m' (the base fleet has no {robot_type} robot to take it from)"
            )
        return templates[robot_type].voxel_leaf_m

    robots = []
    if top.has("robots"):
        for item in top.items("robots"):
            robots.append(_read_robot(item, base.robot_types, robots, default_voxel_leaf_m=voxel_leaf_of))
    site = load_site(base.site_path)
    floor = routes.Floor(site)
    if top.has("generate"):
        robots += _generated_robots(top.child("generate"), base, templates, robots, site)
    if not robots:
        raise top.error(None, "the fleet has no robots (give robots: and/or generate:)")
    for i, robot in enumerate(robots):
        _check_robot(robot, robots[:i], site, floor)
    return dataclasses.replace(base, path=os.path.abspath(doc.path), robots=tuple(robots))


def _generated_robots(gen, base, templates, listed, site):
    """The robots of a `generate:` block: round-robin over its types, routes per share of the aisles."""
    from cps_fleet import routes

    gen.known_keys("count", "types", "routes", "clearance_m", "flight_altitude_m")
    count = _positive_int(gen, "count")
    types = gen.get("types", list, default=[t for t in base.robot_types if t in templates])
    for i, robot_type in enumerate(types):
        if robot_type not in base.robot_types:
            raise ConfigError(
                gen.doc.path,
                gen.doc.line(gen.key_path + ("types", i)),
                f"generate.types[{i}]: unknown robot type '{robot_type}' (known: {', '.join(base.robot_types)})",
            )
        if robot_type not in templates:
            raise ConfigError(
                gen.doc.path,
                gen.doc.line(gen.key_path + ("types", i)),
                f"generate.types[{i}]: the base fleet has no {robot_type} robot to take its name and voxel_leaf_m from",
            )
    if not types:
        raise gen.error("types", "needs at least one robot type")
    kind = gen.get("routes", str, default="per_area")
    if kind != "per_area":
        raise gen.error("routes", f"unknown route scheme '{kind}' (known: per_area)")
    clearance_m = gen.number("clearance_m", default=routes.DEFAULT_CLEARANCE_M, low=routes.ROUTE_MARGIN_M, high=5.0)
    altitude_m = gen.number("flight_altitude_m", default=routes.DEFAULT_FLIGHT_ALTITUDE_M, low=0.5, high=20.0)
    try:
        shares = routes.generate_routes(site, count, clearance_m=clearance_m)
    except routes.RouteError as exc:
        raise gen.error("count", str(exc)) from exc
    path, line = os.path.abspath(gen.doc.path), gen.doc.line(gen.key_path)
    out, per_type = [], {}
    for k, share in enumerate(shares):
        robot_type = types[k % len(types)]
        per_type[robot_type] = per_type.get(robot_type, 0) + 1
        template = templates[robot_type]
        name = f"{template.name}_{per_type[robot_type]}"
        if name in (r.name for r in listed):
            raise gen.error("count", f"generated robot '{name}' is also listed under robots:")
        z = altitude_m if template.robot_type.is_aerial else 0.0
        waypoints = tuple(Waypoint(w.x, w.y, z, w.inspect) for w in share.waypoints)
        out.append(
            RobotConfig(
                name=name,
                type=robot_type,
                initial_pose=Pose2D(share.start[0], share.start[1], 0.0, share.yaw_deg),
                voxel_leaf_m=template.voxel_leaf_m,
                route_path=path,
                robot_type=template.robot_type,
                route=Route(path=path, waypoints=waypoints, lines=(line,) * len(waypoints)),
                source=(path, line),
            )
        )
    return out


def _check_robot(robot, others, site, floor):
    """ConfigError at the robot's line (or its route's) if its start is not free, is too close to
    another robot's, or its route leaves the hall or crosses a fence or equipment."""
    from cps_fleet import routes
    from cps_fleet.site import check_waypoint

    path, line = robot.source
    pose = robot.initial_pose
    reason = check_waypoint(site, pose.x, pose.y, max(pose.z, 0.0), robot.robot_type, margin_m=0.2)
    if reason:
        raise ConfigError(path, line, f"robot '{robot.name}' initial_pose: {reason}")
    for other in others:
        distance = math.hypot(pose.x - other.initial_pose.x, pose.y - other.initial_pose.y)
        if distance < routes.MIN_SEPARATION_M:
            raise ConfigError(
                path,
                line,
                f"robot '{robot.name}' starts {distance:.2f} m from '{other.name}' "
                f"(at least {routes.MIN_SEPARATION_M:g} m apart; the hall has no room "
                f"for this many robots here)",
            )
    route = robot.route if robot.route is not None else load_route(robot.route_path)
    problem = routes.route_problem(floor, (pose.x, pose.y), route.waypoints, robot.robot_type.is_aerial)
    if problem:
        index, why = problem
        raise ConfigError(route.path, route.lines[index], f"robot '{robot.name}' route: {why}")


def check_fleet_routes(fleet: FleetConfig):
    """The checks a derived fleet file gets at load time, for any fleet (ConfigError on the first problem)."""
    from cps_fleet import routes
    from cps_fleet.site import load_site

    site = load_site(fleet.site_path)
    floor = routes.Floor(site)
    for i, robot in enumerate(fleet.robots):
        _check_robot(robot, fleet.robots[:i], site, floor)


def robot_names_arg(fleet: FleetConfig, names: Optional[List[str]]):
    """Validate a user's robot list against the fleet; raise ValueError naming the unknown ones."""
    if not names:
        return fleet
    unknown = [n for n in names if n not in fleet.robot_names]
    if unknown:
        raise ValueError(f"unknown robot(s) {', '.join(unknown)}; the fleet has {', '.join(fleet.robot_names)}")
    return fleet.with_robots(names)
