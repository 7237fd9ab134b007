"""octomap_server's occupied_cells_vis_array, serialized from numpy arrays.

genpy serializes a CUBE_LIST by building one geometry_msgs/Point and one std_msgs/ColorRGBA object
per voxel and packing each with struct: about 1 s for the 80 k occupied voxels of the hall, every
publish period, with the GIL held (the map server's insertion starved behind it). Here genpy
writes each marker without its points and colours, and the two arrays are spliced in as bytes:
the same message on the wire in a few milliseconds.
"""

import io
import struct

import numpy as np
from visualization_msgs.msg import Marker, MarkerArray

from cps_mapping.fused_map import height_colors

# Marker's fields after `colors` (text, mesh_resource: empty strings; mesh_use_embedded_materials).
_TAIL_BYTES = 4 + 4 + 1
# The two empty arrays' lengths (points, colors) before that tail.
_EMPTY_ARRAYS_BYTES = 4 + 4


class SerializedMarkerArray(MarkerArray):
    """A MarkerArray whose serialized bytes are made in advance; `markers` stays empty on this
    side (a subscriber deserializes the full message)."""

    __slots__ = ("serialized",)

    def __init__(self, serialized: bytes):
        super().__init__()
        self.serialized = serialized

    def serialize(self, buff):
        buff.write(self.serialized)


def _marker_bytes(marker: Marker, points_m: np.ndarray, colors_rgba: np.ndarray) -> bytes:
    """`marker` (no points, no colours, empty text and mesh_resource) serialized with the arrays."""
    buff = io.BytesIO()
    marker.serialize(buff)
    data = buff.getvalue()
    head = data[: -(_EMPTY_ARRAYS_BYTES + _TAIL_BYTES)]
    n = len(points_m)
    return b"".join(
        (
            head,
            struct.pack("<I", n),
            np.ascontiguousarray(points_m, dtype="<f8").tobytes(),
            struct.pack("<I", n),
            np.ascontiguousarray(colors_rgba, dtype="<f4").tobytes(),
            data[-_TAIL_BYTES:],
        )
    )


def occupied_cells_markers(centers_m, sizes_m, resolution_m, header) -> SerializedMarkerArray:
    """One CUBE_LIST per leaf size (ids 0, 1, ... by increasing size), coloured by height, as
    octomap_server's occupied_cells_vis_array; a size with no leaves gets a DELETE marker."""
    centers_m = np.asarray(centers_m, dtype=np.float64).reshape(-1, 3)
    levels = np.round(np.asarray(sizes_m, dtype=np.float64) / resolution_m).astype(int)
    rgba = np.ones((len(centers_m), 4), dtype=np.float32)
    if len(centers_m):
        rgba[:, :3] = height_colors(centers_m[:, 2])
    chunks = []
    for marker_id, level in enumerate(sorted(set(levels.tolist()) | {1})):
        sel = levels == level
        marker = Marker(
            header=header,
            ns="map",
            id=marker_id,
            type=Marker.CUBE_LIST,
            action=Marker.ADD if sel.any() else Marker.DELETE,
        )
        marker.scale.x = marker.scale.y = marker.scale.z = level * resolution_m
        marker.pose.orientation.w = 1.0
        marker.color.a = 1.0
        chunks.append(_marker_bytes(marker, centers_m[sel], rgba[sel]))
    return SerializedMarkerArray(struct.pack("<I", len(chunks)) + b"".join(chunks))
