"""Rigid bodies (clumps) in the critical-step analysis (docs/time-step-elements.md).

A body's degrees of freedom are the velocity v and angular velocity omega of its centre
of mass; a member sphere at the arm a = R d from it moves with u_m = v + omega x a and
omega_m = omega, so the member contacts' stiffness maps to the body as
K_body = G^T K_members G. The mass matrix is block diagonal: m I and the world inertia
tensor I_w = R I_principal R^T of each body, whose M^-1/2 block is
R diag(I_k^-1/2) R^T. Free spheres keep their own DOFs; a sphere that belongs to a body
is an "owner" no more. The central-difference scheme of the engine for bodies
(:mod:`demstep.kernels.clumps`) linearised about rest is the central difference with
this mass matrix, so lambda_max(M^-1/2 K M^-1/2) gives its exact critical step.

Owners are numbered: the free spheres in their order, then the bodies.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from demstep.clumps import check_connected, mass_properties
from demstep.errors import InputError
from demstep.kernels.timestep_kernels import owner_expand


@dataclass
class RigidBodies:
    """The bodies of an assembly: ``sphere_body`` (N,) the body of each sphere (-1:
    free), ``arm`` (N, 3) [L] each member's centre relative to its body's centre of
    mass (world frame), body ``mass`` (B,) [M], world ``inertia`` (B, 3, 3) [M L^2]
    and ``fixed`` (B,) bodies (infinite mass)."""

    sphere_body: np.ndarray
    arm: np.ndarray
    mass: np.ndarray
    inertia: np.ndarray
    fixed: np.ndarray

    def __post_init__(self):
        self.sphere_body = np.asarray(self.sphere_body, dtype=np.int64)
        self.arm = np.ascontiguousarray(self.arm, dtype=np.float64)
        self.mass = np.asarray(self.mass, dtype=np.float64)
        self.inertia = np.asarray(self.inertia, dtype=np.float64).reshape(-1, 3, 3)
        self.fixed = np.asarray(self.fixed, dtype=bool)

    @property
    def n(self) -> int:
        return len(self.mass)

    @classmethod
    def from_members(cls, x, r, body, density: float) -> "RigidBodies":
        """Bodies made of the spheres at ``x`` (N, dim) [L] with radii ``r`` that share
        a ``body`` id (>= 0; -1: a free sphere), for a ``density``: the mass
        properties of each union of members (:func:`demstep.clumps.mass_properties`) in
        the world frame."""
        x = np.asarray(x, dtype=np.float64)
        body = np.asarray(body, dtype=np.int64)
        dim = x.shape[1]
        ids = np.unique(body[body >= 0])
        index = np.full(len(body), -1, dtype=np.int64)
        arm = np.zeros((len(body), 3))
        mass, inertia = [], []
        for b, ident in enumerate(ids):
            members = np.flatnonzero(body == ident)
            check_connected(x[members], r[members], f"body {ident}")
            props = mass_properties(x[members], r[members], density)
            index[members] = b
            arm[members, :dim] = x[members] - props.com
            mass.append(props.mass)
            inertia.append(props.inertia)
        return cls(index, arm, np.array(mass), np.array(inertia).reshape(-1, 3, 3),
                   np.zeros(len(ids), dtype=bool))


def owners(n_spheres: int, bodies: RigidBodies | None):
    """(owner of each sphere (N,), number of free spheres, number of owners)."""
    if bodies is None or bodies.n == 0:
        return np.arange(n_spheres, dtype=np.int64), n_spheres, n_spheres
    sb = bodies.sphere_body
    free = sb < 0
    owner = np.empty(n_spheres, dtype=np.int64)
    n_free = int(free.sum())
    owner[free] = np.arange(n_free)
    owner[~free] = n_free + sb[~free]
    return owner, n_free, n_free + bodies.n


def _inv_sqrt_blocks(inertia: np.ndarray, dim: int, fixed) -> np.ndarray:
    """I^-1/2 of world inertia tensors (B, n_rot, n_rot) (2D: the zz entry); zero for
    fixed bodies."""
    if dim == 2:
        out = (1.0 / np.sqrt(inertia[:, 2, 2]))[:, None, None]
    else:
        w, V = np.linalg.eigh(inertia)
        out = np.einsum("bij,bj,bkj->bik", V, 1.0 / np.sqrt(w), V)
    out = out.copy()
    out[fixed] = 0.0
    return out


class OwnerMap:
    """Scaled owner DOFs <-> sphere DOFs, the arrays of the compiled owner product
    (:func:`demstep.kernels.timestep_kernels.owner_contact_matvec`, which also reduces
    sphere forces back to scaled owner forces). ``expand`` takes q (owners, nd), the
    DOFs scaled by M^1/2, to physical sphere displacements (N, nd). Spheres' own scales
    come from ``sphere_scale`` (N, nd) (M^-1/2 of free spheres)."""

    def __init__(self, sphere_scale: np.ndarray, bodies: RigidBodies, dim: int, rotation: bool):
        n = sphere_scale.shape[0]
        self.nd = sphere_scale.shape[1]
        self.owner, self.n_free, self.n_owners = owners(n, bodies)
        self.rotation = rotation
        self.dim = dim
        sb = bodies.sphere_body
        self.free_index = np.flatnonzero(sb < 0)
        self.member_index = np.flatnonzero(sb >= 0)
        self.member_body = sb[self.member_index]
        #: the member rows of body b: body_members[body_start[b]:body_start[b + 1]]
        #: (in member order)
        self.body_members = np.argsort(self.member_body, kind="stable")
        self.body_start = np.searchsorted(self.member_body[self.body_members],
                                          np.arange(bodies.n + 1))
        self.arm = bodies.arm[self.member_index]
        self.free_scale = sphere_scale[self.free_index]
        self.body_trans = np.where(bodies.fixed, 0.0, 1.0 / np.sqrt(bodies.mass))
        self.body_rot = (_inv_sqrt_blocks(bodies.inertia, dim, bodies.fixed) if rotation
                         else np.zeros((bodies.n, 0, 0)))

    def expand(self, q: np.ndarray, n_spheres: int, out: np.ndarray | None = None) -> np.ndarray:
        """The spheres' physical DOFs (N, nd) of scaled owner DOFs q (owners, nd) (into
        ``out`` when given): :func:`demstep.kernels.timestep_kernels.owner_expand`."""
        u = np.empty((n_spheres, self.nd)) if out is None else out
        return owner_expand(self, q, u)


# ---------------------------------------------------------- element bounds for bodies
def cross_matrix(v):
    """[v]x (C, 3, 3)."""
    X = np.zeros(v.shape[:-1] + (3, 3))
    X[..., 0, 1], X[..., 0, 2] = -v[..., 2], v[..., 1]
    X[..., 1, 0], X[..., 1, 2] = v[..., 2], -v[..., 0]
    X[..., 2, 0], X[..., 2, 1] = -v[..., 1], v[..., 0]
    return X


def contact_arms_from_owner(contacts, bodies: RigidBodies | None, dim: int):
    """For each contact, the vector from each side's owner centre to the contact point
    (C, 3) [L]: r_i = arm_i + a_i n, r_j = arm_j - a_j n (a wall side: zero)."""
    n3 = np.zeros((contacts.n, 3))
    n3[:, :dim] = contacts.normal
    ri = contacts.arm_i[:, None] * n3
    rj = -contacts.arm_j[:, None] * n3
    if bodies is not None and bodies.n:
        ri = ri + bodies.arm[contacts.i]
        pp = contacts.j >= 0
        rj[pp] = rj[pp] + bodies.arm[contacts.j[pp]]
    rj[contacts.j < 0] = 0.0
    return ri, rj


def owner_mass_shares(particles, contacts, bodies: RigidBodies | None, rotation: bool):
    """The uniform Rayleigh partition over owners: each owner's mass and inertia
    (3x3, world) divided by its number of contacts (walls included). Returns for sides
    i and j the reciprocal mass (C,) and the inverse inertia share (C, 3, 3) (zero:
    walls, fixed). Only the owners the contacts touch are looked at (a group of added
    contacts touches a few of them)."""
    owner, n_free, _ = owners(particles.n, bodies)
    oi = owner[contacts.i]
    pp = contacts.j >= 0
    oj = owner[np.maximum(contacts.j, 0)]
    used, slot = np.unique(np.concatenate([oi, oj[pp]]), return_inverse=True)
    counts = np.bincount(slot, minlength=len(used)).astype(np.float64)
    si, sj = slot[:contacts.n], np.zeros(contacts.n, dtype=np.int64)
    sj[pp] = slot[contacts.n:]
    inv_m = np.zeros(len(used))
    inv_I = np.zeros((len(used), 3, 3))
    free = used < n_free
    spheres = (np.flatnonzero(owner < n_free)[used[free]] if bodies is not None and bodies.n
               else used[free])
    inv_m[free] = np.where(particles.fixed[spheres], 0.0, 1.0 / particles.m[spheres])
    if rotation:
        iso = np.where(particles.fixed[spheres], 0.0, 1.0 / particles.inertia[spheres])
        inv_I[free] = iso[:, None, None] * np.eye(3)
    if bodies is not None and bodies.n and not free.all():
        b = used[~free] - n_free
        inv_m[~free] = np.where(bodies.fixed[b], 0.0, 1.0 / bodies.mass[b])
        if rotation:
            if particles.dim == 2:
                inv_I[~free] = (1.0 / bodies.inertia[b, 2, 2])[:, None, None] * np.eye(3)
            else:
                inv_I[~free] = np.linalg.inv(bodies.inertia[b])
            inv_I[np.flatnonzero(~free)[bodies.fixed[b]]] = 0.0
    mi = inv_m[si] * counts[si]
    Ii = inv_I[si] * counts[si][:, None, None]
    mj = np.where(pp, inv_m[sj] * counts[sj], 0.0)
    Ij = np.where(pp[:, None, None], inv_I[sj] * counts[sj][:, None, None], 0.0)
    return mi, Ii, mj, Ij


def body_element_matrices(particles, contacts, bodies, rotation: bool, rows=None):
    """W = B M_e^-1 B^T (C, s, s) of every contact element with owners' shares
    (:func:`owner_mass_shares`) and the local spring and dashpot matrices D, G (C, s, s)
    (k_n n n^T + k_t (I - n n^T), likewise c_n, c_t), global frame; 2D in the plane.

    The strain is the slip Delta at the contact point (s = 3) or, with rotation and
    rolling resistance in the contacts, (Delta, phi) (s = 6) with phi = omega_j -
    omega_i the relative rotation of the owners (a member rotates with its body): then
    D and G hold also k_r (I - n n^T) + k_w n n^T and c_r, c_w on phi (2D: k_r, c_r on
    phi_z), and W = J M^-1 J^T with, per side, dDelta/domega = +/-[r]x and
    dphi/domega = -/+I (``r`` the arm from the owner's centre to the contact point).

    ``rows`` (indices): the elements of those contacts only, with the shares of all."""
    dim = particles.dim
    mi, Ii, mj, Ij = owner_mass_shares(particles, contacts, bodies, rotation)
    if rows is not None:
        mi, Ii, mj, Ij = mi[rows], Ii[rows], mj[rows], Ij[rows]
        contacts = contacts.subset(rows)
    ri, rj = contact_arms_from_owner(contacts, bodies, dim)
    W = (mi + mj)[:, None, None] * np.eye(3)
    if rotation:
        Xi, Xj = cross_matrix(ri), cross_matrix(rj)
        W = W + np.einsum("cij,cjk,clk->cil", Xi, Ii, Xi) + np.einsum("cij,cjk,clk->cil", Xj, Ij, Xj)
    n3 = np.zeros((contacts.n, 3))
    n3[:, :dim] = contacts.normal
    P = np.einsum("ci,cj->cij", n3, n3)
    tang = np.eye(3) - P
    if dim == 2:
        tang[:, 2, 2] = 0.0  # no out-of-plane slip in 2D
        W[:, 2, :] = 0.0
        W[:, :, 2] = 0.0
    D = contacts.k_n[:, None, None] * P + contacts.k_s[:, None, None] * tang
    G = contacts.c_n[:, None, None] * P + contacts.c_t[:, None, None] * tang
    if not (rotation and contacts.has_rolling):
        return W, D, G
    c = contacts.n
    # slip-rotation coupling: -(X_i I_i + X_j I_j); rotations: I_i + I_j
    Wr = np.zeros((c, 6, 6))
    Wr[:, :3, :3] = W
    coupling = -(np.einsum("cij,cjk->cik", Xi, Ii) + np.einsum("cij,cjk->cik", Xj, Ij))
    Wr[:, :3, 3:] = coupling
    Wr[:, 3:, :3] = coupling.transpose(0, 2, 1)
    Wr[:, 3:, 3:] = Ii + Ij
    if dim == 2:  # disks: phi_z only
        roll = np.zeros((c, 3, 3))
        roll[:, 2, 2] = 1.0
        twist = np.zeros((c, 3, 3))
        Wr[:, 2, :] = 0.0
        Wr[:, :, 2] = 0.0
        Wr[:, 3:5, :] = 0.0
        Wr[:, :, 3:5] = 0.0
    else:
        roll, twist = tang, P
    Dr = np.zeros((c, 6, 6))
    Gr = np.zeros((c, 6, 6))
    Dr[:, :3, :3] = D
    Gr[:, :3, :3] = G
    Dr[:, 3:, 3:] = contacts.k_r[:, None, None] * roll + contacts.k_w[:, None, None] * twist
    Gr[:, 3:, 3:] = contacts.c_r[:, None, None] * roll + contacts.c_w[:, None, None] * twist
    return Wr, Dr, Gr


def body_element_dt(particles, contacts, bodies, rotation: bool, mass_damping: float = 0.0,
                    stiffness_damping: float = 0.0, rows=None) -> np.ndarray:
    """Critical step (C,) [T] of each contact element of an assembly with bodies, the
    owners' masses and inertia tensors split uniformly among their contacts (Rayleigh's
    partition, rigorous as :func:`demstep.timestep.elements.coupled_element_damped_dt`):
    the largest root sigma of det(sigma^2 I - sigma (a1 I + W^1/2 (a2 D + G) W^1/2) -
    W^1/2 D W^1/2) = 0 on the element's strain space (the slip, and with rolling
    resistance the relative rotation: :func:`body_element_matrices`), dt = 2 / sigma.
    ``rows`` (indices): of those contacts only (the shares still of all of them)."""
    W, D, G = body_element_matrices(particles, contacts, bodies, rotation, rows)
    w, V = np.linalg.eigh(W)
    w = np.clip(w, 0.0, None)
    Wh = np.einsum("cij,cj,ckj->cik", V, np.sqrt(w), V)
    B = np.einsum("cij,cjk,ckl->cil", Wh, D, Wh)
    A = np.einsum("cij,cjk,ckl->cil", Wh, stiffness_damping * D + G, Wh)
    if not A.any() and mass_damping == 0.0:
        lam = np.linalg.eigvalsh(B)[:, -1]
        with np.errstate(divide="ignore"):
            return np.where(lam > 0, 2.0 / np.sqrt(lam), np.inf)
    c = W.shape[0]
    s = W.shape[1]  # 3, or 6 with rolling resistance
    L = np.zeros((c, 2 * s, 2 * s))
    L[:, :s, s:] = np.eye(s)
    L[:, s:, :s] = B
    L[:, s:, s:] = A + mass_damping * np.eye(s)
    ev = np.linalg.eigvals(L)
    real = np.where(np.abs(ev.imag) <= 1e-9 * np.maximum(np.abs(ev).max(axis=1, keepdims=True), 1e-300),
                    ev.real, -np.inf)
    sigma = real.max(axis=1)
    with np.errstate(divide="ignore"):
        return np.where(sigma > 0, 2.0 / sigma, np.inf)


def likely_stiffest_elements(particles, contacts, bodies, rotation: bool,
                             count: int = 32) -> np.ndarray:
    """Rows of the contacts (at most 2 ``count``) whose elements are likely the stiffest
    and the most damped: the ``count`` largest k_max (m_i^-1 + m_j^-1) and c_max (m_i^-1 +
    m_j^-1) with the owners' mass shares (:func:`owner_mass_shares`; k_max, c_max the
    largest spring and dashpot of each contact). The min of :func:`body_element_dt` over
    any rows is at least the min over all (an upper bound on it, for a quick test that
    the bound cannot be large enough); these rows make it close."""
    mi, _, mj, _ = owner_mass_shares(particles, contacts, bodies, rotation)
    width = mi + mj
    picks = []
    for coefficients in ((contacts.k_n, contacts.k_s), (contacts.c_n, contacts.c_t)):
        score = width * np.maximum(*coefficients)
        picks.append(np.argsort(score)[-count:])
    return np.unique(np.concatenate(picks))


def body_stiffness_diagonal(particles, contacts, bodies, rotation: bool, springs="k"):
    """The diagonal of K (or C with springs='c') per owner DOF (owners, nd), for the
    nodal rule: sum over contacts of diag(B^T D B) of each side, plus with rotation the
    rolling and twisting springs k_r (1 - n_k^2) + k_w n_k^2 (2D: k_r) on the owner's
    rotations (a member rotates with its body)."""
    dim = particles.dim
    owner, n_free, n_owners = owners(particles.n, bodies)
    ri, rj = contact_arms_from_owner(contacts, bodies, dim)
    n3 = np.zeros((contacts.n, 3))
    n3[:, :dim] = contacts.normal
    kn, kt = (contacts.k_n, contacts.k_s) if springs == "k" else (contacts.c_n, contacts.c_t)
    kr, kw = (contacts.k_r, contacts.k_w) if springs == "k" else (contacts.c_r, contacts.c_w)
    rolling = rotation and contacts.has_rolling
    P = np.einsum("ci,cj->cij", n3, n3)
    D = kn[:, None, None] * P + kt[:, None, None] * (np.eye(3) - P)
    nrot = (1 if dim == 2 else 3) if rotation else 0
    nd = dim + nrot
    diag = np.zeros((n_owners, nd))
    for side, r in ((contacts.i, ri), (contacts.j, rj)):
        ok = side >= 0
        o = owner[np.maximum(side, 0)][ok]
        dt_ = np.einsum("cii->ci", D)[ok, :dim]
        np.add.at(diag, (o, slice(0, dim)), dt_)
        if rotation:
            X = cross_matrix(r[ok])
            rot = np.einsum("cji,cjk,cki->ci", X, D[ok], X)  # diag of X^T D X
            if dim == 2:
                np.add.at(diag, (o, slice(dim, nd)), rot[:, 2:3])
            else:
                np.add.at(diag, (o, slice(dim, nd)), rot)
        if rolling:
            if dim == 2:
                np.add.at(diag, (o, slice(dim, nd)), kr[ok, None])
            else:
                n2 = n3[ok] ** 2
                np.add.at(diag, (o, slice(dim, nd)),
                          kr[ok, None] * (1.0 - n2) + kw[ok, None] * n2)
    return diag


def owner_mass_diagonal(particles, bodies, rotation: bool) -> tuple[np.ndarray, np.ndarray]:
    """(mass diagonal per owner DOF (owners, nd), free flags (owners,))."""
    dim = particles.dim
    owner, n_free, n_owners = owners(particles.n, bodies)
    nrot = (1 if dim == 2 else 3) if rotation else 0
    diag = np.zeros((n_owners, dim + nrot))
    free_flag = np.zeros(n_owners, dtype=bool)
    sph = np.flatnonzero(owner < n_free) if bodies is not None and bodies.n else np.arange(particles.n)
    diag[owner[sph], :dim] = particles.m[sph, None]
    if rotation:
        diag[owner[sph], dim:] = particles.inertia[sph, None]
    free_flag[owner[sph]] = ~particles.fixed[sph]
    if bodies is not None and bodies.n:
        b = n_free + np.arange(bodies.n)
        diag[b, :dim] = bodies.mass[:, None]
        if rotation:
            if dim == 2:
                diag[b, dim:] = bodies.inertia[:, 2, 2][:, None]
            else:
                diag[b, dim:] = np.einsum("bii->bi", bodies.inertia)
        free_flag[b] = ~bodies.fixed
    return diag, free_flag


def check_bodies(particles, bodies):
    if bodies is None:
        return
    if bodies.sphere_body.shape != (particles.n,):
        raise InputError(f"bodies: expected a body index per sphere ({particles.n}), got "
                         f"{bodies.sphere_body.shape}")


