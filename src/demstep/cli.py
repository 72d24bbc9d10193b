"""The ``demstep`` command line: a thin layer; each subcommand imports what it needs.

Bad input gives a one-line ``demstep: error: ...`` on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys

from demstep.errors import InputError


def _positive(name):
    def parse(text):
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name}: not a number: {text!r}") from None
        if not (v > 0 and v < float("inf")):
            raise argparse.ArgumentTypeError(f"{name}: must be a finite positive number, got {text!r}")
        return v
    return parse


def _non_negative(name):
    def parse(text):
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name}: not a number: {text!r}") from None
        if not (v >= 0 and v < float("inf")):
            raise argparse.ArgumentTypeError(f"{name}: must be a finite number >= 0, got {text!r}")
        return v
    return parse


def _positive_int(name):
    def parse(text):
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name}: not an integer: {text!r}") from None
        if v < 1:
            raise argparse.ArgumentTypeError(f"{name}: must be >= 1, got {text!r}")
        return v
    return parse


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2
        self.exit(2, f"demstep: error: {message}\n")


# ----------------------------------------------------------------------- fcc

def _finite_or_none(d: dict) -> dict:
    import math

    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}


def _add_fcc(sub):
    p = sub.add_parser("fcc", help="the paper's FCC plane-strain compression at one alpha",
                       description="Plane-strain compression of 150 FCC spheres (paper Figs. "
                       "10-12): peak stress ratio against Thornton's theory and the energy "
                       "balance.")
    p.add_argument("--mu", type=_non_negative("mu"), default=0.3, help="friction (default 0.3)")
    p.add_argument("--alpha", type=_positive("alpha"), default=0.05,
                   help="time step as alpha sqrt(m/K) (default 0.05)")
    p.add_argument("--strain", type=_positive("strain"), default=0.02,
                   help="final axial strain (default 0.02)")
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
    if args.out:
        from pathlib import Path

        from demstep.io.lock import check_folder_creatable

        out = Path(args.out)
        check_folder_creatable(out, "out")
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

def _add_stability(sub):
    from demstep.experiments.stability import STUDY_NAMES

    p = sub.add_parser("stability", help="measured stability threshold against the estimates",
                       description="Bisection for the smallest alpha at which the engine goes "
                       "unstable on a pre-compressed periodic specimen, beside every estimate.")
    p.add_argument("--lattice", required=True, help=f"one of {', '.join(STUDY_NAMES)}")
    p.add_argument("--rtol", type=_positive("rtol"), default=2e-3,
                   help="relative tolerance of the bisection (default 2e-3)")
    p.add_argument("--steps", type=_positive_int("steps"), default=3000,
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

def _add_paper(sub):
    p = sub.add_parser("paper", help="reproduce the paper's validation with plots and a report",
                       description="The critical-step tables (Figs. 8, 9), the FCC alpha study "
                       "(Figs. 11, 12), the measured stability thresholds, and report.html.")
    p.add_argument("--out", default="demstep-paper", help="output folder (default demstep-paper)")
    p.add_argument("--quick", action="store_true", help="shorter runs (under 2 minutes)")
    p.add_argument("--workers", type=_positive_int("workers"), default=2,
                   help="Dask workers on this machine (default 2)")
    p.add_argument("--scheduler", help="address of an existing Dask scheduler (tcp://HOST:PORT)")
    p.add_argument("--quiet", action="store_true", help="no progress display")
    p.set_defaults(func=cmd_paper)


def cmd_paper(args) -> int:
    from pathlib import Path

    from demstep.experiments.paper import run_paper
    from demstep.io.lock import check_folder_creatable

    check_folder_creatable(Path(args.out), "out")
    summary = run_paper(args.out, quick=args.quick, workers=args.workers,
                        scheduler=args.scheduler, show_progress=not args.quiet)
    print(f"report: {args.out}/report.html ({summary['wall_time_s']:.0f} s)")
    for r in summary["fcc"]:
        rot = "" if r["rotation"] else " (rotation blocked)"
        peak = r.get("peak_ratio")
        shown = "-" if peak is None or peak != peak or r["status"] == "unstable" else f"{peak:.3f}"
        print(f"  alpha {r['alpha']:.2f}{rot}: {r['status']}, peak ratio {shown}, max energy difference "
              f"{r.get('max_energy_error', float('nan')):.2e}")
    return 0


# -------------------------------------------------------------------------- main

def build_parser() -> argparse.ArgumentParser:
    from demstep import __version__

    parser = _Parser(prog="demstep", description="Explicit DEM with a certified time step.")
    parser.add_argument("--version", action="version", version=f"demstep {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    from demstep.cli_dt import add_dt_parser

    add_dt_parser(sub)
    _add_fcc(sub)
    _add_stability(sub)
    _add_paper(sub)
    from demstep.cli_run import add_plot_parser, add_run_parser

    add_run_parser(sub)
    add_plot_parser(sub)
    from demstep.cli_sweep import add_sweep_parser

    add_sweep_parser(sub)
    return parser


def run_parser(parser: argparse.ArgumentParser, argv=None) -> int:
    """Parse ``argv`` and run the chosen subcommand: InputError -> one line, exit 2;
    an operating-system error (disk full, no permission) -> one line, exit 1;
    Ctrl-C -> exit 130; a closed standard output (``| head``) -> quiet exit 141 as for
    the Unix tools killed by SIGPIPE."""
    args = parser.parse_args(argv)
    try:
        status = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe fails here, not at exit
        return status
    except BrokenPipeError:
        return _stdout_closed()
    except InputError as exc:
        print(f"demstep: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("demstep: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:
        where = f": {exc.filename}" if getattr(exc, "filename", None) else ""
        print(f"demstep: error: {exc.strerror or type(exc).__name__}{where}", file=sys.stderr)
        return 1


#: exit status after the reader of standard output went away (128 + SIGPIPE)
EXIT_BROKEN_PIPE = 141


def _stdout_closed() -> int:
    """Standard output is a pipe whose reader has gone: stop quietly. Point the file
    descriptor at /dev/null so that the interpreter's final flush does not fail again
    (https://docs.python.org/3/library/signal.html#note-on-sigpipe)."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass
    return EXIT_BROKEN_PIPE


def main(argv=None) -> int:
    return run_parser(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
