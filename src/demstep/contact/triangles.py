"""Sphere-triangle contact geometry: the closest point of a triangle to a sphere's centre,
and which feature of the triangle (its face, an edge, a vertex) holds it.

The closest point follows the Voronoi regions of the triangle (Ericson, Real-Time
Collision Detection, 5.1.5): the centre's barycentric position decides whether the
point lies at a vertex, on an edge or inside the face. A sphere of radius r centred at
c touches the triangle when |c - p| < r: overlap r - |c - p|, unit normal (c - p) / |c -
p| from the triangle towards the sphere.

Features are numbered per triangle: 0 the face, 1-3 the edges (v0v1, v1v2, v2v0), 4-6 the
vertices (v0, v1, v2).
"""

from __future__ import annotations

import math

from demstep._numba import njit

FACE = 0
EDGES = (1, 2, 3)
VERTICES = (4, 5, 6)


@njit(inline="always")
def closest_point_on_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """The point of triangle (a, b, c) closest to p [L], and its feature (module
    docstring): (qx, qy, qz, feature). Scalars only (inlined in the contact loops)."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az, 4  # vertex a
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz, 5  # vertex b
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        t = d1 / (d1 - d3)
        return ax + t * abx, ay + t * aby, az + t * abz, 1  # edge ab
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz, 6  # vertex c
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        t = d2 / (d2 - d6)
        return ax + t * acx, ay + t * acy, az + t * acz, 3  # edge ca
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return bx + t * (cx - bx), by + t * (cy - by), bz + t * (cz - bz), 2  # edge bc
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w, 0


@njit(inline="always")
def triangle_contact(px, py, pz, radius, ax, ay, az, bx, by, bz, cx, cy, cz):
    """The contact of a sphere (centre p, ``radius`` [L]) with triangle (a, b, c): its
    overlap r - |p - q| [L] (<= 0: apart), unit normal (p - q) / |p - q| from the
    triangle towards the sphere, the distance |p - q| [L], the closest point q and its
    feature. A centre on the triangle itself (distance 0) takes the face normal."""
    qx, qy, qz, feature = closest_point_on_triangle(px, py, pz, ax, ay, az, bx, by, bz,
                                                    cx, cy, cz)
    dx, dy, dz = px - qx, py - qy, pz - qz
    dist = math.sqrt(dx * dx + dy * dy + dz * dz)
    if dist > 0.0:
        inv = 1.0 / dist
        nx, ny, nz = dx * inv, dy * inv, dz * inv
    else:
        ux, uy, uz = bx - ax, by - ay, bz - az
        vx, vy, vz = cx - ax, cy - ay, cz - az
        nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        inv = 1.0 / math.sqrt(nx * nx + ny * ny + nz * nz)
        nx, ny, nz = nx * inv, ny * inv, nz * inv
    return radius - dist, nx, ny, nz, dist, qx, qy, qz, feature
