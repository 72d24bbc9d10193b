"""How the cost of the time-step analysis grows with N (issue: element bounds on 10^6
spheres in < 2 s; exact lambda_max with rotation on 10^5 spheres in < 60 s, < 4 GB).

Each case runs in a fresh subprocess so that its peak memory (ru_maxrss) is its own.
Times are medians over ``--repeat`` runs of the analysis alone; contact detection
(scipy cKDTree) is timed separately. The assembly is a jittered, polydisperse grid of
spheres (radii +/-10 %, about 5.6 contacts per sphere).

    python benchmarks/timestep_scaling.py [--json] [--max-exact 100000] [--max-element 1000000]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

CASE = r"""
import json, resource, statistics, sys, time
import numpy as np
from demstep.contacts import find_contacts
from demstep.packings import jittered_polydisperse
from demstep.particles import Particles
from demstep.timestep.estimates import element_coupled_dt, element_paper_dt, nodal_dt, exact_dt

n, what, repeat = int(sys.argv[1]), sys.argv[2], int(sys.argv[3])
x, r = jittered_polydisperse(n, 3, seed=1, overlap=0.12)
p = Particles.from_density(x, r, 2000.0)
t = time.perf_counter(); c = find_contacts(p, 1e11); t_contacts = time.perf_counter() - t
fn = {"element": lambda: (element_coupled_dt(p, c, True), element_paper_dt(p, c, True),
                          nodal_dt(p, c, True)),
      "exact": lambda: exact_dt(p, c, True)}[what]
times = []
for _ in range(repeat):
    t = time.perf_counter(); fn(); times.append(time.perf_counter() - t)
print(json.dumps({"what": what, "n": p.n, "contacts": c.n, "t_contacts": t_contacts,
                  "t_median": statistics.median(times), "t_min": min(times), "t_max": max(times),
                  "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def run_case(n, what, repeat):
    out = subprocess.run([sys.executable, "-c", CASE, str(n), what, str(repeat)],
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--max-element", type=int, default=1_000_000)
    ap.add_argument("--max-exact", type=int, default=100_000)
    args = ap.parse_args()
    sizes = [1_000, 10_000, 100_000, 1_000_000]
    results = []
    for what, limit in (("element", args.max_element), ("exact", args.max_exact)):
        for n in sizes:
            if n <= limit:
                res = run_case(n, what, args.repeat if n < 1_000_000 or what == "element" else 1)
                results.append(res)
                if not args.json:
                    print(f"{what:8s} N={res['n']:>8d} contacts={res['contacts']:>8d} "
                          f"analysis {res['t_median']:8.3f} s (min {res['t_min']:.3f}, max "
                          f"{res['t_max']:.3f})  contact detection {res['t_contacts']:6.2f} s  "
                          f"peak RSS {res['rss_mb']:7.0f} MB", flush=True)
    if args.json:
        print(json.dumps({"benchmark": "timestep_scaling", "results": results}))


if __name__ == "__main__":
    main()
