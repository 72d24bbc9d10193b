"""Mesh walls in case files: [[meshes]] read with their transforms, material and
motion; their force, torque and contacts in history.csv; their triangles and the force
on each in the VTK output; stage changes of their motion; bad mesh input refused in one
line before anything is written."""

import subprocess
import sys

import meshio
import numpy as np
import pytest
import tomli_w

from demstep.case import build_simulation, case_from_dict
from demstep.case.stages import apply_stage
from demstep.errors import InputError
from demstep.io.history import read_history
from demstep.mesh.shapes import plane
from demstep.runner import run_case

R, DENSITY, G = 0.001, 2500.0, 9.81


def write_floor(path, n=4):
    """A unit square of 2 n^2 triangles in z = 0 centred on the origin, as ASCII STL."""
    m = plane(n, size=1.0)
    meshio.write_points_cells(str(path), np.asarray(m.vertices, float),
                              [("triangle", np.asarray(m.triangles))], file_format="stl")
    return path


def tray_case(tmp_path, **mesh):
    """3 x 3 x 2 beads over a 20 mm square floor at z = 1 mm read from an STL file of a
    unit square (scaled and moved on load), side walls as planes."""
    write_floor(tmp_path / "floor.stl")
    spec = {"name": "floor", "file": "floor.stl",
            "transforms": "scale 0.02 move 0 0 0.001"}
    spec.update(mesh)
    return {
        "name": "tray", "gravity": [0.0, 0.0, -G],
        "particles": {"generator": "grid", "count": [3, 3, 2], "spacing": 0.0025,
                      "origin": [-0.00375, -0.00375, 0.0025], "radius_min": R,
                      "radius_max": R, "density": DENSITY},
        "contact": {"law": "linear", "k_n": 2e3, "mu": 0.3, "restitution": 0.6},
        "walls": [{"name": f"side{k}", "point": p, "normal": n} for k, (p, n) in enumerate([
            ([-0.0055, 0, 0], [1, 0, 0]), ([0.0055, 0, 0], [-1, 0, 0]),
            ([0, -0.0055, 0], [0, 1, 0]), ([0, 0.0055, 0], [0, -1, 0])])],
        "meshes": [spec],
        "timestep": {"dt": 2e-5},
        "stages": [{"name": "settle", "duration": 0.15, "damping": {"local": 0.3}}],
        "output": {"history_every": 500, "vtk_every": 2500},
    }


def test_beads_settle_on_a_mesh_floor_read_from_a_case_file(tmp_path):
    """The floor's force in history.csv is the beads' weight at rest (the side walls
    are frictionless planes: they carry none of it), its torque about its centre
    (0.01, 0, 0) that of the weights about it, every bottom bead touches it; the VTK frame
    holds the floor where the transforms put it, and its per-triangle forces add up to
    the force in the history."""
    data = tray_case(tmp_path)
    data["contact"]["mu_wall"] = 0.0
    data["meshes"][0].update(friction=0.3, center=[0.01, 0.0, 0.0])
    case = case_from_dict(data, base_dir=tmp_path)
    out = tmp_path / "out"
    run_case(case, out, quiet=True)
    h = read_history(out / "history.csv")
    sim = build_simulation(case)
    weight = float(sim.m.sum()) * G
    np.testing.assert_allclose(h["floor.fz"][-1], -weight, rtol=1e-3)
    assert abs(h["floor.fx"][-1]) < 1e-3 * weight and abs(h["floor.fy"][-1]) < 1e-3 * weight
    # the moment of the weights about the floor's centre c = (0.01, 0, 0): the beads
    # rest on z = 0 symmetric about the origin, sum (x_i - c) x (0, 0, -m_i g)
    np.testing.assert_allclose(h["floor.ty"][-1], -0.01 * weight, rtol=2e-3)
    assert abs(h["floor.tx"][-1]) < 1e-3 * 0.01 * weight
    assert h["floor.contacts"][-1] == 9
    assert h["n_contacts"][-1] >= 9
    frames = sorted((out / "vtk").glob("meshes_*.vtu"))
    assert frames and (out / "vtk" / "meshes.pvd").exists()
    last = meshio.read(frames[-1])
    pts = last.points
    np.testing.assert_allclose(pts.min(axis=0), [-0.01, -0.01, 0.001], atol=1e-12)
    np.testing.assert_allclose(pts.max(axis=0), [0.01, 0.01, 0.001], atol=1e-12)
    assert len(last.cells_dict["triangle"]) == 32
    force = last.cell_data["force"][0]
    assert np.count_nonzero(np.abs(force[:, 2]) > 0) >= 3  # spread over several triangles
    row = np.flatnonzero(h["step"] == int(frames[-1].stem.split("_")[1]))[0]
    np.testing.assert_allclose(force.sum(axis=0), [h["floor.fx"][row], h["floor.fy"][row],
                                                   h["floor.fz"][row]], rtol=1e-12, atol=1e-15)
    area = 0.02 * 0.02 / 32
    np.testing.assert_allclose(last.cell_data["pressure"][0], force[:, 2] / area, rtol=1e-9)


def test_a_stage_moves_a_mesh_and_a_turned_mesh_keeps_its_axis(tmp_path):
    """``[stages.meshes."lid"]`` sets a velocity from the second stage on: the lid's
    corners in the last frame are shifted by v times the second stage's duration only.
    A stage that turns a mesh about another axis than before is refused by the case
    check, naming the key."""
    data = tray_case(tmp_path)
    write_floor(tmp_path / "lid.stl")
    data["meshes"].append({"name": "lid", "file": "lid.stl",
                           "transforms": "scale 0.02 move 0 0 0.02"})
    data["stages"] = [{"name": "rest", "duration": 0.01},
                      {"name": "lift", "duration": 0.02,
                       "meshes": {"lid": {"velocity": [0.0, 0.0, 0.5]}}}]
    data["output"] = {"history_every": 100, "vtk_every": 1500}
    out = tmp_path / "out"
    run_case(case_from_dict(data, base_dir=tmp_path), out, quiet=True)
    last = meshio.read(sorted((out / "vtk").glob("meshes_*.vtu"))[-1])
    lid = last.points[np.repeat(last.cell_data["mesh_id"][0], 3) == 1]
    np.testing.assert_allclose(lid[:, 2], 0.02 + 0.5 * 0.02, rtol=1e-9)
    floor = last.points[np.repeat(last.cell_data["mesh_id"][0], 3) == 0]
    np.testing.assert_array_equal(floor[:, 2], 0.001)

    data["meshes"][1]["omega"] = [0.0, 0.0, 1.0]
    data["stages"][1]["meshes"] = {"lid": {"omega": [1.0, 0.0, 0.0]}}
    with pytest.raises(InputError, match=r'stages\[1\]\.meshes\."lid"\.omega: a mesh keeps'):
        case_from_dict(data, base_dir=tmp_path)
    data["stages"][1]["meshes"] = {"lid": {"omega": [0.0, 0.0, 3.0]}}  # a new rate: fine
    case = case_from_dict(data, base_dir=tmp_path)
    sim = build_simulation(case)
    apply_stage(sim, case, 1)
    np.testing.assert_array_equal(sim.meshes.omega[1], [0.0, 0.0, 3.0])


@pytest.mark.parametrize("change, message", [
    (lambda d: d["meshes"][0].update(file="nowhere.stl"),
     r"meshes\[0\]\.file: .*'nowhere.stl'"),
    (lambda d: d["meshes"][0].update(transforms="scale 0.02 spin 3"),
     r"meshes\[0\]\.transforms: unknown operation 'spin'"),
    (lambda d: d["meshes"][0].update(material={"youngs_modulus": 1e9}),
     r"meshes\[0\]\.material\.youngs_modulus: not a parameter of the linear law"),
    (lambda d: d["meshes"][0].update(name="side0"),
     r"meshes\[0\]\.name: duplicate wall name, got 'side0'"),
    (lambda d: d["meshes"][0].update(velocity=[0.0, 1.0]),
     r"meshes\[0\]\.velocity: expected 3 components"),
    (lambda d: d["meshes"][0].update(friction=-0.1), r"meshes\[0\]\.friction"),
    (lambda d: d["stages"][0].update(meshes={"roof": {"velocity": [0, 0, 1]}}),
     r'stages\[0\]\.meshes\."roof": no such mesh \(have floor\)'),
    (lambda d: (d["particles"].update(count=[3, 3], spacing=0.0025, origin=[0, 0]),
                d.update(gravity=[0.0, -G], walls=[])),
     r"meshes\[0\]: triangle meshes bound 3D cases, the case is 2D"),
])
def test_bad_mesh_input_is_one_line_naming_the_key(tmp_path, change, message):
    data = tray_case(tmp_path)
    change(data)
    with pytest.raises(InputError, match=message) as err:
        build_simulation(case_from_dict(data, base_dir=tmp_path))
    assert "\n" not in str(err.value)


def test_a_broken_mesh_file_stops_the_run_before_it_writes(tmp_path):
    """A truncated binary STL named in the case: exit 2, one line naming the key and
    the file, and no output folder."""
    data = tray_case(tmp_path)
    (tmp_path / "floor.stl").write_bytes(b"\0" * 80 + np.uint32(10).tobytes() + b"\1" * 100)
    (tmp_path / "case.toml").write_text(tomli_w.dumps(data))
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "demstep.cli", "run", str(tmp_path / "case.toml"),
                           "--out", str(out)], capture_output=True, text=True)
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "meshes[0].file:" in lines[0] and "floor.stl" in lines[0]
    assert not out.exists()
