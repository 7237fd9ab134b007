"""Triangle meshes and surface samples of the site's primitives (numpy only).

The lidar casts its rays against one static triangle mesh of the whole hall: Bullet's BVH
triangle mesh answers ~30 000 rays in tens of ms, where the same hall built from convex
cylinders takes over a second. The ground truth samples the same primitives' surfaces.
"""

import math

import numpy as np

CYLINDER_SEGMENTS = 32


def _rotation_z(yaw):
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _cylinder_local_to_z(prim):
    """Rotation taking a local cylinder along z to the primitive's axis (before yaw)."""
    if prim.axis == "z":
        return np.eye(3)
    return np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # z -> x


def _place(prim, local):
    rot = _rotation_z(prim.yaw_rad)
    if prim.kind == "cylinder":
        rot = rot @ _cylinder_local_to_z(prim)
    return local @ rot.T + np.asarray(prim.center)


def primitive_mesh(prim, segments=CYLINDER_SEGMENTS):
    """(vertices (V, 3), triangle indices (T, 3)) of a primitive, in `map`."""
    if prim.kind == "box":
        hx, hy, hz = prim.half_extents
        corners = np.array([[sx * hx, sy * hy, sz * hz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        faces = np.array(
            [
                [0, 1, 3],
                [0, 3, 2],
                [4, 6, 7],
                [4, 7, 5],  # x- , x+
                [0, 4, 5],
                [0, 5, 1],
                [2, 3, 7],
                [2, 7, 6],  # y- , y+
                [0, 2, 6],
                [0, 6, 4],
                [1, 5, 7],
                [1, 7, 3],  # z- , z+
            ]
        )
        return _place(prim, corners), faces
    angles = np.linspace(0.0, 2 * math.pi, segments, endpoint=False)
    # Vertices on the circumscribed polygon would bulge; use a polygon whose edge midpoints and
    # vertices straddle the true radius so the mean radial error is ~0.
    r = prim.radius / math.cos(math.pi / segments) ** 0.5
    ring = np.stack([r * np.cos(angles), r * np.sin(angles)], axis=1)
    h = prim.half_length
    bottom = np.hstack([ring, np.full((segments, 1), -h)])
    top = np.hstack([ring, np.full((segments, 1), h)])
    centers = np.array([[0.0, 0.0, -h], [0.0, 0.0, h]])
    verts = np.vstack([bottom, top, centers])
    k = np.arange(segments)
    k1 = (k + 1) % segments
    side = np.concatenate([np.stack([k, k1, k + segments], 1), np.stack([k1, k1 + segments, k + segments], 1)])
    caps = np.concatenate(
        [
            np.stack([np.full(segments, 2 * segments), k1, k], 1),
            np.stack([np.full(segments, 2 * segments + 1), k + segments, k1 + segments], 1),
        ]
    )
    return _place(prim, verts), np.concatenate([side, caps])


def merged_mesh(primitives, segments=CYLINDER_SEGMENTS):
    """One (vertices, indices) mesh of all primitives."""
    verts, tris, offset = [], [], 0
    for prim in primitives:
        v, t = primitive_mesh(prim, segments)
        verts.append(v)
        tris.append(t + offset)
        offset += len(v)
    return np.vstack(verts), np.vstack(tris)


def surface_points(prim, spacing_m, inset_m=1e-6):
    """Points on the primitive's surface about `spacing_m` apart, moved `inset_m` inwards.

    The inset puts a face lying exactly on a voxel boundary into the voxel inside the solid.
    """
    if prim.kind == "box":
        half = np.asarray(prim.half_extents, dtype=float)
        pts = []
        for axis in range(3):
            others = [a for a in range(3) if a != axis]
            grids = [
                np.linspace(-half[a], half[a], max(int(math.ceil(2 * half[a] / spacing_m)) + 1, 2)) for a in others
            ]
            g0, g1 = np.meshgrid(*grids, indexing="ij")
            for sign in (-1.0, 1.0):
                face = np.zeros((g0.size, 3))
                face[:, others[0]] = g0.ravel()
                face[:, others[1]] = g1.ravel()
                face[:, axis] = sign * (half[axis] - inset_m)
                pts.append(face)
        local = np.vstack(pts)
        local = np.clip(local, -(half - inset_m), half - inset_m)
        return local @ _rotation_z(prim.yaw_rad).T + np.asarray(prim.center)
    r, h = prim.radius - inset_m, prim.half_length
    n_around = max(int(math.ceil(2 * math.pi * r / spacing_m)), 8)
    n_along = max(int(math.ceil(2 * h / spacing_m)) + 1, 2)
    a = np.linspace(0.0, 2 * math.pi, n_around, endpoint=False)
    z = np.linspace(-h + inset_m, h - inset_m, n_along)
    aa, zz = np.meshgrid(a, z, indexing="ij")
    side = np.stack([r * np.cos(aa).ravel(), r * np.sin(aa).ravel(), zz.ravel()], axis=1)
    g = np.arange(-r, r + spacing_m, spacing_m)
    gx, gy = np.meshgrid(g, g, indexing="ij")
    inside = gx**2 + gy**2 <= r**2
    disk = np.stack([gx[inside], gy[inside]], axis=1)
    caps = [np.hstack([disk, np.full((len(disk), 1), sign * (h - inset_m))]) for sign in (-1.0, 1.0)]
    local = np.vstack([side] + caps)
    return _place(prim, local)
