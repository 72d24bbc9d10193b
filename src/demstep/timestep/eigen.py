"""Largest eigenvalue of a symmetric positive semi-definite matrix, with a bound.

Two paths: dense ``scipy.linalg.eigh`` for small systems (exact to rounding), and
ARPACK's implicitly restarted Lanczos (``eigsh``, which='LA') on a sparse matrix or a
matrix-free operator, started from a given vector (a warm start: the last critical
mode) or a fixed pseudo-random one, so that results are reproducible.

A Ritz value theta is never above the true largest eigenvalue; a certificate needs an
upper bound. With the Ritz vector y (|y| = 1) and the residual r = A y - theta y, some
eigenvalue lies within |r| of theta (Bauer-Fike for symmetric matrices), so
``theta + |r|`` bounds the eigenvalue the solver converged to. The bound is on the top
of the spectrum when Lanczos has found the largest eigenvalue, which it does from a
start vector with a component along it (a random start, or a warm start mixed with
one: :func:`top_eigenpair` mixes 1 % of a random vector into any warm start).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

#: systems up to this many DOFs are solved densely (exact to rounding); above, Lanczos
#: on the matrix-free operator is faster (a dense eigh is O(n^3))
DENSE_LIMIT = 300
#: relative accuracy requested from ARPACK for the largest eigenvalue
EIGSH_TOL = 1e-10
#: weight of the fixed random vector mixed into a warm start (keeps every direction)
WARM_START_MIX = 1e-2
#: seed of the fixed pseudo-random start vector
START_SEED = 12345


@dataclass
class Eigenpair:
    """Ritz value ``value`` (<= the largest eigenvalue), unit vector ``vector`` and the
    residual norm ``residual`` = |A y - value y|; ``upper`` = value + residual bounds
    the eigenvalue found from above."""

    value: float
    vector: np.ndarray
    residual: float

    @property
    def upper(self) -> float:
        return self.value + self.residual


def start_vector(n: int, warm: np.ndarray | None = None) -> np.ndarray:
    """A reproducible start vector: the fixed pseudo-random one, or ``warm`` with 1 % of
    it mixed in (so that no eigen-direction is missing from the start)."""
    rand = np.random.default_rng(START_SEED).standard_normal(n)
    rand /= np.linalg.norm(rand)
    if warm is None or warm.shape != (n,) or not np.all(np.isfinite(warm)):
        return rand
    norm = np.linalg.norm(warm)
    if norm == 0:
        return rand
    return warm / norm + WARM_START_MIX * rand


def top_eigenpair(A, v0: np.ndarray | None = None, dense_limit: int = DENSE_LIMIT,
                  tol: float = EIGSH_TOL, dense=None) -> Eigenpair:
    """Largest eigenpair of the symmetric PSD ``A`` (ndarray, sparse matrix or
    ``scipy.sparse.linalg.LinearOperator``) with its residual.

    Up to ``dense_limit`` DOFs the dense matrix (``dense()`` when given, else A itself)
    goes to ``eigh``; above, ``eigsh`` runs on A from the start :func:`start_vector`."""
    n = A.shape[0]
    if n == 0:
        return Eigenpair(0.0, np.zeros(0), 0.0)
    if n <= dense_limit:
        M = dense() if dense is not None else A
        M = M.toarray() if sp.issparse(M) else np.asarray(M)
        w, V = scipy.linalg.eigh(M, subset_by_index=[n - 1, n - 1])
        y = V[:, 0]
        return Eigenpair(float(w[0]), y, float(np.linalg.norm(M @ y - w[0] * y)))
    start = start_vector(n, v0)
    vals, vecs = spla.eigsh(A, k=1, which="LA", tol=tol, v0=start, ncv=min(n - 1, 32),
                            maxiter=100 * n)
    y = vecs[:, 0] / np.linalg.norm(vecs[:, 0])
    theta = float(y @ (A @ y))
    return Eigenpair(theta, y, float(np.linalg.norm(A @ y - theta * y)))


def lambda_max(A, dense_limit: int = DENSE_LIMIT, tol: float = EIGSH_TOL) -> float:
    """Largest eigenvalue (the Ritz value) of the symmetric matrix A (sparse or dense)."""
    return top_eigenpair(A, dense_limit=dense_limit, tol=tol).value
