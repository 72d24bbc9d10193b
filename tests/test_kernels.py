"""Each kernel against a slow pure-numpy reference (tests/reference.py)."""

import os
import subprocess
import sys
from collections import namedtuple

import numpy as np
import pytest

from demstep.contact.laws import HertzMindlin, LinearSpring, damping_ratio_from_restitution
from demstep.kernels import dem
from demstep.kernels.neighbors import build_pair_list, transfer_history

import reference

# The loops read the state bundles by field (demstep.state); these tests build the
# arrays one by one, so they call the loops through bundles of just those fields.
_Spheres = namedtuple("_Spheres", "x v w r m inv_m inv_I inertia force torque applied "
                                  "damp_force damp_torque x_ref")
_Pairs = namedtuple("_Pairs", "i j shear dashpot shear_energy chunks spans force_band "
                              "torque_band geo cover")
_Controls = namedtuple("_Controls", "gravity local_damping viscous_damping store_damping")


def pair_call(loop):
    """The pair loop ``loop`` taking its arrays in the order of its bundles' fields."""
    def call(x, v, w, r, m, inv_m, pi, pj, periodic_len, box_rate, params, dt, ft, fd, etan,
             store_dashpot, chunks, spans, force, torque, force_band, torque_band, box_sums,
             geo, cover):
        none = np.zeros((0, 3))
        sph = _Spheres(x, v, w, r, m, inv_m, inv_m, r, force, torque, none, none, none, none)
        pairs = _Pairs(pi, pj, ft, fd, etan, chunks, spans, force_band, torque_band, geo, cover)
        return loop(sph, pairs, periodic_len, box_rate, params, dt, store_dashpot, box_sums)
    return call


def integrate_call(loop):
    """The integrator ``loop`` taking its arrays one by one."""
    def call(x, v, w, m, inertia, inv_m, inv_I, r, force, torque, f_app, gravity, dt, dt_prev,
             local_damping, global_damping, fd_prev, td_prev, x_ref, first, store_damping,
             acc_out, sphere_body):
        sph = _Spheres(x, v, w, r, m, inv_m, inv_I, inertia, force, torque, f_app, fd_prev,
                       td_prev, x_ref)
        ctl = _Controls(gravity, local_damping, global_damping, store_damping)
        return loop(sph, ctl, dt, dt_prev, first, acc_out, sphere_body)
    return call


PAIR_FORCES, PAIR_FORCES_SERIAL = pair_call(dem.pair_forces), pair_call(dem.pair_forces_serial)


def pair_loop_for(*kind):
    return pair_call(dem.pair_loop_for(*kind))


def random_cloud(seed, n=200, dim=3, box=8.0):
    rng = np.random.default_rng(seed)
    x = np.zeros((n, 3))
    x[:, :dim] = rng.uniform(0, box, (n, dim))
    r = rng.uniform(0.3, 0.6, n)
    return rng, x, r


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("periodic", [False, True])
def test_pair_list_equals_brute_force(dim, periodic):
    rng, x, r = random_cloud(3 + dim, dim=dim)
    skin = 0.2
    box = np.zeros(3)
    if periodic:
        box[:dim] = 8.0
    pi, pj = build_pair_list(x, r, skin, box)
    got = set(zip(pi.tolist(), pj.tolist()))
    assert got == reference.brute_force_pairs(x, r, skin, box if periodic else None)
    key = pi * len(r) + pj
    assert np.all(np.diff(key) > 0)  # sorted by (i, j), no duplicates


@pytest.mark.parametrize("n_threads", [1, 3])
@pytest.mark.parametrize("axis", [0, 2])
def test_pair_list_chunks_and_buffer_overflow(n_threads, axis):
    """Dense polydisperse cloud in a box periodic along one axis with exactly three
    cells (the stencil wraps at both ends): the per-thread buffers overflow first (the
    build reports the size it needs); the rebuilt list equals brute force whatever the
    number of chunks."""
    from demstep.kernels.neighbors import _build_pairs

    rng = np.random.default_rng(11 + axis)
    n = 300
    r = rng.uniform(0.2, 0.6, n)
    skin = 0.1
    reach = (2 * r.max() + skin) * (1 + 1e-9)
    box = np.zeros(3)
    box[axis] = 3 * reach + 1e-6
    x = rng.uniform(0, 5, (n, 3))
    x[:, axis] = rng.uniform(0, box[axis], n)
    lo = x.min(axis=0) - 1e-9
    lo[axis] = 0.0
    ncell = np.full(3, max(1, int(5 // reach)), dtype=np.int64)
    inv_cell = ncell / 5.1
    ncell[axis], inv_cell[axis] = 3, 3 / box[axis]
    ncells = int(np.prod(ncell))
    scratch = (np.empty(n + 1, np.int64), np.empty(ncells + 1, np.int64), np.empty(n, np.int64),
               np.empty((n, 3)), np.empty(n))
    args = (x, r, lo, inv_cell, ncell, box, skin, n_threads)

    def buffers(capacity):
        return np.empty((n_threads, capacity), np.int32), np.empty((n_threads, capacity), np.int32)

    pi, pj, needed = _build_pairs(*args, 5, *scratch, *buffers(5))
    assert needed > 5 and len(pi) == 0
    pi, pj, again = _build_pairs(*args, int(needed), *scratch, *buffers(int(needed)))
    assert again == 0
    assert set(zip(pi.tolist(), pj.tolist())) == reference.brute_force_pairs(x, r, skin, box)
    assert np.all(np.diff(pi * n + pj) > 0)


@pytest.mark.parametrize("n,side", [(50, 4), (30_000, 40)])
def test_binning_is_a_stable_sort_by_cell(n, side):
    """The counting sort of the particles by cell against numpy's stable argsort by
    cell: the same members, cell starts and cells, with a few cells and with 64,000,
    empty cells included."""
    from demstep.kernels.neighbors import _bin

    rng = np.random.default_rng(n)
    x = rng.uniform(0.0, 1.0, (n, 3)) ** 2  # crowded near 0: many empty cells too
    ncell = np.full(3, side, dtype=np.int64)
    lo, inv_cell = np.zeros(3), np.full(3, float(side))
    ncells = side ** 3
    cell_of, start, members = np.empty(n + 1, np.int64), np.empty(ncells + 1, np.int64), \
        np.empty(n, np.int64)
    start[:] = -7  # garbage: zeroed first
    _bin(x, lo, inv_cell, ncell, cell_of, start, members)
    idx = np.minimum((x * side).astype(np.int64), side - 1)
    cell = (idx[:, 0] * side + idx[:, 1]) * side + idx[:, 2]
    np.testing.assert_array_equal(cell_of[:n], cell)
    np.testing.assert_array_equal(members, np.argsort(cell, kind="stable"))
    np.testing.assert_array_equal(start, np.searchsorted(np.sort(cell), np.arange(ncells + 1)))


def test_pair_lists_from_kept_scratch_equal_brute_force():
    """One Workspace through builds of clouds whose size, extent (number of cells),
    pair count (the buffers overflow and grow) and thread count change: every list
    equals brute force, as a build with fresh scratch does."""
    import numba

    from demstep.scratch import Workspace

    work = Workspace()
    threads = numba.get_num_threads()
    try:
        for k, (n, box, chunks) in enumerate([(200, 8.0, 1), (200, 4.0, 2), (350, 12.0, 2),
                                              (120, 3.0, 1), (350, 5.0, 2)]):
            numba.set_num_threads(min(chunks, threads))
            rng, x, r = random_cloud(20 + k, n=n, box=box)
            pi, pj = build_pair_list(x, r, 0.2, np.zeros(3), expected_pairs=10, work=work)
            assert set(zip(pi.tolist(), pj.tolist())) == reference.brute_force_pairs(x, r, 0.2)
            assert np.all(np.diff(pi * n + pj) > 0)
    finally:
        numba.set_num_threads(threads)


def test_transfer_history_keeps_common_pairs():
    old_i, old_j = np.array([0, 0, 1, 3]), np.array([1, 2, 2, 4])
    hist = np.arange(8.0).reshape(4, 2)
    new_i, new_j = np.array([0, 1, 2, 3]), np.array([2, 2, 3, 4])
    (out,) = transfer_history(old_i, old_j, new_i, new_j, hist)
    assert np.array_equal(out, [[2, 3], [4, 5], [0, 0], [6, 7]])


def overlapping_pairs(seed):
    rng, x, r = random_cloud(seed, n=120, box=4.0)
    pi, pj = build_pair_list(x, r, 0.1, np.zeros(3))
    v = rng.normal(0, 1, (len(r), 3))
    w = rng.normal(0, 1, (len(r), 3))
    m = rng.uniform(0.5, 2, len(r))
    P = len(pi)
    ft = rng.normal(0, 1.0, (P, 3))
    fd = rng.normal(0, 0.5, (P, 3))
    etan = np.sum(ft**2, axis=1) / (2 * 800.0)
    return x, v, w, r, m, pi, pj, ft, fd, etan


def chunk_buffers(pi, pj, n, n_chunks):
    """The pair loop's chunks, spans, particle forces and torques and band buffers, all
    NaN (rows a chunk must zero first: NaN must not leak out)."""
    chunks, spans = dem.pair_chunks(pi, pj, n, n_chunks)
    rows = dem.band_rows(spans, n) + 3  # (the engine's are longer too)
    f, t = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
    fbuf = np.full((n_chunks, rows if n_chunks > 1 else 0, 3), np.nan)
    return chunks, spans, f, t, fbuf, fbuf.copy()


def reduced(kernel, fbuf, tbuf, spans, f, t):
    """The particle forces and torques once the bands are added (several chunks)."""
    if len(spans) > 1:
        (dem.reduce_forces_serial if kernel == "serial" else dem.reduce_forces)(
            fbuf, tbuf, spans, f, t)
    return f, t


@pytest.mark.parametrize("kernel", ["serial", "parallel"])
def test_pair_forces_equal_numpy_reference(kernel):
    x, v, w, r, m, pi, pj, ft, fd, etan = overlapping_pairs(5)
    law = LinearSpring(k_n=1000.0, k_s=800.0, mu=0.4, damping_normal=3.0, damping_tangential=2.0)
    params = law.params()
    dt = 1e-3
    P = len(pi)
    ref = reference.linear_pair_forces(x, v, w, r, m, np.stack([pi, pj], 1), 1000.0, 800.0,
                                       0.4, 3.0, 2.0, dt, ft.copy(), fd.copy(), etan.copy())
    n_chunks = 1 if kernel == "serial" else 3
    chunks, spans, f, t, fbuf, tbuf = chunk_buffers(pi, pj, len(r), n_chunks)
    sums = np.zeros((4, 3))
    fn = PAIR_FORCES_SERIAL if kernel == "serial" else PAIR_FORCES
    ft2, fd2, et2 = ft.copy(), fd.copy(), etan.copy()
    # the cover of each pair (0: none, inf: any overlap, else an overlap limit)
    delta = r[pi] + r[pj] - np.linalg.norm(x[pj] - x[pi], axis=1)
    cover = np.choose(np.arange(P) % 3, [np.zeros(P), np.full(P, np.inf), 0.5 * np.abs(delta)])
    e_n, e_t, fric, dash, nc, uncovered, headroom = fn(
        x, v, w, r, m, 1.0 / m, pi, pj, np.zeros(3), np.zeros(3), params, dt, ft2, fd2, et2,
        True, chunks, spans, f, t, fbuf, tbuf, sums, np.empty((P, 4)), cover)
    assert uncovered == np.count_nonzero(delta > cover) > 0
    # the smallest headroom cover - delta over every pair (here a touching one's < 0)
    assert headroom == pytest.approx(np.min(cover - delta), rel=1e-12) and headroom < 0
    assert nc == np.count_nonzero(delta > 0)
    force, new_t, new_fd, new_et, ref_en, ref_fric, ref_dash, arm_i, arm_j, n = ref
    tol = dict(rtol=1e-10, atol=1e-12)
    assert np.allclose(ft2, new_t, **tol)
    assert np.allclose(fd2, new_fd, **tol)
    assert np.allclose(et2, new_et, **tol)
    assert e_n == pytest.approx(ref_en.sum(), rel=1e-10)
    assert e_t == pytest.approx(new_et.sum(), rel=1e-10)
    assert fric == pytest.approx(ref_fric.sum(), rel=1e-9)
    assert dash == pytest.approx(ref_dash.sum(), rel=1e-9)
    touching = (r[pi] + r[pj] - np.linalg.norm(x[pj] - x[pi], axis=1)) > 0
    assert nc == touching.sum()
    # the virial: sum of F_on_j d over pairs
    assert np.allclose(sums[0], np.sum(force * (x[pj] - x[pi]), axis=0), rtol=1e-10)
    # per-particle sums against np.add.at, once the chunks' bands are added
    f, t = reduced(kernel, fbuf, tbuf, spans, f, t)
    f_ref, t_ref = reference.gather(np.stack([pi, pj], 1), force, n, arm_i, arm_j, len(r))
    assert np.allclose(f, f_ref, rtol=1e-10, atol=1e-10)
    assert np.allclose(t, t_ref, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("kernel", ["serial", "parallel"])
def test_hertz_pair_forces_equal_numpy_reference(kernel):
    """Hertz-Mindlin with restitution dashpots and friction against the textbook
    formulas in numpy (tests/reference.py), forces, springs, energies and per-particle
    sums."""
    x, v, w, r, m, pi, pj, ft, fd, etan = overlapping_pairs(6)
    law = HertzMindlin(youngs_modulus=2000.0, poisson_ratio=0.3, mu=0.4, restitution=0.6,
                       restitution_tangential=0.8)
    params = law.params()
    dt = 1e-3
    P = len(pi)
    beta_n = damping_ratio_from_restitution(0.6)
    beta_t = damping_ratio_from_restitution(0.8)
    ref = reference.hertz_pair_forces(x, v, w, r, m, np.stack([pi, pj], 1), 2000.0, 0.3, 0.4,
                                      beta_n, beta_t, dt, ft.copy(), fd.copy(), etan.copy())
    force, new_t, new_fd, new_et, ref_en, ref_fric, ref_dash, arm_i, arm_j, n = ref
    touching = (r[pi] + r[pj] - np.linalg.norm(x[pj] - x[pi], axis=1)) > 0
    sliding = touching & (np.linalg.norm(new_t, axis=1) > 0) & np.isclose(
        np.linalg.norm(new_t, axis=1), 0.4 * np.linalg.norm(force - new_t - new_fd, axis=1))
    assert 0 < sliding.sum() < touching.sum()  # both sticking and sliding contacts
    n_chunks = 1 if kernel == "serial" else 3
    chunks, spans, f, t, fbuf, tbuf = chunk_buffers(pi, pj, len(r), n_chunks)
    sums = np.zeros((4, 3))
    fn = PAIR_FORCES_SERIAL if kernel == "serial" else PAIR_FORCES
    ft2, fd2, et2 = ft.copy(), fd.copy(), etan.copy()
    e_n, e_t, fric, dash, nc, _, _ = fn(x, v, w, r, m, 1.0 / m, pi, pj, np.zeros(3), np.zeros(3),
                                  params, dt, ft2, fd2, et2, True, chunks, spans,
                                  f, t, fbuf, tbuf, sums, np.empty((P, 4)), np.zeros(0))
    tol = dict(rtol=1e-10, atol=1e-12)
    assert np.allclose(ft2, new_t, **tol)
    assert np.allclose(fd2, new_fd, **tol)
    assert np.allclose(et2, new_et, **tol)
    assert e_n == pytest.approx(ref_en.sum(), rel=1e-10)
    assert e_t == pytest.approx(new_et.sum(), rel=1e-10)
    assert fric == pytest.approx(ref_fric.sum(), rel=1e-9)
    assert dash == pytest.approx(ref_dash.sum(), rel=1e-9)
    assert nc == touching.sum()
    assert np.allclose(sums[0], np.sum(force * (x[pj] - x[pi]), axis=0), rtol=1e-10)
    f, t = reduced(kernel, fbuf, tbuf, spans, f, t)
    f_ref, t_ref = reference.gather(np.stack([pi, pj], 1), force, n, arm_i, arm_j, len(r))
    assert np.allclose(f, f_ref, rtol=1e-10, atol=1e-10)
    assert np.allclose(t, t_ref, rtol=1e-10, atol=1e-10)


def test_pair_forces_without_dashpot_skip_its_history():
    """A law without dashpots: skipping the (all-zero) dashpot history gives the same
    forces, springs and energies as carrying it."""
    x, v, w, r, m, pi, pj, ft, fd, etan = overlapping_pairs(6)
    params = LinearSpring(k_n=1000.0, k_s=800.0, mu=0.4).params()
    P = len(pi)
    results = []
    for store in (True, False):
        ft2, fd2, et2 = ft.copy(), np.zeros((P, 3)), etan.copy()
        f, t = np.zeros((len(r), 3)), np.zeros((len(r), 3))
        out = PAIR_FORCES_SERIAL(x, v, w, r, m, 1.0 / m, pi, pj, np.zeros(3), np.zeros(3),
                                     params, 1e-3, ft2, fd2, et2, store, np.array([0, P]),
                                     np.array([[0, len(r)]]), f, t, np.zeros((1, 0, 3)),
                                     np.zeros((1, 0, 3)), np.zeros((4, 3)), np.empty((P, 4)),
                                     np.zeros(0))
        assert not fd2.any()
        results.append((out, ft2, et2, f, t))
    (o1, *a1), (o2, *a2) = results
    assert o1 == o2
    assert all(np.array_equal(p, q) for p, q in zip(a1, a2))
    assert o1[4] > 0 and np.abs(a1[2]).max() > 0  # contacts did push


INTEGRATORS = {"serial": integrate_call(dem.integrate_serial),
               "parallel": integrate_call(dem.integrate),
               "plain_serial": integrate_call(dem.integrate_plain_serial),
               "plain": integrate_call(dem.integrate_plain)}


@pytest.mark.parametrize("kernel, store_damping",
                         [(k, s) for k in INTEGRATORS for s in (True, False)
                          if not (k.startswith("plain") and s)])
def test_integrate_equals_numpy_leapfrog(kernel, store_damping):
    """The undamped leapfrog step after the first, by the integrator that takes any step
    and by its copy for plain steps (which the engine calls only without damping
    history), each serial and threaded."""
    rng, x, r = random_cloud(9, n=50)
    v = rng.normal(0, 1, (50, 3))
    w = rng.normal(0, 1, (50, 3))
    m = rng.uniform(0.5, 2, 50)
    inertia = 0.4 * m * r**2
    force = rng.normal(0, 3, (50, 3))
    torque = rng.normal(0, 3, (50, 3))
    g = np.array([0.0, 0.0, -9.81])
    dt = 1e-2
    x_ref, v_ref, w_ref = reference.leapfrog(x, v, w, m, inertia, force, torque, g, dt)
    out = np.zeros(8)
    xx, vv, ww = x.copy(), v.copy(), w.copy()
    INTEGRATORS[kernel](
        xx, vv, ww, m, inertia, 1 / m, 1 / inertia, r, force, torque, np.zeros((50, 3)), g, dt, dt,
        0.0, 0.0, np.zeros((50, 6)), np.zeros((50, 6)), x.copy(), False, store_damping, out,
        np.full(50, -1))
    assert np.allclose(xx, x_ref, rtol=1e-14, atol=1e-14)
    assert np.allclose(vv, v_ref, rtol=1e-14, atol=1e-14)
    assert np.allclose(ww, w_ref, rtol=1e-14, atol=1e-14)
    # kinetic energy from the mean of the half-step velocities
    ke = 0.5 * np.sum(m[:, None] * (0.5 * (v + v_ref)) ** 2)
    assert out[4] == pytest.approx(ke, rel=1e-12)
    # gravity work over the previous step m g . dt v_old
    assert out[0] == pytest.approx(np.sum(m * (v @ g)) * dt, rel=1e-12)


def test_pure_python_kernels_match_compiled():
    """NUMBA_DISABLE_JIT=1 runs every kernel as Python; a short run must agree."""
    script = (
        "import numpy as np, sys\n"
        "from demstep.particles import Particles\n"
        "from demstep.engine import Simulation, TimeStep\n"
        "from demstep.contact.laws import LinearSpring\n"
        "rng = np.random.default_rng(1)\n"
        "x = np.stack(np.meshgrid(*[np.arange(3) * 1.9] * 3, indexing='ij'), -1).reshape(-1, 3)\n"
        "p = Particles.from_density(x, np.full(27, 1.0), 1.0)\n"
        "sim = Simulation(p, LinearSpring(k_n=1e3, mu=0.3, restitution=0.7),\n"
        "                 velocities=rng.normal(0, 1, (27, 3)), timestep=TimeStep.fixed(1e-3))\n"
        "sim.run(steps=60)\n"
        "np.save(sys.argv[1], np.concatenate([sim.x.ravel(), sim.v.ravel(), sim.w.ravel(),\n"
        "        sim.ledger.acc, sim.ledger.energy]))\n")
    outs = {}
    for jit in ("0", "1"):
        path = f"/tmp/demstep_jit_{jit}_{os.getpid()}.npy"
        env = {**os.environ, "NUMBA_DISABLE_JIT": jit}
        subprocess.run([sys.executable, "-c", script, path], check=True, env=env, timeout=600)
        outs[jit] = np.load(path)
        os.unlink(path)
    assert np.allclose(outs["0"], outs["1"], rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("n_chunks", [1, 2, 3, 5])
def test_pair_chunk_spans_cover_every_particle(n_chunks):
    """Chunks start at a particle's first pair, so every i of a chunk's pairs is its own
    (the own ranges tile the particles in order) and its j lie in its span; about equal
    numbers of pairs each. The reduction adds each band (the span past the own range)
    to the particles it holds, in chunk order, and nothing else."""
    rng, x, r = random_cloud(11, n=200, box=5.0)
    pi, pj = build_pair_list(x, r, 0.2, np.zeros(3))
    n = len(r) + 7  # particles past the last pair's j
    chunks, spans = dem.pair_chunks(pi, pj, n, n_chunks)
    own_hi = np.append(spans[1:, 0], n)
    assert spans[0, 0] == 0 and np.all(own_hi >= spans[:, 0])
    assert chunks[0] == 0 and chunks[-1] == len(pi) and np.all(np.diff(chunks) >= 0)
    assert np.all(pi[chunks[1:-1]] != pi[chunks[1:-1] - 1])  # cut at particle starts
    assert np.diff(chunks).max() - np.diff(chunks).min() <= 2 * np.bincount(pi).max()
    rows = int(np.max(spans[:, 1] - own_hi, initial=0))
    assert dem.band_rows(spans, n) == rows
    f0, t0 = rng.normal(0, 1, (n, 3)), rng.normal(0, 1, (n, 3))
    fbuf, tbuf = np.full((n_chunks, rows + 2, 3), np.nan), np.full((n_chunks, rows + 2, 3), np.nan)
    expected_f, expected_t = f0.copy(), t0.copy()
    for c in range(n_chunks):
        lo, hi = spans[c]
        a, b = chunks[c], chunks[c + 1]
        assert np.all((pi[a:b] >= lo) & (pi[a:b] < own_hi[c]) & (pj[a:b] < hi))
        band = max(hi - own_hi[c], 0)
        fbuf[c, :band] = rng.normal(0, 1, (band, 3))
        tbuf[c, :band] = rng.normal(0, 1, (band, 3))
        expected_f[own_hi[c]:own_hi[c] + band] += fbuf[c, :band]
        expected_t[own_hi[c]:own_hi[c] + band] += tbuf[c, :band]
    if n_chunks > 1:
        assert rows > 0  # the bands are exercised
    for reduce in (dem.reduce_forces_serial, dem.reduce_forces):
        f, t = f0.copy(), t0.copy()
        reduce(fbuf, tbuf, spans, f, t)
        assert np.allclose(f, expected_f, rtol=1e-14, atol=1e-14)
        assert np.allclose(t, expected_t, rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("n_chunks", [1, 3])
def test_wall_list_equals_brute_force_and_retries(n_chunks):
    """(particle, wall) pairs within r + skin of each wall plane, sorted, from several
    particle runs; a capacity too small for them is detected and retried."""
    from demstep.kernels.neighbors import _build_wall_pairs, build_wall_list

    _, x, r = random_cloud(12, n=400, box=6.0)
    point = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 6.0], [3.0, 0.0, 0.0]])
    normal = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.6, 0.8, 0.0]])
    skin = 0.25
    dist = np.einsum("pwk,wk->pw", x[:, None, :] - point[None], normal)
    p_ref, w_ref = np.nonzero(dist < (r + skin)[:, None])  # row-major: sorted by (p, w)
    args = (x, r, point, normal, skin, n_chunks)

    def buffers(capacity):
        return np.empty((n_chunks, capacity), np.int32), np.empty((n_chunks, capacity), np.int32)

    wp, ww, needed = _build_wall_pairs(*args, 5, *buffers(5))
    assert len(wp) == 0 and needed > 5
    wp, ww, needed = _build_wall_pairs(*args, int(needed), *buffers(int(needed)))
    assert needed == 0
    assert np.array_equal(wp, p_ref) and np.array_equal(ww, w_ref)
    wp, ww = build_wall_list(x, r, point, normal, skin, expected_pairs=1)
    assert np.array_equal(wp, p_ref) and np.array_equal(ww, w_ref)
    # kept buffers, grown by the first build, then reused by a build of fewer pairs
    from demstep.scratch import Workspace

    work = Workspace()
    for shift in (0.0, 1.5):
        xs = x + [0.0, 0.0, shift]
        d = np.einsum("pwk,wk->pw", xs[:, None, :] - point[None], normal)
        p_ref, w_ref = np.nonzero(d < (r + skin)[:, None])
        wp, ww = build_wall_list(xs, r, point, normal, skin, expected_pairs=1, work=work)
        assert np.array_equal(wp, p_ref) and np.array_equal(ww, w_ref)


@pytest.mark.parametrize("n", [1, 4095, 70001])
def test_bounds_equal_numpy_extremes(n):
    from demstep.kernels.neighbors import _bounds

    x = np.random.default_rng(n).normal(0, 10, (n, 3))
    lo, hi = _bounds(x)
    assert np.array_equal(lo, x.min(axis=0)) and np.array_equal(hi, x.max(axis=0))


@pytest.mark.parametrize("n_chunks", [1, 2, 5, 7])
def test_pair_blocks_any_chunking_equal_numpy_reference(n_chunks):
    """The pair loop runs in blocks of PAIR_BLOCK pairs (gather, vectorised law,
    scatter): chunk boundaries anywhere inside a block, partial last blocks, pairs apart
    with history (released) and without (no force, history stays zero) all give the
    numpy reference's forces, torques, history and ledger."""
    x, v, w, r, m, pi, pj, ft, fd, etan = overlapping_pairs(7)
    P = len(pi)
    assert P > 3 * dem.PAIR_BLOCK  # several blocks, the last one partial
    apart = (r[pi] + r[pj] - np.linalg.norm(x[pj] - x[pi], axis=1)) <= 0
    quiet = apart & (np.arange(P) % 2 == 0)  # half of the pairs apart carry no history
    ft[quiet], fd[quiet], etan[quiet] = 0.0, 0.0, 0.0
    assert quiet.sum() > 5 and (apart & ~quiet).sum() > 5
    law = LinearSpring(k_n=1000.0, k_s=800.0, mu=0.4, damping_normal=3.0, damping_tangential=2.0)
    dt = 1e-3
    ref = reference.linear_pair_forces(x, v, w, r, m, np.stack([pi, pj], 1), 1000.0, 800.0,
                                       0.4, 3.0, 2.0, dt, ft.copy(), fd.copy(), etan.copy())
    force, new_t, new_fd, new_et, ref_en, ref_fric, ref_dash, arm_i, arm_j, n = ref
    chunks, spans, f, t, fbuf, tbuf = chunk_buffers(pi, pj, len(r), n_chunks)
    ft2, fd2, et2 = ft.copy(), fd.copy(), etan.copy()
    fn = PAIR_FORCES_SERIAL if n_chunks == 1 else PAIR_FORCES
    e_n, e_t, fric, dash, nc, _, _ = fn(x, v, w, r, m, 1.0 / m, pi, pj, np.zeros(3), np.zeros(3),
                                  law.params(), dt, ft2, fd2, et2, True, chunks, spans, f, t,
                                  fbuf, tbuf, np.zeros((4, 3)), np.empty((0, 4)), np.zeros(0))
    tol = dict(rtol=1e-10, atol=1e-12)
    assert np.allclose(ft2, new_t, **tol) and np.allclose(fd2, new_fd, **tol)
    assert np.allclose(et2, new_et, **tol)
    assert not ft2[quiet].any() and not fd2[quiet].any() and not et2[quiet].any()
    assert e_n == pytest.approx(ref_en.sum(), rel=1e-10)
    assert fric == pytest.approx(ref_fric.sum(), rel=1e-9)
    assert dash == pytest.approx(ref_dash.sum(), rel=1e-9)
    assert nc == (~apart).sum()
    f, t = reduced("parallel", fbuf, tbuf, spans, f, t)
    f_ref, t_ref = reference.gather(np.stack([pi, pj], 1), force, n, arm_i, arm_j, len(r))
    assert np.allclose(f, f_ref, rtol=1e-10, atol=1e-10)
    assert np.allclose(t, t_ref, rtol=1e-10, atol=1e-10)


def test_reach_speed_equals_numpy():
    """|v| + h |a| per particle, a = (F + F_app) / m + g, zero acceleration of gravity on
    a fixed particle (inv_m 0): the compiled kernel against numpy."""
    from demstep.kernels.integration import reach_speed

    rng = np.random.default_rng(4)
    n = 50
    v, f, fa = (rng.normal(0, 1, (n, 3)) for _ in range(3))
    inv_m = rng.uniform(0.5, 2.0, n)
    inv_m[::7] = 0.0
    g = np.array([0.0, -1.0, -9.81])
    out = np.empty(n)
    reach_speed(v, f, fa, inv_m, g, 0.25, out)
    acc = (f + fa) * inv_m[:, None] + g * (inv_m[:, None] > 0)
    ref = np.linalg.norm(v, axis=1) + 0.25 * np.linalg.norm(acc, axis=1)
    assert np.allclose(out, ref, rtol=1e-14, atol=0)
    assert np.allclose(out[::7], np.linalg.norm(v[::7], axis=1) + 0.25 * np.linalg.norm(
        (f + fa)[::7] * 0.0, axis=1))


def test_rolling_loop_in_chunks_equals_one_chunk():
    """The rolling and twisting moments summed in three chunks (own rows directly, the
    rest through the bands and the reduction) equal one chunk's, and so do the history
    and the energies."""
    x, v, w, r, m, pi, pj, ft, fd, etan = overlapping_pairs(8)
    P = len(pi)
    law = LinearSpring(k_n=1000.0, k_s=800.0, mu=0.4, rolling_convention="beta",
                       rolling_stiffness=0.3, twisting_stiffness=0.2, rolling_friction=0.05,
                       twisting_friction=0.05, rolling_damping=0.3)
    params = law.params()
    inertia = 0.4 * m * r**2
    geo = np.empty((P, 4))
    PAIR_FORCES_SERIAL(x, v, w, r, m, 1.0 / m, pi, pj, np.zeros(3), np.zeros(3), params,
                           1e-3, ft.copy(), fd.copy(), etan.copy(), True, np.array([0, P]),
                           np.array([[0, len(r)]]), np.zeros((len(r), 3)),
                           np.zeros((len(r), 3)), np.zeros((1, 0, 3)), np.zeros((1, 0, 3)),
                           np.zeros((4, 3)), geo, np.zeros(0))
    roll0 = np.random.default_rng(2).normal(0, 1e-3, (P, 8))
    results = []
    for n_chunks in (1, 3):
        chunks, spans, f, t, fbuf, tbuf = chunk_buffers(pi, pj, len(r), n_chunks)
        t[:] = 0.0
        if n_chunks > 1:
            tbuf[:] = 0.0  # (the pair loop zeroes the bands; here the rolling loop alone)
        roll = roll0.copy()
        fn = dem.rolling_forces_serial if n_chunks == 1 else dem.rolling_forces
        out = fn(w, r, m, inertia, 1.0 / m, pi, pj, geo, params, 1e-3, roll, chunks, spans,
                 t, tbuf)
        if n_chunks > 1:
            dem.reduce_forces(fbuf * 0.0, tbuf, spans, np.zeros((len(r), 3)), t)
            assert np.abs(tbuf).max() > 0  # some moments went through a band
        results.append((np.array(out), roll, t))
    (o1, h1, t1), (o3, h3, t3) = results
    assert np.abs(t1).max() > 0
    assert np.allclose(o1, o3, rtol=1e-12) and np.array_equal(h1, h3)
    assert np.allclose(t1, t3, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("parallel", [False, True])
@pytest.mark.parametrize("dashpot", [False, True])
@pytest.mark.parametrize("periodic", [False, True])
def test_pair_loop_for_a_law_and_box_equals_the_general_one(parallel, dashpot, periodic):
    """The pair loops compiled for a law's dashpot history and a box (the engine's) give
    the general loop's forces, history, sums and counts to the bit, pairs through a
    periodic boundary included; called for another law or box, they refuse."""
    rng, x, r = random_cloud(8, n=150, box=4.0)
    box = np.array([4.0, 0.0, 0.0]) if periodic else np.zeros(3)
    pi, pj = build_pair_list(x, r, 0.1, box)
    n, P = len(r), len(pi)
    if periodic:
        assert np.any(np.abs(x[pj, 0] - x[pi, 0]) > 2.0)  # some pairs cross the boundary
    v, w = rng.normal(0, 1, (n, 3)), rng.normal(0, 1, (n, 3))
    m = rng.uniform(0.5, 2, n)
    law = LinearSpring(k_n=1000.0, k_s=800.0, mu=0.4, restitution=0.6 if dashpot else None)
    params = law.params()
    assert params.has_dashpots == dashpot
    ft0, fd0 = rng.normal(0, 1, (P, 3)), rng.normal(0, 0.5, (P, 3)) * dashpot
    n_chunks = 3 if parallel else 1

    def call(fn, store_dashpot=dashpot):
        chunks, spans, f, t, fbuf, tbuf = chunk_buffers(pi, pj, n, n_chunks)
        ft, fd, et = ft0.copy(), fd0.copy(), np.sum(ft0**2, axis=1) / 1600.0
        sums = np.zeros((4, 3))
        cover = np.full(P, 0.01)
        out = fn(x, v, w, r, m, 1.0 / m, pi, pj, box, np.array([0.1, 0.0, 0.0]), params,
                 1e-3, ft, fd, et, store_dashpot, chunks, spans, f, t, fbuf, tbuf, sums,
                 np.empty((0, 4)), cover)
        f, t = reduced("parallel" if parallel else "serial", fbuf, tbuf, spans, f, t)
        return out, [ft, fd, et, sums, f, t]

    general, g_arrays = call(PAIR_FORCES if parallel else PAIR_FORCES_SERIAL)
    special_loop = pair_loop_for(parallel, dashpot, periodic)
    special, s_arrays = call(special_loop)
    assert special == general and general[4] > 0 and general[5] > 0
    assert all(np.array_equal(a, b) for a, b in zip(g_arrays, s_arrays))
    if periodic:
        assert g_arrays[3][2, 0] > 0  # contacts through the boundary were counted
    with pytest.raises(ValueError, match="another kind of law"):
        call(special_loop, store_dashpot=not dashpot)
    with pytest.raises(ValueError, match="another kind of box"):
        call(pair_loop_for(parallel, dashpot, not periodic))


def test_a_pair_across_a_moving_periodic_boundary_is_its_unwrapped_image():
    """A pair touching across a periodic boundary whose length changes at the rate
    Ldot gives the forces, torques and dashpot history of the same pair unwrapped in an
    open box, with j at its image x_j - L moving at v_j - Ldot (the image moves with the
    box: a sign error in the image's velocity changes the dashpot and shear forces)."""
    L, rate = 4.0, 0.7
    law = LinearSpring(k_n=1000.0, k_s=800.0, mu=0.4, damping_normal=3.0,
                       damping_tangential=2.0)
    r = np.array([0.35, 0.35])
    m = np.array([1.0, 1.3])
    v = np.array([[0.1, 0.2, -0.1], [-0.3, 0.05, 0.2]])
    w = np.array([[0.3, -0.2, 0.1], [0.2, 0.4, -0.3]])
    wrapped = np.array([[0.3, 1.0, 1.0], [L - 0.3, 1.1, 1.0]])
    image, v_image = wrapped.copy(), v.copy()
    image[1, 0] -= L
    v_image[1, 0] -= rate

    def forces(x, vel, box, box_rate):
        f, t = np.zeros((2, 3)), np.zeros((2, 3))
        ft, fd, et = np.zeros((1, 3)), np.zeros((1, 3)), np.zeros(1)
        PAIR_FORCES_SERIAL(x, vel, w, r, m, 1.0 / m, np.array([0]), np.array([1]), box,
                               box_rate, law.params(), 1e-3, ft, fd, et, True,
                               np.array([0, 1]), np.array([[0, 2]]), f, t,
                               np.zeros((1, 0, 3)), np.zeros((1, 0, 3)), np.zeros((4, 3)),
                               np.empty((1, 4)), np.zeros(0))
        return f, t, ft, fd

    across = forces(wrapped, v, np.array([L, 0.0, 0.0]), np.array([rate, 0.0, 0.0]))
    unwrapped = forces(image, v_image, np.zeros(3), np.zeros(3))
    assert np.abs(across[0]).max() > 0 and np.abs(across[3]).max() > 0
    for a, b in zip(across, unwrapped):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-13)
