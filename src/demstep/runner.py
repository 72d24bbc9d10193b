"""Run a case: stages, outputs, progress, checkpoints and restarts.

:func:`run_case` validates everything (the case, the particle file, the walls against
the particles, the restart checkpoint) before it creates the output folder, so a bad
input leaves nothing behind. The folder then holds::

    case.toml        the resolved case (every default filled in)
    run.json         demstep version, status, steps, times, restarts
    run.log          the log
    history.csv      every output.history_every steps (demstep.io.history)
    vtk/             particles/contacts/walls frames and .pvd series (demstep.io.vtk)
    checkpoints/     stepNNNNNNNNNN.npz (demstep.io.checkpoint) + .json (where the run was)

Stages run in chunks of steps (``Simulation.run(steps=n)``). Chunk ends fall on every
output step (multiples of the intervals, counted from step 0) and on every
``check_every`` steps of a stage (counted from the stage start); between chunks the
runner writes outputs, updates the progress bar and reacts to SIGINT/SIGTERM by saving
a checkpoint and stopping cleanly. Where the chunks end does not change the
trajectory, so a run restarted from any checkpoint continues bit for bit as the
uninterrupted run would have: the checkpoint restores the dynamic state, and the JSON
beside it records the stage, the steps done in it and its start, from which the stage
changes are replayed and the stage's remaining steps recomputed.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import platform
import signal
import sys
import threading
import time as wallclock
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

from demstep import __version__
from demstep.case import Case, apply_stage, build_simulation, check_stages, dump_case
from demstep.energy import EnergyBalanceError
from demstep.errors import InputError, SimulationDiverged
from demstep.io.atomic import remove_orphans, write_text_atomic
from demstep.io.checkpoint import load_checkpoint, save_checkpoint
from demstep.io.history import HistoryWriter
from demstep.io.lock import FolderLock, check_folder_creatable, folder_is_empty, make_folder
from demstep.io.manifest import OutputManifest, remove_written
from demstep.io.textfile import not_a_file_reason
from demstep.io.vtk import VtkWriter

log = logging.getLogger("demstep")

STATE_FORMAT = 1
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
#: default chunk: about this many particle-steps (a fraction of a second of computing)
CHUNK_PARTICLE_STEPS = 500_000
MIN_CHUNK_STEPS, MAX_CHUNK_STEPS = 10, 20_000
#: the steps a stage ending on ``until_kinetic_below`` takes at most when it gives no
#: ``max_steps`` (a kinetic energy never reached, e.g. elastic particles that never
#: settle, would run forever); said in a warning when the stage starts
DEFAULT_SETTLE_MAX_STEPS = 1_000_000


def default_chunk_steps(n_particles: int) -> int:
    """Steps per chunk for ``n_particles`` particles. Chunk ends must not depend on the
    wall clock: ``Simulation.time`` is summed chunk by chunk, so a restart reproduces
    the times of the uninterrupted run only when both chunk alike."""
    steps = CHUNK_PARTICLE_STEPS // max(1, n_particles)
    return int(min(MAX_CHUNK_STEPS, max(MIN_CHUNK_STEPS, steps)))


@dataclass
class RunResult:
    """How a run ended: ``status`` is completed, interrupted (a signal; checkpoint
    saved), aborted (a second signal; no checkpoint), diverged or energy_stop;
    ``checkpoint`` is the last checkpoint written (restart from it); ``signal`` the
    name of the signal that stopped the run (SIGINT, SIGTERM) or None."""

    status: str
    out_dir: Path
    step: int
    time: float
    checkpoint: Path | None = None
    message: str = ""
    signal: str | None = None

    @property
    def ok(self) -> bool:
        return self.status == "completed"

    @property
    def exit_status(self) -> int:
        """The command line's exit status: 0 completed, 128 + the signal number when a
        signal stopped the run (130 SIGINT, 143 SIGTERM), 1 otherwise."""
        if self.signal is not None:
            return 128 + int(signal.Signals[self.signal])
        return 0 if self.ok else 1


@dataclass
class RunPosition:
    """Where a run is: stage index, steps done in it, its start step and time [T], and
    its planned number of steps (None when it ends on a time or an energy condition)."""

    stage: int
    stage_step: int
    stage_start_step: int
    stage_start_time: float
    stage_total: int | None


# ------------------------------------------------------------------ checkpoints
def state_path(checkpoint) -> Path:
    """The JSON beside a checkpoint recording where the run was."""
    return Path(checkpoint).with_suffix(".json")


def write_state(checkpoint, pos: RunPosition, case: Case, sim, reason: str) -> Path:
    data = {"format": STATE_FORMAT, "demstep_version": __version__, "reason": reason,
            "checkpoint": Path(checkpoint).name, "step": sim.step, "time": sim.time,
            "stage_name": case.stage_label(pos.stage) if pos.stage < len(case.stages) else None,
            "case_sha256": case_hash(case), **asdict(pos)}
    return _write_text(state_path(checkpoint), json.dumps(data, indent=2) + "\n")


def read_state(checkpoint, key: str = "restart",
               stages: int | None = None) -> tuple[RunPosition, dict]:
    """Where the run that wrote ``checkpoint`` was; errors name the option ``key``
    (``restart`` for ``demstep run --restart``, ``checkpoint`` for ``demstep dt``) and
    the field and value at fault: the stage an integer in [0, ``stages``] (the number of
    stages of the case; ``stages``: its end, the run completed), the step counts
    integers >= 0 (``stage_total`` also null), the times finite numbers >= 0."""
    path = state_path(checkpoint)
    if not path.is_file():
        raise InputError(f"{key}: no run state {path.name} beside the checkpoint {checkpoint}")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(data, dict):
            raise ValueError(f"a JSON {type(data).__name__}, not an object")
        if data.get("format") != STATE_FORMAT:
            raise ValueError(f"format {data.get('format')!r}")
        missing = [name for name in ("stage", "stage_step", "stage_start_step",
                                     "stage_start_time", "stage_total") if name not in data]
        if missing:
            raise ValueError(f"no {missing[0]!r}")
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{key}: {path}: not a demstep run state ({exc})") from None

    def bad(name, rule):
        return InputError(f"{key}: {path}: {name} must be {rule}, got {data[name]!r}")

    def count(name, top=None):
        value = data[name]
        if isinstance(value, bool) or not isinstance(value, int) or value < 0 \
                or (top is not None and value > top):
            raise bad(name, "an integer >= 0" if top is None else f"an integer in [0, {top}] "
                      f"(the case has {top} stage(s))")
        return value

    def seconds(name):
        value = data[name]
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value) or value < 0:
            raise bad(name, "a finite number >= 0")
        return float(value)

    if "step" in data:  # (the step and time of the checkpoint, beside the position)
        count("step")
    if "time" in data:
        seconds("time")
    pos = RunPosition(count("stage", stages), count("stage_step"), count("stage_start_step"),
                      seconds("stage_start_time"),
                      None if data["stage_total"] is None else count("stage_total"))
    return pos, data


#: reasons of checkpoints written when a run failed; a folder restart skips them
FAILED = ("diverged", "energy_stop")


def find_checkpoint(path) -> Path:
    """A checkpoint file, or the newest good checkpoint (by step; not one saved at a
    divergence or an energy stop) in a checkpoint folder or a run folder."""
    path = Path(path)
    try:
        path.stat()
    except FileNotFoundError:
        pass  # (said below)
    except OSError as exc:  # e.g. a name too long: Path.is_dir raises it
        raise InputError(f"restart: cannot read {str(path)!r} "
                         f"({exc.strerror or type(exc).__name__})") from None
    if path.is_dir():
        folder = path / "checkpoints" if (path / "checkpoints").is_dir() else path
        found = []
        for js in folder.glob("*.json"):
            try:
                data = json.loads(js.read_text(encoding="utf-8"))
                npz = folder / data["checkpoint"]
                if npz.is_file() and data.get("reason") not in FAILED:
                    found.append((int(data["step"]), js.stat().st_mtime, npz))
            except (ValueError, KeyError, TypeError, OSError):
                continue
        if not found:
            raise InputError(f"restart: no checkpoint with a run state in {folder}")
        return max(found)[2]
    if path.suffix.lower() == ".json" and path.is_file():
        raise InputError(f"restart: {path} is the run state beside a checkpoint; give the "
                         f"checkpoint {path.with_suffix('.npz')} or the run folder")
    if not path.is_file():
        reason = not_a_file_reason(path) or "no such file"
        raise InputError(f"restart: not a checkpoint file ({reason}), got {str(path)!r}")
    return path


def kept_checkpoints(folder: Path) -> list[Path]:
    """The checkpoints in ``folder`` that ``output.checkpoint_keep`` counts, oldest
    (lowest step) first: every one with a run state, but those saved at a failure
    (:data:`FAILED`: the state a divergence left, kept as evidence)."""
    found = []
    for js in Path(folder).glob("*.json") if Path(folder).is_dir() else ():
        try:
            data = json.loads(js.read_text(encoding="utf-8"))
            npz = js.with_suffix(".npz")
            if npz.is_file() and data.get("reason") not in FAILED:
                found.append((int(data["step"]), js.stat().st_mtime, npz))
        except (ValueError, KeyError, TypeError, OSError):
            continue
    return [npz for *_, npz in sorted(found)]


def case_hash(case: Case) -> str:
    return hashlib.sha256(dump_case(case).encode()).hexdigest()


def _write_text(path, text: str) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(path, text)


# ---------------------------------------------------------------- stop signals
class StopRequest:
    """SIGINT/SIGTERM during a run.

    The first signal asks the run to stop at the end of the current chunk of steps
    (a fraction of a second) with a checkpoint: status 'interrupted'. A second signal
    aborts without a checkpoint: status 'aborted'. With ``exit_now`` (the command
    line), the abort is at once: ``on_abort(signal_name, started)`` records it (run.json,
    log) and the process exits with 128 + the signal number (130 SIGINT, 143 SIGTERM);
    the first signal also acts at once while no chunk of steps has finished in this
    process (``started`` False: during the first compilation of the kernels, which can
    take a minute), when nothing would be saved anyway. Without ``exit_now`` (the
    Python API) an abort takes effect at the end of the chunk.

    The handler never raises: an exception raised from a signal handler while numba's
    dispatcher runs C code surfaces as "SystemError: ... returned a result with an
    exception set" instead of the KeyboardInterrupt."""

    def __init__(self, exit_now: bool = False, on_abort: Callable | None = None):
        self.signal_name: str | None = None
        self.abort_signal: str | None = None
        self.started = False
        #: the run has ended and is being recorded: later signals change nothing
        self.finished = False
        self.exit_now = exit_now
        self.on_abort = on_abort
        self._previous = {}

    def __bool__(self):
        return self.signal_name is not None

    def _handle(self, signum, frame):
        name = signal.Signals(signum).name
        if self.finished:
            return  # the run has ended and is being recorded (or the process exits)
        if self.signal_name is None and (self.started or not self.exit_now):
            self.signal_name = name
            log.warning("%s received: saving a checkpoint and stopping after this chunk "
                        "(again to abort at once)", name)
            return
        if self.signal_name is None:
            self.signal_name = name
        self.abort_signal = name
        if not self.exit_now:
            log.warning("%s received again: stopping after this chunk without a checkpoint",
                        name)
            return
        try:
            if self.on_abort is not None:
                self.on_abort(name, self.started)
        finally:
            os._exit(128 + signum)

    def install(self):
        if threading.current_thread() is not threading.main_thread():
            return
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._handle)

    def restore(self):
        """The handlers from before :meth:`install`; with ``exit_now`` after a signal
        stopped the run, signals ignored instead: the process is about to exit with
        128 + that signal's number, and a second signal arriving now must neither kill
        it with the default action nor turn the exit into a traceback."""
        ignore = self.exit_now and self.signal_name is not None
        for sig, handler in self._previous.items():
            signal.signal(sig, signal.SIG_IGN if ignore else handler)
        self._previous.clear()


# ------------------------------------------------------------------- progress
class _NoProgress:
    def start_stage(self, label, total):
        pass

    def update(self, sim, pos, total):
        pass

    def stop(self):
        pass


class _RichProgress:
    """rich progress bar per stage: steps, simulated time, dt, energy error, ETA."""

    def __init__(self):
        from rich.console import Console  # (deferred: a heavy import, loaded only when used)
        from rich.progress import (BarColumn,  # (deferred: a heavy import, loaded only when used)
                                   MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                   TimeRemainingColumn)

        self.console = Console(stderr=True)
        self.progress = Progress(
            TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
            TextColumn("t={task.fields[t]}"), TextColumn("dt={task.fields[dt]}"),
            TextColumn("err={task.fields[err]}"), TimeElapsedColumn(), TimeRemainingColumn(),
            console=self.console, transient=False)
        self.progress.start()
        self.task = None

    def start_stage(self, label, total):
        self.task = self.progress.add_task(label, total=total, t="0", dt="-", err="-")

    def update(self, sim, pos, total):
        self.progress.update(self.task, completed=pos.stage_step, total=total,
                             t=f"{sim.time:.4g}", dt=f"{sim.dt:.3g}" if sim.dt else "-",
                             err=f"{sim.ledger.balance_error():.2e}")

    def stop(self):
        self.progress.stop()


# ---------------------------------------------------------------------- logging
class _LogFile(logging.FileHandler):
    """The run's log, appended to, never through a symbolic link: every other output is
    replaced atomically, and a link named run.log (a restart appended to its target)
    is replaced by a regular file first (:func:`_own_log`); O_NOFOLLOW refuses a link
    made in between."""

    def _open(self):
        fd = os.open(self.baseFilename, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW,
                     0o666)
        return open(fd, "a", encoding=self.encoding, errors=self.errors)


def _own_log(path: Path) -> str | None:
    """Replace a symbolic link at ``path`` by a regular file holding what the link's
    target held (when it is a readable file): the target is never written. Returns the
    warning to log (None: no link)."""
    if not path.is_symlink():
        return None
    try:
        text = path.read_text(encoding="utf-8", errors="replace") if path.is_file() else ""
    except OSError:
        text = ""
    target = os.readlink(path)
    write_text_atomic(path, text)  # (os.replace swaps the link itself for the file)
    return (f"run.log was a symbolic link to {target}: replaced by a regular file (the "
            f"link's target is left as it was)")


def _setup_logging(out_dir: Path, level: str, console) -> list[logging.Handler]:
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(message)s")
    handlers: list[logging.Handler] = []
    fh = _LogFile(out_dir / "run.log", encoding="utf-8", delay=False)
    fh.setFormatter(fmt)
    handlers.append(fh)
    if console is not None:
        from rich.logging import RichHandler  # (deferred: a heavy import, loaded only when used)

        handlers.append(RichHandler(console=console, show_path=False))
    else:
        sh = logging.StreamHandler(sys.stderr)
        sh.setFormatter(logging.Formatter("demstep: %(levelname)s: %(message)s"))
        handlers.append(sh)
    for h in handlers:
        h.setLevel(level)
        log.addHandler(h)
    return handlers


# ------------------------------------------------------------------- the runner
class _Runner:
    def __init__(self, case, sim, out_dir, pos, max_steps, quiet, on_chunk, chunk_steps,
                 stop: StopRequest, progress, manifest: OutputManifest):
        self.case, self.sim, self.out_dir, self.pos = case, sim, out_dir, pos
        self.max_steps = max_steps
        self.on_chunk = on_chunk
        self.chunk_steps = chunk_steps or default_chunk_steps(len(sim.r))
        self.stop = stop
        self.progress = progress
        self.ckpt_dir = out_dir / "checkpoints"
        self.manifest = manifest
        #: the checkpoints ``checkpoint_keep`` counts, oldest first: those in the folder
        #: from before (a restart), then this run's
        self.kept_ckpts: list[Path] = kept_checkpoints(self.ckpt_dir)
        out = case.output
        resume = sim.step if pos is not None else None
        self.history = None
        if out.history_every:
            manifest.record(out_dir / "history.csv")
            self.history = HistoryWriter(out_dir / "history.csv", sim,
                                         extra={"stage": lambda s: self.pos.stage},
                                         resume_after_step=resume)
        self.vtk = None
        if out.vtk_every:
            self.vtk = VtkWriter(out_dir / "vtk", contacts=out.vtk_contacts,
                                 resume_after_step=resume, on_write=manifest.record)
        self.last_checkpoint: Path | None = None

    # ---- outputs
    def _outputs(self):
        sim, out = self.sim, self.case.output
        if self.history is not None and sim.step % out.history_every == 0:
            self.history.write(sim)
        if self.vtk is not None and sim.step % out.vtk_every == 0:
            self.vtk.write(sim)
        if out.checkpoint_every and sim.step % out.checkpoint_every == 0:
            self.checkpoint("periodic")

    def checkpoint(self, reason: str) -> Path:
        """Save a checkpoint and its run state; then, past ``checkpoint_keep``, remove
        the oldest of the kept ones (:func:`kept_checkpoints`: every reason but a
        failure; the newest is never removed)."""
        path = self.ckpt_dir / f"step{self.sim.step:010d}.npz"
        self.manifest.record(path, state_path(path))
        save_checkpoint(self.sim, path)
        write_state(path, self.pos, self.case, self.sim, reason)
        self.last_checkpoint = path
        log.info("checkpoint (%s) at step %d: %s", reason, self.sim.step, path)
        self.kept_ckpts = [p for p in self.kept_ckpts if p != path] + [path]
        keep = self.case.output.checkpoint_keep
        while keep and len(self.kept_ckpts) > keep:
            old = self.kept_ckpts.pop(0)
            for p in (old, state_path(old)):
                if p.exists():
                    p.unlink()
        return path

    # ---- stage bookkeeping
    def _start_stage(self, k: int):
        sim, stage = self.sim, self.case.stages[k]
        apply_stage(sim, self.case, k, fresh=True)
        sim.prepare()
        total = None
        if stage.steps is not None:
            total = stage.steps
        elif stage.duration is not None and sim.timestep.mode != "auto":
            total = int(math.ceil(stage.duration / sim.dt - 1e-9))
        self.pos = RunPosition(k, 0, sim.step, sim.time, total)
        log.info("stage %d/%d '%s' starts at step %d (t = %.6g)", k + 1, len(self.case.stages),
                 self.case.stage_label(k), sim.step, sim.time)
        if stage.until_kinetic_below is not None and stage.max_steps is None:
            log.warning("stage '%s': until_kinetic_below without max_steps: it stops after "
                        "%d steps if the kinetic energy stays above %.4g (give max_steps to "
                        "choose)", self.case.stage_label(k), DEFAULT_SETTLE_MAX_STEPS,
                        stage.until_kinetic_below)

    def _start_stage_keeping_work(self, k: int, done_here: bool):
        """:meth:`_start_stage`; when the stage cannot start (its changes are bad input
        only its start can tell, e.g. a bond file's pair too far apart by then) after
        stages this run did (``done_here``), a checkpoint of the state they left first,
        named in the one-line error (their work was lost: no checkpoint was written)."""
        try:
            self._start_stage(k)
        except InputError as exc:
            if not done_here:
                raise
            path = self.checkpoint("stage_error")
            raise InputError(f"{exc} (stage {k + 1} '{self.case.stage_label(k)}' could not "
                             f"start; the state after stage {k} is saved: fix the case and "
                             f"restart with --restart {path} --allow-changed-case)") from None

    def _stage_budget(self) -> int | None:
        """Steps this stage may still take at most (None: no fixed bound)."""
        stage = self.case.stages[self.pos.stage]
        bounds = []
        if self.pos.stage_total is not None:
            bounds.append(self.pos.stage_total)
        if stage.max_steps is not None:
            bounds.append(stage.max_steps)
        elif stage.until_kinetic_below is not None:
            bounds.append(DEFAULT_SETTLE_MAX_STEPS)
        if self.max_steps is not None:
            bounds.append(self.max_steps)
        return min(bounds) - self.pos.stage_step if bounds else None

    def _kinetic_below(self) -> bool:
        """Whether the stage's ``until_kinetic_below`` is met now, logged when it is: the
        kinetic energy of the last step (the ledger's, updated every step) below it,
        after at least one step of the stage (none done: not measured yet)."""
        sim, pos = self.sim, self.pos
        stage = self.case.stages[pos.stage]
        if pos.stage_step == 0 or not sim.ledger.kinetic < stage.until_kinetic_below:
            return False
        log.info("stage '%s': kinetic energy %.4g below %.4g after %d steps",
                 self.case.stage_label(pos.stage), sim.ledger.kinetic,
                 stage.until_kinetic_below, pos.stage_step)
        return True

    def _stage_done(self) -> bool:
        sim, pos = self.sim, self.pos
        stage = self.case.stages[pos.stage]
        if stage.until_kinetic_below is not None \
                and pos.stage_step % stage.check_every == 0 and self._kinetic_below():
            return True
        budget = self._stage_budget()
        if budget is not None and budget <= 0:
            # the stage ends on its step budget: measured there, below or not (between
            # two checks the energy may have fallen below already)
            if stage.until_kinetic_below is not None and not self._kinetic_below():
                if pos.stage_step == 0:
                    log.info("stage '%s': ended after 0 steps, kinetic energy not measured",
                             self.case.stage_label(pos.stage))
                else:
                    log.warning("stage '%s': kinetic energy %.4g still above %.4g after %d "
                                "steps", self.case.stage_label(pos.stage), sim.ledger.kinetic,
                                stage.until_kinetic_below, pos.stage_step)
            return True
        if stage.duration is not None and pos.stage_total is None:
            # as Simulation.run(duration=...): the first step at or past the end time
            t_end = pos.stage_start_time + stage.duration
            if sim.time >= t_end * (1 - 1e-12) or stage.duration == 0:
                return True
        return False

    def _chunk(self) -> int:
        sim, pos, out = self.sim, self.pos, self.case.output
        stage = self.case.stages[pos.stage]
        n = self.chunk_steps
        for every in (self.chunk_steps, out.history_every, out.vtk_every, out.checkpoint_every):
            if every:
                n = min(n, every - sim.step % every)
        budget = self._stage_budget()
        if budget is not None:
            n = min(n, budget)
        if stage.until_kinetic_below is not None:
            n = min(n, stage.check_every - pos.stage_step % stage.check_every)
        if stage.duration is not None and pos.stage_total is None:
            n = min(n, self._steps_within(pos.stage_start_time + stage.duration - sim.time, n))
        return max(1, n)

    def _steps_within(self, remaining: float, cap: int) -> int:
        """Steps that surely end before ``remaining`` [T] with auto dt (dt may grow by
        the factor 1 + growth once per 'every' steps, from the certified step: the
        motion limit may hold it below and let it go back up at once); at least 1."""
        ts = self.sim.timestep
        dt = max(self.sim.dt, self.sim.dt_certified or 0.0)
        n = cap
        while n > 1:
            growth = (1.0 + ts.growth) ** (n // max(1, int(ts.every)) + 2)
            if n * dt * growth < remaining:
                return n
            n //= 2
        return 1

    # ---- the loop
    def run(self) -> RunResult:
        sim, case = self.sim, self.case
        try:
            fresh_run = self.pos is None
            start = 0 if fresh_run else self.pos.stage
            for k in range(start, len(case.stages)):
                # a stage with no step done has not started (its changes are not applied)
                if fresh_run or k > start or self.pos.stage_step == 0:
                    self._start_stage_keeping_work(k, done_here=k > start)
                else:
                    sim.prepare()
                if fresh_run and k == 0 and self.vtk is not None:
                    self.vtk.write(sim)  # the initial state
                self.progress.start_stage(case.stage_label(k), self._stage_total_display())
                while not self._stage_done():
                    n = self._chunk()
                    before = sim.step
                    try:
                        sim.run(steps=n)
                    except SimulationDiverged as exc:
                        self.pos.stage_step += sim.step - before
                        return self._emergency("diverged", exc.checkpoint, str(exc))
                    except EnergyBalanceError as exc:
                        self.pos.stage_step += sim.step - before
                        path = Path(exc.checkpoint) if exc.checkpoint else None
                        return self._emergency("energy_stop", path, str(exc))
                    self.pos.stage_step += sim.step - before
                    self.stop.started = True
                    if self.stop.abort_signal is not None:
                        return self._aborted()
                    self._outputs()
                    self.progress.update(sim, self.pos, self._stage_total_display())
                    if self.on_chunk is not None:
                        self.on_chunk(sim)
                    if self.stop.abort_signal is not None:
                        return self._aborted()
                    if self.stop:
                        path = self.checkpoint(f"signal {self.stop.signal_name}")
                        return RunResult("interrupted", self.out_dir, sim.step, sim.time, path,
                                         f"stopped by {self.stop.signal_name} at step "
                                         f"{sim.step}; restart with --restart {path}",
                                         signal=self.stop.signal_name)
                self.progress.update(sim, self.pos, self._stage_total_display())
            # completed: final outputs and a checkpoint to extend the run from
            if self.history is not None:
                self.history.write(sim)
            if self.vtk is not None:
                self.vtk.write(sim)
            self.pos = RunPosition(len(case.stages), 0, sim.step, sim.time, 0)
            path = self.checkpoint("completed")
            return RunResult("completed", self.out_dir, sim.step, sim.time, path,
                             f"completed {len(case.stages)} stage(s): {sim.step} steps, "
                             f"t = {sim.time:.6g}, max energy error "
                             f"{sim.monitor.max_error:.3g}")
        finally:
            if self.history is not None:
                self.history.close()

    def _aborted(self) -> RunResult:
        """A second signal: stop without a checkpoint (the last one stays valid)."""
        sim = self.sim
        last = self.last_checkpoint
        restart = f"; restart from {last}" if last is not None else ""
        return RunResult("aborted", self.out_dir, sim.step, sim.time, last,
                         f"aborted by a second {self.stop.abort_signal} at step {sim.step} "
                         f"without a checkpoint{restart}", signal=self.stop.abort_signal)

    def _stage_total_display(self):
        budget = self._stage_budget()
        return None if budget is None else self.pos.stage_step + budget

    def _emergency(self, status, checkpoint, message) -> RunResult:
        path = Path(checkpoint) if checkpoint else None
        if path is not None and path.exists():
            self.manifest.record(path, state_path(path))
            write_state(path, self.pos, self.case, self.sim, status)
        log.error("%s", message)
        return RunResult(status, self.out_dir, self.sim.step, self.sim.time, path, message)


#: what a run writes into its folder (``overwrite`` removes what the folder's manifest
#: lists, :mod:`demstep.io.manifest`; nothing else is touched)
OUTPUTS = ("case.toml", "run.json", "run.log", "history.csv", "vtk", "checkpoints", "plots")


def remove_outputs(out_dir: Path, outputs=OUTPUTS) -> str | None:
    """Remove the outputs of an earlier run in ``out_dir``: the files its manifest lists
    (for a folder from before manifests, the names ``outputs`` and demstep's own files
    in its output folders). Files demstep did not write stay; returns the warning that
    says so (None: none stayed)."""
    kept = remove_written(out_dir, outputs)
    if not kept:
        return None
    return (f"out: kept {len(kept)} file(s) demstep did not write in {out_dir} "
            f"(e.g. {kept[0]})")

def _version_info() -> dict:
    import numba  # (deferred: a heavy import, loaded only when used)
    import numpy  # (deferred: a heavy import, loaded only when used)


    return {"demstep_version": __version__, "python": platform.python_version(),
            "numpy": numpy.__version__, "numba": numba.__version__,
            "platform": platform.platform()}


def earlier_results(out_dir: Path) -> str | None:
    """What ``out_dir`` holds of an earlier run's results, in words ("2 checkpoints (the
    newest at step 5000), 106 history rows, 36 VTK files"), or None: no checkpoint, no
    history row, no VTK frame but the initial one, no plot. Read from the files
    themselves, not from run.json (a run killed by SIGKILL never records its results)."""
    found = []
    ckpt = out_dir / "checkpoints"
    if ckpt.is_dir():
        npz = sorted(ckpt.glob("*.npz"))
        if npz:
            try:
                newest = f" (the newest at step {_checkpoint_step(find_checkpoint(out_dir))})"
            except InputError:
                newest = ""
            found.append(f"{len(npz)} checkpoint(s){newest}")
    history = out_dir / "history.csv"
    if history.is_file():
        with open(history, "rb") as fh:
            rows = sum(1 for _ in fh) - 1
        if rows > 0:
            found.append(f"{rows} history row(s)")
    vtk = out_dir / "vtk"
    if vtk.is_dir():
        frames = [f for f in vtk.iterdir() if f.suffix == ".vtu" and not f.stem.endswith(
            "_" + "0" * 10)]
        if frames:
            found.append(f"{len(frames)} VTK frame(s)")
    plots = out_dir / "plots"
    if plots.is_dir() and any(plots.iterdir()):
        found.append("plots")
    return ", ".join(found) or None


def _checkpoint_step(path: Path) -> int:
    data = json.loads(state_path(path).read_text(encoding="utf-8"))
    return int(data["step"])


def _replaceable(out_dir: Path) -> bool:
    """Whether a fresh run may write into ``out_dir`` without ``overwrite``: it does
    not exist, holds nothing but its lock file, or holds only what a run that stopped
    before its first step leaves (run.json, case.toml, run.log, a history header, the
    initial VTK frame; e.g. interrupted while compiling): no result
    (:func:`earlier_results`) and nothing that is not demstep's."""
    if _empty(out_dir):
        return True
    if not (out_dir / "run.json").is_file() or earlier_results(out_dir) is not None:
        return False
    return all(p.name in OUTPUTS or p.name.startswith(".") for p in out_dir.iterdir())


def _input_files(case: Case) -> list[tuple[str, Path]]:
    """The files a run of ``case`` reads, each with the key that names it: the case file
    itself, the particle file, the clumps' body file and template files, the bond file,
    the mesh files."""
    def from_case(name) -> Path:  # (relative paths are taken from the case file's folder)
        p = Path(name).expanduser()
        return p if p.is_absolute() else case.base_dir / p

    files = []
    if case.source and Path(case.source).is_file():
        files.append(("case", Path(case.source)))
    p = case.particles
    if p.generator == "file":
        files.append(("particles.path", case.particle_file()))
    elif getattr(p, "file", None) is not None:
        files.append(("particles.file", from_case(p.file)))
    for k, spec in enumerate(case.clumps):
        if spec.file is not None:
            files.append((f"clumps[{k}].file", from_case(spec.file)))
    if case.bond_file() is not None:
        files.append(("bonds.file", case.bond_file()))
    for k in range(len(case.meshes)):
        files.append((f"meshes[{k}].file", case.mesh_file(k)))
    return files


def _check_inputs_kept(case: Case, out_dir: Path, restart) -> None:
    """InputError when a file the run reads is one the run writes (or removes, with
    ``overwrite``) in ``out_dir``: one of :data:`OUTPUTS` or inside one of their folders.
    A restart may read the case.toml it rewrites (the run folder's resolved case)."""
    out = out_dir.resolve()
    for key, path in _input_files(case):
        source = path.resolve()
        for name in OUTPUTS:
            dest = out / name
            hit = source == dest or dest in source.parents
            if not hit and source.is_file() and dest.is_file():
                try:
                    hit = os.path.samefile(source, dest)  # (a hard link)
                except OSError:
                    pass
            if hit and not (restart is not None and key == "case" and name == "case.toml"):
                raise InputError(f"out: a run writes {name} into {out_dir}, which would "
                                 f"replace the input {key} {str(path)!r}; choose another "
                                 f"folder or move the input")


def _empty(out_dir: Path) -> bool:
    """Whether ``out_dir`` does not exist or holds nothing but its lock file."""
    return not out_dir.is_dir() or folder_is_empty(out_dir)


def check_out_empty(out_dir: Path, overwrite: bool,
                    hint: str = "give --restart to continue a run or --overwrite to replace it",
                    replaceable: Callable[[Path], bool] = _empty) -> None:
    """The rule of every output folder a fresh result goes into (``run --out``,
    ``paper --out``): unless ``overwrite``, it must be new, empty, or ``replaceable``;
    else an InputError naming the option and the folder, with ``hint`` (what to do);
    for a run folder with results (:func:`earlier_results`), what it holds and the
    command that continues it. Check it before anything is written, and again under
    the folder's lock."""
    if overwrite or replaceable(out_dir):
        return
    results = earlier_results(out_dir) if out_dir.is_dir() else None
    if results is not None and (out_dir / "checkpoints").is_dir():
        try:
            restart = f"--restart {find_checkpoint(out_dir)}"
        except InputError:
            restart = None
        if restart is not None:
            raise InputError(f"out: {out_dir} holds the results of an earlier run ({results}); "
                             f"continue it with {restart}, or give --overwrite to replace them")
    raise InputError(f"out: {out_dir} exists and is not empty ({hint})")


def _check_restart_case(state: dict, case: Case, checkpoint, allow_changed_case: bool) -> bool:
    """Whether the case differs from the one that wrote ``checkpoint``; an InputError
    unless ``allow_changed_case``."""
    changed = state.get("case_sha256") != case_hash(case)
    if changed and not allow_changed_case:
        raise InputError(f"restart: the case differs from the one that wrote {checkpoint} "
                         f"(give --allow-changed-case to continue with the changed case)")
    return changed


class _RunRecord:
    """run.json of a run: written at the start (status 'running') and at the end."""

    def __init__(self, path: Path, info: dict):
        self.path = path
        self.info = info
        self.written = False

    def write(self, **fields):
        self.info.update(fields)
        _write_text(self.path, json.dumps(self.info, indent=2, default=str) + "\n")
        self.written = True

    def finish(self, status: str, sim, message: str, checkpoint=None, **fields):
        # the energy monitor owns the alarm record (checkpointed with the state, restored
        # on a restart): run.json reports it, as of the step the run ended at
        monitor = sim.monitor
        alarm = None
        if monitor.first_alarm is not None:
            a_step, a_time, a_err = monitor.first_alarm
            alarm = {"step": int(a_step), "time": float(a_time), "energy_error": float(a_err)}
        self.info["first_energy_alarm"] = alarm
        self.info["energy_alarms"] = int(monitor.n_alarms)
        self.write(status=status, finished=wallclock.strftime("%Y-%m-%dT%H:%M:%S%z"),
                   step=sim.step, time=sim.time, message=message,
                   checkpoint=None if checkpoint is None else str(checkpoint),
                   max_energy_error=sim.monitor.max_error, **fields)


def run_case(case: Case, out_dir, quiet: bool = False, log_level: str = "INFO",
             restart=None, max_steps: int | None = None, overwrite: bool = False,
             chunk_steps: int | None = None,
             on_chunk: Callable | None = None, allow_changed_case: bool = False,
             exit_on_abort: bool = False) -> RunResult:
    """Run every stage of ``case`` writing into ``out_dir``.

    ``restart``: a checkpoint (or a folder: its newest checkpoint) to continue from;
    the case must be the one that wrote it unless ``allow_changed_case``.
    ``max_steps``: at most this many steps per stage (previews, smoke tests).
    ``overwrite``: allow a non-empty ``out_dir`` without ``restart`` (the outputs of
    an earlier run there, :data:`OUTPUTS`, are removed first). A folder whose run
    stopped before its first step needs no ``overwrite``. An input file of the case
    (the case file, its particle, clump or bond files) among the outputs is refused
    in any case: the run would replace or delete it.
    ``chunk_steps``: steps between returns to Python, where outputs, progress and
    signals are handled (default :func:`default_chunk_steps`); chunks end at multiples
    of it. A restart reproduces the uninterrupted run bit for bit when both use the
    same value (the default does).
    ``on_chunk(sim)``: called after every chunk.
    ``exit_on_abort``: a second SIGINT/SIGTERM (or the first before any chunk is done)
    ends the process at once after recording run.json, and after a run stopped by a
    signal, SIGINT and SIGTERM stay ignored while the process exits (the command line;
    see :class:`StopRequest`).

    The folder is locked (:class:`demstep.io.lock.FolderLock`) while the run writes:
    a second run into it fails with an InputError. Raises InputError (before creating
    anything) for bad input. Returns a RunResult: interruptions (SIGINT/SIGTERM),
    divergence and an energy monitor set to 'stop' end the run with a checkpoint and
    a status, not an exception. An unexpected exception is recorded in run.json
    (status 'failed') and raised."""
    level = str(log_level).upper()
    if level not in LOG_LEVELS:
        raise InputError(f"log-level: must be one of {', '.join(LOG_LEVELS)}, got {log_level!r}")
    if max_steps is not None and (not isinstance(max_steps, int) or max_steps < 0):
        raise InputError(f"max-steps: must be an integer >= 0, got {max_steps!r}")
    if chunk_steps is not None and (not isinstance(chunk_steps, int) or chunk_steps < 1):
        raise InputError(f"chunk_steps: must be an integer >= 1, got {chunk_steps!r}")
    check_folder_creatable(out_dir, "out")
    out_dir = Path(out_dir)
    if restart is None:
        check_out_empty(out_dir, overwrite, replaceable=_replaceable)
    _check_inputs_kept(case, out_dir, restart)
    # everything that can fail on input happens before the folder is created: the
    # case's particles, walls, parameters and initial state (demstep.case), the restart
    check_stages(case)
    sim = build_simulation(case, checkpoint_dir=out_dir / "checkpoints")
    pos = None
    restart_info = None
    checkpoint = None
    if restart is not None:
        checkpoint = find_checkpoint(restart)
        pos, state = read_state(checkpoint, stages=len(case.stages))
        case_changed = _check_restart_case(state, case, checkpoint, allow_changed_case)
        # replay the changes of every stage already started, then restore the state
        started = pos.stage + 1 if pos.stage_step > 0 else pos.stage
        for k in range(min(started, len(case.stages))):
            apply_stage(sim, case, k, fresh=False)
        try:
            load_checkpoint(sim, checkpoint)
        except InputError as exc:
            raise InputError(f"restart: {exc}") from None
        except (KeyError, ValueError, IndexError) as exc:
            raise InputError(f"restart: {checkpoint}: not a checkpoint of this demstep "
                             f"({type(exc).__name__}: {exc})") from None
        restart_info = {"checkpoint": str(checkpoint), "step": sim.step, "time": sim.time,
                        "case_changed": case_changed}

    stop = StopRequest(exit_now=exit_on_abort)
    stop.install()
    lock = None
    try:
        make_folder(out_dir, "out")
        lock = FolderLock(out_dir, "out").acquire()
        # under the lock: another process may have written here since the check above
        if restart is None:
            check_out_empty(out_dir, overwrite, replaceable=_replaceable)
        remove_orphans(out_dir, *(out_dir / name for name in ("checkpoints", "vtk", "plots")))
        notes = [remove_outputs(out_dir)] if restart is None else []
        return _run_locked(case, sim, out_dir, pos, restart_info, checkpoint, level, quiet,
                           max_steps, chunk_steps, on_chunk, stop, __version__, notes)
    finally:
        stop.restore()
        if lock is not None:
            lock.release()


def _run_locked(case, sim, out_dir, pos, restart_info, checkpoint, level, quiet, max_steps,
                chunk_steps, on_chunk, stop, version, notes) -> RunResult:
    """The part of :func:`run_case` that writes (the folder is locked); ``notes``:
    warnings to log once the log is open."""
    run_json = out_dir / "run.json"
    info = {}
    if restart_info is not None and run_json.is_file():
        try:
            info = json.loads(run_json.read_text(encoding="utf-8"))
        except ValueError:
            info = {}
        if not isinstance(info, dict):
            info = {}
        if info.get("status") == "running":  # we hold the lock: that process is gone
            restart_info["previous_status"] = "running (the process was killed)"
    info.update(_version_info())
    info.update({"case": case.source, "case_sha256": case_hash(case), "status": "running",
                 "started": wallclock.strftime("%Y-%m-%dT%H:%M:%S%z"), "max_steps": max_steps,
                 "pid": os.getpid(), "host": platform.node(),
                 "results": restart_info is not None})
    if restart_info:
        info.setdefault("restarts", []).append(restart_info)
    record = _RunRecord(run_json, info)
    previous_level = log.level
    handlers = []
    progress = _NoProgress()
    runner = None

    def on_abort(name: str, started: bool):
        """Record an abort from the signal handler (the process exits after it)."""
        if started:
            status = "aborted"
            message = (f"aborted by a second {name} at step {sim.step} without a checkpoint"
                       + (f"; restart from {runner.last_checkpoint}"
                          if runner is not None and runner.last_checkpoint else ""))
        else:
            status = "interrupted"
            message = (f"stopped by {name} before the first step was done (while "
                       f"compiling or starting)"
                       + (f"; restart again from {checkpoint}" if checkpoint is not None
                          else "; nothing to keep: run the same command again (no "
                               "--overwrite needed)"))
        try:
            record.finish(status, sim, message,
                          runner.last_checkpoint if runner is not None else checkpoint,
                          signal=name)
            log.error("%s", message)
            for h in handlers:
                h.flush()
            console = getattr(progress, "console", None)
            if console is not None and console.is_terminal:
                sys.stderr.write("\x1b[?25h\n")  # rich hid the cursor
            print(f"demstep run: {status}: {message}", file=sys.stderr, flush=True)
        except Exception:  # the process exits in any case
            pass

    stop.on_abort = on_abort
    manifest = OutputManifest(out_dir)
    manifest.record(run_json, out_dir / "case.toml", out_dir / "run.log")
    record.write()  # first, so that an abort from now on is recorded
    case_text = f"# resolved case written by demstep {version}\n" + dump_case(case)
    _write_text(out_dir / "case.toml", case_text)
    notes = [*notes, _own_log(out_dir / "run.log")]
    log.setLevel(level)
    try:
        progress = _NoProgress() if quiet else _RichProgress()
        handlers = _setup_logging(out_dir, level, getattr(progress, "console", None))
        for note in notes:
            if note:
                log.warning("%s", note)
        runner = _Runner(case, sim, out_dir, pos, max_steps, quiet, on_chunk, chunk_steps,
                         stop, progress, manifest)
        if checkpoint is not None:
            runner.last_checkpoint = Path(checkpoint)
        log.info("demstep %s: case '%s', %d %dD particles, %d walls, %d stage(s)%s",
                 version, case.name, len(sim.r), sim.dim, len(sim.walls), len(case.stages),
                 f", restarted at step {sim.step}" if restart_info else "")
        if restart_info and restart_info["case_changed"]:
            log.warning("restart: the case differs from the one that wrote %s "
                        "(--allow-changed-case)", restart_info["checkpoint"])
        if pos is not None and pos.stage == len(case.stages):
            result = RunResult("completed", out_dir, sim.step, sim.time,
                               Path(restart_info["checkpoint"]),
                               "nothing to run: the checkpoint is at the end of the last stage")
        else:
            result = runner.run()
        stop.finished = True
        if result.status not in FAILED:  # (a failure was logged as an error already)
            log.info("%s", result.message)
    except BaseException as exc:
        stop.finished = True
        status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        text = " ".join(str(exc).split()) or type(exc).__name__
        message = f"{type(exc).__name__}: {text}" if status == "failed" else "interrupted"
        log.error("run %s: %s", status, message)
        record.finish(status, sim, message,
                      runner.last_checkpoint if runner is not None else checkpoint,
                      results=_has_results(record, stop, status))
        raise
    finally:
        stop.on_abort = None
        progress.stop()
        for h in handlers:
            log.removeHandler(h)
            h.close()
        log.setLevel(previous_level)
    record.finish(result.status, sim, result.message, result.checkpoint,
                  signal=result.signal, results=_has_results(record, stop, result.status))
    return result


def _has_results(record: _RunRecord, stop: StopRequest, status: str) -> bool:
    """Whether the folder holds results worth keeping: an earlier run's (a restart), a
    chunk of steps done, or a finished run (even of zero steps)."""
    return bool(record.info.get("results")) or stop.started or status in (
        "completed", "diverged", "energy_stop")
