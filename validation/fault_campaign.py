"""Fault campaign: a hostile user's audit of ``demstep run`` / ``dt`` / ``sweep`` that
anyone can re-run.

Every attempt runs the real command line in a child process
(``python -m demstep.cli ...`` with this checkout's ``src`` first on PYTHONPATH) and
prints one line, ``ok`` or ``FAIL`` with a short reason (``skip`` where the machine
cannot do it); a last line counts them. The exit status is 0 only when no attempt
failed. What is checked:

1. **Kill/restart cycles.** A small case (``examples/polydisperse_settling_3d.toml``
   with 8 x 8 x 12 particles in a 0.024 x 0.024 x 0.06 box, a checkpoint every 1000
   steps; shorter stages with ``--fast``) is run uninterrupted once (the reference).
   Then the same case is started and killed at a random moment (SIGTERM, SIGKILL or
   SIGTERM twice; one kill in five during the start-up, the others while it steps),
   restarted with ``--restart DIR``, killed again, ... and finally left to complete.
   Its final checkpoint (every array, loaded with numpy, compared exactly), its
   history.csv and its VTK frames must equal the reference's byte for byte (restarts
   continue bit for bit; the runner's chunks do not depend on the wall clock). Every
   kill must end without a traceback and with the right exit status. Where the folder
   has no checkpoint yet, ``--restart DIR`` must be refused with one line and the run
   starts afresh with ``--overwrite``.
2. **A killed folder.** A run killed with SIGKILL leaves run.json with status
   "running"; a plain ``demstep run`` into that folder (no ``--overwrite``, no
   ``--restart``) must exit non-zero with one line and delete nothing. Checked on a
   fresh run killed after its first checkpoint, and on a copy of the folder after
   every SIGKILL of the cycles.
3. **Damaged checkpoints** (truncated, a range of bytes zeroed, one byte flipped, an
   empty file, the JSON run state beside it garbled): ``--restart FILE`` must give one
   line on stderr, exit 2, no traceback, and create no output folder -- or, where the
   damage hit a byte nothing reads, complete with the reference's final state. With
   ``--restart DIR`` (the newest checkpoint of a run folder damaged) the restart may
   also fall back to an older checkpoint, and must then end as the reference did.
4. **Damaged histories** (NUL bytes appended, a row replaced by junk, a row cut short,
   bytes that are no UTF-8; all after the checkpoint's step, where a crash leaves
   them): a restart from the checkpoint must complete and leave a history.csv that is
   well formed and equal to the reference's.
5. **A full disk.** Where a tmpfs can be mounted (root), the case runs into one with
   too little free space: it must end with an error line naming a file, a non-zero
   exit and no traceback; after the space is freed, ``--restart DIR`` must complete
   with the reference's results.
6. **Concurrent runs** into one folder, started together or one during the other:
   exactly one completes (with the reference's results), the other exits 2 with one
   line.
7. **Malformed inputs**: bad case files (missing sections, wrong types, NaN, a
   negative radius, no TOML, a stage name with a newline), bad particle files (a
   negative radius, NaN, a missing column, a field over 128 KiB, a binary file named
   .csv, /dev/zero, an empty file), ``--out ""``, ``--max-steps -1``, a missing
   restart checkpoint, ``demstep dt --wall -0.03,0,0:1,0,0`` (a valid wall: it must be
   taken as ``--wall=-0.03,...`` is, or refused naming it), and ``demstep sweep
   --scheduler`` pointing at a plain HTTP server started here. Each must exit 2 with
   one line on stderr, no traceback, and leave nothing written (the ``--out`` folder
   absent, the working folder empty). These run from an empty working folder, with
   ``--quiet --max-steps 1`` (a run wrongly accepted stays short) and an address-space
   limit of 4 GiB (a reader that swallowed /dev/zero would fail instead of filling
   the machine's memory).

Run (from the repository; the first run of a cold numba cache also compiles the
kernels, a minute or two, charged to the reference run):

    python validation/fault_campaign.py --fast          # CI subset: 2 cycles, one of each damage
    python validation/fault_campaign.py                 # 20 random cycles, every variant
    python validation/fault_campaign.py --seed 7 --cycles 40 --keep

``--fast`` runs the short case (6400 steps) with 2 cycles, one attempt of each kind
of damage (and one ``--restart DIR`` with a damage drawn at random), one full disk,
one pair of concurrent runs and 12 of the 22 malformed inputs (no stages, a wrong
type, NaN, a negative radius, the stage name; a negative radius, the long field, the
binary file and /dev/zero as particle files; ``--out ""``, ``--wall``,
``--scheduler``): 40-65 s on 2 cores shared with other work (about 35 processes,
each paying numba's import, a second or more). The full mode runs the longer case
(48000 steps) with ``--cycles`` (default 20), three of each damage, every damage
with ``--restart DIR``, two full disks, three pairs and every malformed input: about
3 minutes. ``--seed`` makes the random choices (signals, kill moments, damaged
bytes, free space) repeatable; the seed is printed. The kill moments are seconds of
wall-clock time (counted from the first new history row for kills while stepping),
so a busy machine moves where the kills land, never what is checked. ``--keep``
keeps the temporary folder (its path is printed). ``--jobs`` (default 2) runs that
many attempts at a time after the cycles, which run alone.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import csv
import http.server
import io
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
SRC = REPO / "src"
EXAMPLE = REPO / "examples" / "polydisperse_settling_3d.toml"

#: the lock file a run keeps in its folder (not a result: ignored when comparing folders)
LOCK_NAME = ".demstep.lock"
#: a temporary file of an atomic write (``.<name>.<8 hex>.tmp``)
TEMP_NAME = re.compile(r"^\..+\.[0-9a-f]{8}\.tmp$")
#: seconds any one command may take before it counts as hung
TIMEOUT = 600
#: address-space limit of the malformed-input commands [bytes]
MEMORY_LIMIT = 4 << 30


# ======================================================================= the case
def shrunk_case(fast: bool) -> str:
    """The settling example shrunk as the campaign runs it (a checkpoint every 1000
    steps; with ``fast`` short stages: about 6400 steps against 48000)."""
    text = EXAMPLE.read_text(encoding="utf-8")
    edits = [("count = [5, 5, 8]", "count = [8, 8, 12]"),
             ("upper = [0.015, 0.015, 0.04]", "upper = [0.024, 0.024, 0.06]"),
             ("checkpoint_every = 20000", "checkpoint_every = 1000")]
    if fast:
        edits += [("duration = 0.12", "duration = 0.02"), ("max_steps = 20000", "max_steps = 2000")]
    for old, new in edits:
        if old not in text:
            raise SystemExit(f"fault_campaign: {EXAMPLE.name} changed: {old!r} not found")
        text = text.replace(old, new)
    return text


# ============================================================ running the commands
def child_env() -> dict:
    path = os.environ.get("PYTHONPATH")
    return dict(os.environ, PYTHONPATH=str(SRC) + (os.pathsep + path if path else ""))


def _limit_memory():  # (in the child, before exec)
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))


@dataclass
class Exit:
    """How a command ended."""

    code: int | None
    out: str
    err: str
    seconds: float
    timed_out: bool = False


def demstep(args, cwd, timeout: float = TIMEOUT, limit_memory: bool = False) -> Exit:
    """Run ``demstep ARGS`` in ``cwd`` to its end (killed after ``timeout`` s)."""
    start = time.monotonic()
    try:
        proc = subprocess.run([sys.executable, "-m", "demstep.cli", *map(str, args)], cwd=cwd,
                              env=child_env(), capture_output=True, text=True,
                              errors="replace", timeout=timeout,
                              preexec_fn=_limit_memory if limit_memory else None)
    except subprocess.TimeoutExpired as exc:
        return Exit(None, _text(exc.stdout), _text(exc.stderr), time.monotonic() - start, True)
    return Exit(proc.returncode, proc.stdout, proc.stderr, time.monotonic() - start)


def _text(data) -> str:
    if isinstance(data, bytes):
        return data.decode("utf-8", "replace")
    return data or ""


class Started:
    """``demstep ARGS`` started in the background, its output going to files in
    ``logs`` (so that a chatty run never blocks on a full pipe)."""

    def __init__(self, args, cwd, logs: Path, tag: str):
        logs.mkdir(parents=True, exist_ok=True)
        self.out_path, self.err_path = logs / f"{tag}.out", logs / f"{tag}.err"
        with open(self.out_path, "w") as out, open(self.err_path, "w") as err:
            self.proc = subprocess.Popen([sys.executable, "-m", "demstep.cli", *map(str, args)],
                                         cwd=cwd, env=child_env(), stdout=out, stderr=err)
        self.start = time.monotonic()

    def elapsed(self) -> float:
        return time.monotonic() - self.start

    def send(self, sig):
        if self.proc.poll() is None:
            self.proc.send_signal(sig)

    def wait(self, timeout: float = TIMEOUT) -> Exit:
        try:
            self.proc.wait(timeout=timeout)
            timed_out = False
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            timed_out = True
        read = lambda p: p.read_text(encoding="utf-8", errors="replace")
        return Exit(None if timed_out else self.proc.returncode, read(self.out_path),
                    read(self.err_path), self.elapsed(), timed_out)


def last_line(text: str, width: int = 150) -> str:
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    line = lines[-1] if lines else "(nothing on stderr)"
    return line if len(line) <= width else line[: width - 3] + "..."


def gist(x: Exit) -> str:
    """A short account of how ``x`` ended, for a FAIL line."""
    if x.timed_out:
        return f"timed out after {x.seconds:.0f} s"
    traceback = " with a Traceback" if "Traceback" in x.err else ""
    return f"exit {x.code}{traceback}: {last_line(x.err)}"


def one_line_problem(x: Exit, code: int = 2, words=(), refused_words=()) -> str | None:
    """None when ``x`` exited ``code`` with exactly one line 'demstep: error: ...' on
    stderr holding every one of ``words`` and none of ``refused_words``, no traceback;
    else what is wrong."""
    if x.timed_out or "Traceback" in x.err or x.code != code:
        return gist(x)
    lines = x.err.splitlines()
    if len(lines) != 1 or not lines[0].startswith("demstep: error: "):
        return f"exit {x.code}, {len(lines)} line(s) on stderr: {last_line(x.err)}"
    for word in words:
        if word not in lines[0]:
            return f"the message does not name {word!r}: {last_line(x.err)}"
    for word in refused_words:
        if word in lines[0]:
            return f"the message says {word!r}: {last_line(x.err)}"
    return None


# ======================================================================== folders
def snapshot(folder) -> dict[str, bytes] | None:
    """Every file under ``folder`` with its bytes, but the lock file and the temporary
    files a killed write left (no results: any run may remove them); None when
    ``folder`` does not exist."""
    folder = Path(folder)
    if not folder.exists():
        return None
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != LOCK_NAME and not TEMP_NAME.match(p.name)}


def snapshot_change(before, after) -> str | None:
    """What changed between two snapshots, in a few words (None: nothing)."""
    if before == after:
        return None
    if before is None or after is None:
        return "the folder was created" if before is None else "the folder was deleted"
    gone = sorted(set(before) - set(after))
    new = sorted(set(after) - set(before))
    changed = sorted(k for k in set(before) & set(after) if before[k] != after[k])
    parts = [f"{len(names)} file(s) {what} (e.g. {names[0]})"
             for names, what in ((gone, "deleted"), (changed, "changed"), (new, "added")) if names]
    return ", ".join(parts)


def checkpoints(folder) -> list[tuple[int, Path, dict]]:
    """The checkpoints of a run folder with their run state, by step: (step, .npz,
    state) for each .npz whose JSON beside it can be read."""
    found = []
    for npz in sorted((Path(folder) / "checkpoints").glob("step*.npz")):
        try:
            state = json.loads(npz.with_suffix(".json").read_text(encoding="utf-8"))
            found.append((int(state["step"]), npz, state))
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return sorted(found, key=lambda item: item[0])


def restartable(folder) -> int | None:
    """The step of the newest checkpoint a restart from ``folder`` can use, or None."""
    good = [step for step, _, state in checkpoints(folder)
            if state.get("reason") not in ("diverged", "energy_stop")]
    return max(good) if good else None


def final_checkpoint(folder) -> Path | None:
    done = [npz for _, npz, state in checkpoints(folder) if state.get("reason") == "completed"]
    return done[-1] if done else None


def run_info(folder) -> dict:
    try:
        info = json.loads((Path(folder) / "run.json").read_text(encoding="utf-8"))
        return info if isinstance(info, dict) else {}
    except (OSError, ValueError):
        return {}


def history_step(folder) -> int | None:
    """The step of the last complete row of a run's history.csv (None: no row)."""
    try:
        lines = (Path(folder) / "history.csv").read_bytes().split(b"\n")
    except OSError:
        return None
    for line in reversed(lines[1:-1]):  # (the part after the last newline is incomplete)
        try:
            return int(line.split(b",", 1)[0])
        except ValueError:
            continue
    return None


# ==================================================================== comparisons
def npz_arrays(path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as data:
        return {name: data[name] for name in data.files}


def array_difference(a: dict, b: dict) -> str | None:
    """None when the two sets of arrays are identical (names, dtypes, shapes, bytes)."""
    if a.keys() != b.keys():
        return f"arrays in one only: {sorted(a.keys() ^ b.keys())[:3]}"
    for name in sorted(a):
        x, y = a[name], b[name]
        if x.dtype != y.dtype or x.shape != y.shape:
            return f"array {name!r}: {x.dtype}{x.shape} against {y.dtype}{y.shape}"
        if x.tobytes() != y.tobytes():
            n = int(np.count_nonzero(x != y)) if x.dtype.kind in "fiub" else "some"
            return f"array {name!r}: {n} of {x.size} values differ"
    return None


def first_line_difference(a: bytes, b: bytes, name: str) -> str | None:
    if a == b:
        return None
    la, lb = a.split(b"\n"), b.split(b"\n")
    for k, (x, y) in enumerate(zip(la, lb), start=1):
        if x != y:
            return f"{name} line {k} differs: {x[:60]!r} against the reference's {y[:60]!r}"
    return f"{name}: {len(la)} lines against the reference's {len(lb)}"


def compare_results(folder, ref_folder) -> list[tuple[str, str | None, str]]:
    """(what, problem, detail) for the final checkpoint (arrays and run state), the
    other checkpoints both folders hold, history.csv and the VTK frames of ``folder``
    against those of the reference run ``ref_folder``."""
    folder, ref_folder = Path(folder), Path(ref_folder)
    results = []
    final, ref_final = final_checkpoint(folder), final_checkpoint(ref_folder)
    if final is None:
        results.append(("final checkpoint", "no checkpoint of a completed run", ""))
    elif final.name != ref_final.name:
        results.append(("final checkpoint", f"{final.name} against the reference's "
                        f"{ref_final.name}", ""))
    else:
        problem = array_difference(npz_arrays(final), npz_arrays(ref_final))
        state = json.loads(final.with_suffix(".json").read_text())
        ref_state = json.loads(ref_final.with_suffix(".json").read_text())
        if problem is None and state != ref_state:
            keys = sorted(k for k in state.keys() | ref_state.keys()
                          if state.get(k) != ref_state.get(k))
            problem = f"run state {final.with_suffix('.json').name} differs in {keys}"
        common = sorted({npz.name for _, npz, _ in checkpoints(folder)}
                        & {npz.name for _, npz, _ in checkpoints(ref_folder)} - {final.name})
        for name in common:
            if problem is None:
                problem = array_difference(npz_arrays(folder / "checkpoints" / name),
                                           npz_arrays(ref_folder / "checkpoints" / name))
                problem = problem and f"{name}: {problem}"
        n = len(npz_arrays(ref_final))
        results.append(("final checkpoint", problem,
                        f"{final.name}: {n} arrays identical, and {len(common)} other "
                        f"checkpoint(s) both hold"))
    hist, ref_hist = folder / "history.csv", ref_folder / "history.csv"
    problem = (first_line_difference(hist.read_bytes(), ref_hist.read_bytes(), "history.csv")
               if hist.is_file() else "no history.csv")
    rows = ref_hist.read_bytes().count(b"\n") - 1
    results.append(("history.csv", problem, f"{rows} rows identical"))
    vtk, ref_vtk = snapshot(folder / "vtk") or {}, snapshot(ref_folder / "vtk") or {}
    problem = None
    if vtk.keys() != ref_vtk.keys():
        only = sorted(vtk.keys() ^ ref_vtk.keys())
        problem = f"{len(only)} file(s) in one folder only (e.g. {only[0]})"
    else:
        differ = sorted(k for k in vtk if vtk[k] != ref_vtk[k])
        if differ:
            problem = f"{len(differ)} file(s) differ (e.g. {differ[0]})"
    results.append(("VTK frames", problem, f"{len(ref_vtk)} files identical"))
    return results


# ====================================================================== reporting
class Campaign:
    """The tally: one printed line per attempt."""

    def __init__(self, root: Path, rng_seed: int, fast: bool, cycles: int, jobs: int,
                 keep: bool = False):
        self.root = root
        self.keep = keep
        self.seed = rng_seed
        self.fast = fast
        self.cycles = cycles
        self.jobs = jobs
        self.counts = {"ok": 0, "FAIL": 0, "skip": 0}
        self._lock = threading.Lock()

    def rng(self, section: str) -> random.Random:
        """A random generator of its own for each section (one section's draws do not
        move another's)."""
        return random.Random(f"{self.seed}/{section}")

    def folder(self, name: str) -> Path:
        """A new folder ``name`` in the campaign's folder (``name-2``, ... if taken)."""
        with self._lock:
            path, n = self.root / name, 1
            while path.exists():
                n += 1
                path = self.root / f"{name}-{n}"
            path.mkdir(parents=True)
        return path

    def report(self, name: str, problem: str | None, detail: str = "", skip: str | None = None):
        """One line: ``ok`` (with ``detail``), ``FAIL`` (with ``problem``) or ``skip``."""
        with self._lock:
            if skip is not None:
                kind, text = "skip", f"{name}: {skip}"
            elif problem is None:
                kind, text = "ok", name + (f" ({detail})" if detail else "")
            else:
                kind, text = "FAIL", f"{name}: {problem}"
            self.counts[kind] += 1
            print(f"{kind:<4} {text}", flush=True)

    def run_all(self, attempts):
        """Run the callables ``attempts`` (each returns a list of (name, problem,
        detail)), ``jobs`` at a time, reporting in the order given."""
        if self.jobs <= 1:
            for attempt in attempts:
                for result in attempt():
                    self.report(*result)
            return
        with concurrent.futures.ThreadPoolExecutor(self.jobs) as pool:
            for results in pool.map(lambda attempt: attempt(), attempts):
                for result in results:
                    self.report(*result)


@dataclass
class Reference:
    """The uninterrupted run: its folder, wall time, start-up time (until its first
    history row), the seconds it spent stepping and its number of steps."""

    case: Path
    folder: Path
    seconds: float
    startup: float
    steps: int

    @property
    def stepping(self) -> float:
        return max(0.2, self.seconds - self.startup)


def reference_run(c: Campaign, case: Path) -> Reference | None:
    """Run the case uninterrupted; when the kernels had to be compiled (a start-up over
    5 s), once more for the timings the kill moments are drawn from."""
    for attempt in (1, 2):
        folder = c.root / f"reference{attempt}"
        run = Started(["run", case, "--out", folder, "--quiet"], c.root, c.root / "logs",
                      f"reference{attempt}")
        startup = None
        while run.proc.poll() is None:
            if startup is None and history_step(folder) is not None:
                startup = run.elapsed()
            time.sleep(0.01)
        x = run.wait()
        steps = history_step(folder)
        problem = None if x.code == 0 and final_checkpoint(folder) else gist(x)
        c.report(f"reference: uninterrupted run {attempt}", problem,
                 f"{steps} steps in {x.seconds:.1f} s, start-up {startup or 0:.1f} s")
        if problem is not None:
            return None
        if startup is not None and startup < 5.0:
            return Reference(case, folder, x.seconds, startup, steps)
    return Reference(case, folder, x.seconds, min(startup or 2.0, 5.0), steps)


# ========================================================= 1-2. kills and restarts
SIGNALS = ("SIGTERM", "SIGKILL", "SIGTERM twice")
#: exit statuses of a run stopped by each (a handler not installed yet: killed by the
#: signal itself, -15)
EXPECTED_EXIT = {"SIGTERM": (143, -15), "SIGKILL": (-9,), "SIGTERM twice": (143, -15)}


def kill_moment(rng: random.Random, ref: Reference, done_step: int,
                kills_left: int) -> tuple[bool, float]:
    """When to kill a run that resumes at ``done_step``: (False, s) ``s`` seconds after
    its start, during the start-up (imports, case check, checkpoint, kernels from the
    cache: one kill in five), or (True, s) ``s`` seconds after its first new history
    row, within its share of the remaining steps (so that ``kills_left`` kills spread
    over the run; counted from the first row, the moment does not depend on how long
    the start-up took on a busy machine)."""
    if rng.random() < 0.2:
        return False, rng.uniform(0.0, ref.startup)
    remaining = ref.stepping * max(0.0, ref.steps - done_step) / ref.steps
    return True, rng.uniform(0.0, remaining * 2.0 / (kills_left + 1))


def wait_for_moment(run: Started, folder: Path, stepping: bool, delay: float) -> str:
    """Wait for the moment of :func:`kill_moment` (or the run's end); says when it was."""
    if not stepping:
        while run.proc.poll() is None and run.elapsed() < delay:
            time.sleep(0.005)
        return f"{run.elapsed():.2f} s after the start"
    seen = history_step(folder) or 0  # (rows a killed run wrote after its checkpoint)
    while run.proc.poll() is None and (history_step(folder) or 0) <= seen:
        time.sleep(0.005)
    first = run.elapsed()
    while run.proc.poll() is None and run.elapsed() < first + delay:
        time.sleep(0.005)
    return f"{run.elapsed():.2f} s after the start, {run.elapsed() - first:.2f} s of stepping"


def kill(run: Started, how: str, rng: random.Random):
    if how == "SIGKILL":
        run.send(signal.SIGKILL)
    elif how == "SIGTERM":
        run.send(signal.SIGTERM)
    else:
        run.send(signal.SIGTERM)
        time.sleep(rng.uniform(0.0, 0.3))
        run.send(signal.SIGTERM)


def plain_rerun_problem(c: Campaign, ref: Reference, folder: Path) -> str | None:
    """A plain ``demstep run`` (no --overwrite, no --restart) into a copy of the killed
    ``folder``: None when it exits non-zero with one line and deletes nothing."""
    copy = c.folder(f"rerun-{folder.name}") / "run"
    shutil.copytree(folder, copy)
    before = snapshot(copy)
    x = demstep(["run", ref.case, "--out", copy, "--quiet", "--max-steps", "1"], c.root)
    change = snapshot_change(before, snapshot(copy))
    if x.code == 0 or change:
        return (f"exit {x.code}, the plain run went into the killed run's folder"
                + (f": {change}" if change else ""))
    return one_line_problem(x, x.code)


def killed_folder(c: Campaign, ref: Reference):
    """A fresh run killed with SIGKILL after its first checkpoint: a plain re-run into
    its folder must be refused and delete nothing."""
    def attempt():
        work = c.folder("killed")
        folder = work / "run"
        run = Started(["run", ref.case, "--out", folder, "--quiet"], work, work, "killed")
        while run.proc.poll() is None and restartable(folder) is None:
            time.sleep(0.01)
        run.send(signal.SIGKILL)
        x = run.wait()
        status = run_info(folder).get("status")
        name = "killed folder: a plain re-run is refused"
        if x.code != -9 or status != "running":
            return [(name, f"could not kill the run after its first checkpoint ({gist(x)}, "
                     f"status {status!r})", "")]
        return [(name, plain_rerun_problem(c, ref, folder), f"SIGKILL at step "
                 f"{history_step(folder)}, status 'running': one line, nothing deleted")]
    return attempt


def kill_restart_cycles(c: Campaign, ref: Reference):
    """Start, kill at a random moment, restart with --restart DIR, ... (``cycles``
    kills), let the last restart complete, compare with the reference."""
    rng = c.rng("cycles")
    folder = c.root / "cycles"
    fresh = ["run", ref.case, "--out", folder, "--quiet"]
    args = fresh
    done_step = 0
    completed = False
    for k in range(1, c.cycles + 1):
        name = f"cycle {k}/{c.cycles}"
        how = rng.choice(SIGNALS)
        stepping, delay = kill_moment(rng, ref, done_step, c.cycles - k + 1)
        run = Started(args, c.root, c.root / "logs", f"cycle{k}")
        when = wait_for_moment(run, folder, stepping, delay)
        kill(run, how, rng)
        x = run.wait()
        status = run_info(folder).get("status")
        if x.code == 0 or (status == "completed" and x.code in EXPECTED_EXIT[how]):
            # (a signal after the run was recorded complete may still end the process)
            completed = True
            c.report(name, None if "Traceback" not in x.err else gist(x),
                     f"the run completed before the {how} {when}: exit {x.code}")
            break
        problem = None
        if x.timed_out or "Traceback" in x.err or x.code not in EXPECTED_EXIT[how]:
            problem = f"{how} {when}: {gist(x)}"
        elif how != "SIGKILL" and x.code == 143 and status not in ("interrupted", "aborted"):
            problem = f"{how} {when}: exit 143 but run.json status {status!r}"
        resume = restartable(folder)
        c.report(name, problem, f"{how} {when}: exit {x.code}, history at step "
                 f"{history_step(folder) or '-'}, newest checkpoint "
                 f"{'-' if resume is None else resume}, run.json {status or '-'}")
        if how == "SIGKILL" and status == "running":
            c.report(f"cycle {k}/{c.cycles}: a plain re-run into the killed folder is refused",
                     plain_rerun_problem(c, ref, folder), "one line, nothing deleted")
        if resume is None:  # nothing to restart from: --restart DIR must say so
            before = snapshot(folder)
            x = demstep(["run", ref.case, "--out", folder, "--quiet", "--restart", folder],
                        c.root)
            change = snapshot_change(before, snapshot(folder))
            problem = one_line_problem(x, 2, ("restart",)) or (change and f"it changed the "
                                                               f"folder: {change}")
            c.report(f"cycle {k}/{c.cycles}: --restart DIR without a checkpoint is refused",
                     problem, "one line, exit 2")
            args, done_step = fresh + ["--overwrite"], 0
        else:
            args, done_step = fresh + ["--restart", folder], resume
    if not completed:
        x = demstep(args, c.root)
        c.report("cycles: the last restart completes", None if x.code == 0 and
                 "Traceback" not in x.err else gist(x), f"from step {done_step}")
    for what, problem, detail in compare_results(folder, ref.folder):
        c.report(f"cycles against the uninterrupted run: {what}", problem, detail)
    left = [str(p.relative_to(folder)) for p in folder.rglob("*")
            if p.name == LOCK_NAME or TEMP_NAME.match(p.name)]
    info = run_info(folder)
    problem = f"left behind: {left[:3]}" if left else None
    if info.get("status") != "completed":
        problem = f"run.json status {info.get('status')!r}"
    c.report("cycles: run.json completed, no lock or temporary file left", problem,
             f"{len(info.get('restarts', []))} restart(s) recorded")


# ============================================================ 3. damaged checkpoints
CHECKPOINT_DAMAGE = ("truncated", "zeroed", "flipped", "empty", "state garbled")


def zip_region(data: bytes, at: int) -> str:
    """Which part of the zip archive ``data`` the byte ``at`` lies in (for messages)."""
    try:
        infos = zipfile.ZipFile(io.BytesIO(data)).infolist()
    except zipfile.BadZipFile:
        return "?"
    for info in infos:
        start = info.header_offset
        header = 30 + int.from_bytes(data[start + 26:start + 28], "little") \
            + int.from_bytes(data[start + 28:start + 30], "little")
        if start <= at < start + header:
            return f"{info.filename} local header"
        if start + header <= at < start + header + info.compress_size:
            return f"{info.filename} data"
    return "central directory"


def damage_checkpoint(kind: str, npz: Path, rng: random.Random) -> str:
    """Damage the checkpoint ``npz`` (or its run state) in place; says how."""
    data = npz.read_bytes()
    if kind == "truncated":
        cut = rng.randrange(1, len(data))
        npz.write_bytes(data[:cut])
        return f"cut to {cut} of {len(data)} bytes"
    if kind == "zeroed":  # (a range that is not all zeros already)
        n = rng.randint(16, 4096)
        at = rng.randrange(0, len(data) - n)
        while not any(data[at:at + n]):
            at = rng.randrange(0, len(data) - n)
        npz.write_bytes(data[:at] + bytes(n) + data[at + n:])
        return f"{n} bytes zeroed at {at} ({zip_region(data, at)})"
    if kind == "flipped":
        at = rng.randrange(len(data))
        npz.write_bytes(data[:at] + bytes([data[at] ^ 0xFF]) + data[at + 1:])
        return f"byte {at} of {len(data)} flipped ({zip_region(data, at)})"
    if kind == "empty":
        npz.write_bytes(b"")
        return "an empty file"
    state = npz.with_suffix(".json")
    text = state.read_bytes()
    junk = b"\x00\xff#garbled"
    at = rng.randrange(len(text) - len(junk))
    state.write_bytes(text[:at] + junk + text[at + len(junk):])
    return f"{len(junk)} bytes of {state.name} garbled at {at}"


def periodic_checkpoints(ref: Reference) -> list[tuple[int, Path]]:
    return [(step, npz) for step, npz, state in checkpoints(ref.folder)
            if state.get("reason") == "periodic"]


def damaged_checkpoint_file(c: Campaign, ref: Reference, kind: str, k: int):
    """``--restart FILE`` from a damaged copy of a reference checkpoint, into a new
    folder: one line, exit 2, nothing created -- or, where nothing read the damaged
    byte, the reference's final state."""
    def attempt():
        rng = c.rng(f"checkpoint-file/{kind}/{k}")
        work = c.folder(f"checkpoint-file-{kind.replace(' ', '-')}")
        step, src = rng.choice(periodic_checkpoints(ref))
        npz = work / src.name
        shutil.copy(src, npz)
        shutil.copy(src.with_suffix(".json"), npz.with_suffix(".json"))
        how = damage_checkpoint(kind, npz, rng)
        out = work / "out"
        x = demstep(["run", ref.case, "--out", out, "--quiet", "--restart", npz], work)
        name = f"damaged checkpoint, --restart FILE: {kind}"
        if x.code == 0 and kind in ("zeroed", "flipped"):  # the damage was never read
            what, problem, _ = compare_results(out, ref.folder)[0]  # (the final checkpoint)
            return [(name, problem and f"{what}: {problem}",
                     f"step {step}, {how}: not read, the restart completed as the reference")]
        problem = one_line_problem(x, 2, ("restart",))
        if problem is None and out.exists():
            problem = f"one line, but it created {out.name}/"
        return [(name, problem, f"step {step}, {how}: one line, exit 2")]
    return attempt


def damaged_checkpoint_folder(c: Campaign, ref: Reference, kind: str, k: int):
    """``--restart DIR`` where the newest checkpoint of the run folder DIR is damaged:
    refused with one line and the folder unchanged, or a fall-back to an older
    checkpoint that ends with the reference's results."""
    def attempt():
        rng = c.rng(f"checkpoint-folder/{kind}/{k}")
        work = c.folder(f"checkpoint-folder-{kind.replace(' ', '-')}")
        folder = work / "run"
        shutil.copytree(ref.folder, folder)
        final = final_checkpoint(folder)  # as if killed after its last periodic checkpoint
        final.unlink()
        final.with_suffix(".json").unlink()
        step, npz, _ = checkpoints(folder)[-1]
        how = damage_checkpoint(kind, npz, rng)
        before = snapshot(folder)
        x = demstep(["run", ref.case, "--out", folder, "--quiet", "--restart", folder], work)
        name = f"damaged checkpoint, --restart DIR: {kind}"
        if x.code == 0:
            problem = next((f"{what}: {p}" for what, p, _ in compare_results(folder, ref.folder)
                            if p), None)
            if "Traceback" in x.err:
                problem = gist(x)
            return [(name, problem, f"newest checkpoint (step {step}) {how}: the restart "
                     f"completed as the reference")]
        problem = one_line_problem(x, 2, ("restart",))
        change = snapshot_change(before, snapshot(folder))
        if problem is None and change:
            problem = f"one line, but the folder changed: {change}"
        return [(name, problem, f"newest checkpoint (step {step}) {how}: one line, "
                 f"exit 2, folder unchanged")]
    return attempt


# ============================================================== 4. damaged histories
HISTORY_DAMAGE = ("NUL bytes appended", "a garbled row", "a row cut short", "invalid UTF-8")


def damage_history(kind: str, path: Path, step: int, rng: random.Random) -> str:
    """Damage the rows of ``path`` after ``step`` as a crash could (in place)."""
    lines = path.read_bytes().split(b"\n")[:-1]
    after = [k for k in range(1, len(lines)) if int(lines[k].split(b",", 1)[0]) > step]
    if kind == "NUL bytes appended":
        n = rng.randint(512, 8192)
        path.write_bytes(b"\n".join(lines) + b"\n" + bytes(n))
        return f"{n} NUL bytes appended"
    k = rng.choice(after)
    row = lines[k]
    if kind == "a garbled row":  # (the whole row: junk of its length, no step first)
        junk = b"#" + bytes(rng.choice(b"abcxyz#;:?! ,\x07") for _ in range(len(row) - 1))
        lines[k] = junk
        how = f"row {k + 1} replaced by {len(junk)} bytes of junk"
    elif kind == "a row cut short":  # (a write cut by a crash, the next rows behind it)
        cut = rng.randrange(1, len(row))
        lines[k] = row[:cut]
        how = f"row {k + 1} cut after {cut} of {len(row)} characters"
    else:
        at = rng.randrange(len(row))
        lines[k] = row[:at] + b"\xff\xfe\xc3" + row[at:]
        how = f"bytes FF FE C3 in row {k + 1}"
    path.write_bytes(b"\n".join(lines) + b"\n")
    return how


def history_problem(path: Path, ref_path: Path) -> str | None:
    """None when the history at ``path`` is well formed (UTF-8, no NUL, the header
    and row lengths of the reference, numbers, steps rising) and equals the
    reference's; else the first problem."""
    data = path.read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        return f"history.csv holds bytes that are no UTF-8 (at {exc.start})"
    if "\x00" in text:
        return f"history.csv holds {text.count(chr(0))} NUL byte(s)"
    rows = list(csv.reader(io.StringIO(text)))
    header = ref_path.read_text().split("\n", 1)[0].split(",")
    if rows[0] != header:
        return "history.csv: its header is not the reference's"
    previous = -1
    for line, row in enumerate(rows[1:], start=2):
        try:
            if len(row) != len(header):
                raise ValueError(f"{len(row)} values")
            values = [float(v) for v in row]
        except ValueError as exc:
            return f"history.csv line {line} is malformed ({exc})"
        if values[0] <= previous:
            return f"history.csv line {line}: step {values[0]:g} after {previous:g}"
        previous = values[0]
    return first_line_difference(data, ref_path.read_bytes(), "history.csv")


def damaged_history(c: Campaign, ref: Reference, kind: str, k: int):
    """A restart from a checkpoint of a copy of the reference folder whose history
    rows after the checkpoint's step are damaged: it completes, and history.csv is
    well formed and equal to the reference's."""
    def attempt():
        rng = c.rng(f"history/{kind}/{k}")
        work = c.folder(f"history-{kind.split()[-1].lower()}")
        folder = work / "run"
        shutil.copytree(ref.folder, folder)
        step, src = rng.choice(periodic_checkpoints(ref))
        how = damage_history(kind, folder / "history.csv", step, rng)
        x = demstep(["run", ref.case, "--out", folder, "--quiet", "--restart",
                     folder / "checkpoints" / src.name], work)
        name = f"damaged history: {kind}"
        if x.code != 0 or "Traceback" in x.err:
            return [(name, f"{how}, restart from step {step}: {gist(x)}", "")]
        return [(name, history_problem(folder / "history.csv", ref.folder / "history.csv"),
                 f"{how}, restart from step {step}: completed, history as the reference")]
    return attempt


# ===================================================================== 5. full disk
def full_disk(c: Campaign, ref: Reference, k: int):
    """Run into a tmpfs with too little free space, free it, restart."""
    def attempt():
        rng = c.rng(f"disk/{k}")
        name = f"full disk {k + 1}"
        mount = c.folder("disk")
        total = sum(p.stat().st_size + 4096 for p in ref.folder.rglob("*") if p.is_file())
        free = int(total * rng.uniform(0.35, 0.75))
        filler_size = total + (1 << 20)  # (deleted to free the space)
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={free + filler_size}",
                                  "tmpfs", str(mount)], capture_output=True, text=True)
        if mounted.returncode != 0:
            return [(name, None, "", f"cannot mount a tmpfs ({last_line(mounted.stderr)})")]
        try:
            return filled_disk(c, ref, mount, free, filler_size, name)
        finally:
            for _ in range(20):
                if subprocess.run(["umount", str(mount)], capture_output=True).returncode == 0:
                    break
                time.sleep(0.5)
            else:
                subprocess.run(["umount", "-l", str(mount)], capture_output=True)
    return attempt


def filled_disk(c: Campaign, ref: Reference, mount: Path, free: int, filler_size: int,
                name: str) -> list:
    """The run into the file system ``mount`` with ``free`` bytes free (a filler file
    takes the rest), then the restart after deleting the filler."""
    results = []
    filler = mount / "filler"
    with open(filler, "wb") as fh:
        fh.write(bytes(filler_size))
    folder = mount / "run"
    x = demstep(["run", ref.case, "--out", folder, "--quiet"], c.root)
    last = (x.err.splitlines() or [""])[-1]
    problem = None
    if x.timed_out or "Traceback" in x.err or x.code in (0, None):
        problem = gist(x) + (" (the disk never filled)" if x.code == 0 else "")
    elif not last.startswith("demstep: error: ") or not (
            str(mount) in last or re.search(r"\.(npz|json|csv|vtu|pvd|log|toml)\b", last)):
        problem = f"exit {x.code}, its error names no file: {last_line(x.err)}"
    results.append((f"{name}: the run stops with an error line naming a file", problem,
                    f"{free // 1024} KiB free: exit {x.code}, {last_line(x.err, 90)!r}"))
    filler.unlink()
    resume = restartable(folder)
    x = demstep(["run", ref.case, "--out", folder, "--quiet", "--restart", folder], c.root)
    if x.code != 0 or "Traceback" in x.err:
        problem = f"from step {resume}: {gist(x)}"
    else:
        problem = next((f"{what}: {p}" for what, p, _ in compare_results(folder, ref.folder)
                        if p), None)
    results.append((f"{name}: the restart after freeing space completes", problem,
                    f"from step {resume}, results identical to the reference"))
    if c.keep:
        shutil.copytree(folder, mount.parent / f"{mount.name}-kept")
    return results


# ================================================================ 6. concurrent runs
def concurrent_runs(c: Campaign, ref: Reference, offset: float):
    """Two runs into one new folder, the second ``offset`` s after the first: exactly
    one completes with the reference's results, the other exits 2 with one line."""
    return lambda: concurrent_pair(c, ref, offset)


def concurrent_pair(c: Campaign, ref: Reference, offset: float) -> list:
    work = c.folder("concurrent")
    folder = work / "out"
    runs = []
    for tag in ("A", "B"):
        case = work / f"case_{tag}.toml"  # (the same case: the results must be the reference's)
        shutil.copy(ref.case, case)
        runs.append(Started(["run", case, "--out", folder, "--quiet"], work, work, tag))
        if tag == "A":
            time.sleep(offset)
    exits = [run.wait() for run in runs]
    name = f"concurrent runs, the second {offset:.2f} s after the first"
    winners = [k for k, x in enumerate(exits) if x.code == 0]
    if len(winners) != 1:
        return [(name, "exits " + ", ".join(gist(x) for x in exits), "")]
    win, lose = winners[0], 1 - winners[0]
    problem = one_line_problem(exits[lose], 2)
    tag = "AB"[win]
    info = run_info(folder)
    if problem is None and not str(info.get("case", "")).endswith(f"case_{tag}.toml"):
        problem = f"run.json names {info.get('case')!r}, not the winner's case_{tag}.toml"
    if problem is None:
        problem = next((f"{what}: {p}" for what, p, _ in compare_results(folder, ref.folder)
                        if p), None)
    return [(name, problem, f"{tag} won, the other: {last_line(exits[lose].err, 80)!r}")]


# ============================================================== 7. malformed inputs
FILE_CASE = """name = "file_case"
[particles]
generator = "file"
path = "{path}"
density = 2500.0
[contact]
law = "linear"
k_n = 1.0e4
mu = 0.4
[box]
lower = [-0.01, -0.01, -0.01]
upper = [0.01, 0.01, 0.01]
[[stages]]
name = "go"
steps = 10
"""

GOOD_CSV = "x,y,z,r\n0.0,0.0,0.0,0.001\n0.0025,0.0,0.0,0.001\n0.0,0.0025,0.0,0.001\n"
#: three spheres in contact (``demstep dt`` needs contacts)
TOUCHING_CSV = "x,y,z,r\n0.0,0.0,0.0,0.001\n0.002,0.0,0.0,0.001\n0.0,0.002,0.0,0.001\n"


class HttpServer:
    """A plain HTTP server on 127.0.0.1 (no Dask scheduler) in a thread."""

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            body = b"<html><body>not a Dask scheduler</body></html>"
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):
            pass

    def __enter__(self):
        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), self.Handler)
        threading.Thread(target=self.server.serve_forever, daemon=True).start()
        return f"tcp://127.0.0.1:{self.server.server_address[1]}"

    def __exit__(self, *exc):
        self.server.shutdown()
        self.server.server_close()


@dataclass
class BadInput:
    """One malformed input: ``args`` (with {case}, {out}, {dir}, {scheduler} filled
    in), the files to make first in {dir} (name -> text or bytes), the words the error
    must name and those it must not say; ``fast``: part of the --fast subset."""

    name: str
    args: list
    files: dict
    words: tuple = ()
    refused: tuple = ()
    fast: bool = True


def malformed_inputs(case_text: str) -> list[BadInput]:
    def case(old, new):
        if old not in case_text:
            raise SystemExit(f"fault_campaign: the case has no {old!r}")
        return {"case.toml": case_text.replace(old, new)}

    def file_case(name, content):
        return {name: content, "case.toml": FILE_CASE.format(path=name)}

    run = ["run", "{dir}/case.toml", "--out", "{out}", "--quiet", "--max-steps", "1"]
    run_dev_zero = {"case.toml": FILE_CASE.format(path="/dev/zero")}
    stages_at = case_text.index("[[stages]]")
    particles = re.search(r"\[particles\]\n(.*?\n)\n", case_text, re.S).group(0)
    big = "x,y,z,r\n" + "1" * (140 * 1024) + ",0,0,0.001\n"
    binary = bytes(random.Random(13).randrange(256) for _ in range(4096))
    return [
        BadInput("case: no [[stages]]", run, {"case.toml": case_text[:stages_at]}, ("stages",)),
        BadInput("case: no [particles]", run, case(particles, ""), ("particles",), fast=False),
        BadInput("case: count of the wrong type", run,
                 case("count = [8, 8, 12]", 'count = "eight"'), ("count",)),
        BadInput("case: spacing = nan", run, case("spacing = 0.003", "spacing = nan"),
                 ("spacing",)),
        BadInput("case: negative radius", run, case("radius_min = 0.0008", "radius_min = -0.0008"),
                 ("radius_min",)),
        BadInput("case: no TOML", run, {"case.toml": binary}, ("case.toml",), fast=False),
        BadInput("case: a stage name with a newline", run,
                 case('name = "settle"', 'name = "set\\ntle"'), ("name",)),
        BadInput("particle file: negative radius", run,
                 file_case("p.csv", GOOD_CSV.replace(",0.001\n0.0025", ",-0.001\n0.0025")),
                 ("p.csv",)),
        BadInput("particle file: NaN", run, file_case("p.csv", GOOD_CSV.replace("0.0025,", "nan,")),
                 ("p.csv",), fast=False),
        BadInput("particle file: no r column", run,
                 file_case("p.csv", "x,y,z\n0,0,0\n0.0025,0,0\n"), ("p.csv",), fast=False),
        BadInput("particle file: empty", run, file_case("p.csv", ""), ("p.csv",), fast=False),
        BadInput("particle file: a field over 128 KiB", run, file_case("p.csv", big), ("p.csv",)),
        BadInput("particle file: a binary file named .csv", run, file_case("p.csv", binary),
                 ("p.csv",)),
        BadInput("particle file: /dev/zero", run, run_dev_zero, ("/dev/zero",),
                 ("no such file",)),
        BadInput("dt: a field over 128 KiB", ["dt", "{dir}/p.csv", "--kn", "1e4"],
                 {"p.csv": big}, ("p.csv",), fast=False),
        BadInput("dt: a binary file named .csv", ["dt", "{dir}/p.csv", "--kn", "1e4"],
                 {"p.csv": binary}, ("p.csv",), fast=False),
        BadInput("dt: /dev/zero", ["dt", "/dev/zero", "--kn", "1e4"], {}, ("/dev/zero",),
                 ("no such file",), fast=False),
        BadInput('run --out ""', ["run", "{case}", "--out", "", "--quiet", "--max-steps", "1"],
                 {}, ("out",)),
        BadInput("run --max-steps -1", ["run", "{case}", "--out", "{out}", "--max-steps", "-1"],
                 {}, ("max-steps",), fast=False),
        BadInput("run --restart of a missing checkpoint",
                 ["run", "{case}", "--out", "{out}", "--restart", "{dir}/nothing.npz"], {},
                 ("restart",), fast=False),
        BadInput("sweep --scheduler at a plain HTTP server",
                 ["sweep", "{case}", "--param", "contact.mu=0.1,0.2", "--out", "{out}",
                  "--scheduler", "{scheduler}", "--quiet"], {}, ("scheduler",)),
    ]


def fill(args, **values) -> list[str]:
    return [str(a).format(**values) for a in args]


def bad_input_attempt(c: Campaign, ref: Reference, bad: BadInput, scheduler: str):
    """Make the files, run the command from an empty working folder: exit 2, one line,
    no traceback, nothing written."""
    def attempt():
        work = c.folder("input")
        for name, content in bad.files.items():
            path = work / name
            if isinstance(content, bytes):
                path.write_bytes(content)
            else:
                path.write_text(content, encoding="utf-8")
        cwd = work / "cwd"
        cwd.mkdir()
        out = work / "out"
        x = demstep(fill(bad.args, case=ref.case, out=out, dir=work, scheduler=scheduler),
                    cwd, limit_memory=True)
        problem = one_line_problem(x, 2, bad.words, bad.refused)
        written = [str(p.relative_to(work)) for p in (out, *cwd.iterdir()) if p.exists()]
        if written:
            where = (f"{written[0]} in the working folder" if written[0].startswith("cwd")
                     else f"{written[0]}/")
            problem = ("accepted (exit 0), it wrote " if x.code == 0
                       else f"{problem}; and it wrote ") + where
        return [(f"input: {bad.name}", problem, last_line(x.err, 100))]
    return attempt


def negative_wall_attempt(c: Campaign):
    """``demstep dt FILE --wall -0.03,0,0:1,0,0``: a wall at x = -0.03, a valid one:
    taken as ``--wall=-0.03,...`` is (the same output), or refused with one line
    naming it; argparse's "expected one argument" (it took the value for an option)
    is a failure."""
    def attempt():
        work = c.folder("input-wall")
        csv_path = work / "p.csv"
        csv_path.write_text(TOUCHING_CSV)
        spec = "-0.03,0,0:1,0,0"
        common = ["dt", csv_path, "--kn", "1e4", "--density", "2500"]
        name = "input: dt --wall -0.03,0,0:1,0,0"
        control = demstep(common + [f"--wall={spec}"], work, limit_memory=True)
        if control.code != 0:
            return [(name, f"the control --wall={spec} fails: {gist(control)}", "")]
        x = demstep(common + ["--wall", spec], work, limit_memory=True)
        if x.code == 0:
            problem = None if x.out == control.out else f"its output differs from --wall={spec}'s"
            return [(name, problem, f"taken as --wall={spec}")]
        problem = one_line_problem(x, 2, (spec,))
        if problem and "expected one argument" in x.err:
            problem = (f"refused as {last_line(x.err).removeprefix('demstep: error: ')!r}: "
                       f"the value was taken for an option (--wall={spec} is accepted)")
        return [(name, problem, "refused, naming the wall")]
    return attempt


def file_case_control(c: Campaign):
    """The file case of the particle-file attempts runs with a good file (else they
    would pass for the wrong reason)."""
    def attempt():
        work = c.folder("input-control")
        (work / "p.csv").write_text(GOOD_CSV)
        (work / "case.toml").write_text(FILE_CASE.format(path="p.csv"))
        x = demstep(["run", work / "case.toml", "--out", work / "out", "--quiet",
                     "--max-steps", "1"], work)
        return [("input: control, the particle-file case with a good file runs",
                 None if x.code == 0 else gist(x), "exit 0")]
    return attempt


# ============================================================================ main
def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     epilog="See the module docstring for what is checked.")
    parser.add_argument("--seed", type=int, default=None,
                        help="seed of the random choices (default: a new one, printed)")
    parser.add_argument("--cycles", type=int, default=None, metavar="N",
                        help="kill/restart cycles (default 2 with --fast, else 20)")
    parser.add_argument("--fast", action="store_true",
                        help="the CI subset: a short case, 2 cycles, one of each damage")
    parser.add_argument("--keep", action="store_true", help="keep the temporary folder")
    parser.add_argument("--jobs", type=int, default=2, metavar="N",
                        help="attempts after the kill/restart cycles run N at a time (default 2)")
    args = parser.parse_args(argv)
    seed = args.seed if args.seed is not None else random.SystemRandom().randrange(10**6)
    cycles = args.cycles if args.cycles is not None else (2 if args.fast else 20)
    root = Path(tempfile.mkdtemp(prefix="demstep-fault-campaign-"))
    c = Campaign(root, seed, args.fast, max(1, cycles), max(1, args.jobs), args.keep)
    start = time.monotonic()
    print(f"fault campaign: seed {seed} (again: --seed {seed}), "
          f"{'fast' if args.fast else 'full'}, {c.cycles} cycle(s), in {root}", flush=True)
    try:
        case_text = shrunk_case(args.fast)
        case = root / "case.toml"
        case.write_text(case_text, encoding="utf-8")
        ref = reference_run(c, case)
        if ref is not None:
            campaign(c, ref, case_text)
    finally:
        if args.keep:
            print(f"fault campaign: kept {root}")
        else:
            shutil.rmtree(root, ignore_errors=True)
    n = sum(c.counts.values())
    print(f"fault campaign: seed {seed}: {n} attempts, {c.counts['ok']} ok, "
          f"{c.counts['FAIL']} failed, {c.counts['skip']} skipped "
          f"({time.monotonic() - start:.0f} s)", flush=True)
    return 0 if c.counts["FAIL"] == 0 and c.counts["ok"] > 0 else 1


def campaign(c: Campaign, ref: Reference, case_text: str):
    """Every attempt after the reference run: the kill/restart cycles alone (their
    moments are wall-clock times), then the others, ``jobs`` at a time."""
    kill_restart_cycles(c, ref)
    rng = c.rng("plan")
    repeats = 1 if c.fast else 3
    with HttpServer() as scheduler:
        bad_inputs = [bad for bad in malformed_inputs(case_text) if bad.fast or not c.fast]
        sweep = [bad for bad in bad_inputs if bad.args[0] == "sweep"]  # (slow: dask) first
        attempts = [bad_input_attempt(c, ref, bad, scheduler) for bad in sweep]
        attempts += [killed_folder(c, ref)]
        attempts += [full_disk(c, ref, k) for k in range(1 if c.fast else 2)]
        offsets = [0.0] if c.fast else [0.0, rng.uniform(0.0, ref.startup),
                                        ref.startup + rng.uniform(0.0, ref.stepping)]
        attempts += [concurrent_runs(c, ref, offset) for offset in offsets]
        attempts += [damaged_checkpoint_file(c, ref, kind, k)
                     for k in range(repeats) for kind in CHECKPOINT_DAMAGE]
        folder_kinds = [rng.choice(CHECKPOINT_DAMAGE)] if c.fast else list(CHECKPOINT_DAMAGE)
        attempts += [damaged_checkpoint_folder(c, ref, kind, 0) for kind in folder_kinds]
        attempts += [damaged_history(c, ref, kind, k) for k in range(repeats)
                     for kind in HISTORY_DAMAGE]
        attempts += [file_case_control(c), negative_wall_attempt(c)]
        attempts += [bad_input_attempt(c, ref, bad, scheduler) for bad in bad_inputs
                     if bad not in sweep]
        c.run_all(attempts)


if __name__ == "__main__":
    sys.exit(main())
