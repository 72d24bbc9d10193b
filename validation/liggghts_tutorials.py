"""LIGGGHTS' own tutorials run in LIGGGHTS and in demstep, side by side.

    python validation/liggghts_tutorials.py [--tutorials meshGran ...] [--out FILE]

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
step by step; the table gives both and their ratio. The results are written to
``validation/results/liggghts_tutorials.json`` and summarised in
``docs/validation-tutorials.md``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

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
        if header is None or len(words) < 4:
            continue
        try:
            values = [float(w) for w in words[:len(header)]]
        except ValueError:
            header = None
            continue
        # (the compute's column is headed "1" in this LIGGGHTS version, "c_1" in others)
        rot = header.index("c_1") if "c_1" in header else header.index("1")
        rows[int(values[0])] = (int(values[1]), values[header.index("KinEng")], values[rot])
    return rows


def run_liggghts(name: str, work: Path) -> tuple[dict, float]:
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
    return liggghts_thermo((dest / "log.liggghts").read_text()), elapsed


def run_demstep(name: str, work: Path) -> tuple[dict, float]:
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
    return rows, elapsed


def compare(name: str, work: Path) -> dict:
    lig, t_lig = run_liggghts(name, work)
    dem, t_dem = run_demstep(name, work)
    steps = sorted(s for s in lig if s in dem and s > 0)
    table = []
    for s in steps:
        (n_l, ke_l, er_l), (n_d, ke_d, er_d) = lig[s], dem[s]
        table.append({"step": s, "particles_liggghts": n_l, "particles_demstep": n_d,
                      "ke_liggghts": ke_l, "ke_demstep": ke_d,
                      "erot_liggghts": er_l, "erot_demstep": er_d})
    return {"tutorial": name, "seconds_liggghts": t_lig, "seconds_demstep": t_dem,
            "rows": table}


def print_table(result: dict) -> None:
    print(f"\n{result['tutorial']}: LIGGGHTS {result['seconds_liggghts']:.1f} s, demstep "
          f"{result['seconds_demstep']:.1f} s (wall clock, one thread each)")
    print(f"{'step':>7} {'N lig':>6} {'N dem':>6} {'KE lig [J]':>11} {'KE dem [J]':>11} "
          f"{'ratio':>6} {'Erot lig':>9} {'Erot dem':>9}")
    for r in result["rows"]:
        ratio = r["ke_demstep"] / r["ke_liggghts"] if r["ke_liggghts"] > 0 else float("nan")
        print(f"{r['step']:>7} {r['particles_liggghts']:>6} {r['particles_demstep']:>6} "
              f"{r['ke_liggghts']:>11.4g} {r['ke_demstep']:>11.4g} {ratio:>6.2f} "
              f"{r['erot_liggghts']:>9.3g} {r['erot_demstep']:>9.3g}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tutorials", nargs="*", default=["meshGran"])
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
    Path(args.out).write_text(json.dumps(results, indent=1) + "\n")
    print(f"\nwritten {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
