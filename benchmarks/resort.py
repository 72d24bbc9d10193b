"""What re-sorting during a run buys and costs (``Simulation(sort_every=...)``).

The peer problems of ``peers.py`` run in the lattice order they are generated in and
in a fixed random order (as particles come from another code's file or from an
insertion), each without re-sorting and with ``sort_every`` steps: the first
neighbour-list build sorts a random order; in lattice order the sort finds the
particles in place (what it costs when there is nothing to gain). Each run is its own
process; the cases are interleaved, ``--repeat`` times; medians.

    python benchmarks/resort.py [--problem dense] [--n 100000] [--steps 500]
                                [--sort-every 100] [--repeat 3] [--threads 1]
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
sys.path.insert(0, sys.argv[1])
import demstep  # before numba.set_num_threads: demstep chooses the threading layer
import numba
from peers import demstep_simulation, make_problem
from demstep.engine import TimeStep

problem, n, steps, threads, order, sort_every = (sys.argv[2], int(sys.argv[3]), int(sys.argv[4]),
                                                 int(sys.argv[5]), sys.argv[6], int(sys.argv[7]))
numba.set_num_threads(threads)
x, spec = make_problem(problem, n)
if order == "random":
    x = x[np.random.default_rng(0).permutation(len(x))]
sim = demstep_simulation(x, spec, TimeStep.fixed(spec["dt"]))
sim.ordering.every = sort_every or None
import warnings
warnings.simplefilter("ignore")  # (the random-order warning)
sim.run(steps=20)
t = time.perf_counter()
sim.run(steps=steps)
elapsed = time.perf_counter() - t
print(json.dumps({"rate": len(x) * steps / elapsed, "sorts": sim.ordering.n_sorts,
                  "n": len(x)}))
"""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problem", choices=("dense", "settle"), default="dense")
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--sort-every", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    cases = [(order, sort) for order in ("lattice", "random") for sort in (0, args.sort_every)]
    rates = {case: [] for case in cases}
    for _ in range(args.repeat):
        for order, sort in cases:
            out = subprocess.run(
                [sys.executable, "-c", CASE, str(HERE), args.problem, str(args.n),
                 str(args.steps), str(args.threads), order, str(sort)],
                capture_output=True, text=True, check=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
            rates[(order, sort)].append(r["rate"])
            print(f"  {args.problem} {order:7s} sort_every {sort or 'never':>5}: "
                  f"{r['rate']:.3e} particle-steps/s ({r['sorts']} sorts)", flush=True)
    print(f"{args.problem}, N = {r['n']}, {args.steps} steps, {args.threads} thread(s); "
          f"medians of {args.repeat}:")
    for (order, sort), values in rates.items():
        base = statistics.median(rates[(order, 0)])
        med = statistics.median(values)
        print(f"  {order:7s} sort_every {sort or 'never':>5}: {med:.3e} particle-steps/s "
              f"({med / base:.3f}x the same order unsorted)")


if __name__ == "__main__":
    main()
