"""voxel_downsample has pcl::VoxelGrid's semantics: one centroid per occupied voxel, voxel index
floor(p / leaf), non-finite points ignored, pcl's voxel order."""

import numpy as np
import pytest

from cps_transport.voxel import voxel_downsample


def _reference(points, leaf):
    """Centroids by np.unique over integer voxel indices, sorted as pcl (z, then y, then x)."""
    points = points[np.isfinite(points).all(axis=1)]
    keys = np.floor(points * np.float32(1.0 / leaf)).astype(np.int64)
    voxels, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    centroids = np.stack([np.bincount(inverse, weights=points[:, i].astype(np.float64)) / counts for i in range(3)], 1)
    return centroids[np.lexsort((voxels[:, 0], voxels[:, 1], voxels[:, 2]))]


@pytest.mark.parametrize("leaf", [0.01, 0.1, 0.5])
@pytest.mark.parametrize("extent", [2.0, 60.0])  # dense-table path and sort path
def test_matches_reference(leaf, extent):
    rng = np.random.default_rng(1)
    points = (rng.random((20000, 3)) * extent - extent / 3).astype(np.float32)
    points[::97] = np.nan
    got = voxel_downsample(points, leaf)
    want = _reference(points, leaf)
    assert got.shape == want.shape
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=2e-6 * extent)


def test_points_beyond_one_metre_are_kept_and_centroids_are_means():
    near = np.array([[0.01, 0.02, 0.03], [0.03, 0.04, 0.05]])
    far = near + [0.0, 0.0, 10.0]
    got = voxel_downsample(np.vstack([near, far]), 0.1)
    np.testing.assert_allclose(got, [near.mean(axis=0), far.mean(axis=0)])


def test_voxel_index_is_floor_also_for_negative_coordinates():
    got = voxel_downsample(np.array([[-0.05, 0, 0], [0.05, 0, 0]]), 0.1)
    assert len(got) == 2  # -0.05 is in voxel -1, 0.05 in voxel 0 (truncation would merge them)


def test_extra_fields_are_averaged_per_voxel_and_colours_per_channel():
    points = np.array([[0.01, 0, 0], [0.02, 0, 0], [5.0, 0, 0]], dtype=np.float32)
    rgb = np.array([0x00FF0000, 0x00000010, 0x00102030], dtype=np.uint32).view(np.float32)
    ring = np.array([1, 2, 7], dtype=np.uint16)
    intensity = np.array([1.0, 2.0, 3.0], dtype=np.float32)
    centroids, extras = voxel_downsample(points, 0.1, {"rgb": rgb, "ring": ring, "intensity": intensity})
    assert len(centroids) == 2
    assert extras["rgb"].view(np.uint32).tolist() == [0x00800008, 0x00102030]
    assert extras["ring"].dtype == np.uint16 and extras["ring"].tolist() == [2, 7]
    np.testing.assert_allclose(extras["intensity"], [1.5, 3.0])


def test_all_nan_and_bad_arguments():
    assert voxel_downsample(np.full((5, 3), np.nan, dtype=np.float32), 0.1).shape == (0, 3)
    with pytest.raises(ValueError, match="leaf_size_m"):
        voxel_downsample(np.zeros((2, 3)), 0.0)
    with pytest.raises(ValueError, match="shape"):
        voxel_downsample(np.zeros((2, 2)), 0.1)
