"""``demstep dt``: the critical time step of a state, every method side by side.

Inputs: a particle file (CSV, LIGGGHTS/LAMMPS dump, YADE text), a demstep case file
(its initial state) or checkpoint (the run's contacts and overlaps), or a regular
lattice. Contact models: linear (k_n, k_t) or Hertz-Mindlin (E, nu per material), with
dashpots by restitution or absolute coefficients, rolling and twisting resistance
(conventions beta and epsd, :mod:`demstep.contact.laws`), and global damping. Output: the
table (or JSON), where the danger is (the particles and contacts carrying the critical
mode, optionally as VTK) and an optional bar chart.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from demstep.cli.common import number, positive_int
from demstep.errors import InputError

#: documented defaults (the paper's Table I)
DEFAULT_KN = 1.0e11
DEFAULT_DENSITY = 2000.0
DEFAULT_RADIUS = 20.0
#: bytes of memory per particle of the analysis, measured (benchmarks/timestep_scaling.py:
#: 3D with rotation, about 6 contacts per particle, Lanczos with 32 vectors), with margin
BYTES_PER_PARTICLE = 4000
#: the same with --low-memory (no Lanczos basis: three vectors): measured 2.0 KB per
#: particle on an FCC block of 5e5 spheres (benchmarks/RESULTS.md, section 17), with margin
LOW_MEMORY_BYTES_PER_PARTICLE = 2500
#: formats of the positional input
INPUT_FORMATS = ("auto", "csv", "liggghts", "yade", "lammps-data", "case", "checkpoint")
#: image formats of --plot (matplotlib)
PLOT_FORMATS = (".png", ".pdf", ".svg")


def add_dt_parser(sub):
    p = sub.add_parser(
        "dt", help="critical time step of a state, every method side by side",
        description="Critical time step of central-difference DEM for a state (a particle "
        "file, a LIGGGHTS/LAMMPS dump, a YADE text export, a demstep case file or checkpoint) "
        "or a regular lattice: the exact step (damped when there is damping), rigorous "
        "bounds and the rules users know, side by side.",
        epilog="Files: CSV with header x,y[,z],r and optional m (mass) and type columns; "
        "LIGGGHTS/LAMMPS 'dump custom' (x y z radius, optional mass type vx vy vz; the BOX "
        "BOUNDS flags pp make an axis periodic); YADE text (x y z r); a demstep case (.toml) "
        "at its initial state; a demstep checkpoint (.npz) with its run folder's case.toml.")
    src = p.add_argument_group("input")
    src.add_argument("state", nargs="?", metavar="FILE",
                     help="CSV, LIGGGHTS/LAMMPS dump, YADE text, case (.toml) or checkpoint (.npz)")
    src.add_argument("--format", choices=INPUT_FORMATS, default="auto",
                     help="format of FILE (default: by extension, then content)")
    src.add_argument("--snapshot", type=int, default=-1,
                     help="which snapshot of a dump (0 first, -1 last; default -1)")
    src.add_argument("--case", help="case file of a checkpoint (default: the run folder's case.toml)")
    src.add_argument("--stage", type=positive_int("stage"), default=1,
                     help="case files: the stage whose settings apply (default 1)")
    src.add_argument("--lattice", help="regular lattice: square, hex, sc, bcc, fcc, rhombic")
    src.add_argument("--size", type=positive_int("size"), default=4,
                     help="lattice block of SIZE^dim conventional cells (default 4)")
    src.add_argument("--periodic", nargs="?", const="lattice", default=None, metavar="AXES",
                     help="lattice: a periodic supercell; files: the periodic axes, e.g. x,y,z "
                     "(dumps: default from their BOX BOUNDS flags)")
    src.add_argument("--box", nargs="+", type=number("box"), metavar="LO_HI",
                     help="box bounds xlo xhi ylo yhi [zlo zhi] (files without one, or to "
                     "override); negative bounds as they are: --box -5 5 -5 5")
    src.add_argument("--wall", action="append", default=[], metavar="SPEC",
                     help="a wall: a box side (x-, x+, y-, y+, z-, z+) or 'px,py,pz:nx,ny,nz' "
                     "(normal into the packing); repeat for several; a negative first "
                     "coordinate as it is or after '=': --wall -1,0,0:1,0,0 or "
                     "--wall=-1,0,0:1,0,0")
    src.add_argument("--mesh", action="append", default=[], metavar="SPEC",
                     help="a triangle-mesh wall (3D): 'FILE [type T] [scale S] [move DX DY DZ] "
                     "[rotate axis AX AY AZ angle DEG]' as LIGGGHTS' fix mesh/surface "
                     "(STL, OBJ, or what meshio reads; type T: the material of particle "
                     "type T, else the touching particle's); repeat for several")
    src.add_argument("--radius", type=number("radius", 0, strict=True), default=DEFAULT_RADIUS,
                     help=f"lattice particle radius (default {DEFAULT_RADIUS:g})")
    src.add_argument("--density", type=number("density", 0, strict=True), default=None,
                     help=f"particle density of a file without a mass column (refused with "
                     f"one; default {DEFAULT_DENSITY:g})")
    src.add_argument("--contact-tol", type=number("contact-tol", 0), default=1e-6,
                     help="relative gap still counted as contact (default 1e-6)")
    mod = p.add_argument_group("contact model and damping")
    from demstep.contact.laws import LAWS

    law_options = _law_options()
    mod.add_argument("--model", choices=tuple(LAWS), default=None,
                     help="the contact law: " + "; ".join(
                         f"{name} ({', '.join('--' + o for o in cls.cli)})"
                         for name, cls in LAWS.items())
                     + "; default: the law of the options given, else "
                     + next(n for n, c in LAWS.items() if c.default))
    for option, (help_text, laws, bounds) in law_options.items():
        low = bounds.get("gt", bounds.get("ge"))
        mod.add_argument(f"--{option}", type=number(option, low, strict="gt" in bounds),
                         default=None,
                         help=f"{help_text} ({', '.join(laws)})"
                         + (f"; default {DEFAULT_KN:g}, the paper's Table I" if option == "kn"
                            else ""))
    mod.add_argument("--materials", metavar="FILE.toml",
                     help="Hertz: materials per particle type ([[material]] type, youngs, "
                     "poisson, density)")
    mod.add_argument("--overlap", type=number("overlap", 0), default=None,
                     help="Hertz: evaluate stiffnesses at least at this overlap / R* "
                     "(default 0: the actual overlaps; case files: their timestep.overlap)")
    mod.add_argument("--restitution", type=number("restitution"), default=None,
                     help="dashpots from a coefficient of restitution in (0, 1]")
    mod.add_argument("--restitution-t", type=number("restitution-t"), default=None,
                     help="demstep convention: tangential dashpot from this restitution")
    mod.add_argument("--gamma-n", type=number("gamma-n", 0), default=0.0,
                     help="absolute normal dashpot coefficient [M/T] (force -gamma v_n)")
    mod.add_argument("--gamma-t", type=number("gamma-t", 0), default=0.0,
                     help="absolute tangential dashpot coefficient [M/T]")
    mod.add_argument("--tangential-damping", action=argparse.BooleanOptionalAction,
                     default=True, help="LIGGGHTS' tangential_damping (default on)")
    mod.add_argument("--convention", choices=("demstep", "liggghts"), default=None,
                     help="restitution to dashpots, and the lever arm of wall contacts "
                     "(r - delta or r - delta/2): demstep's engine or LIGGGHTS 3.8 "
                     "(default: liggghts for dumps, demstep otherwise)")
    mod.add_argument("--lammps-model", metavar="TEXT", default=None,
                     help="LAMMPS pair_style granular: the contacts' springs and dashpots as "
                     "LAMMPS computes them from this pair_coeff text, e.g. 'hertz/material "
                     "5e7 0.5 0.3 tangential mindlin NULL 1.0 0.5 damping tsuji' (instead "
                     "of --model and the law's options; docs/lammps.md)")
    mod.add_argument("--rolling-convention", choices=("beta", "epsd"), default=None,
                     help="rolling and twisting resistance: 'beta' (k_r = beta_r k_t R*^2, "
                     "k_w = beta_w k_t R*^2) or 'epsd' (k_r = 2.25 k_n mu_r^2 R*^2, "
                     "k_w = 2.25 k_n mu_w^2 R*^2, k_n the secant F_n / delta as "
                     "LIGGGHTS' epsd); default none")
    mod.add_argument("--rolling-stiffness", type=number("rolling-stiffness", 0), default=None,
                     metavar="BETA_R", help="beta convention: rolling stiffness factor beta_r")
    mod.add_argument("--twisting-stiffness", type=number("twisting-stiffness", 0), default=None,
                     metavar="BETA_W", help="beta convention: twisting stiffness factor beta_w")
    mod.add_argument("--rolling-friction", type=number("rolling-friction", 0), default=None,
                     metavar="MU_R", help="rolling friction mu_r (epsd: sets k_r; the moment "
                     "limit mu_r R* F_n does not enter the linear analysis)")
    mod.add_argument("--twisting-friction", type=number("twisting-friction", 0), default=None,
                     metavar="MU_W", help="twisting friction mu_w (epsd: sets k_w)")
    mod.add_argument("--rolling-damping", type=number("rolling-damping", 0), default=None,
                     metavar="ETA_R", help="viscous ratio of the rolling and twisting springs: "
                     "c = 2 eta sqrt(I* k) [M L^2/T]")
    mod.add_argument("--viscous", type=number("viscous", 0), default=0.0,
                     help="global mass-proportional damping a1 [1/T] (force -a1 m v)")
    mod.add_argument("--rayleigh", nargs=2, type=number("rayleigh", 0), metavar=("A1", "A2"),
                     help="Rayleigh damping C = A1 M + A2 K (paper eq. 26)")
    ana = p.add_argument_group("analysis and output")
    ana.add_argument("--rotation", action=argparse.BooleanOptionalAction, default=None,
                     help="rotational degrees of freedom (default: yes; case files and "
                     "checkpoints: as in the run)")
    ana.add_argument("--mass-split", choices=("uniform", "zoned"), default="uniform",
                     help="element mass split for element-paper (default uniform)")
    ana.add_argument("--methods", help="comma-separated subset of methods to compute")
    ana.add_argument("--exact-tol", type=number("exact-tol", 0, strict=True), default=None,
                     metavar="TOL", help="relative residual at which the exact solver stops "
                     "(default 1e-10, at most 1e-3); the step, from an upper bound on the "
                     "largest eigenvalue found, lies at most about 4 x TOL below the "
                     "critical one")
    ana.add_argument("--failure", type=number("failure", 0, strict=True), default=None,
                     help="failure probability of the 'certified' step where it is "
                          "probabilistic (default 1e-9; at most 0.5)")
    ana.add_argument("--seed", type=int, default=None,
                     help="seed of the random start of the 'certified' check (default: "
                          "fresh entropy, printed; give it to reproduce a certificate)")
    ana.add_argument("--low-memory", action="store_true",
                     help="certify from the random-start checks alone, without the exact "
                          "solver's Lanczos basis (about a tenth of its memory; no "
                          "'exact', no critical mode)")
    ana.add_argument("--impact-velocity", type=number("impact-velocity", 0, strict=True),
                     default=None, help="Hertz time (hertz model only): the impact "
                     "velocity [L/T] (default: twice the largest particle speed in the "
                     "input, as LIGGGHTS)")
    ana.add_argument("--top", type=int, default=10,
                     help="how many particles and contacts of the critical mode to list (default 10)")
    ana.add_argument("--mode-vtk", metavar="FILE.vtu",
                     help="write the critical mode per particle as VTK (ParaView)")
    ana.add_argument("--max-memory", type=number("max-memory", 0, strict=True), default=None,
                     metavar="GB", help="refuse analyses estimated to need more (default: the "
                     "memory available)")
    ana.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ana.add_argument("--plot", metavar="FILE.png", help="bar chart of the methods (.png, .pdf, .svg)")
    ana.add_argument("--paper-table", action="store_true",
                     help="reproduce the paper's Figures 8 and 9 (element estimates beside exact values)")
    p.set_defaults(func=cmd_dt)


# ----------------------------------------------------------------------- checks
def _check_output_path(option: str, path, suffixes) -> Path:
    """An output path with a known suffix whose folder exists or can be made
    (:func:`~demstep.io.lock.check_folder_creatable`) and takes files
    (:func:`~demstep.io.atomic.check_writable`): checked before the analysis runs."""
    from demstep.io.atomic import check_name_lengths, check_writable
    from demstep.io.lock import check_folder_creatable

    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise InputError(f"{option}: the file name must end in {', '.join(suffixes)}, "
                         f"got {str(path)!r}")
    check_name_lengths(path, option)  # (first: is_dir raises on a name too long)
    if path.is_dir():
        raise InputError(f"{option}: {str(path)!r} is a folder")
    check_folder_creatable(path.absolute().parent, option)
    check_writable(path.absolute().parent, option)
    return path


def available_memory_gb() -> float:
    import psutil

    return psutil.virtual_memory().available / 1e9


def check_memory(n_particles: int, limit_gb: float | None, what: str,
                 low_memory: bool = False):
    """Refuse, before allocating, an analysis estimated above ``limit_gb`` (default: the
    memory available now); ``low_memory``: the analysis without the solver's basis."""
    per = LOW_MEMORY_BYTES_PER_PARTICLE if low_memory else BYTES_PER_PARTICLE
    need = n_particles * per / 1e9
    limit = available_memory_gb() if limit_gb is None else limit_gb
    if need > limit:
        raise InputError(f"memory: {what} ({n_particles:,} particles) needs about {need:.3g} GB, "
                         f"more than {'the' if limit_gb is None else 'the --max-memory'} "
                         f"{limit:.3g} GB {'available' if limit_gb is None else 'allowed'}")


def _law_options() -> dict:
    """``demstep dt``'s options of the laws' own parameters (every law's ``cli``): option ->
    (help, the laws that take it)."""
    from demstep.contact.laws import LAWS

    out = {}
    for name, cls in LAWS.items():
        meta = {f.name: f.metadata for f in cls.own_fields()}
        for option, field_name in cls.cli.items():
            doc, unit = meta[field_name]["doc"], meta[field_name]["unit"]
            help_text, laws, bounds = out.get(option, (f"{doc} [{unit}]", [],
                                                       meta[field_name]["bounds"]))
            out[option] = (help_text, laws + [name], bounds)
    return out


def _model(args, default_convention: str):
    from demstep.analysis_input import ContactModel, Material, read_materials
    from demstep.contact.laws import LAWS

    given = {o: getattr(args, o) for o in _law_options() if getattr(args, o) is not None}
    if args.model is not None:
        cls = LAWS[args.model]
    else:  # the one law that takes every option given, else the default law
        takes = [c for c in LAWS.values() if set(given) <= set(c.cli)
                 and (not args.materials or c.uses_materials)]
        default = next(c for c in LAWS.values() if c.default)
        cls = default if default in takes or not takes else takes[0]
    for option in given:
        if option not in cls.cli:
            others = [n for n, c in LAWS.items() if option in c.cli]
            raise InputError(f"model: --{option} belongs to the {'/'.join(others)} model(s), "
                             f"not {cls.name} (its options: "
                             f"{', '.join('--' + o for o in cls.cli)})")
    parameters, materials = {}, {}
    if cls.uses_materials:
        if args.materials:
            if given:
                raise InputError(f"materials: give either --materials or "
                                 f"{'/'.join('--' + o for o in cls.cli)}")
            materials = read_materials(args.materials)
        else:
            missing = [o for o in cls.cli if o not in given]
            if missing:
                raise InputError(f"{missing[0]}: the {cls.name} model needs both "
                                 f"{' and '.join('--' + o for o in cls.cli)}")
            materials = {None: Material(*(given[o] for o in cls.cli), args.density)}
    else:
        if args.materials:
            raise InputError(f"materials: only for a model with materials, not {cls.name}")
        parameters = {cls.cli[o]: v for o, v in given.items()}
        if "kn" in cls.cli and "kn" not in given:
            parameters[cls.cli["kn"]] = DEFAULT_KN
    convention = args.convention or default_convention
    if not cls.kernels.nonlinear and args.overlap is not None:
        raise InputError(f"overlap: only used with a law whose stiffness depends on the "
                         f"overlap (a {cls.name} spring's does not), got {args.overlap!r}")
    overlap = args.overlap if args.overlap is not None else 0.0
    cm = ContactModel(cls.name, parameters, materials, args.restitution, args.restitution_t,
                      args.gamma_n, args.gamma_t, args.tangential_damping, convention, overlap,
                      **_rolling(args))
    cm.validate()
    return cm


def _rolling(args) -> dict:
    """The rolling-resistance fields of the ContactModel from the options (argparse
    attributes of the same names; 0 when not given, the convention None: none)."""
    from demstep.analysis_input import ROLLING_OPTIONS

    out = {name: (getattr(args, name) if getattr(args, name) is not None else 0.0)
           for name in ROLLING_OPTIONS}
    out["rolling_convention"] = args.rolling_convention
    return out


def _damping(args):
    from demstep.timestep.damping import GlobalDamping

    if args.rayleigh is not None:
        if args.viscous:
            raise InputError("viscous: give either --viscous or --rayleigh (its A1), not both")
        return GlobalDamping(*map(float, args.rayleigh))
    return GlobalDamping(float(args.viscous))


def _file_format(args) -> str:
    if args.format != "auto":
        return args.format
    suffix = Path(args.state).suffix.lower()
    if suffix == ".toml":
        return "case"
    if suffix == ".npz":
        return "checkpoint"
    from demstep.io.formats import detect_format

    return detect_format(args.state)


def _box(args, dim=None):
    if args.box is None:
        return None
    if len(args.box) not in (4, 6):
        raise InputError(f"box: expected 4 (2D) or 6 (3D) numbers lo hi per axis, got {len(args.box)}")
    return np.array(args.box).reshape(-1, 2)


def _periodic_axes(text):
    if text is None:
        return None
    axes = [a.strip() for a in text.split(",") if a.strip()]
    bad = [a for a in axes if a not in ("x", "y", "z")]
    if bad or not axes:
        raise InputError(f"periodic: expected axes among x, y, z separated by commas, got {text!r}")
    return "".join(axes)


def load_input(args):
    """The AnalysisInput for the command line (every check before any work)."""
    from demstep import analysis_input as ti

    if args.mode_vtk:
        _check_output_path("mode-vtk", args.mode_vtk, (".vtu",))
    if args.plot:
        _check_output_path("plot", args.plot, PLOT_FORMATS)
    if (args.state is None) == (args.lattice is None):
        raise InputError("give either a FILE or --lattice NAME (exactly one)")
    damping = _damping(args)
    if args.lattice is not None:
        from demstep.packings import LATTICE_NAMES, lattice

        if args.lattice not in LATTICE_NAMES:
            raise InputError(f"lattice: unknown lattice {args.lattice!r}; choose one of "
                             f"{', '.join(LATTICE_NAMES)}")
        if args.periodic not in (None, "lattice"):
            raise InputError("periodic: with --lattice, give --periodic without axes")
        if args.wall or args.box or args.mesh:
            raise InputError("wall: --wall, --mesh and --box apply to files, not to --lattice")
        if args.lammps_model is not None:
            raise InputError("lammps-model: applies to particle files (a LAMMPS dump or data "
                             "file), not to --lattice")
        _check_source_options(args, "lattice")
        lat = lattice(args.lattice, args.radius)
        check_memory(len(lat.basis) * args.size ** lat.dim, args.max_memory,
                     f"the {args.lattice} lattice of size {args.size}", args.low_memory)
        model = _model(args, "demstep")
        density = DEFAULT_DENSITY if args.density is None else args.density
        return ti.from_lattice(args.lattice, args.size, args.radius, density, model,
                               periodic=args.periodic is not None, contact_tol=args.contact_tol,
                               damping=damping, impact_velocity=args.impact_velocity)
    path = Path(args.state)
    try:
        path.stat()
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except OSError as exc:  # e.g. a name too long (Path.exists raises it)
        raise InputError(f"{path}: cannot read ({exc.strerror or type(exc).__name__})") from None
    if path.is_dir():
        raise InputError(f"{path}: is a folder, expected a file")
    fmt = _file_format(args)
    _check_source_options(args, fmt)
    if fmt in ("case", "checkpoint"):
        given = [o for o, v in (*(("--" + opt, getattr(args, opt)) for opt in _law_options()),
                                ("--materials", args.materials),
                                ("--restitution", args.restitution),
                                ("--model", args.model), ("--box", args.box),
                                ("--periodic", args.periodic), ("--density", args.density),
                                ("--lammps-model", args.lammps_model))
                 + tuple(("--" + name.replace("_", "-"), getattr(args, name))
                         for name in ti.ROLLING_OPTIONS)
                 if v is not None] + (["--wall"] if args.wall else []) \
            + (["--mesh"] if args.mesh else []) \
            + (["--gamma-n/--gamma-t"] if args.gamma_n or args.gamma_t else []) \
            + (["--viscous/--rayleigh"] if args.viscous or args.rayleigh else [])
        if given:
            raise InputError(f"{given[0]}: a {fmt} file brings its own contact law, walls, box "
                             f"and damping; this option does not apply")
        if fmt == "case":
            return ti.from_case(path, args.stage, args.contact_tol, args.impact_velocity)
        _check_run_position(path, args.case)
        return ti.from_checkpoint(path, args.case, args.impact_velocity)
    check_memory(_estimate_rows(path), args.max_memory, f"{path}", args.low_memory)
    if args.lammps_model is not None:
        return _load_lammps_model(args, path, fmt, damping)
    if args.density is not None:
        from demstep.case.build import mass_and_density
        from demstep.io.formats import read_particle_file

        if read_particle_file(path, fmt, args.snapshot).m is not None:
            raise mass_and_density(path, "density", args.density)
    model = _model(args, "liggghts" if fmt == "liggghts" else "demstep")
    density = args.density
    if density is None and not (model.model == "hertz" and model.materials
                                and all(m.density is not None for m in model.materials.values())):
        density = DEFAULT_DENSITY
    return ti.from_file(path, model, fmt, density, _box(args), _periodic_axes(args.periodic),
                        args.wall, args.contact_tol, damping, args.impact_velocity,
                        args.snapshot, [ti.parse_mesh(spec) for spec in args.mesh])


def _check_run_position(path, case_path):
    """The run state beside a checkpoint read with the number of stages of its case
    (:func:`demstep.runner.read_state`: the stage must be one of them, or their end),
    before :func:`demstep.analysis_input.from_checkpoint` applies the stages that had
    started. (The case as from_checkpoint finds it; a missing one it reports.)"""
    from demstep.case import load_case
    from demstep.runner import find_checkpoint, read_state

    checkpoint = find_checkpoint(path)
    case_file = Path(case_path) if case_path is not None else \
        checkpoint.resolve().parent.parent / "case.toml"
    if case_file.is_file():
        read_state(checkpoint, key="checkpoint", stages=len(load_case(case_file).stages))


#: options that apply to one kind of input only: (option, attribute, default, formats)
SOURCE_OPTIONS = (("--snapshot", "snapshot", -1, ("liggghts",)),
                  ("--stage", "stage", 1, ("case",)),
                  ("--case", "case", None, ("checkpoint",)))


def _check_source_options(args, fmt: str):
    """An option of another kind of input given (``fmt``: the input's format, or
    "lattice"): one line naming it, instead of ignoring it."""
    for option, name, default, formats in SOURCE_OPTIONS:
        value = getattr(args, name)
        if value != default and fmt not in formats:
            raise InputError(f"{option[2:]}: applies to {' or '.join(formats)} files, not to "
                             f"a {fmt} input, got {value!r}")


def _estimate_rows(path: Path) -> int:
    """The number of lines of a text file (an upper bound on its particles), counted
    without reading it into memory; a file that is not text (a NUL byte, a line
    without end) is refused where that is found, before it is parsed."""
    from demstep.io.textfile import count_lines

    return count_lines(path)


# ----------------------------------------------------------------------- command
def _load_lammps_model(args, path: Path, fmt: str, damping):
    """A particle file with LAMMPS' pair granular contacts (``--lammps-model``): the law
    options of demstep's own models do not apply."""
    from demstep import analysis_input as ti
    from demstep.integrations.lammps_model import GranularModel

    given = [o for o, v in (*(("--" + opt, getattr(args, opt)) for opt in _law_options()),
                            ("--model", args.model), ("--materials", args.materials),
                            ("--restitution", args.restitution),
                            ("--restitution-t", args.restitution_t),
                            ("--convention", args.convention), ("--overlap", args.overlap))
             + tuple(("--" + name.replace("_", "-"), getattr(args, name))
                     for name in ti.ROLLING_OPTIONS)
             if v is not None] + (["--mesh"] if args.mesh else []) \
        + (["--gamma-n/--gamma-t"] if args.gamma_n or args.gamma_t else []) \
        + (["--viscous/--rayleigh"] if args.viscous or args.rayleigh else [])
    if given:
        raise InputError(f"{given[0]}: --lammps-model gives the contact law and its damping; "
                         f"this option does not apply")
    model = GranularModel.parse(args.lammps_model)
    return ti.from_file(path, None, fmt, args.density, _box(args), _periodic_axes(args.periodic),
                        args.wall, damping=damping, snapshot=args.snapshot, lammps_model=model)


def cmd_dt(args) -> int:
    if args.paper_table:
        if args.state is not None or args.lattice is not None:
            given = args.state if args.state is not None else f"--lattice {args.lattice}"
            raise InputError("paper-table: reproduces the paper's tables and takes no input, "
                             f"got {given}")
        from demstep.timestep.paper_table import format_table, paper_table, table_json

        rows = paper_table()
        _print(json.dumps(table_json(rows), indent=2) if args.json else format_table(rows))
        return 0
    from demstep.timestep import estimate_time_steps

    if args.top < 0:
        raise InputError(f"top: must be >= 0, got {args.top}")
    if args.exact_tol is not None:
        # the loosest residual that certifies (demstep.timestep.eigen.MAX_CERTIFIED_TOL)
        from demstep.timestep.eigen import check_certified_tol

        check_certified_tol("exact-tol", args.exact_tol)
    methods = None if args.methods is None else [m.strip() for m in args.methods.split(",")]
    if args.mode_vtk and args.low_memory:
        raise InputError("mode-vtk: the critical mode comes from the exact solver's basis, "
                         "which --low-memory does without")
    if args.mode_vtk and methods is not None and not {"exact", "exact-undamped"} & set(methods):
        raise InputError(f"mode-vtk: the critical mode comes from the exact method, not in "
                         f"--methods {args.methods}")
    data = load_input(args)
    rotation = data.rotation if args.rotation is None else (args.rotation and data.rotation)
    if args.rotation and not data.rotation:
        raise InputError("rotation: the run locks rotation; --rotation does not apply")
    report = estimate_time_steps(data.particles, data.contacts, rotation=rotation,
                                 mass_split=args.mass_split, damping=data.damping,
                                 methods=methods, lattice=data.lattice, density=data.density,
                                 materials=data.materials, bodies=data.bodies,
                                 exact_tol=args.exact_tol, seed=args.seed,
                                 low_memory=args.low_memory,
                                 **({} if args.failure is None else {"failure": args.failure}))
    report.notes[:0] = data.notes
    danger = critical_mode_report(report, data, args.top)
    if args.json:
        out = report.to_json()
        out["critical_mode"] = danger
        _print(json.dumps(out))
    else:
        _print(format_report(report, danger))
    if args.mode_vtk and report.exact is not None:
        write_mode_vtk(args.mode_vtk, data, report)
    if args.plot:
        from demstep.plotting import plot_estimates

        plot_estimates(report, args.plot)
    return 0


def _print(text: str):
    print(text)
    sys.stdout.flush()


def largest_first(values: np.ndarray, top: int) -> np.ndarray:
    """Indices of the ``top`` largest of ``values``, largest first, ties in index order:
    the first ``top`` of a stable argsort of -values, in O(n) (a million particles' and
    six million contacts' shares: 1.1 s sorted)."""
    n = len(values)
    if top >= n:
        return np.argsort(-values, kind="stable")
    if top <= 0:
        return np.zeros(0, dtype=np.int64)
    threshold = np.partition(values, n - top)[n - top]  # the top-th largest
    above = np.flatnonzero(values > threshold)
    ties = np.flatnonzero(values == threshold)[:top - len(above)]
    picked = np.concatenate((above, ties))
    return picked[np.argsort(-values[picked], kind="stable")]


def critical_mode_report(report, data, top: int) -> dict | None:
    """Where the danger is: the particles carrying most of the critical mode (share of
    its kinetic energy, translation and rotation) and the contacts carrying most of its
    strain energy; how far the mode spreads: its participation number 1 / sum(share^2)
    over the particles (1: one particle carries it all; N: all carry it alike) and the
    share the listed particles carry together."""
    if report.exact is None or report.exact.mode is None:
        return None
    op = report.exact.operator
    trans, rot, contact_share = op.mode_shares(report.exact.mode)
    share = trans + rot
    p = data.particles
    order = largest_first(share, top)
    counts = data.contacts.count_per_particle(p.n)
    if data.bodies is not None and data.bodies.n:  # owners: free spheres, then bodies
        from demstep.timestep.clumps import owners

        owner, n_free, _ = owners(p.n, data.bodies)
        free = np.flatnonzero(data.bodies.sphere_body < 0)
        owner_counts = np.bincount(owner, weights=counts, minlength=len(share))
        particles = []
        for k in order:
            if k < n_free:
                s_index = int(free[k])
                entry = {"index": data.particle_id(s_index), "radius": float(p.r[s_index]),
                         "mass": float(p.m[s_index])}
            else:
                b = int(k - n_free)
                entry = {"index": None, "body": b, "radius": None,
                         "mass": float(data.bodies.mass[b])}
            entry.update(share=float(share[k]), translation=float(trans[k]),
                         rotation=float(rot[k]), contacts=int(owner_counts[k]))
            particles.append(entry)
    else:
        particles = [{"index": data.particle_id(k), "radius": float(p.r[k]),
                      "mass": float(p.m[k]),
                      "share": float(share[k]), "translation": float(trans[k]),
                      "rotation": float(rot[k]), "contacts": int(counts[k])} for k in order]
    c = data.contacts
    corder = largest_first(contact_share, top)
    contacts = [{"i": data.particle_id(c.i[k]),
                 "j": data.particle_id(c.j[k]) if c.j[k] >= 0 else None,
                 "wall": int(c.wall[k]) if c.j[k] < 0 else None, "k_n": float(c.k_n[k]),
                 "k_t": float(c.k_s[k]), "c_n": float(c.c_n[k]), "c_t": float(c.c_t[k]),
                 "k_r": float(c.k_r[k]), "k_w": float(c.k_w[k]),
                 "share": float(contact_share[k])} for k in corder]
    squares = float(np.dot(share, share))
    return {"sigma": report.exact.sigma, "lambda_undamped": report.exact.lambda_undamped,
            "lambda_undamped_tol": report.exact.undamped_tol,
            "participation": float(share.sum()) ** 2 / squares if squares > 0 else 0.0,
            "listed_share": float(share[order].sum()),
            "particles": particles, "contacts": contacts}


def format_report(report, danger=None) -> str:
    rot = "with rotation" if report.rotation else "translation only"
    lines = [f"{report.dim}D assembly: {report.n_particles} particles, {report.n_contacts} "
             f"contacts, {rot}; m_min = {report.m_min:.6g}, K_max = {report.k_max:.6g}"]
    lines += [f"  {n}" for n in report.notes]
    if report.damped:
        parts = []
        if report.dashpots:
            parts.append("contact dashpots")
        if report.damping.mass:
            parts.append(f"global viscous a1 = {report.damping.mass:g}")
        if report.damping.stiffness:
            parts.append(f"stiffness-proportional a2 = {report.damping.stiffness:g}")
        lines.append("damping: " + ", ".join(parts) + " -- every estimate is the damped one "
                     "(the engine's scheme, damping on the half-step velocity)")
    lines.append(f"{'method':<17}{'dt':>14}{'alpha':>10}  {'guarantee':<14}"
                 "conservative vs exact")
    for e in report.estimates:
        cons = "-" if e.conservative is None else ("yes" if e.conservative else "NO")
        tag = "  (material rule)" if e.kind == "rule" else ""
        lines.append(f"{e.method:<17}{e.dt:>14.6g}{e.alpha:>10.4f}  "
                     f"{_guarantee_tag(e.guarantee):<14}{cons}{tag}")
    lines.append("alpha = dt / sqrt(m_min / K_max); exact: the critical step of this state"
                 + (" with its damping" if report.damped else "") + ", from the top "
                 "eigenvalue the solver found")
    certified = next((e for e in report.estimates if e.method == "certified"), None)
    if certified is not None and certified.guarantee is not None:
        lines.append(f"certified: {certified.guarantee.describe()}")
        check = report.exact.check if report.exact is not None else None
        if check is not None and not check.reached:
            lines.append("  the random-start check found a larger eigenvalue than the exact "
                         "solve: 'exact' is above the critical step here; trust 'certified'")
    if danger and danger["particles"]:
        lines.append("")
        lines.append("Where the danger is -- the particles carrying most of the critical mode:")
        lines.append(f"  (it spreads over about {danger['participation']:.3g} particles; those "
                     f"listed carry {100 * danger['listed_share']:.3g} % of it)")
        lines.append(f"  {'particle':>9}{'radius':>12}{'mass':>12}{'contacts':>9}{'share':>8}"
                     f"{'transl.':>9}{'rotat.':>8}")
        for q in danger["particles"]:
            label = q["index"] if q.get("index") is not None else f"body {q['body']}"
            radius = f"{q['radius']:>12.4g}" if q.get("radius") is not None else f"{'-':>12}"
            lines.append(f"  {label:>9}{radius}{q['mass']:>12.4g}"
                         f"{q['contacts']:>9}{_share(q['share'])}{_share(q['translation'], 9)}"
                         f"{_share(q['rotation'])}")
        lines.append("  and the contacts carrying most of its strain energy:")
        rolling = any(q.get("k_r") or q.get("k_w") for q in danger["contacts"])
        roll_head = f"{'k_r':>11}{'k_w':>11}" if rolling else ""
        lines.append(f"  {'i':>9}{'j / wall':>10}{'k_n':>12}{'k_t':>12}{'c_n':>11}{'c_t':>11}"
                     f"{roll_head}{'share':>8}")
        for q in danger["contacts"]:
            other = str(q["j"]) if q["j"] is not None else f"wall {q['wall']}"
            roll = f"{q['k_r']:>11.4g}{q['k_w']:>11.4g}" if rolling else ""
            lines.append(f"  {q['i']:>9}{other:>10}{q['k_n']:>12.4g}{q['k_t']:>12.4g}"
                         f"{q['c_n']:>11.4g}{q['c_t']:>11.4g}{roll}{_share(q['share'])}")
    return "\n".join(lines)


def _guarantee_tag(g) -> str:
    """The guarantee column: proof, p >= 1-1e-09, lower bound, estimate or rule."""
    if g is None:
        return "-"
    if g.kind == "probability":
        return f"p >= 1-{g.failure:.0e}"
    return {"lower-bound": "lower bound"}.get(g.kind, g.kind)


def _share(value: float, width: int = 8) -> str:
    """A share in [0, 1], three decimals, or three digits when it is below 0.001 (a mode
    spread over many particles)."""
    if value == 0.0 or value >= 1e-3:
        return f"{value:>{width}.3f}"
    return f"{value:>{width}.{max(0, width - 7)}e}"  # (at least one space before it)


def write_mode_vtk(path, data, report) -> Path:
    """The critical mode per particle as VTK point data: ``translation`` (vector [L],
    the mode shape, normalised to a largest displacement of one), ``rotation`` (vector,
    rad, same scale), ``share`` (of the mode's kinetic energy), ``radius``, ``mass``."""
    import meshio

    from demstep.io.vtk import write_mesh

    op = report.exact.operator
    u = op.displacement(report.exact.mode)
    dim = data.particles.dim
    trans3 = np.zeros((data.particles.n, 3))
    trans3[:, :dim] = u[:, :dim]
    rot3 = np.zeros((data.particles.n, 3))
    if u.shape[1] > dim:
        if dim == 2:
            rot3[:, 2] = u[:, 2]
        else:
            rot3[:] = u[:, 3:6]
    scale = np.abs(trans3).max() or 1.0
    t_share, r_share, _ = op.mode_shares(report.exact.mode)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    x3 = np.zeros((data.particles.n, 3))
    x3[:, :dim] = data.particles.x
    mesh = meshio.Mesh(x3, [("vertex", np.arange(data.particles.n).reshape(-1, 1))],
                       point_data={"radius": data.particles.r, "mass": data.particles.m,
                                   "translation": trans3 / scale, "rotation": rot3 / scale,
                                   "share": t_share + r_share,
                                   "id": (np.arange(data.particles.n, dtype=np.int64)
                                          if data.ids is None else np.asarray(data.ids))})
    return write_mesh(path, mesh)
