"""`demstep dt`: the JSON shape, the table and one-line errors with exit status 2."""

import json
import subprocess
import sys

import numpy as np
import pytest

from demstep.cli import main
from demstep.timestep import METHODS


def run(argv, capsys):
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse errors
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def test_json_shape_lattice(capsys):
    code, out, err = run(["dt", "--lattice", "fcc", "--size", "2", "--json"], capsys)
    assert code == 0, err
    data = json.loads(out)
    assert set(data) == {"dim", "n_particles", "n_contacts", "m_min", "k_max", "rotation",
                         "damped", "damping", "estimates", "notes", "critical_mode"}
    assert data["dim"] == 3 and data["n_particles"] == 16 and data["damped"] is False
    # undamped: every method but exact-undamped (a lattice also gives exact-periodic)
    assert [e["method"] for e in data["estimates"]] == [m for m in METHODS if m != "exact-undamped"]
    for e in data["estimates"]:
        assert set(e) == {"method", "dt", "alpha", "conservative", "kind", "guarantee"}
        assert e["dt"] > 0 and e["alpha"] == pytest.approx(e["dt"] / np.sqrt(data["m_min"] / data["k_max"]))
    kinds = {e["method"]: e["guarantee"]["kind"] for e in data["estimates"]}
    # 96 DOFs: the dense path, a proof; the elements a rigorous lower bound; rules none
    assert kinds["certified"] == "proof" and kinds["element-coupled"] == "lower-bound"
    assert kinds["exact"] == "estimate" and kinds["nodal"] == kinds["itasca"] == "rule"
    by = {e["method"]: e["dt"] for e in data["estimates"]}
    assert by["exact"] * (1 - 1e-9) <= by["certified"] <= by["exact"]


def test_certified_step_is_probabilistic_with_a_seed_that_reproduces_it(capsys):
    """Above the dense limit the certified step carries a failure probability and the
    seed of its random start; the same seed gives the same certificate, --failure sets
    the probability, and a bad one is refused naming it."""
    argv = ["dt", "--lattice", "fcc", "--size", "4", "--json", "--methods", "certified,exact"]
    runs = []
    for extra in (["--seed", "17"], ["--seed", "17"], ["--seed", "17", "--failure", "1e-3"]):
        code, out, err = run(argv + extra, capsys)
        assert code == 0, err
        runs.append({e["method"]: e for e in json.loads(out)["estimates"]})
    g = runs[0]["certified"]["guarantee"]
    assert g["kind"] == "probability" and g["failure"] == 1e-9 and g["seed"] == 17
    assert runs[0]["certified"] == runs[1]["certified"]
    assert runs[2]["certified"]["guarantee"]["failure"] == 1e-3
    assert runs[2]["certified"]["guarantee"]["steps"] <= g["steps"]
    exact = runs[0]["exact"]["dt"]
    assert exact * (1 - 1e-4) <= runs[0]["certified"]["dt"] < exact
    code, out, err = run(argv[:-3] + ["--failure", "0.9"], capsys)
    assert code != 0 and "failure" in err and "0.9" in err


def test_csv_file_and_table(tmp_path, capsys):
    f = tmp_path / "a.csv"
    f.write_text("x,y,r\n0,0,1\n2,0,1\n4,0,1\n1,1.7320508075688772,1\n")
    code, out, err = run(["dt", str(f), "--kn", "10", "--density", "3"], capsys)
    assert code == 0, err
    assert "exact" in out and "itasca" in out and "element-coupled" in out
    code, out, _ = run(["dt", str(f), "--kn", "10", "--json", "--no-rotation"], capsys)
    data = json.loads(out)
    assert data["dim"] == 2 and data["n_contacts"] == 4 and data["k_max"] == 10


def test_csv_mass_column_used(tmp_path, capsys):
    f = tmp_path / "a.csv"
    f.write_text("x,y,z,r,m\n0,0,0,1,4\n2,0,0,1,4\n")
    code, out, _ = run(["dt", str(f), "--kn", "1", "--json", "--no-rotation"], capsys)
    data = json.loads(out)
    exact = next(e for e in data["estimates"] if e["method"] == "exact")
    assert data["m_min"] == 4
    assert exact["dt"] == pytest.approx(2 * np.sqrt(2.0 / 1.0))  # m_eff = 2


def test_plot_written(tmp_path, capsys):
    png = tmp_path / "sub" / "dt.png"
    code, _, err = run(["dt", "--lattice", "hex", "--size", "3", "--plot", str(png)], capsys)
    assert code == 0, err
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_paper_table_json(capsys):
    code, out, _ = run(["dt", "--paper-table", "--json"], capsys)
    data = json.loads(out)
    assert {r["lattice"] for r in data["rows"]} == {"square", "hex", "sc", "bcc", "fcc", "rhombic"}
    for m in data["minima"]:
        assert m["demstep"] == pytest.approx(m["paper"], rel=0.01)


@pytest.mark.parametrize("content,needle", [
    ("x,y\n0,0\n", "missing column 'r'"),
    ("x,y,r\n0,0,-1\n2,0,1\n", "radius must be > 0"),
    ("x,y,r\n0,0,0\n2,0,1\n", "radius must be > 0"),
    ("x,y,r\n0,nan,1\n2,0,1\n", "not finite"),
    ("x,y,r\n0,0,1\n10,0,1\n", "no contacts"),
    ("x,y,r\n0,zero,1\n", "not a number"),
    ("", "empty file"),
])
def test_bad_files(tmp_path, capsys, content, needle):
    f = tmp_path / "bad.csv"
    f.write_text(content)
    code, out, err = run(["dt", str(f)], capsys)
    assert code == 2
    assert needle in err and err.count("\n") == 1 and "Traceback" not in err
    assert out == ""


@pytest.mark.parametrize("argv,needle", [
    (["dt", "--lattice", "diamond"], "unknown lattice 'diamond'"),
    (["dt", "/nonexistent/file.csv"], "no such file"),
    (["dt", "--lattice", "fcc", "--kn", "-3"], "kn"),
    (["dt", "--lattice", "fcc", "--size", "0"], "size"),
    (["dt"], "exactly one"),
    (["dt", "--lattice", "hex", "--mass-split", "zoned"], "zoned"),
    (["dt", "--lattice", "fcc", "--methods", "exact,magic"], "unknown method 'magic'"),
    (["dt", "--lattice", "fcc", "--exact-tol", "0.5"], "exact-tol: must be in (0, 0.001], got 0.5"),
    (["dt", "--lattice", "fcc", "--exact-tol", "0"], "exact-tol"),
    # a negative number in exponent form reaches the option's check (argparse before
    # Python 3.13 took it for an option: "expected one argument")
    (["dt", "--lattice", "fcc", "--exact-tol", "-1e-5"],
     "exact-tol: must be a finite number > 0, got '-1e-5'"),
    (["dt", "--lattice", "fcc", "--kn", "-.5E+3"], "kn: must be a finite number > 0, got '-.5E+3'"),
    (["dt", "--lattice", "fcc", "--kn", "-inf"], "kn: must be a finite number > 0, got '-inf'"),
    (["dt", "--lattice", "fcc", "--kn", "1e308"], "kn: must be 0 or between 1e-100 and 1e+100"),
    (["dt", "--lattice", "fcc", "--kn", "1e6", "--density", "1e-300"], "density: must be 0 or"),
    (["dt", "--lattice", "fcc", "--kn", "1e6", "--restitution", "nan"],
     "restitution: must be a finite number, got 'nan'"),
    (["dt", "--lattice", "fcc", "--size", "2", "--youngs", "1e6", "--poisson", "0.3"],
     "contacts: every normal stiffness is 0"),
    (["dt", "--lattice", "fcc", "--youngs", "1e6", "--poisson", "0.7", "--overlap", "1e-3"],
     "error: poisson: must lie in (-1, 0.5), got 0.7"),
    (["dt", "--lattice", "fcc", "--kn", "1e6", "--mode-vtk", "m.vtu", "--methods", "nodal"],
     "mode-vtk: the critical mode comes from the exact method"),
    (["dt", "--lattice", "fcc", "--kn", "1e6", "--snapshot", "0"],
     "snapshot: applies to liggghts files, not to a lattice input, got 0"),
    (["dt", "--lattice", "fcc", "--kn", "1e6", "--stage", "2"], "stage: applies to case files"),
    (["dt", "--lattice", "fcc", "--kn", "1e6", "--case", "c.toml"],
     "case: applies to checkpoint files"),
    (["dt", "--lattice", "fcc", "--kn", "1e6", "--methods", "hertz-time,exact-undamped"],
     "methods: none of hertz-time, exact-undamped applies to this input (hertz-time: needs"),
    (["dt", "--lattice", "zz", "--paper-table"], "paper-table: reproduces the paper's tables "
                                                "and takes no input, got --lattice zz"),
])
def test_bad_options(capsys, argv, needle):
    code, out, err = run(argv, capsys)
    assert code == 2
    assert needle in err and "Traceback" not in err


def test_unreadable_file_subprocess(tmp_path):
    f = tmp_path / "binary.csv"
    f.write_bytes(b"\xff\xfe\x00\x01garbage")
    proc = subprocess.run([sys.executable, "-m", "demstep.cli", "dt", str(f)],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.startswith("demstep: error:") and "Traceback" not in proc.stderr
    assert proc.stderr.count("\n") == 1


def test_exact_tol_certified_and_close(capsys):
    """A looser exact solve (FCC block of 4,000 spheres, a clustered top spectrum) still
    certifies: its step is below the tight solve's and within 4 x tol of it; the
    report says which residual it used."""
    argv = ["dt", "--lattice", "fcc", "--size", "10", "--kn", "1e6", "--methods", "exact",
            "--json", "--top", "0"]
    steps = {}
    for tol in (None, "1e-5"):
        code, out, err = run(argv + ([] if tol is None else ["--exact-tol", tol]), capsys)
        assert code == 0, err
        data = json.loads(out)
        steps[tol] = data["estimates"][0]["dt"]
        assert any("relative residual of 1e-05" in n for n in data["notes"]) == (tol is not None)
    # the looser bound gives a smaller step (the option reached the solver), not by much
    assert steps[None] * (1 - 4e-5) <= steps["1e-5"] < steps[None]


def test_a_method_that_does_not_apply_is_named_in_a_note(capsys):
    code, out, err = run(["dt", "--lattice", "fcc", "--size", "2", "--kn", "1e6", "--json",
                          "--methods", "nodal,exact-undamped,rayleigh-time,nodal"], capsys)
    assert code == 0, err
    data = json.loads(out)
    assert [e["method"] for e in data["estimates"]] == ["nodal"]
    assert "exact-undamped: does not apply here (no damping: exact is the undamped step)" \
        in data["notes"]
    assert any(n.startswith("rayleigh-time: does not apply here (needs Hertz materials")
               for n in data["notes"])


@pytest.mark.parametrize("law", [
    dict(restitution_tangential=0.2),
    dict(restitution=1.0, restitution_tangential=0.2),
    dict(restitution=0.5),
    dict(restitution=0.5, damping_normal=10.0),
    dict(restitution=0.4, restitution_tangential=0.6, damping_normal=3.0,
         damping_tangential=2.0),
], ids=["tangential-only", "normal-1", "normal-only", "with-absolute", "all"])
def test_dt_models_an_engine_law_with_the_engine_s_dashpots(law):
    """The analysis' contact model of an engine law (a case's contact table) has the
    dashpot parameters the engine's force uses: a tangential restitution without a
    normal one (it was dropped: the certified step 3.3x the damped one), and absolute
    dashpots added to those of a restitution (they were refused, naming options the
    user never gave)."""
    from demstep.contact.laws import HertzMindlin, LinearSpring
    from demstep.analysis_input import model_from_law

    for engine_law in (LinearSpring(k_n=1e6, mu=0.3, **law),
                       HertzMindlin(youngs_modulus=1e8, poisson_ratio=0.3, **law)):
        model = model_from_law(engine_law)
        model.validate()
        mine, engine = model.law_params(), engine_law.params()
        for name in ("c_n", "c_t", "beta_n", "beta_t"):
            assert getattr(mine, name) == getattr(engine, name), name
        assert model.damped


def test_a_case_with_tangential_restitution_alone_is_damped(tmp_path, capsys):
    """`demstep dt` on a case whose contact table has only restitution_tangential: the
    same exact step as with restitution = 1 and that tangential one, below the
    undamped one."""
    steps = {}
    for name, extra in (("alone", "restitution_tangential = 0.2\n"),
                        ("normal-1", "restitution = 1.0\nrestitution_tangential = 0.2\n"),
                        ("undamped", "")):
        case = tmp_path / f"{name}.toml"
        case.write_text(
            'name = "c"\nstages = [{ name = "s1", steps = 10 }]\n'
            '[particles]\ngenerator = "lattice"\nlattice = "hex"\nradius = 1.0\n'
            'size = [4, 3]\ndensity = 1000.0\n'
            '[contact]\nlaw = "linear"\nk_n = 1e6\nmu = 0.3\n' + extra +
            '[box]\nmargin = 0.0\n')
        code, out, err = run(["dt", str(case), "--methods", "exact", "--json"], capsys)
        assert code == 0, err
        steps[name] = json.loads(out)["estimates"][0]["dt"]
    assert steps["alone"] == pytest.approx(steps["normal-1"], rel=1e-9)
    assert steps["alone"] < 0.5 * steps["undamped"]


def test_largest_first_is_the_head_of_a_stable_descending_sort():
    """The report's top particles and contacts, chosen in O(n): the same indices in the
    same order as a stable argsort of -values, ties (many here) in index order."""
    from demstep.cli.dt import largest_first

    rng = np.random.default_rng(4)
    for values in (rng.integers(0, 5, 200).astype(float), rng.random(50), np.zeros(30)):
        for top in (1, 3, 10, 29, 30, 200, 250):
            np.testing.assert_array_equal(largest_first(values, top),
                                          np.argsort(-values, kind="stable")[:top])
