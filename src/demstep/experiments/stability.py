"""Measured stability threshold of the engine against every prediction (beyond the paper).

For a specimen whose contacts all stay closed (a pre-compressed periodic lattice, or
the confined FCC specimen of the plane-strain test) the explicit scheme is a linear
system, so it goes unstable exactly when dt exceeds 2 / omega_max. We find the
smallest unstable alpha = dt / sqrt(m/K) by bisection and compare it with the
estimates of ``demstep dt`` on the same specimen.

Protocol: radii are inflated by ``precompression`` (relative overlap 1e-3), every
particle gets a random velocity and angular velocity of small amplitude (the
displacements stay ``perturbation`` = 1e-7 of the overlap), and the run lasts
``steps`` steps with linear springs K_n = K_s and friction 0.5.

Energy criterion: the run is unstable when its kinetic energy exceeds
``growth`` (1000) times the kinetic energy it started with -- energy the integrator
created. Below the critical step the kinetic energy stays bounded (the mean
half-step velocities inflate the highest mode's energy by at most 1 / (1 - (omega
dt / 2)^2), ~100 at 0.5 % below critical); above it the unstable mode grows by a
factor |lambda| > 1 per step (1.2 at 0.5 % above for the undamped lattices), so 3000
steps separate the two cases to within the bisection tolerance (heavily damped modes
grow far more slowly: below).

Why the perturbation is so small: the measurement is of the linear system, and the
engine has one nonlinearity that acts long before any contact opens or slides. The
tangential dashpot of a sticking contact is capped so that spring plus dashpot stay
within mu F_n (:func:`demstep.kernels.response.coulomb_dashpot`). In the fastest mode
of a heavily damped packing near the damped critical step the dashpot force is many
times the spring force (c s x against k x, s ~ c / m for strong damping: 17 times at
restitution 0.2), so the cap binds while the displacements are still ~1e-2 of the
overlap. Capping lowers the damping, the mode falls back below its critical step and
decays: the growth saturates instead of reaching the criterion. With a perturbation
of 1e-4 of the overlap (this module's earlier default) and mu = 0.5 the unstable
mode of the FCC specimen stopped at ~150 times the initial kinetic energy at 1 %
above the damped exact step (restitution 0.2), and the measured thresholds came out
0.5 % (restitution 0.5) and 1.5 % (0.2) above that step. From 1e-6 of the overlap down
they do not move, and they equal those with mu = 100 (no cap). The engine's own
linearised step map (:mod:`demstep.experiments.amplification`) has spectral radius 1
at the damped exact step.

Slow growth near a damped threshold: the random start projects very weakly on the
critical mode of the damped FCC specimen (~1e-12 of the kinetic energy), so the
detection needs ln(1e15) / (2 (|lambda| - 1)) steps; with |lambda| - 1 ~ 2.5 x the
relative excess of dt, 3000 steps detect 0.2 % above the threshold and 30000 steps
0.03 % (measured: +0.17 % and +0.023 % at restitution 0.5). The damping study runs
:data:`DAMPING_STEPS`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from demstep.contact.laws import LinearSpring
from demstep.energy import EnergyMonitor
from demstep.engine import Simulation, TimeStep
from demstep.errors import InputError, SimulationDiverged
from demstep.experiments.fcc_plane_strain import FCCConfig, fcc_specimen
from demstep.packings import LATTICE_NAMES, lattice
from demstep.particles import Particles
from demstep.timestep.estimates import estimate_time_steps
from demstep.timestep.rules import rayleigh_time

SPECIMEN = "fcc-specimen"
STUDY_NAMES = LATTICE_NAMES + (SPECIMEN,)
#: supercell sizes giving periodic boxes of at least 3 contact reaches
SUPERCELL = {"square": 4, "hex": 4, "sc": 4, "bcc": 3, "fcc": 4, "rhombic": 4}
COMPARED = ("exact", "element-coupled", "element-paper", "nodal", "itasca")


@dataclass
class StabilityResult:
    lattice: str
    alpha_empirical: float
    estimates: dict
    bracket: tuple
    trials: int

    def to_json(self) -> dict:
        """The documented JSON of ``demstep stability --json``."""
        return {"lattice": self.lattice, "alpha_empirical": self.alpha_empirical,
                "estimates": self.estimates}


def build_specimen(name: str, alpha: float, k: float = 1.0e6, density: float = 1.0,
                   precompression: float = 1.0e-3, rotation: bool = True, seed: int = 1,
                   law_options: dict | None = None, bonds=None,
                   perturbation: float = 1.0e-7):
    """A pre-compressed periodic specimen with a small random perturbation;
    ``law_options`` are keyword arguments of :class:`LinearSpring`: dashpots
    (``restitution``, ``restitution_tangential``, ``damping_normal``,
    ``damping_tangential``), rolling resistance (``rolling_convention``, ...) and the
    friction ``mu`` (default 0.5);
    ``bonds`` (:class:`demstep.contact.bonds.ParallelBonds`) bonds every contact;
    ``perturbation``: the random displacements as a fraction of the overlap (module
    docstring: small enough that the Coulomb cap of the tangential dashpots never binds
    before the growth criterion)."""
    if name == SPECIMEN:
        cfg = FCCConfig()
        x, length, _ = fcc_specimen(cfg)
        x[:, 2] -= cfg.radius - math.sqrt(2.0) * cfg.radius / 2
        box = [length, length, cfg.layers * math.sqrt(2.0) * cfg.radius]
        radius = cfg.radius
    elif name in LATTICE_NAMES:
        lat = lattice(name, 1.0)
        x, box = lat.supercell(SUPERCELL[name])
        box, radius = list(box), lat.radius
    else:
        raise InputError(f"lattice: unknown lattice {name!r}; choose one of {', '.join(STUDY_NAMES)}")
    dim = x.shape[1]
    r = np.full(len(x), radius * (1.0 + precompression))
    p = Particles.from_density(x, r, density)
    rng = np.random.default_rng(seed)
    omega = math.sqrt(k / float(p.m[0]))
    amplitude = perturbation * precompression * radius * omega  # displacement / overlap
    v = rng.normal(0.0, amplitude, (len(x), dim))
    w = rng.normal(0.0, amplitude / radius, len(x) if dim == 2 else (len(x), 3))
    law = LinearSpring(**{"k_n": k, "k_s": k, "mu": 0.5, **(law_options or {})})
    sim = Simulation(p, law, periodic=box, velocities=v, angular_velocities=w if rotation else None,
                     timestep=TimeStep.from_alpha(alpha), rotation=rotation, runaway_factor=0,
                     jump_limit=np.inf, energy=EnergyMonitor(every=10**9))
    if bonds is not None:
        sim.add_bonds(bonds)
    return sim


def is_unstable(name: str, alpha: float, steps: int = 3000, growth: float = 1.0e3,
                rotation: bool = True, law_options: dict | None = None, bonds=None,
                perturbation: float = 1.0e-7) -> bool:
    """The energy criterion of the module docstring."""
    sim = build_specimen(name, alpha, rotation=rotation, law_options=law_options, bonds=bonds,
                         perturbation=perturbation)
    sim.run(steps=1)
    ke0 = sim.ledger.kinetic
    flag = {"unstable": False}

    def check(s):
        if not math.isfinite(s.ledger.kinetic) or s.ledger.kinetic > growth * ke0:
            flag["unstable"] = True

    sim.every(10, check)
    try:
        sim.run(until=lambda s: flag["unstable"], max_steps=steps, check_every=10)
    except SimulationDiverged:
        return True
    return flag["unstable"]


def specimen_estimates(name: str, rotation: bool = True, law_options: dict | None = None) -> dict:
    """alpha of every compared method on the specimen (its current contacts with their
    dashpots and rolling springs: the damped estimates)."""
    sim = build_specimen(name, 0.1, rotation=rotation, law_options=law_options)
    sim.prepare()
    contacts = sim.contact_set()
    report = estimate_time_steps(sim.particles_now(), contacts, rotation=rotation,
                                 methods=COMPARED)
    return {e.method: e.alpha for e in report.estimates}


def stability_threshold(name: str, rtol: float = 2e-3, lo: float = 0.05, hi: float = 2.0,
                        steps: int = 3000, rotation: bool = True,
                        law_options: dict | None = None,
                        perturbation: float = 1.0e-7) -> StabilityResult:
    """Bisection for the smallest unstable alpha, to relative tolerance ``rtol``."""
    estimates = specimen_estimates(name, rotation, law_options)
    kw = dict(rotation=rotation, law_options=law_options, perturbation=perturbation)
    if is_unstable(name, lo, steps, **kw) or not is_unstable(name, hi, steps, **kw):
        raise RuntimeError(f"{name}: the bracket [{lo}, {hi}] does not contain the threshold")
    trials = 2
    while hi / lo - 1.0 > rtol:
        mid = 0.5 * (lo + hi)
        trials += 1
        if is_unstable(name, mid, steps, **kw):
            hi = mid
        else:
            lo = mid
    return StabilityResult(name, hi, estimates, (lo, hi), trials)


def engine_threshold(name: str, law_options: dict | None = None, bonds=None,
                     rotation: bool = True, rtol: float = 2e-3, steps: int = 3000,
                     perturbation: float = 1.0e-7) -> dict:
    """The engine's measured threshold and the exact critical step of the specimen with
    the given law options (rolling resistance, dashpots) and bonds, both as alpha =
    dt / sqrt(m / K) with the engine's K (:meth:`Simulation.stiffness_max`), plus the
    exact step of the contact law's normal and tangential springs alone (what a rule
    that ignores rolling springs and bonds would certify)."""
    sim = build_specimen(name, 0.1, rotation=rotation, law_options=law_options, bonds=bonds)
    sim.prepare()
    scale = math.sqrt(sim.m_min / sim.stiffness_max())
    exact = sim.critical_dt("exact", rotation=rotation) / scale
    springs_only = build_specimen(name, 0.1, rotation=rotation)
    springs_only.prepare()
    exact_springs = springs_only.critical_dt("exact", rotation=rotation) / scale
    kw = dict(rotation=rotation, law_options=law_options, bonds=bonds, steps=steps,
              perturbation=perturbation)
    lo, hi = 0.5 * exact, 1.5 * exact
    if is_unstable(name, lo, **kw) or not is_unstable(name, hi, **kw):
        raise RuntimeError(f"{name}: the bracket [{lo:.4g}, {hi:.4g}] does not contain the threshold")
    while hi / lo - 1.0 > rtol:
        mid = 0.5 * (lo + hi)
        if is_unstable(name, mid, **kw):
            hi = mid
        else:
            lo = mid
    return {"measured": hi, "bracket": (lo, hi), "exact": exact, "exact_springs_only": exact_springs}


# ------------------------------------------------------------- damping study
#: restitution coefficients of the damping study (normal and tangential dashpots)
DAMPING_RESTITUTIONS = (1.0, 0.9, 0.5, 0.2)
#: steps of a trial run of the damping study: near a damped threshold the critical mode
#: grows slowly from a tiny share of the start (module docstring)
DAMPING_STEPS = 10000
#: Poisson's ratio of the material equivalent to the specimen's linear springs
EQUIVALENT_POISSON = 0.25


def equivalent_rayleigh_alpha(precompression: float = 1.0e-3,
                              poisson: float = EQUIVALENT_POISSON) -> float:
    """alpha = T_R / sqrt(m/K) of the Rayleigh time of the material whose Hertz tangent
    stiffness at the specimen's overlap equals its linear K (the rule of thumb a
    Hertz-model user would apply): K = 2 E* sqrt(R* delta) with delta = 2 p r and
    R* = r (1 + p) / 2 for a relative pre-compression p, E = 2 (1 - nu^2) E*.
    Dimensionless: independent of K, r and the density."""
    r, k, rho = 1.0, 1.0, 1.0
    rad = r * (1.0 + precompression)
    e_star = k / (2.0 * math.sqrt(0.5 * rad * 2.0 * precompression * r))
    youngs = 2.0 * (1.0 - poisson**2) * e_star
    mass = rho * 4.0 / 3.0 * math.pi * rad**3
    return rayleigh_time([rad], [rho], [youngs], [poisson]) / math.sqrt(mass / k)


def damping_study(restitution: float, rtol: float = 2e-3, steps: int = DAMPING_STEPS,
                  name: str = SPECIMEN, perturbation: float = 1.0e-7) -> dict:
    """The measured threshold and the (damped) estimates of the specimen with normal and
    tangential dashpots of restitution ``restitution`` (1: none), demstep convention."""
    dashpots = None if restitution >= 1.0 else dict(restitution=restitution,
                                                    restitution_tangential=restitution)
    result = stability_threshold(name, rtol=rtol, lo=0.02, hi=1.0, steps=steps,
                                 law_options=dashpots, perturbation=perturbation)
    sim = build_specimen(name, 0.1, law_options=dashpots)
    sim.prepare()
    report = estimate_time_steps(sim.particles_now(), sim.contact_set(), rotation=True,
                                 methods=("exact", "exact-undamped", "element-coupled",
                                          "nodal", "itasca", "guidance"))
    alphas = {e.method: e.alpha for e in report.estimates}
    alphas.setdefault("exact-undamped", alphas["exact"])
    return {"restitution": restitution, "alpha_empirical": result.alpha_empirical,
            "bracket": list(result.bracket), "estimates": alphas,
            "rayleigh_20": 0.2 * equivalent_rayleigh_alpha(), "steps": steps,
            "perturbation": perturbation}
