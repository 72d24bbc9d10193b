"""Where a demstep process's memory goes: the fixed floor of Python, numpy and numba
against the data of a problem.

Each stage runs in a fresh process and reports the resident set (VmRSS) and its peak
(VmHWM) from /proc/self/status, in MB:

- ``python``: the interpreter alone;
- ``numpy``, ``numba``: after importing them (numba imports scipy itself);
- ``trivial kernel``: after calling one trivial ``@njit(cache=True)`` function loaded
  from numba's cache (numba's typing and lowering registries, LLVM's code pages): what
  any process that runs a numba kernel pays, before any data;
- ``demstep kernels``: a 500-sphere piece of the problem stepped twice (the step's
  kernels loaded), then the whole problem (``--problem``, ``--n``) built and stepped
  ``--steps`` times: the peak is what ``benchmarks/peers.py`` reports, the difference
  to the kernels' floor is the problem's data.

    python benchmarks/memory_floor.py --problem dense --n 100000

The issue's targets (at most 1.5x LIGGGHTS' peak at 1e5, 2.5x at 1e4) are compared by
``peers.py``; this script says how much of demstep's figure is the floor.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent

STATUS = r"""
def status():
    out = {}
    for line in open("/proc/self/status"):
        key = line.split(":")[0]
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(line.split()[1]) / 1024
    return out
"""

STAGES = {
    "python": "",
    "numpy": "import numpy",
    "numba": "import numpy, numba",
    "trivial kernel": "import numpy, numba, trivial_kernel\ntrivial_kernel.total(numpy.ones(3))",
}

#: the trivial kernel's module (numba caches only functions defined in files)
TRIVIAL = """
import numba

@numba.njit(cache=True)
def total(a):
    s = 0.0
    for v in a:
        s += v
    return s
"""

PROBLEM = r"""
import json, sys
sys.path.insert(0, sys.argv[1])
import demstep  # noqa: F401  (the threading layer before numba starts threads)
import numba
numba.set_num_threads(1)
from demstep.engine import TimeStep
from peers import demstep_simulation, make_problem
x, spec = make_problem(sys.argv[2], int(sys.argv[3]))
piece = demstep_simulation(x[:500], spec, TimeStep.fixed(spec["dt"]))
piece.run(steps=2)
kernels = status()
del piece
sim = demstep_simulation(x, spec, TimeStep.fixed(spec["dt"]))
sim.run(steps=int(sys.argv[4]))
print(json.dumps({"kernels": kernels, "problem": status(), "n": len(x),
                  "pairs": int(len(sim.pi))}))
"""


def run(code: str, cwd: str) -> dict:
    out = subprocess.run([sys.executable, "-c", "import sys; sys.path.insert(0, '.')\n"
                          + STATUS + code + "\nimport json\nprint(json.dumps(status()))"],
                         capture_output=True, text=True, check=True, cwd=cwd)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problem", choices=("dense", "settle"), default="dense")
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--steps", type=int, default=20)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        (Path(folder) / "trivial_kernel.py").write_text(TRIVIAL)
        run(STAGES["trivial kernel"], folder)  # compiles it into numba's cache
        stages = {name: run(code, folder) for name, code in STAGES.items()}
    for name, s in stages.items():
        print(f"{name:18s} RSS {s['VmRSS']:7.1f} MB   peak {s['VmHWM']:7.1f} MB")
    out = subprocess.run([sys.executable, "-c", STATUS + PROBLEM, str(HERE), args.problem,
                          str(args.n), str(args.steps)],
                         capture_output=True, text=True, check=True)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    k, p = got["kernels"], got["problem"]
    print(f"{'demstep kernels':18s} RSS {k['VmRSS']:7.1f} MB   peak {k['VmHWM']:7.1f} MB")
    print(f"{args.problem + ' ' + str(got['n']):18s} RSS {p['VmRSS']:7.1f} MB   peak "
          f"{p['VmHWM']:7.1f} MB   ({got['pairs']} pairs; data and work space "
          f"{p['VmHWM'] - k['VmRSS']:.1f} MB above the kernels' floor)")


if __name__ == "__main__":
    main()
