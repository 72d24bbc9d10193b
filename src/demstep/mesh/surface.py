"""Triangle meshes for mesh walls: the mesh, its edges and their convexity, and the
checks and repairs every mesh goes through before a simulation sees it.

:class:`TriangleMesh` holds ``vertices`` (V, 3) float64 [L] and ``triangles`` (T, 3)
int64 (vertex indices, counter-clockwise seen from the side the normal points to:
the right-hand rule). Everything else is derived from them once, on first use, and
cached (the arrays are read-only):

* per triangle: unit ``normals``, ``areas`` [L^2], ``centroids`` [L];
* per edge (an unordered vertex pair used by at least one triangle): ``edges`` (E, 2)
  (i < j), ``edge_counts`` (how many triangles use it), ``edge_triangles`` (E, 2)
  (the two triangles of a manifold edge; -1 for the missing one of a boundary edge)
  and :meth:`TriangleMesh.edge_incidence` (every triangle of every edge, for
  non-manifold edges);
* per triangle, ``triangle_edges`` (T, 3): the index of its edge k, which joins its
  vertices k and (k + 1) % 3;
* per edge, ``edge_angles`` [rad] and :meth:`TriangleMesh.edge_kinds`
  (:class:`EdgeKind`: flat, convex, concave, boundary, non-manifold, misoriented).

:func:`mesh_from_arrays` builds a mesh from raw arrays (a file's, or code's) with the
checks and repairs of ``docs/meshes.md``; :func:`demstep.mesh.read_mesh` reads a file
through it.
"""

from __future__ import annotations

import enum
import logging
import warnings
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from demstep.errors import MAX_MAGNITUDE, InputError

log = logging.getLogger("demstep")

#: default vertex-merge tolerance, relative to the bounding-box diagonal
MERGE_TOL = 1e-9
#: default degeneracy tolerance: a triangle is degenerate when twice its area is at
#: most this times the square of its longest edge (an aspect ratio above ~1e10)
AREA_TOL = 1e-10
#: default angle [rad] between two triangles' normals below which their edge is flat:
#: 0.256235 deg, acos(0.99999), the default ``curvature`` of LIGGGHTS' fix mesh/surface
FLAT_ANGLE = float(np.arccos(0.99999))

_AXES = "xyz"


class MeshWarning(UserWarning):
    """A mesh was repaired on load (triangles dropped or re-oriented) or has
    non-manifold edges."""


class EdgeKind(enum.IntEnum):
    """What an edge is, seen from the side the normals point to.

    FLAT, CONVEX, CONCAVE: an edge shared by exactly two consistently oriented
    triangles whose normals make an angle at most / above the flat angle, bending away
    from (convex) or towards (concave) the side the normals point to (a cube with
    outward normals has convex edges only). BOUNDARY: used by one triangle (the rim of
    an open surface). NONMANIFOLD: used by three or more triangles. MISORIENTED: two
    triangles traverse it in the same direction (never after :func:`mesh_from_arrays`).
    """

    FLAT = 0
    CONVEX = 1
    CONCAVE = 2
    BOUNDARY = 3
    NONMANIFOLD = 4
    MISORIENTED = 5


@dataclass(frozen=True, eq=False)
class TriangleMesh:
    """A triangle surface: ``vertices`` (V, 3) [L], ``triangles`` (T, 3) vertex indices
    (right-hand rule gives the normal), ``name``.

    The constructor checks shapes, finiteness and index ranges only (one-line
    :class:`~demstep.errors.InputError`); it repairs nothing: build meshes from raw
    data with :func:`mesh_from_arrays` or :func:`~demstep.mesh.read_mesh`. The arrays
    are copied and made read-only, so the derived quantities, computed on first use,
    stay valid.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    name: str = "mesh"

    def __post_init__(self):
        v = np.array(self.vertices, dtype=np.float64)
        t = np.asarray(self.triangles)
        name = self.name
        if v.ndim != 2 or v.shape[1] != 3:
            raise InputError(f"{name}: vertices: expected an (V, 3) array, got shape {v.shape}")
        if t.ndim != 2 or t.shape[1] != 3:
            raise InputError(f"{name}: triangles: expected a (T, 3) array, got shape {t.shape}")
        if t.shape[0] == 0:
            raise InputError(f"{name}: no triangles (an empty mesh)")
        if not np.issubdtype(t.dtype, np.integer):
            raise InputError(f"{name}: triangles: expected integer vertex indices, got "
                             f"{t.dtype}")
        t = t.astype(np.int64)
        bad = np.flatnonzero(~np.isfinite(v).all(axis=1))
        if len(bad):
            axis = int(np.flatnonzero(~np.isfinite(v[bad[0]]))[0])
            value = float(v[bad[0], axis])
            raise InputError(f"{name}: vertex {bad[0]}: {_AXES[axis]} = {value!r}: not finite")
        out = (t < 0) | (t >= len(v))
        if out.any():
            k, c = np.argwhere(out)[0]
            raise InputError(f"{name}: triangle {k}: vertex index {t[k, c]} out of range "
                             f"(0 to {len(v) - 1})")
        v.flags.writeable = False
        t.flags.writeable = False
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "triangles", t)

    # --- sizes --------------------------------------------------------------------

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    @property
    def n_edges(self) -> int:
        return len(self.edges)

    def bounding_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi): the smallest and largest vertex coordinates, each (3,) [L]."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    # --- per triangle -------------------------------------------------------------

    @cached_property
    def corners(self) -> np.ndarray:
        """(T, 3, 3) [L]: the three vertices of every triangle, in order."""
        return _readonly(self.vertices[self.triangles])

    @cached_property
    def _cross(self) -> np.ndarray:
        p = self.corners
        return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])

    @cached_property
    def areas(self) -> np.ndarray:
        """(T,) [L^2]: the triangles' areas."""
        return _readonly(0.5 * np.linalg.norm(self._cross, axis=1))

    @cached_property
    def normals(self) -> np.ndarray:
        """(T, 3): unit normals, (p1 - p0) x (p2 - p0) normalised (right-hand rule);
        NaN for a zero-area triangle (none after :func:`mesh_from_arrays`)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return _readonly(self._cross / (2.0 * self.areas[:, None]))

    @cached_property
    def centroids(self) -> np.ndarray:
        """(T, 3) [L]: the triangles' centroids."""
        return _readonly(self.corners.mean(axis=1))

    # --- edges --------------------------------------------------------------------

    @cached_property
    def _edge_table(self):
        t = self.triangles
        half = t[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)  # half-edge 3 k + c: corner c -> c + 1
        lo, hi = half.min(axis=1), half.max(axis=1)
        keys, inverse, counts = np.unique(lo * np.int64(len(self.vertices)) + hi,
                                          return_inverse=True, return_counts=True)
        n = np.int64(len(self.vertices))
        edges = np.stack([keys // n, keys % n], axis=1)
        order = np.argsort(inverse, kind="stable")  # half-edges grouped by edge
        offsets = np.zeros(len(keys) + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        forward = half[:, 0] < half[:, 1]  # traverses its edge from edges[:, 0] to [:, 1]
        return edges, inverse.reshape(-1, 3), counts.astype(np.int64), offsets, order, forward

    @cached_property
    def edges(self) -> np.ndarray:
        """(E, 2): every edge as its vertex pair (i < j), sorted."""
        return _readonly(self._edge_table[0])

    @cached_property
    def triangle_edges(self) -> np.ndarray:
        """(T, 3): the index (into :attr:`edges`) of each triangle's edge k, the one
        joining its vertices k and (k + 1) % 3."""
        return _readonly(self._edge_table[1])

    @cached_property
    def edge_counts(self) -> np.ndarray:
        """(E,): how many triangles use each edge (1: boundary, 2: manifold, 3 or
        more: non-manifold)."""
        return _readonly(self._edge_table[2])

    def edge_incidence(self) -> tuple[np.ndarray, np.ndarray]:
        """(offsets (E + 1,), triangles): the triangles of edge e are
        ``triangles[offsets[e]:offsets[e + 1]]``, in increasing index (every one,
        also for non-manifold edges)."""
        _, _, _, offsets, order, _ = self._edge_table
        return offsets, _readonly(order // 3)

    @cached_property
    def edge_triangles(self) -> np.ndarray:
        """(E, 2): the two triangles sharing each edge, lower index first; -1 for the
        missing second one of a boundary edge; for a non-manifold edge the two lowest
        (all of them: :meth:`edge_incidence`)."""
        _, _, counts, offsets, order, _ = self._edge_table
        first = order[offsets[:-1]] // 3
        second = np.where(counts >= 2, order[np.minimum(offsets[:-1] + 1, len(order) - 1)] // 3,
                          -1)
        return _readonly(np.stack([first, second], axis=1))

    @cached_property
    def _edge_consistent(self) -> np.ndarray:
        """(E,) bool: an edge of two triangles that traverse it in opposite directions."""
        _, _, counts, offsets, order, forward = self._edge_table
        two = counts == 2
        a = forward[order[offsets[:-1]]]
        b = forward[order[np.minimum(offsets[:-1] + 1, len(order) - 1)]]
        return two & (a != b)

    @cached_property
    def edge_angles(self) -> np.ndarray:
        """(E,) [rad]: the signed angle between the normals of an edge's two
        triangles, in (-pi, pi]: > 0 convex (the surface bends away from the side the
        normals point to: every edge of a cube with outward normals is +pi/2), < 0
        concave, 0 flat. NaN for boundary, non-manifold and misoriented edges.

        With A and B the edge's triangles and e the unit edge direction as A traverses
        it, the angle is atan2((n_A x n_B) . e, n_A . n_B)."""
        edges = self.edges
        _, _, _, offsets, order, forward = self._edge_table
        ok = self._edge_consistent
        angles = np.full(len(edges), np.nan)
        if not ok.any():
            return _readonly(angles)
        ha = order[offsets[:-1][ok]]  # A's half-edge
        a, b = self.edge_triangles[ok].T
        e = self.vertices[edges[ok, 1]] - self.vertices[edges[ok, 0]]
        e = e / np.linalg.norm(e, axis=1)[:, None] * np.where(forward[ha], 1.0, -1.0)[:, None]
        na, nb = self.normals[a], self.normals[b]
        angles[ok] = np.arctan2(np.einsum("ij,ij->i", np.cross(na, nb), e),
                                np.einsum("ij,ij->i", na, nb))
        return _readonly(angles)

    def edge_kinds(self, flat_angle: float = FLAT_ANGLE) -> np.ndarray:
        """(E,) int8 :class:`EdgeKind` values; an edge is flat when the angle between
        its triangles' normals is at most ``flat_angle`` [rad] (default
        :data:`FLAT_ANGLE`, 0.256 deg)."""
        angles = self.edge_angles
        counts = self.edge_counts
        kinds = np.full(len(angles), EdgeKind.MISORIENTED, dtype=np.int8)
        ok = self._edge_consistent
        kinds[ok & (angles > flat_angle)] = EdgeKind.CONVEX
        kinds[ok & (angles < -flat_angle)] = EdgeKind.CONCAVE
        kinds[ok & (np.abs(angles) <= flat_angle)] = EdgeKind.FLAT
        kinds[counts == 1] = EdgeKind.BOUNDARY
        kinds[counts >= 3] = EdgeKind.NONMANIFOLD
        return kinds

    def vertex_triangles(self) -> tuple[np.ndarray, np.ndarray]:
        """(offsets (V + 1,), triangles): the triangles using vertex v are
        ``triangles[offsets[v]:offsets[v + 1]]``, in increasing index."""
        flat = self.triangles.reshape(-1)
        order = np.argsort(flat, kind="stable")
        offsets = np.zeros(len(self.vertices) + 1, dtype=np.int64)
        np.cumsum(np.bincount(flat, minlength=len(self.vertices)), out=offsets[1:])
        return offsets, order // 3

    # --- whole mesh ---------------------------------------------------------------

    @property
    def is_closed(self) -> bool:
        """Every edge is shared by exactly two triangles."""
        return bool(np.all(self.edge_counts == 2))

    def n_parts(self) -> int:
        """The number of parts: sets of triangles connected through shared edges."""
        return _n_parts(self.triangles, self.edge_incidence())

    def flipped(self) -> TriangleMesh:
        """The same surface with every normal reversed (a drum read with outward
        normals, flipped to face the particles inside)."""
        return TriangleMesh(self.vertices, self.triangles[:, [0, 2, 1]], self.name)

    def transformed(self, transforms) -> TriangleMesh:
        """A copy with ``transforms`` (:mod:`demstep.mesh.transforms`: a sequence of
        operations applied in order, or their LIGGGHTS-style text) applied to the
        vertices."""
        from demstep.mesh.transforms import apply_transforms

        return TriangleMesh(apply_transforms(self.vertices, transforms, self.name),
                            self.triangles, self.name)

    def summary(self, flat_angle: float = FLAT_ANGLE) -> str:
        """One line: sizes, bounding box, open or closed, and the edges by kind."""
        lo, hi = self.bounding_box()
        kinds = np.bincount(self.edge_kinds(flat_angle), minlength=len(EdgeKind))
        words = ", ".join(f"{kinds[k]} {k.name.lower().replace('nonmanifold', 'non-manifold')}"
                          for k in EdgeKind if kinds[k] or k <= EdgeKind.BOUNDARY)
        shape = "closed" if self.is_closed else f"open ({kinds[EdgeKind.BOUNDARY]} boundary edges)"
        return (f"{self.name}: {self.n_triangles} triangles, {self.n_vertices} vertices, "
                f"{self.n_parts()} part(s), {shape}; bounding box "
                f"[{_fmt(lo)}] to [{_fmt(hi)}]; edges: {words}")


def _readonly(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


def _fmt(x) -> str:
    return ", ".join(f"{v:.6g}" for v in x)


def _n_parts(triangles, incidence) -> int:
    offsets, tris = incidence
    counts = np.diff(offsets)
    # join each edge's triangles to its first one
    first = np.repeat(tris[offsets[:-1]], counts)
    graph = coo_matrix((np.ones(len(tris)), (first, tris)),
                       shape=(len(triangles), len(triangles)))
    return int(connected_components(graph, directed=False)[0])


# --- checks and repairs ---------------------------------------------------------------


def mesh_from_arrays(vertices, triangles, name: str = "mesh", *, transforms=(),
                     merge_tol: float = MERGE_TOL, area_tol: float = AREA_TOL,
                     source: str | None = None) -> TriangleMesh:
    """A checked and repaired :class:`TriangleMesh` from raw ``vertices`` (V, 3) [L]
    and ``triangles`` (T, 3) (vertex indices).

    In this order (``docs/meshes.md``):

    1. errors: a wrong shape, no triangles, a vertex index out of range, a non-finite
       coordinate or one beyond 1e100 in magnitude;
    2. vertices closer than ``merge_tol`` times the bounding-box diagonal are merged
       (each group keeps its lowest-index vertex);
    3. degenerate triangles (two equal vertex indices after merging, or twice the area
       at most ``area_tol`` times the square of the longest edge) are dropped, then
       duplicated triangles (the same vertex set, either orientation; the first is
       kept), each with one :class:`MeshWarning`; none left is an error;
    4. unused vertices are removed (the order of the others is kept);
    5. edges shared by three or more triangles get one :class:`MeshWarning`;
    6. triangles are re-oriented so that neighbours across every two-triangle edge
       traverse it in opposite directions: in each part the minority is flipped (on a
       tie, the triangles oriented unlike the part's lowest-index one), with one
       :class:`MeshWarning`; a non-orientable part (a Moebius strip) is an error;
    7. ``transforms`` are applied in order (:mod:`demstep.mesh.transforms`).

    Messages name ``source`` (default ``name``) and triangles by their index in the
    ``triangles`` given (0-based). Errors are one-line
    :class:`~demstep.errors.InputError`.
    """
    where = source if source is not None else name
    v = np.asarray(vertices)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"{where}: vertices: expected an (V, 3) array, got shape {v.shape}")
    if t.size == 0:
        raise InputError(f"{where}: no triangles (an empty mesh)")
    if t.ndim != 2 or t.shape[1] != 3:
        raise InputError(f"{where}: triangles: expected a (T, 3) array, got shape {t.shape}")
    if not np.issubdtype(t.dtype, np.integer):
        raise InputError(f"{where}: triangles: expected integer vertex indices, got {t.dtype}")
    if not (np.issubdtype(v.dtype, np.floating) or np.issubdtype(v.dtype, np.integer)):
        raise InputError(f"{where}: vertices: expected numbers, got {v.dtype}")
    v = v.astype(np.float64)
    t = t.astype(np.int64)
    _check_indices(t, len(v), where)
    _check_coordinates(v, t, where)

    index = np.arange(len(t))  # each kept triangle's index in the input
    t = _merge_vertices(v, t, merge_tol, where)
    t, index = _drop_degenerate(v, t, index, area_tol, where)
    t, index = _drop_duplicates(t, index, where)
    v, t = _compact(v, t)
    mesh = TriangleMesh(v, t, name)
    _warn_nonmanifold(mesh, index, where)
    mesh = _orient(mesh, index, where)
    if transforms:
        mesh = mesh.transformed(transforms)
    return mesh


def _check_indices(t, n_vertices, where):
    out = (t < 0) | (t >= n_vertices)
    if out.any():
        k, c = np.argwhere(out)[0]
        raise InputError(f"{where}: triangle {k}: vertex index {t[k, c]} out of range "
                         f"(0 to {n_vertices - 1})")


def _check_coordinates(v, t, where):
    bad = ~np.isfinite(v) | (np.abs(v) > MAX_MAGNITUDE)
    if not bad.any():
        return
    vertex, axis = np.argwhere(bad)[0]
    value = float(v[vertex, axis])
    what = "not finite" if not np.isfinite(value) else f"beyond {MAX_MAGNITUDE:g} in magnitude"
    hit = np.argwhere(bad.any(axis=1)[t])
    if len(hit):  # name the first triangle using a bad vertex, and its corner
        k, c = hit[0]
        vertex = t[k, c]
        axis = int(np.flatnonzero(bad[vertex])[0])
        value = float(v[vertex, axis])
        what = "not finite" if not np.isfinite(value) else f"beyond {MAX_MAGNITUDE:g} in magnitude"
        raise InputError(f"{where}: triangle {k}: corner {c} (vertex {vertex}): "
                         f"{_AXES[axis]} = {value!r}: {what}")
    raise InputError(f"{where}: vertex {vertex} (used by no triangle): {_AXES[axis]} = "
                     f"{value!r}: {what}")


def _merge_vertices(v, t, merge_tol, where):
    """``t`` with every vertex replaced by the lowest-index vertex of its group of
    vertices within ``merge_tol`` times the diagonal of the used vertices' box."""
    if not (np.isfinite(merge_tol) and 0 <= merge_tol < 1):
        raise InputError(f"{where}: merge_tol = {merge_tol!r}: must be >= 0 and < 1")
    used = np.unique(t)
    diagonal = float(np.linalg.norm(np.ptp(v[used], axis=0)))
    pairs = cKDTree(v[used]).query_pairs(merge_tol * diagonal, output_type="ndarray")
    if len(pairs) == 0:
        return t
    n = len(used)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    keep = np.full(labels.max() + 1, n)
    np.minimum.at(keep, labels, np.arange(n))
    new = np.arange(len(v))
    new[used] = used[keep[labels]]
    log.info("%s: merged %d coincident vertices (within %.3g)", where,
             int(np.count_nonzero(new[used] != used)), merge_tol * diagonal)
    return new[t]


def _drop_degenerate(v, t, index, area_tol, where):
    if not (np.isfinite(area_tol) and 0 <= area_tol < 1):
        raise InputError(f"{where}: area_tol = {area_tol!r}: must be >= 0 and < 1")
    p = v[t]
    twice_area = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    longest2 = np.max([np.sum((p[:, (c + 1) % 3] - p[:, c]) ** 2, axis=1) for c in range(3)],
                      axis=0)
    repeated = (t[:, 0] == t[:, 1]) | (t[:, 1] == t[:, 2]) | (t[:, 2] == t[:, 0])
    bad = repeated | (twice_area <= area_tol * longest2)
    if bad.all():
        raise InputError(f"{where}: no triangles left: all {len(t)} are degenerate (zero "
                         "area or a repeated vertex)")
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        why = ("a repeated vertex" if repeated[k]
               else f"area {0.5 * twice_area[k]:.3g}, longest edge {np.sqrt(longest2[k]):.3g}")
        warnings.warn(f"demstep: {where}: dropped {int(bad.sum())} degenerate triangle(s) "
                      f"(first: triangle {index[k]}, {why})", MeshWarning, stacklevel=3)
    return t[~bad], index[~bad]


def _drop_duplicates(t, index, where):
    _, first = np.unique(np.sort(t, axis=1), axis=0, return_index=True)
    if len(first) == len(t):
        return t, index
    keep = np.zeros(len(t), dtype=bool)
    keep[first] = True
    k = int(np.flatnonzero(~keep)[0])
    warnings.warn(f"demstep: {where}: dropped {int((~keep).sum())} duplicated triangle(s) "
                  f"(first: triangle {index[k]}, vertices {sorted(t[k].tolist())})",
                  MeshWarning, stacklevel=3)
    return t[keep], index[keep]


def _compact(v, t):
    used, inverse = np.unique(t, return_inverse=True)
    return v[used], inverse.reshape(t.shape)


def _warn_nonmanifold(mesh, index, where):
    many = np.flatnonzero(mesh.edge_counts >= 3)
    if len(many):
        offsets, tris = mesh.edge_incidence()
        e = many[0]
        warnings.warn(f"demstep: {where}: {len(many)} non-manifold edge(s), shared by 3 or "
                      f"more triangles (first: triangles "
                      f"{index[tris[offsets[e]:offsets[e + 1]]].tolist()})", MeshWarning,
                      stacklevel=3)


def _orient(mesh, index, where) -> TriangleMesh:
    """``mesh`` with the minority of each part flipped so that every two-triangle edge
    is traversed in opposite directions by its triangles."""
    counts = mesh.edge_counts
    two = counts == 2
    a, b = mesh.edge_triangles[two].T
    consistent = mesh._edge_consistent[two]
    if consistent.all():
        return mesh
    n = mesh.n_triangles
    # the orientation double cover: node t + s n is "triangle t, flipped s times";
    # a consistent edge joins equal flips, an inconsistent one opposite flips
    flip = (~consistent).astype(np.int64)
    rows = np.concatenate([a, a + n])
    cols = np.concatenate([b + flip * n, b + (1 - flip) * n])
    cover = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(2 * n, 2 * n))
    _, cover_label = connected_components(cover, directed=False)
    twisted = np.flatnonzero(cover_label[:n] == cover_label[n:])
    if len(twisted):
        raise InputError(f"{where}: triangle {index[twisted[0]]}: its part of the surface is "
                         "not orientable (a Moebius strip: no choice of normals agrees across "
                         "every edge)")
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n))
    n_parts, part = connected_components(graph, directed=False)
    root = np.full(n_parts, n)
    np.minimum.at(root, part, np.arange(n))
    same = cover_label[:n] == cover_label[root[part]]  # oriented like its part's root
    n_same = np.bincount(part, weights=same, minlength=n_parts)
    n_other = np.bincount(part, minlength=n_parts) - n_same
    to_flip = np.where((n_same < n_other)[part], same, ~same)
    k = int(np.flatnonzero(to_flip)[0])
    warnings.warn(f"demstep: {where}: re-oriented {int(to_flip.sum())} triangle(s) whose "
                  f"normals disagreed with their neighbours' (first: triangle {index[k]})",
                  MeshWarning, stacklevel=3)
    t = mesh.triangles.copy()
    t[to_flip] = t[to_flip][:, [0, 2, 1]]
    return TriangleMesh(mesh.vertices, t, mesh.name)
