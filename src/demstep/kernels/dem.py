"""Explicit DEM kernels: contact forces, wall forces, central-difference update, ledger.

All arrays are 3D (disks live in the plane z = 0 with rotation about z), float64,
C-contiguous. :func:`advance` runs whole steps inside compiled code until a stop
condition (step budget, neighbour-list expiry, divergence) and returns to Python.

The order of a step is documented once, in :mod:`demstep.engine`; :func:`advance`
numbers its stages the same way. The energy ledger's work and dissipation terms use
the trapezoidal rule over [t - dt, t] (second order, exact for constant forces).

Slip increments use the lagged half-step velocities v(t - dt/2) (so du = x(t) - x(t-dt)
at the contact point); damping forces likewise use v(t - dt/2), the form for which
the paper's eq. 28 holds.
"""

from __future__ import annotations

import math

import numpy as np
from numba import uint64 as _U

from demstep._numba import CONTRACT, compile_parallel_and_serial, njit, prange, with_globals as _with_globals
from demstep.contact.geometry import any_periodic, pair_geometry, wall_geometry
from demstep.contact.laws import needs_r_star as law_needs_r_star, normal_force
from demstep.kernels.clumps import body_step, body_step_serial
from demstep.kernels.bonds import bond_forces
from demstep.kernels.integration import moved_since_build, step_weights, store_step_terms
from demstep.kernels.meshes import mesh_forces, mesh_forces_serial, move_meshes
from demstep.kernels.response import coulomb_dashpot, contact_response
from demstep.kernels.rolling import (  # noqa: F401  (ROLL_*: the history's columns, by name)
    ROLL_ENERGY, ROLL_M, ROLL_TWIST, ROLL_VISCOUS, rolling_contact,
)

from demstep.energy import (  # the ledger's layout and sums are the energy module's
    A_APPLIED, A_BODY, A_BOND_BROKEN, A_BOX, A_DASHPOT, A_FRICTION, A_GLOBAL, A_INITIAL, A_LOCAL,
    A_ROLLING, A_ROLLING_VISCOUS, A_WALLS, E_KIN_R, E_KIN_T, E_STRAIN_BOND, E_STRAIN_N, E_STRAIN_R,
    E_STRAIN_T, runaway_reference, update_peaks,
)


# stop reasons returned by advance()
STOP_DONE, STOP_REBUILD, STOP_NONFINITE, STOP_RUNAWAY, STOP_JUMP, STOP_UNCOVERED, STOP_CHECK = \
    range(7)

# wall motions
WALL_FIXED, WALL_VELOCITY, WALL_SERVO = 0, 1, 2
# servo parameter columns: target stress, gain [L T/M] (0: automatic), speed limit,
# fixed area (0: from the box), factor of the automatic gain
S_TARGET, S_GAIN, S_MAXSPEED, S_AREA, S_FACTOR = range(5)
# periodic box motions (per axis)
BOX_FIXED, BOX_RATE, BOX_SERVO = 0, 1, 2


def _rolling_loop(w, r, m, inertia, inv_m, pi, pj, geo, params, dt, roll, chunks,
                  spans, torque, torque_band):
    """Rolling and twisting resistance of all Verlet pairs (compiled twice), after the
    pair loop of the same step: reads its unit normals and distances ``geo``, adds the
    moments (j +M, i -M) to ``torque`` and the chunks' bands ``torque_band`` as
    :func:`_pair_loop` does, updates the history ``roll`` (P, ROLL_WIDTH). A fixed
    particle (``inv_m`` 0) counts as a wall in the equivalent inertia. Returns (stored
    energy, plastic dissipation, viscous dissipation)."""
    e_s = 0.0
    d_p = 0.0
    d_v = 0.0
    n_chunks = chunks.shape[0] - 1
    for c in prange(n_chunks):
        own_hi = spans[c + 1, 0] if c + 1 < n_chunks else torque.shape[0]
        tb = torque_band[c]
        for k in range(chunks[c], chunks[c + 1]):
            i = pi[k]
            j = pj[k]
            free_i = inv_m[i] > 0.0  # a fixed particle counts as a wall
            free_j = inv_m[j] > 0.0
            touched, mx, my, mz, e_new, c_p, c_v = rolling_contact(
                params, roll[k], geo[k, 0], geo[k, 1], geo[k, 2], r[i] + r[j] - geo[k, 3],
                r[i] * r[j] / (r[i] + r[j]), inertia[i] if free_i else 0.0,
                m[i] if free_i else 0.0, r[i], inertia[j] if free_j else 0.0,
                m[j] if free_j else 0.0, r[j], w[j, 0] - w[i, 0], w[j, 1] - w[i, 1],
                w[j, 2] - w[i, 2], dt)
            if not touched:
                continue
            if j < own_hi:
                torque[j, 0] += mx
                torque[j, 1] += my
                torque[j, 2] += mz
            else:
                tb[j - own_hi, 0] += mx
                tb[j - own_hi, 1] += my
                tb[j - own_hi, 2] += mz
            torque[i, 0] -= mx
            torque[i, 1] -= my
            torque[i, 2] -= mz
            e_s += e_new
            d_p += c_p
            d_v += c_v
    return e_s, d_p, d_v


def _wall_rolling_loop(x, w, r, m, inertia, wp, ww, wall_point, wall_normal, params, dt,
                       roll, torque, n_chunks):
    """Rolling and twisting resistance of the particle-wall contacts (compiled twice),
    after the wall loop of the same step, in its runs of wall pairs cut between
    particles; the wall is j (it does not rotate). Adds the moments to ``torque``,
    updates ``roll`` (Q, ROLL_WIDTH); returns (stored energy, plastic and viscous
    dissipation)."""
    e_s = 0.0
    d_p = 0.0
    d_v = 0.0
    n_pairs = wp.shape[0]
    for c in prange(n_chunks):
        for q in range(_particle_boundary(wp, (n_pairs * c) // n_chunks),
                       _particle_boundary(wp, (n_pairs * (c + 1)) // n_chunks)):
            p = wp[q]
            wi = ww[q]
            nx, ny, nz, dist, delta, a = wall_geometry(
                x[p, 0], x[p, 1], x[p, 2], r[p], wall_point[wi, 0], wall_point[wi, 1],
                wall_point[wi, 2], wall_normal[wi, 0], wall_normal[wi, 1], wall_normal[wi, 2])
            touched, mx, my, mz, e_new, c_p, c_v = rolling_contact(
                params, roll[q], nx, ny, nz, delta, r[p], inertia[p], m[p], r[p], 0.0, 0.0,
                0.0, -w[p, 0], -w[p, 1], -w[p, 2], dt)
            if not touched:
                continue
            torque[p, 0] -= mx
            torque[p, 1] -= my
            torque[p, 2] -= mz
            e_s += e_new
            d_p += c_p
            d_v += c_v
    return e_s, d_p, d_v


@njit
def _pair_chunks(pi, pj, n_particles, chunks, spans):
    """:func:`pair_chunks` into ``chunks`` (n_chunks + 1,) and ``spans`` (n_chunks, 2)."""
    n_pairs = pi.shape[0]
    n_chunks = spans.shape[0]
    for c in range(n_chunks + 1):
        chunks[c] = (n_pairs * c) // n_chunks
    for c in range(1, n_chunks):
        a = chunks[c]
        if a >= n_pairs:
            chunks[c] = n_pairs
            continue
        # back to the first pair of that particle's row (rows are contiguous)
        while a > 0 and pi[a - 1] == pi[a]:
            a -= 1
        chunks[c] = max(a, chunks[c - 1])
    for c in range(n_chunks):
        a, b = chunks[c], chunks[c + 1]
        own_lo = 0 if c == 0 else (pi[a] if a < n_pairs else n_particles)
        own_hi = n_particles
        if c + 1 < n_chunks:
            own_hi = pi[b] if b < n_pairs else n_particles
        reach = 0
        for k in range(a, b):
            reach = max(reach, pj[k] + 1)
        spans[c, 0] = own_lo
        spans[c, 1] = max(own_hi, reach)


def pair_chunks(pi, pj, n_particles: int, n_chunks: int):
    """Cut a pair list sorted by i into ``n_chunks`` runs of about equal numbers of
    pairs, each starting at a particle's first pair (boundaries (n_chunks + 1,)), and
    give each chunk's particle range [lo, hi) (spans (n_chunks, 2)). Chunk c owns the
    particles from its first pair's i (0 for the first chunk) up to the next chunk's
    first i (N for the last): every i of its pairs is its own. Its span is that range,
    stretched to the largest j of its pairs; the part beyond its own range (its
    *band*, in later chunks' ranges) is where the pair loop writes into a band buffer
    instead of the particles' forces. The spans cover every particle. Compiled: after
    every rebuild of the lists (numpy took 80 us of Python per call at 1e5 particles)."""
    chunks = np.empty(n_chunks + 1, dtype=np.int64)
    spans = np.empty((n_chunks, 2), dtype=np.int64)
    _pair_chunks(pi, pj, int(n_particles), chunks, spans)
    return chunks, spans


def band_rows(spans, n_particles: int) -> int:
    """The rows a band buffer needs (:func:`_pair_loop`): the most particles any chunk
    reaches past its own range (chunk c owns up to ``spans[c + 1, 0]``, the last one up
    to N; its span ends at ``spans[c, 1]``)."""
    own_hi = np.append(spans[1:, 0], n_particles)
    return int(np.max(spans[:, 1] - own_hi, initial=0))


#: pairs per block of the pair loop (:func:`_pair_loop`): the block's scratch,
#: PAIR_ROWS x PAIR_BLOCK doubles (18 KB), stays in the L1 cache
PAIR_BLOCK = 64
# rows of the scratch: the law's inputs, gathered per active pair of a block ...
(S_NX, S_NY, S_NZ, S_DIST, S_DELTA, S_AI, S_AJ, S_N0, S_N1, S_N2, S_VX, S_VY, S_VZ, S_OX, S_OY,
 S_OZ, S_FDX, S_FDY, S_FDZ, S_EOLD, S_MSTAR, S_RSTAR,
 # ... and its outputs
 S_FX, S_FY, S_FZ, S_EN, S_ET, S_FRIC, S_DASH, S_KN, S_TX, S_TY, S_TZ, S_NDX, S_NDY,
 S_NDZ) = range(36)
PAIR_ROWS = 36


def _law_block(params, count, dt, store_dashpot, needs_m_star, needs_r_star, s):
    """The contact law (:func:`contact_response`) applied to the ``count`` gathered pairs
    of a block; ``s`` is the block's scratch (rows S_*, PAIR_BLOCK columns). Its own
    compiled function over contiguous rows only, without branches the compiler cannot
    turn into selects: the compiler vectorises it (8 pairs at a time with AVX-512), the
    same IEEE operations as pair by pair, so the same results to the bit."""
    mu = params.mu
    B = PAIR_BLOCK
    for b in range(count):
        fdx, fdy, fdz = 0.0, 0.0, 0.0
        if store_dashpot:
            fdx, fdy, fdz = s[S_FDX * B + b], s[S_FDY * B + b], s[S_FDZ * B + b]
        m_star = s[S_MSTAR * B + b] if needs_m_star else 0.0
        r_star = s[S_RSTAR * B + b] if needs_r_star else 0.0
        (fx, fy, fz, c_en, c_et, c_fric, c_dash, c_kn, _, tx, ty, tz, ndx, ndy, ndz,
         _) = contact_response(params, mu, s[S_NX * B + b], s[S_NY * B + b],
                               s[S_NZ * B + b], s[S_DELTA * B + b], r_star, m_star,
                               s[S_VX * B + b], s[S_VY * B + b], s[S_VZ * B + b], dt,
                               s[S_OX * B + b], s[S_OY * B + b], s[S_OZ * B + b],
                               fdx, fdy, fdz, s[S_EOLD * B + b])
        s[S_FX * B + b] = fx
        s[S_FY * B + b] = fy
        s[S_FZ * B + b] = fz
        s[S_EN * B + b] = c_en
        s[S_ET * B + b] = c_et
        s[S_FRIC * B + b] = c_fric
        s[S_DASH * B + b] = c_dash
        s[S_KN * B + b] = c_kn
        s[S_TX * B + b] = tx
        s[S_TY * B + b] = ty
        s[S_TZ * B + b] = tz
        s[S_NDX * B + b] = ndx
        s[S_NDY * B + b] = ndy
        s[S_NDZ * B + b] = ndz


law_block = njit(_law_block)


#: what a compiled pair loop knows before it runs (:func:`pair_loop_for`): -1 the
#: general loop, which tests it at run time; 0 or 1 a copy compiled for a law without
#: or with dashpot history, a box without or with periodic axes
_PAIR_DASHPOT = -1
_PAIR_PERIODIC = -1


def _pair_chunk(c, sph, pairs, periodic_len, box_rate, params, dt, store_dashpot):
    """The pairs of chunk ``c`` of :func:`_pair_loop` (``chunks[c]`` to
    ``chunks[c + 1]``), compiled once and called by the serial and the
    threaded driver alike: the same loop compiled inside a prange body ran 12 % slower
    per pair (dense 1e5: 15.45 against 13.80 ms on one thread), most of what two
    threads lost against two processes. Returns the chunk's PAIR_SUMS sums, all as
    floats (the counts exact below 2^53): strain_n, strain_t, friction, dashpot,
    contacts, uncovered, then the rows of ``box_sums``: virial (3), crossing sums (3),
    crossing contacts (3), their k_n (3); last the chunk's smallest headroom cover -
    delta [L] (+inf without a cover).

    In the copies :func:`pair_loop_for` compiles, whether the law keeps dashpot history
    and whether the box is periodic are constants, and the branches on them are gone
    from the gather and scatter loops (dense 1e5, one thread: 8-10 % less time per
    pair); its driver refuses a call that does not match them."""
    x, v, w, r, m, inv_m = sph.x, sph.v, sph.w, sph.r, sph.m, sph.inv_m
    force, torque = sph.force, sph.torque
    pi, pj, ft, fd, etan = pairs.i, pairs.j, pairs.shear, pairs.dashpot, pairs.shear_energy
    chunks, spans, geo, cover = pairs.chunks, pairs.spans, pairs.geo, pairs.cover
    force_band, torque_band = pairs.force_band, pairs.torque_band
    periodic = any_periodic(periodic_len) if _PAIR_PERIODIC < 0 else _PAIR_PERIODIC == 1
    if _PAIR_DASHPOT >= 0:
        store_dashpot = _PAIR_DASHPOT == 1
    e_n = 0.0
    e_t = 0.0
    d_fric = 0.0
    d_dash = 0.0
    n_contacts = 0
    n_uncovered = 0
    headroom = np.inf
    vir0 = 0.0
    vir1 = 0.0
    vir2 = 0.0
    cr0 = 0.0
    cr1 = 0.0
    cr2 = 0.0
    nc0 = 0
    nc1 = 0
    nc2 = 0
    kc0 = 0.0
    kc1 = 0.0
    kc2 = 0.0
    needs_m_star = params.beta_n > 0.0 or params.beta_t > 0.0
    needs_r_star = law_needs_r_star(params)
    store_geo = geo.shape[0] > 0
    track_cover = cover.shape[0] == pi.shape[0]
    len0, len1, len2 = periodic_len[0], periodic_len[1], periodic_len[2]
    rate0, rate1, rate2 = box_rate[0], box_rate[1], box_rate[2]
    X = x.reshape(-1)
    V = v.reshape(-1)
    W = w.reshape(-1)
    FT = ft.reshape(-1)
    FD = fd.reshape(-1)
    one, two, three = _U(1), _U(2), _U(3)
    B = PAIR_BLOCK
    F = force.reshape(-1)
    T = torque.reshape(-1)
    n_chunks = chunks.shape[0] - 1
    # the block's scratch, the chunk's own allocation: the compiler knows it aliases
    # no argument (with a row of one array of the driver's, the pair loop ran 13-17 %
    # slower on two threads, dense 1e5); a cache line of margin on each side, since
    # another thread's allocation may lie next to it
    s = np.empty(PAIR_ROWS * PAIR_BLOCK + 16)[8:8 + PAIR_ROWS * PAIR_BLOCK]
    own_hi = _U(spans[c + 1, 0] if c + 1 < n_chunks else force.shape[0])
    band_start = three * own_hi
    FB = force_band[c].reshape(-1)
    TB = torque_band[c].reshape(-1)
    for p in range(three * _U(spans[c, 0]), band_start):
        F[p] = 0.0
        T[p] = 0.0
    for p in range(three * (_U(max(spans[c, 1], own_hi)) - own_hi)):
        FB[p] = 0.0
        TB[p] = 0.0
    for k0 in range(chunks[c], chunks[c + 1], PAIR_BLOCK):
        # (1) gather the block's pairs
        count = min(PAIR_BLOCK, chunks[c + 1] - k0)
        for b in range(count):
            k = k0 + b
            i = _U(pi[k])
            j = _U(pj[k])
            a = three * i
            q = three * j
            r_i = r[i]
            r_j = r[j]
            d0, d1, d2, dist, delta, a_i, a_j, n0, n1, n2 = pair_geometry(
                X[a], X[a + one], X[a + two], X[q], X[q + one], X[q + two], r_i, r_j,
                len0, len1, len2, periodic)
            inv_dist = 1.0 / dist
            nx, ny, nz = d0 * inv_dist, d1 * inv_dist, d2 * inv_dist
            if store_geo:
                geo[k, 0] = nx
                geo[k, 1] = ny
                geo[k, 2] = nz
                geo[k, 3] = dist
            h = three * _U(k)
            ox, oy, oz = FT[h], FT[h + one], FT[h + two]
            fdx, fdy, fdz = 0.0, 0.0, 0.0
            if store_dashpot:
                fdx, fdy, fdz = FD[h], FD[h + one], FD[h + two]
            e_old = etan[k]
            # contact-point velocities: v + omega x b, b_i = a_i n, b_j = -a_j n;
            # j's periodic image moves with the box
            vix = V[a] + a_i * (W[a + one] * nz - W[a + two] * ny)
            viy = V[a + one] + a_i * (W[a + two] * nx - W[a] * nz)
            viz = V[a + two] + a_i * (W[a] * ny - W[a + one] * nx)
            vjx = V[q] - a_j * (W[q + one] * nz - W[q + two] * ny) - n0 * rate0
            vjy = V[q + one] - a_j * (W[q + two] * nx - W[q] * nz) - n1 * rate1
            vjz = V[q + two] - a_j * (W[q] * ny - W[q + one] * nx) - n2 * rate2
            s[S_NX * B + b] = nx
            s[S_NY * B + b] = ny
            s[S_NZ * B + b] = nz
            s[S_DIST * B + b] = dist
            s[S_DELTA * B + b] = delta
            s[S_AI * B + b] = a_i
            s[S_AJ * B + b] = a_j
            if periodic:
                s[S_N0 * B + b] = n0
                s[S_N1 * B + b] = n1
                s[S_N2 * B + b] = n2
            s[S_VX * B + b] = vjx - vix
            s[S_VY * B + b] = vjy - viy
            s[S_VZ * B + b] = vjz - viz
            s[S_OX * B + b] = ox
            s[S_OY * B + b] = oy
            s[S_OZ * B + b] = oz
            s[S_EOLD * B + b] = e_old
            if store_dashpot:
                s[S_FDX * B + b] = fdx
                s[S_FDY * B + b] = fdy
                s[S_FDZ * B + b] = fdz
            # effective mass and radius only where the law reads them (restitution
            # dashpots; Hertz)
            if needs_m_star:
                inv_sum = inv_m[i] + inv_m[j]
                s[S_MSTAR * B + b] = 1.0 / inv_sum if inv_sum > 0.0 else m[i]
            if needs_r_star:
                s[S_RSTAR * B + b] = r_i * r_j / (r_i + r_j)
        # (2) the law, vectorised
        law_block(params, count, dt, store_dashpot, needs_m_star, needs_r_star, s)
        # (3) scatter
        for b in range(count):
            k = k0 + b
            i = _U(pi[k])
            j = _U(pj[k])
            a = three * i
            q = three * j
            h = three * _U(k)
            FT[h] = s[S_TX * B + b]
            FT[h + one] = s[S_TY * B + b]
            FT[h + two] = s[S_TZ * B + b]
            if store_dashpot:
                FD[h] = s[S_NDX * B + b]
                FD[h + one] = s[S_NDY * B + b]
                FD[h + two] = s[S_NDZ * B + b]
            c_et = s[S_ET * B + b]
            etan[k] = c_et
            fx, fy, fz = s[S_FX * B + b], s[S_FY * B + b], s[S_FZ * B + b]
            nx, ny, nz = s[S_NX * B + b], s[S_NY * B + b], s[S_NZ * B + b]
            a_i, a_j = s[S_AI * B + b], s[S_AJ * B + b]
            cx, cy, cz = ny * fz - nz * fy, nz * fx - nx * fz, nx * fy - ny * fx
            F[a] -= fx
            F[a + one] -= fy
            F[a + two] -= fz
            T[a] -= a_i * cx
            T[a + one] -= a_i * cy
            T[a + two] -= a_i * cz
            # j's rows: its own particle's, or in the band past the chunk's range
            # (written out twice: choosing the array in a variable cost 25-30 % of
            # the whole loop, measured on dense 1e5, one thread)
            if q < band_start:
                F[q] += fx
                F[q + one] += fy
                F[q + two] += fz
                T[q] -= a_j * cx
                T[q + one] -= a_j * cy
                T[q + two] -= a_j * cz
            else:
                q -= band_start
                FB[q] += fx
                FB[q + one] += fy
                FB[q + two] += fz
                TB[q] -= a_j * cx
                TB[q + one] -= a_j * cy
                TB[q + two] -= a_j * cz
            e_n += s[S_EN * B + b]
            e_t += c_et
            d_fric += s[S_FRIC * B + b]
            d_dash += s[S_DASH * B + b]
            dist = s[S_DIST * B + b]
            vir0 += fx * nx * dist
            vir1 += fy * ny * dist
            vir2 += fz * nz * dist
            delta = s[S_DELTA * B + b]
            touching = delta > 0.0
            if touching:
                n_contacts += 1
            if track_cover:
                room = cover[k] - delta
                headroom = min(headroom, room)
                if touching and room < 0.0:
                    n_uncovered += 1
            if periodic:
                n0, n1, n2 = s[S_N0 * B + b], s[S_N1 * B + b], s[S_N2 * B + b]
                cr0 += fx * n0
                cr1 += fy * n1
                cr2 += fz * n2
                if touching:
                    c_kn = s[S_KN * B + b]
                    if n0 != 0.0:
                        nc0 += 1
                        kc0 += c_kn
                    if n1 != 0.0:
                        nc1 += 1
                        kc1 += c_kn
                    if n2 != 0.0:
                        nc2 += 1
                        kc2 += c_kn
    return (e_n, e_t, d_fric, d_dash, float(n_contacts), float(n_uncovered), vir0, vir1, vir2,
            cr0, cr1, cr2, float(nc0), float(nc1), float(nc2), kc0, kc1, kc2, headroom)


#: the sums a chunk of the pair loop returns (:func:`_pair_chunk`): six, then the
#: four rows of three of ``box_sums``, then the headroom (a minimum, not a sum)
PAIR_SUMS = 19
PAIR_HEADROOM = 18


pair_chunk = njit(fastmath=CONTRACT)(_pair_chunk)
#: the same, inlined into the serial driver (called, it ran 2-3 % slower there)
pair_chunk_inline = njit(fastmath=CONTRACT, inline="always")(_pair_chunk)


def _pair_loop(sph, pairs, periodic_len, box_rate, params, dt, store_dashpot, box_sums):
    """Forces of all Verlet pairs (compiled twice: parallel and serial) of the Spheres
    ``sph`` and the Pairs ``pairs`` (:mod:`demstep.state`): the pairs ``i``, ``j`` and
    their history ``shear`` (ft), ``dashpot`` (fd), ``shear_energy`` (etan) (see
    :func:`contact_response`), at the slip step ``dt`` [T] with the law's ``params``.
    The pairs are cut into chunks
    (``pairs.chunks``: pair-index boundaries at particle starts, one chunk per thread;
    :func:`pair_chunks`); chunk c adds the force (on j +F, on i -F) and torque (-a n x F
    on each) of its pairs to the ``sph.force``/``sph.torque`` rows (N, 3) of the particles it
    owns, which it zeroes first, and those of particles beyond (its band: up to
    ``spans[c, 1]``) to ``pairs.force_band[c]``/``torque_band[c]`` (rows from the first
    particle past its own), which :func:`_reduce_loop` adds once every chunk is done:
    no two threads write the same memory, and with one chunk there is no band. Returns
    (strain_n, strain_t, friction, dashpot, contacts, uncovered, headroom). ``box_sums`` (4, 3)
    receives per axis the virial sum F_on_j,k d_k (Love stress times volume), the
    boundary sum F_on_j,k n_img,k over pairs crossing a
    periodic boundary (times a change of box length: the work done on the contacts),
    the number of crossing contacts and the sum of their k_n. ``box_rate`` (3,): rate of
    change of the periodic lengths; the image of j across a boundary moves with
    v_j - n_img dL/dt. ``store_dashpot`` False (a law without dashpots, ``fd`` all
    zero) skips reading and writing ``fd``. ``pairs.geo`` (P, 4) or (0, 4): when it has a
    row per pair, it receives the unit normal and the centre distance of every pair
    (the rolling-resistance loop reads them). ``pairs.cover`` (P,) or (0,): when it has a row
    per pair, the largest overlap [L] the last certified time step covered each pair at
    (0: not covered; see :meth:`demstep.engine.auto_step.AutoStep.accept`): the
    touching pairs whose overlap exceeds it are counted (``uncovered``), and the
    smallest headroom cover - delta [L] over all pairs is returned last (+inf without a
    cover): a pair whose gap or overlap changes by less than it in the next step stays
    within its cover.

    A chunk runs in blocks of PAIR_BLOCK pairs, in three passes whose work stays in
    the L1 cache: (1) gather: each pair's geometry, contact-point relative velocity
    and history into the block's scratch; (2) the law on the scratch
    (:func:`law_block`, vectorised by the compiler); (3) scatter: history written
    back, forces and torques added to the buffers, the ledger's sums. Pairs apart and
    without history go through all three (the law gives them zeros): skipping them
    measured 6 % slower on a dense packing and no faster on a settling one; compacting
    the block to the pairs that touch or keep history (measured 2026-12-08) made a loose
    hopper bed 1.24x faster per call (3.5 Verlet pairs per contact) and the dense 1e5
    packing 9 % slower per step, and was dropped. Particle
    arrays are read through flat views with unsigned indices (no negative-index
    wrap-around per access). Measured at 1e5 spheres, 1 thread, against the one-pass
    loop: see benchmarks/RESULTS.md; the results are the same to the bit."""
    # a copy compiled for a kind of law and box (pair_loop_for) takes no other
    if _PAIR_PERIODIC >= 0 and any_periodic(periodic_len) != (_PAIR_PERIODIC == 1):
        raise ValueError("pair loop: compiled for another kind of box")
    if _PAIR_DASHPOT >= 0 and store_dashpot != (_PAIR_DASHPOT == 1):
        raise ValueError("pair loop: compiled for another kind of law")
    n_chunks = pairs.chunks.shape[0] - 1
    sums = np.zeros((max(n_chunks, 1), PAIR_SUMS))
    for c in prange(n_chunks):
        got = pair_chunk(c, sph, pairs, periodic_len, box_rate, params, dt, store_dashpot)
        for q in range(PAIR_SUMS):
            sums[c, q] = got[q]
    # the chunks' sums added in chunk order: the same whatever the threads did
    for c in range(1, n_chunks):
        for q in range(PAIR_HEADROOM):
            sums[0, q] += sums[c, q]
        sums[0, PAIR_HEADROOM] = min(sums[0, PAIR_HEADROOM], sums[c, PAIR_HEADROOM])
    for row in range(4):
        for k in range(3):
            box_sums[row, k] = sums[0, 6 + 3 * row + k]
    headroom = sums[0, PAIR_HEADROOM] if n_chunks > 0 else np.inf
    return (sums[0, 0], sums[0, 1], sums[0, 2], sums[0, 3], int(sums[0, 4]), int(sums[0, 5]),
            headroom)


def _reduce_loop(force_band, torque_band, spans, force, torque):
    """Add the chunks' band buffers (:func:`_pair_loop`) to the particle forces and
    torques: chunk c's band holds particles ``spans[c + 1, 0]`` (the first past its
    own) to ``spans[c, 1] - 1``. Each chunk's own range receives the bands of the
    earlier chunks that reach into it, in chunk order (the sums do not depend on the
    threads)."""
    n_chunks = spans.shape[0]
    for c in prange(n_chunks):
        lo = spans[c, 0]
        hi = spans[c + 1, 0] if c + 1 < n_chunks else force.shape[0]
        for c2 in range(c):
            start = spans[c2 + 1, 0]
            for p in range(lo, min(hi, spans[c2, 1])):
                for k in range(3):
                    force[p, k] += force_band[c2, p - start, k]
                    torque[p, k] += torque_band[c2, p - start, k]


@njit
def pair_contact_forces(x, r, pi, pj, periodic_len, params, ft, fd, force, normal):
    """For output: force on j of every touching pair (elastic at the current positions
    plus the stored tangential and dashpot forces) and the unit normal; returns the
    boolean mask of touching pairs."""
    on = np.zeros(pi.shape[0], dtype=np.bool_)
    for k in range(pi.shape[0]):
        i = pi[k]
        j = pj[k]
        d0, d1, d2, dist, delta, _, _, _, _, _ = pair_geometry(
            x[i, 0], x[i, 1], x[i, 2], x[j, 0], x[j, 1], x[j, 2], r[i], r[j],
            periodic_len[0], periodic_len[1], periodic_len[2])
        if delta <= 0.0:
            continue
        on[k] = True
        f_el, _, _ = normal_force(params, delta, r[i] * r[j] / (r[i] + r[j]))
        for a, d in enumerate((d0, d1, d2)):
            normal[k, a] = d / dist
            force[k, a] = f_el * d / dist + ft[k, a] + fd[k, a]
    return on


@njit(inline="always")
def _particle_boundary(wp, q):
    """The first wall pair at or after ``q`` that starts a new particle (pairs sorted by
    particle): chunks cut there never share a particle."""
    while 0 < q < wp.shape[0] and wp[q] == wp[q - 1]:
        q += 1
    return q


def _wall_loop(sph, walls, params, dt, n_chunks):
    """Particle-wall contacts (compiled twice: parallel and serial) of the Spheres ``sph``
    with the Walls ``walls`` (their particle-wall list ``p``, ``wall`` and its history),
    at the slip step ``dt`` [T] with the law's ``params``, in ``n_chunks`` runs
    of wall pairs cut between particles, so that each run adds to the ``force``/
    ``torque`` rows of its own particles only. ``walls.force`` (W, 3) receives the force
    the particles exert on each wall, ``walls.contacts`` and ``walls.k_sum`` the number of
    touching particles and the sum of their k_n (per run first, then summed). ``walls.cover``
    as in :func:`_pair_loop` (per wall pair). Returns (strain_n, strain_t, friction,
    dashpot, uncovered, headroom). Arrays of particles and wall pairs are read
    through flat views with unsigned indices (as in :func:`_pair_loop`)."""
    x, v, w, r, m, force, torque = sph.x, sph.v, sph.w, sph.r, sph.m, sph.force, sph.torque
    wp, ww, cover = walls.p, walls.wall, walls.cover
    wall_point, wall_normal, wall_vel, wall_mu = walls.point, walls.normal, walls.vel, walls.mu
    wft, wfd, wetan = walls.shear, walls.dashpot, walls.shear_energy
    wall_force, wall_contacts, wall_k = walls.force, walls.contacts, walls.k_sum
    e_n = 0.0
    e_t = 0.0
    d_fric = 0.0
    d_dash = 0.0
    n_uncovered = 0
    track_cover = cover.shape[0] == wp.shape[0]
    n_walls = wall_force.shape[0]
    n_pairs = wp.shape[0]
    # per run and wall: force on the wall (3), touching particles, their k_n; a run's
    # rows sit between 64-byte pads, so that two threads never share a cache line
    per_run_padded = np.zeros((n_chunks, n_walls + 2, 8))
    per_run = per_run_padded[:, 1:n_walls + 1, :5]
    # per run, the smallest headroom cover - delta (in the run's own first pad row)
    for c in range(n_chunks):
        per_run_padded[c, 0, 0] = np.inf
    # flat views, unsigned indices (as in the pair loop)
    X = x.reshape(-1)
    V = v.reshape(-1)
    W = w.reshape(-1)
    F = force.reshape(-1)
    T = torque.reshape(-1)
    FT = wft.reshape(-1)
    FD = wfd.reshape(-1)
    one, two, three = _U(1), _U(2), _U(3)
    for c in prange(n_chunks):
        run = per_run[c]
        for q in range(_particle_boundary(wp, (n_pairs * c) // n_chunks),
                       _particle_boundary(wp, (n_pairs * (c + 1)) // n_chunks)):
            p = _U(wp[q])
            wi = ww[q]
            b = three * p
            h = three * _U(q)
            nx, ny, nz, dist, delta, a = wall_geometry(
                X[b], X[b + one], X[b + two], r[p], wall_point[wi, 0], wall_point[wi, 1],
                wall_point[wi, 2], wall_normal[wi, 0], wall_normal[wi, 1], wall_normal[wi, 2])
            ox, oy, oz = FT[h], FT[h + one], FT[h + two]
            fdx, fdy, fdz = FD[h], FD[h + one], FD[h + two]
            e_old = wetan[q]
            if track_cover:
                room = cover[q] - delta
                if room < per_run_padded[c, 0, 0]:
                    per_run_padded[c, 0, 0] = room
                if delta > 0.0 and room < 0.0:
                    n_uncovered += 1
            if delta <= 0.0 and e_old == 0.0 and ox == 0.0 and oy == 0.0 and oz == 0.0 \
                    and fdx == 0.0 and fdy == 0.0 and fdz == 0.0:
                continue
            vix = V[b] + a * (W[b + one] * nz - W[b + two] * ny)
            viy = V[b + one] + a * (W[b + two] * nx - W[b] * nz)
            viz = V[b + two] + a * (W[b] * ny - W[b + one] * nx)
            (fx, fy, fz, c_en, c_et, c_fric, c_dash, c_kn, _, tx, ty, tz, ndx, ndy, ndz,
             e_new) = contact_response(
                params, wall_mu[wi], nx, ny, nz, delta, r[p], m[p],
                wall_vel[wi, 0] - vix, wall_vel[wi, 1] - viy, wall_vel[wi, 2] - viz, dt,
                ox, oy, oz, fdx, fdy, fdz, e_old)
            FT[h] = tx
            FT[h + one] = ty
            FT[h + two] = tz
            FD[h] = ndx
            FD[h + one] = ndy
            FD[h + two] = ndz
            wetan[q] = e_new
            F[b] -= fx
            F[b + one] -= fy
            F[b + two] -= fz
            T[b] -= a * (ny * fz - nz * fy)
            T[b + one] -= a * (nz * fx - nx * fz)
            T[b + two] -= a * (nx * fy - ny * fx)
            run[wi, 0] += fx
            run[wi, 1] += fy
            run[wi, 2] += fz
            e_n += c_en
            e_t += c_et
            d_fric += c_fric
            d_dash += c_dash
            if delta > 0.0:
                run[wi, 3] += 1.0
                run[wi, 4] += c_kn
    for wi in range(n_walls):
        for k in range(3):
            wall_force[wi, k] = 0.0
        wall_contacts[wi] = 0
        wall_k[wi] = 0.0
        for c in range(n_chunks):
            for k in range(3):
                wall_force[wi, k] += per_run[c, wi, k]
            wall_contacts[wi] += int(per_run[c, wi, 3])
            wall_k[wi] += per_run[c, wi, 4]
    headroom = np.inf
    for c in range(n_chunks):
        headroom = min(headroom, per_run_padded[c, 0, 0])
    return e_n, e_t, d_fric, d_dash, n_uncovered, headroom


@njit
def box_extents(wall_point, box_lo, box_hi, periodic_len, dim, extents):
    """Extent of the specimen along each axis [L]: the periodic length, else the gap
    between the opposing box walls, else NaN; 1 for the z axis of a 2D run."""
    for k in range(3):
        if k >= dim:
            extents[k] = 1.0
        elif periodic_len[k] > 0.0:
            extents[k] = periodic_len[k]
        elif box_lo[k] >= 0 and box_hi[k] >= 0:
            extents[k] = wall_point[box_hi[k], k] - wall_point[box_lo[k], k]
        else:
            extents[k] = np.nan


@njit
def wall_areas(wall_point, wall_normal, servo, box_lo, box_hi, periodic_len, dim, areas):
    """Current loaded area of each wall [L^2] (length in 2D): the fixed area if given,
    else the product of the specimen's extents along the other axes, taken from the
    opposing box walls or the periodic box. NaN when unknown."""
    extents = np.empty(3)
    box_extents(wall_point, box_lo, box_hi, periodic_len, dim, extents)
    for wi in range(wall_point.shape[0]):
        if servo[wi, S_AREA] > 0.0:
            areas[wi] = servo[wi, S_AREA]
            continue
        axis = 0
        best = 0.0
        for k in range(3):
            if abs(wall_normal[wi, k]) > best:
                best = abs(wall_normal[wi, k])
                axis = k
        area = 1.0
        for k in range(3):
            if k != axis:
                area *= extents[k]
        areas[wi] = area


@njit
def servo_speed(stress, target, gain, factor, area, n_contacts, k_sum, dt, max_speed):
    """Speed [L/T] of a servo boundary that closes the gap between ``stress`` and
    ``target`` (positive: towards the specimen). With ``gain`` = 0 the gain is
    automatic, factor * area / (sum of k_n of its contacts * dt): a stress error is
    then corrected by ``factor`` of itself per step at the current stiffness."""
    g = gain
    if g <= 0.0:
        if k_sum <= 0.0 or n_contacts == 0:
            # touching nothing: approach at the speed limit (if one is set)
            if target > stress and math.isfinite(max_speed):
                return max_speed
            return 0.0
        g = factor * area / (k_sum * dt)
    speed = g * (target - stress)
    if speed > max_speed:
        speed = max_speed
    elif speed < -max_speed:
        speed = -max_speed
    return speed


#: True in the integrator that takes any step (:func:`_integrate_loop`); False in its
#: copy for undamped steps after the first (:func:`integrate_plain`)
_ANY_STEP = True


def _integrate_loop(sph, ctl, dt, dt_prev, first, acc_out, sphere_body):
    """Central-difference update of all particles of the Spheres ``sph`` (positions,
    half-step velocities, forces, applied forces ``applied``, the last step's damping
    forces ``damp_force``/``damp_torque``) under the Controls ``ctl`` (gravity, local and
    global damping, ``store_damping``), over the step ``dt`` after ``dt_prev`` [T]
    (``first``: initialise the half step), with damping and the particle terms
    of the ledger (a change of step from ``dt_prev`` to ``dt`` kicks by their mean,
    :func:`~demstep.kernels.integration.step_weights`). ``acc_out`` (8,): work of
    gravity, of applied forces, local and global damping dissipation, kinetic energy
    (translation, rotation) at t, the largest squared displacement since the list was
    built, the largest |v| dt / r.
    ``fd_prev``/``td_prev`` (N, 6) hold the damping forces of the last step (local,
    global) for the trapezoid; ``store_damping`` False (damping off and those arrays
    all zero) skips reading and writing them. Members of rigid bodies
    (``sphere_body`` >= 0) are left to :mod:`demstep.kernels.clumps`. The (N, 3) arrays
    are read through flat views with unsigned indices, a sphere's scalars once.

    Compiled twice more as :func:`integrate_plain` (and its serial twin), with the
    global ``_ANY_STEP`` False: a step after the first without damping, whose branches
    on ``first``, the damping coefficients and ``store_damping`` are then dead code
    (measured on 1e5 spheres, one thread: 0.67 against 1.02 ms per call, the same
    results to the bit)."""
    x, v, w, m, r = sph.x, sph.v, sph.w, sph.m, sph.r
    inertia, inv_m, inv_I = sph.inertia, sph.inv_m, sph.inv_I
    force, torque, f_app, x_ref = sph.force, sph.torque, sph.applied, sph.x_ref
    fd_prev, td_prev = sph.damp_force, sph.damp_torque
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
    X = x.reshape(-1)
    V = v.reshape(-1)
    W = w.reshape(-1)
    F = force.reshape(-1)
    T = torque.reshape(-1)
    FA = f_app.reshape(-1)
    XR = x_ref.reshape(-1)
    three = _U(3)
    kick, c_old, c_new = step_weights(dt, dt_prev, _ANY_STEP and first)
    for p in prange(x.shape[0]):
        i_m = inv_m[p]
        if i_m == 0.0 or sphere_body[p] >= 0:
            continue  # fixed particle, or a member of a body
        m_p = m[p]
        inertia_p = inertia[p]
        i_I = inv_I[p]
        b = three * _U(p)
        # the sphere's own sums first, added to the step's once (short dependency chains)
        g_dx = 0.0
        fa_dx = 0.0
        dl = 0.0
        dg = 0.0
        vv = 0.0
        ww = 0.0
        for k in range(3):
            q = b + _U(k)
            g = gravity[k]
            fa = FA[q]
            fl = F[q] + m_p * g + fa
            tl = T[q]
            v_old = V[q]
            w_old = W[q]
            if _ANY_STEP and first:
                # initialise the half step: v(-dt/2) = v(0) - dt/2 F(0)/m
                v_old -= 0.5 * dt * fl * i_m
                w_old -= 0.5 * dt * tl * i_I
            fdk = 0.0
            tdk = 0.0
            if _ANY_STEP and local_damping > 0.0:
                fdk -= local_damping * abs(fl) * np.sign(v_old)
                tdk -= local_damping * abs(tl) * np.sign(w_old)
            gdk = 0.0
            gtk = 0.0
            if _ANY_STEP and global_damping > 0.0:
                gdk = -global_damping * m_p * v_old
                gtk = -global_damping * inertia_p * w_old
            v_new = v_old + kick * (fl + fdk + gdk) * i_m
            w_new = w_old + kick * (tl + tdk + gtk) * i_I
            if not (_ANY_STEP and first):
                dx = dt_prev * v_old
                g_dx += g * dx
                fa_dx += fa * dx
                if _ANY_STEP and store_damping:
                    dth = dt_prev * w_old
                    dl += (fd_prev[p, k] + fdk) * dx + (td_prev[p, k] + tdk) * dth
                    dg += (fd_prev[p, 3 + k] + gdk) * dx + (td_prev[p, 3 + k] + gtk) * dth
            if _ANY_STEP and store_damping:
                fd_prev[p, k] = fdk
                td_prev[p, k] = tdk
                fd_prev[p, 3 + k] = gdk
                td_prev[p, 3 + k] = gtk
            # twice the velocities at t
            vm = c_old * v_old + c_new * v_new
            wm = c_old * w_old + c_new * w_new
            vv += vm * vm
            ww += wm * wm
            V[q] = v_new
            W[q] = w_new
            X[q] += dt * v_new
        w_body += m_p * g_dx
        w_app += fa_dx
        d_local -= 0.5 * dl
        d_global -= 0.5 * dg
        ke_t += 0.125 * m_p * vv
        ke_r += 0.125 * inertia_p * ww
        d2, jp2 = moved_since_build(X, V, XR, r, p)
        disp2 = max(disp2, d2)
        jump2 = max(jump2, jp2)
    store_step_terms(acc_out, w_body, w_app, d_local, d_global, ke_t, ke_r, disp2, jump2, dt)


# every loop driver compiled twice: in parallel (prange) and serially, for small
# systems and for sweeps that run one simulation per core
# the pair loop's gather and scatter passes fuse multiply-adds (FMA; measured 1.11x on
# a dense packing); the law itself (law_block) is compiled without
pair_forces, pair_forces_serial = compile_parallel_and_serial(
    _pair_loop, serial_globals={"pair_chunk": pair_chunk_inline}, fastmath=CONTRACT)

#: the pair loops compiled for a kind of law and box, by (parallel, dashpot, periodic)
_PAIR_LOOPS = {}


def pair_loop_for(parallel: bool, dashpot: bool, periodic: bool):
    """The pair loop (:func:`_pair_loop`, threaded or serial) compiled for a law with or
    without dashpot history (``store_dashpot``) and a box with or without periodic axes:
    a copy of its own (its own on-disk cache entry) that refuses other calls. The
    engine's step calls these; :data:`pair_forces` and :data:`pair_forces_serial` are
    the general loops."""
    key = (bool(parallel), bool(dashpot), bool(periodic))
    loop = _PAIR_LOOPS.get(key)
    if loop is None:
        name = "_pair_chunk_{}_{}{}".format("called" if parallel else "inlined",
                                            *(int(f) for f in key[1:]))
        chunk = _with_globals(_pair_chunk, name, {"_PAIR_DASHPOT": int(dashpot),
                                                  "_PAIR_PERIODIC": int(periodic)})
        called = njit(fastmath=CONTRACT, inline="never" if parallel else "always")(chunk)
        driver = _with_globals(_pair_loop, "_pair_loop_{}_{}{}".format(
            "parallel" if parallel else "serial", *(int(f) for f in key[1:])),
            {"pair_chunk": called, "_PAIR_DASHPOT": int(dashpot),
             "_PAIR_PERIODIC": int(periodic)})
        loop = _PAIR_LOOPS[key] = njit(parallel=bool(parallel), fastmath=CONTRACT)(driver)
    return loop

reduce_forces, reduce_forces_serial = compile_parallel_and_serial(_reduce_loop)
integrate, integrate_serial = compile_parallel_and_serial(_integrate_loop, fastmath=CONTRACT)
integrate_plain, integrate_plain_serial = compile_parallel_and_serial(
    _with_globals(_integrate_loop, "_integrate_plain_loop", {"_ANY_STEP": False}),
    fastmath=CONTRACT)
wall_forces, wall_forces_serial = compile_parallel_and_serial(_wall_loop)
rolling_forces, rolling_forces_serial = compile_parallel_and_serial(_rolling_loop)
wall_rolling, wall_rolling_serial = compile_parallel_and_serial(_wall_rolling_loop)


@njit(inline="always")
def _step_move(v, p, dt):
    """|v_p| dt [L]: how far particle p moves in a step of ``dt`` at its velocity now."""
    return dt * math.sqrt(v[p, 0] * v[p, 0] + v[p, 1] * v[p, 1] + v[p, 2] * v[p, 2])


@njit(cache=True)
def closing_beyond_cover(x, v, r, pi, pj, periodic_len, cover, wp, ww, wall_point, wall_normal,
                         wall_cover, dt, boundary) -> int:
    """How many pairs (pi, pj) and wall pairs (wp, ww) are closed at the positions ``x``
    beyond the overlap [L] their cover allows (``cover``, ``wall_cover``: one per pair,
    else none checked; +inf: any, skipped without reading the positions; 0: not
    covered), or will be after one more step of ``dt`` at the velocities ``v`` (each
    overlap taken (|v_i| + |v_j|) dt + ``boundary`` ahead, ``boundary`` the walls' and
    the box's last move [L]): a pass of the geometry alone, which :func:`_advance`
    makes only after a step whose headrooms left room for such a contact. The engine
    covers them before the next step (:meth:`demstep.engine.auto_step.AutoStep.uncovered`
    looks further ahead): a contact closed beyond its cover must not act in a step,
    and a contact about to close had better close at a step certified for it (a light
    particle that closes at a step certified for heavy ones only penetrates deep in
    it, and its spring returns far more energy than it took)."""
    count = 0
    if cover.shape[0] == pi.shape[0]:
        periodic = any_periodic(periodic_len)
        for k in range(pi.shape[0]):
            limit = cover[k]
            if limit == np.inf:
                continue
            i, j = pi[k], pj[k]
            delta = pair_geometry(x[i, 0], x[i, 1], x[i, 2], x[j, 0], x[j, 1], x[j, 2], r[i],
                                  r[j], periodic_len[0], periodic_len[1], periodic_len[2],
                                  periodic)[4]
            delta += _step_move(v, i, dt) + _step_move(v, j, dt) + boundary
            if delta > 0.0 and delta > limit:
                count += 1
    if wall_cover.shape[0] == wp.shape[0]:
        for q in range(wp.shape[0]):
            limit = wall_cover[q]
            if limit == np.inf:
                continue
            p, w = wp[q], ww[q]
            delta = wall_geometry(x[p, 0], x[p, 1], x[p, 2], r[p], wall_point[w, 0],
                                  wall_point[w, 1], wall_point[w, 2], wall_normal[w, 0],
                                  wall_normal[w, 1], wall_normal[w, 2])[4]
            delta += _step_move(v, p, dt) + boundary
            if delta > 0.0 and delta > limit:
                count += 1
    return count


#: ``ledger.counters``: the particle-particle and particle-wall contacts touching after
#: the last step, the largest |v| dt / r of the last step, the contacts found closed
#: beyond the 'auto' step's cover since the engine last reset the count
COUNT_PAIR_CONTACTS, COUNT_WALL_CONTACTS, COUNT_JUMP, COUNT_UNCOVERED = 0, 1, 2, 3
#: ``ledger.counters``: the slots of the drift's displacement bound (:func:`drift_used`)
DRIFT_SUM, DRIFT_OFFSET, DRIFT_WALL_OFFSET, DRIFT_NOW, DRIFT_WALL_NOW = 4, 5, 6, 7, 8
N_COUNTERS = 9


@njit(inline="always")
def drift_used(counters):
    """How far [L] the ends of any pair or wall contact can have moved relative to each
    other since the last check of the certified step's drift: the smaller of two
    bounds. (1) The sum over the steps of 2 r_max (|v| dt / r)_max plus the walls' and
    the box's moves (``counters[4]``): a path length, which grows without bound while
    the particles vibrate in place. (2) Each end moved by at most its displacement,
    |x - x_check| <= |x - x_ref| + |x_ref - x_check| (``x_ref``: the positions of the
    last rebuild; across rebuilds, the displacement of each at its rebuild): 2 (D_check
    + D_rebuilds + D_now) + the walls' and the box's (B_check + B_rebuilds + B_now), D the
    largest particle displacement from its reference, B the kernels' boundary move;
    ``counters[5]``, ``counters[6]`` hold the check's and the rebuilds' D and B (the
    engine sets them; negative: unknown, bound (2) unused), ``counters[7]``,
    ``counters[8]`` D and B after the last step."""
    used = counters[DRIFT_SUM]
    if counters[DRIFT_OFFSET] >= 0.0:
        used = min(used, 2.0 * (counters[DRIFT_OFFSET] + counters[DRIFT_NOW])
                   + counters[DRIFT_WALL_OFFSET] + counters[DRIFT_WALL_NOW])
    return used


def _advance(n_steps, ctl, sph, bodies, pairs, bonds, walls, meshes, box, ledger, params):
    """Run up to ``n_steps`` steps of the documented order
    (:meth:`demstep.engine.Simulation.run`) on the bundles of :mod:`demstep.state`
    (``ctl`` Controls, ``sph`` Spheres, ``bodies`` Bodies, ``pairs`` Pairs, ``bonds`` Bonds,
    ``walls`` Walls, ``meshes`` Meshes, ``box`` Box, ``ledger`` Ledger) with the law's
    parameters ``params`` (its Params tuple, :mod:`demstep.contact.laws`). Compiled twice, with the threaded loops
    (:func:`advance_parallel`) and with the serial ones (:func:`advance_serial`), so that
    a run compiles only the version it uses; :func:`advance` picks by ``ctl.parallel``.
    Returns (steps done, stop reason).

    Periodic box: ``box.motion`` (3,) fixed / rate / servo; ``box.servo`` (3, 5) with
    the columns of the wall ``servo`` (rate in the gain column for BOX_RATE: dL/dt
    [L/T]); ``box.sums`` (6, 3): virial, crossing sum, crossing contacts, their k_n
    sum, the previous crossing sum and the last change of length. ``ledger.counters``
    (5,): particle-particle contacts, particle-wall contacts, largest jump |v| dt / r,
    and (added to, step after step) the contacts closed beyond the overlap the last
    certified time step covered them at (``pairs.cover``, ``walls.cover``; none counted
    when those are empty), and those closed beyond it at the positions a step ends
    with or closing in the next step (:func:`closing_beyond_cover`, looked for when the
    smallest headroom of the step's pair and wall loops leaves room for one): the
    chunk then ends (STOP_UNCOVERED), so that the engine covers such a contact before
    any force of it acts (not one step late). With a finite
    ``ctl.check_budget`` [L], ``counters[4]`` adds up, step after step, how far the
    ends of any pair or wall contact can have moved relative to each other (2 r_max
    (|v| dt / r)_max plus the walls' and the box's moves), ``counters[7]``, ``[8]``
    keep the largest displacement since the lists were built and the boundaries' move,
    and the chunk ends (STOP_CHECK) once the smaller of the two bounds of
    :func:`drift_used` exceeds the budget: the engine then checks the drift of the
    certified step (:meth:`demstep.engine.auto_step.AutoStep.accept`)."""
    x, v, w, r, m = sph.x, sph.v, sph.w, sph.r, sph.m
    inv_m, force, torque = sph.inv_m, sph.force, sph.torque
    acc, energy, counters = ledger.acc, ledger.energy, ledger.counters
    periodic_len, box_state = box.length, box.sums
    wall_point, wall_normal, wall_vel = walls.point, walls.normal, walls.vel
    wall_force, servo = walls.force, walls.servo
    dt = ctl.dt
    dt_prev = ctl.dt_prev
    first = ctl.first
    wall_chunks = pairs.force_band.shape[0] if ctl.parallel else 1
    out = np.empty(8)
    out_bodies = np.empty(8)
    box_sums = np.zeros((4, 3))
    box_rate = np.zeros(3)
    extents = np.empty(3)
    nw = wall_point.shape[0]
    n_chunks = pairs.force_band.shape[0]
    force_band, torque_band = pairs.force_band, pairs.torque_band
    budget = ctl.check_budget
    r_max = 0.0
    if pairs.cover.shape[0] > 0 or walls.cover.shape[0] > 0 or budget < np.inf:
        for p in range(r.shape[0]):
            r_max = max(r_max, r[p])
    for step in range(n_steps):
        # 1. pair contact forces; the slip increment of step n is x(t) - x(t - dt_prev)
        dt_slip = 0.0 if first else dt_prev
        for k in range(3):
            box_rate[k] = 0.0 if first else box_state[5, k] / dt_prev
        e_n, e_t, d_fric, d_dash, n_pp, pp_uncovered, pp_headroom = pair_forces(
            sph, pairs, periodic_len, box_rate, params, dt_slip, ctl.store_dashpot, box_sums)
        # 1b. rolling and twisting resistance of the pairs (a law with it only)
        er_s, er_p, er_v = 0.0, 0.0, 0.0
        if pairs.roll.shape[0] > 0:
            er_s, er_p, er_v = rolling_forces(
                w, r, m, sph.inertia, inv_m, pairs.i, pairs.j, pairs.geo, params,
                dt_slip, pairs.roll, pairs.chunks, pairs.spans, torque, torque_band)
        if n_chunks > 1:
            reduce_forces(force_band, torque_band, pairs.spans, force, torque)
        # 2. particle-wall contact forces
        we_n, we_t, wd_fric, wd_dash, pw_uncovered, pw_headroom = wall_forces(
            sph, walls, params, dt_slip, wall_chunks)
        if walls.roll.shape[0] > 0:
            wr_s, wr_p, wr_v = wall_rolling(
                x, w, r, m, sph.inertia, walls.p, walls.wall, wall_point, wall_normal,
                params, dt_slip, walls.roll, torque, wall_chunks)
            er_s += wr_s
            er_p += wr_p
            er_v += wr_v
        # 2c. triangle-mesh walls (threaded over runs of spheres: a sphere's rows its own)
        me_n, me_t, md_fric, md_dash = 0.0, 0.0, 0.0, 0.0
        if meshes.tri.shape[0] > 0:
            meshes.cover_ctl[3] = dt  # (the look-ahead of the 'auto' step's mesh cover)
            me_n, me_t, md_fric, md_dash, mr_s, mr_p, mr_v = mesh_forces(
                sph, meshes, params, dt_slip, wall_chunks)
            er_s += mr_s
            er_p += mr_p
            er_v += mr_v
        # 2b. parallel bonds (serial: bonds share particles)
        eb_s, eb_r = 0.0, 0.0
        if bonds.i.shape[0] > 0:
            eb_s, eb_r, _ = bond_forces(x, v, w, r, bonds, periodic_len, box_rate, dt_slip,
                                        ctl.dim, force, torque, box_sums)
        for row in range(4):
            for k in range(3):
                box_state[row, k] = box_sums[row, k]
        # 3. boundary work over the last step (trapezoid): walls push particles with -F;
        # a change of periodic length dL does work (crossing sum) * dL on the contacts
        if not first:
            for wi in range(nw):
                acc[A_WALLS] -= 0.5 * ((walls.force_prev[wi, 0] + wall_force[wi, 0]) * walls.disp_prev[wi, 0]
                                       + (walls.force_prev[wi, 1] + wall_force[wi, 1]) * walls.disp_prev[wi, 1]
                                       + (walls.force_prev[wi, 2] + wall_force[wi, 2]) * walls.disp_prev[wi, 2])
            for k in range(3):
                acc[A_BOX] += 0.5 * (box_state[4, k] + box_sums[1, k]) * box_state[5, k]
            # moving meshes: the power they put into the particles, over the last step
            for mk in range(meshes.power.shape[0]):
                acc[A_WALLS] += 0.5 * (meshes.power_prev[mk] + meshes.power[mk]) * dt_prev
        for mk in range(meshes.power.shape[0]):
            meshes.power_prev[mk] = meshes.power[mk]
        # 4. servo-controlled walls: velocity along the normal from the stress error
        wall_areas(wall_point, wall_normal, servo, walls.box_lo, walls.box_hi, periodic_len,
                   ctl.dim, walls.areas)
        for wi in range(nw):
            if walls.motion[wi] == WALL_SERVO:
                push = -(wall_force[wi, 0] * wall_normal[wi, 0] + wall_force[wi, 1] * wall_normal[wi, 1]
                         + wall_force[wi, 2] * wall_normal[wi, 2])
                speed = servo_speed(push / walls.areas[wi], servo[wi, S_TARGET], servo[wi, S_GAIN],
                                    servo[wi, S_FACTOR], walls.areas[wi], walls.contacts[wi],
                                    walls.k_sum[wi], dt, servo[wi, S_MAXSPEED])
                for k in range(3):
                    wall_vel[wi, k] = speed * wall_normal[wi, k]
        # periodic box lengths: prescribed rate or servo on the Love stress
        box_extents(wall_point, walls.box_lo, walls.box_hi, periodic_len, ctl.dim, extents)
        volume = extents[0] * extents[1] * extents[2]
        box_speed = np.zeros(3)
        for k in range(3):
            if periodic_len[k] > 0.0:
                if box.motion[k] == BOX_RATE:
                    box_speed[k] = box.servo[k, S_GAIN]
                elif box.motion[k] == BOX_SERVO:
                    stress = box_sums[0, k] / volume
                    # shrinking the box (negative speed) raises the stress
                    box_speed[k] = -servo_speed(stress, box.servo[k, S_TARGET], box.servo[k, S_GAIN],
                                                box.servo[k, S_FACTOR], volume / periodic_len[k],
                                                int(box_sums[2, k]), box_sums[3, k], dt,
                                                box.servo[k, S_MAXSPEED])
        # 5. central-difference update with damping; particle ledger terms
        if first or ctl.store_damping or ctl.local_damping > 0.0 or ctl.viscous_damping > 0.0:
            integrate(sph, ctl, dt, dt_prev, first, out, bodies.sphere_body)
        else:  # (no damping, not the first step: the copy without those branches)
            integrate_plain(sph, ctl, dt, dt_prev, False, out, bodies.sphere_body)
        if bodies.m.shape[0] > 0:
            # rigid bodies: forces summed from their members, leapfrog, members follow
            body_step(bodies, sph, ctl, dt, dt_prev, first, out_bodies)
            for k in range(6):
                out[k] += out_bodies[k]
            out[6] = max(out[6], out_bodies[6])
            out[7] = max(out[7], out_bodies[7])
        # 6. walls and the periodic box move
        boundary_move = 0.0
        boundary_step = 0.0  # how far a wall or the box moved in this step, at most
        for wi in range(nw):
            d2 = 0.0
            s2 = 0.0
            for k in range(3):
                disp = dt * wall_vel[wi, k] if walls.motion[wi] != WALL_FIXED else 0.0
                wall_point[wi, k] += disp
                walls.disp_prev[wi, k] = disp
                walls.force_prev[wi, k] = wall_force[wi, k]
                dd = wall_point[wi, k] - walls.ref[wi, k]
                d2 += dd * dd
                s2 += disp * disp
            boundary_move = max(boundary_move, math.sqrt(d2))
            boundary_step = max(boundary_step, math.sqrt(s2))
        for k in range(3):
            box_state[4, k] = box_sums[1, k]
            box_state[5, k] = dt * box_speed[k]
            periodic_len[k] += dt * box_speed[k]
            boundary_move += abs(periodic_len[k] - box.ref[k])
            boundary_step += abs(dt * box_speed[k])
        if meshes.tri.shape[0] > 0:  # moving meshes: their corners' moves
            mesh_step = move_meshes(meshes.tri, meshes.tri0, meshes.tri_mesh, meshes.motion,
                                    meshes.vel, meshes.omega, meshes.axis, meshes.center,
                                    meshes.shift, meshes.turn, dt)
            meshes.moved[0] += mesh_step
            meshes.cover_ctl[2] = mesh_step
            boundary_move += meshes.moved[0]
            boundary_step += mesh_step
        # 7. ledger
        acc[A_BODY] += out[0]
        acc[A_APPLIED] += out[1]
        acc[A_LOCAL] += out[2]
        acc[A_GLOBAL] += out[3]
        acc[A_FRICTION] += d_fric + wd_fric + md_fric
        acc[A_DASHPOT] += d_dash + wd_dash + md_dash
        energy[E_KIN_T] = out[4]
        energy[E_KIN_R] = out[5]
        energy[E_STRAIN_N] = e_n + we_n + me_n
        energy[E_STRAIN_T] = e_t + we_t + me_t
        energy[E_STRAIN_R] = er_s
        energy[E_STRAIN_BOND] = eb_s
        acc[A_BOND_BROKEN] += eb_r
        acc[A_ROLLING] += er_p
        acc[A_ROLLING_VISCOUS] += er_v
        counters[COUNT_PAIR_CONTACTS] = n_pp
        wc = 0
        for wi in range(nw):
            wc += walls.contacts[wi]
        for mk in range(meshes.contacts.shape[0]):
            wc += meshes.contacts[mk]
        counters[COUNT_WALL_CONTACTS] = wc
        counters[COUNT_JUMP] = out[7]
        counters[COUNT_UNCOVERED] += pp_uncovered + pw_uncovered + meshes.cover_out[2]
        counters[DRIFT_NOW] = math.sqrt(out[6])
        counters[DRIFT_WALL_NOW] = boundary_move
        if budget < np.inf:  # how far any pair's ends can have moved relative to each other
            counters[DRIFT_SUM] += 2.0 * r_max * out[7] + boundary_step
        if first:
            # the energy held at t = 0 is the ledger's initial input
            acc[A_INITIAL] = (out[4] + out[5] + e_n + we_n + me_n + e_t + we_t + me_t + er_s
                              + eb_s)
        update_peaks(acc, energy)
        dt_prev = dt
        first = False
        # 8. divergence checks, then the expiry of the neighbour lists
        ke = out[4] + out[5]
        if not (math.isfinite(ke) and math.isfinite(e_n + we_n + e_t + we_t + er_s + eb_s)):
            return step + 1, STOP_NONFINITE
        if out[7] > ctl.jump_limit:
            return step + 1, STOP_JUMP
        if ctl.runaway_factor > 0.0 \
                and ke > ctl.runaway_factor * (runaway_reference(acc, energy) + ctl.energy_floor):
            return step + 1, STOP_RUNAWAY
        # contacts closed beyond the cover of the certified step at the positions now,
        # or closing in the next step at these velocities, looked for when the
        # smallest headroom at the start of this step leaves room for one (twice how
        # far a gap can close in a step: both ends' moves, at most r_max (|v| dt / r)_max
        # each, and the walls' or the box's); the engine covers them before the next
        # step's forces (after a rebuild too)
        if min(pp_headroom, pw_headroom) <= 2.0 * (2.0 * r_max * out[7] + boundary_step):
            counters[COUNT_UNCOVERED] += closing_beyond_cover(x, v, r, pairs.i, pairs.j, periodic_len,
                                                pairs.cover, walls.p, walls.wall, wall_point,
                                                wall_normal, walls.cover, dt, boundary_step)
        # neighbour lists expire after skin / 2 of particle, wall or box motion
        if math.sqrt(out[6]) + boundary_move > 0.5 * ctl.skin:
            return step + 1, STOP_REBUILD
        if counters[COUNT_UNCOVERED] > 0:
            return step + 1, STOP_UNCOVERED
        # the drift of the certified step is due for a check (the mesh contacts' drift
        # is measured at every step: :func:`demstep.kernels.meshes.mesh_forces`)
        if drift_used(counters) > budget or meshes.cover_out[0] > meshes.cover_ctl[1]:
            return step + 1, STOP_CHECK
    return n_steps, STOP_DONE


#: the serial loops each serial version of :func:`_advance` calls, by the names it uses
#: (its pair loop comes from :func:`pair_loop_for`)
_SERIAL_LOOPS = {"rolling_forces": rolling_forces_serial,
                 "reduce_forces": reduce_forces_serial, "wall_forces": wall_forces_serial,
                 "mesh_forces": mesh_forces_serial,
                 "wall_rolling": wall_rolling_serial, "integrate": integrate_serial,
                 "integrate_plain": integrate_plain_serial,
                 "body_step": body_step_serial}


@njit
def _no_rolling(*args):
    """Stands in for the rolling-resistance loops in a step compiled without them."""
    return 0.0, 0.0, 0.0


@njit
def _no_bonds(*args):
    """Stands in for the bond loop in a step compiled without bonds."""
    return 0.0, 0.0, 0


@njit
def _no_bodies(*args):
    """Stands in for the rigid-body step in a step compiled without clumps."""
    return None


@njit
def _no_mesh_forces(*args):
    """Stands in for the mesh contacts in a step compiled without meshes."""
    return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0


@njit
def _no_mesh_moves(*args):
    """Stands in for the meshes' motion in a step compiled without meshes."""
    return 0.0


#: the compiled versions of the step made so far, by (parallel, rolling, bonds, bodies)
_STEPS = {}


def step_kernel(parallel: bool, rolling: bool, bonds: bool, bodies: bool,
                dashpot: bool = True, periodic: bool = True, meshes: bool = False):
    """The compiled step (:func:`_advance`) with the threaded or the serial loops and
    only the features a run uses: a law without rolling resistance, a run without
    bonds or clumps does not compile (or load) their loops; the pair loop is the one
    compiled for the law's dashpot history and the box (:func:`pair_loop_for`). Each
    version has its own name, so its own on-disk cache entry."""
    key = (bool(parallel), bool(rolling), bool(bonds), bool(bodies), bool(dashpot),
           bool(periodic), bool(meshes))
    kernel = _STEPS.get(key)
    if kernel is None:
        overrides = {} if parallel else dict(_SERIAL_LOOPS)
        overrides["pair_forces"] = pair_loop_for(parallel, dashpot, periodic)
        if not rolling:
            overrides.update(rolling_forces=_no_rolling, wall_rolling=_no_rolling)
        if not bonds:
            overrides["bond_forces"] = _no_bonds
        if not bodies:
            overrides["body_step"] = _no_bodies
        if not meshes:
            overrides.update(mesh_forces=_no_mesh_forces, move_meshes=_no_mesh_moves)
        name = "advance_{}_{}{}{}{}{}{}".format("parallel" if parallel else "serial",
                                                *(int(f) for f in key[1:]))
        kernel = _STEPS[key] = njit(_with_globals(_advance, name, overrides))
    return kernel


def advance(n_steps, ctl, sph, bodies, pairs, bonds, walls, meshes, box, ledger, params):
    """:func:`_advance` compiled for this call's loops (threaded when ``ctl.parallel``)
    and features (rolling history, bonds, rigid bodies, meshes present), with the pair
    loop for its law's dashpot history and its box (periodic axes or none)."""
    run = step_kernel(ctl.parallel, pairs.roll.shape[0] > 0 or walls.roll.shape[0] > 0,
                      bonds.i.shape[0] > 0, bodies.m.shape[0] > 0, ctl.store_dashpot,
                      bool(any_periodic(box.length)), meshes.tri.shape[0] > 0)
    return run(n_steps, ctl, sph, bodies, pairs, bonds, walls, meshes, box, ledger, params)
