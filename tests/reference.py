"""Slow pure-numpy references of the engine's kernels, written independently of them."""

import numpy as np


def brute_force_pairs(x, r, skin, box=None):
    """All pairs (i < j) with |x_j - x_i| < r_i + r_j + skin (minimum image if box)."""
    d = x[None, :, :] - x[:, None, :]
    if box is not None:
        box = np.asarray(box, dtype=float)
        per = box > 0
        d[..., per] -= box[per] * np.round(d[..., per] / box[per])
    dist = np.linalg.norm(d, axis=2)
    reach = r[:, None] + r[None, :] + skin
    i, j = np.nonzero(np.triu(dist < reach, 1))
    return set(zip(i.tolist(), j.tolist()))


def linear_pair_forces(x, v, w, r, m, pairs, k_n, k_s, mu, c_n, c_t, dt, ft, fd, etan):
    """Linear spring-dashpot with Coulomb friction, for each pair (i, j), numpy only.

    Returns force on j (P, 3), new tangential force, new dashpot force, new tangential
    energy, and the per-pair strain (normal, tangential), friction and dashpot terms."""
    overlap = _overlap(x, r, pairs)
    return _spring_slider(x, v, w, r, pairs, k_n * overlap, 0.5 * k_n * overlap**2,
                          np.full(len(pairs), float(k_s)), mu, c_n, c_t, dt, ft, fd, etan)


def hertz_pair_forces(x, v, w, r, m, pairs, youngs_modulus, poisson_ratio, mu, beta_n,
                      beta_t, dt, ft, fd, etan):
    """Hertz-Mindlin (no-slip) with Coulomb friction and restitution dashpots (damping
    ratios ``beta_n``, ``beta_t``), numpy only, from the textbook formulas for one
    material: E* = E / (2 (1 - nu^2)), G* = G / (2 (2 - nu)) with G = E / (2 (1 + nu)),
    R* = r_i r_j / (r_i + r_j), m* = m_i m_j / (m_i + m_j);
    F_n = 4/3 E* sqrt(R*) delta^(3/2), stored energy 8/15 E* sqrt(R*) delta^(5/2),
    tangent stiffnesses k_n = 2 E* sqrt(R* delta), k_t = 8 G* sqrt(R* delta), dashpots
    c = 2 sqrt(5/6) beta sqrt(m* k) (Tsuji et al. 1992). Returns as
    :func:`linear_pair_forces`."""
    i, j = pairs[:, 0], pairs[:, 1]
    overlap = _overlap(x, r, pairs)
    delta = np.clip(overlap, 0.0, None)
    e_star = youngs_modulus / (2.0 * (1.0 - poisson_ratio**2))
    g_star = youngs_modulus / (2.0 * (1.0 + poisson_ratio)) / (2.0 * (2.0 - poisson_ratio))
    r_star = r[i] * r[j] / (r[i] + r[j])
    m_star = m[i] * m[j] / (m[i] + m[j])
    f_el = 4.0 / 3.0 * e_star * np.sqrt(r_star) * delta**1.5
    e_n = 8.0 / 15.0 * e_star * np.sqrt(r_star) * delta**2.5
    k_n = 2.0 * e_star * np.sqrt(r_star * delta)
    k_t = 8.0 * g_star * np.sqrt(r_star * delta)
    c_n = 2.0 * np.sqrt(5.0 / 6.0) * beta_n * np.sqrt(m_star * k_n)
    c_t = 2.0 * np.sqrt(5.0 / 6.0) * beta_t * np.sqrt(m_star * k_t)
    return _spring_slider(x, v, w, r, pairs, f_el, e_n, k_t, mu, c_n, c_t, dt, ft, fd, etan)


def _overlap(x, r, pairs):
    i, j = pairs[:, 0], pairs[:, 1]
    return r[i] + r[j] - np.linalg.norm(x[j] - x[i], axis=1)


def _spring_slider(x, v, w, r, pairs, f_el, e_el, k_t, mu, c_n, c_t, dt, ft, fd, etan):
    """The part common to the laws: elastic normal force ``f_el`` and energy ``e_el``
    per pair, an incremental tangential spring of stiffness ``k_t`` (per pair) rotated
    with the contact plane, a Coulomb slider and dashpots ``c_n``, ``c_t``."""
    i, j = pairs[:, 0], pairs[:, 1]
    d = x[j] - x[i]
    dist = np.linalg.norm(d, axis=1)
    n = d / dist[:, None]
    overlap = r[i] + r[j] - dist
    arm_i = (dist + r[i] - r[j]) / 2.0  # contact point in the middle of the overlap
    arm_j = dist - arm_i
    vc_i = v[i] + np.cross(w[i], arm_i[:, None] * n)
    vc_j = v[j] + np.cross(w[j], -arm_j[:, None] * n)
    vrel = vc_j - vc_i
    du = vrel * dt
    du_n = np.sum(du * n, axis=1)
    du_t = du - du_n[:, None] * n
    # old spring force projected on the new tangent plane, magnitude kept
    old = ft - np.sum(ft * n, axis=1)[:, None] * n
    norm_ft = np.linalg.norm(ft, axis=1)
    norm_old = np.linalg.norm(old, axis=1)
    scale = np.divide(norm_ft, norm_old, out=np.ones_like(norm_ft), where=norm_old > 0)
    old = old * scale[:, None]
    touching = overlap > 0
    v_n = np.sum(vrel * n, axis=1)
    f_nd = -c_n * v_n
    trial = old - k_t[:, None] * du_t
    limit = mu * f_el
    mag = np.linalg.norm(trial, axis=1)
    sliding = mag > limit
    new_t = np.where(sliding[:, None], trial * (limit / np.where(mag > 0, mag, 1))[:, None], trial)
    v_t = vrel - v_n[:, None] * n
    damp_t = np.where(sliding[:, None], 0.0, -np.broadcast_to(c_t, v_n.shape)[:, None] * v_t)
    damp_t = _within_coulomb(new_t, damp_t, limit)
    e_t = np.sum(new_t**2, axis=1) / (2 * np.where(k_t > 0, k_t, np.inf))
    new_fd = f_nd[:, None] * n + damp_t
    force = (f_el + f_nd)[:, None] * n + new_t + damp_t
    w_in = -0.5 * np.sum((old + new_t) * du_t, axis=1)
    friction = w_in - (e_t - etan)
    dashpot = -0.5 * np.sum((fd + new_fd) * du, axis=1)
    # pairs apart: no force, history released
    apart = ~touching
    force[apart] = 0.0
    friction[apart] = (-0.5 * np.sum(old * du_t, axis=1) + etan)[apart]
    dashpot[apart] = (-0.5 * np.sum(fd * du, axis=1))[apart]
    new_t[apart] = 0.0
    new_fd[apart] = 0.0
    e_t[apart] = 0.0
    e_n = np.where(touching, e_el, 0.0)
    return force, new_t, new_fd, e_t, e_n, friction, dashpot, arm_i, arm_j, n


def _within_coulomb(spring, dashpot, limit):
    """The dashpot forces scaled by the largest alpha in [0, 1] with |spring + alpha
    dashpot| <= limit (found by bisection: the squared norm is convex in alpha and at
    most limit^2 at 0, the spring sticking)."""
    def norm2(alpha):
        return np.sum((spring + alpha[:, None] * dashpot) ** 2, axis=1)

    over = norm2(np.ones(len(limit))) > limit**2
    lo, hi = np.zeros(len(limit)), np.ones(len(limit))
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        inside = norm2(mid) <= limit**2
        lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
    return np.where(over[:, None], lo[:, None] * dashpot, dashpot)


def gather(pairs, force, n, arm_i, arm_j, n_particles):
    """Per-particle force and torque from pair forces (force on j, -force on i)."""
    f = np.zeros((n_particles, 3))
    t = np.zeros((n_particles, 3))
    np.add.at(f, pairs[:, 1], force)
    np.add.at(f, pairs[:, 0], -force)
    np.add.at(t, pairs[:, 0], np.cross(arm_i[:, None] * n, -force))
    np.add.at(t, pairs[:, 1], np.cross(-arm_j[:, None] * n, force))
    return f, t


def leapfrog(x, v, w, m, inertia, force, torque, gravity, dt):
    """One central-difference step (no damping)."""
    v_new = v + dt * (force / m[:, None] + gravity)
    w_new = w + dt * torque / inertia[:, None]
    return x + dt * v_new, v_new, w_new
