"""Exact largest eigenvalue of M^-1 K: sparse Lanczos for large systems, dense below."""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

#: systems up to this many DOFs are solved densely (exact to rounding)
DENSE_LIMIT = 1500
#: relative accuracy requested from ARPACK for the largest eigenvalue
EIGSH_TOL = 1e-10


def lambda_max(A, dense_limit: int = DENSE_LIMIT, tol: float = EIGSH_TOL) -> float:
    """Largest eigenvalue of the symmetric matrix A (sparse or dense).

    Dense ``scipy.linalg.eigh`` up to ``dense_limit`` DOFs, else ARPACK's implicitly
    restarted Lanczos (``eigsh``, which='LA') started from a fixed vector so that
    results are reproducible."""
    n = A.shape[0]
    if n == 0:
        return 0.0
    if n <= dense_limit:
        dense = A.toarray() if sp.issparse(A) else np.asarray(A)
        return float(scipy.linalg.eigh(dense, eigvals_only=True, subset_by_index=[n - 1, n - 1])[0])
    v0 = np.random.default_rng(12345).standard_normal(n)
    vals = spla.eigsh(A, k=1, which="LA", tol=tol, v0=v0, ncv=min(n - 1, 32),
                      maxiter=100 * n, return_eigenvectors=False)
    return float(vals[0])
