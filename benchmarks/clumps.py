"""Cost of clumps against free spheres: gravity settling in a box, the same member
spheres either glued into 4-sphere clumps or free (issue target: a member sphere of a
clump costs at most 1.5 times a free sphere in the same packing).

Both runs use the same spheres (radius 0.5, density 2500, linear springs k = 1e6,
restitution 0.5, friction 0.5), the same box and dt = 0.1 sqrt(m_sphere / k); clumps
are tetrahedra of four members 0.8 diameters apart, randomly oriented on a grid, the
free case the same tetrahedral groups of spheres 1.02 diameters apart (not touching). Each case runs in a fresh
subprocess (its own threads and memory); times are the medians of ``--repeat``
interleaved runs of ``--steps`` steps after ``--warmup`` steps. With ``--auto`` a third
case, the clumps with the 'auto' time step (safety 0.8), whose certificate is checked
at every step (the clumps' drift, see demstep.timestep.certificate): the cost per step
of that control against the fixed step, and its number of estimates.

    python benchmarks/clumps.py [--bodies 25000] [--steps 500] [--repeat 3] [--threads 1]
                                [--auto] [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys

CASE = r"""
import json, math, sys, time
import numpy as np
import numba
from demstep.clumps import ClumpTemplate, expand, place, random_quaternions
from demstep.contact.laws import LinearSpring
from demstep.engine import Simulation, TimeStep
from demstep.particles import Particles
from demstep.walls import box_walls

mode, n_bodies, warmup, steps, threads = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
numba.set_num_threads(threads)
r, rho, k = 0.5, 2500.0, 1.0e6
# clumps: members 0.8 diameters apart; free spheres: the same tetrahedra, touching,
# then spread 2 % about their centres (not overlapping)
d = (0.8 if mode.startswith("clumps") else 1.0) * 2 * r
tetra = ClumpTemplate("tetra", np.array([[0, 0, 0], [d, 0, 0], [d / 2, d * math.sqrt(3) / 2, 0],
                                         [d / 2, d / (2 * math.sqrt(3)), d * math.sqrt(2 / 3)]]), np.full(4, r))
nz = 6
nxy = max(1, round(math.sqrt(n_bodies / nz)))
spacing = 2.4
g = np.stack(np.meshgrid(np.arange(nxy), np.arange(nxy), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
pos = (g + 0.5) * spacing
cs = place([tetra], np.zeros(len(pos), dtype=np.int64), pos, random_quaternions(len(pos), np.random.default_rng(1)), rho)
walls = box_walls([-0.5, -0.5, -0.5], [nxy * spacing + 0.5, nxy * spacing + 0.5, nz * spacing + 20.0])
law = LinearSpring(k_n=k, k_s=k, mu=0.5, restitution=0.5)
m_sphere = rho * 4 / 3 * math.pi * r ** 3
dt = 0.1 * math.sqrt(m_sphere / k)
common = dict(walls=walls, gravity=[0, 0, -9.81], timestep=TimeStep.fixed(dt))
if mode == "clumps-auto":  # (the motion limit holds the free fall at 0.1 r per step)
    common.update(timestep=TimeStep.auto(safety=0.8))
if mode.startswith("clumps"):
    sim = Simulation(None, law, clumps=cs, **common)
else:
    xm, rm, body = expand(cs)[:3]
    xm = cs.x[body] + 1.02 * (xm - cs.x[body])
    sim = Simulation(Particles.from_density(xm, rm, rho), law, **common)
sim.run(steps=warmup)
estimates = getattr(sim, "n_dt_estimates", 0)
t = time.perf_counter()
sim.run(steps=steps)
wall = time.perf_counter() - t
print(json.dumps({"mode": mode, "spheres": len(sim.r), "bodies": int(sim.bodies.n), "threads": threads,
                  "contacts": sim.n_contacts, "s_per_step": wall / steps, "dt": sim.dt,
                  "estimates": getattr(sim, "n_dt_estimates", 0) - estimates,
                  "ns_per_sphere_step": 1e9 * wall / steps / len(sim.r)}))
"""


def run(mode, bodies, warmup, steps, threads):
    out = subprocess.run([sys.executable, "-c", CASE, mode, str(bodies), str(warmup), str(steps),
                          str(threads)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bodies", type=int, default=25000)
    ap.add_argument("--warmup", type=int, default=200)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--auto", action="store_true",
                    help="also the clumps with the 'auto' time step")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    results = {"clumps": [], "spheres": []}
    if args.auto:
        results["clumps-auto"] = []
    for _ in range(args.repeat):  # interleaved
        for mode in results:
            results[mode].append(run(mode, args.bodies, args.warmup, args.steps, args.threads))
    summary = {mode: {"spheres": rows[0]["spheres"], "bodies": rows[0]["bodies"],
                      "contacts": rows[-1]["contacts"], "dt": rows[-1]["dt"],
                      "estimates": [r["estimates"] for r in rows],
                      "ns_per_sphere_step": statistics.median(r["ns_per_sphere_step"] for r in rows),
                      "runs": [r["ns_per_sphere_step"] for r in rows]}
               for mode, rows in results.items()}
    ratio = summary["clumps"]["ns_per_sphere_step"] / summary["spheres"]["ns_per_sphere_step"]
    auto = (summary["clumps-auto"]["ns_per_sphere_step"] / summary["clumps"]["ns_per_sphere_step"]
            if args.auto else None)
    if args.json:
        print(json.dumps({"benchmark": "clumps", "threads": args.threads, "summary": summary,
                          "ratio_clump_member_to_free_sphere": ratio,
                          "ratio_auto_to_fixed_step": auto}))
        return
    for mode, s in summary.items():
        print(f"{mode:8s} {s['spheres']:>7d} spheres {s['bodies']:>6d} bodies {s['contacts']:>7d} "
              f"contacts  {s['ns_per_sphere_step']:8.1f} ns per sphere-step (runs "
              f"{', '.join(f'{v:.1f}' for v in s['runs'])}; dt {s['dt']:.3g} s, estimates "
              f"{s['estimates']})")
    print(f"a clump member costs {ratio:.2f} x a free sphere (target <= 1.5)")
    if auto is not None:
        print(f"a step of the clumps with the 'auto' time step costs {auto:.2f} x a fixed one")


if __name__ == "__main__":
    main()
