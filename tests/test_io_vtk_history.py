"""VTK frames (read back with meshio), .pvd series, and the CSV history writer."""

import math
import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest

from demstep.contact.laws import LinearSpring
from demstep.engine import Simulation, TimeStep
from demstep.io.history import HistoryWriter, history_columns, read_history
from demstep.io.vtk import VtkWriter, contact_lines, read_pvd, write_pvd
from demstep.packings import lattice
from demstep.particles import Particles
from demstep.walls import box_walls


def settling(dim):
    """A small lattice under gravity in a box: contacts form."""
    lat = lattice("hex" if dim == 2 else "fcc", radius=1.0)
    x = lat.block(3)
    x = x + 1.0
    p = Particles.from_density(x, np.ones(len(x)), 1.0)
    g = np.zeros(dim)
    g[-1] = -10.0
    lo = x.min(axis=0) - 1.0
    hi = x.max(axis=0) + 1.0
    walls = box_walls(lo, hi)
    sim = Simulation(p, LinearSpring(k_n=1e4, mu=0.3), walls=walls, gravity=g,
                     timestep=TimeStep.from_alpha(0.1))
    return sim


@pytest.mark.parametrize("dim", [2, 3])
def test_vtk_frames_read_back(tmp_path, dim):
    sim = settling(dim)
    writer = VtkWriter(tmp_path / "vtk")
    sim.every(200, writer)
    sim.run(steps=600)
    files = sorted(p.name for p in (tmp_path / "vtk").glob("*.vtu"))
    assert files == sorted(f"{s}_{k:010d}.vtu" for s in ("particles", "contacts", "walls")
                           for k in (200, 400, 600))
    mesh = meshio.read(tmp_path / "vtk" / "particles_0000000600.vtu")
    assert np.array_equal(mesh.points, sim.x)
    assert np.array_equal(mesh.point_data["radius"], sim.r)
    assert np.array_equal(mesh.point_data["velocity"], sim.v)
    assert np.array_equal(mesh.point_data["angular_velocity"], sim.w)
    assert np.array_equal(mesh.point_data["force"], sim.force)
    assert mesh.cells_dict["vertex"].shape == (len(sim.r), 1)
    # contact network: one line per touching pair, compression positive
    lines, f_n, _ = contact_lines(sim)
    assert len(lines) == sim.counters[0] > 0
    contacts = meshio.read(tmp_path / "vtk" / "contacts_0000000600.vtu")
    assert np.array_equal(contacts.cells_dict["line"], lines)
    assert np.array_equal(contacts.cell_data["normal_force"][0], f_n)
    assert (f_n > 0).all()
    # walls: quads in 3D, lines in 2D, on the wall planes
    walls = meshio.read(tmp_path / "vtk" / "walls_0000000600.vtu")
    kind = "quad" if dim == 3 else "line"
    cells = walls.cells_dict[kind]
    assert cells.shape == (2 * dim, 4 if dim == 3 else 2)
    for k in range(2 * dim):
        corners = walls.points[cells[k]]
        dist = (corners - sim.wall_point[k]) @ sim.wall_normal[k]
        assert np.allclose(dist, 0.0, atol=1e-9)
    assert np.array_equal(walls.cell_data["force"][0], sim.wall_force)
    # the series: three frames at their simulated times
    for series in ("particles", "contacts", "walls"):
        entries = read_pvd(tmp_path / "vtk" / f"{series}.pvd")
        assert [f for _, f in entries] == [f"{series}_{k:010d}.vtu" for k in (200, 400, 600)]
        assert entries[-1][0] == sim.time
        root = ET.parse(tmp_path / "vtk" / f"{series}.pvd").getroot()
        assert root.attrib["type"] == "Collection"


def test_vtk_frame_without_contacts_is_readable(tmp_path):
    p = Particles.from_density(np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]]), np.ones(2), 1.0)
    sim = Simulation(p, LinearSpring(k_n=1.0), timestep=TimeStep.fixed(0.01))
    sim.run(steps=3)
    VtkWriter(tmp_path).write(sim)
    mesh = meshio.read(tmp_path / "contacts_0000000003.vtu")
    assert mesh.cell_data["normal_force"][0].tolist() == [0.0]  # the placeholder line
    assert not (tmp_path / "walls.pvd").exists()  # no walls, no wall series


def test_vtk_resume_keeps_earlier_frames(tmp_path):
    write_pvd(tmp_path / "particles.pvd", [(0.1, "particles_0000000010.vtu"),
                                           (0.2, "particles_0000000020.vtu"),
                                           (0.3, "particles_0000000030.vtu")])
    writer = VtkWriter(tmp_path, resume_after_step=20)
    assert [f for _, f in writer.entries["particles"]] == ["particles_0000000010.vtu",
                                                           "particles_0000000020.vtu"]


@pytest.mark.parametrize("dim", [2, 3])
def test_history_rows_match_simulation(tmp_path, dim):
    sim = settling(dim)
    rows = []
    writer = HistoryWriter(tmp_path / "history.csv", sim, extra={"label": lambda s: 7})
    sim.every(100, writer)
    sim.every(100, lambda s: rows.append((s.step, s.time, s.ledger.as_dict(), s.wall_stress().copy(),
                                          s.wall_force.copy(), s.n_contacts)))
    sim.run(steps=500)
    writer.close()
    h = read_history(tmp_path / "history.csv")
    assert list(h) == history_columns(sim, {"label": None})
    assert h["step"].tolist() == [100, 200, 300, 400, 500]
    for k, (step, time, ledger, stress, force, nc) in enumerate(rows):
        assert h["time"][k] == time  # repr round trip: bit-identical
        assert h["dt"][k] == sim.dt and math.isnan(h["dt_estimate"][k])
        for key, value in ledger.items():
            assert h[key][k] == value
        assert h["n_contacts"][k] == nc
        for w, wall in enumerate(sim.walls):
            assert h[f"{wall.name}.stress"][k] == stress[w]
            assert h[f"{wall.name}.fx"][k] == force[w, 0]
        assert h["label"][k] == 7
    floor = sim.walls[2 * dim - 2]  # the bottom wall carries the weight
    weight = sim.m.sum() * 10.0
    assert h[f"{floor.name}.f{'xyz'[dim - 1]}"][-1] == pytest.approx(-weight, rel=0.2)
    assert "energy_error" in h


def test_history_resume_truncates_later_rows(tmp_path):
    sim = settling(2)
    path = tmp_path / "history.csv"
    with HistoryWriter(path, sim) as writer:
        sim.every(50, writer)
        sim.run(steps=300)
    with HistoryWriter(path, sim, resume_after_step=150):
        pass
    assert read_history(path)["step"].tolist() == [50, 100, 150]


def periodic_square(box=(8.0, 8.0)):
    """A square lattice of disks, slightly overlapping, periodic along x and y (lengths
    ``box``), with contacts across both boundaries, small random velocities."""
    nx, ny = int(round(box[0] / 2)), int(round(box[1] / 2))
    x = np.stack(np.meshgrid(np.arange(nx) * 2.0, np.arange(ny) * 2.0, indexing="ij"),
                 -1).reshape(-1, 2) + 0.5
    p = Particles.from_density(x, np.full(len(x), 1.002), 1.0)
    return Simulation(p, LinearSpring(k_n=1e4, mu=0.3), periodic=list(box),
                      timestep=TimeStep.fixed(1e-3),
                      velocities=np.random.default_rng(0).normal(0, 0.01, (len(x), 2)))


def test_vtk_particle_fields_and_contact_forces_in_a_periodic_box(tmp_path):
    """The particle fields read back equal the simulation's (mass, torque, fixed, id);
    the contact lines are the touching pairs found by brute force (none drawn across
    the box: each line joins two touching disks), and each line's force projected on
    its centre line is its (compressive) normal force."""
    sim = periodic_square()
    sim.run(steps=5)
    VtkWriter(tmp_path).write(sim)
    mesh = meshio.read(tmp_path / "particles_0000000005.vtu")
    for name, value in (("mass", sim.m), ("torque", sim.torque),
                        ("fixed", sim.fixed.astype(int)), ("id", np.arange(len(sim.r)))):
        np.testing.assert_array_equal(mesh.point_data[name], value)
    c = meshio.read(tmp_path / "contacts_0000000005.vtu")
    lines = c.cells_dict["line"]
    d = sim.x[lines[:, 1]] - sim.x[lines[:, 0]]
    dist = np.linalg.norm(d, axis=1)
    assert np.all(dist < sim.r[lines[:, 0]] + sim.r[lines[:, 1]])
    gaps = np.linalg.norm(sim.x[None] - sim.x[:, None], axis=2)
    touching = np.triu(gaps < sim.r[:, None] + sim.r[None], 1)
    assert len(lines) == touching.sum() > 0
    f_n = np.einsum("ck,ck->c", c.cell_data["force"][0], d / dist[:, None])
    np.testing.assert_allclose(f_n, c.cell_data["normal_force"][0], rtol=1e-12)
    assert (f_n > 0).all()


def test_history_periodic_box_and_love_stress_columns(tmp_path):
    """A periodic box of two different lengths: the history's box.Lx, box.Ly and
    love.xx, love.yy columns are the simulation's, row by row (a column written from
    another axis fails)."""
    sim = periodic_square((10.0, 8.0))
    writer = HistoryWriter(tmp_path / "h.csv", sim)
    sim.every(5, writer)
    rows = []
    sim.every(5, lambda s: rows.append((s.periodic_len.copy(), s.love_stress().copy())))
    sim.run(steps=10)
    writer.close()
    h = read_history(tmp_path / "h.csv")
    assert len(rows) == 2
    for k, (length, love) in enumerate(rows):
        assert h["box.Lx"][k] == length[0] == 10.0 and h["box.Ly"][k] == length[1] == 8.0
        assert h["love.xx"][k] == love[0] and h["love.yy"][k] == love[1]
        assert np.all(np.isfinite(love[:2])) and np.all(love[:2] != 0) and love[0] != love[1]


def test_history_wall_position_columns():
    """The walls' position columns are the walls' points (not their velocities)."""
    import tempfile

    sim = settling(2)
    with tempfile.TemporaryDirectory() as folder:
        writer = HistoryWriter(f"{folder}/h.csv", sim)
        sim.every(50, writer)
        sim.run(steps=100)
        writer.close()
        h = read_history(f"{folder}/h.csv")
    for k, wall in enumerate(sim.walls):
        assert h[f"{wall.name}.x"][-1] == sim.wall_point[k, 0]
        assert h[f"{wall.name}.y"][-1] == sim.wall_point[k, 1]


def test_a_run_that_starts_empty_draws_its_walls_across_the_walls_alone(tmp_path):
    """No particles at the start (insertion fills the run later): the VTK frame of
    step 0 is written, its floor drawn as a quad of non-zero area (the extent comes
    from the walls when there is nothing else; it failed on an empty reduction)."""
    import meshio

    from demstep.case import case_from_dict
    from demstep.runner import run_case

    data = {"name": "empty", "gravity": [0.0, 0.0, -9.81],
            "particles": {"generator": "none"},
            "box": {"lower": [-0.1, -0.1, -0.1], "upper": [0.1, 0.1, 0.1]},
            "contact": {"law": "linear", "k_n": 1000.0},
            "walls": [{"name": "floor", "point": [0.0, 0.0, -0.1], "normal": [0.0, 0.0, 1.0]}],
            "insert": [{"name": "in", "region": {"shape": "box", "lower": [-0.05, -0.05, 0.0],
                                                  "upper": [0.05, 0.05, 0.05]},
                        "radius": 0.005, "density": 2500.0, "rate": 1000.0, "every": 100,
                        "start": 0.001}],
            "timestep": {"dt": 1e-5}, "stages": [{"name": "a", "steps": 200}],
            "output": {"history_every": 100, "vtk_every": 100}}
    run_case(case_from_dict(data, base_dir=tmp_path), tmp_path / "out", quiet=True)
    walls = meshio.read(tmp_path / "out" / "vtk" / "walls_0000000000.vtu")
    quads = walls.points[walls.cells[0].data]  # (the box's six walls and the floor)
    assert len(quads) == 7
    areas = np.linalg.norm(np.cross(quads[:, 1] - quads[:, 0], quads[:, 3] - quads[:, 0]), axis=1)
    assert np.all(areas > 0.0)
    assert any(np.allclose(q[:, 2], -0.1) for q in quads)
