"""`demstep dt --mesh`: triangle-mesh walls in the certificate of a particle file. A
tessellated floor certifies the step a plane wall does; a mesh of its own material
(a particle type, as LIGGGHTS gives a mesh) pairs it with the particles' by Hertz'
rule, checked against the analytic step of one sphere on the floor; bad mesh options
are one line."""

import json
import math

import meshio
import numpy as np
import pytest

from conftest import cli
from demstep.mesh.shapes import plane

R, RHO = 0.01, 2500.0


run = cli  # (the command line in this process: exit status, stdout, stderr)


def exact_dt(out) -> float:
    data = json.loads(out)
    return {e["method"]: e for e in data["estimates"]}["exact"]["dt"], data


def write_floor(path, n=6):
    """A unit square centred on the origin cut into 2 n^2 triangles in z = 0, ASCII
    STL."""
    m = plane(n, size=1.0)
    meshio.write_points_cells(str(path), np.asarray(m.vertices, float),
                              [("triangle", np.asarray(m.triangles))], file_format="stl")
    return path


def write_csv(path, x, r, types=None):
    head = "x,y,z,r" + (",type" if types is not None else "")
    rows = [",".join(repr(float(v)) for v in (*xi, ri)) + (f",{types[k]}" if types is not None
                                                           else "")
            for k, (xi, ri) in enumerate(zip(x, r))]
    path.write_text(head + "\n" + "\n".join(rows) + "\n")
    return path


def resting_layers(seed=3):
    """Two jittered layers of spheres on the floor z = 0 (the bottom ones pressed into
    it by up to 1 % of the radius) around the centre of the floor (the unit square
    scaled by 0.2): many of them over its edges and vertices."""
    rng = np.random.default_rng(seed)
    g = (np.arange(4) - 1.5) * 2.05 * R
    xx, yy = np.meshgrid(g, g)
    bottom = np.column_stack([xx.ravel(), yy.ravel(),
                              R * (1 - rng.uniform(0.001, 0.01, xx.size))])
    top = bottom + [1.02 * R, 1.02 * R, 1.98 * R]
    x = np.concatenate([bottom, top[:9]])
    x[:, :2] += rng.normal(0, 0.05 * R, (len(x), 2))
    return x, np.full(len(x), R)


@pytest.mark.parametrize("model", [["--kn", "1e5"], ["--youngs", "1e8", "--poisson", "0.3"]])
def test_a_tessellated_floor_certifies_the_step_of_a_plane_wall(tmp_path, capsys, model):
    """Spheres pressed into a floor of 72 triangles (many of them over shared edges
    and vertices): the exact step and every element bound equal those of the plane
    wall z = 0, to round-off (one contact per sphere, the same arm and normal)."""
    x, r = resting_layers()
    state = write_csv(tmp_path / "s.csv", x, r)
    floor = write_floor(tmp_path / "floor.stl")
    base = ["dt", state, "--density", RHO, "--json", *model]
    code, out_mesh, err = run(base + ["--mesh", f"{floor} scale 0.2"], capsys)
    assert code == 0, err
    code, out_wall, err = run(base + ["--wall", "0,0,0:0,0,1"], capsys)
    assert code == 0, err
    code, out_none, err = run(base, capsys)
    assert code == 0, err
    dt_mesh, data_mesh = exact_dt(out_mesh)
    dt_wall, data_wall = exact_dt(out_wall)
    dt_none, _ = exact_dt(out_none)
    assert data_mesh["n_contacts"] == data_wall["n_contacts"]
    assert dt_mesh == pytest.approx(dt_wall, rel=1e-12)
    assert dt_mesh < dt_none * (1 - 1e-3)  # the floor's contacts matter here
    for e_mesh, e_wall in zip(data_mesh["estimates"], data_wall["estimates"]):
        assert e_mesh["dt"] == pytest.approx(e_wall["dt"], rel=1e-12), e_mesh["method"]


def test_a_mesh_of_its_own_material_gives_the_analytic_step(tmp_path, capsys):
    """One sphere (type 1, soft) pressed by delta into a steel floor (type 2): the
    contact's tangent stiffnesses k_n = 2 E* sqrt(R delta), k_t = 8 G* sqrt(R delta)
    with E*, G* of the two materials; the sphere's modes are the normal one k_n / m
    and the coupled slip-roll one k_t (1/m + a^2/I), a = R - delta the arm; the exact
    step is 2 / sqrt of the largest. The particle's own material (no type) gives
    the softer step."""
    delta = 2e-4
    state = write_csv(tmp_path / "one.csv", [[0.1, 0.2, R - delta]], [R], types=[1])
    floor = write_floor(tmp_path / "floor.stl", n=2)
    mats = tmp_path / "mats.toml"
    e1, nu1, e2, nu2 = 5e7, 0.3, 2e11, 0.29
    mats.write_text(f"[[material]]\ntype = 1\nyoungs = {e1}\npoisson = {nu1}\ndensity = {RHO}\n"
                    f"[[material]]\ntype = 2\nyoungs = {e2}\npoisson = {nu2}\n"
                    f"density = 7800.0\n")
    code, out, err = run(["dt", state, "--materials", mats, "--json",
                          "--mesh", f"{floor} type 2"], capsys)
    assert code == 0, err
    dt, data = exact_dt(out)
    assert data["n_contacts"] == 1
    e_star = 1 / ((1 - nu1 ** 2) / e1 + (1 - nu2 ** 2) / e2)
    g_star = 1 / (2 * (2 - nu1) * (1 + nu1) / e1 + 2 * (2 - nu2) * (1 + nu2) / e2)
    root = math.sqrt(R * delta)
    k_n, k_t = 2 * e_star * root, 8 * g_star * root
    m = RHO * 4 / 3 * math.pi * R ** 3
    inertia = 0.4 * m * R ** 2
    arm = R - delta
    lam = max(k_n / m, k_t * (1 / m + arm ** 2 / inertia))
    assert dt == pytest.approx(2 / math.sqrt(lam), rel=1e-9)
    code, out_soft, err = run(["dt", state, "--materials", mats, "--json",
                               "--mesh", str(floor)], capsys)
    assert code == 0, err
    assert exact_dt(out_soft)[0] > 1.3 * dt


@pytest.mark.parametrize("argv, words", [
    (["--lattice", "fcc", "--mesh", "floor.stl"], ["--mesh", "not to --lattice"]),
    (["STATE", "--kn", "1e5", "--mesh", "floor.stl spin 3"], ["mesh:", "unknown operation 'spin'"]),
    (["STATE", "--kn", "1e5", "--mesh", "nowhere.stl"], ["mesh:", "nowhere.stl"]),
    (["STATE", "--kn", "1e5", "--mesh", "floor.stl type 2"], ["mesh:", "type 2", "linear law has no materials"]),
    (["STATE", "--kn", "1e5", "--mesh", "floor.stl type x"], ["mesh: type:", "'x'"]),
    (["FLAT", "--kn", "1e5", "--mesh", "floor.stl"], ["mesh:", "3D"]),
])
def test_bad_mesh_options_are_one_line(tmp_path, capsys, monkeypatch, argv, words):
    monkeypatch.chdir(tmp_path)
    write_floor(tmp_path / "floor.stl", n=2)
    write_csv(tmp_path / "s.csv", [[0.5, 0.5, R * 0.99]], [R])
    (tmp_path / "flat.csv").write_text("x,y,r\n0.5,0.5,0.01\n")
    argv = [{"STATE": "s.csv", "FLAT": "flat.csv"}.get(a, a) for a in argv]
    code, out, err = run(["dt", *argv, "--density", RHO], capsys)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1 and out == "", err
    for w in words:
        assert w in lines[0], lines[0]


@pytest.mark.parametrize("convention, arm_of", [("demstep", lambda r, d: r - d),
                                                 ("liggghts", lambda r, d: r - d / 2)])
def test_the_wall_arm_of_each_convention(tmp_path, capsys, convention, arm_of):
    """One sphere pressed by delta = 5 % of its radius into a mesh floor, rotation free:
    the slip-roll mode k_t (1/m + a^2/I) sets the step, with the arm a of the convention
    (demstep's engine: the distance to the contact point, r - delta; LIGGGHTS' surface
    model: r - delta/2)."""
    delta = 0.05 * R
    state = write_csv(tmp_path / "one.csv", [[0.1, 0.2, R - delta]], [R])
    floor = write_floor(tmp_path / "floor.stl", n=2)
    code, out, err = run(["dt", state, "--kn", "1e5", "--ks", "8e4", "--density", RHO,
                          "--json", "--convention", convention, "--mesh", str(floor)], capsys)
    assert code == 0, err
    dt, data = exact_dt(out)
    m = RHO * 4 / 3 * math.pi * R ** 3
    inertia = 0.4 * m * R ** 2
    lam = max(1e5 / m, 8e4 * (1 / m + arm_of(R, delta) ** 2 / inertia))
    assert data["n_contacts"] == 1
    assert dt == pytest.approx(2 / math.sqrt(lam), rel=1e-9)
