"""The certified 'auto' step with triangle-mesh walls: mesh contacts in the estimate as
wall elements, contacts beyond the cover found before they act, the drift of their
normals bounded (checked against dense matrices), the added group's bound, restarts."""

import numpy as np
import pytest

from demstep.contact.laws import HertzMindlin, LinearSpring
from demstep.engine import Simulation, TimeStep
from demstep.engine.meshes import MeshWall
from demstep.kernels.meshes import _matched_drift
from demstep.mesh import mesh_from_arrays
from demstep.mesh.shapes import cylinder, plane
from demstep.particles import Particles
from demstep.timestep.certificate import mesh_added_bound

DENSITY = 2500.0


def poured_can(law, material, n_side=4, seed=1):
    """Spheres (radius 0.016-0.02) thrown into a closed can of 16 facets (radius 0.2,
    height 0.4, normals inward) of its own ``material``, under gravity, 'auto' step."""
    rng = np.random.default_rng(seed)
    g = np.linspace(-0.1, 0.1, n_side)
    xx, yy, zz = np.meshgrid(g, g, np.arange(0.03, 0.3, 0.05), indexing="ij")
    x = np.stack([xx.ravel(), yy.ravel(), zz.ravel()], 1)
    r = 0.02 * rng.uniform(0.8, 1.0, len(x))
    can = cylinder(16, radius=0.2, height=0.4, caps=True).flipped()
    return Simulation(Particles.from_density(x, r, DENSITY), law,
                      meshes=[MeshWall(can, name="can", material=material)],
                      gravity=[0, 0, -9.81], velocities=rng.normal(0, 0.3, (len(x), 3)),
                      timestep=TimeStep.auto())


def test_the_auto_step_in_a_stiff_mesh_can_stays_below_the_critical_step():
    """A linear law with a mesh 10 times stiffer than the pairs (its contacts decide the
    critical step): at every sample the step is below the exact critical step of the
    contacts closed then (pairs and mesh), and close to safety x it once settled.
    Leaving the mesh contacts out of the estimate puts the step above it."""
    sim = poured_can(LinearSpring(k_n=2e5, restitution=0.5, mu=0.4), {"k_n": 2e6})
    ratios = []
    for _ in range(8):
        sim.run(steps=1500)
        crit = sim.critical_dt("exact")
        ratios.append(sim.dt / crit)
    assert sim.meshes.contacts.sum() > 20
    assert max(ratios) <= 1.0
    # settled: safety (0.8) x the exact step of every contact that can close within the
    # horizon (those within the skin of a particle that accelerates: gravity on the
    # rattlers), within the growth cap and the drift since the estimate
    within = sim.critical_dt("exact", horizon=sim.auto.horizon)
    assert 0.75 * within <= sim.dt <= 0.8 * within
    # the mesh contacts decide: the pairs alone would allow a larger step
    pairs_only = Simulation(Particles.from_density(sim.x, sim.r, DENSITY), sim.law,
                            timestep=TimeStep.fixed(1e-9))
    pairs_only.run(steps=1)
    assert pairs_only.critical_dt("exact") > 1.5 * sim.critical_dt("exact")


def _patch(centre, name):
    """A flat square of side 0.2 at z = 0 centred on ``centre`` (x, y): 32 triangles."""
    m = plane(4, size=0.2)
    v = np.asarray(m.vertices, dtype=float).copy()
    v[:, :2] += np.asarray(centre) - v[:, :2].mean(axis=0)
    return mesh_from_arrays(v, np.asarray(m.triangles), name=name)


def _resting_pair_and_a_ball(material, speed=0.3):
    """Two spheres resting on a soft mesh patch (the estimates' certificate) and a third
    thrown down from 3 radii above another patch of ``material``, under gravity: the
    estimates, one every 10^6 steps, are made with it in flight; it lands and stays
    (restitution 0.3)."""
    r = 0.01
    x = np.array([[0.3, 0.3, r], [0.3, 0.3 + 2 * r, r], [0.0, 0.0, 4 * r]])
    meshes = [MeshWall(_patch((0.3, 0.3), "soft"), material={"k_n": 3e3}),
              MeshWall(_patch((0.0, 0.0), "target"), material=material)]
    return Simulation(Particles.from_density(x, np.full(3, r), DENSITY),
                      LinearSpring(k_n=1e4, restitution=0.3, mu=0.5), meshes=meshes,
                      gravity=[0, 0, -9.81],
                      velocities=[[0, 0, 0], [0, 0, 0], [0.01, 0.003, -speed]],
                      timestep=TimeStep.auto(every=1_000_000))


@pytest.mark.parametrize("k_mesh, extended", [(1e3, True), (3e5, False)])
def test_a_ball_reaching_a_mesh_is_covered_before_its_contact_acts(k_mesh, extended):
    """The estimate is made with the ball in flight. As it lands, its contact is found
    before it acts: added to the certificate (a mesh softer than the pairs) or, when
    that does not fit (30 times stiffer than the pairs), a new estimate lowers the step; at every
    step of the contact the step is below the exact critical step."""
    sim = _resting_pair_and_a_ball({"k_n": k_mesh})
    sim.run(steps=1)
    first = sim.auto.n_estimates
    touched = 0
    for _ in range(3000):
        sim.run(steps=1)
        on = np.flatnonzero(sim.meshes.active)
        if 2 in sim.meshes.cand_p[on]:  # (the ball's contact acted in this step)
            touched += 1
            assert sim.dt <= sim.critical_dt("exact")
            if touched == 60:
                break
    assert touched == 60
    added = sim.auto.mesh_added
    if extended:
        assert sim.auto.n_estimates == first and added is not None and added[2, 0] == 1
    else:
        assert sim.auto.n_estimates > first and added[2, 0] == 0


def _element(n, arm, k_n, k_t, inv_m, inv_i):
    """The mass-scaled 6 x 6 matrix of a particle-wall element (normal n, arm a): the
    relative motion at the contact L x = u / sqrt(m) + a (w x n) / sqrt(I), its normal
    part on k_n, its tangential part on k_t."""
    n = np.asarray(n, dtype=float) / np.linalg.norm(n)
    cross = np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])
    L = np.hstack([np.sqrt(inv_m) * np.eye(3), -arm * np.sqrt(inv_i) * cross])
    B = k_n * np.outer(n, n) + k_t * (np.eye(3) - np.outer(n, n))
    return L.T @ B @ L


def test_the_mesh_drift_bounds_the_change_of_the_element():
    """The drift a step measures for a mesh contact that turned from its reference
    normal and changed its arm bounds the 2-norm of the change of its element matrix
    (dense), for springs and dashpots, and is zero when nothing moved."""
    rng = np.random.default_rng(3)
    m, radius = 0.02, 0.01
    inv_m, inv_i = 1 / m, 1 / (0.4 * m * radius**2)
    for _ in range(300):
        n_ref = rng.normal(size=3)
        n_ref /= np.linalg.norm(n_ref)
        n_now = n_ref + rng.uniform(0, 0.5) * rng.normal(size=3)
        n_now /= np.linalg.norm(n_now)
        a_ref, a_now = radius * rng.uniform(0.95, 1.0, 2)
        k_n, k_t, c_n, c_t = rng.uniform(0.1, 1.0, 4) * [1e5, 1e5, 10, 10]
        ref = np.array([[*n_ref, a_ref, k_n, k_t, c_n, c_t, np.inf, inv_m, inv_i]])
        g = np.zeros((1, 9))
        g[0, 1:4] = -n_now  # (the kernels' normal points from the triangle to the centre)
        g[0, 4] = a_now
        for w_k, w_c, b_n, b_t in ((1.0, 0.0, k_n, k_t), (0.0, 1.0, c_n, c_t)):
            change = (_element(n_now, a_now, b_n, b_t, inv_m, inv_i)
                      - _element(n_ref, a_ref, b_n, b_t, inv_m, inv_i))
            bound = _matched_drift(g, 0, ref, 0, w_k, w_c)
            assert np.abs(np.linalg.eigvalsh(change)).max() <= bound * (1 + 1e-12)
        g[0, 1:4], g[0, 4] = -n_ref, a_ref
        assert _matched_drift(g, 0, ref, 0, 1.0, 0.0) == 0.0


def test_the_added_mesh_group_bound_is_the_largest_eigenvalue_for_one_contact():
    """One contact: the bound is the element's largest eigenvalue (dense) at any normal;
    several on one particle: at least the largest eigenvalue of their sum."""
    rng = np.random.default_rng(4)
    m, radius = 0.02, 0.01
    inv_m, inv_i = 1 / m, 1 / (0.4 * m * radius**2)
    for k_n, k_t in ((1e5, 1e5), (1e5, 2e4), (1e5, 1e3)):
        bound = mesh_added_bound([1], [k_n], [k_t], [0.0], [0.0], [radius], [inv_m], [inv_i])[0]
        n = rng.normal(size=3)
        top = np.linalg.eigvalsh(_element(n, radius, k_n, k_t, inv_m, inv_i)).max()
        assert bound == pytest.approx(top, rel=1e-12)
        total = sum(_element(rng.normal(size=3), radius * rng.uniform(0.9, 1), k_n, k_t,
                             inv_m, inv_i) for _ in range(3))
        three = mesh_added_bound([3], [k_n], [k_t], [0.0], [0.0], [radius], [inv_m], [inv_i])
        assert np.linalg.eigvalsh(total).max() <= three[0]
    # a fixed particle adds nothing
    assert mesh_added_bound([2], [1e5], [1e5], [1.0], [1.0], [radius], [0.0], [0.0]) == (0, 0)


def test_an_auto_run_in_a_hertz_mesh_can_restarts_bit_for_bit(tmp_path):
    from demstep.io.checkpoint import load_checkpoint, save_checkpoint

    def make():
        return poured_can(HertzMindlin(youngs_modulus=5e7, poisson_ratio=0.3, mu=0.4,
                                       restitution=0.5),
                          {"youngs_modulus": 2e11, "poisson_ratio": 0.3}, n_side=3)

    a = make()
    a.run(steps=1500)
    save_checkpoint(a, tmp_path / "c.npz")
    a.run(steps=1500)
    b = make()
    load_checkpoint(b, tmp_path / "c.npz")
    b.run(steps=1500)
    for name in ("x", "v", "w"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.dt == b.dt and a.auto.n_estimates > 0
    assert np.array_equal(a.meshes.cover_ctl, b.meshes.cover_ctl)


def test_auto_mode_with_clumps_and_meshes_is_refused_in_one_line():
    from demstep.clumps import ClumpTemplate, place, random_quaternions
    from demstep.errors import InputError

    pair = ClumpTemplate("pair", np.array([[0, 0, 0], [0.015, 0, 0]]), np.array([0.01, 0.01]))
    clumps = place([pair], [0], [[0.0, 0.0, 0.05]],
                   random_quaternions(1, np.random.default_rng(1)), DENSITY)
    sim = Simulation(None, LinearSpring(k_n=1e4), clumps=clumps,
                     meshes=[MeshWall(plane(2, size=1.0))], timestep=TimeStep.auto())
    with pytest.raises(InputError, match="clumps with mesh walls are not covered"):
        sim.run(steps=1)
