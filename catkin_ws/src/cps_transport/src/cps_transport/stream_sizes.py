"""Bytes per cloud at each stage of the tissue (raw, voxel-filtered, Draco-compressed), as the
running pipeline produces them: pcl_ros's VoxelGrid keeps the input's point layout, so a filtered
cloud is voxels x point_step; the encoder node sends x,y,z with an error of at most leaf/2.
Shared by bench/transport_bench.py and cps_bringup's experiments (Table 4, Fig. 11/12)."""

import dataclasses

from cps_transport.draco import DracoEncoder
from cps_transport.pointcloud import array_to_cloud, cloud_to_array, xyz_of
from cps_transport.voxel import voxel_downsample


def filter_cloud(cloud, leaf_size_m):
    """voxel_downsample over every field, as a PointCloud2 (the input's header), and the bytes
    pcl_ros's output would have (voxels x the input's point_step)."""
    points = cloud_to_array(cloud)
    extras = {n: points[n] for n in points.dtype.names if n not in ("x", "y", "z")}
    centroids, averaged = voxel_downsample(xyz_of(points), leaf_size_m, extras)
    out = array_to_cloud(
        {"x": centroids[:, 0], "y": centroids[:, 1], "z": centroids[:, 2], **averaged}, header=cloud.header
    )
    return out, len(centroids) * cloud.point_step


@dataclasses.dataclass(frozen=True)
class StageSizes:
    leaf_size_m: float
    points: int
    voxels: int
    raw_bytes: int
    filtered_bytes: int
    compressed_bytes: int


def stage_sizes(cloud, leaf_size_m, encoder=None):
    """StageSizes of one cloud at one leaf size; `encoder` defaults to the encoder node's settings
    for that leaf (DracoEncoder(leaf_size_m=leaf), x,y,z, speed 7)."""
    filtered, filtered_bytes = filter_cloud(cloud, leaf_size_m)
    encoder = encoder or DracoEncoder(leaf_size_m=leaf_size_m)
    compressed = encoder.encode(filtered)
    return StageSizes(
        leaf_size_m=float(leaf_size_m),
        points=cloud.width * cloud.height,
        voxels=filtered.width,
        raw_bytes=len(cloud.data),
        filtered_bytes=filtered_bytes,
        compressed_bytes=len(compressed.compressed_data),
    )
