"""The exact critical step of an assembly, damped or not, matrix-free.

Undamped: dt = 2 / sqrt(lambda_max(A)), A = M^-1/2 K M^-1/2 (paper eqs. 2-3).

Damped (:mod:`demstep.timestep.damping`): dt = 2 / sigma_max, the largest root of
det(sigma^2 I - sigma C^ - K^) = 0 with C^ = M^-1/2 C M^-1/2, K^ = A. It is found by the
safeguarded iteration for the extreme eigenvalue of a quadratic pencil (Werner 1970;
Voss 2004, "Numerical methods for sparse nonlinear eigenvalue problems"): with q_k the
top eigenvector of the symmetric matrix A(sigma_k) = sigma_k C^ + K^,

    sigma_{k+1} = (c_k + sqrt(c_k^2 + 4 k_k)) / 2,  c_k = q_k.C^ q_k,  k_k = q_k.K^ q_k,

starting from sigma_0 = 0 (q_0 the top undamped mode). Every iterate is a value of the
Rayleigh functional, so sigma_k increases to sigma_max (quadratically at the end), and
each Lanczos solve is warm-started from the previous vector. The result is then
certified: sigma_up = sigma (1 + margin) is accepted as an upper bound on sigma_max
only when sigma_up^2 >= the residual-based upper bound on lambda_max(A(sigma_up))
(that makes sigma_up^2 I - A(sigma_up) positive semi-definite, and sigma_max is the only
root), else the margin grows. The certified step is 2 / sigma_up.

Every product with K^ or C^ is computed from the contact list by a compiled kernel
(no matrix is assembled: memory O(contacts)); systems up to
:data:`~demstep.timestep.eigen.DENSE_LIMIT` DOFs are assembled and solved densely.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse.linalg as spla

from demstep.contacts import ContactSet
from demstep.errors import InputError
from demstep.kernels.timestep_kernels import contact_energies, contact_matvec, scaled_contact_matvec
from demstep.particles import Particles
from demstep.timestep.assembly import assemble_stiffness, inverse_sqrt_mass
from demstep.timestep.damping import GlobalDamping
from demstep.timestep.eigen import DENSE_LIMIT, EIGSH_TOL, Eigenpair, top_eigenpair
from demstep.timestep.elements import dofs_per_particle
from demstep.timestep.stability import damped_sigma

#: relative convergence of the safeguarded iteration
SIGMA_RTOL = 1e-10
#: first relative margin tried when certifying sigma_max from above
CERTIFY_MARGIN = 1e-9


class ScaledContactOperator:
    """K^ = M^-1/2 K M^-1/2 and C^_d = M^-1/2 C_d M^-1/2 of an assembly as products.

    DOFs are (N, nd) per particle (translations, then rotations); fixed particles have
    infinite mass (their DOFs are scaled by zero). ``pencil(sigma)`` is the operator
    (1 + sigma a2) K^ + sigma C^_d; the mass-proportional part sigma a1 I of
    A(sigma) = sigma C^ + K^ is a shift added by the caller."""

    def __init__(self, particles: Particles, contacts: ContactSet, rotation: bool,
                 damping: GlobalDamping | None = None, bodies=None):
        if contacts.n and contacts.dim != particles.dim:
            raise InputError(f"contacts: dimension {contacts.dim} does not match the "
                             f"particles' {particles.dim}")
        self.particles = particles
        self.contacts = contacts
        self.rotation = bool(rotation)
        self.damping = damping or GlobalDamping()
        self.nd = dofs_per_particle(particles.dim, rotation)
        self.scale = inverse_sqrt_mass(particles, rotation).reshape(particles.n, self.nd)
        self.size = particles.n * self.nd
        self._work = np.empty_like(self.scale)
        self.bodies = bodies if bodies is not None and bodies.n else None
        self.owner_map = None
        if self.bodies is not None:
            from demstep.timestep.bodies import OwnerMap, check_bodies

            check_bodies(particles, self.bodies)
            self.owner_map = OwnerMap(self.scale, self.bodies, particles.dim, self.rotation)
            self.size = self.owner_map.n_owners * self.nd

    def springs(self, sigma: float):
        """(k_n, k_t) per contact of the pencil at ``sigma``."""
        a2 = self.damping.stiffness
        c = self.contacts
        if sigma == 0.0:
            return c.k_n, c.k_s
        return ((1.0 + sigma * a2) * c.k_n + sigma * c.c_n,
                (1.0 + sigma * a2) * c.k_s + sigma * c.c_t)

    def apply(self, x: np.ndarray, k_n, k_t) -> np.ndarray:
        """S K(k_n, k_t) S x for flat x (size,) (with bodies: G^T K G through the owner
        map, :mod:`demstep.timestep.bodies`)."""
        if self.owner_map is None:
            return scaled_contact_matvec(self.contacts, k_n, k_t, self.rotation, self.scale,
                                         x, self._work)
        om = self.owner_map
        u = om.expand(np.asarray(x).reshape(om.n_owners, self.nd), self.particles.n)
        y = contact_matvec(self.contacts, k_n, k_t, self.rotation, u)
        return om.reduce(y).reshape(-1)

    def stiffness(self, x):
        return self.apply(x, self.contacts.k_n, self.contacts.k_s)

    def dashpots(self, x):
        return self.apply(x, self.contacts.c_n, self.contacts.c_t)

    def pencil(self, sigma: float) -> spla.LinearOperator:
        k_n, k_t = self.springs(sigma)
        return spla.LinearOperator((self.size, self.size), dtype=np.float64,
                                   matvec=lambda x: self.apply(np.ravel(x), k_n, k_t))

    def dense_pencil(self, sigma: float) -> np.ndarray:
        k_n, k_t = self.springs(sigma)
        if self.owner_map is not None:  # small systems: column by column
            return np.stack([self.apply(e, k_n, k_t) for e in np.eye(self.size)], axis=1)
        springs = replace(self.contacts, k_n=k_n, k_s=k_t)
        return assemble_stiffness(self.particles, springs, self.rotation,
                                  scale=self.scale.reshape(-1)).toarray()

    def top(self, sigma: float, v0=None, dense_limit: int = DENSE_LIMIT,
            tol: float = EIGSH_TOL) -> Eigenpair:
        """Top eigenpair of the pencil at ``sigma`` (without the a1 shift)."""
        return top_eigenpair(self.pencil(sigma), v0=v0, dense_limit=dense_limit, tol=tol,
                             dense=lambda: self.dense_pencil(sigma))

    def rayleigh_terms(self, q: np.ndarray):
        """(k_q, c_q): q.K^ q and q.C^ q for a unit vector q (C^ with a1 and a2)."""
        kq = float(q @ self.stiffness(q))
        cq = float(q @ self.dashpots(q)) if self.contacts.damped else 0.0
        return kq, cq + self.damping.mass + self.damping.stiffness * kq

    def damping_bound(self) -> float:
        """An upper bound on lambda_max(C^) [1/T] (C^ with a1, a2 and the dashpots) from
        Rayleigh's theorem on the coupled elements (uniform mass split)."""
        from demstep.timestep.elements import coupled_element_lambda
        from demstep.timestep.mass_split import element_mass

        d = self.damping
        bound = d.mass
        if self.contacts.n and self.bodies is not None:
            from demstep.timestep.bodies import body_element_matrices

            # lambda_max(W^1/2 X W^1/2) <= lambda_max(X) lambda_max(W) per element
            W, D, G = body_element_matrices(self.particles, self.contacts, self.bodies,
                                            self.rotation)
            wmax = np.linalg.eigvalsh(W)[:, -1]
            if d.stiffness:
                bound += d.stiffness * float(np.max(np.linalg.eigvalsh(D)[:, -1] * wmax))
            if self.contacts.damped:
                bound += float(np.max(np.linalg.eigvalsh(G)[:, -1] * wmax))
        elif self.contacts.n:
            mass = element_mass(self.particles, self.contacts)
            if d.stiffness:
                bound += d.stiffness * float(coupled_element_lambda(self.contacts, mass,
                                                                    self.rotation).max())
            if self.contacts.damped:
                dashpots = replace(self.contacts, k_n=self.contacts.c_n, k_s=self.contacts.c_t)
                bound += float(coupled_element_lambda(dashpots, mass, self.rotation).max())
        return bound

    def mode_shares(self, q: np.ndarray):
        """Where the mode q (unit, mass-scaled) lives: per owner (particle, or body) the
        translational and rotational shares of its kinetic energy (all shares sum to 1),
        and per contact its share of the strain energy (C,)."""
        dim = self.particles.dim
        qq = (q.reshape(-1, self.nd)) ** 2
        trans = qq[:, :dim].sum(axis=1)
        rot = qq[:, dim:].sum(axis=1)
        total = trans.sum() + rot.sum()
        u = self.displacement(q)
        energy = contact_energies(self.contacts, self.contacts.k_n, self.contacts.k_s,
                                  self.rotation, u)
        e_sum = energy.sum()
        return (trans / total, rot / total,
                energy / e_sum if e_sum > 0 else energy)

    def displacement(self, q: np.ndarray) -> np.ndarray:
        """The physical mode shape of every sphere (N, nd) [L; rad for rotations]: M^-1/2 q
        (with bodies, the members move with their bodies)."""
        if self.owner_map is not None:
            return self.owner_map.expand(q.reshape(-1, self.nd), self.particles.n)
        return self.scale * q.reshape(self.scale.shape)


@dataclass
class ExactStep:
    """The exact critical step of an assembly.

    ``dt`` [T]: the certified critical step (from an upper bound on sigma_max);
    ``dt_undamped`` [T]: the same without any damping (certified likewise);
    ``sigma`` [1/T]: the converged largest root (its Ritz estimate);
    ``lambda_undamped`` [1/T^2]: the Ritz value of lambda_max(M^-1 K);
    ``mode`` (size,): the critical mode, unit and mass-scaled (q = M^1/2 u);
    ``iterations``: safeguarded iterations (0 undamped); ``damped``: whether damping
    entered."""

    dt: float
    dt_undamped: float
    sigma: float
    lambda_undamped: float
    mode: np.ndarray
    iterations: int
    damped: bool
    operator: ScaledContactOperator


def exact_critical_step(particles: Particles, contacts: ContactSet, rotation: bool,
                        damping: GlobalDamping | None = None, v0: np.ndarray | None = None,
                        dense_limit: int = DENSE_LIMIT, rtol: float = SIGMA_RTOL,
                        max_iter: int = 100, bodies=None) -> ExactStep:
    """Exact (and certified) critical step, with contact dashpots and global damping when
    present; ``v0`` warm-starts the eigensolver (a previous ``mode``); ``bodies``
    (:class:`demstep.timestep.bodies.RigidBodies`): clumps, six DOFs each."""
    op = ScaledContactOperator(particles, contacts, rotation, damping, bodies)
    if contacts.n == 0 and not op.damping.mass:
        raise InputError("contacts: the assembly has no contacts")
    top = op.top(0.0, v0=v0, dense_limit=dense_limit)
    lam = top.value
    dt_undamped = 2.0 / np.sqrt(top.upper) if top.upper > 0 else np.inf
    damped = contacts.damped or op.damping.active
    if not damped:
        return ExactStep(float(dt_undamped), float(dt_undamped), float(np.sqrt(lam)), lam,
                         top.vector, 0, False, op)
    a1 = op.damping.mass
    q = top.vector
    sigma = float(damped_sigma(*op.rayleigh_terms(q)))
    iterations = 0
    while iterations < max_iter:
        iterations += 1
        top = op.top(sigma, v0=q, dense_limit=dense_limit)
        q = top.vector
        new = float(damped_sigma(*op.rayleigh_terms(q)))
        converged = new <= sigma * (1.0 + rtol)
        sigma = max(sigma, new)
        if converged:
            break
    # certify from above. First in closed form: for s >= sigma, lambda_max(A(s)) <=
    # U + (s - sigma) Lambda_C with U the residual bound at sigma and Lambda_C >=
    # lambda_max(C^) from the (rigorous) element bounds of K and C_d; sigma_up is the
    # root of s^2 = U + (s - sigma) Lambda_C. When that bound is loose, check candidates
    # with the solver: sigma_up^2 >= upper bound of lambda_max(A(sigma_up)).
    upper = top.upper + a1 * sigma
    lam_c = op.damping_bound()
    up = float(damped_sigma(max(upper - sigma * lam_c, 0.0), lam_c))
    if not up <= sigma * (1.0 + 1e-6):
        margin = CERTIFY_MARGIN
        for _ in range(60):
            up = sigma * (1.0 + margin)
            check = op.top(up, v0=q, dense_limit=dense_limit)
            if up * up >= check.upper + a1 * up:
                break
            margin *= 4.0
        else:  # pragma: no cover - the iteration always converges for PSD K, C
            raise RuntimeError("exact damped step: could not certify sigma_max")
    return ExactStep(float(2.0 / up), float(dt_undamped), sigma, lam, q, iterations, True, op)
