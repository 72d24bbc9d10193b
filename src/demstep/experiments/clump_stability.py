"""Clump packings: the measured stability threshold against the exact critical step.

The paper ends by warning that clusters of glued spheres, with their high coordination,
are where a guessed time step goes most wrong. This study measures it on periodic
packings of clumps of 2, 3, 4 and 8 members (touching, or overlapping by their member
``spacing`` < 1), centrosymmetric shapes (a dimer, a straight trimer, a square and a
cube) in one orientation on an orthorhombic lattice whose neighbouring bodies overlap
by ``overlap`` of a radius: every body sees the same surroundings, so the packing is at
rest by symmetry with every contact closed (a random packing relaxed numerically keeps
residual motion that hides the onset of instability). Then:

* the exact critical step of the state (six DOFs per body, the world inertia tensors;
  :mod:`demstep.timestep.clumps`), the rigorous body element bound, YADE's nodal rule
  for clumps and Itasca's sqrt(m_min / K_max);
* the engine's own stability threshold found by bisection: every body gets a small
  random velocity and spin, friction 0.5 keeps every contact stuck, and a run is
  unstable when its kinetic energy exceeds 1000 times the initial one, or when the
  largest kinetic energy of the second half of its ``steps`` steps exceeds ten times
  the largest of the first half (an unstable mode grows exponentially; a stable run,
  undamped, keeps its energy).

alpha = dt / sqrt(m_min / K) with m_min the lightest body's mass and K = k_n = k_t.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from demstep.clumps import ClumpTemplate, place
from demstep.contact.laws import LinearSpring
from demstep.energy import EnergyMonitor
from demstep.engine import Simulation, TimeStep
from demstep.errors import SimulationDiverged
from demstep.timestep import estimate_time_steps

#: member centres of the studied shapes in units of the member radius, before the
#: overlap factor: spacing 2 (touching) times ``spacing`` (< 1: overlapping)
SHAPES = {
    "dimer": [[0, 0, 0], [2, 0, 0]],
    "trimer": [[0, 0, 0], [2, 0, 0], [4, 0, 0]],
    "square": [[0, 0, 0], [2, 0, 0], [0, 2, 0], [2, 2, 0]],
    "cube8": [[a, b, c] for a in (0, 2) for b in (0, 2) for c in (0, 2)],
}


def shape_template(name: str, spacing: float = 1.0, radius: float = 1.0) -> ClumpTemplate:
    """The clump ``name`` of :data:`SHAPES` with members ``spacing`` x 2 r apart."""
    centers = np.asarray(SHAPES[name], dtype=np.float64) * radius * spacing
    return ClumpTemplate(name, centers, np.full(len(centers), radius))


@dataclass
class ClumpSpecimen:
    """A jammed periodic clump packing: body centres, orientations, box, and its
    coordination (contacts per body)."""

    shape: str
    spacing: float
    x: np.ndarray
    q: np.ndarray
    box: np.ndarray
    contacts_per_body: float
    template: ClumpTemplate


def lattice_packing(shape: str, spacing: float = 1.0, per_axis: int = 4,
                    overlap: float = 1.0e-3, density: float = 1.0) -> ClumpSpecimen:
    """``per_axis``^3 bodies of ``shape`` (unit member radius) on the orthorhombic lattice
    whose neighbouring end members overlap by ``overlap`` (module docstring)."""
    template = shape_template(shape, spacing)
    c = template.centers
    span = c.max(axis=0) - c.min(axis=0)
    cell = span + 2.0 * (1.0 - overlap)
    grid = np.stack(np.meshgrid(*[np.arange(per_axis)] * 3, indexing="ij"), -1).reshape(-1, 3)
    origin = grid * cell + 1.0
    cs = place([template], np.zeros(len(origin), dtype=np.int64), origin - c.min(axis=0),
               np.tile([1.0, 0, 0, 0], (len(origin), 1)), density)
    box = cell * per_axis
    spec = ClumpSpecimen(shape, spacing, cs.x.copy(), cs.q.copy(), box, 0.0, template)
    sim = specimen_simulation(spec, 0.1)
    sim.prepare()
    spec.contacts_per_body = 2.0 * sim.contact_set().n / sim.bodies.n
    return spec


def specimen_clumps(spec: ClumpSpecimen, density: float = 1.0):
    """The packing's bodies as a ClumpSet (:func:`demstep.clumps.place`) of ``density``."""
    cs = place([spec.template], np.zeros(len(spec.x), dtype=np.int64), np.zeros_like(spec.x),
               np.tile([1.0, 0, 0, 0], (len(spec.x), 1)), density)
    cs.x[:] = spec.x
    cs.q[:] = spec.q
    return cs


def perturbation(n: int, m: float, k: float, seed: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """The small random velocities [L/T] and spins [1/T] (``n``, 3) of the bodies, of
    amplitude 1e-6 sqrt(k / m)."""
    rng = np.random.default_rng(seed)
    amplitude = 1e-6 * math.sqrt(k / m)
    return rng.normal(0, amplitude, (n, 3)), rng.normal(0, amplitude, (n, 3))


def specimen_simulation(spec: ClumpSpecimen, alpha: float, k: float = 1.0e6, density: float = 1.0,
                        rotation: bool = True, seed: int = 2) -> Simulation:
    """The jammed packing at rest, friction 0.5, a small random perturbation, and
    dt = alpha sqrt(m_min / K)."""
    cs = specimen_clumps(spec, density)
    m = cs.frames[0][2]
    velocities, spins = perturbation(len(spec.x), m, k, seed)
    sim = Simulation(None, LinearSpring(k_n=k, k_s=k, mu=0.5), periodic=list(spec.box[:3]),
                     clumps=cs, clump_velocities=velocities,
                     clump_angular_velocities=spins if rotation else None, rotation=rotation,
                     timestep=TimeStep.fixed(alpha * math.sqrt(m / k)),
                     energy=EnergyMonitor(every=10**9), runaway_factor=0.0, jump_limit=np.inf)
    return sim


def estimates(spec: ClumpSpecimen, rotation: bool = True, k: float = 1.0e6) -> dict:
    """alpha of the exact step, the body element bound, the nodal rule and Itasca."""
    sim = specimen_simulation(spec, 0.1, k=k, rotation=rotation)
    sim.prepare()
    report = estimate_time_steps(sim.particles_now(), sim.contact_set(), rotation=rotation,
                                 methods=("exact", "element-coupled", "nodal", "itasca",
                                          "guidance"), bodies=sim.rigid_bodies())
    return {e.method: e.alpha for e in report.estimates}


def is_unstable(spec: ClumpSpecimen, alpha: float, steps: int = 3000, rotation: bool = True,
                growth: float = 10.0) -> bool:
    """The criterion of the module docstring (non-finite values count as unstable)."""
    sim = specimen_simulation(spec, alpha, rotation=rotation)
    energies = []
    try:
        sim.run(steps=1)
        start = sim.ledger.kinetic
        sim.every(10, lambda s: energies.append(s.ledger.kinetic))
        sim.run(steps=steps)
    except SimulationDiverged:
        return True
    energies = np.asarray(energies)
    if not np.isfinite(energies).all():
        return True
    half = len(energies) // 2
    return bool(energies.max() > 1e3 * start
                or energies[half:].max() > growth * energies[:half].max())


def measured_threshold(spec: ClumpSpecimen, rotation: bool = True, rtol: float = 2e-3,
                       steps: int = 3000) -> tuple[float, tuple[float, float]]:
    """The smallest unstable alpha (bisection to ``rtol``), from a bracket around the
    exact value."""
    exact = estimates(spec, rotation)["exact"]
    lo, hi = 0.8 * exact, 1.25 * exact
    if is_unstable(spec, lo, steps, rotation) or not is_unstable(spec, hi, steps, rotation):
        raise RuntimeError(f"{spec.shape}: the threshold is not within [0.8, 1.25] x exact")
    while hi / lo - 1.0 > rtol:
        mid = math.sqrt(lo * hi)
        if is_unstable(spec, mid, steps, rotation):
            hi = mid
        else:
            lo = mid
    return hi, (lo, hi)


def clump_study(shape: str, spacing: float = 1.0, rotation: bool = True, rtol: float = 2e-3,
                steps: int = 3000, per_axis: int = 4) -> dict:
    """One row of the study: coordination, measured threshold and the estimates."""
    spec = lattice_packing(shape, spacing, per_axis=per_axis)
    est = estimates(spec, rotation)
    alpha, bracket = measured_threshold(spec, rotation, rtol, steps)
    return {"shape": shape, "members": len(SHAPES[shape]), "spacing": spacing,
            "rotation": rotation, "contacts_per_body": spec.contacts_per_body,
            "alpha_empirical": alpha, "bracket": list(bracket), "estimates": est}
