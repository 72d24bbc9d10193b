"""The cost of the certified 'auto' time step during a run (issue target: at most 5 % of
the run time at 1e5 particles with the exact method re-evaluated every 500 steps).

The peer problems of ``peers.py`` (``dense``: a pre-compressed FCC block in a box;
``settle``: spheres falling onto a floor, contacts forming all the time) run with
``TimeStep.auto(safety=0.8, method="exact", every=500)``; the time spent choosing dt
(the estimates, warm-started from the last critical mode) and checking that every
closed contact was covered is measured against the whole run. One process per case.
An estimate solves only where the solve can change dt (no kept certificate or cheaper
bound decides it); ``--solve-always`` makes every estimate an exact solve, the cost of
a run whose dt follows the exact step all along.

    python benchmarks/auto_cost.py [--n 100000] [--steps 2000] [--threads 1] [--repeat 3]
                                   [--solve-always] [--json]

With ``--repeat`` R the problems run R times, interleaved (dense, settle, dense, ...);
each run is printed and, per problem, the median of the fractions.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent

CASE = r"""
import json, sys, time
import numpy as np
sys.path.insert(0, sys.argv[5])
import demstep  # before numba.set_num_threads: demstep chooses the threading layer
import numba
from peers import demstep_simulation, make_problem
from demstep.engine import TimeStep

problem, n, steps, threads = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
numba.set_num_threads(threads)
x, spec = make_problem(problem, n)
sim = demstep_simulation(x, spec, TimeStep.auto(safety=0.8, method="exact", every=500))
if sys.argv[6] == "1":  # every estimate an exact solve: no kept certificate, no element bound
    sim.auto.AUTO_REFRESH_RTOL = -1.0
    sim.auto.estimate_cannot_change_dt = lambda *a, **k: False
spent = {"choose_dt": 0.0, "covered": 0.0, "estimates": 0, "checks": 0}  # checks: coverage and extensions
choose, still = sim.auto.propose_dt, sim.auto.accept

def timed(func, key, count):
    def wrapper(*a, **k):
        t = time.perf_counter(); out = func(*a, **k)
        spent[key] += time.perf_counter() - t; spent[count] += 1
        return out
    return wrapper

sim.auto.propose_dt = timed(choose, "choose_dt", "estimates")
sim.auto.accept = timed(still, "covered", "checks")
sim.run(steps=20)  # compile / load caches, first estimate
for key in ("choose_dt", "covered", "estimates", "checks"):
    spent[key] = 0
# kernels first used after the warm-up (the settling run's first contacts close later)
# are loaded from numba's cache inside the timed run: a once-per-process cost, reported
spent["kernel_loads_s"], spent["kernel_loads"] = 0.0, 0
from numba.core import caching
caching.Cache.load_overload = timed(caching.Cache.load_overload, "kernel_loads_s", "kernel_loads")
t = time.perf_counter()
sim.run(steps=steps)
total = time.perf_counter() - t
print(json.dumps({"problem": problem, "n": len(x), "steps": steps, "threads": threads,
                  "total_s": total, **spent,
                  "fraction": (spent["choose_dt"] + spent["covered"]) / total,
                  "dt": sim.dt, "dt_estimate": sim.dt_estimate, "contacts": sim.n_contacts,
                  "refreshes": getattr(sim, "n_dt_refreshes", 0),
                  "extensions": getattr(sim, "n_dt_extensions", 0),
                  "solves": (getattr(sim, "n_dt_solves", 0)  # None: code before the counter
                             if hasattr(sim, "_element_estimate") else None),
                  "element": getattr(sim, "n_dt_element", 0)}))
"""


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--problems", default="dense,settle")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--solve-always", action="store_true",
                    help="an exact solve at every estimate (the shortcuts off: no kept "
                         "certificate, no element bound): the cost where dt is the exact "
                         "step's all along")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    rows = []
    problems = args.problems.split(",")
    for problem in problems * max(1, args.repeat):
        out = subprocess.run([sys.executable, "-c", CASE, problem, str(args.n), str(args.steps),
                              str(args.threads), str(HERE), str(int(args.solve_always))],
                             capture_output=True, text=True,
                             check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        r = rows[-1]
        if not args.json:
            print(f"{problem:7s} N={r['n']} {r['steps']} steps: run {r['total_s']:.1f} s, estimates "
                  f"{r['choose_dt']:.2f} s ({r['estimates']}), coverage checks {r['covered']:.2f} s "
                  f"({r['checks']}): {100 * r['fraction']:.1f} % of the run; exact solves "
                  f"{r['solves'] if r['solves'] is not None else '?'}, element bounds enough "
                  f"{r['element']}, certificates kept "
                  f"{r['refreshes']}, extended {r['extensions']}; kernels loaded from numba's "
                  f"cache in the run {r['kernel_loads_s']:.2f} s ({r['kernel_loads']})",
                  flush=True)
    medians = {problem: statistics.median(r["fraction"] for r in rows if r["problem"] == problem)
               for problem in problems}
    if args.json:
        print(json.dumps({"benchmark": "auto_cost", "results": rows, "median_fraction": medians}))
    elif args.repeat > 1:
        for problem, fraction in medians.items():
            print(f"{problem:7s} median of {args.repeat} runs: {100 * fraction:.1f} % of the run")


if __name__ == "__main__":
    main()
