"""Triangle-mesh walls of a Simulation: the meshes' state, their candidate lists and the
outputs (force, torque, work) of each mesh.

A :class:`MeshWall` is a :class:`~demstep.mesh.TriangleMesh` with its friction and its
motion (a velocity, an angular velocity about a centre: a conveyor, a drum, a mixer
blade). The Simulation keeps them in one :class:`~demstep.state.Meshes` bundle (the
triangles of every mesh, their vertex ids, the motion, the outputs, and the candidate
(particle, triangle) rows with their contact slots: :mod:`demstep.kernels.meshes`).
:func:`build_candidates` finds, at every rebuild of the neighbour lists, the triangles
within the skin of each sphere (each sphere looks at the triangles listed in its cell
of a grid over the meshes, a :class:`TriangleGrid` kept while the meshes do not move),
and :func:`carry_slots` carries each sphere's contacts over to its new rows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from demstep.errors import InputError
from demstep.kernels.meshes import (MAX_CANDIDATES, grid_candidates, mesh_contact_geometry,
                                    triangle_grid)
from demstep.mesh import TriangleMesh
from demstep.state import ROLL_WIDTH, Meshes

MESH_FIXED, MESH_MOVING = 0, 1


@dataclass
class MeshWall:
    """A triangle mesh as a wall of the simulation: ``mesh`` (its triangles, normals
    towards the particles or not: contacts take the closest point, whichever side),
    ``name``, friction ``mu`` (None: the law's wall friction), ``material`` (the contact
    law's own parameters for the mesh, None: the particles'; a Hertz mesh gives its
    Young's modulus and Poisson's ratio, paired with the particles' as a pair of two
    materials; a linear one the contact's stiffnesses), and its motion: a
    translation at ``velocity`` (3,) [L/T] and a rotation at ``omega`` (3,) [1/T] (the
    rotation vector: axis and rate, right-hand rule) about ``center`` (3,) [L], which
    moves with the translation; and a surface velocity ``surface_velocity`` (3,) [L/T]:
    its contacts see the surface move at it while its triangles stay in place (a
    conveyor belt, LIGGGHTS' ``surface_vel``; meant along the surface); ``enabled``
    False: the mesh is there (it moves, it is written out) but has no contacts, as a
    LIGGGHTS ``fix mesh/surface`` that no ``fix wall/gran`` names yet
    (:meth:`~demstep.engine.Simulation.set_mesh_motion` switches it on or off);
    ``finnie_k`` [L T^2/M]: Finnie's wear coefficient (an inverse pressure: the wear
    is then a depth [L]; LIGGGHTS' ``k_finnie``), > 0 to accumulate the wear of each
    triangle (:mod:`demstep.kernels.meshes`), 0 (default) not to."""

    mesh: TriangleMesh
    name: str = "mesh"
    mu: float | None = None
    material: dict | None = None
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    omega: np.ndarray = field(default_factory=lambda: np.zeros(3))
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    surface_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    enabled: bool = True
    finnie_k: float = 0.0

    def __post_init__(self):
        for name in ("velocity", "omega", "center", "surface_velocity"):
            value = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            if value.shape != (3,) or not np.isfinite(value).all():
                raise InputError(f"mesh {self.name!r}: {name} must have 3 finite components, "
                                 f"got {getattr(self, name)!r}")
            setattr(self, name, value.copy())
        if self.mu is not None and not (math.isfinite(self.mu) and self.mu >= 0):
            raise InputError(f"mesh {self.name!r}: mu must be finite and >= 0, got {self.mu!r}")
        if not isinstance(self.enabled, (bool, np.bool_)):
            raise InputError(f"mesh {self.name!r}: enabled must be true or false, got "
                             f"{self.enabled!r}")
        self.enabled = bool(self.enabled)
        if not (math.isfinite(self.finnie_k) and self.finnie_k >= 0):
            raise InputError(f"mesh {self.name!r}: finnie_k must be finite and >= 0, got "
                             f"{self.finnie_k!r}")
        self.finnie_k = float(self.finnie_k)

    @property
    def moving(self) -> bool:
        return bool(np.any(self.velocity != 0.0) or np.any(self.omega != 0.0))


def mesh_law_rows(walls: list[MeshWall], law) -> np.ndarray:
    """The parameters of the contacts with each of ``walls`` (M, F): the contact law
    ``law``'s Params tuple for the wall's material and friction
    (:meth:`~demstep.contact.laws.base.ContactLaw.wall_params`), as float rows."""
    rows = []
    for wall in walls:
        try:
            rows.append(tuple(law.wall_params(wall.material, wall.mu)))
        except InputError as err:
            raise InputError(f"mesh {wall.name!r}: {err}") from None
    return np.array(rows, dtype=np.float64).reshape(len(walls), len(law.Params._fields))


def meshes_bundle(walls: list[MeshWall], law) -> Meshes:
    """The Meshes bundle of ``walls`` (their triangles numbered mesh after mesh; the
    vertex ids of each mesh offset so that no two meshes share one) with the contact
    law ``law`` (:func:`mesh_law_rows`; None: no parameters, a bundle for the geometry
    only). No candidates yet (:func:`build_candidates`)."""
    tri, vid, owner = [], [], []
    offset = 0
    for k, wall in enumerate(walls):
        m = wall.mesh
        tri.append(m.vertices[m.triangles].reshape(-1, 9))
        vid.append(m.triangles.astype(np.int64) + offset)
        owner.append(np.full(len(m.triangles), k, dtype=np.int64))
        offset += len(m.vertices)
    n = len(walls)
    tri = np.ascontiguousarray(np.concatenate(tri)) if n else np.zeros((0, 9))
    z3 = np.zeros((n, 3))
    return Meshes(
        tri=tri, tri0=tri.copy(), vid=np.concatenate(vid) if n else np.zeros((0, 3), np.int64),
        tri_mesh=np.concatenate(owner) if n else np.zeros(0, np.int64),
        motion=np.array([MESH_MOVING if w.moving else MESH_FIXED for w in walls], np.int64),
        vel=np.array([w.velocity for w in walls]).reshape(n, 3),
        omega=np.array([w.omega for w in walls]).reshape(n, 3),
        axis=np.array([rotation_axis(w.omega) for w in walls]).reshape(n, 3),
        surface=np.array([w.surface_velocity for w in walls]).reshape(n, 3),
        center=np.array([w.center for w in walls]).reshape(n, 3),
        shift=z3.copy(), turn=np.zeros(n),
        law=mesh_law_rows(walls, law) if law is not None else np.zeros((n, 0)),
        force=z3.copy(), torque=z3.copy(), power=np.zeros(n), power_prev=np.zeros(n),
        contacts=np.zeros(n, np.int64), moved=np.zeros(1),
        cand_p=np.zeros(0, np.int64), cand_t=np.zeros(0, np.int64), cand_d=np.zeros(0),
        active=np.zeros(0, np.int64), slot_mesh=np.zeros(0, np.int64),
        slot_tri=np.zeros(0, np.int64), normal=np.zeros((0, 3)), shear=np.zeros((0, 3)),
        dashpot=np.zeros((0, 3)), etan=np.zeros(0), fslot=np.zeros((0, 3)),
        roll=np.zeros((0, ROLL_WIDTH)),
        wear_k=np.array([w.finnie_k for w in walls], dtype=np.float64),
        wear=np.zeros(len(tri)), **no_mesh_cover())


def rotation_axis(omega, default=(0.0, 0.0, 1.0)) -> np.ndarray:
    """The unit axis of a rotation vector ``omega`` (3,) [1/T]; ``default`` for 0."""
    omega = np.asarray(omega, dtype=np.float64)
    size = float(np.linalg.norm(omega))
    return omega / size if size > 0.0 else np.asarray(default, dtype=np.float64)


def no_mesh_cover() -> dict:
    """The Meshes fields of the 'auto' step's cover when it is not followed (no
    certificate): empty rows, no drift limit (:class:`demstep.state.Meshes`)."""
    return dict(cover_start=np.zeros(0, np.int64), cover_mesh=np.zeros(0, np.int64),
                cover_ref=np.zeros((0, 11)), cover_extra=np.zeros((0, 2)),
                cover_ctl=np.array([0.0, np.inf, 0.0, 0.0]), cover_out=np.zeros(3))


def body_frame(meshes: Meshes, k: int, x) -> np.ndarray:
    """The points ``x`` (N, 3) [L] in the frame of mesh ``k`` as read (where its corners
    are ``tri0``): its corners now are R (tri0 - o) + c, c its centre now, o = c - shift
    the centre as read and R the turn about its axis (as
    :func:`demstep.kernels.meshes.move_meshes` has them), so y = R^T (x - c) + o."""
    c = meshes.center[k]
    o = c - meshes.shift[k]
    axis = meshes.axis[k]
    ang = float(meshes.turn[k])
    d = np.asarray(x, dtype=np.float64) - c
    if ang != 0.0:  # (Rodrigues, by -ang: R^T)
        cos, sin = math.cos(ang), -math.sin(ang)
        d = (d * cos + np.cross(axis, d) * sin
             + axis * (d @ axis)[:, None] * (1.0 - cos))
    return np.ascontiguousarray(d + o)


class TriangleGrid:
    """The triangles near each cell of grids over the meshes
    (:func:`demstep.kernels.meshes.triangle_grid`), kept from one search to the next:
    one grid of the meshes that do not move, kept while their triangles, the reach and
    the enabled meshes are the same; one per moving mesh over its triangles as read
    (``tri0``), searched with the particles carried into its frame
    (:func:`body_frame`), kept while the reach is the same: a moving mesh is binned
    once too."""

    #: a grid has at most 8 cells per triangle plus this many (its cells grow until it
    #: fits), and at most 16 entries per triangle plus this many
    MAX_CELLS_EXTRA = 100_000

    def __init__(self):
        self.grids = {}
        #: grids built (a diagnostic: once for each mesh, and the fixed ones together)
        self.n_builds = 0

    def groups(self, meshes: Meshes, reach: float, enabled) -> list:
        """[(frame, corners, (lo, cell, ncell, start, triangles))]: ``frame`` None for
        the grid of the meshes that do not move (``corners`` ``meshes.tri``), else the
        moving mesh's index (``corners`` ``meshes.tri0``); only the triangles of the
        ``enabled`` meshes (None: all) [``reach``: r_max + skin, L]."""
        on = (np.ones(meshes.n, dtype=bool) if enabled is None
              else np.asarray(enabled, dtype=bool))
        moving = (meshes.motion != MESH_FIXED) & on
        out = []
        fixed_use = (on & ~moving)[meshes.tri_mesh]
        if fixed_use.any():
            tri = meshes.tri
            # (the corners of a mesh at rest follow from the corners as read, its shift
            # and turn: a sample of the corners guards against anything else)
            rest = on & ~moving
            sample = tri[fixed_use][::max(1, int(fixed_use.sum()) // 64)]
            key = (float(reach), fixed_use.tobytes(), meshes.shift[rest].tobytes(),
                   meshes.turn[rest].tobytes(), sample.tobytes())
            out.append((None, tri, self._get(None, key, tri, fixed_use, reach)))
        for k in np.flatnonzero(moving):
            use = meshes.tri_mesh == k
            key = (float(reach), int(k), use.tobytes())
            out.append((int(k), meshes.tri0, self._get(int(k), key, meshes.tri0, use, reach)))
        return out

    def _get(self, name, key, tri, use, reach):
        held = self.grids.get(name)
        if held is None or held[0] != key:
            held = self.grids[name] = (key, self._build(tri, use, float(reach)))
            self.n_builds += 1
        return held[1]

    def _build(self, tri, use, reach):
        corners = tri[use].reshape(-1, 3)
        lo = corners.min(axis=0) - reach
        extent = corners.max(axis=0) + reach - lo
        cell = max(reach, 1e-12 * float(extent.max()), 1e-300)
        n_used = int(use.sum())
        max_cells = 8 * n_used + self.MAX_CELLS_EXTRA
        while True:
            while np.prod(np.floor(extent / cell) + 1.0) > max_cells:
                cell *= 1.5
            ncell = (np.floor(extent / cell) + 1).astype(np.int64)
            start, cell_tri = triangle_grid(tri, use, lo, cell, ncell, reach)
            if len(cell_tri) <= 16 * n_used + self.MAX_CELLS_EXTRA:
                return lo, cell, ncell, start, cell_tri
            cell *= 1.5  # (large triangles over many cells: coarser)


def build_candidates(meshes: Meshes, x, r, skin: float, particle_id,
                     enabled=None, grid: TriangleGrid | None = None,
                     with_distance: bool = False) -> tuple:
    """The (particle, triangle) pairs whose distance is below r + ``skin`` [L], sorted by
    particle then triangle: (cand_p, cand_t), the triangles of the meshes where
    ``enabled`` (M,) is true only (None: every mesh). The triangles are binned in grids
    of cells (side r_max + skin or more; each triangle listed in the cells whose centre
    lies within r_max + skin plus half a diagonal of it), and each particle looks at
    the triangles of its own cell (:func:`demstep.kernels.meshes.grid_candidates`): the
    cost is the particles near a mesh times the triangles near each, whatever the
    mesh's size. The grids are kept in ``grid`` (a :class:`TriangleGrid`; None: grids
    for this search only): the meshes at rest in one grid, each moving mesh in a grid
    of its own frame. More than :data:`MAX_CANDIDATES` triangles near one sphere is
    refused (a mesh far finer than the particles), naming the particle. With
    ``with_distance``, also each row's distance [L] (cand_d)."""
    n_tri = len(meshes.tri)
    if enabled is not None and not np.any(enabled):
        n_tri = 0
    if n_tri == 0 or len(r) == 0:
        empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
        return empty + (np.zeros(0),) if with_distance else empty
    x = np.ascontiguousarray(x, dtype=np.float64)
    r = np.ascontiguousarray(r, dtype=np.float64)
    reach = float(r.max()) + float(skin)
    if grid is None:
        grid = TriangleGrid()
    found = []
    for frame, corners, (lo, cell, ncell, start, cell_tri) in grid.groups(meshes, reach,
                                                                          enabled):
        points = x if frame is None else body_frame(meshes, frame, x)
        found.append(grid_candidates(points, r, float(skin), corners, lo, cell, ncell, start,
                                     cell_tri))
    if len(found) == 1:
        cand_p, cand_t, cand_d = found[0]
    else:
        cand_p, cand_t, cand_d = (np.concatenate([f[k] for f in found]) for k in range(3))
        order = np.lexsort((cand_t, cand_p))
        cand_p, cand_t, cand_d = cand_p[order], cand_t[order], cand_d[order]
    if len(cand_p):
        per = np.bincount(cand_p)
        if per.max() > MAX_CANDIDATES:
            p = int(np.argmax(per))
            raise InputError(f"meshes: {int(per.max())} triangles lie within the skin of "
                             f"particle {particle_id(p)} (at most {MAX_CANDIDATES}): the mesh "
                             f"is far finer than the particles; coarsen it")
    return (cand_p, cand_t, cand_d) if with_distance else (cand_p, cand_t)


def carry_slots(meshes: Meshes, cand_p, cand_t, cand_d=None) -> Meshes:
    """The bundle with the new candidate rows (their distances ``cand_d`` [L] at the
    build; None: zeros, every row computed at each step) and each sphere's active
    contact slots carried over to the first of its new rows (the rest empty)."""
    k = len(cand_p)
    slots = {f: np.zeros((k,) + getattr(meshes, f).shape[1:], getattr(meshes, f).dtype)
             for f in Meshes.SLOTS}
    old = np.flatnonzero(meshes.active == 1)
    if len(old) and k:
        old_p = meshes.cand_p[old]
        starts = np.searchsorted(cand_p, old_p, side="left")
        ends = np.searchsorted(cand_p, old_p, side="right")
        # the rank of each old slot among its sphere's (the slots are sorted by sphere)
        first = np.searchsorted(old_p, old_p, side="left")
        rank = np.arange(len(old)) - first
        room = starts + rank < ends  # (a sphere with fewer candidates now: its extra
        dest = (starts + rank)[room]  # slots end; their stored energy is negligible)
        src = old[room]
        for f in Meshes.SLOTS:
            slots[f][dest] = getattr(meshes, f)[src]
    cand_d = np.zeros(k) if cand_d is None else np.ascontiguousarray(cand_d, dtype=np.float64)
    return meshes._replace(cand_p=cand_p, cand_t=cand_t, cand_d=cand_d, **slots)


def touching_meshes(meshes: list[TriangleMesh], x, r, contact_tol: float = 0.0):
    """The contacts of spheres (centres ``x`` (N, 3) [L], radii ``r``) with
    ``meshes`` (TriangleMesh) at their positions, touching within ``contact_tol``
    (the centre within r (1 + tol) of the surface, as plane walls), by the engine's
    rule (one per surface): particle (C,), mesh (C,), unit normal from the particle
    to the mesh (C, 3) and distance from the centre to the closest point [L]."""
    bundle = meshes_bundle([MeshWall(m, name=m.name) for m in meshes], None)
    x = np.ascontiguousarray(x, dtype=np.float64)
    reach = np.ascontiguousarray(np.asarray(r, dtype=np.float64) * (1.0 + contact_tol))
    cand_p, cand_t = build_candidates(bundle, x, reach, 0.0, lambda p: p)
    bundle = bundle._replace(cand_p=cand_p, cand_t=cand_t, cand_d=np.zeros(len(cand_p)))
    p, mk, normal, dist, _ = mesh_contacts(bundle, x, reach)
    return p, mk, normal, dist


def mesh_contacts(meshes: Meshes, x, r):
    """The particle-mesh contacts at the positions ``x`` [L] by the engine's rule (one
    per surface, :mod:`demstep.kernels.meshes`), among the candidate rows of
    ``meshes``: particle (C,), mesh (C,), unit normal from the particle to the mesh
    (C, 3), distance from the centre to the triangle's closest point [L] and overlap
    r - distance [L] (> 0)."""
    rows, delta, normal, dist = mesh_contact_geometry(
        np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(r, dtype=np.float64),
        meshes.cand_p, meshes.cand_t, meshes.cand_d, meshes.tri, meshes.vid, meshes.tri_mesh)
    return (meshes.cand_p[rows], meshes.tri_mesh[meshes.cand_t[rows]], normal, dist,
            delta)


def set_mesh_motion(sim, index: int, velocity=None, omega=None, friction=None,
                    surface_velocity=None, center=None) -> None:
    """Change how mesh ``index`` of ``sim`` moves between stages: its translation
    ``velocity`` (3,) [L/T], its rotation ``omega`` (3,) [1/T] about its centre, the
    centre ``center`` (3,) [L] (where it is now), its surface velocity
    ``surface_velocity`` (3,) [L/T], its friction ``friction`` (takes effect at the next
    run). A mesh that has turned keeps its axis and its centre (its corners are
    recomputed from the total turn about them): a new rate about the same axis, or no
    rotation, is allowed; another axis, or a new centre, is refused."""
    wall = sim.mesh_walls[index]
    meshes = sim.meshes
    if center is not None:
        new = _vector3(center, f"mesh {wall.name!r}: center")
        if meshes.turn[index] != 0.0:
            raise InputError(f"mesh {wall.name!r}: center: a mesh that has turned keeps its "
                             f"centre {meshes.center[index].tolist()}, got {new.tolist()}")
        # (unturned, the corners are the corners as read plus the shift, whatever the
        # centre: move_meshes takes the centre as read to be the centre less the shift)
        meshes.center[index] = new
    if velocity is not None:
        wall.velocity = _vector3(velocity, f"mesh {wall.name!r}: velocity")
        meshes.vel[index] = wall.velocity
    if omega is not None:
        new = _vector3(omega, f"mesh {wall.name!r}: omega")
        old = meshes.omega[index]
        if meshes.turn[index] != 0.0 and np.any(new != 0.0):
            cross = np.linalg.norm(np.cross(new, old))
            same = np.dot(new, old) > 0 and cross <= 1e-12 * np.linalg.norm(new) * np.linalg.norm(old)
            if not same:
                raise InputError(f"mesh {wall.name!r}: omega: a mesh that has turned keeps its "
                                 f"axis {old.tolist()} (a new rate about it, or 0), got "
                                 f"{new.tolist()}")
        wall.omega = new
        meshes.omega[index] = new
        if np.any(new != 0.0):
            meshes.axis[index] = rotation_axis(new)
    if surface_velocity is not None:
        wall.surface_velocity = _vector3(surface_velocity, f"mesh {wall.name!r}: surface_velocity")
        meshes.surface[index] = wall.surface_velocity
    if friction is not None:
        if not (math.isfinite(friction) and friction >= 0):
            raise InputError(f"mesh {wall.name!r}: friction must be finite and >= 0, got "
                             f"{friction!r}")
        wall.mu = float(friction)
    meshes.motion[index] = MESH_MOVING if wall.moving else MESH_FIXED


def _vector3(value, what: str) -> np.ndarray:
    out = np.asarray(value, dtype=np.float64).reshape(-1)
    if out.shape != (3,) or not np.isfinite(out).all():
        raise InputError(f"{what} must have 3 finite components, got {value!r}")
    return out.copy()
