"""Contact-point geometry shared by the engine and the time-step analysis."""

import numpy as np

from demstep._numba import njit


@njit(inline="always")
def image_count(d, length):
    """Number of box lengths to subtract from a separation component ``d`` [L] for the
    minimum image along a periodic axis of ``length`` [L] (0 when ``length`` is 0: the
    axis is not periodic)."""
    if length > 0.0:
        return np.rint(d / length)
    return 0.0


@njit(inline="always")
def contact_arms(r_i, r_j, distance):
    """Distances [L] from each centre to the contact point of two overlapping particles.

    The contact point is the middle of the overlap delta_n = r_i + r_j - distance, so
    arm_i = r_i - delta_n / 2 and arm_j = r_j - delta_n / 2 (arm_i + arm_j = distance).
    """
    half_overlap = 0.5 * (r_i + r_j - distance)
    return r_i - half_overlap, r_j - half_overlap


@njit(inline="always")
def wall_contact_arm(distance):
    """Arm [L] of a particle-wall contact: the contact point is on the wall plane, at
    the centre's distance from it (rigid wall, no overlap split)."""
    return distance


def contact_arms_array(r_i, r_j, distance):
    """Vectorised :func:`contact_arms` over numpy arrays."""
    half_overlap = 0.5 * (np.asarray(r_i) + np.asarray(r_j) - np.asarray(distance))
    return r_i - half_overlap, r_j - half_overlap


def tangent_basis(normal: np.ndarray) -> np.ndarray:
    """Local frames (C, dim, dim) whose rows are (n, t1[, t2]) for unit normals (C, dim).

    2D: t = (-n_y, n_x), the paper's local v axis (eq. 8). 3D: t1 is the normalised
    component of the global axis least aligned with n, t2 = n x t1 (right-handed).
    """
    n = np.asarray(normal, dtype=np.float64)
    c, dim = n.shape
    R = np.empty((c, dim, dim))
    R[:, 0] = n
    if dim == 2:
        R[:, 1, 0] = -n[:, 1]
        R[:, 1, 1] = n[:, 0]
        return R
    axis = np.argmin(np.abs(n), axis=1)
    e = np.zeros_like(n)
    e[np.arange(c), axis] = 1.0
    t1 = e - (e * n).sum(axis=1)[:, None] * n
    t1 /= np.linalg.norm(t1, axis=1)[:, None]
    R[:, 1] = t1
    R[:, 2] = np.cross(n, t1)
    return R
