"""Two versions of demstep side by side on the peer problems (A/B, interleaved).

Runs ``benchmarks/peers.py --codes demstep`` on the same problem alternately with two
source trees (``--a`` and ``--b``, each a ``src`` folder of a checkout, e.g. a
``git worktree`` of an older commit), ``--repeat`` times each after one untimed run per
tree (numba compiles or loads its cache), and prints the median particle-steps per
second of each and their ratio b / a. The issue's target for the engine redesign:
spheres as single-member bodies within 3 % of the throughput before it.

    git worktree add /tmp/before <commit>
    python benchmarks/ab_demstep.py --a /tmp/before/src --b src --problem dense --n 100000
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def one_run(src, problem, n, threads, steps, warmup) -> float:
    cmd = [sys.executable, str(HERE / "peers.py"), "--codes", "demstep", "--problem", problem,
           "--n", str(n), "--threads", str(threads), "--steps", str(steps), "--warmup",
           str(warmup), "--repeat", "1", "--json", "--demstep-src", str(src)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True, cwd=HERE)
    report = json.loads(out.stdout.strip().splitlines()[-1])
    row = next(r for r in report["results"] if r["code"] == "demstep")
    return float(row["psps_median"])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", required=True, help="src folder of version A (before)")
    ap.add_argument("--b", required=True, help="src folder of version B (after)")
    ap.add_argument("--problem", choices=("dense", "settle", "hopper", "drum"), default="dense")
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    for src in (args.a, args.b):  # compile or load the caches, untimed
        one_run(src, args.problem, 2000, args.threads, 20, 2)
    runs = {"a": [], "b": []}
    for _ in range(args.repeat):
        for key, src in (("a", args.a), ("b", args.b)):
            runs[key].append(one_run(src, args.problem, args.n, args.threads, args.steps,
                                     args.warmup))
    med = {k: statistics.median(v) for k, v in runs.items()}
    out = {"problem": args.problem, "n": args.n, "threads": args.threads, "runs": runs,
           "median_psps": med, "ratio_b_over_a": med["b"] / med["a"]}
    if args.json:
        print(json.dumps(out))
        return
    for k in ("a", "b"):
        print(f"{k}: {med[k] / 1e6:.3f} M particle-steps/s (runs "
              f"{', '.join(f'{v / 1e6:.3f}' for v in runs[k])})")
    print(f"{args.problem} N={args.n} threads={args.threads}: b / a = {out['ratio_b_over_a']:.3f}")


if __name__ == "__main__":
    main()
