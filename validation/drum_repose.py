"""A rotating drum of our own in LIGGGHTS and in demstep: the dynamic angle of repose
against the rotation rate.

    python validation/drum_repose.py [--quick] [--seeds N] [--rates 1 2 4] [--out FILE]
                                     [--keep]

The drum (``validation/drum/drum.stl``, written by ``validation/drum/make_drum.py``): a
closed cylinder of 64 side facets, radius 50 mm, 20 mm long, its axis along y through
the origin, 256 triangles, read by both codes as it is (metres). The case is
``examples/rotating_drum_validation.toml``: 1,008 spheres (r = 2 mm, 2500 kg/m^3) on a
jittered 18 x 4 x 14 grid in the drum, LIGGGHTS' ``hooke`` (E = 2e7 Pa, nu = 0.3, v_c =
1 m/s) as demstep's linear law (k_n = k_t = 3798.5 N/m between spheres, 5757.4 N/m on
the drum), friction 0.5 everywhere, restitution 0.5, no rolling resistance, no
damping, dt = 2e-5 s in both.

Both codes start from the same positions (demstep's grid generator, seed 1, 2, ...;
its positions written into LIGGGHTS' input as ``create_atoms single``), let the spheres
settle with the drum at rest, then turn the drum about +y (right-handed in both:
demstep's ``omega = [0, w, 0]``, LIGGGHTS' ``move/mesh rotate axis 0 1 0 period
2 pi / w``) at each rate in turn, in one run: each rate's stage is a transient (the bed
taking up the new rate) followed by a measuring window. The rates rise, so each starts
from the previous one's flowing bed. LIGGGHTS changes the rate by ``unfix`` and a new
``fix move/mesh`` (the mesh keeps the turn it has made).

Measured, from the particle positions every 2,500 steps (0.05 s; LIGGGHTS ``dump
custom``, demstep's VTK frames) in the measuring windows: the dynamic angle of repose.
The spheres are projected on the drum's cross-section (x, z); the cross-section is cut
into 4 mm bins along x; each bin's free surface is its highest centre; the surface's
extent is the range of x of the bins holding spheres; a straight line is fitted to the
tops of the bins in its central 60 %; the angle is atan of minus its slope (the drum
turning about +y carries the bed up the -x side). Per rate: the mean and standard
deviation over the window's frames. Also the torque of the particles on the drum
about its axis (y; LIGGGHTS' ``fix mesh/surface/stress``, T + p x F with p its
reference point; demstep's ``drum.ty``), averaged over the window (every 500 steps),
and the wall-clock seconds of each run (one thread: NUMBA_NUM_THREADS=1, one serial
LIGGGHTS process; the two codes run side by side on two cores).

``--quick``: shorter stages (settle 0.3 s; per rate 0.6 s of transient and 0.6 s
measured). ``--seeds N``: N grids (seeds 1..N), each run in both codes.

Results: ``validation/results/drum_repose.json``; summarised in
``docs/validation-drum.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "validation"))
from liggghts_tutorials import (demstep_stage_seconds, engine_commit,  # noqa: E402
                                liggghts_thermo_table, one_thread, read_demstep_vtu)

CASE = ROOT / "examples" / "rotating_drum_validation.toml"
STL = ROOT / "validation" / "drum" / "drum.stl"
OUT = ROOT / "validation" / "results" / "drum_repose.json"

DT = 2.0e-5            # [s]
RADIUS = 0.002         # [m] spheres
DENSITY = 2500.0
DRUM_R = 0.05          # [m]
G = 9.81
E, NU, VC = 2.0e7, 0.3, 1.0       # LIGGGHTS hooke's material
MU, REST = 0.5, 0.5
FRAME_EVERY = 2500     # [steps] particle frames
THERMO_EVERY = 500     # [steps] torque rows
BIN = 0.004            # [m] surface bins along x
CENTRAL = 0.6          # fraction of the surface fitted

#: (rate [rad/s], transient [s], measured [s])
FULL = [(0.5, 4.0, 2 * math.pi), (1.0, 2.0, 2 * math.pi), (2.0, 1.5, math.pi),
        (4.0, 1.0, math.pi / 2)]
QUICK = [(1.0, 0.6, 0.6), (2.0, 0.6, 0.6), (4.0, 0.6, 0.6)]
SETTLE = {"full": 0.4, "quick": 0.3}


def hooke_k(r_eff: float, m_eff: float) -> float:
    """LIGGGHTS' hooke stiffness (normal_model_hooke.h), one material."""
    es = E / (2.0 * (1.0 - NU ** 2))
    return 16.0 / 15.0 * math.sqrt(r_eff) * es * (
        15.0 * m_eff * VC ** 2 / (16.0 * math.sqrt(r_eff) * es)) ** 0.2


def schedule_steps(settle: float, rates) -> list[dict]:
    """The stages in steps: settle, then per rate its first and last step and the first
    step of its measuring window."""
    stages, step = [], int(round(settle / DT))
    for w, transient, measured in rates:
        n_tr, n_me = int(round(transient / DT)), int(round(measured / DT))
        stages.append({"omega": w, "start": step, "measure_from": step + n_tr,
                       "end": step + n_tr + n_me, "transient": transient, "measured": measured})
        step += n_tr + n_me
    return stages


# --------------------------------------------------------------------- demstep
def case_text(seed: int, settle: float, rates) -> str:
    text = CASE.read_text()
    text, n = re.subn(r"(?m)^seed = \d+", f"seed = {seed}", text)
    assert n == 1
    text = text.replace('file = "../validation/drum/drum.stl"', f'file = "{STL}"')
    head = text.split("# (the schedule of validation/drum_repose.py")[0]
    out = head + f'[[stages]]\nname = "settle"\nduration = {settle!r}\n\n'
    for w, transient, measured in rates:
        out += (f'[[stages]]\nname = "w{w:g}"\nduration = {transient + measured!r}\n'
                f'[stages.meshes."drum"]\nomega = [0.0, {w!r}, 0.0]\n\n')
    out += (f"[output]\nhistory_every = {THERMO_EVERY}\nvtk_every = {FRAME_EVERY}\n"
            "vtk_contacts = false\ncheckpoint_every = 0\n")
    return out


def initial_positions(text: str) -> tuple[np.ndarray, np.ndarray]:
    from demstep.case.build import generate_particles
    from demstep.case.schema import case_from_text

    x, r, _ = generate_particles(case_from_text(text, base_dir=CASE.parent))
    return x, r


def run_demstep(text: str, work: Path, tag: str) -> dict:
    from demstep.io.history import read_history

    case = work / f"{tag}.toml"
    case.write_text(text)
    out = work / tag
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "demstep.cli", "run", str(case), "--out",
                           str(out), "--quiet"], capture_output=True, text=True,
                          env=one_thread())
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        sys.exit(f"demstep failed: {proc.stdout[-2000:]}{proc.stderr[-2000:]}")
    h = read_history(out / "history.csv")
    torque = {int(s): float(t) for s, t in zip(h["step"], h["drum.ty"])}
    frames = {}
    for path in sorted((out / "vtk").glob("particles_*.vtu")):
        frames[int(path.stem.split("_")[-1])] = read_demstep_vtu(path)["x"]
    return {"seconds": seconds, "stage_seconds": demstep_stage_seconds(out),
            "torque": torque, "frames": frames, "dir": str(out)}


# -------------------------------------------------------------------- LIGGGHTS
def liggghts_input(x: np.ndarray, r: np.ndarray, settle: float, rates) -> str:
    atoms = "\n".join(f"create_atoms 1 single {p[0]:.17g} {p[1]:.17g} {p[2]:.17g} units box"
                      for p in x)
    assert np.allclose(r, RADIUS)
    lines = [f"""# the rotating drum of validation/drum_repose.py
atom_style    granular
atom_modify   map array
boundary      f f f
newton        off
communicate   single vel yes
units         si
region        domain block -0.056 0.056 -0.016 0.016 -0.056 0.056 units box
create_box    1 domain
neighbor      0.001 bin
neigh_modify  delay 0
fix  m1 all property/global youngsModulus peratomtype {E!r}
fix  m2 all property/global poissonsRatio peratomtype {NU!r}
fix  m3 all property/global coefficientRestitution peratomtypepair 1 {REST!r}
fix  m4 all property/global coefficientFriction peratomtypepair 1 {MU!r}
fix  m5 all property/global characteristicVelocity scalar {VC!r}
pair_style  gran model hooke tangential history
pair_coeff  * *
timestep    {DT!r}
fix  gravi all gravity {G!r} vector 0.0 0.0 -1.0
fix  cad all mesh/surface/stress file drum.stl type 1
fix  granwalls all wall/gran model hooke tangential history mesh n_meshes 1 meshes cad
{atoms}
set  group all diameter {2 * RADIUS!r}
set  group all density {DENSITY!r}
fix  integr all nve/sphere
compute       rke all erotate/sphere
variable      tyO equal f_cad[5]+f_cad[9]*f_cad[1]-f_cad[7]*f_cad[3]
thermo_style  custom step atoms ke c_rke f_cad[1] f_cad[3] v_tyO
thermo_modify format float %.10g lost ignore norm no
thermo        {THERMO_EVERY}
dump   dmp all custom {FRAME_EVERY} post/dump*.txt id x y z
run    {int(round(settle / DT))}
"""]
    for k, (w, transient, measured) in enumerate(rates):
        if k:
            lines.append(f"unfix mv{k - 1}")
        lines.append(f"fix  mv{k} all move/mesh mesh cad rotate origin 0. 0. 0. axis 0. 1. 0. "
                     f"period {2 * math.pi / w!r}")
        lines.append(f"run  {int(round((transient + measured) / DT))}")
    return "\n".join(lines) + "\n"


def read_dump(path: Path) -> np.ndarray:
    lines = path.read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith("ITEM: ATOMS"))
    data = np.array([line.split() for line in lines[i + 1:]], dtype=float)
    return data[np.argsort(data[:, 0])][:, 1:4]


def run_liggghts(x, r, settle, rates, work: Path, tag: str) -> dict:
    dest = work / tag
    (dest / "post").mkdir(parents=True)
    (dest / "drum.stl").write_text(STL.read_text())
    (dest / "in.drum").write_text(liggghts_input(x, r, settle, rates))
    start = time.perf_counter()
    proc = subprocess.run(["liggghts", "-in", "in.drum", "-log", "log.liggghts"], cwd=dest,
                          capture_output=True, text=True, env=one_thread())
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        sys.exit(f"liggghts failed: {proc.stdout[-3000:]}{proc.stderr[-2000:]}")
    rows = {int(s): row for s, row in
            liggghts_thermo_table((dest / "log.liggghts").read_text()).items()}
    torque = {s: row["v_tyO"] if "v_tyO" in row else row["tyO"] for s, row in rows.items()}
    atoms = {s: int(row["Atoms"]) for s, row in rows.items()}
    frames = {int(p.stem[4:]): read_dump(p) for p in (dest / "post").glob("dump*.txt")}
    loops = [float(v) for v in re.findall(r"Loop time of ([0-9.eE+-]+) on",
                                          (dest / "log.liggghts").read_text())]
    stage_seconds = dict(zip(["settle"] + [f"w{w:g}" for w, _, _ in rates], loops))
    return {"seconds": seconds, "torque": torque, "atoms_min": min(atoms.values()),
            "frames": frames, "dir": str(dest), "stage_seconds": stage_seconds}


# ------------------------------------------------------------------- measuring
def surface_angle(x: np.ndarray) -> dict:
    """The dynamic angle of repose [deg] of one frame (see the module's docstring)."""
    px, pz = x[:, 0], x[:, 2]
    edges = np.arange(-DRUM_R, DRUM_R + BIN / 2, BIN)
    idx = np.clip(np.digitize(px, edges) - 1, 0, len(edges) - 2)
    tops = np.full(len(edges) - 1, np.nan)
    for b in np.unique(idx):
        tops[b] = pz[idx == b].max()
    centres = 0.5 * (edges[1:] + edges[:-1])
    filled = np.flatnonzero(np.isfinite(tops))
    lo, hi = centres[filled[0]], centres[filled[-1]]
    mid, half = 0.5 * (lo + hi), 0.5 * CENTRAL * (hi - lo)
    use = np.isfinite(tops) & (np.abs(centres - mid) <= half)
    slope, intercept = np.polyfit(centres[use], tops[use], 1)
    return {"angle": math.degrees(math.atan(-slope)), "bins": int(use.sum()),
            "height": float(intercept)}


def stats(values) -> dict:
    a = np.asarray(values, dtype=float)
    return {"mean": float(a.mean()), "std": float(a.std(ddof=1)) if len(a) > 1 else 0.0,
            "n": len(a)}


def measure(run: dict, stages: list[dict]) -> list[dict]:
    out = []
    for st in stages:
        steps = [s for s in sorted(run["frames"]) if st["measure_from"] <= s <= st["end"]]
        angles = [surface_angle(run["frames"][s])["angle"] for s in steps]
        torque = [t for s, t in run["torque"].items() if st["measure_from"] < s <= st["end"]]
        # the angle through the transient too (how fast it settles)
        course = [[s, round(surface_angle(run["frames"][s])["angle"], 3)]
                  for s in sorted(run["frames"]) if st["start"] <= s <= st["end"]]
        out.append({"omega": st["omega"], "froude": st["omega"] ** 2 * DRUM_R / G,
                    "angle": stats(angles), "torque": stats(torque), "course": course})
    return out


def settled(run: dict, settle_steps: int) -> dict:
    x = run["frames"][settle_steps]
    return {"angle": surface_angle(x)["angle"], "top": float(x[:, 2].max()),
            "fill_height": surface_angle(x)["height"]}


def one_seed(seed: int, settle: float, rates, work: Path) -> dict:
    text = case_text(seed, settle, rates)
    x, r = initial_positions(text)
    stages = schedule_steps(settle, rates)
    with ThreadPoolExecutor(2) as pool:
        fl = pool.submit(run_liggghts, x, r, settle, rates, work, f"liggghts-{seed}")
        fd = pool.submit(run_demstep, text, work, f"demstep-{seed}")
        lig, dem = fl.result(), fd.result()
    n_settle = int(round(settle / DT))
    result = {"seed": seed, "particles": len(x)}
    for name, run in (("liggghts", lig), ("demstep", dem)):
        result[name] = {"seconds": round(run["seconds"], 1), "settled": settled(run, n_settle),
                        "rates": measure(run, stages)}
    result["liggghts"]["atoms_min"] = lig["atoms_min"]
    result["liggghts"]["stage_seconds"] = lig["stage_seconds"]  # (its loop times)
    result["demstep"]["stage_seconds"] = dem["stage_seconds"]
    return result


def print_seed(res: dict) -> None:
    print(f"seed {res['seed']}: LIGGGHTS {res['liggghts']['seconds']:.0f} s, demstep "
          f"{res['demstep']['seconds']:.0f} s; settled surface angle "
          f"{res['liggghts']['settled']['angle']:.1f} / {res['demstep']['settled']['angle']:.1f}")
    print(f"{'omega':>6} {'Fr':>7} | {'LIGGGHTS angle':>16} {'demstep angle':>16} | "
          f"{'LIGGGHTS T_y':>14} {'demstep T_y':>14}")
    for a, b in zip(res["liggghts"]["rates"], res["demstep"]["rates"]):
        print(f"{a['omega']:6.2f} {a['froude']:7.4f} | {a['angle']['mean']:7.2f} +- "
              f"{a['angle']['std']:5.2f} {b['angle']['mean']:7.2f} +- {b['angle']['std']:5.2f} | "
              f"{a['torque']['mean']:14.4e} {b['torque']['mean']:14.4e}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--rates", type=float, nargs="+", help="a subset of the rates [rad/s]")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--keep", action="store_true", help="keep the work folder")
    args = ap.parse_args(argv)
    mode = "quick" if args.quick else "full"
    rates = QUICK if args.quick else FULL
    if args.rates:
        rates = [r for r in rates if r[0] in args.rates]
    settle = SETTLE[mode]
    work = Path(tempfile.mkdtemp(prefix="drum_repose_"))
    print(f"work folder {work}")
    seeds = []
    for seed in range(1, args.seeds + 1):
        res = one_seed(seed, settle, rates, work)
        print_seed(res)
        seeds.append(res)
        write(args.out, mode, settle, rates, seeds, work if args.keep else None)
    if not args.keep:
        import shutil
        shutil.rmtree(work, ignore_errors=True)
    return 0


def write(path: Path, mode: str, settle: float, rates, seeds: list[dict], work) -> None:
    """The results so far (rewritten after each seed)."""
    summary = []
    for k, (w, transient, measured) in enumerate(rates):
        row = {"omega": w, "froude": w ** 2 * DRUM_R / G, "transient": transient,
               "measured": measured}
        for code in ("liggghts", "demstep"):
            means = [s[code]["rates"][k]["angle"]["mean"] for s in seeds]
            row[code] = {"angle_seeds": stats(means),
                         "torque_seeds": stats([s[code]["rates"][k]["torque"]["mean"]
                                                for s in seeds])}
        summary.append(row)
    result = {"mode": mode, "dt": DT, "settle": settle, "rates": rates,
              "k_pair": hooke_k(RADIUS / 2, DENSITY * 4 / 3 * math.pi * RADIUS ** 3 / 2),
              "k_wall": hooke_k(RADIUS, DENSITY * 4 / 3 * math.pi * RADIUS ** 3),
              "engine_commit": engine_commit(), "work": str(work) if work else None,
              "summary": summary, "seeds": seeds}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1) + "\n")
    print(f"written {path}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
