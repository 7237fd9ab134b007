"""The map server's messages built from numpy arrays and the map's figures; no master needed."""

from typing import Sequence

import numpy as np
from geometry_msgs.msg import Point
from nav_msgs.msg import OccupancyGrid
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from cps_msgs.msg import MapStats, Octomap, RobotMapStats
from cps_transport.pointcloud import array_to_cloud

_APPEARED_RGBA = (0.1, 0.9, 0.1, 0.6)
_DISAPPEARED_RGBA = (0.9, 0.1, 0.1, 0.6)
_MOVED_RGBA = (0.1, 0.4, 0.95, 0.6)
_CHANGE_RGBA = {"appeared": _APPEARED_RGBA, "disappeared": _DISAPPEARED_RGBA, "moved": _MOVED_RGBA}
_CHANGE_TEXT_LIFT_M = 0.3


def octomap_message(fields, header: Header) -> Octomap:
    """cps_msgs/Octomap from `fused_map.message_fields` (binary, id, resolution, body bytes)."""
    binary, tree_id, resolution_m, body = fields
    msg = Octomap(header=header, binary=binary, id=tree_id, resolution=resolution_m)
    msg.data = np.frombuffer(body, dtype=np.int8).tolist()
    return msg


def centers_cloud(centers_m: np.ndarray, header: Header):
    """sensor_msgs/PointCloud2 (x, y, z float32) of voxel centres."""
    centers = np.asarray(centers_m, dtype=np.float32).reshape(-1, 3)
    return array_to_cloud({"x": centers[:, 0], "y": centers[:, 1], "z": centers[:, 2]}, header=header)


def projected_map(grid: np.ndarray, origin_m, resolution_m: float, header: Header) -> OccupancyGrid:
    """nav_msgs/OccupancyGrid of `projected_grid`'s (rows = y, columns = x) cells, loaded at the header's stamp."""
    msg = OccupancyGrid()
    msg.header = header
    msg.info.map_load_time = header.stamp
    msg.info.resolution = resolution_m
    msg.info.height, msg.info.width = grid.shape
    msg.info.origin.position.x, msg.info.origin.position.y = np.asarray(origin_m).tolist()
    msg.info.origin.orientation.w = 1.0
    msg.data = grid.ravel().tolist()
    return msg


def robot_map_stats(robot: str, counters, queue_length: int, now_s: float, contributed_voxels: int) -> RobotMapStats:
    """One robot's RobotMapStats from its `RobotCounters`."""
    c = counters
    return RobotMapStats(
        robot=robot,
        clouds_received=c.clouds_received,
        clouds_inserted=c.clouds_inserted,
        clouds_dropped_queue=c.clouds_dropped_queue,
        clouds_dropped_tf=c.clouds_dropped_tf,
        clouds_dropped_invalid=c.clouds_dropped_invalid,
        clouds_superseded=c.clouds_superseded,
        clouds_dropped_decoder=c.clouds_dropped_decoder,
        queue_length=queue_length,
        insertion_ms_avg=c.insertion_ms_avg,
        insertion_ms_max=c.insertion_ms_max,
        points_inserted=c.points_inserted,
        map_age_s=c.map_age_s(now_s),
        occupied_voxels_contributed=contributed_voxels,
        published_map_age_s=c.published_map_age_s(now_s),
        clouds_missed_upstream=c.clouds_missed_upstream,
    )


def map_stats(header: Header, resolution_m: float, snapshot, robots: Sequence[RobotMapStats]) -> MapStats:
    """MapStats with the figures of the published `MapSnapshot` (zero before the first one)."""
    msg = MapStats(header=header, resolution=resolution_m, robots=list(robots))
    if snapshot is not None:
        msg.occupied_voxels = len(snapshot.leaf_centers_m)
        msg.tree_nodes = snapshot.tree_nodes
        msg.memory_bytes = snapshot.memory_bytes
    return msg


def change_markers(changes, header: Header) -> MarkerArray:
    """A DELETEALL, then per `change_detection.Change` a green (appeared), red (disappeared) or blue
    (moved: where the item stands now) box (its `text` the kind, for readers other than rviz), a
    text above it and, for a move, an arrow from where the item stood (its `text` "moved from"),
    ns `map_changes`."""
    array = MarkerArray(markers=[Marker(header=header, ns="map_changes", action=Marker.DELETEALL)])
    for i, change in enumerate(changes):
        rgba = _CHANGE_RGBA.get(change.kind, _DISAPPEARED_RGBA)
        box = _change_marker(header, 3 * i + 1, Marker.CUBE, rgba, change.kind)
        box.pose.position = Point(*box_centre(change))
        box.scale.x, box.scale.y, box.scale.z = change.size_m
        moved = getattr(change, "displacement_m", None)
        label = f"moved {np.hypot(moved[0], moved[1]):.2f} m" if moved else f"{change.kind} {change.volume_m3:.2f} m3"
        text = _change_marker(header, 3 * i + 2, Marker.TEXT_VIEW_FACING, (1.0, 1.0, 1.0, 1.0), label)
        text.pose.position = Point(change.centroid_m[0], change.centroid_m[1], change.max_m[2] + _CHANGE_TEXT_LIFT_M)
        text.scale.z = 0.3
        array.markers += [box, text]
        if moved and getattr(change, "from_m", None) is not None:
            arrow = _change_marker(header, 3 * i + 3, Marker.ARROW, (*rgba[:3], 1.0), "moved from")
            arrow.points = [Point(*change.from_m), Point(*box_centre(change))]
            arrow.scale.x, arrow.scale.y, arrow.scale.z = 0.05, 0.15, 0.2  # shaft, head diameters; head length
            array.markers.append(arrow)
    return array


def _change_marker(header, marker_id, marker_type, rgba, text):
    """One marker of ns `map_changes` (added, identity orientation)."""
    marker = Marker(
        header=header,
        ns="map_changes",
        id=marker_id,
        type=marker_type,
        action=Marker.ADD,
        color=ColorRGBA(*rgba),
        text=text,
    )
    marker.pose.orientation.w = 1.0
    return marker


def box_centre(change):
    return ((np.asarray(change.min_m) + change.max_m) / 2).tolist()
