"""What a certified step guarantees, and the random-start check that makes it a guarantee.

The exact step (:mod:`demstep.timestep.exact`) comes from ``theta + |r|``: a Ritz value
and its residual bound the eigenvalue the solver converged to (Bauer-Fike), which is the
top of the spectrum when the solver found it. Nothing in a residual proves that: a stiff
mode localised on a few particles, barely present in the start vector, can be missed,
and no number of products from a *deterministic* start can rule that out (Kuczynski &
Wozniakowski 1992, "Estimating the largest eigenvalue by the power and Lanczos
algorithms with a random start", SIAM J. Matrix Anal. Appl. 13(4), 1094-1122).

From a start drawn uniformly on the unit sphere it can be ruled out with a stated
probability. :func:`probable_upper_bound` runs plain Lanczos (the three-term recurrence
only: three vectors of storage, whatever the number of steps) from such a start and,
after j steps, bounds lambda_max of a symmetric positive semi-definite operator A in two
independent ways, each allowed half of the failure probability p:

* **a posteriori** (van Dorsselaer, Hochstenbach & van der Vorst 2000, "Computing
  probabilistic bounds for extreme eigenvalues of symmetric matrices with the Lanczos
  method", SIAM J. Matrix Anal. Appl. 22(3), 837-852): the (j+1)-th Lanczos vector is
  P_j(A) b with P_j the Lanczos polynomial (its roots are the Ritz values, its
  normalisation beta_1 ... beta_j), and |b| = 1, |P_j(A) b| = 1. With gamma the share of
  b on the top eigenvector, |gamma P_j(lambda_max)| <= 1. P_j increases beyond the
  largest Ritz value, so if |gamma| >= delta, lambda_max lies below the root U of
  P_j(U) = 1 / delta. For b uniform on the sphere of R^n, P(|gamma| < delta) <=
  delta sqrt(2 (n - 1) / pi) (the density of one coordinate is at most
  Gamma(n/2) / (sqrt(pi) Gamma((n-1)/2)) < sqrt((n - 1) / (2 pi))); delta is chosen so
  that this is p/2. The event does not depend on j: the bound may be checked after every
  step and the iteration stopped when it is good enough, at no extra risk.
* **a priori** (Kuczynski & Wozniakowski 1992, Theorem 4.2): after k products the top
  Ritz value theta_k satisfies P(theta_k < (1 - eps) lambda_max) <= 1.648 sqrt(n)
  exp(-sqrt(eps) (2k - 1)) for every symmetric positive definite A (and, by continuity,
  semi-definite). Setting the right side to p/2 gives eps_k, and lambda_max <=
  theta_k / (1 - eps_k). It is taken with k one less than the products made (the
  conservative reading of the theorem's count).

The bound returned is the smaller of the two (the union of two failure events of
probability p/2 each). Both are theorems in exact arithmetic. Plain Lanczos in floating
point loses orthogonality and repeats converged Ritz values (ghosts), but its recurrence
holds to rounding at every step (Paige 1976) and it behaves as exact Lanczos on a matrix
whose eigenvalues lie in tiny intervals around those of A (Greenbaum 1989), with the
start's weight on each cluster that of the eigenvector; the bound is widened by
:data:`ROUNDING_MARGIN` per step, relative, for that. The tests hide stiff localised
modes from smooth starts and compare with dense solves.

The seed of the start is recorded so a certificate can be reproduced; it is drawn from
the operating system's entropy unless given (a fixed seed is a deterministic start for
anyone who knows it).

The other two kinds of guarantee a step may carry are proofs: the dense eigensolver (up
to :data:`DENSE_LIMIT` DOFs; LAPACK's symmetric solver is backward stable, every
eigenvalue within :data:`DENSE_ROUNDING` n eps |A| of the exact one) and the element
bounds (Rayleigh's theorem on each contact element: rigorous, lower).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from demstep.errors import InputError
from demstep.kernels import timestep_kernels as tk

#: default failure probability of a probabilistic certificate
FAILURE = 1e-9
#: relative widening of the probabilistic bound per Lanczos step for rounding (module
#: docstring): 1000 eps, far above Paige's local errors of the recurrence
ROUNDING_MARGIN = 1000.0 * np.finfo(np.float64).eps
#: relative slack of a claim the random-start check confirms: the certified eigenvalue
#: bound is the claim times (1 + CLAIM_SLACK) (a step 0.005 % below the claim's)
CLAIM_SLACK = 1e-4
#: products of the random-start check at most (the a priori bound alone reaches
#: CLAIM_SLACK at 1e-9 within about 480 steps at n = 1e7)
MAX_STEPS = 2000
#: steps between evaluations of the bounds (each a few ms: a tridiagonal eigenvalue and
#: a root of the Lanczos polynomial)
CHECK_EVERY = 8
#: relative accuracy of a dense symmetric eigenvalue: |lambda - lambda_exact| <=
#: DENSE_ROUNDING n eps |A|_F (a generous constant on LAPACK's backward error)
DENSE_ROUNDING = 10.0


@dataclass(frozen=True)
class Guarantee:
    """What a step guarantees: ``kind`` one of

    * ``"proof"``: dt <= the critical step, proven (``method`` says how);
    * ``"probability"``: dt <= the critical step with probability >= 1 - ``failure``
      over the random start drawn with ``seed`` (``steps`` Lanczos products);
    * ``"lower-bound"``: a rigorous lower bound (element bounds: below the critical
      step by construction, often far below);
    * ``"estimate"``: bounds the eigenvalue the solver converged to, which is the top one
      when the solver found it (no proof that it did);
    * ``"rule"``: a rule of thumb, no bound at all.
    """

    kind: str
    method: str
    failure: float = 0.0
    seed: int | None = None
    steps: int = 0

    def describe(self) -> str:
        if self.kind == "probability":
            return (f"dt <= critical with probability >= 1 - {self.failure:.0e} "
                    f"({self.method}, {self.steps} steps, seed {self.seed})")
        if self.kind == "proof":
            return f"dt <= critical, proven ({self.method})"
        if self.kind == "lower-bound":
            return f"rigorous lower bound ({self.method})"
        if self.kind == "estimate":
            return f"no proof: {self.method}"
        return f"no bound: {self.method}"

    def to_json(self) -> dict:
        out = {"kind": self.kind, "method": self.method}
        if self.kind == "probability":
            out.update(failure=self.failure, seed=self.seed, steps=self.steps)
        return out


@dataclass
class ProbableBound:
    """The result of :func:`probable_upper_bound`: with probability >= 1 - ``failure``
    over the start drawn with ``seed``, lambda_max <= ``upper``; ``ritz`` is the largest
    Ritz value (a lower bound on lambda_max, to rounding), ``steps`` the products made,
    ``reached`` whether ``upper`` came down to the target asked for (when not, and
    ``ritz`` is above the target, the claim was wrong: an eigenvalue lies above it)."""

    upper: float
    ritz: float
    steps: int
    failure: float
    seed: int
    reached: bool

    def guarantee(self) -> Guarantee:
        return Guarantee("probability", "random-start Lanczos bound", self.failure, self.seed,
                         self.steps)


def check_failure(value) -> float:
    """``value`` as a failure probability in (0, 0.5], else an InputError naming it."""
    try:
        p = float(value)
    except (TypeError, ValueError):
        raise InputError(f"failure: must be a probability in (0, 0.5], got {value!r}") from None
    if not 0.0 < p <= 0.5:
        raise InputError(f"failure: must be a probability in (0, 0.5], got {value!r}")
    return p


def draw_seed() -> int:
    """A fresh seed from the operating system's entropy (recorded with the result)."""
    return int(np.random.SeedSequence().entropy % (1 << 63))


def sphere_share_quantile(n: int, probability: float) -> float:
    """delta with P(|b_1| < delta) <= ``probability`` for b uniform on the unit sphere of
    R^n (the density of b_1 is at most sqrt((n - 1) / (2 pi)); n = 1: b_1 = +-1)."""
    if n <= 1:
        return 1.0
    return min(1.0, probability / np.sqrt(2.0 * (n - 1) / np.pi))


def a_priori_eps(n: int, products: int, probability: float) -> float:
    """eps with 1.648 sqrt(n) exp(-sqrt(eps) (2k - 1)) = ``probability``, k = ``products``
    - 1 (Kuczynski & Wozniakowski's bound on the relative error of the top Ritz value
    after k products); 1.0 (no bound) when k < 2."""
    k = products - 1
    if k < 2:
        return 1.0
    root = np.log(1.648 * np.sqrt(n) / probability) / (2 * k - 1)
    return float(min(1.0, max(root, 0.0) ** 2))


def _log_lanczos_poly(t: float, alpha: np.ndarray, beta: np.ndarray) -> float:
    """log P_j(t) for t above every root of P_j (the Lanczos polynomial with
    beta_i P_i = (t - alpha_i) P_{i-1} - beta_{i-1} P_{i-2}, P_0 = 1); -inf when t is
    not above them (a ratio P_i / P_{i-1} not positive)."""
    total = 0.0
    ratio = np.inf  # P_0 / P_{-1}: the first step has no beta_0 term
    prev_beta = 0.0
    for a, b in zip(alpha, beta):
        ratio = ((t - a) - prev_beta / ratio) / b
        if not ratio > 0.0:
            return -np.inf
        total += np.log(ratio)
        prev_beta = b
    return total


def a_posteriori_upper(theta: float, alpha: np.ndarray, beta: np.ndarray, delta: float) -> float:
    """The root U > ``theta`` (the largest Ritz value) of P_j(U) = 1 / ``delta``
    (:func:`_log_lanczos_poly`), by bisection to a relative 1e-13 from above (the value
    returned is on the safe side)."""
    target = -np.log(delta)
    scale = max(abs(theta), float(np.max(np.abs(alpha))), 1e-300)
    lo = theta
    gap = 1e-14 * scale
    hi = theta + gap
    while _log_lanczos_poly(hi, alpha, beta) < target:
        lo = hi
        gap *= 4.0
        hi = theta + gap
        if gap > 1e6 * scale:  # pragma: no cover - P_j grows at least linearly
            return np.inf
    while hi - lo > 1e-13 * scale:
        mid = 0.5 * (lo + hi)
        if _log_lanczos_poly(mid, alpha, beta) < target:
            lo = mid
        else:
            hi = mid
    return hi


def probable_upper_bound(matvec, n: int, failure: float = FAILURE, seed: int | None = None,
                         target: float = 0.0, max_steps: int = MAX_STEPS,
                         check_every: int = CHECK_EVERY,
                         slack: float = CLAIM_SLACK) -> ProbableBound:
    """An upper bound on lambda_max of the symmetric positive semi-definite operator of
    size ``n`` (``matvec(x, out)`` writes A x into ``out``), holding with probability >=
    1 - ``failure`` over a start drawn uniformly on the unit sphere from ``seed`` (None:
    fresh entropy, :func:`draw_seed`); plain Lanczos (module docstring) stopped once the
    bound is at most ``target`` (then ``upper`` is ``target`` itself; 0: run
    ``max_steps``), or at most (1 + ``slack``) times a Ritz value above ``target`` (the
    claim was wrong: the top is higher, and the bound is as tight as a confirmed claim's;
    ``upper`` is that), or the Krylov space is invariant (then lambda_max is the largest
    Ritz value, almost surely)."""
    failure = check_failure(failure)
    seed = draw_seed() if seed is None else int(seed)
    if n == 0:
        return ProbableBound(0.0, 0.0, 0, failure, seed, True)
    delta = sphere_share_quantile(n, 0.5 * failure)
    v = np.random.default_rng(seed).standard_normal(n)
    tk.scale_into(v, 1.0 / np.sqrt(tk._norm2(v)), v)
    v_prev = np.zeros(n)
    w = np.empty(n)
    alpha = np.empty(max_steps)
    beta = np.empty(max_steps)
    beta_prev = 0.0
    theta = 0.0
    upper = np.inf
    steps = 0
    for j in range(max_steps):
        matvec(v, w)
        steps += 1
        a, b2 = tk.lanczos_recurrence(v, w, v_prev, beta_prev)
        b = float(np.sqrt(b2))
        alpha[j], beta[j] = a, b
        scale = max(abs(a), b, abs(theta), 1e-300)
        invariant = b <= 1e-13 * scale
        last = invariant or j + 1 == max_steps
        if last or (j + 1) % check_every == 0:
            al, be = alpha[:j + 1], beta[:j + 1]
            if j == 0:
                theta = a
            else:
                theta = float(scipy.linalg.eigvalsh_tridiagonal(
                    al, be[:-1], select="i", select_range=(j, j))[0])
            widen = 1.0 + ROUNDING_MARGIN * (j + 1)
            eps = a_priori_eps(n, j + 1, 0.5 * failure)
            prior = theta / (1.0 - eps) if eps < 1.0 else np.inf
            if invariant:
                upper = theta * widen
                break
            # reached when either bound is below the target: P_j(target / widen) at
            # least 1 / delta (one evaluation; the root itself only at the end)
            goal = max(target, theta * (1.0 + slack)) if target > 0 else 0.0
            claim = goal / widen
            if goal > 0 and (prior <= claim or (
                    claim > theta and _log_lanczos_poly(claim, al, be) >= -np.log(delta))):
                upper = goal
                break
            if last:
                upper = min(a_posteriori_upper(theta, al, be, delta), prior) * widen
                break
        # the next vector: v_prev <- v, v <- w / b (no new arrays)
        v_prev, v, w = v, w, v_prev
        tk.scale_into(v, 1.0 / b, v)
        beta_prev = b
    return ProbableBound(float(upper), float(theta), steps, failure, seed,
                         bool(target > 0 and upper <= target))
