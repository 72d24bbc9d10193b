"""The ``demstep`` command line: a thin layer; each subcommand imports what it needs.

Subcommands live in their own modules (``dt``, ``run`` and ``plot``, ``sweep``, and
``fcc``/``stability``/``paper`` in ``experiments``), which import only
:mod:`demstep.cli.common`. Bad input gives a one-line ``demstep: error: ...`` on stderr
and exit status 2.
"""

from __future__ import annotations

import argparse

from demstep.cli.common import Parser, run_parser


def build_parser() -> argparse.ArgumentParser:
    from demstep import __version__
    from demstep.cli.dt import add_dt_parser
    from demstep.cli.experiments import add_fcc_parser, add_paper_parser, add_stability_parser
    from demstep.cli.run import add_plot_parser, add_run_parser
    from demstep.cli.sweep import add_sweep_parser

    parser = Parser(prog="demstep", description="Explicit DEM with a certified time step.")
    parser.add_argument("--version", action="version", version=f"demstep {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True
    for add in (add_dt_parser, add_fcc_parser, add_stability_parser, add_paper_parser,
                add_run_parser, add_plot_parser, add_sweep_parser):
        add(sub)
    return parser


def main(argv=None) -> int:
    return run_parser(build_parser(), argv)
