"""Estimates side by side: bounds are conservative, paper values reproduced."""

import math

import numpy as np
import pytest
import scipy.linalg
from hypothesis import HealthCheck, given, settings, strategies as st

from demstep.contacts import find_contacts
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
    """DESIGN 1.6: with coupled rotation the exact FCC step is below the paper's 0.35."""
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
