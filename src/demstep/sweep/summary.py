"""One run of a sweep on a worker, and the summary of the runs: summary.csv and
summary.png (see :mod:`demstep.sweep`)."""

from __future__ import annotations

import contextlib
import copy
import csv
import io
import json
import logging
import math
import os
import platform
import sys
import threading
import time as wallclock
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from demstep.case import case_from_dict
from demstep.errors import InputError
from demstep.io.history import read_history
from demstep.plotting import _pyplot, save_figure
from demstep.runner import _write_text, run_case
from demstep.sweep.cluster import numba_one_thread, one_line
from demstep.sweep.plan import SweepPlan, key_text, value_text

#: run statuses that count as finished (a resumed sweep does not run them again)
FINISHED = ("completed", "diverged", "energy_stop")
#: summary.csv columns before and after the swept keys
SUMMARY_LEAD = ("run_id",)
SUMMARY_TAIL = ("status", "max_energy_error", "peak_column", "peak", "final_step",
                "final_time", "wall_time_s", "error")

log = logging.getLogger("demstep")



# ============================================================ one run (worker)
@dataclass
class RunTask:
    """What a worker needs to run one case of a sweep (pickled to the worker)."""

    run_id: str
    overrides: list  # [(key text, value)]
    data: dict
    base_dir: str
    source: str
    run_dir: str
    max_steps: int | None = None
    peak: str | None = None
    log_level: str = "INFO"


def run_task(task: RunTask) -> dict:
    """Run one case of a sweep into ``task.run_dir`` (on a worker) and return its
    summary row. Any exception is recorded (status 'failed', in ``run.json`` too),
    never raised. The runner's console log is silenced; ``run.log`` keeps it."""
    numba_one_thread()
    run_dir = Path(task.run_dir)
    start = wallclock.perf_counter()
    status, error, trace = "failed", "", ""
    try:
        case = case_from_dict(copy.deepcopy(task.data), base_dir=task.base_dir,
                              source=task.source)
        with _quiet_stderr():
            result = run_case(case, run_dir, quiet=True, log_level=task.log_level,
                              max_steps=task.max_steps, overwrite=True)
        status = result.status
        if status != "completed":
            error = " ".join(result.message.split())
    except Exception as exc:
        error, trace = one_line(exc), traceback.format_exc()
    wall = wallclock.perf_counter() - start
    _record_run(run_dir, task, status, wall, error, trace)
    return summarize_run(run_dir, task.peak, status=status, error=error, wall_time=wall)


class _ThreadQuietStream:
    """A stand-in for ``sys.stderr`` that drops what the threads marked quiet write and
    passes everything else on (worker threads may run tasks side by side)."""

    def __init__(self, stream):
        self._stream = stream
        self._local = threading.local()

    def write(self, text):
        if getattr(self._local, "quiet", False):
            return len(text)
        return self._stream.write(text)

    def __getattr__(self, name):
        return getattr(self._stream, name)


@contextlib.contextmanager
def _quiet_stderr():
    """Silence this thread's writes to sys.stderr (the runner's console log: each run
    keeps its run.log) without touching the worker's other threads."""
    if not isinstance(sys.stderr, _ThreadQuietStream):
        sys.stderr = _ThreadQuietStream(sys.stderr)
    stream = sys.stderr
    stream._local.quiet = True
    try:
        yield
    finally:
        stream._local.quiet = False


def _record_run(run_dir: Path, task: RunTask, status: str, wall: float, error: str,
                trace: str) -> None:
    """Add the sweep's record to run.json (creating it for a run that failed early)."""
    path = run_dir / "run.json"
    info: dict = {}
    if path.is_file():
        try:
            info = json.loads(path.read_text(encoding="utf-8"))
        except ValueError:
            info = {}
    if status == "failed":
        info.update({"status": "failed", "message": error, "traceback": trace,
                     "max_steps": task.max_steps})
    info["sweep"] = {"run_id": task.run_id,
                     "overrides": {k: v for k, v in task.overrides},
                     "wall_time_s": wall, "host": platform.node(), "pid": os.getpid()}
    _write_text(path, json.dumps(info, indent=2, default=str) + "\n")


def default_peak_column(columns: Sequence[str]) -> str | None:
    """The top wall's stress (``y+.stress`` in 2D, ``z+.stress`` in 3D), else the first
    wall's stress, else the first Love stress; None when there is none."""
    for name in ("z+.stress", "y+.stress"):
        if name in columns:
            return name
    for c in columns:
        if c.endswith(".stress"):
            return c
    for c in columns:
        if c.startswith("love."):
            return c
    return None


def summarize_run(run_dir, peak: str | None = None, status: str | None = None,
                  error: str | None = None, wall_time: float | None = None) -> dict:
    """The summary of a run folder: status, max energy error of the history, peak of
    ``peak`` (default :func:`default_peak_column`), final step and time, wall time."""
    import numpy as np  # (deferred: a heavy import, loaded only when used)

    run_dir = Path(run_dir)
    info: dict = {}
    try:
        info = json.loads((run_dir / "run.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        pass
    row = {"status": status or info.get("status", "failed"),
           "max_energy_error": math.nan, "peak_column": peak or "", "peak": math.nan,
           "final_step": info.get("step", ""), "final_time": info.get("time", math.nan),
           "wall_time_s": wall_time if wall_time is not None
           else info.get("sweep", {}).get("wall_time_s", math.nan),
           "error": error if error is not None else
           ("" if info.get("status") == "completed" else info.get("message", ""))}
    # the monitor's checks (run.json), and the history's rows: the same definition
    # (EnergyLedger.balance_error with the monitor's floor: NaN below it, never counted)
    value = info.get("max_energy_error")
    monitor = _finite(value)
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
        row["max_energy_error"] = float(value)
    history = run_dir / "history.csv"
    if history.is_file():
        try:
            h = read_history(history)
        except InputError as exc:
            row["error"] = row["error"] or str(exc)
            return row
        column = peak or default_peak_column(list(h))
        row["peak_column"] = column or ""
        if len(h.get("step", ())):
            err = h["energy_error"][np.isfinite(h["energy_error"])]
            if err.size:
                row["max_energy_error"] = max(float(np.max(np.abs(err))), monitor)
            if column in h:
                values = h[column][np.isfinite(h[column])]
                if values.size:
                    row["peak"] = float(values.max())
            if row["final_step"] == "":
                row["final_step"] = int(h["step"][-1])
                row["final_time"] = float(h["time"][-1])
    return row


def _finite(value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return 0.0
    return v if math.isfinite(v) else 0.0


def is_finished(run_dir, case_sha256: str, max_steps: int | None) -> bool:
    """Whether ``run_dir`` holds a finished run (completed, diverged, energy_stop) of
    this case (same resolved-case hash) and ``max_steps``."""
    try:
        info = json.loads((Path(run_dir) / "run.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return (info.get("status") in FINISHED and info.get("case_sha256") == case_sha256
            and info.get("max_steps") == max_steps)


# ===================================================================== summary
def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)
    return str(value)


def write_summary(path, plan: SweepPlan, rows: list[dict | None]) -> Path:
    """summary.csv: run_id, the swept keys, then :data:`SUMMARY_TAIL` (runs not yet
    finished have status 'pending')."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow([*SUMMARY_LEAD, *plan.key_names, *SUMMARY_TAIL])
    for run, row in zip(plan.runs, rows):
        row = row or {"status": "pending"}
        values = [value_text(run.overrides[k]) if k in run.overrides else "" for k in plan.keys]
        writer.writerow([run.run_id, *values, *[_cell(row.get(c)) for c in SUMMARY_TAIL]])
    return _write_text(path, buf.getvalue())


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def plot_summary(path, plan: SweepPlan, rows: list[dict | None]) -> Path:
    """summary.png: max energy error (log scale, the monitor's limit drawn) and the peak
    value against the first swept key, one line per combination of the other keys;
    runs that did not complete are marked with a red x."""
    import numpy as np  # (deferred: a heavy import, loaded only when used)

    plt = _pyplot()
    fig, (ax_err, ax_peak) = plt.subplots(1, 2, figsize=(11, 4.2))
    xkey = plan.keys[0] if plan.keys else None
    xs = [run.overrides.get(xkey) for run in plan.runs]
    numeric = all(_is_number(v) for v in xs)
    if numeric:
        xpos = [float(v) for v in xs]
    else:
        labels = list(dict.fromkeys(value_text(v) if v is not None else "-" for v in xs))
        xpos = [float(labels.index(value_text(v) if v is not None else "-")) for v in xs]
    groups: dict[str, list[int]] = {}
    for k, run in enumerate(plan.runs):
        label = ", ".join(f"{key_text(key)}={value_text(run.overrides[key])}"
                          for key in plan.keys[1:] if key in run.overrides)
        groups.setdefault(label, []).append(k)
    peak_column = next((r.get("peak_column") for r in rows if r and r.get("peak_column")), "")
    for label, members in groups.items():
        members = sorted(members, key=lambda k: xpos[k])
        x = np.array([xpos[k] for k in members])
        err = np.array([_float(rows[k], "max_energy_error") for k in members])
        peak = np.array([_float(rows[k], "peak") for k in members])
        err = np.where(err > 0, err, np.nan)
        bad = [i for i, k in enumerate(members)
               if rows[k] is None or rows[k].get("status") != "completed"]
        if bad:
            label = f"{label} ({len(bad)} not completed)" if label else \
                f"{len(bad)} not completed"
        line, = ax_err.plot(x, err, marker="o", label=label or None)
        ax_peak.plot(x, peak, marker="o", color=line.get_color(), label=label or None)
        if bad:
            ax_err.plot(x[bad], err[bad], "x", color="red", ms=9, mew=2)
            ax_peak.plot(x[bad], peak[bad], "x", color="red", ms=9, mew=2)
    ax_err.set_yscale("log")
    ax_err.axhline(plan.eps, color="r", ls="--", lw=1, label=f"limit {plan.eps:g}")
    ax_err.set_ylabel("max normalized energy error (eq. 22)")
    ax_peak.set_ylabel(f"peak {peak_column}" if peak_column else "peak")
    for ax in (ax_err, ax_peak):
        ax.set_xlabel(key_text(xkey) if xkey else "run")
        if not numeric:
            ax.set_xticks(range(len(labels)), labels, rotation=30, ha="right", fontsize=8)
        ax.grid(True, alpha=0.3)
    handles, _ = ax_err.get_legend_handles_labels()
    if 0 < len(handles) <= 13:
        ax_err.legend(fontsize=7)
    fig.suptitle(f"{plan.case_name}: sweep of {len(plan.runs)} runs (red x: not completed)",
                 fontsize=10)
    return save_figure(fig, path)


def _float(row: dict | None, key: str) -> float:
    if row is None:
        return math.nan
    try:
        return float(row.get(key))
    except (TypeError, ValueError):
        return math.nan


