"""demstep's certificate under LAMMPS' own conventions (``demstep dt --lammps-model``)
against the thresholds LAMMPS' runs measured (``validation/lammps_thresholds.py``).

For every case of ``validation/results/lammps_thresholds.json`` with a measured
bracket, the same dump is certified with the case's ``pair_coeff`` text (the slab with
its two ``fix wall/gran`` planes as ``--wall z- --wall z+``); prints a markdown table
(exact and element-coupled steps, the gap to the bracket's centre) and writes
``validation/results/lammps_model_check.json``. No LAMMPS run: seconds.

    python validation/lammps_model_check.py
"""

from __future__ import annotations

import ast
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))

from lammps_thresholds import pair_lines  # noqa: E402


def model_text(case: dict) -> str:
    """The ``pair_coeff * *`` text LAMMPS ran the case with."""
    p = case["parameters"]
    p = ast.literal_eval(p) if isinstance(p, str) else p
    return pair_lines(p)[1].split("* *", 1)[1].strip()


def check_case(case: dict) -> dict:
    from demstep.analysis_input import from_file
    from demstep.integrations.lammps_model import GranularModel
    from demstep.timestep.estimates import element_coupled_dt, exact_dt

    walls = ["z-", "z+"] if case["state"].startswith("slab") else ()
    text = model_text(case)
    data = from_file(REPO / case["dump"], None, lammps_model=GranularModel.parse(text),
                     walls=walls)
    low, high = case["threshold"]["bracket"]
    exact = exact_dt(data.particles, data.contacts, case["rotation"])
    element = element_coupled_dt(data.particles, data.contacts, case["rotation"])
    centre = (low * high) ** 0.5
    return {"model": text, "bracket": [low, high], "exact": exact, "element_coupled": element,
            "gap": exact / centre - 1.0, "above": exact > high}


def main() -> int:
    cases = json.loads((HERE / "results" / "lammps_thresholds.json").read_text())["cases"]
    out = {name: check_case(c) for name, c in sorted(cases.items()) if c.get("threshold")}
    (HERE / "results" / "lammps_model_check.json").write_text(json.dumps(out, indent=1))
    print("| case | LAMMPS bracket [s] | exact, --lammps-model [s] | (exact - thr) / thr | "
          "element-coupled [s] |")
    print("|---|---|---|---|---|")
    for name, r in out.items():
        low, high = r["bracket"]
        flag = " **above**" if r["above"] else ""
        print(f"| {name} | {low:.7g} - {high:.7g} | {r['exact']:.7g} | {100 * r['gap']:+.3f} %"
              f"{flag} | {r['element_coupled']:.5g} |")
    above = [n for n, r in out.items() if r["above"]]
    print(f"\n{len(out)} cases; above the bracket: {len(above)}; largest gap below: "
          f"{100 * min(r['gap'] for r in out.values()):+.3f} %")
    return 1 if above else 0


if __name__ == "__main__":
    raise SystemExit(main())
