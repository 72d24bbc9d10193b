"""Largest eigenvalue of a symmetric positive semi-definite matrix, with a bound.

Two paths: dense ``scipy.linalg.eigh`` for small systems (exact to rounding), and a
thick-restart Lanczos iteration (:func:`lanczos_top`; Wu & Simon 2000, "Thick-restart
Lanczos method for large symmetric eigenvalue problems") on a sparse matrix or a
matrix-free operator, started from a given vector (a warm start: the last critical
mode) or a fixed pseudo-random one, so that results are reproducible. ARPACK's
implicitly restarted Lanczos (``eigsh``, which='LA') stays available
(``solver="arpack"``); the package's own iteration replaced it because, on 1e5-particle
assemblies, ARPACK spent 3-6x the time of the products themselves in its
orthogonalisation and in the BLAS thread pool (measured: "Exact damped step: solver
choices" in benchmarks/results/history-2026-11-30.md), and
it always builds a full basis of ``ncv`` vectors, so a warm start that is already
nearly converged still costs ``ncv`` products.

A Ritz value theta is never above the true largest eigenvalue; a certificate needs an
upper bound. With the Ritz vector y (|y| = 1) and the residual r = A y - theta y, some
eigenvalue lies within |r| of theta (Bauer-Fike for symmetric matrices), so
``theta + |r|`` bounds the eigenvalue the solver converged to. The bound is on the top
of the spectrum when Lanczos has found the largest eigenvalue, which it does from a
random start: every direction has a share of it, and the iteration brings out the
top ones first. A warm start (a previous mode) is no such start: where the top of the
spectrum is a cluster (regular packings), Lanczos stops on the cluster's eigenvector
the start sits on once its residual is small, whatever random share was mixed in
(measured below the top by up to 1.4 %: :data:`demstep.timestep.exact.CHAIN_MIX`).
The solves that certify a step therefore start from the fixed random vector; warm
starts serve the solves that certify nothing. From the random start, the bound held
at every tolerance up to 1e-3 on every assembly measured; at 1e-2 one FCC block
stopped 0.6 % below the top.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from demstep.errors import InputError
from demstep.kernels import timestep_kernels as tk
from demstep.kernels.timestep_kernels import _norm2, _rayleigh_residual
from demstep.scratch import Workspace

#: systems up to this many DOFs are solved densely (exact to rounding); above, Lanczos
#: on the matrix-free operator is faster (a dense eigh is O(n^3))
DENSE_LIMIT = 300
#: relative accuracy requested from ARPACK for the largest eigenvalue
EIGSH_TOL = 1e-10
#: the loosest relative residual a solve that certifies may run to: from the random
#: start the bound held at every tolerance up to this on every assembly measured (at
#: 1e-2 one FCC block stopped 0.6 % below the top; module docstring)
MAX_CERTIFIED_TOL = 1e-3
#: weight of the fixed random vector mixed into a warm start (keeps every direction)
WARM_START_MIX = 1e-2
#: seed of the fixed pseudo-random start vector
START_SEED = 12345
#: Lanczos basis size before a thick restart, and Ritz vectors kept across it
LANCZOS_BASIS = 40
LANCZOS_KEEP = 8
#: orthogonality kept by :func:`lanczos_top`: a new Lanczos vector whose cosines with
#: the kept Ritz vectors and its two predecessors are all at most
#: min(LANCZOS_SEMI, LANCZOS_SEMI_PER_TOL * tol) skips its second orthogonalisation
#: pass. sqrt(eps) is the semi-orthogonality that keeps the Ritz values accurate
#: (Simon 1984); a tight ``tol`` needs tighter (measured at tol = 1e-10 with sqrt(eps):
#: 4 % more products on an FCC block, 34 % on a dense packing; with 0.1 tol none more;
#: benchmarks/results/history-2026-12-01.md, ninth session)
LANCZOS_SEMI = float(np.sqrt(np.finfo(np.float64).eps))
LANCZOS_SEMI_PER_TOL = 0.1
#: Lanczos runs per eigenpair when the explicit residual is 10x above the tolerance
LANCZOS_RETRIES = 2
#: products per Lanczos run at most
LANCZOS_MAX_MATVECS = 50_000


#: the arrays of :func:`lanczos_top` in a :class:`Workspace` (the basis, which also
#: holds the block of top Ritz vectors returned, and the new vector, which also holds
#: the start) and the rows of the operator's projections
#: (:meth:`demstep.timestep.exact.ScaledContactOperator.subspace_start`, when it is
#: given no spare basis rows, :attr:`Eigenpair.spare`); blocks of
#: k x n of more than 32 MB come from the system as fresh pages at every allocation
#: (glibc maps them anew), measured 2 ms per MB inside a running simulation
LANCZOS_ARRAYS = ("lanczos_basis", "lanczos_w", "subspace_rows")


@dataclass
class Eigenpair:
    """Ritz value ``value`` (<= the largest eigenvalue), unit vector ``vector`` and the
    residual norm ``residual`` = |A y - value y|; ``upper`` = value + residual bounds
    the eigenvalue found from above."""

    value: float
    vector: np.ndarray
    residual: float
    matvecs: int = 0
    #: the top Ritz vectors of the last Lanczos basis (k, n), largest first, when asked
    #: (the first rows of the basis in the solver's workspace: the next solve overwrites
    #: them)
    block: np.ndarray | None = None
    #: as many basis rows right after ``block``, free until the next solve (scratch for
    #: a caller working on the block: no memory of its own), or None
    spare: np.ndarray | None = None

    @property
    def upper(self) -> float:
        return self.value + self.residual


@functools.lru_cache(maxsize=4)
def _random_unit(n: int) -> np.ndarray:
    rand = np.random.default_rng(START_SEED).standard_normal(n)
    rand /= np.linalg.norm(rand)
    rand.setflags(write=False)
    return rand


def start_vector(n: int, warm: np.ndarray | None = None, mix: float = WARM_START_MIX,
                 out: np.ndarray | None = None) -> np.ndarray:
    """A reproducible start vector: the fixed pseudo-random one (read-only, unless
    written into ``out``), or ``warm`` with ``mix`` (1 %) of it mixed in (so that no
    eigen-direction is missing from the start); into ``out`` (n,) when given."""
    rand = _random_unit(n)  # (read-only: shared, not copied)
    norm = 0.0
    if warm is not None and np.shape(warm) == (n,):
        warm = np.ascontiguousarray(warm, dtype=np.float64)
        norm = np.sqrt(_squared_norm(warm))  # (not finite when an element is not)
    if not 0.0 < norm < np.inf:
        if out is None:
            return rand
        out[:] = rand
        return out
    if out is None:
        return warm / norm + mix * rand
    np.multiply(warm, 1.0 / norm, out=out)
    return scipy.linalg.blas.daxpy(rand, out, a=mix)  # (in place: out += mix rand)


def check_certified_tol(name: str, value: float) -> float:
    """``value`` as a float when it is a relative residual a certifying solve may run
    to, in (0, :data:`MAX_CERTIFIED_TOL`]; else an InputError naming ``name``."""
    try:
        tol = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: must be a number in (0, {MAX_CERTIFIED_TOL:g}], "
                         f"got {value!r}") from None
    if not 0.0 < tol <= MAX_CERTIFIED_TOL:
        raise InputError(f"{name}: must be in (0, {MAX_CERTIFIED_TOL:g}], got {value!r} (a "
                         "looser solve certifies nothing)")
    return tol


def _squared_norm(x: np.ndarray) -> float:
    """|x|^2 by the compiled kernel (inf or nan when x has a non-finite element)."""
    return float(_norm2(x))


def lanczos_top(matvec, v0: np.ndarray, tol: float = EIGSH_TOL, basis: int = LANCZOS_BASIS,
                keep: int = LANCZOS_KEEP, max_matvecs: int | None = None,
                stop_above: float = np.inf, stop_tol: float = 0.0, block: int = 0,
                workspace: Workspace | None = None):
    """Largest eigenpair of a symmetric operator by thick-restart Lanczos.

    ``matvec(x, out)`` writes A x into ``out`` and returns x.(A x) as a float when it
    computed it on its way (anything else is ignored); ``v0`` is the start. Returns
    (theta, y, matvecs, Y, spare): the largest Ritz value, its unit Ritz vector, the
    number of products and (``block`` > 0) the top ``block`` Ritz vectors (block, n),
    largest first, with the ``block`` basis rows after them, which hold nothing the
    caller needs until the next solve (None where the basis has fewer rows; both None
    without ``block``), once the Ritz estimate |beta s_last| of the residual is at most
    ``tol * theta`` (or the basis is exhausted, or after ``max_matvecs`` products), or
    once theta exceeds ``stop_above`` with an estimate at most ``stop_tol * theta`` (a
    Ritz value is a lower bound on the largest eigenvalue: the caller's question is
    answered, and the vector is as good as a ``stop_tol`` solve's).

    Each new Lanczos vector is orthogonalised against its two predecessors (and, right
    after a restart, against the kept Ritz vectors it couples to), then once more
    against those and the ``keep`` Ritz vectors kept at the last restart: selective
    orthogonalisation against the converging top Ritz vectors (Parlett & Scott 1979),
    not the full basis, which costs a pass over the whole basis per product. Without
    it the loss of orthogonality made the estimate claim convergence at a true
    residual of 8 % (measured, dense packing); against the top 4 of the 8 kept only,
    the FCC block (1e5 spheres, a cluster of converging Ritz values) gave a Ritz value
    30x the largest eigenvalue. That second pass subtracts only when the vector is
    not semi-orthogonal to those rows: when its cosines with all of them are at most
    min(:data:`LANCZOS_SEMI`, :data:`LANCZOS_SEMI_PER_TOL` ``tol``), its dots were the
    whole cost (most vectors, measured). The projected matrix holds
    every computed coefficient and is solved densely. The caller checks the result with
    an explicit residual (:func:`top_eigenpair`). The basis lives in ``workspace`` when
    given.
    """
    n = v0.shape[0]
    semi = min(LANCZOS_SEMI, LANCZOS_SEMI_PER_TOL * tol)
    m = max(2, min(basis, n))
    keep = max(1, min(keep, m // 2))
    if max_matvecs is None:
        max_matvecs = LANCZOS_MAX_MATVECS
    workspace = workspace if workspace is not None else Workspace()
    V = workspace.array(LANCZOS_ARRAYS[0], (m, n))
    # basis vector r is s[r] V[r]: a product writes straight into the next row, which
    # the orthogonalisation turns into the new vector in place, and 1/beta goes into s
    # (no pass over a vector just to normalise it)
    s = np.ones(m)
    T = np.zeros((m + 1, m + 1))
    tk.scale_into(v0, 1.0 / np.sqrt(tk._norm2(v0)), V[0])
    # (v0 may be the scratch vector w itself: it is read before the first product)
    w = workspace.array(LANCZOS_ARRAYS[1], (n,))
    h = np.empty(m + 1)
    h2 = np.empty(m + 2)
    j = 0       # the basis vector to expand
    kept = 0    # V[:kept] are the Ritz vectors kept at the last restart
    matvecs = 0
    while True:
        size = j + 1
        # the new vector: the next row, or (the basis full) the scratch vector
        new = V[size] if size < m else w
        quad = matvec(V[j], new)
        matvecs += 1
        lo = 0 if j == kept else j - 1
        local = np.arange(lo, j + 1, dtype=np.int64)
        rows = local if lo == 0 else np.concatenate((np.arange(kept, dtype=np.int64), local))
        nr = len(rows)
        # past a restart's first vector the first pass' coefficients are the recurrence's
        # (Paige): beta_{j-1} from the last step and alpha_j = v_j.A v_j, when the product
        # gave V[j].A V[j] on its way; the second pass measures what they leave
        known = isinstance(quad, float) and j > kept
        if known:
            h[0] = T[j, j - 1]
            h[1] = s[j] * s[j] * quad
        beta2 = tk.lanczos_orthogonalize(V, s, local, rows, new, s[j], h, h2, semi, known)
        T[rows, j] = h2[:nr]
        T[local, j] += h[:len(local)]
        T[j, rows] = T[rows, j]
        beta = np.sqrt(beta2)
        theta, S = scipy.linalg.eigh(T[:size, :size])
        top = theta[-1]
        estimate = beta * abs(S[size - 1, -1])
        scale_a = max(abs(theta[0]), abs(top))
        exhausted = size == n or beta <= 1e-14 * scale_a
        if (estimate <= tol * abs(top) or exhausted or matvecs >= max_matvecs
                or (top > stop_above and estimate <= stop_tol * abs(top))):
            nb = max(1, min(block, size))
            # the block overwrites the first rows of the basis (no new memory, and none
            # touched for the first time): valid until the next solve
            Y = V[:nb] if block else np.empty((1, n))
            tk.combine_rows(V, size, s[:size, None] * S[:, ::-1][:, :nb], Y)
            y = Y[0].copy() if block else Y[0]  # (no second vector when Y is not kept)
            tk.scale_into(y, 1.0 / np.sqrt(tk._norm2(y)), y)
            spare = V[nb:2 * nb] if block and 2 * nb <= m else None
            return float(top), y, matvecs, (Y if block else None), spare
        T[size, j] = T[j, size] = beta
        if size == m:
            # thick restart: keep the top ``keep`` Ritz vectors and the residual vector
            # (written after them from the scratch vector: the basis needs no row m)
            tk.combine_rows(V, m, s[:, None] * S[:, -keep:], V)
            tk.scale_into(w, 1.0 / beta, V[keep])
            s[:] = 1.0
            T[:] = 0.0
            T[np.arange(keep), np.arange(keep)] = theta[-keep:]
            T[:keep, keep] = T[keep, :keep] = beta * S[m - 1, -keep:]
            j = kept = keep
        else:
            s[size] = 1.0 / beta
            j = size


def top_eigenpair(A, v0: np.ndarray | None = None, dense_limit: int = DENSE_LIMIT,
                  tol: float = EIGSH_TOL, dense=None, solver: str = "lanczos",
                  mix: float = WARM_START_MIX, stop_above: float = np.inf,
                  stop_tol: float = 0.0, block: int = 0,
                  workspace: Workspace | None = None) -> Eigenpair:
    """Largest eigenpair of the symmetric PSD ``A`` (ndarray, sparse matrix or
    ``scipy.sparse.linalg.LinearOperator``) with its residual.

    Up to ``dense_limit`` DOFs the dense matrix (``dense()`` when given, else A itself)
    goes to ``eigh``; above, :func:`lanczos_top` (``solver="lanczos"``) or ARPACK's
    ``eigsh`` (``"arpack"``) runs on A from the start :func:`start_vector` (a warm start
    ``v0`` with ``mix`` of the random vector; Lanczos stops early once its Ritz value
    exceeds ``stop_above`` with a relative residual estimate <= ``stop_tol``; ``block``
    > 0 also returns that many top Ritz vectors, :attr:`Eigenpair.block`). An operator
    with a method ``matvec_into(x, out)`` is applied through it (no new array per
    product). The returned value and residual are recomputed from the returned vector
    (one more product), so the bound ``upper`` does not rely on the solver's own
    estimates; when Lanczos' estimate was 10x too optimistic, it goes on from there.
    ``workspace`` (:class:`Workspace`) keeps the Lanczos basis between calls."""
    n = A.shape[0]
    if n == 0:
        return Eigenpair(0.0, np.zeros(0), 0.0)
    if n <= dense_limit:
        M = dense() if dense is not None else A
        M = M.toarray() if sp.issparse(M) else np.asarray(M)
        w, V = scipy.linalg.eigh(M, subset_by_index=[n - 1, n - 1])
        y = V[:, 0]
        return Eigenpair(float(w[0]), y, float(np.linalg.norm(M @ y - w[0] * y)))

    into = getattr(A, "matvec_into", None)
    if into is None:
        def into(x, out):
            out[:] = np.ravel(A @ x)
    if solver == "arpack":
        start = start_vector(n, v0, mix)
        Ay = np.empty(n)
        vals, vecs = spla.eigsh(A, k=1, which="LA", tol=tol, v0=start, ncv=min(n - 1, 32),
                                maxiter=100 * n)
        y = vecs[:, 0] / np.linalg.norm(vecs[:, 0])
        into(np.ascontiguousarray(y), Ay)
        theta, residual = _rayleigh_residual(y, Ay)
        return Eigenpair(float(theta), y, float(residual))
    if solver != "lanczos":
        raise ValueError(f"solver: lanczos or arpack, got {solver!r}")
    matvecs = 0
    workspace = workspace if workspace is not None else Workspace()
    # the start goes into Lanczos' scratch vector (read before its first product)
    start = start_vector(n, v0, mix, out=workspace.array(LANCZOS_ARRAYS[1], (n,)))
    for _ in range(LANCZOS_RETRIES):
        ritz, y, used, Y, spare = lanczos_top(into, start, tol=tol, stop_above=stop_above,
                                       stop_tol=stop_tol, block=block, workspace=workspace)
        Ay = workspace.array(LANCZOS_ARRAYS[1], (n,))  # (Lanczos' scratch vector, free now)
        into(y, Ay)
        matvecs += used + 1
        theta, residual = _rayleigh_residual(y, Ay)
        if ritz > stop_above or residual <= 10.0 * tol * abs(theta) or used < 2:
            break
        start = y  # the estimate was wrong (lost orthogonality): go on from y
    return Eigenpair(float(theta), y, float(residual), matvecs, Y, spare)


def lambda_max(A, dense_limit: int = DENSE_LIMIT, tol: float = EIGSH_TOL) -> float:
    """Largest eigenvalue (the Ritz value) of the symmetric matrix A (sparse or dense)."""
    return top_eigenpair(A, dense_limit=dense_limit, tol=tol).value
