"""Neighbour search: cell list with a Verlet skin, pair lists sorted by (i, j).

A pair (i < j) enters the list when |x_j - x_i| < r_i + r_j + skin (minimum image on
periodic axes). The list stays valid until some particle (or wall) has moved more
than skin / 2 since it was built. Lists are sorted by the key i * N + j so that
contact history carries over a rebuild by a merge (:func:`transfer_history`).
"""

from __future__ import annotations

import numpy as np

from demstep._numba import njit, prange
from demstep.errors import InputError


@njit
def _cell_coords(x, lo, cell, ncell):
    n = x.shape[0]
    coords = np.empty((n, 3), dtype=np.int64)
    for p in range(n):
        for k in range(3):
            c = int(np.floor((x[p, k] - lo[k]) / cell[k]))
            if c < 0:
                c = 0
            if c >= ncell[k]:
                c = ncell[k] - 1
            coords[p, k] = c
    return coords


@njit
def _bin(coords, ncell):
    n = coords.shape[0]
    ncells = ncell[0] * ncell[1] * ncell[2]
    cell_of = np.empty(n, dtype=np.int64)
    start = np.zeros(ncells + 1, dtype=np.int64)
    for p in range(n):
        c = (coords[p, 0] * ncell[1] + coords[p, 1]) * ncell[2] + coords[p, 2]
        cell_of[p] = c
        start[c + 1] += 1
    for c in range(ncells):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    members = np.empty(n, dtype=np.int64)
    for p in range(n):
        c = cell_of[p]
        members[fill[c]] = p
        fill[c] += 1
    return start, members


@njit(inline="always")
def _neighbours_of(p, x, r, coords, ncell, len0, len1, len2, start, members, skin, out,
                   offset, count_only):
    """Pairs (p, q > p) within reach; writes q into out[offset:] (unless count_only);
    returns the count. Inlined: array arguments to a called function would cost a
    reference-count update per particle."""
    found = 0
    xp0, xp1, xp2 = x[p, 0], x[p, 1], x[p, 2]
    for dx in range(-1, 2):
        cx = coords[p, 0] + dx
        if len0 > 0.0:
            cx = (cx + ncell[0]) % ncell[0]
        elif cx < 0 or cx >= ncell[0]:
            continue
        for dy in range(-1, 2):
            cy = coords[p, 1] + dy
            if len1 > 0.0:
                cy = (cy + ncell[1]) % ncell[1]
            elif cy < 0 or cy >= ncell[1]:
                continue
            for dz in range(-1, 2):
                cz = coords[p, 2] + dz
                if len2 > 0.0:
                    cz = (cz + ncell[2]) % ncell[2]
                elif cz < 0 or cz >= ncell[2]:
                    continue
                c = (cx * ncell[1] + cy) * ncell[2] + cz
                for m in range(start[c], start[c + 1]):
                    q = members[m]
                    if q <= p:
                        continue
                    d0 = x[q, 0] - xp0
                    d1 = x[q, 1] - xp1
                    d2 = x[q, 2] - xp2
                    if len0 > 0.0:
                        d0 -= len0 * np.rint(d0 / len0)
                    if len1 > 0.0:
                        d1 -= len1 * np.rint(d1 / len1)
                    if len2 > 0.0:
                        d2 -= len2 * np.rint(d2 / len2)
                    reach = r[p] + r[q] + skin
                    if d0 * d0 + d1 * d1 + d2 * d2 < reach * reach:
                        if not count_only:
                            out[offset + found] = q
                        found += 1
    return found


@njit(parallel=True)
def _build_pairs(x, r, lo, cell, ncell, periodic_len, skin):
    n = x.shape[0]
    len0, len1, len2 = periodic_len[0], periodic_len[1], periodic_len[2]
    coords = _cell_coords(x, lo, cell, ncell)
    start, members = _bin(coords, ncell)
    counts = np.zeros(n + 1, dtype=np.int64)
    dummy = np.empty(0, dtype=np.int64)
    for p in prange(n):
        counts[p + 1] = _neighbours_of(p, x, r, coords, ncell, len0, len1, len2, start,
                                       members, skin, dummy, 0, True)
    for p in range(n):
        counts[p + 1] += counts[p]
    pj = np.empty(counts[n], dtype=np.int64)
    pi = np.empty(counts[n], dtype=np.int64)
    for p in prange(n):
        lo_k, hi_k = counts[p], counts[p + 1]
        _neighbours_of(p, x, r, coords, ncell, len0, len1, len2, start, members, skin, pj,
                       lo_k, False)
        # insertion sort of the (few) neighbours of p: the list is sorted by (i, j)
        for a in range(lo_k + 1, hi_k):
            key = pj[a]
            b = a - 1
            while b >= lo_k and pj[b] > key:
                pj[b + 1] = pj[b]
                b -= 1
            pj[b + 1] = key
        for k in range(lo_k, hi_k):
            pi[k] = p
    return pi, pj


def build_pair_list(x, r, skin: float, periodic_len):
    """Verlet pairs (pi, pj), i < j, sorted by (i, j). ``x`` (N, 3); ``periodic_len``
    (3,) box lengths, 0 for non-periodic axes (periodic boxes start at 0)."""
    reach = 2.0 * float(r.max()) + skin
    periodic_len = np.asarray(periodic_len, dtype=np.float64)
    lo = x.min(axis=0) - 1e-9
    hi = x.max(axis=0) + 1e-9
    ncell = np.ones(3, dtype=np.int64)
    cell = np.ones(3)
    for k in range(3):
        if periodic_len[k] > 0:
            lo[k] = 0.0
            nc = int(periodic_len[k] // reach)
            if nc < 3:
                raise InputError(f"periodic: box length {periodic_len[k]:g} along axis {'xyz'[k]} "
                                 f"must be at least 3 x (2 r_max + skin) = {3 * reach:g}")
            ncell[k], cell[k] = nc, periodic_len[k] / nc
        else:
            span = hi[k] - lo[k]
            nc = max(1, int(span // reach))
            # cap the grid so that a dilute assembly does not allocate a huge cell array
            ncell[k], cell[k] = nc, max(span / nc, reach)
    while ncell.prod() > 8 * len(r) + 1000:
        k = int(np.argmax(ncell))
        if periodic_len[k] > 0 and ncell[k] <= 3:
            break
        ncell[k] = max(1, ncell[k] // 2)
        cell[k] = (periodic_len[k] if periodic_len[k] > 0 else hi[k] - lo[k]) / ncell[k]
        cell[k] = max(cell[k], reach)
    return _build_pairs(x, r, lo, cell, ncell, periodic_len, float(skin))


@njit
def _build_wall_pairs(x, r, wall_point, wall_normal, skin):
    n = x.shape[0]
    nw = wall_point.shape[0]
    count = 0
    for w in range(nw):
        for p in range(n):
            d = 0.0
            for k in range(3):
                d += (x[p, k] - wall_point[w, k]) * wall_normal[w, k]
            if d < r[p] + skin:
                count += 1
    wp = np.empty(count, dtype=np.int64)
    ww = np.empty(count, dtype=np.int64)
    m = 0
    for p in range(n):
        for w in range(nw):
            d = 0.0
            for k in range(3):
                d += (x[p, k] - wall_point[w, k]) * wall_normal[w, k]
            if d < r[p] + skin:
                wp[m] = p
                ww[m] = w
                m += 1
    return wp, ww


def build_wall_list(x, r, wall_point, wall_normal, skin: float):
    """Particle-wall candidate pairs (particle, wall) sorted by (particle, wall)."""
    return _build_wall_pairs(x, r, wall_point, wall_normal, float(skin))


@njit
def _transfer(old_key, new_key):
    """Position in the old list of each new key (-1 if absent); both lists sorted."""
    pos = np.full(new_key.shape[0], -1, dtype=np.int64)
    a = 0
    for b in range(new_key.shape[0]):
        while a < old_key.shape[0] and old_key[a] < new_key[b]:
            a += 1
        if a < old_key.shape[0] and old_key[a] == new_key[b]:
            pos[b] = a
    return pos


def transfer_history(old_a, old_b, new_a, new_b, n_b: int, *old_arrays):
    """Carry per-pair arrays (e.g. tangential springs) from an old sorted pair list to a
    new one; pairs that are new get zeros. Keys are a * n_b + b (both lists sorted)."""
    pos = _transfer(old_a * n_b + old_b, new_a * n_b + new_b)
    hit = pos >= 0
    out = []
    for arr in old_arrays:
        o = np.zeros((len(pos),) + arr.shape[1:], dtype=arr.dtype)
        o[hit] = arr[pos[hit]]
        out.append(o)
    return out
