"""Angle of repose of a 2D heap of disks against the rolling-resistance coefficient.

Disks (radii uniform in [0.8, 1.2] mm, 2500 kg/m^3 per unit thickness, linear springs
k_n = 1e5 N/m, k_s = k_n / 2, restitution 0.3, friction 0.5) settle in a column
between two walls on a floor (all walls with the disks' friction and rolling
resistance); the side walls are then pulled away and the column collapses into a heap
(the collapse test); rolling resistance (convention epsd: k_r = 2.25 k_n mu_r^2 R*^2,
limit mu_r R* F_n) with mu_r in the list given. The angle is the mean of the two flanks' slopes, each a
least-squares line through the highest disk tops in bins of one diameter between 30 %
and 90 % of the heap's height (below, single disks that rolled away flatten it). Without rolling resistance round disks roll apart into a
low heap; the angle rises with mu_r (the figure of docs/rolling-resistance.md).

    python validation/rolling_repose.py --mu-r 0,0.05,0.1,0.2,0.4 --png docs/img/repose.png
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

from demstep.contact.laws import LinearSpring
from demstep.engine import Simulation, TimeStep
from demstep.particles import Particles
from demstep.walls import Wall

R_MEAN = 1.0e-3
RHO = 2500.0
K_N = 1.0e5
G = 9.81


WIDTH = 16  # disks across the column


def column(n: int, seed: int):
    """n disks on a jittered grid WIDTH wide above the floor (not touching)."""
    rng = np.random.default_rng(seed)
    r = R_MEAN * rng.uniform(0.8, 1.2, n)
    spacing = 2.5 * R_MEAN
    k = np.arange(n)
    x = np.column_stack([(k % WIDTH - (WIDTH - 1) / 2) * spacing,
                         1.3 * R_MEAN + (k // WIDTH) * spacing])
    x += rng.uniform(-0.1, 0.1, x.shape) * R_MEAN
    return x, r


def heap_angle(x, r) -> float:
    """Mean flank angle [deg] of the heap (module docstring)."""
    top = x[:, 1] + r
    height = top.max()
    edges = np.arange(x[:, 0].min(), x[:, 0].max() + 2 * R_MEAN, 2 * R_MEAN)
    centre = 0.5 * (edges[:-1] + edges[1:])
    prof = np.full(len(centre), np.nan)
    idx = np.digitize(x[:, 0], edges) - 1
    for b in range(len(centre)):
        sel = idx == b
        if sel.any():
            prof[b] = top[sel].max()
    ok = np.isfinite(prof) & (prof > 0.3 * height) & (prof < 0.9 * height)
    peak = centre[np.nanargmax(prof)]
    slopes = []
    for side in (centre < peak, centre > peak):
        s = ok & side
        if s.sum() >= 3:
            slopes.append(abs(np.polyfit(centre[s], prof[s], 1)[0]))
    return float(np.degrees(np.arctan(np.mean(slopes)))) if slopes else 0.0


def settle(sim, n, max_time, min_time):
    t_end = sim.time + max_time
    while sim.time < t_end:
        sim.run(duration=0.05)
        if sim.time > min_time and sim.kinetic_energy() < 1e-10 * n:
            break


def pile(mu_r: float, n: int, seed: int, max_time: float) -> dict:
    x, r = column(n, seed)
    extra = dict(rolling_convention="epsd", rolling_friction=mu_r) if mu_r > 0 else {}
    law = LinearSpring(k_n=K_N, k_s=0.5 * K_N, mu=0.5, restitution=0.3, **extra)
    half = 0.5 * WIDTH * 2.5 * R_MEAN + R_MEAN
    walls = [Wall(point=[-half, 0.0], normal=[1.0, 0.0], name="left"),
             Wall(point=[half, 0.0], normal=[-1.0, 0.0], name="right"),
             Wall(point=[0.0, 0.0], normal=[0.0, 1.0], name="floor")]
    sim = Simulation(Particles.from_density(x, r, RHO), law, walls=walls,
                     gravity=[0.0, -G], timestep=TimeStep.from_alpha(0.1))
    t0 = time.perf_counter()
    settle(sim, n, 1.0, 0.2)
    for k, sign in ((0, -1.0), (1, 1.0)):  # pull the walls away
        sim.set_wall_motion(k, "velocity", velocity=[sign * 1.0, 0.0])
    settle(sim, n, max_time, sim.time + 0.3)
    return {"mu_r": mu_r, "n": n, "seed": seed, "angle_deg": heap_angle(sim.x, sim.r),
            "time": sim.time, "steps": sim.step, "wall_s": time.perf_counter() - t0,
            "energy_error": sim.monitor.max_error, "x": sim.x[:, :2].tolist(),
            "r": sim.r.tolist()}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mu-r", default="0,0.05,0.1,0.2,0.4")
    ap.add_argument("--n", type=int, default=480)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--max-time", type=float, default=3.0, help="[s] of simulated time")
    ap.add_argument("--png", default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    rows = [pile(float(m), args.n, args.seed, args.max_time) for m in args.mu_r.split(",")]
    print("| mu_r | angle of repose [deg] | settled at t [s] | steps | wall time [s] | max energy error |")
    print("|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        print(f"| {row['mu_r']:g} | {row['angle_deg']:.1f} | {row['time']:.2f} | {row['steps']} | "
              f"{row['wall_s']:.1f} | {row['energy_error']:.2g} |")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump([{k: v for k, v in row.items() if k not in ("x", "r")}
                       for row in rows], fh,
                      indent=1)
    if args.png:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.collections import PatchCollection
        from matplotlib.patches import Circle

        fig, axes = plt.subplots(len(rows), 1, figsize=(7, 1.6 * len(rows)), sharex=True)
        for ax, row in zip(np.atleast_1d(axes), rows):
            xs = np.asarray(row["x"]) * 1e3
            patches = [Circle(c, rr * 1e3) for c, rr in zip(xs, row["r"])]
            ax.add_collection(PatchCollection(patches, facecolor="0.6", edgecolor="0.2", lw=0.2))
            ax.set_aspect("equal")
            ax.set_xlim(-80, 80)
            ax.set_ylim(0, 45)
            ax.set_title(f"mu_r = {row['mu_r']:g}: {row['angle_deg']:.1f} deg", fontsize=9)
        np.atleast_1d(axes)[-1].set_xlabel("x [mm]")
        fig.tight_layout()
        fig.savefig(args.png, dpi=120)
        print(f"figure: {args.png}")


if __name__ == "__main__":
    main()
