"""Hot loops of the time-step analysis."""

import numpy as np

from demstep._numba import njit


@njit
def _stiffness_diagonal(i, j, normal, arm_i, arm_j, k_n, k_s, n, nd, rotation):
    dim = normal.shape[1]
    diag = np.zeros((n, nd))
    for c in range(i.shape[0]):
        for side in range(2):
            p = i[c] if side == 0 else j[c]
            if p < 0:
                continue
            arm = arm_i[c] if side == 0 else arm_j[c]
            rot = k_s[c] * arm * arm
            for k in range(dim):
                n2 = normal[c, k] * normal[c, k]
                diag[p, k] += k_n[c] * n2 + k_s[c] * (1.0 - n2)
                if rotation and dim == 3:
                    diag[p, dim + k] += rot * (1.0 - n2)
            if rotation and dim == 2:
                diag[p, 2] += rot
    return diag


def stiffness_diagonal_kernel(contacts, n_particles: int, nd: int, rotation: bool) -> np.ndarray:
    """Summed contact stiffness per particle DOF (n, nd); see timestep.assembly."""
    return _stiffness_diagonal(contacts.i, contacts.j, contacts.normal, contacts.arm_i,
                               contacts.arm_j, contacts.k_n, contacts.k_s, int(n_particles),
                               int(nd), bool(rotation))


@njit(inline="always")
def _contact_slip(c, i, j, normal, arm_i, arm_j, x, dim, nd, rotation):
    """Relative displacement of j's contact point w.r.t. i's for contact ``c`` (global
    axes, padded to 3): Delta = u_j - u_i - (a_i theta_i + a_j theta_j) x n; a wall
    side (j < 0) does not move. ``x`` (n, nd) holds the DOFs already scaled."""
    p = i[c]
    q = j[c]
    d0 = -x[p, 0]
    d1 = -x[p, 1]
    d2 = -x[p, 2] if dim == 3 else 0.0
    if q >= 0:
        d0 += x[q, 0]
        d1 += x[q, 1]
        if dim == 3:
            d2 += x[q, 2]
    n0 = normal[c, 0]
    n1 = normal[c, 1]
    n2 = normal[c, 2] if dim == 3 else 0.0
    if rotation:
        if dim == 2:
            th = arm_i[c] * x[p, 2]
            if q >= 0:
                th += arm_j[c] * x[q, 2]
            # theta z x n = theta (-n1, n0)
            d0 += th * n1
            d1 -= th * n0
        else:
            t0 = arm_i[c] * x[p, 3]
            t1 = arm_i[c] * x[p, 4]
            t2 = arm_i[c] * x[p, 5]
            if q >= 0:
                t0 += arm_j[c] * x[q, 3]
                t1 += arm_j[c] * x[q, 4]
                t2 += arm_j[c] * x[q, 5]
            d0 -= t1 * n2 - t2 * n1
            d1 -= t2 * n0 - t0 * n2
            d2 -= t0 * n1 - t1 * n0
    return d0, d1, d2, n0, n1, n2


@njit
def _contact_matvec(i, j, normal, arm_i, arm_j, k_n, k_t, rotation, x, y):
    """y += K x for the coupled contact stiffness K = sum B^T D B (springs ``k_n``,
    ``k_t`` per contact) without assembling it; x, y (n, nd)."""
    dim = normal.shape[1]
    nd = x.shape[1]
    for c in range(i.shape[0]):
        d0, d1, d2, n0, n1, n2 = _contact_slip(c, i, j, normal, arm_i, arm_j, x, dim, nd,
                                               rotation)
        dn = d0 * n0 + d1 * n1 + d2 * n2
        kt = k_t[c]
        a = (k_n[c] - kt) * dn
        f0 = kt * d0 + a * n0
        f1 = kt * d1 + a * n1
        f2 = kt * d2 + a * n2
        p = i[c]
        q = j[c]
        y[p, 0] -= f0
        y[p, 1] -= f1
        if dim == 3:
            y[p, 2] -= f2
        if q >= 0:
            y[q, 0] += f0
            y[q, 1] += f1
            if dim == 3:
                y[q, 2] += f2
        if rotation:
            if dim == 2:
                # d Delta / d theta = -a t, t = (-n1, n0)
                tf = -n1 * f0 + n0 * f1
                y[p, 2] -= arm_i[c] * tf
                if q >= 0:
                    y[q, 2] -= arm_j[c] * tf
            else:
                # d Delta / d theta = a [n]x: gradient -a (n x f)
                c0 = n1 * f2 - n2 * f1
                c1 = n2 * f0 - n0 * f2
                c2 = n0 * f1 - n1 * f0
                y[p, 3] -= arm_i[c] * c0
                y[p, 4] -= arm_i[c] * c1
                y[p, 5] -= arm_i[c] * c2
                if q >= 0:
                    y[q, 3] -= arm_j[c] * c0
                    y[q, 4] -= arm_j[c] * c1
                    y[q, 5] -= arm_j[c] * c2


@njit
def _contact_energies(i, j, normal, arm_i, arm_j, k_n, k_t, rotation, x, out):
    """out[c] = 1/2 Delta_c . D_c Delta_c, the strain energy of each contact for DOFs x."""
    dim = normal.shape[1]
    nd = x.shape[1]
    for c in range(i.shape[0]):
        d0, d1, d2, n0, n1, n2 = _contact_slip(c, i, j, normal, arm_i, arm_j, x, dim, nd,
                                               rotation)
        dn = d0 * n0 + d1 * n1 + d2 * n2
        dt2 = d0 * d0 + d1 * d1 + d2 * d2 - dn * dn
        out[c] = 0.5 * (k_n[c] * dn * dn + k_t[c] * max(dt2, 0.0))


@njit
def _scaled_contact_matvec(i, j, normal, arm_i, arm_j, k_n, k_t, rotation, scale, x, work, y):
    """y = S K S x (S = diag(scale)) for flat x, y (n nd,), ``work`` (n, nd) scratch."""
    n, nd = work.shape
    for p in range(n):
        for a in range(nd):
            work[p, a] = scale[p, a] * x[p * nd + a]
    out = y.reshape((n, nd))
    out[:] = 0.0
    _contact_matvec(i, j, normal, arm_i, arm_j, k_n, k_t, rotation, work, out)
    for p in range(n):
        for a in range(nd):
            out[p, a] *= scale[p, a]


def scaled_contact_matvec(contacts, k_n, k_t, rotation: bool, scale, x, work=None):
    """S K S x for flat x (n nd,), S = diag(scale) with scale (n, nd) = M^-1/2."""
    if work is None:
        work = np.empty_like(scale)
    y = np.empty(x.shape[0])
    _scaled_contact_matvec(contacts.i, contacts.j, contacts.normal, contacts.arm_i,
                           contacts.arm_j, k_n, k_t, bool(rotation), scale,
                           np.ascontiguousarray(x, dtype=np.float64), work, y)
    return y


def contact_matvec(contacts, k_n, k_t, rotation: bool, x: np.ndarray) -> np.ndarray:
    """K x (n, nd) for the coupled contact stiffness with springs ``k_n``, ``k_t`` (C,)."""
    y = np.zeros_like(x)
    _contact_matvec(contacts.i, contacts.j, contacts.normal, contacts.arm_i, contacts.arm_j,
                    k_n, k_t, bool(rotation), x, y)
    return y


def contact_energies(contacts, k_n, k_t, rotation: bool, x: np.ndarray) -> np.ndarray:
    """Strain energy (C,) of each contact's springs ``k_n``, ``k_t`` for the DOFs x (n, nd)."""
    out = np.empty(contacts.n)
    _contact_energies(contacts.i, contacts.j, contacts.normal, contacts.arm_i,
                      contacts.arm_j, k_n, k_t, bool(rotation), x, out)
    return out


def damping_diagonal_kernel(contacts, n_particles: int, nd: int, rotation: bool) -> np.ndarray:
    """Summed dashpot coefficient per particle DOF (n, nd): the diagonal of C = sum
    B^T G B (same form as the stiffness diagonal, with c_n, c_t for k_n, k_s)."""
    return _stiffness_diagonal(contacts.i, contacts.j, contacts.normal, contacts.arm_i,
                               contacts.arm_j, contacts.c_n, contacts.c_t, int(n_particles),
                               int(nd), bool(rotation))
