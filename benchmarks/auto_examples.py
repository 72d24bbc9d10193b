"""How many exact solves the certified 'auto' step needs on the shipped examples.

Each example of ``examples/`` (the 2D biaxial consolidation against servo walls, the
3D polydisperse settling) runs in 'auto' mode (``method = "exact"``, ``--safety``,
re-evaluated ``--every`` steps, as ``tests/test_auto_timestep.py``) for at most
``--max-steps`` per stage; printed per example (JSON lines): the steps and simulated
time reached, and the 'auto' control's counters: exact solves, refreshes of a kept
certificate, scheduled estimates, element bounds, cover extensions. Counts, not
timings: they compare across machines.

    python benchmarks/auto_examples.py [--safety 0.9] [--every 200]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import tomllib
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
#: (example, steps per stage at most)
CASES = (("hex_biaxial_2d.toml", 1600), ("polydisperse_settling_3d.toml", 2400))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--safety", type=float, default=0.9)
    ap.add_argument("--every", type=int, default=200)
    args = ap.parse_args()

    import demstep.engine as engine
    from demstep.case import case_from_dict
    from demstep.runner import run_case

    built = []
    init = engine.Simulation.__init__

    def recording_init(self, *a, **k):  # (the runner builds the simulation inside)
        init(self, *a, **k)
        built.append(self)

    engine.Simulation.__init__ = recording_init
    for name, max_steps in CASES:
        data = tomllib.loads((EXAMPLES / name).read_text())
        data["timestep"] = {"mode": "auto", "method": "exact", "safety": args.safety,
                            "every": args.every}
        data["output"] = {"history_every": 100, "checkpoint_every": 10**9}
        case = case_from_dict(data, base_dir=EXAMPLES, source=name)
        built.clear()
        with tempfile.TemporaryDirectory() as folder:
            result = run_case(case, Path(folder) / "out", quiet=True, max_steps=max_steps)
        sim = built[-1]
        print(json.dumps({"example": name, "status": result.status, "steps": result.step,
                          "time": result.time, "solves": sim.n_dt_solves,
                          "refreshes": sim.n_dt_refreshes,
                          "estimates": getattr(sim, "n_dt_estimates", 0),
                          "element": getattr(sim, "n_dt_element", 0),
                          "extensions": getattr(sim, "n_dt_extensions", 0)}))


if __name__ == "__main__":
    main()
