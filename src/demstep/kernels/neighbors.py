"""Neighbour search: cell list with a Verlet skin, pair lists sorted by (i, j).

A pair (i < j) enters the list when |x_j - x_i| < r_i + r_j + skin (minimum image on
periodic axes). The list stays valid until some particle (or wall) has moved more
than skin / 2 since it was built. Lists are sorted by the key i * N + j so that
contact history carries over a rebuild by a merge (:func:`transfer_history`).
"""

from __future__ import annotations

import numba
import numpy as np

from demstep._numba import njit, prange
from demstep.contact.geometry import any_periodic, minimum_image
from demstep.errors import InputError
from demstep.scratch import Workspace


@njit(parallel=True)
def _bin(x, lo, inv_cell, ncell, cell_of, start, members):
    """Counting sort of the particles by cell into ``start`` (ncells+1,) and ``members``
    (N,), the particle indices in cell order (``cell_of`` (N,): scratch)."""
    n = x.shape[0]
    ncells = ncell[0] * ncell[1] * ncell[2]
    for p in prange(n):
        c = 0
        for k in range(3):
            ck = int(np.floor((x[p, k] - lo[k]) * inv_cell[k]))
            if ck < 0:
                ck = 0
            if ck >= ncell[k]:
                ck = ncell[k] - 1
            c = c * ncell[k] + ck
        cell_of[p] = c
    for c in prange(ncells + 1):
        start[c] = 0
    for p in range(n):
        start[cell_of[p] + 1] += 1
    for c in range(ncells):
        start[c + 1] += start[c]
    for p in range(n):  # start[c] runs up to the next cell's start...
        c = cell_of[p]
        members[start[c]] = p
        start[c] += 1
    for c in range(ncells, 0, -1):  # ...and back
        start[c] = start[c - 1]
    start[0] = 0


#: the most solid volume one cell of the neighbour grid (a side of 2 r_max + skin) may
#: hold, as a multiple of the cell's volume, before the search refuses: a packing fills
#: at most about 0.74 of it (disks counted as spheres, less); several times the cell
#: means particles piled on one another, and the pair list would grow as the square of
#: their number (a periodic box far smaller than the particles' extent, say)
MAX_CELL_FILL = 8.0


@njit(parallel=True)
def _build_pairs(x, r, lo, inv_cell, ncell, periodic_len, skin, n_threads, capacity, cell_of,
                 start, members, xs, rs, buf_a, buf_b):
    """One sweep of a half stencil (each cell against itself and its 13 forward
    neighbours: z + 1 and the columns (x, y + 1), (x + 1, y - 1 .. y + 1)), each of ``n_threads`` chunks over its own run of cells, pairs written
    to per-chunk buffers of ``capacity``; then a counting sort into rows i < j, each row sorted.
    Returns (pi, pj, needed): ``needed`` > 0 (pi, pj empty) when a buffer overflowed,
    -1 when a cell holds more than :data:`MAX_CELL_FILL` times its volume in spheres
    (found before the pairs are searched). Scratch (:class:`~demstep.scratch.Workspace`): ``cell_of``
    (N + 1,), ``start`` (ncells + 1,), ``members`` (N,), ``xs`` (N, 3), ``rs`` (N,), the
    buffers ``buf_a``, ``buf_b`` (n_threads, capacity) of int32 particle indices."""
    n = x.shape[0]
    len0, len1, len2 = periodic_len[0], periodic_len[1], periodic_len[2]
    n0, n1, n2 = ncell[0], ncell[1], ncell[2]
    ncells = n0 * n1 * n2
    periodic = any_periodic(periodic_len)
    _bin(x, lo, inv_cell, ncell, cell_of, start, members)
    # positions and radii in cell order: the inner loop reads contiguous memory
    for m in prange(n):
        q = members[m]
        xs[m, 0], xs[m, 1], xs[m, 2] = x[q, 0], x[q, 1], x[q, 2]
        rs[m] = r[q]
    limit = MAX_CELL_FILL / (inv_cell[0] * inv_cell[1] * inv_cell[2] * (4.0 / 3.0 * np.pi))
    crowded = 0
    for c in prange(ncells):
        solid = 0.0
        for m in range(start[c], start[c + 1]):
            solid += rs[m] ** 3
        if solid > limit:
            crowded += 1
    if crowded:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64), -1
    # runs of cells holding about equal numbers of particles
    bounds = np.empty(n_threads + 1, dtype=np.int64)
    bounds[0] = 0
    c = 0
    for t in range(1, n_threads):
        target = (n * t) // n_threads
        while c < ncells and start[c] < target:
            c += 1
        bounds[t] = c
    bounds[n_threads] = ncells
    found = np.zeros(n_threads, dtype=np.int64)
    # each thread's stencil ranges, between 64-byte pads (no cache line shared)
    seg_all = np.empty((n_threads, 20, 2), dtype=np.int64)
    for t in prange(n_threads):
        k = 0
        # particle ranges to test against the particles of a cell: cells adjacent along
        # z are adjacent in cell order, so each column of the stencil is one range of
        # ``members`` (two where it wraps around a periodic z)
        seg = seg_all[t, 4:16]
        for c in range(bounds[t], bounds[t + 1]):
            if start[c] == start[c + 1]:
                continue
            cz = c % n2
            cy = (c // n2) % n1
            cx = c // (n1 * n2)
            n_seg = 0
            # own column: the cell itself (from the particle after m, below) and z + 1
            own_end = start[c + 2] if cz + 1 < n2 else start[c + 1]
            if cz + 1 >= n2 and len2 > 0.0:
                base = c - cz
                seg[n_seg, 0], seg[n_seg, 1] = start[base], start[base + 1]
                n_seg += 1
            # the forward columns (0, +1) and (+1, -1..+1), each over z - 1 .. z + 1
            for col in range(4):
                dx = 0 if col == 0 else 1
                dy = 1 if col == 0 else col - 2
                ox = cx + dx
                if ox >= n0:
                    if len0 > 0.0:
                        ox -= n0
                    else:
                        continue
                oy = cy + dy
                if oy < 0 or oy >= n1:
                    if len1 > 0.0:
                        oy = (oy + n1) % n1
                    else:
                        continue
                base = (ox * n1 + oy) * n2
                if len2 > 0.0 and cz == 0:
                    seg[n_seg, 0], seg[n_seg, 1] = start[base], start[base + 2]
                    seg[n_seg + 1, 0], seg[n_seg + 1, 1] = start[base + n2 - 1], start[base + n2]
                    n_seg += 2
                elif len2 > 0.0 and cz == n2 - 1:
                    seg[n_seg, 0], seg[n_seg, 1] = start[base + cz - 1], start[base + n2]
                    seg[n_seg + 1, 0], seg[n_seg + 1, 1] = start[base], start[base + 1]
                    n_seg += 2
                else:
                    z_lo = cz - 1 if cz > 0 else 0
                    z_hi = cz + 2 if cz + 2 <= n2 else n2
                    seg[n_seg, 0], seg[n_seg, 1] = start[base + z_lo], start[base + z_hi]
                    n_seg += 1
            for m in range(start[c], start[c + 1]):
                x0, x1, x2, rm = xs[m, 0], xs[m, 1], xs[m, 2], rs[m]
                for s_k in range(-1, n_seg):
                    first = m + 1 if s_k < 0 else seg[s_k, 0]
                    last = own_end if s_k < 0 else seg[s_k, 1]
                    for m2 in range(first, last):
                        d0 = xs[m2, 0] - x0
                        d1 = xs[m2, 1] - x1
                        d2 = xs[m2, 2] - x2
                        if periodic:  # (a loop-invariant test: 20 % of a build)
                            d0, d1, d2 = minimum_image(d0, d1, d2, len0, len1, len2)[:3]
                        reach = rm + rs[m2] + skin
                        if d0 * d0 + d1 * d1 + d2 * d2 < reach * reach:
                            if k < capacity:
                                p, q = members[m], members[m2]
                                if p < q:
                                    buf_a[t, k], buf_b[t, k] = p, q
                                else:
                                    buf_a[t, k], buf_b[t, k] = q, p
                            k += 1
        found[t] = k
    needed = found.max()
    if needed > capacity:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64), needed
    # counting sort by i, then each (short) row by j (in the binning's scratch)
    row = cell_of[:n + 1]
    row[:] = 0
    for t in range(n_threads):
        for k in range(found[t]):
            row[buf_a[t, k] + 1] += 1
    for p in range(n):
        row[p + 1] += row[p]
    total = row[n]
    pi = np.empty(total, dtype=np.int64)
    pj = np.empty(total, dtype=np.int64)
    at = members  # (read no more)
    for p in range(n):
        at[p] = row[p]
    for t in range(n_threads):
        for k in range(found[t]):
            a = buf_a[t, k]
            pj[at[a]] = buf_b[t, k]
            at[a] += 1
    for p in prange(n):
        lo_k, hi_k = row[p], row[p + 1]
        for a in range(lo_k + 1, hi_k):
            key = pj[a]
            b = a - 1
            while b >= lo_k and pj[b] > key:
                pj[b + 1] = pj[b]
                b -= 1
            pj[b + 1] = key
        for k in range(lo_k, hi_k):
            pi[k] = p
    return pi, pj, 0


@njit(parallel=True)
def _bounds(x):
    """Smallest and largest coordinate along each axis of the points ``x`` (N, 3):
    per-run extremes (runs in parallel), then the extremes of those."""
    n = x.shape[0]
    n_runs = max(1, min(64, n // 4096))
    lo_run = np.full((n_runs, 3), np.inf)
    hi_run = np.full((n_runs, 3), -np.inf)
    for t in prange(n_runs):
        for p in range((n * t) // n_runs, (n * (t + 1)) // n_runs):
            for k in range(3):
                lo_run[t, k] = min(lo_run[t, k], x[p, k])
                hi_run[t, k] = max(hi_run[t, k], x[p, k])
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for t in range(n_runs):
        for k in range(3):
            lo[k] = min(lo[k], lo_run[t, k])
            hi[k] = max(hi[k], hi_run[t, k])
    return lo, hi


def build_pair_list(x, r, skin: float, periodic_len, expected_pairs: int | None = None,
                    work=None):
    """Verlet pairs (pi, pj), i < j, sorted by (i, j). ``x`` (N, 3); ``periodic_len``
    (3,) box lengths, 0 for non-periodic axes (periodic boxes start at 0);
    ``expected_pairs`` (e.g. the previous list's length) sizes the work buffers;
    ``work`` (:class:`~demstep.scratch.Workspace`) keeps the scratch from one build to the next."""
    if len(r) < 2:  # (no pair: a run that starts empty and fills by insertion)
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    # cells a hair wider than the longest reach: rounding cannot split a pair in reach
    # over two cells that are not neighbours
    reach = (2.0 * float(r.max()) + skin) * (1.0 + 1e-9)
    periodic_len = np.asarray(periodic_len, dtype=np.float64)
    lo, hi = _bounds(x)  # numpy's min(axis=0) of an (N, 3) array: 40x slower
    lo -= 1e-9
    hi += 1e-9
    ncell = np.ones(3, dtype=np.int64)
    cell = np.ones(3)
    max_cells = 8 * len(r) + 1000  # cells per axis at most (and in all, below)
    for k in range(3):
        if periodic_len[k] > 0:
            lo[k] = 0.0
            nc = int(min(periodic_len[k] // reach, max_cells))
            if nc < 3:
                raise InputError(f"periodic: box length {periodic_len[k]:g} along axis {'xyz'[k]} "
                                 f"must be at least 3 x (2 r_max + skin) = {3 * reach:g}")
            ncell[k], cell[k] = nc, periodic_len[k] / nc
        else:
            span = hi[k] - lo[k]
            if not np.isfinite(span):
                raise InputError(f"positions: coordinates along {'xyz'[k]} are not finite or "
                                 f"span more than float64 holds ({lo[k]:.3g} to {hi[k]:.3g})")
            nc = max(1, int(min(span // reach, max_cells)))
            # cap the grid so that a dilute assembly does not allocate a huge cell array
            ncell[k], cell[k] = nc, max(span / nc, reach)
    while int(ncell[0]) * int(ncell[1]) * int(ncell[2]) > max_cells:  # no int64 overflow
        k = int(np.argmax(ncell))
        if periodic_len[k] > 0 and ncell[k] <= 3:
            break
        ncell[k] = max(1, ncell[k] // 2)
        cell[k] = (periodic_len[k] if periodic_len[k] > 0 else hi[k] - lo[k]) / ncell[k]
        cell[k] = max(cell[k], reach)
    n_threads = numba.get_num_threads()
    expected = 4 * len(r) if expected_pairs is None else int(expected_pairs)
    capacity = int(1.5 * expected / n_threads) + 1024
    work = work if work is not None else Workspace()
    n, ncells = len(r), int(np.prod(ncell))
    if n >= 2**31:
        raise InputError(f"particles: at most 2**31 - 1 per simulation, got {n}")
    scratch = (work.array("cell_of", (n + 1,), np.int64),
               work.array("start", (ncells + 1,), np.int64, grow=True),
               work.array("members", (n,), np.int64),
               work.array("xs", (n, 3), np.float64), work.array("rs", (n,), np.float64))
    args = (x, r, lo, 1.0 / cell, ncell, periodic_len, float(skin), n_threads)
    while True:
        buf_a = work.array("buf_a", (n_threads, capacity), np.int32, grow=True, spare=True)
        buf_b = work.array("buf_b", (n_threads, capacity), np.int32, grow=True, spare=True)
        pi, pj, needed = _build_pairs(*args, buf_a.shape[1], *scratch, buf_a, buf_b)
        if needed < 0:
            raise _crowding_error(x, r, lo, cell, ncell)
        if not needed:
            return pi, pj
        capacity = int(needed)  # a thread's buffer was too small: again with what it needed


def _crowding_error(x, r, lo, cell, ncell) -> InputError:
    """The error for a cell of the grid holding more than :data:`MAX_CELL_FILL` times its
    volume in spheres (the pair search found one; this names it)."""
    idx = np.clip(np.floor((x - lo) / cell).astype(np.int64), 0, ncell - 1)
    flat = (idx[:, 0] * ncell[1] + idx[:, 1]) * ncell[2] + idx[:, 2]
    solid = np.bincount(flat, weights=(4.0 / 3.0 * np.pi) * r ** 3)
    worst = int(np.argmax(solid))
    fill = float(solid[worst]) / float(np.prod(cell))
    count = int(np.count_nonzero(flat == worst))
    return InputError(f"particles: {count} particles lie within one neighbour cell (a side of "
                      f"{float(cell.min()):.3g}) with {fill:.3g} times its volume: they "
                      f"overlap heavily (a periodic box much smaller than the particles' "
                      f"extent, or overlapping input positions)")


@njit(parallel=True)
def _build_wall_pairs(x, r, wall_point, wall_normal, skin, n_chunks, capacity, buf_p, buf_w):
    """(particle, wall) pairs within reach, sorted by (particle, wall): ``n_chunks``
    runs of particles searched in parallel into the buffers ``buf_p``, ``buf_w``
    (n_chunks, capacity) of int32, then joined; (empty, empty, needed) when a buffer was
    too small."""
    n = x.shape[0]
    nw = wall_point.shape[0]
    found = np.zeros(n_chunks, dtype=np.int64)
    for t in prange(n_chunks):
        m = 0
        for p in range((n * t) // n_chunks, (n * (t + 1)) // n_chunks):
            x0, x1, x2, reach = x[p, 0], x[p, 1], x[p, 2], r[p] + skin
            for w in range(nw):
                d = ((x0 - wall_point[w, 0]) * wall_normal[w, 0]
                     + (x1 - wall_point[w, 1]) * wall_normal[w, 1]
                     + (x2 - wall_point[w, 2]) * wall_normal[w, 2])
                if d < reach:
                    if m < capacity:
                        buf_p[t, m] = p
                        buf_w[t, m] = w
                    m += 1
        found[t] = m
    needed = found.max()
    if needed > capacity:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64), needed
    offset = np.zeros(n_chunks + 1, dtype=np.int64)
    for t in range(n_chunks):
        offset[t + 1] = offset[t] + found[t]
    wp = np.empty(offset[n_chunks], dtype=np.int64)
    ww = np.empty(offset[n_chunks], dtype=np.int64)
    for t in prange(n_chunks):
        for m in range(found[t]):
            wp[offset[t] + m] = buf_p[t, m]
            ww[offset[t] + m] = buf_w[t, m]
    return wp, ww, 0


def build_wall_list(x, r, wall_point, wall_normal, skin: float, expected_pairs: int | None = None,
                    work=None):
    """Particle-wall candidate pairs (particle, wall) sorted by (particle, wall);
    ``work`` (:class:`~demstep.scratch.Workspace`) keeps the search's buffers between builds."""
    n_walls = len(wall_point)
    if n_walls == 0 or len(r) == 0:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    n_chunks = numba.get_num_threads()
    expected = len(r) if expected_pairs is None else int(expected_pairs)
    capacity = min((len(r) // n_chunks + 1) * n_walls, int(2 * expected / n_chunks) + 1024)
    work = work if work is not None else Workspace()
    args = (x, r, wall_point, wall_normal, float(skin), n_chunks)
    while True:
        buf_p = work.array("wall_p", (n_chunks, capacity), np.int32, grow=True, spare=True)
        buf_w = work.array("wall_w", (n_chunks, capacity), np.int32, grow=True, spare=True)
        wp, ww, needed = _build_wall_pairs(*args, buf_p.shape[1], buf_p, buf_w)
        if not needed:
            return wp, ww
        capacity = int(needed)


@njit(inline="always")
def _before(a0, b0, a1, b1):
    """(a0, b0) < (a1, b1) in lexicographic order."""
    return a0 < a1 or (a0 == a1 and b0 < b1)


@njit(parallel=True)
def _positions_in_old(old_a, old_b, new_a, new_b, n_chunks):
    """Index in the old list of each new pair (-1 if absent); both lists sorted by (a, b).
    A merge in ``n_chunks`` independent runs of the new list, each starting where a
    binary search puts its first pair in the old list."""
    n_new = new_a.shape[0]
    n_old = old_a.shape[0]
    pos = np.empty(n_new, dtype=np.int64)
    for t in prange(n_chunks):
        m0 = (n_new * t) // n_chunks
        m1 = (n_new * (t + 1)) // n_chunks
        if m0 >= m1:
            continue
        lo, hi = 0, n_old  # first old pair not before new pair m0
        while lo < hi:
            mid = (lo + hi) // 2
            if _before(old_a[mid], old_b[mid], new_a[m0], new_b[m0]):
                lo = mid + 1
            else:
                hi = mid
        k = lo
        for m in range(m0, m1):
            a, b = new_a[m], new_b[m]
            while k < n_old and _before(old_a[k], old_b[k], a, b):
                k += 1
            pos[m] = k if (k < n_old and old_a[k] == a and old_b[k] == b) else -1
    return pos


@njit(parallel=True)
def _gather_rows(old, pos):
    """Rows of ``old`` (n_old, w) at ``pos``; zero rows where pos < 0."""
    out = np.empty((pos.shape[0], old.shape[1]), dtype=old.dtype)
    for m in prange(pos.shape[0]):
        k = pos[m]
        for c in range(old.shape[1]):
            out[m, c] = old[k, c] if k >= 0 else 0
    return out


@njit(parallel=True)
def _gather_rows3(a, b, c, pos):
    """:func:`_gather_rows` of three float arrays in one pass over ``pos`` (a rebuild
    carries the tangential spring, the dashpot force and the stored energy together);
    an array with no rows gives an output with none."""
    n = pos.shape[0]
    out_a = np.empty((n if a.shape[0] else 0, a.shape[1]))
    out_b = np.empty((n if b.shape[0] else 0, b.shape[1]))
    out_c = np.empty((n if c.shape[0] else 0, c.shape[1]))
    for m in prange(n):
        k = pos[m]
        if out_a.shape[0]:
            for w in range(a.shape[1]):
                out_a[m, w] = a[k, w] if k >= 0 else 0.0
        if out_b.shape[0]:
            for w in range(b.shape[1]):
                out_b[m, w] = b[k, w] if k >= 0 else 0.0
        if out_c.shape[0]:
            for w in range(c.shape[1]):
                out_c[m, w] = c[k, w] if k >= 0 else 0.0
    return out_a, out_b, out_c


def transfer_history(old_a, old_b, new_a, new_b, *old_arrays):
    """Carry per-pair arrays (e.g. tangential springs) from an old pair list to a new
    one, both sorted by (a, b); pairs that are new get zeros. Float arrays are carried
    three at a time in one pass (:func:`_gather_rows3`)."""
    pos = _positions_in_old(old_a, old_b, new_a, new_b, numba.get_num_threads())
    flat = [np.ascontiguousarray(arr).reshape(len(arr), int(np.prod(arr.shape[1:])))
            for arr in old_arrays]
    rows = [None] * len(flat)
    floats = [k for k, arr in enumerate(flat) if arr.dtype == np.float64 and len(arr)]
    for g in range(0, len(floats), 3):
        group = floats[g:g + 3]
        if len(group) == 1:
            continue
        padded = [flat[k] for k in group] + [np.empty((0, 1))] * (3 - len(group))
        for k, out in zip(group, _gather_rows3(*padded, pos)):
            rows[k] = out
    for k, arr in enumerate(flat):
        if rows[k] is None:
            rows[k] = _gather_rows(arr, pos)
    return [out.reshape((len(pos),) + arr.shape[1:]) for out, arr in zip(rows, old_arrays)]
