"""Exact critical step of an infinite periodic lattice by Bloch-wave analysis.

For a lattice with cell vectors L (orthorhombic, lengths ``cell``) and nb particles per
cell, a Bloch wave u_b(R) = u_b exp(i k.R) turns the infinite eigenproblem into the
Hermitian dynamical matrix D(k) (nb nd x nb nd):

    D_ab(k) = sum over contacts of a with b in cell R of  K_ab exp(i k.R)  (+ K_aa on a),

built from the same coupled element blocks as the finite assembly. omega_max^2 is the
maximum over the Brillouin zone of lambda_max(M^-1/2 D(k) M^-1/2): a grid that contains
the zone centre and boundary points, refined by Nelder-Mead from its best points.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from demstep.contacts import DEFAULT_CONTACT_TOL, ContactSet
from demstep.packings import Lattice
from demstep.particles import particle_inertia, particle_mass
from demstep.timestep.elements import coupled_element_blocks, dofs_per_particle, n_rotations


@dataclass
class PeriodicContacts:
    """Directed contacts of the basis particles: a in the home cell touches b in the
    cell shifted by ``shift`` (integer cell offsets); ``contacts`` holds their geometry
    (i = a, j = b) and stiffnesses."""

    shift: np.ndarray
    contacts: ContactSet


def periodic_contacts(lat: Lattice, k_n: float, k_s: float,
                      tol: float = DEFAULT_CONTACT_TOL) -> PeriodicContacts:
    """All directed touching pairs of the lattice's basis particles."""
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
    cs = ContactSet(a, b, normals, arm, arm, k_n, k_s)
    return PeriodicContacts(np.asarray(shifts, dtype=float), cs)


class DynamicalMatrix:
    """M^-1/2 D(k) M^-1/2 for a lattice of equal particles of ``density``."""

    def __init__(self, lat: Lattice, k_n: float, k_s: float, density: float, rotation: bool):
        self.lattice = lat
        self.rotation = rotation
        self.pc = periodic_contacts(lat, k_n, k_s)
        self.nb = len(lat.basis)
        self.nd = dofs_per_particle(lat.dim, rotation)
        Kii, Kij, _ = coupled_element_blocks(self.pc.contacts, rotation)
        m = float(particle_mass(lat.radius, density, lat.dim))
        inertia = float(particle_inertia(m, lat.radius, lat.dim))
        s = 1.0 / np.sqrt(np.array([m] * lat.dim + [inertia] * n_rotations(lat.dim, rotation)))
        self.Kii = Kii * s[None, :, None] * s[None, None, :]
        self.Kij = Kij * s[None, :, None] * s[None, None, :]
        self.mass = m

    def __call__(self, k_frac: np.ndarray) -> np.ndarray:
        """A(k) for fractional wave vectors (nk, dim): k = 2 pi f / cell. (nk, n, n)."""
        k_frac = np.atleast_2d(k_frac)
        phase = np.exp(2j * np.pi * (k_frac @ self.pc.shift.T))  # (nk, C)
        nb, nd = self.nb, self.nd
        A = np.zeros((k_frac.shape[0], nb, nd, nb, nd), dtype=complex)
        a, b = self.pc.contacts.i, self.pc.contacts.j
        for c in range(len(a)):
            A[:, a[c], :, a[c], :] += self.Kii[c]
            A[:, a[c], :, b[c], :] += phase[:, c, None, None] * self.Kij[c]
        return A.reshape(k_frac.shape[0], nb * nd, nb * nd)

    def lambda_max_at(self, k_frac) -> np.ndarray:
        return np.linalg.eigvalsh(self(k_frac))[:, -1]

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


def bloch_lambda_max(lat: Lattice, k_n: float, k_s: float, density: float, rotation: bool):
    """omega_max^2 [1/T^2] of the infinite lattice and the wave vector (fractional) of
    the fastest mode."""
    return DynamicalMatrix(lat, k_n, k_s, density, rotation).lambda_max()
