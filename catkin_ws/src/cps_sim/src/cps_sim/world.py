"""The PyBullet world: the hall, the robots' bodies, rendering and ray casting (no rospy).

One DIRECT-mode client holds the whole fleet. The hall is built twice: coloured visual-only
bodies (what the cameras render) and one static triangle mesh (what the lidar's rays hit,
fast in Bullet's BVH). Robots are kinematic bodies moved to their integrated pose.
"""
import logging
import math
import pkgutil

import numpy as np
import pybullet

from cps_sim.geometry import merged_mesh

log = logging.getLogger(__name__)

RENDERERS = ("egl", "tiny", "auto")
# Below this many pixels per frame TinyRenderer costs less CPU than the EGL plugin on llvmpipe:
# EGL pays ~60 ms per frame whatever the size (a fixed 2560x2048 window and a shadow-map pass),
# TinyRenderer ~0.5 us per pixel (measured in docs/benchmarks/sim.md).
AUTO_TINY_MAX_PIXELS = 170_000


def resolve_renderer(requested, width, height):
    """'egl' or 'tiny' for a requested renderer; 'auto' picks the cheaper one for the frame size."""
    if requested not in RENDERERS:
        raise ValueError(f"unknown renderer '{requested}' (known: {', '.join(RENDERERS)})")
    if requested == "auto":
        return "tiny" if width * height <= AUTO_TINY_MAX_PIXELS else "egl"
    return requested
# PyBullet refuses batches over 16384 rays and silently returns nothing for exactly 16384.
MAX_RAYS_PER_BATCH = 16383


def _quaternion_z(yaw):
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


class SimWorld:
    """A PyBullet client with the site and the robots' bodies in it."""

    def __init__(self, site, renderer="egl"):
        if renderer not in ("egl", "tiny"):
            raise ValueError(f"unknown renderer '{renderer}' (known: egl, tiny; resolve 'auto' first)")
        self.site = site
        self.client = pybullet.connect(pybullet.DIRECT)
        self.renderer = "tiny"
        self._egl_plugin = None
        if renderer == "egl":
            # The EGL plugin must be loaded before any body exists.
            try:
                loader = pkgutil.get_loader("eglRenderer")
                plugin = pybullet.loadPlugin(loader.get_filename(), "_eglRendererPlugin", physicsClientId=self.client)
                if plugin >= 0:
                    self._egl_plugin = plugin
                    self.renderer = "egl"
            except Exception as exc:  # pragma: no cover - depends on the machine's EGL
                log.warning("EGL renderer unavailable (%s); using TinyRenderer", exc)
            if self.renderer != "egl":
                log.warning("EGL renderer plugin did not load; using TinyRenderer")
        self._bullet_renderer = (pybullet.ER_BULLET_HARDWARE_OPENGL if self.renderer == "egl"
                                 else pybullet.ER_TINY_RENDERER)
        pybullet.configureDebugVisualizer(pybullet.COV_ENABLE_SHADOWS, 0, physicsClientId=self.client)
        self.hall_body = None
        self.visual_bodies = []
        self.robot_bodies = {}
        self._build_site()

    def _build_site(self):
        c = self.client
        prims = self.site.primitives()
        for prim in prims:
            if prim.kind == "box":
                vis = pybullet.createVisualShape(pybullet.GEOM_BOX, halfExtents=prim.half_extents, rgbaColor=prim.rgba,
                                                 physicsClientId=c)
                orn = _quaternion_z(prim.yaw_rad)
            else:
                vis = pybullet.createVisualShape(pybullet.GEOM_CYLINDER, radius=prim.radius, length=2 * prim.half_length,
                                                 rgbaColor=prim.rgba, physicsClientId=c)
                orn = _quaternion_z(prim.yaw_rad)
                if prim.axis == "x":
                    orn = pybullet.multiplyTransforms((0, 0, 0), orn, (0, 0, 0),
                                                      pybullet.getQuaternionFromEuler((0.0, math.pi / 2, 0.0)))[1]
            body = pybullet.createMultiBody(0.0, -1, vis, prim.center, orn, physicsClientId=c)
            self.visual_bodies.append(body)
        verts, tris = merged_mesh(prims)
        col = pybullet.createCollisionShape(pybullet.GEOM_MESH, vertices=verts.tolist(), indices=tris.ravel().tolist(),
                                            physicsClientId=c)
        self.hall_body = pybullet.createMultiBody(0.0, col, -1, (0, 0, 0), physicsClientId=c)

    def add_robot(self, robot):
        """A kinematic body (visual + collision box) for `robot`, so other robots see it."""
        spec = robot.spec
        c = self.client
        col = pybullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=spec.body_half_extents_m, physicsClientId=c)
        vis = pybullet.createVisualShape(pybullet.GEOM_BOX, halfExtents=spec.body_half_extents_m,
                                         rgbaColor=tuple(spec.rgb) + (1.0,), physicsClientId=c)
        body = pybullet.createMultiBody(0.0, col, vis, (robot.x, robot.y, robot.z + spec.body_center_z_m),
                                        _quaternion_z(robot.yaw), physicsClientId=c)
        self.robot_bodies[robot.name] = body
        return body

    def sync_robot(self, robot):
        pybullet.resetBasePositionAndOrientation(self.robot_bodies[robot.name],
                                                 (robot.x, robot.y, robot.z + robot.spec.body_center_z_m),
                                                 _quaternion_z(robot.yaw), physicsClientId=self.client)

    def render(self, width, height, view_matrix, projection_matrix):
        """(rgba uint8 H x W x 4, OpenGL depth buffer float32 H x W)."""
        _, _, rgba, depth, _ = pybullet.getCameraImage(
            width, height, view_matrix, projection_matrix, renderer=self._bullet_renderer,
            flags=pybullet.ER_NO_SEGMENTATION_MASK, shadow=0, physicsClientId=self.client)
        rgba = np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)
        depth = np.asarray(depth, dtype=np.float32).reshape(height, width)
        return rgba, depth

    def cast_rays(self, origins, ends):
        """Hit fractions (N,), hit positions (N, 3), hit normals (N, 3), body ids (N,) (-1 = miss).

        Batches stay within PyBullet's limit. Positions are interpolated from the fractions, as
        Bullet computes them, rather than converted from its tuples (a third of the scan's cost);
        a miss's position and normal mean nothing, so use the id.
        """
        n = len(origins)
        ids = np.empty(n, dtype=np.int64)
        fractions = np.empty(n)
        normals = np.empty((n, 3))
        for start in range(0, n, MAX_RAYS_PER_BATCH):
            stop = min(start + MAX_RAYS_PER_BATCH, n)
            results = pybullet.rayTestBatch(origins[start:stop], ends[start:stop], physicsClientId=self.client)
            if len(results) != stop - start:
                raise RuntimeError(f"rayTestBatch returned {len(results)} results for {stop - start} rays")
            batch_ids, _, batch_fractions, _, batch_normals = zip(*results)
            ids[start:stop] = np.fromiter(batch_ids, dtype=np.int64, count=stop - start)
            fractions[start:stop] = np.fromiter(batch_fractions, dtype=np.float64, count=stop - start)
            normals[start:stop] = batch_normals
        positions = origins + fractions[:, None] * (ends - origins)
        return fractions, positions, normals, ids

    def close(self):
        if self.client is not None and pybullet.isConnected(self.client):
            if self._egl_plugin is not None:
                pybullet.unloadPlugin(self._egl_plugin, physicsClientId=self.client)
            pybullet.disconnect(self.client)
        self.client = None
