"""Parallel bonds (Potyondy & Cundall 2004) against beam theory and exact discrete
solutions: a bonded chain as a cantilever (Euler-Bernoulli, and the chain's exact
deflection with its shear springs), its axial vibration against sqrt(E/rho), breakage
at the stated strengths with the released energy in the ledger, restarts, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from demstep.contact.bonds import ParallelBonds, bond_candidates
from demstep.contact.laws import LinearSpring
from demstep.engine import Damping, Simulation, TimeStep
from demstep.errors import InputError
from demstep.particles import Particles

from conftest import oscillation_period

R = 0.5
RHO = 1000.0
KN = 1.0e6


def chain(n_bonds, dim=3, fixed_first=True, gap=0.0, **kw):
    """n_bonds + 1 spheres (disks) along x, ``gap`` apart (touching: 0), the first one
    fixed."""
    x = np.zeros((n_bonds + 1, dim))
    x[:, 0] = np.arange(n_bonds + 1) * (2 * R + gap)
    fixed = np.zeros(n_bonds + 1, bool)
    fixed[0] = fixed_first
    p = Particles.from_density(x, np.full(n_bonds + 1, R), RHO, fixed=fixed)
    return p, Simulation(p, LinearSpring(k_n=1e5, mu=0.5), **kw)


@pytest.mark.parametrize("k_s_ratio", [1.0, 0.05])
def test_bonded_cantilever_matches_beam_theory(k_s_ratio):
    """Tip load F on a clamped chain of N bonds of length l = 2r, at rest (damped):
    the bonds' rotations add up to the chain's exact deflection
    F l^2 / (k_n I) (N^3/3 - N/12) + N F / (k_s A) (bending at the bond points plus the
    shear springs), which tends to Euler-Bernoulli F L^3 / (3 E I) with E I = k_n I l
    (within 2 % here even with soft shear springs: Timoshenko's term is the second)."""
    n = 20
    p, _ = chain(n)
    m = p.m[1]
    area, second = math.pi * R**2, math.pi * R**4 / 4
    length, seg = n * 2 * R, 2 * R
    w1 = 3.516 * math.sqrt(KN * second * seg / (m / seg * length**4))
    _, sim = chain(n, damping=Damping(viscous=2 * w1),
                   timestep=TimeStep.fixed(0.2 * math.sqrt(m / (KN * area))))
    assert sim.add_bonds(ParallelBonds(normal_stiffness=KN, shear_stiffness=k_s_ratio * KN)) == n
    force = 1e-2
    sim.applied_force[n, 2] = -force
    sim.run(duration=12 * 2 * math.pi / w1)
    tip = -sim.x[n, 2]
    euler = force * length**3 / (3 * KN * second * seg)
    discrete = (force * seg**2 / (KN * second) * (n**3 / 3 - n / 12)
                + n * force / (k_s_ratio * KN * area))
    assert tip == pytest.approx(discrete, rel=1e-6)
    assert tip == pytest.approx(euler, rel=2e-2)
    timoshenko = euler + force * length / (k_s_ratio * KN * area * seg) * seg
    assert tip == pytest.approx(timoshenko, rel=2e-3)
    assert sim.ledger.balance_error() < 1e-5
    assert sim.bonds.intact.all()


def test_axial_vibration_of_a_bonded_chain_against_the_bar():
    """A free chain of N + 1 spheres vibrating along its axis in its first mode: the
    period of the discrete chain, 2 pi / (2 sqrt(k/m) sin(pi / (2 (N + 1)))), k = k_n A,
    and within 1 % the free bar's 2 L / c with c = sqrt(E / rho), E = k_n l,
    rho = m / (A l), L = (N + 1) l. The spheres are bonded across a small gap, so that
    their contacts (stiff in compression only) stay open."""
    n, gap = 24, 1e-3
    p, _ = chain(n, fixed_first=False, gap=gap)
    m, area, seg = p.m[0], math.pi * R**2, 2 * R + gap
    k = KN * area
    _, sim = chain(n, fixed_first=False, gap=gap, timestep=TimeStep.fixed(0.05 * math.sqrt(m / k)))
    assert sim.add_bonds(ParallelBonds(normal_stiffness=KN, gap=2 * gap)) == n
    count = n + 1
    xs = np.arange(count) * seg
    amplitude = 1e-4
    sim.v[:, 0] = amplitude * np.cos(math.pi * (np.arange(count) + 0.5) / count)
    period_chain = 2 * math.pi / (2 * math.sqrt(k / m) * math.sin(math.pi / (2 * count)))
    c = math.sqrt(KN * seg / (m / (area * seg)))
    period_bar = 2 * count * seg / c
    times, vs = [], []
    sim.every(1, lambda s: (times.append(s.time), vs.append(s.v[0, 0])))
    sim.run(duration=2.3 * period_chain)
    measured = oscillation_period(times, vs)
    assert measured == pytest.approx(period_chain, rel=2e-3)
    assert measured == pytest.approx(period_bar, rel=1e-2)
    assert abs(sim.x[:, 0] - xs).max() < 1e-3 * R  # small motion: linear


@pytest.mark.parametrize("mode", ["tension", "shear"])
def test_bond_breaks_at_its_strength_and_releases_its_energy(mode):
    """Two bonded spheres pulled apart (or sheared) at a slow constant speed: the bond
    breaks when its rim stress first reaches the strength (tension F/A = sigma_c; pure
    shear F/A = tau_c, the bending stress it also carries left below sigma_c), its
    stored energy F^2 / (2 k A) moves into the ledger's bond_broken term, and the
    particles are free afterwards."""
    sigma_c, tau_c = 50.0, 30.0
    x = np.array([[0.0, 0.0, 0.0], [2 * R, 0.0, 0.0]])
    p = Particles.from_density(x, np.full(2, R), RHO, fixed=[True, True])
    area = math.pi * R**2
    dt = 0.05 * math.sqrt(p.m[0] / (KN * area))
    sim = Simulation(p, LinearSpring(k_n=1e5, mu=0.5), timestep=TimeStep.fixed(dt))
    sim.add_bonds(ParallelBonds(normal_stiffness=KN, shear_stiffness=KN, tensile_strength=sigma_c,
                                shear_strength=tau_c))
    speed = 1e-6
    sim.v[1, 0 if mode == "tension" else 2] = speed  # fixed particles move with their velocity
    forces = []
    sim.every(1, lambda s: forces.append((s.bonds.intact[0], s.bonds.normal[0],
                                          np.linalg.norm(s.bonds.shear[0]), s.bonds.energy[0])))
    sim.run(duration=2 * (sigma_c if mode == "tension" else 4 * tau_c) * area / (KN * area * speed))
    states = np.asarray(forces)
    broke = int(np.argmin(states[:, 0]))
    assert states[-1, 0] == 0 and broke > 10
    last = states[broke - 1]
    step_force = KN * area * speed * dt
    if mode == "tension":
        assert -last[1] / area == pytest.approx(sigma_c, abs=step_force / area)
        assert -last[1] / area < sigma_c
    else:
        assert last[2] / area == pytest.approx(tau_c, abs=step_force / area)
    if mode == "tension":  # the stored energy of a bar: F^2 / (2 k A)
        assert last[3] == pytest.approx(last[1] ** 2 / (2 * KN * area), rel=1e-9)
    released = sim.ledger.bond_broken
    assert released > 0
    # the energy at the break is the last stored energy plus one step's increment
    held = (last[1] ** 2 + last[2] ** 2) ** 0.5
    assert released == pytest.approx(last[3], rel=2.5 * step_force / held)
    assert released > last[3]
    assert sim.bonds.energy[0] == 0 and sim.ledger.energy[5] == 0


def test_twisted_bond_oscillates_with_its_torsional_stiffness():
    """A sphere bonded to a fixed one (a small gap: no contact) spinning about the bond
    axis: a torsional oscillator of stiffness k_s^b J (J = pi R^4 / 2) and the sphere's
    inertia, period 2 pi sqrt(I / (k_s^b J)); at the turning points the bond holds the
    initial kinetic energy as M_t^2 / (2 k_s^b J)."""
    ks, gap, w0 = 4.0e5, 1e-3, 1e-2
    x = np.array([[0.0, 0.0, 0.0], [2 * R + gap, 0.0, 0.0]])
    p = Particles.from_density(x, np.full(2, R), RHO, fixed=[True, False])
    polar = math.pi * R**4 / 2
    period = 2 * math.pi * math.sqrt(p.inertia[1] / (ks * polar))
    sim = Simulation(p, LinearSpring(k_n=1e5, mu=0.5), timestep=TimeStep.fixed(period / 400))
    sim.add_bonds(ParallelBonds(normal_stiffness=KN, shear_stiffness=ks, gap=2 * gap))
    sim.w[1, 0] = w0
    times, spins, energies = [], [], []
    sim.every(1, lambda s: (times.append(s.time), spins.append(s.w[1, 0]),
                            energies.append(s.bonds.energy[0])))
    sim.run(duration=2.3 * period)
    assert oscillation_period(times, spins) == pytest.approx(period, rel=1e-3)
    assert max(energies) == pytest.approx(0.5 * p.inertia[1] * w0**2, rel=1e-3)
    assert np.abs(sim.w[1, 1:]).max() < 1e-12 * w0  # a pure twist
    assert sim.ledger.balance_error() < (2 * math.pi / 400) ** 2  # O((omega dt)^2): 5.6e-5


def test_bond_candidates_follow_the_gap_and_the_periodic_image():
    x = np.array([[0.1, 0.0, 0.0], [1.15, 0.0, 0.0], [9.95, 0.0, 0.0], [5.0, 5.0, 0.0]])
    r = np.full(4, 0.5)
    i, j = bond_candidates(x, r, 0.1, np.array([10.0, 0.0, 0.0]), 3)
    assert list(zip(i, j)) == [(0, 1), (0, 2)]  # 0-2 across the periodic boundary
    i, j = bond_candidates(x, r, 0.01, np.zeros(3), 3)
    assert len(i) == 0


@pytest.mark.parametrize("strength", [1e3, math.inf])
def test_restart_with_bonds_is_bit_identical(strength):
    """A run restored from its state continues bit for bit, with strengths or without a
    limit (inf: a value the checkpoint's checks accept)."""
    n = 6
    p, _ = chain(n)
    m, area = p.m[1], math.pi * R**2

    def make():
        _, sim = chain(n, timestep=TimeStep.fixed(0.2 * math.sqrt(m / (KN * area))))
        sim.add_bonds(ParallelBonds(normal_stiffness=KN, tensile_strength=strength,
                                    shear_strength=strength))
        sim.applied_force[n, 2] = -1.0
        return sim

    whole = make()
    whole.run(steps=900)
    first = make()
    first.run(steps=400)
    state = {k: np.array(v, copy=True) for k, v in first.state_dict().items()}
    second = make()
    second.bonds = second.bonds._replace(normal=np.zeros(n))  # overwritten by the restore
    second.load_state_dict(state)
    second.run(steps=500)
    assert np.array_equal(second.x, whole.x)
    assert np.array_equal(second.bonds.shear, whole.bonds.shear)
    assert np.array_equal(second.bonds.intact, whole.bonds.intact)
    assert np.array_equal(second.ledger.acc, whole.ledger.acc)


@pytest.mark.parametrize("kwargs, key", [
    ({"normal_stiffness": -1.0}, "bonds.normal_stiffness"),
    ({"normal_stiffness": 1.0, "tensile_strength": 0.0}, "bonds.tensile_strength"),
    ({"normal_stiffness": 1.0, "shear_strength": float("nan")}, "bonds.shear_strength"),
    ({"normal_stiffness": 1.0, "gap": -0.1}, "bonds.gap"),
])
def test_bad_bond_parameters_name_the_key(kwargs, key):
    with pytest.raises(InputError) as err:
        ParallelBonds(**kwargs).validate()
    assert str(err.value).startswith(key)


def test_bond_between_distant_particles_is_refused():
    p, sim = chain(3)
    with pytest.raises(InputError, match=r"bonds: pair \(0, 2\) is 1 apart, beyond the gap 0.1"):
        sim.add_bonds(ParallelBonds(normal_stiffness=KN, gap=0.1), pairs=[[0, 2]])


@pytest.mark.parametrize("pairs", [[[0, 1], [1, 2], [0, 1]], [[1, 0], [0, 1]]])
def test_a_pair_listed_twice_is_refused(pairs):
    """Two bonds on one pair (the list had it twice, in either order) were made: a
    bond file's duplicate is an error naming the pair, and no bond is added."""
    p, sim = chain(3)
    with pytest.raises(InputError, match=r"bonds: pair \(0, 1\) is listed twice"):
        sim.add_bonds(ParallelBonds(normal_stiffness=KN, gap=0.1), pairs=pairs)
    assert len(sim.bonds.i) == 0


BONDED_CASE = """
[particles]
generator = "lattice"
lattice = "hex"
radius = 1.0
size = [4, 3]
density = 1000.0
[contact]
law = "linear"
k_n = 1.0e5
mu = 0.5
[bonds]
normal_stiffness = 1.0e5
tensile_strength = 1.0e3
shear_strength = 1.0e3
gap = 0.01
stage = "load"
{extra}
[box]
margin = 0.0
[[stages]]
name = "settle"
steps = 150
[[stages]]
name = "load"
steps = 1500
[stages.walls."y+"]
motion = "velocity"
velocity = [0.0, -0.05]
"""


def test_case_bonds_created_at_their_stage_break_under_the_moving_wall(tmp_path):
    """[bonds] at the stage named 'load': the hex packing's touching pairs are bonded
    there (not before), the lid crushes it, bonds break and their released energy is in
    the history; the ledger balances."""
    import csv

    from demstep.case import build_simulation, load_case
    from demstep.runner import run_case

    path = tmp_path / "case.toml"
    path.write_text(BONDED_CASE.format(extra=""))
    case = load_case(path)
    sim = build_simulation(case)
    assert case.bond_stage() == 1 and sim.bonds.n == 0
    run_case(case, tmp_path / "out")
    rows = list(csv.DictReader(open(tmp_path / "out" / "history.csv")))
    last = rows[-1]
    assert float(last["bond_broken"]) > 0
    assert float(last["energy_error"]) < 1e-2
    assert all(float(r["strain_bonds"]) == 0.0 for r in rows if r["stage"] == "0")
    assert max(float(r["strain_bonds"]) for r in rows if r["stage"] == "1") > 0


@pytest.mark.parametrize("extra, content, message", [
    ('file = "bonds.csv"', "i,j\n0,1\n0,99\n", "bonds.file: particle index 99"),
    ('file = "bonds.csv"', "i,k\n0,1\n", "missing column 'j'"),
    ('file = "bonds.csv"', "i,j\n0,x\n", "not an integer: 'x'"),
    ('file = "missing.csv"', None, "missing.csv"),
])
def test_bad_bond_list_is_one_line_before_anything_is_written(tmp_path, extra, content, message):
    import subprocess
    import sys

    path = tmp_path / "case.toml"
    path.write_text(BONDED_CASE.format(extra=extra))
    if content is not None:
        (tmp_path / "bonds.csv").write_text(content)
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-m", "demstep.cli", "run", str(path), "--out", str(out)],
                         capture_output=True, text=True)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], lines
    assert not out.exists()


@pytest.mark.parametrize("name, k_ratio", [("fcc", 1.0), ("hex", 0.3)])
def test_engine_threshold_with_bonds_matches_the_exact_step(name, k_ratio):
    """A bonded pre-compressed lattice (bonds k^b A = k_ratio x the contact springs, with
    bending and twisting): the engine's measured stability threshold lies within 0.5 %
    above the exact critical step of the bonded assembly, and well below the step of
    the contacts alone (which a k_n-only rule would take)."""
    from demstep.experiments.stability import engine_threshold

    k_contact = 1.0e6
    area = math.pi if name == "fcc" else 2.0  # bond section at radius 1 (2D: per thickness)
    bonds = ParallelBonds(normal_stiffness=k_ratio * k_contact / area)
    res = engine_threshold(name, bonds=bonds)
    assert res["exact"] <= res["bracket"][1]
    assert res["measured"] == pytest.approx(res["exact"], rel=5e-3)
    assert res["exact"] < 0.9 * res["exact_springs_only"]


def test_bonds_between_clumps_load_the_bodies_and_keep_the_balance():
    """Bonds between the members of different two-sphere clumps (never within one):
    after bonding a settled heap of clumps, the bonds carry strain and the ledger
    still closes."""
    from test_rolling_resistance import _settling_clumps

    sim = _settling_clumps(LinearSpring(k_n=1e5, mu=0.4, restitution=0.5))
    added = sim.add_bonds(ParallelBonds(normal_stiffness=1e5, tensile_strength=2e3,
                                        shear_strength=2e3, gap=0.05))
    sb = sim.bodies.sphere_body
    assert added > 5
    assert np.all(sb[sim.bonds.i] != sb[sim.bonds.j])
    sim.run(steps=4000)
    assert sim.ledger.as_dict()["strain_bonds"] > 0
    assert sim.monitor.max_error < 2e-3
