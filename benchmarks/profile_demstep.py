"""Where does a demstep step go? Times the compiled kernels of one step separately.

    python benchmarks/profile_demstep.py --problem dense --n 100000 --threads 1 [--reps 30]

Builds the problem of ``peers.py``, runs ``--warmup`` steps (compilation, a realistic
contact state), then times, on copies of the simulation's arrays:
``pair_forces`` (the copy for the problem's law and box, as the step calls it),
``reduce_forces`` (more than one thread), ``wall_forces``, ``mesh_forces`` (the
problems with meshes; each called ``--reps`` times on copies of the engine's state,
the threaded or the serial version as the engine chooses) and one neighbour-list
rebuild (and its parts), and compares their sum with the time per step of
``sim.run`` (the rest: the integration and the bookkeeping).
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
    ap.add_argument("--problem", choices=("dense", "settle", "hopper", "drum"), default="dense")
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

    import copy

    from demstep.kernels.meshes import mesh_forces, mesh_forces_serial

    params = sim.law.params()
    parallel = sim.threaded()
    pairs = sim.lists.work_space(parallel)
    chunks = pairs.force_band.shape[0] if parallel else 1
    out = {"problem": args.problem, "n": len(x), "threads": numba.get_num_threads(),
           "pairs": int(len(sim.pi)), "contacts": sim.n_contacts, "wall_pairs": int(len(sim.wp)),
           "mesh_rows": int(len(sim.meshes.cand_p)) if sim.meshes is not None else 0,
           "step_s": t_step, "rebuilds_per_step": rebuilds_per_step, "kernels_s": {}}

    def bench(kernel, *values):
        """Seconds per call of ``kernel`` on deep copies of ``values`` (the engine's
        state is left alone)."""
        values = [copy.deepcopy(v) for v in values]
        kernel(*values)  # compiled already; the first call checks the types
        t = time.perf_counter()
        for _ in range(args.reps):
            kernel(*values)
        return (time.perf_counter() - t) / args.reps

    # the kernels of one step, as :func:`demstep.kernels.dem._advance` calls them (the
    # pair loop: the copy compiled for this law and box); the integration is the rest
    pair_loop = dem.pair_loop_for(parallel, bool(params.has_dashpots),
                                  bool(np.any(sim.periodic_len > 0)))
    out["kernels_s"]["pair_forces"] = bench(pair_loop, sim.spheres, pairs, sim.periodic_len,
                                            np.zeros(3), params, sim.dt, bool(params.has_dashpots),
                                            np.zeros((4, 3)))
    if chunks > 1:
        out["kernels_s"]["reduce_forces"] = bench(dem.reduce_forces, pairs.force_band,
                                                  pairs.torque_band, pairs.spans,
                                                  sim.spheres.force, sim.spheres.torque)
    wall_loop = dem.wall_forces if parallel else dem.wall_forces_serial
    out["kernels_s"]["wall_forces"] = bench(wall_loop, sim.spheres, sim.wall_state, params,
                                            sim.dt, chunks)
    if sim.meshes is not None and len(sim.meshes.tri):
        out["kernels_s"]["mesh_forces"] = bench(mesh_forces if parallel else mesh_forces_serial,
                                                sim.spheres, sim.meshes, params, sim.dt, chunks)

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
