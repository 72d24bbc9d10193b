"""What a triangle-mesh floor costs against a plane wall.

Spheres (radius 1, linear springs, friction, gravity) settle from a jittered grid onto
a floor that is, in turn: a plane wall; a mesh of 2 triangles; a mesh of ``--fine``
squares a side (2 x fine^2 triangles, about 1e5 by default) with squares about a
particle diameter wide, most of it far from the particles (a large CAD floor); and
the same number of triangles packed under the particles only (squares about a third
of a diameter: each sphere within reach of some 15 triangles). Each run is its own process; the
cases are interleaved, ``--repeat`` times; medians of particle-steps per second, the
ratio to the plane wall, on the final state the time to bin the triangles in their
grid (once per mesh: a fixed mesh's grid, and a moving mesh's in its own frame, are
kept from one rebuild to the next) and of one candidate search through it (each
rebuild's), and, settled,
the time of a step and of the mesh contacts' loop alone, against the plane's step
(the mesh contacts' cost beside the step's pair work).

    python benchmarks/meshes.py [--n 20000] [--steps 2000] [--fine 224] [--repeat 3]
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
from demstep.contact.laws import LinearSpring
from demstep.engine import Simulation, TimeStep
from demstep.engine.meshes import MeshWall, build_candidates
from demstep.mesh import mesh_from_arrays
from demstep.mesh.shapes import plane
from demstep.particles import Particles
from demstep.walls import Wall

floor, n, steps, fine = sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
side = int(round((n / 4) ** 0.5))
rng = np.random.default_rng(1)
g = np.stack(np.meshgrid(np.arange(side), np.arange(side), np.arange(4), indexing="ij"),
             -1).reshape(-1, 3) * 2.2
x = g + [1.1 - 1.1 * side, 1.1 - 1.1 * side, 1.2] + rng.normal(0, 0.05, g.shape)
p = Particles.from_density(x, np.full(len(x), 1.0), 1.0)
law = LinearSpring(k_n=1e5, mu=0.3, mu_wall=0.3, restitution=0.5)
kw = dict(gravity=[0, 0, -10.0], timestep=TimeStep.fixed(1e-3))
extent = 2.2 * side + 10.0

def mesh(nsq, size):
    m = plane(nsq, size=size)
    return mesh_from_arrays(np.asarray(m.vertices), np.asarray(m.triangles), name="floor")

if floor == "plane":
    sim = Simulation(p, law, walls=[Wall([0, 0, 0], [0, 0, 1], name="floor")], **kw)
elif floor == "mesh-2":
    sim = Simulation(p, law, meshes=[MeshWall(mesh(1, extent))], **kw)
elif floor == "mesh-large":
    sim = Simulation(p, law, meshes=[MeshWall(mesh(fine, 2.0 * fine))], **kw)
else:  # mesh-fine: the same triangle count under the particles
    sim = Simulation(p, law, meshes=[MeshWall(mesh(fine, extent))], **kw)
sim.run(steps=20)
t = time.perf_counter()
sim.run(steps=steps)
elapsed = time.perf_counter() - t
# the settled state: a step, and the mesh contacts' loop alone (threaded as the step's)
t = time.perf_counter()
sim.run(steps=100)
step_s = (time.perf_counter() - t) / 100
loop_s = 0.0
if floor != "plane":
    from demstep.kernels.meshes import mesh_forces
    chunks = sim.pairs.force_band.shape[0] if sim.threaded() else 1
    mesh_forces(sim.spheres, sim.meshes, sim.law.params(), 1e-3, chunks)
    t = time.perf_counter()
    for _ in range(100):
        mesh_forces(sim.spheres, sim.meshes, sim.law.params(), 1e-3, chunks)
    loop_s = (time.perf_counter() - t) / 100
search = build = float("nan")
if floor != "plane":
    from demstep.engine.meshes import TriangleGrid
    grid = TriangleGrid()
    t0 = time.perf_counter()
    build_candidates(sim.meshes, sim.x, sim.r, sim.skin, lambda k: k, None, grid)
    build = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(3):
        build_candidates(sim.meshes, sim.x, sim.r, sim.skin, lambda k: k, None, grid)
    search = (time.perf_counter() - t0) / 3
    build -= search
print(json.dumps({"rate": len(x) * steps / elapsed, "n": len(x), "triangles": len(sim.meshes.tri),
                  "search_s": search, "grid_s": build, "contacts": sim.n_contacts, "step_s": step_s,
                  "loop_s": loop_s, "candidates": len(sim.meshes.cand_p)}))
"""

FLOORS = ("plane", "mesh-2", "mesh-large", "mesh-fine")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20_000)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--fine", type=int, default=224, help="squares a side of the fine meshes")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    src = str(HERE.parent / "src")
    for floor in FLOORS:  # compile or load the caches, untimed
        subprocess.run([sys.executable, "-c", CASE, src, floor, "400", "20", "8"], check=True,
                       capture_output=True)
    runs = {f: [] for f in FLOORS}
    steps_of = {f: [] for f in FLOORS}
    loops_of = {f: [] for f in FLOORS}
    info = {}
    for _ in range(args.repeat):
        for floor in FLOORS:
            out = subprocess.run([sys.executable, "-c", CASE, src, floor, str(args.n),
                                  str(args.steps), str(args.fine)], check=True,
                                 capture_output=True, text=True)
            row = json.loads(out.stdout.strip().splitlines()[-1])
            runs[floor].append(row["rate"])
            steps_of[floor].append(row["step_s"])
            loops_of[floor].append(row["loop_s"])
            info[floor] = row
    med = {f: statistics.median(v) for f, v in runs.items()}
    result = {"n": args.n, "steps": args.steps, "runs": runs, "median_psps": med,
              "ratio_to_plane": {f: med[f] / med["plane"] for f in FLOORS}, "last": info}
    if args.json:
        print(json.dumps(result))
        return
    print(f"{info['plane']['n']} spheres settling, {args.steps} steps, medians of {args.repeat}")
    print(f"{'floor':<12}{'triangles':>10}{'M p-s/s':>10}{'/ plane':>9}{'grid ms':>9}{'search ms':>11}"
          f"{'contacts':>10}{'cands':>8}{'step ms':>9}{'mesh ms':>9}{'/ plane step':>13}")
    plane_step = statistics.median(steps_of["plane"])
    for f in FLOORS:
        step = statistics.median(steps_of[f])
        loop = statistics.median(loops_of[f])
        print(f"{f:<12}{info[f]['triangles']:>10}{med[f] / 1e6:>10.2f}"
              f"{med[f] / med['plane']:>9.3f}{1e3 * info[f]['grid_s']:>9.1f}"
              f"{1e3 * info[f]['search_s']:>11.1f}{info[f]['contacts']:>10}{info[f]['candidates']:>8}{1e3 * step:>9.3f}"
              f"{1e3 * loop:>9.3f}{loop / plane_step:>13.3f}")


if __name__ == "__main__":
    main()
