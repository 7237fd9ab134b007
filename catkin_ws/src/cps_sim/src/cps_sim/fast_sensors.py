"""Fast sensor rendering of the SimWorld's scene (numpy, moderngl, embreex; no pybullet, no rospy).

PyBullet's EGL plugin renders a fixed 2560x2048 window with a shadow pass per frame and its
rayTestBatch costs ~2 us per ray, so on llvmpipe a 640x480 frame costs ~130 ms and a 30 000-ray
scan ~110-160 ms. Here the static hall is uploaded once: cameras rasterize it with OpenGL 3.3
(moderngl on a headless EGL context) and the lidar casts rays against it with Intel Embree; the
robots' boxes are the only things that move, drawn with a per-frame model matrix and
intersected analytically per scan. Outputs are what SimWorld.render / cast_rays return.
"""

import dataclasses
import math
from typing import Sequence, Tuple

import numpy as np

from cps_sim.geometry import primitive_mesh

# Triangles with less area than this (m^2) are dropped: they render nothing and only make
# Embree's BVH build and the normals ill-defined.
MIN_TRIANGLE_AREA_M2 = 1e-10
# Lambert shading towards a light above and to the side; ambient keeps faces away from it visible.
LIGHT_DIRECTION = (0.35, 0.25, 0.9)
AMBIENT_FRACTION = 0.45
SKY_RGB = (0.70, 0.73, 0.80)


class RendererUnavailable(RuntimeError):
    """The fast renderer cannot run on this machine (no EGL / GL 3.3 context, no Embree)."""


class EmptyMeshError(ValueError):
    """The site has no triangle with a non-zero area: there is nothing to render."""


@dataclasses.dataclass
class BoxBody:
    """A robot's body box: PyBullet body id, half extents (m), centre in map (m), yaw (rad), rgb 0-1."""

    body_id: int
    half_extents_m: Tuple[float, float, float]
    center_m: Tuple[float, float, float]
    yaw_rad: float
    rgb: Tuple[float, float, float]

    def rotation(self):
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def model_matrix(self):
        """4x4 taking the unit cube [-1, 1]^3 to the box in map."""
        model = np.eye(4)
        model[:3, :3] = self.rotation() * np.asarray(self.half_extents_m)
        model[:3, 3] = self.center_m
        return model


def hall_triangles(primitives):
    """(triangles (T, 3, 3) float64 in map, rgba (T, 4) float) of the site; degenerate ones dropped.

    Raises EmptyMeshError when no triangle with an area is left.
    """
    triangles, colours, given = [], [], 0
    for prim in primitives:
        verts, faces = primitive_mesh(prim)
        tris = verts[faces]
        given += len(tris)
        area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
        tris = tris[area > MIN_TRIANGLE_AREA_M2]
        triangles.append(tris)
        colours.append(np.broadcast_to(np.asarray(prim.rgba, dtype=float), (len(tris), 4)))
    if not triangles or sum(len(t) for t in triangles) == 0:
        raise EmptyMeshError(
            f"the site mesh has no triangle with a non-zero area ({len(primitives)} primitives, "
            f"{given} triangles given): nothing to render or ray-cast"
        )
    return np.concatenate(triangles), np.concatenate(colours)


def _face_normals(triangles):
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _unit_cube_triangles():
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    faces = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
        ]
    )
    return corners[faces]


def _vertex_buffer(triangles, rgba):
    """Interleaved float32 per vertex: position (3), face normal (3), rgba (4)."""
    normals = np.repeat(_face_normals(triangles)[:, None, :], 3, axis=1)
    colours = np.repeat(np.asarray(rgba, dtype=float)[:, None, :], 3, axis=1)
    return np.concatenate([triangles, normals, colours], axis=2).astype("f4").reshape(-1, 10)


_VERTEX_SHADER = """
#version 330
uniform mat4 view_projection;
uniform mat4 model;
uniform vec4 tint;
uniform vec3 light_direction;
uniform float ambient;
in vec3 in_position;
in vec3 in_normal;
in vec4 in_rgba;
out vec4 rgba;
void main() {
    gl_Position = view_projection * model * vec4(in_position, 1.0);
    vec3 normal = normalize(mat3(model) * in_normal);
    float lambert = abs(dot(normal, light_direction));
    rgba = vec4(in_rgba.rgb * tint.rgb * (ambient + (1.0 - ambient) * lambert), 1.0);
}
"""

_FRAGMENT_SHADER = """
#version 330
in vec4 rgba;
out vec4 colour;
void main() { colour = rgba; }
"""


def create_egl_context():
    """A headless OpenGL >= 3.3 context on EGL; RendererUnavailable with the reason otherwise."""
    try:
        import moderngl
    except ImportError as exc:
        raise RendererUnavailable(f"moderngl is not installed ({exc})") from exc
    try:
        ctx = moderngl.create_standalone_context(backend="egl")
    except Exception as exc:  # moderngl/glcontext raise plain Exceptions for a missing EGL
        raise RendererUnavailable(f"no headless EGL OpenGL context ({type(exc).__name__}: {exc})") from exc
    if ctx.version_code < 330:
        ctx.release()
        raise RendererUnavailable(f"EGL gives OpenGL {ctx.version_code}, need 330")
    return ctx


class GlRasterizer:
    """Colour + depth frames of the hall and the robots' boxes by OpenGL rasterization."""

    def __init__(self, triangles, rgba):
        self.ctx = create_egl_context()
        ctx = self.ctx
        self.program = ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        light = np.asarray(LIGHT_DIRECTION, dtype=float)
        self.program["light_direction"].value = tuple(light / np.linalg.norm(light))
        self.program["ambient"].value = AMBIENT_FRACTION
        layout = ("3f 3f 4f", "in_position", "in_normal", "in_rgba")
        self._hall_buffer = ctx.buffer(_vertex_buffer(triangles, rgba).tobytes())
        self.hall = ctx.vertex_array(self.program, [(self._hall_buffer, *layout)])
        cube = _unit_cube_triangles()
        self._cube_buffer = ctx.buffer(_vertex_buffer(cube, np.ones((len(cube), 4))).tobytes())
        self.cube = ctx.vertex_array(self.program, [(self._cube_buffer, *layout)])
        self._identity = np.eye(4, dtype="f4").tobytes(order="F")
        self._framebuffers = {}

    def _framebuffer(self, width, height):
        fbo = self._framebuffers.get((width, height))
        if fbo is None:
            fbo = self.ctx.framebuffer(
                color_attachments=[self.ctx.renderbuffer((width, height), 4)],
                depth_attachment=self.ctx.depth_renderbuffer((width, height)),
            )
            self._framebuffers[(width, height)] = fbo
        return fbo

    def _draw(self, width, height, view_matrix, projection_matrix, boxes):
        """Rasterize into the (width, height) framebuffer; the caller holds the context."""
        view = np.asarray(view_matrix, dtype=np.float64).reshape(4, 4).T
        projection = np.asarray(projection_matrix, dtype=np.float64).reshape(4, 4).T
        fbo = self._framebuffer(width, height)
        fbo.use()
        ctx = self.ctx
        ctx.viewport = (0, 0, width, height)
        ctx.enable(ctx.DEPTH_TEST)
        ctx.disable(ctx.CULL_FACE)
        fbo.clear(*SKY_RGB, 1.0, depth=1.0)
        self.program["view_projection"].write((projection @ view).astype("f4").tobytes(order="F"))
        self.program["model"].write(self._identity)
        self.program["tint"].value = (1.0, 1.0, 1.0, 1.0)
        self.hall.render()
        for box in boxes:
            self.program["model"].write(box.model_matrix().astype("f4").tobytes(order="F"))
            self.program["tint"].value = (*box.rgb, 1.0)
            self.cube.render()
        return fbo

    def render_colour(self, width, height, view_matrix, projection_matrix, boxes: Sequence[BoxBody] = ()):
        """The colour image only (rgb uint8 H x W x 3, row 0 = top): no depth read back (video)."""
        with self.ctx:
            fbo = self._draw(width, height, view_matrix, projection_matrix, boxes)
            rgb = np.frombuffer(fbo.read(components=3, alignment=1), dtype=np.uint8).reshape(height, width, 3)
        return np.ascontiguousarray(rgb[::-1])

    def render(self, width, height, view_matrix, projection_matrix, boxes: Sequence[BoxBody] = ()):
        """(rgba uint8 H x W x 4, depth buffer float32 H x W in [0, 1]), row 0 = top of the image.

        view_matrix and projection_matrix are 16 floats in OpenGL's column-major order, as
        pybullet.computeViewMatrix / computeProjectionMatrixFOV return them.
        """
        # Another GL user in this process (PyBullet's EGL plugin) may have made its context current.
        with self.ctx:
            fbo = self._draw(width, height, view_matrix, projection_matrix, boxes)
            rgba = np.frombuffer(fbo.read(components=4, alignment=1), dtype=np.uint8).reshape(height, width, 4)
            depth = np.frombuffer(
                fbo.read(components=1, attachment=-1, alignment=1, dtype="f4"), dtype=np.float32
            ).reshape(height, width)
        # GL's first row is the bottom of the image; PyBullet's (and the camera's) is the top.
        return np.ascontiguousarray(rgba[::-1]), np.ascontiguousarray(depth[::-1])

    def close(self):
        if self.ctx is not None:
            self.ctx.release()
            self.ctx = None


class EmbreeRayCaster:
    """Nearest hits of line segments with the hall (a static Embree scene built once) and the
    robots' boxes (a small Embree scene rebuilt per call, ~0.1 ms)."""

    def __init__(self, triangles, hall_body_id=-1):
        """`hall_body_id` is the id a hit on the hall reports (the PyBullet body of the hall mesh)."""
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
        except ImportError as exc:
            raise RendererUnavailable(f"embreex is not installed ({exc})") from exc
        self._new_scene, self._mesh = rtcore_scene.EmbreeScene, TriangleMesh
        self.hall_body_id = int(hall_body_id)
        self.scene = self._new_scene()
        self._hall_mesh = TriangleMesh(self.scene, np.ascontiguousarray(triangles, dtype=np.float32))
        self._cube = _unit_cube_triangles()

    def _query(self, scene, origins32, segments32):
        """(hit mask, fraction, geometric normal (not unit), primitive index) per ray."""
        n = len(origins32)
        hits = scene.run(origins32, segments32, dists=np.ones(n, dtype=np.float32), output=1)
        return hits["geomID"] >= 0, hits["tfar"], hits["Ng"], hits["primID"]

    def cast(self, origins, ends, boxes: Sequence[BoxBody] = ()):
        """(fractions (N,), positions (N, 3), normals (N, 3), body ids (N,), -1 = miss), as
        SimWorld.cast_rays: fraction 1 for a miss (its position and normal mean nothing).

        A box hit from inside (a ray starting in a robot's body) is not a hit, as in Bullet's ray
        test of a convex shape.
        """
        origins = np.asarray(origins, dtype=np.float64)
        segments = np.asarray(ends, dtype=np.float64) - origins
        n = len(origins)
        if n == 0:
            return np.ones(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
        origins32 = np.ascontiguousarray(origins, dtype=np.float32)
        segments32 = np.ascontiguousarray(segments, dtype=np.float32)
        hit, fractions, normals, _ = self._query(self.scene, origins32, segments32)
        ids = np.where(hit, self.hall_body_id, -1).astype(np.int64)
        fractions = np.where(hit, fractions, np.float32(1.0)).astype(np.float64)
        if boxes:
            scene = self._new_scene()
            box_triangles = np.concatenate(
                [self._cube @ box.model_matrix()[:3, :3].T + box.model_matrix()[:3, 3] for box in boxes]
            )
            self._mesh(scene, np.ascontiguousarray(box_triangles, dtype=np.float32))
            box_hit, box_fractions, box_normals, prim = self._query(scene, origins32, segments32)
            rays = np.nonzero(box_hit & (box_fractions < fractions))[0]
            rays = rays[np.einsum("ij,ij->i", box_normals[rays], segments32[rays]) < 0.0]  # entering only
            body_ids = np.array([box.body_id for box in boxes])
            ids[rays] = body_ids[prim[rays] // len(self._cube)]
            fractions[rays] = box_fractions[rays]
            normals[rays] = box_normals[rays]
        length = np.sqrt(np.einsum("ij,ij->i", normals, normals))
        normals = normals.astype(np.float64) / np.maximum(length, np.float32(1e-30))[:, None]
        positions = origins + fractions[:, None] * segments
        return fractions, positions, normals, ids.astype(np.int64)
