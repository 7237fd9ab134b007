"""The RGB-D camera and the 3D lidar over a SimWorld (numpy, no rospy).

The camera renders an image and a depth buffer, turns it into an organized cloud in the
optical frame (z forward, x right, y down) with NaN where there is no return. The lidar casts
a VLP-16-like ray pattern with rayTestBatch and returns an unorganized scan (misses dropped).
"""

import dataclasses
import math

import numpy as np
import pybullet

# Structured layouts of the clouds (little-endian), as Gazebo's depth camera and the velodyne
# driver publish them.
DEPTH_DTYPE = np.dtype(
    {"names": ["x", "y", "z", "rgb"], "formats": ["<f4", "<f4", "<f4", "<u4"], "offsets": [0, 4, 8, 16], "itemsize": 32}
)
LIDAR_DTYPE = np.dtype(
    {
        "names": ["x", "y", "z", "intensity", "ring", "time"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
        "offsets": [0, 4, 8, 12, 16, 18],
        "itemsize": 22,
    }
)
LIDAR_MIN_RANGE_M = 0.4


@dataclasses.dataclass
class DepthFrame:
    rgb: np.ndarray  # H x W x 3 uint8
    depth_m: np.ndarray  # H x W float32, NaN = no return
    cloud: np.ndarray  # H x W structured DEPTH_DTYPE, optical frame
    sensor_in_map: np.ndarray  # 4 x 4


@dataclasses.dataclass
class LidarScan:
    points: np.ndarray  # N structured LIDAR_DTYPE, lidar frame
    sensor_in_map: np.ndarray  # 4 x 4


def camera_intrinsics(width, height, hfov_deg):
    """fx, fy, cx, cy (pixels, ROS convention: pixel centres at integers) of a pinhole camera."""
    fx = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    return fx, fx, (width - 1) / 2.0, (height - 1) / 2.0


def vertical_fov_deg(width, height, hfov_deg):
    return math.degrees(2.0 * math.atan(math.tan(math.radians(hfov_deg) / 2.0) * height / width))


def pack_rgb(rgb):
    """H x W x 3 uint8 -> H x W uint32 0x00RRGGBB (PCL's packed rgb)."""
    rgb = rgb.astype(np.uint32)
    return (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]


@dataclasses.dataclass(frozen=True)
class CameraModel:
    """Intrinsics of the pinhole camera (what camera_info carries), without a world to render."""

    width: int
    height: int
    hfov_deg: float

    @property
    def fx(self):
        return camera_intrinsics(self.width, self.height, self.hfov_deg)[0]

    @property
    def fy(self):
        return camera_intrinsics(self.width, self.height, self.hfov_deg)[1]

    @property
    def cx(self):
        return camera_intrinsics(self.width, self.height, self.hfov_deg)[2]

    @property
    def cy(self):
        return camera_intrinsics(self.width, self.height, self.hfov_deg)[3]


class DepthCamera:
    """A pinhole RGB-D camera: width x height, hfov_deg, depth range [near_m, far_m]."""

    def __init__(self, world, width, height, hfov_deg, near_m, far_m):
        self.world = world
        self.width, self.height = int(width), int(height)
        self.hfov_deg = float(hfov_deg)
        self.near_m, self.far_m = float(near_m), float(far_m)
        self.fx, self.fy, self.cx, self.cy = camera_intrinsics(self.width, self.height, self.hfov_deg)
        # Render with a slightly nearer/farther clip so near/far returns are not cut by the buffer.
        self._clip_near, self._clip_far = self.near_m * 0.5, self.far_m * 1.05
        self.projection = pybullet.computeProjectionMatrixFOV(
            vertical_fov_deg(self.width, self.height, self.hfov_deg),
            self.width / self.height,
            self._clip_near,
            self._clip_far,
        )
        u = np.arange(self.width, dtype=np.float32)
        v = np.arange(self.height, dtype=np.float32)
        self._ray_x = np.broadcast_to((u - self.cx) / self.fx, (self.height, self.width))
        self._ray_y = np.broadcast_to(((v - self.cy) / self.fy)[:, None], (self.height, self.width))
        self._video_projections = {}

    @staticmethod
    def view_matrix(optical_in_map):
        eye = optical_in_map[:3, 3]
        forward = optical_in_map[:3, 2]
        up = -optical_in_map[:3, 1]
        return pybullet.computeViewMatrix(eye.tolist(), (eye + forward).tolist(), up.tolist())

    def video_projection(self, width, height):
        """The projection of a colour image of width x height through this camera's optics."""
        key = (int(width), int(height))
        projection = self._video_projections.get(key)
        if projection is None:
            projection = pybullet.computeProjectionMatrixFOV(
                vertical_fov_deg(key[0], key[1], self.hfov_deg), key[0] / key[1], self._clip_near, self._clip_far
            )
            self._video_projections[key] = projection
        return projection

    def render_colour(self, optical_in_map, width, height):
        """The colour image alone at width x height (the video; same optics, no depth, no cloud)."""
        return self.world.render_colour(
            int(width), int(height), self.view_matrix(optical_in_map), self.video_projection(width, height)
        )

    def depth_from_buffer(self, buffer):
        """Metric depth along the optical axis from the OpenGL depth buffer; NaN outside range."""
        n, f = self._clip_near, self._clip_far
        depth = (f * n / (f - (f - n) * buffer.astype(np.float64))).astype(np.float32)
        depth[(buffer >= 1.0) | (depth < self.near_m) | (depth > self.far_m)] = np.nan
        return depth

    def capture(self, optical_in_map):
        rgba, buffer = self.world.render(self.width, self.height, self.view_matrix(optical_in_map), self.projection)
        rgb = np.ascontiguousarray(rgba[..., :3])
        depth = self.depth_from_buffer(buffer)
        return DepthFrame(rgb=rgb, depth_m=depth, cloud=self.organized_cloud(depth, rgb), sensor_in_map=optical_in_map)

    def organized_cloud(self, depth, rgb):
        cloud = np.zeros((self.height, self.width), dtype=DEPTH_DTYPE)
        cloud["x"] = self._ray_x * depth
        cloud["y"] = self._ray_y * depth
        cloud["z"] = depth
        cloud["rgb"] = pack_rgb(rgb)
        return cloud


class Lidar:
    """A spinning multi-ring lidar: rings evenly over ±vertical_fov/2, samples_per_ring azimuths."""

    def __init__(self, world, rings, samples_per_ring, vertical_fov_deg, max_range_m, ignore_body=None):
        self.world = world
        self.rings, self.samples = int(rings), int(samples_per_ring)
        self.max_range_m = float(max_range_m)
        half = math.radians(vertical_fov_deg) / 2.0
        self.elevations = np.linspace(-half, half, self.rings) if self.rings > 1 else np.zeros(1)
        self.azimuths = np.linspace(0.0, 2 * math.pi, self.samples, endpoint=False)
        el, az = np.meshgrid(self.elevations, self.azimuths, indexing="ij")
        self.directions = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(
            -1, 3
        )
        self.ring_of_ray = np.repeat(np.arange(self.rings, dtype=np.uint16), self.samples)
        self.ignore_body = ignore_body

    @property
    def ring_spacing_rad(self):
        return float(self.elevations[1] - self.elevations[0]) if self.rings > 1 else 0.0

    def capture(self, lidar_in_map):
        rot, origin = lidar_in_map[:3, :3], lidar_in_map[:3, 3]
        dirs_map = self.directions @ rot.T
        origins = origin + dirs_map * LIDAR_MIN_RANGE_M
        ends = origin + dirs_map * self.max_range_m
        fractions, positions, normals, ids = self.world.cast_rays(np.ascontiguousarray(origins), ends)
        hit = ids >= 0
        if self.ignore_body is not None:
            hit &= ids != self.ignore_body
        local = (positions[hit] - origin) @ rot
        cos_incidence = np.abs(np.einsum("ij,ij->i", normals[hit], dirs_map[hit]))
        points = np.zeros(int(hit.sum()), dtype=LIDAR_DTYPE)
        points["x"], points["y"], points["z"] = local[:, 0], local[:, 1], local[:, 2]
        points["intensity"] = np.round(100.0 * cos_incidence)
        points["ring"] = self.ring_of_ray[hit]
        points["time"] = 0.0  # every ray of a scan is cast at the capture instant
        return LidarScan(points=points, sensor_in_map=lidar_in_map)
