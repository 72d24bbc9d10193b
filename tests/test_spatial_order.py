"""Spatial order of particles: rows of cells, the locality the order buys, and
``demstep run`` on a particle file in random order (reordered internally, named by the
file's rows everywhere)."""

import numpy as np
import pytest

import demstep.case.build as case_build
from demstep.case import build_simulation, load_case
from demstep.contacts import find_contacts
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
    assert plain.source_index is None
    np.testing.assert_array_equal(particle_mesh(plain).point_data["id"], np.arange(len(x)))
    sim.run(steps=60)
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

    import demstep.timestep_input as ti
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
    reordered = ti.from_file(tmp_path / "spheres.csv", ti.ContactModel(k_n=1e5, k_t=1e5),
                             density=2500.0, contact_tol=0.05)
    assert reordered.ids is not None
    original = ti.from_particles(Particles.from_density(x, r, 2500.0),
                                 ti.ContactModel(k_n=1e5, k_t=1e5), None, None, (), 0.05)
    assert original.contacts.n == reordered.contacts.n
    np.testing.assert_array_equal(reordered.particles.r, r[reordered.ids])
    from demstep.timestep.exact import exact_critical_step

    dt_a = exact_critical_step(reordered.particles, reordered.contacts, True).dt
    dt_b = exact_critical_step(original.particles, original.contacts, True).dt
    assert dt_a == pytest.approx(dt_b, rel=1e-8)
    dt_json = [m["dt"] for m in out["estimates"] if m["method"] == "exact"]
    assert dt_json and dt_json[0] == pytest.approx(dt_b, rel=1e-8)
