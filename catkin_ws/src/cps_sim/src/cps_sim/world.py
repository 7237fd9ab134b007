"""The PyBullet world: the hall, the robots' bodies, rendering and ray casting (no rospy).

One DIRECT-mode client holds the whole fleet: one static triangle mesh of the hall and the
robots as kinematic bodies moved to their integrated pose. The sensors see that scene through
one of the renderers in RENDERERS: 'fast' (cps_sim.fast_sensors: OpenGL rasterization on a
headless EGL context and Embree ray casting of the same hall and robot boxes) or PyBullet's own
('egl' plugin, 'tiny' TinyRenderer, each with rayTestBatch; those need coloured visual bodies
of the hall too).
"""

import logging
import math
import pkgutil

import numpy as np
import pybullet

from cps_sim import fast_sensors
from cps_sim.geometry import merged_mesh
from cps_sim.renderers import DEFAULT_RENDERER, RENDERERS  # noqa: F401 (re-exported)

log = logging.getLogger(__name__)
# Below this many pixels per frame TinyRenderer costs less CPU than the EGL plugin on llvmpipe:
# EGL pays ~60 ms per frame whatever the size (a fixed 2560x2048 window and a shadow-map pass),
# TinyRenderer ~0.5 us per pixel (measured in docs/benchmarks/sim.md).
AUTO_TINY_MAX_PIXELS = 170_000


def resolve_renderer(requested, width, height):
    """'fast', 'egl' or 'tiny' for a requested renderer; 'auto' picks the cheaper PyBullet one for
    the frame size."""
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

    def __init__(self, site, renderer=DEFAULT_RENDERER, fallback_renderer="tiny"):
        """`fallback_renderer` ('egl' or 'tiny') is used, with a logged reason in
        `fallback_reason`, when 'fast' cannot run here (no EGL context, no Embree)."""
        if renderer not in ("fast", "egl", "tiny") or fallback_renderer not in ("egl", "tiny"):
            raise ValueError(
                f"unknown renderer '{renderer}' or fallback '{fallback_renderer}' "
                f"(known: fast, egl, tiny; resolve 'auto' first)"
            )
        self.site = site
        self._prims = site.primitives()
        self._hall_triangles, self._hall_rgba = fast_sensors.hall_triangles(self._prims)
        self.fallback_reason = None
        self._rasterizer = None
        self._ray_caster = None
        self._robot_boxes = {}
        if renderer == "fast":
            try:
                self._ray_caster = fast_sensors.EmbreeRayCaster(self._hall_triangles)
                self._rasterizer = fast_sensors.GlRasterizer(self._hall_triangles, self._hall_rgba)
            except fast_sensors.RendererUnavailable as exc:
                self._ray_caster = None
                self.fallback_reason = str(exc)
                log.warning(
                    "fast renderer unavailable: %s; using PyBullet's '%s' renderer (slower)", exc, fallback_renderer
                )
                renderer = fallback_renderer
        self.client = pybullet.connect(pybullet.DIRECT)
        self.renderer = "tiny"
        self._egl_plugin = None
        if renderer == "fast":
            self.renderer = "fast"
        elif renderer == "egl":
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
        self._bullet_renderer = (
            pybullet.ER_BULLET_HARDWARE_OPENGL if self.renderer == "egl" else pybullet.ER_TINY_RENDERER
        )
        pybullet.configureDebugVisualizer(pybullet.COV_ENABLE_SHADOWS, 0, physicsClientId=self.client)
        self.hall_body = None
        self.visual_bodies = []
        self.robot_bodies = {}
        self._build_site()

    def _build_site(self):
        c = self.client
        prims = self._prims
        if self.renderer == "fast":
            prims = ()  # the rasterizer draws the hall from its own copy of the mesh
        for prim in prims:
            if prim.kind == "box":
                vis = pybullet.createVisualShape(
                    pybullet.GEOM_BOX, halfExtents=prim.half_extents, rgbaColor=prim.rgba, physicsClientId=c
                )
                orn = _quaternion_z(prim.yaw_rad)
            else:
                vis = pybullet.createVisualShape(
                    pybullet.GEOM_CYLINDER,
                    radius=prim.radius,
                    length=2 * prim.half_length,
                    rgbaColor=prim.rgba,
                    physicsClientId=c,
                )
                orn = _quaternion_z(prim.yaw_rad)
                if prim.axis == "x":
                    orn = pybullet.multiplyTransforms(
                        (0, 0, 0), orn, (0, 0, 0), pybullet.getQuaternionFromEuler((0.0, math.pi / 2, 0.0))
                    )[1]
            body = pybullet.createMultiBody(0.0, -1, vis, prim.center, orn, physicsClientId=c)
            self.visual_bodies.append(body)
        verts, tris = merged_mesh(self._prims)
        col = pybullet.createCollisionShape(
            pybullet.GEOM_MESH, vertices=verts.tolist(), indices=tris.ravel().tolist(), physicsClientId=c
        )
        self.hall_body = pybullet.createMultiBody(0.0, col, -1, (0, 0, 0), physicsClientId=c)
        if self._ray_caster is not None:
            self._ray_caster.hall_body_id = self.hall_body

    def add_robot(self, robot):
        """A kinematic body (visual + collision box) for `robot`, so other robots see it."""
        spec, body_box = robot.spec, robot.robot_type.body
        c = self.client
        col = pybullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=body_box.half_extents_m, physicsClientId=c)
        vis = pybullet.createVisualShape(
            pybullet.GEOM_BOX,
            halfExtents=body_box.half_extents_m,
            rgbaColor=tuple(spec.rgb) + (1.0,),
            physicsClientId=c,
        )
        body = pybullet.createMultiBody(
            0.0,
            col,
            vis,
            (robot.x, robot.y, robot.z + body_box.center_z_m),
            _quaternion_z(robot.yaw),
            physicsClientId=c,
        )
        self.robot_bodies[robot.name] = body
        self._robot_boxes[robot.name] = fast_sensors.BoxBody(
            body,
            tuple(body_box.half_extents_m),
            (robot.x, robot.y, robot.z + body_box.center_z_m),
            robot.yaw,
            tuple(spec.rgb),
        )
        return body

    def sync_robot(self, robot):
        center = (robot.x, robot.y, robot.z + robot.robot_type.body.center_z_m)
        pybullet.resetBasePositionAndOrientation(
            self.robot_bodies[robot.name], center, _quaternion_z(robot.yaw), physicsClientId=self.client
        )
        box = self._robot_boxes[robot.name]
        box.center_m, box.yaw_rad = center, robot.yaw

    def render(self, width, height, view_matrix, projection_matrix):
        """(rgba uint8 H x W x 4, OpenGL depth buffer float32 H x W), row 0 = top of the image."""
        if self._rasterizer is not None:
            return self._rasterizer.render(
                width, height, view_matrix, projection_matrix, list(self._robot_boxes.values())
            )
        _, _, rgba, depth, _ = pybullet.getCameraImage(
            width,
            height,
            view_matrix,
            projection_matrix,
            renderer=self._bullet_renderer,
            flags=pybullet.ER_NO_SEGMENTATION_MASK,
            shadow=0,
            physicsClientId=self.client,
        )
        rgba = np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)
        depth = np.asarray(depth, dtype=np.float32).reshape(height, width)
        return rgba, depth

    def render_colour(self, width, height, view_matrix, projection_matrix):
        """The colour image alone (rgb uint8 H x W x 3, row 0 = top): the fast renderer reads no
        depth back; PyBullet's renderers always produce both."""
        if self._rasterizer is not None:
            return self._rasterizer.render_colour(
                width, height, view_matrix, projection_matrix, list(self._robot_boxes.values())
            )
        rgba, _ = self.render(width, height, view_matrix, projection_matrix)
        return np.ascontiguousarray(rgba[..., :3])

    def cast_rays(self, origins, ends):
        """Hit fractions (N,), hit positions (N, 3), hit normals (N, 3), body ids (N,) (-1 = miss).

        Batches stay within PyBullet's limit. Positions are interpolated from the fractions, as
        Bullet computes them, rather than converted from its tuples (a third of the scan's cost);
        a miss's position and normal mean nothing, so use the id.
        """
        if self._ray_caster is not None:
            return self._ray_caster.cast(origins, ends, list(self._robot_boxes.values()))
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
        if self._rasterizer is not None:
            self._rasterizer.close()
            self._rasterizer = None
        if self.client is not None and pybullet.isConnected(self.client):
            if self._egl_plugin is not None:
                pybullet.unloadPlugin(self._egl_plugin, physicsClientId=self.client)
            pybullet.disconnect(self.client)
        self.client = None
