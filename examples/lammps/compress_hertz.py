"""A Hertz packing compressed in LAMMPS: a time step stable when the packing jams is not
stable once it is squeezed further, and demstep's certificate keeps the run stable.

LAMMPS (``pair_style granular``, Hertz with Mindlin tangential springs and Tsuji
dashpots) packs 512 spheres in a periodic box by compressing it (``fix deform``) to
jamming. There demstep certifies the critical step; then the box is squeezed on by 8 %
(volume), the overlaps grow, the Hertz contacts stiffen and the critical step falls:

* run A keeps 0.95 x the step certified at jamming: it becomes unstable (its kinetic
  energy grows by orders of magnitude);
* run B lets demstep certify the step every ``--every`` steps and set it to 0.8 x the
  certified one (:class:`demstep.integrations.lammps.LammpsCertifier`): it stays
  stable, and the log says when and why the step changed.

    python examples/lammps/compress_hertz.py [--every 200] [--quiet]

Needs Debian's LAMMPS: apt-get install lammps python3-lammps liblammps-dev
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from demstep.integrations.lammps import LammpsCertifier, load_lammps

#: the pair_coeff text of the run (and of the certificate)
MODEL = "hertz/material 1e7 0.5 0.3 tangential mindlin NULL 1.0 10.0 damping tsuji"
#: spheres on a jittered simple-cubic lattice of CELLS^3 sites, spacing LATTICE (a solid
#: fraction of about 0.28)
CELLS = 8
LATTICE = 1.25
DENSITY = 2500.0
#: the relative volume the box loses after jamming
SQUEEZE = 0.08


def setup(lammps, quiet: bool):
    """A LAMMPS instance with 512 spheres (radii 0.4-0.6) on a jittered lattice at a solid
    fraction of about 0.28."""
    args = ["-log", "none", "-nocite"] + (["-screen", "none"] if quiet else [])
    lmp = lammps.lammps(cmdargs=args)
    lmp.commands_string(f"""
units si
atom_style sphere
atom_modify map array
boundary p p p
comm_modify vel yes
neighbor 0.1 bin
neigh_modify delay 0 every 1 check yes
lattice sc {LATTICE!r}
region box block 0 {CELLS} 0 {CELLS} 0 {CELLS}
create_box 1 box
create_atoms 1 box
displace_atoms all random 0.1 0.1 0.1 4811 units box
variable dia atom 0.8+0.4*random(0,1,771)
set group all diameter v_dia
set group all density {DENSITY!r}
pair_style granular
pair_coeff * * hertz/material 1e7 0.9 0.3 tangential mindlin NULL 1.0 0.0 damping tsuji
fix integ all nve/sphere
timestep 2e-4
thermo 1000
thermo_style custom step atoms ke vol
""")
    return lmp


def solid_fraction(lmp) -> float:
    r = np.ctypeslib.as_array(lmp.gather_atoms("radius", 1, 1))
    lo, hi = lmp.extract_box()[:2]
    return float((4.0 / 3.0 * math.pi * r**3).sum() / np.prod(np.subtract(hi, lo)))


def squeeze(lmp, fraction: float, steps: int):
    """Scale the box to reach solid fraction ``fraction`` over ``steps`` steps."""
    scale = (solid_fraction(lmp) / fraction) ** (1.0 / 3.0)
    lmp.command(f"fix squeeze all deform 1 x scale {scale!r} y scale {scale!r} "
                f"z scale {scale!r} remap x")
    lmp.command(f"run {steps}")
    lmp.command("unfix squeeze")


def jammed(lammps, quiet: bool):
    lmp = setup(lammps, quiet)
    squeeze(lmp, 0.64, 20000)  # frictionless (mu = 0), e = 0.9: packs densely
    lmp.command(f"pair_coeff * * {MODEL}")
    lmp.command("run 5000")  # relaxed with the run's law
    return lmp


def kinetic_energy(lmp) -> float:
    v = np.ctypeslib.as_array(lmp.gather_atoms("v", 1, 3)).reshape(-1, 3)
    m = np.ctypeslib.as_array(lmp.gather_atoms("rmass", 1, 1))
    return float(0.5 * (m * (v * v).sum(axis=1)).sum())


def squeezed_run(lmp, certifier, steps: int, every: int, label: str):
    """Squeeze the box by SQUEEZE in volume over ``steps`` steps, ``every`` at a time
    (certifying between parts when ``certifier`` is given); the kinetic energy after
    each part."""
    scale = (1.0 - SQUEEZE) ** (1.0 / 3.0)
    lmp.command(f"fix squeeze all deform 1 x scale {scale!r} y scale {scale!r} "
                f"z scale {scale!r} remap x")
    energies = []
    done = 0
    first = int(lmp.extract_global("ntimestep"))
    while done < steps:
        if certifier is not None:
            certifier.apply()
        lmp.command(f"run {every} start {first} stop {first + steps} "
                    f"pre {'yes' if not done else 'no'} post no")
        done += every
        ke = kinetic_energy(lmp)
        energies.append(ke)
        if not math.isfinite(ke) or ke > 1e6 * max(min(energies), 1e-300):
            print(f"{label}: unstable after {done} steps (kinetic energy {ke:.3g} J, "
                  f"{ke / min(energies):.3g} x its smallest)")
            return False, energies
    print(f"{label}: stable over {steps} steps (kinetic energy at most "
          f"{max(energies):.3g} J)")
    return True, energies


def run_from(lammps, restart: str, dt: float, quiet: bool):
    """A LAMMPS instance continuing from ``restart`` with the run's law at step ``dt``."""
    lmp = lammps.lammps(cmdargs=["-log", "none", "-nocite"] + (["-screen", "none"] if quiet else []))
    lmp.commands_string(f"""
read_restart {restart}
comm_modify vel yes
neighbor 0.1 bin
neigh_modify delay 0 every 1 check yes
pair_style granular
pair_coeff * * {MODEL}
fix integ all nve/sphere
timestep {dt!r}
thermo 1000
""")
    return lmp


def part(args) -> int:
    """One part in its own process (a LAMMPS error ends the process: Debian's LAMMPS is
    built without C++ exceptions)."""
    lammps = load_lammps()
    if args.part == "prepare":
        lmp = jammed(lammps, args.quiet)
        cert = LammpsCertifier(lmp, MODEL, safety=1.0).certify()
        lmp.command(f"write_restart {args.restart}")
        print(f"PREPARED {cert.dt!r} {cert.contacts} {solid_fraction(lmp)!r}", flush=True)
        return 0
    lmp = run_from(lammps, args.restart, args.dt, args.quiet)
    if args.part == "fixed":
        stable, _ = squeezed_run(lmp, None, args.steps, args.every,
                                 f"A (fixed step {args.dt:.6g} s)")
    else:
        cert = LammpsCertifier(lmp, MODEL, safety=0.8)
        stable, _ = squeezed_run(lmp, cert, args.steps, args.every, "B (certified step)")
        print(f"B: certified step {cert.history[0].dt:.6g} -> {cert.history[-1].dt:.6g} s, "
              f"{len(cert.history)} certificates of "
              f"{np.mean([c.seconds for c in cert.history]):.3f} s each", flush=True)
    return 0 if stable else 2


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--every", type=int, default=200)
    ap.add_argument("--steps", type=int, default=10000)
    ap.add_argument("--quiet", action="store_true", help="no LAMMPS screen output")
    ap.add_argument("--part", choices=("prepare", "fixed", "certified"), default=None,
                    help=argparse.SUPPRESS)
    ap.add_argument("--restart", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--dt", type=float, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.part is not None:
        return part(args)
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory(prefix="demstep-compress-") as folder:
        restart = f"{folder}/jammed.restart"
        common = [sys.executable, __file__, "--restart", restart, "--steps", str(args.steps),
                  "--every", str(args.every)] + (["--quiet"] if args.quiet else [])
        prep = subprocess.run(common + ["--part", "prepare"], capture_output=True, text=True)
        line = next((x for x in prep.stdout.splitlines() if x.startswith("PREPARED")), None)
        if line is None:
            print(prep.stdout[-2000:], prep.stderr[-2000:])
            return 1
        dt_jammed, contacts, phi = (float(v) for v in line.split()[1:])
        print(f"jammed at solid fraction {phi:.4f}: {int(contacts)} contacts, certified step "
              f"{dt_jammed:.6g} s")
        dt0 = 0.95 * dt_jammed
        results = {}
        for name in ("fixed", "certified"):
            proc = subprocess.run(common + ["--part", name, "--dt", repr(dt0)],
                                  capture_output=True, text=True)
            for x in proc.stdout.splitlines():
                if x.startswith(("A ", "B ", "B:", "demstep:")):
                    print(x)
            error = next((x for x in proc.stdout.splitlines() if x.startswith("ERROR")), None)
            if error:
                print(f"{'A' if name == 'fixed' else 'B'}: LAMMPS stopped: {error}")
            results[name] = proc.returncode == 0
    print("as expected: the fixed step failed, the certified one held" if
          (results["certified"] and not results["fixed"]) else
          f"NOT as expected: fixed step {'held' if results['fixed'] else 'failed'}, certified "
          f"step {'held' if results['certified'] else 'failed'}")
    return 0 if (results["certified"] and not results["fixed"]) else 1


if __name__ == "__main__":
    raise SystemExit(main())
