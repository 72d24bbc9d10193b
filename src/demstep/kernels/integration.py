"""What the sphere and the body integrators share: the motion of a sphere since the
lists were built, and the layout of the terms they hand to the ledger."""

import math

from numba import uint64 as _U

from demstep._numba import njit, prange


@njit(inline="always")
def moved_since_build(x_flat, v_flat, x_ref_flat, r, p):
    """(squared displacement of sphere p since the lists were built, its (|v| / r)^2
    [1/T^2]; :func:`store_step_terms` turns the largest into |v| dt / r), from flat
    views of the (N, 3) positions, velocities and positions at the last build."""
    d2 = 0.0
    vv = 0.0
    b = _U(3) * _U(p)
    for k in range(3):
        q = b + _U(k)
        dd = x_flat[q] - x_ref_flat[q]
        d2 += dd * dd
        vv += v_flat[q] * v_flat[q]
    return d2, vv / (r[p] * r[p])


@njit(inline="always")
def step_weights(dt, dt_prev, first):
    """(kick [T], c_old, c_new) of the central-difference step from t to t + dt after a
    step ``dt_prev`` [T]: the half-step velocities are (dt_prev + dt) / 2 apart,

        v(t + dt/2) = v(t - dt_prev/2) + kick a(t),      kick = (dt_prev + dt) / 2,

    and twice the velocity at t is c_old v(t - dt_prev/2) + c_new v(t + dt/2) with
    c_old = 2 dt / (dt_prev + dt), c_new = 2 dt_prev / (dt_prev + dt) (exact for a
    constant acceleration). For a constant step: (dt, 1, 1) exactly; the ``first`` step
    starts from v(-dt/2), as after a step dt. A kick of dt after a change of step gave
    every accelerated particle a lasting velocity error of a (dt - dt_prev) / 2."""
    if first:
        return dt, 1.0, 1.0
    span = dt_prev + dt
    return 0.5 * span, 2.0 * dt / span, 2.0 * dt_prev / span


@njit(inline="always")
def store_step_terms(out, w_body, w_app, d_local, d_global, ke_t, ke_r, disp2, jump2, dt):
    """``out`` (8,): work of gravity, of applied forces, local and global damping
    dissipation, kinetic energy of translation and rotation at t, the largest squared
    displacement since the lists were built, the largest |v| dt / r (from the largest
    (|v| / r)^2 ``jump2``: one root per step, not per sphere)."""
    out[0] = w_body
    out[1] = w_app
    out[2] = d_local
    out[3] = d_global
    out[4] = ke_t
    out[5] = ke_r
    out[6] = disp2
    out[7] = math.sqrt(jump2) * dt


@njit
def reach_speed(v, force, applied, inv_m, gravity, horizon, out):
    """out[p] = |v_p| + h |a_p| [L/T] with a_p = (F_p + F_app,p) / m_p + g (zero for a
    fixed particle, inv_m 0): the speed a particle can reach within the horizon h [T]
    (the 'auto' step's reach, :meth:`demstep.engine.Simulation.contact_set`)."""
    for p in range(v.shape[0]):
        im = inv_m[p]
        vv = 0.0
        aa = 0.0
        for k in range(3):
            vv += v[p, k] * v[p, k]
            a = (force[p, k] + applied[p, k]) * im + (gravity[k] if im > 0.0 else 0.0)
            aa += a * a
        out[p] = math.sqrt(vv) + horizon * math.sqrt(aa)


@njit(parallel=True)
def copy_positions(x, out):
    """out[:] = x for (N, 3) positions, on numba's threads (the positions at a rebuild of
    the lists: numpy copied them on one thread, 0.1-0.15 ms at 1e5 particles)."""
    for p in prange(x.shape[0]):
        for k in range(3):
            out[p, k] = x[p, k]
