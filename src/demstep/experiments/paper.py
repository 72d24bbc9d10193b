"""`demstep paper`: the paper's validation end to end, and one step further.

1. The critical-step table of Figures 8 and 9 (element estimates beside exact values).
2. The FCC plane-strain alpha study of Figures 11 and 12 (alpha = 0.05, 0.35, 0.40,
   0.45, 0.75), with the exact critical step of the specimen with and without rotation,
   and two supplementary runs with rotation blocked.
3. The measured stability threshold of every regular lattice and of the FCC specimen
   against every estimate.
4. Damping and the critical step: the FCC specimen with contact dashpots of
   restitution 0.9, 0.5 and 0.2 (normal and tangential), its damped and undamped exact
   steps, the measured thresholds, and where the 20 % Rayleigh-time rule falls.
5. Clumps (the paper's closing warning): the critical alpha of clump packings of 2, 3,
   4 and 8 members against their coordination, measured and exact, beside the rules.
6. report.md and report.html with PNG figures, CSV data beside them, the resolved
   parameters and the package version.

Runs are independent tasks mapped on Dask (:func:`demstep.sweep.dask_map`), so both
cores work; stage 1 of the FCC test is shared through a checkpoint.
"""

from __future__ import annotations

import csv
import json
import logging
import platform
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from demstep import __version__, plotting
from demstep.errors import InputError
from demstep.experiments.clump_stability import clump_study
from demstep.experiments.fcc_plane_strain import FCCConfig, build_fcc, run_stage2
from demstep.experiments.report import write_report
from demstep.experiments.stability import DAMPING_STEPS, damping_study, stability_threshold
from demstep.io.atomic import remove_orphans, write_text_atomic
from demstep.io.checkpoint import load_checkpoint, save_checkpoint
from demstep.io.lock import FolderLock, check_folder_creatable, make_folder
from demstep.io.manifest import OutputManifest
from demstep.runner import check_out_empty, remove_outputs
from demstep.sweep import WORKER_TIMEOUT, dask_client
from demstep.timestep.paper_table import paper_table, table_json

ALPHAS = (0.05, 0.35, 0.40, 0.45, 0.75)
#: supplementary runs with particle rotation blocked (translation-only model)
ALPHAS_NO_ROTATION = (0.35, 0.45)


@dataclass
class PaperSettings:
    """Resolved parameters of `demstep paper` (recorded in the report)."""

    quick: bool = False
    strain: float = 0.02
    alphas: tuple = ALPHAS
    alphas_no_rotation: tuple = ALPHAS_NO_ROTATION
    stability_rtol: float = 2e-3
    stability_steps: int = 3000
    #: trial runs of the damping study, quick or not: heavily damped critical modes grow
    #: slowly (5000 steps left restitution 0.2's exact step below the 1 % bracket)
    damping_steps: int = DAMPING_STEPS
    stability_names: tuple = ("square", "hex", "sc", "bcc", "fcc", "rhombic", "fcc-specimen")
    damping_restitutions: tuple = (1.0, 0.9, 0.5, 0.2)
    clump_cases: tuple = (("dimer", 1.0), ("trimer", 0.75), ("square", 1.0), ("cube8", 0.75))
    workers: int = 2
    scheduler: str | None = None
    fcc: dict = field(default_factory=dict)

    @classmethod
    def make(cls, quick: bool = False, **kw) -> "PaperSettings":
        s = cls(quick=quick, **kw)
        if quick:
            s.strain = 0.004
            s.stability_rtol = 1e-2
            s.stability_steps = 2000
        s.fcc = asdict(FCCConfig(strain=s.strain))
        return s


# ---------------------------------------------------------------- tasks (picklable)

def fcc_task(item):
    """One stage-2 run from the shared stage-1 checkpoint. item = (config dict, path)."""
    cfg_dict, stage1_path = item
    _quiet_logs()
    cfg = FCCConfig(**cfg_dict)
    sim = build_fcc(cfg)
    load_checkpoint(sim, stage1_path)
    if not cfg.rotation:
        sim.w[:] = 0.0
    start = time.perf_counter()
    result = run_stage2(sim, cfg)
    out = asdict(result)
    out["curves"] = {k: np.asarray(v).tolist() for k, v in result.curves.items()}
    out["wall_time"] = time.perf_counter() - start
    return out


def stability_task(item):
    """Bisection for one specimen. item = (name, rtol, steps)."""
    name, rtol, steps = item
    _quiet_logs()
    start = time.perf_counter()
    result = stability_threshold(name, rtol=rtol, steps=steps)
    out = result.to_json()
    out["bracket"] = list(result.bracket)
    out["trials"] = result.trials
    out["wall_time"] = time.perf_counter() - start
    return out


def damping_task(item):
    """The damping study at one restitution. item = (restitution, rtol, steps)."""
    restitution, rtol, steps = item
    _quiet_logs()
    start = time.perf_counter()
    out = damping_study(restitution, rtol=rtol, steps=steps)
    out["wall_time"] = time.perf_counter() - start
    return out


def clump_task(item):
    """The clump study of one shape, rotation free and locked. item = (shape, spacing,
    rtol, steps)."""
    shape, spacing, rtol, steps = item
    _quiet_logs()
    start = time.perf_counter()
    rows = [clump_study(shape, spacing, rotation, rtol=rtol, steps=steps)
            for rotation in (True, False)]
    for row in rows:
        row["wall_time"] = time.perf_counter() - start
    return rows


def _quiet_logs():
    """The energy monitor's warnings are recorded in the results; keep the console clean."""
    logging.getLogger("demstep").setLevel(logging.ERROR)


def _map(func, items, settings, progress, label):
    """Map on Dask when available, in order; failures come back as exceptions."""
    try:
        from demstep.sweep import dask_map
    except ImportError:  # pragma: no cover - the sweep module ships with the package
        dask_map = None
    if dask_map is None or settings.workers <= 1 and settings.scheduler is None:
        results = []
        for item in items:
            try:
                results.append(func(item))
            except Exception as exc:  # recorded, the study goes on
                results.append(exc)
            if progress:
                progress(label)
        return results

    def waiting(pending, seconds):  # a cluster without workers: say so, give up in time
        print(f"demstep paper: waiting for workers: {pending} task(s) of {label} pending, no "
              f"worker connected for {seconds:.0f} s (giving up after {WORKER_TIMEOUT:g} s)",
              file=sys.stderr, flush=True)

    raw = dask_map(func, items, scheduler=settings.scheduler, workers=settings.workers,
                   progress=(lambda *a: progress(label)) if progress else None,
                   worker_timeout=WORKER_TIMEOUT, on_wait=waiting)
    return [_unwrap(r) for r in raw]


def _unwrap(r):
    """dask_map returns results or failure records; turn failures into exceptions."""
    failed = getattr(r, "failed", None)
    if failed is None and isinstance(r, dict) and "failed" in r and "error" in r:
        failed = r["failed"]
    if failed:
        err = getattr(r, "error", None) or (r.get("error") if isinstance(r, dict) else None)
        return RuntimeError(str(err))
    return getattr(r, "value", r) if not isinstance(r, dict) or "failed" not in r else r.get("value")


# ------------------------------------------------------------------------ driver

#: what `demstep paper` writes into its folder (``overwrite`` removes what the folder's
#: manifest lists, :mod:`demstep.io.manifest`; nothing else there is touched)
OUTPUTS = ("data", "summary.json", "report.md", "report.html", "critical_steps.png",
           "fcc_stress_ratio.png", "fcc_energy_error.png", "stability.png", "damping.png",
           "clumps.png")
#: what to do about a folder that is not empty (``paper`` has no restart)
NOT_EMPTY_HINT = "choose a new or empty folder, or give --overwrite to replace the results there"


def run_paper(out_dir, quick: bool = False, workers: int = 2, scheduler: str | None = None,
              show_progress: bool = True, overwrite: bool = False) -> dict:
    """Run the whole validation into ``out_dir``; returns the summary dictionary.

    ``out_dir`` follows the rule of ``demstep run --out``
    (:func:`demstep.runner.check_out_empty`): it must be new or empty unless
    ``overwrite`` (then the results of an earlier paper run there, :data:`OUTPUTS`, are
    removed first), and is locked while the study writes into it (a second process
    gets an InputError). Everything is checked before the folder is created."""
    check_folder_creatable(out_dir, "out")
    out = Path(out_dir)
    check_out_empty(out, overwrite, NOT_EMPTY_HINT)
    if workers < 1:
        raise InputError(f"--workers: must be >= 1, got {workers}")
    settings = PaperSettings.make(quick=quick, workers=workers, scheduler=scheduler)
    if scheduler:  # unreachable: say so before anything is written

        with dask_client(scheduler, workers):
            pass
    make_folder(out, "out")
    lock = FolderLock(out, "out").acquire()
    try:
        # under the lock: another process may have written here since the check above
        check_out_empty(out, overwrite, NOT_EMPTY_HINT)
        remove_orphans(out, out / "data")
        if overwrite:
            kept = remove_outputs(out, OUTPUTS)
            if kept:
                print(f"demstep paper: {kept}", file=sys.stderr)
        manifest = OutputManifest(out)
        manifest.record(*(out / name for name in OUTPUTS if name != "data"))
        before = set((out / "data").rglob("*")) if (out / "data").is_dir() else set()
        try:
            return _run_paper_locked(out, settings, show_progress)
        finally:  # the data files this run wrote (their names depend on the settings)
            if (out / "data").is_dir():
                manifest.record(*sorted(p for p in (out / "data").rglob("*")
                                        if p.is_file() and p not in before))
    finally:
        lock.release()


def _run_paper_locked(out: Path, settings: PaperSettings, show_progress: bool) -> dict:
    """The part of :func:`run_paper` that computes and writes (the folder is locked)."""
    from demstep.experiments.fcc_plane_strain import run_stage1, thornton_peak_ratio

    (out / "data").mkdir(exist_ok=True)
    started = time.perf_counter()
    n_tasks = (4 + len(settings.alphas) + len(settings.alphas_no_rotation)
               + len(settings.stability_names) + len(settings.damping_restitutions)
               + len(settings.clump_cases))
    progress, finish = _progress(show_progress, n_tasks)

    # 1. Figures 8 and 9
    rows = paper_table()
    table = table_json(rows)
    _write_json(out / "data" / "critical_steps.json", table)
    _write_table_csv(out / "data" / "critical_steps.csv", table)
    progress("critical-step table")

    # 2. the FCC alpha study
    base = FCCConfig(**settings.fcc)
    stage1 = run_stage1(base)
    stage1_path = out / "data" / "fcc_stage1.npz"
    save_checkpoint(stage1, stage1_path)
    progress("FCC stage 1 (isotropic confinement)")
    items = [(asdict(FCCConfig(**{**settings.fcc, "alpha": a})), str(stage1_path))
             for a in settings.alphas]
    items += [(asdict(FCCConfig(**{**settings.fcc, "alpha": a, "rotation": False})), str(stage1_path))
              for a in settings.alphas_no_rotation]
    fcc_results = _map(fcc_task, items, settings, progress, "FCC plane strain")
    fcc_summary = []
    for item, res in zip(items, fcc_results):
        cfg = item[0]
        if isinstance(res, Exception):
            fcc_summary.append({"alpha": cfg["alpha"], "rotation": cfg["rotation"],
                                "status": "failed", "message": str(res)})
            continue
        tag = f"alpha_{cfg['alpha']:.2f}" + ("" if cfg["rotation"] else "_norotation")
        _write_curves(out / "data" / f"fcc_{tag}.csv", res["curves"])
        fcc_summary.append({"alpha": cfg["alpha"], "rotation": cfg["rotation"],
                            "peak_ratio": res["peak_ratio"], "peak_strain": res["peak_strain"],
                            "theory": res["theory"], "max_energy_error": res["max_energy_error"],
                            "status": res["status"], "steps": res["steps"], "dt": res["dt"],
                            "alpha_exact_rotation": res["alpha_exact_rotation"],
                            "alpha_exact_translation": res["alpha_exact_translation"],
                            "alpha_element_coupled": res["alpha_element_coupled"],
                            "wall_time": res["wall_time"], "message": res["message"],
                            "curves": res["curves"]})
    # 3. stability thresholds
    st_items = [(name, settings.stability_rtol, settings.stability_steps)
                for name in settings.stability_names]
    st_results = _map(stability_task, st_items, settings, progress, "stability threshold")
    stability = []
    for (name, _, _), res in zip(st_items, st_results):
        if isinstance(res, Exception):
            stability.append({"lattice": name, "status": "failed", "message": str(res)})
        else:
            stability.append(res)
    _write_json(out / "data" / "stability.json", stability)
    # 4. damping and the critical step
    dp_items = [(e, settings.stability_rtol, settings.damping_steps)
                for e in settings.damping_restitutions]
    dp_results = _map(damping_task, dp_items, settings, progress, "damping study")
    damping = [{"restitution": e, "status": "failed", "message": str(res)}
               if isinstance(res, Exception) else res
               for (e, _, _), res in zip(dp_items, dp_results)]
    _write_json(out / "data" / "damping.json", damping)
    # 5. clumps
    cl_items = [(shape, spacing, settings.stability_rtol, settings.stability_steps)
                for shape, spacing in settings.clump_cases]
    cl_results = _map(clump_task, cl_items, settings, progress, "clump study")
    clumps = []
    for (shape, spacing, _, _), res in zip(cl_items, cl_results):
        if isinstance(res, Exception):
            clumps.append({"shape": shape, "spacing": spacing, "status": "failed",
                           "message": str(res)})
        else:
            clumps.extend(res)
    _write_json(out / "data" / "clumps.json", clumps)

    # 4. figures and report

    figures = {
        "critical_steps": plotting.plot_critical_step_table(table, out / "critical_steps.png"),
        "stress_ratio": plotting.plot_fcc_ratio(fcc_summary, thornton_peak_ratio(base.mu),
                                                out / "fcc_stress_ratio.png"),
        "energy_error": plotting.plot_fcc_energy(fcc_summary, base.energy_eps,
                                                 out / "fcc_energy_error.png"),
        "stability": plotting.plot_stability(stability, out / "stability.png"),
        "damping": plotting.plot_damping(damping, out / "damping.png"),
        "clumps": plotting.plot_clumps(clumps, stability, out / "clumps.png"),
    }
    progress("figures")
    summary = {
        "version": __version__, "python": platform.python_version(),
        "machine": platform.machine(), "wall_time_s": None,
        "settings": asdict(settings),
        "fcc": [{k: v for k, v in r.items() if k != "curves"} for r in fcc_summary],
        "stability": stability,
        "damping": damping,
        "clumps": clumps,
        "critical_step_minima": table["minima"],
    }
    summary["wall_time_s"] = time.perf_counter() - started
    _write_json(out / "summary.json", summary)

    write_report(out, summary, table, figures)
    progress("report")
    finish()
    return summary


# ------------------------------------------------------------------------ output

def _progress(show: bool, total: int):
    if not show:
        return (lambda label: None), (lambda: None)
    from rich.progress import (BarColumn,  # (deferred: a heavy import, loaded only when used)
                               Progress, TextColumn, TimeElapsedColumn)

    bar = Progress(TextColumn("[bold]demstep paper[/bold] {task.description}"), BarColumn(),
                   TextColumn("{task.completed}/{task.total}"), TimeElapsedColumn(), transient=False)
    bar.start()
    task = bar.add_task("starting", total=total)

    def step(label):
        bar.update(task, advance=1, description=label)

    return step, bar.stop


def _write_json(path: Path, data):
    write_text_atomic(path, json.dumps(data, indent=2, default=_json_default))


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, tuple):
        return list(o)
    raise TypeError(type(o))


def _write_curves(path: Path, curves: dict):
    keys = list(curves)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(keys)
        for row in zip(*(curves[k] for k in keys)):
            w.writerow([repr(float(v)) for v in row])


def _write_table_csv(path: Path, table: dict):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["lattice", "dim", "coordination"] + table["columns"])
        for r in table["rows"]:
            w.writerow([r["lattice"], r["dim"], r["coordination"]]
                       + ["" if r["alpha"][c] is None else r["alpha"][c] for c in table["columns"]])
