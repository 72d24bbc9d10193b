"""The minimum image across periodic axes and the contact-point geometry, shared by the
engine, the neighbour search, the time-step analysis and the input checks."""

import math

import numpy as np

from demstep._numba import njit


def _image_count(d, length):
    """The minimum-image rule, the one place it is written: the number of box lengths
    to subtract from a separation component ``d`` [L] (a float or a numpy array) along
    a periodic axis of ``length`` [L]: np.rint(d * (1 / length)), rounded half to even
    (0 when ``length`` is 0: the axis is not periodic). The inverse, not a division:
    inside a loop over pairs it is loop-invariant and computed once, not a division per
    pair and axis. (At an exact half-box tie d / length = k + 1/2 the inverse's rounding
    may pick either of the two equally near images.) Compiled as :func:`image_count`;
    :func:`minimum_image_arrays` runs it on numpy arrays."""
    inverse = 1.0 / length if length > 0.0 else 0.0
    return np.rint(d * inverse)


#: :func:`_image_count` compiled (scalars, inlined in the compiled loops); modules other
#: than this one call :func:`minimum_image` or :func:`pair_geometry` instead
image_count = njit(inline="always")(_image_count)


@njit(inline="always")
def minimum_image(d0, d1, d2, len0, len1, len2):
    """The minimum image of a separation (d0, d1, d2) [L] across the periodic axes of
    lengths ``len0``, ``len1``, ``len2`` [L] (0: the axis is not periodic, and its
    component comes back as it was, a -0.0 as +0.0): the wrapped components
    d_k - len_k n_k [L] and the image counts n_k [-] (floats, :func:`image_count`)
    subtracted, one axis after the other. Every module that needs a minimum image calls
    this (or :func:`pair_geometry`, or :func:`minimum_image_arrays`). Scalars only,
    inlined in the compiled loops (:func:`pair_geometry` and the neighbour search skip
    it when no axis is periodic, :func:`any_periodic`)."""
    n0 = image_count(d0, len0)
    d0 = d0 - len0 * n0
    n1 = image_count(d1, len1)
    d1 = d1 - len1 * n1
    n2 = image_count(d2, len2)
    d2 = d2 - len2 * n2
    return d0, d1, d2, n0, n1, n2


def minimum_image_arrays(d, periodic_len):
    """:func:`minimum_image` of separations ``d`` (C, dim) [L], vectorised with numpy:
    a new array, column k wrapped along the axis of length ``periodic_len[k]`` [L] (0:
    not periodic). The same rule (:func:`_image_count`) and the same operations, element
    by element, as the compiled :func:`minimum_image`: the same bits."""
    d = np.array(d, dtype=np.float64)
    for k in range(d.shape[1]):
        length = float(periodic_len[k])
        d[:, k] -= length * _image_count(d[:, k], length)
    return d


@njit(inline="always")
def any_periodic(periodic_len):
    """Whether any axis of the box lengths ``periodic_len`` (3,) [L] is periodic (> 0):
    the loop-invariant flag with which the loops over pairs skip the minimum image."""
    return periodic_len[0] > 0.0 or periodic_len[1] > 0.0 or periodic_len[2] > 0.0


@njit(inline="always")
def contact_arms(r_i, r_j, distance):
    """Distances [L] from each centre to the contact point of two overlapping particles.

    The contact point is the middle of the overlap delta_n = r_i + r_j - distance, so
    arm_i = r_i - delta_n / 2 and arm_j = r_j - delta_n / 2 (arm_i + arm_j = distance).
    """
    half_overlap = 0.5 * (r_i + r_j - distance)
    return r_i - half_overlap, r_j - half_overlap


@njit(inline="always")
def pair_geometry(xi0, xi1, xi2, xj0, xj1, xj2, r_i, r_j, len0, len1, len2, periodic=True):
    """The geometry of a pair, the one place it is computed: branch vector from i to j
    (d0, d1, d2) [L] with the minimum image (:func:`minimum_image`) along periodic axes
    (lengths ``len*`` [L], 0: not periodic), centre distance [L], overlap
    delta_n = r_i + r_j - distance [L] (> 0: touching), the arms from each centre to the contact point [L]
    (:func:`contact_arms`) and the image counts (n0, n1, n2) [-] subtracted. ``periodic``
    False (no axis periodic: a loop-invariant test in a loop over pairs) skips the
    image counts. Scalars only (array arguments cost a reference count per call in the
    compiled loops)."""
    d0 = xj0 - xi0
    d1 = xj1 - xi1
    d2 = xj2 - xi2
    n0 = 0.0
    n1 = 0.0
    n2 = 0.0
    if periodic:
        d0, d1, d2, n0, n1, n2 = minimum_image(d0, d1, d2, len0, len1, len2)
    dist = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    a_i, a_j = contact_arms(r_i, r_j, dist)
    return d0, d1, d2, dist, r_i + r_j - dist, a_i, a_j, n0, n1, n2


@njit(inline="always")
def into_tangent_plane(ox, oy, oz, nx, ny, nz):
    """A history vector (a tangential force, a rolling or bending moment) carried into
    the tangent plane of the current unit normal n: its normal component removed and
    its magnitude kept (zero stays zero)."""
    mag2_old = ox * ox + oy * oy + oz * oz
    if mag2_old > 0.0:
        on = ox * nx + oy * ny + oz * nz
        ox, oy, oz = ox - on * nx, oy - on * ny, oz - on * nz
        mag2 = ox * ox + oy * oy + oz * oz
        if mag2 > 0.0:
            s = math.sqrt(mag2_old / mag2)  # one root for the ratio of the magnitudes
            ox, oy, oz = ox * s, oy * s, oz * s
    return ox, oy, oz


@njit
def pair_geometry_arrays(x, r, i, j, periodic_len):
    """:func:`pair_geometry` of pairs (i, j) (C,): branch vectors (C, 3), distances,
    overlaps, arms (C,) each and image counts (C, 3)."""
    c = i.shape[0]
    branch = np.empty((c, 3))
    images = np.empty((c, 3))
    dist = np.empty(c)
    delta = np.empty(c)
    arm_i = np.empty(c)
    arm_j = np.empty(c)
    for k in range(c):
        p = i[k]
        q = j[k]
        (branch[k, 0], branch[k, 1], branch[k, 2], dist[k], delta[k], arm_i[k], arm_j[k],
         images[k, 0], images[k, 1], images[k, 2]) = pair_geometry(
            x[p, 0], x[p, 1], x[p, 2], x[q, 0], x[q, 1], x[q, 2], r[p], r[q],
            periodic_len[0], periodic_len[1], periodic_len[2])
    return branch, dist, delta, arm_i, arm_j, images


@njit(inline="always")
def wall_geometry(x0, x1, x2, r, p0, p1, p2, n0, n1, n2):
    """The geometry of a particle (centre x, radius r) against the plane through p with
    unit normal n (into the packing): contact normal from the particle to the wall
    (-n), centre distance to the plane [L], overlap r - distance [L] and the arm
    (:func:`wall_contact_arm`)."""
    dist = (x0 - p0) * n0 + (x1 - p1) * n1 + (x2 - p2) * n2
    return -n0, -n1, -n2, dist, r - dist, wall_contact_arm(dist)


@njit
def wall_geometry_arrays(x, r, p, w, point, normal):
    """:func:`wall_geometry` of particle-wall pairs (p, w) (C,): normals (C, 3),
    distances, overlaps, arms (C,) each."""
    c = p.shape[0]
    nrm = np.empty((c, 3))
    dist = np.empty(c)
    delta = np.empty(c)
    arm = np.empty(c)
    for k in range(c):
        a = p[k]
        b = w[k]
        nrm[k, 0], nrm[k, 1], nrm[k, 2], dist[k], delta[k], arm[k] = wall_geometry(
            x[a, 0], x[a, 1], x[a, 2], r[a], point[b, 0], point[b, 1], point[b, 2],
            normal[b, 0], normal[b, 1], normal[b, 2])
    return nrm, dist, delta, arm


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
