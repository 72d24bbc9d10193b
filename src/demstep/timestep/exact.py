"""The exact critical step of an assembly, damped or not, matrix-free.

Undamped: dt = 2 / sqrt(lambda_max(A)), A = M^-1/2 K M^-1/2 (paper eqs. 2-3).

Damped (:mod:`demstep.timestep.damping`): dt = 2 / sigma_max, the largest root of
det(sigma^2 I - sigma C^ - K^) = 0 with C^ = M^-1/2 C M^-1/2, K^ = A. It is found by the
safeguarded iteration for the extreme eigenvalue of a quadratic pencil (Werner 1970;
Voss 2004, "Numerical methods for sparse nonlinear eigenvalue problems"): with q_k the
top eigenvector of the symmetric matrix A(sigma_k) = sigma_k C^ + K^,

    sigma_{k+1} = (c_k + sqrt(c_k^2 + 4 k_k)) / 2,  c_k = q_k.C^ q_k,  k_k = q_k.K^ q_k,

starting from the best of the undamped solve's top Ritz vectors (q_0 the top undamped
mode among them; :meth:`ScaledContactOperator.subspace_start`). Every iterate is a value
of the Rayleigh functional, a lower bound on sigma_max; the iteration is Newton's method
on lambda_max(A(sigma)) = sigma^2 (quadratic at the end). Only the vector's direction
matters for the next iterate and its error enters quadratically, so the intermediate
solves are loose (FIRST_TOL, then LOOSE_TOL; warm-started from the previous vector).

The result is certified from above by one tight solve at a candidate
t = sigma (1 + margin) just above the iterate: t is an upper bound on sigma_max when
t^2 >= the residual-based upper bound on lambda_max(A(t)) (then t^2 I - A(t) is positive
semi-definite, which it is not below sigma_max). When the residual is a little too
large, the closed form from :meth:`ScaledContactOperator.damping_bound` (lambda_max(A)
grows at most with slope lambda_max(C^) beyond t) may still give a bound within 1e-6;
else the margin grows. When the certifying solve finds a larger eigenvalue than the
loose ones did (its start holds a random share that it must reduce by 5 decades, so it
explores the spectrum), t was below sigma_max and the iteration goes on. The certified
step is 2 / sigma_up, at most about the margin (4e-9) below the exact one.

Every product with K^ or C^ is computed from the contact list by a compiled kernel
(no matrix is assembled: memory O(contacts)); systems up to
:data:`~demstep.timestep.eigen.DENSE_LIMIT` DOFs are assembled and solved densely.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import scipy.sparse.linalg as spla

from demstep.timestep.contacts import ContactSet
from demstep.errors import InputError
from demstep.kernels.timestep_kernels import (chunked_scaled_contact_matvec, combine_rows,
                                              contact_chunks, contact_energies, contact_gram,
                                              contact_quadratic_forms, ordered_contact_runs,
                                              ordered_scaled_contact_matvec, owner_contact_matvec,
                                              scaled_contact_matvec)
from demstep.particles import Particles
from demstep.timestep.assembly import assemble_stiffness, inverse_sqrt_mass
from demstep.timestep.clumps import OwnerMap, body_element_matrices, check_bodies
from demstep.timestep.damping import GlobalDamping
from demstep.timestep.eigen import (DENSE_LIMIT, EIGSH_TOL, LANCZOS_ARRAYS, WARM_START_MIX,
                                    Eigenpair, Workspace, check_certified_tol, top_eigenpair)
from demstep.timestep.elements import coupled_element_lambda, dofs_per_particle
from demstep.timestep.guarantee import (CLAIM_SLACK, DENSE_ROUNDING, FAILURE, Guarantee,
                                        ProbableBound, check_failure, probable_upper_bound)
from demstep.timestep.mass_split import element_mass
from demstep.timestep.stability import damped_sigma

#: relative convergence of the safeguarded iteration
SIGMA_RTOL = 1e-10
#: relative margin of the first candidate upper bound t = sigma (1 + margin) on the
#: Lanczos path (the certifying solve needs a residual of about margin / 4: the
#: certified step is at most ~4e-9 below the exact one); on the dense path
CERTIFY_MARGIN = 4e-9
DENSE_CERTIFY_MARGIN = 1e-11
#: an upper bound (the candidate t or the closed form) is accepted within this of the
#: iterate, or within twice the margin when a looser ``tol`` (or a margin widened after
#: a certifying solve's residual was too large for it) makes that larger (the candidate
#: itself sits a margin above the iterate)
CLOSED_FORM_RTOL = 1e-8
#: eigen-tolerances of the intermediate solves of the safeguarded iteration: each only
#: needs a vector good enough for a Rayleigh-functional value, whose error is quadratic
#: in the vector's (measured: benchmarks/results/history-2026-11-30.md, "Exact damped
#: step: solver choices"). The first (the damped mode is new: its vector is only a
#: start for the next) at FIRST_TOL, the next ones at LOOSE_TOL.
FIRST_TOL = 1e-3
LOOSE_TOL = 1e-6
#: the certifying solve starts once a LOOSE_TOL solve moved the iterate by less than
#: this (relative); the iterate is then within ~TIGHT_SWITCH^2 of sigma_max
TIGHT_SWITCH = 1e-4
#: random share mixed into the warm starts (the previous iterate's vector) of the
#: intermediate solves, which certify nothing. Every solve that certifies (the undamped
#: one, and the damped iteration's certifying ones) starts from the fixed random vector
#: instead: a warm start sits on one eigenvector of a cluster, and Lanczos stops on it as
#: soon as its residual is small, before the random share has brought out a larger
#: eigenvalue of the cluster. Measured (eleventh session in
#: benchmarks/results/history-2026-12-01.md): on the dense FCC block of 1e5 spheres, warm
#: starts from the previous critical mode gave a "bound" 1.0e-4 and 1.9e-4 below the
#: largest eigenvalue at tolerances 1e-4 and 1e-5 (random shares 1e-2 to 0.3 alike); on a
#: 500-sphere block started from the second eigenvector, 1.4 % below at 1e-4 and 1e-5, and
#: at 1e-6 with a random share of 1e-4 (the certifying solves' before); cold starts
#: bounded it at every tolerance up to 1e-3 on all of them, for at most ~20 % more
#: products
CHAIN_MIX = 1e-6
#: top Ritz vectors of the undamped solve searched for the damped iteration's start
START_BLOCK = 4
#: contacts from which the products run on several threads (when numba has them). Each
#: product is three parallel regions; on a 2-core machine shared with other work a
#: region can wait for a descheduled thread, which cost 20x at 3e4 contacts (0.07 s ->
#: 1.4 s, loose 1e4), while an idle machine runs a product 1.6-1.8x faster on 2 threads
#: at 3e5 contacts (benchmarks/results/history-2026-11-30.md, "Exact damped step: solver
#: choices")
PARALLEL_MIN_CONTACTS = 100_000


class Springs(NamedTuple):
    """Per-contact coefficients (C,) of one operator: normal and tangential springs
    ``k_n``, ``k_t`` [M/T^2] and the rolling and twisting springs ``k_r``, ``k_w``
    [M L^2/T^2 per rad] (None: none, or rotation locked); or any combination with the
    dashpots in the same slots (a pencil, or the damping matrix itself)."""

    k_n: np.ndarray
    k_t: np.ndarray
    k_r: np.ndarray | None = None
    k_w: np.ndarray | None = None


#: candidate roots :func:`certify_step` tries on a damped problem before the closed form
DAMPED_CANDIDATES = 6
#: checks of the damped fixed point at most in :func:`certified_without_basis`
FIXED_POINT_ITERATIONS = 40
#: contacts per part of :meth:`ScaledContactOperator.damping_bound`'s element bounds
DAMPING_BOUND_PART = 1 << 16


class ScaledContactOperator:
    """K^ = M^-1/2 K M^-1/2 and C^_d = M^-1/2 C_d M^-1/2 of an assembly as products.

    DOFs are (N, nd) per particle (translations, then rotations); fixed particles have
    infinite mass (their DOFs are scaled by zero). K and C_d hold every contact's
    springs and dashpots: normal and tangential on the slip at the contact point, and
    with rotation the rolling and twisting ones on the relative rotation
    (:class:`~demstep.timestep.contacts.ContactSet`). ``pencil(sigma)`` is the operator
    (1 + sigma a2) K^ + sigma C^_d; the mass-proportional part sigma a1 I of
    A(sigma) = sigma C^ + K^ is a shift added by the caller. Its buffers (its scaling
    M^-1/2 too) and the eigensolver's basis live in ``workspace``
    (:class:`~demstep.scratch.Workspace`; a new one when not given), which successive
    operators of the same assembly size may share (one at a time: a new operator and
    every product overwrite the buffers)."""

    def __init__(self, particles: Particles, contacts: ContactSet, rotation: bool,
                 damping: GlobalDamping | None = None, bodies=None,
                 threads: int | None = None, workspace: Workspace | None = None):
        if contacts.n and contacts.dim != particles.dim:
            raise InputError(f"contacts: dimension {contacts.dim} does not match the "
                             f"particles' {particles.dim}")
        self.particles = particles
        self.contacts = contacts
        self.rotation = bool(rotation)
        #: whether the rolling and twisting springs (and viscous parts) enter: the
        #: contacts have some and the rotations are free
        self.rolling = self.rotation and contacts.has_rolling
        self.damping = damping or GlobalDamping()
        self.nd = dofs_per_particle(particles.dim, rotation)
        self.size = particles.n * self.nd
        self.workspace = workspace if workspace is not None else Workspace()
        self.scale = inverse_sqrt_mass(
            particles, rotation, self.workspace.array("operator_scale", (self.size,))
        ).reshape(particles.n, self.nd)
        self._work = self.workspace.array("operator_work", self.scale.shape)
        self.bodies = bodies if bodies is not None and bodies.n else None
        self.owner_map = None
        self._damping_bound = None
        if self.bodies is not None:
            check_bodies(particles, self.bodies)
            self.owner_map = OwnerMap(self.scale, self.bodies, particles.dim, self.rotation)
            self.size = self.owner_map.n_owners * self.nd
            self._body_forces = self.workspace.array("operator_body_forces", self.scale.shape)
        if threads is None:
            import numba  # (deferred: a heavy import, loaded only when used)

            threads = numba.get_num_threads() if contacts.n >= PARALLEL_MIN_CONTACTS else 1
        #: number of contact runs summed in parallel (1: the serial product)
        self.threads = max(1, min(int(threads), max(contacts.n, 1)))
        self._chunks, self._spans = contact_chunks(contacts, particles.n, self.threads)
        #: on several threads, the runs of an ordered contact list (sorted by i, j above
        #: i, then walls: the contact search's), whose product writes each row once, complete
        #: and scaled (:func:`~demstep.kernels.timestep_kernels.ordered_scaled_contact_matvec`:
        #: no buffer of every row per thread, no pass to sum and scale them: 1.14-1.18x
        #: on two threads at 1e6 spheres, 0.92x on one, where the loop is the limit);
        #: None for other lists, one thread and bodies
        self._ordered = (ordered_contact_runs(contacts, particles.n, self.threads)
                         if self.bodies is None and self.threads > 1 else None)
        self._buf = None
        if self._ordered is not None:
            self._band = self.workspace.array("operator_band",
                                              (self.threads, self._ordered[3], self.nd))
        elif self.threads > 1:
            self._buf = self.workspace.array("operator_runs",
                                             (self.threads - 1, particles.n, self.nd))

    def springs(self, sigma: float) -> Springs:
        """The per-contact coefficients of the pencil at ``sigma``: each spring k
        combined with its dashpot c as (1 + sigma a2) k + sigma c, for the normal and
        tangential springs and (when the contacts have them and rotation is on) the
        rolling and twisting ones (else ``k_r``, ``k_w`` None)."""
        a2 = self.damping.stiffness
        c = self.contacts
        rolling = self.rolling
        if sigma == 0.0:
            return Springs(c.k_n, c.k_s, c.k_r if rolling else None, c.k_w if rolling else None)
        f = 1.0 + sigma * a2
        if not rolling:
            return Springs(f * c.k_n + sigma * c.c_n, f * c.k_s + sigma * c.c_t)
        return Springs(f * c.k_n + sigma * c.c_n, f * c.k_s + sigma * c.c_t,
                       f * c.k_r + sigma * c.c_r, f * c.k_w + sigma * c.c_w)

    def apply(self, x: np.ndarray, springs: Springs, out: np.ndarray | None = None,
              quadratic: bool = False):
        """S K(springs) S x for flat x (size,) (into ``out`` when given); on
        ``threads`` > 1 the contact runs are summed in parallel; with bodies, G^T K G
        through the owner map (:mod:`demstep.timestep.clumps`). With ``quadratic``,
        (y, x.y) when the product computed x.y on its way (the ordered runs), else
        (y, None)."""
        k_n, k_t, k_r, k_w = springs
        if self._ordered is not None:
            y, quad = ordered_scaled_contact_matvec(
                self.contacts, k_n, k_t, self.rotation, self.scale, x, self._work,
                self._ordered, self._band, out, self.threads > 1, k_r, k_w)
            return (y, quad) if quadratic else y
        if self.owner_map is not None:
            om = self.owner_map
            contiguous = out is not None and out.flags.c_contiguous
            y = out if contiguous else np.empty(self.size)
            runs = (self._chunks, self._spans,
                    self._buf if self._buf is not None else np.zeros((0, 0, self.nd)))
            owner_contact_matvec(om, self.contacts, k_n, k_t, self.rotation,
                                 np.asarray(x).reshape(om.n_owners, self.nd), self._work,
                                 self._body_forces, y.reshape(om.n_owners, self.nd), runs,
                                 k_r, k_w)
            if out is not None and not contiguous:
                out[:] = y
                y = out
        elif self.threads > 1:
            y = chunked_scaled_contact_matvec(self.contacts, k_n, k_t, self.rotation,
                                              self.scale, x, self._work, self._chunks,
                                              self._spans, self._buf, out, k_r=k_r, k_w=k_w)
        else:
            y = scaled_contact_matvec(self.contacts, k_n, k_t, self.rotation, self.scale,
                                      x, self._work, out, k_r, k_w)
        return (y, None) if quadratic else y

    def stiffness(self, x):
        return self.apply(x, self.springs(0.0))

    def dashpots(self, x):
        c = self.contacts
        rolling = self.rolling
        return self.apply(x, Springs(c.c_n, c.c_t, c.c_r if rolling else None,
                                     c.c_w if rolling else None))

    def pencil(self, sigma: float) -> spla.LinearOperator:
        return _Pencil(self, self.springs(sigma))

    def dense_pencil(self, sigma: float) -> np.ndarray:
        springs = self.springs(sigma)
        if self.owner_map is not None:  # small systems: column by column
            return np.stack([self.apply(e, springs) for e in np.eye(self.size)], axis=1)
        k_n, k_t, k_r, k_w = springs
        if k_r is None:
            contacts = replace(self.contacts, k_n=k_n, k_s=k_t)
        else:
            contacts = replace(self.contacts, k_n=k_n, k_s=k_t, k_r=k_r, k_w=k_w)
        return assemble_stiffness(self.particles, contacts, self.rotation,
                                  scale=self.scale.reshape(-1)).toarray()

    def top(self, sigma: float, v0=None, dense_limit: int = DENSE_LIMIT,
            tol: float = EIGSH_TOL, solver: str = "lanczos",
            mix: float = WARM_START_MIX, stop_above: float = np.inf,
            stop_tol: float = 0.0, block: int = 0) -> Eigenpair:
        """Top eigenpair of the pencil at ``sigma`` (without the a1 shift)."""
        return top_eigenpair(self.pencil(sigma), v0=v0, dense_limit=dense_limit, tol=tol,
                             dense=lambda: self.dense_pencil(sigma), solver=solver, mix=mix,
                             stop_above=stop_above, stop_tol=stop_tol, block=block,
                             workspace=self.workspace)

    def rayleigh_terms(self, q: np.ndarray):
        """(k_q, c_q): q.K^ q and q.C^ q for a unit vector q (C^ with a1 and a2), summed
        over the contacts in one pass (Delta.D Delta per contact)."""
        u = self.displacement(q, self.workspace.array("operator_mode", self.scale.shape))
        kq, cq = contact_quadratic_forms(self.contacts, self.rotation, u, self._chunks,
                                         parallel=self.threads > 1)
        return kq, cq + self.damping.mass + self.damping.stiffness * kq

    def subspace_start(self, Y: np.ndarray, spare: np.ndarray | None = None):
        """Rayleigh-Ritz of the damped problem on span(Y) (Y (k, size) orthonormal, e.g.
        the top Ritz vectors of the undamped solve): the largest root of the projected
        det(s^2 I - s C_p - K_p) = 0, by the safeguarded iteration on k x k matrices
        (both projections from one pass over the contacts), and its vector in span(Y)
        (unit). A start for the damped iteration: the critical mode is often one of the
        undamped top modes, not the top one (measured: dense packing, overlap 0.98 with
        the 2nd-8th). ``spare`` (k, size): rows free to take the projections' input
        (:attr:`Eigenpair.spare`; at 1e6 spheres an array of 192 MB otherwise)."""
        import scipy.linalg  # (deferred: a heavy import, loaded only when used)

        k = Y.shape[0]
        if self.owner_map is not None:
            X = np.stack([self.displacement(y) for y in Y])
        else:
            X = (spare.reshape((k,) + self.scale.shape) if spare is not None else
                 self.workspace.array(LANCZOS_ARRAYS[2], (k,) + self.scale.shape))
            np.multiply(self.scale[None], Y.reshape(k, *self.scale.shape), out=X)
        K_p, C_p = contact_gram(self.contacts, self.rotation, X, self._chunks,
                                parallel=self.threads > 1)
        d = self.damping
        C_p = C_p + d.stiffness * K_p + d.mass * np.eye(k)
        s = 0.0
        u = np.eye(k)[0]
        for _ in range(100):
            _, U = scipy.linalg.eigh(s * C_p + K_p)
            u = U[:, -1]
            new = float(damped_sigma(float(u @ K_p @ u), float(u @ C_p @ u)))
            if new <= s * (1.0 + 1e-14):
                break
            s = new

        z = np.empty((1, Y.shape[1]))
        combine_rows(Y, k, u[:, None], z)
        z /= np.linalg.norm(z[0])
        return z[0]

    def damping_bound(self) -> float:
        """An upper bound on lambda_max(C^) [1/T] (C^ with a1, a2 and the dashpots, rolling
        and twisting ones included) from Rayleigh's theorem on the coupled elements
        (uniform mass split); computed once per operator."""
        if self._damping_bound is None:
            self._damping_bound = self._element_damping_bound()
        return self._damping_bound

    def _element_damping_bound(self) -> float:
        d = self.damping
        bound = d.mass
        if self.contacts.n and self.bodies is not None:
            # with rolling resistance W, D, G act on the strains (Delta, phi)
            # lambda_max(W^1/2 X W^1/2) <= lambda_max(X) lambda_max(W) per element; D and
            # G are springs (dashpots) times complementary projectors (n n^T, I - n n^T on
            # each strain), so lambda_max(D) is the largest spring of the contact
            c = self.contacts
            W = body_element_matrices(self.particles, c, self.bodies, self.rotation)[0]
            wmax = np.linalg.eigvalsh(W)[:, -1]
            rolling = self.rotation and c.has_rolling
            twist = c.dim == 3  # (disks: no twisting strain)
            if d.stiffness:
                springs = (c.k_n, c.k_s) + ((c.k_r,) + ((c.k_w,) if twist else ())
                                            if rolling else ())
                bound += d.stiffness * float(np.max(np.max(springs, axis=0) * wmax))
            if c.damped:
                dashpots = (c.c_n, c.c_t) + ((c.c_r,) + ((c.c_w,) if twist else ())
                                             if rolling else ())
                bound += float(np.max(np.max(dashpots, axis=0) * wmax))
        elif self.contacts.n:
            # in parts of DAMPING_BOUND_PART contacts (views): the element formulas make
            # a dozen temporaries per contact, 950 MB at 7e6 contacts, on top of the
            # basis at the damped solve's peak (benchmarks/results/history-2026-12-04.md,
            # twenty-third session)
            c = self.contacts
            counts = c.count_per_particle(self.particles.n)
            damped = c.damped
            stiff = damp = 0.0
            for start in range(0, c.n, DAMPING_BOUND_PART):
                part = c.subset(slice(start, start + DAMPING_BOUND_PART))
                mass = element_mass(self.particles, part, counts=counts)
                if d.stiffness:
                    stiff = max(stiff, float(coupled_element_lambda(part, mass,
                                                                    self.rotation).max()))
                if damped:
                    damp = max(damp, float(coupled_element_lambda(part.dashpot_springs(), mass,
                                                                  self.rotation).max()))
            bound += d.stiffness * stiff  # (then the dashpots': the old order of sums)
            bound += damp
        return bound

    def mode_shares(self, q: np.ndarray):
        """Where the mode q (unit, mass-scaled) lives: per owner (particle, or body) the
        translational and rotational shares of its kinetic energy (all shares sum to 1),
        and per contact its share of the strain energy (C,; rolling and twisting
        springs included)."""
        dim = self.particles.dim
        qq = (q.reshape(-1, self.nd)) ** 2
        trans = qq[:, :dim].sum(axis=1)
        rot = qq[:, dim:].sum(axis=1)
        total = trans.sum() + rot.sum()
        u = self.displacement(q)
        k = self.springs(0.0)
        energy = contact_energies(self.contacts, k.k_n, k.k_t, self.rotation, u, k.k_r, k.k_w)
        e_sum = energy.sum()
        return (trans / total, rot / total,
                energy / e_sum if e_sum > 0 else energy)

    def displacement(self, q: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """The physical mode shape of every sphere (N, nd) [L; rad for rotations]: M^-1/2 q
        (with bodies, the members move with their bodies); into ``out`` (N, nd) when
        given, without bodies."""
        if self.owner_map is not None:
            return self.owner_map.expand(q.reshape(-1, self.nd), self.particles.n)
        return np.multiply(self.scale, q.reshape(self.scale.shape), out=out)


class _Pencil(spla.LinearOperator):
    """The pencil K(springs) of a :class:`ScaledContactOperator` as a LinearOperator
    with ``matvec_into(x, out)`` for the Lanczos iteration."""

    def __init__(self, op: ScaledContactOperator, springs: Springs):
        super().__init__(np.float64, (op.size, op.size))
        self.op, self.springs_ = op, springs

    def _matvec(self, x):
        return self.op.apply(np.ravel(x), self.springs_)

    def _rmatvec(self, x):
        return self._matvec(x)

    def matvec_into(self, x, out):
        """out = the pencil times x; returns x.out when the product computed it on its
        way (:meth:`ScaledContactOperator.apply`), else None."""
        return self.op.apply(x, self.springs_, out, quadratic=True)[1]


@dataclass
class ExactStep:
    """The exact critical step of an assembly.

    ``dt`` [T]: the certified critical step (from an upper bound on sigma_max);
    ``dt_undamped`` [T]: the same without any damping (certified likewise, to the
    undamped solve's relative residual ``undamped_tol``: looser than the damped step's
    when :func:`exact_critical_step` was asked so);
    ``sigma`` [1/T]: the converged largest root (its Ritz estimate, a lower bound: the
    certified step is ``dt``, not 2 / sigma);
    ``lambda_undamped`` [1/T^2]: the Ritz value of lambda_max(M^-1 K) (to ``undamped_tol``);
    ``mode`` (size,): the critical mode, unit and mass-scaled (q = M^1/2 u);
    ``iterations``: safeguarded iterations (0 undamped); ``damped``: whether damping
    entered; ``matvecs``: products with the operator (0 on the dense path);
    ``dt_certified`` [T]: the step with a guarantee (:mod:`demstep.timestep.guarantee`),
    None unless asked for; ``guarantee``: what ``dt_certified`` guarantees (a proof on
    the dense path, a failure probability from the random-start check on the Lanczos
    path); ``check``: that check's record (None on the dense path). ``dt`` itself bounds
    the root the solver converged to (the top one when the solver found it: its
    guarantee is :data:`ESTIMATE`)."""

    dt: float
    dt_undamped: float
    sigma: float
    lambda_undamped: float
    mode: np.ndarray
    iterations: int
    damped: bool
    operator: ScaledContactOperator
    matvecs: int = 0
    undamped_tol: float = EIGSH_TOL
    dt_certified: float | None = None
    guarantee: Guarantee | None = None
    check: ProbableBound | None = None


#: what ``ExactStep.dt`` guarantees on the Lanczos path
ESTIMATE = Guarantee("estimate", "bounds the top eigenvalue the solver found (Ritz value + "
                     "residual); not proven to be the largest")
#: what the dense path proves
DENSE_PROOF = Guarantee("proof", "dense symmetric eigensolver, with its rounding bound")


def exact_critical_step(particles: Particles, contacts: ContactSet, rotation: bool,
                        damping: GlobalDamping | None = None, v0: np.ndarray | None = None,
                        dense_limit: int = DENSE_LIMIT, rtol: float = SIGMA_RTOL,
                        max_iter: int = 100, tol: float = EIGSH_TOL,
                        loose_tol: float = LOOSE_TOL, threads: int | None = None,
                        solver: str = "lanczos", bodies=None,
                        workspace: Workspace | None = None,
                        undamped_tol: float | None = None, guarantee: bool = False,
                        failure: float = FAILURE, seed: int | None = None) -> ExactStep:
    """Exact (and certified) critical step, with contact dashpots and global damping when
    present; ``v0`` (a previous ``mode``) is a start the damped iteration tries (the
    solves that certify start from the fixed random vector: :data:`CHAIN_MIX`).

    ``tol``: relative residual of the undamped solve (the certifying damped solves use
    max(tol, CERTIFY_MARGIN / 4)), in (0, :data:`~demstep.timestep.eigen.MAX_CERTIFIED_TOL`]
    like ``undamped_tol`` (a looser solve certifies nothing: InputError); ``loose_tol``: that of the intermediate solves of
    the safeguarded iteration (with ``loose_tol <= tol`` every step is a certifying
    one); ``rtol``: the smallest increase of the iterate that counts as progress;
    ``threads``: contact runs summed in parallel in each product (None: numba's threads
    from :data:`PARALLEL_MIN_CONTACTS` contacts on); ``solver``: "lanczos" or "arpack"
    (scipy's eigsh, the earlier solver, for comparison); ``bodies``
    (:class:`demstep.timestep.clumps.RigidBodies`): clumps, six DOFs each;
    ``workspace``: the scratch arrays, kept by a caller that solves again (a run);
    without one, the Lanczos basis is released on return (the result's operator keeps
    only its product buffers); ``undamped_tol``: when damping enters, the relative
    residual of the undamped solve (None: ``tol``), for a caller that needs only the
    damped step: that solve then only starts the damped iteration, and ``dt_undamped``
    comes from it (still from an upper bound on lambda_max: below the undamped critical
    step, by up to about 4 ``undamped_tol``; recorded in :attr:`ExactStep.undamped_tol`);
    ``guarantee``: also compute :attr:`ExactStep.dt_certified` (:func:`certify_step`),
    with probability of failure ``failure`` over a start drawn from ``seed`` (None: fresh
    entropy, recorded in the result)."""
    tol = check_certified_tol("tol", tol)
    failure = check_failure(failure)
    undamped_tol = tol if undamped_tol is None else check_certified_tol("undamped_tol",
                                                                        undamped_tol)
    op = ScaledContactOperator(particles, contacts, rotation, damping, bodies, threads=threads,
                               workspace=workspace)
    try:
        result = _exact_step(op, v0, dense_limit, rtol, max_iter, tol, loose_tol, solver,
                             undamped_tol)
        if guarantee:
            certify_step(result, dense_limit, failure, seed)
        return result
    finally:
        if workspace is None:
            op.workspace.release(*LANCZOS_ARRAYS)


def certified_without_basis(particles: Particles, contacts: ContactSet, rotation: bool,
                            damping: GlobalDamping | None = None, bodies=None,
                            threads: int | None = None, failure: float = FAILURE,
                            seed: int | None = None) -> ExactStep:
    """The certified step from the random-start check alone
    (:func:`demstep.timestep.guarantee.probable_upper_bound`), with no Lanczos basis: the
    memory of three vectors instead of the exact solver's ~40 (for an assembly whose
    basis does not fit). The check runs until its bound U on lambda_max(K^) is within
    :data:`~demstep.timestep.guarantee.CLAIM_SLACK` of its own top Ritz value;
    undamped, dt = 2 / sqrt(U). Damped, the fixed point t = sqrt(lambda_max(A(t))) is
    approached from below on the checks' Ritz values (the map grows with slope c/(2
    sigma) < 1 at the root: linear convergence, slower the heavier the damping; at most
    :data:`FIXED_POINT_ITERATIONS` checks), then a candidate (1 + 2 CLAIM_SLACK) above
    is proven an upper bound on sigma_max by a check of lambda_max(A(t)) <= t^2, as in
    :func:`certify_step`. The result has no mode (``mode`` None) and ``dt`` equals
    ``dt_certified`` (there is no separate estimate); ``lambda_undamped`` is the
    undamped check's bound; ``matvecs`` counts every check's products. The seeds of the
    checks are all ``seed`` (each check is a new draw when None)."""
    failure = check_failure(failure)
    op = ScaledContactOperator(particles, contacts, rotation, damping, bodies, threads=threads)
    if contacts.n == 0 and not op.damping.mass:
        raise InputError("contacts: the assembly has no contacts")
    tiny = np.finfo(np.float64).tiny  # (a target below any bound: the check's own)
    check = probable_upper_bound(op.pencil(0.0).matvec_into, op.size, failure, seed,
                                 target=tiny)
    steps = check.steps
    upper = check.upper
    dt_undamped = 2.0 / np.sqrt(upper) if upper > 0 else np.inf
    damped = contacts.damped or op.damping.active
    if not damped or not upper > 0:
        return ExactStep(float(dt_undamped), float(dt_undamped), float(np.sqrt(upper)),
                         check.ritz, None, 0, bool(damped), op, steps, EIGSH_TOL,
                         float(dt_undamped), check.guarantee(), check)
    # damped: the fixed point t = sqrt(lambda_max(A(t))) (A(t) = the pencil + a1 t) from
    # below, on the checks' Ritz values (each a lower bound: the iterates stay below
    # sigma_max), then candidates just above it proven as certify_step does
    a1 = op.damping.mass
    t = float(np.sqrt(check.ritz))
    iterations = 0
    for iterations in range(1, FIXED_POINT_ITERATIONS + 1):
        check = probable_upper_bound(op.pencil(t).matvec_into, op.size, failure, seed,
                                     target=tiny)
        steps += check.steps
        new = float(np.sqrt(check.ritz + a1 * t))
        if new <= t * (1.0 + CLAIM_SLACK):
            t = max(t, new)
            break
        t = new
    slack = CLAIM_SLACK
    for _ in range(DAMPED_CANDIDATES):
        t = t * (1.0 + 2.0 * slack)
        claim = t * t - a1 * t
        check = probable_upper_bound(op.pencil(t).matvec_into, op.size, failure, seed,
                                     target=claim)
        steps += check.steps
        if check.upper <= claim:
            sigma = t
            break
        t = float(np.sqrt(check.upper + a1 * t))
    else:  # the closed form from the last bound (lambda_max(A) grows at most with Lambda_C)
        lam_c = op.damping_bound()
        bound = check.upper + a1 * t
        sigma = float(damped_sigma(max(bound - t * lam_c, 0.0), lam_c))
    guarantee = Guarantee("probability", "random-start Lanczos bounds, no basis", failure,
                          check.seed, steps)
    return ExactStep(float(2.0 / sigma), float(dt_undamped), sigma, float(upper), None,
                     iterations, True, op, steps, EIGSH_TOL, float(2.0 / sigma), guarantee,
                     check)


def certify_step(result: ExactStep, dense_limit: int = DENSE_LIMIT, failure: float = FAILURE,
                 seed: int | None = None) -> ExactStep:
    """Sets ``result.dt_certified`` and its ``guarantee`` (and returns ``result``).

    The bound on the top eigenvalue comes from the dense eigenvalue plus its rounding
    bound on the dense path (DENSE_ROUNDING n^1.5 eps lambda_max >= DENSE_ROUNDING n eps
    |A|_F: a proof), else from the random-start check
    (:func:`demstep.timestep.guarantee.probable_upper_bound`: with probability >= 1 -
    ``failure``). Undamped, the check confirms lambda_max(K^) <= (1 + CLAIM_SLACK) 4 /
    dt^2, or returns a larger bound, which then counts (the solver missed the top).
    Damped, a candidate t a little above the certified root 2 / dt is proven an upper
    bound on sigma_max by lambda_max(A(t)) <= t^2 (the pencil at t, with the a1 shift;
    the claim's slack comes from the growth of t^2, at least (t - s) s faster than
    lambda_max(A(t)) near the root s); when the bound U does not prove it, the next
    candidate is sqrt(U + a1 t) (1 + 2 slack), up to :data:`DAMPED_CANDIDATES` times, then
    the closed form s'^2 = U + (s' - t) Lambda_C from the last bound U (lambda_max(A)
    grows at most with slope Lambda_C >= lambda_max(C^) beyond t)."""
    op = result.operator
    n = op.size
    s = 2.0 / result.dt if result.dt > 0 and np.isfinite(result.dt) else 0.0
    if not s > 0:  # no stiffness on the moving DOFs: stable at any step
        result.dt_certified, result.guarantee = result.dt, DENSE_PROOF
        return result
    dense = n <= dense_limit
    rounding = DENSE_ROUNDING * n ** 1.5 * np.finfo(np.float64).eps
    if not result.damped:
        if dense:
            upper = s * s * (1.0 + rounding)
            result.guarantee = DENSE_PROOF
        else:
            check = probable_upper_bound(op.pencil(0.0).matvec_into, n, failure, seed,
                                         target=s * s * (1.0 + CLAIM_SLACK))
            upper = check.upper
            result.check, result.guarantee = check, check.guarantee()
        result.dt_certified = float(2.0 / np.sqrt(upper))
        return result
    a1 = op.damping.mass
    slack = max(rounding, 1e-10) if dense else CLAIM_SLACK
    t = s * (1.0 + 2.0 * slack)
    for _ in range(DAMPED_CANDIDATES):
        claim = t * t - a1 * t  # (the pencil's top, without the a1 shift)
        if dense:
            upper = op.top(t, dense_limit=dense_limit).upper * (1.0 + rounding)
            result.guarantee = DENSE_PROOF
        else:
            check = probable_upper_bound(op.pencil(t).matvec_into, n, failure, seed,
                                         target=claim)
            upper = check.upper
            result.check, result.guarantee = check, check.guarantee()
        if upper <= claim:
            result.dt_certified = float(2.0 / t)
            return result
        # t is not proven: the next candidate from the bound, sqrt(U + a1 t) >= the root
        # of the pencil at t (an increasing map with the root sigma_max as fixed point)
        t = max(t * (1.0 + 2.0 * slack), np.sqrt(upper + a1 * t) * (1.0 + 2.0 * slack))
    lam_c = op.damping_bound()
    bound = upper + a1 * t
    result.dt_certified = float(2.0 / damped_sigma(max(bound - t * lam_c, 0.0), lam_c))
    return result


def _exact_step(op, v0, dense_limit, rtol, max_iter, tol, loose_tol, solver,
                undamped_tol) -> ExactStep:
    """:func:`exact_critical_step` on the operator ``op`` (its contacts and damping)."""
    contacts = op.contacts
    if contacts.n == 0 and not op.damping.mass:
        raise InputError("contacts: the assembly has no contacts")
    damped = contacts.damped or op.damping.active
    # the undamped solve certifies dt_undamped: from the fixed random start (CHAIN_MIX)
    if not damped:
        undamped_tol = tol
    top = op.top(0.0, dense_limit=dense_limit, tol=undamped_tol, solver=solver,
                 block=START_BLOCK if damped else 0)
    matvecs = top.matvecs
    lam = top.value
    dt_undamped = 2.0 / np.sqrt(top.upper) if top.upper > 0 else np.inf
    if not damped or not top.upper > 0:
        # (K = 0 on the moving degrees of freedom, e.g. contacts only between fixed
        # particles and walls: damping alone, (I + dt C/2)^-1 (I - dt C/2) with C >= 0,
        # is stable at any dt)
        return ExactStep(float(dt_undamped), float(dt_undamped), float(np.sqrt(lam)), lam,
                         top.vector, 0, bool(damped), op, matvecs, undamped_tol)
    a1 = op.damping.mass
    lam_c = op.damping_bound()

    def closed_form_upper(pair: Eigenpair, s: float, bound: float) -> float:
        """The root of t^2 = U + (t - s) Lambda_C, U = ``bound`` >= lambda_max(A(s))."""
        return float(damped_sigma(max(bound - s * lam_c, 0.0), lam_c))

    q = top.vector
    sigma = float(damped_sigma(*op.rayleigh_terms(q)))
    candidates = []
    if top.block is not None and len(top.block) > 1:
        # the best vector for the damped problem among the undamped solve's top Ritz
        # vectors (a lower bound on sigma_max like any other)
        candidates.append(op.subspace_start(top.block, top.spare))
    if v0 is not None and v0.shape == (op.size,) and np.all(np.isfinite(v0)) and v0.any():
        candidates.append(v0 / np.linalg.norm(v0))  # a previous (damped) critical mode
    for z in candidates:
        sigma_z = float(damped_sigma(*op.rayleigh_terms(z)))
        if sigma_z > sigma:
            q, sigma = z, sigma_z
    dense_path = op.size <= dense_limit
    margin = DENSE_CERTIFY_MARGIN if dense_path else max(CERTIFY_MARGIN, 4.0 * tol)
    certify_tol = margin / 4.0
    accept_rtol = max(CLOSED_FORM_RTOL, 2.0 * margin)
    solve_tol = max(FIRST_TOL, loose_tol) if loose_tol > tol and not dense_path else tol
    iterations = 0
    while True:
        iterations += 1
        if iterations > max_iter:  # pragma: no cover - the iteration converges for PSD K, C
            raise RuntimeError("exact damped step: could not certify sigma_max")
        if solve_tol > tol:
            # an intermediate step of the safeguarded iteration: a loose solve at sigma
            top = op.top(sigma, v0=q, dense_limit=dense_limit, tol=solve_tol,
                         solver=solver, mix=CHAIN_MIX)
            matvecs += top.matvecs
            q = top.vector
            new = float(damped_sigma(*op.rayleigh_terms(q)))
            step = (new - sigma) / sigma
            solve_tol = tol if step <= TIGHT_SWITCH and solve_tol <= loose_tol else loose_tol
            sigma = max(sigma, new)
            continue
        # a certifying step: a tight solve at the candidate t just above the iterate.
        # t is an upper bound on sigma_max when t^2 >= the residual bound of
        # lambda_max(A(t)) (then t^2 I - A(t) is positive semi-definite; below sigma_max
        # it is not). Else the closed form from the same solve may still bound it: for
        # s >= t, lambda_max(A(s)) <= U + (s - t) Lambda_C with U that residual bound and
        # Lambda_C >= lambda_max(C^) from the (rigorous) element bounds of K and C_d, so
        # the root of s^2 = U + (s - t) Lambda_C is one. Lanczos stops early once its
        # Ritz value (a lower bound) shows that t is below sigma_max, with a vector as
        # good as an intermediate solve's: then it was a step of the iteration. The
        # solve starts from the fixed random vector, not from q (CHAIN_MIX).
        t = sigma * (1.0 + margin)
        top = op.top(t, dense_limit=dense_limit, tol=certify_tol, solver=solver,
                     stop_above=t * t - a1 * t, stop_tol=loose_tol)
        matvecs += top.matvecs
        q = top.vector
        new = float(damped_sigma(*op.rayleigh_terms(q)))
        bound = top.upper + a1 * t
        up = t if t * t >= bound else closed_form_upper(top, t, bound)
        lower = max(sigma, new)
        if up <= lower * (1.0 + accept_rtol):
            sigma = lower
            break
        if new > sigma * (1.0 + rtol):
            # t was below sigma_max: the iteration goes on from new (the exploration of
            # the certifying solve found a larger eigenvalue than the loose solves)
            sigma = new
        else:
            # the residual was too large for this margin: a candidate further up, a
            # tighter solve, and acceptance within the wider margin (the candidate
            # itself sits a margin above the iterate: with the first margin's
            # acceptance it could never be taken, and the iteration ran out)
            margin *= 4.0
            certify_tol = margin / 4.0
            accept_rtol = max(accept_rtol, 2.0 * margin)
    return ExactStep(float(2.0 / up), float(dt_undamped), sigma, lam, q, iterations, True, op,
                     matvecs, undamped_tol)
