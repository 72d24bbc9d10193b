"""Clumps: mass properties, rigid-body dynamics against analytic solutions, the
critical step of clump assemblies against dense references, restarts, bad input."""

import math
from dataclasses import replace

import numpy as np
import pytest
import scipy.linalg
import scipy.spatial.transform

from demstep.clumps import (ClumpTemplate, _integrate_union, _separate, mass_properties, place,
                            principal_frame, quat_to_matrix, random_quaternions)
from demstep.contact.laws import LinearSpring
from demstep.timestep.contacts import ContactSet, find_contacts
from demstep.engine import Damping, Simulation, TimeStep
from demstep.engine.analysis import global_damping
from demstep.errors import InputError
from demstep.particles import Particles
from demstep.timestep.assembly import assemble_stiffness
from demstep.timestep.clumps import RigidBodies, body_element_dt
from demstep.timestep.damping import GlobalDamping
from demstep.timestep.guarantee import CLAIM_SLACK
from demstep.timestep.exact import exact_critical_step
from demstep.walls import Wall

ASYM = ClumpTemplate("asym", np.array([[0, 0, 0], [1.6, 0, 0], [0, 1.2, 0], [0, 0, 0.8]]),
                     np.array([1.0, 0.8, 0.7, 0.6]))


# -------------------------------------------------------------- mass properties
def test_separate_members_exact_and_numerical_agree():
    c = np.array([[0, 0, 0], [3.0, 0.5, -1], [0.2, 2.5, 0.7]])
    r = np.array([1.0, 1.2, 0.8])
    exact = mass_properties(c, r, 2.0)
    assert exact.exact
    numeric = _integrate_union(c, r, 2.0, 1024)
    assert numeric.mass == pytest.approx(exact.mass, rel=1e-4)
    assert numeric.com == pytest.approx(exact.com, abs=1e-4)
    assert np.abs(numeric.inertia - exact.inertia).max() < 1e-4 * np.abs(exact.inertia).max()


def test_overlapping_members_converge_to_the_lens_volume():
    """Two unit spheres at distance d: union = two spheres minus the lens
    pi (4r + d)(2r - d)^2 / 12; its inertia about the axis by a fine reference."""
    for d in (0.5, 1.0, 1.7):
        props = mass_properties(np.array([[0, 0, 0], [d, 0, 0]]), np.ones(2), 1.0)
        volume = 2 * 4 / 3 * math.pi - math.pi * (4 + d) * (2 - d) ** 2 / 12
        assert not props.exact
        assert props.mass == pytest.approx(volume, rel=1e-4)
        assert props.com[0] == pytest.approx(d / 2, abs=1e-6)
        fine = _integrate_union(np.array([[0, 0, 0], [d, 0, 0]]), np.ones(2), 1.0, 2048)
        assert np.abs(props.inertia - fine.inertia).max() < 5e-3 * np.abs(fine.inertia).max()


def test_principal_frame_diagonalises_the_inertia():
    rel, moments, mass, axes, com, props = principal_frame(ASYM, 2.0)
    # members' offsets in the principal frame rebuild the tensor as a diagonal one
    back = axes @ np.diag(moments) @ axes.T
    assert back == pytest.approx(props.inertia, rel=1e-12, abs=1e-12 * moments.max())
    assert np.linalg.det(axes) == pytest.approx(1.0)
    # the offsets, turned back into the template frame about the centre of mass, are
    # the members' centres
    assert rel @ axes.T + com == pytest.approx(ASYM.centers, abs=1e-12)
    assert moments[0] < moments[1] < moments[2]


# --------------------------------------------------------------------- dynamics
def free_clump(omega, dt, steps):
    cs = place([ASYM], [0], [[0, 0, 0]], random_quaternions(1, np.random.default_rng(1)), 1.0)
    sim = Simulation(None, LinearSpring(k_n=1e3), clumps=cs, clump_angular_velocities=[omega],
                     timestep=TimeStep.fixed(dt))
    L0 = sim.bodies.L.copy()
    sim.run(steps=1)
    e0 = sim.ledger.kinetic
    sim.run(steps=steps)
    return sim, L0, e0


def test_torque_free_rotation_conserves_L_and_energy_to_second_order():
    """The largest kinetic-energy error over the same 20 time units (sampled at the same
    times) falls by 4 when dt halves; L stays exactly constant."""
    errors = []
    for dt, every in ((4e-3, 2), (2e-3, 4), (1e-3, 8)):
        sim, L0, e0 = free_clump([0.3, 1.5, 0.4], dt, 1)
        energies = []
        sim.every(every, lambda s: energies.append(s.ledger.kinetic))
        sim.run(steps=int(round(20.0 / dt)))
        assert np.abs(sim.bodies.L - L0).max() <= 1e-12 * np.abs(L0).max()
        errors.append(max(abs(e / e0 - 1) for e in energies))
    assert errors[0] / errors[1] == pytest.approx(4.0, rel=0.02)
    assert errors[1] / errors[2] == pytest.approx(4.0, rel=0.02)


def test_clump_free_fall_stays_exact_across_changes_of_step():
    """A spinning clump in free fall: its centre follows the parabola exactly and its
    angular momentum stays constant through changes of step (the kick by the mean of
    the two steps), and the ledger balances after a change to the rotation's O(dt^2)."""
    cs = place([ASYM], [0], [[0, 0, 0]], random_quaternions(1, np.random.default_rng(1)), 1.0)
    g = np.array([0.0, 0.0, -9.81])
    sim = Simulation(None, LinearSpring(k_n=1e3), clumps=cs, gravity=g,
                     clump_angular_velocities=[[0.3, 1.5, 0.4]], timestep=TimeStep.fixed(1e-3))
    x0 = sim.bodies.x[0].copy()
    L0 = sim.bodies.L.copy()
    for dt, steps in ((1e-3, 100), (4e-4, 1), (4e-4, 200), (1.5e-3, 1), (1.5e-3, 50)):
        sim.timestep = TimeStep.fixed(dt)
        sim.run(steps=steps)
        t = sim.time
        assert np.abs(sim.bodies.x[0] - (x0 + 0.5 * g * t * t)).max() < 1e-12, (dt, steps)
        assert np.abs(sim.bodies.L - L0).max() <= 1e-12 * np.abs(L0).max()
        assert sim.ledger.balance_error() < 1e-5, (dt, steps)


def test_viscous_damping_decays_a_free_clump_geometrically():
    """Global viscous damping a1 on a free clump (force -a1 m v, torque -a1 L on the
    lagged half-step values): its velocity and angular momentum fall by (1 - a1 dt)
    per step, exactly (to rounding)."""
    a1, dt, steps = 2.0, 1e-3, 300
    cs = place([ASYM], [0], [[0, 0, 0]], random_quaternions(1, np.random.default_rng(3)), 1.0)
    sim = Simulation(None, LinearSpring(k_n=1e3), clumps=cs, damping=Damping(viscous=a1),
                     clump_velocities=[[0.4, -0.1, 0.2]],
                     clump_angular_velocities=[[0.3, 1.5, 0.4]], timestep=TimeStep.fixed(dt))
    v0, L0 = sim.bodies.v[0].copy(), sim.bodies.L[0].copy()
    sim.run(steps=steps)
    decay = (1 - a1 * dt) ** steps
    assert sim.bodies.v[0] == pytest.approx(v0 * decay, rel=1e-12)
    assert sim.bodies.L[0] == pytest.approx(L0 * decay, rel=1e-12)


def test_intermediate_axis_flips():
    """Spin about the intermediate principal axis with a small perturbation: the
    body-frame angular momentum along it reverses (the tennis-racket effect), while the
    spin about the largest axis is stable."""
    cs = place([ASYM], [0], [[0, 0, 0]], np.array([[1.0, 0, 0, 0]]), 1.0)
    moments = cs.frames[0][1]

    def body_L(sim):
        R = quat_to_matrix(sim.bodies.q[0])
        return R.T @ sim.bodies.L[0]

    for axis, flips in ((1, True), (2, False)):
        omega_body = np.full(3, 1e-3)
        omega_body[axis] = 1.0
        R0 = quat_to_matrix(cs.q[0])
        sim = Simulation(None, LinearSpring(k_n=1e3), clumps=cs, timestep=TimeStep.fixed(2e-3),
                         clump_angular_velocities=[R0 @ omega_body])
        start = body_L(sim)[axis]
        signs = []
        sim.every(50, lambda s: signs.append(np.sign(body_L(s)[axis])))
        sim.run(steps=30000)
        assert (min(signs) < 0) == flips, (axis, start)


def test_clump_comes_to_rest_on_a_floor():
    cs = place([ASYM], [0], [[0, 0, 3.0]], random_quaternions(1, np.random.default_rng(5)), 1.0)
    sim = Simulation(None, LinearSpring(k_n=1e5, mu=0.5, restitution=0.3, restitution_tangential=0.3),
                     walls=[Wall(np.zeros(3), np.array([0, 0, 1.0]), name="floor")],
                     gravity=[0, 0, -9.81], clumps=cs, damping=Damping(local=0.3),
                     timestep=TimeStep.auto(safety=0.8, method="exact", every=100))
    sim.run(duration=8.0)
    weight = sim.bodies.m[0] * 9.81
    assert np.linalg.norm(sim.bodies.v[0]) < 1e-3
    assert -sim.wall_force[0, 2] == pytest.approx(weight, rel=1e-3)
    assert sim.contact_set().n >= 3  # a stable rest on at least three members


def test_dimer_rolls_down_an_incline_at_the_analytic_acceleration():
    """Two equal touching spheres (axis horizontal) roll without slipping:
    a = g sin(theta) / (1 + I / (m r_c^2)), I = 0.4 m r^2 about the axis, r_c the
    distance from the axis to the contact point (r minus the overlap)."""
    r = 0.5
    dimer = ClumpTemplate("dimer", np.array([[0, -r, 0], [0, r, 0]]), np.array([r, r]))
    theta = math.radians(20)
    n = np.array([-math.sin(theta), 0, math.cos(theta)])
    cs = place([dimer], [0], [n * r * 0.999], np.array([[1.0, 0, 0, 0]]), 1000.0)
    sim = Simulation(None, LinearSpring(k_n=1e6, k_s=1e6, mu=0.9, restitution=0.3,
                                        restitution_tangential=0.3),
                     walls=[Wall(np.zeros(3), n, name="incline")], gravity=[0, 0, -9.81],
                     clumps=cs, timestep=TimeStep.from_alpha(0.05))
    sim.run(duration=0.2)
    v0, t0 = sim.bodies.v[0].copy(), sim.time
    sim.run(duration=0.5)
    a = (sim.bodies.v[0] - v0) / (sim.time - t0)
    downhill = -np.array([math.cos(theta), 0, math.sin(theta)])
    r_c = float(np.dot(sim.bodies.x[0], n))  # the centre's height above the plane
    m = sim.bodies.m[0]
    theory = 9.81 * math.sin(theta) / (1 + 0.4 * m * r * r / (m * r_c * r_c))
    assert a @ downhill == pytest.approx(theory, rel=2e-3)
    assert abs(a @ np.array([0, 1.0, 0])) < 1e-6 * theory


@pytest.mark.parametrize("auto", [False, True])
def test_clump_restart_is_bit_identical(tmp_path, auto):
    """A clump run (the clumps spinning about z as they land) restarted from a
    checkpoint continues bit for bit; with the 'auto' time step the certificate (with
    its clumps' rows) comes back with it, so the restarted run estimates when the
    uninterrupted one does (and not at its start), forced estimates between the
    scheduled ones included. The checkpoint is taken with both drift budgets of the
    last check partly spent (the bodies turned part of the way it allows): the turn
    budget is not saved, so the restarted run checks the drift at its first step, where
    the uninterrupted one does not, and still takes the same steps and estimates. A
    checkpoint whose certificate rows are corrupted is refused naming the array."""
    from demstep.io.checkpoint import load_checkpoint, save_checkpoint
    from demstep.kernels import dem

    def build():
        rng = np.random.default_rng(2)
        pos = np.stack(np.meshgrid(np.arange(3), np.arange(3), [0], indexing="ij"), -1).reshape(-1, 3) * 4.5
        cs = place([ASYM], [0] * len(pos), pos + [0, 0, 2.0], random_quaternions(len(pos), rng), 1.0)
        spin = np.zeros((len(pos), 3))
        spin[:, 2] = rng.uniform(1.0, 3.0, len(pos))
        return Simulation(None, LinearSpring(k_n=1e4, mu=0.4, restitution=0.5),
                          walls=[Wall(np.zeros(3), np.array([0, 0, 1.0]), name="floor")],
                          gravity=[0, 0, -9.81], clumps=cs,
                          timestep=TimeStep.auto(safety=0.8) if auto else TimeStep.from_alpha(0.1),
                          clump_velocities=rng.normal(0, 0.5, (len(pos), 3)),
                          clump_angular_velocities=spin)

    def checks_of(sim):
        """The steps at which ``sim``'s 'auto' control checks the drift, from now on."""
        steps = []
        check = sim.auto.renew_drift_budget

        def recorded():
            steps.append(sim.step)
            return check()

        sim.auto.renew_drift_budget = recorded
        return steps

    a = build()
    a.run(steps=300)
    if auto:  # both budgets of the last check partly spent
        assert 0.0 < a.auto.turned_since_check() < a.auto.turn_budget
        assert 0.0 < dem.drift_used(a.counters) < a.auto.check_budget
    save_checkpoint(a, tmp_path / "c.npz")
    saved, before = a.step, a.n_dt_estimates if auto else 0
    checks_a = checks_of(a)
    a.run(steps=400)
    b = build()
    load_checkpoint(b, tmp_path / "c.npz")
    checks_b = checks_of(b)
    b.run(steps=400)
    assert np.array_equal(a.bodies.x, b.bodies.x) and np.array_equal(a.bodies.q, b.bodies.q)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.ledger.acc, b.ledger.acc)
    assert a.n_contacts > 0
    if not auto:
        return
    assert checks_b[0] == saved + 1 < checks_a[0]  # (the restart's own check)
    assert a.dt == b.dt and b.auto.certificate.has_bodies and len(b.auto.certificate.body_pairs)
    # (b: none at its start; the scheduled one at step 500 and forced ones)
    assert a.n_dt_estimates - before == b.n_dt_estimates > 1
    data = dict(np.load(tmp_path / "c.npz"))
    assert len(data["ts_cert_body_pairs"])
    for key, value, needle in (("ts_cert_body_pairs", lambda p: p + [0, 0, 5, 0], "wall"),
                               ("ts_cert_body_q", lambda q: q[:-1], "expected"),
                               ("ts_cert_body_ref", lambda r: r * np.nan, "non-finite")):
        bad = dict(data)
        bad[key] = value(bad[key])
        np.savez(tmp_path / "bad.npz", **bad)
        with pytest.raises(InputError, match=f"{key}.*{needle}"):
            load_checkpoint(build(), tmp_path / "bad.npz")


# -------------------------------------------------------------- the certificate
def clump_assembly(seed, n_bodies=5, inflate=1.25):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, 5.0, (n_bodies, 3))
    cs = place([ASYM], [0] * n_bodies, pos, random_quaternions(n_bodies, rng), 1.0)
    from demstep.clumps import expand

    xm, rm, body, off = expand(cs)
    p = Particles.from_density(xm, rm * inflate, 1.0)
    R = quat_to_matrix(cs.q)
    arm = np.einsum("mij,mj->mi", R[body], off)
    mass = np.array([cs.frames[0][2]] * n_bodies)
    Iw = np.einsum("bij,bj,bkj->bik", R, np.array([cs.frames[0][1]] * n_bodies), R)
    bodies = RigidBodies(body, arm, mass, Iw, np.zeros(n_bodies, bool))
    c = find_contacts(p, 1.0)
    c = c.subset(body[c.i] != body[c.j])
    c.k_n[:] = rng.random(c.n) + 0.5
    c.k_s[:] = rng.random(c.n) * 0.7
    return p, c, bodies, rng


def body_matrices(p, c, bodies, rotation=True):
    """Dense G^T K G, G^T C G and the block mass matrix of the bodies (reference)."""
    K = assemble_stiffness(p, c, True).toarray()
    Cd = assemble_stiffness(p, replace(c, k_n=c.c_n, k_s=c.c_t), True).toarray()
    n, nb = p.n, bodies.n
    G = np.zeros((n * 6, nb * 6))
    for s in range(n):
        b, a = bodies.sphere_body[s], bodies.arm[s]
        X = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        G[6 * s:6 * s + 3, 6 * b:6 * b + 3] = np.eye(3)
        G[6 * s:6 * s + 3, 6 * b + 3:6 * b + 6] = -X
        G[6 * s + 3:6 * s + 6, 6 * b + 3:6 * b + 6] = np.eye(3)
    M = np.zeros((nb * 6, nb * 6))
    for b in range(nb):
        M[6 * b:6 * b + 3, 6 * b:6 * b + 3] = bodies.mass[b] * np.eye(3)
        M[6 * b + 3:6 * b + 6, 6 * b + 3:6 * b + 6] = bodies.inertia[b]
    return G.T @ K @ G, G.T @ Cd @ G, M


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_exact_step_of_clumps_equals_dense_body_matrices(seed):
    p, c, bodies, _ = clump_assembly(seed)
    assert c.n >= 3
    Kb, _, M = body_matrices(p, c, bodies)
    lam = scipy.linalg.eigh(Kb, M, eigvals_only=True)[-1]
    for dense_limit in (10**6, 0):
        e = exact_critical_step(p, c, True, bodies=bodies, dense_limit=dense_limit)
        assert e.dt == pytest.approx(2 / math.sqrt(lam), rel=1e-8)
    assert body_element_dt(p, c, bodies, True).min() <= e.dt * (1 + 1e-12)


@pytest.mark.parametrize("seed", [4, 5])
def test_damped_exact_step_of_clumps_is_the_amplification_threshold(seed):
    p, c, bodies, rng = clump_assembly(seed)
    c = replace(c, c_n=rng.random(c.n) * 0.3, c_t=rng.random(c.n) * 0.3)
    Kb, Cb, M = body_matrices(p, c, bodies)
    Cb = Cb + 0.05 * M
    Minv = np.linalg.inv(M)
    n = len(M)
    eye = np.eye(n)

    def rho(dt):
        A = np.block([[eye - dt * dt * Minv @ Kb, dt * (eye - dt * Minv @ Cb)],
                      [-dt * Minv @ Kb, eye - dt * Minv @ Cb]])
        mu = np.linalg.eigvals(A)
        return np.abs(mu[np.abs(mu - 1) > 1e-5]).max()

    lo, hi = 0.0, 10.0
    for _ in range(45):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if rho(mid) > 1 + 1e-9 else (mid, hi)
    e = exact_critical_step(p, c, True, damping=GlobalDamping(0.05), bodies=bodies)
    assert e.dt == pytest.approx(lo, rel=1e-6) and e.dt <= lo * (1 + 1e-9)
    assert body_element_dt(p, c, bodies, True, 0.05).min() <= e.dt


def scaled_body_matrices(p, c, bodies):
    """M^-1/2 (G^T K G) M^-1/2 and likewise for the dashpots (dense, reference)."""
    Kb, Cb, M = body_matrices(p, c, bodies)
    w, V = np.linalg.eigh(M)
    W = V @ np.diag(w ** -0.5) @ V.T
    return W @ Kb @ W, W @ Cb @ W


def dense_damped_root(K, C):
    """The largest sigma with lambda_max(sigma C + K) = sigma^2 (bisection)."""
    f = lambda s: np.linalg.eigvalsh(s * C + K)[-1] - s * s  # noqa: E731
    lo, hi = 0.0, 1.0
    while f(hi) > 0:
        hi *= 2.0
    for _ in range(200):
        lo, hi = (0.5 * (lo + hi), hi) if f(0.5 * (lo + hi)) > 0 else (lo, 0.5 * (lo + hi))
    return hi


@pytest.mark.parametrize("seed", [6, 7, 8])
def test_turned_clumps_stay_below_the_drifted_certificate(seed):
    """Five clumps of four spheres, their touching contacts with springs and dashpots,
    certified at their dense damped root; then every body turns by up to 0.08 rad about
    its centre and moves by up to 3 % of the smallest radius (the contacts' normals and
    arms those of the new geometry, their lever arms and the world inertia turned with
    the bodies): the dense lambda_max(sigma C' + K') of the moved bodies stays below the
    certificate's bound with its drift (demstep.timestep.certificate, Clumps) for every
    sigma above sigma_c, the bound without drift does not always (the drift is needed),
    and a translation of every body drifts by nothing."""
    from conftest import contacts_now
    from demstep.clumps import expand
    from demstep.timestep.certificate import BodyPose, StepCertificate

    p, c, bodies, rng = clump_assembly(seed, inflate=1.3)
    ref = contacts_now(replace(c, c_n=0.2 * np.sqrt(c.k_n), c_t=0.1 * np.sqrt(c.k_n)),
                       p.x, p.r)
    assert ref.n >= 4
    K, C = scaled_body_matrices(p, ref, bodies)
    sigma_c = dense_damped_root(K, C)
    lam_c = np.linalg.eigvalsh(C)[-1]
    n_bodies = bodies.n
    cs = place([ASYM], [0] * n_bodies, np.zeros((n_bodies, 3)), np.tile([1.0, 0, 0, 0],
                                                                      (n_bodies, 1)), 1.0)
    _, _, body, offset = expand(cs)
    R0 = np.zeros((n_bodies, 3, 3))
    # the orientation of each body from its members' world arms and body-frame offsets
    for b in range(n_bodies):
        m = body == b
        u, _, vt = np.linalg.svd(bodies.arm[m].T @ offset[m])
        R0[b] = u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt
    assert np.allclose(np.einsum("mij,mj->mi", R0[body], offset), bodies.arm, atol=1e-12)
    q0 = np.array([quat_of(R) for R in R0])
    cert = StepCertificate.from_estimate(sigma_c, lam_c, ref, 1.0 / p.m, 1.0 / p.inertia,
                                         radius=p.r, sphere_body=body, body_q=q0)
    assert cert.has_bodies and len(cert.body_pairs) == ref.n
    moments = np.array([cs.frames[0][1]] * n_bodies)
    centre = p.x - bodies.arm

    def pose(q):
        return BodyPose(body, offset, q, 1.0 / bodies.mass, 1.0 / moments)

    shift = p.x + [0.3, -0.2, 0.1]
    assert max(cert.drift(shift, np.zeros(3), None, pose(q0))) < 1e-12 * sigma_c ** 2
    exceeded = 0
    for trial in range(12):
        axis = rng.normal(size=(n_bodies, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        angle = rng.uniform(0.0, 0.08, n_bodies)
        turn = np.array([scipy.spatial.transform.Rotation.from_rotvec(a * e).as_matrix()
                         for a, e in zip(angle, axis)])
        R1 = turn @ R0
        q1 = np.array([quat_of(R) for R in R1])
        move = 0.03 * p.r.min() * rng.uniform(-1, 1, (n_bodies, 3))
        arm1 = np.einsum("mij,mj->mi", R1[body], offset)
        x1 = centre + move[body] + arm1
        drift = cert.drift(x1, np.zeros(3), None, pose(q1))
        assert drift[0] > 0 and drift[1] > 0
        moved = RigidBodies(body, arm1, bodies.mass,
                            np.einsum("bij,bj,bkj->bik", R1, moments, R1), bodies.fixed)
        now = contacts_now(ref, x1, p.r)
        p1 = Particles.from_density(x1, p.r, 1.0)
        K1, C1 = scaled_body_matrices(p1, now, moved)
        for sigma in sigma_c * np.array([1.0, 1.1, 1.5, 3.0]):
            actual = np.linalg.eigvalsh(sigma * C1 + K1)[-1]
            assert actual <= cert.bound(sigma, drift) * (1 + 1e-12)
            exceeded += actual > cert.bound(sigma) * (1 + 1e-12)
    assert exceeded > 0


def body_drift_reference(cert, x, walls, pose):
    """(D_K, D_C) of the clumps' contacts of ``cert`` by the module doc (Clumps), in
    plain numpy with dense 3 x 3 norms: the slow reference of _body_drift_sums."""
    n = len(x)
    sums = np.zeros((2, n + len(pose.q)))
    root = np.sqrt(pose.inv_I)
    planar = cert.body_dim == 2

    def side(s, sign, a_ref, a_now, n_ref, n_now):
        b = pose.sphere_body[s]
        if b < 0:
            S_ref = S_now = np.sqrt(cert.particles[s, 2]) * np.eye(3)
            o_ref = o_now = np.zeros(3)
            inv_m, owner = cert.particles[s, 1], s
        else:
            R_ref, R_now = quat_to_matrix(cert.body_q[b]), quat_to_matrix(pose.q[b])
            S_ref = R_ref @ np.diag(root[b]) @ R_ref.T
            S_now = R_now @ R_ref.T @ S_ref  # (S' Q)
            o_ref, o_now = R_ref @ pose.offset[s], R_now @ pose.offset[s]
            inv_m, owner = pose.inv_m[b], n + b
        A_ref = cross_of(o_ref + sign * a_ref * n_ref) @ S_ref
        A_now = cross_of(o_now + sign * a_now * n_now) @ S_now
        norm = lambda m: np.linalg.norm(m, 2) ** 2  # noqa: E731
        return (owner, inv_m, norm(A_ref), norm(A_now), norm(A_now - A_ref), norm(S_ref),
                norm(S_now - S_ref))

    for c, (a, b, w, bond) in enumerate(cert.body_pairs):
        n_ref = cert.body_ref[c, 2:]
        if b >= 0:
            d = x[b] - x[a]
            dist = np.linalg.norm(d)
            if not bond and dist >= cert.particles[a, 0] + cert.particles[b, 0]:
                continue
            n_now = d / dist
            half = 0.5 * (cert.particles[a, 0] + cert.particles[b, 0] - dist)
            arms = (cert.particles[a, 0] - half, cert.particles[b, 0] - half)
        else:
            point, normal = walls[0][w], walls[1][w]
            dist = (x[a] - point) @ normal
            if dist >= cert.particles[a, 0]:
                continue
            n_now, arms = -normal, (dist, 0.0)
        turn = np.linalg.norm(n_now - n_ref)
        rows = [side(a, 1.0, cert.body_ref[c, 0], arms[0], n_ref, n_now)]
        if b >= 0:
            rows.append(side(b, -1.0, cert.body_ref[c, 1], arms[1], n_ref, n_now))
        owners = [row[0] for row in rows]
        trans, rot_ref, rot_now, eta2, phi2, phi_eta2 = np.sum([row[1:] for row in rows], axis=0)
        l_ref, l_now, eta = np.sqrt(trans + rot_ref), np.sqrt(trans + rot_now), np.sqrt(eta2)
        k_n, k_t, c_n, c_t, k_r, k_w, c_r, c_w = cert.body_coef[c]
        for row, (bn, bt, br, bw) in enumerate(((k_n, k_t, k_r, k_w), (c_n, c_t, c_r, c_w))):
            f = (l_ref + l_now) * (abs(bn - bt) * turn * l_now + max(bn, bt) * eta)
            if (k_r, k_w, c_r, c_w) != (0, 0, 0, 0):
                swing = 0.0 if planar else turn * np.sqrt(phi2)
                f += 2 * np.sqrt(phi2) * (abs(bw - br) * swing + max(br, bw) * np.sqrt(phi_eta2))
            for o in owners:
                sums[row, o] += f
    return sums[0].max(), sums[1].max()


def cross_of(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def synthetic_body_certificate(dim, rng):
    """A certificate of 14 overlapping spheres (3 free, 11 members of 4 bodies), 20
    random pairs (one a bond) and 10 wall contacts with random arms, normals, springs,
    dashpots, rolling and twisting at the estimate: (cert, x, walls, axes of the
    bodies' turns, a function making the BodyPose of orientations q)."""
    from demstep.timestep.certificate import BodyPose, StepCertificate

    n, n_bodies = 14, 4
    x = np.zeros((n, 3))
    x[:, :dim] = rng.uniform(0, 1.5, (n, dim))
    body = np.array([-1, -1, -1, 0, 0, 1, 1, 1, 2, 2, 3, 3, 3, 3])
    offset = np.zeros((n, 3))
    offset[body >= 0, :dim] = rng.uniform(-0.6, 0.6, (np.count_nonzero(body >= 0), dim))
    radius = rng.uniform(0.9, 1.2, n)
    axis = np.zeros((n_bodies, 3))
    if dim == 2:
        axis[:, 2] = 1.0
    else:
        axis = rng.normal(size=(n_bodies, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(0, np.pi, n_bodies)
    q_ref = np.column_stack([np.cos(angle / 2), np.sin(angle / 2)[:, None] * axis])
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)
             if body[i] < 0 or body[i] != body[j]]
    pairs = [pairs[k] for k in rng.choice(len(pairs), 20, replace=False)]
    walls = (np.array([[0.0, -0.5, 0.0], [-0.5, 0.0, 0.0]]),
             np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]))
    wall_rows = [(s, w) for s in (0, 4, 6, 9, 12) for w in (0, 1)]
    m = len(pairs) + len(wall_rows)
    rows = np.array([(i, j, -1, 0) for i, j in pairs] + [(s, -1, w, 0) for s, w in wall_rows])
    rows[0, 3] = 1  # (a bond)
    ref = np.zeros((m, 5))
    ref[:, :2] = rng.uniform(0.5, 1.0, (m, 2))
    ref[:, 2:2 + dim] = rng.normal(size=(m, dim))
    ref[:, 2:] /= np.linalg.norm(ref[:, 2:], axis=1, keepdims=True)
    coef = rng.uniform(0.1, 2.0, (m, 8))
    if dim == 2:
        coef[:, 5] = coef[:, 7] = 0.0  # (disks do not twist)
    cert = StepCertificate(1.0, 0.5, body_q=q_ref, body_pairs=rows, body_ref=ref,
                           body_coef=coef, body_dim=dim,
                           particles=np.column_stack([radius, rng.uniform(0.5, 2, n),
                                                      rng.uniform(0.5, 2, n)]))
    inv_I = rng.uniform(0.3, 3.0, (n_bodies, 3))
    if dim == 2:
        inv_I[:, :2] = 0.0
    inv_m = rng.uniform(0.2, 1.0, n_bodies)
    return cert, x, walls, axis, lambda q: BodyPose(body, offset, q, inv_m, inv_I)


def turned(q, axis, angle):
    """The orientations q turned further by ``angle`` (B,) about ``axis`` (B, 3)."""
    dq = np.column_stack([np.cos(angle / 2), np.sin(angle / 2)[:, None] * axis])
    return np.array([quat_product(a, b) for a, b in zip(dq, q)])


@pytest.mark.parametrize("dim", [2, 3])
def test_body_drift_equals_a_numpy_reference(dim):
    """The compiled drift of the clumps' contacts (free spheres, members of several
    bodies, walls, a bond, springs, dashpots, rolling and twisting) equals a plain
    numpy evaluation of the module doc's bound with dense 3 x 3 norms, for random
    turns and moves (the soundness of the bound: the dense eigenvalue test above)."""
    rng = np.random.default_rng(dim)
    cert, x, walls, axis, pose = synthetic_body_certificate(dim, rng)
    for trial in range(5):
        q = turned(cert.body_q, axis, rng.uniform(0, 0.3, len(axis)))
        moved = x.copy()
        moved[:, :dim] += rng.uniform(-0.1, 0.1, (len(x), dim))
        got = cert.drift(moved, np.zeros(3), walls, pose(q))
        want = body_drift_reference(cert, moved, walls, pose(q))
        assert want[0] > 0 and want[1] > 0
        assert got == pytest.approx(want, rel=1e-8)


@pytest.mark.parametrize("dim", [2, 3])
def test_body_budgets_keep_the_step_certified_on_the_way(dim):
    """From a turned and moved state, the budgets (E, Theta) of a step with room left:
    at any state whose pairs' ends moved by at most E relative to each other (each
    sphere by at most E / 2, each in its own direction) and whose bodies turned by at
    most Theta further, the drift still certifies the step; the budgets are not
    vanishingly small, and vanish without room."""
    rng = np.random.default_rng(10 + dim)
    cert, x, walls, axis, pose = synthetic_body_certificate(dim, rng)
    q_now = turned(cert.body_q, axis, rng.uniform(0, 0.2, len(axis)))
    now = x.copy()
    now[:, :dim] += rng.uniform(-0.05, 0.05, (len(x), dim))
    drift = cert.drift(now, np.zeros(3), walls, pose(q_now))
    sigma = 1.3 * cert.smallest_sigma(drift)
    e_cap, angle_cap = 0.02, 0.02  # (the engine's caps, times the radii ~ 1)
    budget, turn = cert.body_budgets(sigma, now, np.zeros(3), walls, pose(q_now), e_cap,
                                     angle_cap)
    assert 1e-4 < budget <= e_cap and 1e-4 < turn <= angle_cap
    used = 0.0
    for trial in range(40):
        step = np.zeros_like(now)
        direction = rng.normal(size=(len(x), dim))
        step[:, :dim] = (0.5 * budget * rng.uniform(0.5, 1.0, (len(x), 1)) * direction
                         / np.linalg.norm(direction, axis=1, keepdims=True))
        # |dR_x - I| = 2 sin(angle / 2) <= turn
        q = turned(q_now, axis if dim == 2 else unit_rows(rng.normal(size=axis.shape)),
                   2 * np.arcsin(0.5 * turn * rng.uniform(0.5, 1.0, len(axis))))
        later = cert.drift(now + step, np.zeros(3), walls, pose(q))
        assert cert.certifies(sigma, later)
        used = max(used, (cert.bound(sigma, later) - cert.bound(sigma, drift))
                   / (sigma * sigma - cert.bound(sigma, drift)))
    # (the states reached use some of the room: random moves and turns are far from
    # the worst case the budgets allow for, a few percent of it)
    assert used > 0.005
    tight = cert.smallest_sigma(cert.drift(now, np.zeros(3), walls, pose(q_now)))
    assert cert.body_budgets(tight, now, np.zeros(3), walls, pose(q_now), e_cap,
                             angle_cap) == (0.0, 0.0)


def unit_rows(v):
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def quat_product(a, b):
    """The quaternion product a b (w, x, y, z)."""
    w1, v1, w2, v2 = a[0], a[1:], b[0], b[1:]
    return np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])


def quat_of(R):
    """The unit quaternion (w, x, y, z) of a rotation matrix."""
    x, y, z, w = scipy.spatial.transform.Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


# -------------------------------------------------------------------- bad input
@pytest.mark.parametrize("centers,radii,needle", [
    (np.zeros((0, 3)), np.zeros(0), "at least one member"),
    (np.array([[0, 0, 0], [1.0, 0, 0]]), np.array([1.0, -0.5]), "radius must be > 0"),
    (np.array([[0, 0, 0], [5.0, 0, 0]]), np.array([1.0, 1.0]), "not one rigid body"),
    (np.array([[0, 0, 0], [0, 0, 0]]), np.array([1.0, 1.0]), "same centre"),
])
def test_bad_templates(centers, radii, needle):
    with pytest.raises(InputError, match=needle):
        ClumpTemplate("t", centers, radii)


@pytest.mark.parametrize("shape,spacing,rotation", [("dimer", 1.0, True), ("cube8", 0.75, True),
                                                    ("square", 1.0, False)])
def test_engine_threshold_of_clump_packings_matches_the_exact_step(shape, spacing, rotation):
    """The engine's measured stability threshold (bisection to 0.2 %) of a clump
    packing at rest against the exact step of its bodies (six DOFs, inertia tensors)."""
    from demstep.experiments.clump_stability import clump_study

    row = clump_study(shape, spacing, rotation, rtol=2e-3)
    exact = row["estimates"]["exact"]
    assert exact <= row["bracket"][1]
    assert row["alpha_empirical"] == pytest.approx(exact, rel=5e-3)
    # the body element bound: below the exact step (equal to it for some locked packings)
    assert row["estimates"]["element-coupled"] <= exact * (1 + 1e-12)


# ------------------------------------------------------------------- case files
CLUMP_CASE = """
name = "clumps"
gravity = [0.0, 0.0, -9.81]

[[clumps]]
name = "tetra"
members = [[0.0, 0.0, 0.0, 0.5], [0.8, 0.0, 0.0, 0.5], [0.4, 0.7, 0.0, 0.5], [0.4, 0.23, 0.65, 0.5]]

[[clumps]]
name = "dimer"
members = [[0.0, 0.0, 0.0, 0.5], [0.9, 0.0, 0.0, 0.45]]

[particles]
generator = "clumps"
templates = ["tetra", "dimer"]
count = [3, 3, 2]
spacing = 2.5
density = 2500.0
seed = 3

[contact]
law = "linear"
k_n = 1.0e5
mu = 0.4
restitution = 0.5

[box]
lower = [0.0, 0.0, 0.0]
upper = [7.5, 7.5, 10.0]

[timestep]
alpha = 0.1

[[stages]]
name = "settle"
steps = 1200

[output]
history_every = 100
checkpoint_every = 600
"""


def test_clump_case_runs_and_restarts_bit_for_bit(tmp_path):
    from demstep.case import case_from_text
    from demstep.runner import run_case

    case = case_from_text(CLUMP_CASE, base_dir=tmp_path, source="clumps.toml")
    straight = run_case(case, tmp_path / "a", quiet=True)
    assert straight.status == "completed"
    half = sorted((tmp_path / "a" / "checkpoints").glob("*600.npz"))[0]
    resumed = run_case(case, tmp_path / "b", quiet=True, restart=half)
    assert resumed.status == "completed"
    a, b = np.load(straight.checkpoint), np.load(resumed.checkpoint)
    for key in ("bodies.x", "bodies.q", "bodies.L", "spheres.x", "ledger.acc"):
        assert np.array_equal(a[key], b[key]), key
    assert a["bodies.x"].shape == (18, 3)
    # the bodies fell and landed: contacts between bodies, none within one
    from demstep.io.checkpoint import load_checkpoint
    from demstep.case import build_simulation

    sim = build_simulation(case)
    load_checkpoint(sim, straight.checkpoint)
    c = sim.contact_set()
    sb = sim.bodies.sphere_body
    assert c.n > 0 and not np.any((c.j >= 0) & (sb[c.i] == sb[np.maximum(c.j, 0)]))


@pytest.mark.parametrize("change,needle", [
    (('members = [[0.0, 0.0, 0.0, 0.5], [0.9, 0.0, 0.0, 0.45]]', 'members = []'),
     "at least one member"),
    (('[0.9, 0.0, 0.0, 0.45]', '[0.9, 0.0, 0.0, -0.45]'), "radius must be > 0"),
    (('[0.9, 0.0, 0.0, 0.45]', '[3.0, 0.0, 0.0, 0.45]'), "not one rigid body"),
    (('templates = ["tetra", "dimer"]', 'templates = ["tetra", "rod"]'), "no [[clumps]] template named 'rod'"),
])
def test_bad_clump_cases_give_one_line(tmp_path, change, needle, capsys):
    from demstep.cli import main

    path = tmp_path / "bad.toml"
    path.write_text(CLUMP_CASE.replace(*change))
    code = main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet"])
    _, err = capsys.readouterr()
    assert code == 2 and needle in err and err.count("\n") == 1
    assert not (tmp_path / "out").exists()


def test_body_file_naming_a_missing_template(tmp_path, capsys):
    from demstep.cli import main

    (tmp_path / "bodies.csv").write_text("x,y,z,template\n1.5,1.5,1.5,tetra\n4,1.5,1.5,rod\n")
    text = (CLUMP_CASE.replace('templates = ["tetra", "dimer"]\ncount = [3, 3, 2]\nspacing = 2.5\n',
                               'file = "bodies.csv"\n'))
    (tmp_path / "case.toml").write_text(text)
    code = main(["run", str(tmp_path / "case.toml"), "--out", str(tmp_path / "out"), "--quiet"])
    _, err = capsys.readouterr()
    assert code == 2 and "column 'template'" in err and "'rod'" in err
    assert not (tmp_path / "out").exists()


def test_resolved_case_finds_its_body_and_template_files_from_elsewhere(tmp_path):
    """The resolved case (what a run folder's case.toml holds) names the clump body file
    and a template's member file by absolute paths: written to another folder it loads
    and builds the same bodies (relative, it would look for them in that folder)."""
    import tomli_w

    from demstep.case import build_simulation, case_from_dict, load_case

    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "bodies.csv").write_text("x,y,z,template\n1.5,1.5,1.5,tetra\n"
                                               "4,1.5,1.5,dimer\n")
    (tmp_path / "in" / "dimer.csv").write_text("x,y,z,r\n0,0,0,0.5\n0.9,0,0,0.45\n")
    text = (CLUMP_CASE.replace('templates = ["tetra", "dimer"]\ncount = [3, 3, 2]\nspacing = 2.5\n',
                               'file = "bodies.csv"\n')
            .replace('members = [[0.0, 0.0, 0.0, 0.5], [0.9, 0.0, 0.0, 0.45]]', 'file = "dimer.csv"'))
    assert 'file = "dimer.csv"' in text
    (tmp_path / "in" / "case.toml").write_text(text)
    case = load_case(tmp_path / "in" / "case.toml")
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "case.toml").write_text(tomli_w.dumps(case.resolved()))
    again = load_case(tmp_path / "elsewhere" / "case.toml")
    a, b = build_simulation(case), build_simulation(again)
    assert a.bodies is not None and len(a.x) == len(b.x) == 6
    assert np.array_equal(a.x, b.x) and np.array_equal(a.m, b.m)


def test_dt_on_a_file_with_a_body_column(tmp_path, capsys):
    """`demstep dt` on spheres with a body column: clumps with six DOFs, the same exact
    step as the bodies of the Python API."""
    import json

    from demstep.cli import main
    from demstep.io.formats import write_csv

    p, c, bodies, _ = clump_assembly(11, inflate=1.0)
    write_csv(tmp_path / "c.csv", p.x, p.r, body=bodies.sphere_body)
    code = main(["dt", str(tmp_path / "c.csv"), "--kn", "1", "--density", "1", "--json",
                 "--contact-tol", "0.3"])
    out, err = capsys.readouterr()
    assert code == 0, err
    data = json.loads(out)
    assert any("clumps" in n for n in data["notes"])
    assert "element-paper" not in [e["method"] for e in data["estimates"]]


def mixed_owner_assembly(dim, seed):
    """Free spheres (one fixed), four bodies of 2-3 members (one fixed), random pair
    and wall contacts between different owners with springs, dashpots and rolling and
    twisting springs; the bodies' inertia tensors random (SPD)."""
    rng = np.random.default_rng(seed)
    body = np.array([-1, -1, 0, 0, -1, 1, 1, 1, 2, 2, -1, 3, 3])
    n = len(body)
    x = rng.uniform(0.0, 3.0, (n, dim))
    r = rng.uniform(0.3, 0.6, n)
    fixed = np.zeros(n, bool)
    fixed[4] = True
    p = Particles(x, r, rng.uniform(0.5, 2.0, n), rng.uniform(0.1, 0.5, n), fixed)
    n_bodies = 4
    A = rng.normal(size=(n_bodies, 3, 3))
    inertia = np.einsum("bij,bkj->bik", A, A) + 0.5 * np.eye(3)
    arm = np.zeros((n, 3))
    arm[body >= 0, :dim] = rng.normal(scale=0.4, size=(int((body >= 0).sum()), dim))
    bodies = RigidBodies(body, arm, rng.uniform(1.0, 3.0, n_bodies), inertia,
                         np.array([False, False, True, False]))
    owner = np.where(body >= 0, 100 + body, np.arange(n))
    pairs = [(a, b) for a in range(n) for b in range(a + 1, n) if owner[a] != owner[b]]
    pick = rng.choice(len(pairs), 18, replace=False)
    i = np.array([pairs[k][0] for k in pick] + [1, 6, 9])
    j = np.array([pairs[k][1] for k in pick] + [-1, -1, -1])
    c = len(i)
    normal = rng.normal(size=(c, dim))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    contacts = ContactSet(i, j, normal, rng.uniform(0.2, 0.6, c),
                          np.where(j >= 0, rng.uniform(0.2, 0.6, c), 0.0),
                          rng.uniform(0.5, 2.0, c), rng.uniform(0.1, 1.0, c),
                          c_n=rng.uniform(0.0, 0.5, c), c_t=rng.uniform(0.0, 0.5, c),
                          k_r=rng.uniform(0.0, 0.3, c), k_w=rng.uniform(0.0, 0.3, c),
                          c_r=rng.uniform(0.0, 0.1, c), c_w=rng.uniform(0.0, 0.1, c))
    return p, contacts, bodies


def owner_reference(p, bodies):
    """Dense G (spheres' DOFs from the owners') and the owners' M^-1/2 (zero: fixed),
    free spheres first in their order, then the bodies."""
    dim = p.dim
    nd = 3 if dim == 2 else 6
    body = bodies.sphere_body
    free = np.flatnonzero(body < 0)
    n_owners = len(free) + bodies.n
    G = np.zeros((p.n * nd, n_owners * nd))
    S = np.zeros((n_owners * nd, n_owners * nd))
    for o, s in enumerate(free):
        G[nd * s:nd * s + nd, nd * o:nd * o + nd] = np.eye(nd)
        if not p.fixed[s]:
            S[nd * o:nd * o + nd, nd * o:nd * o + nd] = np.diag(
                [p.m[s] ** -0.5] * dim + [p.inertia[s] ** -0.5] * (nd - dim))
    for s in np.flatnonzero(body >= 0):
        o = len(free) + body[s]
        a = bodies.arm[s]
        G[nd * s:nd * s + dim, nd * o:nd * o + dim] = np.eye(dim)
        if dim == 2:  # u = v + theta_z x a
            G[nd * s:nd * s + 2, nd * o + 2] = [-a[1], a[0]]
            G[nd * s + 2, nd * o + 2] = 1.0
        else:
            X = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
            G[nd * s:nd * s + 3, nd * o + 3:nd * o + 6] = -X
            G[nd * s + 3:nd * s + 6, nd * o + 3:nd * o + 6] = np.eye(3)
    for b in range(bodies.n):
        if bodies.fixed[b]:
            continue
        o = len(free) + b
        S[nd * o:nd * o + dim, nd * o:nd * o + dim] = bodies.mass[b] ** -0.5 * np.eye(dim)
        if dim == 2:
            S[nd * o + 2, nd * o + 2] = bodies.inertia[b, 2, 2] ** -0.5
        else:
            w, V = np.linalg.eigh(bodies.inertia[b])
            S[nd * o + 3:nd * o + 6, nd * o + 3:nd * o + 6] = V @ np.diag(w ** -0.5) @ V.T
    return G, S


@pytest.mark.parametrize("dim", [2, 3])
def test_the_compiled_owner_product_equals_dense_body_matrices(dim):
    """S G^T K G S x of the compiled product (expand, contact product, reduce in one
    kernel; serial, and threaded in runs of contacts with the bodies reduced in
    parallel) against the dense matrices, with free spheres (one fixed), bodies (one
    fixed), wall contacts and rolling and twisting springs, a sphere without contacts,
    after a first product has left values in the scratch arrays; and the expansion of
    a mode (the owners' DOFs to the spheres') against G S."""
    from demstep.timestep.exact import ScaledContactOperator

    p, contacts, bodies = mixed_owner_assembly(dim, 11 + dim)
    contacts = contacts.subset((contacts.i != 0) & (contacts.j != 0))  # (sphere 0 apart)
    G, S = owner_reference(p, bodies)
    K = assemble_stiffness(p, contacts, True).toarray()
    C = assemble_stiffness(p, replace(contacts, k_n=contacts.c_n, k_s=contacts.c_t,
                                      k_r=contacts.c_r, k_w=contacts.c_w), True).toarray()
    rng = np.random.default_rng(dim)
    for threads, _ in ((1, 0), (1, 1), (2, 0), (2, 1), (3, 0)):
        op = ScaledContactOperator(p, contacts, True, bodies=bodies, threads=threads)
        assert op.size == S.shape[0] and op.threads == threads
        op.stiffness(rng.normal(size=op.size))  # (its scratch rows hold values now)
        q = rng.normal(size=op.size)
        np.testing.assert_allclose(op.stiffness(q), S @ G.T @ K @ G @ S @ q, rtol=1e-12,
                                   atol=1e-12 * np.abs(K).max() * np.abs(q).max())
        np.testing.assert_allclose(op.dashpots(q), S @ G.T @ C @ G @ S @ q, rtol=1e-12,
                                   atol=1e-12 * np.abs(C).max() * np.abs(q).max())
        np.testing.assert_allclose(op.displacement(q).reshape(-1), G @ S @ q, rtol=1e-13,
                                   atol=1e-13 * np.abs(q).max())


def test_element_steps_of_some_rows_take_the_mass_shares_of_all_contacts():
    """body_element_dt on rows: the steps of those elements in the whole assembly (the
    owners' masses split among all their contacts, not the rows' only), so their min is
    an upper bound on the min over all (the 'auto' control's screen of an element
    estimate); the rows likeliest stiffest hold the smallest step here."""
    from demstep.timestep.clumps import likely_stiffest_elements

    p, contacts, bodies = mixed_owner_assembly(3, 5)
    every = body_element_dt(p, contacts, bodies, True, 0.05, 0.01)
    rows = np.array([0, 3, 7, 20])
    np.testing.assert_array_equal(body_element_dt(p, contacts, bodies, True, 0.05, 0.01, rows),
                                  every[rows])
    likely = likely_stiffest_elements(p, contacts, bodies, True, count=3)
    assert len(likely) <= 6 and np.argmin(every) in likely


def landing_clumps(n_side=5, layers=3):
    """Tetrahedral clumps on a grid dropped into a box (the case of
    benchmarks/clumps.py, smaller), in 'auto' (safety 0.8)."""
    from demstep.clumps import random_quaternions
    from demstep.walls import box_walls

    r, d = 0.5, 0.8
    tetra = ClumpTemplate("tetra", np.array([[0, 0, 0], [d, 0, 0], [d / 2, d * math.sqrt(3) / 2, 0],
                                             [d / 2, d / (2 * math.sqrt(3)),
                                              d * math.sqrt(2 / 3)]]), np.full(4, r))
    g = np.stack(np.meshgrid(np.arange(n_side), np.arange(n_side), np.arange(layers),
                             indexing="ij"), -1).reshape(-1, 3)
    pos = (g + 0.5) * 2.4
    cs = place([tetra], np.zeros(len(pos), dtype=np.int64), pos,
               random_quaternions(len(pos), np.random.default_rng(1)), 2500.0)
    walls = box_walls([-0.5] * 3, [n_side * 2.4 + 0.5, n_side * 2.4 + 0.5, layers * 2.4 + 20])
    return Simulation(None, LinearSpring(k_n=1e6, k_s=1e6, mu=0.5, restitution=0.5),
                      clumps=cs, walls=walls, gravity=[0, 0, -9.81],
                      timestep=TimeStep.auto(safety=0.8))


def test_the_element_screen_only_skips_bounds_that_could_not_be_kept():
    """Clumps landing in 'auto': whenever the screen of an element estimate (its 64
    likeliest stiffest elements) says the coupled element bound cannot decide dt, the
    full bound over every contact could not either (the screen's min is an upper
    bound on it), for the control's test and for thresholds about the full bound; the
    screen decides most of them here, and the steps stay below the exact step of the
    contacts closed."""
    from demstep.timestep.estimates import element_coupled_dt

    sim = landing_clumps()
    screen = sim.auto.element_bound_falls_short
    seen = {"short": 0, "checked": 0}

    def checked(contacts, keep):
        short = screen(contacts, keep)
        if contacts.n > 4 * sim.auto.ELEMENT_SCREEN:
            full = element_coupled_dt(sim.particles_now(), contacts, sim.rotation,
                                      damping=global_damping(sim), bodies=sim.rigid_bodies())
            assert not (short and keep(full))
            for factor in (0.5, 0.999, 1.0, 1.001, 2.0):  # other thresholds on the bound
                at_most = lambda dt, t=factor * full: dt >= t  # noqa: E731
                assert not (screen(contacts, at_most) and at_most(full))
            seen["short"] += short
            seen["checked"] += 1
        return short

    sim.auto.element_bound_falls_short = checked
    worst = 0.0
    for _ in range(30):
        sim.run(steps=10)
        crit = sim.critical_dt("exact")
        if crit is not None:
            worst = max(worst, sim.dt / crit)
    assert seen["checked"] >= 5 and seen["short"] >= seen["checked"] // 2
    assert 0.0 < worst <= 1.0


def test_solves_under_the_motion_limit_run_to_a_looser_residual():
    """While the motion limit holds the step at least 5 % below the certified one, the
    exact solves of 'auto' stop at a relative residual of 1e-4 (AUTO_MOTION_TOL) instead
    of 1e-6: their certified step is then within 8e-4 of a tight solve's and never
    above it. Landing clumps solve with both (measured: 33 loose, 24 tight in 400
    steps)."""
    sim = landing_clumps()
    solve = sim.auto.solve
    seen = {"loose": 0, "tight": 0}

    def checked(method, horizon, tol, prepared=None):
        certified, limit = sim.dt_certified, sim.auto.motion_limit()
        loose = certified is not None and limit < 0.95 * certified
        assert tol == (sim.auto.AUTO_MOTION_TOL if loose else sim.auto.AUTO_EXACT_TOL)
        estimate = solve(method, horizon, tol, prepared)
        if estimate is not None:
            tight = sim.critical_dt(method, horizon=horizon)  # (to the package's 1e-10)
            # ('auto' runs on the certified step: below the solve's own by the random-
            # start check's claim slack, at most 2 CLAIM_SLACK on a damped root)
            lowest = tight * (1 - 8 * tol) / (1 + 2 * CLAIM_SLACK)
            assert lowest <= estimate <= tight * (1 + 1e-8)
            seen["loose" if loose else "tight"] += 1
        return estimate

    sim.auto.solve = checked
    sim.run(steps=400)
    assert seen["loose"] >= 10 and seen["tight"] >= 10


@pytest.mark.parametrize("dim", [2, 3])
def test_owner_mass_shares_split_each_owner_among_its_contacts(dim):
    """Each side's share: the owner's inverse mass and inverse inertia (world; 2D: the
    zz moment) times its number of contacts in the set (walls: none; fixed: zero), for
    the whole set and for a part of it, against a loop over the contacts."""
    from demstep.timestep.clumps import owner_mass_shares

    p, contacts, bodies = mixed_owner_assembly(dim, 7)
    body = bodies.sphere_body

    def owner(s):
        return ("body", body[s]) if body[s] >= 0 else ("sphere", s)

    def inverse(o):
        kind, k = o
        if kind == "sphere":
            return (0.0, np.zeros((3, 3))) if p.fixed[k] else (1 / p.m[k],
                                                               np.eye(3) / p.inertia[k])
        if bodies.fixed[k]:
            return 0.0, np.zeros((3, 3))
        inertia = (np.eye(3) / bodies.inertia[k, 2, 2] if dim == 2
                   else np.linalg.inv(bodies.inertia[k]))
        return 1 / bodies.mass[k], inertia

    for rows in (np.arange(contacts.n), np.array([0, 2, 3, 5, 19, 20])):
        part = contacts.subset(rows)
        count = {}
        for a, b in zip(part.i, part.j):
            for s in ((a, b) if b >= 0 else (a,)):
                count[owner(s)] = count.get(owner(s), 0) + 1
        mi, Ii, mj, Ij = owner_mass_shares(p, part, bodies, True)
        for c, (a, b) in enumerate(zip(part.i, part.j)):
            m, inertia = inverse(owner(a))
            assert mi[c] == pytest.approx(m * count[owner(a)], rel=1e-14)
            np.testing.assert_allclose(Ii[c], inertia * count[owner(a)], rtol=1e-12, atol=0)
            if b < 0:
                assert mj[c] == 0.0 and not Ij[c].any()
            else:
                m, inertia = inverse(owner(b))
                assert mj[c] == pytest.approx(m * count[owner(b)], rel=1e-14)
                np.testing.assert_allclose(Ij[c], inertia * count[owner(b)], rtol=1e-12,
                                           atol=0)
