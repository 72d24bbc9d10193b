"""Rolling and twisting resistance (Ai et al. 2011 type C) in the engine, against
analytic solutions: stopping distances of a rolling sphere and disk, the saturated
moment, the rocking and twisting frequencies of the elastic springs, a spin stopped by
the twisting limit; the ledger's balance; restarts; bad input."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from demstep.contact.laws import HertzMindlin, LinearSpring
from demstep.energy import A_ROLLING, E_STRAIN_R
from demstep.engine import Simulation, TimeStep
from demstep.errors import InputError
from demstep.kernels.dem import ROLL_TWIST
from demstep.particles import Particles
from demstep.walls import Wall

from conftest import oscillation_period

G = 9.81
RHO = 2500.0


def sphere_on_floor(law, r=0.01, dim=3, k_n=1e5, steps_per_period=40.0, **kw):
    """One sphere (disk) resting on the floor at its static overlap under gravity."""
    m = RHO * (4.0 / 3.0 * math.pi * r**3 if dim == 3 else math.pi * r**2)
    delta = m * G / k_n
    x = np.zeros((1, dim))
    x[0, -1] = r - delta
    p = Particles.from_density(x, np.array([r]), RHO)
    floor = Wall(point=[0.0] * dim, normal=[0.0] * (dim - 1) + [1.0], name="floor")
    gravity = [0.0] * (dim - 1) + [-G]
    dt = 2 * math.pi * math.sqrt(m / k_n) / steps_per_period
    return Simulation(p, law, walls=[floor], gravity=gravity, timestep=TimeStep.fixed(dt), **kw)


@pytest.mark.parametrize("dim", [3, 2])
@pytest.mark.parametrize("convention", ["epsd", "beta"])
def test_rolling_sphere_stops_at_the_analytic_distance(dim, convention):
    """Rolling without slip (v = omega b, b the arm from the centre to the floor)
    against the saturated moment M = mu_r R* F_n (R* = r at a wall, F_n = m g):
    (m + I/b^2) dv/dt = -M / b, and the distance is v0^2 / (2 a); I = 2/5 m r^2
    (sphere) or 1/2 m r^2 (disk). During the roll the spring moment sits on its limit.
    A stiff normal spring keeps the elastic rolling angle M / k_r (which the simple
    solution ignores) below 1e-4 of the distance."""
    mu_r, r, v0, k_n = 0.05, 0.01, 0.2, 1e7
    extra = {"rolling_stiffness": 0.5} if convention == "beta" else {}
    law = LinearSpring(k_n=k_n, mu=0.8, rolling_convention=convention, rolling_friction=mu_r,
                       **extra)
    sim = sphere_on_floor(law, r=r, dim=dim, k_n=k_n)
    arm = sim.x[0, dim - 1]
    sim.v[0, 0] = v0
    spin = 1 if dim == 3 else 2
    sim.w[0, spin] = v0 / arm if dim == 3 else -v0 / arm
    a = mu_r * r * sim.m[0] * G / arm / (sim.m[0] + sim.inertia[0] / arm**2)
    assert sim.inertia[0] == pytest.approx((0.4 if dim == 3 else 0.5) * sim.m[0] * r * r)
    t_stop = v0 / a
    sim.run(duration=0.5 * t_stop)
    m_roll = np.linalg.norm(sim.wall_state.roll[0, :3])
    f_n = sim.law.k_n * (r - sim.x[0, dim - 1])
    assert m_roll == pytest.approx(mu_r * r * f_n, rel=1e-9)
    # (the undamped tangential spring rocks about the mean motion: 4e-4 of v here)
    assert sim.v[0, 0] == pytest.approx(v0 - a * sim.time, rel=1e-3)
    peak = [0.0]
    sim.every(1, lambda s: peak.__setitem__(0, max(peak[0], s.x[0, 0])))
    sim.run(duration=0.6 * t_stop)
    # where it stops (then the spring gives back its elastic rolling angle)
    distance = v0**2 / (2 * a)
    assert peak[0] == pytest.approx(distance, rel=1e-3)
    assert abs(sim.v[0, 0]) < 2e-2 * v0
    assert sim.ledger.balance_error() < 1e-6
    # nearly all the kinetic energy went into the rolling limit, none into sliding
    assert sim.ledger.acc[A_ROLLING] == pytest.approx(sim.ledger.acc[7], rel=1e-3)
    assert abs(sim.ledger.friction) < 1e-6 * sim.ledger.acc[A_ROLLING]


def test_rocking_frequency_of_the_elastic_rolling_spring():
    """A sphere on the floor with an elastic rolling spring (convention beta, no limit)
    and a tangential spring: a two-DOF system (x, theta_y) with the slip x - a theta
    (arm a) and the rolling angle theta; K = [[k_s, -a k_s], [-a k_s, a^2 k_s + k_r]],
    M = diag(m, I). The simulated rocking period equals 2 pi / omega_1 of that system."""
    r, k_n, beta = 0.01, 1e5, 0.2
    law = LinearSpring(k_n=k_n, k_s=0.5 * k_n, mu=0.8, rolling_convention="beta",
                       rolling_stiffness=beta)
    sim = sphere_on_floor(law, r=r, steps_per_period=400.0)
    m, inertia = sim.m[0], sim.inertia[0]
    a = r - (r - sim.x[0, 2])  # the arm: centre to the floor
    k_s = 0.5 * k_n
    k_r = beta * k_s * r * r
    K = np.array([[k_s, -a * k_s], [-a * k_s, a * a * k_s + k_r]])
    Minv = np.diag([1 / m, 1 / inertia])
    w2 = np.sort(np.linalg.eigvals(Minv @ K).real)
    period = 2 * math.pi / math.sqrt(w2[0])
    # start in the slow mode's shape: theta_y > 0 rolls towards +x with x = a theta
    vec = np.linalg.eig(Minv @ K)
    slow = vec[1][:, np.argmin(vec[0].real)].real
    slow = slow / slow[1] * 1e-3  # angular velocity 1e-3
    sim.v[0, 0], sim.w[0, 1] = slow[0], slow[1]
    times, xs = [], []
    sim.every(1, lambda s: (times.append(s.time), xs.append(s.x[0, 0])))
    sim.run(duration=2.2 * period)
    # (the upward zero crossings of x)
    assert oscillation_period(times, -np.asarray(xs)) == pytest.approx(period, rel=5e-3)
    # the engine without the rolling spring: the same start is a free roll, no return
    free = sphere_on_floor(LinearSpring(k_n=k_n, k_s=0.5 * k_n, mu=0.8), r=r,
                           steps_per_period=400.0)
    free.v[0, 0], free.w[0, 1] = slow[0], slow[1]
    x_free = []
    free.every(1, lambda s: x_free.append(s.x[0, 0]))
    free.run(duration=2.2 * period)
    assert min(x_free) > 0 and x_free[-1] > 0.5 * slow[0] * free.time


def stacked_pair(law, spin, k_n=1e5, r=0.01):
    """Sphere j resting on a fixed sphere i under gravity, spinning about the vertical."""
    m = RHO * 4.0 / 3.0 * math.pi * r**3
    delta = m * G / k_n
    x = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2 * r - delta]])
    p = Particles.from_density(x, np.full(2, r), RHO, fixed=[True, False])
    dt = 2 * math.pi * math.sqrt(m / k_n) / 200.0
    sim = Simulation(p, law, gravity=[0, 0, -G], timestep=TimeStep.fixed(dt))
    sim.w[1, 2] = spin
    return sim


def test_twisting_spring_frequency_between_two_spheres():
    """Twisting about the common normal of two spheres (the lower one fixed): an
    oscillator of stiffness k_w = beta_w k_t R*^2 and inertia I_j, period
    2 pi sqrt(I / k_w); the twisting moment lies along the normal."""
    r, beta_w = 0.01, 0.5
    law = LinearSpring(k_n=1e5, mu=0.5, rolling_convention="beta", twisting_stiffness=beta_w)
    sim = stacked_pair(law, spin=1e-2, r=r)
    k_w = beta_w * 1e5 * (r / 2) ** 2
    period = 2 * math.pi * math.sqrt(sim.inertia[1] / k_w)
    times, ws = [], []
    sim.every(1, lambda s: (times.append(s.time), ws.append(s.w[1, 2])))
    sim.run(duration=2.3 * period)
    assert oscillation_period(times, ws) == pytest.approx(period, rel=2e-3)
    assert sim.pairs.roll[0, ROLL_TWIST] != 0.0
    assert np.abs(sim.pairs.roll[0, :3]).max() < 1e-12 * abs(sim.pairs.roll[0, ROLL_TWIST])
    assert sim.ledger.balance_error() < 1e-6


def test_epsd_with_hertz_takes_the_secant_normal_stiffness():
    """The epsd convention as LIGGGHTS' epsd model with Hertz contacts: k = 2.25 k_n
    mu^2 R*^2 with k_n the secant F_n / delta = 4/3 E* sqrt(R* delta), not the tangent
    2 E* sqrt(R* delta) (1.5x stiffer, as before): the twisting period of a sphere
    resting on a fixed sphere is 2 pi sqrt(I / k_w), its moment below the limit."""
    r, mu_w = 0.01, 0.3
    law = HertzMindlin(youngs_modulus=1e7, poisson_ratio=0.3, mu=0.5, rolling_convention="epsd",
                       rolling_friction=0.1, twisting_friction=mu_w)
    m = RHO * 4.0 / 3.0 * math.pi * r**3
    r_star, e_star = r / 2, 1e7 / (2 * (1 - 0.3**2))
    delta = (3 * m * G / (4 * e_star * math.sqrt(r_star))) ** (2 / 3)  # at rest: F_n = m g
    x = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2 * r - delta]])
    p = Particles.from_density(x, np.full(2, r), RHO, fixed=[True, False])
    k_tangent = 2 * e_star * math.sqrt(r_star * delta)
    sim = Simulation(p, law, gravity=[0, 0, -G],
                     timestep=TimeStep.fixed(2 * math.pi * math.sqrt(m / k_tangent) / 200))
    w0 = 1e-3
    sim.w[1, 2] = w0
    k_w = 2.25 * (4.0 / 3.0 * e_star * math.sqrt(r_star * delta)) * mu_w**2 * r_star**2
    period = 2 * math.pi * math.sqrt(sim.inertia[1] / k_w)
    assert w0 * math.sqrt(sim.inertia[1] * k_w) < 0.1 * mu_w * r_star * m * G  # elastic
    times, ws = [], []
    sim.every(1, lambda s: (times.append(s.time), ws.append(s.w[1, 2])))
    sim.run(duration=2.3 * period)
    assert oscillation_period(times, ws) == pytest.approx(period, rel=2e-3)


def test_twisting_limit_stops_a_spin_at_a_constant_rate():
    """A spin against the saturated twisting moment mu_w R* F_n decays linearly,
    I dw/dt = -mu_w R* F_n, and stops at t = I w0 / (mu_w R* F_n)."""
    r, mu_w, w0 = 0.01, 0.1, 30.0
    law = LinearSpring(k_n=1e5, mu=0.5, rolling_convention="beta", twisting_stiffness=1.0,
                       twisting_friction=mu_w)
    sim = stacked_pair(law, spin=w0, r=r)
    f_n = sim.m[1] * G
    rate = mu_w * (r / 2) * f_n / sim.inertia[1]
    sim.run(duration=0.5 * w0 / rate)
    assert sim.w[1, 2] == pytest.approx(w0 - rate * sim.time, rel=1e-3)
    sim.run(duration=0.6 * w0 / rate)
    assert abs(sim.w[1, 2]) < 2e-3 * w0
    assert sim.ledger.balance_error() < 1e-6


def test_restart_continues_bit_for_bit_with_rolling_history(tmp_path):
    """state_dict / load_state_dict carry the rolling history (pairs and walls): a run
    split by a restore equals the unbroken one bit for bit."""
    law = LinearSpring(k_n=1e5, mu=0.5, rolling_convention="epsd", rolling_friction=0.05,
                       twisting_friction=0.05, rolling_damping=0.3)

    def make():
        sim = sphere_on_floor(law)
        sim.v[0, 0] = 0.2
        sim.w[0, 2] = 3.0
        return sim

    whole = make()
    whole.run(steps=3000)
    first = make()
    first.run(steps=1200)
    state = {k: np.array(v, copy=True) for k, v in first.state_dict().items()}
    assert np.abs(state["wall_state.roll"]).max() > 0
    second = make().load_state_dict(state)
    second.run(steps=1800)
    assert np.array_equal(second.x, whole.x)
    assert np.array_equal(second.w, whole.w)
    assert np.array_equal(second.wall_state.roll, whole.wall_state.roll)
    assert np.array_equal(second.ledger.acc, whole.ledger.acc)


def test_switching_rolling_off_releases_its_stored_energy():
    """A law change without rolling resistance drops the history; its stored energy
    moves into the rolling dissipation, so the balance still closes."""
    law = LinearSpring(k_n=1e5, mu=0.5, rolling_convention="beta", rolling_stiffness=0.5)
    sim = sphere_on_floor(law)
    sim.w[0, 1] = 0.5
    sim.run(steps=40)
    stored = sim.ledger.energy[E_STRAIN_R]
    assert stored > 0
    before = sim.ledger.acc[A_ROLLING]
    sim.law = LinearSpring(k_n=1e5, mu=0.5)
    sim.run(steps=1)
    assert sim.ledger.energy[E_STRAIN_R] == 0.0
    assert len(sim.wall_state.roll) == 0
    assert sim.ledger.acc[A_ROLLING] - before == pytest.approx(stored, rel=1e-12)


def test_rolling_acts_on_pairs_that_form_after_an_empty_start_and_over_runs():
    """Spheres poured from apart (no pair in the first lists): the pairs that form get
    rolling history in that same run, and a second run reuses the lists (it once kept
    the first run's empty pair geometry and read past its end)."""
    rng = np.random.default_rng(5)
    grid = np.stack(np.meshgrid(np.arange(3), np.arange(3), np.arange(4), indexing="ij"), -1)
    x = grid.reshape(-1, 3) * 3.0 + 1.5 + rng.uniform(-0.1, 0.1, (36, 3))
    from demstep.walls import box_walls

    law = LinearSpring(k_n=2e5, k_s=1e5, mu=0.4, restitution=0.5, rolling_convention="beta",
                       rolling_stiffness=0.5)
    sim = Simulation(Particles.from_density(x, rng.uniform(0.8, 1.0, 36), 2.0), law,
                     walls=box_walls([0, 0, 0], [9.0, 9.0, 30.0]), gravity=[0, 0, -9.81],
                     timestep=TimeStep.fixed(2e-4))
    sim.prepare()
    assert len(sim.pairs.i) == 0
    sim.run(steps=6000)
    assert sim.n_contacts > 0 and len(sim.pairs.roll) == len(sim.pairs.i) > 0
    assert np.abs(sim.pairs.roll).sum() > 0  # rolling springs loaded in the first run
    sim.run(steps=500)
    assert np.isfinite(sim.x).all() and len(sim.pairs.roll) == len(sim.pairs.i)
    assert sim.ledger.energy[E_STRAIN_R] > 0


def test_switching_rolling_on_mid_run_steps_as_a_run_that_starts_with_it():
    """A pile settled without rolling resistance, then the law changed to one with it:
    the next steps equal those of a new simulation with that law loaded from the same
    state, to the bit (the pair loop's work space, with its rolling geometry, is sized
    anew after the switch; kept from before it, the rolling loop read an empty
    geometry and the run diverged)."""
    from demstep.walls import box_walls

    def pile(law):
        rng = np.random.default_rng(5)
        grid = np.stack(np.meshgrid(np.arange(3), np.arange(3), np.arange(4), indexing="ij"), -1)
        x = grid.reshape(-1, 3) * 3.0 + 1.5 + rng.uniform(-0.1, 0.1, (36, 3))
        return Simulation(Particles.from_density(x, rng.uniform(0.8, 1.0, 36), 2.0), law,
                          walls=box_walls([0, 0, 0], [9.0, 9.0, 30.0]), gravity=[0, 0, -9.81],
                          timestep=TimeStep.fixed(2e-4))

    common = dict(k_n=2e5, k_s=1e5, mu=0.4, restitution=0.5)
    rolling = LinearSpring(**common, rolling_convention="beta", rolling_stiffness=0.5)
    switched = pile(LinearSpring(**common))
    switched.run(steps=6000)
    assert switched.n_contacts > 0 and len(switched.pairs.roll) == 0
    state = {k: np.array(v, copy=True) for k, v in switched.state_dict().items()}
    switched.law = rolling
    switched.run(steps=300)
    fresh = pile(rolling)
    fresh.load_state_dict(state)
    fresh.run(steps=300)
    assert np.abs(switched.pairs.roll).sum() > 0
    assert np.array_equal(switched.x, fresh.x) and np.array_equal(switched.w, fresh.w)


@pytest.mark.parametrize("kwargs, key", [
    ({"rolling_friction": 0.1}, "rolling_friction"),
    ({"rolling_convention": "beta"}, "rolling_stiffness"),
    ({"rolling_convention": "epsd", "rolling_stiffness": 1.0}, "rolling_friction"),
    ({"rolling_convention": "stiff", "rolling_stiffness": 1.0}, "rolling_convention"),
    ({"rolling_convention": "beta", "rolling_stiffness": -1.0}, "rolling_stiffness"),
])
def test_bad_rolling_parameters_name_the_key(kwargs, key):
    with pytest.raises(InputError) as err:
        LinearSpring(k_n=1e5, **kwargs).params()
    assert str(err.value).startswith(key)


def test_case_with_a_rolling_coefficient_but_no_convention_exits_2(tmp_path):
    case = tmp_path / "case.toml"
    case.write_text("""
[particles]
generator = "lattice"
lattice = "hex"
radius = 1.0
size = [2, 2]
density = 1000.0
[contact]
law = "linear"
k_n = 1.0e5
rolling_friction = 0.1
[[stages]]
steps = 10
""")
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-m", "demstep.cli", "run", str(case), "--out", str(out)],
                         capture_output=True, text=True)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "rolling_friction" in lines[0] and "0.1" in lines[0]
    assert not out.exists()


@pytest.mark.slow
def test_angle_of_repose_rises_with_rolling_resistance():
    """The collapse test of validation/rolling_repose.py (480 disks, about 15 s each):
    without rolling resistance round disks roll apart into a low heap; the angle rises
    with mu_r (measured 6.6, 9.5, 17.6 degrees at 0, 0.1, 0.4)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "validation" / "rolling_repose.py"
    spec = importlib.util.spec_from_file_location("rolling_repose", path)
    repose = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(repose)
    angles = [repose.pile(mu_r, 480, 1, 2.0)["angle_deg"] for mu_r in (0.0, 0.1, 0.4)]
    assert angles[0] < 9.0
    assert angles[1] > angles[0] + 1.5
    assert angles[2] > angles[1] + 4.0


@pytest.mark.parametrize("name, options", [
    ("fcc", dict(rolling_convention="beta", rolling_stiffness=10.0, twisting_stiffness=10.0)),
    ("hex", dict(rolling_convention="beta", rolling_stiffness=10.0)),
    ("fcc", dict(rolling_convention="beta", rolling_stiffness=4.0, rolling_damping=0.5)),
])
def test_engine_threshold_with_rolling_springs_matches_the_exact_step(name, options):
    """The engine's own stability threshold (bisection on a pre-compressed periodic
    lattice whose contacts stay closed, elastic rolling springs without limit) lies
    within 0.5 % above the exact critical step with the rolling springs (and their
    viscous part), far below the step of the normal and tangential springs alone."""
    from demstep.experiments.stability import engine_threshold

    res = engine_threshold(name, options)
    assert res["exact"] <= res["bracket"][1]
    assert res["measured"] == pytest.approx(res["exact"], rel=5e-3)
    assert res["exact"] < 0.85 * res["exact_springs_only"]


def _settling_clumps(law, steps=4000):
    from demstep.clumps import ClumpTemplate, place, random_quaternions
    from demstep.energy import EnergyMonitor
    from demstep.walls import box_walls

    pair = ClumpTemplate("pair", np.array([[0.0, 0, 0], [0.9, 0, 0]]), np.full(2, 0.5))
    grid = np.stack(np.meshgrid(np.arange(3), np.arange(3), np.arange(2), indexing="ij"),
                    -1).reshape(-1, 3) * 2.2 + 1.2
    clumps = place([pair], np.zeros(len(grid), dtype=np.int64), grid,
                   random_quaternions(len(grid), np.random.default_rng(2)), 1000.0)
    sim = Simulation(None, law, clumps=clumps, walls=box_walls([0, 0, 0], [7.2, 7.2, 20]),
                     gravity=[0, 0, -9.81], timestep=TimeStep.from_alpha(0.05),
                     energy=EnergyMonitor(every=10))
    sim.run(steps=steps)
    return sim


def test_rolling_resistance_acts_on_clumps_and_the_ledger_closes():
    """Two-sphere clumps settling in a box with rolling and twisting resistance: the
    members' rolling moments reach the bodies (otherwise the energy they dissipate,
    more than 5 % of the work of gravity here, would open the balance), and the
    balance stays as tight as without rolling resistance."""
    plain = _settling_clumps(LinearSpring(k_n=1e5, mu=0.4, restitution=0.5))
    rolling = _settling_clumps(LinearSpring(k_n=1e5, mu=0.4, restitution=0.5,
                                            rolling_convention="epsd", rolling_friction=0.2,
                                            twisting_friction=0.1, rolling_damping=0.3))
    assert rolling.ledger.rolling > 0.05 * rolling.ledger.external
    assert rolling.monitor.max_error < 2e-3
    assert rolling.monitor.max_error < 2 * plain.monitor.max_error + 1e-4
