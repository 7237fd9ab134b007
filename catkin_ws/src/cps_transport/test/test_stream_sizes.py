"""stage_sizes: the bytes each stage of the tissue sends for one cloud, as the nodes produce them."""

import numpy as np

from cps_harness.synthetic_clouds import depth_camera_cloud
from cps_transport.draco import DracoDecoder, DracoEncoder
from cps_transport.pointcloud import cloud_to_array, xyz_of
from cps_transport.stream_sizes import filter_cloud, stage_sizes
from cps_transport.voxel import voxel_downsample


def test_stage_sizes_follow_the_pipeline():
    cloud = depth_camera_cloud(width=160, height=120)
    sizes = stage_sizes(cloud, 0.1)
    centroids = voxel_downsample(xyz_of(cloud_to_array(cloud)), 0.1)
    assert sizes.points == 160 * 120 and sizes.raw_bytes == len(cloud.data)
    assert sizes.voxels == len(centroids) and sizes.filtered_bytes == len(centroids) * cloud.point_step
    filtered, _ = filter_cloud(cloud, 0.1)
    assert sizes.compressed_bytes == len(DracoEncoder(leaf_size_m=0.1).encode(filtered).compressed_data)
    assert sizes.raw_bytes > sizes.filtered_bytes > sizes.compressed_bytes > 0
    decoded = DracoDecoder().decode(DracoEncoder(leaf_size_m=0.1).encode(filtered))
    np.testing.assert_allclose(xyz_of(cloud_to_array(decoded)), centroids, atol=0.05)
