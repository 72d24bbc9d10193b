"""Spatial order of particles: rows of cells, the locality the order buys, and
``demstep run`` on a particle file in random order (reordered internally, named by the
file's rows everywhere)."""

import numpy as np
import pytest

import demstep.case.build as case_build
from demstep.case import build_simulation, load_case
from demstep.timestep.contacts import find_contacts
from demstep.errors import InputError
from demstep.io.formats import write_csv
from demstep.io.vtk import particle_mesh
from demstep.packings import lattice, spatial_order
from demstep.particles import Particles


@pytest.mark.parametrize("dim", [2, 3])
def test_spatial_order_is_rows_of_cells_x_fastest(dim):
    """Cells of side ``cell`` in rows: z (2D: y) slowest, x fastest; the given order
    kept within a cell."""
    rng = np.random.default_rng(dim)
    x = rng.uniform(0.0, 10.0, (500, dim))
    x[0] = 0.0  # the corner cell starts at the origin
    order = spatial_order(x, 2.0)
    cells = np.floor(x[order] / 2.0).astype(int)
    keys = sum(cells[:, k] * 10**k for k in range(dim))  # row-major, x fastest
    assert (np.diff(keys) >= 0).all()
    same = np.diff(keys) == 0
    assert (np.diff(order)[same] > 0).all()  # stable within a cell


def test_spatial_order_brings_contacts_close_in_memory():
    x = lattice("fcc", 0.5).block(10)
    r = np.full(len(x), 0.5 * 1.001)
    shuffled = np.random.default_rng(3).permutation(len(x))
    xs = x[shuffled]
    order = spatial_order(xs, 2.0 * r.max())
    np.testing.assert_array_equal(np.sort(order), np.arange(len(x)))  # a permutation

    def median_gap(xx):
        c = find_contacts(Particles.from_density(xx, r, 1.0), 1.0)
        return np.median(np.abs(c.i - c.j))

    assert median_gap(xs[order]) < median_gap(xs) / 20
    # stable within a cell: one big cell keeps the given order
    np.testing.assert_array_equal(spatial_order(xs, 1e9), np.arange(len(x)))
    with pytest.raises(InputError, match="cell"):
        spatial_order(xs, 0.0)


CASE = """
name = "shuffled"
[particles]
generator = "file"
path = "{path}"
density = 2500.0
[particles.fixed]
indices = [{fixed}]
[contact]
law = "linear"
k_n = 1.0e5
mu = 0.5
[box]
margin = 0.0
[timestep]
alpha = 0.1
{bonds}
[[stages]]
name = "squeeze"
steps = 40
[stages.walls."z+"]
motion = "velocity"
velocity = [0.0, 0.0, -0.05]
"""


def shuffled_packing(n_side=8):
    x = lattice("fcc", 0.5).block(n_side)
    rng = np.random.default_rng(7)
    x = x[rng.permutation(len(x))] + rng.normal(0.0, 1e-4, x.shape)
    return x, np.full(len(x), 0.5 * 1.001)


def make_case(tmp_path, x, r, fixed=(3, 900), bonds=""):
    write_csv(tmp_path / "spheres.csv", x, r)
    text = CASE.format(path="spheres.csv", fixed=", ".join(map(str, fixed)), bonds=bonds)
    (tmp_path / "case.toml").write_text(text)
    return load_case(tmp_path / "case.toml")


def test_a_file_in_random_order_runs_reordered_and_named_by_its_rows(tmp_path, monkeypatch):
    x, r = shuffled_packing()
    assert len(x) >= case_build.SPATIAL_ORDER_MIN
    case = make_case(tmp_path, x, r)
    sim = build_simulation(case)
    src = sim.source_index
    assert src is not None and sorted(src) == list(range(len(x)))
    np.testing.assert_array_equal(sim.x, x[src])  # particle k is the file's row src[k]
    assert set(src[sim.fixed]) == {3, 900}  # fixed by the file's rows
    # a restart rebuilds the case and loads its checkpoint: the same order every time
    np.testing.assert_array_equal(build_simulation(case).source_index, src)
    np.testing.assert_array_equal(particle_mesh(sim).point_data["id"], src)
    # the same run without reordering: the same motion, particle by particle
    monkeypatch.setattr(case_build, "SPATIAL_ORDER_MIN", 10**9)
    plain = build_simulation(case)
    assert plain.source_index is None and plain.sort_every == 1000  # (the case's default)
    plain.ordering.every = None  # (nor sorted by the engine at its first build)
    np.testing.assert_array_equal(particle_mesh(plain).point_data["id"], np.arange(len(x)))
    sim.run(steps=60)
    assert sim.ordering.n_sorts == 0  # the file's order, sorted by the case already
    with pytest.warns(RuntimeWarning, match="random order"):  # the engine notices
        plain.run(steps=60)
    moved = np.abs(plain.x - x).max()
    assert moved > 1e-6  # something happened
    np.testing.assert_allclose(sim.x, plain.x[src], rtol=0, atol=1e-9 * moved)
    np.testing.assert_allclose(sim.v, plain.v[src], rtol=0,
                               atol=1e-9 * np.abs(plain.v).max())


def test_messages_and_bond_files_name_the_files_rows(tmp_path):
    x, r = shuffled_packing()
    x[1000] = x[5]  # coincident with row 5
    case = make_case(tmp_path, x, r)
    with pytest.raises(InputError) as err:
        build_simulation(case)
    message = str(err.value)
    assert "coincident" in message and " 5 " in message + " " and "1000" in message

    x, r = shuffled_packing()
    rows = (10, int(np.argmin(np.linalg.norm(x - x[10], axis=1) + 1e9 * (np.arange(len(x)) == 10))))
    (tmp_path / "bonds.csv").write_text(f"i,j\n{rows[0]},{rows[1]}\n")
    bonds = ('[bonds]\nnormal_stiffness = 1.0e6\ngap = 0.01\nfile = "bonds.csv"\n'
             'stage = 1')
    case = make_case(tmp_path, x, r, bonds=bonds)
    from demstep.case.stages import create_bonds

    sim = build_simulation(case)
    create_bonds(sim, case)
    assert sim.bonds.n == 1
    assert {sim.particle_id(sim.bonds.i[0]), sim.particle_id(sim.bonds.j[0])} == set(rows)
    (tmp_path / "bonds.csv").write_text(f"i,j\n{rows[0]},{len(x)}\n")
    with pytest.raises(InputError, match=f"particle index {len(x)} outside"):
        create_bonds(build_simulation(case), case)


def test_dt_of_a_reordered_case_reports_the_files_rows(tmp_path, capsys):
    """`demstep dt CASE` on a file the run reorders: the particles and contacts of the
    danger report are the file's rows (radii differ per particle, so a wrong mapping
    shows), and its VTK ids likewise."""
    import json

    import meshio

    from demstep.cli import main

    x, _ = shuffled_packing()
    r = 0.5 * 1.001 * (1.0 + 0.02 * np.random.default_rng(9).random(len(x)))
    x = x * (1.0 + 0.021)  # spacing for the largest radii: contacts by the tolerance
    case = make_case(tmp_path, x, r)
    assert build_simulation(case).source_index is not None
    vtk = tmp_path / "mode.vtu"
    code = main(["dt", str(tmp_path / "case.toml"), "--methods", "exact", "--json",
                 "--contact-tol", "0.05", "--top", "5", "--mode-vtk", str(vtk)])
    out = json.loads(capsys.readouterr().out)
    assert code in (0, None)
    particles = out["critical_mode"]["particles"]
    assert particles
    for q in particles:
        assert q["radius"] == pytest.approx(r[q["index"]], rel=1e-12)
    for c in out["critical_mode"]["contacts"]:
        if c["j"] is not None:  # the two rows touch (within the tolerance)
            gap = np.linalg.norm(x[c["i"]] - x[c["j"]]) - r[c["i"]] - r[c["j"]]
            assert gap <= 0.05 * min(r[c["i"]], r[c["j"]])
    mesh = meshio.read(vtk)
    ids = mesh.point_data["id"]
    np.testing.assert_allclose(mesh.point_data["radius"], r[ids], rtol=1e-12)


def test_a_simulation_of_particles_in_random_order_warns_once(recwarn):
    from demstep.engine import Simulation

    x, r = shuffled_packing()
    sim = Simulation(Particles.from_density(x, r, 2500.0))
    sim.run(steps=3)
    sim.run(steps=3)
    warned = [w for w in recwarn if "random order" in str(w.message)]
    assert len(warned) == 1
    recwarn.clear()
    order = spatial_order(x, 2.0 * r.max())
    Simulation(Particles.from_density(x[order], r, 2500.0)).run(steps=3)
    assert not [w for w in recwarn if "random order" in str(w.message)]


def test_dt_of_a_file_in_random_order_is_solved_reordered_and_reports_its_rows(tmp_path,
                                                                               capsys):
    """`demstep dt FILE` renumbers a file's particles in spatial order after reading and
    checking them: the step is the same as in the file's order (the dense reference on
    the file's numbering, within the certificate's margin), and the reports and the
    mode VTK name the file's rows (radii differ per particle)."""
    import json

    import meshio

    import demstep.analysis_input as ti
    from demstep.cli import main

    x, _ = shuffled_packing()
    r = 0.5 * 1.001 * (1.0 + 0.02 * np.random.default_rng(4).random(len(x)))
    x = x * 1.021
    write_csv(tmp_path / "spheres.csv", x, r)
    argv = ["dt", str(tmp_path / "spheres.csv"), "--methods", "exact", "--json",
            "--kn", "1e5", "--density", "2500", "--contact-tol", "0.05", "--top", "5"]
    vtk = tmp_path / "mode.vtu"
    assert main(argv + ["--mode-vtk", str(vtk)]) in (0, None)
    out = json.loads(capsys.readouterr().out)
    for q in out["critical_mode"]["particles"]:
        assert q["radius"] == pytest.approx(r[q["index"]], rel=1e-12)
    mesh = meshio.read(vtk)
    np.testing.assert_allclose(mesh.point_data["radius"], r[mesh.point_data["id"]],
                               rtol=1e-12)
    reordered = ti.from_file(tmp_path / "spheres.csv", ti.ContactModel(parameters={"k_n": 1e5, "k_s": 1e5}),
                             density=2500.0, contact_tol=0.05)
    assert reordered.ids is not None
    original = ti.from_particles(Particles.from_density(x, r, 2500.0),
                                 ti.ContactModel(parameters={"k_n": 1e5, "k_s": 1e5}), None, None, (), 0.05)
    assert original.contacts.n == reordered.contacts.n
    np.testing.assert_array_equal(reordered.particles.r, r[reordered.ids])
    from demstep.timestep.exact import exact_critical_step

    dt_a = exact_critical_step(reordered.particles, reordered.contacts, True).dt
    dt_b = exact_critical_step(original.particles, original.contacts, True).dt
    assert dt_a == pytest.approx(dt_b, rel=1e-8)
    dt_json = [m["dt"] for m in out["estimates"] if m["method"] == "exact"]
    assert dt_json and dt_json[0] == pytest.approx(dt_b, rel=1e-8)


# ----------------------------------------------------------- re-sorting during a run
def _mixed_box(timestep=None, sort_every=None, seed=7, gravity=(0, 0, -9.81)):
    """216 spheres thrown about in a box: friction, dashpots, rolling and twisting
    resistance, walls and parallel bonds (some breaking), all with history."""
    from demstep.contact.bonds import ParallelBonds
    from demstep.contact.laws import LinearSpring
    from demstep.engine import Simulation, TimeStep
    from demstep.walls import box_walls

    rng = np.random.default_rng(seed)
    grid = np.stack(np.meshgrid(*[np.arange(6) * 1.0] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = grid * 1.02 + 0.6 + rng.uniform(-0.03, 0.03, grid.shape)
    r = rng.uniform(0.45, 0.52, len(x))
    law = LinearSpring(k_n=1e5, mu=0.5, restitution=0.6, rolling_convention="epsd",
                       rolling_friction=0.05, twisting_friction=0.05, rolling_damping=0.3)
    sim = Simulation(Particles.from_density(x, r, 1000.0), law,
                     walls=box_walls(np.zeros(3), np.full(3, 7.0)), gravity=list(gravity),
                     velocities=rng.normal(0, 0.3, x.shape), sort_every=sort_every,
                     timestep=timestep or TimeStep.fixed(2e-4))
    sim.add_bonds(ParallelBonds(1e5, tensile_strength=2e3, shear_strength=2e3, gap=0.06))
    return sim


def _shuffled_box(sort_every=None, seed=3, **kw):
    """:func:`_mixed_box` as if built from particles in a random order."""
    sim = _mixed_box(sort_every=sort_every, **kw)
    sim.reorder(np.random.default_rng(seed).permutation(len(sim.r)))
    sim.source_index = None
    return sim


def test_a_renumbered_simulation_runs_on_as_the_original():
    """reorder() by a random permutation mid-run (about half the pairs and bonds swap
    their ends): the run goes on as the unrenumbered one, particle by particle, to
    rounding (the forces are summed in another order). Without the sign changes of the
    history on j (tangential spring, rolling moments, bond shear and bending) the
    positions differ by 1e-5 to 3e-2 here (measured), with friction, rolling and bonds
    each."""
    a, b = _mixed_box(), _mixed_box()
    a.run(steps=400)
    b.run(steps=400)
    assert a.n_contacts > 30 and (a.bonds.intact == 1).sum() > 50 and len(a.wp) > 5
    order = np.random.default_rng(1).permutation(len(a.r))
    b.reorder(order)
    inv = np.argsort(order)
    np.testing.assert_array_equal(b.source_index, order)
    assert (b.pi < b.pj).all() and (b.bonds.i < b.bonds.j).all()
    assert (np.diff(b.pi * len(b.r) + b.pj) > 0).all()  # sorted by (i, j) again
    keys_a = {(int(inv[i]), int(inv[j])): s for i, j, s in zip(a.pi, a.pj, a.pairs.shear)}
    for i, j, s in zip(b.pi, b.pj, b.pairs.shear):  # the same spring, on j either way
        s_a = keys_a.get((int(i), int(j)))
        s_a = -keys_a[(int(j), int(i))] if s_a is None else s_a
        np.testing.assert_array_equal(s, s_a)
    a.run(steps=600)
    b.run(steps=600)
    assert (a.bonds.intact == 1).sum() < 50  # bonds broke after the renumbering
    np.testing.assert_allclose(b.x, a.x[order], rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.w, a.w[order], rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.ledger.acc, a.ledger.acc, rtol=1e-10, atol=1e-12)
    assert (b.bonds.intact == 1).sum() == (a.bonds.intact == 1).sum()


def test_reorder_rejects_what_is_not_a_permutation():
    sim = _mixed_box()
    n = len(sim.r)
    for bad in (np.zeros(n, dtype=int), np.arange(n - 1), np.arange(n) * 1.0):
        with pytest.raises(InputError, match="order: expected a permutation"):
            sim.reorder(bad)
    with pytest.raises(InputError, match="sort_every"):
        _mixed_box(sort_every=0)


def test_sorting_during_a_run_keeps_neighbours_close_and_the_run_unchanged():
    """sort_every: particles given in random order are sorted at the first build (the
    pairs close in memory); scrambled again mid-run, at the first rebuild ``sort_every``
    steps after the last sort. A sort that would not bring the pairs closer is not
    done. The run is the unsorted one's to rounding, each particle named by its input
    row in ``source_index``."""
    scramble = np.random.default_rng(5).permutation(216)

    def by_row(sim, a):
        out = np.empty_like(a)
        out[sim.source_index] = a
        return out

    def spread(sim):
        return np.median(sim.pj - sim.pi)

    plain, sorted_ = _shuffled_box(None), _shuffled_box(50)
    plain.run(steps=300)
    sorted_.run(steps=300)
    # sorted at the first build; looked at again at a later rebuild: nothing to gain
    assert sorted_.ordering.n_sorts == 1 and sorted_.ordering.last_sort > 0
    tidy = spread(sorted_)
    assert tidy < 0.25 * spread(plain)
    for sim in (plain, sorted_):
        sim.reorder(scramble)
    assert spread(sorted_) > 4 * tidy
    rebuilds = sorted_.lists.n_rebuilds
    sorted_.run(steps=300)
    plain.run(steps=300)
    assert sorted_.lists.n_rebuilds > rebuilds and sorted_.ordering.n_sorts == 2
    assert spread(sorted_) < 0.25 * spread(plain)
    np.testing.assert_array_equal(np.sort(sorted_.source_index), np.arange(216))
    np.testing.assert_allclose(by_row(sorted_, sorted_.x), by_row(plain, plain.x), rtol=0,
                               atol=1e-12)
    np.testing.assert_allclose(sorted_.ledger.acc, plain.ledger.acc, rtol=1e-10, atol=1e-12)


def test_a_checkpoint_of_a_sorted_run_restarts_bit_for_bit(tmp_path):
    """The checkpoint holds the order its arrays are in: a Simulation built afresh (in
    the input order) takes that order when it loads it and continues exactly as the
    unbroken run (its later sorts at the same steps)."""
    from demstep.io.checkpoint import load_checkpoint, save_checkpoint

    whole = _shuffled_box(sort_every=100)
    whole.run(steps=700)
    part = _shuffled_box(sort_every=100)
    part.run(steps=350)
    assert part.ordering.n_sorts >= 1 and not np.array_equal(part.source_index, np.arange(216))
    path = save_checkpoint(part, tmp_path / "c.npz")
    fresh = _shuffled_box(sort_every=100)  # (built in the input order again)
    load_checkpoint(fresh, path)
    np.testing.assert_array_equal(fresh.source_index, part.source_index)
    fresh.run(steps=350)
    np.testing.assert_array_equal(fresh.source_index, whole.source_index)
    np.testing.assert_array_equal(fresh.x, whole.x)
    np.testing.assert_array_equal(fresh.pairs.shear, whole.pairs.shear)


def test_the_auto_step_certificate_follows_a_renumbering():
    """'auto' with the exact method: after a renumbering every closed contact is still
    covered, the certificate's drift term is the same number, and the run goes on as
    the unrenumbered one (the same estimates)."""
    from demstep.engine import TimeStep

    ts = lambda: TimeStep.auto(safety=0.8, method="exact", every=100)  # noqa: E731
    a, b = (_mixed_box(timestep=ts(), gravity=(0, 0, 0)) for _ in range(2))
    a.run(steps=250)
    b.run(steps=250)
    drift = b.auto.drift(b.auto.certificate)
    assert drift[0] > 0
    order = np.random.default_rng(2).permutation(len(b.r))
    b.reorder(order)
    assert b.auto.contacts_covered()
    assert b.auto.drift(b.auto.certificate) == pytest.approx(drift, rel=1e-12)
    np.testing.assert_array_equal(b.auto.mode.reshape(len(b.r), -1),
                                  a.auto.mode.reshape(len(a.r), -1)[order])
    a.run(steps=300)
    b.run(steps=300)
    assert b.dt == pytest.approx(a.dt, rel=1e-9)
    # (rounding: the estimates' sums run in another order too, and steps at 0.8 of the
    # critical one amplify it; a history sign left unchanged moves particles by 1e-5)
    np.testing.assert_allclose(b.x, a.x[order], rtol=0, atol=1e-9)


def test_clumps_follow_a_renumbering():
    """Clumps' members are renumbered with the spheres: a run of clumps and free spheres
    goes on as the unrenumbered one."""
    from demstep.clumps import ClumpTemplate, place, random_quaternions
    from demstep.contact.laws import LinearSpring
    from demstep.engine import Simulation, TimeStep
    from demstep.walls import box_walls

    template = ClumpTemplate("t", np.array([[0, 0, 0], [0.9, 0, 0], [0, 0.7, 0]]),
                             np.array([0.5, 0.4, 0.35]))

    def make():
        rng = np.random.default_rng(11)
        pos = np.stack(np.meshgrid(*[np.arange(3) * 3.0] * 3, indexing="ij"), -1).reshape(-1, 3)
        cs = place([template], [0] * len(pos), pos + 1.5, random_quaternions(len(pos), rng), 1.0)
        free = Particles.from_density(rng.uniform(0.6, 9.0, (20, 3)) * [1, 1, 0] + [0, 0, 9.2],
                                      np.full(20, 0.3), 1.0)
        return Simulation(free, LinearSpring(k_n=1e4, mu=0.4, restitution=0.5),
                          walls=box_walls(np.zeros(3), np.full(3, 10.0)), gravity=[0, 0, -9.81],
                          clumps=cs, timestep=TimeStep.fixed(5e-4))

    a, b = make(), make()
    a.run(steps=2000)
    b.run(steps=2000)
    order = np.random.default_rng(4).permutation(len(a.r))
    b.reorder(order)
    np.testing.assert_array_equal(b.x[b.bodies.member], a.x[a.bodies.member])
    a.run(steps=2500)
    b.run(steps=2500)
    closed = a.contact_set()
    assert closed.n > 30 and (closed.j >= 0).sum() > 5  # (on the floor, touching)
    # (to rounding: 2500 steps of collisions grow the other order's last bits to 1e-12)
    np.testing.assert_allclose(b.bodies.x, a.bodies.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.x, a.x[order], rtol=0, atol=1e-9)


def test_a_renumbered_periodic_2d_simulation_runs_on_as_the_original():
    """Disks in a box periodic along x (pairs across the boundary), floor and roof
    walls, friction and rolling resistance: a random renumbering mid-run changes
    nothing but the numbering."""
    from demstep.contact.laws import LinearSpring
    from demstep.engine import Simulation, TimeStep
    from demstep.walls import box_walls

    def make():
        rng = np.random.default_rng(2)
        grid = np.stack(np.meshgrid(np.arange(16) * 1.0, np.arange(15) * 1.02, indexing="ij"),
                        -1).reshape(-1, 2)  # (16 columns fill the periodic length)
        x = grid + 0.5 + rng.uniform(-0.03, 0.03, grid.shape)
        law = LinearSpring(k_n=1e5, mu=0.5, restitution=0.6, rolling_convention="epsd",
                           rolling_friction=0.05, rolling_damping=0.3)
        walls = [w for w in box_walls(np.zeros(2), np.full(2, 16.0)) if w.normal[1] != 0]
        return Simulation(Particles.from_density(x, rng.uniform(0.45, 0.52, len(x)), 1000.0),
                          law, walls=walls, gravity=[0, -9.81], periodic=[16.0, None],
                          velocities=rng.normal(0, 0.3, x.shape), timestep=TimeStep.fixed(2e-4))

    a, b = make(), make()
    a.run(steps=400)
    b.run(steps=400)
    order = np.random.default_rng(1).permutation(len(a.r))
    b.reorder(order)
    a.run(steps=800)
    b.run(steps=800)
    assert a.n_contacts > 100
    across = np.abs(a.x[a.pj, 0] - a.x[a.pi, 0]) > 8.0  # pairs through the periodic side
    assert across.any()
    np.testing.assert_allclose(b.x, a.x[order], rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.w, a.w[order], rtol=0, atol=1e-12)


def test_inverse_order_names_each_old_particle_by_its_new_index():
    from demstep.packings import inverse_order

    order = np.random.default_rng(3).permutation(57)
    inverse = inverse_order(order)
    assert np.array_equal(inverse[order], np.arange(57))
    assert np.array_equal(order[inverse], np.arange(57))
    assert inverse_order(np.zeros(0, dtype=np.int64)).shape == (0,)
