"""Triangle-mesh walls in the engine: one contact per surface, history carried from
triangle to triangle, the same physics as a plane wall on a flat tessellated plane,
genuine corners kept, moving meshes' work in the ledger, and the contacts in the
time-step analysis."""

import math

import numpy as np
import pytest

from demstep.contact.laws import HertzMindlin, LinearSpring
from demstep.energy import A_ROLLING, A_ROLLING_VISCOUS
from demstep.engine import Simulation, TimeStep
from demstep.engine.meshes import MeshWall
from demstep.mesh import mesh_from_arrays
from demstep.mesh.shapes import plane
from demstep.particles import Particles
from demstep.walls import Wall

R, DENSITY = 0.05, 2500.0


def flat_mesh(n=8, size=2.0, z=0.0, name="floor"):
    """A square of side ``size`` centred on the origin at height z, n x n squares cut in
    two triangles each (2 n^2), normals up."""
    m = plane(n, size=size, name=name)
    v = np.asarray(m.vertices, dtype=float).copy()
    v[:, :2] -= v[:, :2].mean(axis=0)
    v[:, 2] = z
    return mesh_from_arrays(v, np.asarray(m.triangles), name=name)


def sphere_on(floor, law, x0=(-0.31, 0.17), v0=(1.1, 0.45, 0.0), w0=(3.0, -7.0, 2.0),
              overlap=2e-5, gravity=-9.81, dt=2e-5):
    """One sphere resting on ``floor`` ('plane': a plane wall at z = 0, else a MeshWall)
    with a sliding, spinning start."""
    x = np.array([[x0[0], x0[1], R - overlap]])
    p = Particles.from_density(x, np.array([R]), DENSITY)
    kw = dict(velocities=[list(v0)], angular_velocities=[list(w0)], gravity=[0, 0, gravity],
              timestep=TimeStep.fixed(dt))
    if floor == "plane":
        return Simulation(p, law, walls=[Wall([0, 0, 0], [0, 0, 1], name="floor")], **kw)
    return Simulation(p, law, meshes=[MeshWall(floor, name="floor")], **kw)


LAWS = {"linear": LinearSpring(k_n=2e5, mu=0.3, restitution=0.6),
        "rolling": LinearSpring(k_n=2e5, mu=0.3, restitution=0.6, rolling_convention="beta",
                                rolling_stiffness=0.8, twisting_stiffness=0.4,
                                rolling_friction=0.02, twisting_friction=0.05,
                                rolling_damping=0.3),
        "hertz": HertzMindlin(youngs_modulus=5e7, poisson_ratio=0.3, mu=0.3, restitution=0.6)}


@pytest.mark.parametrize("law", ["linear", "hertz", "rolling"])
def test_a_sphere_across_a_tessellated_plane_feels_the_plane(law):
    """A sphere sliding, spinning and rolling across the edges and vertices of a flat
    plane of 128 triangles moves as on a plane wall: forces, position, velocity,
    spin, the tangential spring (history carried from triangle to triangle; with rolling
    resistance its rolling and twisting springs too) and every
    term of the energy ledger agree to round-off at every sampled step, and it crossed
    many triangles (no double force at an edge or vertex: that would push it up)."""
    mesh = sphere_on(flat_mesh(), LAWS[law])
    wall = sphere_on("plane", LAWS[law])
    crossed = set()
    touching = 0
    for _ in range(60):
        for sim in (mesh, wall):
            sim.run(steps=500)
        rows = np.flatnonzero(mesh.meshes.active == 1)
        assert len(rows) == len(wall.wp) == 1 or len(rows) == wall.counters[1] == 0
        if not len(rows):
            continue
        touching += 1
        crossed.add(int(mesh.meshes.slot_tri[rows[0]]))
        for name in ("x", "v", "w", "force", "torque"):
            np.testing.assert_allclose(getattr(mesh, name), getattr(wall, name), rtol=1e-9,
                                       atol=1e-12, err_msg=name)
        np.testing.assert_allclose(mesh.meshes.shear[rows[0]], wall.wft[0], rtol=1e-9,
                                   atol=1e-14)
        if law == "rolling":  # (the rolling and twisting history, carried likewise)
            assert np.abs(wall.wall_state.roll[0, :7]).max() > 0.0
            # (moments ~1e-2 N m: the round-off of the triangles' normals shows at 1e-15)
            np.testing.assert_allclose(mesh.meshes.roll[rows[0]], wall.wall_state.roll[0],
                                       rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(mesh.ledger.acc, wall.ledger.acc, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(mesh.ledger.energy, wall.ledger.energy, rtol=1e-9,
                                   atol=1e-15)
    assert len(crossed) >= 4 and touching >= 50
    assert np.linalg.norm(mesh.x[0, :2] - np.array([-0.31, 0.17])) > 1.5 * 0.25  # squares
    # the force on the mesh is the weight's reaction and the spheres' friction
    np.testing.assert_allclose(mesh.mesh_force[0], wall.wall_force[0], rtol=1e-9, atol=1e-12)


def test_a_centre_over_a_shared_vertex_or_edge_makes_one_contact():
    """A sphere pressed onto a plane right above a vertex shared by six triangles, or
    above an edge shared by two: every triangle finds it; one contact acts, with the
    plane's force."""
    law = LinearSpring(k_n=2e5)
    floor = flat_mesh(n=4, size=2.0)
    vertex = floor.vertices[np.argmin(np.linalg.norm(floor.vertices[:, :2], axis=1))]
    edge_mid = 0.5 * (floor.vertices[floor.triangles[0, 0]] + floor.vertices[floor.triangles[0, 1]])
    for spot in (vertex, edge_mid):
        mesh = sphere_on(floor, law, x0=spot[:2], v0=(0, 0, 0), w0=(0, 0, 0), gravity=0.0)
        wall = sphere_on("plane", law, x0=spot[:2], v0=(0, 0, 0), w0=(0, 0, 0), gravity=0.0)
        for sim in (mesh, wall):
            sim.run(steps=1)
        assert int(mesh.meshes.active.sum()) == 1
        assert mesh.n_contacts == wall.n_contacts == 1  # (counted once: the step's count)
        np.testing.assert_allclose(mesh.force, wall.force, rtol=1e-12)


def test_a_sphere_in_a_groove_touches_both_faces():
    """Two faces meeting at a concave edge (a V groove of 90 degrees): a sphere pressed
    into it has two contacts, one per face, each as with a plane wall of that face."""
    law = LinearSpring(k_n=2e5)
    s = math.sqrt(0.5)
    v = np.array([[-1, -1, 1], [1, -1, 1], [-1, 0, 0], [1, 0, 0], [-1, 1, 1], [1, 1, 1]],
                 dtype=float)
    t = np.array([[0, 2, 1], [1, 2, 3], [2, 4, 3], [3, 4, 5]])
    groove = mesh_from_arrays(v, t, name="groove")
    depth = R / s - 0.003  # the centre's height: both faces overlapped by 0.003 s
    x = np.array([[0.0, 0.0, depth]])
    p = Particles.from_density(x, np.array([R]), DENSITY)
    mesh = Simulation(p, law, meshes=[MeshWall(groove)], timestep=TimeStep.fixed(1e-5))
    walls = [Wall([0, 0, 0], [0, s, s], name="a"), Wall([0, 0, 0], [0, -s, s], name="b")]
    plane_sim = Simulation(p, law, walls=walls, timestep=TimeStep.fixed(1e-5))
    for sim in (mesh, plane_sim):
        sim.run(steps=1)
    assert int(mesh.meshes.active.sum()) == 2
    np.testing.assert_allclose(mesh.force, plane_sim.force, rtol=1e-10,
                               atol=1e-12 * np.abs(plane_sim.force).max())
    assert mesh.force[0, 2] > 0 and abs(mesh.force[0, 1]) < 1e-9 * mesh.force[0, 2]


def test_a_moving_plate_does_work_the_ledger_counts():
    """A plate (a mesh moving up at constant speed) lifts a sphere resting on it against
    gravity: the mesh's work in the ledger is the energy the sphere gains (potential,
    kinetic, elastic, dissipated), the balance closes, and the sphere rides at the
    plate's speed."""
    law = LinearSpring(k_n=2e5, restitution=0.5)
    x = np.array([[0.0, 0.0, R - 1e-3]])
    p = Particles.from_density(x, np.array([R]), DENSITY)
    plate = MeshWall(flat_mesh(n=2, size=1.0), velocity=[0, 0, 0.2])
    sim = Simulation(p, law, meshes=[plate], gravity=[0, 0, -9.81],
                     timestep=TimeStep.fixed(2e-5))
    sim.run(steps=20000)
    assert sim.v[0, 2] == pytest.approx(0.2, rel=1e-3)
    assert sim.ledger.external > 0.0
    assert sim.ledger.balance_error() < 1e-4
    assert sim.meshes.shift[0, 2] == pytest.approx(0.2 * sim.time, rel=1e-12)
    # the plate's force is the sphere's weight (at rest relative to it)
    assert -sim.mesh_force[0, 2] == pytest.approx(sim.m[0] * 9.81, rel=1e-3)


def test_a_sphere_on_a_rotating_drum_turns_with_it():
    """A cylinder (48 facets) turning about its axis at 1 rad/s carries a sphere that
    cannot roll (rotation locked) and sticks by friction (mu 0.8: up to 38.7 degrees)
    up its wall: the sphere moves with the drum's surface at the contact point (its
    centre, nearer the axis, so turns faster than the drum), and the energy balance
    closes with the drum's work."""
    from demstep.mesh.shapes import cylinder

    drum = cylinder(48, radius=0.5, height=0.4, name="drum")
    v = np.asarray(drum.vertices, dtype=float).copy()
    # axis along y through the origin (the shape's axis is z)
    v = v[:, [0, 2, 1]]
    v[:, 1] -= 0.2
    drum = mesh_from_arrays(v, np.asarray(drum.triangles), name="drum")
    law = LinearSpring(k_n=2e5, mu=0.8, restitution=0.3)
    x = np.array([[0.0, 0.0, -0.5 + R - 1e-3]])
    p = Particles.from_density(x, np.array([R]), DENSITY)
    omega = np.array([0, -1.0, 0])  # the bottom moves towards +x
    sim = Simulation(p, law, meshes=[MeshWall(drum, omega=omega)],
                     gravity=[0, 0, -9.81], timestep=TimeStep.fixed(2e-5), rotation=False)
    sim.run(steps=5000)  # settled on the wall
    ratios = []
    for _ in range(20):
        sim.run(steps=1000)
        row = np.flatnonzero(sim.meshes.active == 1)
        assert len(row) == 1
        q = sim.x[0] + R * sim.meshes.normal[row[0]]  # the contact point
        surface = np.cross(omega, q)  # the drum's velocity there
        ratios.append(float(sim.v[0] @ surface) / float(surface @ surface))
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.01)
    angle = math.atan2(sim.x[0, 0], -sim.x[0, 2])
    assert 0.3 < angle < 38.7 * math.pi / 180
    assert sim.meshes.turn[0] == pytest.approx(sim.time, rel=1e-12)
    assert sim.ledger.external > 0 and sim.ledger.balance_error() < 1e-3


def test_mesh_contacts_enter_the_critical_step_as_walls():
    """A sphere resting on a tessellated plane has the critical step of the same sphere
    on a plane wall (exact and element bounds)."""
    law = LinearSpring(k_n=2e5)
    mesh = sphere_on(flat_mesh(), law, v0=(0, 0, 0), w0=(0, 0, 0), gravity=0.0)
    wall = sphere_on("plane", law, v0=(0, 0, 0), w0=(0, 0, 0), gravity=0.0)
    for sim in (mesh, wall):
        sim.run(steps=1)
    for method in ("exact", "element-coupled"):
        assert mesh.critical_dt(method) == pytest.approx(wall.critical_dt(method), rel=1e-10)
    # the fastest mode: the tangential spring at the arm a (the centre's height) turning
    # the sphere, omega^2 = k_s (1/m + a^2/I) (I = 0.4 m r^2, k_s = k_n)
    arm = mesh.x[0, 2]  # (the geometry of the state analysed: the positions now)
    omega2 = 2e5 * (1 / mesh.m[0] + arm**2 / mesh.inertia[0])
    assert mesh.critical_dt("exact") == pytest.approx(2 / math.sqrt(omega2), rel=1e-9)


def test_a_run_with_a_mesh_restarts_bit_for_bit(tmp_path):
    from demstep.io.checkpoint import load_checkpoint, save_checkpoint

    def make():
        return sphere_on(flat_mesh(), LAWS["hertz"])

    a = make()
    a.run(steps=3000)
    save_checkpoint(a, tmp_path / "c.npz")
    a.run(steps=3000)
    b = make()
    load_checkpoint(b, tmp_path / "c.npz")
    b.run(steps=3000)
    for name in ("x", "v", "w"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(a.meshes.shear, b.meshes.shear)
    assert np.array_equal(a.ledger.acc, b.ledger.acc)


def _resting(law, material, overlap=1e-4):
    """A sphere pressed ``overlap`` into a mesh of ``material`` (gravity off), after
    one step: the force the mesh exerts and the critical step."""
    x = np.array([[-0.31, 0.17, R - overlap]])
    sim = Simulation(Particles.from_density(x, np.array([R]), DENSITY), law,
                     meshes=[MeshWall(flat_mesh(), name="floor", material=material)],
                     timestep=TimeStep.fixed(1e-9))
    sim.run(steps=1)
    return sim


def test_a_stiff_hertz_mesh_pairs_its_material_with_the_particles():
    """A steel mesh under glass spheres: the contact's E* pairs the two materials,
    1/E* = (1 - nu_p^2)/E_p + (1 - nu_w^2)/E_w, in the force (4/3 E* sqrt(r) delta^1.5)
    and in the critical step (k_n = 2 E* sqrt(r delta), 2/sqrt(k_n/m), the normal mode
    being the fastest here: mu = 0, no tangential spring stiffer)."""
    law = HertzMindlin(youngs_modulus=5e7, poisson_ratio=0.3)
    steel = {"youngs_modulus": 2e11, "poisson_ratio": 0.29}
    sim = _resting(law, steel)
    delta = R - sim.x[0, 2]
    e_star = 1 / ((1 - 0.3**2) / 5e7 + (1 - 0.29**2) / 2e11)
    assert sim.mesh_force[0, 2] == pytest.approx(-4 / 3 * e_star * math.sqrt(R) * delta**1.5,
                                                 rel=1e-9)
    same = _resting(law, None)
    assert same.mesh_force[0, 2] == pytest.approx(
        -4 / 3 * (5e7 / (2 * (1 - 0.3**2))) * math.sqrt(R) * delta**1.5, rel=1e-9)
    contacts = sim.contact_set()
    kn = 2 * e_star * math.sqrt(R * delta)
    assert contacts.k_n[0] == pytest.approx(kn, rel=1e-9)
    g_star = 1 / (2 * (2 - 0.3) * (1 + 0.3) / 5e7 + 2 * (2 - 0.29) * (1 + 0.29) / 2e11)
    assert contacts.k_s[0] == pytest.approx(8 * g_star * math.sqrt(R * delta), rel=1e-9)


def test_a_linear_mesh_material_sets_the_contact_stiffness():
    """A linear mesh's material is the contact's spring: k_n = 4e6 instead of the
    particles' 2e5 in the force and the critical step."""
    law = LinearSpring(k_n=2e5)
    sim = _resting(law, {"k_n": 4e6})
    delta = R - sim.x[0, 2]
    assert sim.mesh_force[0, 2] == pytest.approx(-4e6 * delta, rel=1e-9)
    assert sim.contact_set().k_n[0] == pytest.approx(4e6)
    assert sim.contact_set().k_s[0] == pytest.approx(4e6)  # (k_s: k_n by default)


def test_a_mesh_material_the_law_does_not_have_is_refused():
    from demstep.errors import InputError

    with pytest.raises(InputError, match=r"mesh 'floor': material\.youngs_modulus: not a "
                                         r"parameter of the linear law"):
        _resting(LinearSpring(k_n=2e5), {"youngs_modulus": 1e9})
    with pytest.raises(InputError, match=r"material\.poisson_ratio: the hertz law pairs"):
        _resting(HertzMindlin(youngs_modulus=5e7), {"youngs_modulus": 1e9})
    with pytest.raises(InputError, match="youngs_modulus"):
        _resting(HertzMindlin(youngs_modulus=5e7), {"youngs_modulus": -1.0,
                                                    "poisson_ratio": 0.3})


def test_the_candidate_search_finds_every_triangle_a_brute_force_search_finds():
    """The grid search (cells over the particles, each triangle visiting the cells of
    its grown bounding box) against every (particle, triangle) distance computed:
    triangles large and small, slanted, beyond the particles' extent, spheres of
    several radii."""
    from demstep.engine.meshes import build_candidates, meshes_bundle
    from demstep.kernels.meshes import triangle_distances
    from demstep.mesh.shapes import cube

    rng = np.random.default_rng(12)
    small = flat_mesh(n=12, size=1.0, z=0.2)                  # 288 small triangles
    big = cube(2.0, name="big")                                # 12 triangles, 2 m sides
    walls = [MeshWall(small, name="small"), MeshWall(big, name="big")]
    bundle = meshes_bundle(walls, LinearSpring(k_n=1.0))
    x = rng.uniform(-1.1, 1.1, (3000, 3))
    r = rng.uniform(0.01, 0.05, 3000)
    skin = 0.02
    cand_p, cand_t = build_candidates(bundle, x, r, skin, lambda p: p)
    n_tri = len(bundle.tri)
    p_all = np.repeat(np.arange(len(x)), n_tri)
    t_all = np.tile(np.arange(n_tri), len(x))
    near = triangle_distances(x, p_all, bundle.tri, t_all) < r[p_all] + skin
    expected = set(zip(p_all[near].tolist(), t_all[near].tolist()))
    assert len(expected) > 500
    assert set(zip(cand_p.tolist(), cand_t.tolist())) == expected
    assert len(cand_p) == len(expected)  # (each pair once)
    assert np.all(np.diff(cand_p * n_tri + cand_t) > 0)  # sorted by particle, then triangle


def test_the_triangle_grid_is_kept_while_the_meshes_stay_and_built_anew_when_they_move():
    """A grid kept across searches (a TriangleGrid): built once for a fixed mesh, again
    when a mesh has moved, when the reach grows (a larger particle) or a mesh is
    switched off; its candidates are the brute-force ones every time."""
    from demstep.engine.meshes import TriangleGrid, build_candidates, meshes_bundle
    from demstep.kernels.meshes import triangle_distances

    rng = np.random.default_rng(3)
    walls = [MeshWall(flat_mesh(n=10, size=1.0, z=0.0), name="a"),
             MeshWall(flat_mesh(n=3, size=1.0, z=0.3), name="b")]
    bundle = meshes_bundle(walls, LinearSpring(k_n=1.0))
    x = rng.uniform(-0.6, 0.6, (2000, 3))
    r = np.full(2000, 0.03)
    grid = TriangleGrid()

    def brute(b, radii, enabled=(True, True)):
        n_tri = len(b.tri)
        p_all = np.repeat(np.arange(len(x)), n_tri)
        t_all = np.tile(np.arange(n_tri), len(x))
        near = (triangle_distances(x, p_all, b.tri, t_all) < radii[p_all] + 0.01) \
            & np.asarray(enabled)[b.tri_mesh[t_all]]
        return set(zip(p_all[near].tolist(), t_all[near].tolist()))

    def found(b, radii, enabled=None):
        p, t = build_candidates(b, x, radii, 0.01, lambda k: k, enabled, grid)
        return set(zip(p.tolist(), t.tolist()))

    assert found(bundle, r) == brute(bundle, r) and grid.n_builds == 1
    assert found(bundle, r) == brute(bundle, r) and grid.n_builds == 1  # (kept)
    moved = bundle._replace(tri=bundle.tri + np.tile([0.0, 0.0, 0.05], 3),
                            shift=bundle.shift + [0.0, 0.0, 0.05])
    assert found(moved, r) == brute(moved, r) and grid.n_builds == 2
    big = r.copy()
    big[7] = 0.2  # (a larger particle: a longer reach)
    assert found(moved, big) == brute(moved, big) and grid.n_builds == 3
    assert found(moved, big, (True, False)) == brute(moved, big, (True, False))
    assert grid.n_builds == 4


def test_a_moving_mesh_is_searched_in_its_own_frame_and_binned_once():
    """A mesh that turns about a tilted axis and translates (and a fixed one beside
    it): after every move the candidates are the brute-force ones at the corners now
    (the particles carried into the moving mesh's frame as read), and its grid, like
    the fixed one's, was built once."""
    from demstep.engine.meshes import TriangleGrid, build_candidates, meshes_bundle
    from demstep.kernels.meshes import move_meshes, triangle_distances

    rng = np.random.default_rng(5)
    walls = [MeshWall(flat_mesh(n=8, size=1.0, z=0.0), name="blade",
                      velocity=[0.3, -0.1, 0.2], omega=[1.0, 2.0, 0.5],
                      center=[0.1, 0.0, 0.05]),
             MeshWall(flat_mesh(n=4, size=1.0, z=-0.4), name="floor")]
    b = meshes_bundle(walls, LinearSpring(k_n=1.0))
    x = rng.uniform(-0.8, 0.8, (3000, 3))
    r = np.full(3000, 0.02)
    grid = TriangleGrid()
    for step in range(6):
        n_tri = len(b.tri)
        p_all = np.repeat(np.arange(len(x)), n_tri)
        t_all = np.tile(np.arange(n_tri), len(x))
        near = triangle_distances(x, p_all, b.tri, t_all) < r[p_all] + 0.01
        # (pairs within 1e-12 of the limit may go either way by round-off)
        cand_p, cand_t = build_candidates(b, x, r, 0.01, lambda k: k, None, grid)
        got = set(zip(cand_p.tolist(), cand_t.tolist()))
        assert got == set(zip(p_all[near].tolist(), t_all[near].tolist()))
        assert np.all(np.diff(cand_p * n_tri + cand_t) > 0)
        for _ in range(40):
            move_meshes(b.tri, b.tri0, b.tri_mesh, b.motion, b.vel, b.omega, b.axis,
                        b.center, b.shift, b.turn, 0.01)
    assert b.turn[0] > 2.0 and grid.n_builds == 2


def test_a_sphere_dropped_on_a_conveyor_belt_rolls_off_at_two_sevenths_of_its_speed():
    """A fixed mesh with a surface velocity V (a belt): a sphere at rest on it is dragged
    by friction until its contact point moves with the belt; with the friction force
    the only horizontal force, m v = -F t and I w = r F t give v + r w = V at the end,
    so v = V / (1 + m r^2 / I) = 2/7 V (a solid sphere). The triangles stay in place,
    and the ledger counts the belt's work (the balance holds)."""
    belt = 0.5
    floor = flat_mesh()
    x = np.array([[-0.31, 0.17, R - 2e-5]])
    p = Particles.from_density(x, np.array([R]), DENSITY)
    mesh = MeshWall(floor, name="belt", surface_velocity=[belt, 0.0, 0.0])
    sim = Simulation(p, LAWS["linear"], meshes=[mesh], gravity=[0, 0, -9.81],
                     timestep=TimeStep.fixed(2e-5))
    tri0 = sim.meshes.tri.copy()
    sim.run(steps=10000)  # (sticking from t = 5/7 V / (mu g) = 0.12 s on)
    # then the tangential spring rings (period 2 pi sqrt(2/7 m / k_s), 430 steps):
    # the velocities averaged over five periods
    seen = []
    sim.every(1, lambda s: seen.append((s.v[0, 0], s.v[0, 0] - R * s.w[0, 1])))
    sim.run(steps=2150)
    v, contact = np.mean(seen, axis=0)
    assert np.array_equal(sim.meshes.tri, tri0)
    assert v == pytest.approx(2.0 / 7.0 * belt, rel=3e-3)
    # its contact point (v - R w_y, below the centre) moves with the belt
    assert contact == pytest.approx(belt, rel=3e-3)
    assert abs(sim.ledger.imbalance()) < 1e-3 * sim.ledger.scale()
    assert sim.ledger.acc[2] > 0.0  # (A_WALLS: the belt did work)


def test_rolling_resistance_on_a_rotating_drum_balances_the_ledger():
    """A sphere in a drum turning about a horizontal axis, with rolling and twisting
    resistance (springs, viscous part, friction limits): the couple the drum's rolling
    spring exerts does work as the drum turns (its power -M . omega is in the mesh's
    boundary work), so the ledger balances (without it, the imbalance would be the
    couple's work); the rolling history is carried from triangle to triangle and the
    mesh's torque includes the couple."""
    from demstep.mesh.shapes import cylinder

    law = LinearSpring(k_n=2e5, mu=0.5, restitution=0.5, rolling_convention="beta",
                       rolling_stiffness=0.8, twisting_stiffness=0.4, rolling_friction=0.05,
                       twisting_friction=0.05, rolling_damping=0.3)
    drum = cylinder(48, radius=0.3, height=0.4, caps=True, name="drum").flipped()
    x = np.array([[0.0, -0.3 * math.cos(math.pi / 48) + R - 1e-4, 0.2]])
    sim = Simulation(Particles.from_density(x, np.array([R]), DENSITY), law,
                     meshes=[MeshWall(drum, name="drum", omega=[0, 0, 3.0],
                                      center=[0, 0, 0.2])],
                     gravity=[0, -9.81, 0], timestep=TimeStep.fixed(2e-5))
    tris = set()
    rolled = 0.0
    for _ in range(40):
        sim.run(steps=500)
        rows = np.flatnonzero(sim.meshes.active == 1)
        tris.update(int(t) for t in sim.meshes.slot_tri[rows])
        rolled = max(rolled, float(np.abs(sim.meshes.roll[rows, :3]).max(initial=0.0)))
    assert len(tris) >= 3 and rolled > 0.0
    assert sim.ledger.acc[A_ROLLING] + sim.ledger.acc[A_ROLLING_VISCOUS] > 0.0
    # (measured: 3.2e-6 of the scale; the same drum without rolling resistance 4.4e-6;
    # without the couple's power in the drum's work, 0.036 of it)
    assert abs(sim.ledger.imbalance()) < 1e-4 * sim.ledger.scale()


def test_auto_step_refuses_rolling_resistance_on_meshes_in_one_line():
    from demstep.errors import InputError

    law = LinearSpring(k_n=2e5, mu=0.3, rolling_convention="beta", rolling_stiffness=0.5,
                       rolling_friction=0.1)
    x = np.array([[0.1, 0.1, R - 1e-5]])
    sim = Simulation(Particles.from_density(x, np.array([R]), DENSITY), law,
                     meshes=[MeshWall(flat_mesh(), name="floor")],
                     timestep=TimeStep.auto())
    with pytest.raises(InputError, match="rolling resistance on mesh walls is not followed"):
        sim.run(steps=1)




def test_mesh_contacts_carry_their_rolling_springs_into_the_certificate():
    """With rolling resistance, a sphere on a mesh floor and on a plane wall: the same
    rolling and twisting springs and viscous parts in the contact set (by the mesh's
    own law: a mesh twice as stiff gives twice k_r), and the same critical step."""
    law = LAWS["rolling"]
    mesh = sphere_on(flat_mesh(), law, v0=(0, 0, 0), w0=(0, 0, 0), gravity=0.0)
    wall = sphere_on("plane", law, v0=(0, 0, 0), w0=(0, 0, 0), gravity=0.0)
    for sim in (mesh, wall):
        sim.run(steps=1)
    a, b = mesh.contact_set(), wall.contact_set()
    assert a.n == b.n == 1 and a.k_r[0] > 0.0 and a.k_w[0] > 0.0 and a.c_r[0] > 0.0
    for name in ("k_n", "k_s", "k_r", "k_w", "c_r", "c_w"):
        assert getattr(a, name)[0] == pytest.approx(getattr(b, name)[0], rel=1e-12), name
    assert mesh.critical_dt() == pytest.approx(wall.critical_dt(), rel=1e-9)
    x = np.array([[-0.31, 0.17, R - 2e-5]])
    stiff = Simulation(Particles.from_density(x, np.array([R]), DENSITY), law,
                       meshes=[MeshWall(flat_mesh(), name="floor", material={"k_n": 4e5})],
                       timestep=TimeStep.fixed(1e-9))
    stiff.run(steps=1)
    assert stiff.contact_set().k_r[0] == pytest.approx(2.0 * a.k_r[0], rel=1e-9)


def test_the_threaded_mesh_loop_gives_the_serial_one():
    """A bed of spheres settling on a fine floor mesh (several triangles under each
    sphere), with rolling resistance and wear: the mesh contacts' loop threaded over
    runs of spheres gives every particle the same force, torque and motion as the
    serial loop, bit for bit (each sphere's contacts are summed in its own run, in the
    same order), the same wear (reduced in row order) and the same force on the mesh
    to round-off (its per-run sums are added after)."""
    import numba

    if numba.get_num_threads() < 2:
        pytest.skip("needs two numba threads")
    law = LAWS["rolling"]
    rng = np.random.default_rng(4)
    g = np.stack(np.meshgrid(np.arange(12), np.arange(12), np.arange(3), indexing="ij"),
                 -1).reshape(-1, 3) * 2.2 * R
    x = g + [-13 * R, -13 * R, 1.05 * R] + rng.normal(0, 0.02 * R, g.shape)

    def make(parallel):
        floor = flat_mesh(n=40, size=1.6)
        return Simulation(Particles.from_density(x, np.full(len(x), R), DENSITY), law,
                          meshes=[MeshWall(floor, name="floor", finnie_k=1e-6)],
                          gravity=[0, 0, -9.81], timestep=TimeStep.fixed(2e-5),
                          parallel=parallel)

    a, b = make(True), make(False)
    for sim in (a, b):
        sim.run(steps=1000)
    assert a.meshes.contacts[0] > 40 and a.meshes.wear.max() > 0.0  # (the bed lands)
    for name in ("x", "v", "w", "force", "torque"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(a.meshes.wear, b.meshes.wear)
    np.testing.assert_allclose(a.mesh_force, b.mesh_force, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.ledger.acc, b.ledger.acc, rtol=1e-12, atol=1e-15)


def test_a_turned_mesh_stopped_and_translated_keeps_its_pose():
    """A mesh turned about x, then its rotation stopped (omega 0) and a velocity given:
    its corners move on by v dt from where the turn left them (its axis is kept: the
    corners follow from the total turn about it; taking z for a zero omega would throw
    them to another pose)."""
    x = np.array([[5.0, 5.0, 5.0]])
    sim = Simulation(Particles.from_density(x, np.array([R]), DENSITY), LAWS["linear"],
                     meshes=[MeshWall(flat_mesh(n=2, size=1.0), name="lid", omega=[2.0, 0, 0])],
                     timestep=TimeStep.fixed(1e-3))
    sim.run(steps=300)
    turned = sim.meshes.tri.copy()
    assert np.abs(turned[:, 2::3]).max() > 0.1  # (it turned out of the plane z = 0)
    sim.set_mesh_motion(0, omega=[0.0, 0.0, 0.0], velocity=[0.1, 0.0, 0.0])
    sim.run(steps=10)
    expect = turned + np.tile([0.1 * 10 * 1e-3, 0.0, 0.0], 3)
    np.testing.assert_allclose(sim.meshes.tri, expect, rtol=0, atol=1e-12)


def test_rows_beyond_reach_since_the_build_are_skipped_with_the_same_result():
    """The mesh loop leaves out candidate rows that were farther at the lists' build
    than the sphere and the meshes have moved since: a bed settling on a fine mesh
    (a moving one, so the meshes' move counts too) gives bit for bit the motion, the
    tangential history and the wear of the same run with every row computed (the
    build's distances zeroed before each step), and most rows were skippable."""
    rng = np.random.default_rng(8)
    g = np.stack(np.meshgrid(np.arange(8), np.arange(8), np.arange(2), indexing="ij"),
                 -1).reshape(-1, 3) * 2.2 * R
    x = g + [-8 * R, -8 * R, 1.05 * R] + rng.normal(0, 0.02 * R, g.shape)

    def make():
        floor = flat_mesh(n=40, size=1.6)
        return Simulation(Particles.from_density(x, np.full(len(x), R), DENSITY),
                          LAWS["hertz"], gravity=[0, 0, -9.81], timestep=TimeStep.fixed(2e-5),
                          meshes=[MeshWall(floor, name="floor", finnie_k=1e-6,
                                           velocity=[0.01, 0.0, 0.0])])

    a, b = make(), make()
    skippable = []

    def every_row(sim):
        sim.meshes.cand_d[:] = 0.0

    b.every(1, every_row)
    for _ in range(10):
        a.run(steps=150)
        b.run(steps=150)
        m = a.meshes
        skippable.append(float(np.mean(m.cand_d > a.r[m.cand_p] + 1e-3 * R)))
    assert a.meshes.contacts[0] > 30 and max(skippable) > 0.3
    for name in ("x", "v", "w"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(a.meshes.shear, b.meshes.shear)
    assert np.array_equal(a.meshes.wear, b.meshes.wear)
