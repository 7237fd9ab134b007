"""The baseline map of a monitoring mission: loaded and checked against the running map's
resolution and frame (no rospy).

A .bt file holds its resolution but not its frame, so the map server writes a small sidecar
`<map>.json` (`{"frame_id": ..., "resolution_m": ..., "robot_poses": ...}`) next to every map it
saves; a baseline whose sidecar names another frame is refused, one without a sidecar is taken as
in `frame_id`. `robot_poses` (cps_mapping.robot_bodies.RobotTrails) are the robots' sensor poses and
bodies during the mission that made the map, so that change detection can ignore the robots in it,
and `sensor_views` (cps_mapping.sensor_views.SensorViews) where the clouds it inserted were taken
from and what each sensor could see, its viewpoints;
a map without them (saved before they were kept) is still usable: `read_map_trails` returns None
and the monitoring report says that robots seen in the baseline may come out as changes.
"""

import json
import os

from cps_mapping.atomic_file import write_atomically
from cps_mapping.fused_map import FusedLogOddsMap, MapFileError


class BaselineError(ValueError):
    """The baseline map cannot serve: missing, unreadable, or of another resolution or frame."""


def metadata_path(map_path):
    return f"{map_path}.json"


def write_map_metadata(map_path, frame_id, resolution_m, robot_trails=None, sensor_views=None):
    """The sidecar of a saved map (with the robots' trails, a RobotTrails, and the inserted clouds'
    SensorViews, if given); MapFileError if it cannot be written. Written to a temporary file first:
    a reader never sees half a sidecar."""
    doc = {"frame_id": frame_id, "resolution_m": resolution_m}
    if robot_trails is not None:
        doc["robot_poses"] = robot_trails.as_json()
    if sensor_views is not None:
        doc["sensor_views"] = sensor_views.as_json()
    path = metadata_path(map_path)
    try:
        write_atomically(path, lambda stream: json.dump(doc, stream), binary=False)
    except OSError as exc:
        raise MapFileError(f"cannot write {metadata_path(map_path)}: {exc}") from exc


def read_map_frame(map_path):
    """The frame the sidecar names, or None without a sidecar; BaselineError if it is unreadable."""
    path = metadata_path(map_path)
    if not os.path.exists(path):
        return None
    try:
        with open(path) as stream:
            frame = json.load(stream)["frame_id"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise BaselineError(f"{path}: unreadable map metadata ({exc})") from exc
    if not isinstance(frame, str) or not frame:
        raise BaselineError(f"{path}: frame_id must be a non-empty string, got {frame!r}")
    return frame


def _read_sidecar_entry(map_path, key, parse, what):
    """`parse(doc[key])` of a saved map's sidecar, or None if the sidecar is missing or predates
    `key`; BaselineError (naming `what`) if it is unreadable."""
    path = metadata_path(map_path)
    if not os.path.exists(path):
        return None
    try:
        with open(path) as stream:
            doc = json.load(stream)
        return parse(doc[key]) if key in doc else None
    except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
        raise BaselineError(f"{path}: unreadable {what} ({type(exc).__name__}: {exc})") from exc


def read_map_trails(map_path):
    """The robots' trails saved with a map (cps_mapping.robot_bodies.RobotTrails), or None if the
    sidecar is missing or predates them; BaselineError if they are unreadable."""
    from cps_mapping.robot_bodies import RobotTrails

    return _read_sidecar_entry(map_path, "robot_poses", RobotTrails.from_json, "robot poses")


def read_map_views(map_path):
    """The inserted clouds' viewpoints saved with a map (cps_mapping.sensor_views.SensorViews), or
    None if the sidecar is missing or predates them; BaselineError if they are unreadable."""
    from cps_mapping.sensor_views import SensorViews

    return _read_sidecar_entry(map_path, "sensor_views", SensorViews.from_json, "sensor views")


def load_baseline(path, mapping, frame_id="map") -> FusedLogOddsMap:
    """The baseline map at `path` for a map of fleet `mapping` (cps_fleet's MappingConfig) in
    `frame_id`; BaselineError says why it cannot be used."""
    if not path:
        raise BaselineError("no baseline map given: a monitoring mission compares the site with an earlier map")
    path = os.path.abspath(os.path.expanduser(path))
    if not os.path.isfile(path):
        raise BaselineError(
            f"baseline map {path} does not exist (run a characterization mission first, "
            f"e.g. `make demo`, which saves out/demo/map.bt)"
        )
    frame = read_map_frame(path)
    if frame is not None and frame != frame_id:
        raise BaselineError(
            f"baseline map {path} is in frame '{frame}' ({metadata_path(path)}), "
            f"this map is in '{frame_id}': the two cannot be compared"
        )
    baseline = FusedLogOddsMap.from_mapping_config(mapping)
    try:
        baseline.load(path)
    except MapFileError as exc:
        raise BaselineError(f"baseline map refused: {exc}") from exc
    return baseline
