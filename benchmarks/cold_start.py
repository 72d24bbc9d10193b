"""What a user waits on a fresh machine: cold (empty numba cache) and warm wall times
of `demstep run` on the settling example and of `demstep dt` on a lattice.

Each cold run gets an empty NUMBA_CACHE_DIR (nothing compiled yet, as after pip
install); the warm run reuses it. ``--src`` runs another source tree (e.g. a worktree of
an older commit, for a before/after).

    python benchmarks/cold_start.py [--src /tmp/before/src] [--repeat 2]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = {
    "run settle example": ["run", str(ROOT / "examples" / "polydisperse_settling_3d.toml"),
                           "--out", "{out}", "--quiet"],
    "dt fcc lattice": ["dt", "--lattice", "fcc", "--size", "4", "--kn", "1e6"],
}


def timed(argv, env) -> float:
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "demstep.cli", *argv], env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--src", default=str(ROOT / "src"))
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    for label, argv in COMMANDS.items():
        cold, warm = [], []
        for _ in range(args.repeat):
            with tempfile.TemporaryDirectory() as tmp:
                env = {**os.environ, "PYTHONPATH": args.src, "NUMBA_CACHE_DIR": str(Path(tmp) / "cache")}
                cmd = [a.replace("{out}", str(Path(tmp) / "out1")) for a in argv]
                cold.append(timed(cmd, env))
                cmd = [a.replace("{out}", str(Path(tmp) / "out2")) for a in argv]
                warm.append(timed(cmd, env))
        print(f"{label:20s} cold {statistics.median(cold):6.1f} s  warm {statistics.median(warm):5.1f} s  "
              f"(runs cold {', '.join(f'{c:.1f}' for c in cold)}; src {args.src})")


if __name__ == "__main__":
    main()
