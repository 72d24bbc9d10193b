"""The certified 'auto' step in a hopper bounded by a mesh and fed by insertion.

    python validation/auto_mesh_hopper.py [--out FILE] [--every SECONDS]

Runs ``examples/hopper_feed.toml`` (a square STL hopper of steel, Hertz beads inserted
at 0.15 kg/s for 0.4 s, an outlet under it) twice: with the step the example fixes
(2e-5 s) and with ``timestep.mode = "auto"`` (safety 0.8, the defaults). Every
``--every`` seconds of the auto run it computes the exact critical step of the contacts
closed then (pairs and mesh contacts, ``Simulation.critical_dt``) and of the same
contacts without the mesh ones, and records the step taken, the particles, the mesh
contacts and the estimates. Written to ``validation/results/auto_mesh_hopper.json``,
summarised in ``docs/meshes.md``.

What it checks: the step taken never lies above the critical step of the contacts
closed (with the meshes); how far below it lies; how far above it the step certified
without the mesh contacts would lie; what 'auto' costs beside the fixed step.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "src"))

from demstep.case import build_simulation, case_from_text  # noqa: E402
from demstep.engine import Simulation, TimeStep  # noqa: E402
from demstep.particles import Particles  # noqa: E402

CASE = ROOT / "examples" / "hopper_feed.toml"


def simulation(mode: str):
    """The example's Simulation, with its fixed step or in 'auto' mode."""
    text = CASE.read_text()
    if mode == "auto":
        text = re.sub(r"\[timestep\]\ndt = [^\n]*\n", '[timestep]\nmode = "auto"\n', text)
    case = case_from_text(text, base_dir=CASE.parent, source=str(CASE))
    return case, build_simulation(case)


def without_meshes(sim) -> float | None:
    """The exact critical step of the pairs closed now, the meshes left out."""
    p = Particles.from_density(sim.x, sim.r, 2500.0)
    bare = Simulation(p, sim.law, timestep=TimeStep.fixed(1e-12))
    bare.run(steps=1)
    return bare.critical_dt("exact")


def run(mode: str, every: float, samples: list | None):
    case, sim = simulation(mode)
    duration = sum(stage.duration for stage in case.stages)
    t0 = time.perf_counter()
    sampling = 0.0
    while sim.time < duration - 1e-12:
        sim.run(duration=min(every, duration - sim.time))
        if samples is None or not len(sim.r):
            continue
        s0 = time.perf_counter()
        crit = sim.critical_dt("exact")
        bare = without_meshes(sim)
        sampling += time.perf_counter() - s0
        samples.append(dict(
            t=round(sim.time, 6), particles=int(len(sim.r)), dt=sim.dt, critical=crit,
            critical_without_meshes=bare,
            mesh_contacts=int(sim.meshes.contacts.sum()),
            estimates=sim.auto.n_estimates, solves=sim.auto.n_solves,
            extensions=sim.auto.n_extensions))
        print(samples[-1], flush=True)
    wall = time.perf_counter() - t0 - sampling
    return dict(mode=mode, steps=int(sim.step), wall_s=round(wall, 2),
                inserted=int(sim.feed.inserters[0].inserted) if sim.feed.inserters else None)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "validation" / "results" /
                                         "auto_mesh_hopper.json"))
    ap.add_argument("--every", type=float, default=0.02)
    args = ap.parse_args(argv)
    samples: list = []
    auto = run("auto", args.every, samples)
    fixed = run("fixed", args.every, None)
    touching = [s for s in samples if s["critical"]]
    ratio = [s["dt"] / s["critical"] for s in touching]
    above = [s["critical_without_meshes"] / s["critical"] for s in touching
             if s["critical_without_meshes"] and s["mesh_contacts"]]
    summary = dict(
        samples=len(touching), dt_over_critical_max=max(ratio), dt_over_critical_min=min(ratio),
        dt_over_critical_median=float(np.median(ratio)),
        without_meshes_over_critical_max=max(above) if above else None,
        without_meshes_over_critical_median=float(np.median(above)) if above else None,
        auto=auto, fixed=fixed)
    print(json.dumps(summary, indent=2))
    Path(args.out).write_text(json.dumps(dict(summary=summary, samples=samples), indent=1))
    return 0 if max(ratio) <= 1.0 else 1


if __name__ == "__main__":
    sys.exit(main())
