"""The ``demstep`` command line: a thin layer; each subcommand imports what it needs.

Bad input gives a one-line ``demstep: error: ...`` on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys

from demstep.errors import InputError

#: documented defaults (the paper's Table I)
DEFAULT_KN = 1.0e11
DEFAULT_DENSITY = 2000.0
DEFAULT_RADIUS = 20.0


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


# ------------------------------------------------------------------------------ dt

def _add_dt(sub):
    p = sub.add_parser("dt", help="critical time step of an assembly or lattice, every method",
                       description="Critical time step of central-difference DEM for an "
                       "assembly file or a regular lattice, by every method side by side.")
    p.add_argument("assembly", nargs="?", help="assembly file (CSV with header x,y,r or x,y,z,r, optional m)")
    p.add_argument("--lattice", help="regular lattice: square, hex, sc, bcc, fcc, rhombic")
    p.add_argument("--size", type=_positive_int("size"), default=4,
                   help="lattice block of SIZE^dim conventional cells (default 4)")
    p.add_argument("--periodic", action="store_true",
                   help="treat the lattice block as a periodic supercell")
    p.add_argument("--radius", type=_positive("radius"), default=DEFAULT_RADIUS,
                   help=f"lattice particle radius (default {DEFAULT_RADIUS:g})")
    p.add_argument("--density", type=_positive("density"), default=DEFAULT_DENSITY,
                   help=f"particle density when the file has no m column (default {DEFAULT_DENSITY:g})")
    p.add_argument("--kn", type=_positive("kn"), default=DEFAULT_KN,
                   help=f"normal contact stiffness (default {DEFAULT_KN:g}, the paper's Table I)")
    p.add_argument("--ks", type=_non_negative("ks"), default=None,
                   help="tangential contact stiffness (default: equal to --kn)")
    p.add_argument("--rotation", action=argparse.BooleanOptionalAction, default=True,
                   help="include rotational degrees of freedom (default: yes)")
    p.add_argument("--mass-split", choices=("uniform", "zoned"), default="uniform",
                   help="element mass split for element-paper (default uniform)")
    p.add_argument("--rayleigh", nargs=2, type=_non_negative("rayleigh"), metavar=("A1", "A2"),
                   help="Rayleigh damping C = A1 M + A2 K: apply the reduction of eq. 28")
    p.add_argument("--contact-tol", type=_non_negative("contact-tol"), default=1e-6,
                   help="relative gap still counted as contact (default 1e-6)")
    p.add_argument("--methods", help="comma-separated subset of methods to compute")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--plot", metavar="FILE.png", help="bar chart of the methods")
    p.add_argument("--paper-table", action="store_true",
                   help="reproduce the paper's Figures 8 and 9 (element estimates beside exact values)")
    p.set_defaults(func=cmd_dt)


def cmd_dt(args) -> int:
    import numpy as np

    if args.paper_table:
        from demstep.timestep.paper_table import format_table, paper_table, table_json

        rows = paper_table()
        print(json.dumps(table_json(rows), indent=2) if args.json else format_table(rows))
        return 0

    from demstep.contacts import find_contacts
    from demstep.particles import Particles
    from demstep.timestep import estimate_time_steps

    if (args.assembly is None) == (args.lattice is None):
        raise InputError("give either an assembly file or --lattice NAME (exactly one)")
    methods = None if args.methods is None else [m.strip() for m in args.methods.split(",")]
    lattice_obj, periodic = None, None
    if args.lattice is not None:
        from demstep.packings import lattice

        lattice_obj = lattice(args.lattice, args.radius)
        if args.periodic:
            x, box = lattice_obj.supercell(args.size)
            periodic = list(box)
        else:
            x = lattice_obj.block(args.size)
        particles = Particles.from_density(x, np.full(len(x), args.radius), args.density)
    else:
        from demstep.io.assembly_files import read_assembly
        from demstep.particles import particle_inertia

        data = read_assembly(args.assembly)
        if data.m is None:
            particles = Particles.from_density(data.x, data.r, args.density)
        else:
            particles = Particles(data.x, data.r, data.m,
                                  particle_inertia(data.m, data.r, data.x.shape[1]))
    contacts = find_contacts(particles, args.kn, args.ks, args.contact_tol, periodic=periodic)
    report = estimate_time_steps(particles, contacts, rotation=args.rotation,
                                 mass_split=args.mass_split, rayleigh=args.rayleigh,
                                 methods=methods, lattice=lattice_obj, density=args.density)
    if args.plot:
        from demstep.plotting import plot_estimates

        plot_estimates(report, args.plot)
    if args.json:
        print(json.dumps(report.to_json()))
    else:
        print(format_report(report))
    return 0


def format_report(report) -> str:
    rot = "with rotation" if report.rotation else "translation only"
    lines = [f"{report.dim}D assembly: {report.n_particles} particles, {report.n_contacts} "
             f"contacts, {rot}; m_min = {report.m_min:.6g}, K_max = {report.k_max:.6g}"]
    if report.rayleigh:
        lines.append(f"Rayleigh damping a1 = {report.rayleigh[0]:g}, a2 = {report.rayleigh[1]:g} (eq. 28 applied)")
    lines.append(f"{'method':<17}{'dt':>14}{'alpha':>10}  conservative vs exact")
    for e in report.estimates:
        cons = "-" if e.conservative is None else ("yes" if e.conservative else "NO")
        lines.append(f"{e.method:<17}{e.dt:>14.6g}{e.alpha:>10.4f}  {cons}")
    lines.append("alpha = dt / sqrt(m_min / K_max)")
    return "\n".join(lines)


# -------------------------------------------------------------------------- main

def build_parser() -> argparse.ArgumentParser:
    from demstep import __version__

    parser = _Parser(prog="demstep", description="Explicit DEM with a certified time step.")
    parser.add_argument("--version", action="version", version=f"demstep {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    _add_dt(sub)
    from demstep.cli_run import add_plot_parser, add_run_parser

    add_run_parser(sub)
    add_plot_parser(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"demstep: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("demstep: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
