"""The certificate that keeps an 'auto' time step stable between two estimates.

An estimate of the 'auto' control certifies the damped critical root sigma_c [1/T] of
the contacts it covered (every Verlet pair at the overlap it can reach, see
:meth:`demstep.engine.Simulation.contact_set`), at the geometry of that moment:
lambda_max(sigma_c C^ + K^) <= sigma_c^2, with C^ = M^-1/2 C M^-1/2 and K^ likewise,
and Lambda_C >= lambda_max(C^). Between estimates the assembly moves on: contacts the
estimate did not cover close, and the normals of the covered ones turn. The step
sigma = 2 / dt stays certified as long as

    lambda_max(sigma C^ + K^)(now) <= sigma_c^2 + max(sigma - sigma_c, 0) Lambda_C
                                      + sigma A_C + A_K + D(sigma) <= sigma^2,

where

* the first two terms bound the covered contacts at the estimate's geometry (the
  left side is convex in sigma with slope at most lambda_max(C^), and does not
  decrease; Lambda_C stands for min(Lambda_C, sigma_c) there, as
  sigma_c lambda_max(C^) <= lambda_max(sigma_c C^ + K^) <= sigma_c^2);
* A_K + sigma A_C bounds the contacts added since (:meth:`StepCertificate.set_added`;
  all of them as one group, by the largest of their coupled elements with the
  particles' masses split among them, Rayleigh's theorem on the group alone, and
  Weyl's inequality for the sum with the rest: :func:`added_contacts_bound`, rolling
  and twisting springs included; or, when smaller, the sum of the bounds of the groups
  as they were added, each with its own split: both bound them);
* D(sigma) bounds how far the covered contacts' normals have turned (Weyl's inequality
  again): a contact's mass-scaled element matrix is E(n) = L(n)^T B(n) L(n) with
  B = b_n n n^T + b_t (I - n n^T) (b = sigma c + k) and L the map from the two
  particles' scaled motions x = (u, w) to the relative displacement at the contact,
  L(n) x = v + n x omega: v = u_j / sqrt(m_j) - u_i / sqrt(m_i), |v| <= tau |u| with
  tau^2 = 1/m_i + 1/m_j, and omega = r_i w_i / sqrt(I_i) + r_j w_j / sqrt(I_j) (signs
  aside), |omega| <= rho |w| with rho^2 = r_i^2/I_i + r_j^2/I_j (r the arms). The
  rotation does not move the contact along n, so x.E x = b_t |L x|^2 + (b_n - b_t)
  (n.v)^2. With d = n' - n and s = n' + n (d.s = 0, |s| <= 2):

      |L(n') x|^2 - |L(n) x|^2 = 2 v.(d x omega) - (d.omega)(s.omega),
      (n'.v)^2 - (n.v)^2 = (d.v)(s.v), at most |d| |v|^2 |s| / 2 <= |d| tau^2 |u|^2.

  Only the part of omega across d, rho q = |omega| sin(phi), enters d x omega and
  s.omega, and d.omega = |d| rho p with rho p = |omega| cos(phi). With a = |u|:
  a^2 + p^2 + q^2 <= |x|^2, and |x.(E(n') - E(n)) x| / |d| is at most

      |b_n - b_t| tau^2 a^2 + 2 b_t tau rho a q + 2 b_t rho^2 p q = y.M y,
      M = [[A, 0, B], [0, 0, C], [B, C, 0]], A = |b_n - b_t| tau^2, B = b_t tau rho,
      C = b_t rho^2, y = (a, p, q) >= 0,

  so |E(n') - E(n)| <= |n' - n| lambda_max(M) (:func:`_turn_factor`). For disks omega
  is normal to the plane, across d (p = 0): the 2 x 2 [[A, B], [B, 0]]. lambda_max(M)
  is at most b_t rho l + A (l^2 = tau^2 + rho^2), attained for b_n = b_t by a pure
  turn; the earlier |n' - n| l (2 rho max(b_n, b_t) + l |b_n - b_t|) was twice that
  for b_n = b_t and about 8 times for solid spheres with b_t = 2/7 b_n (the tangential
  springs are what a turn moves). A sum of two-particle element matrices has its norm
  below the largest sum over the elements of one particle (x.E x <= |E| (|x_i|^2 +
  |x_j|^2) per element).

  The arms change too: a contact's shorten as it closes (the estimate took the radii,
  the longest), a bond's lengthen as it stretches, and lambda_max of an assembly is
  not monotone in them (measured: shortening 1 % of the arms of random 12-sphere
  assemblies from the radii raised it by up to 5.6e-5, relative). With the arms a
  of the estimate and a' now, E(n', a') - E(n, a) = [E(n', a') - E(n, a')] +
  [E(n, a') - E(n, a)]: the first is bounded as above with l and rho at the arms a'
  now, the second by the arms' change of omega, |omega' - omega| <= eta |w| with
  eta^2 = (a_i' - a_i)^2/I_i + (a_j' - a_j)^2/I_j: the arms move only the tangential
  part P L x = P v + n x omega (P = I - n n^T), so x.(E' - E) x = b_t (|P L' x|^2 -
  |P L x|^2), at most b_t eta (l(a) + l(a')) |x|^2 with l(a)^2 = tau^2 + rho(a)^2
  >= |L(a)|^2. A covered wall contact keeps its normal (walls do not turn) and
  changes its arm alike (one particle).

  Rolling and twisting resistance (3D) adds to E the rotational element
  L_phi^T R(n) L_phi with R = b_r (I - n n^T) + b_w n n^T (b = sigma c + k for the
  rolling and twisting springs k_r, k_w and their viscous parts c_r, c_w) and L_phi
  the map to phi = theta_j - theta_i, which does not depend on n:
  |L_phi|^2 = 1/I_i + 1/I_j and R(n') - R(n) = (b_w - b_r)(n' n'^T - n n^T), whose
  norm is at most |b_w - b_r| |n' - n|. So each pair's turn factor gains
  (1/I_i + 1/I_j) |b_w - b_r|. For disks R = b_r does not depend on n: no term.
  Splitting b = k + sigma c gives the sums for the springs (D_K) and the viscous parts
  (D_C): every term is at most the sum of its spring and sigma times its viscous part.

Removed contacts only lower lambda_max (each element is positive semi-definite).

Clumps. A contact with a member sphere acts on its body's motion: the arm from the
body's centre to the contact point is r = R o + a n (o the member's centre in the body
frame, R the body's rotation, a the member's arm; -a n on side j), and the body's
scaled rotation w maps to omega = S w with S = R I^-1/2 R^T (I the principal
moments), so the element's map is L x = sum of u/sqrt(m) + A w over its sides (signs
aside) with A = -[r]x S, and E = S_e^T S_e with S_e = B^1/2 L. The body turns by
dR = R' R^T between the estimate and now. lambda_max is unchanged by an orthogonal
change of coordinates Q, and with Q = dR on each body's rotation (the identity
elsewhere) S' Q = dR S: the rotation block of L' Q - L is A' - A with A' = -[r']x dR S.
Its norm is computed per side (3 x 3: |M|_2^2 = lambda_max(M^T M), closed form,
rounded up), eta^2 = the sum over the sides of |A' - A|^2 (the translations do not
change), and |L| <= l = sqrt(tau^2 + |A_i|^2 + |A_j|^2), likewise l' now. A free
sphere's side has S = I^-1/2 and Q = 1: |A' - A| = |a' n' - a n| / sqrt(I); a
disk's rotation is about z, which dR leaves alone (its S has the zz entry only). With
|B'^1/2 - B^1/2| <= |sqrt(b_n) - sqrt(b_t)| |n' - n|,

    x.(Q^T E' Q - E) x <= |S_e' Q - S_e| (|S_e'| + |S_e|) |x|^2
                       <= (l + l') (|b_n - b_t| |n' - n| l' + max(b_n, b_t) eta) |x|^2

(|sqrt(b_n) - sqrt(b_t)| sqrt(max(b_n, b_t)) <= |b_n - b_t|): linear in b, so split
into springs and viscous parts as above. A rolling and twisting element on
phi = omega_j - omega_i, with L_phi = (-S_i, S_j) and R = b_r (I - n n^T) + b_w n n^T,
adds 2 l_phi (|b_w - b_r| |n' - n| l_phi + max(b_r, b_w) eta_phi) with
l_phi^2 = sum |S|^2 and eta_phi^2 = sum |(dR - I) S|^2 (S' Q - S = (dR - I) S); a
disk's R does not turn. These bounds hold per element as above, summed per owner (a
free sphere or a body) and the largest sum taken: :func:`_body_drift_sums`. A contact
apart has no element now (its change, -E, lowers lambda_max): it counts once it
touches. Contacts added with clumps are bounded at any orientation of the bodies
(:func:`added_contacts_bound`), so they need no drift term. Between checks, a
certificate with clumps holds while the pairs' ends moved by at most E relative to
each other and the bodies turned by at most Theta since the last check
(:meth:`StepCertificate.body_budgets`): from the state of the check, a side's A moves
by at most |S| (Theta (|o| + a) + |a'' n'' - a' n'|) (the same decomposition, dR_x
the further turn), so the drift terms grow at most linearly in E and Theta.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from demstep._numba import njit
from demstep.contact.geometry import (any_periodic, contact_arms, minimum_image, pair_geometry,
                                      wall_geometry)
from demstep.kernels.turn_factor import (TURN_FACTOR_ITERATIONS, TURN_FACTOR_MARGIN,  # noqa: F401
                                         turn_factor as _turn_factor)
from demstep.timestep.clumps import cross_matrix, owner_mass_shares
from demstep.timestep.elements import coupled_element_lambda
from demstep.timestep.mass_split import element_mass

@njit(inline="always")
def _branch(x, a, b, periodic_len):
    """(d0, d1, d2, |d|): the branch vector [L] from a's centre to b's (nearest periodic
    image, :func:`~demstep.contact.geometry.minimum_image`) and its length."""
    d0, d1, d2 = minimum_image(x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2],
                               periodic_len[0], periodic_len[1], periodic_len[2])[:3]
    return d0, d1, d2, math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)


@njit(cache=True, inline="always")
def _pair_turn(x, a, b, normal_ref, c, periodic_len):
    """(|d|, turn) of pair c = (a, b): its centre distance [L] now (nearest periodic
    image) and |d/|d| - n_ref| [-], how far its normal turned from ``normal_ref[c]``
    (2, a half turn, for coincident centres: any normal)."""
    d0, d1, d2, dist = _branch(x, a, b, periodic_len)
    if not dist > 0.0:
        return dist, 2.0
    t0 = d0 / dist - normal_ref[c, 0]
    t1 = d1 / dist - normal_ref[c, 1]
    t2 = (d2 / dist - normal_ref[c, 2]) if normal_ref.shape[1] == 3 else 0.0
    return dist, math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)


@njit(cache=True)
def _drift_sums(x, i, j, bond, normal_ref, factors, particles, periodic_len, sum_k, sum_c):
    """Adds to ``sum_k`` [1/T^2] and ``sum_c`` [1/T] (N,), per particle, over its covered
    pairs (i, j), the bounds on how far the pair's element moved since the estimate
    (module doc), for the springs and the viscous parts: the turn |n - n_ref| (n the
    unit normal now, minimum image along periodic axes) times the turn factor at the
    arms now, plus the arm term eta (l_ref + l) b_t. ``factors`` (P, 8) per
    pair (:attr:`StepCertificate.factors`): the arms [L] of the estimate, (b_n, b_t) of
    the springs and of the dashpots, the rolling and twisting turn factors (springs,
    viscous parts; no arms in them); ``particles`` (N, 3) the radius,
    inverse mass and inverse moment of inertia (zero when fixed, and rotation off). The
    arms now are those of the geometry for a touching contact and a bond (``bond``
    true: it acts apart too), the estimate's for a contact apart (it has no element
    now, and closing it shortens them: counted once it touches)."""
    planar = normal_ref.shape[1] == 2
    for c in range(i.shape[0]):
        a, b = i[c], j[c]
        dist, turn = _pair_turn(x, a, b, normal_ref, c, periodic_len)
        ref_i, ref_j = factors[c, 0], factors[c, 1]
        r_a, r_b = particles[a, 0], particles[b, 0]
        if bond[c] or dist < r_a + r_b:
            arm_i, arm_j = contact_arms(r_a, r_b, dist)
        else:
            arm_i, arm_j = ref_i, ref_j
        trans = particles[a, 1] + particles[b, 1]
        inv_ia, inv_ib = particles[a, 2], particles[b, 2]
        rot = arm_i * arm_i * inv_ia + arm_j * arm_j * inv_ib
        l_now = math.sqrt(trans + rot)
        l_ref = math.sqrt(trans + ref_i * ref_i * inv_ia + ref_j * ref_j * inv_ib)
        eta = math.sqrt((arm_i - ref_i) ** 2 * inv_ia + (arm_j - ref_j) ** 2 * inv_ib)
        arm_term = eta * (l_ref + l_now)
        k_n, k_t, c_n, c_t = factors[c, 2], factors[c, 3], factors[c, 4], factors[c, 5]
        f_k = (turn * (_turn_factor(trans, rot, k_n, k_t, planar) + factors[c, 6])
               + arm_term * k_t)
        f_c = (turn * (_turn_factor(trans, rot, c_n, c_t, planar) + factors[c, 7])
               + arm_term * c_t)
        sum_k[a] += f_k
        sum_k[b] += f_k
        sum_c[a] += f_c
        sum_c[b] += f_c


@njit(cache=True)
def _lookahead_sums(x, i, j, bond, normal_ref, factors, particles, periodic_len, e_cap,
                    up_k, up_c, rate_k, rate_c):
    """Adds per particle, over its covered pairs (i, j), what bounds their drift terms
    (:func:`_drift_sums`) at any positions x' whose pairs' relative displacements from
    ``x`` are at most E <= ``e_cap`` [L]: ``up_k``, ``up_c`` the terms at ``x`` with
    the turn factors and l taken at the longest arms a pair can have then (a contact's
    radii, a bond's arms now + e_cap; both at least the estimate's), a contact apart
    taken with the radii for arms (those it would close with); ``rate_k``, ``rate_c``
    [1/(T^2 L)], [1/(T L)] their growth per unit of E. A normal turns by at most
    2 E / |d| (|d| the centre distance now: |a/|a| - b/|b|| <= 2 |a - b| / |a|), and the
    arms, half the overlap from the radii, move by at most E / 2, so that eta grows by
    at most E sqrt(1/I_i + 1/I_j) (module doc)."""
    planar = normal_ref.shape[1] == 2
    for c in range(i.shape[0]):
        a, b = i[c], j[c]
        dist, turn = _pair_turn(x, a, b, normal_ref, c, periodic_len)
        per_length = 2.0 / dist if dist > 0.0 else math.inf
        ref_i, ref_j = factors[c, 0], factors[c, 1]
        r_a, r_b = particles[a, 0], particles[b, 0]
        if bond[c]:
            arm_i, arm_j = contact_arms(r_a, r_b, dist)
            up_i, up_j = max(arm_i + e_cap, ref_i), max(arm_j + e_cap, ref_j)
        else:
            if dist < r_a + r_b:
                arm_i, arm_j = contact_arms(r_a, r_b, dist)
            else:
                arm_i, arm_j = r_a, r_b
            up_i, up_j = max(r_a, ref_i), max(r_b, ref_j)
        trans = particles[a, 1] + particles[b, 1]
        inv_ia, inv_ib = particles[a, 2], particles[b, 2]
        rot_up = up_i * up_i * inv_ia + up_j * up_j * inv_ib
        width = (math.sqrt(trans + ref_i * ref_i * inv_ia + ref_j * ref_j * inv_ib)
                 + math.sqrt(trans + rot_up))
        eta = math.sqrt((arm_i - ref_i) ** 2 * inv_ia + (arm_j - ref_j) ** 2 * inv_ib)
        spread = math.sqrt(inv_ia + inv_ib)
        k_n, k_t, c_n, c_t = factors[c, 2], factors[c, 3], factors[c, 4], factors[c, 5]
        tf_k = _turn_factor(trans, rot_up, k_n, k_t, planar) + factors[c, 6]
        tf_c = _turn_factor(trans, rot_up, c_n, c_t, planar) + factors[c, 7]
        f_k = turn * tf_k + eta * width * k_t
        f_c = turn * tf_c + eta * width * c_t
        g_k = per_length * tf_k + spread * width * k_t
        g_c = per_length * tf_c + spread * width * c_t
        up_k[a] += f_k
        up_k[b] += f_k
        up_c[a] += f_c
        up_c[b] += f_c
        rate_k[a] += g_k
        rate_k[b] += g_k
        rate_c[a] += g_c
        rate_c[b] += g_c


@njit(cache=True)
def _wall_lookahead_sums(x, p, w, point, normal, wall_factors, particles, up_k, up_c, rate_k,
                         rate_c):
    """:func:`_lookahead_sums` for the covered wall contacts (their arm terms: the arm,
    the distance from the centre to the wall, moves by at most E)."""
    for c in range(p.shape[0]):
        a, b = p[c], w[c]
        geo = wall_geometry(x[a, 0], x[a, 1], x[a, 2], particles[a, 0], point[b, 0],
                            point[b, 1], point[b, 2], normal[b, 0], normal[b, 1],
                            normal[b, 2])
        ref = wall_factors[c, 0]
        r_a = particles[a, 0]
        arm = geo[5] if geo[4] > 0.0 else r_a
        up = max(r_a, ref)
        inv_m, inv_i = particles[a, 1], particles[a, 2]
        spread = math.sqrt(inv_i)
        width = math.sqrt(inv_m + up * up * inv_i) + math.sqrt(inv_m + ref * ref * inv_i)
        up_k[a] += abs(arm - ref) * spread * width * wall_factors[c, 1]
        up_c[a] += abs(arm - ref) * spread * width * wall_factors[c, 2]
        rate_k[a] += spread * width * wall_factors[c, 1]
        rate_c[a] += spread * width * wall_factors[c, 2]


@njit(cache=True)
def _wall_drift_sums(x, p, w, point, normal, wall_factors, particles, sum_k, sum_c):
    """Adds to ``sum_k`` and ``sum_c`` (N,) the arm terms of the covered wall contacts
    (p, w) (walls keep their normals): eta (l_ref + l) b_t, eta the change of
    the arm (the geometry's now for a touching contact, else the estimate's) over
    sqrt(I); ``wall_factors`` (W, 3): the estimate's arm [L], the tangential spring
    k_t and dashpot c_t; ``particles`` as :func:`_drift_sums`."""
    for c in range(p.shape[0]):
        a, b = p[c], w[c]
        geo = wall_geometry(x[a, 0], x[a, 1], x[a, 2], particles[a, 0], point[b, 0],
                            point[b, 1], point[b, 2], normal[b, 0], normal[b, 1],
                            normal[b, 2])
        ref = wall_factors[c, 0]
        arm = geo[5] if geo[4] > 0.0 else ref  # (apart: no element now)
        inv_m, inv_i = particles[a, 1], particles[a, 2]
        term = abs(arm - ref) * math.sqrt(inv_i) * (math.sqrt(inv_m + arm * arm * inv_i)
                                                     + math.sqrt(inv_m + ref * ref * inv_i))
        sum_k[a] += term * wall_factors[c, 1]
        sum_c[a] += term * wall_factors[c, 2]


@njit(inline="always")
def _sym3_top(a00, a01, a02, a11, a12, a22):
    """The largest eigenvalue of a symmetric 3 x 3 matrix (closed form, trigonometric),
    raised by a relative 1e-9 past its rounding (an upper bound for the certificate)."""
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    if not p2 > 0.0:
        return q * (1.0 + 1e-9) if q > 0.0 else q
    p = math.sqrt(p2 / 6.0)
    b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
    b01, b02, b12 = a01 / p, a02 / p, a12 / p
    half_det = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02)
                      + b02 * (b01 * b12 - b11 * b02))
    half_det = min(1.0, max(-1.0, half_det))
    top = q + 2.0 * p * math.cos(math.acos(half_det) / 3.0)
    return top + 1e-9 * abs(top)


@njit(inline="always")
def _norm2(m):
    """|m|_2^2 = lambda_max(m^T m) of a 3 x 3 matrix, from above."""
    g00 = m[0, 0] * m[0, 0] + m[1, 0] * m[1, 0] + m[2, 0] * m[2, 0]
    g01 = m[0, 0] * m[0, 1] + m[1, 0] * m[1, 1] + m[2, 0] * m[2, 1]
    g02 = m[0, 0] * m[0, 2] + m[1, 0] * m[1, 2] + m[2, 0] * m[2, 2]
    g11 = m[0, 1] * m[0, 1] + m[1, 1] * m[1, 1] + m[2, 1] * m[2, 1]
    g12 = m[0, 1] * m[0, 2] + m[1, 1] * m[1, 2] + m[2, 1] * m[2, 2]
    g22 = m[0, 2] * m[0, 2] + m[1, 2] * m[1, 2] + m[2, 2] * m[2, 2]
    return _sym3_top(g00, g01, g02, g11, g12, g22)


@njit(inline="always")
def _cross_times(r0, r1, r2, a, out):
    """out = [r]x a for a 3 x 3 matrix a."""
    for k in range(3):
        out[0, k] = r1 * a[2, k] - r2 * a[1, k]
        out[1, k] = r2 * a[0, k] - r0 * a[2, k]
        out[2, k] = r0 * a[1, k] - r1 * a[0, k]


@njit(inline="always")
def _rotation(q, out):
    """out = R(q) (3 x 3) of a quaternion (w, x, y, z), normalised."""
    size = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    w, x, y, z = q[0] / size, q[1] / size, q[2] / size, q[3] / size
    out[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    out[0, 1] = 2.0 * (x * y - w * z)
    out[0, 2] = 2.0 * (x * z + w * y)
    out[1, 0] = 2.0 * (x * y + w * z)
    out[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    out[1, 2] = 2.0 * (y * z - w * x)
    out[2, 0] = 2.0 * (x * z - w * y)
    out[2, 1] = 2.0 * (y * z + w * x)
    out[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@njit(cache=True)
def body_frames(q_ref, q, inv_m, inv_I):
    """(frames (B, 5, 3, 3), scalars (B, 3)) of :func:`_body_drift_sums` for bodies
    turned from the orientations ``q_ref`` to ``q`` (B, 4) with inverse masses
    ``inv_m`` (B,) and principal inverse moments ``inv_I`` (B, 3): R_ref, R now,
    S_ref = R_ref I^-1/2 R_ref^T, dR S_ref (dR = R R_ref^T) and the world inverse
    inertia now R I^-1 R^T; 1/m, |S|^2 and |(dR - I) S_ref|^2."""
    n = q.shape[0]
    frames = np.zeros((n, 5, 3, 3))
    scalars = np.zeros((n, 3))
    diff = np.empty((3, 3))
    for b in range(n):
        r_ref, r_now, s_ref, ds = frames[b, 0], frames[b, 1], frames[b, 2], frames[b, 3]
        _rotation(q_ref[b], r_ref)
        _rotation(q[b], r_now)
        for i in range(3):
            for j in range(3):
                acc = 0.0
                for k in range(3):
                    acc += r_ref[i, k] * math.sqrt(inv_I[b, k]) * r_ref[j, k]
                s_ref[i, j] = acc
        for i in range(3):  # dR S_ref = R_now (R_ref^T S_ref) = R_now I^-1/2 R_ref^T
            for j in range(3):
                acc = 0.0
                for k in range(3):
                    acc += r_now[i, k] * math.sqrt(inv_I[b, k]) * r_ref[j, k]
                ds[i, j] = acc
                diff[i, j] = acc - s_ref[i, j]
        inertia_now = frames[b, 4]  # (I^-1 now: R_now I^-1 R_now^T)
        for i in range(3):
            for j in range(3):
                acc = 0.0
                for k in range(3):
                    acc += r_now[i, k] * inv_I[b, k] * r_now[j, k]
                inertia_now[i, j] = acc
        scalars[b, 0] = inv_m[b]
        scalars[b, 1] = max(inv_I[b, 0], inv_I[b, 1], inv_I[b, 2])
        scalars[b, 2] = _norm2(diff)
    return frames, scalars


@njit(inline="always")
def _lever_norm2(r0, r1, r2, w):
    """|[r]x W^1/2|^2 = |r|^2 lambda_max(P W P) (P the projection across r, W a symmetric
    3 x 3 inverse inertia): the 2 x 2 eigenvalue problem in the plane across r, in
    closed form, raised by a relative 1e-9 past its rounding."""
    size2 = r0 * r0 + r1 * r1 + r2 * r2
    if not size2 > 0.0:
        return 0.0
    size = math.sqrt(size2)
    e0, e1, e2 = r0 / size, r1 / size, r2 / size
    # u across e: e x (the axis least along e), v = e x u
    if abs(e0) <= abs(e1) and abs(e0) <= abs(e2):
        u0, u1, u2 = 0.0, e2, -e1
    elif abs(e1) <= abs(e2):
        u0, u1, u2 = -e2, 0.0, e0
    else:
        u0, u1, u2 = e1, -e0, 0.0
    un = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    u0, u1, u2 = u0 / un, u1 / un, u2 / un
    v0, v1, v2 = e1 * u2 - e2 * u1, e2 * u0 - e0 * u2, e0 * u1 - e1 * u0
    wu0 = w[0, 0] * u0 + w[0, 1] * u1 + w[0, 2] * u2
    wu1 = w[1, 0] * u0 + w[1, 1] * u1 + w[1, 2] * u2
    wu2 = w[2, 0] * u0 + w[2, 1] * u1 + w[2, 2] * u2
    wv0 = w[0, 0] * v0 + w[0, 1] * v1 + w[0, 2] * v2
    wv1 = w[1, 0] * v0 + w[1, 1] * v1 + w[1, 2] * v2
    wv2 = w[2, 0] * v0 + w[2, 1] * v1 + w[2, 2] * v2
    a = u0 * wu0 + u1 * wu1 + u2 * wu2
    b = u0 * wv0 + u1 * wv1 + u2 * wv2
    c = v0 * wv0 + v1 * wv1 + v2 * wv2
    top = 0.5 * (a + c) + math.sqrt(0.25 * (a - c) ** 2 + b * b)
    return size2 * top * (1.0 + 1e-9)


@njit(inline="always")
def _arm_side(s, sign, arm_ref, arm, n_ref, n_now, particles, sphere_body, offset, frames,
              body_scalars, a_ref, a_now, cache, c, at):
    """One side of a contact in :func:`_body_drift_sums`: (owner: -1 for a free sphere,
    else its body; inverse mass, |A_ref|^2, |A_now|^2, |A_now - A_ref|^2, |S|^2,
    |(dR - I) S|^2) with A = [r]x S the map of the owner's scaled rotation to the
    contact point's motion (now, in the coordinates turned by dR), r the arm from the
    owner's centre to the contact point (``sign`` -1 for side j)."""
    k = sphere_body[s]
    if k < 0:
        inv_i = particles[s, 2]
        d0 = arm * n_now[0] - arm_ref * n_ref[0]
        d1 = arm * n_now[1] - arm_ref * n_ref[1]
        d2 = arm * n_now[2] - arm_ref * n_ref[2]
        return (-1, particles[s, 1], inv_i * arm_ref * arm_ref, inv_i * arm * arm,
                inv_i * (d0 * d0 + d1 * d1 + d2 * d2), inv_i, 0.0)
    r_ref, r_now = frames[k, 0], frames[k, 1]
    o0, o1, o2 = offset[s, 0], offset[s, 1], offset[s, 2]
    f0 = r_ref[0, 0] * o0 + r_ref[0, 1] * o1 + r_ref[0, 2] * o2 + sign * arm_ref * n_ref[0]
    f1 = r_ref[1, 0] * o0 + r_ref[1, 1] * o1 + r_ref[1, 2] * o2 + sign * arm_ref * n_ref[1]
    f2 = r_ref[2, 0] * o0 + r_ref[2, 1] * o1 + r_ref[2, 2] * o2 + sign * arm_ref * n_ref[2]
    _cross_times(f0, f1, f2, frames[k, 2], a_ref)
    size_ref = cache[c, at]  # (the estimate's: computed once)
    if not size_ref >= 0.0:
        size_ref = cache[c, at] = _norm2(a_ref)
    f0 = r_now[0, 0] * o0 + r_now[0, 1] * o1 + r_now[0, 2] * o2 + sign * arm * n_now[0]
    f1 = r_now[1, 0] * o0 + r_now[1, 1] * o1 + r_now[1, 2] * o2 + sign * arm * n_now[1]
    f2 = r_now[2, 0] * o0 + r_now[2, 1] * o1 + r_now[2, 2] * o2 + sign * arm * n_now[2]
    _cross_times(f0, f1, f2, frames[k, 3], a_now)
    size_now = _lever_norm2(f0, f1, f2, frames[k, 4])
    for i in range(3):
        for j in range(3):
            a_now[i, j] -= a_ref[i, j]
    return (k, body_scalars[k, 0], size_ref, size_now, _norm2(a_now), body_scalars[k, 1],
            body_scalars[k, 2])


@njit(cache=True)
def _body_drift_sums(x, pairs, ref, coef, cache, particles, sphere_body, offset, frames,
                     body_scalars, wall_point, wall_normal, periodic_len, planar, sum_k,
                     sum_c, lookahead, e_cap, angle_cap, rate_ek, rate_ec, rate_ak, rate_ac):
    """Adds to ``sum_k`` [1/T^2] and ``sum_c`` [1/T] (N + B,), per owner (the free
    spheres, then the bodies), the bounds of the module doc (Clumps) on how far the
    elements of the covered contacts with a member moved since the estimate:
    ``pairs`` (C, 4) the spheres i, j (-1: a wall contact), the wall (-1: a pair) and 1
    for a bond; ``ref`` (C, 5) the estimate's arms a_i, a_j [L] and unit normal (3
    components); ``coef`` (C, 8) k_n, k_t, c_n, c_t, k_r, k_w, c_r, c_w; ``cache``
    (C, 2) the estimate's |A|^2 of each member side (NaN: not yet computed; filled);
    ``particles``
    (N, 3) radius, inverse mass, inverse moment of inertia (free spheres); per sphere
    its ``sphere_body`` (-1: free) and member ``offset`` (N, 3) [L] in the body frame;
    per body ``frames`` (B, 5, 3, 3): R at the estimate, R now, S at the estimate,
    dR S and I^-1 now (world), and ``body_scalars`` (B, 3): 1/m, |S|^2 and |(dR - I) S|^2 (:meth:`BodyPose.
    frames`).

    With ``lookahead``, what bounds these terms at any state whose pairs' ends moved by
    at most E <= ``e_cap`` [L] relative to each other and whose bodies turned by at most
    Theta <= ``angle_cap`` (|dR_x - I|) from the state ``x`` now: ``sum_k``, ``sum_c``
    the terms at E = Theta = 0 with l' at its largest (below), ``rate_ek``, ``rate_ec``
    their growth per unit of E and ``rate_ak``, ``rate_ac`` per unit of Theta (module
    doc, Clumps). A normal turns by at most 2 E / |d|, an arm by E / 2 (a wall's by E),
    up to the radius (a bond's: its arm now + E); a side's A moves from A now by at
    most |S| (Theta (|o| + a) + |a'' n'' - a' n'|) (the decomposition of the module doc
    from the state now; a free sphere's without Theta), so |A'' - A_ref| by at most
    that more than |A' - A_ref|, and l'' is at most its value with both caps. A contact
    apart is taken with the radii for arms (those it would close with), unless its gap
    is at least ``e_cap`` (it cannot close within the budget)."""
    n = x.shape[0]
    a_ref = np.empty((3, 3))
    a_now = np.empty((3, 3))
    n_now = np.zeros(3)
    for c in range(pairs.shape[0]):
        a, b, w = pairs[c, 0], pairs[c, 1], pairs[c, 2]
        arm_ref_i, arm_ref_j = ref[c, 0], ref[c, 1]
        n_ref = ref[c, 2:]
        if b >= 0:
            d0, d1, d2, dist = _branch(x, a, b, periodic_len)
            if not dist > 0.0:
                return False  # (coincident centres: no normal, a new estimate)
            bond = pairs[c, 3] != 0
            touching = dist < particles[a, 0] + particles[b, 0]
            if not (bond or touching or (
                    lookahead and dist - particles[a, 0] - particles[b, 0] < e_cap)):
                continue  # (apart: no element now, nor within the look-ahead's reach)
            n_now[0], n_now[1], n_now[2] = d0 / dist, d1 / dist, d2 / dist
            if bond or touching:
                arm_i, arm_j = contact_arms(particles[a, 0], particles[b, 0], dist)
            else:
                arm_i, arm_j = particles[a, 0], particles[b, 0]
            per_length = 2.0 / dist
            move_i = 0.5 + per_length * (arm_i + e_cap if bond else particles[a, 0])
            move_j = 0.5 + per_length * (arm_j + e_cap if bond else particles[b, 0])
            top_i = max(arm_i + e_cap, arm_ref_i) if bond else particles[a, 0]
            top_j = max(arm_j + e_cap, arm_ref_j) if bond else particles[b, 0]
        else:
            geo = wall_geometry(x[a, 0], x[a, 1], x[a, 2], particles[a, 0], wall_point[w, 0],
                                wall_point[w, 1], wall_point[w, 2], wall_normal[w, 0],
                                wall_normal[w, 1], wall_normal[w, 2])
            if not (geo[4] > 0.0 or (lookahead and -geo[4] < e_cap)):
                continue
            n_now[0], n_now[1], n_now[2] = geo[0], geo[1], geo[2]
            arm_i, arm_j = (geo[5] if geo[4] > 0.0 else particles[a, 0]), 0.0
            per_length, move_i, move_j = 0.0, 1.0, 0.0
            top_i, top_j = particles[a, 0], 0.0
        turn = math.sqrt((n_now[0] - n_ref[0]) ** 2 + (n_now[1] - n_ref[1]) ** 2
                         + (n_now[2] - n_ref[2]) ** 2)
        oa, trans, rot_ref, rot_now, eta2, phi2, phi_eta2 = _arm_side(
            a, 1.0, arm_ref_i, arm_i, n_ref, n_now, particles, sphere_body, offset, frames,
            body_scalars, a_ref, a_now, cache, c, 0)
        # (lookahead: per side |S| (Theta (|o| + a) + E move) bounds how far A moves)
        spin_a = 0.0 if oa < 0 else math.sqrt(phi2) * (_length(offset, a) + top_i)
        shift_a = math.sqrt(phi2) * move_i
        grow2 = (math.sqrt(rot_now) + angle_cap * spin_a + e_cap * shift_a) ** 2
        spin_phi2 = 0.0 if oa < 0 else phi2
        oa = a if oa < 0 else n + oa
        ob = -1
        if b >= 0:
            ob, inv_m, r_ref2, r_now2, e2, p2, pe2 = _arm_side(
                b, -1.0, arm_ref_j, arm_j, n_ref, n_now, particles, sphere_body, offset,
                frames, body_scalars, a_ref, a_now, cache, c, 1)
            spin_b = 0.0 if ob < 0 else math.sqrt(p2) * (_length(offset, b) + top_j)
            shift_b = math.sqrt(p2) * move_j
            grow2 += (math.sqrt(r_now2) + angle_cap * spin_b + e_cap * shift_b) ** 2
            spin_a += spin_b
            shift_a += shift_b
            spin_phi2 += 0.0 if ob < 0 else p2
            ob = b if ob < 0 else n + ob
            trans += inv_m
            rot_ref += r_ref2
            rot_now += r_now2
            eta2 += e2
            phi2 += p2
            phi_eta2 += pe2
        l_now = math.sqrt(trans + (grow2 if lookahead else rot_now))
        width = l_now + math.sqrt(trans + rot_ref)
        eta = math.sqrt(eta2)
        k_n, k_t, c_n, c_t = coef[c, 0], coef[c, 1], coef[c, 2], coef[c, 3]
        f_k = width * (abs(k_n - k_t) * turn * l_now + max(k_n, k_t) * eta)
        f_c = width * (abs(c_n - c_t) * turn * l_now + max(c_n, c_t) * eta)
        g_ek = width * (abs(k_n - k_t) * per_length * l_now + max(k_n, k_t) * shift_a)
        g_ec = width * (abs(c_n - c_t) * per_length * l_now + max(c_n, c_t) * shift_a)
        g_ak = width * max(k_n, k_t) * spin_a
        g_ac = width * max(c_n, c_t) * spin_a
        k_r, k_w, c_r, c_w = coef[c, 4], coef[c, 5], coef[c, 6], coef[c, 7]
        if k_r > 0.0 or k_w > 0.0 or c_r > 0.0 or c_w > 0.0:
            l_phi = math.sqrt(phi2)
            eta_phi = math.sqrt(phi_eta2)
            swing = 0.0 if planar else turn * l_phi  # (disks: R does not turn)
            f_k += 2.0 * l_phi * (abs(k_w - k_r) * swing + max(k_r, k_w) * eta_phi)
            f_c += 2.0 * l_phi * (abs(c_w - c_r) * swing + max(c_r, c_w) * eta_phi)
            swing_rate = 0.0 if planar else per_length * l_phi
            g_ek += 2.0 * l_phi * abs(k_w - k_r) * swing_rate
            g_ec += 2.0 * l_phi * abs(c_w - c_r) * swing_rate
            g_ak += 2.0 * l_phi * max(k_r, k_w) * math.sqrt(spin_phi2)
            g_ac += 2.0 * l_phi * max(c_r, c_w) * math.sqrt(spin_phi2)
        sum_k[oa] += f_k
        sum_c[oa] += f_c
        if ob >= 0:
            sum_k[ob] += f_k
            sum_c[ob] += f_c
        if lookahead:
            rate_ek[oa] += g_ek
            rate_ec[oa] += g_ec
            rate_ak[oa] += g_ak
            rate_ac[oa] += g_ac
            if ob >= 0:
                rate_ek[ob] += g_ek
                rate_ec[ob] += g_ec
                rate_ak[ob] += g_ak
                rate_ac[ob] += g_ac
    return True


@njit(inline="always")
def _length(offset, s):
    """|o| [L] of sphere s's offset in its body (0 for a free sphere)."""
    return math.sqrt(offset[s, 0] ** 2 + offset[s, 1] ** 2 + offset[s, 2] ** 2)


@dataclass
class BodyPose:
    """The clumps now, as a certificate's drift takes them: ``sphere_body`` (N,) each
    sphere's body (-1: free), ``offset`` (N, 3) [L] each member's centre in its body's
    frame (zeros for free spheres), ``q`` (B, 4) the bodies' orientations (w, x, y, z),
    ``inv_m`` (B,) [1/M] and ``inv_I`` (B, 3) [1/(M L^2)] their inverse mass and
    principal moments (zeros: fixed, rotation locked; disks: only the third)."""

    sphere_body: np.ndarray
    offset: np.ndarray
    q: np.ndarray
    inv_m: np.ndarray
    inv_I: np.ndarray

    def frames(self, q_ref) -> tuple[np.ndarray, np.ndarray]:
        """:func:`body_frames` from the orientations ``q_ref`` of the estimate to now."""
        return body_frames(np.ascontiguousarray(q_ref, dtype=np.float64),
                           np.ascontiguousarray(self.q, dtype=np.float64),
                           np.ascontiguousarray(self.inv_m, dtype=np.float64),
                           np.ascontiguousarray(self.inv_I, dtype=np.float64))


def cover_limits(keys, known, assumed, nonlinear: bool) -> np.ndarray:
    """The record of covered contacts (sorted ``known`` keys, the overlaps ``assumed``
    for them) per contact of sorted ``keys``: the largest overlap it is covered at (any,
    +inf, unless ``nonlinear``), 0 when it is not in the record: a touching contact is
    uncovered when its overlap exceeds it, as :func:`uncovered_pairs` finds by a merge
    (the engine's pair loops compare with these limits at every step)."""
    known = np.asarray(known, dtype=np.int64)
    if len(known) == 0:
        return np.zeros(len(keys))
    at = np.minimum(np.searchsorted(known, keys), len(known) - 1)
    found = known[at] == keys
    value = np.asarray(assumed, dtype=np.float64)[at] if nonlinear else np.inf
    return np.where(found, value, 0.0)


def merge_cover(known, assumed, keys, overlaps):
    """The record of covered contacts (sorted unique ``known`` keys, overlaps
    ``assumed``) extended by the contacts ``keys`` (unique) at ``overlaps``: (sorted
    keys, overlaps), the larger one for a key in both. A merge (a copy of the record),
    not a sort of it: the record has every covered contact, the extension a few."""
    known = np.asarray(known, dtype=np.int64)
    assumed = np.array(assumed, dtype=np.float64)  # (a copy: raised in place)
    order = np.argsort(keys, kind="stable")
    keys = np.asarray(keys, dtype=np.int64)[order]
    overlaps = np.asarray(overlaps, dtype=np.float64)[order]
    at = np.searchsorted(known, keys)
    found = known[np.minimum(at, len(known) - 1)] == keys if len(known) else np.zeros(
        len(keys), dtype=bool)
    assumed[at[found]] = np.maximum(assumed[at[found]], overlaps[found])
    new = ~found
    return np.insert(known, at[new], keys[new]), np.insert(assumed, at[new], overlaps[new])


@njit(inline="always")
def _not_covered(known, assumed, pos, key, delta, check_overlap):
    """One step of the merge of a sorted contact list with the sorted ``known`` keys
    (from ``pos``): whether the touching contact ``key`` (overlap ``delta``) is missing
    from them or, with ``check_overlap``, covered at a smaller overlap; and the merge's
    new position."""
    while pos < known.shape[0] and known[pos] < key:
        pos += 1
    if pos == known.shape[0] or known[pos] != key:
        return True, pos
    return check_overlap and delta > assumed[pos], pos


@njit(cache=True)
def uncovered_pairs(x, r, pi, pj, periodic_len, known, assumed, check_overlap, move,
                    boundary=0.0):
    """Mask over the pair list (pi, pj), sorted by (i, j), of the closed pairs whose key
    i N + j is not among ``known`` (sorted) or, with ``check_overlap``, whose overlap
    exceeds the one its coefficients ``assumed``: one pass merging the two sorted
    lists. Each pair's overlap is taken ``move[i] + move[j] + boundary`` [L] ahead
    (``move`` (N,) how far each particle moves in the steps looked ahead, ``boundary``
    the walls and the box; zeros: the pairs closed now)."""
    n = r.shape[0]
    mask = np.zeros(pi.shape[0], dtype=np.bool_)
    pos = 0
    periodic = any_periodic(periodic_len)
    for c in range(pi.shape[0]):
        p, q = pi[c], pj[c]
        delta = pair_geometry(x[p, 0], x[p, 1], x[p, 2], x[q, 0], x[q, 1], x[q, 2], r[p], r[q],
                              periodic_len[0], periodic_len[1], periodic_len[2], periodic)[4]
        delta += move[p] + move[q] + boundary
        if delta <= 0.0:
            continue
        key = p * n + q
        mask[c], pos = _not_covered(known, assumed, pos, key, delta, check_overlap)
    return mask


@njit(cache=True)
def uncovered_walls(x, r, wp, ww, wall_point, wall_normal, n_walls, known, assumed,
                    check_overlap, move, boundary=0.0):
    """Mask over the particle-wall list (wp, ww), sorted by (p, w), of the touching
    contacts whose key p n_walls + w is not among ``known`` (sorted; empty: none
    covered) or, with ``check_overlap``, whose overlap exceeds the one ``assumed`` for
    it: one pass merging the two sorted lists, as :func:`uncovered_pairs` (overlaps
    taken ``move[p] + boundary`` ahead)."""
    mask = np.zeros(wp.shape[0], dtype=np.bool_)
    pos = 0
    for c in range(wp.shape[0]):
        p, w = wp[c], ww[c]
        delta = wall_geometry(x[p, 0], x[p, 1], x[p, 2], r[p], wall_point[w, 0],
                              wall_point[w, 1], wall_point[w, 2], wall_normal[w, 0],
                              wall_normal[w, 1], wall_normal[w, 2])[4]
        delta += move[p] + boundary
        if delta <= 0.0:
            continue
        key = p * n_walls + w
        mask[c], pos = _not_covered(known, assumed, pos, key, delta, check_overlap)
    return mask


def _normal_tangential(b_n, b_t, count: int) -> np.ndarray:
    """(b_n, b_t) (count, 2) of the normal and tangential springs or dashpots (arrays,
    or None: none) of ``count`` contacts: what a pair's turn factor and arm term take
    (module doc)."""
    out = np.zeros((count, 2))
    if b_n is not None:
        out[:, 0] = b_n
        if b_t is not None:
            out[:, 1] = b_t
    return out


def _rolling_turn_factor(l_phi2, b_r, b_w):
    """l_phi^2 |b_w - b_r|: the rolling element's |E(n') - E(n)| / |n' - n| (module doc),
    l_phi^2 = 1/I_i + 1/I_j [1/(M L^2)]."""
    return l_phi2 * np.abs(b_w - b_r)


def mesh_added_bound(count, k_n, k_t, c_n, c_t, radius, inv_m, inv_I) -> tuple[float, float]:
    """Bounds on lambda_max(K^) [1/T^2] and lambda_max(C^) [1/T] of a group of
    particle-mesh contacts, whatever their normals: per particle (arrays over the
    particles concerned) ``count`` contacts, each with springs at most ``k_n``, ``k_t``
    [M/T^2] and dashpots at most ``c_n``, ``c_t`` [M/T], its arm at most the ``radius``
    [L], the particle's inverse mass ``inv_m`` and moment of inertia ``inv_I`` (zero:
    fixed, or rotation off). A wall element's mass-scaled matrix gives
    x.E x = k_n (n.u)^2 / m + k_t |P (u / sqrt(m) + a n x w / sqrt(I))|^2 (P the
    tangent projector), at most max(k_n / m, k_t (1/m + a^2 / I)) |x|^2 (Cauchy-Schwarz
    on the tangential part), a bound that does not depend on n; a particle's contacts
    act on it alone, so the group's largest eigenvalue is at most the largest sum over
    one particle's contacts: ``count`` times that."""
    count = np.asarray(count, dtype=np.float64)
    inv_m = np.asarray(inv_m, dtype=np.float64)
    reach = inv_m + np.asarray(radius, dtype=np.float64) ** 2 * np.asarray(inv_I, float)
    lam_k = count * np.maximum(np.asarray(k_n) * inv_m, np.asarray(k_t) * reach)
    lam_c = count * np.maximum(np.asarray(c_n) * inv_m, np.asarray(c_t) * reach)
    return float(lam_k.max(initial=0.0)), float(lam_c.max(initial=0.0))


def added_contacts_bound(particles, added, rotation: bool, bodies=None) -> tuple[float, float]:
    """(A_K [1/T^2], A_C [1/T]): bounds on lambda_max(K^) and lambda_max(C^) of a group
    of ``added`` contacts alone (a ContactSet; with their longest possible arms), the
    largest of their coupled elements with the particles' masses split uniformly among
    the group's contacts (Rayleigh's theorem): springs and dashpots, rolling and
    twisting ones included (with ``rotation``). With ``bodies`` (RigidBodies) a bound
    that holds at any orientation of the bodies (module doc, Clumps): an element's
    |L M_e^-1/2|^2 is at most w = tau^2 + rho_i^2 + rho_j^2 (+ |S_i|^2 + |S_j|^2 with
    rolling and twisting), taken with the owners' shares
    (:func:`demstep.timestep.clumps.owner_mass_shares`, S^2 the share's inverse
    inertia) and rho = |[o]x S| + r |S| >= |[o + r n]x S| for any normal n (o the
    member's arm from its body's centre, r its radius; both norms the same in any
    orientation of the body); times the largest of the element's springs (dashpots).
    Set them with :meth:`StepCertificate.set_added`."""
    if added.n == 0:
        return 0.0, 0.0
    if bodies is None:
        mass = element_mass(particles, added)
        add_k = float(np.max(coupled_element_lambda(added, mass, rotation)))
        add_c = float(np.max(coupled_element_lambda(added.dashpot_springs(), mass, rotation)))
        return add_k, add_c

    mi, Ii, mj, Ij = owner_mass_shares(particles, added, bodies, rotation)
    pair = added.j >= 0
    j = np.maximum(added.j, 0)
    top_i = np.clip(np.linalg.eigvalsh(Ii)[:, -1], 0.0, None)
    top_j = np.where(pair, np.clip(np.linalg.eigvalsh(Ij)[:, -1], 0.0, None), 0.0)

    def reach(side, share, top):  # rho of the side (free spheres: arm 0)
        X = cross_matrix(bodies.arm[side])
        lever = np.clip(np.linalg.eigvalsh(X @ share @ X.transpose(0, 2, 1))[:, -1], 0.0, None)
        return np.sqrt(lever) + particles.r[side] * np.sqrt(top)

    width = (mi + mj + reach(added.i, Ii, top_i) ** 2
             + np.where(pair, reach(j, Ij, top_j) ** 2, 0.0)) * (1.0 + 1e-12)
    rolling = rotation and added.has_rolling
    if rolling:
        width = width + top_i + top_j

    def largest(*coefficients):
        present = [np.zeros(added.n) if c is None else np.asarray(c, dtype=np.float64)
                   for c in coefficients]
        return np.max(present, axis=0)

    springs = largest(added.k_n, added.k_s, *((added.k_r, added.k_w) if rolling else ()))
    dashpots = largest(added.c_n, added.c_t, *((added.c_r, added.c_w) if rolling else ()))
    return float(np.max(width * springs)), float(np.max(width * dashpots))


@dataclass
class StepCertificate:
    """What an 'auto' estimate certified (module doc): ``sigma`` = sigma_c [1/T],
    ``lam_c`` = Lambda_C [1/T], ``add_k`` [1/T^2] and ``add_c`` [1/T] from contacts
    added since; for the drift term, the covered pairs (``pair_i``, ``pair_j``) with
    their reference normals ``normal`` and ``factors`` (P, 8): reference arms [L], the
    springs' and the dashpots' (normal, tangential) coefficients, the
    rolling and twisting turn factors (springs, viscous parts); the covered wall
    contacts (``wall_p``, ``wall_w``) with ``wall_factors`` (W, 3): reference arm,
    k_t, c_t; per particle ``particles`` (N, 3): radius, inverse
    mass and inverse moment of inertia; with clumps, the covered contacts with a member
    (``body_pairs``, ``body_ref``, ``body_coef``: :func:`_body_drift_sums`) and the
    bodies' orientations ``body_q`` (B, 4) at the estimate; ``bounded`` False when the
    drift is not followed (a certificate restored from a checkpoint that did not
    record it)."""

    sigma: float
    lam_c: float
    add_k: float = 0.0
    add_c: float = 0.0
    pair_i: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    pair_j: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    #: per covered pair, 1 for a bond (its arms followed apart too), else 0
    pair_bond: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    normal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    factors: np.ndarray = field(default_factory=lambda: np.zeros((0, 8)))
    bounded: bool = True
    #: what the estimate was made with besides the geometry and the masses
    #: (:meth:`demstep.engine.Simulation.certificate_inputs`: the law's springs and
    #: dashpots, the global damping); a certificate holds for those only
    inputs: np.ndarray = field(default_factory=lambda: np.zeros(0))
    wall_p: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    wall_w: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    wall_factors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    particles: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    body_q: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    body_pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), dtype=np.int64))
    body_ref: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    body_coef: np.ndarray = field(default_factory=lambda: np.zeros((0, 8)))
    #: the dimension of the contacts with a member (disks: their rolling does not turn)
    body_dim: int = 3
    #: the covered particle-mesh contacts: particle ``mesh_p`` (Q,), mesh ``mesh_k``
    #: (Q,) and ``mesh_ref`` (Q, 11), the rows of ``Meshes.cover_ref`` (reference
    #: normal, arm, springs, dashpots, overlap covered, the particle's inverse mass and
    #: moment of inertia); their drift is measured at every step by the kernels
    #: (:mod:`demstep.kernels.meshes`), not bounded ahead
    mesh_p: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    mesh_k: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    mesh_ref: np.ndarray = field(default_factory=lambda: np.zeros((0, 11)))
    #: bounds on lambda_max(K^) [1/T^2] and lambda_max(C^) [1/T] of the mesh contacts
    #: added since the estimate (:func:`mesh_added_bound`; Weyl's inequality adds them)
    mesh_add_k: float = 0.0
    mesh_add_c: float = 0.0

    @property
    def has_bodies(self) -> bool:
        """Whether the estimate was made with clumps (the drift then needs their pose:
        :meth:`drift`'s ``bodies``)."""
        return self.body_q.shape[0] > 0

    @classmethod
    def from_estimate(cls, sigma: float, lam_c: float, contacts, inv_m, inv_I,
                      bounded: bool = True, inputs=(), radius=None,
                      bond=None, sphere_body=None, body_q=None) -> "StepCertificate":
        """The certificate of an estimate: its certified root ``sigma``, ``lam_c`` and the
        covered ``contacts`` (a ContactSet at the estimate's geometry: pairs have
        ``j`` >= 0, their rolling and twisting springs count in the drift; walls
        ``j`` < 0 and their wall in ``wall``) with the particles' inverse masses and
        inverse moments of inertia (zero for fixed particles, and for rotations when
        rotation is off) and radii ``radius`` (N,) [L] (the arms now follow from them),
        ``bond`` (C,) true for the elements that are bonds (None: none), made with
        ``inputs`` (:attr:`inputs`). With clumps, ``sphere_body`` (N,) each sphere's body
        (-1: free) and ``body_q`` (B, 4) the bodies' orientations: the contacts with a
        member are followed by :func:`_body_drift_sums`, the others as without."""
        if body_q is not None and len(body_q) and bounded:
            return cls._with_bodies(sigma, lam_c, contacts, inv_m, inv_I, inputs, radius,
                                    bond, np.asarray(sphere_body, dtype=np.int64), body_q)
        cert = cls(float(sigma), float(lam_c), bounded=bounded,
                   inputs=np.array(inputs, dtype=np.float64).reshape(-1))
        if not bounded or contacts.n == 0:
            return cert
        if radius is None:
            raise ValueError("from_estimate: the radii are needed to follow the arms")
        cert.particles = np.ascontiguousarray(np.stack(
            [np.asarray(radius, dtype=np.float64), np.asarray(inv_m, dtype=np.float64),
             np.asarray(inv_I, dtype=np.float64)], axis=1))
        pair = contacts.j >= 0
        i = np.ascontiguousarray(contacts.i[pair], dtype=np.int64)
        j = np.ascontiguousarray(contacts.j[pair], dtype=np.int64)
        n = len(i)
        c_n = None if contacts.c_n is None else contacts.c_n[pair]
        c_t = None if contacts.c_t is None else contacts.c_t[pair]
        roll = np.zeros((n, 2))
        if contacts.dim == 3 and contacts.has_rolling:
            l_phi2 = inv_I[i] + inv_I[j]  # zero when rotation is off
            roll[:, 0] = _rolling_turn_factor(l_phi2, contacts.k_r[pair], contacts.k_w[pair])
            roll[:, 1] = _rolling_turn_factor(l_phi2, contacts.c_r[pair], contacts.c_w[pair])
        cert.pair_i, cert.pair_j = i, j
        cert.pair_bond = (np.zeros(n, dtype=np.int64) if bond is None
                          else np.asarray(bond, dtype=np.int64)[pair])
        cert.normal = np.ascontiguousarray(contacts.normal[pair], dtype=np.float64)
        cert.factors = np.ascontiguousarray(np.concatenate(
            [contacts.arm_i[pair, None], contacts.arm_j[pair, None],
             _normal_tangential(contacts.k_n[pair], contacts.k_s[pair], n),
             _normal_tangential(c_n, c_t, n), roll], axis=1), dtype=np.float64)
        wall = ~pair
        if wall.any():
            if contacts.wall is None:
                raise ValueError("from_estimate: wall contacts without their walls")
            m = int(wall.sum())
            cert.wall_p = np.ascontiguousarray(contacts.i[wall], dtype=np.int64)
            cert.wall_w = np.ascontiguousarray(contacts.wall[wall], dtype=np.int64)
            cert.wall_factors = np.ascontiguousarray(np.stack(
                [contacts.arm_i[wall],
                 _normal_tangential(contacts.k_n[wall], contacts.k_s[wall], m)[:, 1],
                 _normal_tangential(None if c_n is None else contacts.c_n[wall],
                                    None if c_t is None else contacts.c_t[wall], m)[:, 1]],
                axis=1), dtype=np.float64)
        return cert

    @classmethod
    def _with_bodies(cls, sigma, lam_c, contacts, inv_m, inv_I, inputs, radius, bond,
                     sphere_body, body_q) -> "StepCertificate":
        """:meth:`from_estimate` with clumps: the contacts without a member as without
        clumps, those with one in the ``body_*`` arrays."""
        if radius is None:
            raise ValueError("from_estimate: the radii are needed to follow the arms")
        bond = np.zeros(contacts.n, dtype=bool) if bond is None else np.asarray(bond, bool)
        pair = contacts.j >= 0
        j = np.maximum(contacts.j, 0)
        member = (sphere_body[contacts.i] >= 0) | (pair & (sphere_body[j] >= 0))
        cert = cls.from_estimate(sigma, lam_c, contacts.subset(~member), inv_m, inv_I,
                                 inputs=inputs, radius=radius, bond=bond[~member])
        cert.particles = np.ascontiguousarray(np.stack(
            [np.asarray(radius, dtype=np.float64), np.asarray(inv_m, dtype=np.float64),
             np.asarray(inv_I, dtype=np.float64)], axis=1))
        cert.body_q = np.array(body_q, dtype=np.float64).reshape(-1, 4)
        cert.body_dim = int(contacts.dim)
        near = contacts.subset(member)
        k = near.n
        wall = np.full(k, -1, dtype=np.int64)
        if near.wall is not None:
            wall = np.where(near.j < 0, near.wall, -1).astype(np.int64)
        cert.body_pairs = np.ascontiguousarray(np.stack(
            [near.i, np.where(near.j >= 0, near.j, -1), wall,
             bond[member].astype(np.int64)], axis=1), dtype=np.int64).reshape(k, 4)
        ref = np.zeros((k, 5))
        ref[:, 0], ref[:, 1] = near.arm_i, near.arm_j
        ref[:, 2:2 + near.dim] = near.normal
        cert.body_ref = ref
        cert.body_coef = np.ascontiguousarray(np.concatenate(
            [_normal_tangential(near.k_n, near.k_s, k), _normal_tangential(near.c_n, near.c_t, k),
             _normal_tangential(near.k_r, near.k_w, k), _normal_tangential(near.c_r, near.c_w, k)],
            axis=1), dtype=np.float64)
        return cert

    def drift(self, x, periodic_len, walls=None, bodies: BodyPose | None = None
              ) -> tuple[float, float]:
        """(D_K [1/T^2], D_C [1/T]): D(sigma) <= D_K + sigma D_C for the positions ``x``
        (N, 3) now and ``walls`` = (points, unit normals) (n_walls, 3) of the walls now
        (needed when wall contacts are covered) and, with clumps, their pose now
        ``bodies``; zero when not ``bounded``."""
        if not self.bounded or (len(self.pair_i) == 0 and len(self.wall_p) == 0
                                and len(self.body_pairs) == 0):
            return 0.0, 0.0
        x = np.ascontiguousarray(x, dtype=np.float64)
        part = self.particles
        size = x.shape[0] + len(self.body_q)
        sum_k = np.zeros(size)
        sum_c = np.zeros(size)
        if len(self.body_pairs):
            none = np.zeros(0)
            if not self._body_sums(x, periodic_len, walls, bodies, sum_k, sum_c, False, 0.0,
                                   0.0, none, none, none, none):
                return math.inf, math.inf
        _drift_sums(x, self.pair_i, self.pair_j, self.pair_bond, self.normal, self.factors,
                    part, np.asarray(periodic_len, dtype=np.float64), sum_k, sum_c)
        if len(self.wall_p):
            if walls is None:
                raise ValueError("drift: the walls are needed (wall contacts are covered)")
            point, normal = (np.ascontiguousarray(a, dtype=np.float64) for a in walls)
            _wall_drift_sums(x, self.wall_p, self.wall_w, point, normal, self.wall_factors,
                             part, sum_k, sum_c)
        return float(sum_k.max()), float(sum_c.max())

    def _body_sums(self, x, periodic_len, walls, bodies, *sums) -> bool:
        """:func:`_body_drift_sums` of the clumps' contacts at ``x`` and the ``bodies``'
        pose now (False: coincident centres, no bound)."""
        if bodies is None:
            raise ValueError("drift: the bodies' pose is needed (clumps are covered)")
        point, normal = ((np.zeros((1, 3)), np.zeros((1, 3))) if walls is None else
                         (np.ascontiguousarray(a, dtype=np.float64) for a in walls))
        frames, scalars = bodies.frames(self.body_q)
        cache = getattr(self, "_body_norms", None)
        if cache is None or cache.shape[0] != len(self.body_pairs):
            cache = self._body_norms = np.full((len(self.body_pairs), 2), np.nan)
        return _body_drift_sums(x, self.body_pairs, self.body_ref, self.body_coef, cache,
                                self.particles, np.asarray(bodies.sphere_body, dtype=np.int64),
                                np.ascontiguousarray(bodies.offset, dtype=np.float64), frames,
                                scalars, point, normal,
                                np.asarray(periodic_len, dtype=np.float64), self.body_dim == 2,
                                *sums)

    def body_budgets(self, sigma: float, x, periodic_len, walls, bodies: BodyPose,
                     e_cap: float, angle_cap: float) -> tuple[float, float]:
        """With clumps: (E [L], Theta): how far the pairs' ends (and the walls) may move
        relative to each other from the positions ``x`` now, at most ``e_cap``, and the
        bodies turn from their pose ``bodies`` now (|dR - I|), at most ``angle_cap``,
        with the step 2 / ``sigma`` still certified at every state reached: the drift
        there is at most D_up + E G_E + Theta G_Theta (:func:`_lookahead_sums`,
        :func:`_body_drift_sums` with its lookahead), and half the room left goes to
        each. (0, 0) when even D_up leaves no room."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        size = x.shape[0] + len(self.body_q)
        up_k, up_c, rate_ek, rate_ec, rate_ak, rate_ac = (np.zeros(size) for _ in range(6))
        lengths = np.asarray(periodic_len, dtype=np.float64)
        if len(self.pair_i):
            _lookahead_sums(x, self.pair_i, self.pair_j, self.pair_bond, self.normal,
                            self.factors, self.particles, lengths, float(e_cap), up_k, up_c,
                            rate_ek, rate_ec)
        if len(self.wall_p):
            point, normal = (np.ascontiguousarray(a, dtype=np.float64) for a in walls)
            _wall_lookahead_sums(x, self.wall_p, self.wall_w, point, normal, self.wall_factors,
                                 self.particles, up_k, up_c, rate_ek, rate_ec)
        if not self._body_sums(x, periodic_len, walls, bodies, up_k, up_c, True, float(e_cap),
                               float(angle_cap), rate_ek, rate_ec, rate_ak, rate_ac):
            return 0.0, 0.0
        slack = sigma * sigma - self.bound(sigma, (float(up_k.max()), float(up_c.max())))
        if not slack > 0.0:
            return 0.0, 0.0
        share = 0.5 * (1.0 - 1e-9) * slack  # (a relative margin for the rounding)
        rate_e = float(rate_ek.max()) + sigma * float(rate_ec.max())
        rate_a = float(rate_ak.max()) + sigma * float(rate_ac.max())
        return (float(min(e_cap, share / rate_e)) if rate_e > 0.0 else float(e_cap),
                float(min(angle_cap, share / rate_a)) if rate_a > 0.0 else float(angle_cap))

    def drift_budget(self, sigma: float, x, periodic_len, walls=None,
                     e_cap: float = math.inf, reserved: float = 0.0) -> float:
        """How far [L] the pairs' ends (and the walls) may move relative to each other
        from the positions ``x`` now, at most ``e_cap``, with the step 2 / ``sigma``
        still certified at every position reached (:func:`_lookahead_sums`): the
        largest E with sigma^2 >= :meth:`bound` at the drift D_up + ``reserved`` + E G
        (``reserved`` [1/T^2]: the part of the drift left to the mesh contacts, which
        the kernels measure). 0 when even D_up does not leave room; +inf with nothing
        covered."""
        if not self.bounded or self.has_bodies:  # (clumps: a check at every step)
            return 0.0
        if len(self.pair_i) == 0 and len(self.wall_p) == 0:
            return math.inf if self.certifies(sigma, (reserved, 0.0)) else 0.0
        x = np.ascontiguousarray(x, dtype=np.float64)
        up_k, up_c, rate_k, rate_c = (np.zeros(x.shape[0]) for _ in range(4))
        _lookahead_sums(x, self.pair_i, self.pair_j, self.pair_bond, self.normal, self.factors,
                        self.particles, np.asarray(periodic_len, dtype=np.float64),
                        float(e_cap), up_k, up_c, rate_k, rate_c)
        if len(self.wall_p):
            point, normal = (np.ascontiguousarray(a, dtype=np.float64) for a in walls)
            _wall_lookahead_sums(x, self.wall_p, self.wall_w, point, normal, self.wall_factors,
                                 self.particles, up_k, up_c, rate_k, rate_c)
        slack = sigma * sigma - self.bound(sigma, (float(up_k.max(initial=0.0)) + reserved,
                                                   float(up_c.max(initial=0.0))))
        if not slack > 0.0:
            return 0.0
        rate = float(rate_k.max(initial=0.0)) + sigma * float(rate_c.max(initial=0.0))
        # (a relative margin for the rounding of the sums)
        return float(min(e_cap, (1.0 - 1e-9) * slack / rate)) if rate > 0.0 else float(e_cap)

    @property
    def slope(self) -> float:
        """The slope [1/T] the covered contacts' lambda_max(sigma C^ + K^) grows with at
        most: min(Lambda_C, sigma_c), as lambda_max(C^) <= sigma_c (sigma_c
        lambda_max(C^) <= lambda_max(sigma_c C^ + K^) <= sigma_c^2, K^ being positive
        semi-definite): a step above sigma_c's keeps its room whatever Lambda_C."""
        return min(self.lam_c, self.sigma)

    def bound(self, sigma: float, drift=(0.0, 0.0), added=None) -> float:
        """Upper bound on lambda_max(sigma C^ + K^) [1/T^2] of the covered and added
        contacts now, for the drift (D_K, D_C) of :meth:`drift`; ``added`` (A_K, A_C):
        with these bounds of the added contacts in place of the certificate's."""
        d_k, d_c = drift
        add_k, add_c = (self.add_k, self.add_c) if added is None else added
        add_k, add_c = add_k + self.mesh_add_k, add_c + self.mesh_add_c
        return (self.sigma ** 2 + max(sigma - self.sigma, 0.0) * self.slope
                + sigma * (add_c + d_c) + add_k + d_k)

    def certifies(self, sigma: float, drift=(0.0, 0.0)) -> bool:
        """Whether the step 2 / ``sigma`` is certified (its square bounds the bound)."""
        return sigma * sigma >= self.bound(sigma, drift)

    def smallest_sigma(self, drift=(0.0, 0.0)) -> float:
        """The smallest sigma [1/T] that :meth:`certifies`: the larger root of
        sigma^2 = :meth:`bound` (at least sigma_c, below which the bound exceeds
        sigma^2), nudged up past rounding."""
        d_k, d_c = drift
        slope = self.slope + self.add_c + self.mesh_add_c + d_c
        const = (self.sigma ** 2 - self.sigma * self.slope + self.add_k + self.mesh_add_k
                 + d_k)
        s = max(0.5 * (slope + math.sqrt(max(slope * slope + 4.0 * const, 0.0))), self.sigma)
        while not self.certifies(s, drift):
            s = math.nextafter(s, math.inf)
        return s

    def renumber(self, order, inv):
        """The particles renumbered (row k now was row ``order[k]``; ``inv`` the
        inverse): the pairs' and wall contacts' indices and the per-particle rows (a
        pair's normal keeps its direction from pair_i to pair_j)."""
        if len(self.pair_i):
            self.pair_i, self.pair_j = inv[self.pair_i], inv[self.pair_j]
        if len(self.wall_p):
            self.wall_p = inv[self.wall_p]
        if len(self.body_pairs):
            moved = self.body_pairs.copy()
            moved[:, 0] = inv[moved[:, 0]]
            pair = moved[:, 1] >= 0
            moved[pair, 1] = inv[moved[pair, 1]]
            self.body_pairs = moved
        if len(self.particles):
            self.particles = np.ascontiguousarray(self.particles[order])
        if len(self.mesh_p):
            self.mesh_p = inv[self.mesh_p]

    def remove(self, keep, inv):
        """Particles taken out (``keep`` the rows kept, in order; ``inv`` each old row's
        new one, -1 when removed): the covered contacts with a removed particle are
        dropped, the others renamed. The certificate still holds: what remains is a
        principal submatrix of the scaled matrices it bounded (one element fewer for
        each dropped contact, each positive semi-definite), and by Cauchy's interlacing
        lambda_max(sigma C^ + K^) of a principal submatrix is at most the whole's."""
        def rows(name, ok):
            setattr(self, name, np.ascontiguousarray(getattr(self, name)[ok]))

        if len(self.pair_i):
            ok = (inv[self.pair_i] >= 0) & (inv[self.pair_j] >= 0)
            self.pair_i = np.ascontiguousarray(inv[self.pair_i[ok]])
            self.pair_j = np.ascontiguousarray(inv[self.pair_j[ok]])
            for name in ("pair_bond", "normal", "factors"):
                rows(name, ok)
        if len(self.wall_p):
            ok = inv[self.wall_p] >= 0
            self.wall_p = np.ascontiguousarray(inv[self.wall_p[ok]])
            rows("wall_w", ok)
            rows("wall_factors", ok)
        if len(self.mesh_p):
            ok = inv[self.mesh_p] >= 0
            self.mesh_p = np.ascontiguousarray(inv[self.mesh_p[ok]])
            rows("mesh_k", ok)
            rows("mesh_ref", ok)
        if len(self.body_pairs):  # (clumps are not removed: their drift is not followed here)
            self.bounded = False
        if len(self.particles):
            self.particles = np.ascontiguousarray(self.particles[keep])

    def extend(self, radius, inv_m, inv_I):
        """Particles appended after the last ones (their radii [L], inverse masses and
        inverse moments of inertia, as :meth:`from_estimate` takes them): the
        certificate still holds. The matrices it bounded, with rows and columns of
        zeros for particles in none of its contacts, have the same eigenvalues and
        zeros; the new particles' contacts are added as any contact the estimate did
        not cover (:func:`added_contacts_bound`, or a new estimate)."""
        if len(self.particles):
            rows = np.stack([np.asarray(radius, dtype=np.float64),
                             np.asarray(inv_m, dtype=np.float64),
                             np.asarray(inv_I, dtype=np.float64)], axis=1)
            self.particles = np.ascontiguousarray(np.concatenate([self.particles, rows]))

    def set_added(self, k: float, c: float):
        """All the contacts added since the estimate: bounds on lambda_max(K^) [1/T^2]
        and lambda_max(C^) [1/T] of them together (Weyl's inequality adds them to the
        certificate's bound)."""
        self.add_k = float(k)
        self.add_c = float(c)

    # ---------------------------------------------------------------- checkpoints
    def state(self) -> dict:
        return {"ts_cert": np.array([self.sigma, self.lam_c, self.add_k, self.add_c,
                                     float(self.bounded), self.mesh_add_k, self.mesh_add_c]),
                "ts_cert_meshes": np.stack([self.mesh_p, self.mesh_k]),
                "ts_cert_mesh_ref": self.mesh_ref,
                "ts_cert_pairs": np.stack([self.pair_i, self.pair_j, self.pair_bond]),
                "ts_cert_normal": self.normal,
                "ts_cert_coefficients": self.factors,
                "ts_cert_walls": np.stack([self.wall_p, self.wall_w]),
                "ts_cert_wall_factors": self.wall_factors,
                "ts_cert_particles": self.particles,
                "ts_cert_inputs": self.inputs,
                "ts_cert_body_q": self.body_q,
                "ts_cert_body_pairs": self.body_pairs,
                "ts_cert_body_ref": self.body_ref,
                "ts_cert_body_coef": self.body_coef,
                "ts_cert_body_dim": np.array([self.body_dim])}

    def made_with(self, inputs) -> bool:
        """Whether the estimate was made with these ``inputs`` (:attr:`inputs`; a
        certificate restored from a checkpoint that did not record them: False)."""
        return np.array_equal(self.inputs, np.asarray(inputs, dtype=np.float64).reshape(-1))

    @classmethod
    def from_state(cls, data: dict) -> "StepCertificate":
        """Inverse of :meth:`state`. A checkpoint from before the arms were followed, or
        from before the factors held the springs themselves (``ts_cert_factors``, their
        (max, |difference|)), gives a certificate without inputs (:meth:`made_with` is
        False: the run estimates anew)."""
        values = [float(v) for v in np.asarray(data["ts_cert"]).reshape(-1)]
        if (len(values) < 5 or "ts_cert_particles" not in data
                or "ts_cert_coefficients" not in data):
            return cls(values[0], values[1], bounded=False)
        pairs = np.asarray(data["ts_cert_pairs"], dtype=np.int64)
        walls = np.asarray(data["ts_cert_walls"], dtype=np.int64).reshape(2, -1)
        inputs = np.asarray(data.get("ts_cert_inputs", np.zeros(0)), dtype=np.float64)

        def rows(key, width):
            return np.ascontiguousarray(np.asarray(data[key], dtype=np.float64)
                                        .reshape(-1, width))

        cert = cls(values[0], values[1], values[2], values[3],
                   np.ascontiguousarray(pairs[0]), np.ascontiguousarray(pairs[1]),
                   np.ascontiguousarray(pairs[2]),
                   np.ascontiguousarray(data["ts_cert_normal"], dtype=np.float64),
                   rows("ts_cert_coefficients", 8), bool(values[4]), inputs.reshape(-1),
                   np.ascontiguousarray(walls[0]), np.ascontiguousarray(walls[1]),
                   rows("ts_cert_wall_factors", 3), rows("ts_cert_particles", 3))
        if "ts_cert_body_q" in data:
            cert.body_q = rows("ts_cert_body_q", 4)
            cert.body_pairs = np.ascontiguousarray(
                np.asarray(data["ts_cert_body_pairs"], dtype=np.int64).reshape(-1, 4))
            cert.body_ref = rows("ts_cert_body_ref", 5)
            cert.body_coef = rows("ts_cert_body_coef", 8)
            cert.body_dim = int(np.asarray(data["ts_cert_body_dim"]).reshape(-1)[0])
        if "ts_cert_meshes" in data:  # (older checkpoints: no mesh contacts covered)
            meshes = np.asarray(data["ts_cert_meshes"], dtype=np.int64).reshape(2, -1)
            cert.mesh_p = np.ascontiguousarray(meshes[0])
            cert.mesh_k = np.ascontiguousarray(meshes[1])
            cert.mesh_ref = rows("ts_cert_mesh_ref", 11)
        if len(values) >= 7:
            cert.mesh_add_k, cert.mesh_add_c = values[5], values[6]
        return cert
