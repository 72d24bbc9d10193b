"""Markdown table of peer benchmark reports (the JSON lines of run_peers_matrix.sh).

    python benchmarks/peers_table.py benchmarks/results/peers-matrix.jsonl
"""

from __future__ import annotations

import json
import sys


def fmt(v):
    return f"{v / 1e6:.2f}" if v is not None else "-"


def main(paths):
    reports = []
    for path in paths:
        with open(path) as f:
            reports += [json.loads(line) for line in f if line.strip()]
    order = {"dense": 0, "settle": 1}
    reports.sort(key=lambda r: (order.get(r["problem"], 9), r["n"], r["threads"]))
    print("| problem | N | threads | code | M particle-steps/s median (min-max) | best | "
          "per CPU-s (1 thread) | peak RSS MB (runs) | demstep / LIGGGHTS median (best) | other load % |")
    print("|---|---:|---:|---|---|---:|---:|---:|---|---|")
    for r in reports:
        lig = next((e for e in r["results"] if e["code"] == "liggghts"), None)
        for e in r["results"]:
            ratio = "-"
            if e["code"] == "demstep" and lig:
                ratio = (f"{e['psps_median'] / lig['psps_median']:.2f} "
                         f"({e['psps_max'] / lig['psps_max']:.2f})")
            load = "/".join(f"{100 * x:.0f}" for x in e.get("foreign_load", []))
            rss = f"{e['rss_mb']:.0f}"
            if "rss_mb_runs" in e:  # each run's, in order (a first run may compile)
                rss += " (" + "/".join(f"{x:.0f}" for x in e["rss_mb_runs"]) + ")"

            print(f"| {r['problem']} | {e['n']} | {e['threads']} | {e['code']} | "
                  f"{fmt(e['psps_median'])} ({fmt(e['psps_min'])}-{fmt(e['psps_max'])}) | "
                  f"{fmt(e['psps_max'])} | {fmt(e.get('psps_cpu_median'))} | {rss} | "
                  f"{ratio} | {load} |")


if __name__ == "__main__":
    main(sys.argv[1:])
