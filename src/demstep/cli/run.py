"""``demstep run`` and ``demstep plot``: subcommands of :mod:`demstep.cli`.

Heavy modules are imported only when a subcommand runs. Bad input raises InputError
(the main CLI prints ``demstep: error: ...`` and exits 2) before anything is written.
Exit status of ``run``: 0 completed, 1 diverged, stopped by the energy monitor or
failed, 2 bad input (including an output folder in use by another run), 130 after
SIGINT and 143 after SIGTERM (128 + the signal number, as the shell reports a process
killed by it): the first signal saves a checkpoint and stops (status 'interrupted'),
a second one stops at once without a checkpoint (status 'aborted'); both are recorded
in run.json.
"""

from __future__ import annotations

import argparse
import sys

from demstep.errors import InputError

def _non_negative_int(text):
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"max-steps: not an integer: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"max-steps: must be >= 0, got {text!r}")
    return value


def add_run_parser(subparsers):
    """``demstep run CASE.toml --out DIR [--quiet] [--log-level L] [--restart CKPT]``."""
    p = subparsers.add_parser(
        "run", help="run a TOML case file: stages, outputs, checkpoints",
        description="Run the stages of a TOML case file, writing the resolved case, a CSV "
        "history, VTK frames and checkpoints into --out. The whole case is checked before "
        "the folder is created. SIGINT/SIGTERM save a checkpoint and stop; --restart "
        "continues bit for bit.")
    p.add_argument("case", help="case file (TOML; see demstep.case.schema for the keys)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--log-level", default="INFO", metavar="LEVEL",
                   help="DEBUG, INFO (default), WARNING or ERROR")
    p.add_argument("--restart", metavar="CHECKPOINT",
                   help="continue from a checkpoint (.npz, or a run folder: its newest)")
    p.add_argument("--max-steps", type=_non_negative_int, default=None, metavar="N",
                   help="run at most N steps per stage (previews, smoke tests)")
    p.add_argument("--overwrite", action="store_true",
                   help="allow a non-empty --out folder without --restart (an earlier "
                   "run's outputs there are replaced; never the case's input files)")
    p.add_argument("--allow-changed-case", action="store_true",
                   help="with --restart: continue although the case differs from the one "
                   "that wrote the checkpoint")
    p.set_defaults(func=cmd_run)
    return p


def add_plot_parser(subparsers):
    """``demstep plot DIR``."""
    p = subparsers.add_parser(
        "plot", help="plot a run's history (energies, energy error, wall stresses, dt)",
        description="Draw PNG figures from DIR/history.csv into DIR/plots.")
    p.add_argument("dir", help="output folder of 'demstep run'")
    p.set_defaults(func=cmd_plot)
    return p


def cmd_run(args) -> int:
    from demstep.case import load_case
    from demstep.runner import run_case

    if args.allow_changed_case and args.restart is None:
        raise InputError("allow-changed-case: only used with --restart")
    case = load_case(args.case)
    result = run_case(case, args.out, quiet=args.quiet, log_level=args.log_level,
                      restart=args.restart, max_steps=args.max_steps, overwrite=args.overwrite,
                      allow_changed_case=args.allow_changed_case, exit_on_abort=True)
    stream = sys.stdout if result.ok else sys.stderr
    print(f"demstep run: {result.status}: {result.message}", file=stream)
    return result.exit_status


def cmd_plot(args) -> int:
    from demstep.plotting_run import plot_run

    for path in plot_run(args.dir):
        print(path)
    return 0


def main(argv=None) -> int:
    """``python -m demstep.cli.run``: only this module's subcommands."""
    from demstep.cli.common import run_parser, subcommand_parser

    return run_parser(subcommand_parser(add_run_parser, add_plot_parser), argv)


if __name__ == "__main__":
    sys.exit(main())
