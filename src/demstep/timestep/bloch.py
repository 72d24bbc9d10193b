"""Exact critical step of an infinite periodic lattice by Bloch-wave analysis.

For a lattice with cell vectors L (orthorhombic, lengths ``cell``) and nb particles per
cell, a Bloch wave u_b(R) = u_b exp(i k.R) turns the infinite eigenproblem into the
Hermitian dynamical matrix D(k) (nb nd x nb nd):

    D_ab(k) = sum over contacts of a with b in cell R of  K_ab exp(i k.R)  (+ K_aa on a),

built from the same coupled element blocks as the finite assembly (rolling and twisting
springs included: uniform ``k_r``, ``k_w`` and their viscous parts). omega_max^2 is the
maximum over the Brillouin zone of lambda_max(M^-1/2 D(k) M^-1/2): a grid that contains
the zone centre and boundary points, refined by Nelder-Mead from its best points.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from demstep.timestep.contacts import DEFAULT_CONTACT_TOL, ContactSet
from demstep.packings import Lattice
from demstep.particles import particle_inertia, particle_mass
from demstep.timestep.damping import GlobalDamping
from demstep.timestep.elements import coupled_element_blocks, dofs_per_particle, n_rotations


@dataclass
class PeriodicContacts:
    """Directed contacts of the basis particles: a in the home cell touches b in the
    cell shifted by ``shift`` (integer cell offsets); ``contacts`` holds their geometry
    (i = a, j = b) and stiffnesses."""

    shift: np.ndarray
    contacts: ContactSet


def periodic_contacts(lat: Lattice, k_n: float, k_s: float,
                      tol: float = DEFAULT_CONTACT_TOL, k_r: float = 0.0, k_w: float = 0.0,
                      c_r: float = 0.0, c_w: float = 0.0) -> PeriodicContacts:
    """All directed touching pairs of the lattice's basis particles, with springs k_n,
    k_s [M/T^2] and rolling and twisting springs k_r, k_w [M L^2/T^2 per rad] (viscous
    parts c_r, c_w [M L^2/T])."""
    r = lat.radius
    rows = []
    for shift in itertools.product(range(-2, 3), repeat=lat.dim):
        offset = np.array(shift) * lat.cell
        for a, xa in enumerate(lat.basis):
            for b, xb in enumerate(lat.basis):
                d = xb + offset - xa
                dist = float(np.linalg.norm(d))
                if 0 < dist <= 2 * r * (1 + tol):
                    rows.append((a, b, shift, d / dist, dist))
    a, b, shifts, normals, dist = map(np.array, zip(*rows))
    arm = dist / 2.0
    cs = ContactSet(a, b, normals, arm, arm, k_n, k_s, k_r=k_r, k_w=k_w, c_r=c_r, c_w=c_w)
    return PeriodicContacts(np.asarray(shifts, dtype=float), cs)


class DynamicalMatrix:
    """M^-1/2 D(k) M^-1/2 for a lattice of equal particles of ``density``; with
    dashpots ``c_n``, ``c_t`` [M/T] on every contact and global damping, also the
    damping matrix C^(k) = a1 I + a2 A(k) + M^-1/2 C_d(k) M^-1/2. Rolling and twisting
    springs ``k_r``, ``k_w`` [M L^2/T^2 per rad] and their viscous parts ``c_r``,
    ``c_w`` [M L^2/T] on every contact (with rotation)."""

    def __init__(self, lat: Lattice, k_n: float, k_s: float, density: float, rotation: bool,
                 c_n: float = 0.0, c_t: float = 0.0, damping: GlobalDamping | None = None,
                 k_r: float = 0.0, k_w: float = 0.0, c_r: float = 0.0, c_w: float = 0.0):
        self.lattice = lat
        self.rotation = rotation
        self.pc = periodic_contacts(lat, k_n, k_s, k_r=k_r, k_w=k_w, c_r=c_r, c_w=c_w)
        self.nb = len(lat.basis)
        self.nd = dofs_per_particle(lat.dim, rotation)
        m = float(particle_mass(lat.radius, density, lat.dim))
        inertia = float(particle_inertia(m, lat.radius, lat.dim))
        s = 1.0 / np.sqrt(np.array([m] * lat.dim + [inertia] * n_rotations(lat.dim, rotation)))
        self.blocks = self._scaled_blocks(self.pc.contacts, s)
        self.damping = damping or GlobalDamping()
        self.pc.contacts.c_n[:] = c_n
        self.pc.contacts.c_t[:] = c_t
        self.damped = self.pc.contacts.damped or self.damping.active
        if self.damped:
            self.dashpot_blocks = self._scaled_blocks(self.pc.contacts.dashpot_springs(), s)
        self.mass = m

    def _scaled_blocks(self, contacts, s):
        Kii, Kij, _ = coupled_element_blocks(contacts, self.rotation)
        return (Kii * s[None, :, None] * s[None, None, :],
                Kij * s[None, :, None] * s[None, None, :])

    def __call__(self, k_frac: np.ndarray, blocks=None) -> np.ndarray:
        """A(k) for fractional wave vectors (nk, dim): k = 2 pi f / cell. (nk, n, n)."""
        Kii, Kij = self.blocks if blocks is None else blocks
        k_frac = np.atleast_2d(k_frac)
        phase = np.exp(2j * np.pi * (k_frac @ self.pc.shift.T))  # (nk, C)
        nb, nd = self.nb, self.nd
        A = np.zeros((k_frac.shape[0], nb, nd, nb, nd), dtype=complex)
        a, b = self.pc.contacts.i, self.pc.contacts.j
        for c in range(len(a)):
            A[:, a[c], :, a[c], :] += Kii[c]
            A[:, a[c], :, b[c], :] += phase[:, c, None, None] * Kij[c]
        return A.reshape(k_frac.shape[0], nb * nd, nb * nd)

    def lambda_max_at(self, k_frac) -> np.ndarray:
        """omega_max^2 at each wave vector; damped, sigma_max^2 (dt = 2 / sigma_max), the
        largest real root of det(sigma^2 I - sigma C^(k) - A(k)) from the companion
        linearisation [[0, I], [A, C^]] (:mod:`demstep.timestep.damping`)."""
        A = self(k_frac)
        if not self.damped:
            return np.linalg.eigvalsh(A)[:, -1]
        n = A.shape[1]
        C = self(k_frac, self.dashpot_blocks) + self.damping.stiffness * A
        C += self.damping.mass * np.eye(n)
        out = np.empty(A.shape[0])
        for q in range(A.shape[0]):
            L = np.block([[np.zeros((n, n)), np.eye(n)], [A[q], C[q]]])
            ev = np.linalg.eigvals(L)
            real = ev[np.abs(ev.imag) <= 1e-9 * max(1.0, np.abs(ev).max())].real
            out[q] = real.max() ** 2
        return out

    def lambda_max(self, grid: int | None = None, refine: int = 4):
        """max over the Brillouin zone of lambda_max(A(k)); returns (lambda, k_frac)."""
        dim = self.lattice.dim
        if grid is None:
            grid = 24 if dim == 2 else 12
        axes = [np.arange(grid) / grid - 0.5] * dim  # contains 0 and -1/2 (zone boundary)
        f = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, dim)
        lam = np.concatenate([self.lambda_max_at(chunk) for chunk in np.array_split(f, max(1, len(f) // 512))])
        best = np.argsort(lam)[::-1][:refine]
        best_lam, best_f = float(lam[best[0]]), f[best[0]]
        for start in f[best]:
            res = minimize(lambda q: -self.lambda_max_at(q)[0], start, method="Nelder-Mead",
                           options=dict(xatol=1e-7, fatol=1e-12 * best_lam, maxiter=2000))
            if -res.fun > best_lam:
                best_lam, best_f = float(-res.fun), res.x
        return best_lam, np.mod(best_f + 0.5, 1.0) - 0.5


def bloch_lambda_max(lat: Lattice, k_n: float, k_s: float, density: float, rotation: bool,
                     c_n: float = 0.0, c_t: float = 0.0, damping: GlobalDamping | None = None,
                     k_r: float = 0.0, k_w: float = 0.0, c_r: float = 0.0, c_w: float = 0.0):
    """omega_max^2 [1/T^2] of the infinite lattice (damped: sigma_max^2, so that
    dt = 2 / sqrt(value) either way) and the wave vector (fractional) of the fastest
    mode; uniform coefficients as in :class:`DynamicalMatrix`."""
    return DynamicalMatrix(lat, k_n, k_s, density, rotation, c_n, c_t, damping,
                           k_r, k_w, c_r, c_w).lambda_max()
