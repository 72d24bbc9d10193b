"""All critical-step estimates of one assembly, side by side (the `demstep dt` table)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from demstep.contacts import ContactSet
from demstep.errors import InputError
from demstep.particles import Particles
from demstep.timestep.assembly import inverse_sqrt_mass, lumped_mass, scaled_stiffness, stiffness_diagonal
from demstep.timestep.eigen import lambda_max
from demstep.timestep.elements import coupled_element_lambda, paper_element_lambda
from demstep.timestep.mass_split import element_mass
from demstep.timestep.stability import GUIDANCE_ALPHA, alpha_of, dt_from_lambda, rayleigh_damped_dt

METHODS = ("exact", "exact-periodic", "element-coupled", "element-paper", "nodal",
           "itasca", "guidance")

#: relative slack when calling an estimate conservative (dt_method <= dt_exact)
CONSERVATIVE_RTOL = 1e-9


@dataclass
class Estimate:
    """One method's critical step ``dt`` [T] and ``alpha`` = dt / sqrt(m_min/K_max);
    ``conservative`` says whether dt <= the exact step (None when there is none)."""

    method: str
    dt: float
    alpha: float
    conservative: bool | None = None


@dataclass
class TimeStepReport:
    dim: int
    n_particles: int
    n_contacts: int
    m_min: float
    k_max: float
    rotation: bool
    mass_split: str
    rayleigh: tuple[float, float] | None
    estimates: list[Estimate] = field(default_factory=list)

    def get(self, method: str) -> Estimate:
        for e in self.estimates:
            if e.method == method:
                return e
        raise KeyError(method)

    def to_json(self) -> dict:
        """The documented JSON shape of ``demstep dt --json``."""
        return {"dim": self.dim, "n_particles": self.n_particles, "n_contacts": self.n_contacts,
                "m_min": self.m_min, "k_max": self.k_max,
                "estimates": [{"method": e.method, "dt": e.dt, "alpha": e.alpha}
                              for e in self.estimates]}


def element_paper_dt(particles, contacts, rotation, mass_split="uniform") -> float:
    """min over contacts of 2/sqrt(lambda_e) for the paper's elements [T]."""
    lam = paper_element_lambda(contacts, element_mass(particles, contacts, mass_split), rotation)
    return float(dt_from_lambda(lam.max()))


def element_coupled_dt(particles, contacts, rotation, mass_split="uniform") -> float:
    """min over contacts of 2/sqrt(lambda_e) for the coupled elements [T] (a rigorous
    lower bound on the exact step for any partition of the masses)."""
    lam = coupled_element_lambda(contacts, element_mass(particles, contacts, mass_split), rotation)
    return float(dt_from_lambda(lam.max()))


def exact_dt(particles, contacts, rotation) -> float:
    """2/sqrt(lambda_max(M^-1/2 K M^-1/2)) for the assembly's sparse K [T]."""
    return float(dt_from_lambda(lambda_max(scaled_stiffness(particles, contacts, rotation))))


def nodal_dt(particles, contacts, rotation) -> float:
    """YADE GlobalStiffnessTimeStepper's rule without safety factor [T]:
    sqrt(2) * sqrt(min over free DOFs of M_dd / K_dd), K_dd the summed contact
    stiffness of the DOF (translation and, with rotation, rotation)."""
    diag = stiffness_diagonal(particles, contacts, rotation)
    free = (inverse_sqrt_mass(particles, rotation) > 0) & (diag > 0)
    ratio = lumped_mass(particles, rotation)[free] / diag[free]
    return float(np.sqrt(2.0) * np.sqrt(ratio.min()))


def itasca_dt(m_min: float, k_max: float) -> float:
    """sqrt(m_min / K_max) (Itasca 1998, quoted in the paper) [T]."""
    return float(np.sqrt(m_min / k_max))


def guidance_dt(m_min: float, k_max: float, dim: int) -> float:
    """The paper's recommendation 0.3 (2D) / 0.17 (3D) sqrt(m_min/K_max) [T]."""
    return GUIDANCE_ALPHA[dim] * itasca_dt(m_min, k_max)


_DENSEST = {2: "hex", 3: "fcc"}


def densest_packing_alpha(dim: int, rotation: bool = True) -> float:
    """alpha of the coupled element bound for the densest packing of equal particles
    (hexagonal disks, FCC spheres; uniform split): the step to use before any contact
    has formed (1/3 in 2D and about 0.218 in 3D with rotation)."""
    from demstep.contacts import find_contacts
    from demstep.packings import lattice

    lat = lattice(_DENSEST[dim], 1.0)
    x, box = lat.supercell(3)
    p = Particles.from_density(x, np.ones(len(x)), 1.0)
    c = find_contacts(p, 1.0, periodic=box)
    return element_coupled_dt(p, c, rotation) / np.sqrt(p.m[0])


def estimate_time_steps(particles: Particles, contacts: ContactSet, rotation: bool = True,
                        mass_split: str = "uniform", rayleigh=None, methods=None,
                        lattice=None, density: float | None = None) -> TimeStepReport:
    """Every estimate for ``particles`` with ``contacts``.

    ``lattice`` (a :class:`demstep.packings.Lattice`) with ``density`` adds
    ``exact-periodic`` (uniform k_n, k_s taken from the contacts). ``rayleigh`` =
    (a1, a2) applies the damping reduction of eq. 28 to every estimate.
    ``element-coupled`` always uses the uniform split, whose partition makes it a
    rigorous bound; ``element-paper`` uses ``mass_split``.
    """
    if contacts.n == 0:
        raise InputError("contacts: the assembly has no contacts (check radii, positions "
                         "and --contact-tol)")
    if particles.fixed.all():
        raise InputError("particles: every particle is fixed")
    methods = list(METHODS if methods is None else methods)
    for m in methods:
        if m not in METHODS:
            raise InputError(f"method: unknown method {m!r}; choose from {', '.join(METHODS)}")
    if "exact-periodic" in methods and lattice is None:
        methods.remove("exact-periodic")
    m_min = float(particles.m[~particles.fixed].min())
    k_max = contacts.k_max()
    dim = particles.dim
    compute = {
        "exact": lambda: exact_dt(particles, contacts, rotation),
        "exact-periodic": lambda: _periodic_dt(lattice, contacts, density, rotation),
        "element-coupled": lambda: element_coupled_dt(particles, contacts, rotation),
        "element-paper": lambda: element_paper_dt(particles, contacts, rotation, mass_split),
        "nodal": lambda: nodal_dt(particles, contacts, rotation),
        "itasca": lambda: itasca_dt(m_min, k_max),
        "guidance": lambda: guidance_dt(m_min, k_max, dim),
    }
    report = TimeStepReport(dim, particles.n, contacts.n, m_min, k_max, rotation, mass_split,
                            None if rayleigh is None else tuple(map(float, rayleigh)))
    for m in methods:
        dt = compute[m]()
        if rayleigh is not None:
            dt = float(rayleigh_damped_dt(dt, *rayleigh))
        report.estimates.append(Estimate(m, dt, float(alpha_of(dt, m_min, k_max))))
    if "exact" in methods:
        ref = report.get("exact").dt
        for e in report.estimates:
            e.conservative = bool(e.dt <= ref * (1.0 + CONSERVATIVE_RTOL))
    return report


def _periodic_dt(lattice, contacts, density, rotation):
    from demstep.timestep.bloch import bloch_lambda_max

    if density is None:
        raise InputError("density: needed for the exact-periodic estimate")
    lam, _ = bloch_lambda_max(lattice, float(contacts.k_n.max()), float(contacts.k_s.max()),
                              density, rotation)
    return float(dt_from_lambda(lam))
