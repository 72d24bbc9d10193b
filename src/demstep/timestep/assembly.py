"""Global sparse stiffness K and lumped mass M of an assembly (coupled formulation).

DOFs are numbered per particle, nd = dim (+ rotations) each: translations then
rotations, so K is block-sparse with nd x nd blocks and is stored as a scipy BSR
matrix. Fixed particles keep their rows and columns but get zero weight in the
mass-scaled matrix (infinite mass), which leaves their modes at eigenvalue 0.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from demstep.timestep.contacts import ContactSet
from demstep.kernels.timestep_kernels import stiffness_diagonal_kernel
from demstep.particles import Particles
from demstep.timestep.elements import coupled_element_blocks, dofs_per_particle


def _per_dof(particles: Particles, rotation: bool, translation: np.ndarray,
             rotational: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """(N * nd,): each particle's ``translation`` value on its dim translational DOFs
    and its ``rotational`` value on its rotations (the DOF layout of the mass matrix);
    into ``out`` when given."""
    dim = particles.dim
    nd = dofs_per_particle(dim, rotation)
    s = np.empty((particles.n, nd)) if out is None else out.reshape(particles.n, nd)
    s[:, :dim] = translation[:, None]
    if nd > dim:
        s[:, dim:] = rotational[:, None]
    return s.reshape(-1) if out is None else out


def lumped_mass(particles: Particles, rotation: bool) -> np.ndarray:
    """Diagonal of the lumped global mass matrix (N * nd,) [M; M L^2 for rotations]."""
    return _per_dof(particles, rotation, particles.m, particles.inertia)


def inverse_sqrt_mass(particles: Particles, rotation: bool,
                      out: np.ndarray | None = None) -> np.ndarray:
    """M^-1/2 per DOF (N * nd,), the diagonal of :func:`lumped_mass` to the power -1/2,
    zero on fixed particles (infinite mass); into ``out`` (N * nd,) when given (an
    'auto' run builds it at every estimate: a fresh array of that size costs its page
    faults, more than the arithmetic). One square root per particle and kind of DOF."""
    s = _per_dof(particles, rotation, 1.0 / np.sqrt(particles.m),
                 1.0 / np.sqrt(particles.inertia), out)
    s.reshape(particles.n, -1)[particles.fixed] = 0.0
    return s


def _bsr_from_blocks(rows, cols, blocks, n_blocks):
    """BSR matrix from (possibly repeated) block coordinates; repeated blocks add up."""
    nd = blocks.shape[1]
    key = rows.astype(np.int64) * n_blocks + cols
    order = np.argsort(key, kind="stable")
    key = key[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    data = np.add.reduceat(blocks[order], starts, axis=0) if len(order) else blocks[:0]
    ukey = key[starts]
    urow, ucol = ukey // n_blocks, ukey % n_blocks
    indptr = np.zeros(n_blocks + 1, dtype=np.int64)
    np.add.at(indptr, urow + 1, 1)
    indptr = np.cumsum(indptr)
    return sp.bsr_matrix((data, ucol, indptr), shape=(n_blocks * nd, n_blocks * nd))


def assemble_stiffness(particles: Particles, contacts: ContactSet, rotation: bool,
                       scale: np.ndarray | None = None) -> sp.bsr_matrix:
    """Global stiffness K [M/T^2; rotational entries M L^2/T^2] as BSR, or S K S for a
    DOF scaling S = diag(scale); the contacts' rolling and twisting springs included
    (with rotation: :func:`~demstep.timestep.elements.coupled_element_blocks`)."""
    n = particles.n
    nd = dofs_per_particle(particles.dim, rotation)
    Kii, Kij, Kjj = coupled_element_blocks(contacts, rotation)
    pp = contacts.j >= 0
    i, j = contacts.i, contacts.j[pp]
    rows = np.concatenate([contacts.i, j, i[pp], j])
    cols = np.concatenate([contacts.i, j, j, i[pp]])
    blocks = np.concatenate([Kii, Kjj[pp], Kij[pp], Kij[pp].transpose(0, 2, 1)])
    if scale is not None:
        s = scale.reshape(n, nd)
        blocks = blocks * s[rows][:, :, None] * s[cols][:, None, :]
    return _bsr_from_blocks(rows, cols, blocks, n)


def scaled_stiffness(particles: Particles, contacts: ContactSet, rotation: bool):
    """A = M^-1/2 K M^-1/2 (BSR); lambda_max(A) = lambda_max(M^-1 K) = omega_max^2."""
    return assemble_stiffness(particles, contacts, rotation,
                              scale=inverse_sqrt_mass(particles, rotation))


def stiffness_diagonal(particles: Particles, contacts: ContactSet, rotation: bool) -> np.ndarray:
    """Diagonal of the global K (N * nd,), in closed form: per contact and particle,
    translation K_n n_k^2 + K_s (1 - n_k^2); rotation K_s a^2 (1 - n_k^2) in 3D, K_s a^2
    in 2D (the summed stiffness of YADE's GlobalStiffnessTimeStepper), plus the rolling
    and twisting springs k_r (1 - n_k^2) + k_w n_k^2 in 3D, k_r in 2D."""
    nd = dofs_per_particle(particles.dim, rotation)
    return stiffness_diagonal_kernel(contacts, particles.n, nd, rotation).reshape(-1)
