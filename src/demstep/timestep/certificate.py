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
  left side is convex in sigma with slope at most Lambda_C, and does not decrease);
* A_K + sigma A_C bounds the contacts added since (:meth:`StepCertificate.add`; each
  group by the largest of its coupled elements, the particles' masses split among the
  group's contacts, Rayleigh's theorem on the group alone, and Weyl's inequality for
  the sum: :func:`added_contacts_bound`, rolling and twisting springs included);
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
With clumps the members' arms turn with their bodies, which this bound does not
follow: their certificate has no drift term (``bounded`` False).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from demstep._numba import njit
from demstep.contact.geometry import (any_periodic, contact_arms, image_count, pair_geometry,
                                     wall_geometry)


#: relative margin added to the root :func:`_turn_factor` finds (its Newton iterates
#: approach the root from above in exact arithmetic; this covers their rounding), and
#: the most iterations it takes (an early stop leaves a larger, still valid, bound)
TURN_FACTOR_MARGIN = 1e-12
TURN_FACTOR_ITERATIONS = 30


@njit(inline="always")
def _turn_factor(trans, rot, b_n, b_t, planar):
    """lambda_max(M) of the module doc, an upper bound on |E(n') - E(n)| / |n' - n| for
    a turn at the arms now: ``trans`` = tau^2 = 1/m_i + 1/m_j, ``rot`` = rho^2, the
    normal and tangential coefficients ``b_n``, ``b_t`` (springs or dashpots); for
    disks (``planar``) the 2 x 2 block's, in closed form. In 3D the largest root of
    det(M - x) = -(x^3 - A x^2 - (B^2 + C^2) x + A C^2), which is convex and increasing
    from A (<= the root) on: Newton's iterates from the upper bound b_t rho l + A
    decrease to it and stay above it, until a step is below 1e-14 of it, plus
    :data:`TURN_FACTOR_MARGIN`."""
    big_a = abs(b_n - b_t) * trans
    b2 = b_t * b_t * trans * rot
    if planar:
        return (0.5 * big_a + math.sqrt(0.25 * big_a * big_a + b2)) * (1.0 + TURN_FACTOR_MARGIN)
    c2 = b_t * b_t * rot * rot
    x = b_t * math.sqrt(rot * (trans + rot)) + big_a
    for _ in range(TURN_FACTOR_ITERATIONS):
        slope = x * (3.0 * x - 2.0 * big_a) - (b2 + c2)
        value = x * (x * (x - big_a) - (b2 + c2)) + big_a * c2
        if slope <= 0.0 or value <= 0.0:
            break
        step = value / slope
        x -= step
        if step <= 1e-14 * x:
            break
    return x * (1.0 + TURN_FACTOR_MARGIN)


@njit(cache=True, inline="always")
def _pair_turn(x, a, b, normal_ref, c, periodic_len):
    """(|d|, turn) of pair c = (a, b): its centre distance [L] now (nearest periodic
    image) and |d/|d| - n_ref| [-], how far its normal turned from ``normal_ref[c]``
    (2, a half turn, for coincident centres: any normal)."""
    d0 = x[b, 0] - x[a, 0]
    d1 = x[b, 1] - x[a, 1]
    d2 = x[b, 2] - x[a, 2]
    d0 -= periodic_len[0] * image_count(d0, periodic_len[0])
    d1 -= periodic_len[1] * image_count(d1, periodic_len[1])
    d2 -= periodic_len[2] * image_count(d2, periodic_len[2])
    dist = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
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


def added_contacts_bound(particles, added, rotation: bool, bodies=None) -> tuple[float, float]:
    """(A_K [1/T^2], A_C [1/T]): bounds on lambda_max(K^) and lambda_max(C^) of a group
    of ``added`` contacts alone (a ContactSet; with their longest possible arms), the
    largest of their coupled elements with the particles' masses split uniformly among
    the group's contacts (Rayleigh's theorem): springs and dashpots, rolling and
    twisting ones included (with ``rotation``). With ``bodies`` (RigidBodies) the
    elements of :func:`demstep.timestep.bodies.body_element_matrices`. Add them with
    :meth:`StepCertificate.add`."""
    if added.n == 0:
        return 0.0, 0.0
    if bodies is None:
        from demstep.timestep.elements import coupled_element_lambda
        from demstep.timestep.mass_split import element_mass

        mass = element_mass(particles, added)
        add_k = float(np.max(coupled_element_lambda(added, mass, rotation)))
        add_c = float(np.max(coupled_element_lambda(added.dashpot_springs(), mass, rotation)))
        return add_k, add_c
    from demstep.timestep.bodies import body_element_matrices

    W, D, G = body_element_matrices(particles, added, bodies, rotation)
    w, V = np.linalg.eigh(W)
    Wh = np.einsum("cij,cj,ckj->cik", V, np.sqrt(np.clip(w, 0.0, None)), V)
    add_k = float(np.linalg.eigvalsh(Wh @ D @ Wh)[:, -1].max())
    add_c = float(np.linalg.eigvalsh(Wh @ G @ Wh)[:, -1].max())
    return add_k, add_c


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
    mass and inverse moment of inertia; ``bounded`` False when the drift is not
    followed (clumps)."""

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

    @classmethod
    def from_estimate(cls, sigma: float, lam_c: float, contacts, inv_m, inv_I,
                      bounded: bool = True, inputs=(), radius=None,
                      bond=None) -> "StepCertificate":
        """The certificate of an estimate: its certified root ``sigma``, ``lam_c`` and the
        covered ``contacts`` (a ContactSet at the estimate's geometry: pairs have
        ``j`` >= 0, their rolling and twisting springs count in the drift; walls
        ``j`` < 0 and their wall in ``wall``) with the particles' inverse masses and
        inverse moments of inertia (zero for fixed particles, and for rotations when
        rotation is off) and radii ``radius`` (N,) [L] (the arms now follow from them),
        ``bond`` (C,) true for the elements that are bonds (None: none), made with
        ``inputs`` (:attr:`inputs`)."""
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

    def drift(self, x, periodic_len, walls=None) -> tuple[float, float]:
        """(D_K [1/T^2], D_C [1/T]): D(sigma) <= D_K + sigma D_C for the positions ``x``
        (N, 3) now and ``walls`` = (points, unit normals) (n_walls, 3) of the walls now
        (needed when wall contacts are covered); zero when not ``bounded``."""
        if not self.bounded or (len(self.pair_i) == 0 and len(self.wall_p) == 0):
            return 0.0, 0.0
        x = np.ascontiguousarray(x, dtype=np.float64)
        part = self.particles
        sum_k = np.zeros(x.shape[0])
        sum_c = np.zeros(x.shape[0])
        _drift_sums(x, self.pair_i, self.pair_j, self.pair_bond, self.normal, self.factors,
                    part, np.asarray(periodic_len, dtype=np.float64), sum_k, sum_c)
        if len(self.wall_p):
            if walls is None:
                raise ValueError("drift: the walls are needed (wall contacts are covered)")
            point, normal = (np.ascontiguousarray(a, dtype=np.float64) for a in walls)
            _wall_drift_sums(x, self.wall_p, self.wall_w, point, normal, self.wall_factors,
                             part, sum_k, sum_c)
        return float(sum_k.max()), float(sum_c.max())

    def drift_budget(self, sigma: float, x, periodic_len, walls=None,
                     e_cap: float = math.inf) -> float:
        """How far [L] the pairs' ends (and the walls) may move relative to each other
        from the positions ``x`` now, at most ``e_cap``, with the step 2 / ``sigma``
        still certified at every position reached (:func:`_lookahead_sums`): the
        largest E with sigma^2 >= :meth:`bound` at the drift D_up + E G. 0 when even
        D_up does not leave room; +inf with nothing covered."""
        if not self.bounded:
            return 0.0
        if len(self.pair_i) == 0 and len(self.wall_p) == 0:
            return math.inf if self.certifies(sigma) else 0.0
        x = np.ascontiguousarray(x, dtype=np.float64)
        up_k, up_c, rate_k, rate_c = (np.zeros(x.shape[0]) for _ in range(4))
        _lookahead_sums(x, self.pair_i, self.pair_j, self.pair_bond, self.normal, self.factors,
                        self.particles, np.asarray(periodic_len, dtype=np.float64),
                        float(e_cap), up_k, up_c, rate_k, rate_c)
        if len(self.wall_p):
            point, normal = (np.ascontiguousarray(a, dtype=np.float64) for a in walls)
            _wall_lookahead_sums(x, self.wall_p, self.wall_w, point, normal, self.wall_factors,
                                 self.particles, up_k, up_c, rate_k, rate_c)
        slack = sigma * sigma - self.bound(sigma, (float(up_k.max()), float(up_c.max())))
        if not slack > 0.0:
            return 0.0
        rate = float(rate_k.max()) + sigma * float(rate_c.max())
        # (a relative margin for the rounding of the sums)
        return float(min(e_cap, (1.0 - 1e-9) * slack / rate)) if rate > 0.0 else float(e_cap)

    def bound(self, sigma: float, drift=(0.0, 0.0)) -> float:
        """Upper bound on lambda_max(sigma C^ + K^) [1/T^2] of the covered and added
        contacts now, for the drift (D_K, D_C) of :meth:`drift`."""
        d_k, d_c = drift
        return (self.sigma ** 2 + max(sigma - self.sigma, 0.0) * self.lam_c
                + sigma * (self.add_c + d_c) + self.add_k + d_k)

    def certifies(self, sigma: float, drift=(0.0, 0.0)) -> bool:
        """Whether the step 2 / ``sigma`` is certified (its square bounds the bound)."""
        return sigma * sigma >= self.bound(sigma, drift)

    def smallest_sigma(self, drift=(0.0, 0.0)) -> float:
        """The smallest sigma [1/T] that :meth:`certifies`: the larger root of
        sigma^2 = :meth:`bound` (at least sigma_c, below which the bound exceeds
        sigma^2), nudged up past rounding."""
        d_k, d_c = drift
        slope = self.lam_c + self.add_c + d_c
        const = self.sigma ** 2 - self.sigma * self.lam_c + self.add_k + d_k
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
        if len(self.particles):
            self.particles = np.ascontiguousarray(self.particles[order])

    def add(self, k: float, c: float):
        """Contacts added since the estimate: their group bound k + sigma c."""
        self.add_k += float(k)
        self.add_c += float(c)

    # ---------------------------------------------------------------- checkpoints
    def state(self) -> dict:
        return {"ts_cert": np.array([self.sigma, self.lam_c, self.add_k, self.add_c,
                                     float(self.bounded)]),
                "ts_cert_pairs": np.stack([self.pair_i, self.pair_j, self.pair_bond]),
                "ts_cert_normal": self.normal,
                "ts_cert_coefficients": self.factors,
                "ts_cert_walls": np.stack([self.wall_p, self.wall_w]),
                "ts_cert_wall_factors": self.wall_factors,
                "ts_cert_particles": self.particles,
                "ts_cert_inputs": self.inputs}

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

        return cls(values[0], values[1], values[2], values[3],
                   np.ascontiguousarray(pairs[0]), np.ascontiguousarray(pairs[1]),
                   np.ascontiguousarray(pairs[2]),
                   np.ascontiguousarray(data["ts_cert_normal"], dtype=np.float64),
                   rows("ts_cert_coefficients", 8), bool(values[4]), inputs.reshape(-1),
                   np.ascontiguousarray(walls[0]), np.ascontiguousarray(walls[1]),
                   rows("ts_cert_wall_factors", 3), rows("ts_cert_particles", 3))
