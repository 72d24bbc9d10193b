"""Small triangle meshes built in code (for tests, examples and simple walls). All
lengths [L]; closed shapes have outward normals, and the hopper's face the axis.

* :func:`square`: a flat square of 2 triangles in z = 0, normals +z;
* :func:`plane`: a flat square tessellated into n x n squares (2 n^2 triangles);
* :func:`cube`: a closed cube of 12 triangles;
* :func:`pyramid`: a closed square pyramid of 6 triangles;
* :func:`cylinder`: a tube of n facets (2 n triangles), closed by two caps on demand;
* :func:`hopper`: an open frustum (outlet below, wide top) with normals facing the axis.
"""

from __future__ import annotations

import numpy as np

from demstep.mesh.surface import TriangleMesh


def plane(n: int = 1, size: float = 1.0, name: str = "plane") -> TriangleMesh:
    """The square [-size/2, size/2]^2 in z = 0 cut into n x n squares of two triangles
    each; normals +z; (n + 1)^2 vertices, 2 n^2 triangles."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    s = np.linspace(-0.5 * size, 0.5 * size, n + 1)
    x, y = np.meshgrid(s, s, indexing="ij")
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()  # corner (i, j); (i + 1, j) is a + n + 1
    b, c, d = a + n + 1, a + n + 2, a + 1
    triangles = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return TriangleMesh(vertices, triangles, name)


def square(size: float = 1.0, name: str = "square") -> TriangleMesh:
    """A flat square of side ``size`` in z = 0, centred on the origin: 2 triangles,
    normals +z."""
    return plane(1, size, name)


def cube(size: float = 1.0, name: str = "cube") -> TriangleMesh:
    """The cube [-size/2, size/2]^3: 8 vertices, 12 triangles, outward normals."""
    bits = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=np.float64)
    vertices = (bits - 0.5) * size  # vertex 4 x + 2 y + z
    faces = np.array([[1, 5, 7, 3], [0, 2, 6, 4],   # +z, -z
                      [4, 6, 7, 5], [0, 1, 3, 2],   # +x, -x
                      [2, 3, 7, 6], [0, 4, 5, 1]])  # +y, -y (counter-clockwise seen from outside)
    triangles = np.concatenate([faces[:, [0, 1, 2]], faces[:, [0, 2, 3]]])
    return TriangleMesh(vertices, triangles, name)


def pyramid(base: float = 1.0, height: float = 1.0, name: str = "pyramid") -> TriangleMesh:
    """A square pyramid: base of side ``base`` in z = 0 centred on the origin, apex at
    (0, 0, height); 5 vertices, 6 triangles, outward normals."""
    a = 0.5 * base
    vertices = np.array([[-a, -a, 0], [a, -a, 0], [a, a, 0], [-a, a, 0], [0, 0, height]],
                        dtype=np.float64)
    triangles = np.array([[0, 2, 1], [0, 3, 2],
                          [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    return TriangleMesh(vertices, triangles, name)


def _frustum(n: int, r0: float, r1: float, z0: float, z1: float):
    """Vertices (ring at z0 of radius r0, then ring at z1 of radius r1; corners at
    angles 2 pi (k + 1/2) / n) and the 2 n side triangles, normals away from the axis."""
    if n < 3:
        raise ValueError(f"n must be >= 3, got {n}")
    theta = 2 * np.pi * (np.arange(n) + 0.5) / n
    ring = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    vertices = np.concatenate([np.column_stack([r0 * ring, np.full(n, z0)]),
                               np.column_stack([r1 * ring, np.full(n, z1)])])
    k = np.arange(n)
    a, b, c, d = k, (k + 1) % n, (k + 1) % n + n, k + n
    triangles = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return vertices, triangles


def cylinder(n: int = 16, radius: float = 1.0, height: float = 1.0, caps: bool = False,
             name: str = "cylinder") -> TriangleMesh:
    """A prism of n side facets around the z axis from z = 0 to ``height``, its corners
    on the circle of ``radius``: 2 n triangles (open tube), plus n per cap with
    ``caps`` (closed). Normals outward (:meth:`TriangleMesh.flipped` for a drum)."""
    vertices, triangles = _frustum(n, radius, radius, 0.0, height)
    if caps:
        k = np.arange(n)
        centres = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, height]])
        c0, c1 = 2 * n, 2 * n + 1
        bottom = np.stack([np.full(n, c0), (k + 1) % n, k], 1)
        top = np.stack([np.full(n, c1), k + n, (k + 1) % n + n], 1)
        vertices = np.concatenate([vertices, centres])
        triangles = np.concatenate([triangles, bottom, top])
    return TriangleMesh(vertices, triangles, name)


def hopper(n: int = 4, outlet_radius: float = 0.25, top_radius: float = 1.0,
           height: float = 1.0, name: str = "hopper") -> TriangleMesh:
    """An open frustum of n facets around the z axis: the outlet (corners on the circle
    of ``outlet_radius``) in z = 0, the top (``top_radius``) in z = ``height``; 2 n
    triangles, normals facing the axis (the particles' side). n = 4: a square
    hopper."""
    vertices, triangles = _frustum(n, outlet_radius, top_radius, 0.0, height)
    return TriangleMesh(vertices, triangles[:, [0, 2, 1]], name)
