"""What the sphere and the body integrators share: the motion of a sphere since the
lists were built, and the layout of the terms they hand to the ledger."""

import math

from demstep._numba import njit


@njit(inline="always")
def moved_since_build(x, v, x_ref, r, p, dt):
    """(squared displacement of sphere p since the lists were built, its |v| dt / r)."""
    d2 = 0.0
    vv = 0.0
    for k in range(3):
        dd = x[p, k] - x_ref[p, k]
        d2 += dd * dd
        vv += v[p, k] * v[p, k]
    return d2, math.sqrt(vv) * dt / r[p]


@njit(inline="always")
def store_step_terms(out, w_body, w_app, d_local, d_global, ke_t, ke_r, disp2, jump):
    """``out`` (8,): work of gravity, of applied forces, local and global damping
    dissipation, kinetic energy of translation and rotation at t, the largest squared
    displacement since the lists were built, the largest |v| dt / r."""
    out[0] = w_body
    out[1] = w_app
    out[2] = d_local
    out[3] = d_global
    out[4] = ke_t
    out[5] = ke_r
    out[6] = disp2
    out[7] = jump
