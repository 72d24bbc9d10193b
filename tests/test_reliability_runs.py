"""Reliability of run folders (issue 41): no run lost after a hard kill, no user file
deleted by ``--overwrite``, no stage that runs forever, ``checkpoint_keep`` across
restarts, and a log that is never written through a symbolic link."""

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, cli, snapshot

from demstep import runner
from demstep.case import load_case
from demstep.io.manifest import MANIFEST_NAME, read_manifest
from demstep.runner import run_case

CASE = """
name = "small"
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
vtk_every = {vtk_every}
checkpoint_every = {checkpoint_every}
checkpoint_keep = {keep}
"""


def write_case(folder, steps=300, checkpoint_every=100, keep=3, vtk_every=100, extra=""):
    path = Path(folder) / "small.toml"
    path.write_text(CASE.format(steps=steps, checkpoint_every=checkpoint_every, keep=keep,
                                vtk_every=vtk_every) + extra)
    return path


def as_a_hard_kill_leaves_it(out: Path):
    """run.json as a run killed by SIGKILL leaves it: written at its start, never again
    (status 'running', no results recorded)."""
    info = json.loads((out / "run.json").read_text())
    info.update(status="running", results=False)
    for key in ("finished", "message", "checkpoint", "max_energy_error"):
        info.pop(key, None)
    (out / "run.json").write_text(json.dumps(info))


# ------------------------------------------------ 1. a killed run is not deleted
def test_a_killed_run_needs_restart_or_overwrite(tmp_path, capsys):
    case = write_case(tmp_path)
    out = tmp_path / "lost"
    code, _, err = cli(["run", case, "--out", out, "--quiet"], capsys)
    assert code == 0, err
    as_a_hard_kill_leaves_it(out)
    before = snapshot(out)
    code, _, err = cli(["run", case, "--out", out, "--quiet", "--max-steps", "10"], capsys)
    assert_one_line_error(code, err, "holds the results of an earlier run", "--restart",
                          "step0000000300.npz", "--overwrite", "history row")
    assert snapshot(out) == before
    # the command it names continues the run
    restart = err.split("continue it with ")[1].split(",")[0]
    code, _, err = cli(["run", case, "--out", out, "--quiet", *restart.split()], capsys)
    assert code == 0, err


def test_a_run_killed_by_sigkill_for_real_is_kept(tmp_path, capsys):
    case = write_case(tmp_path, steps=200000, checkpoint_every=200, vtk_every=1000)
    out = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "demstep.cli", "run", str(case), "--out",
                             str(out), "--quiet"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    try:
        end = time.monotonic() + 240
        while time.monotonic() < end and len(list((out / "checkpoints").glob("*.npz"))) < 2:
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.05)
    finally:
        proc.kill()
        proc.communicate()
    assert json.loads((out / "run.json").read_text())["status"] == "running"
    before = snapshot(out)
    code, _, err = cli(["run", case, "--out", out, "--quiet", "--max-steps", "10"], capsys)
    assert_one_line_error(code, err, "holds the results of an earlier run", "--restart")
    assert snapshot(out) == before


def test_a_run_stopped_while_compiling_is_replaced_without_overwrite(tmp_path, capsys):
    """What a run that never took a step leaves (run.json, case.toml, run.log, a history
    header, the initial frame) holds no result: a plain run replaces it, as before."""
    case = write_case(tmp_path)
    out = tmp_path / "early"
    code, _, err = cli(["run", case, "--out", out, "--quiet", "--max-steps", "0"], capsys)
    assert code == 0, err
    for f in (out / "checkpoints").iterdir():
        f.unlink()
    (out / "history.csv").write_text((out / "history.csv").read_text().splitlines()[0] + "\n")
    as_a_hard_kill_leaves_it(out)
    code, _, err = cli(["run", case, "--out", out, "--quiet"], capsys)
    assert code == 0, err


# ------------------------------------------ 7. --out "" and the manifest of outputs
@pytest.mark.parametrize("command", [["run", "{case}"], ["paper", "--quick"],
                                     ["sweep", "{case}", "--param", "contact.mu=0.1,0.2"]])
def test_an_empty_out_is_refused(tmp_path, capsys, monkeypatch, command):
    case = write_case(tmp_path)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "vtk").mkdir()
    (tmp_path / "vtk" / "mine.vtu").write_text("the user's own")
    (tmp_path / "notes.txt").write_text("keep me")
    before = snapshot(tmp_path)
    argv = [a.format(case=case) for a in command] + ["--out", "", "--overwrite"]
    if command[0] == "sweep":
        argv.remove("--overwrite")
    code, _, err = cli(argv, capsys)
    assert_one_line_error(code, err, "out", "empty")
    assert snapshot(tmp_path) == before


def test_overwrite_removes_only_what_the_run_wrote(tmp_path, capsys):
    case = write_case(tmp_path)
    out = tmp_path / "out"
    code, _, err = cli(["run", case, "--out", out, "--quiet"], capsys)
    assert code == 0, err
    code, _, err = cli(["plot", out], capsys)
    assert code == 0, err
    written = read_manifest(out)
    assert "history.csv" in written and "plots/energies.png" in written
    assert any(w.startswith("vtk/particles_") for w in written)
    assert "checkpoints/step0000000300.npz" in written
    # the user's files beside the run's, in its folders and at the top
    (out / "vtk" / "mine.vtu").write_text("the user's own")
    (out / "plots" / "figure.png").write_text("hand-made")
    (out / "notes.txt").write_text("keep me")
    code, _, err = cli(["run", case, "--out", out, "--quiet", "--overwrite", "--max-steps",
                        "50"], capsys)
    assert code == 0, err
    assert (out / "vtk" / "mine.vtu").read_text() == "the user's own"
    assert (out / "plots" / "figure.png").read_text() == "hand-made"
    assert (out / "notes.txt").read_text() == "keep me"
    # the earlier run's files are gone (the new one stopped at step 50)
    assert not (out / "checkpoints" / "step0000000300.npz").exists()
    assert not (out / "plots" / "energies.png").exists()
    assert not (out / "vtk" / "particles_0000000300.vtu").exists()
    assert "kept 2 file(s) demstep did not write" in (out / "run.log").read_text()


def test_overwrite_of_a_folder_from_before_manifests(tmp_path, capsys):
    """An older demstep kept no manifest: there only its own file names are removed."""
    case = write_case(tmp_path)
    out = tmp_path / "out"
    code, _, err = cli(["run", case, "--out", out, "--quiet"], capsys)
    assert code == 0, err
    (out / MANIFEST_NAME).unlink()
    (out / "vtk" / "mine.vtu").write_text("the user's own")
    (out / "checkpoints" / "notes.txt").write_text("keep me")
    code, _, err = cli(["run", case, "--out", out, "--quiet", "--overwrite", "--max-steps",
                        "50"], capsys)
    assert code == 0, err
    assert (out / "vtk" / "mine.vtu").exists() and (out / "checkpoints" / "notes.txt").exists()
    assert not (out / "checkpoints" / "step0000000300.npz").exists()
    assert not (out / "vtk" / "particles_0000000300.vtu").exists()


# -------------------------------------------- 6. a settling stage that never settles
def test_a_stage_that_never_settles_stops_at_its_cap(tmp_path, monkeypatch):
    """Elastic particles never come to rest: without max_steps the stage stops at the
    default cap, said in a warning when it starts (the cap made small here). Before, it
    ran forever (the guard below stops the old code)."""
    monkeypatch.setattr(runner, "DEFAULT_SETTLE_MAX_STEPS", 400, raising=False)
    path = tmp_path / "elastic.toml"
    path.write_text(CASE.format(steps=100, checkpoint_every=0, keep=3, vtk_every=0).replace(
        'steps = 100\ndamping = { local = 0.1 }', 'until_kinetic_below = 1e-90'))

    def guard(sim):
        assert sim.step <= 4000, "the stage did not stop"

    result = run_case(load_case(path), tmp_path / "out", quiet=True, chunk_steps=50,
                      on_chunk=guard)
    assert result.status == "completed"
    assert result.step == 400
    log = (tmp_path / "out" / "run.log").read_text()
    assert "until_kinetic_below without max_steps: it stops after 400 steps" in log
    assert "still above" in log


# ---------------------------------------------- 9. checkpoint_keep across restarts
def test_checkpoint_keep_holds_across_interrupted_restarts(tmp_path):
    """Five interrupt-and-restart cycles with checkpoint_keep = 3 leave the 3 newest
    checkpoints (before: the list restarted empty each time, and the checkpoints of the
    interruptions were never counted: 16 left)."""
    case = load_case(write_case(tmp_path, steps=3000, checkpoint_every=100, keep=3,
                                vtk_every=0))
    out = tmp_path / "out"

    def interrupt_after(n):
        def on_chunk(sim):
            on_chunk.calls += 1
            if on_chunk.calls == n:
                os.kill(os.getpid(), signal.SIGINT)
        on_chunk.calls = 0
        return on_chunk

    result = run_case(case, out, quiet=True, chunk_steps=50, on_chunk=interrupt_after(7))
    assert result.status == "interrupted"
    for _ in range(4):
        result = run_case(case, out, quiet=True, chunk_steps=50, restart=out,
                          on_chunk=interrupt_after(5))
        assert result.status == "interrupted"
    left = sorted(p.name for p in (out / "checkpoints").glob("*.npz"))
    assert len(left) == 3, left
    assert left[-1] == result.checkpoint.name  # the newest is the one to restart from
    assert sorted(p.name for p in (out / "checkpoints").glob("*.json")) == \
        [n.replace(".npz", ".json") for n in left]
    result = run_case(case, out, quiet=True, chunk_steps=50, restart=out)
    assert result.status == "completed"
    assert len(list((out / "checkpoints").glob("*.npz"))) == 3


# ------------------------------------------------ 10. run.log as a symbolic link
def test_run_log_is_never_written_through_a_link(tmp_path, capsys):
    case = write_case(tmp_path, steps=300, checkpoint_every=100)
    out = tmp_path / "out"
    code, _, err = cli(["run", case, "--out", out, "--quiet", "--max-steps", "200"], capsys)
    assert code == 0, err
    # the log's text moved elsewhere and run.log made a link to it
    target = tmp_path / "elsewhere.log"
    target.write_text((out / "run.log").read_text())
    before = target.read_text()
    (out / "run.log").unlink()
    (out / "run.log").symlink_to(target)
    checkpoint = sorted((out / "checkpoints").glob("*.npz"))[0]
    code, _, err = cli(["run", case, "--out", out, "--quiet", "--restart", checkpoint], capsys)
    assert code == 0, err
    assert target.read_text() == before  # the link's target untouched
    log = out / "run.log"
    assert not log.is_symlink() and log.is_file()
    text = log.read_text()
    assert text.startswith(before)  # the earlier log kept, the restart's appended
    assert "was a symbolic link" in text and "restarted at step" in text


# ------------------------------------------- 8. one definition of the energy error
def test_the_sweep_summary_and_the_run_agree_on_the_energy_error(tmp_path, capsys):
    """The history's energy_error is the monitor's (NaN while the energies are below its
    floor), so the sweep's summary and run.json give the same maximum. Before, the
    history ignored the floor: a run whose monitor never counted an error (run.json:
    0.0) was summarised with the errors of its smallest energies."""
    from demstep.io.history import read_history
    from demstep.sweep.summary import summarize_run

    case = write_case(tmp_path, extra="[energy]\nfloor = 1.0e90\nevery = 25\n")
    out = tmp_path / "out"
    code, _, err = cli(["run", case, "--out", out, "--quiet"], capsys)
    assert code == 0, err
    info = json.loads((out / "run.json").read_text())
    assert info["max_energy_error"] == 0.0  # never above the floor: never evaluated
    h = read_history(out / "history.csv")
    assert len(h["energy_error"]) > 5 and all(map(math.isnan, h["energy_error"]))
    assert summarize_run(out)["max_energy_error"] == 0.0
    # and above the floor (the default) both are the same number, sampled alike
    case = write_case(tmp_path, extra="[energy]\nevery = 25\n")
    out = tmp_path / "out2"
    code, _, err = cli(["run", case, "--out", out, "--quiet"], capsys)
    assert code == 0, err
    info = json.loads((out / "run.json").read_text())
    errors = read_history(out / "history.csv")["energy_error"]
    assert info["max_energy_error"] > 0
    assert summarize_run(out)["max_energy_error"] == info["max_energy_error"] \
        == float(np.nanmax(errors))


# ------------------------------------------- checkpoints of the previous format
def test_a_checkpoint_of_the_previous_format_restarts_bit_for_bit(tmp_path, capsys):
    """tests/data/format3: a run of an earlier demstep (format 3: the scalars in one
    array; Hertz contacts with friction and dashpots, local damping, a moving wall)
    checkpointed at step 200 and completed at step 300. Restarted from step 200 by this
    demstep, it ends at the old run's final state bit for bit: the format loads, and
    the physics are those of the earlier code. (An 'auto' checkpoint loads too; its
    certificate, made with the old law parameters, is estimated anew at the restart.)"""
    data = Path(__file__).resolve().parent / "data" / "format3"
    for name in ("case.toml", "step0000000200.npz", "step0000000200.json"):
        shutil.copy(data / name, tmp_path / name)
    code, _, err = cli(["run", tmp_path / "case.toml", "--out", tmp_path / "out", "--quiet",
                        "--restart", tmp_path / "step0000000200.npz"], capsys)
    assert code == 0, err
    new = dict(np.load(tmp_path / "out" / "checkpoints" / "step0000000300.npz"))
    old = dict(np.load(data / "step0000000300.npz"))
    assert int(old["format"][0]) == 3 and int(new["format"][0]) == 4
    for key in ("spheres.x", "spheres.v", "spheres.w", "pairs.shear", "wall_state.point",
                "ledger.acc", "ledger.energy"):
        width = min(len(old[key]), len(new[key])) if key.startswith("ledger") else None
        assert np.array_equal(old[key][:width], new[key][:width]), key
    assert new["scalars.dt"][0] == old["scalars"][2]
    assert new["scalars.step"][0] == old["scalars"][0] == 300
