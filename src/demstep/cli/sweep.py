"""``demstep sweep``: parameter sweeps of a case on Dask (:mod:`demstep.sweep`).

Bad input (a key that is not in the schema, a value the schema refuses, a bad runs
file, a ``--peak`` that is no column of a run's history, a ``--scheduler`` that cannot be
reached or is no Dask scheduler: an SSH or HTTP server, one that never answers; see
:func:`demstep.sweep.cluster.probe_scheduler`) raises InputError before anything is
written (the main CLI prints ``demstep: error: ...`` and exits 2; so does an output
folder another sweep is writing into). Exit status: 0 when every run finished (completed, diverged or
energy_stop: results of the sweep), 1 when any run failed with an error or was left
unfinished because no worker was connected for ``--worker-timeout`` seconds (its
message is in summary.csv; running the sweep again re-runs it).
"""

from __future__ import annotations

import argparse
import sys

from demstep.errors import InputError

DEFAULT_WORKERS = 2


def _int_at_least(name, low):
    def parse(text):
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name}: not an integer: {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"{name}: must be >= {low}, got {text!r}")
        return value
    return parse


def add_sweep_parser(subparsers):
    """``demstep sweep CASE.toml --param KEY=V1,V2 ... --out DIR``."""
    p = subparsers.add_parser(
        "sweep", help="run a case for many parameter values on Dask, with a summary",
        description="Run a TOML case once per combination of parameter values (the "
        "cartesian product of every --param, or the rows of --runs), in parallel on a "
        "local Dask cluster or an existing one (--scheduler). Each run writes "
        "DIR/runs/<run-id>/; DIR/summary.csv and DIR/summary.png compare them. Every "
        "run's case is validated before anything is written. Running the same sweep "
        "into the same DIR again skips the runs already finished.",
        epilog="examples:\n"
        "  demstep sweep case.toml --param contact.mu=0.1,0.3 "
        "--param timestep.alpha=0.05,0.35 --out sweep\n"
        "  demstep sweep case.toml --param 'stages[1].mu=0.2,0.5' --max-steps 1000 --out s\n"
        "  demstep sweep case.toml --runs runs.csv --scheduler tcp://10.0.0.5:8786 --out s",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("case", help="case file (TOML; see demstep.case.schema for the keys)")
    p.add_argument("--param", action="append", default=[], metavar="KEY=V1,V2,...",
                   help="a dotted key of the case (contact.mu, timestep.alpha, "
                   "stages[1].mu, particles.density) and its values, TOML scalars "
                   "separated by commas; repeat for a cartesian product")
    p.add_argument("--runs", metavar="FILE", default=None,
                   help="runs listed in a CSV file (header: the keys; a row per run) or a "
                   "TOML file of [[runs]] tables; combined with every --param")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder of the sweep")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT", default=None,
                   help="address of a running Dask scheduler, its scheduler port (Dask's "
                   "default 8786), not the dashboard's (default: start a local cluster)")
    p.add_argument("--workers", type=_int_at_least("workers", 1), default=None, metavar="N",
                   help=f"worker processes of the local cluster, one thread each "
                   f"(default {DEFAULT_WORKERS})")
    p.add_argument("--max-steps", type=_int_at_least("max-steps", 0), default=None,
                   metavar="N", help="run at most N steps per stage (previews, smoke tests)")
    p.add_argument("--peak", metavar="COLUMN", default=None,
                   help="history.csv column whose maximum is reported as 'peak' (default: "
                   "the top wall's stress, else the first wall's); checked against each "
                   "run's history columns before anything runs")
    p.add_argument("--log-level", default="INFO", metavar="LEVEL",
                   help="level of each run's run.log: DEBUG, INFO (default), WARNING, ERROR")
    p.add_argument("--worker-timeout", type=_positive_seconds, default=None, metavar="S",
                   help="give up the runs not done after S seconds without any worker "
                   "connected, marking them unfinished (default "
                   f"{_default_worker_timeout():g}); while waiting, a line reports how many "
                   "runs are pending")
    p.add_argument("--quiet", action="store_true", help="no line per finished run")
    p.set_defaults(func=cmd_sweep)
    return p


def _positive_seconds(text):
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"worker-timeout: not a number: {text!r}") from None
    if not (0 < value < float("inf")):
        raise argparse.ArgumentTypeError(f"worker-timeout: must be a finite number of "
                                         f"seconds > 0, got {text!r}")
    return value


def _default_worker_timeout() -> float:
    from demstep.sweep import WORKER_TIMEOUT

    return WORKER_TIMEOUT


def _fmt(value, spec=".3g") -> str:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return "-"
    return "-" if v != v else format(v, spec)


def cmd_sweep(args) -> int:
    from demstep.sweep import run_sweep

    if args.scheduler and args.workers is not None:
        raise InputError("workers: not used with --scheduler (the cluster has its workers)")

    def progress(done, total, run_id, row, skipped):
        if args.quiet:
            return
        if skipped:
            text = f"{row.get('status')} earlier, skipped"
        else:
            text = (f"{row.get('status')}, max energy error {_fmt(row.get('max_energy_error'))}"
                    f", {_fmt(row.get('wall_time_s'), '.1f')} s")
            if row.get("status") not in ("completed", None):
                error = str(row.get("error", ""))
                text += f": {error[:157] + '...' if len(error) > 160 else error}"
        print(f"[{done}/{total}] {run_id}: {text}", file=sys.stderr, flush=True)

    timeout = args.worker_timeout if args.worker_timeout is not None \
        else _default_worker_timeout()

    def waiting(pending, seconds):  # always shown: a silent wait looks like a hang
        print(f"demstep sweep: waiting for workers: {pending} run(s) pending, no worker "
              f"connected for {seconds:.0f} s (giving up after {timeout:g} s)",
              file=sys.stderr, flush=True)

    result = run_sweep(args.case, args.out, params=args.param, runs_file=args.runs,
                       scheduler=args.scheduler,
                       workers=args.workers if args.workers is not None else DEFAULT_WORKERS,
                       max_steps=args.max_steps, peak=args.peak, log_level=args.log_level,
                       progress=progress, worker_timeout=timeout, on_wait=waiting)
    counts = ", ".join(f"{result.count(s)} {s}" for s in
                       ("completed", "diverged", "energy_stop", "failed", "unfinished")
                       if result.count(s))
    skipped = f"; {len(result.skipped)} finished earlier" if result.skipped else ""
    files = ", ".join(str(p) for p in (result.summary_csv, result.summary_png) if p)
    print(f"demstep sweep: {len(result.rows)} runs ({counts}{skipped}): {files}")
    return 1 if result.count("failed") or result.count("unfinished") else 0


def main(argv=None) -> int:
    """``python -m demstep.cli.sweep``: only this module's subcommands."""
    from demstep.cli.common import run_parser, subcommand_parser

    return run_parser(subcommand_parser(add_sweep_parser), argv)


if __name__ == "__main__":
    sys.exit(main())
