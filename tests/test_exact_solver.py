"""The matrix-free eigensolver of the exact step: threaded products against the serial
ones and the assembled matrices, the one-pass Rayleigh terms and projections, the
thick-restart Lanczos iteration against dense eigh, and the damped iteration with loose
intermediate solves against all-tight ones, ARPACK and the dense path."""

from dataclasses import replace

import numpy as np
import pytest
import scipy.linalg

from conftest import random_polydisperse
from demstep.kernels.timestep_kernels import (_chunked_scaled_matvec_parallel,
                                              _chunked_scaled_matvec_serial, contact_chunks,
                                              contact_matvec, ordered_contact_runs,
                                              ordered_scaled_contact_matvec,
                                              contact_gram, contact_quadratic_forms)
from demstep.timestep.contacts import ContactSet
from demstep.timestep.assembly import assemble_stiffness, inverse_sqrt_mass
from demstep.timestep.elements import dofs_per_particle
from demstep.timestep.damping import GlobalDamping
from demstep.errors import InputError
from demstep.timestep.eigen import EIGSH_TOL, lanczos_top, top_eigenpair
from demstep.timestep.exact import ScaledContactOperator, exact_critical_step


def damped_assembly(seed, dim, n=64, walls=True, fixed=True):
    p, c = random_polydisperse(seed, dim, n=n, walls=walls, fixed=fixed)
    rng = np.random.default_rng(seed)
    return p, replace(c, c_n=rng.uniform(0.0, 0.5, c.n), c_t=rng.uniform(0.0, 0.5, c.n))


def assembled(p, c, rotation, k_n, k_t):
    s = inverse_sqrt_mass(p, rotation)
    return assemble_stiffness(p, replace(c, k_n=k_n, k_s=k_t), rotation, scale=s).toarray()


@pytest.mark.parametrize("dim,rotation", [(2, True), (2, False), (3, True), (3, False)])
@pytest.mark.parametrize("shuffle", [False, True])
def test_threaded_product_equals_serial_and_assembled(dim, rotation, shuffle):
    """Contact runs summed into per-run buffers: one run is bit-identical to the serial
    product, several agree to rounding, parallel and serial compilations of the same runs
    are bit-identical (fixed order), and all equal the assembled S K S x; in any contact
    order (shuffled: the runs' particle ranges overlap)."""
    p, c = damped_assembly(7 + dim, dim)
    if shuffle:
        c = c.subset(np.random.default_rng(1).permutation(c.n))
    x = np.random.default_rng(2).standard_normal(
        p.n * (dim + (dim * (dim - 1) // 2 if rotation else 0)))
    serial = ScaledContactOperator(p, c, rotation, threads=1)
    ref = assembled(p, c, rotation, c.k_n, c.k_s) @ x
    y_serial = serial.stiffness(x)
    np.testing.assert_allclose(y_serial, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    for runs in (1, 3, 7):
        chunks, spans = contact_chunks(c, p.n, runs)
        buf = np.empty((runs - 1, p.n, serial.nd))
        out = {}
        for name, kernel in (("parallel", _chunked_scaled_matvec_parallel),
                             ("serial", _chunked_scaled_matvec_serial)):
            y = np.empty_like(x)
            kernel(c.i, c.j, c.normal, c.arm_i, c.arm_j, c.k_n, c.k_s, rotation,
                   serial.scale, x, np.empty_like(serial.scale), chunks, spans, buf, y)
            out[name] = y
        np.testing.assert_array_equal(out["parallel"], out["serial"])
        if runs == 1:
            np.testing.assert_array_equal(out["serial"], y_serial)
        np.testing.assert_allclose(out["serial"], ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    threaded = ScaledContactOperator(p, c, rotation, threads=3)
    assert threaded.threads == 3
    np.testing.assert_allclose(threaded.dashpots(x), assembled(p, c, rotation, c.c_n, c.c_t) @ x,
                               rtol=1e-12, atol=1e-12 * np.abs(ref).max())


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("rotation,rolling", [(True, True), (True, False), (False, False)])
@pytest.mark.parametrize("with_walls", [False, True])
def test_ordered_product_writes_every_row_once_and_scaled(dim, rotation, rolling, with_walls):
    """A contact list sorted by i with j above i (the search's pairs) on several threads:
    each run writes its own rows complete and scaled, terms on later runs' rows into its
    band. On 2, 3 and 7 runs (bands spanning runs), with a fixed particle and particles
    that are no contact's i (scaled after the runs), the product equals the assembled
    S K S x, and so does x.(S K S x) the product gathers on its way, and the
    parallel and serial compilations agree bit for bit; with walls after the pairs (the
    search's order) as well. A shuffled list is not ordered and keeps the summed runs."""
    p, c = random_polydisperse(21 + dim, dim, n=60, fixed=True, walls=with_walls)
    walls = np.flatnonzero(c.j < 0)
    if with_walls:
        assert len(walls) >= 2 and walls[0] > 0 and (c.j[walls[0]:] < 0).all()
        assert np.isin(c.i[walls], c.i[:walls[0]]).any()  # rows with pairs and walls
    else:
        assert len(walls) == 0
    rng = np.random.default_rng(5)
    if rolling:
        c = replace(c, k_r=rng.uniform(0.1, 1.0, c.n), k_w=rng.uniform(0.1, 1.0, c.n))
    assert ordered_contact_runs(c, p.n, 2) is not None
    unheld = ordered_contact_runs(c, p.n, 2)[2]
    assert len(unheld) >= 2 and unheld[-1] == p.n - 1
    s = inverse_sqrt_mass(p, rotation)
    x = rng.standard_normal(len(s))
    ref = assemble_stiffness(p, c, rotation, scale=s) @ x
    springs = (c.k_n, c.k_s, c.k_r, c.k_w) if rolling else (c.k_n, c.k_s, None, None)
    for runs in (2, 3, 7):
        op = ScaledContactOperator(p, c, rotation, threads=runs)
        assert op._ordered is not None and op._buf is None
        assert np.count_nonzero(op._ordered[1][:-1, 1] > op._ordered[1][1:, 0]) >= 1
        y = op.stiffness(x)
        np.testing.assert_allclose(y, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max(),
                                   err_msg=f"{runs} runs")
        y_serial, quad = ordered_scaled_contact_matvec(c, *springs[:2], rotation, op.scale, x,
                                                       op._work, op._ordered, op._band,
                                                       parallel=False, k_r=springs[2],
                                                       k_w=springs[3])
        np.testing.assert_array_equal(y_serial, y)
        # the quadratic form gathered on the way: written rows, unheld rows and bands
        assert quad == pytest.approx(x @ ref, rel=1e-12)
    assert ordered_contact_runs(c.subset(rng.permutation(c.n)), p.n, 2) is None


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("rotation,rolling", [(True, True), (True, False), (False, False)])
def test_product_holding_a_row_matches_assembled_in_any_order(dim, rotation, rolling):
    """The product keeps the current contact's first particle's rows in registers while
    the contacts share it: in the search's order, reversed (each row's runs come after
    its rows were written as second particles), shuffled (a held row is left and taken
    up again) and with contacts of a particle with itself (the second row is the held
    one), it equals the assembled K x."""
    p, c = random_polydisperse(11 + dim, dim, n=40, walls=True)
    rng = np.random.default_rng(3)
    if rolling:
        c = replace(c, k_r=rng.uniform(0.1, 1.0, c.n), k_w=rng.uniform(0.1, 1.0, c.n))
    own = c.subset(np.flatnonzero(c.j >= 0)[::4])
    own = replace(own, j=own.i.copy())
    nd = dofs_per_particle(dim, rotation)
    x = rng.standard_normal((p.n, nd))
    for order in ("search", "reversed", "shuffled", "with self-contacts"):
        cc = c
        if order == "reversed":
            cc = c.subset(np.arange(c.n)[::-1])
        elif order == "shuffled":
            cc = c.subset(rng.permutation(c.n))
        elif order == "with self-contacts":
            cc = ContactSet.concatenate([c, own])
            cc = cc.subset(np.argsort(cc.i, kind="stable"))
        k_r, k_w = (cc.k_r, cc.k_w) if rolling else (None, None)
        y = contact_matvec(cc, cc.k_n, cc.k_s, rotation, x, k_r, k_w)
        ref = (assemble_stiffness(p, cc, rotation) @ x.ravel()).reshape(y.shape)
        np.testing.assert_allclose(y, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max(),
                                   err_msg=order)


@pytest.mark.parametrize("dim", [2, 3])
def test_rayleigh_terms_and_projections_match_assembled(dim):
    p, c = damped_assembly(3 + dim, dim)
    d = GlobalDamping(0.2, 0.05)
    K = assembled(p, c, True, c.k_n, c.k_s)
    Cd = assembled(p, c, True, c.c_n, c.c_t)
    rng = np.random.default_rng(dim)
    for threads in (1, 4):
        op = ScaledContactOperator(p, c, True, d, threads=threads)
        q = rng.standard_normal(op.size)
        q /= np.linalg.norm(q)
        kq, cq = op.rayleigh_terms(q)
        assert kq == pytest.approx(q @ K @ q, rel=1e-12)
        assert cq == pytest.approx(q @ Cd @ q + 0.2 + 0.05 * (q @ K @ q), rel=1e-12)
        Y = rng.standard_normal((5, op.size))
        X = op.scale[None] * Y.reshape(5, *op.scale.shape)
        K_p, C_p = contact_gram(c, True, X, op._chunks, parallel=threads > 1)
        np.testing.assert_allclose(K_p, Y @ K @ Y.T, rtol=1e-11, atol=1e-11 * np.abs(K_p).max())
        np.testing.assert_allclose(C_p, Y @ Cd @ Y.T, rtol=1e-11, atol=1e-11 * np.abs(C_p).max())
        x = op.displacement(q)
        assert contact_quadratic_forms(c, True, x, op._chunks, parallel=True) == \
            contact_quadratic_forms(c, True, x, op._chunks, parallel=False)


def spectrum_matrix(n, top, seed):
    """A symmetric PSD matrix with the given top eigenvalues above a random spectrum."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    w = np.sort(rng.uniform(0.0, 0.9, n))
    w[n - len(top):] = np.sort(top)
    return (Q * w) @ Q.T, w


@pytest.mark.parametrize("top", [[1.0], [1.0, 1.0], [1.0, 1.0 - 1e-7, 0.999], [1.0, 0.95]])
@pytest.mark.parametrize("basis,keep", [(40, 8), (8, 2)])
def test_lanczos_finds_the_top_eigenpair(top, basis, keep):
    """Against dense eigh: well separated, exactly double, nearly double (1e-7) and
    clustered tops, with a basis large and small enough to restart many times."""
    A, w = spectrum_matrix(400, top, 5)
    start = np.random.default_rng(0).standard_normal(400)
    theta, y, matvecs, *_ = lanczos_top(lambda x, out: np.matmul(A, x, out=out), start,
                                       tol=1e-10, basis=basis, keep=keep)
    assert 0 < matvecs < 2000
    assert theta == pytest.approx(w[-1], rel=1e-9)
    assert theta <= w[-1] * (1 + 1e-12)
    r = np.linalg.norm(A @ y - (y @ A @ y) * y)
    assert r <= 1e-9 * w[-1]
    pair = top_eigenpair(A, v0=y, dense_limit=0, tol=1e-10)
    assert pair.value <= w[-1] * (1 + 1e-12) <= pair.upper * (1 + 1e-12)


@pytest.mark.parametrize("n", [13, 16384 * 3 + 5])
@pytest.mark.parametrize("local,rows", [([3], [3]), ([2, 3], [0, 1, 2, 3]),
                                        ([1, 2, 3], [0, 1, 2, 3, 4]),
                                        ([4, 5], [0, 1, 2, 3, 4, 5]),
                                        ([8, 9, 10], list(range(10))),
                                        ([10, 11], list(range(12)))])
def test_blocked_vector_operations_match_numpy(monkeypatch, n, local, rows):
    """The Lanczos vector kernels against numpy: the two Gram-Schmidt passes against
    basis vectors stored unnormalised with their factors apart (odd and even row counts,
    one to three passes of five rows for the dots with a last one full or partial, one
    or two passes of two rows for a subtraction, a last partial block, the new vector
    scaled on the way), the row combination written
    over the rows it reads (a thick restart) and the scaling; the threaded versions give
    the same bits as the serial ones (the summation order is the blocks', not the
    threads')."""
    from demstep.kernels import timestep_kernels as tk

    rng = np.random.default_rng(n)
    Q = np.linalg.qr(rng.standard_normal((n, 12)))[0].T.copy()
    s = rng.uniform(0.1, 10.0, 12)  # basis vector r = s[r] V[r]
    V = Q / s[:, None]
    w_scale = 0.37
    w0 = rng.standard_normal(n) + 3.0 * Q[3]
    local_a, rows_a = np.array(local, dtype=np.int64), np.array(rows, dtype=np.int64)
    u0 = w_scale * w0
    h_ref = Q[local_a] @ u0
    w1 = u0 - Q[local_a].T @ h_ref
    h2_ref = Q[rows_a] @ w1
    w2 = w1 - Q[rows_a].T @ h2_ref
    S = rng.standard_normal((5, 3))
    results = []
    for threshold in (10**9, 1):  # serial, then threaded
        monkeypatch.setattr(tk, "PARALLEL_MIN_DOFS", threshold)
        w = w0.copy()
        h, h2 = np.empty(12), np.empty(13)
        beta2 = tk.lanczos_orthogonalize(V, s, local_a, rows_a, w, w_scale, h, h2)
        np.testing.assert_allclose(h[:len(local)], h_ref, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(h2[:len(rows)], h2_ref, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(w, w2, rtol=1e-12, atol=1e-12)
        assert beta2 == pytest.approx(w2 @ w2, rel=1e-12)
        U = V.copy()
        tk.combine_rows(U, 5, S, U)  # in place: U[:3] = S^T V[:5]
        np.testing.assert_allclose(U[:3], S.T @ V[:5], rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(U[3:], V[3:])
        out = np.empty(n)
        tk.scale_into(w0, 0.25, out)
        np.testing.assert_array_equal(out, 0.25 * w0)
        results.append((w, h[:len(local)], h2[:len(rows) + 1], U))
    for a, b in zip(*results):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("n", [7, 16384 * 3 + 5])
def test_second_pass_skipped_exactly_when_semi_orthogonal(monkeypatch, n):
    """The second Gram-Schmidt pass is skipped when every cosine of the new vector
    (after the first pass) with the basis vectors is at most ``semi``: just above the
    largest cosine, it keeps its components and h2 is zero; just below, the pass runs
    as with ``semi`` 0; serial and threaded alike, the basis stored with factors."""
    from demstep.kernels import timestep_kernels as tk

    rng = np.random.default_rng(n)
    Q = np.linalg.qr(rng.standard_normal((n, 6)))[0].T.copy()
    s = rng.uniform(0.1, 10.0, 6)
    V = Q / s[:, None]
    w0 = rng.standard_normal(n) + 3.0 * Q[3] + 1e-3 * Q[1]
    w_scale = 2.5
    local, rows = np.array([2, 3]), np.array([0, 1, 2, 3])
    w1 = w_scale * w0 - Q[local].T @ (Q[local] @ (w_scale * w0))
    h2_ref = Q[rows] @ w1
    cosine = np.max(np.abs(h2_ref)) / np.linalg.norm(w1)
    w2 = w1 - Q[rows].T @ h2_ref
    for threshold in (10**9, 1):  # serial, then threaded
        monkeypatch.setattr(tk, "PARALLEL_MIN_DOFS", threshold)
        for semi, skipped in ((cosine * (1 + 1e-6), True), (cosine * (1 - 1e-6), False)):
            w, h, h2 = w0.copy(), np.empty(6), np.empty(7)
            beta2 = tk.lanczos_orthogonalize(V, s, local, rows, w, w_scale, h, h2, semi)
            expect = w1 if skipped else w2
            np.testing.assert_allclose(w, expect, rtol=1e-12, atol=1e-12)
            assert beta2 == pytest.approx(expect @ expect, rel=1e-12)
            if skipped:
                np.testing.assert_array_equal(h2[:4], 0.0)
            else:
                np.testing.assert_allclose(h2[:4], h2_ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("tol", [1e-6, 1e-10])
@pytest.mark.parametrize("recurrence", [False, True])
def test_lanczos_basis_stays_semi_orthogonal_to_the_kept_vectors(monkeypatch, tol, recurrence):
    """Every new Lanczos vector is at most min(sqrt(eps), 0.1 tol) from orthogonal to
    the rows it is checked against (the kept Ritz vectors and its predecessors), with
    the second pass skipped for most of them, and the top eigenpair is still found;
    also when the product gives x.(A x) and the first pass takes the three-term
    recurrence's coefficients instead of its dots (then on every step past a restart's
    first)."""
    from demstep.kernels import timestep_kernels as tk
    from demstep.timestep import eigen

    A, w = spectrum_matrix(600, [1.0, 1.0 - 1e-4, 0.999], 3)
    semi = min(eigen.LANCZOS_SEMI, eigen.LANCZOS_SEMI_PER_TOL * tol)
    kernel = tk.lanczos_orthogonalize
    worst, skipped, calls, recurred = [], [0], [0], [0]

    def checked(V, s, local, rows, w_, w_scale, h, h2, semi_, known=False):
        assert semi_ == semi
        beta2 = kernel(V, s, local, rows, w_, w_scale, h, h2, semi_, known)
        calls[0] += 1
        recurred[0] += known
        skipped[0] += not h2[:len(rows)].any()
        basis = s[rows, None] * V[rows]  # the basis vectors (stored with factors apart)
        # the vector just expanded is a unit Lanczos vector through its factor
        assert np.linalg.norm(s[local[-1]] * V[local[-1]]) == pytest.approx(1.0, rel=1e-12)
        worst.append(np.max(np.abs(basis @ w_)) / np.sqrt(beta2))
        return beta2

    monkeypatch.setattr(tk, "lanczos_orthogonalize", checked)
    start = np.random.default_rng(1).standard_normal(600)

    def matvec(x, out):
        np.matmul(A, x, out=out)
        return float(x @ out) if recurrence else None

    theta, y, *_ = lanczos_top(matvec, start, tol=tol, basis=12, keep=4)
    assert max(worst) <= semi * (1 + 1e-6)
    assert skipped[0] > calls[0] // 2
    assert (recurred[0] > calls[0] // 2) == recurrence
    assert theta == pytest.approx(w[-1], rel=10 * tol)


def test_lanczos_stops_once_above_a_threshold():
    A, w = spectrum_matrix(300, [1.0, 0.99], 2)
    start = np.random.default_rng(1).standard_normal(300)
    full = lanczos_top(lambda x, out: np.matmul(A, x, out=out), start, tol=1e-12)
    early = lanczos_top(lambda x, out: np.matmul(A, x, out=out), start, tol=1e-12,
                        stop_above=0.98, stop_tol=1e-2)
    assert early[0] > 0.98 and early[2] < full[2]


def test_lanczos_returns_the_top_ritz_block():
    A, w = spectrum_matrix(300, [1.0, 0.99, 0.98, 0.97], 3)
    start = np.random.default_rng(2).standard_normal(300)
    theta, y, _, Y, _ = lanczos_top(lambda x, out: np.matmul(A, x, out=out), start, tol=1e-12,
                                 block=3)
    assert Y.shape == (3, 300)
    np.testing.assert_allclose(Y @ Y.T, np.eye(3), atol=1e-10)
    np.testing.assert_allclose(np.diag(Y @ A @ Y.T), w[::-1][:3], rtol=1e-8)
    assert abs(Y[0] @ y) == pytest.approx(1.0, abs=1e-12)


def test_start_vector_written_into_a_buffer_matches_the_new_one():
    """The start written into a caller's buffer (the Lanczos scratch vector): the warm
    vector normalised plus the mixed random one, as the allocating form gives it; the
    random vector itself for no, a zero or a non-finite warm vector (the buffer then
    holds a writable copy of it)."""
    from demstep.timestep.eigen import _random_unit, start_vector

    n = 1000
    warm = np.random.default_rng(4).standard_normal(n) * 7.0
    out = np.full(n, np.nan)
    got = start_vector(n, warm, 1e-2, out=out)
    assert got is out
    np.testing.assert_allclose(out, warm / np.linalg.norm(warm) + 1e-2 * _random_unit(n),
                               rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(start_vector(n, warm, 1e-2), out, rtol=1e-14, atol=1e-15)
    bad = warm.copy()
    bad[5] = np.inf
    for w in (None, np.zeros(n), bad, warm[:10]):
        out[:] = np.nan
        assert start_vector(n, w) is _random_unit(n)
        np.testing.assert_array_equal(start_vector(n, w, out=out), _random_unit(n))
        assert out.flags.writeable


@pytest.mark.parametrize("dim,seed", [(2, 1), (3, 2), (3, 3)])
def test_loose_intermediate_solves_give_the_tight_result(dim, seed):
    """Sparse path (dense_limit=0) on small damped assemblies: loose intermediate solves
    (default), every solve tight, ARPACK, and the dense path agree within 1e-8, and the
    certified step is never above the dense one's exact root."""
    p, c = damped_assembly(seed, dim, n=40)
    d = GlobalDamping(0.1, 0.01)
    dense = exact_critical_step(p, c, True, d, dense_limit=10**6)
    loose = exact_critical_step(p, c, True, d, dense_limit=0)
    tight = exact_critical_step(p, c, True, d, dense_limit=0, loose_tol=1e-10)
    arpack = exact_critical_step(p, c, True, d, dense_limit=0, solver="arpack")
    threaded = exact_critical_step(p, c, True, d, dense_limit=0, threads=3)
    for r in (loose, tight, arpack, threaded):
        assert r.dt == pytest.approx(dense.dt, rel=1e-8)
        assert r.dt <= 2.0 / dense.sigma * (1 + 1e-12)
        assert r.dt_undamped == pytest.approx(dense.dt_undamped, rel=1e-8)
    assert loose.matvecs > 0 and loose.iterations >= 2


def test_undamped_sparse_step_matches_dense_eigh():
    p, c = random_polydisperse(4, 3, n=64, walls=True)
    op = ScaledContactOperator(p, c, True)
    lam = scipy.linalg.eigh(op.dense_pencil(0.0), eigvals_only=True)[-1]
    r = exact_critical_step(p, c, True, dense_limit=0)
    assert r.lambda_undamped == pytest.approx(lam, rel=1e-10)
    assert r.dt <= 2.0 / np.sqrt(lam) * (1 + 1e-12)
    assert r.dt == pytest.approx(2.0 / np.sqrt(lam), rel=1e-9)


def test_a_workspace_without_huge_pages_refuses_them():
    """The engine's workspace maps its large arrays with transparent huge pages refused
    (in a running simulation the kernel compacted memory for each 2 MB page): the
    mapping is not eligible for them (/proc/self/smaps), while numpy's own large
    arrays are where the system offers them on request."""
    import re
    from pathlib import Path

    from demstep.scratch import SMALL_PAGES_MIN, Workspace

    smaps = Path("/proc/self/smaps")
    mode = Path("/sys/kernel/mm/transparent_hugepage/enabled")
    if not smaps.exists() or not mode.exists() or "[never]" in mode.read_text():
        pytest.skip("no transparent huge pages here")

    def eligible(a):
        addr = a.__array_interface__["data"][0] + a.nbytes // 2  # numpy's advice skips the head
        text = smaps.read_text()
        for m in re.finditer(r"^([0-9a-f]+)-([0-9a-f]+) .*?THPeligible:\s+(\d)", text,
                             re.M | re.S):
            if int(m.group(1), 16) <= addr < int(m.group(2), 16):
                return m.group(3) == "1"
        raise AssertionError("mapping not found")

    ws = Workspace(huge_pages=False)
    a = ws.array("basis", (4, SMALL_PAGES_MIN // 8))
    a[:] = 1.0
    assert np.shares_memory(ws.array("basis", (4, SMALL_PAGES_MIN // 8)), a)  # kept
    assert not eligible(a)
    b = Workspace().array("basis", (4, SMALL_PAGES_MIN // 8))
    b[:] = 1.0
    assert eligible(b)
    small = Workspace(huge_pages=False).array("w", (SMALL_PAGES_MIN // 16,))
    assert isinstance(small.base, (np.ndarray, type(None)))  # numpy's own allocation


@pytest.mark.parametrize("damped", [False, True])
@pytest.mark.parametrize("tol", [1e-4, 1e-5, 1e-6])
def test_a_warm_start_on_a_cluster_member_still_bounds_the_top(damped, tol):
    """The top of an FCC block's spectrum is a cluster (relative gaps 1.4 % here). A
    previous mode given as ``v0`` that is the cluster's second eigenvector made Lanczos
    stop on it: the "certified" step was 0.7 % above the critical one at 1e-4 and 1e-5,
    damped or not. The certifying solves start from the fixed random vector: the step
    stays below the dense path's at every tolerance."""
    from demstep.analysis_input import ContactModel, from_lattice

    model = ContactModel(parameters={"k_n": 1e6, "k_s": 5e5})
    inp = from_lattice("fcc", 5, 1.0, 1000.0, model)
    contacts = inp.contacts
    damping = None
    if damped:
        contacts = replace(contacts, c_n=np.full(contacts.n, 2.0), c_t=np.full(contacts.n, 1.0))
        damping = GlobalDamping(mass=0.5)
    op = ScaledContactOperator(inp.particles, contacts, False, damping)
    w, V = scipy.linalg.eigh(op.dense_pencil(0.0))
    assert (w[-1] - w[-2]) / w[-1] > 1e-2  # a gap the loose tolerances cannot resolve
    reference = exact_critical_step(inp.particles, contacts, False, damping,
                                    dense_limit=10**4)  # the dense path
    assert reference.matvecs == 0
    # the wrong start: the second eigenvector (undamped), or the damped iteration's
    # vector moved onto it
    for v0 in (V[:, -2], V[:, -3]):
        step = exact_critical_step(inp.particles, contacts, False, damping, v0=v0,
                                   dense_limit=0, tol=tol)
        assert step.matvecs > 0
        assert step.dt <= reference.dt * (1 + 1e-12)
        assert step.dt >= reference.dt * (1 - 8 * tol)


def test_a_loose_undamped_solve_still_certifies_the_damped_step():
    """``undamped_tol``: a caller that needs only the damped step solves the undamped
    problem loosely (it only starts the damped iteration). The damped step is the same
    certified one (below the dense path's, within the certifying margin of it), for
    fewer products; ``dt_undamped`` is then a looser certified bound (below the dense
    path's undamped step, within the looser tolerance)."""
    from demstep.analysis_input import ContactModel, from_lattice

    model = ContactModel(parameters={"k_n": 1e6, "k_s": 5e5})
    inp = from_lattice("fcc", 5, 1.0, 1000.0, model)
    contacts = replace(inp.contacts, c_n=np.full(inp.contacts.n, 2.0),
                       c_t=np.full(inp.contacts.n, 1.0))
    damping = GlobalDamping(mass=0.5)
    reference = exact_critical_step(inp.particles, contacts, True, damping, dense_limit=10**5)
    assert reference.matvecs == 0
    tight = exact_critical_step(inp.particles, contacts, True, damping, dense_limit=0)
    loose = exact_critical_step(inp.particles, contacts, True, damping, dense_limit=0,
                                undamped_tol=1e-3)
    for step in (tight, loose):
        assert step.dt <= reference.dt * (1 + 1e-12)
        assert step.dt >= reference.dt * (1 - 1e-8)
        assert step.dt_undamped <= reference.dt_undamped * (1 + 1e-12)
    assert tight.dt_undamped >= reference.dt_undamped * (1 - 1e-9)
    assert loose.dt_undamped >= reference.dt_undamped * (1 - 4e-3)
    assert loose.matvecs < tight.matvecs


def test_estimates_solve_the_undamped_problem_tightly_only_when_it_is_listed():
    """estimate_time_steps: with 'exact-undamped' among the methods the undamped step is
    the tight one; without it the undamped solve is loose (fewer products) and the
    damped step the same certified one."""
    from demstep.timestep.estimates import estimate_time_steps
    from demstep.analysis_input import ContactModel, from_lattice

    inp = from_lattice("fcc", 5, 1.0, 1000.0, ContactModel(parameters={"k_n": 1e6, "k_s": 5e5}))
    contacts = replace(inp.contacts, c_n=np.full(inp.contacts.n, 2.0),
                       c_t=np.full(inp.contacts.n, 1.0))
    both = estimate_time_steps(inp.particles, contacts, True, methods=["exact", "exact-undamped"])
    alone = estimate_time_steps(inp.particles, contacts, True, methods=["exact"])
    tight = exact_critical_step(inp.particles, contacts, True)
    assert both.exact.dt_undamped == tight.dt_undamped
    assert alone.exact.matvecs < both.exact.matvecs
    assert alone.exact.dt == pytest.approx(both.exact.dt, rel=1e-8)
    # the loose solve is labelled as such: its tolerance recorded, a note
    assert both.exact.undamped_tol == EIGSH_TOL and alone.exact.undamped_tol == 1e-3
    assert not any("undamped problem solved only" in n for n in both.notes)
    assert any("undamped problem solved only to a relative residual of 0.001" in n
               for n in alone.notes)
    # exact-undamped alone: the damped step it computes is shown, the 'conservative' reference
    only = estimate_time_steps(inp.particles, contacts, True, methods=["exact-undamped", "nodal"])
    assert [e.method for e in only.estimates] == ["exact", "exact-undamped", "nodal"]
    assert only.estimates[0].dt == both.exact.dt
    assert only.estimates[2].conservative == (only.estimates[2].dt <= both.exact.dt * (1 + 1e-9))


@pytest.mark.parametrize("name,options", [
    ("tol", {"tol": 1e-2}), ("undamped_tol", {"undamped_tol": 0.5}), ("tol", {"tol": 0.0}),
    ("undamped_tol", {"undamped_tol": float("nan")}), ("exact_tol", {"exact_tol": 2e-3}),
])
def test_a_tolerance_that_certifies_nothing_is_refused(name, options):
    """Above MAX_CERTIFIED_TOL a solve may stop below the top of a clustered spectrum:
    the API refuses it (as the CLI does) with an error naming the parameter."""
    from demstep.timestep.estimates import estimate_time_steps
    from demstep.analysis_input import ContactModel, from_lattice

    inp = from_lattice("fcc", 3, 1.0, 1000.0, ContactModel(parameters={"k_n": 1e6, "k_s": 5e5}))
    if name == "exact_tol":
        call = lambda: estimate_time_steps(inp.particles, inp.contacts, True, **options)
    else:
        call = lambda: exact_critical_step(inp.particles, inp.contacts, True,
                                           GlobalDamping(mass=0.5), **options)
    with pytest.raises(InputError, match=rf"^{name}: must be in \(0, 0.001\], got"):
        call()
