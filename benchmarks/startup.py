"""Start-up cost: seconds from a fresh interpreter to the end of the first step.

    python benchmarks/startup.py [--repeat 5] [--n 1000] [--json]

Each measurement is a new process (``python -c ...``) that imports demstep, builds a
small FCC block (``--n`` spheres inside walls, the ``dense`` problem of peers.py) and
runs one step; the time is taken from the parent's clock before the process starts
to the child's report after the step. The first measurement fills numba's on-disk
cache if it is empty (it is reported apart); the median of the others is the warm
start-up (issue: under 2 s). Also reported: the bare ``import numba`` of a fresh
interpreter, the floor under any numba code.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

CHILD = r"""
import sys, time
import numpy as np
import demstep
from demstep.contact.laws import LinearSpring
from demstep.engine import Simulation, TimeStep
from demstep.packings import lattice
from demstep.particles import Particles
from demstep.walls import Wall
n = int(sys.argv[1])
side = max(2, round((n / 2) ** (1 / 3)))
x = lattice("fcc", 0.5).block(side)
r = 0.5 * 1.001
lo, hi = x.min(axis=0) - r, x.max(axis=0) + r
walls = [Wall(np.where(np.arange(3) == k, lo[k], 0.0), np.eye(3)[k]) for k in range(3)]
walls += [Wall(np.where(np.arange(3) == k, hi[k], 0.0), -np.eye(3)[k]) for k in range(3)]
sim = Simulation(Particles.from_density(x, np.full(len(x), r), 2500.0),
                 LinearSpring(k_n=1e6, mu=0.5), walls, timestep=TimeStep.from_alpha(0.1))
sim.run(steps=1)
print("DONE", time.time(), flush=True)
"""


def once(code, *args):
    t0 = time.time()
    out = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                         check=True).stdout
    end = float(next(line.split()[1] for line in out.splitlines() if line.startswith("DONE")))
    return end - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--n", type=int, default=1000)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    first = once(CHILD, str(args.n))
    warm = [once(CHILD, str(args.n)) for _ in range(args.repeat)]
    numba_only = [once("import time, numba; print('DONE', time.time())") for _ in range(args.repeat)]
    out = {"benchmark": "startup", "n": args.n, "first_s": first,
           "warm_median_s": statistics.median(warm), "warm_min_s": min(warm), "warm_max_s": max(warm),
           "import_numba_median_s": statistics.median(numba_only)}
    if args.json:
        print(json.dumps(out))
        return
    print(f"first run (fills the cache if empty)   {first:6.2f} s")
    print(f"warm start to first step done (median) {out['warm_median_s']:6.2f} s "
          f"(min {min(warm):.2f}, max {max(warm):.2f}, {args.repeat} runs)")
    print(f"bare 'import numba' (median)           {out['import_numba_median_s']:6.2f} s")


if __name__ == "__main__":
    main()
