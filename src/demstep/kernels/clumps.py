"""Rigid bodies of member spheres (clumps): the forces summed to the bodies, their
central-difference update, and the members moved with them.

Translation is the same leapfrog as for spheres. Rotation uses the angular momentum
L (world frame) at half steps and the orientation quaternion q at whole steps:

    L(t + dt/2) = L(t - dt/2) + dt T(t)
    q(t + dt)   = the free rotation of the body over dt with angular momentum
                  L(t + dt/2), by the symmetric splitting of the free rigid-body
                  Hamiltonian into rotations about the principal axes,
                  x(dt/2) y(dt/2) z(dt) y(dt/2) x(dt/2)

(Dullweber, Leimkuhler & McLachlan 1997, J. Chem. Phys. 107:5840, the NO_SQUISH
family): second order, time reversible, L conserved exactly without torque and the
kinetic energy to O(dt^2) over long times. The principal moments may all differ (the
plain central difference applies only to spheres, as the paper notes). Linearised about
a state at rest it is the central difference with the world inertia tensor as mass
matrix, which is what the critical-step analysis of clumps uses.

Damping on bodies, as on spheres, uses the lagged half-step values: local damping on
each component of the force and torque, global viscous damping -a1 m v and -a1 L (the
torque -a1 I omega of the world inertia tensor).

Members follow their body: x_m = x_b + R d_m (R from q, d_m the member's offset in the
principal frame); a member's half-step velocity is its displacement over the step
divided by dt (so contact slips telescope exactly) and its angular velocity the
rotation vector of q(t + dt) q(t)^-1 divided by dt.
"""

from __future__ import annotations

import math

import numpy as np

from demstep._numba import compile_parallel_and_serial, njit, prange
from demstep.kernels.integration import moved_since_build, step_weights, store_step_terms


@njit(inline="always")
def quat_mul(a0, a1, a2, a3, b0, b1, b2, b3):
    """The quaternion product a b (w, x, y, z)."""
    return (a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3,
            a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
            a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1,
            a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0)


@njit(inline="always")
def quat_rotate(q0, q1, q2, q3, x, y, z):
    """R(q) (x, y, z) for a unit quaternion q."""
    # t = 2 q_vec x v; v' = v + q0 t + q_vec x t
    tx = 2.0 * (q2 * z - q3 * y)
    ty = 2.0 * (q3 * x - q1 * z)
    tz = 2.0 * (q1 * y - q2 * x)
    return (x + q0 * tx + (q2 * tz - q3 * ty),
            y + q0 * ty + (q3 * tx - q1 * tz),
            z + q0 * tz + (q1 * ty - q2 * tx))


@njit(inline="always")
def _axis_step(q0, q1, q2, q3, l0, l1, l2, axis, angle):
    """Rotate the body about its principal ``axis`` by ``angle``: q <- q q_axis(angle),
    body-frame angular momentum l <- R_axis(angle)^T l."""
    c = math.cos(0.5 * angle)
    s = math.sin(0.5 * angle)
    ca = math.cos(angle)
    sa = math.sin(angle)
    if axis == 0:
        q0, q1, q2, q3 = quat_mul(q0, q1, q2, q3, c, s, 0.0, 0.0)
        l1, l2 = ca * l1 + sa * l2, -sa * l1 + ca * l2
    elif axis == 1:
        q0, q1, q2, q3 = quat_mul(q0, q1, q2, q3, c, 0.0, s, 0.0)
        l0, l2 = ca * l0 - sa * l2, sa * l0 + ca * l2
    else:
        q0, q1, q2, q3 = quat_mul(q0, q1, q2, q3, c, 0.0, 0.0, s)
        l0, l1 = ca * l0 + sa * l1, -sa * l0 + ca * l1
    return q0, q1, q2, q3, l0, l1, l2


@njit(inline="always")
def free_rotation(q0, q1, q2, q3, L0, L1, L2, i0, i1, i2, dt):
    """Orientation after a free rotation over ``dt`` with world angular momentum L and
    reciprocal principal moments (i0, i1, i2) (the splitting of the module docstring);
    the result is renormalised."""
    # body-frame angular momentum l = R^T L
    l0, l1, l2 = quat_rotate(q0, -q1, -q2, -q3, L0, L1, L2)
    h = 0.5 * dt
    q0, q1, q2, q3, l0, l1, l2 = _axis_step(q0, q1, q2, q3, l0, l1, l2, 0, h * l0 * i0)
    q0, q1, q2, q3, l0, l1, l2 = _axis_step(q0, q1, q2, q3, l0, l1, l2, 1, h * l1 * i1)
    q0, q1, q2, q3, l0, l1, l2 = _axis_step(q0, q1, q2, q3, l0, l1, l2, 2, dt * l2 * i2)
    q0, q1, q2, q3, l0, l1, l2 = _axis_step(q0, q1, q2, q3, l0, l1, l2, 1, h * l1 * i1)
    q0, q1, q2, q3, l0, l1, l2 = _axis_step(q0, q1, q2, q3, l0, l1, l2, 0, h * l0 * i0)
    norm = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    return q0 / norm, q1 / norm, q2 / norm, q3 / norm


@njit(inline="always")
def world_omega(q0, q1, q2, q3, L0, L1, L2, i0, i1, i2):
    """omega = R I^-1 R^T L [1/T] (world frame)."""
    l0, l1, l2 = quat_rotate(q0, -q1, -q2, -q3, L0, L1, L2)
    return quat_rotate(q0, q1, q2, q3, l0 * i0, l1 * i1, l2 * i2)


@njit
def _kick(b, k, f, t, omega, m, inv_m, rotating, gravity, v, L, x, applied, damp_force,
          damp_torque, dt, dt_prev, kick, c_old, c_new, local_damping, global_damping, first,
          store_damping):
    """Component k of body b: the leapfrog kick of the velocity and the angular
    momentum with gravity, applied force and damping (by ``kick``, the mean of the last
    and the new step, weights ``c_old``, ``c_new`` of the velocity at t:
    :func:`~demstep.kernels.integration.step_weights`), the drift of the centre;
    returns the lagged angular momentum and the ledger terms (gravity work, applied
    work, local and global damping dissipation, kinetic energy of translation at t)."""
    g = gravity[k]
    fl = f + m * g + applied[b, k]
    v_old = v[b, k]
    L_old = L[b, k]
    if first:
        v_old -= 0.5 * dt * fl * inv_m[b]
        L_old -= 0.5 * dt * t
    fdk = 0.0
    tdk = 0.0
    if local_damping > 0.0:
        fdk = -local_damping * abs(fl) * np.sign(v_old)
        tdk = -local_damping * abs(t) * np.sign(omega)
    gdk = 0.0
    gtk = 0.0
    if global_damping > 0.0:
        gdk = -global_damping * m * v_old
        gtk = -global_damping * L_old
    v_new = v_old + kick * (fl + fdk + gdk) * inv_m[b]
    L_new = L_old + kick * (t + tdk + gtk) if rotating else 0.0
    w_body = 0.0
    w_app = 0.0
    d_local = 0.0
    d_global = 0.0
    if not first:
        dx = dt_prev * v_old
        w_body = m * g * dx
        w_app = applied[b, k] * dx
        if store_damping:
            dth = dt_prev * omega
            d_local = -0.5 * ((damp_force[b, k] + fdk) * dx + (damp_torque[b, k] + tdk) * dth)
            d_global = -0.5 * ((damp_force[b, 3 + k] + gdk) * dx
                               + (damp_torque[b, 3 + k] + gtk) * dth)
    if store_damping:
        damp_force[b, k] = fdk
        damp_torque[b, k] = tdk
        damp_force[b, 3 + k] = gdk
        damp_torque[b, 3 + k] = gtk
    vm = 0.5 * (c_old * v_old + c_new * v_new)
    v[b, k] = v_new
    L[b, k] = L_new
    x[b, k] += dt * v_new
    return L_old, w_body, w_app, d_local, d_global, 0.5 * m * vm * vm


def _body_loop(bodies, sph, ctl, dt, dt_prev, first, out):
    """Sum the member forces to each body, update the bodies (module docstring) and move
    their members; ledger terms as :func:`demstep.kernels.dem._integrate_loop` fills
    them (``out`` (8,): work of gravity, of applied forces, local and global damping
    dissipation, kinetic energy of translation and rotation at t, the largest squared
    member displacement since the lists were built, the largest member |v| dt / r).
    ``bodies``, ``sph``: the Bodies and Spheres bundles (:mod:`demstep.state`); ``ctl``
    the Controls (gravity, damping); the step ``dt``, the previous one ``dt_prev`` [T],
    ``first`` (initialise the half step)."""
    bx, bq, bv, bL, bm = bodies.x, bodies.q, bodies.v, bodies.L, bodies.m
    binertia, binv_m, binv_I = bodies.inertia, bodies.inv_m, bodies.inv_I
    bforce, btorque, bapplied = bodies.force, bodies.torque, bodies.applied
    start, member, offset = bodies.start, bodies.member, bodies.offset
    damp_force, damp_torque = bodies.damp_force, bodies.damp_torque
    x, v, w, r, force, torque, x_ref = sph.x, sph.v, sph.w, sph.r, sph.force, sph.torque, sph.x_ref
    gravity, store_damping = ctl.gravity, ctl.store_damping
    local_damping, global_damping = ctl.local_damping, ctl.viscous_damping
    w_body = 0.0
    w_app = 0.0
    d_local = 0.0
    d_global = 0.0
    ke_t = 0.0
    ke_r = 0.0
    disp2 = 0.0
    jump2 = 0.0
    x_flat, v_flat, x_ref_flat = x.reshape(-1), v.reshape(-1), x_ref.reshape(-1)
    kick, c_old, c_new = step_weights(dt, dt_prev, first)
    for b in prange(bm.shape[0]):
        q0, q1, q2, q3 = bq[b, 0], bq[b, 1], bq[b, 2], bq[b, 3]
        # 1. forces and torques about the centre of mass
        f0 = 0.0
        f1 = 0.0
        f2 = 0.0
        t0 = 0.0
        t1 = 0.0
        t2 = 0.0
        for k in range(start[b], start[b + 1]):
            p = member[k]
            a0, a1, a2 = quat_rotate(q0, q1, q2, q3, offset[k, 0], offset[k, 1], offset[k, 2])
            f0 += force[p, 0]
            f1 += force[p, 1]
            f2 += force[p, 2]
            t0 += torque[p, 0] + a1 * force[p, 2] - a2 * force[p, 1]
            t1 += torque[p, 1] + a2 * force[p, 0] - a0 * force[p, 2]
            t2 += torque[p, 2] + a0 * force[p, 1] - a1 * force[p, 0]
        bforce[b, 0] = f0
        bforce[b, 1] = f1
        bforce[b, 2] = f2
        btorque[b, 0] = t0
        btorque[b, 1] = t1
        btorque[b, 2] = t2
        m = bm[b]
        i0, i1, i2 = binv_I[b, 0], binv_I[b, 1], binv_I[b, 2]
        # 2. translation and angular momentum (leapfrog, damping on the lagged values)
        xo0, xo1, xo2 = bx[b, 0], bx[b, 1], bx[b, 2]
        rotating = binv_I[b, 0] > 0.0
        om0, om1, om2 = 0.0, 0.0, 0.0
        if rotating:
            om0, om1, om2 = world_omega(q0, q1, q2, q3, bL[b, 0], bL[b, 1], bL[b, 2], i0, i1, i2)
        lo0, wb0, wa0, dl0, dg0, ke0 = _kick(b, 0, f0, t0, om0, m, binv_m, rotating, gravity, bv, bL, bx, bapplied,
                        damp_force, damp_torque, dt, dt_prev, kick, c_old, c_new,
                        local_damping, global_damping, first, store_damping)
        lo1, wb1, wa1, dl1, dg1, ke1 = _kick(b, 1, f1, t1, om1, m, binv_m, rotating, gravity, bv, bL, bx, bapplied,
                        damp_force, damp_torque, dt, dt_prev, kick, c_old, c_new,
                        local_damping, global_damping, first, store_damping)
        lo2, wb2, wa2, dl2, dg2, ke2 = _kick(b, 2, f2, t2, om2, m, binv_m, rotating, gravity, bv, bL, bx, bapplied,
                        damp_force, damp_torque, dt, dt_prev, kick, c_old, c_new,
                        local_damping, global_damping, first, store_damping)
        w_body += wb0 + wb1 + wb2
        w_app += wa0 + wa1 + wa2
        d_local += dl0 + dl1 + dl2
        d_global += dg0 + dg1 + dg2
        ke_t += ke0 + ke1 + ke2
        # rotational kinetic energy at t from the angular momentum at t (body frame)
        lm0, lm1, lm2 = quat_rotate(q0, -q1, -q2, -q3, 0.5 * (c_old * lo0 + c_new * bL[b, 0]),
                                    0.5 * (c_old * lo1 + c_new * bL[b, 1]),
                                    0.5 * (c_old * lo2 + c_new * bL[b, 2]))
        ke_r += 0.5 * (lm0 * lm0 * i0 + lm1 * lm1 * i1 + lm2 * lm2 * i2)
        # 3. orientation
        n0, n1, n2, n3 = q0, q1, q2, q3
        if rotating:
            n0, n1, n2, n3 = free_rotation(q0, q1, q2, q3, bL[b, 0], bL[b, 1], bL[b, 2],
                                           i0, i1, i2, dt)
        bq[b, 0], bq[b, 1], bq[b, 2], bq[b, 3] = n0, n1, n2, n3
        # angular velocity over the step: the rotation vector of q_new q_old^-1
        d0, d1, d2, d3 = quat_mul(n0, n1, n2, n3, q0, -q1, -q2, -q3)
        if d0 < 0.0:
            d0, d1, d2, d3 = -d0, -d1, -d2, -d3
        s = math.sqrt(d1 * d1 + d2 * d2 + d3 * d3)
        om0, om1, om2 = 0.0, 0.0, 0.0
        if s > 0.0:
            angle = 2.0 * math.atan2(s, d0)
            om0 = angle * d1 / (s * dt)
            om1 = angle * d2 / (s * dt)
            om2 = angle * d3 / (s * dt)
        # 4. members follow
        for k in range(start[b], start[b + 1]):
            p = member[k]
            a0, a1, a2 = quat_rotate(q0, q1, q2, q3, offset[k, 0], offset[k, 1], offset[k, 2])
            c0, c1, c2 = quat_rotate(n0, n1, n2, n3, offset[k, 0], offset[k, 1], offset[k, 2])
            v[p, 0] = (bx[b, 0] - xo0 + c0 - a0) / dt
            v[p, 1] = (bx[b, 1] - xo1 + c1 - a1) / dt
            v[p, 2] = (bx[b, 2] - xo2 + c2 - a2) / dt
            w[p, 0] = om0
            w[p, 1] = om1
            w[p, 2] = om2
            for j in range(3):
                x[p, j] += dt * v[p, j]
            d2, jp2 = moved_since_build(x_flat, v_flat, x_ref_flat, r, p)
            disp2 = max(disp2, d2)
            jump2 = max(jump2, jp2)
    store_step_terms(out, w_body, w_app, d_local, d_global, ke_t, ke_r, disp2, jump2, dt)


body_step, body_step_serial = compile_parallel_and_serial(_body_loop)


@njit
def place_members(bx, bq, start, member, offset, x, periodic_len):
    """Members at x_b + R d (wrapped into the periodic box along its axes)."""
    for b in range(bx.shape[0]):
        for k in range(start[b], start[b + 1]):
            p = member[k]
            a = quat_rotate(bq[b, 0], bq[b, 1], bq[b, 2], bq[b, 3],
                            offset[k, 0], offset[k, 1], offset[k, 2])
            for j in range(3):
                value = bx[b, j] + a[j]
                if periodic_len[j] > 0.0:
                    value = value - periodic_len[j] * math.floor(value / periodic_len[j])
                x[p, j] = value


@njit
def member_velocities(bx, bq, bv, bL, binv_I, start, member, offset, v, w):
    """Members' velocities v_b + omega x (R d) and angular velocities omega of bodies at
    rest or moving (omega = R I^-1 R^T L), at the start of a run."""
    for b in range(bx.shape[0]):
        q0, q1, q2, q3 = bq[b, 0], bq[b, 1], bq[b, 2], bq[b, 3]
        om = world_omega(q0, q1, q2, q3, bL[b, 0], bL[b, 1], bL[b, 2],
                         binv_I[b, 0], binv_I[b, 1], binv_I[b, 2])
        for k in range(start[b], start[b + 1]):
            p = member[k]
            a = quat_rotate(q0, q1, q2, q3, offset[k, 0], offset[k, 1], offset[k, 2])
            v[p, 0] = bv[b, 0] + om[1] * a[2] - om[2] * a[1]
            v[p, 1] = bv[b, 1] + om[2] * a[0] - om[0] * a[2]
            v[p, 2] = bv[b, 2] + om[0] * a[1] - om[1] * a[0]
            for j in range(3):
                w[p, j] = om[j]
