"""Where does a demstep step go? Times the compiled kernels of one step separately.

    python benchmarks/profile_demstep.py --problem dense --n 100000 --threads 1 [--reps 30]

Builds the problem of ``peers.py``, runs ``--warmup`` steps (compilation, a realistic
contact state), then times, on copies of the simulation's arrays:
``pair_forces`` (the copy for the problem's law and box, as the step calls it),
``reduce_forces`` (more than one thread), ``wall_forces``,
``integrate_plain`` (undamped) or ``integrate`` (each called ``--reps`` times, the
threaded or the serial version as the engine chooses) and one neighbour-list rebuild (``Simulation._rebuild`` and its
parts), and compares their sum with the time per step of ``sim.run``. Kernel arguments
are matched by parameter name, so the script follows signature changes as long as
the names stay those of the engine's attributes.
"""

from __future__ import annotations

import argparse
import inspect
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problem", choices=("dense", "settle"), default="dense")
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=30)
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    import demstep  # noqa: F401  (chooses the threading layer before numba starts threads)
    import numba

    from demstep.engine import TimeStep
    from demstep.kernels import dem, neighbors
    from peers import demstep_simulation, make_problem

    numba.set_num_threads(args.threads)
    x, spec = make_problem(args.problem, args.n)
    sim = demstep_simulation(x, spec, TimeStep.fixed(spec["dt"]))
    sim.run(steps=args.warmup)

    # a whole step, as the benchmark times it
    t = time.perf_counter()
    r0 = sim.lists.n_rebuilds
    sim.run(steps=args.reps)
    t_step = (time.perf_counter() - t) / args.reps
    rebuilds_per_step = (sim.lists.n_rebuilds - r0) / args.reps

    params = sim.law.params()
    parallel = sim.threaded()
    pairs = sim.lists.work_space(parallel)
    chunks, spans, force_band, torque_band, geo = (pairs.chunks, pairs.spans, pairs.force_band,
                                                   pairs.torque_band, pairs.geo)
    names = {
        "periodic_len": sim.periodic_len, "law": int(params.law),
        "params": params, "box_rate": np.zeros(3),
        "dt": sim.dt, "dt_prev": sim.dt, "f_app": sim.applied_force,
        "local_damping": sim.damping.local, "global_damping": sim.damping.viscous,
        "first": False, "acc_out": np.empty(8), "box_sums": np.zeros((4, 3)),
        "store_dashpot": params.has_dashpots, "store_damping": False,
        "chunks": chunks, "spans": spans, "force_band": force_band,
        "torque_band": torque_band,
        "geo": geo, "n_chunks": len(chunks) - 1, "sphere_body": sim.bodies.sphere_body,
        "cover": np.zeros(0),  # (a fixed step: no cover tracked)
    }

    def arg(name):
        if name in names:
            return names[name]
        value = getattr(sim, name)
        return value.copy() if isinstance(value, np.ndarray) else value

    def bench(kernel):
        sig = inspect.signature(kernel.py_func)
        values = [arg(p) for p in sig.parameters]
        kernel(*values)  # compiled already; first call checks types
        t = time.perf_counter()
        for _ in range(args.reps):
            kernel(*values)
        return (time.perf_counter() - t) / args.reps

    out = {"problem": args.problem, "n": len(x), "threads": numba.get_num_threads(),
           "pairs": int(len(sim.pi)), "contacts": sim.n_contacts, "wall_pairs": int(len(sim.wp)),
           "step_s": t_step, "rebuilds_per_step": rebuilds_per_step, "kernels_s": {}}
    suffix = "" if parallel else "_serial"
    # the integrator the engine calls after the first step: the plain copy when undamped
    undamped = sim.damping.local == 0.0 and sim.damping.viscous == 0.0
    kernels = ["pair_forces", "wall_forces", "integrate_plain" if undamped else "integrate"]
    if len(chunks) > 2:
        kernels.insert(1, "reduce_forces")
    for name in kernels:
        if name == "pair_forces":  # the copy compiled for this law and box, as the step's
            kernel = dem.pair_loop_for(parallel, bool(params.has_dashpots),
                                       bool(np.any(sim.periodic_len > 0)))
        else:
            kernel = getattr(dem, name + suffix)
        out["kernels_s"][name] = bench(kernel)

    # one neighbour rebuild and its parts
    parts = {}
    t = time.perf_counter()
    pi, pj = neighbors.build_pair_list(sim.x, sim.r, sim.skin, sim.periodic_len,
                                       expected_pairs=len(sim.pi))
    parts["build_pair_list"] = time.perf_counter() - t
    t = time.perf_counter()
    neighbors.transfer_history(sim.pi, sim.pj, pi, pj, sim.ft, sim.fd, sim.etan)
    parts["transfer_history"] = time.perf_counter() - t
    t = time.perf_counter()
    neighbors.build_wall_list(sim.x, sim.r, sim.wall_point, sim.wall_normal, sim.skin)
    parts["build_wall_list"] = time.perf_counter() - t
    t = time.perf_counter()
    sim.lists.rebuild()
    parts["_rebuild_total"] = time.perf_counter() - t
    out["rebuild_s"] = parts
    out["kernel_sum_s"] = sum(out["kernels_s"].values())
    if args.json:
        print(json.dumps(out))
        return
    n = len(x)
    print(f"{args.problem}: N = {n}, {out['pairs']} Verlet pairs, {out['contacts']} contacts, "
          f"{out['wall_pairs']} wall pairs, {out['threads']} thread(s)")
    print(f"  whole step (sim.run)      {1e3 * t_step:9.3f} ms  {1e9 * t_step / n:7.1f} ns/particle"
          f"  (rebuilds per step {rebuilds_per_step:.2f})")
    for name, s in out["kernels_s"].items():
        print(f"  {name:25s} {1e3 * s:9.3f} ms  {1e9 * s / n:7.1f} ns/particle  {100 * s / t_step:5.1f} %")
    print(f"  {'sum of the kernels':25s} {1e3 * out['kernel_sum_s']:9.3f} ms")
    for name, s in parts.items():
        print(f"  rebuild: {name:16s} {1e3 * s:9.3f} ms")


if __name__ == "__main__":
    main()
