"""Rolling and twisting resistance of one contact (the laws' module docstring; Ai et
al. 2011 type C): the response and its history update, shared by the pair and wall
loops (:mod:`demstep.kernels.dem`) and the mesh contacts (:mod:`demstep.kernels.meshes`).
"""

from __future__ import annotations

import math

from demstep._numba import njit
from demstep.contact.geometry import into_tangent_plane
from demstep.contact.laws import coulomb_load, normal_force, rolling_coefficients, tangential_stiffness

#: columns of the rolling-resistance history (Pairs.roll, Walls.roll, Meshes.roll;
#: state.ROLL_WIDTH of them): rolling spring moment on j (3), twisting spring moment on
#: j along n, viscous moment on j (3), stored rolling and twisting energy
ROLL_M, ROLL_TWIST, ROLL_VISCOUS, ROLL_ENERGY = 0, 3, 4, 7


@njit(inline="always")
def rolling_response(params, nx, ny, nz, delta, r_star, i_star, k_n, k_t, f_el, wx, wy, wz,
                     dt, mrx, mry, mrz, mw, mdx, mdy, mdz, e_old):
    """Rolling and twisting resistance of one contact (laws module docstring; Ai et al.
    2011 type C) and its history update. Inputs: unit normal n (i -> j), overlap
    ``delta`` [L], effective radius [L] and rotational inertia ``i_star`` [M L^2],
    tangent stiffnesses k_n, k_t [M/T^2] and elastic normal force ``f_el`` [M L/T^2] of
    the contact, relative angular velocity of j w.r.t. i (w_x, w_y, w_z) [1/T] at
    t - dt/2, ``dt``, and the history: rolling spring moment on j (m_r), twisting moment
    along n (m_w), viscous moment on j (m_d), stored energy. Returns the moment on j
    (3), the stored energy, the plastic and viscous dissipation of the step, then the
    new history (rolling moment 3, twisting, viscous 3, energy)."""
    dpx, dpy, dpz = wx * dt, wy * dt, wz * dt
    dpn = dpx * nx + dpy * ny + dpz * nz
    drx, dry, drz = dpx - dpn * nx, dpy - dpn * ny, dpz - dpn * nz
    # the old rolling moment, rotated into the current tangent plane (magnitude kept);
    # the twisting moment is a component along n
    mrx, mry, mrz = into_tangent_plane(mrx, mry, mrz, nx, ny, nz)
    d_visc_old = -0.5 * (mdx * dpx + mdy * dpy + mdz * dpz)
    if delta <= 0.0:
        # separated: the stored energy is released (dissipated)
        d_plastic = -0.5 * (mrx * drx + mry * dry + mrz * drz + mw * dpn) + e_old
        return (0.0, 0.0, 0.0, 0.0, d_plastic, d_visc_old,
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    k_r, k_w, c_r, c_w = rolling_coefficients(params, k_n, k_t, r_star, i_star)
    # rolling: trial increment, then the limit mu_r R* F_n (mu_r = 0: no limit)
    tx, ty, tz = mrx - k_r * drx, mry - k_r * dry, mrz - k_r * drz
    vx, vy, vz = 0.0, 0.0, 0.0
    limit = params.mu_r * r_star * max(f_el, 0.0)
    mag = math.sqrt(tx * tx + ty * ty + tz * tz)
    if params.mu_r > 0.0 and mag > limit:
        s = limit / mag
        tx, ty, tz = tx * s, ty * s, tz * s
    else:
        wn = wx * nx + wy * ny + wz * nz
        vx, vy, vz = -c_r * (wx - wn * nx), -c_r * (wy - wn * ny), -c_r * (wz - wn * nz)
    # twisting, along n
    tw = mw - k_w * dpn
    limit_w = params.mu_w * r_star * max(f_el, 0.0)
    if params.mu_w > 0.0 and abs(tw) > limit_w:
        tw = limit_w if tw > 0.0 else -limit_w
    else:
        vw = -c_w * (wx * nx + wy * ny + wz * nz)
        vx, vy, vz = vx + vw * nx, vy + vw * ny, vz + vw * nz
    e_new = 0.0
    if k_r > 0.0:
        e_new += (tx * tx + ty * ty + tz * tz) / (2.0 * k_r)
    if k_w > 0.0:
        e_new += tw * tw / (2.0 * k_w)
    w_in = -0.5 * ((mrx + tx) * drx + (mry + ty) * dry + (mrz + tz) * drz + (mw + tw) * dpn)
    d_plastic = w_in - (e_new - e_old)
    d_visc = d_visc_old - 0.5 * (vx * dpx + vy * dpy + vz * dpz)
    return (tx + tw * nx + vx, ty + tw * ny + vy, tz + tw * nz + vz, e_new, d_plastic, d_visc,
            tx, ty, tz, tw, vx, vy, vz, e_new)


@njit(inline="always")
def rolling_inertia_pair(inertia_i, m_i, r_i, inertia_j, m_j, r_j):
    """1 / (1/(I_i + m_i r_i^2) + 1/(I_j + m_j r_j^2)) [M L^2]; a side with zero
    inertia and mass (a wall: pass zeros) adds nothing."""
    inv = 0.0
    a = inertia_i + m_i * r_i * r_i
    if a > 0.0:
        inv += 1.0 / a
    b = inertia_j + m_j * r_j * r_j
    if b > 0.0:
        inv += 1.0 / b
    return 1.0 / inv if inv > 0.0 else 0.0


@njit(inline="always")
def rolling_contact(params, h, nx, ny, nz, delta, r_star, inertia_i, m_i, r_i,
                     inertia_j, m_j, r_j, wx, wy, wz, dt):
    """:func:`rolling_response` of one contact whose history row is ``h``
    (ROLL_WIDTH values, updated in place): the law's normal force and tangent
    stiffnesses at ``delta``, the equivalent inertia of the two sides (a side of zero
    inertia and mass adds nothing), then the response. Returns (touched, moment on j (3),
    stored energy, plastic and viscous dissipation); touched False (and zeros) for a
    contact apart and without history."""
    if delta <= 0.0 and h[ROLL_ENERGY] == 0.0 and h[0] == 0.0 and h[1] == 0.0 \
            and h[2] == 0.0 and h[3] == 0.0 and h[4] == 0.0 and h[5] == 0.0 and h[6] == 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    i_star = rolling_inertia_pair(inertia_i, m_i, r_i, inertia_j, m_j, r_j)
    k_n = 0.0
    k_t = 0.0
    f_el = 0.0
    if delta > 0.0:
        f_el, k_n, _ = normal_force(params, delta, r_star)
        f_el = coulomb_load(params, f_el)  # (the load the moment limits scale with)
        k_t = tangential_stiffness(params, delta, r_star)
    (mx, my, mz, e_new, c_p, c_v, h0, h1, h2, h3, h4, h5, h6, h7) = rolling_response(
        params, nx, ny, nz, delta, r_star, i_star, k_n, k_t, f_el, wx, wy, wz, dt,
        h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7])
    h[0] = h0
    h[1] = h1
    h[2] = h2
    h[3] = h3
    h[4] = h4
    h[5] = h5
    h[6] = h6
    h[7] = h7
    return True, mx, my, mz, e_new, c_p, c_v
