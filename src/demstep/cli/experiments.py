"""``demstep fcc``, ``demstep stability`` and ``demstep paper``: the paper's studies."""

from __future__ import annotations

import argparse
import json
import sys

from demstep.cli.common import fraction, non_negative, positive, positive_int
from demstep.errors import InputError


# ----------------------------------------------------------------------- fcc

def _finite_or_none(d: dict) -> dict:
    import math

    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}


def add_fcc_parser(sub):
    p = sub.add_parser("fcc", help="the paper's FCC plane-strain compression at one alpha",
                       description="Plane-strain compression of 150 FCC spheres (paper Figs. "
                       "10-12): peak stress ratio against Thornton's theory and the energy "
                       "balance.")
    p.add_argument("--mu", type=non_negative("mu"), default=0.3, help="friction (default 0.3)")
    p.add_argument("--alpha", type=positive("alpha"), default=0.05,
                   help="time step as alpha sqrt(m/K) (default 0.05)")
    p.add_argument("--strain", type=fraction("strain"), default=0.02,
                   help="final axial strain, in (0, 1) (default 0.02)")
    p.add_argument("--rotation", action=argparse.BooleanOptionalAction, default=True,
                   help="free particle rotation (default) or blocked")
    p.add_argument("--boundary", choices=("periodic", "platens"), default="periodic",
                   help="periodic cell (default) or rigid frictionless platens in z")
    p.add_argument("--out", help="folder for the curves (CSV), PNGs and, if the run "
                   "diverges, its saved state (without --out that goes to the system's "
                   "temporary folder; its path is printed)")
    p.add_argument("--json", action="store_true", help="print the documented JSON summary")
    p.set_defaults(func=cmd_fcc)


def cmd_fcc(args) -> int:
    from demstep.experiments.fcc_plane_strain import FCCConfig, run_fcc

    cfg = FCCConfig(mu=args.mu, alpha=args.alpha, strain=args.strain, rotation=args.rotation,
                    boundary=args.boundary)
    cfg.validate()
    out = None
    if args.out is not None:
        from pathlib import Path

        from demstep.io.lock import check_folder_creatable

        check_folder_creatable(args.out, "out")
        out = Path(args.out)
    result = run_fcc(cfg, checkpoint_dir=out)
    if result.diverged_state:
        print(f"demstep fcc: the run diverged; its state is saved in {result.diverged_state}",
              file=sys.stderr)
    summary = _finite_or_none(result.summary())
    if out is not None:
        from demstep import plotting
        from demstep.experiments.paper import _write_curves, _write_json
        from demstep.io.lock import make_folder

        make_folder(out, "out")
        _write_curves(out / "fcc_curves.csv", result.curves)
        record = {**summary, "alpha": cfg.alpha, "rotation": cfg.rotation, "curves": result.curves}
        plotting.plot_fcc_ratio([record], result.theory, out / "fcc_stress_ratio.png")
        plotting.plot_fcc_energy([record], cfg.energy_eps, out / "fcc_energy_error.png")
        details = {k: v for k, v in vars(result).items() if k != "curves"}
        _write_json(out / "fcc_summary.json", details)
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"FCC plane strain, mu = {cfg.mu:g}, alpha = {cfg.alpha:g}: {summary['status']}")
        print(f"  peak sigma_zz/sigma_xx = {result.peak_ratio:.4g} (Thornton {result.theory:.4g}) "
              f"at {100 * result.peak_strain:.3g} % strain")
        print(f"  max normalized energy difference = {result.max_energy_error:.3g}")
        print(f"  exact critical alpha of the specimen: {result.alpha_exact_rotation:.4f} with "
              f"rotation, {result.alpha_exact_translation:.4f} without")
        if result.message:
            print("  " + result.message)
    return 0


# ----------------------------------------------------------------- stability

def add_stability_parser(sub):
    from demstep.experiments.stability import STUDY_NAMES

    p = sub.add_parser("stability", help="measured stability threshold against the estimates",
                       description="Bisection for the smallest alpha at which the engine goes "
                       "unstable on a pre-compressed periodic specimen, beside every estimate.")
    p.add_argument("--lattice", required=True, help=f"one of {', '.join(STUDY_NAMES)}")
    p.add_argument("--rtol", type=fraction("rtol"), default=2e-3,
                   help="relative tolerance of the bisection, in (0, 1) (default 2e-3)")
    p.add_argument("--steps", type=positive_int("steps"), default=3000,
                   help="steps per trial (default 3000)")
    p.add_argument("--json", action="store_true", help="print the documented JSON")
    p.set_defaults(func=cmd_stability)


def cmd_stability(args) -> int:
    from demstep.experiments.stability import STUDY_NAMES, stability_threshold

    if args.lattice not in STUDY_NAMES:
        raise InputError(f"lattice: unknown lattice {args.lattice!r}; choose one of "
                         f"{', '.join(STUDY_NAMES)}")
    result = stability_threshold(args.lattice, rtol=args.rtol, steps=args.steps)
    if args.json:
        print(json.dumps(result.to_json()))
    else:
        print(f"{args.lattice}: measured threshold alpha = {result.alpha_empirical:.4f} "
              f"(bracket {result.bracket[0]:.4f} - {result.bracket[1]:.4f}, {result.trials} trials)")
        for method, a in result.estimates.items():
            print(f"  {method:<16} alpha = {a:.4f}  ({100 * (a / result.alpha_empirical - 1):+.1f} %)")
    return 0


# --------------------------------------------------------------------- paper

def add_paper_parser(sub):
    p = sub.add_parser("paper", help="reproduce the paper's validation with plots and a report",
                       description="The critical-step tables (Figs. 8, 9), the FCC alpha study "
                       "(Figs. 11, 12), the measured stability thresholds, and report.html.")
    p.add_argument("--out", default="demstep-paper", help="output folder (default demstep-paper)")
    p.add_argument("--quick", action="store_true", help="shorter runs (under 2 minutes)")
    p.add_argument("--workers", type=positive_int("workers"), default=None,
                   help="Dask workers on this machine (default 2)")
    p.add_argument("--scheduler", help="address of an existing Dask scheduler (tcp://HOST:PORT; "
                   "instead of --workers)")
    p.add_argument("--quiet", action="store_true", help="no progress display")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the results of an earlier run in --out (only the files "
                   "the paper writes; other files there are kept)")
    p.set_defaults(func=cmd_paper)


def cmd_paper(args) -> int:
    from demstep.experiments.paper import run_paper
    from demstep.io.lock import check_folder_creatable

    check_folder_creatable(args.out, "out")
    if args.scheduler and args.workers is not None:
        raise InputError(f"workers: not used with --scheduler (its cluster has its own "
                         f"workers), got {args.workers}")
    summary = run_paper(args.out, quick=args.quick,
                        workers=2 if args.workers is None else args.workers,
                        scheduler=args.scheduler, show_progress=not args.quiet,
                        overwrite=args.overwrite)
    print(f"report: {args.out}/report.html ({summary['wall_time_s']:.0f} s)")
    for r in summary["fcc"]:
        rot = "" if r["rotation"] else " (rotation blocked)"
        peak = r.get("peak_ratio")
        shown = "-" if peak is None or peak != peak or r["status"] == "unstable" else f"{peak:.3f}"
        print(f"  alpha {r['alpha']:.2f}{rot}: {r['status']}, peak ratio {shown}, max energy difference "
              f"{r.get('max_energy_error', float('nan')):.2e}")
    return 0


