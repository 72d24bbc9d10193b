"""Reliability under faults and bad input (issue 13): every item reproduced.

Each bad input gives one line naming the cause, a non-zero exit (2 for bad input) and
writes nothing; faults (a second process, signals, a killed worker pool, a closed
pipe, no numba cache) end cleanly with the state recorded."""

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, cli, snapshot

from demstep.case import build_simulation, case_from_text, load_case
from demstep.errors import InputError
from demstep.io.atomic import write_text_atomic
from demstep.io.checkpoint import load_checkpoint
from demstep.io.history import read_history
from demstep.io.lock import LOCK_NAME, FolderLock
from demstep.kernels.neighbors import build_pair_list
from demstep.runner import run_case

import reference

SRC = Path(__file__).resolve().parent.parent / "src"

SMALL = """
name = "{name}"
[particles]
generator = "lattice"
lattice = "hex"
radius = 1.0
size = [4, 3]
density = 1.0
[contact]
law = "linear"
k_n = 1.0e4
mu = 0.3
[box]
margin = 0.0
[timestep]
alpha = 0.1
[[stages]]
name = "squeeze"
steps = {steps}
damping = {{ local = 0.1 }}
[stages.walls."y+"]
motion = "velocity"
velocity = [0.0, -0.01]
[output]
history_every = 25
checkpoint_every = {checkpoint_every}
"""


def write_case(folder, name="small", steps=300, checkpoint_every=100, extra=""):
    path = Path(folder) / f"{name}.toml"
    path.write_text(SMALL.format(name=name, steps=steps, checkpoint_every=checkpoint_every)
                    + extra)
    return path





def start_run(case, out, *extra, env=None):
    return subprocess.Popen([sys.executable, "-m", "demstep.cli", "run", str(case), "--out",
                             str(out), "--quiet", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def wait_for(predicate, timeout=120.0, proc=None):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        if proc is not None and proc.poll() is not None:
            return predicate()
        time.sleep(0.05)
    return False


def history_rows(out):
    path = Path(out) / "history.csv"
    try:
        return path.read_text().count("\n") - 1
    except OSError:
        return 0


def run_json(out):
    return json.loads((Path(out) / "run.json").read_text())


# =============================================== 1. one output folder, one writer
def test_folder_lock_excludes_a_second_holder(tmp_path):
    first = FolderLock(tmp_path).acquire()
    with pytest.raises(InputError, match=r"in use by another demstep process \(pid \d+"):
        FolderLock(tmp_path).acquire()
    first.release()
    with FolderLock(tmp_path):  # free again
        assert (tmp_path / LOCK_NAME).is_file()
    assert not (tmp_path / LOCK_NAME).exists()  # a finished holder leaves no file


def test_folder_lock_whose_file_was_deleted_while_waiting_is_taken_anew(tmp_path,
                                                                        monkeypatch):
    """The holder deletes the lock file when it releases it. A process that opened the
    file just before that would lock a deleted file, and a third process would create
    and lock a new one: two holders. It must notice and open the new file instead."""
    from demstep.io import lock as lock_module

    first = FolderLock(tmp_path).acquire()
    real_open = os.open
    opened = []

    def open_then_holder_releases(*args, **kwargs):
        fd = real_open(*args, **kwargs)
        if args and str(args[0]).endswith(LOCK_NAME):
            opened.append(os.fstat(fd).st_ino)
            if len(opened) == 1:
                first.release()  # the holder ends between this open and the flock
        return fd

    monkeypatch.setattr(lock_module.os, "open", open_then_holder_releases)
    second = FolderLock(tmp_path).acquire()
    monkeypatch.undo()
    assert len(opened) == 2
    assert os.fstat(second._fd).st_ino == os.stat(tmp_path / LOCK_NAME).st_ino
    with pytest.raises(InputError, match="in use by another demstep process"):
        FolderLock(tmp_path).acquire()
    second.release()


def test_folder_lock_release_leaves_a_newer_holders_file_alone(tmp_path):
    """A lock file deleted by hand while its holder runs: a second process makes and
    locks a new one; when the first ends it must not delete the second's file (a third
    process would then lock a file of its own beside the second)."""
    first = FolderLock(tmp_path).acquire()
    (tmp_path / LOCK_NAME).unlink()
    second = FolderLock(tmp_path).acquire()
    first.release()
    assert (tmp_path / LOCK_NAME).is_file()
    with pytest.raises(InputError, match="in use by another demstep process"):
        FolderLock(tmp_path).acquire()
    second.release()
    assert not (tmp_path / LOCK_NAME).exists()


def test_folder_lock_gives_up_when_its_file_keeps_changing(tmp_path, monkeypatch):
    """A file system on which the locked file never matches the path (or something
    replacing the file all the time) ends in a one-line error, not an endless loop."""
    from demstep.io import lock as lock_module

    monkeypatch.setattr(lock_module, "_is_file_at", lambda fd, path: False)
    with pytest.raises(InputError, match=f"changed under each of {lock_module.LOCK_ATTEMPTS}"):
        FolderLock(tmp_path).acquire()
    monkeypatch.undo()
    with FolderLock(tmp_path):  # no descriptor left holding the lock
        pass


def test_folder_lock_on_a_file_system_without_locks(tmp_path, monkeypatch, caplog):
    """Some network mounts refuse flock (ENOLCK): the run goes on, with a warning,
    rather than being refused as if another process held the folder."""
    import errno

    from demstep.io import lock as lock_module

    def no_locks(fd, operation):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(lock_module.fcntl, "flock", no_locks)
    with FolderLock(tmp_path) as held:
        assert held.held
    assert "cannot lock" in caplog.text and "No locks available" in caplog.text


def test_run_refused_while_another_process_writes_the_folder(tmp_path, capsys):
    """The second of two runs into one --out exits 2 and leaves the first's outputs
    alone (before: both ran and interleaved their files)."""
    case_a = write_case(tmp_path, "first", steps=10**8)
    case_b = write_case(tmp_path, "second", steps=50)
    out = tmp_path / "out"
    proc = start_run(case_a, out)
    try:
        assert wait_for(lambda: history_rows(out) >= 2, proc=proc), proc.stderr
        before = (out / "case.toml").read_text()
        code, _, err = cli(["run", case_b, "--out", out, "--overwrite"], capsys)
        assert_one_line_error(code, err, "out:", "in use by another demstep process",
                              f"pid {proc.pid}")
        assert (out / "case.toml").read_text() == before and 'name = "first"' in before
        assert run_json(out)["pid"] == proc.pid
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert run_json(out)["status"] == "interrupted"


def test_two_runs_started_together_one_wins(tmp_path):
    """Started at the same moment: one run writes the folder, the other exits 2, and
    every file in the folder comes from the same case."""
    cases = [write_case(tmp_path, name, steps=2000) for name in ("one", "two")]
    out = tmp_path / "out"
    procs = [start_run(case, out) for case in cases]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    codes = sorted(code for code, _ in results)
    assert codes == [0, 2], results
    loser = next(err for code, err in results if code == 2)
    # (the loser finds the folder locked, or being written, or, when the winner's steps
    # were compiled already and it finished first, holding its results)
    assert ("in use by another demstep process" in loser or "not empty" in loser
            or "holds the results of" in loser)
    winner = json.loads((out / "run.json").read_text())["case"]
    name = Path(winner).stem
    assert f'name = "{name}"' in (out / "case.toml").read_text()
    assert read_history(out / "history.csv")["step"][-1] == 2000


# ==================================== 2. an --out that cannot be a writable folder
@pytest.fixture
def small(tmp_path):
    return write_case(tmp_path, steps=50)


def out_cases(tmp_path):
    (tmp_path / "afile").write_text("not a folder")
    return {"parent is a file": (tmp_path / "afile" / "out", "is a file"),
            "is a file": (tmp_path / "afile", "not a folder"),
            "under /proc": (Path("/proc/demstep-no-such-folder/out"), "out:")}


@pytest.mark.parametrize("kind", ["parent is a file", "is a file", "under /proc"])
@pytest.mark.parametrize("command", ["run", "sweep", "fcc"])
def test_out_that_cannot_be_a_folder(tmp_path, small, capsys, kind, command):
    out, words = out_cases(tmp_path)[kind]
    before = snapshot(tmp_path)
    argv = {"run": ["run", small, "--out", out],
            "sweep": ["sweep", small, "--param", "contact.mu=0.1", "--out", out],
            "fcc": ["fcc", "--out", out, "--strain", "1e-4"]}[command]
    code, _, err = cli(argv, capsys)
    assert_one_line_error(code, err, words)
    assert snapshot(tmp_path) == before


def test_out_in_a_read_only_folder(tmp_path, small, capsys, monkeypatch):
    """A read-only parent (os.access says so, as it does for any user but root) and a
    file system that refuses the folder at creation both give one line."""
    ro = tmp_path / "ro"
    ro.mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw:
                        False if Path(p) == ro else real_access(p, mode, **kw))
    code, _, err = cli(["run", small, "--out", ro / "out"], capsys)
    assert_one_line_error(code, err, "cannot write into", "not writable")
    monkeypatch.undo()

    def refuse(self, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(Path, "mkdir", refuse)
    code, _, err = cli(["run", small, "--out", ro / "out"], capsys)
    assert_one_line_error(code, err, "cannot create the folder", "Permission denied")
    assert list(ro.iterdir()) == []


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0,
                    reason="root writes into read-only folders")
def test_out_in_a_read_only_folder_for_real(tmp_path, small, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        code, _, err = cli(["run", small, "--out", ro / "out"], capsys)
        assert_one_line_error(code, err, "out:")
    finally:
        ro.chmod(0o755)


# ========================================================= 3. initial overlaps
PAIR_CASE = """
[particles]
generator = "file"
path = "pair.csv"
density = 1000.0
{fixed}
[contact]
law = "linear"
k_n = 1.0e4
[[stages]]
steps = 100
{numerics}
"""


def pair_case(tmp_path, rows, numerics="", fixed=""):
    (tmp_path / "pair.csv").write_text("x,y,z,r\n" + "\n".join(rows) + "\n")
    path = tmp_path / "pair.toml"
    path.write_text(PAIR_CASE.format(numerics=numerics, fixed=fixed))
    return path


def test_heavy_initial_overlap_refused_unless_allowed(tmp_path, capsys):
    """Centres 0.1 apart with r = 0.4 (an overlap of 1.75 radii) used to run to
    'completed' with particles leaving at 17 m/s."""
    case = pair_case(tmp_path, ["0,0,0,0.4", "0.1,0,0,0.4"])
    code, _, err = cli(["run", case, "--out", tmp_path / "out"], capsys)
    assert_one_line_error(code, err, "particles 0 and 1 overlap by 1.75 of the smaller radius",
                          "numerics.max_initial_overlap = 0.05")
    assert not (tmp_path / "out").exists()
    allowed = pair_case(tmp_path, ["0,0,0,0.4", "0.1,0,0,0.4"],
                        numerics="[numerics]\nmax_initial_overlap = 2.0")
    sim = build_simulation(load_case(allowed))
    assert sim.particles.n == 2


def test_sort_every_read_from_the_case_and_checked(tmp_path, capsys):
    """numerics.sort_every: the engine's re-sorting interval (default 1000, 0: never); a
    negative or fractional value is refused in one line naming the key."""
    rows = ["0,0,0,0.4", "0.79,0,0,0.4"]
    assert build_simulation(load_case(pair_case(tmp_path, rows))).sort_every == 1000
    never = pair_case(tmp_path, rows, numerics="[numerics]\nsort_every = 0")
    assert build_simulation(load_case(never)).sort_every is None
    for bad in ("-1", "2.5", '"often"'):
        case = pair_case(tmp_path, rows, numerics=f"[numerics]\nsort_every = {bad}")
        code, _, err = cli(["run", case, "--out", tmp_path / "out"], capsys)
        assert_one_line_error(code, err, "numerics.sort_every")
        assert not (tmp_path / "out").exists()


def test_small_overlaps_and_fixed_pairs_accepted(tmp_path):
    small_overlap = pair_case(tmp_path, ["0,0,0,0.4", "0.79,0,0,0.4"])  # 2.5 % of r
    assert build_simulation(load_case(small_overlap)).particles.n == 2
    fixed_pair = pair_case(tmp_path, ["0,0,0,0.4", "0.1,0,0,0.4", "3,0,0,0.4"],
                           fixed="fixed = { indices = [0, 1] }")
    assert build_simulation(load_case(fixed_pair)).fixed.sum() == 2


def test_coincident_centres_refused_even_when_overlaps_are_allowed(tmp_path, capsys):
    case = pair_case(tmp_path, ["1,2,3,0.4", "1,2,3,0.5"],
                     numerics="[numerics]\nmax_initial_overlap = 10.0")
    code, _, err = cli(["run", case, "--out", tmp_path / "out"], capsys)
    assert_one_line_error(code, err, "particles 0 and 1 have coincident centres")
    assert not (tmp_path / "out").exists()


# ================================== 4. every check that can be made before writing
def test_periodic_length_smaller_than_a_particle_refused_before_writing(tmp_path, capsys):
    """Used to be caught at the first neighbour search, after run.json said 'running'."""
    case = pair_case(tmp_path, ["0.5,0,0,0.4", "3,0,0,0.4"],
                     numerics="[periodic]\nx = 0.7")
    code, _, err = cli(["run", case, "--out", tmp_path / "out"], capsys)
    assert_one_line_error(code, err, "periodic: box length 0.7 along axis x")
    assert not (tmp_path / "out").exists()


def test_servo_wall_without_area_refused_before_writing(tmp_path, capsys):
    """A stage that makes a lone wall servo-controlled (no opposite wall, no periodic
    length: its loaded area is unknown, its speed NaN) is an input error."""
    case = pair_case(tmp_path, ["0,0,0,0.4", "3,0,0,0.4"])
    text = case.read_text().replace("[[stages]]\nsteps = 100", """[[walls]]
name = "floor"
point = [0.0, 0.0, -0.4]
normal = [0.0, 0.0, 1.0]
[[stages]]
steps = 10
[[stages]]
steps = 10
[stages.walls.floor]
motion = "servo"
target_stress = 1.0""")
    case.write_text(text)
    code, _, err = cli(["run", case, "--out", tmp_path / "out"], capsys)
    assert_one_line_error(code, err, 'stages[1]: wall "floor" is servo-controlled',
                          "give its area")
    assert not (tmp_path / "out").exists()
    case.write_text(text + "\narea = 4.0\n")
    assert cli(["run", case, "--out", tmp_path / "out"], capsys)[0] == 0


def test_failure_during_the_run_is_recorded(tmp_path):
    """An exception in the middle of a run leaves run.json at 'failed' with the
    message, not at 'running'."""
    case = load_case(write_case(tmp_path))

    def boom(sim):
        if sim.step >= 100:
            raise RuntimeError("disk on fire")

    with pytest.raises(RuntimeError, match="disk on fire"):
        run_case(case, tmp_path / "out", quiet=True, on_chunk=boom, chunk_steps=50)
    info = run_json(tmp_path / "out")
    assert info["status"] == "failed" and info["message"] == "RuntimeError: disk on fire"
    assert info["step"] == 100 and info["results"] is True


# =================================================== 5. particles far away
def test_pair_list_with_far_particles_equals_brute_force():
    """A particle at 1e7 (no walls) gave 'negative dimensions not allowed' (the cell
    count overflowed int64), at 1e300 an OverflowError: the grid is bounded now."""
    rng = np.random.default_rng(3)
    x = np.zeros((60, 3))
    x[:, :] = rng.uniform(0, 6, (60, 3))
    r = rng.uniform(0.3, 0.6, 60)
    for far in (1e7, 1e300):
        y = x.copy()
        y[-1] = far
        y[-2] = [-far, far, 0.0]
        pi, pj = build_pair_list(y, r, 0.1, np.zeros(3))
        assert set(zip(pi.tolist(), pj.tolist())) == reference.brute_force_pairs(y[:-2], r[:-2], 0.1)


def test_piled_particles_are_refused_before_the_pair_search_allocates():
    """A lattice scaled into a periodic box a thousand times too small (found by the case
    fuzzer) made the pair list grow as N^2 until 12 GB: the search refuses with the cell
    it found; a dense packing with a size ratio of 10 still passes."""
    from demstep.errors import InputError

    rng = np.random.default_rng(5)
    n = 4000
    r = np.full(n, 0.5)
    x = rng.uniform(0, 3.5, (n, 3))  # 4000 spheres of 0.52 each in a box of 43
    with pytest.raises(InputError, match="within one neighbour cell"):
        build_pair_list(x, r, 0.1, np.full(3, 3.5))
    # bidisperse, size ratio 10: 4 large spheres and 3000 small ones in the gaps
    big = np.array([[2.5, 2.5, 2.5], [7.5, 2.5, 2.5], [2.5, 7.5, 2.5], [7.5, 7.5, 7.5]])
    small = rng.uniform(0, 10, (20000, 3))
    gap = np.min(np.linalg.norm(small[:, None, :] - big[None], axis=2), axis=1) > 2.6
    small = small[gap][:3000]
    y = np.vstack([big, small])
    s = np.concatenate([np.full(4, 2.5), np.full(len(small), 0.25)])
    pi, pj = build_pair_list(y, s, 0.05, np.zeros(3))
    assert set(zip(pi.tolist(), pj.tolist())) == reference.brute_force_pairs(y, s, 0.05)


def test_far_particle_runs_and_an_absurd_one_is_refused(tmp_path, capsys):
    case = pair_case(tmp_path, ["0,0,0,0.4", "1e7,1e7,1e7,0.4"])
    code, _, err = cli(["run", case, "--out", tmp_path / "out"], capsys)
    assert code == 0, err
    assert run_json(tmp_path / "out")["status"] == "completed"
    case = pair_case(tmp_path, ["0,0,0,0.4", "1e12,0,0,0.4"])
    code, _, err = cli(["run", case, "--out", tmp_path / "out2"], capsys)
    assert_one_line_error(code, err, "particle 1 lies at 1e+12 from the origin")
    assert not (tmp_path / "out2").exists()
    # beyond any consistent units: refused where the file is read, naming line and column
    case = pair_case(tmp_path, ["0,0,0,0.4", "1e300,0,0,0.4"])
    code, _, err = cli(["run", case, "--out", tmp_path / "out3"], capsys)
    assert_one_line_error(code, err, ":3: column 'x': must be 0 or between 1e-100 and 1e+100",
                          "got '1e300'")
    assert not (tmp_path / "out3").exists()


# ================================================== 6. checkpoints and folders
@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("finished")
    case = write_case(folder, steps=200)
    result = run_case(load_case(case), folder / "out", quiet=True)
    assert result.status == "completed"
    return case, result.checkpoint


@pytest.mark.parametrize("damage,words", [
    ("truncated", "a damaged or truncated checkpoint (BadZipFile"),
    ("flipped", "a damaged or truncated checkpoint"),
    ("empty", "not a demstep checkpoint (.npz): an empty file"),
    ("text", "not a demstep checkpoint (.npz): not a zip archive"),
])
def test_damaged_checkpoint_gives_one_line(tmp_path, finished_run, capsys, damage, words):
    case, checkpoint = finished_run
    data = checkpoint.read_bytes()
    bad = tmp_path / "bad.npz"
    bad.write_bytes({"truncated": data[: len(data) // 2],
                     "flipped": data[:300] + bytes(b ^ 0xFF for b in data[300:700]) + data[700:],
                     "empty": b"", "text": b"x,y,r\n1,2,3\n"}[damage])
    shutil.copy(checkpoint.with_suffix(".json"), bad.with_suffix(".json"))
    code, _, err = cli(["run", case, "--out", tmp_path / "out", "--restart", bad], capsys)
    assert_one_line_error(code, err, "restart:", words)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("state", ["[1, 2]", "\"text\"", "\u00ff"])
def test_a_run_state_that_is_no_json_object_gives_one_line(tmp_path, finished_run, capsys,
                                                           state):
    """A run state beside the checkpoint that is valid JSON but no object (or no JSON):
    one line naming the file, for `run --restart` and `dt` (AttributeError before)."""
    case, checkpoint = finished_run
    bad = tmp_path / "c.npz"
    shutil.copy(checkpoint, bad)
    bad.with_suffix(".json").write_text(state, encoding="latin-1")
    code, _, err = cli(["run", case, "--out", tmp_path / "out", "--restart", bad], capsys)
    assert_one_line_error(code, err, "restart:", "not a demstep run state")
    assert not (tmp_path / "out").exists()
    code, _, err = cli(["dt", bad, "--case", case], capsys)
    assert_one_line_error(code, err, "not a demstep run state")


def test_restart_from_the_run_state_json(tmp_path, finished_run, capsys):
    case, checkpoint = finished_run
    code, _, err = cli(["run", case, "--out", tmp_path / "out", "--restart",
                        checkpoint.with_suffix(".json")], capsys)
    assert_one_line_error(code, err, "is the run state beside a checkpoint",
                          str(checkpoint))
    assert not (tmp_path / "out").exists()


def test_folders_given_as_files(tmp_path, finished_run, capsys):
    case, checkpoint = finished_run
    folder = tmp_path / "a_folder"
    folder.mkdir()
    code, _, err = cli(["run", folder, "--out", tmp_path / "out"], capsys)
    assert_one_line_error(code, err, "a folder, not a case file")
    text = case.read_text().replace('generator = "lattice"\nlattice = "hex"\nradius = 1.0\n'
                                    'size = [4, 3]', f'generator = "file"\npath = "{folder}"')
    file_case = tmp_path / "file.toml"
    file_case.write_text(text)
    code, _, err = cli(["run", file_case, "--out", tmp_path / "out"], capsys)
    assert_one_line_error(code, err, "particles.path: a folder, not a file")
    sim = build_simulation(load_case(case))
    with pytest.raises(InputError, match="a folder, not a checkpoint file"):
        load_checkpoint(sim, folder)
    assert not (tmp_path / "out").exists()


# ============================================================ 8. a closed stdout
def test_closed_stdout_ends_quietly_as_unix_tools_do():
    """``demstep dt ... | true``: a BrokenPipeError traceback before; now exit 141 (128 +
    SIGPIPE) and nothing on stderr."""
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader is gone before anything is written
    proc = subprocess.run([sys.executable, "-m", "demstep.cli", "dt", "--lattice", "square",
                           "--size", "2", "--json"], stdout=write_end, stderr=subprocess.PIPE,
                          text=True, timeout=300)
    os.close(write_end)
    assert proc.returncode == 141, proc.stderr
    assert proc.stderr == ""


# ======================================================== 9. a spreadsheet's BOM
def test_csv_with_byte_order_mark(tmp_path):
    from demstep.io.formats import read_csv

    path = tmp_path / "excel.csv"
    path.write_bytes("x,y,z,r\r\n0,0,0,1\r\n3,0,0,1.5\r\n".encode("utf-8-sig"))
    assert path.read_bytes()[:3] == b"\xef\xbb\xbf"
    data = read_csv(path)
    assert np.array_equal(data.x, [[0, 0, 0], [3, 0, 0]]) and np.array_equal(data.r, [1, 1.5])
    case = tmp_path / "case.toml"
    case.write_text(PAIR_CASE.format(numerics="", fixed="").replace("pair.csv", "excel.csv"))
    assert build_simulation(load_case(case)).particles.n == 2


# =================================================== 10. no numba cache location
def _python(code, env):
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, timeout=600)


def _env(**changes):
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(changes)
    return env


def test_no_cache_locator_falls_back_with_one_warning():
    """numba finds no cache locator: 'RuntimeError: cannot cache function ...' at import
    before; now the kernels compile without the cache after one warning."""
    env = _env(NUMBA_CACHE_LOCATOR_CLASSES="ZipCacheLocator",
               PYTHONPATH=os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")]))
    proc = _python("import demstep.engine, demstep._numba as n; print(n.CACHE_AVAILABLE)", env)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "False"
    assert proc.stderr.count("no writable cache location") == 1, proc.stderr
    assert "Traceback" not in proc.stderr


def test_unwritable_cache_folder_falls_back_with_one_warning(tmp_path):
    """The package in a zip archive and no writable home: numba's cache folder cannot
    be made (NotADirectoryError at the first call before); now one warning."""
    archive = tmp_path / "demstep.zip"
    with zipfile.ZipFile(archive, "w") as zf:
        for path in (SRC / "demstep").rglob("*"):
            if path.is_file() and "__pycache__" not in path.parts:
                zf.write(path, path.relative_to(SRC))
    env = _env(HOME="/dev/null/home", XDG_CACHE_HOME="/dev/null/cache", PYTHONPATH=str(archive))
    code = ("import numpy as np, demstep.kernels.neighbors as nb; "
            "print(nb.__file__); print(nb._bounds(np.arange(12.0).reshape(4, 3))[1])")
    proc = _python(code, env)
    assert proc.returncode == 0, proc.stderr
    assert str(archive) in proc.stdout and "[ 9. 10. 11.]" in proc.stdout
    assert proc.stderr.count("no writable cache location") == 1, proc.stderr



def test_threads_on_tbb_warn_once_unless_chosen(monkeypatch):
    """numba's threads on TBB (numba chose it before demstep was imported): one
    warning naming the fix; none when the user chose TBB, none on one thread, none
    on OpenMP."""
    import warnings

    import numba

    import demstep._numba as nm

    def warnings_for(layer, chosen="default", threads=2):
        monkeypatch.setattr(nm, "_LAYER_WARNED", False)
        monkeypatch.setattr(numba, "threading_layer", lambda: layer)
        monkeypatch.setattr(numba, "get_num_threads", lambda: threads)
        monkeypatch.setattr(numba.config, "THREADING_LAYER", chosen)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            nm.warn_slow_threading_layer()
            nm.warn_slow_threading_layer()
        return [str(w.message) for w in caught]

    told = warnings_for("tbb")
    assert len(told) == 1 and "NUMBA_THREADING_LAYER=omp" in told[0]
    assert warnings_for("tbb", chosen="tbb") == []
    assert warnings_for("tbb", threads=1) == []
    assert warnings_for("omp") == []

# =========================================================== 11. signals
def send_at(step, *signals):
    def on_chunk(sim):
        if sim.step >= step and not on_chunk.sent:
            on_chunk.sent = True
            for sig in signals:
                os.kill(os.getpid(), sig)
    on_chunk.sent = False
    return on_chunk


def test_second_signal_aborts_without_a_checkpoint(tmp_path):
    case = load_case(write_case(tmp_path, steps=2000, checkpoint_every=0))
    before = signal.getsignal(signal.SIGINT)  # (SIG_IGN in a shell's background job)
    result = run_case(case, tmp_path / "out", quiet=True, chunk_steps=50,
                      on_chunk=send_at(200, signal.SIGINT, signal.SIGINT))
    assert result.status == "aborted" and result.signal == "SIGINT"
    assert result.exit_status == 130 and result.checkpoint is None
    assert list((tmp_path / "out" / "checkpoints").glob("*.npz")) == []
    info = run_json(tmp_path / "out")
    assert info["status"] == "aborted" and info["signal"] == "SIGINT"
    assert signal.getsignal(signal.SIGINT) is before


def test_sigterm_exits_143_and_sigint_130(tmp_path):
    case = load_case(write_case(tmp_path, steps=2000, checkpoint_every=0))
    for sig, code in ((signal.SIGTERM, 143), (signal.SIGINT, 130)):
        out = tmp_path / sig.name
        result = run_case(case, out, quiet=True, chunk_steps=50, on_chunk=send_at(200, sig))
        assert result.status == "interrupted" and result.exit_status == code
        assert run_json(out)["status"] == "interrupted" and result.checkpoint.is_file()


@pytest.mark.parametrize("exit_now", [True, False])
def test_signals_after_a_run_stopped_by_one(exit_now):
    """The command line's run stopped by SIGTERM returns and exits with 143: a second
    SIGTERM arriving after the run's handlers were removed used to kill the process by
    the default action (-15, seen once in CI under load). With ``exit_now`` (the command
    line) signals stay ignored after such a run; the Python API gets its handlers back."""
    from demstep.runner import StopRequest

    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        stop = StopRequest(exit_now=exit_now)
        stop.install()
        stop.started = True
        stop._handle(signal.SIGTERM, None)  # stop after this chunk, with a checkpoint
        stop.finished = True
        stop.restore()
        for sig in (signal.SIGINT, signal.SIGTERM):
            assert signal.getsignal(sig) == (signal.SIG_IGN if exit_now else before[sig])
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)
    finished = StopRequest(exit_now=True)  # a run that ended by itself: handlers back
    finished.install()
    finished.restore()
    assert {sig: signal.getsignal(sig) for sig in before} == before


@pytest.mark.parametrize("first,second,gap", [
    (signal.SIGTERM, signal.SIGINT, 0.0),
    (signal.SIGTERM, signal.SIGTERM, 0.02),
    (signal.SIGINT, signal.SIGINT, 0.02)])
def test_two_signals_to_a_real_process(tmp_path, first, second, gap):
    """Before: 'SystemError: CPUDispatcher(...) returned a result with an exception
    set' one time in ten, or 143 where 130 was due, and run.json left at 'running'.
    Now: the exit status is 128 + the signal that ended the run, recorded in run.json
    with the status, and no traceback (three rounds)."""
    case = write_case(tmp_path, "forever", steps=10**8, checkpoint_every=0)
    for k in range(3):
        out = tmp_path / f"out{k}"
        proc = start_run(case, out)
        assert wait_for(lambda: history_rows(out) >= 2, proc=proc), proc.stderr
        proc.send_signal(first)
        if gap:
            time.sleep(gap)
        proc.send_signal(second)
        _, err = proc.communicate(timeout=120)
        info = run_json(out)
        assert info["status"] in ("interrupted", "aborted"), info
        assert proc.returncode == 128 + signal.Signals[info["signal"]], (proc.returncode, info)
        assert "Traceback" not in err and "SystemError" not in err
        assert f"demstep run: {info['status']}: " in err


def test_ctrl_c_during_the_first_compilation(tmp_path):
    """With a cold numba cache the first chunk compiles for a minute or more; Ctrl-C
    used to act only after it. Now the run stops at once, run.json says it stopped
    before its first step, and the same command runs again without --overwrite."""
    case = write_case(tmp_path, steps=100, checkpoint_every=0)
    out = tmp_path / "out"
    cold = tmp_path / "numba-cache"
    cold.mkdir()
    proc = start_run(case, out, env=_env(NUMBA_CACHE_DIR=str(cold)))
    assert wait_for(lambda: (out / "run.json").is_file(), timeout=600, proc=proc), proc.stderr
    assert history_rows(out) == 0  # compiling
    sent = time.monotonic()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=600)
    took = time.monotonic() - sent
    assert proc.returncode == 130, err
    assert took < 20, f"took {took:.0f} s to stop"
    info = run_json(out)
    assert info["status"] == "interrupted" and info["results"] is False
    assert "before the first step" in info["message"]
    again = start_run(case, out)  # the warm cache of the test session; no --overwrite
    _, err = again.communicate(timeout=600)
    assert again.returncode == 0, err
    assert run_json(out)["status"] == "completed"


# ============================================ 12. umask and orphan temporary files
def test_outputs_honour_the_umask(tmp_path):
    """Atomic writes created every output with mode 0600 whatever the umask."""
    case = load_case(write_case(tmp_path, steps=100, extra="vtk_every = 50\n"))
    previous = os.umask(0o027)
    try:
        run_case(case, tmp_path / "out", quiet=True)
        write_text_atomic(tmp_path / "single.txt", "x")
    finally:
        os.umask(previous)
    files = [p for p in (tmp_path / "out").rglob("*") if p.is_file()]
    assert len(files) > 8 and any(p.suffix == ".npz" for p in files)
    assert any(p.suffix == ".vtu" for p in files)
    for p in files + [tmp_path / "single.txt"]:
        assert p.stat().st_mode & 0o777 == 0o640, p


def test_orphan_temporary_files_are_removed(tmp_path):
    """A SIGKILL between creating a temporary file and renaming it left *.tmp files
    for ever; the next run into the folder removes them (it holds the folder's lock)."""
    case = load_case(write_case(tmp_path, steps=100))
    out = tmp_path / "out"
    first = run_case(case, out, quiet=True, max_steps=50)
    orphans = [out / "checkpoints" / ".step0000000100.npz.0123abcd.tmp",
               out / "checkpoints" / "tmpab12_d34.npz.tmp", out / ".run.json.deadbeef.tmp"]
    for p in orphans:
        p.write_bytes(b"half")
    mine = out / "notes.tmp"
    mine.write_text("keep")
    run_case(case, out, quiet=True, restart=first.checkpoint)
    assert not any(p.exists() for p in orphans)
    assert mine.read_text() == "keep"


# ======================================================= 13. a sweep without workers
@pytest.fixture(scope="module")
def no_worker_scheduler():
    """A Dask scheduler that has no worker (all gone)."""
    from distributed import LocalCluster

    cluster = LocalCluster(n_workers=0, processes=False, protocol="tcp", host="127.0.0.1",
                           scheduler_port=0, dashboard_address=None)
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()


def test_sweep_without_workers_reports_and_gives_up(tmp_path, small, no_worker_scheduler):
    from demstep.sweep import run_sweep

    waits = []
    start = time.monotonic()
    result = run_sweep(small, tmp_path / "sweep", params=["contact.mu=0.1,0.2"],
                       scheduler=no_worker_scheduler, worker_timeout=1.5,
                       on_wait=lambda pending, seconds: waits.append((pending, seconds)))
    assert time.monotonic() - start < 60
    assert waits and waits[0][0] == 2
    assert [row["status"] for row in result.rows] == ["unfinished", "unfinished"]
    assert all("no Dask worker for" in row["error"] for row in result.rows)
    with open(result.summary_csv, newline="") as fh:
        assert [row["status"] for row in csv.DictReader(fh)] == ["unfinished", "unfinished"]


def test_sweep_cli_without_workers_says_so_and_exits_1(tmp_path, small, capsys,
                                                        no_worker_scheduler):
    code, out, err = cli(["sweep", small, "--param", "contact.mu=0.1,0.2", "--out",
                          tmp_path / "sweep", "--scheduler", no_worker_scheduler,
                          "--worker-timeout", "1", "--quiet"], capsys)
    assert code == 1, err
    assert "waiting for workers: 2 run(s) pending" in err and "giving up after 1 s" in err
    assert "2 unfinished" in out


def test_sweep_folder_is_locked(tmp_path, small, capsys, no_worker_scheduler):
    out = tmp_path / "sweep"
    out.mkdir()
    with FolderLock(out):
        code, _, err = cli(["sweep", small, "--param", "contact.mu=0.1", "--out", out,
                            "--scheduler", no_worker_scheduler], capsys)
    assert_one_line_error(code, err, "in use by another demstep process")
    assert list(out.iterdir()) == []  # nothing written, and the lock file gone with the lock


def test_unfinished_run_folder_is_marked(tmp_path):
    from demstep.sweep import mark_unfinished

    (tmp_path / "run.json").write_text(json.dumps({"status": "running"}))
    mark_unfinished(tmp_path, "NoWorkers: gone")
    assert run_json(tmp_path) == {"status": "unfinished", "message": "NoWorkers: gone"}


# ================================================================ 14. smaller
def test_fcc_says_where_a_diverged_state_goes(tmp_path, capsys, monkeypatch):
    """Without --out the state went to the temporary folder silently."""
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    code, out, err = cli(["fcc", "--alpha", "0.75", "--strain", "0.002", "--json"], capsys)
    assert code == 0 and json.loads(out)["status"] == "unstable"
    saved = list((tmp_path / "tmp").glob("demstep-diverged-*.npz"))
    assert len(saved) == 1 and f"its state is saved in {saved[0]}" in err
    code, out, err = cli(["fcc", "--alpha", "0.75", "--strain", "0.002", "--out",
                          tmp_path / "fcc"], capsys)
    saved = list((tmp_path / "fcc").glob("demstep-diverged-*.npz"))
    assert code == 0 and len(saved) == 1 and str(saved[0]) in err


def test_overflowing_density_named_without_numpy_warnings(tmp_path):
    text = SMALL.format(name="dense", steps=10, checkpoint_every=0).replace(
        "radius = 1.0", "radius = 1.0e80").replace("density = 1.0", "density = 1.0e90")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a numpy RuntimeWarning fails the test
        case = case_from_text(text, source="dense.toml")
        with pytest.raises(InputError) as info:
            build_simulation(case)
    message = str(info.value)
    assert message.startswith("dense.toml: particles.density: 1e+90 with radius 1e+80")
    assert "gives a mass of 3.14e+250 and a moment of inertia of inf" in message


@pytest.mark.parametrize("key,value", [("k_n", "1.0e308"), ("k_n", "1.0e-150"),
                                       ("mu", "1.0e200")])
def test_non_physical_magnitudes_refused(tmp_path, capsys, key, value):
    """k_n = 1e308 ran with dt around 1e-154."""
    text = SMALL.format(name="huge", steps=10, checkpoint_every=0)
    text = text.replace("k_n = 1.0e4", f"k_n = {value}" if key == "k_n" else "k_n = 1.0e4")
    text = text.replace("mu = 0.3", f"mu = {value}" if key == "mu" else "mu = 0.3")
    case = tmp_path / "huge.toml"
    case.write_text(text)
    code, _, err = cli(["run", case, "--out", tmp_path / "out"], capsys)
    assert_one_line_error(code, err, f"contact.{key}: must be 0 or between 1e-100 and 1e+100 "
                          f"in magnitude", f"got {float(value)!r}")
    assert not (tmp_path / "out").exists()


def test_restart_with_a_changed_case_needs_allowing(tmp_path, capsys):
    case = write_case(tmp_path, steps=200)
    first = run_case(load_case(case), tmp_path / "out", quiet=True, max_steps=100)
    capsys.readouterr()
    case.write_text(case.read_text().replace("mu = 0.3", "mu = 0.5"))
    before = snapshot(tmp_path / "out")
    code, _, err = cli(["run", case, "--out", tmp_path / "out", "--restart", first.checkpoint],
                       capsys)
    assert_one_line_error(code, err, "restart: the case differs", "--allow-changed-case")
    assert snapshot(tmp_path / "out") == before
    code, _, err = cli(["run", case, "--out", tmp_path / "out", "--allow-changed-case"], capsys)
    assert_one_line_error(code, err, "allow-changed-case: only used with --restart")
    code, _, err = cli(["run", case, "--out", tmp_path / "out", "--restart", first.checkpoint,
                        "--allow-changed-case"], capsys)
    assert code == 0, err
    assert run_json(tmp_path / "out")["restarts"][-1]["case_changed"] is True


# ============================================================ 15. energy alarm
ALARM = """
[energy]
eps = 1.0e-9
every = 25
floor = 1.0e-20
"""


def test_energy_alarm_in_history_and_run_json(tmp_path):
    case = load_case(write_case(tmp_path, steps=400, extra=ALARM))
    run_case(case, tmp_path / "out", quiet=True)
    h = read_history(tmp_path / "out" / "history.csv")
    info = run_json(tmp_path / "out")
    first = info["first_energy_alarm"]
    assert first is not None and info["energy_alarms"] >= 1
    alarm = h["energy_alarm"]
    assert set(np.unique(alarm)) <= {0.0, 1.0}
    k = int(np.argmax(alarm == 1))
    assert alarm[k] == 1 and not alarm[:k].any()  # 0 until the first alarm
    assert h["step"][k] == first["step"]  # history and energy checks every 25 steps
    assert h["energy_error"][k] == first["energy_error"] > 1e-9
    assert (h["energy_error"][:k] <= 1e-9).all()


def test_energy_alarm_survives_a_restart(tmp_path):
    """The energy monitor owns the run's alarm record (its checkpointed state: whether
    the balance is above eps now, the first alarm, the number of alarms); run.json
    reports it. A run stopped (SIGINT) in the middle of an excursion above eps, after
    its first alarm, and restarted from the checkpoint written then reports the same
    first alarm (step, time and error: those of the history's first row with the alarm
    set) and the same number of alarms (the excursions the history shows, the one the
    restart cut counted once) as the uninterrupted run, and writes the same history."""
    case = load_case(write_case(tmp_path, steps=400, checkpoint_every=0, extra=ALARM))
    straight = run_case(case, tmp_path / "a", quiet=True, chunk_steps=50)
    stopped = run_case(case, tmp_path / "b", quiet=True, chunk_steps=50,
                       on_chunk=send_at(300, signal.SIGINT))
    assert stopped.status == "interrupted"
    h = read_history(tmp_path / "a" / "history.csv")  # (a row at every energy check)
    alarm = h["energy_alarm"]
    assert set(np.unique(alarm)) <= {0.0, 1.0}
    k = int(np.argmax(alarm == 1))
    stop = int(np.flatnonzero(h["step"] == run_json(tmp_path / "b")["step"])[0])
    assert alarm[k] == 1 and k < stop and alarm[stop] == 1  # the first alarm, then an
    # excursion the stop cuts
    excursions = int(np.count_nonzero(np.diff(np.r_[0.0, alarm]) == 1))
    resumed = run_case(case, tmp_path / "b", quiet=True, chunk_steps=50, restart=stopped.checkpoint)
    assert resumed.status == straight.status == "completed"
    assert (tmp_path / "a" / "history.csv").read_text() == (tmp_path / "b" / "history.csv").read_text()
    first = {"step": int(h["step"][k]), "time": h["time"][k], "energy_error": h["energy_error"][k]}
    assert run_json(tmp_path / "a")["first_energy_alarm"] == first
    assert run_json(tmp_path / "b")["first_energy_alarm"] == first
    assert run_json(tmp_path / "a")["energy_alarms"] == excursions
    assert run_json(tmp_path / "b")["energy_alarms"] == excursions
