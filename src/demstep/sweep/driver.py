"""The sweep driver: plan, lock, run on Dask, summarize (see :mod:`demstep.sweep`)."""

from __future__ import annotations

import json
import logging
import math
import time as wallclock
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

from demstep import __version__
from demstep.errors import InputError
from demstep.io.atomic import remove_orphans
from demstep.io.lock import FolderLock, check_folder_creatable, folder_is_empty, make_folder
from demstep.runner import _write_text
from demstep.sweep.cluster import (WORKER_TIMEOUT, TaskResult, check_scheduler_address, dask_client,
                                   map_on_client, one_line)
from demstep.sweep.plan import SweepPlan, key_text, plan_sweep
from demstep.sweep.summary import (RunTask, is_finished, plot_summary, run_task, summarize_run,
                                   write_summary)

log = logging.getLogger("demstep")



# ====================================================================== driver
@dataclass
class SweepResult:
    """What a sweep did: the plan, one summary row per run, the ids skipped (finished
    before) and the files written."""

    plan: SweepPlan
    rows: list[dict]
    skipped: list[str] = field(default_factory=list)
    summary_csv: Path | None = None
    summary_png: Path | None = None

    def count(self, status: str) -> int:
        return sum(1 for r in self.rows if r.get("status") == status)


def _check_out(out: Path) -> None:
    check_folder_creatable(out, "out")
    if out.is_dir() and not folder_is_empty(out) and not (out / "sweep.json").is_file():
        raise InputError(f"out: {out} exists, is not empty and holds no sweep (sweep.json)")


def _lock_out(out: Path):
    """Create ``out`` and lock it for this sweep (InputError when another process
    holds it); temporary files of interrupted writes are removed."""
    make_folder(out, "out")
    lock = FolderLock(out, "out").acquire()
    remove_orphans(out)
    return lock


def mark_unfinished(run_dir: Path, message: str) -> None:
    """A run given up for want of workers: if its folder says 'running' and no
    process holds it, record status 'unfinished' in its run.json."""
    path = run_dir / "run.json"
    if not path.is_file():
        return
    try:
        lock = FolderLock(run_dir, "run").acquire()
    except InputError:  # a worker still runs it
        return
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
        if isinstance(info, dict) and info.get("status") == "running":
            info.update({"status": "unfinished", "message": message})
            _write_text(path, json.dumps(info, indent=2, default=str) + "\n")
    except (OSError, ValueError):
        pass
    finally:
        lock.release()


def run_sweep(case_path, out, params: Sequence[str] = (), runs_file=None,
              scheduler: str | None = None, workers: int = 2, max_steps: int | None = None,
              peak: str | None = None, log_level: str = "INFO",
              progress: Callable | None = None,
              worker_timeout: float | None = WORKER_TIMEOUT,
              on_wait: Callable | None = None) -> SweepResult:
    """Run a sweep of ``case_path`` into ``out`` (see the module docstring).

    Everything is validated (parameters, runs file, every run's case, the output
    folder, the scheduler connection) before anything is written. The output folder is
    locked while the sweep runs (a second sweep into it is an InputError), and each
    run's folder while the run writes. Runs already finished in ``out`` are skipped.
    ``progress(done, total, run_id, row, skipped)`` is called as each run finishes
    (first for each skipped run). While the cluster has no worker,
    ``on_wait(pending, seconds)`` reports it; after ``worker_timeout`` seconds [s]
    without a worker (None: no limit) the runs not done are marked 'unfinished'
    (summary.csv, and run.json of a run a lost worker had started) and the sweep
    returns. Returns a :class:`SweepResult`."""
    from demstep.runner import LOG_LEVELS

    check_folder_creatable(out, "out")  # (an empty name first: it would resolve to here)
    out = Path(out).resolve()
    if worker_timeout is not None and not (isinstance(worker_timeout, (int, float))
                                           and not isinstance(worker_timeout, bool)
                                           and 0 < worker_timeout < math.inf):
        raise InputError(f"worker-timeout: must be a finite number of seconds > 0, got "
                         f"{worker_timeout!r}")
    if max_steps is not None and (not isinstance(max_steps, int) or max_steps < 0):
        raise InputError(f"max-steps: must be an integer >= 0, got {max_steps!r}")
    if str(log_level).upper() not in LOG_LEVELS:
        raise InputError(f"log-level: must be one of {', '.join(LOG_LEVELS)}, got {log_level!r}")
    if scheduler:
        check_scheduler_address(scheduler)
    plan = plan_sweep(case_path, params, runs_file, peak)
    _check_out(out)
    base_dir = str(plan.case_path.resolve().parent)
    rows: list[dict | None] = [None] * len(plan.runs)
    skipped: list[str] = []
    todo: list[int] = []
    for k, run in enumerate(plan.runs):
        run_dir = out / "runs" / run.run_id
        if is_finished(run_dir, run.case_sha256, max_steps):
            rows[k] = summarize_run(run_dir, peak)
            skipped.append(run.run_id)
        else:
            todo.append(k)

    def write_meta():
        meta = {"demstep_version": __version__, "case": str(plan.case_path.resolve()),
                "case_name": plan.case_name, "keys": plan.key_names,
                "runs": [{"run_id": r.run_id,
                          "overrides": {key_text(k): v for k, v in r.overrides.items()}}
                         for r in plan.runs],
                "max_steps": max_steps, "peak": peak, "scheduler": scheduler,
                "workers": None if scheduler else workers,
                "started": wallclock.strftime("%Y-%m-%dT%H:%M:%S%z")}
        _write_text(out / "sweep.json", json.dumps(meta, indent=2, default=str) + "\n")
        _write_text(out / "case.toml", plan.case_text)

    summary_csv = out / "summary.csv"
    count = {"done": 0}

    def report(k: int, skipped_run: bool):
        count["done"] += 1
        if progress is not None:
            progress(count["done"], len(plan.runs), plan.runs[k].run_id, rows[k], skipped_run)

    lock = None
    try:
        if todo:
            tasks = [RunTask(run_id=plan.runs[k].run_id,
                             overrides=[(key_text(key), v)
                                        for key, v in plan.runs[k].overrides.items()],
                             data=plan.runs[k].data, base_dir=base_dir,
                             source=str(plan.case_path),
                             run_dir=str(out / "runs" / plan.runs[k].run_id),
                             max_steps=max_steps, peak=peak, log_level=str(log_level).upper())
                     for k in todo]
            with dask_client(scheduler, workers) as client:  # connection errors: nothing written
                lock = _lock_out(out)
                write_meta()
                for k in range(len(plan.runs)):
                    if rows[k] is not None:
                        report(k, True)
                write_summary(summary_csv, plan, rows)

                def done(i, result: TaskResult):
                    k = todo[i]
                    if result.unfinished:
                        rows[k] = {"status": "unfinished", "peak_column": peak or "",
                                   "error": result.error}
                        mark_unfinished(Path(tasks[i].run_dir), result.error)
                    else:
                        rows[k] = result.value if result.ok else {
                            "status": "failed", "peak_column": peak or "", "error": result.error}
                    write_summary(summary_csv, plan, rows)
                    report(k, False)

                map_on_client(client, run_task, tasks, progress=done,
                              worker_timeout=worker_timeout, on_wait=on_wait)
        else:
            lock = _lock_out(out)
            write_meta()
            for k in range(len(plan.runs)):
                report(k, True)
        final = [r if r is not None else {"status": "failed", "error": "no result"} for r in rows]
        write_summary(summary_csv, plan, final)
        png = None
        try:
            with warnings.catch_warnings():  # matplotlib on runs without data
                warnings.simplefilter("ignore", UserWarning)
                png = plot_summary(out / "summary.png", plan, final)
        except Exception as exc:  # a figure must not lose the sweep's results
            log.warning("sweep: summary.png not drawn (%s)", one_line(exc))
    finally:
        if lock is not None:
            lock.release()
    return SweepResult(plan, final, skipped, summary_csv, png)
