"""Side-by-side DEM benchmark: demstep against LIGGGHTS, LAMMPS and YADE on the same problems.

    python benchmarks/peers.py --problem dense|settle|hopper|drum --n 100000 --threads 1 \
        [--repeat 3] [--steps 1000] [--codes demstep,liggghts,yade,lammps] [--json]
    python benchmarks/peers.py --check [--n 500]      # do the codes agree? (small case)
    python benchmarks/peers.py --check --problem hopper|drum --n 3000 --steps 3000

Problems (identical input in every code; positions are generated once and written to
files the peers read):

* ``dense``: spheres of radius 0.5 x 1.001 on the FCC lattice of
  ``demstep.packings.lattice('fcc', 0.5).block(side)`` (nearest-neighbour distance 1,
  so all 12 nearest-neighbour contacts per interior sphere overlap by 0.001), inside
  the six fixed walls touching the outer spheres; no gravity, no damping.
* ``settle``: spheres of radius 0.5 on a simple-cubic grid of spacing 1.5 (no
  contacts; a square footprint, at most 8 layers) in a box of a floor and four side
  walls (open top), gravity -9.81 along z, normal dashpots for a restitution of 0.5.

* ``hopper`` (discharge): a conical hopper of triangles (96 facets around, 30 deg from
  the vertical, outlet radius 8 r) under a vertical bin of the same facets, one mesh of
  384 triangles, filled from the outlet up by a jittered simple-cubic grid (spacing
  1.05 d); the outlet is open and a catch box of plane walls lies under it. The timed
  steps are the bed's collapse onto the cone and the start of the discharge: spheres
  falling through the outlet make every code rebuild its lists every ~3 steps.
* ``drum``: a closed drum of triangles (a 96-facet cylinder with fan caps, 384
  triangles, as long as its radius, its axis along y) filled to ~40 % by the same
  grid, turning at omega^2 R / g = 1e-3 (the rolling regime): the bed settles as it
  turns. LIGGGHTS reads the same STL (``fix mesh/surface``, the wall material's
  type; ``fix move/mesh ... rotate``).

All: friction 0.5 (walls too), density 2500, rotation on, dt = 0.1 sqrt(m / k_n),
Verlet skin 0.15 r (demstep's default) in every code; linear springs k_n = k_s = 1e6
(dense, settle) or 1e7 (hopper, drum: their beds are some 40 spheres deep);
restitution 0.5 (settle, hopper, drum).
``--law hertz``: Hertz-Mindlin instead (LIGGGHTS ``model hertz tangential history``),
E = 5.93e7 Pa and nu = 0.25, so that the tangent normal stiffness of the dense
packing's overlap (0.002 r, R* = r/2) is k_n = 1e6; same dt; restitution as above
(LIGGGHTS' Tsuji form, which demstep's Hertz dashpot follows); no YADE row.
The exact peer settings are in :func:`liggghts_input`, :func:`lammps_input` and
:data:`YADE_SCRIPT`.
LAMMPS (``lmp``, ``pair_style granular``; ``dense`` and ``settle`` with linear springs
only): ``units si``, ``atom_style sphere`` read from a data file, ``boundary f f f``,
``comm_modify vel yes``, ``neighbor SKIN bin`` with ``neigh_modify delay 0 every 1
check yes`` (the default delay 10 would miss contacts), ``newton`` and ``atom_modify
sort`` at their defaults; ``pair_coeff * * hooke k_n ETA tangential linear_history k_s 0
mu damping velocity``, which gives F_n = k_n delta + ETA v_n (ETA absolute: demstep's
c_n, 0 on ``dense``) and a tangential dashpot of 0 x ETA (demstep has none); the walls
``fix wall/gran granular`` with the same model and ETA = c_pw, one fix per axis with its
lower and upper plane; ``fix gravity G vector`` (the force's direction); ``fix
nve/sphere``. LAMMPS' sphere-sphere torque arm is r - delta/2 (its slip velocity takes
r): 0.1 % on ``dense``'s overlaps. No ``--law hertz`` row: LAMMPS' Hertz dashpots
(``tsuji``, ``viscoelastic``) are not LIGGGHTS' and demstep's, and the 2021 ``fix
wall/gran hertz/material`` takes E / (2 (1 - nu)) for the wall's E*; no mesh problems
(LAMMPS 2021 has no STL mesh walls).
``--order shuffled``: the same spheres in a fixed random order, in memory and in the
peers' input files, as particles inserted at random places come from another code.
LIGGGHTS sorts its atoms spatially itself (``atom_modify sort``, on by default);
demstep's child puts them in spatial order as ``demstep run`` does with a particle file
(:func:`demstep.packings.spatial_order`; the engine keeps the order it is given).

Only the stepping is timed: every code first runs ``--warmup`` steps (numba compiles
or loads its cache, neighbour lists are built), then ``--steps`` steps are timed:
demstep ``sim.run(steps=...)``, LIGGGHTS and LAMMPS the "Loop time" of their second
``run``, YADE ``O.run(steps, True)``. Each measurement is its own process; its peak memory is
the largest sum of the resident set sizes of its process tree (sampled every 0.1 s,
MPI launchers excluded) or the kernel's ru_maxrss of the child, whichever is larger;
a report gives the largest over the runs (``rss_mb``) and each run's
(``rss_mb_runs``, in order: a first run that compiles numba's cache stands out).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
CODES = ("demstep", "liggghts", "yade", "lammps")
LAUNCHERS = {"mpirun", "mpiexec", "orterun", "prterun", "prte", "orted", "prted"}
RESULT_TAG = "BENCH_RESULT "


# ----------------------------------------------------------------------------- problems
#: Hertz-Mindlin material of ``--law hertz``: E* = k_n / (2 sqrt(R* delta)) with
#: R* = 0.25, delta = 0.001 (the dense packing), E = 2 (1 - nu^2) E*
HERTZ_POISSON = 0.25
HERTZ_YOUNG = 2.0 * (1.0 - HERTZ_POISSON**2) * 1.0e6 / (2.0 * math.sqrt(0.25 * 0.001))


#: seed of the permutation of ``--order shuffled``
SHUFFLE_SEED = 0


#: the problems bounded by triangle meshes, and their springs' stiffness k_n = k_s [N/m]
MESH_PROBLEMS = ("hopper", "drum")
MESH_PROBLEM_K = 1.0e7
#: facets around the hopper's and the drum's axis
MESH_FACETS = 96
#: simple-cubic fill of the mesh problems: spacing (in diameters) and jitter (std, in
#: diameters) of the grid, and the gap kept from every wall
FILL_SPACING, FILL_JITTER, FILL_GAP = 1.05, 0.01, 0.05


def _fill(inside, lo, hi, n_target, radius, rng):
    """The ``n_target`` lowest points (by z) of a jittered simple-cubic grid in the box
    [lo, hi] for which ``inside(points, margin)`` holds with the margin radius + gap
    (centres that far from every wall)."""
    d = 2.0 * radius
    axes = [np.arange(lo[k] + radius, hi[k] - radius, FILL_SPACING * d) for k in range(3)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    g = g[inside(g, radius + FILL_GAP * d + 3 * FILL_JITTER * d)]
    if len(g) < n_target:
        raise SystemExit(f"--n {n_target}: only {len(g)} spheres fit the mesh problem's fill")
    g = g[np.argsort(g[:, 2], kind="stable")[:n_target]]
    g += rng.normal(0.0, FILL_JITTER * d, g.shape)
    return g


def _mesh_entry(name, mesh, omega=(0.0, 0.0, 0.0), center=(0.0, 0.0, 0.0)):
    return {"name": name, "vertices": np.asarray(mesh.vertices, float).tolist(),
            "triangles": np.asarray(mesh.triangles, int).tolist(), "omega": list(omega),
            "center": list(center)}


def hopper_problem(n_target: int, radius: float):
    """A conical hopper (``MESH_FACETS`` facets, half-angle 30 deg from the vertical,
    outlet radius 8 r in z = 0) under a vertical bin of the same facets (one mesh,
    ~4 x MESH_FACETS triangles), filled from the outlet up by a jittered simple-cubic
    grid; under it a catch box of plane walls (a floor 12 r below the outlet, four
    sides just outside the bin). The outlet is open: the bed collapses
    from the loose grid onto the cone and starts to flow out."""
    from demstep.mesh import mesh_from_arrays
    from demstep.mesh.shapes import cylinder, hopper

    d = 2.0 * radius
    r_out = 4.0 * d
    r_top = max(3.0 * r_out, 0.6 * n_target ** (1.0 / 3.0) * d)
    h_cone = (r_top - r_out) / math.tan(math.radians(30.0))
    inscribed = math.cos(math.pi / MESH_FACETS)
    slope = (r_top - r_out) / h_cone

    def inside(p, margin):
        rho = np.hypot(p[:, 0], p[:, 1])
        wall = inscribed * np.where(p[:, 2] < h_cone, r_out + slope * p[:, 2], r_top)
        # distance to the cone ~ (wall radius - rho) cos(30 deg)
        reach = np.where(p[:, 2] < h_cone, margin / math.cos(math.radians(30.0)), margin)
        return (rho < wall - reach) & (p[:, 2] > margin)

    height = h_cone + 4.0 * r_top + 10.0 * d
    x = _fill(inside, [-r_top, -r_top, 0.0], [r_top, r_top, height], n_target, radius,
              np.random.default_rng(3))
    h_bin = max(d, float(x[:, 2].max()) + 2.0 * d - h_cone)
    cone = hopper(MESH_FACETS, r_out, r_top, h_cone)
    tube = cylinder(MESH_FACETS, r_top, h_bin).flipped()
    mesh = mesh_from_arrays(np.concatenate([cone.vertices, np.asarray(tube.vertices) + [0, 0, h_cone]]),
                            np.concatenate([cone.triangles, np.asarray(tube.triangles) + len(cone.vertices)]),
                            name="hopper")
    floor = -12.0 * radius
    # a square catch box under the hopper: the floor and four side planes just outside
    # the bin (no contact with the spheres inside it)
    side = r_top + d
    walls = [{"axis": 2, "pos": floor, "sense": 1},
             {"axis": 0, "pos": -side, "sense": 1}, {"axis": 0, "pos": side, "sense": -1},
             {"axis": 1, "pos": -side, "sense": 1}, {"axis": 1, "pos": side, "sense": -1}]
    lo = [-r_top - 2 * d, -r_top - 2 * d, floor - 2 * d]
    hi = [r_top + 2 * d, r_top + 2 * d, h_cone + h_bin + 2 * d]
    shape = {"outlet_radius": r_out, "top_radius": r_top, "cone_height": h_cone,
             "bin_height": h_bin, "triangles": len(mesh.triangles)}
    return x, walls, [_mesh_entry("hopper", mesh)], lo, hi, shape


def drum_problem(n_target: int, radius: float):
    """A closed drum (a cylinder of ``MESH_FACETS`` facets and two fan caps, its axis
    along y through the origin, as long as its radius) turning about its axis at a
    Froude number omega^2 R / g of 1e-3 (the rolling regime), filled from the bottom up
    (about 40 % of its volume) by a jittered simple-cubic grid that settles as the drum
    turns."""
    from demstep.mesh import mesh_from_arrays
    from demstep.mesh.shapes import cylinder

    d = 2.0 * radius
    r_drum = max(8.0 * d, (n_target * FILL_SPACING**3 / (0.4 * math.pi * 0.85)) ** (1.0 / 3.0) * d)
    length = r_drum
    inscribed = math.cos(math.pi / MESH_FACETS)

    def inside(p, margin):
        return ((np.hypot(p[:, 0], p[:, 2]) < inscribed * r_drum - margin)
                & (np.abs(p[:, 1]) < 0.5 * length - margin))

    x = _fill(inside, [-r_drum, -0.5 * length, -r_drum], [r_drum, 0.5 * length, r_drum],
              n_target, radius, np.random.default_rng(4))
    tube = cylinder(MESH_FACETS, r_drum, length, caps=True)
    v = np.asarray(tube.vertices)
    # the z axis onto y (a rotation about x), centred on the origin
    v = np.column_stack([v[:, 0], v[:, 2] - 0.5 * length, -v[:, 1]])
    mesh = mesh_from_arrays(v, np.asarray(tube.triangles), name="drum")
    omega = math.sqrt(1.0e-3 * 9.81 / r_drum)
    lo = [-r_drum - 2 * d, -0.5 * length - 2 * d, -r_drum - 2 * d]
    hi = [r_drum + 2 * d, 0.5 * length + 2 * d, r_drum + 2 * d]
    shape = {"drum_radius": r_drum, "length": length, "omega": omega,
             "fill_top": float(x[:, 2].max()), "triangles": len(mesh.triangles)}
    return x, [], [_mesh_entry("drum", mesh, omega=(0.0, omega, 0.0))], lo, hi, shape


def make_problem(problem: str, n_target: int, skin: float | None = None, law: str = "linear",
                 order: str = "lattice"):
    """Positions (N, 3) and a JSON-able spec of the problem (same for every code).
    ``order``: the spheres in lattice order (neighbours in space are neighbours in
    memory, as a generator writes them) or ``shuffled`` (a fixed random permutation, as
    particles inserted at random places and numbered in insertion order come from
    another code's file)."""
    k_n = k_s = 1.0e6
    mu = 0.5
    density = 2500.0
    if problem == "dense":
        from demstep.packings import lattice

        side = max(2, int(round((n_target / 2.0) ** (1.0 / 3.0))))
        x = lattice("fcc", 0.5).block(side)
        radius = 0.5 * 1.001
        lo = x.min(axis=0) - radius
        hi = x.max(axis=0) + radius
        walls = []
        for k in range(3):
            walls.append({"axis": k, "pos": float(lo[k]), "sense": 1})
            walls.append({"axis": k, "pos": float(hi[k]), "sense": -1})
        gravity = [0.0, 0.0, 0.0]
        restitution = None
        domain_lo = (lo - 1.0).tolist()
        domain_hi = (hi + 1.0).tolist()
        shape = [side, side, side]
    elif problem == "settle":
        radius = 0.5
        spacing = 1.5
        # at most 8 layers: the top layer falls ~0.25 + 0.5 x 7 = 3.75 before it lands
        # (8.6 m/s), so impacts on these soft springs overlap by < 0.45 r. A tall column
        # (e.g. 29 layers for 1e5 spheres) makes impacts overlap by more than r:
        # spheres tunnel through each other and the floor (LIGGGHTS then loses them).
        nz = max(1, min(8, int(round((n_target / 4.0) ** (1.0 / 3.0)))))
        nxy = max(1, int(round(math.sqrt(n_target / nz))))
        g = np.stack(np.meshgrid(np.arange(nxy), np.arange(nxy), np.arange(nz), indexing="ij"), -1)
        x = 0.5 * spacing + spacing * g.reshape(-1, 3).astype(float)
        length = nxy * spacing
        walls = [{"axis": 0, "pos": 0.0, "sense": 1}, {"axis": 0, "pos": length, "sense": -1},
                 {"axis": 1, "pos": 0.0, "sense": 1}, {"axis": 1, "pos": length, "sense": -1},
                 {"axis": 2, "pos": 0.0, "sense": 1}]
        gravity = [0.0, 0.0, -9.81]
        restitution = 0.5
        domain_lo = [-1.0, -1.0, -1.0]
        domain_hi = [length + 1.0, length + 1.0, nz * spacing + 2.0]
        shape = [nxy, nxy, nz]
    elif problem in MESH_PROBLEMS:
        radius = 0.5
        restitution = 0.5
        gravity = [0.0, 0.0, -9.81]
        # stiffer springs than ``settle``: the deep beds load their bottom contacts with
        # the weight of some 40 spheres (k_n d / (m g) = 780: overlaps of ~2 % of d there)
        k_n = k_s = MESH_PROBLEM_K
        x, walls, meshes, domain_lo, domain_hi, shape = (
            hopper_problem(n_target, radius) if problem == "hopper" else drum_problem(n_target, radius))
    else:
        raise SystemExit(f"unknown problem {problem!r}: dense, settle, hopper or drum")
    mass = density * 4.0 / 3.0 * math.pi * radius**3
    dt = 0.1 * math.sqrt(mass / k_n)
    spec = {"problem": problem, "n": int(len(x)), "shape": shape, "radius": radius,
            "density": density, "mass": mass, "k_n": k_n, "k_s": k_s, "mu": mu, "mu_wall": mu,
            "restitution": restitution, "gravity": gravity, "dt": dt, "walls": walls,
            "skin": 0.15 * radius if skin is None else float(skin),
            "domain_lo": domain_lo, "domain_hi": domain_hi, "law": law,
            "youngs_modulus": HERTZ_YOUNG, "poisson_ratio": HERTZ_POISSON,
            "meshes": meshes if problem in MESH_PROBLEMS else []}
    if law not in ("linear", "hertz"):
        raise SystemExit(f"unknown law {law!r}: linear or hertz")
    if law == "hertz" and problem in MESH_PROBLEMS:
        raise SystemExit(f"--law hertz: the {problem} problem is set up for linear springs only")
    if order == "shuffled":
        x = x[np.random.default_rng(SHUFFLE_SEED).permutation(len(x))]
    elif order != "lattice":
        raise SystemExit(f"unknown order {order!r}: lattice or shuffled")
    spec["order"] = order
    if restitution is not None:
        ln = math.log(restitution)
        beta = -ln / math.sqrt(math.pi**2 + ln**2)
        spec["beta"] = beta
        # demstep: c_n = 2 beta sqrt(m* k_n), m* = m/2 (two spheres), m (sphere-wall)
        spec["c_pp"] = 2.0 * beta * math.sqrt(0.5 * mass * k_n)
        spec["c_pw"] = 2.0 * beta * math.sqrt(mass * k_n)
    return np.ascontiguousarray(x, dtype=np.float64), spec


def write_problem(folder: Path, x, spec):
    np.save(folder / "x.npy", x)
    (folder / "spec.json").write_text(json.dumps(spec, indent=1))


# ----------------------------------------------------------------------------- demstep
def demstep_simulation(x, spec, timestep):
    """The problem ``spec`` with positions ``x`` as a demstep Simulation stepping by
    ``timestep`` (a TimeStep): the one place the benchmarks (peers, auto_cost,
    profile_demstep) translate a problem into demstep."""
    from demstep.contact.laws import HertzMindlin, LinearSpring
    from demstep.engine import Simulation
    from demstep.particles import Particles
    from demstep.walls import Wall

    if spec.get("order") == "shuffled":
        # as ``demstep run`` reads a particle file: in spatial order (LIGGGHTS sorts its
        # atoms likewise, atom_modify sort)
        from demstep.packings import spatial_order

        x = x[spatial_order(x, 2.0 * spec["radius"])]
    particles = Particles.from_density(x, np.full(len(x), spec["radius"]), spec["density"])
    common = dict(mu=spec["mu"], restitution=spec["restitution"])
    if spec.get("law", "linear") == "hertz":
        law = HertzMindlin(youngs_modulus=spec["youngs_modulus"],
                           poisson_ratio=spec["poisson_ratio"], **common)
    else:
        law = LinearSpring(k_n=spec["k_n"], k_s=spec["k_s"], **common)
    walls = []
    for w in spec["walls"]:
        point = np.zeros(3)
        point[w["axis"]] = w["pos"]
        normal = np.zeros(3)
        normal[w["axis"]] = w["sense"]
        walls.append(Wall(point, normal))
    meshes = []
    for m in spec.get("meshes", []):
        from demstep.engine.meshes import MeshWall
        from demstep.mesh import mesh_from_arrays

        meshes.append(MeshWall(mesh_from_arrays(m["vertices"], m["triangles"], name=m["name"]),
                               name=m["name"], omega=m["omega"], center=m["center"]))
    return Simulation(particles, law, walls, gravity=spec["gravity"], timestep=timestep,
                      skin=spec["skin"], meshes=meshes)


DEMSTEP_CHILD = r"""
import json, sys, time
from pathlib import Path
import numpy as np
import demstep  # before numba.set_num_threads: demstep chooses the threading layer
import numba
from demstep.engine import TimeStep

folder, threads, warmup, steps, dump = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5] == "1"
sys.path.insert(0, sys.argv[6])
from peers import demstep_simulation
numba.set_num_threads(threads)
spec = json.loads((folder / "spec.json").read_text())
x = np.load(folder / "x.npy")
t_setup = time.perf_counter()
sim = demstep_simulation(x, spec, TimeStep.fixed(spec["dt"]))
if warmup:
    sim.run(steps=warmup)
t_setup = time.perf_counter() - t_setup
rebuilds0 = sim.lists.n_rebuilds
c0, t0 = time.process_time(), time.perf_counter()
sim.run(steps=steps)
elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
if dump:
    np.save(folder / "final_demstep_x.npy", sim.x)
    np.save(folder / "final_demstep_v.npy", sim.v)
    np.save(folder / "final_demstep_wall_force.npy", sim.wall_force)
print("BENCH_RESULT " + json.dumps({
    "elapsed": elapsed, "cpu_s": cpu, "steps": steps, "n": len(x), "threads": numba.get_num_threads(),
    "threading_layer": numba.threading_layer(), "setup_s": t_setup,
    "rebuilds": sim.lists.n_rebuilds - rebuilds0, "contacts": sim.n_contacts,
    "demstep": str(Path(demstep.__file__).parent)}), flush=True)
"""


def demstep_command(folder, threads, warmup, steps, dump, demstep_src):
    env = dict(os.environ)
    if demstep_src:
        env["PYTHONPATH"] = str(demstep_src) + os.pathsep + env.get("PYTHONPATH", "")
    cmd = [sys.executable, "-c", DEMSTEP_CHILD, str(folder), str(threads), str(warmup),
           str(steps), "1" if dump else "0", str(HERE)]
    return cmd, env, threads


# ----------------------------------------------------------------------------- LIGGGHTS
def write_data_file(folder: Path, x, spec, types: int, style: str = ""):
    """The LAMMPS data file ``data.bench`` both LIGGGHTS (atom_style granular) and LAMMPS
    (atom_style sphere) read: id type diameter density x y z, every sphere of type 1;
    ``types`` atom types declared (LIGGGHTS: 2, the walls' material the second),
    ``style`` the Atoms section's style comment ("sphere" for LAMMPS)."""
    lo, hi = spec["domain_lo"], spec["domain_hi"]
    rows = np.empty((len(x), 7))
    rows[:, 0] = np.arange(1, len(x) + 1)
    rows[:, 1] = 1
    rows[:, 2] = 2.0 * spec["radius"]
    rows[:, 3] = spec["density"]
    rows[:, 4:] = x
    with open(folder / "data.bench", "w") as f:
        f.write("demstep peers benchmark\n\n")
        f.write(f"{len(x)} atoms\n{types} atom types\n\n")
        for k, a in enumerate("xyz"):
            f.write(f"{_g(lo[k])} {_g(hi[k])} {a}lo {a}hi\n")
        f.write(f"\nAtoms{' # ' + style if style else ''}\n\n")
        np.savetxt(f, rows, fmt=["%d", "%d", "%.17g", "%.17g", "%.17g", "%.17g", "%.17g"])


def _g(v):
    return "%.17g" % float(v)


def write_stl(path: Path, vertices, triangles):
    """An ASCII STL of the triangles (meshio's writer), as LIGGGHTS' ``fix mesh/surface``
    reads it."""
    import meshio

    meshio.write_points_cells(str(path), np.asarray(vertices, float),
                              [("triangle", np.asarray(triangles))], file_format="stl", binary=False)


def liggghts_input(spec, warmup, steps, dump):
    """The LIGGGHTS script. Atom type 1: the spheres; type 2: the walls' material (so that
    the sphere-wall dashpot can differ from the sphere-sphere one, as in demstep)."""
    kn, ks, mu, muw = spec["k_n"], spec["k_s"], spec["mu"], spec["mu_wall"]
    if spec["restitution"] is None:
        g11 = g12 = 0.0
    else:
        # hooke/stiffness, absolute_damping off: c_n = meff * gamman, meff = m/2 for two
        # spheres, m for sphere-wall; demstep: c_n = 2 beta sqrt(m* k_n)
        m = spec["mass"]
        g11 = spec["c_pp"] / (0.5 * m)
        g12 = spec["c_pw"] / m
    model = "model hooke/stiffness tangential history"
    if spec.get("law", "linear") == "hertz":
        model = "model hertz tangential history"
        e, nu = spec["youngs_modulus"], spec["poisson_ratio"]
        rest = 1.0 if spec["restitution"] is None else spec["restitution"]
        materials = [
            f"fix m1 all property/global youngsModulus peratomtype {e!r} {e!r}",
            f"fix m2 all property/global poissonsRatio peratomtype {nu!r} {nu!r}",
            f"fix m3 all property/global coefficientRestitution peratomtypepair 2 {rest!r} {rest!r} {rest!r} {rest!r}",
            f"fix m5 all property/global coefficientFriction peratomtypepair 2 {mu!r} {muw!r} {muw!r} {muw!r}",
        ]
    else:
        materials = [
            f"fix m1 all property/global kn peratomtypepair 2 {kn!r} {kn!r} {kn!r} {kn!r}",
            f"fix m2 all property/global kt peratomtypepair 2 {ks!r} {ks!r} {ks!r} {ks!r}",
            f"fix m3 all property/global gamman peratomtypepair 2 {g11!r} {g12!r} {g12!r} {g12!r}",
            "fix m4 all property/global gammat peratomtypepair 2 0.0 0.0 0.0 0.0",
            f"fix m5 all property/global coefficientFriction peratomtypepair 2 {mu!r} {muw!r} {muw!r} {muw!r}",
        ]
    lines = [
        "atom_style granular",
        "atom_modify map array",
        "boundary f f f",
        "newton off",
        "communicate single vel yes",
        "units si",
        "read_data data.bench",
        f"neighbor {spec['skin']!r} bin",
        "neigh_modify delay 0",
        f"pair_style gran {model} tangential_damping off",
        "pair_coeff * *",
        *materials,
    ]
    for i, w in enumerate(spec["walls"]):
        plane = "xyz"[w["axis"]] + "plane"
        lines.append(f"fix wall{i} all wall/gran {model} primitive type 2 {plane} {w['pos']!r} "
                     f"tangential_damping off")
    if spec.get("meshes"):
        # the same triangles (written by liggghts_command), the walls' material, moving
        # meshes turned about their centre at the same rate
        names = []
        for i, m in enumerate(spec["meshes"]):
            lines.append(f"fix cad{i} all mesh/surface file mesh{i}.stl type 2")
            names.append(f"cad{i}")
        lines.append(f"fix meshwalls all wall/gran {model} mesh n_meshes {len(names)} meshes "
                     f"{' '.join(names)} tangential_damping off")
        for i, m in enumerate(spec["meshes"]):
            w = math.sqrt(sum(c * c for c in m["omega"]))
            if w > 0:
                axis = " ".join(repr(c / w) for c in m["omega"])
                origin = " ".join(repr(float(c)) for c in m["center"])
                lines.append(f"fix move{i} all move/mesh mesh cad{i} rotate origin {origin} "
                             f"axis {axis} period {2.0 * math.pi / w!r}")
    gx, gy, gz = spec["gravity"]
    gmag = math.sqrt(gx * gx + gy * gy + gz * gz)
    if gmag > 0:
        lines.append(f"fix gravi all gravity {gmag!r} vector {gx / gmag!r} {gy / gmag!r} {gz / gmag!r}")
    lines += [
        "fix integr all nve/sphere",
        f"timestep {spec['dt']!r}",
        "thermo_style custom step atoms ke",
        "thermo_modify lost ignore norm no",
        f"thermo {max(1, steps)}",
    ]
    if warmup:
        lines.append(f"run {warmup}")
    if dump:
        lines += [f"dump dfin all custom {steps} final.dump id x y z vx vy vz",
                  "dump_modify dfin sort id"]
    # CPU time of the timed run: /proc/<liggghts>/stat before and after (process 0 only)
    lines += ["shell sh cpustat.sh cpu_before.txt", f"run {steps}", "shell sh cpustat.sh cpu_after.txt"]
    return "\n".join(lines) + "\n"


# copies /proc/<pid>/stat of the nearest ancestor named liggghts* to the file $1
CPUSTAT_SH = """p=$PPID
while [ "$p" -gt 1 ]; do
  comm=$(cut -d' ' -f2 /proc/$p/stat)
  case "$comm" in *liggghts*) cat /proc/$p/stat > "$1"; exit 0;; esac
  p=$(cut -d' ' -f4 /proc/$p/stat)
done
"""


def liggghts_cpu(folder: Path):
    """CPU seconds (user + system) of LIGGGHTS process 0 during the timed run, or None."""
    try:
        before, after = ((folder / f).read_text().rsplit(")", 1)[1].split()
                         for f in ("cpu_before.txt", "cpu_after.txt"))
    except (OSError, IndexError):
        return None
    # fields after the command name: state is field 3 of stat, utime 14, stime 15
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(after[11]) + int(after[12]) - int(before[11]) - int(before[12])) / ticks


def liggghts_command(folder, x, spec, threads, warmup, steps, dump):
    write_data_file(folder, x, spec, types=2)
    for i, m in enumerate(spec.get("meshes", [])):
        write_stl(folder / f"mesh{i}.stl", np.asarray(m["vertices"]), np.asarray(m["triangles"]))
    (folder / "in.bench").write_text(liggghts_input(spec, warmup, steps, dump))
    (folder / "cpustat.sh").write_text(CPUSTAT_SH)
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [shutil.which("liggghts"), "-in", "in.bench", "-log", "log.bench"]
    if threads > 1:
        env.update(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1")
        cmd = [shutil.which("mpirun"), "-np", str(threads), "--oversubscribe"] + cmd
    return cmd, env, threads


LOOP_RE = re.compile(r"Loop time of ([0-9.eE+-]+) on (\d+) procs for (\d+) steps with (\d+) atoms")


def liggghts_result(stdout, steps, name="LIGGGHTS"):
    """The timed run's "Loop time" line (LIGGGHTS' and LAMMPS' have the same format)."""
    loops = LOOP_RE.findall(stdout)
    timed = [lp for lp in loops if int(lp[2]) == steps]
    if not timed:
        raise RuntimeError(f"{name}: no 'Loop time' line for the timed run:\n" + stdout[-3000:])
    t, procs, nsteps, natoms = timed[-1]
    out = {"elapsed": float(t), "steps": int(nsteps), "n": int(natoms), "threads": int(procs)}
    m = re.search(r"Neighbor list builds = (\d+)", stdout.split("Loop time")[-1])
    if m:
        out["rebuilds"] = int(m.group(1))
    return out


# ----------------------------------------------------------------------------- LAMMPS
def lammps_skip(spec):
    """Why LAMMPS does not run the problem ``spec`` (None: it does)."""
    if spec["problem"] in MESH_PROBLEMS:
        return (f"lammps: the {spec['problem']} problem's triangle meshes are not set up in "
                "LAMMPS (its 2021 release has no STL mesh walls)")
    if spec.get("law", "linear") == "hertz":
        return ("lammps: --law hertz not set up: LAMMPS' Hertz dashpots (tsuji, viscoelastic) are "
                "not LIGGGHTS'/demstep's, and its 2021 fix wall/gran hertz/material takes "
                "E/(2(1-nu)) for the wall's E*, not E/(2(1-nu^2))")
    return None


def lammps_input(spec, warmup, steps, dump):
    """The LAMMPS script (pair_style granular, linear springs only: see :func:`lammps_skip`).
    ``hooke KN ETA ... damping velocity``: F_n = KN delta + ETA v_n, ETA absolute, so
    ETA = demstep's c_n (c_pp between spheres, c_pw on the walls, 0 without
    restitution); ``tangential linear_history KT XGAMMAT MU``: the tangential dashpot is
    XGAMMAT x ETA, and demstep has none (XGAMMAT = 0)."""
    reason = lammps_skip(spec)
    if reason:
        raise SystemExit(reason)
    kn, ks, mu, muw = spec["k_n"], spec["k_s"], spec["mu"], spec["mu_wall"]
    eta_pp, eta_pw = (0.0, 0.0) if spec["restitution"] is None else (spec["c_pp"], spec["c_pw"])

    def model(eta, friction):
        return (f"hooke {_g(kn)} {_g(eta)} tangential linear_history {_g(ks)} 0 {_g(friction)} "
                "damping velocity")

    lines = [
        "units si",
        "atom_style sphere",
        "boundary f f f",
        "comm_modify vel yes",
        "read_data data.bench",
        f"neighbor {_g(spec['skin'])} bin",
        # LAMMPS' default (delay 10 every 1 check yes) would let contacts close unseen
        "neigh_modify delay 0 every 1 check yes",
        "pair_style granular",
        f"pair_coeff * * {model(eta_pp, mu)}",
    ]
    # one fix per axis with its lower and upper plane (a sphere meets the nearer one only:
    # the boxes are wider than a diameter), NULL for a missing one
    by_axis = {}
    for w in spec["walls"]:
        side = "lo" if w["sense"] > 0 else "hi"
        planes = by_axis.setdefault(w["axis"], {})
        if side in planes:
            raise SystemExit(f"lammps: two {side} walls on axis {w['axis']}")
        planes[side] = w["pos"]
    for axis, planes in sorted(by_axis.items()):
        if "lo" in planes and "hi" in planes and planes["hi"] - planes["lo"] < 4.0 * spec["radius"]:
            raise SystemExit("lammps: walls closer than two diameters in one fix wall/gran")
        lo, hi = (_g(planes[k]) if k in planes else "NULL" for k in ("lo", "hi"))
        plane = "xyz"[axis] + "plane"
        lines.append(f"fix wall{plane[0]} all wall/gran granular {model(eta_pw, muw)} {plane} {lo} {hi}")
    gx, gy, gz = spec["gravity"]
    gmag = math.sqrt(gx * gx + gy * gy + gz * gz)
    if gmag > 0:
        # the vector is the force's direction
        lines.append(f"fix gravi all gravity {_g(gmag)} vector {_g(gx / gmag)} {_g(gy / gmag)} {_g(gz / gmag)}")
    lines += [
        "fix integr all nve/sphere",
        f"timestep {_g(spec['dt'])}",
        "thermo_style custom step atoms ke",
        "thermo_modify lost ignore norm no",
        f"thermo {max(1, steps)}",
    ]
    if warmup:
        lines.append(f"run {warmup}")
    # CPU time of the timed run: /proc/<lmp>/stat before and after (process 0 only)
    lines += ["shell sh cpustat.sh cpu_before.txt", f"run {steps}", "shell sh cpustat.sh cpu_after.txt"]
    if dump:  # the final state, after the timed run
        lines.append("write_dump all custom final.dump id x y z vx vy vz modify sort id")
    return "\n".join(lines) + "\n"


def lammps_executable():
    return shutil.which("lmp") or shutil.which("lmp_serial") or shutil.which("lmp_mpi")


def lammps_command(folder, x, spec, threads, warmup, steps, dump):
    write_data_file(folder, x, spec, types=1, style="sphere")
    (folder / "in.bench").write_text(lammps_input(spec, warmup, steps, dump))
    exe = lammps_executable()
    (folder / "cpustat.sh").write_text(CPUSTAT_SH.replace("*liggghts*", f"*{Path(exe).name[:15]}*"))
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [exe, "-nocite", "-in", "in.bench", "-log", "log.bench"]
    if threads > 1:
        env.update(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1")
        cmd = [shutil.which("mpirun"), "-np", str(threads), "--oversubscribe"] + cmd
    return cmd, env, threads


# ----------------------------------------------------------------------------- YADE
YADE_SCRIPT = r"""
import json, math, sys, time
import numpy as np
from yade import utils

folder = FOLDER
spec = json.load(open(folder + "/spec.json"))
x = np.load(folder + "/x.npy")
warmup, steps, dump = WARMUP, STEPS, DUMP
r, rho, kn, ks = spec["radius"], spec["density"], spec["k_n"], spec["k_s"]
if spec["restitution"] is None:
    # linear springs with explicit stiffness: FrictPhys with kn, ks given by value
    mat = O.materials.append(FrictMat(young=kn / r, poisson=ks / kn, density=rho,
                                      frictionAngle=math.atan(spec["mu"])))
    wmat = O.materials.append(FrictMat(young=kn / r, poisson=ks / kn, density=rho,
                                       frictionAngle=math.atan(spec["mu_wall"])))
    ip2 = Ip2_FrictMat_FrictMat_FrictPhys(kn=MatchMaker(algo="val", val=kn),
                                          ks=MatchMaker(algo="val", val=ks))
    law = Law2_ScGeom_FrictPhys_CundallStrack()
else:
    # linear spring-dashpot with explicit kn, ks, cn, cs; ViscElPhys combines the two
    # materials' values in series (1/k = 1/k1 + 1/k2): spheres carry 2 kn, 2 ks, 2 c_pp
    # so that sphere-sphere gives kn, ks, c_pp; the wall material gives c_pw against a sphere
    c_pp, c_pw = spec["c_pp"], spec["c_pw"]
    mat = O.materials.append(ViscElMat(kn=2 * kn, ks=2 * ks, cn=2 * c_pp, cs=0.0, density=rho,
                                       frictionAngle=math.atan(spec["mu"])))
    wmat = O.materials.append(ViscElMat(kn=2 * kn, ks=2 * ks, cn=1.0 / (1.0 / c_pw - 0.5 / c_pp),
                                        cs=0.0, density=rho, frictionAngle=math.atan(spec["mu_wall"])))
    ip2 = Ip2_ViscElMat_ViscElMat_ViscElPhys()
    law = Law2_ScGeom_ViscElPhys_Basic()
t_setup = time.perf_counter()
O.bodies.append([utils.sphere((float(p[0]), float(p[1]), float(p[2])), r, material=mat) for p in x])
for w in spec["walls"]:
    pos = [0.0, 0.0, 0.0]
    pos[w["axis"]] = w["pos"]
    O.bodies.append(utils.wall(tuple(pos), axis=w["axis"], sense=w["sense"], material=wmat))
O.engines = [
    ForceResetter(),
    InsertionSortCollider([Bo1_Sphere_Aabb(), Bo1_Wall_Aabb()], verletDist=0.5 * spec["skin"]),
    InteractionLoop([Ig2_Sphere_Sphere_ScGeom(), Ig2_Wall_Sphere_ScGeom()], [ip2], [law]),
    NewtonIntegrator(damping=0.0, gravity=tuple(spec["gravity"])),
]
O.dt = spec["dt"]
if warmup:
    O.run(warmup, True)
t_setup = time.perf_counter() - t_setup
c0, t0 = time.process_time(), time.perf_counter()
O.run(steps, True)
elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
if dump:
    n = len(x)
    np.save(folder + "/final_yade_x.npy", np.array([list(O.bodies[i].state.pos) for i in range(n)]))
    np.save(folder + "/final_yade_v.npy", np.array([list(O.bodies[i].state.vel) for i in range(n)]))
contacts = sum(1 for i in O.interactions if i.isReal)
print("BENCH_RESULT " + json.dumps({"elapsed": elapsed, "cpu_s": cpu, "steps": steps, "n": len(x),
      "threads": int(__import__("os").environ.get("OMP_NUM_THREADS", "1")),
      "setup_s": t_setup, "contacts": contacts}), flush=True)
"""


def yade_command(folder, threads, warmup, steps, dump):
    script = (YADE_SCRIPT.replace("FOLDER", repr(str(folder))).replace("WARMUP", str(warmup))
              .replace("STEPS", str(steps)).replace("DUMP", "True" if dump else "False"))
    (folder / "bench_yade.py").write_text(script)
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    env.pop("DISPLAY", None)
    cmd = [shutil.which("yade"), "-j", str(threads), "-n", "-x", str(folder / "bench_yade.py")]
    return cmd, env, threads


# ----------------------------------------------------------------------------- running
def _busy_seconds():
    import psutil

    t = psutil.cpu_times()
    return sum(t) - t.idle - getattr(t, "iowait", 0.0)


def wait_idle(limit_s, threshold=0.2):
    """Wait (at most ``limit_s``) until other processes use less than ``threshold`` of
    the machine's CPUs over a 2 s window; returns the last busy fraction seen."""
    import psutil

    t_end = time.time() + limit_s
    while True:
        busy = psutil.cpu_percent(interval=2.0) / 100.0
        if busy < threshold or time.time() >= t_end:
            return busy
        time.sleep(3.0)


def run_measured(cmd, env, cwd, timeout):
    """Run ``cmd``; returns (rc, stdout, stderr, peak RSS [MB], wall time [s], foreign
    load: the CPU time other processes used during the run / (wall time x CPUs))."""
    import psutil

    out_path, err_path = Path(cwd) / "stdout.txt", Path(cwd) / "stderr.txt"
    with open(out_path, "w") as fo, open(err_path, "w") as fe:
        busy0 = _busy_seconds()
        self0 = sum(os.times()[:2])  # this driver (its sampling thread) is not foreign
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, cwd=cwd, stdout=fo, stderr=fe)
        peak = [0]
        done = threading.Event()

        def sample():
            try:
                root = psutil.Process(proc.pid)
            except psutil.Error:
                return
            while not done.is_set():
                total = 0
                try:
                    procs = [root] + root.children(recursive=True)
                except psutil.Error:
                    procs = []
                for p in procs:
                    try:
                        if p.name() in LAUNCHERS:
                            continue
                        total += p.memory_info().rss
                    except psutil.Error:
                        pass
                peak[0] = max(peak[0], total)
                # every 0.1 s: a scan of the process tree costs ~1.5 ms of CPU, which
                # at 50 Hz took 7 % of a core from two-thread runs (measured)
                done.wait(0.1)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        deadline = t0 + timeout
        rusage = None
        while True:
            pid, status, ru = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                proc.returncode = os.waitstatus_to_exitcode(status)
                rusage = ru
                break
            if time.perf_counter() > deadline:
                proc.kill()
                _, status, ru = os.wait4(proc.pid, 0)
                proc.returncode = -9
                rusage = ru
                break
            time.sleep(0.05)
        wall = time.perf_counter() - t0
        done.set()
        sampler.join()
        busy = _busy_seconds() - busy0 - (sum(os.times()[:2]) - self0)
    maxrss = rusage.ru_maxrss * 1024 if rusage else 0  # Linux: kB
    rss_mb = max(peak[0], maxrss) / 2**20
    own = (rusage.ru_utime + rusage.ru_stime) if rusage else 0.0
    foreign = max(0.0, busy - own) / (wall * (os.cpu_count() or 1))
    return proc.returncode, out_path.read_text(), err_path.read_text(), rss_mb, wall, foreign


def parse_tagged(stdout):
    for line in reversed(stdout.splitlines()):
        if line.startswith(RESULT_TAG):
            return json.loads(line[len(RESULT_TAG):])
    raise RuntimeError("no result line in the output:\n" + stdout[-3000:])


def available(code):
    if code == "demstep":
        return True
    if code == "liggghts":
        return shutil.which("liggghts") is not None
    if code == "yade":
        return shutil.which("yade") is not None
    if code == "lammps":
        return lammps_executable() is not None
    return False


def mpi_available():
    return shutil.which("mpirun") is not None


def run_once(code, workdir, x, spec, threads, warmup, steps, dump, demstep_src, timeout,
             idle_wait=0.0):
    """One measurement of ``code`` in its own process, in a fresh folder."""
    folder = Path(tempfile.mkdtemp(prefix=f"{code}-", dir=workdir))
    write_problem(folder, x, spec)
    if code == "demstep":
        cmd, env, used = demstep_command(folder, threads, warmup, steps, dump, demstep_src)
    elif code == "liggghts":
        cmd, env, used = liggghts_command(folder, x, spec, threads, warmup, steps, dump)
    elif code == "lammps":
        cmd, env, used = lammps_command(folder, x, spec, threads, warmup, steps, dump)
    else:
        cmd, env, used = yade_command(folder, threads, warmup, steps, dump)
    if idle_wait > 0:
        wait_idle(idle_wait)
    load1 = os.getloadavg()[0]
    rc, out, err, rss, wall, foreign = run_measured(cmd, env, folder, timeout)
    if rc != 0:
        raise RuntimeError(f"{code} failed (exit {rc}) in {folder}:\n{out[-2000:]}\n{err[-3000:]}")
    if code == "liggghts":
        res = liggghts_result(out, steps)
        if res["n"] != spec["n"]:
            raise RuntimeError(f"LIGGGHTS lost {spec['n'] - res['n']} of {spec['n']} atoms "
                               f"(left the domain) in {folder}")
        cpu = liggghts_cpu(folder)
        if cpu is not None and res["threads"] == 1:
            res["cpu_s"] = cpu
    elif code == "lammps":
        res = liggghts_result(out, steps, "LAMMPS")
        if res["n"] != spec["n"]:
            raise RuntimeError(f"LAMMPS lost {spec['n'] - res['n']} of {spec['n']} atoms "
                               f"(left the domain) in {folder}")
        cpu = liggghts_cpu(folder)  # the same /proc/<pid>/stat files
        if cpu is not None and res["threads"] == 1:
            res["cpu_s"] = cpu
    else:
        res = parse_tagged(out)
    res.update(rss_mb=rss, wall_s=wall, folder=str(folder), load1=load1, foreign_load=foreign)
    return res


def benchmark(args):
    workdir = Path(tempfile.mkdtemp(prefix="demstep-peers-"))
    x, spec = make_problem(args.problem, args.n, args.skin, args.law, args.order)
    codes = [c for c in args.codes.split(",") if c]
    notes = []
    if args.law == "hertz" and "yade" in codes:
        codes.remove("yade")
    if args.problem in MESH_PROBLEMS and "yade" in codes:
        codes.remove("yade")
        notes.append(f"yade: the {args.problem} problem's meshes are not set up in YADE")
    if "lammps" in codes and lammps_skip(spec):
        codes.remove("lammps")
        notes.append(lammps_skip(spec))
    todo = []
    for code in codes:
        if not available(code):
            notes.append(f"{code}: not installed, skipped")
        elif code in ("liggghts", "lammps") and args.threads > 1 and not mpi_available():
            notes.append(f"{code}: MPI code and no mpirun found: not measured with > 1 process")
        else:
            todo.append(code)
    # repeats interleaved (code A, B, C, A, B, C, ...) so that any load from other
    # processes on the machine falls on every code alike
    runs = {code: [] for code in todo}
    for rep in range(args.repeat):
        for code in todo:
            discarded = []
            while True:
                res = run_once(code, workdir, x, spec, args.threads, args.warmup, args.steps, False,
                               args.demstep_src, args.timeout, args.idle_wait)
                res["psps"] = res["n"] * res["steps"] / res["elapsed"]
                if res["foreign_load"] <= args.max_foreign or len(discarded) >= args.retries:
                    break
                discarded.append(res)
                print(f"  {code:9s} run {rep + 1}/{args.repeat}: other processes used "
                      f"{100 * res['foreign_load']:.0f} % of the machine: repeated",
                      file=sys.stderr, flush=True)
            if discarded:  # out of retries: keep the least disturbed attempt
                res = min(discarded + [res], key=lambda r: r["foreign_load"])
            res["discarded"] = len(discarded)
            runs[code].append(res)
            if not args.json:
                print(f"  {code:9s} run {rep + 1}/{args.repeat}: {res['elapsed']:.3f} s "
                      f"({res['psps']:.4g} particle-steps/s, {res['rss_mb']:.0f} MB, "
                      f"foreign load {100 * res['foreign_load']:.0f} %)", file=sys.stderr, flush=True)
    results = []
    for code in todo:
        psps = [r["psps"] for r in runs[code]]
        entry = {"code": code, "psps_median": statistics.median(psps),
                 "rss_mb": max(r["rss_mb"] for r in runs[code]),
                 "rss_mb_runs": [round(r["rss_mb"], 1) for r in runs[code]],
                 "psps_min": min(psps), "psps_max": max(psps), "n": runs[code][0]["n"],
                 "threads": runs[code][0]["threads"], "steps": args.steps,
                 "elapsed_s": [r["elapsed"] for r in runs[code]],
                 "foreign_load": [round(r["foreign_load"], 3) for r in runs[code]],
                 "discarded_runs": sum(r["discarded"] for r in runs[code])}
        if all("cpu_s" in r for r in runs[code]):
            entry["cpu_s"] = [r["cpu_s"] for r in runs[code]]
            if entry["threads"] == 1:
                # one thread: CPU time of the timed run barely depends on other load
                entry["psps_cpu_median"] = statistics.median(
                    r["n"] * r["steps"] / r["cpu_s"] for r in runs[code])
        for key in ("rebuilds", "contacts", "threading_layer"):
            if key in runs[code][-1]:
                entry[key] = runs[code][-1][key]
        results.append(entry)
    by = {r["code"]: r for r in results}
    ratio = ratio_lammps = None
    if "demstep" in by and "liggghts" in by:
        ratio = by["demstep"]["psps_median"] / by["liggghts"]["psps_median"]
    if "demstep" in by and "lammps" in by:
        ratio_lammps = by["demstep"]["psps_median"] / by["lammps"]["psps_median"]
    if not args.keep:
        shutil.rmtree(workdir, ignore_errors=True)
    return {"problem": args.problem, "n": spec["n"], "threads": args.threads, "results": results,
            "ratio_vs_liggghts": ratio, "ratio_vs_lammps": ratio_lammps}, notes, spec


def print_table(report, notes, spec):
    print(f"problem {report['problem']}: N = {report['n']}, {spec['shape']} "
          f"(dt = {spec['dt']:.6g}, skin = {spec['skin']:g}), threads {report['threads']}")
    head = (f"{'code':10s} {'N':>8s} {'threads':>7s} {'particle-steps/s (median, min-max)':>38s} "
            f"{'peak MB':>8s} {'vs LIGGGHTS':>11s} {'foreign load':>12s} {'p-s/CPU-s':>10s}")
    print(head)
    print("-" * len(head))
    lig = next((r for r in report["results"] if r["code"] == "liggghts"), None)
    for r in report["results"]:
        rel = f"{r['psps_median'] / lig['psps_median']:.3f}" if lig else "-"
        rng = f"{r['psps_median']:.4g} ({r['psps_min']:.4g}-{r['psps_max']:.4g})"
        fl = "max {:.0f} %".format(100 * max(r["foreign_load"]))
        cpu = f"{r['psps_cpu_median']:.4g}" if "psps_cpu_median" in r else "-"
        print(f"{r['code']:10s} {r['n']:8d} {r['threads']:7d} {rng:>38s} {r['rss_mb']:8.0f} {rel:>11s} "
              f"{fl:>12s} {cpu:>10s}")
    if report["ratio_vs_liggghts"] is not None:
        print(f"demstep / LIGGGHTS = {report['ratio_vs_liggghts']:.3f} (wall clock)")
    if report.get("ratio_vs_lammps") is not None:
        print(f"demstep / LAMMPS = {report['ratio_vs_lammps']:.3f} (wall clock)")
    print("foreign load: CPU used by other processes during a run / (wall time x CPUs); "
          "p-s/CPU-s: particle-steps per CPU second of the timed run (1 thread)")
    for note in notes:
        print("note:", note)


# ----------------------------------------------------------------------------- check
def read_liggghts_dump(path, n):
    lines = Path(path).read_text().splitlines()
    last = max(i for i, line in enumerate(lines) if line.startswith("ITEM: ATOMS"))
    cols = lines[last].split()[2:]
    data = np.array([list(map(float, line.split())) for line in lines[last + 1:last + 1 + n]])
    data = data[np.argsort(data[:, cols.index("id")])]
    return (data[:, [cols.index(c) for c in ("x", "y", "z")]],
            data[:, [cols.index(c) for c in ("vx", "vy", "vz")]])


def observables(x0, x, v, spec):
    """Code-independent measures computed from the final state alone."""
    m, r, kn = spec["mass"], spec["radius"], spec["k_n"]
    ke = 0.5 * m * float((v * v).sum())
    disp = np.linalg.norm(x - x0, axis=1)
    out = {"ke_translational": ke, "max_displacement": float(disp.max()),
           "rms_displacement": float(np.sqrt((disp**2).mean())), "mean_z": float(x[:, 2].mean())}
    if spec["problem"] == "dense":
        top = next(w for w in spec["walls"] if w["axis"] == 0 and w["sense"] == -1)
        overlap = np.maximum(0.0, r - (top["pos"] - x[:, 0]))
        out["wall_force_xplus"] = float(kn * overlap.sum())  # elastic normal force on x+
    elif spec["problem"] == "settle":
        floor = next(w for w in spec["walls"] if w["axis"] == 2)
        out["floor_contacts"] = int((x[:, 2] - floor["pos"] < r).sum())
    elif spec["problem"] == "hopper":
        out["discharged"] = int((x[:, 2] < 0.0).sum())  # below the outlet
    else:  # drum: the bed's centre, which the turning drum carries up its rising side
        out["mean_x"] = float(x[:, 0].mean())
    return out


def check(args):
    workdir = Path(tempfile.mkdtemp(prefix="demstep-check-"))
    codes = [c for c in args.codes.split(",") if c and available(c)]
    report = {}
    for problem in (args.problem,) if args.problem in MESH_PROBLEMS else ("dense", "settle"):
        x0, spec = make_problem(problem, args.n, args.skin, args.law)
        finals = {}
        for code in codes:
            if code == "lammps" and lammps_skip(spec):
                print("note:", lammps_skip(spec), file=sys.stderr)
                continue
            res = run_once(code, workdir, x0, spec, 1, 0, args.steps, True, args.demstep_src,
                           args.timeout)
            folder = Path(res["folder"])
            if code in ("liggghts", "lammps"):  # the same dump format
                x, v = read_liggghts_dump(folder / "final.dump", spec["n"])
            else:
                x, v = np.load(folder / f"final_{code}_x.npy"), np.load(folder / f"final_{code}_v.npy")
            finals[code] = (x, v)
            obs = observables(x0, x, v, spec)
            if code == "demstep" and problem == "dense":
                wf = np.load(folder / "final_demstep_wall_force.npy")
                k = next(i for i, w in enumerate(spec["walls"]) if w["axis"] == 0 and w["sense"] == -1)
                obs["demstep_wall_force_xplus_total"] = float(wf[k, 0])
            report.setdefault(problem, {"n": spec["n"], "steps": args.steps})[code] = obs
        ref = "demstep" if "demstep" in finals else codes[0]
        xr, _ = finals[ref]
        scale = np.sqrt((np.linalg.norm(xr - x0, axis=1) ** 2).mean())
        for code, (x, _) in finals.items():
            diff = np.linalg.norm(x - xr, axis=1)
            report[problem][code]["rms_position_diff_vs_" + ref] = float(np.sqrt((diff**2).mean()))
            report[problem][code]["rms_position_diff_relative"] = float(np.sqrt((diff**2).mean()) / scale)
    if not args.keep:
        shutil.rmtree(workdir, ignore_errors=True)
    return report


def print_check(report):
    for problem, rows in report.items():
        print(f"{problem}: N = {rows['n']}, {rows['steps']} steps from rest (no warm-up)")
        codes = [c for c in rows if c not in ("n", "steps")]
        keys = list(dict.fromkeys(k for c in codes for k in rows[c]))
        print(f"  {'quantity':34s}" + "".join(f"{c:>16s}" for c in codes))
        for k in keys:
            vals = "".join(f"{rows[c][k]:16.6g}" if k in rows[c] else f"{'-':>16s}" for c in codes)
            print(f"  {k:34s}{vals}")


# ----------------------------------------------------------------------------- main
def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problem", choices=("dense", "settle") + MESH_PROBLEMS, default="dense")
    ap.add_argument("--law", choices=("linear", "hertz"), default="linear")
    ap.add_argument("--order", choices=("lattice", "shuffled"), default="lattice",
                    help="the spheres' order in memory and in the peers' input files")
    ap.add_argument("--n", type=int, default=None, help="target number of spheres (nearest feasible)")
    ap.add_argument("--threads", type=int, default=1,
                    help="demstep numba threads, LIGGGHTS and LAMMPS MPI ranks, YADE OpenMP threads")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--warmup", type=int, default=10, help="untimed steps before the timed run")
    ap.add_argument("--skin", type=float, default=None, help="Verlet skin for every code (default 0.15 r)")
    ap.add_argument("--codes", default=",".join(CODES))
    ap.add_argument("--demstep-src", default=None,
                    help="folder put first on PYTHONPATH of the demstep child (e.g. a snapshot's src/)")
    ap.add_argument("--timeout", type=float, default=3600.0, help="per-run limit [s]")
    ap.add_argument("--idle-wait", type=float, default=0.0,
                    help="before each run wait up to this many seconds for the machine to be idle")
    ap.add_argument("--max-foreign", type=float, default=1.0,
                    help="repeat a run when other processes used more than this fraction of the "
                         "machine's CPUs during it (e.g. 0.1 on a shared machine)")
    ap.add_argument("--retries", type=int, default=3, help="repeats allowed per run for --max-foreign")
    ap.add_argument("--keep", action="store_true", help="keep the work folders")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--check", action="store_true", help="physics agreement on a small case instead")
    args = ap.parse_args(argv)
    if args.demstep_src:
        sys.path.insert(0, str(Path(args.demstep_src).resolve()))
        args.demstep_src = str(Path(args.demstep_src).resolve())
    if args.check:
        args.n = args.n or 500
        report = check(args)
        if args.json:
            print(json.dumps(report, indent=1))
        else:
            print_check(report)
        return
    args.n = args.n or 100_000
    report, notes, spec = benchmark(args)
    if args.json:
        print(json.dumps(report))
    else:
        print_table(report, notes, spec)


if __name__ == "__main__":
    main()
