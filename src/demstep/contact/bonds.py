"""Parallel bonds (Potyondy & Cundall 2004): an elastic beam of finite section glued
between two particles, acting in parallel with their contact law until it breaks.

A bond between i and j has radius R_b = lambda min(r_i, r_j) and section (3D: a disk;
2D: a rectangle of unit thickness)

    3D:  A = pi R^2,   I = pi R^4 / 4,   J = pi R^4 / 2
    2D:  A = 2 R,      I = 2 R^3 / 3,    J = 0 (disks do not twist)

with normal and shear stiffnesses per unit area k_n^b, k_s^b [M/(L^2 T^2)]. Its force
and moment on j grow incrementally from the relative motion of the bond point (the
contact point of the pair: the middle of the gap or overlap; the lagged half-step
velocities of the contact law):

    F_n += -k_n^b A du_n,   F_s += -k_s^b A du_s,   M_t += -k_s^b J dtheta_n,
    M_b += -k_n^b I dtheta_s

(F_n > 0 pushes the particles apart; the shear force and bending moment are rotated
into the current tangent plane first). The largest stresses on the bond's rim,

    sigma = -F_n / A + |M_b| R / I   (tension positive),   tau = |F_s| / A + |M_t| R / J,

break it when sigma >= sigma_c (``tensile_strength``) or tau >= tau_c
(``shear_strength``); a broken bond is gone for good and its strain energy is released
(the ledger's ``bond_broken``). The contact law keeps acting on the pair (a frictional
contact once the bond is gone).

Stiffness seen by the time-step analysis: a contact element of normal and tangential
springs k_n^b A, k_s^b A at the bond point, plus rolling (bending) k_n^b I and twisting
k_s^b J springs on the relative rotation (:func:`bond_springs`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from demstep._numba import njit
from demstep.contact.geometry import minimum_image_arrays
from demstep.contact.laws.base import check_number as _check


@njit(inline="always")
def bond_section(radius, dim):
    """Area A [L^2] (2D: L per unit thickness), second moment I and polar moment J
    [L^4] (2D: L^3, J = 0) of a bond of radius ``radius`` [L]."""
    if dim == 2:
        return 2.0 * radius, 2.0 * radius**3 / 3.0, 0.0
    r2 = radius * radius
    return math.pi * r2, 0.25 * math.pi * r2 * r2, 0.5 * math.pi * r2 * r2


@njit
def bond_springs(radius, k_n, k_s, dim):
    """Springs of bonds (arrays (B,)) as a contact element: normal and tangential
    k_n^b A, k_s^b A [M/T^2], bending and twisting k_n^b I, k_s^b J [M L^2/T^2 per
    rad]."""
    b = radius.shape[0]
    kn = np.empty(b)
    ks = np.empty(b)
    kr = np.empty(b)
    kw = np.empty(b)
    for q in range(b):
        area, second, polar = bond_section(radius[q], dim)
        kn[q] = k_n[q] * area
        ks[q] = k_s[q] * area
        kr[q] = k_n[q] * second
        kw[q] = k_s[q] * polar
    return kn, ks, kr, kw


@dataclass
class ParallelBonds:
    """Parameters of parallel bonds (module docstring): ``normal_stiffness``,
    ``shear_stiffness`` [M/(L^2 T^2)] (stiffness per unit area), ``tensile_strength``,
    ``shear_strength`` [M/(L T^2)] (inf: unbreakable), ``radius_multiplier`` lambda,
    and ``gap`` [L]: pairs whose surfaces are at most this far apart are bonded when
    bonds are created (touching and overlapping pairs always)."""

    normal_stiffness: float
    shear_stiffness: float | None = None
    tensile_strength: float = math.inf
    shear_strength: float = math.inf
    radius_multiplier: float = 1.0
    gap: float = 0.0

    def validate(self) -> "ParallelBonds":
        _check("bonds.normal_stiffness", self.normal_stiffness, strict=True)
        if self.shear_stiffness is not None:
            _check("bonds.shear_stiffness", self.shear_stiffness)
        _check("bonds.tensile_strength", self.tensile_strength, strict=True, allow_inf=True)
        _check("bonds.shear_strength", self.shear_strength, strict=True, allow_inf=True)
        _check("bonds.radius_multiplier", self.radius_multiplier, strict=True)
        _check("bonds.gap", self.gap)
        return self

    @property
    def k_s(self) -> float:
        return float(self.normal_stiffness if self.shear_stiffness is None else self.shear_stiffness)


def bond_candidates(x, r, gap, periodic_len, dim):
    """Pairs (i < j, sorted) whose surfaces are at most ``gap`` [L] apart (overlapping
    included), with the minimum image along axes of ``periodic_len`` > 0 [L]
    (:func:`~demstep.contact.geometry.minimum_image_arrays`)."""
    from scipy.spatial import cKDTree  # (deferred: a heavy import, loaded only when used)

    x = np.asarray(x, dtype=np.float64)
    pts = x[:, :dim].copy()
    reach = 2.0 * float(r.max()) + float(gap)
    box = np.zeros(dim)
    for k in range(dim):
        if periodic_len[k] > 0:
            pts[:, k] = np.mod(pts[:, k], periodic_len[k])
            box[k] = periodic_len[k]
        else:  # a box so large that nothing wraps
            lo = pts[:, k].min()
            pts[:, k] -= lo
            box[k] = pts[:, k].max() + 4.0 * reach + 1.0
    tree = cKDTree(pts, boxsize=box)
    pairs = tree.query_pairs(reach, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    i, j = np.minimum(pairs[:, 0], pairs[:, 1]), np.maximum(pairs[:, 0], pairs[:, 1])
    d = minimum_image_arrays(pts[j] - pts[i], periodic_len)
    surface_gap = np.linalg.norm(d, axis=1) - r[i] - r[j]
    keep = surface_gap <= gap * (1 + 1e-12) + 1e-300
    order = np.lexsort((j[keep], i[keep]))
    return i[keep][order].astype(np.int64), j[keep][order].astype(np.int64)
