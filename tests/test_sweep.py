"""Parameter sweeps on Dask: parameters and run ids, validation before anything is
written, dask_map on a local cluster, a sweep with a diverging and a failing run and
its resume, and a sweep through a scheduler and a worker started as separate processes.
"""

import csv
import json
import math
import os
import signal
import subprocess
import sys
import time

import psutil
import pytest

from demstep.cli.sweep import main as sweep_main
from demstep.errors import InputError
from demstep.sweep import (dask_map, key_text, parse_key, parse_param, parse_value,
                           read_runs_file, run_id, set_key, value_text, worker_info)

TINY = """
name = "tiny"
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
steps = 50
damping = { local = 0.1 }
[stages.walls."y+"]
motion = "velocity"
velocity = [0.0, -0.01]
[[stages]]
name = "hold"
steps = 20
[stages.walls."y+"]
motion = "fixed"
[output]
history_every = 10
"""


@pytest.fixture
def tiny(tmp_path):
    path = tmp_path / "tiny.toml"
    path.write_text(TINY)
    return path


def read_summary(path):
    with open(path, newline="") as fh:
        return {row["run_id"]: row for row in csv.DictReader(fh)}


def descendants():
    """Child processes still alive, except multiprocessing's resource tracker (one per
    interpreter, it exits with the interpreter)."""
    alive = []
    for p in psutil.Process().children(recursive=True):
        try:
            if p.status() != psutil.STATUS_ZOMBIE and \
                    not any("resource_tracker" in part for part in p.cmdline()):
                alive.append(p)
        except psutil.NoSuchProcess:
            continue
    return alive


def wait_no_descendants(timeout=15.0):
    end = time.monotonic() + timeout
    while descendants() and time.monotonic() < end:
        time.sleep(0.2)
    return descendants()


# ------------------------------------------------------------ parameters, ids
def test_parse_param_values_and_keys():
    assert parse_param("contact.mu=0.1,0.2,0.3") == (("contact", "mu"), [0.1, 0.2, 0.3])
    assert parse_param("stages[1].mu=0.5") == (("stages", 1, "mu"), [0.5])
    path, values = parse_param('stages[0].walls."y+".velocity=[0.0, -0.01],[0,0]')
    assert path == ("stages", 0, "walls", "y+", "velocity")
    assert values == [[0.0, -0.01], [0, 0]]
    assert parse_param("contact.law=hertz,\"linear\"")[1] == ["hertz", "linear"]
    assert parse_value("1e4") == 1.0e4 and parse_value(".5") == 0.5
    assert parse_value("true") is True and parse_value("7") == 7
    assert parse_key("stages[0].walls.y+.velocity") == ("stages", 0, "walls", "y+", "velocity")
    assert key_text(("stages", 0, "walls", "y+", "velocity")) == 'stages[0].walls."y+".velocity'
    for v in (0.1, 1e-5, 3, True, "hertz", [0.0, -0.01], {"local": 0.1}):
        assert parse_value(value_text(v)) == v
    for bad in ("contact.mu", "=1", "stages[x].mu=1", "contact..mu=1", "contact.mu=1,,2"):
        with pytest.raises(InputError, match="param"):
            parse_param(bad)


def test_run_ids_are_readable_safe_and_short():
    rid = run_id({("contact", "mu"): 0.1, ("timestep", "alpha"): 0.05})
    assert rid == "contact.mu=0.1__timestep.alpha=0.05"
    assert run_id({("stages", 1, "mu"): 0.5}) == "stages.1.mu=0.5"
    assert run_id({("stages", 0, "walls", "y+", "velocity"): [0.0, -0.01]}) == \
        "stages.0.walls.y+.velocity=0.0_-0.01"
    evil = run_id({("name",): "../../etc/passwd x"})
    assert "/" not in evil and " " not in evil and not evil.startswith(".")
    long = {(f"key{k}" * 5,): 0.123456789 * k for k in range(8)}
    other = dict(long)
    other[("key7" * 5,)] = 1.0
    assert len(run_id(long)) <= 100 and run_id(long) != run_id(other)


def test_set_key_and_runs_files(tmp_path):
    data = {"contact": {"mu": 0.1}, "stages": [{"steps": 1}]}
    set_key(data, ("contact", "mu"), 0.2)
    set_key(data, ("damping", "local"), 0.1)
    set_key(data, ("stages", 0, "walls", "y+", "motion"), "fixed")
    assert data["contact"]["mu"] == 0.2 and data["damping"] == {"local": 0.1}
    assert data["stages"][0]["walls"]["y+"]["motion"] == "fixed"
    with pytest.raises(InputError, match=r"stages\[2\]: no such entry"):
        set_key(data, ("stages", 2, "mu"), 0.1)
    with pytest.raises(InputError, match="not a table"):
        set_key(data, ("contact", "mu", "x"), 0.1)

    runs_csv = tmp_path / "runs.csv"
    runs_csv.write_text("# comment\ncontact.mu,stages[1].mu,gravity\n"
                        "0.1,0.5,\n0.2,,\"[0.0, -1.0]\"\n")
    assert read_runs_file(runs_csv) == [
        {("contact", "mu"): 0.1, ("stages", 1, "mu"): 0.5},
        {("contact", "mu"): 0.2, ("gravity",): [0.0, -1.0]}]
    runs_toml = tmp_path / "runs.toml"
    runs_toml.write_text('[[runs]]\ncontact.mu = 0.1\n"stages[1]".mu = 0.5\n'
                         '[[runs]]\n"stages[0].walls.\\"y+\\".velocity" = [0.0, -0.1]\n')
    assert read_runs_file(runs_toml) == [
        {("contact", "mu"): 0.1, ("stages", 1, "mu"): 0.5},
        {("stages", 0, "walls", "y+", "velocity"): [0.0, -0.1]}]
    bad = tmp_path / "bad.toml"
    bad.write_text("[params]\nx = 1\n")
    with pytest.raises(InputError, match="only \\[\\[runs\\]\\]"):
        read_runs_file(bad)


@pytest.mark.parametrize("args, words", [
    (["--param", "contact.mu=0.1,-1"], ["run 2 of 2", "contact.mu=-1", "contact.mu"]),
    (["--param", "contact.mux=0.1"], ["contact.mux=0.1", "unknown key"]),
    (["--param", "stages[5].mu=0.1"], ["stages[5]", "no such entry"]),
    (["--param", "contact.mu=abc"], ["contact.mu", "abc"]),
    (["--param", "timestep.alpha=0.1", "--param", "particles.size=[4, 3, 2]"],
     ["particles.size", "2D"]),
    (["--param", "contact.mu"], ["KEY=VALUE"]),
    (["--param", "contact.mu=0.1", "--param", "contact.mu=0.2"], ["given twice"]),
    ([], ["--param"]),
    (["--param", "contact.mu=0.1", "--scheduler", "localhost"], ["tcp://HOST:PORT"]),
    (["--param", "contact.mu=0.1", "--scheduler", "tcp://127.0.0.1:1", "--workers", "2"],
     ["workers"]),
    (["--runs", "missing.csv"], ["no such file"]),
    (["--param", "contact.mu=0.1", "--peak", "z+.stress"],
     ["peak", "run 1 of 1", "'z+.stress'", "y+.stress"]),
    (["--param", "output.history_every=10,0", "--peak", "y+.stress"],
     ["peak", "run 2 of 2", "history_every"]),
])
def test_bad_input_exits_2_and_writes_nothing(tiny, tmp_path, capsys, args, words):
    out = tmp_path / "sweep"
    assert sweep_main(["sweep", str(tiny), "--out", str(out), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("demstep: error:")
    for w in words:
        assert w in err
    assert not out.exists()


def test_peak_columns_are_those_the_run_writes():
    """The columns ``--peak`` is checked against before any run (from the case alone)
    are those the run's history writer takes from the built simulation: walls in the
    simulation's order (box walls without the periodic axis, then named walls), the
    periodic length and Love stress columns, the runner's stage column."""
    from demstep.case import build_simulation, case_from_text
    from demstep.io.history import columns_for, history_columns

    text = TINY.replace("[box]", "[periodic]\nx = 8.0\n[box]") + (
        '[[walls]]\nname = "floor"\npoint = [0.0, -1.0]\nnormal = [0.0, 1.0]\n')
    case = case_from_text(text)
    predicted = columns_for(case.dim, case.wall_names(), case.periodic_axes(), ["stage"])
    built = history_columns(build_simulation(case), {"stage": None})
    assert predicted == built
    assert "floor.stress" in built and "box.Lx" in built and "love.yy" in built
    assert "x+.stress" not in built and built[-1] == "stage"


def test_out_folder_not_a_sweep_is_refused(tiny, tmp_path, capsys):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "data.txt").write_text("mine")
    assert sweep_main(["sweep", str(tiny), "--out", str(out), "--param", "contact.mu=0.1"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["data.txt"]


# ------------------------------------------------------------------- dask_map
def test_dask_map_local_cluster_order_errors_threads_and_shutdown():
    seen = []
    results = dask_map(math.sqrt, [4.0, -1.0, 9.0, 16.0], workers=2,
                       progress=lambda k, r: seen.append(k))
    assert [r.ok for r in results] == [True, False, True, True]
    assert [r.failed for r in results] == [False, True, False, False]
    assert [r.value for r in results] == [2.0, None, 3.0, 4.0]
    assert results[1].error.startswith("ValueError: math domain error")
    assert "Traceback" in results[1].traceback
    with pytest.raises(RuntimeError, match="math domain"):
        results[1].unwrap()
    assert sorted(seen) == [0, 1, 2, 3]
    info = [r.unwrap() for r in dask_map(worker_info, range(4), workers=2)]
    assert [i["item"] for i in info] == [0, 1, 2, 3]
    assert all(i["numba_threads"] == 1 and i["NUMBA_NUM_THREADS"] == "1" for i in info)
    assert os.getpid() not in {i["pid"] for i in info}
    assert dask_map(math.sqrt, []) == []
    assert wait_no_descendants() == []


# ------------------------------------------------------------ sweeps, resume
def test_sweep_refuses_a_run_its_build_refuses_before_writing(tiny, tmp_path, capsys):
    """A run whose case builds to nothing (a lattice clipped to no site) is found when
    the sweep is planned: one line naming the run and the key, exit 2, no folder."""
    runs = tmp_path / "runs.csv"
    runs.write_text("contact.mu,particles.clip_upper\n0.1,\n0.2,\"[-50.0, -50.0]\"\n")
    out = tmp_path / "sweep"
    assert sweep_main(["sweep", str(tiny), "--runs", str(runs), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "run 2 of 2" in err and "particles.clip_upper" in err and err.count("\n") == 1
    assert not out.exists()


def test_sweep_local_cluster_diverged_and_resume(tiny, tmp_path, capsys):
    """Runs on a local cluster of two workers: completed and diverged runs in the
    summary and their run.json; a second call skips every finished run."""
    runs = tmp_path / "runs.csv"
    runs.write_text("timestep.alpha,contact.mu\n"
                    "0.1,0.1\n0.2,0.1\n0.1,0.5\n0.2,0.5\n"
                    "3.0,0.5\n")                    # diverges
    out = tmp_path / "sweep"
    args = ["sweep", str(tiny), "--runs", str(runs), "--out", str(out), "--workers", "2",
            "--max-steps", "30"]
    t0 = time.perf_counter()
    assert sweep_main(args) == 0
    first = time.perf_counter() - t0
    captured = capsys.readouterr()
    assert "5 runs (4 completed, 1 diverged)" in captured.out
    summary = read_summary(out / "summary.csv")
    assert len(summary) == 5
    ok = summary["timestep.alpha=0.1__contact.mu=0.1"]
    assert ok["status"] == "completed" and ok["error"] == ""
    assert 0 < float(ok["max_energy_error"]) < 1e-2
    assert ok["peak_column"] == "y+.stress" and float(ok["peak"]) > 0
    assert int(ok["final_step"]) == 50  # 30 + 20 steps (--max-steps 30 per stage)
    assert float(ok["wall_time_s"]) > 0 and float(ok["final_time"]) > 0
    assert summary["timestep.alpha=3.0__contact.mu=0.5"]["status"] == "diverged"
    assert "diverged" in summary["timestep.alpha=3.0__contact.mu=0.5"]["error"]
    assert (out / "summary.png").stat().st_size > 10_000
    meta = json.loads((out / "sweep.json").read_text())
    assert meta["keys"] == ["timestep.alpha", "contact.mu"]
    run_json = json.loads((out / "runs" / ok["run_id"] / "run.json").read_text())
    assert run_json["sweep"]["overrides"] == {"timestep.alpha": 0.1, "contact.mu": 0.1}
    assert run_json["max_steps"] == 30

    # resume: finished runs (completed, diverged) are skipped
    stamps = {rid: (out / "runs" / rid / "run.json").stat().st_mtime_ns for rid in summary}
    assert sweep_main(args) == 0
    captured = capsys.readouterr()
    assert "5 finished earlier" in captured.out
    assert captured.err.count("skipped") == 5
    again = {rid: (out / "runs" / rid / "run.json").stat().st_mtime_ns for rid in summary}
    assert again == stamps
    resumed = read_summary(out / "summary.csv")
    assert resumed[ok["run_id"]]["max_energy_error"] == ok["max_energy_error"]
    assert resumed[ok["run_id"]]["wall_time_s"] == ok["wall_time_s"]

    # another --peak rebuilds the summary of a finished sweep without running anything
    args_ok = ["sweep", str(tiny), "--param", "timestep.alpha=0.1,0.2", "--param",
               "contact.mu=0.1,0.5", "--out", str(out), "--max-steps", "30",
               "--peak", "x+.stress", "--quiet"]
    t0 = time.perf_counter()
    assert sweep_main(args_ok) == 0
    assert time.perf_counter() - t0 < min(first, 10.0)
    rebuilt = read_summary(out / "summary.csv")
    assert len(rebuilt) == 4 and rebuilt[ok["run_id"]]["peak_column"] == "x+.stress"
    # a different --max-steps is a different run: not skipped
    assert sweep_main(args_ok[:-5] + ["--max-steps", "20", "--quiet"]) == 0
    assert int(read_summary(out / "summary.csv")[ok["run_id"]]["final_step"]) == 40
    assert wait_no_descendants() == []


# ------------------------------------------------- an external cluster (loopback)
def _kill_group(proc: subprocess.Popen):
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pass
    try:  # the nanny's worker process is in the same group: make sure it is gone
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
    if proc.poll() is None:
        proc.wait(timeout=10)


@pytest.fixture
def external_cluster(tmp_path):
    """``dask scheduler`` on 127.0.0.1 (a free port) and ``dask worker --nworkers 1
    --nthreads 1`` as separate processes; both killed at the end, always."""
    folder = tmp_path / "cluster"
    folder.mkdir()
    sched_file = folder / "scheduler.json"
    env = {**os.environ, "NUMBA_NUM_THREADS": "1"}
    procs = []

    def start(args, name):
        log = open(folder / f"{name}.log", "w")
        proc = subprocess.Popen([sys.executable, "-m", *args], cwd=folder, env=env,
                                stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        log.close()
        procs.append(proc)
        return proc

    try:
        start(["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
               "--no-dashboard", "--scheduler-file", str(sched_file)], "scheduler")
        end = time.monotonic() + 60
        while not sched_file.is_file() and time.monotonic() < end:
            time.sleep(0.1)
        assert sched_file.is_file(), (folder / "scheduler.log").read_text()
        address = json.loads(sched_file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        start(["distributed.cli.dask_worker", address, "--nworkers", "1", "--nthreads", "1",
               "--no-dashboard", "--local-directory", str(folder)], "worker")
        yield address
    finally:
        for proc in reversed(procs):
            _kill_group(proc)


def test_sweep_through_external_scheduler(tiny, tmp_path, external_cluster, capsys):
    address = external_cluster
    info = dask_map(worker_info, [0, 1], scheduler=address)
    assert all(r.ok for r in info)
    assert {r.value["numba_threads"] for r in info} == {1}
    assert os.getpid() not in {r.value["pid"] for r in info}
    runs = tmp_path / "runs.toml"
    runs.write_text('[[runs]]\ncontact.mu = 0.1\n[[runs]]\ncontact.mu = 0.4\n'
                    '"stages[1]".mu = 0.6\n')
    out = tmp_path / "sweep"
    assert sweep_main(["sweep", str(tiny), "--runs", str(runs), "--param",
                       "timestep.alpha=0.1,0.2", "--out", str(out), "--scheduler", address,
                       "--max-steps", "30", "--quiet"]) == 0
    summary = read_summary(out / "summary.csv")
    assert sorted(summary) == [
        "contact.mu=0.1__timestep.alpha=0.1", "contact.mu=0.1__timestep.alpha=0.2",
        "contact.mu=0.4__stages.1.mu=0.6__timestep.alpha=0.1",
        "contact.mu=0.4__stages.1.mu=0.6__timestep.alpha=0.2"]
    assert {row["status"] for row in summary.values()} == {"completed"}
    assert summary["contact.mu=0.1__timestep.alpha=0.1"]["stages[1].mu"] == ""
    pids = {json.loads((out / "runs" / rid / "run.json").read_text())["sweep"]["pid"]
            for rid in summary}
    assert pids == {info[0].value["pid"]}  # the one external worker ran them all
    assert json.loads((out / "sweep.json").read_text())["scheduler"] == address
    # the sweep only closed its client: the cluster still serves
    assert dask_map(worker_info, [7], scheduler=address)[0].value["item"] == 7
