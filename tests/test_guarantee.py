"""What a certified step guarantees: the random-start Lanczos bound against its
probability statement and dense eigenvalues, and the certified step on assemblies built
to hide a stiff mode from the solver's fixed start (a decoupled stiff pair orthogonal to
it, one very stiff particle, a stiff cluster, a clump pressed into a wall)."""

import json
from dataclasses import replace

import numpy as np
import pytest
import scipy.linalg

from conftest import random_polydisperse
from demstep.errors import InputError
from demstep.particles import Particles
from demstep.timestep.assembly import assemble_stiffness, inverse_sqrt_mass
from demstep.timestep.clumps import RigidBodies
from demstep.timestep.contacts import ContactSet, find_contacts
from demstep.timestep.damping import GlobalDamping
from demstep.timestep.eigen import DENSE_LIMIT, _random_unit
from demstep.timestep.exact import (ScaledContactOperator, certified_without_basis,
                                    exact_critical_step)
from demstep.timestep.guarantee import (CLAIM_SLACK, _log_lanczos_poly, a_posteriori_upper,
                                        a_priori_eps, probable_upper_bound,
                                        sphere_share_quantile)
from demstep.timestep.stability import damped_sigma


def plain_lanczos(A, b, steps):
    """alpha, beta of plain Lanczos on the dense A from b (full reorthogonalisation:
    the exact-arithmetic reference), and the Lanczos vectors."""
    n = len(b)
    V = np.zeros((steps + 1, n))
    V[0] = b / np.linalg.norm(b)
    alpha, beta = np.zeros(steps), np.zeros(steps)
    for j in range(steps):
        w = A @ V[j]
        alpha[j] = V[j] @ w
        w -= V[:j + 1].T @ (V[:j + 1] @ w)
        w -= V[:j + 1].T @ (V[:j + 1] @ w)
        beta[j] = np.linalg.norm(w)
        V[j + 1] = w / beta[j]
    return alpha, beta, V


def test_sphere_share_quantile_bounds_the_probability_and_is_nearly_sharp():
    """P(|b_1| < delta) for b uniform on the sphere, sampled: at most the probability
    asked for, and not far below it (the density bound is nearly attained)."""
    rng = np.random.default_rng(0)
    n, p = 40, 0.05
    delta = sphere_share_quantile(n, p)
    b = rng.standard_normal((200_000, n))
    share = np.abs(b[:, 0]) / np.linalg.norm(b, axis=1)
    freq = float(np.mean(share < delta))
    assert freq <= p * 1.05
    assert freq >= 0.9 * p


def test_a_priori_eps_solves_the_kuczynski_wozniakowski_bound():
    n, k, p = 10_000, 300, 1e-9
    eps = a_priori_eps(n, k, p)
    assert 1.648 * np.sqrt(n) * np.exp(-np.sqrt(eps) * (2 * (k - 1) - 1)) == pytest.approx(p)
    assert a_priori_eps(n, 2, p) == 1.0  # too few products: no bound


def test_lanczos_polynomial_is_the_ritz_product_and_maps_b_to_the_next_vector():
    """log P_j(t) equals log of prod (t - theta_i) / prod beta_i above the Ritz values,
    and P_j(A) b is the (j+1)-th Lanczos vector (evaluated on the eigen-decomposition)."""
    rng = np.random.default_rng(1)
    n = 60
    Q = np.linalg.qr(rng.standard_normal((n, n)))[0]
    lam = np.sort(rng.uniform(0.0, 1.0, n))
    A = (Q * lam) @ Q.T
    b = rng.standard_normal(n)
    b /= np.linalg.norm(b)
    alpha, beta, V = plain_lanczos(A, b, 12)
    ritz = scipy.linalg.eigvalsh_tridiagonal(alpha, beta[:-1])
    t = ritz[-1] + 0.3
    expected = np.sum(np.log(t - ritz)) - np.sum(np.log(beta))
    assert _log_lanczos_poly(t, alpha, beta) == pytest.approx(expected, rel=1e-12)
    assert _log_lanczos_poly(ritz[-1] - 1e-3, alpha, beta) == -np.inf
    # P_12(lambda_i) on each eigenvector: P(A) b = Q diag(P(lam)) Q^T b
    values = np.array([np.prod(l - ritz) / np.prod(beta) for l in lam])
    np.testing.assert_allclose(Q @ (values * (Q.T @ b)), V[12], atol=1e-8)


@pytest.mark.parametrize("seed", range(3))
def test_a_posteriori_bound_holds_whenever_the_start_has_its_share(seed):
    """The a posteriori bound is a deterministic consequence of |gamma_1| >= delta:
    whenever the start's share on the top eigenvector is at least delta, U >= lambda_1.
    With a large delta (the bound tight, near the edge) over many starts, including
    starts that barely touch the top eigenvector."""
    rng = np.random.default_rng(seed)
    n = 80
    Q = np.linalg.qr(rng.standard_normal((n, n)))[0]
    lam = np.sort(rng.uniform(0.0, 1.0, n))
    lam[-1] = 1.0 + 0.05 * seed
    A = (Q * lam) @ Q.T
    exercised = 0
    for trial in range(60):
        b = rng.standard_normal(n)
        b -= (1.0 - 10.0 ** -rng.uniform(0, 4)) * (b @ Q[:, -1]) * Q[:, -1]  # share shrunk
        b /= np.linalg.norm(b)
        gamma = abs(b @ Q[:, -1])
        alpha, beta, _ = plain_lanczos(A, b, 8)
        theta = scipy.linalg.eigvalsh_tridiagonal(alpha, beta[:-1])[-1]
        for delta in (0.5 * gamma, 0.99 * gamma):
            upper = a_posteriori_upper(theta, alpha, beta, delta)
            assert upper >= lam[-1] * (1 - 1e-12)
        if theta < lam[-1] * (1 - 1e-3):
            exercised += 1
            # with delta above the share, the implication does not hold: the bound may
            # lie below the top (it is not a bound without the share)
            upper = a_posteriori_upper(theta, alpha, beta, min(1.0, 50.0 * gamma))
            assert upper < a_posteriori_upper(theta, alpha, beta, 0.99 * gamma)
    assert exercised >= 10  # (starts where the top had not converged: the bound worked)


def test_probable_bound_frequency_of_failure_is_below_the_stated_probability():
    """With a stated failure probability of 0.3 and few steps, over 400 random starts,
    the bound lies below lambda_max at most 30 % of the time (and is informative)."""
    rng = np.random.default_rng(5)
    n = 200
    Q = np.linalg.qr(rng.standard_normal((n, n)))[0]
    lam = np.sort(rng.uniform(0.0, 1.0, n))
    A = (Q * lam) @ Q.T

    def matvec(x, out):
        out[:] = A @ x

    below, widths = 0, []
    for seed in range(400):
        pb = probable_upper_bound(matvec, n, failure=0.3, seed=seed, max_steps=6,
                                  check_every=6)
        below += pb.upper < lam[-1]
        widths.append(pb.upper / lam[-1])
    assert below <= 0.3 * 400
    assert np.median(widths) < 1.5


def test_probable_bound_is_reproducible_from_its_seed_and_refuses_a_bad_failure():
    rng = np.random.default_rng(2)
    n = 400
    M = rng.standard_normal((n, n))
    A = M @ M.T

    def matvec(x, out):
        out[:] = A @ x

    a = probable_upper_bound(matvec, n, seed=7, max_steps=120)
    b = probable_upper_bound(matvec, n, seed=7, max_steps=120)
    c = probable_upper_bound(matvec, n, seed=8, max_steps=120)
    assert (a.upper, a.steps) == (b.upper, b.steps)
    assert a.upper != c.upper
    top = np.linalg.eigvalsh(A)[-1]
    assert top <= a.upper <= top * 1.01
    for bad in (0.0, 0.7, "x", -1e-3):
        with pytest.raises(InputError, match="failure"):
            probable_upper_bound(matvec, n, failure=bad)


def dense_operator(p, c, rotation):
    s = inverse_sqrt_mass(p, rotation)
    return assemble_stiffness(p, c, rotation, scale=s).toarray()


def hidden_dimer(ratio, rotation, damped=False):
    """A polydisperse packing and, far from it, a pair of free spheres whose only
    contact is stiff along a normal chosen orthogonal to the solver's fixed start vector
    (its normal mode has no share of the start): the pair's mode lies ``ratio`` above
    the packing's top eigenvalue (``damped``: with dashpots c = beta k on every contact,
    whose damped modes are the undamped ones: the pair's is the critical one)."""
    p0, c0 = random_polydisperse(5, 3, n=150)
    nd = 6 if rotation else 3
    x = np.vstack([p0.x, [[1e3, 0, 0], [1e3 + 2.0, 0, 0]]])
    r = np.concatenate([p0.r, [1.0, 1.0]])

    def build(x):
        q = Particles.from_density(x, r, 1.0)
        q.m[:p0.n], q.inertia[:p0.n] = p0.m, p0.inertia
        return q

    q = build(x)
    start = _random_unit(q.n * nd).reshape(q.n, nd)
    d = start[-2, :3] / np.sqrt(q.m[-2]) - start[-1, :3] / np.sqrt(q.m[-1])
    normal = np.cross(d, [0.3, 0.5, 0.7])
    normal /= np.linalg.norm(normal)
    x[-1] = x[-2] + 1.998 * normal
    q = build(x)
    c = find_contacts(q, 1.0, 1.0)
    pair = (c.i >= p0.n) | (c.j >= p0.n)
    assert pair.sum() == 1
    k_n, k_s = np.empty(c.n), np.empty(c.n)
    k_n[~pair], k_s[~pair] = c0.k_n, c0.k_s  # (the packing's contacts in the same order)
    k_n[pair], k_s[pair] = 0.0, 1e-6
    c = replace(c, k_n=k_n, k_s=k_s)
    top = np.linalg.eigvalsh(dense_operator(q, c, rotation))[-1]
    k_n[pair] = ratio * top / (1.0 / q.m[-2] + 1.0 / q.m[-1])
    c = replace(c, k_n=k_n)
    if damped:  # dashpots proportional to the springs: the modes stay the undamped ones
        beta = 0.3 / np.sqrt(top)
        c = replace(c, c_n=beta * k_n, c_t=beta * k_s)
    return q, c


def damped_truth(p, c, rotation):
    """sigma_max of det(s^2 I - s C^ - K^) = 0 from the dense linearised problem."""
    K = dense_operator(p, c, rotation)
    C = dense_operator(p, replace(c, k_n=c.c_n, k_s=c.c_t), rotation)
    n = len(K)
    L = np.block([[np.zeros((n, n)), np.eye(n)], [K, C]])
    return float(np.max(np.linalg.eigvals(L).real))


@pytest.mark.parametrize("rotation", [False, True])
@pytest.mark.parametrize("ratio", [1.01, 1.1])
def test_a_stiff_mode_hidden_from_the_fixed_start_is_found(rotation, ratio):
    """The solver's fixed start has no share of the pair's mode: its step (the old
    'certified' one) lies above the true critical step; the certified step, from a
    random start, lies below it, by the claim's slack only."""
    p, c = hidden_dimer(ratio, rotation)
    op_size = p.n * (6 if rotation else 3)
    assert op_size > DENSE_LIMIT  # (the Lanczos path)
    truth = 2.0 / np.sqrt(np.linalg.eigvalsh(dense_operator(p, c, rotation))[-1])
    result = exact_critical_step(p, c, rotation, guarantee=True, seed=11)
    assert result.dt > truth * (1.0 + 0.5 * (1.0 - 1.0 / np.sqrt(ratio)))  # missed
    assert result.guarantee.kind == "probability"
    assert result.check.ritz > 4.0 / result.dt ** 2  # the check saw the larger eigenvalue
    assert truth * (1.0 - CLAIM_SLACK) <= result.dt_certified <= truth


def test_a_hidden_damped_mode_is_found():
    p, c = hidden_dimer(1.1, False, damped=True)
    truth = 2.0 / damped_truth(p, c, False)
    result = exact_critical_step(p, c, False, guarantee=True, seed=3)
    assert result.dt > truth * 1.001  # the damped iteration missed the pair's mode
    assert truth * (1.0 - 4.0 * CLAIM_SLACK) <= result.dt_certified <= truth


def stiff_spot_assembly(kind):
    """A soft packing with a stiff local feature: one particle whose contacts are 1e4x
    stiffer ('particle'), or three touching particles bound 1e3x stiffer ('cluster')."""
    p, c = random_polydisperse(9, 3, n=150)
    k_n, k_s = c.k_n.copy(), c.k_s.copy()
    if kind == "particle":
        hub = int(np.bincount(np.concatenate([c.i, c.j[c.j >= 0]])).argmax())
        near = (c.i == hub) | (c.j == hub)
        k_n[near] *= 1e4
        k_s[near] *= 1e4
    else:
        first = int(c.i[0])
        pairs = np.flatnonzero((c.i == first) | (c.j == first))[:2]
        k_n[pairs] *= 1e3
        k_s[pairs] *= 1e3
    return p, replace(c, k_n=k_n, k_s=k_s)


@pytest.mark.parametrize("kind", ["particle", "cluster"])
@pytest.mark.parametrize("damped", [False, True])
def test_certified_step_below_the_truth_with_a_stiff_spot(kind, damped):
    p, c = stiff_spot_assembly(kind)
    if damped:
        c = replace(c, c_n=0.3 * np.sqrt(c.k_n), c_t=0.3 * np.sqrt(c.k_s))
        truth = 2.0 / damped_truth(p, c, True)
    else:
        truth = 2.0 / np.sqrt(np.linalg.eigvalsh(dense_operator(p, c, True))[-1])
    result = exact_critical_step(p, c, True, guarantee=True, seed=5)
    assert truth * (1.0 - 4.0 * CLAIM_SLACK) <= result.dt_certified <= truth
    assert result.dt_certified <= result.dt


def test_a_clump_pressed_into_a_wall_is_certified_against_the_dense_body_problem():
    """A soft packing and, apart, a two-sphere clump pressed into a wall by stiff
    contacts (the body's six DOFs, its inertia tensor): the certified step lies below
    the dense solve of the bodies' operator."""
    p0, c0 = random_polydisperse(4, 3, n=120)
    n = p0.n + 2
    x = np.vstack([p0.x, [[50.0, 0.0, 0.0], [50.0, 0.0, 1.6]]])
    r = np.concatenate([p0.r, [0.9, 0.9]])
    m = np.concatenate([p0.m, [1.0, 1.0]])
    inertia = np.concatenate([p0.inertia, [0.3, 0.3]])
    p = Particles(x, r, m, inertia, np.zeros(n, bool))
    body = np.full(n, -1)
    body[-2:] = 0
    arm = np.zeros((n, 3))
    arm[-2] = [0.0, 0.0, -0.8]
    arm[-1] = [0.0, 0.0, 0.8]
    bodies = RigidBodies(body, arm, np.array([2.0]), np.diag([1.6, 1.6, 0.6])[None],
                         np.array([False]))
    i = np.concatenate([c0.i, [n - 2, n - 1]])
    j = np.concatenate([c0.j, [-1, -1]])
    normal = np.vstack([c0.normal, [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    stiff = 40.0 * float(c0.k_n.max())
    c = ContactSet(i, j, normal, np.concatenate([c0.arm_i, [0.9, 0.9]]),
                   np.concatenate([c0.arm_j, [0.0, 0.0]]),
                   np.concatenate([c0.k_n, [stiff, stiff]]),
                   np.concatenate([c0.k_s, [0.5 * stiff, 0.5 * stiff]]))
    op = ScaledContactOperator(p, c, True, bodies=bodies)
    dense = np.stack([op.stiffness(e) for e in np.eye(op.size)], axis=1)
    truth = 2.0 / np.sqrt(np.linalg.eigvalsh(0.5 * (dense + dense.T))[-1])
    result = exact_critical_step(p, c, True, bodies=bodies, guarantee=True, seed=2)
    assert result.guarantee.kind == "probability"
    assert truth * (1.0 - CLAIM_SLACK) <= result.dt_certified <= truth


@pytest.mark.parametrize("damping", [None, GlobalDamping(0.05, 0.01)])
def test_the_dense_path_is_a_proof_below_the_truth(damping):
    p, c = random_polydisperse(2, 3, n=30)
    c = replace(c, c_n=0.2 * np.sqrt(c.k_n), c_t=0.1 * np.sqrt(c.k_s))
    result = exact_critical_step(p, c, True, damping=damping, guarantee=True)
    assert result.operator.size <= DENSE_LIMIT
    assert result.guarantee.kind == "proof" and result.check is None
    K = dense_operator(p, c, True)
    C = dense_operator(p, replace(c, k_n=c.c_n, k_s=c.c_t), True)
    if damping is not None:
        C = C + damping.mass * np.eye(len(K)) + damping.stiffness * K
    n = len(K)
    L = np.block([[np.zeros((n, n)), np.eye(n)], [K, C]])
    truth = 2.0 / float(np.max(np.linalg.eigvals(L).real))
    assert truth * (1.0 - 1e-8) <= result.dt_certified <= truth
    assert damped_sigma(1.0, 0.0) == 1.0  # (the root formula the certificate uses)


@pytest.mark.parametrize("damped", [False, True])
def test_the_certified_step_without_a_basis_is_below_the_truth(damped):
    """certified_without_basis (three vectors, no Lanczos basis): undamped, the same
    bound as a confirmed claim (within the slack of the truth); damped, the fixed point
    from below and a proven candidate: below the dense truth, within 4 slacks of it. On
    the hidden pair too (no fixed start to hide from)."""
    for p, c in (stiff_spot_assembly("cluster"), hidden_dimer(1.1, True)):
        if damped:
            c = replace(c, c_n=0.3 * np.sqrt(c.k_n), c_t=0.3 * np.sqrt(c.k_s))
            truth = 2.0 / damped_truth(p, c, True)
        else:
            truth = 2.0 / np.sqrt(np.linalg.eigvalsh(dense_operator(p, c, True))[-1])
        result = certified_without_basis(p, c, True, seed=4)
        assert result.mode is None and result.dt == result.dt_certified
        assert result.guarantee.kind == "probability"
        assert truth * (1.0 - 4.0 * CLAIM_SLACK) <= result.dt_certified <= truth


def test_low_memory_in_demstep_dt_certifies_without_exact(capsys):
    from demstep.cli import main

    argv = ["dt", "--lattice", "fcc", "--size", "4", "--json", "--seed", "3"]
    assert main(argv) == 0
    full = {e["method"]: e for e in json.loads(capsys.readouterr().out)["estimates"]}
    assert main(argv + ["--low-memory"]) == 0
    data = json.loads(capsys.readouterr().out)
    low = {e["method"]: e for e in data["estimates"]}
    assert "exact" not in low and any("low memory" in n for n in data["notes"])
    assert data["critical_mode"] is None
    assert low["certified"]["guarantee"]["kind"] == "probability"
    exact = full["exact"]["dt"]
    assert exact * (1 - CLAIM_SLACK) <= low["certified"]["dt"] <= exact
    assert main(argv + ["--low-memory", "--mode-vtk", "m.vtu"]) != 0
    assert "mode-vtk" in capsys.readouterr().err
