"""Sensor-shaped clouds of a box-shaped hall, for tests and for the benchmark when cps_sim's
renderer is not available: the same layouts as the simulator publishes (ros-graph.md).

- depth camera: organized H x W, fields x, y, z, rgb (offsets 0, 4, 8, 16), point_step 32,
  optical frame (z forward, x right, y down), NaN where a ray has no return;
- 3D lidar: x, y, z, intensity (float32), ring (uint16), time (float32), point_step 22 (as the
  Velodyne driver), unorganized.
"""

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

# Hall half-extents around the sensor (m): side walls at x = +-6, floor 1 m below, ceiling 3 m
# above, a back wall 15 m ahead; a 1 m box 4 m ahead.
_WALL_X_M, _FLOOR_M, _CEILING_M, _BACK_M = 6.0, 1.0, 3.0, 15.0


def _hall_depth(directions):
    """Distance along each unit ray (optical frame) to the first surface of the hall."""
    with np.errstate(divide="ignore", invalid="ignore"):
        candidates = [
            np.where(directions[:, 0] > 0, _WALL_X_M / directions[:, 0], np.inf),
            np.where(directions[:, 0] < 0, -_WALL_X_M / directions[:, 0], np.inf),
            np.where(directions[:, 1] > 0, _FLOOR_M / directions[:, 1], np.inf),
            np.where(directions[:, 1] < 0, -_CEILING_M / directions[:, 1], np.inf),
            np.where(directions[:, 2] > 0, _BACK_M / directions[:, 2], np.inf),
        ]
        # Box: front face at z = 4 between x in [-0.5, 0.5], y in [0, 1].
        t_box = np.where(directions[:, 2] > 0, 4.0 / directions[:, 2], np.inf)
        hit = directions * t_box[:, None]
        inside = (np.abs(hit[:, 0]) <= 0.5) & (hit[:, 1] >= 0.0) & (hit[:, 1] <= 1.0)
        candidates.append(np.where(inside, t_box, np.inf))
    return np.min(candidates, axis=0)


def depth_camera_cloud(
    width=640,
    height=480,
    hfov_deg=60.0,
    far_m=18.0,
    dropout=0.02,
    noise_m=0.003,
    seed=0,
    stamp=None,
    frame_id="camera_depth_optical_frame",
):
    """An organized depth-camera PointCloud2 (x, y, z, rgb; point_step 32) with NaN dropouts."""
    rng = np.random.default_rng(seed)
    focal = (width / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
    u, v = np.meshgrid(np.arange(width) - (width - 1) / 2.0, np.arange(height) - (height - 1) / 2.0)
    rays = np.stack([u / focal, v / focal, np.ones_like(u)], axis=-1).reshape(-1, 3)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    distance = _hall_depth(rays) + rng.normal(0.0, noise_m, len(rays))
    xyz = rays * distance[:, None]
    missing = (xyz[:, 2] > far_m) | (rng.random(len(rays)) < dropout)
    xyz[missing] = np.nan
    shade = np.clip(255 - 12 * np.nan_to_num(distance), 40, 255).astype(np.uint32)
    rgb = (shade << 16 | (shade // 2) << 8 | (255 - shade)).astype(np.uint32)
    dtype = np.dtype(
        {
            "names": ["x", "y", "z", "rgb"],
            "formats": ["<f4", "<f4", "<f4", "<u4"],
            "offsets": [0, 4, 8, 16],
            "itemsize": 32,
        }
    )
    points = np.zeros(len(rays), dtype=dtype)
    points["x"], points["y"], points["z"], points["rgb"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], rgb
    fields = [
        PointField(name=n, offset=o, datatype=PointField.FLOAT32, count=1)
        for n, o in (("x", 0), ("y", 4), ("z", 8), ("rgb", 16))
    ]
    return _message(points, fields, height, width, 32, stamp, frame_id, is_dense=False)


def lidar_cloud(
    rings=16, samples_per_ring=1875, vertical_fov_deg=30.0, max_range_m=100.0, seed=0, stamp=None, frame_id="lidar"
):
    """An unorganized 3D-lidar PointCloud2 (x, y, z, intensity, ring, time; point_step 22)."""
    rng = np.random.default_rng(seed)
    elevation = np.radians(np.linspace(-vertical_fov_deg / 2, vertical_fov_deg / 2, rings))
    azimuth = np.linspace(0, 2 * np.pi, samples_per_ring, endpoint=False)
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    # Lidar frame: x forward, z up -> optical-frame rays for the hall model.
    lidar_rays = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)
    optical = np.stack([-lidar_rays[:, 1], -lidar_rays[:, 2], lidar_rays[:, 0]], axis=1)
    distance = np.minimum(_hall_depth(optical), max_range_m) + rng.normal(0.0, 0.01, len(optical))
    xyz = lidar_rays * distance[:, None]
    dtype = np.dtype(
        {
            "names": ["x", "y", "z", "intensity", "ring", "time"],
            "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
            "offsets": [0, 4, 8, 12, 16, 18],
            "itemsize": 22,
        }
    )
    points = np.zeros(len(xyz), dtype=dtype)
    points["x"], points["y"], points["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    points["intensity"] = np.clip(100.0 / (1.0 + distance), 0, 255) + rng.random(len(xyz))
    points["ring"] = np.repeat(np.arange(rings), samples_per_ring)
    points["time"] = np.tile(np.linspace(0.0, 0.1, samples_per_ring, endpoint=False), rings)
    fields = [
        PointField(name="x", offset=0, datatype=PointField.FLOAT32, count=1),
        PointField(name="y", offset=4, datatype=PointField.FLOAT32, count=1),
        PointField(name="z", offset=8, datatype=PointField.FLOAT32, count=1),
        PointField(name="intensity", offset=12, datatype=PointField.FLOAT32, count=1),
        PointField(name="ring", offset=16, datatype=PointField.UINT16, count=1),
        PointField(name="time", offset=18, datatype=PointField.FLOAT32, count=1),
    ]
    return _message(points, fields, 1, len(xyz), 22, stamp, frame_id, is_dense=True)


def xyz_cloud(xyz, frame_id, stamp=None):
    """A PointCloud2 of float32 x, y, z only (as the map server's voxel centres) from an (N, 3) array."""
    points = np.ascontiguousarray(np.asarray(xyz, dtype="<f4").reshape(-1, 3))
    fields = [PointField(name=k, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, k in enumerate("xyz")]
    return _message(points, fields, 1, len(points), 12, stamp, frame_id, is_dense=True)


def _message(points, fields, height, width, point_step, stamp, frame_id, is_dense):
    msg = PointCloud2()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = height, width
    msg.fields = fields
    msg.is_bigendian = False
    msg.point_step = point_step
    msg.row_step = point_step * width
    msg.is_dense = is_dense
    msg.data = points.tobytes()
    return msg
