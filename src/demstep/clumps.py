"""Clumps: rigid bodies made of overlapping or touching spheres (disks in 2D).

A :class:`ClumpTemplate` lists its members (centres [L] and radii [L] in a frame of
its own). :func:`mass_properties` gives the mass, centre of mass and inertia tensor of
the *union* of the members for a density [M/L^3] (2D: [M/L^2], per unit thickness):

* exact when no two members overlap (sums of spheres, parallel-axis theorem);
* otherwise by numerical integration: along lines parallel to the last axis the union
  of the members' chords is merged and integrated exactly (length and first and second
  moments), and the lines sit on a midpoint grid over the other axes, refined until the
  mass and the inertia change by less than ``rtol`` (the error falls as the square of
  the spacing; the default converges within 1e-4, well inside the 0.5 % asked of it).

:func:`principal_frame` turns a template into the body frame: centre of mass at the
origin, axes along the principal axes of inertia, so that a body's state is its centre,
an orientation quaternion (body to world) and three principal moments.

:class:`ClumpSet` is what a Simulation takes: for each body its template, position and
orientation; :func:`expand` gives the member spheres in the world.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from demstep.errors import InputError
from demstep.particles import INERTIA_FACTOR, Particles
from demstep.state import Bodies

#: relative convergence of the numerical mass properties of overlapping members
MASS_RTOL = 1e-4
#: a gap between members up to this fraction of the smaller radius still joins them
TOUCH_TOL = 1e-9


@dataclass
class ClumpTemplate:
    """Members of one clump shape: ``centers`` (M, dim) [L] and ``radii`` (M,) [L] in
    the template's own frame, and a ``name``."""

    name: str
    centers: np.ndarray
    radii: np.ndarray

    def __post_init__(self):
        self.centers = np.asarray(self.centers, dtype=np.float64)
        self.radii = np.asarray(self.radii, dtype=np.float64).reshape(-1)
        where = f"clump template {self.name!r}"
        if self.radii.size == 0:
            raise InputError(f"{where}: members: a clump needs at least one member")
        if self.centers.ndim != 2 or self.centers.shape[0] != self.radii.size \
                or self.centers.shape[1] not in (2, 3):
            raise InputError(f"{where}: members: expected {self.radii.size} centres of 2 or 3 "
                             f"coordinates, got shape {self.centers.shape}")
        if not (np.isfinite(self.centers).all() and np.isfinite(self.radii).all()):
            raise InputError(f"{where}: members: coordinates and radii must be finite")
        bad = np.flatnonzero(~(self.radii > 0))
        if len(bad):
            raise InputError(f"{where}: member {bad[0]}: radius must be > 0, got "
                             f"{self.radii[bad[0]]:g}")
        check_connected(self.centers, self.radii, where)

    @property
    def dim(self) -> int:
        return self.centers.shape[1]

    @property
    def n_members(self) -> int:
        return len(self.radii)


def check_connected(centers, radii, where: str):
    """The members must form one rigid body: every member touches or overlaps the
    others through a chain of contacts (else InputError naming the first member cut
    off)."""
    n = len(radii)
    if n == 1:
        return
    d = np.linalg.norm(centers[:, None, :] - centers[None, :, :], axis=2)
    touch = d <= (radii[:, None] + radii[None, :]) * (1.0 + TOUCH_TOL)
    seen = np.zeros(n, dtype=bool)
    stack = [0]
    seen[0] = True
    while stack:
        k = stack.pop()
        for j in np.flatnonzero(touch[k] & ~seen):
            seen[j] = True
            stack.append(j)
    if not seen.all():
        k = int(np.flatnonzero(~seen)[0])
        raise InputError(f"{where}: member {k} does not touch or overlap the others: the "
                         f"members are not one rigid body")
    same = np.flatnonzero(np.triu(d < 1e-12 * radii.max(), 1).any(axis=1))
    if len(same):
        raise InputError(f"{where}: member {int(same[0])} has the same centre as another")


@dataclass
class MassProperties:
    """Mass [M], centre of mass (dim,) [L], inertia tensor about it (3, 3) [M L^2]
    (2D: only I_zz is meaningful; the others are set to it), and whether they are exact
    (no overlapping members) or converged numerically (``rtol`` reached)."""

    mass: float
    com: np.ndarray
    inertia: np.ndarray
    exact: bool
    rtol: float = 0.0


def overlapping(centers, radii) -> bool:
    d = np.linalg.norm(centers[:, None, :] - centers[None, :, :], axis=2)
    np.fill_diagonal(d, np.inf)
    return bool((d < (radii[:, None] + radii[None, :]) * (1.0 - TOUCH_TOL)).any())


def mass_properties(centers, radii, density: float, rtol: float = MASS_RTOL,
                    max_lines: int = 2048) -> MassProperties:
    """Mass properties of the union of the members (module docstring)."""
    centers = np.asarray(centers, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    dim = centers.shape[1]
    if not overlapping(centers, radii):
        return _separate(centers, radii, density, dim)
    n = 64
    last = _integrate_union(centers, radii, density, n)
    while True:
        n *= 2
        props = _integrate_union(centers, radii, density, n)
        change = max(abs(props.mass / last.mass - 1.0),
                     np.abs(props.inertia - last.inertia).max() / np.abs(props.inertia).max())
        if change < rtol:
            props.rtol = rtol
            return props
        if n >= max_lines:
            raise InputError(f"clump: the mass properties did not converge to {rtol:g} with "
                             f"{n} integration lines (members too small against the clump)")
        last = props


def _sphere_props(r, density, dim):
    """Mass and moment of inertia about the centre of one member [M], [M L^2]."""
    if dim == 3:
        m = density * 4.0 / 3.0 * math.pi * r**3
        return m, 0.4 * m * r * r
    m = density * math.pi * r**2
    return m, 0.5 * m * r * r


def _separate(centers, radii, density, dim) -> MassProperties:
    masses, own = zip(*(_sphere_props(r, density, dim) for r in radii))
    masses = np.array(masses)
    own = np.array(own)
    mass = masses.sum()
    com = (masses[:, None] * centers).sum(axis=0) / mass
    rel = np.zeros((len(radii), 3))
    rel[:, :dim] = centers - com
    inertia = np.zeros((3, 3))
    for m, i_own, d in zip(masses, own, rel):
        inertia += i_own * np.eye(3) + m * (d @ d * np.eye(3) - np.outer(d, d))
    if dim == 2:
        inertia = np.eye(3) * inertia[2, 2]
    return MassProperties(float(mass), com, inertia, True)


def _integrate_union(centers, radii, density, n) -> MassProperties:
    """Midpoint grid of n (2D) or n x n (3D) lines along the last axis; on each line
    the union of the chords of the members is merged and its length, first and second
    moments integrated exactly."""
    dim = centers.shape[1]
    lo = (centers - radii[:, None]).min(axis=0)
    hi = (centers + radii[:, None]).max(axis=0)
    axes = [lo[k] + (np.arange(n) + 0.5) * (hi[k] - lo[k]) / n for k in range(dim - 1)]
    cell = np.prod([(hi[k] - lo[k]) / n for k in range(dim - 1)])
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, dim - 1)
    # chord half-lengths of every member on every line
    rho2 = ((grid[:, None, :] - centers[None, :, :dim - 1]) ** 2).sum(axis=2)
    h2 = radii[None, :] ** 2 - rho2
    inside = h2 > 0
    h = np.sqrt(np.where(inside, h2, 0.0))
    z_lo = np.where(inside, centers[None, :, -1] - h, np.inf)
    z_hi = np.where(inside, centers[None, :, -1] + h, -np.inf)
    order = np.argsort(z_lo, axis=1)
    z_lo = np.take_along_axis(z_lo, order, axis=1)
    z_hi = np.take_along_axis(z_hi, order, axis=1)
    # merge the sorted intervals of each line: a new piece starts where the lower end
    # passes the running maximum of the upper ends
    run_max = np.maximum.accumulate(z_hi, axis=1)
    prev_max = np.concatenate([np.full((len(grid), 1), -np.inf), run_max[:, :-1]], axis=1)
    start = np.maximum(z_lo, prev_max)  # the part of each interval not yet covered
    end = np.maximum(z_hi, start)
    valid = np.isfinite(z_lo) & (end > start)
    start = np.where(valid, start, 0.0)
    end = np.where(valid, end, 0.0)
    l0 = (end - start).sum(axis=1)
    l1 = 0.5 * (end**2 - start**2).sum(axis=1)
    l2 = (end**3 - start**3).sum(axis=1) / 3.0
    w = density * cell
    mass = w * l0.sum()
    if dim == 2:
        x = grid[:, 0]
        mx, my = w * (x * l0).sum(), w * l1.sum()
        com = np.array([mx, my]) / mass
        ixx = w * (x * x * l0).sum() - mass * com[0] ** 2
        iyy = w * l2.sum() - mass * com[1] ** 2
        izz = ixx + iyy
        return MassProperties(float(mass), com, np.eye(3) * izz, False)
    x, y = grid[:, 0], grid[:, 1]
    s = {"x": w * (x * l0).sum(), "y": w * (y * l0).sum(), "z": w * l1.sum(),
         "xx": w * (x * x * l0).sum(), "yy": w * (y * y * l0).sum(), "zz": w * l2.sum(),
         "xy": w * (x * y * l0).sum(), "xz": w * (x * l1).sum(), "yz": w * (y * l1).sum()}
    com = np.array([s["x"], s["y"], s["z"]]) / mass
    # second moments about the centre of mass
    c = {k: s[k] - mass * com["xyz".index(k[0])] * com["xyz".index(k[1])]
         for k in ("xx", "yy", "zz", "xy", "xz", "yz")}
    inertia = np.array([[c["yy"] + c["zz"], -c["xy"], -c["xz"]],
                        [-c["xy"], c["xx"] + c["zz"], -c["yz"]],
                        [-c["xz"], -c["yz"], c["xx"] + c["yy"]]])
    return MassProperties(float(mass), com, inertia, False)


def principal_frame(template: ClumpTemplate, density: float):
    """(member offsets (M, 3) in the principal frame [L], principal moments (3,)
    [M L^2], mass [M], rotation R (3, 3) from the principal frame to the template
    frame, centre of mass in the template frame, MassProperties). 2D clumps keep their
    frame (rotation about z only)."""
    props = mass_properties(template.centers, template.radii, density)
    dim = template.dim
    rel = np.zeros((template.n_members, 3))
    rel[:, :dim] = template.centers - props.com
    if dim == 2:
        izz = props.inertia[2, 2]
        return rel, np.full(3, izz), props.mass, np.eye(3), props.com, props
    moments, axes = np.linalg.eigh(props.inertia)
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1.0
    return rel @ axes, moments, props.mass, axes, props.com, props


# ------------------------------------------------------------------ quaternions
def quat_from_matrix(R) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of the rotation matrix R (3, 3)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.trace(R)
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        k = int(np.argmax(np.diag(R)))
        i, j = (k + 1) % 3, (k + 2) % 3
        s = 2.0 * math.sqrt(1.0 + R[k, k] - R[i, i] - R[j, j])
        q = np.zeros(4)
        q[0] = (R[j, i] - R[i, j]) / s
        q[1 + k] = 0.25 * s
        q[1 + i] = (R[i, k] + R[k, i]) / s
        q[1 + j] = (R[j, k] + R[k, j]) / s
    q = np.asarray(q, dtype=np.float64)
    return q / np.linalg.norm(q)


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) (w, x, y, z)."""
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def random_quaternions(n: int, rng, dim: int = 3) -> np.ndarray:
    """n uniformly random orientations (3D: uniform on SO(3), Shoemake 1992; 2D: a
    uniform angle about z)."""
    if dim == 2:
        a = rng.uniform(0.0, 2.0 * math.pi, n)
        return np.stack([np.cos(a / 2), np.zeros(n), np.zeros(n), np.sin(a / 2)], axis=1)
    u1, u2, u3 = rng.random((3, n))
    s1, s2 = np.sqrt(1 - u1), np.sqrt(u1)
    return np.stack([s2 * np.cos(2 * math.pi * u3), s1 * np.sin(2 * math.pi * u2),
                     s1 * np.cos(2 * math.pi * u2), s2 * np.sin(2 * math.pi * u3)], axis=1)


# ------------------------------------------------------------------- clump sets
@dataclass
class ClumpSet:
    """Bodies to simulate: ``templates`` (list of ClumpTemplate), for each body the
    index of its template ``kind`` (B,), its centre of mass ``x`` (B, dim) [L] and its
    orientation ``q`` (B, 4) (principal frame to world); ``density`` [M/L^3]. Built
    with :func:`place`."""

    templates: list
    kind: np.ndarray
    x: np.ndarray
    q: np.ndarray
    density: float
    frames: list = field(default_factory=list)  # principal_frame of each template

    def __post_init__(self):
        if not (math.isfinite(self.density) and self.density > 0):
            raise InputError(f"clumps: density must be finite and > 0, got {self.density!r}")
        self.kind = np.asarray(self.kind, dtype=np.int64)
        self.x = np.asarray(self.x, dtype=np.float64)
        self.q = np.asarray(self.q, dtype=np.float64)
        if len(self.kind) and (self.kind.min() < 0 or self.kind.max() >= len(self.templates)):
            raise InputError(f"clumps: template index {int(self.kind.max())} out of range "
                             f"({len(self.templates)} templates)")
        if not self.frames:
            self.frames = [principal_frame(t, self.density) for t in self.templates]

    @property
    def n(self) -> int:
        return len(self.kind)

    @property
    def dim(self) -> int:
        return self.x.shape[1]


def place(templates, kind, positions, orientations, density: float) -> ClumpSet:
    """A ClumpSet with each body's *template origin* at ``positions`` and the template
    frame rotated by ``orientations`` (quaternions): the centres of mass follow."""
    cs = ClumpSet(list(templates), kind, np.zeros_like(np.asarray(positions, float)),
                  np.zeros((len(kind), 4)), density)
    pos = np.asarray(positions, dtype=np.float64)
    dim = pos.shape[1]
    q_in = np.asarray(orientations, dtype=np.float64)
    for b, k in enumerate(cs.kind):
        rel, moments, mass, axes, com, _ = cs.frames[k]
        R_orient = quat_to_matrix(q_in[b])
        com3 = np.zeros(3)
        com3[:dim] = com
        cs.x[b] = (pos[b] if dim == 3 else np.r_[pos[b], 0.0])[:dim] + (R_orient @ com3)[:dim]
        cs.q[b] = quat_from_matrix(R_orient @ axes)
    return cs


def expand(clumps: ClumpSet):
    """The member spheres of every body in the world: centres (M, dim) [L], radii
    (M,) [L], the body of each member (M,) and its offset in the principal frame
    (M, 3) [L]."""
    xs, rs, body, offs = [], [], [], []
    dim = clumps.dim
    R = quat_to_matrix(clumps.q)
    for b, k in enumerate(clumps.kind):
        rel = clumps.frames[k][0]
        world = rel @ R[b].T
        x3 = np.zeros(3)
        x3[:dim] = clumps.x[b]
        xs.append((x3 + world)[:, :dim])
        rs.append(clumps.templates[k].radii)
        body.append(np.full(len(rel), b))
        offs.append(rel)
    if not xs:
        return (np.zeros((0, dim)), np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros((0, 3)))
    return (np.concatenate(xs), np.concatenate(rs), np.concatenate(body).astype(np.int64),
            np.concatenate(offs))


def with_members(free, clumps: ClumpSet, rotation: bool = True, fixed=None,
                 velocities=None, angular_velocities=None):
    """The spheres of a simulation with clumps and its Bodies bundle.

    ``free``: Particles of the free spheres (None: none); the members follow them. A
    member's mass is its body's (the effective mass of its contacts' dashpots, as
    LIGGGHTS' multisphere does). ``fixed`` (B,) holds bodies in place; ``velocities``
    (B, dim) [L/T] and ``angular_velocities`` (B, 3) [1/T] (2D: (B,)) are the bodies'
    at t = 0. Returns (Particles of every sphere, Bodies, index of the first member)."""
    dim = clumps.dim
    if free is not None and free.dim != dim:
        raise InputError(f"clumps: {dim}D bodies with {free.dim}D free particles")
    xm, rm, body, offset = expand(clumps)
    n_free = 0 if free is None else free.n
    b_count = clumps.n
    masses = np.array([clumps.frames[k][2] for k in clumps.kind])
    moments = np.array([clumps.frames[k][1] for k in clumps.kind]).reshape(b_count, 3)
    m_member = masses[body]
    parts = [(free.x, free.r, free.m, free.inertia, free.fixed)] if n_free else []
    parts.append((xm, rm, m_member, INERTIA_FACTOR[dim] * m_member * rm**2,
                  np.zeros(len(rm), dtype=bool)))
    x, r, m, inertia, fx = (np.concatenate([p[k] for p in parts]) for k in range(5))
    spheres = Particles(x, r, m, inertia, fx)
    fixed = np.zeros(b_count, dtype=bool) if fixed is None else np.asarray(fixed, bool)
    if fixed.shape != (b_count,):
        raise InputError(f"clumps: fixed: expected {b_count} flags, got shape {fixed.shape}")
    x3 = np.zeros((b_count, 3))
    x3[:, :dim] = clumps.x
    v3 = np.zeros((b_count, 3))
    if velocities is not None:
        v = np.asarray(velocities, dtype=np.float64)
        if v.shape != (b_count, dim) or not np.isfinite(v).all():
            raise InputError(f"clumps: velocities: expected {b_count} finite vectors of {dim}")
        v3[:, :dim] = v
    L = np.zeros((b_count, 3))
    if angular_velocities is not None:
        w = np.asarray(angular_velocities, dtype=np.float64)
        w = w.reshape(b_count, 1) * np.array([[0.0, 0.0, 1.0]]) if dim == 2 else w.reshape(b_count, 3)
        if not np.isfinite(w).all():
            raise InputError("clumps: angular_velocities: must be finite")
        R = quat_to_matrix(clumps.q)
        # L = R diag(I) R^T omega
        L = np.einsum("bij,bj->bi", R, moments * np.einsum("bji,bj->bi", R, w))
    v3[fixed] = 0.0
    L[fixed] = 0.0
    inv_m = np.where(fixed, 0.0, 1.0 / masses)
    inv_I = np.where((fixed | (not rotation))[:, None], 0.0, 1.0 / moments)
    if not rotation:
        L[:] = 0.0
    start = np.zeros(b_count + 1, dtype=np.int64)
    np.add.at(start, body + 1, 1)
    start = np.cumsum(start)
    sphere_body = np.full(spheres.n, -1, dtype=np.int64)
    sphere_body[n_free:] = body
    z3 = np.zeros((b_count, 3))
    bodies = Bodies(x3, clumps.q.copy(), v3, L, masses, moments, inv_m, inv_I, z3.copy(),
                    z3.copy(), z3.copy(), start, np.arange(n_free, spheres.n, dtype=np.int64),
                    offset, sphere_body, np.zeros((b_count, 6)), np.zeros((b_count, 6)))
    return spheres, bodies, n_free


def clumps_from_members(x, r, body, density: float, names=None) -> ClumpSet:
    """A ClumpSet from member spheres in the world (a particle file's ``body`` column):
    each body id >= 0 is one clump whose template is its members as they lie
    (orientation: the identity of that frame)."""
    x = np.asarray(x, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    body = np.asarray(body, dtype=np.int64)
    ids = np.unique(body[body >= 0])
    templates, positions = [], []
    for ident in ids:
        members = np.flatnonzero(body == ident)
        origin = x[members[0]]
        templates.append(ClumpTemplate(f"body {ident}" if names is None else names[ident],
                                       x[members] - origin, r[members]))
        positions.append(origin)
    dim = x.shape[1]
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(ids), 1))
    return place(templates, np.arange(len(ids)), np.array(positions).reshape(-1, dim), q, density)
