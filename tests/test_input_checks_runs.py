"""Bad input and output safety of `demstep run`, `sweep`, `dt` and `paper`: each bad file,
option or parameter gives one line naming the field and the value, exit status 2, no
traceback, and nothing written or destroyed (review items 2, 3, 5, 6, 12, 13, 14, 15,
16)."""

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, cli, snapshot

from demstep.io.lock import FolderLock

CASE = """
[particles]
generator = "lattice"
lattice = "hex"
radius = 1.0
size = [3, 3]
density = 1000.0

[contact]
law = "linear"
k_n = 1.0e6

[box]
margin = 0.0

[[stages]]
steps = 6
{stage}
[output]
checkpoint_every = 2
checkpoint_keep = 0
"""
#: a name longer than any file system takes (NAME_MAX is 255 bytes)
LONG = "x" * 300





def write_case(folder, stage="", name="case.toml"):
    path = Path(folder) / name
    path.write_text(CASE.format(stage=stage))
    return path


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A run of 6 steps with checkpoints at steps 2, 4 and 6: (case file, run folder)."""
    from demstep.case import load_case
    from demstep.runner import run_case

    folder = tmp_path_factory.mktemp("finished")
    case = write_case(folder)
    result = run_case(load_case(case), folder / "run", quiet=True)
    assert result.ok
    return case, folder / "run"


@pytest.fixture
def run_copy(finished_run, tmp_path):
    """A copy of the finished run: (case file, run folder, the checkpoint at step 4)."""
    case, run = finished_run
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    return case, copy, copy / "checkpoints" / "step0000000004.npz"


def edit_checkpoint(path, **arrays):
    data = dict(np.load(path))
    data.update(arrays)
    with open(path, "wb") as fh:
        np.savez(fh, **data)


def edit_state(checkpoint, **fields):
    path = Path(checkpoint).with_suffix(".json")
    state = json.loads(path.read_text())
    state.update(fields)
    path.write_text(json.dumps(state))


# ----------------------------------------------------------------- 2: sweep
def test_sweep_validates_the_build_of_every_run_before_writing(tmp_path, capsys):
    """A swept value that only the build of the simulation refuses (a fixed index beyond
    the particles) fails the sweep before anything is written, naming the run, the key
    and the value (it was a 'failed' run in a written sweep folder before)."""
    case = write_case(tmp_path)
    out = tmp_path / "sweep"
    code, _, err = cli(["sweep", case, "--param", "particles.fixed.indices=[100]", "--out", out],
                       capsys)
    assert_one_line_error(code, err, "sweep: run 1 of 1", "particles.fixed.indices", "100")
    assert not out.exists()


# ------------------------------------------------------- 3: masses and density
def mass_file_case(folder, density=True):
    folder = Path(folder)
    (folder / "p.csv").write_text("x,y,r,m\n0,0,1,2.0\n2,0,1,3.0\n")
    text = CASE.format(stage="").replace(
        'generator = "lattice"\nlattice = "hex"\nradius = 1.0\nsize = [3, 3]\n',
        'generator = "file"\npath = "p.csv"\n')
    if not density:
        text = text.replace("density = 1000.0\n", "")
    path = folder / "case.toml"
    path.write_text(text)
    return path


def test_run_refuses_a_mass_column_with_a_density(tmp_path, capsys):
    """`run`: a particle file with a mass column and the case's particles.density is
    refused naming both (the density silently replaced the file's masses before);
    either one alone runs."""
    case = mass_file_case(tmp_path)
    out = tmp_path / "out"
    code, _, err = cli(["run", case, "--out", out, "--max-steps", "0", "--quiet"], capsys)
    assert_one_line_error(code, err, "particles.density", "mass column (m)", "p.csv", "1000.0")
    assert not out.exists()
    case = mass_file_case(tmp_path, density=False)
    code, _, err = cli(["run", case, "--out", out, "--max-steps", "0", "--quiet"], capsys)
    assert code == 0, err


def test_dt_refuses_a_mass_column_with_density_option(tmp_path, capsys):
    """`dt FILE --density`: a file with a mass column is refused naming both (--density
    was silently ignored before); without --density its masses are used."""
    f = tmp_path / "m.csv"
    f.write_text("x,y,r,m\n0,0,1,1\n2,0,1,1\n")
    code, out, err = cli(["dt", f, "--density", "5"], capsys)
    assert_one_line_error(code, err, "density:", "mass column (m)", "m.csv", "5.0")
    assert out == ""
    code, out, err = cli(["dt", f, "--methods", "exact"], capsys)
    assert code == 0, err
    assert "masses from the file's mass column" in out


# -------------------------------------------------------- 5: checkpoint arrays
@pytest.mark.parametrize("edit, words", [
    (lambda x: x[:3], ("'spheres.x'", "shape (3, 3)", "expected (18, 3)")),
    (lambda x: x * np.nan, ("'spheres.x'", "non-finite value nan")),
], ids=["short", "nan"])
def test_restart_checks_checkpoint_array_shapes_and_values(run_copy, capsys, edit, words):
    """`run --restart` from a checkpoint whose per-particle positions are cut to 3 of 18
    rows (the kernels read past the end) or NaN (a 'diverged' run) is refused naming
    the array, its shape or value; the run folder is untouched."""
    case, run, checkpoint = run_copy
    edit_checkpoint(checkpoint, **{"spheres.x": edit(np.load(checkpoint)["spheres.x"])})
    before = snapshot(run)
    code, _, err = cli(["run", case, "--out", run, "--quiet", "--restart", checkpoint], capsys)
    assert_one_line_error(code, err, "restart:", str(checkpoint), *words)
    assert snapshot(run) == before


def test_restart_checks_pair_arrays_against_the_pair_count(run_copy, capsys):
    """A pair-history array with fewer rows than the pair list is refused naming it and
    the pair count (as is a pair index beyond the particles)."""
    case, run, checkpoint = run_copy
    data = np.load(checkpoint)
    n_pairs = len(data["pairs.i"])
    edit_checkpoint(checkpoint, **{"pairs.shear": data["pairs.shear"][:2]})
    code, _, err = cli(["run", case, "--out", run, "--quiet", "--restart", checkpoint], capsys)
    assert_one_line_error(code, err, "'pairs.shear'", "shape (2, 3)", f"({n_pairs}, 3)")
    j = data["pairs.j"].copy()
    j[0] = 99
    edit_checkpoint(checkpoint, **{"pairs.shear": data["pairs.shear"], "pairs.j": j})
    code, _, err = cli(["run", case, "--out", run, "--quiet", "--restart", checkpoint], capsys)
    assert_one_line_error(code, err, "'pairs.j'", "particle index 99")


def test_dt_checks_checkpoint_array_shapes_without_warnings(run_copy, capsys):
    """`dt CHECKPOINT` with positions cut to 3 rows: the same one line naming the array
    and its shape, and no RuntimeWarning from computing on it first."""
    case, _, checkpoint = run_copy
    edit_checkpoint(checkpoint, **{"spheres.x": np.load(checkpoint)["spheres.x"][:3]})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code, out, err = cli(["dt", checkpoint, "--case", case, "--methods", "exact"], capsys)
    assert_one_line_error(code, err, str(checkpoint), "'spheres.x'", "shape (3, 3)")
    assert out == ""
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)]


# ------------------------------------------------------------- 6: run state
@pytest.mark.parametrize("field, value, words", [
    ("stage", -3, ("stage must be an integer in [0, 1]", "got -3")),
    ("stage", 7, ("stage must be an integer in [0, 1]", "got 7")),
    ("stage_step", -100, ("stage_step must be an integer >= 0", "got -100")),
    ("stage_start_time", float("nan"), ("stage_start_time must be a finite number", "got nan")),
])
def test_restart_range_checks_the_run_state(run_copy, capsys, field, value, words):
    """The run state beside a checkpoint with a stage outside the case's stages (an
    IndexError traceback and a 'failed' run.json before), a negative step count (110
    steps run silently before) or a NaN time is refused naming the key and value; the
    run folder is untouched."""
    case, run, checkpoint = run_copy
    edit_state(checkpoint, **{field: value})
    before = snapshot(run)
    code, _, err = cli(["run", case, "--out", run, "--quiet", "--restart", checkpoint], capsys)
    assert_one_line_error(code, err, "restart:", "step0000000004.json", *words)
    assert snapshot(run) == before
    assert json.loads((run / "run.json").read_text())["status"] == "completed"


@pytest.mark.parametrize("stage", [-3, 7])
def test_dt_range_checks_the_run_state_stage(run_copy, capsys, stage):
    """`dt CHECKPOINT` with a stage outside the case's stages in the run state is refused
    naming the key and value (it silently applied the wrong stages before)."""
    case, _, checkpoint = run_copy
    edit_state(checkpoint, stage=stage)
    code, out, err = cli(["dt", checkpoint, "--case", case, "--methods", "exact"], capsys)
    assert_one_line_error(code, err, "checkpoint:", "stage must be an integer in [0, 1]",
                          f"got {stage}")
    assert out == ""


# ------------------------------------------------ 12: end of a resting stage
def test_resting_stage_measures_kinetic_energy_before_warning(tmp_path, capsys):
    """A stage `until_kinetic_below` that ends on its max_steps before its first check
    (check_every 100 > 10 steps) measures the kinetic energy there: a packing at rest is
    below the limit, logged as such, with no 'still above' warning."""
    case = tmp_path / "case.toml"
    case.write_text(CASE.format(stage="").replace(
        "steps = 6\n", "until_kinetic_below = 1e-3\nmax_steps = 10\n"))
    out = tmp_path / "out"
    code, _, err = cli(["run", case, "--out", out, "--quiet"], capsys)
    assert code == 0, err
    log = (out / "run.log").read_text()
    assert "still above" not in log and "WARNING" not in err
    assert "below 0.001 after 10 steps" in log


# ----------------------------------------------------- 13: over-long names
@pytest.mark.parametrize("argv, option", [
    (["run", "{case}", "--out", LONG, "--max-steps", "0", "--quiet"], "out:"),
    (["sweep", "{case}", "--param", "contact.mu=0.1", "--out", LONG], "out:"),
    (["paper", "--out", LONG, "--quiet"], "out:"),
    (["dt", "{csv}", "--plot", LONG + ".png"], "plot:"),
    (["dt", "{csv}", "--mode-vtk", LONG + ".vtu"], "mode-vtk:"),
], ids=["run", "sweep", "paper", "dt-plot", "dt-mode-vtk"])
def test_over_long_output_names_name_the_option(tmp_path, capsys, monkeypatch, argv, option):
    """An output name longer than the file system takes: one line naming the option and
    the length, exit 2, nothing written (exit 1 with the bare OSError 'File name too
    long' before: Path.exists raises it on Python 3.11)."""
    monkeypatch.chdir(tmp_path)
    case = write_case(tmp_path)
    csv = tmp_path / "a.csv"
    csv.write_text("x,y,r\n0,0,1\n2,0,1\n")
    before = sorted(p.name for p in tmp_path.iterdir())
    argv = [a.format(case=case, csv=csv) for a in argv]
    code, out, err = cli(argv, capsys)
    assert_one_line_error(code, err, option, "bytes long")
    assert out == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == before


# ------------------------------------------------- 14: --overwrite and inputs
def test_overwrite_refuses_to_replace_the_case_file(tmp_path, capsys, monkeypatch):
    """`cd DIR; demstep run case.toml --out . --overwrite` would replace the user's
    case.toml with the resolved case: refused naming --out and the input; the folder is
    untouched."""
    folder = tmp_path / "ow"
    folder.mkdir()
    write_case(folder)
    monkeypatch.chdir(folder)
    before = snapshot(folder)
    code, _, err = cli(["run", "case.toml", "--out", ".", "--overwrite", "--max-steps", "0",
                        "--quiet"], capsys)
    assert_one_line_error(code, err, "out:", "case.toml", "input case")
    assert snapshot(folder) == before


def test_overwrite_refuses_to_delete_an_input_particle_file(tmp_path, capsys):
    """A particle file named history.csv in the --out folder would be deleted by
    --overwrite (and replaced by the history): refused naming the key and the file."""
    folder = tmp_path / "ow"
    folder.mkdir()
    (folder / "history.csv").write_text("x,y,r\n0,0,1\n2,0,1\n")
    case = folder / "c.toml"
    case.write_text(CASE.format(stage="").replace(
        'generator = "lattice"\nlattice = "hex"\nradius = 1.0\nsize = [3, 3]\n',
        'generator = "file"\npath = "history.csv"\n'))
    before = snapshot(folder)
    code, _, err = cli(["run", case, "--out", folder, "--overwrite", "--max-steps", "0",
                        "--quiet"], capsys)
    assert_one_line_error(code, err, "out:", "particles.path", "history.csv")
    assert snapshot(folder) == before


# --------------------------------------------------- 15: dt output folders
@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux /proc")
@pytest.mark.parametrize("option, name", [("--mode-vtk", "x.vtu"), ("--plot", "x.png")])
def test_dt_checks_output_folders_before_the_analysis(tmp_path, capsys, option, name):
    """`dt --mode-vtk /proc/x.vtu` (a folder that takes no files although its permission
    bits say writable): one line naming the option and the folder before the analysis
    runs (the analysis was printed first, then an error naming a temporary file)."""
    csv = tmp_path / "a.csv"
    csv.write_text("x,y,r\n0,0,1\n2,0,1\n")
    code, out, err = cli(["dt", csv, option, f"/proc/{name}"], capsys)
    assert_one_line_error(code, err, option[2:] + ":", "'/proc'")
    assert out == ""


# ------------------------------------------------------------ 16: paper --out
def test_paper_refuses_a_non_empty_or_locked_folder(tmp_path, capsys, monkeypatch):
    """`paper --out` follows run's rule: a non-empty folder is refused (one line, the
    folder untouched), and a folder another process holds is refused by its lock; the
    study never starts (it wrote into any folder before)."""
    def never(*args, **kwargs):
        raise AssertionError("the study started")

    monkeypatch.setattr("demstep.experiments.paper.paper_table", never)
    out = tmp_path / "paper"
    out.mkdir()
    (out / "notes.txt").write_text("mine\n")
    before = snapshot(out)
    code, _, err = cli(["paper", "--out", out, "--quiet"], capsys)
    assert_one_line_error(code, err, "out:", str(out), "not empty")
    assert "--overwrite" in err
    assert snapshot(out) == before
    # with --overwrite the study starts there, and the user's other files stay
    with pytest.raises(AssertionError, match="the study started"):
        cli(["paper", "--out", out, "--quiet", "--overwrite"], capsys)
    assert (out / "notes.txt").read_text() == "mine\n"
    locked = tmp_path / "locked"
    locked.mkdir()
    with FolderLock(locked, "out"):
        code, _, err = cli(["paper", "--out", locked, "--quiet"], capsys)
    assert_one_line_error(code, err, "out:", "in use by another demstep process")
    assert list(locked.iterdir()) == []


@pytest.mark.parametrize("argv", [["run", LONG + ".toml", "--out", "o", "--quiet"],
                                  ["sweep", LONG + ".toml", "--param", "contact.mu=0.1",
                                   "--out", "o"]], ids=["run", "sweep"])
def test_an_over_long_case_file_name_gives_one_line(tmp_path, capsys, monkeypatch, argv):
    """A case file name longer than the file system takes: one line naming the case file,
    exit 2, nothing written (Path.is_file raised on Python 3.11: exit 1)."""
    monkeypatch.chdir(tmp_path)
    code, _, err = cli(argv, capsys)
    assert_one_line_error(code, err, "case file", "too long")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("option", ["--kn", "--density"])
def test_option_numbers_with_underscores_are_refused(tmp_path, capsys, option):
    """Python's float() reads '1_0' as 10: an option given so is refused, naming it."""
    csv = tmp_path / "a.csv"
    csv.write_text("x,y,r\n0,0,1\n2,0,1\n")
    argv = ["dt", csv, "--kn", "1e4", "--density", "1", option, "1_0"]
    code, out, err = cli(argv, capsys)
    assert code == 2 and "1_0" in err and option.strip("-") in err and out == ""
