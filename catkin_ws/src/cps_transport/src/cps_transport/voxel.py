"""Voxel-grid downsampling with pcl::VoxelGrid's semantics, in numpy.

One output point per occupied voxel, at the centroid of the voxel's points; the voxel of a point
is floor(p / leaf) per axis (computed in the input's float type, as pcl does in float32);
non-finite points are dropped; voxels come out in pcl's order (x fastest, then y, then z).
The cost is one sort of the voxel keys, so it is O(n log n) and independent of the extent.
"""

import numpy as np

_COLOR_FIELDS = ("rgb", "rgba")


def voxel_keys(points_xyz, leaf_size_m):
    """Integer voxel index (N, 3) of every point: floor(p * (1 / leaf)) in the points' float type."""
    points = np.asarray(points_xyz)
    float_type = np.float32 if points.dtype == np.float32 else np.float64
    inverse_leaf = float_type(1.0) / float_type(leaf_size_m)
    return np.floor(points.astype(float_type, copy=False) * inverse_leaf).astype(np.int64)


def voxel_groups(columns_xyz, leaf_size_m):
    """Voxel ordinal of every point (three finite 1-D coordinate arrays), in pcl's voxel order,
    and the number of voxels. A dense table when the bounding grid is small (no sort), else one
    sort of the keys."""
    float_type = np.float32 if columns_xyz[0].dtype == np.float32 else np.float64
    inverse_leaf = float_type(1.0) / float_type(leaf_size_m)
    indices = [np.floor(column * inverse_leaf) for column in columns_xyz]
    lows = [index.min() for index in indices]
    dims = [int(index.max() - low) + 1 for index, low in zip(indices, lows)]
    cells = dims[0] * dims[1] * dims[2]
    int_type = np.int32 if cells < (1 << 31) else np.int64
    axes = [(index - low).astype(int_type) for index, low in zip(indices, lows)]
    linear = axes[2]
    linear *= dims[1]
    linear += axes[1]
    linear *= dims[0]
    linear += axes[0]
    if cells <= max(4 * len(linear), 1 << 20):
        occupied = np.bincount(linear, minlength=cells) > 0
        rank = np.cumsum(occupied, dtype=np.int64) - 1
        return rank[linear], int(rank[-1]) + 1
    order = np.argsort(linear, kind="stable")
    sorted_keys = linear[order]
    new_voxel = np.empty(len(sorted_keys), dtype=bool)
    new_voxel[0] = True
    np.not_equal(sorted_keys[1:], sorted_keys[:-1], out=new_voxel[1:])
    groups = np.empty(len(sorted_keys), dtype=np.int64)
    groups[order] = np.cumsum(new_voxel) - 1
    return groups, int(np.count_nonzero(new_voxel))


def voxel_downsample(points_xyz, leaf_size_m, extra_fields=None):
    """Centroid of the points in every occupied voxel of edge `leaf_size_m` (metres).

    points_xyz: (N, 3) float array; non-finite rows are ignored.
    extra_fields: optional {name: (N,) array} averaged per voxel as well (integers are rounded;
    packed colours named rgb/rgba are averaged per channel, as pcl does).
    Returns the (M, 3) centroids in the input's float type, or (centroids, {name: (M,) array})
    when extra_fields is given.
    """
    if not leaf_size_m > 0:
        raise ValueError(f"leaf_size_m must be > 0, got {leaf_size_m}")
    points = np.asarray(points_xyz)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points_xyz must have shape (N, 3), got {points.shape}")
    out_type = points.dtype if points.dtype in (np.float32, np.float64) else np.dtype(np.float64)
    columns = [points[:, i] for i in range(3)]
    finite = np.isfinite(columns[0]) & np.isfinite(columns[1]) & np.isfinite(columns[2])
    all_finite = bool(finite.all())
    if not all_finite:
        columns = [column[finite] for column in columns]
    extras = {}
    for name, values in (extra_fields or {}).items():
        values = np.asarray(values)
        if len(values) != len(finite):
            raise ValueError(f"extra field '{name}' has {len(values)} values for {len(finite)} points")
        extras[name] = values if all_finite else values[finite]
    if len(columns[0]) == 0:
        empty = np.empty((0, 3), dtype=out_type)
        return empty if extra_fields is None else (empty, {k: v[:0] for k, v in extras.items()})

    groups, n_voxels = voxel_groups(columns, leaf_size_m)
    counts = np.bincount(groups, minlength=n_voxels)
    centroids = np.empty((n_voxels, 3), dtype=out_type)
    for i in range(3):
        centroids[:, i] = np.bincount(groups, weights=columns[i], minlength=n_voxels) / counts
    if extra_fields is None:
        return centroids
    averaged = {name: _average(values, groups, counts, name) for name, values in extras.items()}
    return centroids, averaged


def _average(values, groups, counts, name):
    n_voxels = len(counts)
    if name in _COLOR_FIELDS and values.dtype.itemsize == 4:
        packed_in = np.ascontiguousarray(values).view(np.uint32)
        packed = np.zeros(n_voxels, dtype=np.uint32)
        for shift in (0, 8, 16, 24):
            channel = np.bincount(groups, weights=(packed_in >> shift) & 0xFF, minlength=n_voxels) / counts
            packed |= np.rint(channel).astype(np.uint32) << shift
        return packed.view(values.dtype)
    mean = np.bincount(groups, weights=values.astype(np.float64), minlength=n_voxels) / counts
    if np.issubdtype(values.dtype, np.integer):
        return np.rint(mean).astype(values.dtype)
    return mean.astype(values.dtype)
