"""`demstep dt` on real states: dumps with periodic flags, boxes and walls, Hertz models
from E and nu, materials per type, damping conventions, case files, checkpoints, where the
danger is, and bad input (one line, exit 2, nothing written)."""

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from demstep.cli import main
from demstep.timestep.contacts import find_contacts
from demstep.packings import lattice
from demstep.particles import Particles
from demstep.timestep.exact import exact_critical_step

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def run(argv, capsys):
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def estimates(out):
    data = json.loads(out)
    return data, {e["method"]: e for e in data["estimates"]}


def fcc_state(size=3, precompression=1e-3, seed=0):
    lat = lattice("fcc", 1.0)
    x, box = lat.supercell(size)
    rng = np.random.default_rng(seed)
    x = x + rng.normal(0, 1e-6, x.shape)
    r = np.full(len(x), 1.0 + precompression)
    return x, r, np.asarray(box, dtype=float)


def write_dump(path, x, r, box, flags="pp pp pp", m=None, types=None, v=None, lo=0.0):
    n = len(r)
    cols = ["id", "type", "x", "y", "z", "radius"] + (["mass"] if m is not None else []) \
        + (["vx", "vy", "vz"] if v is not None else [])
    lines = ["ITEM: TIMESTEP", "100", "ITEM: NUMBER OF ATOMS", str(n), f"ITEM: BOX BOUNDS {flags}"]
    lines += [f"{float(lo)!r} {float(lo + b)!r}" for b in box]
    lines.append("ITEM: ATOMS " + " ".join(cols))
    for k in range(n):
        row = [k + 1, 1 if types is None else int(types[k]), *map(float, x[k] + lo), float(r[k])]
        if m is not None:
            row.append(float(m[k]))
        if v is not None:
            row += list(map(float, v[k]))
        lines.append(" ".join(repr(float(a)) if not isinstance(a, int) else str(a) for a in row))
    path.write_text("\n".join(lines) + "\n")
    return path


def reference(x, r, box, m, k_n, k_t, rotation, c_n=0.0, c_t=0.0, periodic=True):
    from demstep.particles import particle_inertia

    p = Particles(x, r, m, particle_inertia(m, r, 3))
    c = find_contacts(p, k_n, k_t, periodic=list(box) if periodic else None)
    return exact_critical_step(p, replace(c, c_n=c_n, c_t=c_t), rotation)


def test_dump_periodic_flags_give_the_cross_boundary_contacts(tmp_path, capsys):
    """Issue 12: a pp pp pp dump used to lose every contact across the boundary (the
    exact step came out 3 % too large). The box also starts away from the origin."""
    x, r, box = fcc_state()
    m = np.full(len(r), 4.0)
    dump = write_dump(tmp_path / "fcc.dump", x, r, box, m=m, lo=-7.5)
    code, out, err = run(["dt", str(dump), "--kn", "1e6", "--json"], capsys)
    assert code == 0, err
    data, est = estimates(out)
    ref = reference(x, r, box, m, 1e6, 1e6, True)
    assert data["n_contacts"] == 6 * len(r)  # FCC coordination 12, each contact once
    assert est["exact"]["dt"] == pytest.approx(ref.dt, rel=1e-8)
    # the same dump with fixed boundaries is a free block: fewer contacts, larger step
    write_dump(tmp_path / "ff.dump", x, r, box, flags="ff ff ff", m=m, lo=-7.5)
    code, out, _ = run(["dt", str(tmp_path / "ff.dump"), "--kn", "1e6", "--json"], capsys)
    free, est_free = estimates(out)
    assert free["n_contacts"] < data["n_contacts"]
    # --periodic on the command line overrides the flags
    code, out, _ = run(["dt", str(tmp_path / "ff.dump"), "--kn", "1e6", "--json",
                        "--periodic", "x,y,z"], capsys)
    assert estimates(out)[1]["exact"]["dt"] == pytest.approx(ref.dt, rel=1e-8)


def test_csv_with_box_and_periodic_axes(tmp_path, capsys):
    x, r, box = fcc_state()
    f = tmp_path / "a.csv"
    f.write_text("x,y,z,r,m\n" + "\n".join(",".join(repr(float(v)) for v in (*p, d, 4.0))
                                            for p, d in zip(x, r)) + "\n")
    box_args = [str(v) for lo_hi in zip(np.zeros(3), box) for v in lo_hi]
    code, out, err = run(["dt", str(f), "--kn", "1e6", "--json", "--box", *box_args,
                          "--periodic", "x,y,z"], capsys)
    assert code == 0, err
    ref = reference(x, r, box, np.full(len(r), 4.0), 1e6, 1e6, True)
    assert estimates(out)[1]["exact"]["dt"] == pytest.approx(ref.dt, rel=1e-8)


@pytest.mark.parametrize("rotation", [True, False])
def test_absolute_dashpots_give_the_damped_step(tmp_path, capsys, rotation):
    x, r, box = fcc_state()
    m = np.full(len(r), 4.0)
    dump = write_dump(tmp_path / "fcc.dump", x, r, box, m=m)
    argv = ["dt", str(dump), "--kn", "1e6", "--gamma-n", "300", "--gamma-t", "200", "--json",
            "--rotation" if rotation else "--no-rotation"]
    code, out, err = run(argv, capsys)
    assert code == 0, err
    data, est = estimates(out)
    ref = reference(x, r, box, m, 1e6, 1e6, rotation, 300.0, 200.0)
    assert data["damped"] and est["exact"]["dt"] == pytest.approx(ref.dt, rel=1e-8)
    assert est["exact-undamped"]["dt"] == pytest.approx(ref.dt_undamped, rel=1e-8)
    assert est["exact-undamped"]["conservative"] is False
    assert est["element-coupled"]["dt"] <= est["exact"]["dt"]


def test_restitution_conventions(tmp_path, capsys):
    """LIGGGHTS' hooke: c_t = c_n = 2 beta sqrt(m* k_n); demstep: tangential dashpot only
    with a tangential restitution. The dump defaults to LIGGGHTS'."""
    x, r, box = fcc_state()
    m = np.full(len(r), 4.0)
    dump = write_dump(tmp_path / "fcc.dump", x, r, box, m=m)
    e = 0.5
    beta = -math.log(e) / math.sqrt(math.pi**2 + math.log(e) ** 2)
    c = 2 * beta * math.sqrt(2.0 * 1e6)  # m* = m/2 = 2
    code, out, _ = run(["dt", str(dump), "--kn", "1e6", "--ks", "5e5", "--restitution", "0.5",
                        "--json"], capsys)
    liggghts = estimates(out)[1]["exact"]["dt"]
    assert liggghts == pytest.approx(reference(x, r, box, m, 1e6, 5e5, True, c, c).dt, rel=1e-8)
    code, out, _ = run(["dt", str(dump), "--kn", "1e6", "--ks", "5e5", "--restitution", "0.5",
                        "--convention", "demstep", "--json"], capsys)
    normal_only = estimates(out)[1]["exact"]["dt"]
    assert normal_only == pytest.approx(reference(x, r, box, m, 1e6, 5e5, True, c, 0.0).dt, rel=1e-8)
    code, out, _ = run(["dt", str(dump), "--kn", "1e6", "--ks", "5e5", "--restitution", "0.5",
                        "--restitution-t", "0.5", "--convention", "demstep", "--json"], capsys)
    c_t = 2 * beta * math.sqrt(2.0 * 5e5)
    both = estimates(out)[1]["exact"]["dt"]
    assert both == pytest.approx(reference(x, r, box, m, 1e6, 5e5, True, c, c_t).dt, rel=1e-8)
    code, out, _ = run(["dt", str(dump), "--kn", "1e6", "--restitution", "0.5",
                        "--no-tangential-damping", "--json"], capsys)
    off = estimates(out)[1]["exact"]["dt"]
    assert off == pytest.approx(reference(x, r, box, m, 1e6, 1e6, True, c, 0.0).dt, rel=1e-8)


def test_hertz_from_youngs_and_poisson(tmp_path, capsys):
    """Tangent stiffnesses at each overlap with LIGGGHTS' E*, G*; dashpots by Tsuji's
    form; the Rayleigh and Hertz times beside them."""
    x, r, box = fcc_state(precompression=2e-3)
    m = np.full(len(r), 4.0)
    v = np.zeros((len(r), 3))
    v[0, 0] = 0.5
    dump = write_dump(tmp_path / "fcc.dump", x, r, box, m=m, v=v)
    E, nu, e = 1e7, 0.3, 0.5
    code, out, err = run(["dt", str(dump), "--youngs", str(E), "--poisson", str(nu),
                          "--restitution", str(e), "--json"], capsys)
    assert code == 0, err
    data, est = estimates(out)
    e_star = E / (2 * (1 - nu**2))
    g_star = E / (4 * (2 - nu) * (1 + nu))
    delta, r_star = 2 * 1.002 - 2.0, 0.5 * 1.002
    root = math.sqrt(r_star * delta)
    k_n, k_t = 2 * e_star * root, 8 * g_star * root
    beta = -math.log(e) / math.sqrt(math.pi**2 + math.log(e) ** 2)
    c_n = 2 * math.sqrt(5 / 6) * beta * math.sqrt(2.0 * k_n)
    c_t = 2 * math.sqrt(5 / 6) * beta * math.sqrt(2.0 * k_t)
    ref = reference(x, r, box, m, k_n, k_t, True, c_n, c_t)
    assert est["exact"]["dt"] == pytest.approx(ref.dt, rel=1e-5)  # overlaps to 1e-6 jitter
    # the material rules: Rayleigh time with the density m / V, Hertz time at 2 |v|max
    rho = 4.0 / (4 / 3 * math.pi * 1.002**3)
    shear = E / (2 * (1 + nu))
    t_r = math.pi * 1.002 * math.sqrt(rho / shear) / (0.1631 * nu + 0.8766)
    assert est["rayleigh-time"]["dt"] == pytest.approx(t_r, rel=1e-12)
    assert est["rayleigh-20%"]["dt"] == pytest.approx(0.2 * t_r, rel=1e-12)
    assert est["rayleigh-20%"]["kind"] == "rule"
    t_h = 2.87 * (16.0 / (0.501 * e_star**2 * 1.0)) ** 0.2
    assert est["hertz-time"]["dt"] == pytest.approx(t_h, rel=1e-12)


def test_materials_per_type(tmp_path, capsys):
    """Two materials: E* and G* of each pair from both (LIGGGHTS' mixing, 1/E* =
    sum (1 - nu^2)/E, 1/G* = sum 2 (2 - nu)(1 + nu)/E): the exact step equals the
    dense reference on contacts whose tangent stiffnesses are built by hand per pair."""
    x, r, box = fcc_state()
    m = np.full(len(r), 4.0)
    types = [1 + (k % 2) for k in range(len(r))]
    dump = write_dump(tmp_path / "two.dump", x, r, box, m=m, types=types)
    mats = tmp_path / "mats.toml"
    mats.write_text("[[material]]\ntype = 1\nyoungs = 1e7\npoisson = 0.3\n"
                    "[[material]]\ntype = 2\nyoungs = 4e7\npoisson = 0.2\n")
    code, out, err = run(["dt", str(dump), "--materials", str(mats), "--json"], capsys)
    assert code == 0, err
    one = tmp_path / "one.toml"
    one.write_text("[[material]]\ntype = 1\nyoungs = 1e7\npoisson = 0.3\n"
                   "[[material]]\ntype = 2\nyoungs = 1e7\npoisson = 0.3\n")
    _, out_one, _ = run(["dt", str(dump), "--materials", str(one), "--json"], capsys)
    _, out_same, _ = run(["dt", str(dump), "--youngs", "1e7", "--poisson", "0.3", "--json"], capsys)
    stiff = estimates(out)[1]["exact"]["dt"]
    soft = estimates(out_one)[1]["exact"]["dt"]
    assert soft == pytest.approx(estimates(out_same)[1]["exact"]["dt"], rel=1e-12)
    assert stiff < soft  # type 2 is four times stiffer
    from demstep.particles import particle_inertia

    youngs, poisson = {1: 1e7, 2: 4e7}, {1: 0.3, 2: 0.2}
    p = Particles(x, r, m, particle_inertia(m, r, 3))
    c = find_contacts(p, 1.0, 1.0, periodic=list(box))
    ti, tj = np.asarray(types)[c.i], np.asarray(types)[c.j]
    e_star = 1.0 / np.array([(1 - poisson[a] ** 2) / youngs[a] + (1 - poisson[b] ** 2) / youngs[b]
                             for a, b in zip(ti, tj)])
    g_star = 1.0 / np.array([2 * (2 - poisson[a]) * (1 + poisson[a]) / youngs[a]
                             + 2 * (2 - poisson[b]) * (1 + poisson[b]) / youngs[b]
                             for a, b in zip(ti, tj)])
    root = np.sqrt(0.5 * 1.001 * (2 * 1.001 - (c.arm_i + c.arm_j)))
    ref = exact_critical_step(p, replace(c, k_n=2 * e_star * root, k_s=8 * g_star * root), True)
    assert stiff == pytest.approx(ref.dt, rel=1e-8)
    code, out, err = run(["dt", str(dump), "--materials", str(tmp_path / "one.toml"),
                          "--json"], capsys)
    mats.write_text("[[material]]\ntype = 1\nyoungs = 1e7\npoisson = 0.3\n")
    code, out, err = run(["dt", str(dump), "--materials", str(mats)], capsys)
    assert code == 2 and "type 2 has no material" in err


def test_walls_from_flags(tmp_path, capsys):
    """A column of spheres on a floor: the floor contact stiffens the system."""
    x = np.array([[0.0, 0.0, 1.0 - 1e-3 + 2.0 * k - 2e-3 * k] for k in range(4)])
    r = np.ones(4)
    f = tmp_path / "col.csv"
    f.write_text("x,y,z,r,m\n" + "\n".join(f"{a},{b},{float(c)!r},1,2" for a, b, c in x) + "\n")
    code, out, err = run(["dt", str(f), "--kn", "100", "--json", "--no-rotation"], capsys)
    free = estimates(out)[1]["exact"]["dt"]
    code, out, err = run(["dt", str(f), "--kn", "100", "--json", "--no-rotation",
                          "--wall", "0,0,0:0,0,1"], capsys)
    assert code == 0, err
    data, est = estimates(out)
    assert data["n_contacts"] == 4 and est["exact"]["dt"] < free
    # a chain of masses 2 on springs 100 fixed at one end: the dense reference
    K = np.diag([200.0] * 3 + [100.0]) - np.diag([100.0] * 3, 1) - np.diag([100.0] * 3, -1)
    lam = np.linalg.eigvalsh(K / 2.0).max()
    assert est["exact"]["dt"] == pytest.approx(2 / math.sqrt(lam), rel=1e-9)
    code, out, err = run(["dt", str(f), "--kn", "100", "--json", "--no-rotation",
                          "--box", "-5", "5", "-5", "5", "0", "20", "--wall", "z-"], capsys)
    assert estimates(out)[1]["exact"]["dt"] == pytest.approx(2 / math.sqrt(lam), rel=1e-9)


def test_where_the_danger_is_and_mode_vtk(tmp_path, capsys):
    """One small particle in a lattice of large ones carries the critical mode."""
    import meshio

    lat = lattice("sc", 1.0)
    x, box = lat.supercell(4)
    r = np.full(len(x), 1.001)
    m = np.full(len(x), 4.0)
    m[17] = 0.05  # a light particle: the fastest mode lives on it
    f = tmp_path / "a.csv"
    f.write_text("x,y,z,r,m\n" + "\n".join(",".join(repr(float(v)) for v in (*p, d, e))
                                            for p, d, e in zip(x, r, m)) + "\n")
    vtu = tmp_path / "mode" / "mode.vtu"
    box_args = [str(v) for lo_hi in zip(np.zeros(3), box) for v in lo_hi]
    code, out, err = run(["dt", str(f), "--kn", "1e4", "--box", *box_args, "--periodic", "x,y,z",
                          "--json", "--mode-vtk", str(vtu), "--top", "3"], capsys)
    assert code == 0, err
    data = json.loads(out)
    top = data["critical_mode"]["particles"]
    assert top[0]["index"] == 17 and top[0]["share"] > 0.5 and len(top) == 3
    # localised: one share above 1/2 bounds the participation number 1/sum(s^2) by 4
    assert 1.0 <= data["critical_mode"]["participation"] < 4.0
    assert data["critical_mode"]["lambda_undamped_tol"] == 1e-10  # undamped: the tight solve
    assert data["critical_mode"]["listed_share"] == pytest.approx(sum(q["share"] for q in top))
    assert all(c["i"] == 17 or c["j"] == 17 for c in data["critical_mode"]["contacts"])
    mesh = meshio.read(vtu)
    share = mesh.point_data["share"]
    assert len(share) == len(x) and int(np.argmax(share)) == 17
    assert share.sum() == pytest.approx(1.0, rel=1e-9)
    code, out, err = run(["dt", str(f), "--kn", "1e4", "--box", *box_args, "--periodic", "x,y,z"],
                         capsys)
    assert "Where the danger is" in out and "\n         17 " in out
    # all particles alike: the mode spreads over most of them, shown as such
    f.write_text("x,y,z,r,m\n" + "\n".join(",".join(repr(float(v)) for v in (*p, 1.001, 4.0))
                                            for p in x) + "\n")
    code, out, err = run(["dt", str(f), "--kn", "1e4", "--box", *box_args, "--periodic", "x,y,z",
                          "--json", "--top", "3"], capsys)
    spread = json.loads(out)["critical_mode"]
    assert len(x) / 4 < spread["participation"] <= len(x) * (1 + 1e-9)
    assert spread["listed_share"] < 0.5
    code, out, err = run(["dt", str(f), "--kn", "1e4", "--box", *box_args, "--periodic", "x,y,z",
                          "--top", "3"], capsys)
    assert f"spreads over about {spread['participation']:.3g} particles" in out


def test_case_file_and_checkpoint(tmp_path, capsys):
    from demstep.runner import run_case
    from demstep.case import load_case

    code, out, err = run(["dt", str(EXAMPLES / "fcc_plane_strain.toml"), "--json"], capsys)
    assert code == 0, err
    data, est = estimates(out)
    assert data["n_contacts"] > 0 and est["exact"]["dt"] > 0
    assert any("case" in n for n in data["notes"])
    run_case(load_case(EXAMPLES / "hex_biaxial_2d.toml"), tmp_path / "hex", quiet=True,
             max_steps=300)
    ck = sorted((tmp_path / "hex" / "checkpoints").glob("*.npz"))[-1]
    code, out, err = run(["dt", str(ck), "--json"], capsys)
    assert code == 0, err
    data, est = estimates(out)
    # the hex example has restitution 0.5: its dashpots enter the analysis
    assert data["damped"] and est["exact"]["dt"] < est["exact-undamped"]["dt"]
    assert not any("is not the case that wrote" in n for n in data["notes"])
    # another case (a stiffer law) on the checkpoint: analysed, and said so
    import tomllib
    import tomli_w

    data_case = tomllib.loads((tmp_path / "hex" / "case.toml").read_text())
    data_case["contact"]["k_n"] *= 4.0
    stiffer = tmp_path / "stiffer.toml"
    stiffer.write_text(tomli_w.dumps(data_case))
    code, out, err = run(["dt", str(ck), "--case", str(stiffer), "--json"], capsys)
    assert code == 0, err
    other, other_est = estimates(out)
    assert any(f"case: {stiffer} is not the case that wrote" in n for n in other["notes"])
    assert other_est["exact"]["dt"] < est["exact"]["dt"]
    code, out, err = run(["dt", str(ck), "--kn", "5"], capsys)
    assert code == 2 and "--kn" in err
    # a checkpoint without its run state: the error names dt's input, not run's --restart
    ck.with_suffix(".json").unlink()
    code, out, err = run(["dt", str(ck)], capsys)
    assert code == 2 and err.startswith("demstep: error: checkpoint: no run state")


HERTZ_CASE = """
name = "hertz-pile"
[particles]
generator = "lattice"
lattice = "fcc"
radius = 1.0
size = [2, 2, 2]
origin = [1.0, 1.0, 1.0]
density = 1000.0
[contact]
law = "hertz"
youngs_modulus = 1.0e7
poisson_ratio = 0.3
mu = 0.3
[box]
margin = 0.0
[[stages]]
steps = 60
gravity = [0.0, 0.0, -9.81]
"""


def test_hertz_checkpoint_brings_its_materials_and_the_impact_velocity(tmp_path, capsys):
    """A checkpoint of a Hertz run reports the Rayleigh time and the Hertz time from
    its law's E and nu and its spheres (the latter at --impact-velocity, default twice
    the largest speed), checked against the rules' formulas; the option on a linear
    law's checkpoint is refused (it was dropped without a word)."""
    from demstep.case import case_from_text
    from demstep.runner import run_case
    from demstep.analysis_input import load_run

    run_case(case_from_text(HERTZ_CASE), tmp_path / "run", quiet=True)
    ck = sorted((tmp_path / "run" / "checkpoints").glob("*.npz"))[-1]
    sim, _ = load_run(ck)
    E, nu = 1.0e7, 0.3
    e_star = E / (2 * (1 - nu**2))
    rho = 1000.0
    t_r = math.pi * 1.0 * math.sqrt(rho / (E / (2 * (1 + nu)))) / (0.1631 * nu + 0.8766)
    m = 1000.0 * 4 / 3 * math.pi

    def hertz_time(v):
        return 2.87 * (m * m / (0.5 * 1.0 * e_star**2 * v)) ** 0.2

    speed = float(np.linalg.norm(sim.v, axis=1).max())
    assert speed > 0
    for argv, v in (([], 2 * speed), (["--impact-velocity", "0.25"], 0.25)):
        code, out, err = run(["dt", str(ck), "--json", *argv], capsys)
        assert code == 0, err
        _, est = estimates(out)
        assert est["rayleigh-time"]["dt"] == pytest.approx(t_r, rel=1e-12)
        assert est["hertz-time"]["dt"] == pytest.approx(hertz_time(v), rel=1e-12)
    linear = HERTZ_CASE.replace('law = "hertz"', 'law = "linear"\nk_n = 1.0e5').replace(
        "youngs_modulus = 1.0e7\npoisson_ratio = 0.3\n", "")
    run_case(case_from_text(linear), tmp_path / "lin", quiet=True)
    capsys.readouterr()  # the run's log
    ck = sorted((tmp_path / "lin" / "checkpoints").glob("*.npz"))[-1]
    code, out, err = run(["dt", str(ck), "--impact-velocity", "0.25"], capsys)
    assert code == 2 and out == "" and err.count("\n") == 1
    assert "impact-velocity: only used by the Hertz time" in err and "linear" in err


@pytest.mark.parametrize("argv,needle", [
    (["--kn", "1e6", "--youngs", "1e7"], "hertz"),
    (["--youngs", "1e7"], "both --youngs and --poisson"),
    (["--youngs", "1e7", "--poisson", "0.7"], "poisson"),
    (["--youngs", "nan", "--poisson", "0.3"], "youngs"),
    (["--youngs", "-1", "--poisson", "0.3"], "youngs"),
    (["--kn", "1e6", "--restitution", "1.5"], "restitution"),
    (["--kn", "1e6", "--restitution", "0"], "restitution"),
    (["--kn", "1e6", "--restitution", "0.5", "--gamma-n", "3"], "restitution"),
    (["--kn", "1e6", "--restitution", "0.5", "--restitution-t", "0.5"], "restitution-t"),
    (["--kn", "1e6", "--viscous", "1", "--rayleigh", "1", "0"], "viscous"),
    (["--kn", "1e6", "--periodic", "x,w"], "periodic"),
    (["--kn", "1e6", "--box", "0", "1"], "box"),
    (["--kn", "1e6", "--wall", "q+"], "wall"),
    (["--kn", "1e6", "--plot", "out.txt"], "plot"),
    (["--kn", "1e6", "--mode-vtk", "mode.csv"], "mode-vtk"),
    (["--kn", "1e6", "--overlap", "0.01"],
     "overlap: only used with a law whose stiffness depends on the overlap"),
    (["--kn", "1e6", "--impact-velocity", "2"],
     "impact-velocity: only used by the Hertz time of the hertz model"),
])
def test_bad_options_on_a_dump(tmp_path, capsys, argv, needle):
    x, r, box = fcc_state(size=3)
    dump = write_dump(tmp_path / "s.dump", x, r, box, m=np.full(len(r), 4.0))
    before = set(tmp_path.iterdir())
    code, out, err = run(["dt", str(dump), *argv], capsys)
    assert code == 2, err
    assert needle in err and err.count("\n") == 1 and "Traceback" not in err and out == ""
    assert set(tmp_path.iterdir()) == before


def test_bad_dumps(tmp_path, capsys):
    x, r, box = fcc_state(size=3)
    tri = tmp_path / "tri.dump"
    text = write_dump(tri, x, r, box).read_text().replace("BOX BOUNDS pp pp pp",
                                                          "BOX BOUNDS xy xz yz pp pp pp")
    tri.write_text(text)
    code, _, err = run(["dt", str(tri), "--kn", "1"], capsys)
    assert code == 2 and "triclinic" in err
    small = write_dump(tmp_path / "small.dump", x, r, box / 2)
    code, _, err = run(["dt", str(small), "--kn", "1"], capsys)
    assert code == 2 and "periodic length" in err
    outside = x.copy()
    outside[3, 0] = box[0] + 5.0
    far = write_dump(tmp_path / "far.dump", outside, r, box)
    code, _, err = run(["dt", str(far), "--kn", "1"], capsys)
    assert code == 2 and "outside the periodic box" in err and "particle 3" in err
    noradius = tmp_path / "nr.dump"
    noradius.write_text(write_dump(tmp_path / "x.dump", x, r, box).read_text()
                        .replace(" radius", " diam"))
    code, _, err = run(["dt", str(noradius), "--kn", "1"], capsys)
    assert code == 2 and "radius" in err


def test_memory_refused_before_allocating(capsys):
    code, out, err = run(["dt", "--lattice", "fcc", "--size", "1000"], capsys)
    assert code == 2 and "memory" in err and "GB" in err
    code, out, err = run(["dt", "--lattice", "fcc", "--size", "10", "--max-memory", "0.001"], capsys)
    assert code == 2 and "--max-memory" in err


def test_plot_path_checked_before_the_work_and_help_lists_formats(tmp_path, capsys):
    """Issue 13, item 7: a bad plot path is refused up front (no traceback, nothing
    computed or written); and `dt --help` names every input format."""
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code, out, err = run(["dt", "--lattice", "hex", "--size", "2", "--plot",
                          str(blocker / "sub" / "dt.png")], capsys)
    assert code == 2 and "plot" in err and "not a folder" in err and out == ""
    code, out, err = run(["dt", "--lattice", "hex", "--size", "2", "--plot",
                          str(tmp_path / "dt.txt")], capsys)
    assert code == 2 and ".png" in err and out == ""
    assert not (tmp_path / "dt.txt").exists()
    code, help_text, _ = run(["dt", "--help"], capsys)
    assert code == 0
    for word in ("CSV", "LIGGGHTS", "LAMMPS", "YADE", "case", "checkpoint"):
        assert word in help_text


@pytest.mark.parametrize("width", [8, 9])
def test_shares_print_with_a_space_before_them(width):
    """A share column never runs into the one before it (exponent form below 0.001)."""
    from demstep.cli.dt import _share

    for value in (0.0, 0.5, 1.0, 0.001, 3.64e-4, 1.97e-23):
        text = _share(value, width)
        assert len(text) == width and text[0] == " "
        assert float(text) == pytest.approx(value, rel=0.05, abs=5e-4)


def test_a_name_too_long_for_the_file_system_is_refused_before_anything_is_written(
        tmp_path, capsys, monkeypatch):
    """A path part longer than NAME_MAX failed half-way before (the report printed, the
    folders made, the error naming a temporary file): now one line naming the option,
    exit 2, nothing written."""
    monkeypatch.chdir(tmp_path)
    long = "n" * 300
    code, out, err = run(["dt", "--lattice", "fcc", "--size", "2", "--kn", "1e6",
                          "--mode-vtk", f"x1/y1/{long}.vtu"], capsys)
    assert code == 2 and err.startswith("demstep: error: mode-vtk: the name")
    assert err.count("\n") == 1 and out == ""
    code, out, err = run(["run", str(EXAMPLES / "hex_biaxial_2d.toml"), "--out", f"a1/{long}",
                          "--quiet"], capsys)
    assert code == 2 and err.startswith("demstep: error: out: the name") and "at most 255" in err
    assert list(tmp_path.iterdir()) == []
