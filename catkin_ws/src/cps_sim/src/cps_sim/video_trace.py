"""Recorded video: each camera robot's frames along its own route at every video level, played
back at the level and rate the bandwidth manager allocates (numpy, no rospy).

Why: on a 2-core machine, rendering and JPEG-encoding four 640x480 cameras at 30 Hz is bound by
the CPU long before a 5 Mbit/s link binds, so the manager-on and manager-off arms would be
compared on the CPU, not on the link. A trace costs ~nothing to play and offers the link the real
frames' sizes at the allocated level and rate.

Record (offline, no ROS; renders every camera robot of the fleet at every level of
fleet.yaml `streams.video_levels`):

    python -m cps_sim.video_trace record --profile paper --out video_trace.npz [--robots a,b] [--frames N]

Play: fleet_sim's `~video_trace` parameter (`cps_bringup all --video-trace video_trace.npz`).

Sampling: `frames_per_level` poses evenly spaced by distance along the robot's closed route
(initial pose -> its route's waypoints -> back to the initial pose), facing the direction of
travel; the same poses at every level, so that the i-th frame of each level shows the same view.
The player walks one cursor per robot through those poses (whatever level each frame is asked
at), looping.

File (an .npz written with numpy.savez, no pickles): `meta` (JSON: format, fleet file, profile,
the levels' name/size/quality, the camera's hfov, the robots' names, types and routes, how the
frames were sampled, the renderer), and per robot k and level i `jpeg_k_i` (the JPEG files end to
end), `offsets_k_i` (their starts and the end) and `encode_s_k_i` (the recorded encode time).
"""

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from typing import Dict, List, Tuple

import numpy as np

from cps_sim.video import VideoFrame, VideoTask

TRACE_FORMAT = "cps_sim.video_trace/1"
# 10 s of 30 Hz video per level, spread over the whole route (the sizes vary along it); the
# paper fleet's 3 cameras x 3 levels render in about 30 s on the shared 2-core test machine.
DEFAULT_FRAMES_PER_LEVEL = 300
SAMPLING = (
    "poses evenly spaced by distance along the closed route (initial pose -> waypoints -> initial pose), "
    "facing the direction of travel; the same poses at every level"
)


class VideoTraceError(ValueError):
    """A trace file that cannot feed this fleet (missing, unreadable, other levels or robots)."""


def _levels(fleet):
    return [
        {"name": lv.name, "width": lv.width, "height": lv.height, "jpeg_quality": lv.jpeg_quality}
        for lv in fleet.streams.video_levels
    ]


def _route_points(fleet, robot):
    """[(x, y, z)] of the robot's closed route: its initial pose, the waypoints, the initial pose."""
    start = robot.initial_pose
    points = [(start.x, start.y, start.z)]
    points += [(w.x, w.y, w.z) for w in fleet.route(robot.name).waypoints]
    points.append(points[0])
    return points


def _camera_robots(fleet):
    return [r for r in fleet.robots if r.has_depth_camera]


def _robot_meta(fleet, robot):
    return {"name": robot.name, "type": robot.type, "route": [list(map(float, p)) for p in _route_points(fleet, robot)]}


def route_poses(points, count, initial_yaw_rad=0.0) -> List[Tuple[float, float, float, float]]:
    """`count` poses (x, y, z, yaw rad) evenly spaced by distance along the polyline `points`,
    each facing its leg's horizontal direction (a vertical leg keeps the previous heading)."""
    pts = np.asarray(points, dtype=float)
    legs = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    total = float(legs.sum())
    if total <= 0.0:
        return [(*pts[0], initial_yaw_rad)] * count
    ends = np.cumsum(legs)
    poses, yaw = [], initial_yaw_rad
    for s in np.arange(count) * total / count:
        i = min(int(np.searchsorted(ends, s, side="right")), len(legs) - 1)
        a, b = pts[i], pts[i + 1]
        fraction = (s - (ends[i] - legs[i])) / legs[i] if legs[i] > 0 else 0.0
        if math.hypot(b[0] - a[0], b[1] - a[1]) > 1e-6:
            yaw = math.atan2(b[1] - a[1], b[0] - a[0])
        x, y, z = a + fraction * (b - a)
        poses.append((float(x), float(y), float(z), yaw))
    return poses


def record_video_trace(fleet, out_path, frames_per_level=DEFAULT_FRAMES_PER_LEVEL, renderer="fast", log=print):
    """Render every camera robot's frames along its route at every video level; write `out_path`."""
    from cps_sim.simulation import FleetSimulation

    if frames_per_level < 1:
        raise ValueError(f"frames_per_level must be >= 1, got {frames_per_level}")
    cameras = _camera_robots(fleet)
    if not cameras:
        raise VideoTraceError(f"{fleet.path}: no camera robot in the fleet ({', '.join(fleet.robot_names)})")
    sim = FleetSimulation(fleet, renderer=renderer)
    arrays = {}
    started = time.monotonic()
    try:
        for k, robot in enumerate(cameras):
            poses = route_poses(_route_points(fleet, robot), frames_per_level, robot.initial_pose.yaw_rad)
            frames = {i: [] for i in range(len(fleet.streams.video_levels))}
            for pose in poses:
                sim.place(robot.name, *pose)
                for i, level in enumerate(fleet.streams.video_levels):
                    task = VideoTask(robot.name, i, level.width, level.height, level.jpeg_quality)
                    frames[i].append(sim.capture_video(task))
            for i, level_frames in frames.items():
                sizes = [len(f.jpeg) for f in level_frames]
                arrays[f"jpeg_{k}_{i}"] = np.concatenate([f.jpeg for f in level_frames])
                arrays[f"offsets_{k}_{i}"] = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
                arrays[f"encode_s_{k}_{i}"] = np.array([f.encode_s for f in level_frames])
            log(f"[video_trace] {robot.name}: {frames_per_level} poses x {len(frames)} levels")
        renderer_used = str(sim.renderer)
    finally:
        sim.close()
    meta = {
        "format": TRACE_FORMAT,
        "fleet_file": fleet.path,
        "profile": fleet.profile.name,
        "camera_hfov_deg": fleet.profile.depth_camera.hfov_deg,
        "levels": _levels(fleet),
        "robots": [_robot_meta(fleet, r) for r in cameras],
        "frames_per_level": frames_per_level,
        "sampling": SAMPLING,
        "renderer": renderer_used,
        "recorded_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "record_s": round(time.monotonic() - started, 1),
    }
    os.makedirs(os.path.dirname(os.path.abspath(out_path)) or ".", exist_ok=True)
    partial = out_path + ".partial.npz"  # a trace is complete or absent: a killed run leaves no half file
    np.savez(partial, meta=np.array(json.dumps(meta)), **arrays)
    os.replace(partial, out_path)
    return out_path


@dataclasses.dataclass
class VideoTrace:
    """A loaded trace: its metadata and, per (robot, level index), the JPEG files and encode times."""

    path: str
    meta: dict
    jpegs: Dict[Tuple[str, int], List[bytes]]
    encode_s: Dict[Tuple[str, int], np.ndarray]

    @property
    def robots(self):
        return [r["name"] for r in self.meta["robots"]]

    @property
    def frames_per_level(self):
        return int(self.meta["frames_per_level"])

    def mean_bytes(self, robot, level_index):
        frames = self.jpegs[(robot, level_index)]
        return sum(map(len, frames)) / len(frames)

    def describe(self):
        return (
            # The file's name only: a report read elsewhere must not carry this machine's folders.
            f"recorded frames of each camera robot's route at each video level ({os.path.basename(self.path)}: "
            f"{self.frames_per_level} per level, {self.meta['renderer']} renderer), played at the level and rate "
            "the camera is set to (the manager's, or without it the finest at the maximum rate)"
        )


def load_video_trace(path, fleet) -> VideoTrace:
    """The trace at `path` if it can feed `fleet`'s cameras, else VideoTraceError naming the file and
    what differs (its levels, the camera's hfov, a camera robot missing, of another type or route)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            arrays = {key: data[key] for key in data.files if key != "meta"}
    except (OSError, ValueError, KeyError) as exc:
        raise VideoTraceError(f"video trace {path}: cannot read it ({exc})") from exc
    if meta.get("format") != TRACE_FORMAT:
        raise VideoTraceError(f"video trace {path}: format {meta.get('format')!r}, expected {TRACE_FORMAT!r}")
    problems = []
    if meta["levels"] != _levels(fleet):
        problems.append(
            f"its video levels {_level_text(meta['levels'])} are not the fleet's {_level_text(_levels(fleet))}"
        )
    if meta["camera_hfov_deg"] != fleet.profile.depth_camera.hfov_deg:
        problems.append(
            f"its camera hfov {meta['camera_hfov_deg']} deg is not profile '{fleet.profile.name}''s "
            f"{fleet.profile.depth_camera.hfov_deg} deg"
        )
    recorded = {r["name"]: r for r in meta["robots"]}
    for robot in _camera_robots(fleet):
        wanted = _robot_meta(fleet, robot)
        got = recorded.get(robot.name)
        if got is None:
            problems.append(f"camera robot '{robot.name}' is not in it (it has {', '.join(recorded) or 'none'})")
        elif got["type"] != wanted["type"]:
            problems.append(f"'{robot.name}' was recorded as a {got['type']}, the fleet's is a {wanted['type']}")
        elif not _same_route(got["route"], wanted["route"]):
            problems.append(f"'{robot.name}''s route differs from the one recorded")
    if problems:
        raise VideoTraceError(
            f"video trace {path} does not match fleet {fleet.path} (profile {fleet.profile.name}): "
            + "; ".join(problems)
            + " - record it again (python -m cps_sim.video_trace record)"
        )
    jpegs, encode_s = {}, {}
    for k, robot in enumerate(meta["robots"]):
        for i in range(len(meta["levels"])):
            data, offsets = arrays[f"jpeg_{k}_{i}"], arrays[f"offsets_{k}_{i}"]
            jpegs[(robot["name"], i)] = [data[a:b].tobytes() for a, b in zip(offsets[:-1], offsets[1:])]
            encode_s[(robot["name"], i)] = arrays[f"encode_s_{k}_{i}"]
    return VideoTrace(os.path.abspath(path), meta, jpegs, encode_s)


def _same_route(a, b):
    return len(a) == len(b) and bool(np.allclose(np.array(a), np.array(b)))


def _level_text(levels):
    return "[" + ", ".join(f"{lv['name']} {lv['width']}x{lv['height']} q{lv['jpeg_quality']}" for lv in levels) + "]"


class VideoTracePlayer:
    """The next recorded frame of a robot at the level a VideoTask asks for, looping over the route.

    One cursor per robot, advanced by every frame whatever its level: a level change keeps the
    robot's place along its route."""

    def __init__(self, trace: VideoTrace):
        self.trace = trace
        self.cursor = {robot: 0 for robot in trace.robots}

    def frame(self, task: VideoTask) -> VideoFrame:
        """The frame at the robot's cursor, at task.level_index; render_s is what fetching it cost
        (~0), encode_s 0 (the recorded encode time: trace.encode_s)."""
        started = time.perf_counter()
        level = self.trace.meta["levels"][task.level_index]
        if (level["width"], level["height"]) != (task.width, task.height):
            raise ValueError(
                f"video task {task.width}x{task.height} is not level {task.level_index} "
                f"({level['width']}x{level['height']}) of trace {self.trace.path}"
            )
        frames = self.trace.jpegs[(task.robot, task.level_index)]
        index = self.cursor[task.robot]
        self.cursor[task.robot] = (index + 1) % len(frames)
        jpeg = np.frombuffer(frames[index], dtype=np.uint8)
        return VideoFrame(
            jpeg=jpeg,
            width=task.width,
            height=task.height,
            level_index=task.level_index,
            render_s=time.perf_counter() - started,
            encode_s=0.0,
        )


def main(argv=None):
    from cps_fleet.config import ConfigError
    from cps_fleet.fleet import PROFILES, load_fleet, robot_names_arg

    parser = argparse.ArgumentParser(prog="python -m cps_sim.video_trace", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    record = sub.add_parser("record", help="render the fleet's camera robots along their routes at every level")
    record.add_argument("--fleet", default=None, help="fleet.yaml (default: cps_bringup/config/fleet.yaml)")
    record.add_argument("--profile", choices=PROFILES, default=None)
    record.add_argument("--robots", default=None, help="comma-separated subset of the fleet")
    record.add_argument("--out", required=True, help="the trace file to write (.npz)")
    record.add_argument("--frames", type=int, default=DEFAULT_FRAMES_PER_LEVEL, help="poses (frames per level)")
    record.add_argument("--renderer", default="fast")
    args = parser.parse_args(argv)
    try:
        fleet = robot_names_arg(load_fleet(args.fleet, args.profile), args.robots.split(",") if args.robots else None)
        path = record_video_trace(fleet, args.out, args.frames, renderer=args.renderer)
        trace = load_video_trace(path, fleet)
    except (ConfigError, KeyError, ValueError) as exc:
        print(f"video_trace: error: {exc}", file=sys.stderr)
        return 2
    for robot in trace.robots:
        sizes = ", ".join(
            f"{lv['name']} {trace.mean_bytes(robot, i) / 1e3:.1f} kB" for i, lv in enumerate(trace.meta["levels"])
        )
        print(f"[video_trace] {robot}: mean JPEG {sizes}")
    print(f"[video_trace] wrote {path} in {trace.meta['record_s']} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
