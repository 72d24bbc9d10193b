"""A runnable tour of the Python API: spheres settling in a box under gravity, with the
time step chosen automatically and certified, an energy check and a history callback.

    python examples/engine_api.py [--steps N]
"""

import argparse

import numpy as np

from demstep.contact.laws import LinearSpring
from demstep.engine import Damping, Simulation, TimeStep
from demstep.energy import EnergyMonitor
from demstep.particles import Particles
from demstep.walls import box_walls


def main(steps: int = 4000):
    rng = np.random.default_rng(0)
    # 6 x 6 x 6 spheres of radius 0.4-0.5 on a loose grid (spacing 1.1), density 2650
    grid = np.stack(np.meshgrid(*[np.arange(6) * 1.1] * 3, indexing="ij"), -1).reshape(-1, 3)
    particles = Particles.from_density(grid + 0.6, rng.uniform(0.4, 0.5, len(grid)), 2650.0)
    sim = Simulation(
        particles,
        LinearSpring(k_n=1e7, k_s=1e7, mu=0.5, restitution=0.6),
        walls=box_walls(lower=[0, 0, 0], upper=[6.8, 6.8, 12.0]),
        gravity=[0.0, 0.0, -9.81],
        damping=Damping(local=0.0),
        # dt = 0.8 x the exact critical step of the current contacts, re-evaluated
        # every 500 steps (before contacts form: the densest-packing bound)
        timestep=TimeStep.auto(safety=0.8, method="exact", every=500),
        energy=EnergyMonitor(eps=1e-2, every=100, action="warn"),
    )
    history = []
    sim.every(500, lambda s: history.append((s.step, s.time, s.dt, s.dt_estimate,
                                             s.ledger.kinetic, s.ledger.balance_error())))
    sim.run(steps=steps)
    print(f"{'step':>6} {'time':>8} {'dt':>10} {'dt_crit':>10} {'kinetic':>10} {'energy err':>10}")
    for step, t, dt, est, ke, err in history:
        est = float("nan") if est is None else est
        print(f"{step:6d} {t:8.4f} {dt:10.3e} {est:10.3e} {ke:10.3e} {err:10.2e}")
    print(f"floor stress {sim.wall_stress()[4]:.4g}, contacts {sim.n_contacts}, "
          f"critical step now {sim.critical_dt('exact'):.3e}")
    return sim


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=4000)
    main(ap.parse_args().steps)
