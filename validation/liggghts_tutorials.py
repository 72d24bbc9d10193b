"""LIGGGHTS' own tutorials run in LIGGGHTS and in demstep, side by side.

    python validation/liggghts_tutorials.py [--tutorials meshGran conveyor movingMeshGran]
                                            [--seeds N] [--out FILE]

Needs Debian's ``liggghts`` and ``liggghts-doc`` (the tutorials and their STL meshes
under /usr/share/doc/liggghts/examples/LIGGGHTS/Tutorials_public). Each tutorial is
copied to a temporary folder and run there by ``liggghts -in in.<name>`` exactly as it
ships (its VTK dumps included); its thermo lines (step, atoms, translational and
rotational kinetic energy) are read from the log. demstep runs the case file that
describes the same simulation (``examples/liggghts_tutorials/<name>.toml``: the same
meshes and transforms, the same insertion face, rate, velocity and extrusion, the same
contact stiffness and damping, LIGGGHTS' ``hooke`` converted to the linear law by its
own formula, the same step), and its ``history.csv`` is read at the same steps.

What is compared, at every thermo step: the particles in the run (insertion at the
same rate from the same face; what leaves the domain), and the kinetic energy of the
flow (translation and rotation, J). The two runs insert at random and their
particles follow different paths, so the kinetic energies agree in magnitude and in
their course over time (the fill, the flow through the chute, the pile at rest), not
step by step; the table gives both and their ratio. For ``conveyor`` the
particles' positions and velocities are also read from both codes' VTK frames (every
2,000 steps): the mass that has left the belt (centres below its plane z = 0), the
particles on the belt and their mean velocity along it, and (LIGGGHTS only) the
particles still above the insertion face, which insert/stream moves at constant
velocity until they cross it. The results are written to
``validation/results/liggghts_tutorials.json`` (the entries of the tutorials run are
replaced, the others kept) and summarised in ``docs/validation-tutorials.md``.

``movingMeshGran`` (a bucket switched on as a wall at step 30,000, driven into the
settled bed and turned about the y axis to lift it) is run with output added to the
copied input, its physics untouched: the bucket's ``fix mesh/surface`` becomes
``mesh/surface/stress`` (the same contacts; the module only sums their forces), its
force and its torque about the axis (from the module's torque about its reference
point, which moves with the mesh, plus p_ref x F) are printed with the thermo output,
instantaneous and averaged by ``fix ave/time 50 20 1000`` (the 20 steps every 50 that
end at each thermo step), and the particle and mesh dumps are written every 1,000 steps
instead of 200. demstep runs a copy of its case with ``history_every = 50`` (the same
20 samples are averaged), no VTK frames and a checkpoint every 1,000 steps, from which
the particles are read. From both: the particles and their kinetic energy; the force
on the bucket; the particles (and their mass) whose centre lies in the bucket's cavity,
followed in the bucket's own frame, and those lifted above z = 0; from demstep also the
particles its inserter dropped at ``stop`` (those still waiting for room at the first
insertion step after it: nothing is inserted after ``stop``, as LIGGGHTS' ``unfix ins``
ends its insert/pack; read from the run's RuntimeWarning).

``--seeds N`` runs each tutorial N times in each code: LIGGGHTS with its seeds (the
particle template's, the distribution's and the insertion's) replaced by other primes
> 10000 (the first run keeps the tutorial's own), demstep with its inserters' ``seed``
1, 2, ... N. With N > 1 the JSON entry holds every run and, for movingMeshGran, each
code's mean, minimum and maximum over the seeds, and the engine's commit
(``engine_commit``; '+modified' if ``src/`` differed from it).
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
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
TUTORIALS = Path("/usr/share/doc/liggghts/examples/LIGGGHTS/Tutorials_public")
CASES = ROOT / "examples" / "liggghts_tutorials"


def liggghts_thermo(log_text: str) -> dict[int, tuple]:
    """Thermo rows of a LIGGGHTS log: step -> (atoms, ke, erotate), from the header
    'Step Atoms KinEng c_1 ...' onwards."""
    rows = {}
    header = None
    for line in log_text.splitlines():
        words = line.split()
        if words[:2] == ["Step", "Atoms"]:
            header = words
            continue
        if words[:2] == ["Loop", "time"]:
            header = None  # (the end of a run's thermo block)
            continue
        if header is None or len(words) < len(header):
            continue
        try:
            values = [float(w) for w in words[:len(header)]]
        except ValueError:
            continue  # (insertion messages between thermo rows)
        # (the tutorials' thermo_style lists the rotational energy's compute right after
        # ke: headed "1" or "c_1" in meshGran, "rke" or "c_rke" in conveyor)
        ke = header.index("KinEng")
        rows[int(values[0])] = (int(values[1]), values[ke], values[ke + 1])
    return rows


def liggghts_thermo_table(log_text: str) -> dict[str, dict]:
    """Every thermo column of a LIGGGHTS log by its header name (``f_`` and ``c_``
    prefixes dropped: 'KinEng', 'cad1[1]', ...): {step: {column: value}}, the first row
    of a step kept (a run's setup prints the last step of the run before again, with
    the forces of its own first evaluation). Keys are strings (JSON)."""
    rows = {}
    header = None
    for line in log_text.splitlines():
        words = line.split()
        if words[:2] == ["Step", "Atoms"]:
            header = [w[2:] if w[:2] in ("f_", "c_") else w for w in words]
            continue
        if words[:2] == ["Loop", "time"]:
            header = None
            continue
        if header is None or len(words) != len(header):
            continue
        try:
            values = [float(w) for w in words]
        except ValueError:
            continue
        rows.setdefault(str(int(values[0])), dict(zip(header, values)))
    return rows


def is_prime(n: int) -> bool:
    if n < 2 or n % 2 == 0:
        return n == 2
    return all(n % d for d in range(3, math.isqrt(n) + 1, 2))


def next_prime(n: int) -> int:
    while not is_prime(n):
        n += 1
    return n


#: the seeds of a LIGGGHTS input: particle templates, distributions, insertions
SEED_RE = re.compile(r"(particletemplate/sphere|particledistribution/discrete|\bseed)(\s+)(\d+)")


def liggghts_seeds(text: str, k: int) -> tuple[str, list[int]]:
    """The input ``text`` with its seeds for run ``k`` (0: the tutorial's own; k > 0:
    each replaced by a different prime > 10000, as LIGGGHTS requires), and the seeds."""
    if k > 0:
        used = set()

        def new_seed(m):
            seed = next_prime(int(m.group(3)) + 100_003 * k)
            while seed in used:
                seed = next_prime(seed + 1)
            used.add(seed)
            return f"{m.group(1)}{m.group(2)}{seed}"

        text = SEED_RE.sub(new_seed, text)
    return text, [int(m.group(3)) for m in SEED_RE.finditer(text)]


def demstep_seeds(text: str, k: int) -> tuple[str, list[int]]:
    """The case ``text`` with its inserters' ``seed`` raised by ``k``, and the seeds."""
    text = re.sub(r"(?m)^(seed\s*=\s*)(\d+)", lambda m: f"{m.group(1)}{int(m.group(2)) + k}", text)
    return text, [int(v) for v in re.findall(r"(?m)^seed\s*=\s*(\d+)", text)]


def replace_once(text: str, old: str, new: str) -> str:
    if text.count(old) != 1:
        sys.exit(f"the input has changed: {old!r} found {text.count(old)} times, expected once")
    return text.replace(old, new)


def one_thread() -> dict:
    """The environment for one thread per code (demstep's package on the path)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT / "src"), env.get("PYTHONPATH")) if p)
    return env


def run_liggghts(name: str, work: Path, k: int = 0) -> tuple[dict, float, Path]:
    """The tutorial run in a copy of its folder (seeds of run ``k``; for movingMeshGran
    the outputs of :func:`moving_mesh_outputs`): (thermo rows, wall seconds, folder);
    the folder holds ``seeds.json`` and the whole thermo table in ``thermo.json``."""
    src = TUTORIALS / name
    dest = work / f"liggghts-{name}-{k}"
    shutil.copytree(src, dest)
    (dest / "post").mkdir(exist_ok=True)
    script = dest / f"in.{name}"
    text, seeds = liggghts_seeds(script.read_text(), k)
    if name == MOVING:
        text = moving_mesh_outputs(text)
    script.write_text(text)
    (dest / "seeds.json").write_text(json.dumps(seeds))
    start = time.perf_counter()
    proc = subprocess.run(["liggghts", "-in", f"in.{name}", "-log", "log.liggghts"], cwd=dest,
                          capture_output=True, text=True, env=one_thread())
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        sys.exit(f"liggghts failed on {name}: {proc.stdout[-2000:]}{proc.stderr[-2000:]}")
    log = (dest / "log.liggghts").read_text()
    (dest / "thermo.json").write_text(json.dumps(liggghts_thermo_table(log)))
    return liggghts_thermo(log), elapsed, dest


def run_demstep(name: str, work: Path, k: int = 0) -> tuple[dict, float, Path]:
    """The case run by ``demstep run`` (seeds of run ``k``; for movingMeshGran the
    outputs of :func:`moving_mesh_case`): (rows, wall seconds, folder); the folder
    holds ``seeds.json`` and the run's standard error in ``stderr.txt``."""
    out = work / f"demstep-{name}-{k}"
    case_file = CASES / f"{name}.toml"
    text, seeds = demstep_seeds(case_file.read_text(), k)
    if name == MOVING:
        text = moving_mesh_case(text)
    if text != case_file.read_text():
        # (the copy is read from the work folder: the cases' mesh files are absolute paths)
        case_file = work / f"{name}-{k}.toml"
        case_file.write_text(text)
    command = [sys.executable, "-m", "demstep.cli", "run", str(case_file), "--out", str(out),
               "--quiet"]
    start = time.perf_counter()
    proc = subprocess.run(command, capture_output=True, text=True, env=one_thread())
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        sys.exit(f"demstep failed on {name}: {proc.stdout[-2000:]}{proc.stderr[-2000:]}")
    (out / "seeds.json").write_text(json.dumps(seeds))
    (out / "stderr.txt").write_text(proc.stderr)
    from demstep.io.history import read_history

    h = read_history(out / "history.csv")
    rows = {int(s): (int(n), kt, kr) for s, n, kt, kr in zip(
        h["step"], h["particles"], h["kinetic_translational"], h["kinetic_rotational"])}
    return rows, elapsed, out


def demstep_stage_seconds(out: Path) -> dict:
    """Wall-clock seconds of each stage of a demstep run, from its run.log's time stamps
    (the first stage's include the start-up: the kernels compiled or loaded from
    numba's cache, the case's checks)."""
    from datetime import datetime

    marks = []
    for line in (out / "run.log").read_text().splitlines():
        m = re.match(r"(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+) INFO "
                     r"(?:stage \d+/\d+ '(.*)' starts|(completed))", line)
        if m:
            t = datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S,%f")
            marks.append((m.group(2) or "end", t))
    return {name: (t1 - t0).total_seconds()
            for (name, t0), (_, t1) in zip(marks, marks[1:])}


# ----------------------------------------------------------------- conveyor's belt
DENSITY = 2500.0    # [kg/m^3] the conveyor tutorial's
FACE_Z = 0.2        # [m] its insertion face
BELT_X = (-0.1, 0.5)  # [m] its belt, at z = 0
ON_BELT_Z = 0.06    # [m] centres up to this height over the belt count as on it


def read_liggghts_vtk(path: Path) -> dict:
    """Positions, velocities and radii of a LIGGGHTS ``dump custom/vtk`` file (legacy
    ASCII polydata)."""
    tokens = path.read_text().split()
    out = {}
    i = 0
    while i < len(tokens):
        t = tokens[i]
        if t == "POINTS":
            n = int(tokens[i + 1])
            out["x"] = np.array(tokens[i + 3:i + 3 + 3 * n], dtype=float).reshape(n, 3)
            i += 3 + 3 * n
        elif t in ("v", "radius") and i + 3 < len(tokens) and tokens[i + 3] in ("double", "float"):
            comps, n = int(tokens[i + 1]), int(tokens[i + 2])
            out[t] = np.array(tokens[i + 4:i + 4 + comps * n], dtype=float).reshape(n, comps)
            i += 4 + comps * n
        else:
            i += 1
    n = len(out.get("x", ()))
    return {"x": out.get("x", np.zeros((0, 3))), "v": out.get("v", np.zeros((n, 3))),
            "m": DENSITY * 4.0 / 3.0 * np.pi * out.get("radius", np.zeros((n, 1)))[:, 0] ** 3}


def read_demstep_vtu(path: Path) -> dict:
    import meshio

    if 'NumberOfPoints="0"' in path.read_text(errors="replace")[:4000]:
        return {"x": np.zeros((0, 3)), "v": np.zeros((0, 3)), "m": np.zeros(0)}
    mesh = meshio.read(path)
    return {"x": np.asarray(mesh.points, dtype=float),
            "v": np.asarray(mesh.point_data["velocity"], dtype=float),
            "m": np.asarray(mesh.point_data["mass"], dtype=float).reshape(-1)}


def belt_state(frame: dict) -> dict:
    """The mass in the run and the mass off the belt (centres below z = 0) [kg], the
    particles on the belt and their mass-weighted mean velocity along x [m/s], the
    particles above the face."""
    x, v, m = frame["x"], frame["v"], frame["m"]
    if len(x) == 0:
        return {"mass": 0.0, "mass_off_belt": 0.0, "on_belt": 0, "vx_on_belt": float("nan"),
                "above_face": 0}
    on = (x[:, 0] >= BELT_X[0]) & (x[:, 0] <= BELT_X[1]) & (x[:, 2] > 0) & (x[:, 2] <= ON_BELT_Z)
    vx = float((m[on] * v[on, 0]).sum() / m[on].sum()) if on.any() else float("nan")
    return {"mass": float(m.sum()), "mass_off_belt": float(m[x[:, 2] < 0].sum()),
            "on_belt": int(on.sum()),
            "vx_on_belt": vx, "above_face": int((x[:, 2] > FACE_Z).sum())}


def conveyor_flow(lig_dir: Path, dem_dir: Path) -> list[dict]:
    """belt_state of both codes at the steps both wrote a frame."""
    # (LIGGGHTS also writes conveyor_boundingBox_STEP.vtk there)
    lig = {int(p.stem.split("_")[-1]): p for p in (lig_dir / "post").glob("conveyor_*.vtk")
           if p.stem.split("_")[-1].isdigit() and p.stem.count("_") == 1}
    dem = {int(p.stem.split("_")[-1]): p for p in (dem_dir / "vtk").glob("particles_*.vtu")}
    rows = []
    for s in sorted(set(lig) & set(dem)):
        if s == 0:
            continue
        a, b = belt_state(read_liggghts_vtk(lig[s])), belt_state(read_demstep_vtu(dem[s]))
        rows.append({"step": s, **{f"{k}_liggghts": val for k, val in a.items()},
                     **{f"{k}_demstep": val for k, val in b.items() if k != "above_face"}})
    return rows


# ------------------------------------------------------- movingMeshGran's bucket
MOVING = "movingMeshGran"
MM_DT = 5.0e-5                          # [s] the tutorial's step
MM_ON, MM_TURN, MM_END = 30000, 45000, 70000   # the bucket a wall; it turns; the end
MM_VELOCITY = np.array([-0.5, 0.0, -0.3])      # [m/s] move/mesh linear, steps 30001-45000
MM_OMEGA = 2.0 * math.pi / 2.0                 # [rad/s] rotate ... axis 0 1 0 period 2.
#: the bucket's cavity where it starts (after the tutorial's transforms): the section
#: (x, z) [m] inside its three plates (the top plate's underside z = 0.0791, the back
#: plate's inner face x = 0.4774, the sloped bottom's upper face from (0.1997, -0.1216)
#: to (0.4774, -0.0202); open towards -x), counter-clockwise, over y in [0, 0.4]
CAVITY_XZ = np.array([(0.1997, -0.1216), (0.4774, -0.0202), (0.4774, 0.0791), (0.1997, 0.0791)])
CAVITY_Y = (0.0, 0.4)
LIFT_Z = 0.0    # [m] lifted: centre above it (the settled bed's top centres: z ~ -0.18 m)
BUCKET_STL = TUTORIALS / MOVING / "meshes" / "bucket.stl"
BUCKET_TRANSFORMS = ("move -50. -250. 0. scale 0.002 rotate axis 0. 1. 0. angle 90. "
                     "rotate axis 0. 0. 1. angle 90.")
POSE_STEPS = (MM_ON, MM_TURN, 55000, MM_END)   # the bucket's pose checked at these


def moving_mesh_outputs(text: str) -> str:
    """LIGGGHTS' input with outputs added (nothing else changed): the bucket's force
    and its torque about the y axis, instantaneous and averaged, with the thermo
    output; dumps every 1,000 steps (the tutorial's 200 would write 350 frames)."""
    text = replace_once(text, "cad1 all mesh/surface file", "cad1 all mesh/surface/stress file")
    text = replace_once(text, "custom/vtk 200", "custom/vtk 1000")
    text = replace_once(text, "mesh/stl 200", "mesh/stl 1000")
    # (cad1[4..6]: the torque about the module's reference point p = cad1[7..9], which
    # moves with the mesh; about the origin T + p x F, whose y component is this)
    return replace_once(
        text, "thermo_style\tcustom step atoms ke c_1 vol",
        "variable\ttyO equal f_cad1[5]+f_cad1[9]*f_cad1[1]-f_cad1[7]*f_cad1[3]\n"
        "fix\t\tfavg all ave/time 50 20 1000 f_cad1[1] f_cad1[2] f_cad1[3] v_tyO\n"
        "thermo_style\tcustom step atoms ke c_1 vol f_cad1[1] f_cad1[2] f_cad1[3] "
        "f_favg[1] f_favg[2] f_favg[3] f_favg[4]")


def moving_mesh_case(text: str) -> str:
    """demstep's case with history rows every 50 steps and a checkpoint every 1,000
    (kept), the outputs compared, and no VTK frames; nothing else changed."""
    text = re.sub(r"(?m)^history_every = \d+", "history_every = 50", text)
    text = re.sub(r"(?m)^vtk_every = \d+", "vtk_every = 0", text)
    return re.sub(r"(?m)^checkpoint_every = \d+", "checkpoint_every = 1000\ncheckpoint_keep = 0",
                  text)


def bucket_pose(step: int) -> tuple[np.ndarray, np.ndarray]:
    """(R, d): the bucket's points at ``step`` are R (x0 + d), x0 where it starts."""
    d = MM_VELOCITY * MM_DT * min(max(step - MM_ON, 0), MM_TURN - MM_ON)
    phi = MM_OMEGA * MM_DT * max(step - MM_TURN, 0)
    c, s = math.cos(phi), math.sin(phi)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]), d   # right-handed about +y


def in_cavity(x: np.ndarray, step: int) -> np.ndarray:
    """Whether each centre x (N, 3) lies in the bucket's cavity at ``step``."""
    R, d = bucket_pose(step)
    x0 = x @ R - d                                       # R^T x - d
    inside = (x0[:, 1] >= CAVITY_Y[0]) & (x0[:, 1] <= CAVITY_Y[1])
    for a, b in zip(CAVITY_XZ, np.roll(CAVITY_XZ, -1, axis=0)):
        inside &= (b[0] - a[0]) * (x0[:, 2] - a[1]) - (b[1] - a[1]) * (x0[:, 0] - a[0]) >= 0
    return inside


def bucket_contents(x: np.ndarray, m: np.ndarray, step: int) -> dict:
    held = in_cavity(x, step) if len(x) else np.zeros(0, bool)
    lifted = x[:, 2] > LIFT_Z if len(x) else np.zeros(0, bool)
    return {"mass": float(m.sum()), "held": int(held.sum()), "held_mass": float(m[held].sum()),
            "lifted": int(lifted.sum()), "lifted_mass": float(m[lifted].sum())}


def bucket_corners(step: int) -> np.ndarray:
    from demstep.mesh import read_mesh

    R, d = bucket_pose(step)
    return (read_mesh(BUCKET_STL, BUCKET_TRANSFORMS).vertices + d) @ R.T


def pose_error(points: np.ndarray, step: int) -> float:
    """The largest difference [m] of the bounding boxes of ``points`` and of the
    bucket where :func:`bucket_pose` puts it."""
    want = bucket_corners(step)
    return float(max(np.abs(points.min(axis=0) - want.min(axis=0)).max(),
                     np.abs(points.max(axis=0) - want.max(axis=0)).max()))


def window_mean(steps: np.ndarray, values: np.ndarray, step: int) -> float:
    """The mean of the rows at steps step - 950, ..., step (every 50), as LIGGGHTS'
    fix ave/time 50 20 1000."""
    sel = (steps > step - 1000) & (steps <= step) & (steps % 50 == 0)
    return float(values[sel].mean()) if sel.sum() == 20 else float("nan")


def moving_series_liggghts(folder: Path, seconds: float) -> dict:
    thermo = json.loads((folder / "thermo.json").read_text())
    rows = []
    for s in range(1000, MM_END + 1, 1000):
        t = thermo[str(s)]
        frame = read_liggghts_vtk(folder / "post" / f"movingMesh_{s}.vtk")
        rows.append({"step": s, "particles": int(t["Atoms"]), "ke": t["KinEng"], "erot": t["1"],
                     "fx": t["cad1[1]"], "fy": t["cad1[2]"], "fz": t["cad1[3]"],
                     "fx_avg": t["favg[1]"], "fy_avg": t["favg[2]"], "fz_avg": t["favg[3]"],
                     "ty_avg": t["favg[4]"] if s >= MM_TURN + 1000 else float("nan"),
                     **bucket_contents(frame["x"], frame["m"], s)})
    from demstep.mesh import read_mesh

    poses = {str(s): pose_error(read_mesh(folder / "post" / f"dump{s}.stl").vertices, s)
             for s in POSE_STEPS}
    return {"seeds": json.loads((folder / "seeds.json").read_text()), "seconds": seconds,
            "rows": rows, "pose_error": poses}


def moving_series_demstep(folder: Path, seconds: float) -> dict:
    from demstep.io.checkpoint import read_checkpoint_arrays
    from demstep.io.history import read_history

    h = read_history(folder / "history.csv")
    steps = np.asarray(h["step"]).astype(int)
    at = {int(s): i for i, s in enumerate(steps)}
    rows, poses = [], {}
    for s in range(1000, MM_END + 1, 1000):
        i = at[s]
        state = read_checkpoint_arrays(folder / "checkpoints" / f"step{s:010d}.npz")
        x, m = np.asarray(state["spheres.x"]), np.asarray(state["spheres.m"])
        if s in POSE_STEPS:
            poses[str(s)] = pose_error(np.asarray(state["meshes.tri"]).reshape(-1, 3), s)
        avg = {f"{k}_avg": window_mean(steps, np.asarray(h[f"bucket.{k}"]), s)
               for k in ("fx", "fy", "fz")}
        # (ty about the mesh's centre: the origin once the rotation has started)
        rows.append({"step": s, "particles": int(h["particles"][i]),
                     "ke": float(h["kinetic_translational"][i]),
                     "erot": float(h["kinetic_rotational"][i]),
                     **{k: float(h[f"bucket.{k}"][i]) for k in ("fx", "fy", "fz")}, **avg,
                     "ty_avg": window_mean(steps, np.asarray(h["bucket.ty"]), s)
                     if s >= MM_TURN + 1000 else float("nan"),
                     **bucket_contents(x, m, s)})
    # (the inserter's RuntimeWarning: "... N particle(s) that found no room by stop = ...
    # are dropped (step S)")
    dropped = [int(n) for n in re.findall(r"(\d+) particle\(s\) that found no room by stop",
                                          (folder / "stderr.txt").read_text())]
    return {"seeds": json.loads((folder / "seeds.json").read_text()), "seconds": seconds,
            "dropped_at_stop": sum(dropped),
            "stage_seconds": demstep_stage_seconds(folder),
            "max_energy_error": float(np.nanmax(np.asarray(h["energy_error"]))),
            "rows": rows, "pose_error": poses}


#: the codes of a movingMeshGran comparison
MOVING_CODES = ("liggghts", "demstep")


def rounded(value, digits: int = 6):
    """``value`` (nested dicts and lists) with its floats to ``digits`` significant
    digits (the JSON file stays small)."""
    if isinstance(value, dict):
        return {k: rounded(v, digits) for k, v in value.items()}
    if isinstance(value, list):
        return [rounded(v, digits) for v in value]
    if isinstance(value, float) and math.isfinite(value) and value != 0.0:
        return round(value, digits - 1 - math.floor(math.log10(abs(value))))
    return value


def spread(runs: list[dict]) -> list[dict]:
    """Each quantity's mean, minimum and maximum over the runs (seeds), at the steps
    of MOVING_SHOWN (the runs hold every 1,000 steps)."""
    out = []
    for rows in zip(*(r["rows"] for r in runs)):
        if rows[0]["step"] not in MOVING_SHOWN:
            continue
        row = {"step": rows[0]["step"]}
        for key in rows[0]:
            if key == "step":
                continue
            v = np.array([r[key] for r in rows], dtype=float)
            if np.isnan(v).all():
                continue
            row[key] = {"mean": float(v.mean()), "min": float(v.min()), "max": float(v.max())}
        out.append(row)
    return out


def compare_moving(work: Path, seeds: int, keep: bool) -> dict:
    runs = {code: [] for code in MOVING_CODES}
    commit = engine_commit()
    for k in range(seeds):
        _, t, folder = run_liggghts(MOVING, work, k)
        runs["liggghts"].append(moving_series_liggghts(folder, t))
        print_moving_run("LIGGGHTS", runs["liggghts"][-1])
        if not keep:
            shutil.rmtree(folder / "post", ignore_errors=True)
        _, t, folder = run_demstep(MOVING, work, k)
        runs["demstep"].append(moving_series_demstep(folder, t))
        print_moving_run("demstep", runs["demstep"][-1])
        if not keep:
            shutil.rmtree(folder / "checkpoints", ignore_errors=True)
    if engine_commit() != commit:   # (src/ changed while the runs ran)
        commit = f"{commit} -> {engine_commit()}"
    return rounded({"tutorial": MOVING, "seeds": seeds, "engine_commit": commit,
                    "runs": runs, "summary": {code: spread(r) for code, r in runs.items()}})


def engine_commit() -> str:
    """The repository's commit (with '+modified' if src/ differs from it), or ''; the
    JSON entry records it as the runs start (and as they end, if it differs)."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, check=True,
                              capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "src"], cwd=ROOT,
                               capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return ""
    return head + ("+modified" if dirty else "")


#: the rows shown on the screen (the JSON file has every 1,000 steps)
MOVING_SHOWN = (2000, 8000, 20000, 29000, 30000, 31000, 35000, 40000, 45000, 46000, 48000,
                50000, 52000, 55000, 58000, 60000, 65000, 70000)


def print_moving_run(code: str, run: dict) -> None:
    extra = ""
    if "stage_seconds" in run:
        extra = (f" (dropped at stop: {run['dropped_at_stop']}; stages: " + ", ".join(f"{k} {v:.1f} s" for k, v in run["stage_seconds"].items())
                 + f"; energy error at most {run['max_energy_error']:.2g})")
    print(f"\n{MOVING} {code}, seeds {run['seeds']}: {run['seconds']:.1f} s{extra}; bucket pose "
          f"error {max(run['pose_error'].values()):.2g} m")
    print(f"{'step':>6} {'N':>5} {'KE [J]':>9} {'Erot':>7} {'Fx avg':>8} {'Fz avg':>8} "
          f"{'Ty avg':>8} {'held':>5} {'kg':>6} {'lifted':>6}")
    for r in run["rows"]:
        if r["step"] in MOVING_SHOWN:
            print(f"{r['step']:>6} {r['particles']:>5} {r['ke']:>9.4g} {r['erot']:>7.3g} "
                  f"{r['fx_avg']:>8.1f} {r['fz_avg']:>8.1f} {r['ty_avg']:>8.1f} {r['held']:>5} "
                  f"{r['held_mass']:>6.1f} {r['lifted']:>6}")


def print_moving_summary(result: dict) -> None:
    print(f"\n{MOVING}: mean [min, max] over {result['seeds']} seed(s)")
    for key in ("particles", "ke", "fz_avg", "ty_avg", "held", "lifted"):
        print(f"\n{key}:")
        print(f"{'step':>6} " + " ".join(f"{c:>30}" for c in MOVING_CODES))
        for rows in zip(*(result["summary"][c] for c in MOVING_CODES)):
            if rows[0]["step"] not in MOVING_SHOWN or key not in rows[0]:
                continue
            cells = [f"{r[key]['mean']:.4g} [{r[key]['min']:.4g}, {r[key]['max']:.4g}]" for r in rows]
            print(f"{rows[0]['step']:>6} " + " ".join(f"{c:>30}" for c in cells))


EXTRA = {"conveyor": ("belt", conveyor_flow)}


def compare(name: str, work: Path, k: int = 0) -> dict:
    lig, t_lig, lig_dir = run_liggghts(name, work, k)
    dem, t_dem, dem_dir = run_demstep(name, work, k)
    steps = sorted(s for s in lig if s in dem and s > 0)
    table = []
    for s in steps:
        (n_l, ke_l, er_l), (n_d, ke_d, er_d) = lig[s], dem[s]
        table.append({"step": s, "particles_liggghts": n_l, "particles_demstep": n_d,
                      "ke_liggghts": ke_l, "ke_demstep": ke_d,
                      "erot_liggghts": er_l, "erot_demstep": er_d})
    result = {"tutorial": name, "seconds_liggghts": t_lig, "seconds_demstep": t_dem,
              "stage_seconds_demstep": demstep_stage_seconds(dem_dir), "rows": table}
    if k > 0:
        result["seeds_liggghts"] = json.loads((lig_dir / "seeds.json").read_text())
        result["seeds_demstep"] = json.loads((dem_dir / "seeds.json").read_text())
    if name in EXTRA:
        key, fn = EXTRA[name]
        result[key] = fn(lig_dir, dem_dir)
    return result


def print_table(result: dict) -> None:
    print(f"\n{result['tutorial']}: LIGGGHTS {result['seconds_liggghts']:.1f} s, demstep "
          f"{result['seconds_demstep']:.1f} s (wall clock, one thread each); demstep's "
          f"stages: " + ", ".join(f"{k} {v:.1f} s" for k, v in
                                  result.get("stage_seconds_demstep", {}).items()))
    print(f"{'step':>7} {'N lig':>6} {'N dem':>6} {'KE lig [J]':>11} {'KE dem [J]':>11} "
          f"{'ratio':>6} {'Erot lig':>9} {'Erot dem':>9}")
    for r in result["rows"]:
        ratio = r["ke_demstep"] / r["ke_liggghts"] if r["ke_liggghts"] > 0 else float("nan")
        print(f"{r['step']:>7} {r['particles_liggghts']:>6} {r['particles_demstep']:>6} "
              f"{r['ke_liggghts']:>11.4g} {r['ke_demstep']:>11.4g} {ratio:>6.2f} "
              f"{r['erot_liggghts']:>9.3g} {r['erot_demstep']:>9.3g}")
    if "belt" in result:
        print(f"\n{'step':>7} {'m lig':>7} {'m dem':>7} {'off lig':>8} {'off dem':>8} "
              f"{'on lig':>6} {'on dem':>6} {'vx lig':>7} {'vx dem':>7} {'above':>5}"
              f"   (kg in the run, off the belt; on it, mean vx m/s)")
        for r in result["belt"]:
            print(f"{r['step']:>7} {r['mass_liggghts']:>7.3f} {r['mass_demstep']:>7.3f} "
                  f"{r['mass_off_belt_liggghts']:>8.3f} "
                  f"{r['mass_off_belt_demstep']:>8.3f} {r['on_belt_liggghts']:>6} "
                  f"{r['on_belt_demstep']:>6} {r['vx_on_belt_liggghts']:>7.3f} "
                  f"{r['vx_on_belt_demstep']:>7.3f} {r['above_face_liggghts']:>5}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tutorials", nargs="*", default=["meshGran", "conveyor", MOVING],
                    choices=["meshGran", "conveyor", MOVING],
                    help="the tutorials to run (default: all); the others' entries in the "
                         "JSON file are kept")
    ap.add_argument("--out", default=str(ROOT / "validation" / "results" / "liggghts_tutorials.json"))
    ap.add_argument("--seeds", type=int, default=1,
                    help="runs per tutorial and code, each with other seeds (default 1: the "
                         "tutorials' own seeds, and demstep's cases' own)")
    ap.add_argument("--keep", action="store_true", help="keep the run folders")
    args = ap.parse_args(argv)
    if args.seeds < 1:
        ap.error("--seeds: at least 1")
    if shutil.which("liggghts") is None or not TUTORIALS.is_dir():
        sys.exit("needs Debian's liggghts and liggghts-doc: apt-get install liggghts liggghts-doc")
    work = Path(tempfile.mkdtemp(prefix="demstep-tutorials-"))
    results = []
    try:
        for name in args.tutorials:
            if name == MOVING:
                result = compare_moving(work, args.seeds, args.keep)
                print_moving_summary(result)
            elif args.seeds == 1:
                result = compare(name, work)
                print_table(result)
            else:
                result = {"tutorial": name, "seeds": args.seeds, "runs": []}
                for k in range(args.seeds):
                    result["runs"].append(compare(name, work, k))
                    print_table(result["runs"][-1])
            results.append(result)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
        else:
            print(f"runs kept in {work}")
    out = Path(args.out)
    kept = json.loads(out.read_text()) if out.is_file() else []
    done = {r["tutorial"]: r for r in results}
    merged = [done.pop(r["tutorial"], r) for r in kept] + list(done.values())
    out.write_text(json.dumps(merged, indent=1) + "\n")
    print(f"\nwritten {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
