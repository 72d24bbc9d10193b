"""The contact law applied to one contact: the force and the history update, written once
and shared by the pair, wall and mesh loops (scalars in, scalars out: inlined in the
compiled loops, and the pair loop's law pass vectorised by the compiler)."""

from __future__ import annotations

import math

from demstep._numba import njit
from demstep.contact.geometry import into_tangent_plane
from demstep.contact.laws import (coulomb_load, dashpot_coefficients, normal_force,
                                  tangential_stiffness)


@njit(inline="always")
def coulomb_dashpot(tx, ty, tz, dx, dy, dz, limit):
    """The tangential dashpot force (d_x, d_y, d_z) of a sticking contact, scaled down
    (by the largest alpha in [0, 1]) so that the total tangential force, spring t plus
    dashpot, stays within the Coulomb limit mu F_n [M L/T^2] (|t| <= limit here).
    LIGGGHTS adds the dashpot unchecked, which let the total reach several times mu F_n
    when a contact starts or turns; LAMMPS' granular pair styles cap the total too."""
    sx, sy, sz = tx + dx, ty + dy, tz + dz
    limit2 = limit * limit
    if sx * sx + sy * sy + sz * sz <= limit2:
        return dx, dy, dz
    a = dx * dx + dy * dy + dz * dz
    b = tx * dx + ty * dy + tz * dz
    c = tx * tx + ty * ty + tz * tz - limit2  # <= 0: the root lies in [0, 1)
    alpha = (math.sqrt(max(b * b - a * c, 0.0)) - b) / a
    return alpha * dx, alpha * dy, alpha * dz


@njit(inline="always")
def contact_response(params, mu, nx, ny, nz, delta, r_star, m_star, vx, vy, vz, dt,
                     ox, oy, oz, fdx, fdy, fdz, etan_old):
    """Force of one contact and its history update (the contact law applied once).

    Inputs: unit normal n (i -> j), overlap ``delta`` [L] (<= 0: not touching),
    effective radius and mass, relative velocity of j's contact point w.r.t. i's
    (v_x, v_y, v_z) [L/T] at t - dt/2, step ``dt`` (the one that produced x(t)), and
    the history: tangential spring force on j (o_x, o_y, o_z), dashpot force on j
    (fd_x, fd_y, fd_z) and stored tangential energy. Returns (F_x, F_y, F_z) on j, the
    normal and tangential strain energies, the friction and dashpot dissipation of the
    step, k_n and k_t (tangent stiffnesses, 0 when not touching), then the new history
    (tangential force, dashpot force, tangential energy).

    Scalars only: array arguments cost a reference-count update per call, which
    measured 60 % of the pair loop.
    """
    dux, duy, duz = vx * dt, vy * dt, vz * dt
    dun = dux * nx + duy * ny + duz * nz
    dtx, dty, dtz = dux - dun * nx, duy - dun * ny, duz - dun * nz
    # the old tangential force, rotated into the current tangent plane (magnitude kept)
    ox, oy, oz = into_tangent_plane(ox, oy, oz, nx, ny, nz)
    if delta <= 0.0:
        # separated: the stored tangential energy is released (dissipated)
        d_fric = -0.5 * (ox * dtx + oy * dty + oz * dtz) + etan_old
        d_dash = -0.5 * (fdx * dux + fdy * duy + fdz * duz)
        return (0.0, 0.0, 0.0, 0.0, 0.0, d_fric, d_dash, 0.0, 0.0,
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    f_el, k_n, e_n = normal_force(params, delta, r_star)
    k_t = tangential_stiffness(params, delta, r_star)
    c_n, c_t = dashpot_coefficients(params, m_star, k_n, k_t)
    # normal dashpot on the lagged normal velocity (not clipped: the total may pull
    # briefly at the end of an impact, as in the model whose restitution is e)
    v_n = vx * nx + vy * ny + vz * nz
    f_nd = -c_n * v_n
    # tangential spring: trial increment, then the Coulomb slider
    tx, ty, tz = ox - k_t * dtx, oy - k_t * dty, oz - k_t * dtz
    mag2 = tx * tx + ty * ty + tz * tz
    limit = mu * coulomb_load(params, f_el)
    tdx, tdy, tdz = 0.0, 0.0, 0.0
    if mag2 > limit * limit:  # (squares: the root only for a sliding contact)
        s = limit / math.sqrt(mag2)
        tx, ty, tz = tx * s, ty * s, tz * s
    elif c_t > 0.0:
        vtx, vty, vtz = vx - v_n * nx, vy - v_n * ny, vz - v_n * nz
        tdx, tdy, tdz = coulomb_dashpot(tx, ty, tz, -c_t * vtx, -c_t * vty, -c_t * vtz,
                                        limit)
    e_t = 0.0
    if k_t > 0.0:
        e_t = (tx * tx + ty * ty + tz * tz) / (2.0 * k_t)
    # work done on the tangential spring over the step (trapezoid) minus its stored change
    w_in = -0.5 * ((ox + tx) * dtx + (oy + ty) * dty + (oz + tz) * dtz)
    ndx, ndy, ndz = f_nd * nx + tdx, f_nd * ny + tdy, f_nd * nz + tdz
    d_fric = w_in - (e_t - etan_old)
    d_dash = -0.5 * ((fdx + ndx) * dux + (fdy + ndy) * duy + (fdz + ndz) * duz)
    f_total = f_el + f_nd
    return (f_total * nx + tx + tdx, f_total * ny + ty + tdy, f_total * nz + tz + tdz,
            e_n, e_t, d_fric, d_dash, k_n, k_t, tx, ty, tz, ndx, ndy, ndz, e_t)
