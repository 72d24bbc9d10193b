"""Unconfined uniaxial compression of a bonded block: stress-strain curve, Young's
modulus and peak strength, with the certified step of the bonded assembly.

A block of spheres (FCC lattice, radius 1 mm, inflated by 1e-3 so that neighbours
touch; 2650 kg/m^3) is bonded at every contact with parallel bonds (Potyondy &
Cundall 2004: k_n^b = k_s^b per unit area, tensile and shear strengths, radius
multiplier 1) acting in parallel with linear contacts (k_n = k_s); the bottom wall is
fixed, the top wall moves down at a constant speed slow enough for a quasi-static
test (the axial strain rate times the block's wave transit time is 1e-4),
the sides are free. Axial stress = force on the top wall / the block's section;
modulus = slope of a line through the curve between 10 % and 40 % of the peak; the
peak and the number of broken bonds are reported. The step is 0.8 of the exact
critical step of the bonded assembly (its bond springs as contact, bending and
twisting elements), and, for comparison, what the contact law alone would certify.

    python validation/bonded_block.py --cells 4,4,8 --csv validation/results/bonded-block.csv
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from demstep.contact.bonds import ParallelBonds
from demstep.contact.laws import LinearSpring
from demstep.engine import Damping, Simulation, TimeStep
from demstep.packings import lattice
from demstep.particles import Particles
from demstep.walls import Wall

RADIUS = 1.0e-3
RHO = 2650.0


def block(cells, k_n: float, bond_stiffness: float, sigma_c: float, tau_c: float):
    """The bonded block between two walls (module docstring); returns the Simulation
    and the block's height and section."""
    lat = lattice("fcc", RADIUS)
    x, box = lat.supercell(1)
    reps = np.stack(np.meshgrid(*[np.arange(c) for c in cells], indexing="ij"), -1).reshape(-1, 3)
    x = (x[None, :, :] + reps[:, None, :] * np.asarray(box)[None, None, :]).reshape(-1, 3)
    x -= x.min(axis=0)
    x += RADIUS
    r = np.full(len(x), RADIUS * (1 + 1e-3))
    height = float(x[:, 2].max() + RADIUS)
    section = float((x[:, 0].max() + 2 * RADIUS) * (x[:, 1].max() + 2 * RADIUS))
    walls = [Wall(point=[0, 0, 0], normal=[0, 0, 1], name="bottom"),
             Wall(point=[0, 0, height], normal=[0, 0, -1], name="top")]
    law = LinearSpring(k_n=k_n, k_s=k_n, mu=0.5)
    sim = Simulation(Particles.from_density(x, r, RHO), law, walls=walls,
                     timestep=TimeStep.fixed(1.0), damping=Damping(local=0.1))
    sim.add_bonds(ParallelBonds(normal_stiffness=bond_stiffness, tensile_strength=sigma_c,
                                shear_strength=tau_c, gap=1e-9))
    return sim, height, section


def compress(cells=(3, 3, 6), k_n=1.0e6, bond_stiffness=1.0e12, sigma_c=5.0e6, tau_c=5.0e6,
             strain_end=3e-2, safety=0.8, rate_factor=1e-4) -> dict:
    sim, height, section = block(cells, k_n, bond_stiffness, sigma_c, tau_c)
    sim.prepare()
    dt_bonded = sim.critical_dt("exact")
    sim.bonds = sim.bonds._replace(intact=np.zeros_like(sim.bonds.intact))
    dt_contacts = sim.critical_dt("exact")
    sim.bonds = sim.bonds._replace(intact=np.ones_like(sim.bonds.intact))
    sim.dt = safety * dt_bonded
    sim.timestep = TimeStep.fixed(sim.dt)
    # quasi-static: axial strain rate x wave transit time (height / c) below rate_factor
    modulus_guess = bond_stiffness * 2 * RADIUS
    c = math.sqrt(modulus_guess / RHO)
    rate = rate_factor * c / height
    speed = rate * height
    top = next(k for k, w in enumerate(sim.walls) if w.name == "top")
    sim.set_wall_motion(top, "velocity", velocity=[0.0, 0.0, -speed])
    steps_total = int(strain_end / rate / sim.dt)
    curve = []
    t0 = time.perf_counter()

    def record(s):
        strain = s.time * rate
        stress = float(s.wall_force[top, 2]) / section
        curve.append((strain, stress, int((s.bonds.intact == 0).sum())))

    sim.every(max(1, steps_total // 400), record)
    sim.run(steps=steps_total)
    curve = np.asarray(curve)
    peak = float(curve[:, 1].max())
    sel = (curve[:, 1] > 0.1 * peak) & (curve[:, 1] < 0.4 * peak) & \
          (np.arange(len(curve)) < np.argmax(curve[:, 1]))
    modulus = float(np.polyfit(curve[sel, 0], curve[sel, 1], 1)[0]) if sel.sum() > 2 else float("nan")
    return {"particles": len(sim.r), "bonds": int(sim.bonds.n), "dt": sim.dt,
            "dt_exact_bonded": dt_bonded, "dt_exact_contacts_only": dt_contacts,
            "steps": sim.step, "wall_s": time.perf_counter() - t0, "peak_stress": peak,
            "strain_at_peak": float(curve[np.argmax(curve[:, 1]), 0]), "modulus": modulus,
            "broken": int((sim.bonds.intact == 0).sum()), "energy_error": sim.monitor.max_error,
            "curve": curve}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", default="4,4,8")
    ap.add_argument("--strain", type=float, default=3e-2)
    ap.add_argument("--rate-factor", type=float, default=1e-4,
                    help="axial strain rate x wave transit time of the block")
    ap.add_argument("--csv", default=None)
    args = ap.parse_args()
    res = compress(tuple(int(c) for c in args.cells.split(",")), strain_end=args.strain,
                   rate_factor=args.rate_factor)
    print(f"particles {res['particles']}, bonds {res['bonds']}, steps {res['steps']} "
          f"({res['wall_s']:.1f} s)")
    print(f"dt = {res['dt']:.4g} s = 0.8 x exact critical step of the bonded assembly "
          f"{res['dt_exact_bonded']:.4g} s (contacts alone: {res['dt_exact_contacts_only']:.4g} s, "
          f"{res['dt_exact_contacts_only'] / res['dt_exact_bonded']:.1f}x larger: unstable with bonds)")
    print(f"Young's modulus {res['modulus'] / 1e6:.1f} MPa, peak stress {res['peak_stress'] / 1e6:.3f} MPa "
          f"at axial strain {res['strain_at_peak']:.2e}, {res['broken']} of {res['bonds']} bonds broken, "
          f"max energy error {res['energy_error']:.2g}")
    if args.csv:
        np.savetxt(args.csv, res["curve"], delimiter=",", header="strain,stress_Pa,broken_bonds",
                   comments="")


if __name__ == "__main__":
    main()
