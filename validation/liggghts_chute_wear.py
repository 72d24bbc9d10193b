"""LIGGGHTS' chute_wear tutorial run in LIGGGHTS and in demstep, wear included.

    python validation/liggghts_chute_wear.py [--seeds 3] [--every 100] [--no-impacts]
                                             [--out FILE] [--keep]

Needs Debian's ``liggghts`` and ``liggghts-doc`` (the tutorial and its STL meshes under
/usr/share/doc/liggghts/examples/LIGGGHTS/Tutorials_public/chute_wear). The tutorial: a
stream of spheres (r = 1.5 and 2.5 mm, 30 % and 70 % of the mass) inserted from a face
at 0.1 kg/s falls onto a curved mesh trough and slides down it for 1 s (100,000 steps);
``fix mesh/surface/stress ... wear finnie`` with ``k_finnie 1.0`` accumulates Finnie's
wear on each triangle of the trough.

LIGGGHTS runs the tutorial copied to a temporary folder with its physics unchanged:
only the dumps' intervals are changed (the particles every 10,000 steps instead of 200;
the mesh, with its per-triangle wear, every 1,000 steps instead of 200: 100 files, not
500) and, for the runs after the first, its four random seeds replaced by other primes
above 10,000 (the first run uses the tutorial's own). demstep runs
``examples/liggghts_tutorials/chute_wear.toml`` with its inserter's ``seed`` 1, 2, ...
(``--every K`` adds a second set of demstep runs with the inserter acting every K
steps). One thread each (NUMBA_NUM_THREADS=1; one serial LIGGGHTS process), one run at
a time.

What is compared, per seed and as each code's mean and scatter (sample standard
deviation) over the seeds:

* every 1,000 steps: the particles in the run (inserted less those that left the
  domain) and their kinetic energy (translation and rotation), from LIGGGHTS' thermo
  output and demstep's history.csv; the mass inserted (LIGGGHTS' insertion messages,
  demstep's ``stream.inserted_mass``);
* every 1,000 steps: the total wear of the trough, the sum over its triangles of wear x
  area [J with k = 1], from LIGGGHTS' mesh VTK files (legacy VTK, CELL_DATA field
  ``wear``) and demstep's ``chute.wear`` column;
* at the end: how the wear is spread along the trough: each triangle's wear x area
  binned by the position of its centroid along the trough's axis (the distance from
  its upper end, 25 mm bins), as fractions of the total; the share of the triangles
  under the inlet face; the worn area.

``--no-impacts`` skips a deterministic check of the law itself: 147 spheres (r = 2.5
mm) on a grid just above the trough, all thrown at it at once with the same velocity
(straight down at 2 m/s, as the stream hits it; and at 2 m/s, 10 degrees to its
floor, downstream), run 1,000 steps (10 ms: the impact and the slide after it) in
both codes from the same positions; the total wear and each triangle's wear are
compared one for one.

Results: ``validation/results/liggghts_chute_wear.json``; summarised in
``docs/validation-wear.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

os.environ["NUMBA_NUM_THREADS"] = "1"   # (demstep single-threaded, here and in the runs)
os.environ["OMP_NUM_THREADS"] = "1"

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "validation"))
from liggghts_tutorials import demstep_stage_seconds, liggghts_thermo  # noqa: E402

TUTORIAL = Path("/usr/share/doc/liggghts/examples/LIGGGHTS/Tutorials_public/chute_wear")
CASE = ROOT / "examples" / "liggghts_tutorials" / "chute_wear.toml"
#: the random seeds in in.chute_wear (two particle templates, the distribution, the
#: insertion)
TUTORIAL_SEEDS = (15485863, 15485867, 32452843, 32452867)
#: the case's inserter acts every this many steps (the tutorial's insert_every is 1000)
CASE_EVERY = 100

# The trough: its floor falls along AXIS (22.9 degrees below -x: the floor's line
# z = 0.4219 x - 0.1077 fitted to the STL's vertices at y = 0); positions along it are
# measured from UPPER, the floor's point at the trough's upper end (x = 0.05).
SLOPE = 0.42191
AXIS = np.array([-1.0, 0.0, -SLOPE]) / np.hypot(1.0, SLOPE)
UPPER = np.array([0.05, 0.0, SLOPE * 0.05 - 0.10769])
BIN = 0.025  # [m] bins along the axis
#: the inlet face's footprint (x, y) [m]: triangles whose centroid lies under it
INLET_X, INLET_Y = (-0.035, 0.0), (-0.035, 0.035)


# --------------------------------------------------------------------- helpers
def is_prime(n: int) -> bool:
    if n < 2:
        return False
    k = 2
    while k * k <= n:
        if n % k == 0:
            return False
        k += 1
    return True


def liggghts_seeds(index: int) -> tuple[int, ...]:
    """The tutorial's seeds for run 0; for run i > 0, four primes above 10,000 (the
    first primes from 10,000 + 100,000 i + 1,000 j, j = 0..3)."""
    if index == 0:
        return TUTORIAL_SEEDS
    out = []
    for j in range(4):
        n = 10_000 + 100_000 * index + 1_000 * j
        while not is_prime(n):
            n += 1
        out.append(n)
    return tuple(out)


def read_liggghts_mesh_vtk(path: Path) -> dict:
    """Triangles (T, 3, 3) and cell fields of a LIGGGHTS ``dump mesh/gran/VTK`` file
    (legacy ASCII polydata, version 5.1: POLYGONS with OFFSETS and CONNECTIVITY, or the
    older rows "3 i j k"; CELL_DATA as a FIELD of arrays ``name ncomp ntuples type``)."""
    tok = path.read_text().split()
    i = tok.index("POINTS")
    n_pts = int(tok[i + 1])
    pts = np.array(tok[i + 3:i + 3 + 3 * n_pts], dtype=float).reshape(n_pts, 3)
    i = tok.index("POLYGONS", i)
    if tok[i + 3] == "OFFSETS":
        n_off, n_conn = int(tok[i + 1]), int(tok[i + 2])
        j = tok.index("CONNECTIVITY", i)
        offsets = np.array(tok[i + 5:i + 5 + n_off], dtype=np.int64)
        conn = np.array(tok[j + 2:j + 2 + n_conn], dtype=np.int64)
        if not np.all(np.diff(offsets) == 3):
            raise ValueError(f"{path}: not all polygons are triangles")
        tri = conn.reshape(-1, 3)
        k = j + 2 + n_conn
    else:
        n_cells = int(tok[i + 1])
        rows = np.array(tok[i + 3:i + 3 + 4 * n_cells], dtype=np.int64).reshape(n_cells, 4)
        if not np.all(rows[:, 0] == 3):
            raise ValueError(f"{path}: not all polygons are triangles")
        tri = rows[:, 1:]
        k = i + 3 + 4 * n_cells
    cells = {}
    k = tok.index("CELL_DATA", k)
    n_cells = int(tok[k + 1])
    if tok[k + 2] == "FIELD":
        n_arrays = int(tok[k + 4])
        k += 5
        for _ in range(n_arrays):
            name, comps, n = tok[k], int(tok[k + 1]), int(tok[k + 2])
            cells[name] = np.array(tok[k + 4:k + 4 + comps * n], dtype=float).reshape(n, comps)
            k += 4 + comps * n
    if len(tri) != n_cells:
        raise ValueError(f"{path}: {len(tri)} triangles, {n_cells} cells")
    return {"tri": pts[tri], **{name: a[:, 0] if a.shape[1] == 1 else a
                                for name, a in cells.items()}}


def read_demstep_meshes_vtu(path: Path) -> dict:
    import meshio

    m = meshio.read(path)
    tri = np.asarray(m.points, dtype=float)[np.asarray(m.cells_dict["triangle"])]
    return {"tri": tri, "wear": np.asarray(m.cell_data["wear"][0], dtype=float)}


def areas_centroids(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return area, tri.mean(axis=1)


def wear_spread(tri: np.ndarray, wear: np.ndarray) -> dict:
    """The total wear (sum of wear x area) and how it is spread: fractions per bin along
    the trough's axis, the share under the inlet, the worn area and the largest
    triangle's wear."""
    area, c = areas_centroids(tri)
    worn = wear * area
    total = float(worn.sum())
    s = (c - UPPER) @ AXIS
    edges = np.arange(0.0, s.max() + BIN, BIN)
    hist, _ = np.histogram(np.clip(s, 0.0, None), bins=edges, weights=worn)
    under = ((c[:, 0] >= INLET_X[0]) & (c[:, 0] <= INLET_X[1])
             & (c[:, 1] >= INLET_Y[0]) & (c[:, 1] <= INLET_Y[1]))
    return {"total": total,
            "bin_edges": [float(e) for e in edges],
            "fractions": [float(h / total) if total > 0 else 0.0 for h in hist],
            "under_inlet_fraction": float(worn[under].sum() / total) if total > 0 else 0.0,
            "worn_area": float(area[wear > 0].sum()),
            "worn_triangles": int((wear > 0).sum()),
            "max_wear": float(wear.max()),
            "mean_position": float((worn * s).sum() / total) if total > 0 else float("nan")}


def run(cmd, cwd=None) -> float:
    start = time.perf_counter()
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        sys.exit(f"{cmd[0]} failed in {cwd}: {proc.stdout[-2000:]}{proc.stderr[-2000:]}")
    return elapsed


# -------------------------------------------------------------------- LIGGGHTS
def liggghts_inserted(log_text: str) -> dict[int, float]:
    """The mass inserted so far [kg] after each insertion step, from LIGGGHTS'
    'inserted N particle templates (mass m) at step S - a total of ... (mass M)'."""
    out = {}
    for m in re.finditer(r"at step (\d+)\s*\n\s*- a total of \d+ particle templates \(mass "
                         r"([0-9.eE+-]+)\)", log_text):
        out[int(m.group(1))] = float(m.group(2))
    return out


def liggghts_masses(log_text: str) -> dict[int, float]:
    """The mass in the run [kg] at each thermo step (the column v_mtot added to the
    tutorial's thermo_style)."""
    out, col = {}, None
    for line in log_text.splitlines():
        words = line.split()
        if words[:2] == ["Step", "Atoms"]:
            # (LIGGGHTS heads the column "mtot")
            col = next((words.index(c) for c in ("v_mtot", "mtot") if c in words), None)
        elif words[:2] == ["Loop", "time"]:
            col = None
        elif col is not None and len(words) > col:
            try:
                out[int(words[0])] = float(words[col])
            except ValueError:
                pass
    return out


def liggghts_input(seeds: tuple[int, ...]) -> str:
    text = (TUTORIAL / "in.chute_wear").read_text()
    for old, new in ((r"custom/vtk 200 ", "custom/vtk 10000 "),
                     (r"mesh/gran/VTK 200 ", "mesh/gran/VTK 1000 "),
                     ("thermo_style  custom step atoms ke c_1 vol",
                      "variable      mtot equal mass(all)\n"
                      "thermo_style  custom step atoms ke c_1 vol v_mtot")):
        text, n = re.subn(re.escape(old), new, text)
        assert n == 1, old
    for old, new in zip(TUTORIAL_SEEDS, seeds):
        text, n = re.subn(rf"\b{old}\b", str(new), text)
        assert n == 1, old
    return text


def run_liggghts(index: int, work: Path) -> dict:
    seeds = liggghts_seeds(index)
    dest = work / f"liggghts-{index}"
    shutil.copytree(TUTORIAL, dest)
    (dest / "in.chute_wear").write_text(liggghts_input(seeds))
    (dest / "post").mkdir(exist_ok=True)
    seconds = run(["liggghts", "-in", "in.chute_wear", "-log", "log.liggghts"], cwd=dest)
    log = (dest / "log.liggghts").read_text()
    thermo = liggghts_thermo(log)
    mass = liggghts_masses(log)
    inserted = liggghts_inserted(log)
    frames = {int(p.stem.split("_")[-1]): p for p in (dest / "post").glob("mesh_*.vtk")}
    area = None
    rows = []
    for step in sorted(s for s in thermo if s > 0 and s % 1000 == 0):
        n, ke, er = thermo[step]
        mesh = read_liggghts_mesh_vtk(frames[step])
        if area is None:
            area, _ = areas_centroids(mesh["tri"])
        ins = max((m for s, m in inserted.items() if s <= step), default=0.0)
        rows.append({"step": step, "particles": n, "mass": mass[step], "ke": ke, "erot": er,
                     "inserted_mass": ins, "wear": float((mesh["wear"] * area).sum())})
    last = read_liggghts_mesh_vtk(frames[max(frames)])
    return {"index": index, "seeds": list(seeds), "seconds": seconds, "rows": rows,
            "spread": wear_spread(last["tri"], last["wear"]), "_dir": str(dest),
            "_final": last}


# --------------------------------------------------------------------- demstep
def demstep_case_text(seed: int, every: int | None) -> str:
    text = CASE.read_text()
    text, n = re.subn(r"(?m)^seed = 1\b", f"seed = {seed}", text)
    assert n == 1
    if every is not None:  # (the inserter's line: the outlets' have no comment)
        text, n = re.subn(r"(?m)^every = \d+(?=\s+# \[steps\])", f"every = {every}", text)
        assert n == 1
    return text


def run_demstep(seed: int, work: Path, every: int | None = None) -> dict:
    from demstep.io.history import read_history

    tag = f"demstep-{seed}" + (f"-every{every}" if every else "")
    case = work / f"{tag}.toml"
    case.write_text(demstep_case_text(seed, every))
    out = work / tag
    seconds = run([sys.executable, "-m", "demstep.cli", "run", str(case), "--out", str(out),
                   "--quiet"])
    h = read_history(out / "history.csv")
    removed = sum(np.asarray(h[k], dtype=float) for k in h if k.endswith(".removed_mass"))
    rows = []
    for i, step in enumerate(h["step"]):
        rows.append({"step": int(step), "particles": int(h["particles"][i]),
                     "mass": float(h["stream.inserted_mass"][i] - removed[i]),
                     "ke": float(h["kinetic_translational"][i]),
                     "erot": float(h["kinetic_rotational"][i]),
                     "inserted_mass": float(h["stream.inserted_mass"][i]),
                     "wear": float(h["chute.wear"][i])})
    frames = sorted((out / "vtk").glob("meshes_*.vtu"))
    last = read_demstep_meshes_vtu(frames[-1])
    return {"seed": seed, "every": every or CASE_EVERY, "seconds": seconds,
            "stage_seconds": demstep_stage_seconds(out), "rows": rows,
            "spread": wear_spread(last["tri"], last["wear"]), "_dir": str(out),
            "_final": last}


# ------------------------------------------------------------------ statistics
def stats(values) -> dict:
    a = np.asarray(values, dtype=float)
    return {"mean": float(a.mean()), "std": float(a.std(ddof=1)) if len(a) > 1 else 0.0,
            "min": float(a.min()), "max": float(a.max())}


def summarise(runs: list[dict]) -> dict:
    """Per step: each quantity's mean, standard deviation and range over the runs."""
    steps = sorted(set.intersection(*[{r["step"] for r in run["rows"]} for run in runs]))
    out = []
    for s in steps:
        rows = [next(r for r in run["rows"] if r["step"] == s) for run in runs]
        out.append({"step": s, **{k: stats([r[k] for r in rows])
                                  for k in ("particles", "mass", "ke", "erot",
                                            "inserted_mass", "wear")}})
    n_bins = min(len(run["spread"]["fractions"]) for run in runs)
    spread = {"bin_edges": runs[0]["spread"]["bin_edges"][:n_bins + 1],
              "fractions": [stats([run["spread"]["fractions"][b] for run in runs])
                            for b in range(n_bins)]}
    for k in ("total", "under_inlet_fraction", "worn_area", "worn_triangles", "max_wear",
              "mean_position"):
        spread[k] = stats([run["spread"][k] for run in runs])
    # the wear rate while the flow is steady (0.5 s to the end): a line fitted to each run
    rates = []
    for run in runs:
        t = np.array([r["step"] * 1e-5 for r in run["rows"] if r["step"] >= 50000])
        w = np.array([r["wear"] for r in run["rows"] if r["step"] >= 50000])
        rates.append(float(np.polyfit(t, w, 1)[0]))
    return {"rows": out, "spread": spread, "wear_rate_after_0.5s": stats(rates),
            "seconds": stats([run["seconds"] for run in runs])}


# -------------------------------------------------------------------- impacts
IMPACT_R = 0.0025
IMPACT_STEPS = 1000   # (10 ms: the impacts and the slide after them)
SLIDE_STEPS = 5000    # (50 ms of sliding and rolling down the floor)


def trough_height(x: np.ndarray, y: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """The lowest height of the trough's surface over each point (x, y) (vertical rays
    against the triangles)."""
    out = np.full(len(x), np.nan)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    for k, (px, py) in enumerate(zip(x, y)):
        d = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
        l1 = ((b[:, 1] - c[:, 1]) * (px - c[:, 0]) + (c[:, 0] - b[:, 0]) * (py - c[:, 1])) / d
        l2 = ((c[:, 1] - a[:, 1]) * (px - c[:, 0]) + (a[:, 0] - c[:, 0]) * (py - c[:, 1])) / d
        l3 = 1.0 - l1 - l2
        inside = (l1 >= 0) & (l2 >= 0) & (l3 >= 0) & (np.abs(d) > 1e-14)
        z = l1 * a[:, 2] + l2 * b[:, 2] + l3 * c[:, 2]
        out[k] = z[inside].min()
    return out


def impact_setup(tri: np.ndarray, gap: float) -> np.ndarray:
    """147 sphere centres on a 10 mm grid (x from -0.25 to -0.05 m, y from -0.03 to
    0.03 m), each ``gap`` (along the vertical) clear of the trough's floor."""
    gx, gy = np.meshgrid(np.arange(-0.25, -0.0499, 0.01), np.arange(-0.03, 0.0301, 0.01),
                         indexing="ij")
    x, y = gx.ravel(), gy.ravel()
    cos_a = 1.0 / np.hypot(1.0, SLOPE)
    z = trough_height(x, y, tri) + IMPACT_R / cos_a + gap
    return np.c_[x, y, z]


def impact_cases() -> dict:
    """name: (velocity, vertical gap, steps): thrown straight down at 2 m/s (as the
    stream hits the trough), at 2 m/s 10 degrees to its floor, downstream, and put on the
    floor (0.05 mm clear) sliding down it at 1 m/s."""
    up = np.array([-SLOPE, 0.0, 1.0]) / np.hypot(1.0, SLOPE)   # the floor's normal
    a = np.radians(10.0)
    return {"vertical": (np.array([0.0, 0.0, -2.0]), 0.001, IMPACT_STEPS),
            "grazing_10deg": (2.0 * (np.cos(a) * AXIS - np.sin(a) * up), 0.001, IMPACT_STEPS),
            "sliding_1ms": (1.0 * AXIS, 0.00005, SLIDE_STEPS)}


def liggghts_head(region: str) -> str:
    """The start of a LIGGGHTS input with the chute_wear tutorial's material, contact
    model, wear constant and step, in a box ``region`` ('xlo xhi ylo yhi zlo zhi' [m])."""
    return f"""atom_style    granular
atom_modify   map array
boundary      f f f
newton        off
communicate   single vel yes
units         si
region        domain block {region} units box
create_box    1 domain
neighbor      0.002 bin
neigh_modify  delay 0
fix  m1 all property/global youngsModulus peratomtype 5.e6
fix  m2 all property/global poissonsRatio peratomtype 0.45
fix  m3 all property/global coefficientRestitution peratomtypepair 1 0.3
fix  m4 all property/global coefficientFriction peratomtypepair 1 0.5
fix  m5 all property/global k_finnie peratomtypepair 1 1.0
pair_style  gran model hertz tangential history
pair_coeff  * *
timestep    0.00001
"""


def liggghts_impact(name: str, x: np.ndarray, v: np.ndarray, steps: int, work: Path) -> dict:
    dest = work / f"liggghts-impact-{name}"
    shutil.copytree(TUTORIAL / "meshes", dest / "meshes")
    (dest / "post").mkdir()
    atoms = "\n".join(f"create_atoms 1 single {p[0]:.17g} {p[1]:.17g} {p[2]:.17g} units box"
                      for p in x)
    (dest / "in.impact").write_text(f"""# the chute_wear tutorial's material and mesh; spheres thrown at the trough
{liggghts_head('-0.5 0.1 -0.2 0.2 -0.4 0.15')}fix  gravi all gravity 9.81 vector 0.0 0.0 -1.0
fix  cad all mesh/surface/stress file meshes/simple_chute.stl type 1 wear finnie
fix  granwalls all wall/gran model hertz tangential history mesh n_meshes 1 meshes cad
{atoms}
set  type 1 diameter {2 * IMPACT_R:.17g}
set  type 1 density 2500
velocity all set {v[0]:.17g} {v[1]:.17g} {v[2]:.17g} units box
fix  integr all nve/sphere
compute       1 all erotate/sphere
thermo_style  custom step atoms ke c_1
thermo        100
thermo_modify lost ignore norm no
dump   dumpstress all mesh/gran/VTK {steps} post/mesh_*.vtk stress wear cad
run    {steps}
""")
    seconds = run(["liggghts", "-in", "in.impact", "-log", "log.liggghts"], cwd=dest)
    mesh = read_liggghts_mesh_vtk(dest / "post" / f"mesh_{steps}.vtk")
    thermo = liggghts_thermo((dest / "log.liggghts").read_text())
    return {"tri": mesh["tri"], "wear": mesh["wear"], "seconds": seconds,
            "particles_end": thermo[max(thermo)][0], "ke_end": thermo[max(thermo)][1]}


def demstep_impact(x: np.ndarray, v: np.ndarray, steps: int) -> dict:
    from demstep.case import load_case
    from demstep.case.build import build_law, build_meshes
    from demstep.engine import Simulation, TimeStep
    from demstep.kernels.dem import COUNT_PAIR_CONTACTS
    from demstep.particles import Particles

    case = load_case(CASE)
    law = build_law(case)
    sim = Simulation(Particles.from_density(x, np.full(len(x), IMPACT_R), 2500.0), law,
                     meshes=build_meshes(case, law), velocities=np.tile(v, (len(x), 1)),
                     gravity=[0.0, 0.0, -9.81], timestep=TimeStep.fixed(1e-5), skin=0.002)
    start = time.perf_counter()
    pair_contacts = 0
    for _ in range(steps // 10):
        sim.run(steps=10)
        pair_contacts = max(pair_contacts, int(sim.counters[COUNT_PAIR_CONTACTS]))
    seconds = time.perf_counter() - start
    v_end = np.asarray(sim.v)
    m = 2500.0 * 4.0 / 3.0 * np.pi * IMPACT_R ** 3
    return {"tri": sim.meshes.tri.reshape(-1, 3, 3).copy(), "wear": np.array(sim.meshes.wear),
            "seconds": seconds, "pair_contacts_max": pair_contacts,
            "ke_end": float(0.5 * m * (v_end ** 2).sum())}


def match_triangles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The index in ``b`` of each triangle of ``a`` (by centroid; both read from the same
    STL file, LIGGGHTS' written as floats)."""
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(b.mean(axis=1)).query(a.mean(axis=1))
    if dist.max() > 1e-5 or len(set(idx)) != len(idx):
        raise ValueError(f"triangles do not match (largest centroid distance {dist.max():.3g})")
    return idx


def impacts(work: Path) -> dict:
    from demstep.mesh import read_mesh

    chute = read_mesh(TUTORIAL / "meshes" / "simple_chute.stl")
    tri = chute.vertices[chute.triangles]
    out = {"radius": IMPACT_R, "cases": {}}
    for name, (v, gap, steps) in impact_cases().items():
        x = impact_setup(tri, gap)
        lig = liggghts_impact(name, x, v, steps, work)
        dem = demstep_impact(x, v, steps)
        idx = match_triangles(lig["tri"], dem["tri"])
        wl, wd = lig["wear"], dem["wear"][idx]
        area, _ = areas_centroids(lig["tri"])
        both = (wl > 0) | (wd > 0)
        ratio = wd[both & (wl > 0)] / wl[both & (wl > 0)]
        out["cases"][name] = {
            "spheres": len(x), "velocity": [float(c) for c in v], "gap": gap, "steps": steps,
            "total_liggghts": float((wl * area).sum()), "total_demstep": float((wd * area).sum()),
            "worn_triangles_liggghts": int((wl > 0).sum()),
            "worn_triangles_demstep": int((wd > 0).sum()),
            "worn_by_one_code_only": int(((wl > 0) != (wd > 0)).sum()),
            "wear_of_those_liggghts": float((wl * area)[(wl > 0) & (wd == 0)].sum()),
            "wear_of_those_demstep": float((wd * area)[(wd > 0) & (wl == 0)].sum()),
            "triangle_ratio_demstep_over_liggghts": {
                "median": float(np.median(ratio)) if len(ratio) else None,
                "p10": float(np.percentile(ratio, 10)) if len(ratio) else None,
                "p90": float(np.percentile(ratio, 90)) if len(ratio) else None},
            "ke_end_liggghts": lig["ke_end"], "ke_end_demstep": dem["ke_end"],
            "particles_end_liggghts": lig["particles_end"],
            "pair_contacts_max_demstep": dem["pair_contacts_max"],
            "seconds_liggghts": lig["seconds"], "seconds_demstep": dem["seconds"]}
    return out


# ---------------------------------------------------------- one sphere, a plate
PLATE_STEPS = 150
FOLD_STEPS = 3000
M_SPHERE = 2500.0 * 4.0 / 3.0 * np.pi * IMPACT_R ** 3


def plate_stl(fold_deg: float | None = None) -> str:
    """A plate of two triangles (z = 0, 0.2 x 0.2 m); with ``fold_deg``, two squares of
    two triangles each, x from -0.1 to 0 flat and x from 0 to 0.1 rising at fold_deg
    (> 0: a concave fold, < 0: a convex ridge, 0: coplanar)."""
    if fold_deg is None:
        quads = [[(-0.1, -0.1, 0.0), (0.1, -0.1, 0.0), (0.1, 0.1, 0.0), (-0.1, 0.1, 0.0)]]
    else:
        h = 0.1 * math.tan(math.radians(fold_deg))
        quads = [[(-0.1, -0.1, 0.0), (0.0, -0.1, 0.0), (0.0, 0.1, 0.0), (-0.1, 0.1, 0.0)],
                 [(0.0, -0.1, 0.0), (0.1, -0.1, h), (0.1, 0.1, h), (0.0, 0.1, 0.0)]]
    out = ["solid plate"]
    for a, b, c, d in quads:
        for tri in ((a, b, c), (a, c, d)):
            out += ["facet normal 0 0 1", " outer loop"]
            out += [f"  vertex {p[0]:.12g} {p[1]:.12g} {p[2]:.12g}" for p in tri]
            out += [" endloop", "endfacet"]
    return "\n".join(out + ["endsolid plate", ""])


def finnie_f(sin_g: float, cos_g: float) -> float:
    return cos_g * cos_g / 3.0 if (cos_g <= 1e-12 or 3.0 * sin_g > cos_g) else \
        2.0 * sin_g * cos_g - 3.0 * sin_g * sin_g


def plate_liggghts(name: str, stl: str, x0, v, gravity: bool, steps: int, work: Path) -> dict:
    """One sphere (r = 2.5 mm, the tutorial's material and wear law) on the plate
    ``stl``: per step its height, velocity along x and z, the contact force on it
    (thermo's force less its weight) and its spin, from the thermo output; the plate's
    wear (wear x area per triangle) at the end, and its total at every step when
    ``steps`` is short (a mesh dump per step)."""
    dest = work / f"liggghts-plate-{name}"
    (dest / "post").mkdir(parents=True)
    (dest / "plate.stl").write_text(stl)
    every = 1 if steps <= PLATE_STEPS else steps
    (dest / "in.plate").write_text(f"""# one sphere on a plate: the chute_wear tutorial's material and wear law
{liggghts_head('-0.1 0.1 -0.1 0.1 -0.05 0.05')}{"fix  gravi all gravity 9.81 vector 0.0 0.0 -1.0" if gravity else ""}
fix  cad all mesh/surface/stress file plate.stl type 1 wear finnie
fix  granwalls all wall/gran model hertz tangential history mesh n_meshes 1 meshes cad
create_atoms 1 single {x0[0]:.17g} {x0[1]:.17g} {x0[2]:.17g} units box
set  type 1 diameter {2 * IMPACT_R:.17g}
set  type 1 density 2500
velocity all set {v[0]:.17g} {v[1]:.17g} {v[2]:.17g} units box
fix  integr all nve/sphere
variable z equal z[1]
variable vx equal vx[1]
variable vz equal vz[1]
variable fx equal fx[1]
variable fz equal fz[1]
variable wy equal omegay[1]
thermo_style  custom step v_z v_vx v_vz v_fx v_fz v_wy
thermo_modify format float %.12g
thermo        1
dump   dumpstress all mesh/gran/VTK {every} post/mesh_*.vtk wear cad
run    {steps}
""")
    run(["liggghts", "-in", "in.plate", "-log", "log.liggghts"], cwd=dest)
    rows, header = [], None
    for line in (dest / "log.liggghts").read_text().splitlines():
        w = line.split()
        if w[:2] == ["Step", "z"]:
            header = w
        elif w[:2] == ["Loop", "time"]:
            header = None
        elif header and len(w) == len(header):
            try:
                rows.append([float(c) for c in w])
            except ValueError:
                pass
    rows = np.array(rows)[1:]  # step z vx vz fx fz wy, from step 1
    if gravity:
        rows[:, 5] += M_SPHERE * 9.81
    wear = []
    for step in rows[:, 0].astype(int):
        if step % every == 0:
            mesh = read_liggghts_mesh_vtk(dest / "post" / f"mesh_{step}.vtk")
            area, centroid = areas_centroids(mesh["tri"])
            wear.append(float((mesh["wear"] * area).sum()))
    return {"rows": rows, "wear": np.array(wear), "triangle_wear": mesh["wear"] * area,
            "centroid": centroid}


def plate_demstep(stl: str, x0, v, gravity: bool, steps: int) -> dict:
    """The same in demstep, step by step (the force on the sphere from the mesh)."""
    from demstep.case import load_case
    from demstep.case.build import build_law
    from demstep.engine import Simulation, TimeStep
    from demstep.engine.meshes import MeshWall
    from demstep.mesh import read_mesh
    from demstep.particles import Particles

    law = build_law(load_case(CASE))
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "plate.stl").write_text(stl)
        plate = read_mesh(Path(tmp) / "plate.stl")
    sim = Simulation(Particles.from_density(np.array([x0]), np.array([IMPACT_R]), 2500.0),
                     law, meshes=[MeshWall(plate, name="plate", finnie_k=1.0)],
                     velocities=[list(v)], gravity=[0.0, 0.0, -9.81 if gravity else 0.0],
                     timestep=TimeStep.fixed(1e-5), skin=0.002)
    rows, wear = [], []
    for _ in range(steps):
        sim.run(steps=1)
        f = -np.asarray(sim.mesh_force[0])
        rows.append([sim.step, sim.x[0, 2], sim.v[0, 0], sim.v[0, 2], f[0], f[2], sim.w[0, 1]])
        wear.append(float(sim.mesh_wear[0]))
    tri = sim.meshes.tri.reshape(-1, 3, 3)
    area, centroid = areas_centroids(tri)
    return {"rows": np.array(rows), "wear": np.array(wear),
            "triangle_wear": np.array(sim.meshes.wear) * area, "centroid": centroid}


def recomputed_wear(rows: np.ndarray) -> dict:
    """LIGGGHTS' wear of a sphere on the flat plate (normal +z) recomputed by the law
    from its thermo rows: |F| the contact force, and the velocity at the force
    evaluation v(n+1/2) = v(n+1) - dt F_total / 2m (the thermo's v is v(n+1)), or, for
    contrast, v(n+1)."""
    dt = 1e-5
    out = {"v_half": 0.0, "v_after": 0.0}
    for step, z, vx, vz, fx, fz, wy in rows:
        f_mag = math.hypot(fx, fz)
        if f_mag == 0.0:
            continue
        for key, (ux, uz) in (("v_half", (vx - 0.5 * dt * fx / M_SPHERE,
                                          vz - 0.5 * dt * fz / M_SPHERE)),
                              ("v_after", (vx, vz))):
            if uz > 0.0:   # (moving away from the plate: no wear)
                continue
            speed = math.hypot(ux, uz)
            out[key] += 2.0 * 1.0 * f_mag * speed * finnie_f(abs(uz) / speed, abs(ux) / speed) * dt
    return out


def plate_checks(work: Path) -> dict:
    """One sphere, both codes, step by step.

    Impacts: thrown at a flat plate at 2 m/s, 10 and 67 degrees from it (67: the
    stream's impact on the 22.9-degree trough), no gravity, 150 steps. LIGGGHTS' wear is
    recomputed from its own force and velocity by the law, to check the formula and
    which velocity it takes; each code's wear, that of the contact's first ten steps,
    and the largest |F_t| / F_n while the sphere approaches.

    Folds: put on the flat half of a plate folded along x = 0 (coplanar, a 0.5 and a 2
    degree concave fold, a 0.5 degree convex ridge), sliding at 1 m/s towards the fold,
    with gravity, 3,000 steps: the wear of the second half and the largest contact force
    along x within 3 mm of the fold, over the sphere's weight (LIGGGHTS starts a new
    contact, and its tangential history, on a triangle that is not coplanar with the
    last one)."""
    out = {}
    for gamma in (10.0, 67.0):
        g = np.radians(gamma)
        v = (2.0 * np.cos(g), 0.0, -2.0 * np.sin(g))
        x0 = (-0.05, 0.03, IMPACT_R + 0.0001)
        lig = plate_liggghts(f"impact{gamma:g}", plate_stl(), x0, v, False, PLATE_STEPS, work)
        dem = plate_demstep(plate_stl(), x0, v, False, PLATE_STEPS)

        def ratio(rows):  # while the sphere approaches the plate (where wear counts)
            on = (rows[:, 5] > 1e-9) & (rows[:, 3] < 0.0)
            return float(np.max(np.abs(rows[on, 4]) / rows[on, 5]))

        def first_steps(rows, wear):  # the wear of the contact's first ten steps
            first = int(np.argmax(np.abs(rows[:, 5]) > 0))
            return float(wear[first + 9])
        again = recomputed_wear(lig["rows"])
        out[f"impact_{gamma:g}deg"] = {
            "velocity": [float(c) for c in v],
            "wear_liggghts": float(lig["wear"][-1]),
            "wear_liggghts_recomputed_v_half": again["v_half"],
            "wear_liggghts_recomputed_v_after": again["v_after"],
            "wear_demstep": float(dem["wear"][-1]),
            "wear_first_10_steps_liggghts": first_steps(lig["rows"], lig["wear"]),
            "wear_first_10_steps_demstep": first_steps(dem["rows"], dem["wear"]),
            "max_ft_over_fn_approach_liggghts": ratio(lig["rows"]),
            "max_ft_over_fn_approach_demstep": ratio(dem["rows"]),
            "vx_end_liggghts": float(lig["rows"][-1, 2]), "vx_end_demstep": float(dem["rows"][-1, 2]),
            "vz_end_liggghts": float(lig["rows"][-1, 3]), "vz_end_demstep": float(dem["rows"][-1, 3]),
            "spin_end_liggghts": float(lig["rows"][-1, 6]),
            "spin_end_demstep": float(dem["rows"][-1, 6])}
    for fold in (0.0, 0.5, 2.0, -0.5):
        x0, v = (-0.01, 0.0, IMPACT_R), (1.0, 0.0, 0.0)
        lig = plate_liggghts(f"fold{fold:g}", plate_stl(fold), x0, v, True, FOLD_STEPS, work)
        dem = plate_demstep(plate_stl(fold), x0, v, True, FOLD_STEPS)
        entry = {"fold_deg": fold}
        for code, r in (("liggghts", lig), ("demstep", dem)):
            rows = r["rows"]
            # around the crossing (the centre within 3 mm of x = 0: from x(t) ~ -0.01 + vx t)
            x = -0.01 + np.cumsum(rows[:, 2]) * 1e-5
            near = np.abs(x) < 0.003
            second = r["centroid"][:, 0] > 0.0
            entry[f"wear_second_half_{code}"] = float(r["triangle_wear"][second].sum())
            entry[f"wear_first_half_{code}"] = float(r["triangle_wear"][~second].sum())
            entry[f"max_fx_over_weight_crossing_{code}"] = float(
                np.max(np.abs(rows[near, 4])) / (M_SPHERE * 9.81)) if near.any() else None
            entry[f"vx_end_{code}"] = float(rows[-1, 2])
            entry[f"spin_end_{code}"] = float(rows[-1, 6])
        out[f"fold_{fold:+g}deg"] = entry
    return out


# ------------------------------------------------------------------------ main
def print_summary(result: dict) -> None:
    lig, dem = result["liggghts"]["summary"], result["demstep"]["summary"]
    print(f"\n{'step':>7} {'N lig':>12} {'N dem':>12} {'KE lig [mJ]':>14} {'KE dem [mJ]':>14}"
          f" {'wear lig [mJ]':>14} {'wear dem [mJ]':>14}")
    for a, b in zip(lig["rows"], dem["rows"]):
        if a["step"] % 10000:
            continue
        f = lambda s, k=1.0: f"{s['mean'] * k:8.2f}±{s['std'] * k:<5.2f}"  # noqa: E731
        print(f"{a['step']:>7} {f(a['particles']):>12} {f(b['particles']):>12} "
              f"{f(a['ke'], 1e3):>14} {f(b['ke'], 1e3):>14} {f(a['wear'], 1e3):>14} "
              f"{f(b['wear'], 1e3):>14}")
    for name, s in (("LIGGGHTS", lig), ("demstep", dem)):
        sp = s["spread"]
        print(f"{name}: under the inlet {sp['under_inlet_fraction']['mean']:.3f}"
              f"±{sp['under_inlet_fraction']['std']:.3f}, mean position "
              f"{sp['mean_position']['mean']:.4f} m, wear rate after 0.5 s "
              f"{s['wear_rate_after_0.5s']['mean'] * 1e3:.2f}±"
              f"{s['wear_rate_after_0.5s']['std'] * 1e3:.2f} mJ/s, wall "
              f"{s['seconds']['mean']:.1f} s")
        print("  fractions along the trough: " + " ".join(
            f"{f['mean']:.3f}" for f in sp["fractions"]))


def rounded(obj, digits: int = 7):
    """``obj`` with its floats rounded to ``digits`` significant digits (a smaller
    results file; the measurements are not that precise)."""
    if isinstance(obj, float):
        return float(f"{obj:.{digits}g}") if math.isfinite(obj) else obj
    if isinstance(obj, dict):
        return {k: rounded(v, digits) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [rounded(v, digits) for v in obj]
    return obj


def compact_json(obj, indent: str = "") -> str:
    """JSON with one line per innermost dict or list (rows, statistics, bins)."""
    def flat(o):
        return not isinstance(o, (dict, list)) or not any(
            isinstance(v, (dict, list)) and not flat_leaf(v)
            for v in (o.values() if isinstance(o, dict) else o))

    def flat_leaf(o):
        return all(not isinstance(v, (dict, list))
                   for v in (o.values() if isinstance(o, dict) else o))
    if not isinstance(obj, (dict, list)) or flat_leaf(obj):
        return json.dumps(obj)
    inner = indent + " "
    if isinstance(obj, dict):
        items = [f"{inner}{json.dumps(k)}: {compact_json(v, inner)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + indent + "}"
    return "[\n" + ",\n".join(inner + compact_json(v, inner) for v in obj) + "\n" + indent + "]"


def markdown_tables(result: dict) -> str:
    """The tables of docs/validation-wear.md from a results file."""
    lig, dem = result["liggghts"]["summary"], result["demstep"]["summary"]
    key = next((k for k in result if k.startswith("demstep_every")), None)
    var = result[key]["summary"] if key else None
    label = f"demstep, every {key[len('demstep_every'):]}" if key else ""
    pm = lambda s, k=1.0, f=".2f": f"{s['mean'] * k:{f}} ± {s['std'] * k:{f}}"  # noqa: E731
    out = ["| step | t [s] | particles LIGGGHTS | demstep | mass in the run LIGGGHTS [g] | "
           "demstep [g] | KE LIGGGHTS [mJ] | demstep [mJ] | E_rot LIGGGHTS [mJ] | demstep [mJ] |",
           "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for a, b in zip(lig["rows"], dem["rows"]):
        if a["step"] % 10000:
            continue
        out.append(f"| {a['step']} | {a['step'] * 1e-5:.1f} | {pm(a['particles'], f='.0f')} | "
                   f"{pm(b['particles'], f='.0f')} | {pm(a['mass'], 1e3, '.1f')} | "
                   f"{pm(b['mass'], 1e3, '.1f')} | {pm(a['ke'], 1e3)} | {pm(b['ke'], 1e3)} | "
                   f"{pm(a['erot'], 1e3)} | {pm(b['erot'], 1e3)} |")
    out += ["", "| step | t [s] | wear LIGGGHTS [mJ] | demstep [mJ] | ratio |"
            + (f" {label} [mJ] |" if var else ""),
            "|---:|---:|---:|---:|---:|" + ("---:|" if var else "")]
    rows_v = var["rows"] if var else [None] * len(lig["rows"])
    for a, b, c in zip(lig["rows"], dem["rows"], rows_v):
        if a["step"] % 10000:
            continue
        ratio = b["wear"]["mean"] / a["wear"]["mean"] if a["wear"]["mean"] > 0 else float("nan")
        out.append(f"| {a['step']} | {a['step'] * 1e-5:.1f} | {pm(a['wear'], 1e3)} | "
                   f"{pm(b['wear'], 1e3)} | {ratio:.3f} |"
                   + (f" {pm(c['wear'], 1e3)} |" if c else ""))
    out += ["", "| s along the trough [m] | LIGGGHTS | demstep |" + (f" {label} |" if var else ""),
            "|---|---:|---:|" + ("---:|" if var else "")]
    edges = lig["spread"]["bin_edges"]
    for k, (a, b) in enumerate(zip(lig["spread"]["fractions"], dem["spread"]["fractions"])):
        c = var["spread"]["fractions"][k] if var else None
        out.append(f"| {edges[k]:.3f}-{edges[k + 1]:.3f} | {pm(a, 1, '.3f')} | {pm(b, 1, '.3f')} |"
                   + (f" {pm(c, 1, '.3f')} |" if c else ""))
    for key, label, k, f in (("under_inlet_fraction", "under the inlet face", 1, ".3f"),
                             ("mean_position", "mean position s [m]", 1, ".4f"),
                             ("worn_area", "worn area [cm^2]", 1e4, ".0f"),
                             ("max_wear", "largest triangle's wear [J/m^2]", 1, ".2f")):
        out.append(f"| {label} | {pm(lig['spread'][key], k, f)} | {pm(dem['spread'][key], k, f)} |"
                   + (f" {pm(var['spread'][key], k, f)} |" if var else ""))
    out.append(f"| wear rate from 0.5 s [mJ/s] | {pm(lig['wear_rate_after_0.5s'], 1e3)} | "
               f"{pm(dem['wear_rate_after_0.5s'], 1e3)} |"
               + (f" {pm(var['wear_rate_after_0.5s'], 1e3)} |" if var else ""))
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=3, help="runs per code (default 3)")
    ap.add_argument("--every", type=int, default=None,
                    help="also run demstep with the inserter acting every EVERY steps")
    ap.add_argument("--no-impacts", action="store_true", help="skip the impact check")
    ap.add_argument("--out", default=str(ROOT / "validation" / "results" / "liggghts_chute_wear.json"))
    ap.add_argument("--keep", action="store_true", help="keep the run folders")
    ap.add_argument("--tables", metavar="JSON", help="print the markdown tables of a results "
                    "file and exit (nothing is run)")
    args = ap.parse_args(argv)
    if args.tables:
        print(markdown_tables(json.loads(Path(args.tables).read_text())))
        return 0
    if shutil.which("liggghts") is None or not TUTORIAL.is_dir():
        sys.exit("needs Debian's liggghts and liggghts-doc: apt-get install liggghts liggghts-doc")
    work = Path(tempfile.mkdtemp(prefix="demstep-chute-wear-"))
    # (the commit of the demstep run: DEMSTEP_COMMIT when it runs from another tree)
    commit = os.environ.get("DEMSTEP_COMMIT") or subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
        text=True).stdout.strip()
    import demstep

    result = {"tutorial": "chute_wear", "date": date.today().isoformat(),
              "liggghts": {"version": "3.8.0 (Debian)"},
              "demstep": {"source": str(Path(demstep.__file__).parent), "commit": commit},
              "seeds": args.seeds, "axis": [float(a) for a in AXIS],
              "upper_end": [float(a) for a in UPPER]}
    try:
        lig_runs, dem_runs, var_runs = [], [], []
        for i in range(args.seeds):
            lig_runs.append(run_liggghts(i, work))
            print(f"LIGGGHTS run {i} (seeds {lig_runs[-1]['seeds']}): "
                  f"{lig_runs[-1]['seconds']:.1f} s, wear {lig_runs[-1]['spread']['total']:.5f}",
                  flush=True)
            dem_runs.append(run_demstep(i + 1, work))
            print(f"demstep run seed {i + 1}: {dem_runs[-1]['seconds']:.1f} s, wear "
                  f"{dem_runs[-1]['spread']['total']:.5f}", flush=True)
            if args.every:
                var_runs.append(run_demstep(i + 1, work, args.every))
                print(f"demstep every {args.every} seed {i + 1}: {var_runs[-1]['seconds']:.1f} s,"
                      f" wear {var_runs[-1]['spread']['total']:.5f}", flush=True)
        strip = lambda runs: [{k: v for k, v in r.items() if not k.startswith("_")}  # noqa: E731
                              for r in runs]
        result["liggghts"].update(runs=strip(lig_runs), summary=summarise(lig_runs))
        result["demstep"].update(runs=strip(dem_runs), summary=summarise(dem_runs))
        if var_runs:
            result[f"demstep_every{args.every}"] = {"runs": strip(var_runs),
                                                    "summary": summarise(var_runs)}
        if not args.no_impacts:
            result["plate"] = plate_checks(work)
            result["impacts"] = impacts(work)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
        else:
            print(f"runs kept in {work}")
    print_summary(result)
    for name, c in result.get("plate", {}).items():
        if name.startswith("impact"):
            print(f"plate {name}: wear LIGGGHTS {c['wear_liggghts']:.4g} J (recomputed from "
                  f"its force and v(n+1/2): {c['wear_liggghts_recomputed_v_half']:.4g}), demstep "
                  f"{c['wear_demstep']:.4g} J; largest |Ft|/Fn approaching "
                  f"{c['max_ft_over_fn_approach_liggghts']:.2f} / "
                  f"{c['max_ft_over_fn_approach_demstep']:.2f}")
        else:
            print(f"plate {name}: wear of the second half LIGGGHTS "
                  f"{c['wear_second_half_liggghts']:.3g} J, demstep "
                  f"{c['wear_second_half_demstep']:.3g} J; largest |F_x| / weight crossing "
                  f"{c['max_fx_over_weight_crossing_liggghts']:.2f} / "
                  f"{c['max_fx_over_weight_crossing_demstep']:.2f}")
    if "impacts" in result:
        for name, c in result["impacts"]["cases"].items():
            print(f"impacts {name}: wear LIGGGHTS {c['total_liggghts']:.4g} J, demstep "
                  f"{c['total_demstep']:.4g} J; triangles {c['worn_triangles_liggghts']} / "
                  f"{c['worn_triangles_demstep']}; per-triangle ratio median "
                  f"{c['triangle_ratio_demstep_over_liggghts']['median']}")
    Path(args.out).write_text(compact_json(rounded(result)) + "\n")
    print(f"\nwritten {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
