"""How the cost of the time-step analysis grows with N, undamped and damped.

Cases (each in a fresh subprocess, so that its peak memory, ru_maxrss, is its own):

* ``element``: the element bounds (coupled, paper, nodal);
* ``exact`` / ``exact-damped``: the certified exact step with rotation, without and with
  contact dashpots (restitution 0.5 on normal and tangential springs, demstep's
  convention c = 2 beta sqrt(m* k)); the issue's target is damped <= 2x undamped;
* ``certified`` / ``certified-damped``: the same with the random-start check of the
  certified step (:mod:`demstep.timestep.guarantee`; seed 1): its extra cost;
* ``cli``: ``demstep dt DUMP --restitution 0.5 --methods exact,element-coupled`` on a
  LIGGGHTS dump written beforehand (reading, contact detection and the damped exact
  step: the whole command, timed from outside; target 1e6 spheres < 2 min, < 6 GB).

Packings: ``loose`` a jittered polydisperse grid (radii +/-10 %, ~5.6 contacts per
sphere); ``dense`` the same grid with radii grown until diagonal neighbours touch (~9
contacts per sphere, a random, clustered top spectrum); ``fcc`` an FCC block (12
contacts, the most clustered top spectrum). Times are medians over ``--repeat`` runs of
the analysis alone; contact detection (scipy cKDTree) is timed separately.

    python benchmarks/timestep_scaling.py [--json] [--sizes 1000,10000,100000]
        [--packings loose,dense,fcc] [--cases element,exact,exact-damped] [--cli 1000000]
        [--compare OLD_SRC] [--threads 2,1] [--tols 1e-10,1e-6]

``--compare OLD_SRC`` runs every case also with the package sources in OLD_SRC (a
``src`` folder of another version, e.g. from ``git archive``), interleaved with the
current ones case by case (the machine's load drifts); ``--threads`` runs the current
version once per numba thread count listed (default: numba's own).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CASE = r"""
import json, math, resource, statistics, sys, time
from dataclasses import replace
import numpy as np
from demstep.timestep.contacts import find_contacts
from demstep.packings import jittered_polydisperse, lattice
from demstep.particles import Particles
from demstep.timestep.estimates import element_coupled_dt, element_paper_dt, nodal_dt
from demstep.timestep.exact import certified_without_basis, exact_critical_step

n, packing, what, repeat = int(sys.argv[1]), sys.argv[2], sys.argv[3], int(sys.argv[4])
tol = float(sys.argv[5])
if packing == "fcc":
    side = max(2, round((n / 4) ** (1 / 3)))
    x = lattice("fcc", 0.5).block(side)
    r = np.full(len(x), 0.5 * 1.001)
else:
    x, r = jittered_polydisperse(n, 3, seed=1, overlap=0.12 if packing == "loose" else 0.45)
p = Particles.from_density(x, r, 2000.0)
t = time.perf_counter(); c = find_contacts(p, 1e6); t_contacts = time.perf_counter() - t
if what in ("exact-damped", "certified-damped", "nobasis-damped"):
    e = 0.5
    beta = -math.log(e) / math.sqrt(math.pi ** 2 + math.log(e) ** 2)
    inv = 1.0 / p.m
    m_star = 1.0 / (inv[c.i] + np.where(c.j >= 0, inv[np.maximum(c.j, 0)], 0.0))
    c = replace(c, c_n=2 * beta * np.sqrt(m_star * c.k_n), c_t=2 * beta * np.sqrt(m_star * c.k_s))
fn = {"element": lambda: (element_coupled_dt(p, c, True), element_paper_dt(p, c, True),
                          nodal_dt(p, c, True)),
      "exact": lambda: exact_critical_step(p, c, True, tol=tol),
      "exact-damped": lambda: exact_critical_step(p, c, True, tol=tol),
      "certified": lambda: exact_critical_step(p, c, True, tol=tol, guarantee=True, seed=1),
      "certified-damped": lambda: exact_critical_step(p, c, True, tol=tol, guarantee=True,
                                                      seed=1),
      "nobasis": lambda: certified_without_basis(p, c, True, seed=1),
      "nobasis-damped": lambda: certified_without_basis(p, c, True, seed=1)}[what]
times = []
for _ in range(repeat):
    t = time.perf_counter(); res = fn(); times.append(time.perf_counter() - t)
extra = {}
if what.startswith(("exact", "certified", "nobasis")):
    extra = {"dt": res.dt, "dt_undamped": res.dt_undamped, "iterations": res.iterations, "tol": tol,
             "matvecs": getattr(res, "matvecs", None)}
if what.startswith(("certified", "nobasis")):
    extra.update(dt_certified=res.dt_certified, guarantee=res.guarantee.kind,
                 check_steps=res.check.steps if res.check else 0)
import numba
extra["threads"] = numba.get_num_threads()
print(json.dumps({"what": what, "packing": packing, "n": p.n, "contacts": c.n,
                  "contacts_per_sphere": 2 * c.n / p.n, "t_contacts": t_contacts,
                  "t_median": statistics.median(times), "t_min": min(times), "t_max": max(times),
                  "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, **extra}))
"""

WRITE_DUMP = r"""
import sys
import numpy as np
from demstep.io.formats import write_liggghts_dump
from demstep.packings import jittered_polydisperse
n, path = int(sys.argv[1]), sys.argv[2]
x, r = jittered_polydisperse(n, 3, seed=1, overlap=0.12)
side = round(len(r) ** (1 / 3))
m = 2000.0 * 4.0 / 3.0 * np.pi * r ** 3
write_liggghts_dump(path, x + 0.5, r, m=m, box=[(0.0, float(side))] * 3, periodic=True)
"""


def run_case(n, packing, what, repeat, src=None, threads=None, tol=1e-10):
    """One case in a fresh process; ``src``: PYTHONPATH of another version's sources,
    ``threads``: NUMBA_NUM_THREADS, ``tol``: the exact solver's relative residual."""
    env = dict(os.environ)
    if src:
        env["PYTHONPATH"] = src
    if threads:
        env["NUMBA_NUM_THREADS"] = str(threads)
    out = subprocess.run([sys.executable, "-c", CASE, str(n), packing, what, str(repeat), str(tol)],
                         capture_output=True, text=True, check=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_cli(n):
    """The whole `demstep dt` command on an n-sphere periodic dump: wall time and peak
    RSS of the process (from /proc via os.wait4)."""
    folder = Path(tempfile.mkdtemp(prefix="demstep-dt-bench-"))
    dump = folder / "state.dump"
    subprocess.run([sys.executable, "-c", WRITE_DUMP, str(n), str(dump)], check=True)
    cmd = [sys.executable, "-m", "demstep.cli", "dt", str(dump), "--kn", "1e6",
           "--restitution", "0.5", "--methods", "exact,element-coupled", "--json", "--top", "0"]
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    out = proc.stdout.read().decode()
    err = proc.stderr.read().decode()
    if status != 0:
        raise SystemExit(f"demstep dt failed: {err}")
    data = json.loads(out)
    dump.unlink()
    folder.rmdir()
    return {"what": "cli", "n": data["n_particles"], "contacts": data["n_contacts"],
            "wall_s": wall, "rss_mb": usage.ru_maxrss / 1024,
            "dt": {e["method"]: e["dt"] for e in data["estimates"]}}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--sizes", default="1000,10000,100000")
    ap.add_argument("--packings", default="loose,dense,fcc")
    ap.add_argument("--cases", default="element,exact,exact-damped")
    ap.add_argument("--cli", type=int, default=0, help="also time `demstep dt` on an N-sphere dump")
    ap.add_argument("--compare", default="", help="sources (a src folder) of a version to "
                    "run interleaved with this one")
    ap.add_argument("--threads", default="", help="numba thread counts for this version")
    ap.add_argument("--tols", default="1e-10", help="relative residuals of the exact solver, "
                    "each a case of its own (default 1e-10, the package's; 'auto' runs use 1e-6)")
    args = ap.parse_args()
    sizes = [int(s) for s in args.sizes.split(",") if s]
    threads = [int(t) for t in args.threads.split(",") if t] or [None]
    variants = [("current", None, t) for t in threads]
    if args.compare:
        variants.append(("compare", str(Path(args.compare).resolve()), None))
    results = []
    for packing in args.packings.split(","):
        for n in sizes:
            for what, tol in ((w, float(t)) for w in args.cases.split(",")
                              for t in (args.tols.split(",")
                                        if w.startswith(("exact", "certified", "nobasis"))
                                        else "1")):
                for label, src, n_threads in variants:
                    res = run_case(n, packing, what, args.repeat if n < 1_000_000 else 1, src,
                                   n_threads, tol)
                    res["version"] = label
                    results.append(res)
                    if not args.json:
                        extra = f"  dt {res['dt']:.10g}" if "dt" in res else ""
                        if res.get("matvecs"):
                            extra += f"  products {res['matvecs']}  tol {res['tol']:g}"
                        print(f"{label:8s} {res['threads']}t {packing:6s} {what:13s} "
                              f"N={res['n']:>8d} contacts/sphere "
                              f"{res['contacts_per_sphere']:5.2f} "
                              f"analysis {res['t_median']:8.3f} s "
                              f"(min {res['t_min']:.3f}, max {res['t_max']:.3f})  "
                              f"contact detection {res['t_contacts']:6.2f} s  "
                              f"peak RSS {res['rss_mb']:7.0f} MB{extra}", flush=True)
    if args.cli:
        res = run_cli(args.cli)
        results.append(res)
        if not args.json:
            print(f"cli    demstep dt    N={res['n']:>8d} contacts {res['contacts']:>8d} wall "
                  f"{res['wall_s']:.1f} s peak RSS {res['rss_mb']:.0f} MB  {res['dt']}", flush=True)
    if args.json:
        print(json.dumps({"benchmark": "timestep_scaling", "results": results}))


if __name__ == "__main__":
    main()
