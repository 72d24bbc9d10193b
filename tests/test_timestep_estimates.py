"""Estimates side by side: bounds are conservative, paper values reproduced."""

import math

import numpy as np
import pytest
import scipy.linalg
from hypothesis import HealthCheck, given, settings, strategies as st

from demstep.timestep.contacts import find_contacts
from demstep.errors import InputError
from demstep.packings import lattice
from demstep.particles import Particles
from demstep.timestep import estimate_time_steps, rayleigh_damped_dt
from demstep.timestep.assembly import scaled_stiffness
from demstep.timestep.eigen import DENSE_LIMIT, lambda_max
from demstep.timestep.estimates import element_coupled_dt, exact_dt
from demstep.timestep.mass_split import cap_fraction, element_mass
from demstep.timestep.paper_table import PAPER_FCC_TRANSLATION_ZONED, PAPER_MINIMA, minima, paper_table
from demstep.timestep.stability import dt_from_lambda

from conftest import random_polydisperse


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10**6), dim=st.sampled_from([2, 3]), rotation=st.booleans(),
       walls=st.booleans(), fixed=st.booleans(), split=st.sampled_from(["uniform", "zoned"]))
def test_coupled_element_bound_is_conservative_and_exact_matches_dense(seed, dim, rotation, walls,
                                                                       fixed, split):
    if split == "zoned" and dim == 2:
        split = "uniform"
    p, c = random_polydisperse(seed, dim, n=27 if dim == 3 else 25, walls=walls, fixed=fixed)
    if c.n == 0:
        return
    A = scaled_stiffness(p, c, rotation)
    assert A.shape[0] <= DENSE_LIMIT  # exact_dt takes the dense path on these sizes...
    exact = exact_dt(p, c, rotation)
    dense = dt_from_lambda(scipy.linalg.eigh(A.toarray(), eigvals_only=True)[-1])
    sparse = dt_from_lambda(lambda_max(A, dense_limit=0))  # ...so force ARPACK on them too
    assert exact == pytest.approx(dense, rel=1e-10)
    assert sparse == pytest.approx(dense, rel=1e-10)
    # Rayleigh's bound holds for any partition of the masses, uniform or zoned
    assert element_coupled_dt(p, c, rotation, split) <= exact * (1 + 1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10**6), dim=st.sampled_from([2, 3]))
def test_mass_splits_are_partitions(seed, dim):
    p, c = random_polydisperse(seed, dim, n=27, walls=True)
    for split in (["uniform", "zoned"] if dim == 3 else ["uniform"]):
        em = element_mass(p, c, split)
        pp = c.j >= 0
        total_m = np.bincount(c.i, 1 / em.inv_m_i, p.n) + np.bincount(c.j[pp], 1 / em.inv_m_j[pp], p.n)
        total_I = np.bincount(c.i, 1 / em.inv_I_i, p.n) + np.bincount(c.j[pp], 1 / em.inv_I_j[pp], p.n)
        has = c.count_per_particle(p.n) > 0
        assert np.allclose(total_m[has], p.m[has], rtol=1e-12)
        assert np.allclose(total_I[has], p.inertia[has], rtol=1e-12)


def test_zoned_split_rows_fcc():
    """FCC: the central row's share is the central zone over 8 contacts."""
    lat = lattice("fcc", 1.0)
    x, box = lat.supercell(3)
    p = Particles.from_density(x, np.ones(len(x)), 1.0)
    c = find_contacts(p, 1.0, periodic=box)
    em = element_mass(p, c, "zoned")
    central = np.abs(c.normal[:, 2]) < 1e-9
    share = 1 / (em.inv_m_i[central] * p.m[0])
    assert np.allclose(share, (1 - 2 * cap_fraction()) / 8)


@pytest.fixture(scope="module")
def table():
    return paper_table()


@pytest.mark.parametrize("key", list(PAPER_MINIMA))
def test_paper_minima_to_their_last_digit(table, key):
    """The paper prints three digits: each minimum within one unit of the last."""
    assert minima(table)[key] == pytest.approx(PAPER_MINIMA[key], abs=1e-3)


def test_paper_fcc_translation_zoned(table):
    fcc = next(r for r in table if r.lattice == "fcc")
    assert fcc.alpha[("paper", False, "zoned")] == pytest.approx(PAPER_FCC_TRANSLATION_ZONED, rel=0.01)


def test_fcc_with_rotation_exact_below_035(table):
    """The paper calls alpha = 0.35 safe for its FCC case (the lattice hardly rotates); with
    coupled rotation the exact FCC step is below it (docs/time-step-elements.md)."""
    fcc = next(r for r in table if r.lattice == "fcc")
    assert fcc.alpha[("exact-periodic", True, None)] < 0.35
    assert fcc.alpha[("exact-periodic", False, None)] > 0.45


def test_element_paper_is_conservative_on_lattices(table):
    for r in table:
        for rot in (False, True):
            assert r.alpha[("paper", rot, "uniform")] <= r.alpha[("exact-periodic", rot, None)] * (1 + 1e-9)
            assert r.alpha[("coupled", rot, "uniform")] <= r.alpha[("exact-periodic", rot, None)] * (1 + 1e-9)


def _sdof_critical_dt(omega, a1, a2):
    """Bisection on the spectral radius of the central-difference amplification matrix
    of m x'' + c x' + k x = 0 with the damping force on the lagged velocity v(t-dt/2)."""
    k, c = omega**2, a1 + a2 * omega**2

    def unstable(dt):
        A = np.array([[1 - k * dt * dt, dt * (1 - c * dt)], [-k * dt, 1 - c * dt]])
        return np.abs(np.linalg.eigvals(A)).max() > 1 + 1e-12

    lo, hi = 1e-6, 2.0 / omega * 1.01
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if unstable(mid) else (mid, hi)
    return lo


@pytest.mark.parametrize("a1,a2", [(0.0, 0.0), (0.4, 0.0), (0.0, 0.05), (0.3, 0.02), (2.0, 0.1)])
def test_rayleigh_eq28_against_amplification_matrix(a1, a2):
    omega = 3.0
    assert rayleigh_damped_dt(2 / omega, a1, a2) == pytest.approx(_sdof_critical_dt(omega, a1, a2),
                                                                  rel=1e-6)


def test_report_rayleigh_applies_to_every_method():
    lat = lattice("sc", 1.0)
    x = lat.block(2)
    p = Particles.from_density(x, np.ones(len(x)), 1.0)
    c = find_contacts(p, 1.0)
    plain = estimate_time_steps(p, c)
    damped = estimate_time_steps(p, c, rayleigh=(0.1, 0.01))
    assert [e.method for e in damped.estimates if e.method != "exact-undamped"] == \
        [e.method for e in plain.estimates]
    # Rayleigh damping is proportional: every method's damped step is eq. 28 at its
    # own highest frequency (the paper's guidance keeps its safety factor 0.75 outside)
    from demstep.timestep.estimates import GUIDANCE_SAFETY

    for a in plain.estimates:
        b = damped.get(a.method)
        f = GUIDANCE_SAFETY if a.method == "guidance" else 1.0
        assert b.dt == pytest.approx(f * float(rayleigh_damped_dt(a.dt / f, 0.1, 0.01)), rel=1e-8)
        assert b.dt < a.dt
    assert damped.get("exact-undamped").dt == pytest.approx(plain.get("exact").dt, rel=1e-12)


def test_no_contacts_is_an_input_error():
    p = Particles.from_density(np.array([[0.0, 0], [5.0, 0]]), np.ones(2), 1.0)
    with pytest.raises(InputError, match="no contacts"):
        estimate_time_steps(p, find_contacts(p, 1.0))


def test_itasca_is_unconservative_on_dense_lattices():
    lat = lattice("fcc", 1.0)
    x = lat.block(2)
    p = Particles.from_density(x, np.ones(len(x)), 1.0)
    rep = estimate_time_steps(p, find_contacts(p, 1.0))
    assert rep.m_min == p.m.min() and rep.k_max == 1.0  # alpha's scale: sqrt(m_min / K_max)
    assert rep.get("itasca").dt == pytest.approx(math.sqrt(p.m.min() / 1.0), rel=1e-12)
    assert rep.get("itasca").conservative is False
    assert rep.get("element-coupled").conservative is True
    assert rep.get("itasca").alpha == pytest.approx(1.0)
    assert rep.get("guidance").alpha == pytest.approx(0.17)


@pytest.mark.parametrize("dim", [2, 3])
def test_damped_paper_element_step_tends_to_the_undamped_one(dim):
    """On a random assembly (normals off the axes: the rotational factor 1 - min n_k^2
    matters) the paper element's damped step with vanishing damping is its undamped
    step (a damped path that drops a factor differs)."""
    from demstep.timestep.damping import GlobalDamping
    from demstep.timestep.estimates import element_paper_dt

    p, c = random_polydisperse(7, dim, n=27)
    undamped = element_paper_dt(p, c, True)
    nearly = element_paper_dt(p, c, True, damping=GlobalDamping(1e-12, 0.0))
    assert nearly == pytest.approx(undamped, rel=1e-9)


def test_tangential_dashpots_alone_set_the_dashpot_ratio():
    """The rules' dashpot ratio is the largest c/k over normal and tangential dashpots:
    with tangential ones only, max(c_t / k_s)."""
    from dataclasses import replace

    from demstep.timestep.estimates import dashpot_ratio

    p, c = random_polydisperse(7, 3, n=27)
    c = replace(c, c_n=np.zeros(c.n), c_t=0.3 * c.k_s)
    assert dashpot_ratio(c) == pytest.approx(0.3, rel=1e-12)


def test_rayleigh_time_against_the_rayleigh_wave_equation():
    """T_R = pi r / c_R with c_R the root of Rayleigh's equation (xi = c_R / c_S):
    xi^6 - 8 xi^4 + (24 - 16 k^2) xi^2 - 16 (1 - k^2) = 0, k^2 = c_S^2 / c_P^2 =
    (1 - 2 nu) / (2 (1 - nu)); the usual fit (0.1631 nu + 0.8766) is within 0.5 %."""
    from demstep.timestep.rules import rayleigh_time

    r, rho, E = 1e-3, 2500.0, 7e10
    for nu in (0.2, 0.3, 0.4):
        G = E / (2 * (1 + nu))
        k2 = (1 - 2 * nu) / (2 * (1 - nu))
        roots = np.roots([1, 0, -8, 0, 24 - 16 * k2, 0, -16 * (1 - k2)])
        xi = min(z.real for z in roots if abs(z.imag) < 1e-12 and 0 < z.real < 1)
        t_exact = np.pi * r / (xi * np.sqrt(G / rho))
        assert rayleigh_time([r], [rho], [E], [nu]) == pytest.approx(t_exact, rel=5e-3)


def test_hertz_time_against_an_integrated_impact():
    """The duration of a Hertz impact of two equal spheres (m* = m/2, R* = r/2,
    F = 4/3 E* sqrt(R*) d^1.5), integrated numerically (scipy's solve_ivp to the
    separation), against hertz_time, which takes its mass and r/2 as the effective mass
    and radius (2.87 (m^2 / (R E*^2 v))^(1/5), LIGGGHTS' form with the particle's mass,
    longer than the pair's impact): given m* and r = 2 R*, it is this impact's duration,
    within 0.2 % (the constant 2.87 is rounded)."""
    from scipy.integrate import solve_ivp

    from demstep.timestep.rules import hertz_time

    m, r, e_star, v = 2.0e-3, 1e-2, 1e8, 1.0
    m_star, r_star = m / 2, r / 2
    k = 4.0 / 3.0 * e_star * np.sqrt(r_star)

    def rhs(t, y):
        return [y[1], -k * max(y[0], 0.0) ** 1.5 / m_star]

    def separated(t, y):
        return y[0] if t > 0 else 1.0

    separated.terminal, separated.direction = True, -1
    scale = (m_star**2 / (r_star * e_star**2 * v)) ** 0.2
    out = solve_ivp(rhs, (0, 10 * scale), [0.0, v], events=separated, rtol=1e-11,
                    atol=1e-15 * v * scale, max_step=scale / 200)
    duration = out.t_events[0][-1]
    assert hertz_time([m_star], [2 * r_star], [e_star], v) == pytest.approx(duration, rel=2e-3)
