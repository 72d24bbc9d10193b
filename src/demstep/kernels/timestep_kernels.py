"""Hot loops of the time-step analysis."""

import numpy as np

from demstep._numba import CONTRACT, compile_parallel_and_serial, njit, prange
from demstep.contact.laws import rolling_coefficients
from demstep.kernels.dem import band_rows, pair_chunks


@njit
def _stiffness_diagonal(i, j, normal, arm_i, arm_j, k_n, k_s, k_r, k_w, rolling, n, nd,
                        rotation):
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
            if rotation and rolling:
                # the rolling element B = k_r (I - n n^T) + k_w n n^T (2D: k_r) on
                # theta_i and theta_j: its diagonal on either side
                if dim == 2:
                    diag[p, 2] += k_r[c]
                else:
                    for k in range(3):
                        n2 = normal[c, k] * normal[c, k]
                        diag[p, 3 + k] += k_r[c] * (1.0 - n2) + k_w[c] * n2
    return diag


#: placeholder for the rolling arrays of contacts without rolling resistance (never read)
_NO_ROLLING = np.zeros(0)


def _rolling_arrays(contacts, viscous: bool = False):
    """(k_r, k_w, rolling) of the contacts for a kernel (``viscous``: their c_r, c_w);
    ``rolling`` False (and empty placeholders) when the contacts have none, so the
    products without rolling resistance are the same operations as before it existed."""
    if not contacts.has_rolling:
        return _NO_ROLLING, _NO_ROLLING, False
    if viscous:
        return contacts.c_r, contacts.c_w, True
    return contacts.k_r, contacts.k_w, True


def stiffness_diagonal_kernel(contacts, n_particles: int, nd: int, rotation: bool) -> np.ndarray:
    """Summed contact stiffness per particle DOF (n, nd), rolling and twisting springs
    included; see timestep.assembly."""
    k_r, k_w, rolling = _rolling_arrays(contacts)
    return _stiffness_diagonal(contacts.i, contacts.j, contacts.normal, contacts.arm_i,
                               contacts.arm_j, contacts.k_n, contacts.k_s, k_r, k_w, rolling,
                               int(n_particles), int(nd), bool(rotation))


@njit(inline="always")
def _row_values(x, p, nd):
    """Row ``p`` of the DOFs ``x`` (n, nd) as a 6-tuple padded with zeros. Values, not a
    view: a view, or ``x`` itself, handed to a helper per contact made numba count
    references in the loop (2x on a loop of slips, 15-20 % on the 3D product: 66-75
    against 56-60 ms over 6e6 contacts, measured)."""
    if nd == 6:
        return x[p, 0], x[p, 1], x[p, 2], x[p, 3], x[p, 4], x[p, 5]
    if nd == 3:
        return x[p, 0], x[p, 1], x[p, 2], 0.0, 0.0, 0.0
    return x[p, 0], x[p, 1], 0.0, 0.0, 0.0, 0.0


@njit(inline="always")
def _slip_of_rows(xp, xq, has_q, n0, n1, n2, a_i, a_j, dim, rotation):
    """Relative displacement of j's contact point w.r.t. i's (global axes, padded to
    3): Delta = u_j - u_i - (a_i theta_i + a_j theta_j) x n, from the particles' DOF
    rows ``xp``, ``xq`` (:func:`_row_values`; already scaled; ``xq`` ignored without
    ``has_q``: a wall side does not move) and the contact's unit normal and arms [L]."""
    d0 = -xp[0]
    d1 = -xp[1]
    d2 = -xp[2] if dim == 3 else 0.0
    t0 = 0.0
    t1 = 0.0
    t2 = 0.0
    if rotation:
        if dim == 2:
            t2 = a_i * xp[2]
        else:
            t0 = a_i * xp[3]
            t1 = a_i * xp[4]
            t2 = a_i * xp[5]
    if has_q:
        d0 += xq[0]
        d1 += xq[1]
        if dim == 3:
            d2 += xq[2]
        if rotation:
            if dim == 2:
                t2 += a_j * xq[2]
            else:
                t0 += a_j * xq[3]
                t1 += a_j * xq[4]
                t2 += a_j * xq[5]
    if rotation:
        if dim == 2:
            # theta z x n = theta (-n1, n0)
            d0 += t2 * n1
            d1 -= t2 * n0
        else:
            d0 -= t1 * n2 - t2 * n1
            d1 -= t2 * n0 - t0 * n2
            d2 -= t0 * n1 - t1 * n0
    return d0, d1, d2


@njit(inline="always")
def _rotation_of_rows(xp, xq, has_q, dim):
    """phi = theta_j - theta_i (padded to 3; 2D: (0, 0, theta_z)) from the DOF rows with
    rotations (``xq`` ignored without ``has_q``: a wall side does not rotate)."""
    if dim == 2:
        f = -xp[2]
        if has_q:
            f += xq[2]
        return 0.0, 0.0, f
    f0 = -xp[3]
    f1 = -xp[4]
    f2 = -xp[5]
    if has_q:
        f0 += xq[3]
        f1 += xq[4]
        f2 += xq[5]
    return f0, f1, f2


@njit(inline="always")
def _contact_slip(c, i, j, normal, arm_i, arm_j, x, dim, nd, rotation):
    """:func:`_slip_of_rows` of contact ``c`` and the normal (padded to 3) for DOFs
    ``x`` (n, nd), already scaled (the second row only when there is one)."""
    q = j[c]
    n0 = normal[c, 0]
    n1 = normal[c, 1]
    n2 = normal[c, 2] if dim == 3 else 0.0
    xp = _row_values(x, i[c], nd)
    xq = _row_values(x, q, nd) if q >= 0 else xp
    d0, d1, d2 = _slip_of_rows(xp, xq, q >= 0, n0, n1, n2, arm_i[c], arm_j[c], dim, rotation)
    return d0, d1, d2, n0, n1, n2


@njit(inline="always")
def _relative_rotation(c, i, j, x, dim):
    """:func:`_rotation_of_rows` of contact ``c`` for DOFs ``x`` (n, nd)."""
    q = j[c]
    nd = x.shape[1]
    xp = _row_values(x, i[c], nd)
    xq = _row_values(x, q, nd) if q >= 0 else xp
    return _rotation_of_rows(xp, xq, q >= 0, dim)


@njit(inline="always")
def _rolling_moment(kr, kw, f0, f1, f2, n0, n1, n2, dim):
    """B phi with B = k_r (I - n n^T) + k_w n n^T (the moment of the rolling and
    twisting springs on j, sign reversed); 2D: k_r phi_z."""
    if dim == 2:
        return 0.0, 0.0, kr * f2
    a = (kw - kr) * (f0 * n0 + f1 * n1 + f2 * n2)
    return kr * f0 + a * n0, kr * f1 + a * n1, kr * f2 + a * n2


@njit(inline="always")
def _rolling_parts(f0, f1, f2, n0, n1, n2, dim):
    """(|phi_perp|^2, phi_n^2): the squared rolling and twisting parts of phi (2D:
    (phi_z^2, 0))."""
    if dim == 2:
        return f2 * f2, 0.0
    fn = f0 * n0 + f1 * n1 + f2 * n2
    return max(f0 * f0 + f1 * f1 + f2 * f2 - fn * fn, 0.0), fn * fn


@njit
def _contact_matvec(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, rolling, rotation, x, y):
    """y += K x for the coupled contact stiffness K = sum B^T D B (springs ``k_n``,
    ``k_t`` per contact), plus with ``rolling`` the rolling elements (springs ``k_r``,
    ``k_w``), without assembling it; x, y (n, nd)."""
    _contact_matvec_range(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, rolling, rotation,
                          x, y, 0, i.shape[0])


@njit(inline="always")
def _store_row(y, p, nd, v0, v1, v2, v3, v4, v5):
    """Row ``p`` of ``y`` (n, nd) = the first ``nd`` of the values."""
    y[p, 0] = v0
    y[p, 1] = v1
    if nd > 2:
        y[p, 2] = v2
    if nd == 6:
        y[p, 3] = v3
        y[p, 4] = v4
        y[p, 5] = v5


@njit(inline="always")
def _row_dot(x0, x1, x2, x3, x4, x5, y0, y1, y2, y3, y4, y5):
    """The dot product of two rows given as values (padded with zeros)."""
    return ((x0 * y0 + x1 * y1) + (x2 * y2 + x3 * y3)) + (x4 * y4 + x5 * y5)


@njit(inline="always")
def _flush_row(y, p, nd, final_scale, v0, v1, v2, v3, v4, v5):
    """:func:`_store_row`, times row ``p`` of ``final_scale`` unless it is None (a
    compile-time choice: a test of the array per row cost the loop 10 %, measured)."""
    if final_scale is None:
        _store_row(y, p, nd, v0, v1, v2, v3, v4, v5)
        return
    s = final_scale
    y[p, 0] = v0 * s[p, 0]
    y[p, 1] = v1 * s[p, 1]
    if nd > 2:
        y[p, 2] = v2 * s[p, 2]
    if nd == 6:
        y[p, 3] = v3 * s[p, 3]
        y[p, 4] = v4 * s[p, 4]
        y[p, 5] = v5 * s[p, 5]


@njit(inline="always")
def _add_second_row(y, q, dim, rotation, f0, f1, f2, m0, m1, m2, aj, c0, c1, c2, tf):
    """The terms of a contact on its second particle's row ``q`` of ``y``: the force f and
    with ``rotation`` the moment m - a_j (n x f) (2D: m_z - a_j t.f)."""
    y[q, 0] += f0
    y[q, 1] += f1
    if dim == 3:
        y[q, 2] += f2
    if rotation:
        if dim == 3:
            y[q, 3] += m0 - aj * c0
            y[q, 4] += m1 - aj * c1
            y[q, 5] += m2 - aj * c2
        else:
            y[q, 2] += m2 - aj * tf


@njit(inline="always")
def _contact_products(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, rolling, rotation, dim,
                      x, y, start, stop, final_scale, band, own_hi):
    """y += K_c x summed over the contacts c = ``start`` ... ``stop`` - 1 (in order).

    Per contact: the translational springs on the slip Delta at the contact point (as
    :func:`_contact_slip`) and, with ``rolling`` and ``rotation``, the rotational
    element [[B, -B], [-B, B]] on (theta_i, theta_j), B = k_r (I - n n^T) + k_w n n^T
    (2D: k_r; a wall side: B on theta_i only). Inlined into drivers that fix ``dim``,
    ``rotation`` and ``rolling`` as constants (:func:`_contact_matvec_range`).

    The particles' rows are taken as values (:func:`_row_values`), the second one only
    when it exists. The first particle's row of x and of y stay in registers while
    consecutive contacts share it (a contact list sorted by ``i``, as the contact
    search gives it: 1.27x on the 3D product with rotation, measured): y's row is
    written back when the next contact's first particle differs, and a contact whose
    second particle is the held one adds into the held row. Every row receives the
    same operations in the same order as when each contact reads and writes memory
    (the same bits in 3D, measured; in 2D with rotation the compiler fuses some
    multiply-adds differently: the last bits), in any contact order. ``x`` and ``y``
    are distinct arrays.

    For a run of an ordered list (:func:`ordered_contact_runs`: sorted by i, each j
    above its i or a wall) a held row is complete when it is written back: with
    ``final_scale`` (n, nd) given it is written back times its row of
    ``final_scale``, and second particles from ``own_hi`` on are added into ``band``
    (their row minus ``own_hi``) instead of y (``final_scale`` None and ``own_hi`` = n
    otherwise). Returns, with ``final_scale``, the sum over the written rows of x's row
    times the row's complete sum (unscaled): x.y over them for y = S K S x / S, i.e. the
    quadratic form of the scaled product; 0 without."""
    # nd from the constants ``dim`` and ``rotation`` (x.shape[1] is the same number):
    # the row writes' tests on it then fold away, and numba's reference-count pruning
    # can take out the counts of the arrays handed to the inlined row writer (with nd
    # read at run time: two increfs and two decrefs per held row, with the held values
    # spilled around the calls: one serial run of 3e6 contacts, 3D with rotation, 35.2 ms
    # against 31.8, measured)
    nd = (6 if rotation else 3) if dim == 3 else (3 if rotation else 2)
    held = -1
    quad = 0.0
    x0 = x1 = x2 = x3 = x4 = x5 = 0.0
    y0 = y1 = y2 = y3 = y4 = y5 = 0.0
    for c in range(start, stop):
        p = i[c]
        q = j[c]
        has_q = q >= 0
        if p != held:
            if held >= 0:
                if final_scale is not None:
                    quad += _row_dot(x0, x1, x2, x3, x4, x5, y0, y1, y2, y3, y4, y5)
                _flush_row(y, held, nd, final_scale, y0, y1, y2, y3, y4, y5)
            held = p
            x0, x1, x2, x3, x4, x5 = _row_values(x, p, nd)
            y0, y1, y2, y3, y4, y5 = _row_values(y, p, nd)
        n0 = normal[c, 0]
        n1 = normal[c, 1]
        n2 = normal[c, 2] if dim == 3 else 0.0
        r0 = 0.0
        r1 = 0.0
        r2 = 0.0
        xp = (x0, x1, x2, x3, x4, x5)
        xq = _row_values(x, q, nd) if has_q else xp
        d0, d1, d2 = _slip_of_rows(xp, xq, has_q, n0, n1, n2, arm_i[c], arm_j[c], dim,
                                   rotation)
        if rotation and rolling:
            r0, r1, r2 = _rotation_of_rows(xp, xq, has_q, dim)
        dn = d0 * n0 + d1 * n1 + d2 * n2
        kt = k_t[c]
        a = (k_n[c] - kt) * dn
        f0 = kt * d0 + a * n0
        f1 = kt * d1 + a * n1
        f2 = kt * d2 + a * n2
        # d Delta / d theta: 3D a [n]x (gradient -a (n x f)); 2D -a t with t = (-n1, n0)
        c0 = n1 * f2 - n2 * f1
        c1 = n2 * f0 - n0 * f2
        c2 = n0 * f1 - n1 * f0
        tf = -n1 * f0 + n0 * f1
        m0 = 0.0
        m1 = 0.0
        m2 = 0.0
        if rotation and rolling:
            m0, m1, m2 = _rolling_moment(k_r[c], k_w[c], r0, r1, r2, n0, n1, n2, dim)
        y0 -= f0
        y1 -= f1
        if dim == 3:
            y2 -= f2
        if rotation:
            ai = arm_i[c]
            if dim == 3:
                y3 -= ai * c0 + m0
                y4 -= ai * c1 + m1
                y5 -= ai * c2 + m2
            else:
                y2 -= ai * tf + m2
        if has_q:
            aj = arm_j[c] if rotation else 0.0
            if q == held:  # (i == j: not from a contact search, but kept exact)
                y0 += f0
                y1 += f1
                if dim == 3:
                    y2 += f2
                if rotation:
                    if dim == 3:
                        y3 += m0 - aj * c0
                        y4 += m1 - aj * c1
                        y5 += m2 - aj * c2
                    else:
                        y2 += m2 - aj * tf
            elif q < own_hi:
                _add_second_row(y, q, dim, rotation, f0, f1, f2, m0, m1, m2, aj, c0, c1, c2,
                                tf)
            else:  # (a branch of its own: no array chosen per contact, no reference counts)
                _add_second_row(band, q - own_hi, dim, rotation, f0, f1, f2, m0, m1, m2, aj,
                                c0, c1, c2, tf)
    if held >= 0:
        if final_scale is not None:
            quad += _row_dot(x0, x1, x2, x3, x4, x5, y0, y1, y2, y3, y4, y5)
        _flush_row(y, held, nd, final_scale, y0, y1, y2, y3, y4, y5)
    return quad


@njit(fastmath=CONTRACT)
def _products_3d_rotation(i, j, normal, arm_i, arm_j, k_n, k_t, x, y, start, stop,
                          final_scale, band, own_hi):
    return _contact_products(i, j, normal, arm_i, arm_j, k_n, k_t, _NO_ROLLING, _NO_ROLLING,
                             False, True, 3, x, y, start, stop, final_scale, band, own_hi)


@njit(fastmath=CONTRACT)
def _products_3d_rolling(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, x, y, start, stop,
                         final_scale, band, own_hi):
    return _contact_products(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, True, True, 3, x,
                             y, start, stop, final_scale, band, own_hi)


@njit(fastmath=CONTRACT)
def _products_3d_translation(i, j, normal, arm_i, arm_j, k_n, k_t, x, y, start, stop,
                             final_scale, band, own_hi):
    return _contact_products(i, j, normal, arm_i, arm_j, k_n, k_t, _NO_ROLLING, _NO_ROLLING,
                             False, False, 3, x, y, start, stop, final_scale, band, own_hi)


@njit(fastmath=CONTRACT)
def _products_2d_rotation(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, rolling, x, y,
                          start, stop, final_scale, band, own_hi):
    return _contact_products(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, rolling, True,
                             2, x, y, start, stop, final_scale, band, own_hi)


@njit(fastmath=CONTRACT)
def _products_2d_translation(i, j, normal, arm_i, arm_j, k_n, k_t, x, y, start, stop,
                             final_scale, band, own_hi):
    return _contact_products(i, j, normal, arm_i, arm_j, k_n, k_t, _NO_ROLLING, _NO_ROLLING,
                             False, False, 2, x, y, start, stop, final_scale, band, own_hi)


@njit
def _contact_matvec_range(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, rolling, rotation,
                          x, y, start, stop):
    """y += K_c x summed over the contacts c = ``start`` ... ``stop`` - 1 (in order):
    :func:`_contact_range_products`, every row written back as summed, no band."""
    _contact_range_products(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, rolling, rotation,
                            x, y, start, stop, None, y, y.shape[0])


@njit
def _contact_range_products(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, rolling,
                            rotation, x, y, start, stop, final_scale, band, own_hi):
    """y += K_c x summed over the contacts c = ``start`` ... ``stop`` - 1 (in order), by
    a driver compiled for the dimension and the DOFs (:func:`_contact_products` with
    them as constants: 2.2x on the 3D product with rotation, measured; in 2D too, so that
    the number of DOFs per row is a constant there as well), with
    multiply-adds fused (:data:`~demstep._numba.CONTRACT`: 3-4 % on that loop); returns
    the quadratic form of the written rows (:func:`_contact_products`)."""
    if normal.shape[1] == 2:
        if rotation:
            return _products_2d_rotation(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w,
                                         rolling, x, y, start, stop, final_scale, band, own_hi)
        return _products_2d_translation(i, j, normal, arm_i, arm_j, k_n, k_t, x, y, start,
                                        stop, final_scale, band, own_hi)
    if not rotation:
        return _products_3d_translation(i, j, normal, arm_i, arm_j, k_n, k_t, x, y, start,
                                        stop, final_scale, band, own_hi)
    if rolling:
        return _products_3d_rolling(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, x, y,
                                    start, stop, final_scale, band, own_hi)
    return _products_3d_rotation(i, j, normal, arm_i, arm_j, k_n, k_t, x, y, start, stop,
                                 final_scale, band, own_hi)


@njit
def _contact_energies(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, rolling, rotation, x,
                      out):
    """out[c] = 1/2 Delta_c . D_c Delta_c (+ 1/2 phi_c . B_c phi_c with ``rolling``), the
    strain energy of each contact for DOFs x."""
    dim = normal.shape[1]
    nd = x.shape[1]
    for c in range(i.shape[0]):
        d0, d1, d2, n0, n1, n2 = _contact_slip(c, i, j, normal, arm_i, arm_j, x, dim, nd,
                                               rotation)
        dn = d0 * n0 + d1 * n1 + d2 * n2
        dt2 = d0 * d0 + d1 * d1 + d2 * d2 - dn * dn
        out[c] = 0.5 * (k_n[c] * dn * dn + k_t[c] * max(dt2, 0.0))
        if rolling and rotation:
            f0, f1, f2 = _relative_rotation(c, i, j, x, dim)
            fr2, fw2 = _rolling_parts(f0, f1, f2, n0, n1, n2, dim)
            out[c] += 0.5 * (k_r[c] * fr2 + k_w[c] * fw2)


@njit
def _scaled_contact_matvec(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, rolling, rotation,
                           scale, x, work, y):
    """y = S K S x (S = diag(scale)) for flat x, y (n nd,), ``work`` (n, nd) scratch."""
    n, nd = work.shape
    for p in range(n):
        for a in range(nd):
            work[p, a] = scale[p, a] * x[p * nd + a]
    out = y.reshape((n, nd))
    out[:] = 0.0
    _contact_matvec(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, rolling, rotation, work,
                    out)
    for p in range(n):
        for a in range(nd):
            out[p, a] *= scale[p, a]


def scaled_contact_matvec(contacts, k_n, k_t, rotation: bool, scale, x, work=None, out=None,
                          k_r=None, k_w=None):
    """S K S x for flat x (n nd,), S = diag(scale) with scale (n, nd) = M^-1/2 (into
    ``out`` when given); K with springs ``k_n``, ``k_t`` [M/T^2] and, when given,
    rolling and twisting springs ``k_r``, ``k_w`` [M L^2/T^2 per rad] (C,) each."""
    if work is None:
        work = np.empty_like(scale)
    y = np.empty(x.shape[0]) if out is None else out
    rolling = k_r is not None and bool(rotation)
    _scaled_contact_matvec(contacts.i, contacts.j, contacts.normal, contacts.arm_i,
                           contacts.arm_j, k_n, k_t, k_r if rolling else _NO_ROLLING,
                           k_w if rolling else _NO_ROLLING, rolling, bool(rotation), scale,
                           np.ascontiguousarray(x, dtype=np.float64), work, y)
    return y


def contact_matvec(contacts, k_n, k_t, rotation: bool, x: np.ndarray, k_r=None,
                   k_w=None) -> np.ndarray:
    """K x (n, nd) for the coupled contact stiffness with springs ``k_n``, ``k_t`` (C,)
    [M/T^2] and, when given, rolling and twisting springs ``k_r``, ``k_w`` (C,)
    [M L^2/T^2 per rad]."""
    y = np.zeros_like(x)
    rolling = k_r is not None and bool(rotation)
    _contact_matvec(contacts.i, contacts.j, contacts.normal, contacts.arm_i, contacts.arm_j,
                    k_n, k_t, k_r if rolling else _NO_ROLLING, k_w if rolling else _NO_ROLLING,
                    rolling, bool(rotation), x, y)
    return y


# --- products through rigid bodies (clumps) ----------------------------------------

@njit(inline="always")
def _body_rotation(body_rot, b, q, o, dim):
    """theta = body_rot[b] q[o, dim:] (3D; 2D: the one entry times q[o, 2], as
    (0, 0, theta_z))."""
    if dim == 2:
        return 0.0, 0.0, body_rot[b, 0, 0] * q[o, 2]
    a0 = q[o, 3]
    a1 = q[o, 4]
    a2 = q[o, 5]
    return (body_rot[b, 0, 0] * a0 + body_rot[b, 0, 1] * a1 + body_rot[b, 0, 2] * a2,
            body_rot[b, 1, 0] * a0 + body_rot[b, 1, 1] * a1 + body_rot[b, 1, 2] * a2,
            body_rot[b, 2, 0] * a0 + body_rot[b, 2, 1] * a1 + body_rot[b, 2, 2] * a2)


@njit(inline="always")
def _expand_member(s, q, member_index, member_body, member_arm, body_trans, body_rot,
                   n_free, rotation, dim, u):
    """Member s's row of u: u = v + theta x a and its rotation theta, with (v, theta)
    = (m^-1/2 q_t, I_w^-1/2 q_r) of its body (owner n_free + b) and a its arm."""
    p = member_index[s]
    b = member_body[s]
    o = n_free + b
    t = body_trans[b]
    for a in range(dim):
        u[p, a] = t * q[o, a]
    if rotation:
        th0, th1, th2 = _body_rotation(body_rot, b, q, o, dim)
        a0 = member_arm[s, 0]
        a1 = member_arm[s, 1]
        if dim == 2:
            u[p, 0] -= th2 * a1
            u[p, 1] += th2 * a0
            u[p, 2] = th2
        else:
            a2 = member_arm[s, 2]
            u[p, 0] += th1 * a2 - th2 * a1
            u[p, 1] += th2 * a0 - th0 * a2
            u[p, 2] += th0 * a1 - th1 * a0
            u[p, 3] = th0
            u[p, 4] = th1
            u[p, 5] = th2


@njit(inline="always")
def _reduce_body(b, y, member_index, member_arm, body_trans, body_rot, body_start,
                 body_members, n_free, rotation, dim, out):
    """Body b's row of out: the force and the torque (+ a x f of each member) of its
    members' rows of y, summed in member order, scaled by m^-1/2 and I_w^-1/2."""
    f0 = 0.0
    f1 = 0.0
    f2 = 0.0
    m0 = 0.0
    m1 = 0.0
    m2 = 0.0
    for k in range(body_start[b], body_start[b + 1]):
        s = body_members[k]
        p = member_index[s]
        f0 += y[p, 0]
        f1 += y[p, 1]
        if dim == 3:
            f2 += y[p, 2]
        if rotation:
            a0 = member_arm[s, 0]
            a1 = member_arm[s, 1]
            if dim == 2:
                m2 += y[p, 2] + (a0 * y[p, 1] - a1 * y[p, 0])
            else:
                a2 = member_arm[s, 2]
                m0 += y[p, 3] + (a1 * y[p, 2] - a2 * y[p, 1])
                m1 += y[p, 4] + (a2 * y[p, 0] - a0 * y[p, 2])
                m2 += y[p, 5] + (a0 * y[p, 1] - a1 * y[p, 0])
    o = n_free + b
    t = body_trans[b]
    out[o, 0] = t * f0
    out[o, 1] = t * f1
    if dim == 3:
        out[o, 2] = t * f2
    if rotation:
        if dim == 2:
            out[o, 2] = body_rot[b, 0, 0] * m2
        else:
            for r in range(3):
                out[o, 3 + r] = (body_rot[b, r, 0] * m0 + body_rot[b, r, 1] * m1
                                 + body_rot[b, r, 2] * m2)


@njit(inline="always")
def _expand_owners(q, free_index, free_scale, member_index, member_body, member_arm,
                   body_trans, body_rot, rotation, dim, u):
    """u (N, nd): the spheres' physical DOFs of the owners' scaled DOFs q (owners, nd)
    (free spheres first, then the bodies): a free sphere's scaled by its M^-1/2, a
    member's by :func:`_expand_member`; per sphere, in parallel when inlined into a
    parallel kernel."""
    nd = u.shape[1]
    n_free = free_index.shape[0]
    for s in prange(n_free):
        for a in range(nd):
            u[free_index[s], a] = free_scale[s, a] * q[s, a]
    for s in prange(member_index.shape[0]):
        _expand_member(s, q, member_index, member_body, member_arm, body_trans, body_rot,
                       n_free, rotation, dim, u)


@njit
def _owner_expand(q, free_index, free_scale, member_index, member_body, member_arm,
                  body_trans, body_rot, rotation, dim, u):
    """:func:`_expand_owners`, serial."""
    _expand_owners(q, free_index, free_scale, member_index, member_body, member_arm,
                   body_trans, body_rot, rotation, dim, u)


def _owner_contact_matvec_runs(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, rolling,
                               rotation, free_index, free_scale, member_index, member_body,
                               member_arm, body_trans, body_rot, body_start, body_members, q,
                               u, y, chunks, spans, buf, out):
    """out (owners, nd) = S G^T K G S q: the owners' scaled DOFs q expanded to the
    spheres' u (N, nd) (per sphere, :func:`_expand_member`), the contact product y = K u
    in runs of contacts each summed into its own buffer over its particle range (the
    first run into y, run c > 0 into ``buf[c - 1]``, added in run order:
    :func:`_chunked_scaled_matvec`), then reduced per owner (a body over its members
    ``body_members[body_start[b]:body_start[b + 1]]``: :func:`_reduce_body`). One run:
    the serial product."""
    dim = normal.shape[1]
    nd = u.shape[1]
    n_free = free_index.shape[0]
    _expand_owners(q, free_index, free_scale, member_index, member_body, member_arm,
                   body_trans, body_rot, rotation, dim, u)
    n_chunks = chunks.shape[0] - 1
    for c in prange(n_chunks):
        part = y if c == 0 else buf[c - 1]
        for p in range(spans[c, 0], spans[c, 1]):
            for a in range(nd):
                part[p, a] = 0.0
        _contact_matvec_range(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, rolling,
                              rotation, u, part, chunks[c], chunks[c + 1])
    for p in prange(y.shape[0]):  # (rows outside every run's range: zero)
        in_first = spans[0, 0] <= p and p < spans[0, 1]
        for a in range(nd):
            total = y[p, a] if in_first else 0.0
            for c in range(1, n_chunks):
                if spans[c, 0] <= p and p < spans[c, 1]:
                    total += buf[c - 1, p, a]
            y[p, a] = total
    for s in prange(n_free):
        for a in range(nd):
            out[s, a] = free_scale[s, a] * y[free_index[s], a]
    for b in prange(body_start.shape[0] - 1):
        _reduce_body(b, y, member_index, member_arm, body_trans, body_rot, body_start,
                     body_members, n_free, rotation, dim, out)


_owner_matvec_parallel, _owner_matvec_serial = \
    compile_parallel_and_serial(_owner_contact_matvec_runs)


def owner_expand(owner_map, q, u):
    """u (N, nd) = the spheres' physical DOFs of owner DOFs q (owners, nd) scaled by
    M^1/2 (:class:`demstep.timestep.clumps.OwnerMap`)."""
    om = owner_map
    _owner_expand(np.ascontiguousarray(q, dtype=np.float64), om.free_index, om.free_scale,
                  om.member_index, om.member_body, om.arm, om.body_trans, om.body_rot,
                  om.rotation, om.dim, u)
    return u


def owner_contact_matvec(owner_map, contacts, k_n, k_t, rotation: bool, q, u, y, out, runs,
                         k_r=None, k_w=None):
    """out (owners, nd) = S G^T K G S q for owner DOFs q (owners, nd): K the contact
    stiffness with springs ``k_n``, ``k_t`` (and, when given, ``k_r``, ``k_w``) of
    the spheres, G the map from the owners' DOFs to the spheres' (members move with
    their bodies), S = M^-1/2 of the owners; u, y (N, nd) scratch. ``runs`` (chunks,
    spans, buffers) of :func:`contact_chunks`: more than one run, threaded."""
    om = owner_map
    rolling = k_r is not None and bool(rotation)
    chunks, spans, buf = runs
    kernel = _owner_matvec_parallel if len(chunks) > 2 else _owner_matvec_serial
    kernel(contacts.i, contacts.j, contacts.normal, contacts.arm_i, contacts.arm_j, k_n, k_t,
           k_r if rolling else _NO_ROLLING, k_w if rolling else _NO_ROLLING, rolling,
           bool(rotation), om.free_index, om.free_scale, om.member_index, om.member_body,
           om.arm, om.body_trans, om.body_rot, om.body_start, om.body_members,
           np.ascontiguousarray(q, dtype=np.float64), u, y, chunks, spans, buf, out)
    return out


def contact_energies(contacts, k_n, k_t, rotation: bool, x: np.ndarray, k_r=None,
                     k_w=None) -> np.ndarray:
    """Strain energy (C,) of each contact's springs ``k_n``, ``k_t`` (and, when given,
    rolling and twisting springs ``k_r``, ``k_w``) for the DOFs x (n, nd)."""
    out = np.empty(contacts.n)
    rolling = k_r is not None and bool(rotation)
    _contact_energies(contacts.i, contacts.j, contacts.normal, contacts.arm_i,
                      contacts.arm_j, k_n, k_t, k_r if rolling else _NO_ROLLING,
                      k_w if rolling else _NO_ROLLING, rolling, bool(rotation), x, out)
    return out


def damping_diagonal_kernel(contacts, n_particles: int, nd: int, rotation: bool) -> np.ndarray:
    """Summed dashpot coefficient per particle DOF (n, nd): the diagonal of C = sum
    B^T G B (same form as the stiffness diagonal, with c_n, c_t, c_r, c_w for k_n, k_s,
    k_r, k_w)."""
    c_r, c_w, rolling = _rolling_arrays(contacts, viscous=True)
    return _stiffness_diagonal(contacts.i, contacts.j, contacts.normal, contacts.arm_i,
                               contacts.arm_j, contacts.c_n, contacts.c_t, c_r, c_w, rolling,
                               int(n_particles), int(nd), bool(rotation))


# --- threaded matrix-free products -------------------------------------------------

def contact_chunks(contacts, n_particles: int, n_chunks: int):
    """Cut the contact list into ``n_chunks`` runs of equal length (boundaries
    (n_chunks + 1,)) and give the particle range [lo, hi) that each run touches
    (spans (n_chunks, 2)): its output buffer is written there only. Any contact order
    works; sorted by ``i`` (as the contact search gives them), the spans barely overlap."""
    n_c = contacts.n
    chunks = np.linspace(0, n_c, n_chunks + 1).astype(np.int64)
    spans = np.zeros((n_chunks, 2), dtype=np.int64)
    for c in range(n_chunks):
        a, b = chunks[c], chunks[c + 1]
        if a == b:
            continue
        jj = contacts.j[a:b]
        jj = jj[jj >= 0]
        lo = int(contacts.i[a:b].min())
        hi = int(contacts.i[a:b].max())
        if len(jj):
            lo, hi = min(lo, int(jj.min())), max(hi, int(jj.max()))
        spans[c] = lo, min(hi + 1, n_particles)
    return chunks, spans


def _chunked_scaled_matvec(i, j, normal, arm_i, arm_j, k_n, k_t, rotation, scale, x, work,
                           chunks, spans, buf, y, k_r=None, k_w=None):
    """y = S K S x like :func:`_scaled_contact_matvec`, the contacts cut into runs
    (``chunks``), one per thread, each summed over its particle range ``spans[c]`` into
    its own buffer: the first run into y itself, run c > 0 into ``buf[c - 1]`` (n, nd)
    (one vector less in memory: 49 MB at 1e6 spheres); the buffers are then added in run
    order (fixed: the result does not depend on the scheduling). With one run it is
    bit-identical to the serial product. Rolling and twisting springs ``k_r``, ``k_w``
    (C,) when given (last, optional: None compiles the product without them)."""
    n, nd = work.shape
    n_chunks = chunks.shape[0] - 1
    if k_r is None:
        kr = np.zeros(0)
        kw = np.zeros(0)
        rolling = False
    else:
        kr = k_r
        kw = k_w
        rolling = rotation
    for p in prange(n):
        for a in range(nd):
            work[p, a] = scale[p, a] * x[p * nd + a]
    first = y.reshape((n, nd))
    for c in prange(n_chunks):
        out = first if c == 0 else buf[c - 1]
        for p in range(spans[c, 0], spans[c, 1]):
            for a in range(nd):
                out[p, a] = 0.0
        _contact_matvec_range(i, j, normal, arm_i, arm_j, k_n, k_t, kr, kw, rolling,
                              rotation, work, out, chunks[c], chunks[c + 1])
    for p in prange(n):
        in_first = spans[0, 0] <= p and p < spans[0, 1]
        for a in range(nd):
            s = first[p, a] if in_first else 0.0
            for c in range(1, n_chunks):
                if spans[c, 0] <= p and p < spans[c, 1]:
                    s += buf[c - 1, p, a]
            y[p * nd + a] = s * scale[p, a]


_chunked_scaled_matvec_parallel, _chunked_scaled_matvec_serial = \
    compile_parallel_and_serial(_chunked_scaled_matvec)


def chunked_scaled_contact_matvec(contacts, k_n, k_t, rotation: bool, scale, x, work, chunks,
                                  spans, buf, out=None, parallel: bool = True, k_r=None,
                                  k_w=None):
    """S K S x for flat x like :func:`scaled_contact_matvec` (rolling and twisting springs
    ``k_r``, ``k_w`` when given), the contact runs (:func:`contact_chunks`) summed in
    parallel into the result and ``buf`` (n_chunks - 1, n, nd)."""
    y = np.empty(x.shape[0]) if out is None else out
    kernel = _chunked_scaled_matvec_parallel if parallel else _chunked_scaled_matvec_serial
    args = (contacts.i, contacts.j, contacts.normal, contacts.arm_i, contacts.arm_j, k_n, k_t,
            bool(rotation), scale, np.ascontiguousarray(x, dtype=np.float64), work, chunks,
            spans, buf, y)
    if k_r is not None and rotation:
        kernel(*args, k_r, k_w)
    else:
        kernel(*args)
    return y


def ordered_contact_runs(contacts, n_particles: int, n_runs: int):
    """The runs of an *ordered* contact list for :func:`ordered_scaled_contact_matvec`,
    or None when the list is not ordered. Ordered: up to its last pair, sorted by i with
    each j above its i (or a wall); after it, walls in any order (the contact search's
    pairs, then its walls). Returns (chunks (n_runs + 1,), spans (n_runs, 2), unheld,
    band rows): run c starts at a particle's first contact and owns the particles from
    its first i to the next run's (:func:`demstep.kernels.dem.pair_chunks`); a row of
    its own is complete once its contacts are done, except for second particles of
    earlier runs (their bands); the walls after the last pair start at chunks[-1].
    ``unheld``: the particles that are no such contact's i (their rows get other terms
    only)."""
    i, j = contacts.i, contacts.j
    pairs = np.flatnonzero(j >= 0)
    end = int(pairs[-1]) + 1 if len(pairs) else 0
    i, j = i[:end], j[:end]
    if end and not (np.all(i[1:] >= i[:-1]) and np.all((j > i) | (j < 0))):
        return None
    chunks, spans = pair_chunks(i, j, n_particles, max(1, int(n_runs)))
    held = np.zeros(n_particles, dtype=bool)
    held[i] = True
    return chunks, spans, np.flatnonzero(~held), band_rows(spans, n_particles)


def _ordered_scaled_matvec(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, rolling, rotation,
                           scale, x, work, chunks, spans, unheld, band, quad, y):
    """y = S K S x for flat x, y (n nd,) of an ordered contact list cut into runs
    (:func:`ordered_contact_runs`), one per thread: x scaled into ``work`` (n, nd); each
    run's own rows and band zeroed; the walls after the last pair added unscaled
    (serial: a boundary's worth); then each run writes its rows, each complete when its
    first particle's contacts are done, scaled as it is written back; terms on rows of
    later runs go to the run's band ``band[c]`` (rows from the next run's first
    particle). Then the unheld rows are scaled, and the bands added scaled, in run
    order (fixed: the result does not depend on the scheduling). No pass over all
    rows to sum buffers or scale the result. Returns x.y (the quadratic form, for the
    Lanczos coefficient alpha without a pass over x and y: the runs' written rows, then
    the unheld rows, then the bands, in order; ``quad`` (n_runs,) scratch)."""
    n, nd = work.shape
    n_runs = chunks.shape[0] - 1
    for p in prange(n):
        for a in range(nd):
            work[p, a] = scale[p, a] * x[p * nd + a]
    out = y.reshape((n, nd))
    for c in prange(n_runs):
        own_lo = spans[c, 0]
        own_hi = spans[c + 1, 0] if c + 1 < n_runs else n
        for p in range(own_lo, own_hi):
            for a in range(nd):
                out[p, a] = 0.0
        b = band[c]
        for p in range(spans[c, 1] - own_hi):
            for a in range(nd):
                b[p, a] = 0.0
    if chunks[n_runs] < i.shape[0]:
        _contact_range_products(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w, rolling,
                                rotation, work, out, chunks[n_runs], i.shape[0], None, out,
                                n)
    for c in prange(n_runs):
        own_hi = spans[c + 1, 0] if c + 1 < n_runs else n
        b = band[c]
        quad[c] = _contact_range_products(i, j, normal, arm_i, arm_j, k_n, k_t, k_r, k_w,
                                          rolling, rotation, work, out, chunks[c],
                                          chunks[c + 1], scale, b, own_hi)
    total = 0.0
    for c in range(n_runs):
        total += quad[c]
    for u in range(unheld.shape[0]):  # (a few: a face of the assembly)
        p = unheld[u]
        for a in range(nd):
            total += work[p, a] * out[p, a]
            out[p, a] *= scale[p, a]
    for c in range(n_runs - 1):
        own_hi = spans[c + 1, 0]
        b = band[c]
        for p in range(own_hi, spans[c, 1]):
            for a in range(nd):
                v = b[p - own_hi, a]
                total += work[p, a] * v
                out[p, a] += scale[p, a] * v
    return total


_ordered_scaled_matvec_parallel, _ordered_scaled_matvec_serial = \
    compile_parallel_and_serial(_ordered_scaled_matvec)


def ordered_scaled_contact_matvec(contacts, k_n, k_t, rotation: bool, scale, x, work, runs,
                                  band, out=None, parallel: bool = True, k_r=None,
                                  k_w=None):
    """S K S x for flat x like :func:`scaled_contact_matvec` (rolling and twisting springs
    ``k_r``, ``k_w`` when given), for an ordered contact list and its ``runs``
    (:func:`ordered_contact_runs`), with ``band`` (n_runs, band rows, nd) scratch.
    Returns (y, x.y)."""
    y = np.empty(x.shape[0]) if out is None else out
    chunks, spans, unheld, _ = runs
    rolling = k_r is not None and bool(rotation)
    kernel = _ordered_scaled_matvec_parallel if parallel else _ordered_scaled_matvec_serial
    quad = kernel(contacts.i, contacts.j, contacts.normal, contacts.arm_i, contacts.arm_j,
                  k_n, k_t, k_r if rolling else _NO_ROLLING, k_w if rolling else _NO_ROLLING,
                  rolling, bool(rotation), scale, np.ascontiguousarray(x, dtype=np.float64),
                  work, chunks, spans, unheld, band, np.empty(len(chunks) - 1), y)
    return y, float(quad)


def _contact_quadratic_forms(i, j, normal, arm_i, arm_j, k_n, k_t, c_n, c_t, k_r, k_w, c_r,
                             c_w, rolling, rotation, x, chunks, sums):
    """sums[c] = (x.K x, x.C x) over the contacts of run c, K with springs ``k_n``,
    ``k_t`` and C with ``c_n``, ``c_t`` (each the sum over contacts of
    Delta.D Delta), plus with ``rolling`` the rolling elements (phi.B phi, springs
    ``k_r``, ``k_w`` and ``c_r``, ``c_w``); x (n, nd) already scaled."""
    dim = normal.shape[1]
    nd = x.shape[1]
    for r in prange(chunks.shape[0] - 1):
        sk = 0.0
        sc = 0.0
        for c in range(chunks[r], chunks[r + 1]):
            d0, d1, d2, n0, n1, n2 = _contact_slip(c, i, j, normal, arm_i, arm_j, x, dim, nd,
                                                   rotation)
            dn = d0 * n0 + d1 * n1 + d2 * n2
            dt2 = max(d0 * d0 + d1 * d1 + d2 * d2 - dn * dn, 0.0)
            sk += k_n[c] * dn * dn + k_t[c] * dt2
            sc += c_n[c] * dn * dn + c_t[c] * dt2
            if rolling:
                f0, f1, f2 = _relative_rotation(c, i, j, x, dim)
                fr2, fw2 = _rolling_parts(f0, f1, f2, n0, n1, n2, dim)
                sk += k_r[c] * fr2 + k_w[c] * fw2
                sc += c_r[c] * fr2 + c_w[c] * fw2
        sums[r, 0] = sk
        sums[r, 1] = sc


_quadratic_forms_parallel, _quadratic_forms_serial = \
    compile_parallel_and_serial(_contact_quadratic_forms)


def _rolling_fields(contacts, rotation: bool):
    """(k_r, k_w, c_r, c_w, rolling) of the contacts for a kernel (placeholders and
    ``rolling`` False without rolling resistance or without rotation)."""
    if rotation and contacts.has_rolling:
        return contacts.k_r, contacts.k_w, contacts.c_r, contacts.c_w, True
    return _NO_ROLLING, _NO_ROLLING, _NO_ROLLING, _NO_ROLLING, False


def contact_quadratic_forms(contacts, rotation: bool, x, chunks=None, parallel: bool = False):
    """(x.K x, x.C_d x) for DOFs x (n, nd) in one pass over the contacts: K with the
    springs ``k_n``, ``k_s`` (and ``k_r``, ``k_w``), C_d with the dashpots ``c_n``,
    ``c_t`` (and ``c_r``, ``c_w``) [same units as the springs times T]. The runs
    ``chunks`` are summed in order (deterministic)."""
    if chunks is None:
        chunks = np.array([0, contacts.n], dtype=np.int64)
    sums = np.zeros((len(chunks) - 1, 2))
    kernel = _quadratic_forms_parallel if parallel else _quadratic_forms_serial
    kernel(contacts.i, contacts.j, contacts.normal, contacts.arm_i, contacts.arm_j,
           contacts.k_n, contacts.k_s, contacts.c_n, contacts.c_t,
           *_rolling_fields(contacts, rotation), bool(rotation),
           np.ascontiguousarray(x, dtype=np.float64), chunks, sums)
    total_k = 0.0
    total_c = 0.0
    for r in range(len(sums)):
        total_k += sums[r, 0]
        total_c += sums[r, 1]
    return total_k, total_c


def _contact_gram(i, j, normal, arm_i, arm_j, k_n, k_t, c_n, c_t, k_r, k_w, c_r, c_w, rolling,
                  rotation, X, chunks, k_sums, c_sums):
    """Upper triangles of X_a.K X_b and X_a.C X_b (a <= b) over the contacts of each
    run r into k_sums[r], c_sums[r] (k, k); X (k, n, nd) already scaled. With
    ``rolling`` the rolling elements are included (phi_a.B phi_b)."""
    dim = normal.shape[1]
    nd = X.shape[2]
    nv = X.shape[0]
    for r in prange(chunks.shape[0] - 1):
        d = np.empty((nv, 4))
        f = np.empty((nv, 4))
        ks = k_sums[r]
        cs = c_sums[r]
        for c in range(chunks[r], chunks[r + 1]):
            n0 = 0.0
            n1 = 0.0
            n2 = 0.0
            for a in range(nv):
                d0, d1, d2, n0, n1, n2 = _contact_slip(c, i, j, normal, arm_i, arm_j, X[a],
                                                       dim, nd, rotation)
                d[a, 0] = d0
                d[a, 1] = d1
                d[a, 2] = d2
                d[a, 3] = d0 * n0 + d1 * n1 + d2 * n2
                if rolling:
                    f0, f1, f2 = _relative_rotation(c, i, j, X[a], dim)
                    f[a, 0] = f0
                    f[a, 1] = f1
                    f[a, 2] = f2
                    f[a, 3] = f0 * n0 + f1 * n1 + f2 * n2
            kn = k_n[c]
            kt = k_t[c]
            cn = c_n[c]
            ct = c_t[c]
            for a in range(nv):
                for b in range(a, nv):
                    nn = d[a, 3] * d[b, 3]
                    tt = d[a, 0] * d[b, 0] + d[a, 1] * d[b, 1] + d[a, 2] * d[b, 2] - nn
                    ks[a, b] += kn * nn + kt * tt
                    cs[a, b] += cn * nn + ct * tt
            if rolling:
                kr = k_r[c]
                cr = c_r[c]
                kw = k_w[c] if dim == 3 else 0.0
                cw = c_w[c] if dim == 3 else 0.0
                for a in range(nv):
                    for b in range(a, nv):
                        ww = f[a, 3] * f[b, 3] if dim == 3 else 0.0
                        rr = f[a, 0] * f[b, 0] + f[a, 1] * f[b, 1] + f[a, 2] * f[b, 2] - ww
                        ks[a, b] += kr * rr + kw * ww
                        cs[a, b] += cr * rr + cw * ww


_gram_parallel, _gram_serial = compile_parallel_and_serial(_contact_gram)


def contact_gram(contacts, rotation: bool, X, chunks=None, parallel: bool = False):
    """(X K X^T, X C_d X^T) (k, k) for k DOF sets X (k, n, nd) in one pass over the
    contacts (K with ``k_n``, ``k_s``, ``k_r``, ``k_w``; C_d with ``c_n``, ``c_t``,
    ``c_r``, ``c_w``); runs summed in order."""
    if chunks is None:
        chunks = np.array([0, contacts.n], dtype=np.int64)
    nv = X.shape[0]
    k_sums = np.zeros((len(chunks) - 1, nv, nv))
    c_sums = np.zeros((len(chunks) - 1, nv, nv))
    kernel = _gram_parallel if parallel else _gram_serial
    kernel(contacts.i, contacts.j, contacts.normal, contacts.arm_i, contacts.arm_j,
           contacts.k_n, contacts.k_s, contacts.c_n, contacts.c_t,
           *_rolling_fields(contacts, rotation), bool(rotation),
           np.ascontiguousarray(X, dtype=np.float64), chunks, k_sums, c_sums)
    out = []
    for sums in (k_sums, c_sums):
        total = sums[0].copy()
        for r in range(1, len(sums)):
            total += sums[r]
        upper = np.triu(total)
        out.append(upper + np.triu(total, 1).T)
    return out[0], out[1]


# --- Lanczos vector operations (compiled: no BLAS thread pool on long vectors) -------

@njit
def _dot(v, w):
    """v . w with 4 partial sums (no reassociation needed to pipeline)."""
    n = w.shape[0]
    m = n - n % 4
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    for p in range(0, m, 4):
        s0 += v[p] * w[p]
        s1 += v[p + 1] * w[p + 1]
        s2 += v[p + 2] * w[p + 2]
        s3 += v[p + 3] * w[p + 3]
    for p in range(m, n):
        s0 += v[p] * w[p]
    return (s0 + s1) + (s2 + s3)


@njit
def _norm2(w):
    return _dot(w, w)


#: elements per block of the Lanczos vector operations below: the unit of their parallel
#: runs and of every dot product's summation order (within a block, then over the blocks
#: in order), so that a result does not depend on the number of threads
VECTOR_BLOCK = 16384
#: vectors from this length on run the Lanczos vector operations on several threads
#: (they are memory-bound: 1.5x on two threads at 6e6, measured in benchmarks/RESULTS.md)
PARALLEL_MIN_DOFS = 200_000


@njit(inline="always")
def _block_dots(V, rows, w, lo, hi, out):
    """out[a] = V[rows[a], lo:hi] . w[lo:hi]: five rows per pass over the block (w read
    once for five), each with two partial sums (even and odd elements, then added).
    Ten independent sums keep the multiply-adds in flight: with two rows per pass the
    sums' latency was the limit (the sweep alone, 10 rows of 6.1e6 on two threads: 17-22
    ms, five per pass 10-15 ms; benchmarks/RESULTS.md). The sums' order is the one of
    two rows per pass (the same bits)."""
    nr = rows.shape[0]
    m = hi - (hi - lo) % 2
    a = 0
    while a < nr:
        last = nr - 1  # (a pass short of five rows repeats the last one: the same reads)
        v0 = V[rows[a]]
        v1 = V[rows[min(a + 1, last)]]
        v2 = V[rows[min(a + 2, last)]]
        v3 = V[rows[min(a + 3, last)]]
        v4 = V[rows[min(a + 4, last)]]
        s0 = s1 = s2 = s3 = s4 = 0.0
        t0 = t1 = t2 = t3 = t4 = 0.0
        for p in range(lo, m, 2):
            e = w[p]
            o = w[p + 1]
            s0 += v0[p] * e
            t0 += v0[p + 1] * o
            s1 += v1[p] * e
            t1 += v1[p + 1] * o
            s2 += v2[p] * e
            t2 += v2[p + 1] * o
            s3 += v3[p] * e
            t3 += v3[p + 1] * o
            s4 += v4[p] * e
            t4 += v4[p + 1] * o
        for p in range(m, hi):
            e = w[p]
            s0 += v0[p] * e
            s1 += v1[p] * e
            s2 += v2[p] * e
            s3 += v3[p] * e
            s4 += v4[p] * e
        out[a] = s0 + t0
        if a + 1 < nr:
            out[a + 1] = s1 + t1
        if a + 2 < nr:
            out[a + 2] = s2 + t2
        if a + 3 < nr:
            out[a + 3] = s3 + t3
        if a + 4 < nr:
            out[a + 4] = s4 + t4
        a += 5


@njit(inline="always")
def _block_subtract(V, rows, g, w, lo, hi, factor):
    """w[lo:hi] = factor w[lo:hi] - sum_a g[a] V[rows[a], lo:hi] (two rows per pass;
    ``factor`` applied in the first; 1 leaves w's own part as it is, bit for bit);
    returns |w[lo:hi]|^2 after it, summed in the last pass (two partial sums, even and
    odd elements: one sum's latency bounded a pass of its own); ``rows`` not empty (the
    Lanczos vector's own row at least)."""
    nr = rows.shape[0]
    m = hi - (hi - lo) % 2
    a = 0
    f = factor
    while True:
        # the next one or two rows (a single row pairs with itself at coefficient 0:
        # g0 v0 + 0 v0 is g0 v0 exactly)
        v0 = V[rows[a]]
        v1 = V[rows[a + 1]] if a + 1 < nr else v0
        g0 = g[a]
        g1 = g[a + 1] if a + 1 < nr else 0.0
        a += 2
        if a < nr:
            for p in range(lo, hi):
                w[p] = f * w[p] - (g0 * v0[p] + g1 * v1[p])
            f = 1.0
            continue
        se = 0.0
        so = 0.0
        for p in range(lo, m, 2):
            e = f * w[p] - (g0 * v0[p] + g1 * v1[p])
            o = f * w[p + 1] - (g0 * v0[p + 1] + g1 * v1[p + 1])
            w[p] = e
            w[p + 1] = o
            se += e * e
            so += o * o
        for p in range(m, hi):
            e = f * w[p] - (g0 * v0[p] + g1 * v1[p])
            w[p] = e
            se += e * e
        return se + so


@njit(inline="always")
def _sum_blocks(part, count, out):
    """out[a] = sum over the blocks (in order) of part[b, a], a < ``count``."""
    for a in range(count):
        s = 0.0
        for b in range(part.shape[0]):
            s += part[b, a]
        out[a] = s


def _lanczos_orthogonalize(V, s, local, rows, w, w_scale, h, h2, semi, known):
    """Orthogonalise the new Lanczos vector u = ``w_scale`` w, in place in w, against
    the basis vectors s[r] V[r] (each row of V is stored unnormalised, with its factor
    in s: no pass over a vector to normalise it): a classical Gram-Schmidt pass against
    the rows ``local`` (h = their dots with u, u -= their combination by h), then one
    against the rows ``rows`` (h2 likewise) when it is needed; returns |u|^2 after both
    (w then holds u). The second pass' coefficients are cosines of u with unit vectors
    times |u|: when every one is at most ``semi`` |u| (u semi-orthogonal to those
    rows), the subtraction is skipped and h2[:len(rows)] is set to zero. Sweeps over
    blocks of :data:`VECTOR_BLOCK` elements: the first pass' dots; its subtraction
    (with the scaling by ``w_scale``), the second pass' dots and |u|^2 (the block is
    still in cache); when needed, the second subtraction with the norm. With ``known``
    the first pass' coefficients are given in h (the three-term recurrence's beta and
    alpha: :func:`demstep.timestep.eigen.lanczos_top`) and its dots are skipped (one
    sweep over the local rows and u fewer)."""
    n = w.shape[0]
    nb = (n + VECTOR_BLOCK - 1) // VECTOR_BLOCK
    nl = local.shape[0]
    nr = rows.shape[0]
    part = np.empty((nb, max(nl, nr + 1)))
    g = np.empty(max(nl, nr))
    if not known:
        for b in prange(nb):
            lo = b * VECTOR_BLOCK
            _block_dots(V, local, w, lo, min(n, lo + VECTOR_BLOCK), part[b])
        _sum_blocks(part, nl, h)
        for a in range(nl):
            h[a] *= w_scale * s[local[a]]
    for a in range(nl):
        g[a] = h[a] * s[local[a]]
    for b in prange(nb):
        lo = b * VECTOR_BLOCK
        hi = min(n, lo + VECTOR_BLOCK)
        part[b, nr] = _block_subtract(V, local, g, w, lo, hi, w_scale)
        _block_dots(V, rows, w, lo, hi, part[b])
    _sum_blocks(part, nr + 1, h2)
    largest = 0.0
    for a in range(nr):
        h2[a] *= s[rows[a]]
        g[a] = h2[a] * s[rows[a]]
        largest = max(largest, abs(h2[a]))
    if largest * largest <= semi * semi * h2[nr]:
        for a in range(nr):
            h2[a] = 0.0
        return h2[nr]
    for b in prange(nb):
        lo = b * VECTOR_BLOCK
        hi = min(n, lo + VECTOR_BLOCK)
        part[b, 0] = _block_subtract(V, rows, g, w, lo, hi, 1.0)
    _sum_blocks(part, 1, h2[nr:])
    return h2[nr]


_lanczos_orthogonalize_parallel, _lanczos_orthogonalize_serial = \
    compile_parallel_and_serial(_lanczos_orthogonalize)


def lanczos_orthogonalize(V, s, local, rows, w, w_scale: float, h, h2,
                          semi: float = 0.0, known: bool = False) -> float:
    """:func:`_lanczos_orthogonalize` (h2 needs one slot more than ``rows``), on
    several threads for vectors of :data:`PARALLEL_MIN_DOFS` elements or more."""
    kernel = (_lanczos_orthogonalize_parallel if w.shape[0] >= PARALLEL_MIN_DOFS
              else _lanczos_orthogonalize_serial)
    return kernel(V, s, local, rows, w, float(w_scale), h, h2, semi, bool(known))


#: elements per block of :func:`combine_rows`: its k partial sums of one block stay in
#: the core's L2 cache while the m rows stream past once
COMBINE_BLOCK = 2048


def _combine_rows_blocks(V, m, S, out):
    """out[c] = sum_{i < m} S[i, c] V[i] (out (k, n) may be V[:k]: each block of
    :data:`COMBINE_BLOCK` elements is read completely before it is written)."""
    n = V.shape[1]
    k = S.shape[1]
    nb = (n + COMBINE_BLOCK - 1) // COMBINE_BLOCK
    for b in prange(nb):
        start = b * COMBINE_BLOCK
        stop = min(start + COMBINE_BLOCK, n)
        size = stop - start
        acc = np.zeros((k, size))
        i = 0
        while i < m:  # four rows per pass over the partial sums (L2 traffic / 4)
            r = min(4, m - i)
            v0 = V[i, start:stop]
            v1 = V[i + 1 if r > 1 else i, start:stop]
            v2 = V[i + 2 if r > 2 else i, start:stop]
            v3 = V[i + 3 if r > 3 else i, start:stop]
            for c in range(k):
                a = acc[c]
                s0 = S[i, c]
                s1 = S[i + 1, c] if r > 1 else 0.0
                s2 = S[i + 2, c] if r > 2 else 0.0
                s3 = S[i + 3, c] if r > 3 else 0.0
                for p in range(size):
                    a[p] += (s0 * v0[p] + s1 * v1[p]) + (s2 * v2[p] + s3 * v3[p])
            i += r
        for c in range(k):
            o = out[c, start:stop]
            a = acc[c]
            for p in range(size):
                o[p] = a[p]


_combine_rows_parallel, _combine_rows_serial = compile_parallel_and_serial(_combine_rows_blocks)


def combine_rows(V, m, S, out):
    """out[c] = sum_{i < m} S[i, c] V[i] for the columns c of S (m, k); ``out`` (k, n)
    may be V[:k] itself (a thick restart); threaded like :func:`lanczos_orthogonalize`."""
    kernel = _combine_rows_parallel if V.shape[1] >= PARALLEL_MIN_DOFS else _combine_rows_serial
    kernel(V, m, np.ascontiguousarray(S), out)


@njit
def scale_into(w, factor, out):
    """out = factor w (serial: on two threads it was slower, 1.4 vs 1.1 ms at 1.5e6)."""
    for p in range(w.shape[0]):
        out[p] = w[p] * factor


@njit
def lanczos_recurrence(v, w, v_prev, beta_prev):
    """One step of plain Lanczos on w = A v, in place: alpha = v.w, then
    w <- w - alpha v - beta_prev v_prev; returns (alpha, |w|^2). Two passes over the
    vectors and no temporaries (the random-start check of
    :mod:`demstep.timestep.guarantee`)."""
    alpha = _dot(v, w)
    n = w.shape[0]
    s0 = 0.0
    s1 = 0.0
    m = n - n % 2
    for p in range(0, m, 2):
        t0 = w[p] - alpha * v[p] - beta_prev * v_prev[p]
        t1 = w[p + 1] - alpha * v[p + 1] - beta_prev * v_prev[p + 1]
        w[p] = t0
        w[p + 1] = t1
        s0 += t0 * t0
        s1 += t1 * t1
    for p in range(m, n):
        t0 = w[p] - alpha * v[p] - beta_prev * v_prev[p]
        w[p] = t0
        s0 += t0 * t0
    return alpha, s0 + s1


@njit
def _rayleigh_residual(y, Ay):
    """(theta, |Ay - theta y|) for a unit vector y."""
    theta = _dot(y, Ay)
    n = y.shape[0]
    r0 = 0.0
    r1 = 0.0
    m = n - n % 2
    for p in range(0, m, 2):
        t0 = Ay[p] - theta * y[p]
        t1 = Ay[p + 1] - theta * y[p + 1]
        r0 += t0 * t0
        r1 += t1 * t1
    for p in range(m, n):
        t0 = Ay[p] - theta * y[p]
        r0 += t0 * t0
    return theta, np.sqrt(r0 + r1)


# --- the coupled element with rolling resistance -------------------------------------

@njit
def symmetric2_top(p, q, r):
    """Largest eigenvalue of the symmetric 2 x 2 matrix [[p, b], [b, q]] with b^2 = ``r``
    (scalars or arrays): (p + q)/2 + sqrt(((p - q)/2)^2 + r)."""
    h = 0.5 * (p - q)
    return 0.5 * (p + q) + np.sqrt(h * h + r)


@njit(inline="always")
def _tangential_rolling_h(s, k_t, g_t, k_r, g_r, w_t, c_th, e2, a1):
    """h(s) = s^2 - a1 s - lambda(s) and h'(s), lambda(s) the largest eigenvalue of the
    tangential-rolling block X^1/2 W X^1/2, X = diag(k_t + s g_t, k_r + s g_r),
    W = [[w_t, e], [e, c_th]] (:func:`tangential_rolling_dt`)."""
    x_t = k_t + s * g_t
    x_r = k_r + s * g_r
    p = x_t * w_t
    q = x_r * c_th
    r = e2 * x_t * x_r
    half = 0.5 * (p - q)
    root = np.sqrt(half * half + r)
    lam = 0.5 * (p + q) + root
    dp = g_t * w_t
    dq = g_r * c_th
    dr = e2 * (g_t * x_r + x_t * g_r)
    if root > 0.0:
        dlam = 0.5 * (dp + dq) + (half * 0.5 * (dp - dq) + 0.5 * dr) / root
    else:
        dlam = 0.5 * (dp + dq) + 0.5 * abs(dp - dq)
    return s * s - a1 * s - lam, 2.0 * s - a1 - dlam


@njit
def _tangential_rolling_sigma(k_t, g_t, k_r, g_r, w_t, c_th, e2, a1):
    """Upper bound on the largest root sigma of h(sigma) = 0 (see
    :func:`_tangential_rolling_h`): h < 0 below that root and >= 0 above it, for
    sigma > 0 (the Rayleigh functional of a quadratic pencil with PSD K and C). Newton's
    method from Weyl's upper bound damped_sigma(lambda(0), a1 + lambda_max(G^1/2 W
    G^1/2)), kept inside the bracket (bisection otherwise); returns the smallest point
    where h >= 0 was found (Weyl's bound if none)."""
    lam_k = symmetric2_top(k_t * w_t, k_r * c_th, e2 * k_t * k_r)
    if g_t == 0.0 and g_r == 0.0:
        return 0.5 * (a1 + np.sqrt(a1 * a1 + 4.0 * lam_k))
    lam_c = symmetric2_top(g_t * w_t, g_r * c_th, e2 * g_t * g_r)
    c = a1 + lam_c
    hi = 0.5 * (c + np.sqrt(c * c + 4.0 * lam_k))
    lo = 0.0
    s = hi
    for _ in range(100):
        h, dh = _tangential_rolling_h(s, k_t, g_t, k_r, g_r, w_t, c_th, e2, a1)
        if h >= 0.0:
            hi = min(hi, s)
        else:
            lo = max(lo, s)
        if hi - lo <= 4e-16 * hi:
            break
        new = s - h / dh if dh > 0.0 else 0.5 * (lo + hi)
        if not (lo < new < hi):
            new = 0.5 * (lo + hi)
        if abs(new - s) <= 1e-15 * s and h >= 0.0:
            break
        s = new
    return hi


@njit
def _tangential_rolling_dt(k_t, g_t, k_r, g_r, w_t, c_th, e2, a1, out):
    for c in range(k_t.shape[0]):
        sigma = _tangential_rolling_sigma(k_t[c], g_t[c], k_r[c], g_r[c], w_t[c], c_th[c],
                                          e2[c], a1)
        out[c] = 2.0 / sigma if sigma > 0.0 else np.inf


def tangential_rolling_dt(k_t, g_t, k_r, g_r, w_t, c_th, e2, a1: float) -> np.ndarray:
    """Critical step (C,) [T] of the tangential-rolling block of coupled elements: the
    largest root sigma of det((sigma^2 - a1 sigma) I - W (D + sigma G)) = 0 with
    D = diag(k_t, k_r), G = diag(g_t, g_r) (springs and damping of the tangential slip
    [M/T^2, M/T] and of the rolling rotation [M L^2/T^2, M L^2/T]) and
    W = [[w_t, e], [e, c_th]] (``e2`` = e^2) the element's B M_e^-1 B^T on that pair of
    strains; dt = 2 / sigma (an upper bound on sigma: dt never above the block's)."""
    arrays = [np.ascontiguousarray(np.broadcast_to(np.asarray(v, dtype=np.float64),
                                                   np.shape(k_t)))
              for v in (k_t, g_t, k_r, g_r, w_t, c_th, e2)]
    out = np.empty(arrays[0].shape[0])
    _tangential_rolling_dt(*arrays, float(a1), out)
    return out


# --- per-contact rolling coefficients -------------------------------------------------

@njit
def _rolling_coefficient_arrays(params, k_n, k_t, r_star, i_star, k_r, k_w, c_r, c_w):
    for c in range(k_n.shape[0]):
        k_r[c], k_w[c], c_r[c], c_w[c] = rolling_coefficients(params, k_n[c], k_t[c],
                                                              r_star[c], i_star[c])


def rolling_coefficient_arrays(params, k_n, k_t, r_star, i_star):
    """Rolling and twisting springs k_r, k_w [M L^2/T^2 per rad] and viscous coefficients
    c_r, c_w [M L^2/T] (C,) each of contacts with tangent stiffnesses ``k_n``, ``k_t``
    [M/T^2], effective radii ``r_star`` [L] and equivalent rotational inertias
    ``i_star`` [M L^2], by the law's formula
    (:func:`demstep.contact.laws.rolling_coefficients`, ``params`` a law's Params tuple)."""
    arrays = [np.ascontiguousarray(v, dtype=np.float64) for v in (k_n, k_t, r_star, i_star)]
    out = [np.zeros(arrays[0].shape[0]) for _ in range(4)]
    _rolling_coefficient_arrays(params, *arrays, *out)
    return tuple(out)
