"""Insertion and outflow: radius distributions against their definitions, regions,
the rates kept, no overlap at insertion, the energy ledger exact across particles
coming and going (free fall: to round-off; a particle taken out of a loaded contact:
the balance unchanged), a restart bit for bit, 'auto' certifying the step of what
was inserted, and case files."""

import math
import warnings

import numpy as np
import pytest
from scipy.stats import truncnorm

from demstep.contact.laws import HertzMindlin, LinearSpring
from demstep.engine import Simulation, TimeStep
from demstep.engine.meshes import MeshWall
from demstep.engine.population import remove_particles
from demstep.errors import InputError
from demstep.engine.feed import Inserter, Outlet
from demstep.feed import (BoxRegion, CylinderRegion, FaceRegion, RadiusDistribution,
                          SphereRegion, distribution_from_spec)
from demstep.mesh.shapes import plane
from demstep.particles import Particles
from demstep.walls import Wall, box_walls

R = 0.002
DENSITY = 2500.0
LINEAR = LinearSpring(k_n=2e3, mu=0.3, restitution=0.5)


# ------------------------------------------------------------ distributions
def _sigma_bound(p, n):
    """Five standard errors of a proportion p from n draws."""
    return 5.0 * math.sqrt(p * (1 - p) / n)


def test_uniform_by_number_and_by_mass():
    rng = np.random.default_rng(0)
    n = 40000
    r = RadiusDistribution("uniform", min=1.0, max=2.0).sample(rng, n)
    assert r.min() >= 1.0 and r.max() <= 2.0
    share = np.mean(r < 1.5)  # half the draws below the middle radius
    assert abs(share - 0.5) < _sigma_bound(0.5, n)
    # by mass (3D): each radius interval holds mass in proportion to its width
    r = RadiusDistribution("uniform", min=1.0, max=2.0, by="mass").sample(rng, n)
    mass = r ** 3
    below = mass[r < 1.25].sum() / mass.sum()
    assert abs(below - 0.25) < 0.01
    assert np.mean(r < 1.25) > 0.35  # (by number the small ones dominate)


def test_discrete_fractions_by_number_and_by_mass():
    rng = np.random.default_rng(1)
    n = 40000
    d = RadiusDistribution("discrete", radii=[1.0, 2.0], fractions=[0.3, 0.7])
    r = d.sample(rng, n)
    assert set(np.unique(r)) == {1.0, 2.0}
    assert abs(np.mean(r == 1.0) - 0.3) < _sigma_bound(0.3, n)
    d = RadiusDistribution("discrete", radii=[1.0, 2.0], fractions=[0.3, 0.7], by="mass", dim=2)
    r = d.sample(rng, n)
    mass = r ** 2
    assert abs(mass[r == 1.0].sum() / mass.sum() - 0.3) < 0.01


def test_lognormal_median_shape_and_truncation():
    rng = np.random.default_rng(2)
    n = 40000
    d = RadiusDistribution("lognormal", median=1e-3, sigma=0.2)
    r = d.sample(rng, n)
    lo, hi = 1e-3 * math.exp(-0.6), 1e-3 * math.exp(0.6)
    assert r.min() >= lo * (1 - 1e-12) and r.max() <= hi * (1 + 1e-12)
    assert abs(np.mean(r < 1e-3) - 0.5) < _sigma_bound(0.5, n)
    expected_sd = truncnorm(-3, 3).std() * 0.2
    assert abs(np.std(np.log(r)) - expected_sd) < 0.02 * expected_sd
    # the mass-weighted median: half the mass in particles below it
    d = RadiusDistribution("lognormal", median=1e-3, sigma=0.2, by="mass", dim=3)
    r = np.sort(d.sample(rng, n))
    mass = r ** 3
    assert abs(mass[r < 1e-3].sum() / mass.sum() - 0.5) < 0.02


@pytest.mark.parametrize("spec, message", [
    ({"distribution": "uniform", "min": 2.0, "max": 1.0}, r"radius\.max: must be >= min"),
    ({"distribution": "discrete", "radii": [1.0, 2.0], "fractions": [1.0]},
     r"radius\.fractions: expected 2 values"),
    ({"distribution": "lognormal", "median": 1.0}, r"radius\.sigma: must be finite and > 0"),
    ({"distribution": "gamma"}, r"radius\.distribution: expected fixed"),
    ({"distribution": "uniform", "min": 1.0, "max": 2.0, "mean": 3}, r"radius\.mean: unknown key"),
    (-1.0, r"radius\.radius: must be finite and > 0"),
])
def test_bad_distributions_are_refused_naming_the_key(spec, message):
    with pytest.raises(InputError, match=message):
        distribution_from_spec(spec, 3)


# ------------------------------------------------------------------ regions
def test_regions_place_spheres_wholly_inside():
    rng = np.random.default_rng(3)
    r = rng.uniform(0.05, 0.2, 5000)
    box = BoxRegion(3, "b", [0, 0, 0], [1, 2, 3])
    x = box.sample(rng, r)
    assert np.all(x - r[:, None] >= -1e-12) and np.all(x + r[:, None] <= [1 + 1e-12, 2, 3])
    cyl = CylinderRegion(3, "c", "z", [1.0, -1.0], 0.5, 0.0, 1.0)
    x = cyl.sample(rng, r)
    rho = np.hypot(x[:, 0] - 1.0, x[:, 1] + 1.0)
    assert np.all(rho + r <= 0.5 + 1e-12)
    assert np.all((x[:, 2] - r >= -1e-12) & (x[:, 2] + r <= 1 + 1e-12))
    # uniform in the disc of radius 0.5 - r: half the points within 1/sqrt(2) of it
    share = np.mean(rho < (0.5 - r) / math.sqrt(2))
    assert abs(share - 0.5) < _sigma_bound(0.5, len(r))
    ball = SphereRegion(3, "s", [0, 0, 0], 1.0)
    x = ball.sample(rng, r)
    assert np.all(np.linalg.norm(x, axis=1) + r <= 1 + 1e-12)
    assert ball.contains(np.array([[0.5, 0, 0], [0.9, 0.9, 0]])).tolist() == [True, False]
    # too big for the region: no position
    assert np.isnan(box.sample(rng, np.array([0.6]))).all()


def test_a_face_places_spheres_off_it_along_the_velocity():
    rng = np.random.default_rng(4)
    m = plane(2, size=1.0, name="inlet")  # z = 0, normal +z
    tri = np.asarray(m.vertices)[np.asarray(m.triangles)].reshape(-1, 9)
    face = FaceRegion(3, "f", tri, "inlet")
    r = np.full(2000, 0.01)
    x = face.sample(rng, r, extrude=np.array([0.0, 0.0, -0.2]))
    # below the face (the velocity points down), by at least r and at most r + 0.2
    assert np.all(x[:, 2] <= -0.01 + 1e-12) and np.all(x[:, 2] >= -0.21 - 1e-12)
    lo, hi = np.asarray(m.vertices).min(axis=0), np.asarray(m.vertices).max(axis=0)
    assert np.all((x[:, :2] >= lo[:2] - 1e-12) & (x[:, :2] <= hi[:2] + 1e-12))


# ---------------------------------------------------------------- insertion
def _inserter(**kw):
    args = dict(region=BoxRegion(3, "r", [0, 0, 0], [0.05, 0.05, 0.05]),
                radius=RadiusDistribution("uniform", min=R, max=1.5 * R), density=DENSITY,
                rate=2000.0, every=50, seed=5)
    args.update(kw)
    return Inserter("feed", **args)


def _sim(items, walls=(), gravity=(0, 0, 0), dt=1e-5, law=LINEAR, particles=None, **kw):
    return Simulation(particles if particles is not None else Particles.empty(3), law,
                      walls=list(walls), gravity=list(gravity), timestep=TimeStep.fixed(dt),
                      feed=items, **kw)


def _min_gap(sim):
    x, r = sim.x, sim.r
    d = np.linalg.norm(x[:, None] - x[None], axis=2) - r[:, None] - r[None]
    np.fill_diagonal(d, np.inf)
    return d.min()


def test_a_count_rate_is_kept_and_nothing_overlaps():
    ins = _inserter()
    sim = _sim([ins])
    for _ in range(4):
        sim.run(steps=1000)
        # (the events at multiples of 50 steps: the count is the rate's at that time)
        assert ins.inserted == math.floor(2000.0 * sim.time + 1e-9)
        assert len(sim.r) == ins.inserted
    assert ins.inserted == 80
    assert _min_gap(sim) >= 0.0  # no gravity, no velocity: as placed
    assert np.all(sim.x - sim.r[:, None] >= 0) and np.all(sim.x + sim.r[:, None] <= 0.05)
    assert np.isclose(ins.inserted_mass, sim.m.sum())


def test_a_mass_rate_and_a_total_are_kept():
    ins = _inserter(rate=None, mass_rate=0.02, total_mass=5e-4)
    sim = _sim([ins])
    m_max = DENSITY * 4 / 3 * math.pi * (1.5 * R) ** 3
    sim.run(steps=1000)  # t = 0.01: 2e-4 kg
    assert 0.0 <= ins.inserted_mass - 0.02 * sim.time < m_max
    sim.run(steps=3000)  # the total reached
    assert 5e-4 <= ins.inserted_mass < 5e-4 + m_max
    n = ins.inserted
    sim.run(steps=500)
    assert ins.inserted == n


def test_inserted_particles_clear_walls_meshes_and_what_is_there():
    # a column of resting spheres, a plane wall cutting the region, a mesh plate in it
    x = np.array([[0.025, 0.025, z] for z in np.arange(0.026, 0.05, 0.0061)])
    there = Particles.from_density(x, np.full(len(x), 0.003), DENSITY)
    plate = plane(2, size=0.05, name="plate")
    v = np.asarray(plate.vertices, dtype=float).copy()
    v[:, 2] = 0.02
    from demstep.mesh import mesh_from_arrays
    mesh = MeshWall(mesh_from_arrays(v, np.asarray(plate.triangles), name="plate"))
    wall = Wall([0.0, 0.0, 0.0], [1.0, 1.0, 0.0] / np.sqrt(2), name="slant")
    ins = _inserter(rate=1e5, every=100)
    sim = _sim([ins], walls=[wall], meshes=[mesh], particles=there)
    sim.run(steps=100)  # (inserted at the end of the steps: nothing moved since)
    new = np.arange(len(x), len(sim.r))
    assert len(new) > 50
    assert _min_gap(sim) >= 0.0
    assert np.all((sim.x[new] @ wall.normal) >= sim.r[new])
    # clear of the plate (a rectangle at z = 0.02): the distance to it
    lo, hi = v.min(axis=0)[:2], v.max(axis=0)[:2]
    xy = sim.x[new, :2]
    out = np.maximum(0.0, np.maximum(lo - xy, xy - hi))
    dist = np.sqrt((out ** 2).sum(axis=1) + (sim.x[new, 2] - 0.02) ** 2)
    assert np.all(dist >= sim.r[new])
    assert np.any((out.sum(axis=1) == 0) & (dist < 3 * sim.r[new]))  # (near it, over it)


def test_a_full_region_delays_insertion_and_drops_nothing():
    small = BoxRegion(3, "r", [0, 0, 0], [0.012, 0.012, 0.012])
    ins = _inserter(region=small, rate=1e5, every=100, total=40,
                    radius=RadiusDistribution("discrete", radii=[R, 2 * R]))
    out = Outlet("drain", BoxRegion(3, "o", [-1, -1, -1], [1, 1, 1]), every=200)
    sim = _sim([ins, out])
    with pytest.warns(RuntimeWarning, match="found no room in the region"):
        sim.run(steps=100)
    waiting = ins.pending.copy()
    assert len(waiting) > 0 and ins.inserted + len(waiting) == 40
    assert np.any(waiting == 2 * R)  # (the large ones wait: they are not redrawn)
    # the outlet empties the region every 200 steps; what waited is placed then
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sim.run(steps=6000)  # (one large sphere fits at a time: one per emptying)
    assert ins.inserted == 40 and len(ins.pending) == 0
    assert out.removed + len(sim.r) == 40


def test_nothing_is_inserted_after_stop_and_what_waits_then_is_dropped():
    """The same full region with a stop: what waits at stop is never inserted (the
    outlet makes room afterwards, nothing comes), it is counted as dropped, and a
    checkpoint's state carries the count."""
    small = BoxRegion(3, "r", [0, 0, 0], [0.012, 0.012, 0.012])
    ins = _inserter(region=small, rate=1e5, every=100, total=40, stop=2e-3,
                    radius=RadiusDistribution("discrete", radii=[R, 2 * R]))
    out = Outlet("drain", BoxRegion(3, "o", [-1, -1, -1], [1, 1, 1]), every=200)
    sim = _sim([ins, out])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sim.run(steps=200)  # (t = 2e-3: the last insertion at stop)
    waiting = len(ins.pending)
    inserted = ins.inserted
    assert waiting > 0
    with pytest.warns(RuntimeWarning, match=r"found no room by stop = 0.002 are dropped"):
        sim.run(steps=6000)
    assert ins.inserted == inserted and len(ins.pending) == 0 and ins.dropped == waiting
    assert out.removed + len(sim.r) == inserted
    again = _inserter(region=small, rate=1e5, every=100, total=40, stop=2e-3,
                      radius=RadiusDistribution("discrete", radii=[R, 2 * R]))
    again.restore(ins.state())
    assert again.dropped == waiting


# ------------------------------------------------------------ energy ledger
def test_the_ledger_balances_exactly_as_particles_come_and_go_in_free_fall():
    ins = _inserter(region=BoxRegion(3, "r", [0, 0, 0], [1, 1, 1]), rate=1000.0, every=20,
                    velocity=[0.1, 0.0, 0.3], radius=RadiusDistribution("fixed", radius=R))
    out = Outlet("drain", BoxRegion(3, "o", [-1, -1, -1], [2, 2, -0.1]), every=30)
    sim = _sim([ins, out], gravity=(0, 0, -9.81), dt=1e-4)
    for _ in range(4):
        sim.run(steps=1000)
        led = sim.ledger
        assert abs(led.imbalance()) <= 1e-11 * led.external
    assert out.removed > 50 and led.removed > 0 and led.inserted > 0


def test_a_particle_taken_out_of_loaded_contacts_leaves_the_balance_unchanged():
    """Three spheres stacked on a plane wall under gravity, settled with damping;
    the middle one is taken out: the energy of its two contacts (normal and
    tangential springs) and its motion leave with it, and the balance is what it was."""
    law = LinearSpring(k_n=5e3, mu=0.5, restitution=0.3)
    x = np.array([[0.0, 0.0, R], [0.0, 0.0, 3 * R], [0.0, 0.0, 5 * R]])
    p = Particles.from_density(x, np.full(3, R), DENSITY)
    sim = Simulation(p, law, walls=[Wall([0, 0, 0], [0, 0, 1], name="floor")],
                     gravity=[0, 0, -9.81], timestep=TimeStep.fixed(5e-6))
    sim.run(steps=16000)
    assert sim.n_contacts == 3
    led = sim.ledger
    before = led.imbalance()
    strain = led.strain
    assert strain > 0
    removed = remove_particles(sim, np.array([False, True, False]))
    assert removed[0] == 1 and len(sim.r) == 2
    assert led.removed > 0.3 * strain  # its contacts held a good share of the springs' energy
    assert abs(led.imbalance() - before) <= 1e-9 * led.external
    # the next step evaluates the ledger without it: the balance moves by far less
    # than the energy that left (by the step's integration error: the bottom sphere,
    # unloaded, springs up; (omega dt)^2 = 1.5e-3)
    sim.run(steps=1)
    assert abs(led.imbalance() - before) <= 0.02 * led.removed
    sim.run(steps=200)  # the top sphere falls onto the bottom one: the run goes on
    assert sim.n_contacts >= 1


# ---------------------------------------------------------------- restarts
def test_a_run_with_insertion_and_an_outlet_restarts_bit_for_bit(tmp_path):
    from demstep.io.checkpoint import load_checkpoint, save_checkpoint

    def make():
        ins = _inserter(velocity=[0.0, 0.0, -0.2], rate=4000.0, every=100)
        out = Outlet("drain", BoxRegion(3, "o", [-1, -1, -1], [1, 1, 0.008]), every=70)
        return _sim([ins, out], walls=box_walls([0, 0, 0], [0.05, 0.05, 0.2]),
                    gravity=(0, 0, -9.81), dt=2e-5)

    a = make()
    a.run(steps=3000)
    save_checkpoint(a, tmp_path / "c.npz")
    a.run(steps=3000)
    b = make()
    load_checkpoint(b, tmp_path / "c.npz")
    b.run(steps=3000)
    assert a.feed.outlets[0].removed > 0
    for name in ("x", "v", "w", "r"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(a.particle_ids(), b.particle_ids())
    assert np.array_equal(a.ledger.acc, b.ledger.acc)
    assert a.feed.inserters[0].inserted == b.feed.inserters[0].inserted


# ------------------------------------------------------------------ 'auto'
@pytest.mark.parametrize("sort_every", [None, 1])
def test_auto_certifies_the_step_of_particles_inserted_lighter_than_any_there(sort_every,
                                                                               monkeypatch):
    """Large spheres rest on the floor; small ones (1/27 of their mass) are inserted
    over them. The certified step must stay below the exact critical step of the
    contacts at every check, including the first contacts of the small ones. With the
    particles sorted at every rebuild (sort_every = 1), the rebuild an insertion makes
    renumbers them before the new estimate (sorted whatever the gain)."""
    from demstep.engine.ordering import SpatialOrder

    if sort_every:
        monkeypatch.setattr(SpatialOrder, "SORT_GAIN", -math.inf)
    law = LinearSpring(k_n=2e3, restitution=0.5)
    x = np.array([[0.01 * i + 0.005, 0.005, 0.006] for i in range(4)])
    p = Particles.from_density(x, np.full(4, 0.006), DENSITY)
    ins = _inserter(region=BoxRegion(3, "r", [0, 0, 0.013], [0.04, 0.01, 0.02]),
                    radius=RadiusDistribution("fixed", radius=0.002), rate=2000.0, every=200,
                    total=12)
    sim = Simulation(p, law, walls=box_walls([0, 0, 0], [0.04, 0.01, 0.1]),
                     gravity=[0, 0, -9.81], timestep=TimeStep.auto(every=200), feed=[ins],
                     sort_every=sort_every)
    worst = []

    def check(s):
        crit = s.critical_dt("exact")
        if crit is not None:
            worst.append(s.dt / crit)

    sim.every(25, check)
    sim.run(steps=4000)
    assert ins.inserted == 12 and sim.n_contacts > 4
    # then an outlet takes the first large sphere and what rests on it: the
    # certificate named particles by index, and the step is certified anew
    sim.feed.add(Outlet("hole", BoxRegion(3, "o", [0.0, 0.0, 0.0], [0.01, 0.01, 0.03]),
                        every=1000))
    sim.run(steps=3000)
    removed = sim.feed.outlets[0].removed
    assert removed >= 1 and len(sim.r) == 16 - removed and sim.n_contacts > 2
    assert len(worst) > 200 and max(worst) < 1.0


def test_particles_taken_out_leave_the_certificate_in_place():
    """A settled pile in 'auto' mode: taking spheres out keeps the certificate (what
    remains is a principal submatrix of what it bounded) with the contacts between those
    left, renamed; no new estimate, and the step stays below the exact critical step."""
    law = LinearSpring(k_n=2e3, restitution=0.5)
    x = np.array([[0.01 * i + 0.005, 0.005, 0.006 + 0.011 * k] for k in range(2)
                  for i in range(4)])
    sim = Simulation(Particles.from_density(x, np.full(8, 0.0055), DENSITY), law,
                     walls=box_walls([0, 0, 0], [0.04, 0.01, 0.1]), gravity=[0, 0, -9.81],
                     timestep=TimeStep.auto(every=100_000))
    sim.run(steps=3000)
    cert, estimates = sim.auto.certificate, sim.auto.n_estimates
    covered = {(int(a), int(b)) for a, b in zip(cert.pair_i, cert.pair_j)}
    ids = sim.particle_ids()
    remove_particles(sim, np.isin(np.arange(8), [1, 6]))
    assert sim.auto.certificate is cert and sim.auto.n_estimates == estimates
    new_ids = list(sim.particle_ids())
    # the covered pairs among those left, under their new numbers
    left = {(new_ids.index(ids[a]), new_ids.index(ids[b])) for a, b in covered
            if ids[a] in new_ids and ids[b] in new_ids}
    assert {(int(a), int(b)) for a, b in zip(cert.pair_i, cert.pair_j)} == left
    assert len(cert.particles) == 6
    worst = []
    sim.every(20, lambda s: worst.append(s.dt / (s.critical_dt("exact") or np.inf)))
    sim.run(steps=2000)
    assert max(worst) < 1.0 and sim.n_contacts > 4


@pytest.mark.parametrize("sort_every", [None, 1])
def test_an_insertion_keeps_the_certificate_and_adds_the_new_contacts(sort_every,
                                                                      monkeypatch):
    """A settled pile in 'auto' mode; spheres inserted over it: the certificate is kept
    at each insertion (its covered pairs the same ones, under the numbers the rebuild
    gave them; its per-particle rows grown), the new particles' first contacts are
    added to it, not estimated anew at each insertion,
    and the step stays below the exact critical step throughout. With the particles
    sorted at every rebuild the certificate follows the renumbering. (Before, each
    insertion dropped the certificate and made a new estimate.)"""
    from demstep.engine.ordering import SpatialOrder

    if sort_every:
        monkeypatch.setattr(SpatialOrder, "SORT_GAIN", -math.inf)
    law = LinearSpring(k_n=2e3, restitution=0.5)
    x = np.array([[0.01 * i + 0.005, 0.005, 0.006 + 0.011 * k] for k in range(2)
                  for i in range(4)])
    ins = _inserter(region=BoxRegion(3, "r", [0, 0, 0.03], [0.04, 0.01, 0.05]),
                    radius=RadiusDistribution("fixed", radius=0.003), rate=20.0, every=200,
                    total=10, start=0.3)
    sim = Simulation(Particles.from_density(x, np.full(8, 0.0055), DENSITY), law,
                     walls=box_walls([0, 0, 0], [0.04, 0.01, 0.1]), gravity=[0, 0, -9.81],
                     timestep=TimeStep.auto(every=100_000), feed=[ins], sort_every=sort_every)
    from demstep.engine.auto_step import AutoStep

    seen = []  # (kept, the same certificate after the insertion's rebuild and check)
    after = AutoStep.after_insertion

    def spy(auto, kept):
        before = auto.certificate
        after(auto, kept)
        seen.append((kept, before is not None and auto.certificate is before))

    monkeypatch.setattr(AutoStep, "after_insertion", spy)
    sim.run(duration=0.3)  # (settled; the insertions from t = 0.3 on)
    assert ins.inserted == 0
    cert, estimates = sim.auto.certificate, sim.auto.n_estimates
    ids = sim.particle_ids()
    covered = {(int(ids[a]), int(ids[b])) for a, b in zip(cert.pair_i, cert.pair_j)}
    assert len(covered) >= 4
    worst = []
    sim.every(10, lambda s: worst.append(s.dt / (s.critical_dt("exact") or np.inf)))
    events = 0
    for _ in range(14):
        before = ins.inserted
        sim.run(duration=0.05)
        events += ins.inserted > before
        if sim.auto.certificate is cert:  # (kept: the same pairs by id, the rows grown)
            now = sim.particle_ids()
            assert {(int(now[a]), int(now[b])) for a, b in zip(cert.pair_i, cert.pair_j)} \
                == covered
            assert len(cert.particles) == len(sim.r)
    assert ins.inserted == 10 and events >= 5 and len(seen) == events
    # (measured: every insertion kept its certificate, no estimate made for it; the
    # estimates made meanwhile come from the spheres' impacts on the pile)
    assert all(kept and same for kept, same in seen)
    assert sim.auto.n_extensions > 0
    assert len(worst) > 200 and max(worst) < 1.0


# ------------------------------------------------------------------- inputs
@pytest.mark.parametrize("kw, message", [
    (dict(rate=None), "give exactly one of rate"),
    (dict(mass_rate=1.0), "give exactly one of rate"),
    (dict(rate=-1.0), r"rate: must be finite and >= 0"),
    (dict(every=0), r"every: expected a number of steps >= 1"),
    (dict(stop=-1.0), r"stop: must be finite and >= 0"),
    (dict(velocity=[1.0, 2.0]), r"velocity: expected 3 finite numbers"),
    (dict(density=0.0), r"density: must be > 0"),
])
def test_bad_inserters_are_refused_in_one_line(kw, message):
    with pytest.raises(InputError, match=message):
        _inserter(**kw)


def test_insertion_with_clumps_is_refused():
    from demstep.clumps import clumps_from_members

    x = np.array([[0.0, 0.0, 0.01], [0.003, 0.0, 0.01]])
    clumps = clumps_from_members(x, np.full(2, R), np.zeros(2, dtype=np.int64), DENSITY)
    with pytest.raises(InputError, match="not supported with clumps"):
        Simulation(None, LINEAR, clumps=clumps, feed=[_inserter()])


def test_disks_and_a_periodic_axis():
    """2D: disks inserted in a box get their mass per unit thickness and no overlap; 3D
    with x periodic: no overlap through the boundary (minimum image)."""
    ins = Inserter("disks", BoxRegion(2, "r", [0.0, 0.0], [0.03, 0.03]),
                   RadiusDistribution("fixed", radius=R, dim=2), density=DENSITY,
                   rate=2e4, every=50, seed=9)
    sim = Simulation(Particles.empty(2), LINEAR, timestep=TimeStep.fixed(1e-5), feed=[ins])
    sim.run(steps=100)
    assert len(sim.r) == 20 and np.allclose(sim.m, DENSITY * math.pi * R ** 2)
    assert np.all(sim.x[:, 2] == 0.0) and _min_gap(sim) >= 0.0
    # (the region reaches across the periodic boundary: positions are wrapped into the box)
    ins = _inserter(region=BoxRegion(3, "r", [-0.01, 0.0, 0.0], [0.03, 0.05, 0.05]), rate=2e5,
                    radius=RadiusDistribution("fixed", radius=R))
    sim = _sim([ins], periodic=[0.02, None, None])
    sim.run(steps=50)
    x = sim.x
    d = x[:, None] - x[None]
    d[..., 0] -= 0.02 * np.round(d[..., 0] / 0.02)
    gap = np.linalg.norm(d, axis=2) - 2 * R
    np.fill_diagonal(gap, np.inf)
    assert len(sim.r) == 100 and gap.min() >= 0.0
    assert np.all((x[:, 0] >= 0.0) & (x[:, 0] < 0.02))


def test_fill_to_tops_the_region_up_at_each_insertion():
    """fill_to = 30: the region holds 30 particles after each insertion, whatever an
    outlet took from it in between (here all of it, every 150 steps)."""
    region = BoxRegion(3, "r", [0, 0, 0], [0.05, 0.05, 0.05])
    ins = _inserter(region=region, rate=None, fill_to=30, every=100)
    out = Outlet("drain", BoxRegion(3, "o", [0, 0, 0], [0.05, 0.05, 0.05]), every=150)
    sim = _sim([ins, out])
    counts = []
    for _ in range(6):
        sim.run(steps=100)
        counts.append(int(region.contains(sim.x).sum()))
    assert counts == [30] * 6
    # filled at 0; drained at 150, 300, 450, 600 (the outlet first) and refilled at
    # 200, 300, 500, 600: 30 each
    assert out.removed == 120 and ins.inserted == 150
    with pytest.raises(InputError, match="give exactly one of rate"):
        _inserter(fill_to=5)  # (with the default rate)
