"""The engine's damped stability threshold against the damped exact step (issue 45, item 2).

The engine's one-step map is built from the engine itself (one ``Simulation.run`` step
per perturbed coordinate, :mod:`demstep.experiments.amplification`), not from a
re-derived formula. Its spectral radius crosses 1 at dt = 2 / s, s the largest root of
det(s^2 M - s C - K) = 0: the dashpots act on the lagged half-step velocity, the scheme
the certificate analyses. What had put the measured threshold of `demstep paper` above
that step (+0.66 % at restitution 0.5, +1.26 % at 0.2) was the Coulomb cap of the
tangential dashpot, which bounds the growth of the unstable mode when the start is not
small enough, and the slow growth of a heavily damped critical mode.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from demstep.contact.laws import LinearSpring
from demstep.energy import EnergyMonitor
from demstep.engine import Simulation, TimeStep
from demstep.experiments.amplification import EngineMap, map_threshold, spectral_radius
from demstep.experiments.stability import SPECIMEN, build_specimen, is_unstable
from demstep.particles import Particles

K = 1.0e6


def _line_of_three(restitution: float = 0.3, dt: float | None = None, v0: float = 0.0):
    """One sphere pressed between two fixed ones along x (an equilibrium), normal and
    tangential dashpots of restitution ``restitution``; ``v0`` its initial x velocity."""
    r, p = 1.0, 1e-3
    x = np.array([[0.0, 0.0, 0.0], [2 * r, 0.0, 0.0], [4 * r, 0.0, 0.0]])
    particles = Particles.from_density(x, np.full(3, r * (1 + p)), 1.0,
                                       fixed=[True, False, True])
    law = LinearSpring(k_n=K, k_s=K, mu=0.5, restitution=restitution,
                       restitution_tangential=restitution)
    ts = TimeStep.fixed(dt) if dt is not None else TimeStep.from_alpha(0.1)
    v = np.zeros((3, 3))
    v[1, 0] = v0
    return Simulation(particles, law, timestep=ts, velocities=v, runaway_factor=0,
                      jump_limit=np.inf, energy=EnergyMonitor(every=10**9))


def _normal_mode(sim):
    """m, k, c of the free sphere's motion along the line (two contacts in parallel)."""
    c_n = sim.contact_set().c_n
    return float(sim.m[1]), 2.0 * K, float(np.sum(c_n))


class _Block:
    """The (x, v) block of the free sphere along the line: a one-degree-of-freedom map
    (it decouples from the rest to first order)."""

    def __init__(self, engine_map):
        self.engine_map = engine_map
        self.rows = [0, 3]  # x_x and v_x of the free sphere (EngineMap.coordinates)

    def matrix(self, dt):
        return self.engine_map.matrix(dt)[np.ix_(self.rows, self.rows)]


def test_one_dof_map_is_the_lagged_dashpot_scheme():
    """The engine's 1-DOF map has trace 2 - k dt^2/m - c dt/m and determinant 1 - c dt/m
    (dashpot on v(t - dt/2)); its spectral radius crosses 1 at dt = 2 / s with
    m s^2 - c s - k = 0, where the engine's measured threshold lies too."""
    sim = _line_of_three()
    block = _Block(EngineMap(sim))
    m, k, c = _normal_mode(sim)
    s = (c + math.sqrt(c * c + 4 * m * k)) / (2 * m)
    dt_c = 2.0 / s
    assert dt_c == pytest.approx(sim.critical_dt("exact", rotation=False), rel=1e-9)
    for dt in (0.5 * dt_c, dt_c):
        a = block.matrix(dt)
        assert np.trace(a) == pytest.approx(2 - k * dt**2 / m - c * dt / m, rel=1e-6, abs=1e-7)
        assert np.linalg.det(a) == pytest.approx(1 - c * dt / m, rel=1e-6, abs=1e-7)
    assert spectral_radius(block.matrix(dt_c * (1 - 1e-6))) <= 1.0
    assert spectral_radius(block.matrix(dt_c * (1 + 1e-6))) > 1.0
    assert map_threshold(block, 0.9 * dt_c, 1.1 * dt_c, rtol=1e-9) == pytest.approx(dt_c, rel=1e-8)

    def unstable(dt, steps=5000):
        run = _line_of_three(dt=dt, v0=1e-9)
        run.run(steps=1)
        ke0 = run.kinetic_energy()
        run.run(steps=steps)
        return not run.kinetic_energy() < 1e3 * ke0

    lo, hi = 0.9 * dt_c, 1.1 * dt_c
    assert not unstable(lo) and unstable(hi)
    while hi / lo - 1 > 1e-3:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if unstable(mid) else (mid, hi)
    assert lo <= dt_c <= hi


def test_coupled_map_of_the_line_of_three_crosses_one_at_the_exact_step():
    """Every coordinate (translation, spin, tangential springs): the map's threshold is
    the damped exact step with rotation (a tangential-rotational mode, half the normal
    one's)."""
    sim = _line_of_three()
    engine_map = EngineMap(sim)
    exact = sim.critical_dt("exact", rotation=True)
    assert exact < 0.6 * sim.critical_dt("exact", rotation=False)
    assert spectral_radius(engine_map.matrix(exact * (1 - 1e-6)), exclude=1e-3) <= 1.0
    assert map_threshold(engine_map, 0.9 * exact, 1.1 * exact, rtol=1e-8) == pytest.approx(
        exact, rel=1e-7)


def test_small_assembly_map_and_measured_threshold():
    """A periodic square lattice of 16 disks with rotation and dashpots of restitution
    0.2: the engine's map has spectral radius <= 1 at the damped exact step and > 1 just
    above it, and the engine's measured threshold (bisection on runs) brackets it."""
    dashpots = dict(restitution=0.2, restitution_tangential=0.2)
    sim = build_specimen("square", 0.1, law_options=dashpots)
    sim.v[:] = 0.0
    sim.w[:] = 0.0
    engine_map = EngineMap(sim)
    exact = sim.critical_dt("exact", rotation=True)
    assert spectral_radius(engine_map.matrix(exact * (1 - 1e-6)), exclude=1e-3) <= 1.0 + 1e-9
    assert spectral_radius(engine_map.matrix(exact * (1 + 1e-4)), exclude=1e-3) > 1.0 + 1e-5

    scale = math.sqrt(sim.m_min / sim.stiffness_max())
    alpha = exact / scale
    lo, hi = 0.99 * alpha, 1.01 * alpha
    while hi / lo - 1 > 1e-3:
        mid = 0.5 * (lo + hi)
        if is_unstable("square", mid, 10000, law_options=dashpots):
            hi = mid
        else:
            lo = mid
    assert lo <= alpha <= hi * (1 + 1e-9)


def test_the_coulomb_cap_hid_the_instability_of_a_large_start():
    """The FCC specimen of `demstep paper` at 1 % above its damped exact step
    (restitution 0.2): from a start of 1e-4 of the overlap the unstable mode drives the
    tangential dashpots to the Coulomb limit, the cap lowers the damping and the growth
    stops below the criterion (the old measurement called it stable); from 1e-7 of the
    overlap, or without the cap (mu = 100), the same run is unstable."""
    dashpots = dict(restitution=0.2, restitution_tangential=0.2)
    sim = build_specimen(SPECIMEN, 0.1, law_options=dashpots)
    sim.prepare()
    alpha = 1.01 * sim.critical_dt("exact", rotation=True) / math.sqrt(
        sim.m_min / sim.stiffness_max())
    assert not is_unstable(SPECIMEN, alpha, 3000, law_options=dashpots, perturbation=1e-4)
    assert is_unstable(SPECIMEN, alpha, 3000, law_options=dashpots, perturbation=1e-7)
    assert is_unstable(SPECIMEN, alpha, 3000, law_options={**dashpots, "mu": 100.0},
                       perturbation=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize("restitution", [0.5, 0.2])
def test_paper_specimen_map_crosses_one_at_the_damped_exact_step(restitution):
    """The FCC specimen of `demstep paper`'s damping section (150 spheres, 3150
    coordinates; about two and a half minutes each): the engine's map has spectral radius <= 1 at the
    damped exact step and > 1 at 0.02 % above it (measured 1 + 5.8e-4 at restitution 0.5,
    1 + 4.5e-4 at 0.2)."""
    dashpots = dict(restitution=restitution, restitution_tangential=restitution)
    sim = build_specimen(SPECIMEN, 0.1, law_options=dashpots)
    sim.v[:] = 0.0
    sim.w[:] = 0.0
    engine_map = EngineMap(sim)
    exact = sim.critical_dt("exact", rotation=True)
    assert spectral_radius(engine_map.matrix(exact * (1 - 1e-6)), exclude=1e-3) <= 1.0 + 1e-9
    assert spectral_radius(engine_map.matrix(exact * (1 + 2e-4)), exclude=1e-3) > 1.0 + 2e-4
