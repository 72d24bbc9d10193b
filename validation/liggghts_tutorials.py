"""LIGGGHTS' own tutorials run in LIGGGHTS and in demstep, side by side.

    python validation/liggghts_tutorials.py [--tutorials meshGran conveyor] [--out FILE]

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
"""

from __future__ import annotations

import argparse
import json
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


def run_liggghts(name: str, work: Path) -> tuple[dict, float, Path]:
    src = TUTORIALS / name
    dest = work / f"liggghts-{name}"
    shutil.copytree(src, dest)
    (dest / "post").mkdir(exist_ok=True)
    start = time.perf_counter()
    proc = subprocess.run(["liggghts", "-in", f"in.{name}", "-log", "log.liggghts"], cwd=dest,
                          capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        sys.exit(f"liggghts failed on {name}: {proc.stdout[-2000:]}{proc.stderr[-2000:]}")
    return liggghts_thermo((dest / "log.liggghts").read_text()), elapsed, dest


def run_demstep(name: str, work: Path) -> tuple[dict, float, Path]:
    out = work / f"demstep-{name}"
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "demstep.cli", "run", str(CASES / f"{name}.toml"),
                           "--out", str(out), "--quiet"], capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        sys.exit(f"demstep failed on {name}: {proc.stderr[-2000:]}")
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


EXTRA = {"conveyor": ("belt", conveyor_flow)}


def compare(name: str, work: Path) -> dict:
    lig, t_lig, lig_dir = run_liggghts(name, work)
    dem, t_dem, dem_dir = run_demstep(name, work)
    steps = sorted(s for s in lig if s in dem and s > 0)
    table = []
    for s in steps:
        (n_l, ke_l, er_l), (n_d, ke_d, er_d) = lig[s], dem[s]
        table.append({"step": s, "particles_liggghts": n_l, "particles_demstep": n_d,
                      "ke_liggghts": ke_l, "ke_demstep": ke_d,
                      "erot_liggghts": er_l, "erot_demstep": er_d})
    result = {"tutorial": name, "seconds_liggghts": t_lig, "seconds_demstep": t_dem,
              "stage_seconds_demstep": demstep_stage_seconds(dem_dir), "rows": table}
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
    ap.add_argument("--tutorials", nargs="*", default=["meshGran", "conveyor"],
                    choices=["meshGran", "conveyor"],
                    help="the tutorials to run (default: all); the others' entries in the "
                         "JSON file are kept")
    ap.add_argument("--out", default=str(ROOT / "validation" / "results" / "liggghts_tutorials.json"))
    ap.add_argument("--keep", action="store_true", help="keep the run folders")
    args = ap.parse_args(argv)
    if shutil.which("liggghts") is None or not TUTORIALS.is_dir():
        sys.exit("needs Debian's liggghts and liggghts-doc: apt-get install liggghts liggghts-doc")
    work = Path(tempfile.mkdtemp(prefix="demstep-tutorials-"))
    results = []
    try:
        for name in args.tutorials:
            result = compare(name, work)
            print_table(result)
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
