"""Contact laws as modules found by a registry, and the cohesive law that shows it: a
linear spring with a constant attraction, F_n = K_n delta - f_c while touching.

The cohesive law is one module (``demstep.contact.laws.cohesive``); the engine compiles
its step, the case schema and ``demstep dt`` take it from the registry. Its stored
energy is negative for small overlaps, which the energy ledger's running scale handles
(:mod:`demstep.energy`)."""

import math

import numpy as np
import pytest
from conftest import cli

from demstep.contact import laws
from demstep.contact.laws import (LAWS, CohesiveLinear, LinearSpring, coulomb_load,
                                  normal_force, tangential_stiffness)
from demstep.engine import Simulation, TimeStep
from demstep.energy import EnergyMonitor
from demstep.particles import Particles

K, F_C, M = 1.0e5, 10.0, 1.0


def touching_pair(law, gap=0.0, speed=0.0):
    """Two unit spheres of mass 1 (radius 1) along x, ``gap`` apart, approaching each
    other at ``speed`` each."""
    x = np.array([[0.0, 0.0, 0.0], [2.0 + gap, 0.0, 0.0]])
    p = Particles(x, np.ones(2), np.full(2, M), np.full(2, 0.4 * M))
    v = np.array([[speed, 0.0, 0.0], [-speed, 0.0, 0.0]])
    return Simulation(p, law, velocities=v, timestep=TimeStep.fixed(0.02 * math.sqrt(0.5 * M / K)),
                      energy=EnergyMonitor(eps=1e-2, every=10))


def test_every_module_of_the_package_is_a_registered_law():
    import pkgutil

    modules = {m.name for m in pkgutil.iter_modules(laws.__path__)} - {"base"}
    assert {cls.__module__.rsplit(".", 1)[1] for cls in LAWS.values()} == modules
    assert {"linear", "hertz", "cohesive"} <= set(LAWS)
    # each law's parameter tuple is a type of its own: numba compiles a step per law
    assert len({cls.Params for cls in LAWS.values()}) == len(LAWS)
    with pytest.raises(AttributeError):
        laws.NoSuchLaw  # noqa: B018


def test_the_cohesive_formulas_by_hand():
    p = CohesiveLinear(k_n=K, k_s=0.5 * K, cohesion=F_C, mu=0.3).params()
    delta = 1e-4
    f, k, e = normal_force(p, delta, 0.5)
    assert f == pytest.approx(K * delta - F_C) and k == K
    assert e == pytest.approx(0.5 * K * delta**2 - F_C * delta)
    assert tangential_stiffness(p, delta, 0.5) == 0.5 * K
    # the Coulomb limit scales with the repulsive part K delta, never negative
    assert coulomb_load(p, f) == pytest.approx(K * delta)
    assert coulomb_load(p, -2 * F_C) == 0.0
    # the linear law: the elastic force itself, the same formulas without f_c
    q = LinearSpring(k_n=K, k_s=0.5 * K).params()
    assert normal_force(q, delta, 0.5) == (K * delta, K, 0.5 * K * delta * delta)
    assert coulomb_load(q, 3.0) == 3.0


def test_a_cohesive_pair_oscillates_about_the_attraction_with_its_energy_balanced():
    """Two spheres at rest overlapping by d0 = f_c / (10 K): the attraction pulls them
    in; without damping they oscillate about d = f_c / K between d0 and 2 f_c / K - d0,
    the stored energy K d^2/2 - f_c d down to -f_c^2 / (2 K) in the middle (it is
    negative throughout). The ledger balances with the negative stored energy (its
    scale the largest magnitude, f_c^2 / (2 K)), and nothing is called diverged."""
    d0 = 0.1 * F_C / K
    sim = touching_pair(CohesiveLinear(k_n=K, cohesion=F_C), gap=-d0)
    omega = math.sqrt(K / (0.5 * M))  # the relative motion: reduced mass M/2
    period = 2 * math.pi / omega
    sim.prepare()
    deepest, lowest_strain = 0.0, 0.0
    for _ in range(200):
        sim.run(steps=max(1, int(period / sim.dt / 40)))
        overlap = 2.0 - (sim.x[1, 0] - sim.x[0, 0])
        deepest = max(deepest, overlap)
        lowest_strain = min(lowest_strain, sim.ledger.strain)
    assert deepest == pytest.approx(2 * F_C / K - d0, rel=2e-3)
    assert lowest_strain == pytest.approx(-F_C**2 / (2 * K), rel=2e-3)
    assert sim.ledger.scale() == pytest.approx(F_C**2 / (2 * K), rel=2e-3)
    assert sim.monitor.max_error < (omega * sim.dt) ** 2
    assert sim.monitor.first_alarm is None
    # still touching: the attraction holds them
    assert sim.counters[0] == 1


def test_cohesion_captures_a_slow_particle_that_a_linear_spring_bounces_off():
    """A slow particle meets another with a dashpot of restitution 0.5: with cohesion
    the pair oscillates about the overlap f_c / K, each swing smaller, and never comes
    back to the surface (captured; without dissipation it would leave with the energy it
    came with: the attraction acts only while touching); the linear spring sends it back
    at half its speed. Both ledgers account for the dashpot's loss."""
    speed = 0.1 * F_C / math.sqrt(K * M)  # kinetic energy far below what cohesion holds
    sticky = touching_pair(CohesiveLinear(k_n=K, cohesion=F_C, restitution=0.5), gap=1e-5,
                           speed=speed)
    plain = touching_pair(LinearSpring(k_n=K, restitution=0.5), gap=1e-5, speed=speed)
    for sim in (sticky, plain):
        sim.run(steps=20000)
    assert sticky.counters[0] == 1 and plain.counters[0] == 0
    assert plain.v[1, 0] == pytest.approx(0.5 * speed, rel=2e-2)
    assert abs(sticky.v[1, 0]) < 1e-3 * speed  # at rest in the well
    overlap = 2.0 - (sticky.x[1, 0] - sticky.x[0, 0])
    assert overlap == pytest.approx(F_C / K, rel=1e-3)
    for sim in (sticky, plain):
        assert sim.ledger.damping > 0 and sim.monitor.max_error < 1e-3


def test_friction_of_a_cohesive_contact_holds_while_the_attraction_wins():
    """A tangential push on a cohesive pair at an overlap where F_n = K d - f_c < 0: the
    Coulomb limit is mu K d (the repulsive part), so the spring holds a force of that
    size and does not turn against the push (a limit mu F_n < 0 would flip it)."""
    law = CohesiveLinear(k_n=K, cohesion=F_C, mu=0.5)
    sim = touching_pair(law, gap=-0.1 * F_C / K)
    sim.run(steps=50)
    # a slow tangential motion of the second sphere
    sim.v[1, 1] = 1e-3
    sim.run(steps=200)
    overlap = 2.0 - np.linalg.norm(sim.x[1] - sim.x[0])
    shear = np.linalg.norm(sim.ft[0])
    assert overlap > 0
    assert shear <= 0.5 * K * overlap * (1 + 1e-9) + 1e-12
    assert sim.ft[0, 1] < 0  # on j, against its motion


def exact_dt(out: str) -> float:
    import json

    return next(e["dt"] for e in json.loads(out)["estimates"] if e["method"] == "exact")


def cohesive_case(tmp_path, extra=""):
    np.savetxt(tmp_path / "pair.csv", [[0, 0, 0, 1.0], [2.0, 0, 0, 1.0]], delimiter=",",
               header="x,y,z,r", comments="")
    path = tmp_path / "case.toml"
    path.write_text(f"""
name = "cohesive pair"
[particles]
generator = "file"
path = "pair.csv"
density = 0.2387324146
[contact]
law = "cohesive"
k_n = {K}
cohesion = {F_C}
{extra}
[timestep]
mode = "fixed"
dt = 1e-4
[[stages]]
name = "hold"
steps = 2000
[output]
history_every = 100
""")
    return path


def test_the_cohesive_law_runs_from_a_case_file_and_in_dt(tmp_path, capsys):
    import json

    from demstep.case import build_simulation, load_case

    case = cohesive_case(tmp_path)
    sim = build_simulation(load_case(case))
    assert isinstance(sim.law, CohesiveLinear) and sim.law.cohesion == F_C
    code, _, err = cli(["run", case, "--out", tmp_path / "out", "--quiet"], capsys)
    assert code == 0, err
    info = json.loads((tmp_path / "out" / "run.json").read_text())
    assert info["status"] == "completed" and info["max_energy_error"] < 1e-2
    # demstep dt on the case: the cohesive law's stiffness is its spring's
    code, out, err = cli(["dt", case, "--methods", "exact", "--json"], capsys)
    assert code == 0, err
    exact_case = exact_dt(out)
    csv = tmp_path / "pair.csv"
    code, out, err = cli(["dt", csv, "--model", "cohesive", "--kn", K, "--cohesion", F_C,
                          "--density", 0.2387324146, "--contact-tol", 1e-3, "--methods",
                          "exact", "--json"], capsys)
    assert code == 0, err
    exact_cohesive = exact_dt(out)
    code, out, err = cli(["dt", csv, "--model", "linear", "--kn", K, "--density",
                          0.2387324146, "--contact-tol", 1e-3, "--methods", "exact", "--json"],
                         capsys)
    assert code == 0, err
    exact_linear = exact_dt(out)
    assert exact_cohesive == exact_linear
    assert exact_case == pytest.approx(exact_linear, rel=1e-9)
    # an option of another law is refused in one line, naming it
    code, _, err = cli(["dt", csv, "--model", "cohesive", "--youngs", 1e9, "--density", 1.0],
                       capsys)
    assert code == 2 and "--youngs" in err and err.count("\n") == 1


@pytest.mark.parametrize("key,value,words", [("cohesion", "-1.0", ("cohesion", "-1")),
                                             ("youngs_modulus", "1e9", ("youngs_modulus",))])
def test_a_bad_cohesive_case_key_is_one_line(tmp_path, capsys, key, value, words):
    case = cohesive_case(tmp_path)
    text = case.read_text()
    line = f"cohesion = {F_C}"
    case.write_text(text.replace(line, f"{key} = {value}" if key == "cohesion"
                                 else f"{line}\n{key} = {value}"))
    code, _, err = cli(["run", case, "--out", tmp_path / "out", "--quiet"], capsys)
    assert code == 2 and err.count("\n") == 1, err
    for word in words:
        assert word in err
    assert not (tmp_path / "out").exists()
