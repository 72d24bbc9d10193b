"""Contact elements: stiffness, transformation and mass matrices, element eigenvalues.

Two formulations, both vectorised over contacts (leading axis C):

* **paper** -- O'Sullivan & Bray (2004) exactly as published: a strut with a normal
  spring K_n and shear springs K_s acting on the relative *translation* of the two
  particles (eqs. 6, 11), plus, with rotation, rotational springs K_s r_eff^2 that
  are decoupled from translation (eqs. 9, 13); transformation T (eqs. 8, 10, 12);
  lumped masses (eqs. 16-19).
* **coupled** -- the tangential springs act on the true slip at the contact point,
  du_s = P (u_j - u_i) - (a_i theta_i + a_j theta_j) x n (P = I - n n^T, a_i and a_j
  the arms from the centres to the contact point; docs/time-step-elements.md), i.e. the
  linearised equations the engine integrates, and the rolling and twisting springs
  (:class:`~demstep.timestep.contacts.ContactSet` ``k_r``, ``k_w``) on the relative rotation
  phi = theta_j - theta_i: a rotational element [[B, -B], [-B, B]] with
  B = k_r (I - n n^T) + k_w n n^T (2D: B = k_r). Its element eigenvalues bound the
  assembly's (Rayleigh, eq. 4) for any polydisperse assembly.

Element DOFs are ordered per particle, translations then rotations:
(u_i, [theta_i], u_j, [theta_j]) -- as in eqs. 9 and 13. A wall contact is an element
whose j side is rigid (its reciprocal mass is zero).
"""

from __future__ import annotations

import numpy as np

from demstep.contact.geometry import tangent_basis
from demstep.kernels.timestep_kernels import symmetric2_top, tangential_rolling_dt
from demstep.timestep.mass_split import ElementMass
from demstep.timestep.stability import damped_dt


def n_rotations(dim: int, rotation: bool) -> int:
    """Rotational DOFs per particle: 0 without rotation, 1 for disks, 3 for spheres."""
    return (1 if dim == 2 else 3) if rotation else 0


def dofs_per_particle(dim: int, rotation: bool) -> int:
    return dim + n_rotations(dim, rotation)


# ----------------------------------------------------------------------------- paper


def paper_effective_radii(normal: np.ndarray, arm: np.ndarray) -> np.ndarray:
    """r_eff (C, n_rot) of eqs. 9 and 13: distance from each rotation axis through the
    centre to the contact point [L].

    2D: the one axis is normal to the plane, r_eff = r (the arm). 3D: the paper
    defines r_eff,k about the particle's axes and illustrates it with rotation about
    the vertical axis (its Figure 4: r for in-plane contacts, r/sqrt(3) for the upper
    row of a rhombic packing); we take the global axes, r_eff,k = a sqrt(1 - n_k^2), so
    the rotational block needs no transformation (T acts on translations only).
    """
    dim = normal.shape[1]
    if dim == 2:
        return arm[:, None].copy()
    return arm[:, None] * np.sqrt(np.clip(1.0 - normal**2, 0.0, None))


def paper_local_stiffness(k_n, k_s, r_eff_i=None, r_eff_j=None, dim: int = 3) -> np.ndarray:
    """Local element stiffness (C, 2nd, 2nd) of eqs. 6 (2D), 9 (2D, rotation),
    11 (3D), 13 (3D, rotation) [M/T^2; rotational entries M L^2/T^2].

    Translation: K_n couples the axial DOFs (+K_n diagonal, -K_n off-diagonal), K_s the
    transverse ones. Rotation (if r_eff given, (C, n_rot)): K_s r_eff_i^2 and
    K_s r_eff_j^2 on the diagonal and -K_s r_eff_i r_eff_j off it, as published (the
    physical slip couples theta_i and theta_j with a + sign; flipping the sign of a DOF
    is a similarity with a diagonal +/-1 matrix, so the eigenvalues are the same).
    """
    k_n = np.atleast_1d(np.asarray(k_n, dtype=np.float64))
    k_s = np.broadcast_to(np.asarray(k_s, dtype=np.float64), k_n.shape)
    c = k_n.shape[0]
    n_rot = 0 if r_eff_i is None else r_eff_i.shape[1]
    nd = dim + n_rot
    K = np.zeros((c, 2 * nd, 2 * nd))
    springs = [k_n] + [k_s] * (dim - 1)
    for a, k in enumerate(springs):
        _couple(K, a, nd + a, k, 1.0, 1.0, -1.0)
    for q in range(n_rot):
        a = dim + q
        _couple(K, a, nd + a, k_s, r_eff_i[:, q], r_eff_j[:, q], -1.0)
    return K


def _couple(K, a, b, k, ra, rb, sign):
    K[:, a, a] += k * ra * ra
    K[:, b, b] += k * rb * rb
    K[:, a, b] += sign * k * ra * rb
    K[:, b, a] += sign * k * ra * rb


def paper_transformation(normal: np.ndarray, rotation: bool) -> np.ndarray:
    """Orthogonal T (C, 2nd, 2nd) of eqs. 8, 10 and 12: per particle, the rows of the
    translational block are the local axes (n, t[, t2]) in global coordinates
    (direction cosines); the rotational block is the identity (eq. 10; in 3D see
    :func:`paper_effective_radii`)."""
    R = tangent_basis(normal)
    c, dim, _ = R.shape
    nd = dofs_per_particle(dim, rotation)
    T = np.zeros((c, 2 * nd, 2 * nd))
    for p in range(2):
        o = p * nd
        T[:, o:o + dim, o:o + dim] = R
        for q in range(dim, nd):
            T[:, o + q, o + q] = 1.0
    return T


def paper_element_mass(mass: ElementMass, dim: int, rotation: bool) -> np.ndarray:
    """Diagonal of the lumped element mass matrix (C, 2nd), eqs. 16-19 [M; M L^2].

    Infinite masses (walls, fixed particles) appear as ``inf``."""
    n_rot = n_rotations(dim, rotation)
    with np.errstate(divide="ignore"):
        cols = ([1.0 / mass.inv_m_i] * dim + [1.0 / mass.inv_I_i] * n_rot
                + [1.0 / mass.inv_m_j] * dim + [1.0 / mass.inv_I_j] * n_rot)
    return np.stack(cols, axis=1)


def paper_element_lambda(contacts, mass: ElementMass, rotation: bool) -> np.ndarray:
    """Largest eigenvalue of M_e^-1 K_e (C,) [1/T^2] for the paper's elements, in closed
    form (eqs. 20-21 reduce it to the local matrices, whose blocks are 2x2 rank one):
    translation max(K_n, K_s)(1/m_i' + 1/m_j'); rotation about axis k
    K_s (r_eff_i,k^2 / I_i' + r_eff_j,k^2 / I_j').

    As the paper defines it: the contacts' rolling and twisting springs (``k_r``,
    ``k_w``) are not part of its elements and are ignored here; the coupled elements
    include them."""
    im = mass.inv_m_i + mass.inv_m_j
    lam = np.maximum(contacts.k_n, contacts.k_s) * im
    if rotation:
        # the largest r_eff^2 over the axes is a^2 (1 - min_k n_k^2) in 3D, a^2 in 2D
        factor = 1.0 if contacts.dim == 2 else 1.0 - (contacts.normal**2).min(axis=1)
        rot = contacts.k_s * factor * (contacts.arm_i**2 * mass.inv_I_i
                                       + contacts.arm_j**2 * mass.inv_I_j)
        lam = np.maximum(lam, rot)
    return lam


def paper_element_matrices(contacts, mass: ElementMass, rotation: bool):
    """Global element stiffness T^T K_local T and mass diagonal of the paper's elements
    (eqs. 7-19; rolling and twisting springs ignored, as in the paper). Returns
    (K_global (C, 2nd, 2nd), M_diag (C, 2nd))."""
    dim = contacts.dim
    if rotation:
        ri = paper_effective_radii(contacts.normal, contacts.arm_i)
        rj = paper_effective_radii(contacts.normal, contacts.arm_j)
    else:
        ri = rj = None
    K_local = paper_local_stiffness(contacts.k_n, contacts.k_s, ri, rj, dim=dim)
    T = paper_transformation(contacts.normal, rotation)
    K_global = np.einsum("cab,cbd,cde->cae", T.transpose(0, 2, 1), K_local, T)
    return K_global, paper_element_mass(mass, dim, rotation)


# --------------------------------------------------------------------------- coupled


def coupled_strain_operator(normal, arm_i, arm_j, rotation: bool):
    """B_i, B_j (C, dim, nd) mapping each particle's DOFs to the relative displacement
    at the contact point in the local frame (n, t1[, t2]):

    Delta = u_j - u_i - (a_i theta_i + a_j theta_j) x n  (2D: theta x n = theta t),
    so Delta_local = B_i q_i + B_j q_j. Dimensionless / [L] for rotational columns.
    """
    R = tangent_basis(normal)
    c, dim, _ = R.shape
    n_rot = n_rotations(dim, rotation)
    Bi = np.zeros((c, dim, dim + n_rot))
    Bj = np.zeros((c, dim, dim + n_rot))
    Bi[:, :, :dim] = -R
    Bj[:, :, :dim] = R
    if rotation:
        if dim == 2:
            # -(a theta z x n) = -a theta t, and t is the second local axis
            Bi[:, 1, 2] = -arm_i
            Bj[:, 1, 2] = -arm_j
        else:
            # -(a theta x n) = a [n]x theta, with [n]x the cross-product matrix of n
            nx = _cross_matrix(normal)
            Bi[:, :, dim:] = arm_i[:, None, None] * np.einsum("cab,cbd->cad", R, nx)
            Bj[:, :, dim:] = arm_j[:, None, None] * np.einsum("cab,cbd->cad", R, nx)
    return Bi, Bj


def _cross_matrix(v):
    c = v.shape[0]
    X = np.zeros((c, 3, 3))
    X[:, 0, 1], X[:, 0, 2] = -v[:, 2], v[:, 1]
    X[:, 1, 0], X[:, 1, 2] = v[:, 2], -v[:, 0]
    X[:, 2, 0], X[:, 2, 1] = -v[:, 1], v[:, 0]
    return X


def spring_diagonal(contacts) -> np.ndarray:
    """D (C, dim): local spring stiffnesses (K_n, K_s[, K_s]) [M/T^2]."""
    return np.concatenate([contacts.k_n[:, None],
                           np.repeat(contacts.k_s[:, None], contacts.dim - 1, axis=1)], axis=1)


def rolling_matrix(contacts, viscous: bool = False) -> np.ndarray:
    """B (C, n_rot, n_rot) of the rolling element: k_r (I - n n^T) + k_w n n^T
    [M L^2/T^2 per rad] in 3D, k_r (1 x 1) for disks (no twisting); ``viscous``: the
    same with c_r, c_w [M L^2/T]."""
    k_r, k_w = (contacts.c_r, contacts.c_w) if viscous else (contacts.k_r, contacts.k_w)
    if contacts.dim == 2:
        return k_r[:, None, None].copy()
    nn = np.einsum("ci,cj->cij", contacts.normal, contacts.normal)
    return k_r[:, None, None] * (np.eye(3) - nn) + k_w[:, None, None] * nn


def coupled_element_blocks(contacts, rotation: bool):
    """Blocks K_ii, K_ij, K_jj (C, nd, nd) of the coupled element stiffness B^T D B, plus
    with rotation the rolling element (+B on the rotations of i and of j, -B between
    them: :func:`rolling_matrix`).

    K_ji = K_ij^T. For wall contacts only K_ii is meaningful."""
    Bi, Bj = coupled_strain_operator(contacts.normal, contacts.arm_i, contacts.arm_j, rotation)
    D = spring_diagonal(contacts)
    DBi = D[:, :, None] * Bi
    DBj = D[:, :, None] * Bj
    Kii = np.einsum("cka,ckb->cab", Bi, DBi)
    Kij = np.einsum("cka,ckb->cab", Bi, DBj)
    Kjj = np.einsum("cka,ckb->cab", Bj, DBj)
    if rotation and contacts.has_rolling:
        dim = contacts.dim
        R = rolling_matrix(contacts)
        Kii[:, dim:, dim:] += R
        Kjj[:, dim:, dim:] += R
        Kij[:, dim:, dim:] -= R
    return Kii, Kij, Kjj


def coupled_element_matrices(contacts, mass: ElementMass, rotation: bool):
    """Global coupled element stiffness (C, 2nd, 2nd) and lumped mass diagonal (C, 2nd)."""
    Kii, Kij, Kjj = coupled_element_blocks(contacts, rotation)
    K = np.concatenate([np.concatenate([Kii, Kij], axis=2),
                        np.concatenate([Kij.transpose(0, 2, 1), Kjj], axis=2)], axis=1)
    return K, paper_element_mass(mass, contacts.dim, rotation)


def _rotation_weights(contacts, mass: ElementMass):
    """c_th = 1/I_i' + 1/I_j' [1/(M L^2)] and e^2 = (a_i/I_i' - a_j/I_j')^2
    [1/(M^2 L^2)]: the entries of W = B M_e^-1 B^T on phi and between phi and the slip
    (:func:`coupled_element_lambda`)."""
    c_th = mass.inv_I_i + mass.inv_I_j
    e = contacts.arm_i * mass.inv_I_i - contacts.arm_j * mass.inv_I_j
    return c_th, e * e


def _rolling_elements(contacts) -> np.ndarray:
    """Mask (C,) of the contacts with a rolling spring or viscous part."""
    return (contacts.k_r != 0) | (contacts.c_r != 0) | (
        ((contacts.k_w != 0) | (contacts.c_w != 0)) if contacts.dim == 3 else False)


def coupled_element_lambda(contacts, mass: ElementMass, rotation: bool) -> np.ndarray:
    """Largest eigenvalue of M_e^-1 K_e (C,) [1/T^2] for coupled elements, closed form.

    The non-zero eigenvalues of M^-1 B^T D B are those of D^1/2 W D^1/2 with
    W = B M^-1 B^T on the element's strains. Without rolling springs the strain is the
    slip Delta and W = (1/m_i' + 1/m_j') I + (a_i^2/I_i' + a_j^2/I_j') P in the local
    frame, so lambda = max(K_n c_m, K_s (c_m + c_r)), c_m = 1/m_i' + 1/m_j',
    c_r = a_i^2/I_i' + a_j^2/I_j' (c_r = 0 without rotation).

    With rolling and twisting springs (rotation on) the strain adds phi = theta_j -
    theta_i: W_phiphi = c_th I (c_th = 1/I_i' + 1/I_j') and W_Deltaphi = e [n]x with
    e = a_j/I_j' - a_i/I_i' (the slip's rotational part is a n x theta). The normal slip
    and the twist phi_n stay apart (K_n c_m and k_w c_th, 3D only); each tangential
    direction pairs with the perpendicular rolling one in the 2 x 2 block
    [[k_t (c_m + c_r), e sqrt(k_t k_r)], [e sqrt(k_t k_r), k_r c_th]] (twice in 3D,
    once in 2D). Contacts without rolling springs give exactly the value above."""
    c_m = mass.inv_m_i + mass.inv_m_j
    c_r = 0.0
    if rotation:
        c_r = contacts.arm_i**2 * mass.inv_I_i + contacts.arm_j**2 * mass.inv_I_j
    lam = np.maximum(contacts.k_n * c_m, contacts.k_s * (c_m + c_r))
    if rotation and contacts.has_rolling:
        c_th, e2 = _rotation_weights(contacts, mass)
        k_t, k_r = contacts.k_s, contacts.k_r
        rolled = np.maximum(contacts.k_n * c_m,
                            symmetric2_top(k_t * (c_m + c_r), k_r * c_th, e2 * k_t * k_r))
        if contacts.dim == 3:
            rolled = np.maximum(rolled, contacts.k_w * c_th)
        lam = np.where(_rolling_elements(contacts), rolled, lam)
    return lam


def element_lambda_numeric(K: np.ndarray, M_diag: np.ndarray) -> np.ndarray:
    """Largest eigenvalue of M_e^-1 K_e for explicit element matrices (slow reference).

    Rigid (infinite-mass) DOFs are dropped: their rows of M^-1 K vanish."""
    with np.errstate(divide="ignore"):
        s = np.where(np.isfinite(M_diag), 1.0 / np.sqrt(M_diag), 0.0)
    A = s[:, :, None] * K * s[:, None, :]
    return np.linalg.eigvalsh(A)[:, -1]


def coupled_element_damped_dt(contacts, mass: ElementMass, rotation: bool,
                              mass_damping: float = 0.0,
                              stiffness_damping: float = 0.0) -> np.ndarray:
    """Critical step (C,) [T] of each coupled element with its dashpots, closed form.

    The element's share of the damped pencil, sigma^2 M_e - sigma C_e - K_e with
    K_e = B^T D B, C_e = a1 M_e + B^T (a2 D + G) B, G = diag(c_n, c_t[, c_t]), is
    positive semi-definite for sigma above every root of, per local axis k,
    sigma^2 - (a1 + (a2 d_k + g_k) w_k) sigma - d_k w_k = 0, where w = (c_m, c_m + c_r,
    ...) are the eigenvalues of B M_e^-1 B^T (see :func:`coupled_element_lambda`), and
    of sigma^2 - a1 sigma = 0 on the complement. Since the element shares sum to the
    global M, C and K, an assembly stepped below min over elements of 2 / sigma_e keeps
    P(dt) = M - dt/2 C - dt^2/4 K positive semi-definite: a rigorous bound for any
    dashpots (:mod:`demstep.timestep.damping`), Rayleigh's theorem (eq. 4) for the
    damped scheme. Without damping it is 2 / sqrt(coupled_element_lambda).

    With rolling and twisting resistance (rotation on; D and G then also hold k_r, k_w
    and c_r, c_w on phi): the normal axis as above, the twist (3D) the root for
    d = k_w, g = c_w, w = c_th, and each tangential-rolling pair of
    :func:`coupled_element_lambda` the largest root of the 2 x 2 pencil
    det((sigma^2 - a1 sigma) I - W (D + sigma (a2 D + G))) = 0, found by Newton's
    method from Weyl's upper bound and returned from above
    (:func:`demstep.kernels.timestep_kernels.tangential_rolling_dt`). Contacts without
    rolling springs or viscous parts give exactly the value above."""
    c_m = mass.inv_m_i + mass.inv_m_j
    c_r = 0.0
    if rotation:
        c_r = contacts.arm_i**2 * mass.inv_I_i + contacts.arm_j**2 * mass.inv_I_j
    w_t = c_m + c_r
    a1, a2 = float(mass_damping), float(stiffness_damping)
    dt_n = damped_dt(contacts.k_n * c_m, a1 + (a2 * contacts.k_n + contacts.c_n) * c_m)
    dt_t = damped_dt(contacts.k_s * w_t, a1 + (a2 * contacts.k_s + contacts.c_t) * w_t)
    if rotation and contacts.has_rolling:
        c_th, e2 = _rotation_weights(contacts, mass)
        rolls = _rolling_elements(contacts)
        dt_tr = tangential_rolling_dt(contacts.k_s, a2 * contacts.k_s + contacts.c_t,
                                      contacts.k_r, a2 * contacts.k_r + contacts.c_r,
                                      w_t, c_th, e2, a1)
        if contacts.dim == 3:
            dt_w = damped_dt(contacts.k_w * c_th, a1 + (a2 * contacts.k_w + contacts.c_w) * c_th)
            dt_tr = np.minimum(dt_tr, dt_w)
        dt_t = np.where(rolls, dt_tr, dt_t)
    return np.minimum(dt_n, dt_t)
