"""Running cases: stages, restart identity, interruption, divergence, the run/plot
subcommands and smoke runs of every example."""

import json
import os
import signal
import subprocess
import sys
import tomllib
from pathlib import Path

import meshio
import numpy as np
import pytest

from demstep.case import apply_stage, build_simulation, load_case
from demstep.cli.run import main as cli_main
from demstep.io.checkpoint import load_checkpoint, save_checkpoint
from demstep.io.history import read_history
from demstep.plotting_run import plot_run
from demstep.runner import find_checkpoint, read_state, run_case

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
EXAMPLE_CASES = sorted(EXAMPLES.glob("*.toml"))

SMALL = """
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
steps = 300
damping = { local = 0.1 }
[stages.walls."y+"]
motion = "velocity"
velocity = [0.0, -0.01]
[[stages]]
name = "settle"
until_kinetic_below = 1.0e-30
check_every = 70
max_steps = 350
mu = 0.5
gravity = [0.0, -1.0]
[stages.walls."y+"]
motion = "servo"
target_stress = 5.0
[[stages]]
name = "hold"
duration = 2.0
[stages.walls."y+"]
motion = "fixed"
[output]
history_every = 25
vtk_every = 100
checkpoint_every = 200
checkpoint_keep = 2
"""


def small_case(tmp_path, text=SMALL, name="small.toml"):
    path = tmp_path / name
    path.write_text(text)
    return load_case(path)


STATE_ARRAYS = ("x", "v", "w", "ft", "wft", "wall_point", "wall_vel", "wall_force")


def assert_same_state(a, b):
    for name in STATE_ARRAYS:
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(a.ledger.acc, b.ledger.acc)
    assert np.array_equal(a.ledger.energy, b.ledger.energy)
    assert a.step == b.step and a.time == b.time and a.dt == b.dt


@pytest.mark.parametrize("example", ["fcc_plane_strain", "hex_biaxial_2d"])
def test_restart_identity_through_checkpoint(tmp_path, example):
    """N steps straight equal N/2, checkpoint, a new simulation from the same case,
    restore, N/2 more: bit for bit."""
    case = load_case(EXAMPLES / f"{example}.toml")
    straight = build_simulation(case)
    apply_stage(straight, case, 0)
    straight.run(steps=1000)
    half = build_simulation(case)
    apply_stage(half, case, 0)
    half.run(steps=500)
    save_checkpoint(half, tmp_path / "half.npz")
    resumed = build_simulation(case)
    apply_stage(resumed, case, 0, fresh=False)
    load_checkpoint(resumed, tmp_path / "half.npz")
    resumed.run(steps=500)
    assert_same_state(straight, resumed)


def test_run_case_writes_outputs(tmp_path):
    case = small_case(tmp_path)
    result = run_case(case, tmp_path / "out", quiet=True)
    assert result.status == "completed", result.message
    out = tmp_path / "out"
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "completed" and info["demstep_version"]
    resolved = tomllib.loads((out / "case.toml").read_text())
    assert resolved["timestep"]["mode"] == "alpha" and resolved["energy"]["eps"] == 0.01
    again = load_case(out / "case.toml")  # the resolved case loads and equals the input
    assert again.model_dump() == case.model_dump()
    h = read_history(out / "history.csv")
    assert h["step"][0] == 25 and h["step"][-1] == result.step
    assert sorted(set(h["stage"].astype(int))) == [0, 1, 2]
    first_of_stage = {int(s): int(h["step"][np.argmax(h["stage"] == s)]) for s in (1, 2)}
    assert first_of_stage[1] == 325  # stage 1 starts after 300 steps
    # stage 1 runs its 350-step cap (the kinetic energy never drops below 1e-30)
    assert first_of_stage[2] == 675
    # stage 3 lasts 2.0 time units
    assert result.time == pytest.approx(h["time"][h["stage"] == 1][-1] + 2.0, abs=h["dt"][-1] * 2)
    assert (out / "vtk" / "particles.pvd").is_file()
    frames = sorted((out / "vtk").glob("particles_*.vtu"))
    assert frames[0].name == "particles_0000000000.vtu"
    meshio.read(frames[-1])
    kept = sorted(p.name for p in (out / "checkpoints").glob("*.npz"))
    assert len(kept) == 2  # checkpoint_keep: the final one and the newest periodic one
    pos, state = read_state(find_checkpoint(out))
    assert state["reason"] == "completed" and pos.stage == 3


def run_interrupted(case, out, at_step, **kw):
    def stopper(sim):
        if sim.step >= at_step:
            os.kill(os.getpid(), signal.SIGINT)
    return run_case(case, out, quiet=True, on_chunk=stopper, chunk_steps=40, **kw)


@pytest.mark.parametrize("at_step", [130, 320, 660, 700])
def test_interrupted_run_restarts_bit_for_bit(tmp_path, at_step):
    case = small_case(tmp_path)
    straight = run_case(case, tmp_path / "a", quiet=True, chunk_steps=40)
    # (the handler before the run: Python's default, or SIG_IGN when pytest was started
    # in the background of a shell)
    before = signal.getsignal(signal.SIGINT)
    stopped = run_interrupted(case, tmp_path / "b", at_step)
    assert stopped.status == "interrupted" and stopped.checkpoint.is_file()
    assert "SIGINT" in stopped.message
    assert signal.getsignal(signal.SIGINT) is before  # handlers restored
    resumed = run_case(case, tmp_path / "b", quiet=True, chunk_steps=40, restart=tmp_path / "b")
    assert resumed.status == "completed"
    assert (tmp_path / "a" / "history.csv").read_text() == (tmp_path / "b" / "history.csv").read_text()
    assert (tmp_path / "a" / "vtk" / "walls.pvd").read_text() == \
        (tmp_path / "b" / "vtk" / "walls.pvd").read_text()
    a, b = np.load(straight.checkpoint), np.load(resumed.checkpoint)
    for key in a.files:
        assert np.array_equal(a[key], b[key], equal_nan=key.startswith("scalars")), key
    info = json.loads((tmp_path / "b" / "run.json").read_text())
    assert info["restarts"][0]["step"] == stopped.step


def test_restart_needs_the_run_state(tmp_path):
    case = small_case(tmp_path)
    sim = build_simulation(case)
    save_checkpoint(sim, tmp_path / "lonely.npz")
    with pytest.raises(Exception, match="no run state"):
        run_case(case, tmp_path / "out", quiet=True, restart=tmp_path / "lonely.npz")
    assert not (tmp_path / "out").exists()


DIVERGING = """
[particles]
generator = "lattice"
lattice = "sc"
radius = 1.0
size = 1
density = 0.2387
[contact]
law = "linear"
k_n = 1.0e4
[[walls]]
name = "left"
point = [-0.6, 0.0, 0.0]
normal = [1.0, 0.0, 0.0]
[[walls]]
name = "right"
point = [0.7, 0.0, 0.0]
normal = [-1.0, 0.0, 0.0]
[timestep]
alpha = 1.5
[energy]
action = "{action}"
every = 10
[numerics]
runaway_factor = {runaway}
jump_limit = {jump}
[[stages]]
steps = 5000
"""


@pytest.mark.parametrize("action,runaway,jump,status", [("warn", 10.0, 0.25, "diverged"),
                                                        ("stop", 0.0, 1e9, "energy_stop")])
def test_divergence_ends_the_run_with_a_checkpoint(tmp_path, action, runaway, jump, status):
    case = small_case(tmp_path, DIVERGING.format(action=action, runaway=runaway, jump=jump))
    result = run_case(case, tmp_path / "out", quiet=True)
    assert result.status == status
    assert result.checkpoint is not None and result.checkpoint.is_file()
    assert result.checkpoint.parent == tmp_path / "out" / "checkpoints"
    pos, state = read_state(result.checkpoint)
    assert state["reason"] == status and pos.stage_step == result.step
    assert json.loads((tmp_path / "out" / "run.json").read_text())["status"] == status


@pytest.mark.parametrize("example", EXAMPLE_CASES, ids=lambda p: p.stem)
def test_examples_run(tmp_path, example):
    case = load_case(example)
    result = run_case(case, tmp_path / "out", quiet=True, max_steps=150)
    assert result.status == "completed", result.message
    h = read_history(tmp_path / "out" / "history.csv")
    assert h["step"][-1] == result.step
    # (a run that starts empty has no energy to balance until its first insertion)
    empty = h["particles"] == 0 if "particles" in h else np.zeros(len(h["step"]), dtype=bool)
    assert np.isfinite(h["energy_error"][~empty]).all() and (~empty).sum() >= 1
    assert np.nanmax(h["energy_error"]) < 1e-2
    assert len(plot_run(tmp_path / "out")) == 4


def test_paper_case_layout():
    sim = build_simulation(load_case(EXAMPLES / "fcc_plane_strain.toml"))
    assert len(sim.r) == 150 and np.all(sim.r == 20.0)
    assert sim.m[0] == pytest.approx(2000 * 4 / 3 * np.pi * 20.0**3)
    layers = np.unique(np.round(sim.x[:, 2], 6))
    counts = [int(np.sum(np.isclose(sim.x[:, 2], z))) for z in layers]
    assert len(layers) == 6 and counts == [25] * 6
    assert sim.periodic_len.tolist() == [200.0, 200.0, 0.0]
    assert [w.name for w in sim.walls] == ["bottom", "top"]


def test_polydisperse_packing_example_reads():
    from demstep.io.assembly_files import read_assembly

    data = read_assembly(EXAMPLES / "polydisperse_packing.csv")
    table = np.loadtxt(EXAMPLES / "polydisperse_packing.csv", delimiter=",", skiprows=1)
    assert data.x.shape == (125, 3) and data.m is None
    assert np.array_equal(data.x, table[:, :3]) and np.array_equal(data.r, table[:, 3])


# ------------------------------------------------------------------ the CLI
def test_cli_run_and_plot(tmp_path, capsys):
    case = tmp_path / "small.toml"
    case.write_text(SMALL)
    out = tmp_path / "out"
    assert cli_main(["run", str(case), "--out", str(out), "--quiet", "--log-level", "WARNING",
                     "--max-steps", "60"]) == 0
    assert "completed" in capsys.readouterr().out
    assert cli_main(["plot", str(out)]) == 0
    pngs = sorted(p.name for p in (out / "plots").glob("*.png"))
    assert pngs == ["energies.png", "energy_error.png", "timestep.png", "wall_stress.png"]
    # the same folder again without --restart or --overwrite: refused, untouched
    before = sorted(p.name for p in out.rglob("*"))
    assert cli_main(["run", str(case), "--out", str(out), "--quiet"]) == 2
    assert "holds the results of an earlier run" in capsys.readouterr().err
    assert sorted(p.name for p in out.rglob("*")) == before
    # --restart from the folder: the last checkpoint is at the end, nothing to run
    assert cli_main(["run", str(case), "--out", str(out), "--quiet", "--restart", str(out),
                     "--max-steps", "60"]) == 0


BAD_CASES = [
    ('[contact]\nlaw = "linear"\nk_n = 1.0\nmu = -0.1', "contact.mu"),
    ("[contact]\nlaw = 'linear'\nk_n = 'stiff'", "contact.k_n"),
    ("[contact]\nlaw = 'linear'\nk_n = 1.0\n[timestep]\ndt = -1.0", "timestep.dt"),
    ("[contact]\nlaw = 'linear'\nk_n = 1.0\n[energy]\ncolour = 1", "energy.colour: unknown key"),
    ("[contact]\nlaw = 'linear'\nk_n = 1.0\n[[walls]]\nname = 'w'\npoint = [0.5, 0.5]\n"
     "normal = [1.0, 0.0]", "cuts deep"),
    ("not toml at all [", "not valid TOML"),
]

BAD_BASE = """
[particles]
generator = "lattice"
lattice = "square"
radius = 1.0
size = 2
density = 1.0
[[stages]]
steps = 10
"""


@pytest.mark.parametrize("extra,expected", BAD_CASES)
def test_cli_errors_exit_2_without_output(tmp_path, capsys, extra, expected):
    case = tmp_path / "bad.toml"
    case.write_text(BAD_BASE + extra if "TOML" not in expected else extra)
    out = tmp_path / "never"
    assert cli_main(["run", str(case), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("demstep: error: ") and err.count("\n") == 1
    assert expected in err
    assert not out.exists()


def test_cli_argument_errors_exit_2(tmp_path, capsys):
    case = tmp_path / "small.toml"
    case.write_text(SMALL)
    with pytest.raises(SystemExit) as info:
        cli_main(["run", str(case)])  # --out missing
    assert info.value.code == 2
    assert cli_main(["run", str(case), "--out", str(tmp_path / "o"), "--log-level", "LOUD"]) == 2
    assert "log-level" in capsys.readouterr().err and not (tmp_path / "o").exists()
    assert cli_main(["run", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "o")]) == 2
    assert cli_main(["plot", str(tmp_path / "nothing")]) == 2


@pytest.mark.parametrize("content, needle", [
    (b"x,y,r\n0,0,1\n", "is not a run's history: no column 'step'"),
    (b"step,time,kinetic_translational\n0,0,0\n", "no column 'dt', 'dt_estimate'"),
    (b"step,time\n0,\xff\xfe\n", "not a text history file (byte 12 is not UTF-8)"),
])
def test_plot_of_a_file_that_is_no_history_is_one_line(tmp_path, capsys, content, needle):
    """`demstep plot` on a particle CSV, a history without the ledger's columns or a
    binary file: exit 2, one line naming the file and what is missing (KeyError and
    UnicodeDecodeError tracebacks before), and no plots folder begun."""
    (tmp_path / "history.csv").write_bytes(content)
    assert cli_main(["plot", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and len(err.splitlines()) == 1 and "history.csv" in err
    assert not (tmp_path / "plots").exists()


def test_sigterm_in_a_subprocess_saves_a_checkpoint(tmp_path):
    """A real signal to a real process: the run stops cleanly with exit status 143
    (128 + SIGTERM, as the shell reports a process killed by it) and a checkpoint to
    restart from."""
    case = tmp_path / "long.toml"
    case.write_text(SMALL.replace("steps = 300", "steps = 100000000"))
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "demstep.cli.run", "run", str(case),
                             "--out", str(out), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    history = out / "history.csv"
    import time

    deadline = time.time() + 120
    while time.time() < deadline:
        if history.is_file() and history.read_text().count("\n") > 3:
            break
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    assert "SIGTERM" in err
    checkpoint = find_checkpoint(out)
    pos, state = read_state(checkpoint)
    assert state["reason"] == "signal SIGTERM" and pos.stage == 0 and pos.stage_step > 0


def test_overwrite_replaces_earlier_outputs_only(tmp_path):
    case = small_case(tmp_path)
    out = tmp_path / "out"
    run_case(case, out, quiet=True, max_steps=60)
    (out / "notes.txt").write_text("mine")
    (out / "checkpoints" / "step9999999999.json").write_text("{}")
    result = run_case(case, out, quiet=True, max_steps=30, overwrite=True)
    assert result.status == "completed"
    assert (out / "notes.txt").read_text() == "mine"  # not an output: kept
    # not written by demstep (whatever its name): kept, and no checkpoint to restart from
    assert (out / "checkpoints" / "step9999999999.json").read_text() == "{}"
    assert find_checkpoint(out) == result.checkpoint
    assert read_history(out / "history.csv")["step"][-1] == result.step


def test_folder_restart_skips_failed_checkpoints(tmp_path):
    case = small_case(tmp_path)
    out = tmp_path / "out"
    good = run_interrupted(case, out, 100).checkpoint
    bad = out / "checkpoints" / "demstep-diverged-step999.npz"
    bad.write_bytes(good.read_bytes())
    (bad.with_suffix(".json")).write_text(json.dumps({"format": 1, "reason": "diverged",
                                                      "checkpoint": bad.name, "step": 999}))
    assert find_checkpoint(out) == good


def test_progress_bar_runs(tmp_path, capsys):
    case = small_case(tmp_path)
    result = run_case(case, tmp_path / "out", quiet=False, max_steps=50, log_level="DEBUG")
    assert result.status == "completed"
    log_text = (tmp_path / "out" / "run.log").read_text()
    assert "stage 3/3 'hold'" in log_text and "checkpoint (completed)" in log_text


def test_paper_case_restarts_bit_for_bit(tmp_path):
    """Periodic servo lengths, a stage time step and a ledger reset survive a restart."""
    case = load_case(EXAMPLES / "fcc_plane_strain.toml")
    case.output.checkpoint_every = 0
    straight = run_case(case, tmp_path / "a", quiet=True, max_steps=300, chunk_steps=40)
    stopped = run_interrupted(case, tmp_path / "b", 450, max_steps=300)
    assert stopped.status == "interrupted" and read_state(stopped.checkpoint)[0].stage == 1
    resumed = run_case(case, tmp_path / "b", quiet=True, max_steps=300, chunk_steps=40,
                       restart=stopped.checkpoint)
    assert resumed.status == "completed"
    ha, hb = read_history(tmp_path / "a" / "history.csv"), read_history(tmp_path / "b" / "history.csv")
    assert "box.Lx" in ha and "love.zz" in ha
    for key in ha:
        assert np.array_equal(ha[key], hb[key], equal_nan=True), key
    a, b = np.load(straight.checkpoint), np.load(resumed.checkpoint)
    for key in ("spheres.x", "spheres.v", "spheres.w", "box.length", "box.sums", "ledger.acc",
                "ledger.energy", "wall_state.point"):
        assert np.array_equal(a[key], b[key]), key


LATER_BONDS = """
name = "bond_later"
[particles]
generator = "file"
path = "two.csv"
density = 1000.0
[contact]
law = "linear"
k_n = 1.0e6
[bonds]
normal_stiffness = 1.0e6
file = "pair.csv"
stage = 2
{gap}
[[stages]]
name = "separate"
steps = 300
[[stages]]
name = "bonded"
steps = 10
"""


def test_a_stage_that_cannot_start_keeps_the_earlier_stages_work(tmp_path, capsys):
    """A bond file for stage 2 whose pair has moved apart during stage 1: the run stops
    with one line naming the pair, and a checkpoint of the state after stage 1 (none
    before: stage 1's work was lost), named in the message; the fixed case restarts
    from it and completes stage 2 only."""
    (tmp_path / "two.csv").write_text("x,y,r\n0,0,1\n1.96,0,1\n")
    (tmp_path / "pair.csv").write_text("i,j\n0,1\n")
    case = tmp_path / "case.toml"
    case.write_text(LATER_BONDS.format(gap=""))
    out = tmp_path / "out"
    assert cli_main(["run", str(case), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    checkpoint = out / "checkpoints" / "step0000000300.npz"
    assert "bonds.file: pair (0, 1) is" in err and "stage 2 'bonded' could not start" in err
    assert f"--restart {checkpoint}" in err and checkpoint.is_file()
    case.write_text(LATER_BONDS.format(gap="gap = 20.0"))
    assert cli_main(["run", str(case), "--out", str(out), "--quiet", "--restart",
                     str(checkpoint), "--allow-changed-case"]) == 0
    assert json.loads((out / "run.json").read_text())["step"] == 310
