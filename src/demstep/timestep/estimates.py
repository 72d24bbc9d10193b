"""All critical-step estimates of one assembly, side by side (the `demstep dt` table).

With damping (contact dashpots in the :class:`ContactSet`, or :class:`GlobalDamping`),
every estimate is the damped one: ``exact`` is the exact damped step
(:mod:`demstep.timestep.exact`) and ``exact-undamped`` is listed beside it;
``element-coupled`` is the rigorous damped element bound; the rules of thumb
(``element-paper``, ``nodal``, ``itasca``, ``guidance``) are damped the same way: each
implies a frequency omega^2 = k per unit mass from its springs, and its dashpots a
damping c per unit mass (``element-paper``: the element's c_n, c_t in place of k_n, k_s;
``nodal``: the summed dashpots of the DOF; ``itasca`` and ``guidance``: stiffness-
proportional damping beta omega^2 with beta the largest dashpot-to-spring ratio c/k of
the contacts), and the step is eq. 28's :func:`~demstep.timestep.stability.damped_dt`
(k, c); ``guidance`` keeps the paper's safety factor 0.75 outside. The material time scales
of :mod:`demstep.timestep.rules` (``rayleigh-*``, ``hertz-time``) are never damped:
they are what the codes that use them check.

Rolling and twisting resistance (the contacts' ``k_r``, ``k_w``, ``c_r``, ``c_w``; with
rotation only) enters ``exact``, ``exact-undamped``, ``exact-periodic``,
``element-coupled`` (the rotational element on the relative rotation) and ``nodal``
(the summed rotational stiffness of a DOF). ``element-paper`` stays the paper's
element (translation and tangential arms: it ignores them), and ``itasca`` and
``guidance`` are rules in K_max = max(k_n, k_t) and m_min that have no rotational
spring; the ``conservative`` column compares each with the exact step that includes
them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from demstep.timestep.contacts import ContactSet, find_contacts
from demstep.errors import InputError
from demstep.kernels.timestep_kernels import damping_diagonal_kernel
from demstep.packings import lattice
from demstep.particles import INERTIA_FACTOR, Particles
from demstep.timestep.assembly import inverse_sqrt_mass, lumped_mass, stiffness_diagonal
from demstep.timestep.bloch import bloch_lambda_max
from demstep.timestep.clumps import body_element_dt, body_stiffness_diagonal, owner_mass_diagonal
from demstep.timestep.damping import GlobalDamping
from demstep.timestep.eigen import DENSE_LIMIT, EIGSH_TOL, check_certified_tol
from demstep.timestep.elements import (coupled_element_damped_dt, dofs_per_particle,
                                       paper_element_lambda)
from demstep.timestep.exact import exact_critical_step
from demstep.timestep.guarantee import FAILURE, Guarantee
from demstep.timestep.mass_split import element_mass
from demstep.timestep.rules import RAYLEIGH_FRACTIONS, hertz_time, rayleigh_time
from demstep.timestep.stability import GUIDANCE_ALPHA, alpha_of, damped_dt, dt_from_lambda

METHODS = ("certified", "exact", "exact-undamped", "exact-periodic", "element-coupled", "element-paper",
           "nodal", "itasca", "guidance")
#: material rules (Hertz contacts, given E and nu)
RULES = ("rayleigh-time",) + tuple(f"rayleigh-{round(100 * f)}%" for f in RAYLEIGH_FRACTIONS) \
    + ("hertz-time",)

#: why a method asked for is not shown (:func:`estimate_time_steps`)
NOT_APPLICABLE = {
    "exact-undamped": "no damping: exact is the undamped step",
    "exact-periodic": "needs a lattice input (--lattice)",
    "element-paper": "not defined for clumps",
    "hertz-time": "needs Hertz materials and an impact velocity",
    **{rule: "needs Hertz materials (--youngs/--poisson or --materials)"
       for rule in RULES if rule != "hertz-time"},
}

def _why_not(method: str) -> str:
    return NOT_APPLICABLE.get(method, "not computed for this input")


#: relative slack when calling an estimate conservative (dt_method <= dt_exact)
CONSERVATIVE_RTOL = 1e-9


@dataclass
class Estimate:
    """One method's critical step ``dt`` [T] and ``alpha`` = dt / sqrt(m_min/K_max);
    ``conservative`` says whether dt <= the exact (damped) step (None when there is
    none); ``kind`` is 'estimate' or 'rule' (a material time scale); ``note`` says how
    it was computed where that is not obvious; ``guarantee``
    (:class:`~demstep.timestep.guarantee.Guarantee`) what the step guarantees."""

    method: str
    dt: float
    alpha: float
    conservative: bool | None = None
    kind: str = "estimate"
    note: str = ""
    guarantee: Guarantee | None = None


@dataclass
class Materials:
    """Per-particle material data for the rules of :mod:`demstep.timestep.rules`: Young's
    modulus [M/(L T^2)], Poisson's ratio, density [M/L^3], the effective modulus E* of a
    contact of the particle with its own material, and the impact velocity [L/T] of the
    Hertz time (None: not reported)."""

    youngs: np.ndarray
    poisson: np.ndarray
    density: np.ndarray
    e_star: np.ndarray
    impact_velocity: float | None = None


@dataclass
class TimeStepReport:
    dim: int
    n_particles: int
    n_contacts: int
    m_min: float
    k_max: float
    rotation: bool
    mass_split: str
    damping: GlobalDamping
    dashpots: bool
    estimates: list[Estimate] = field(default_factory=list)
    exact: object = None  # the ExactStep when 'exact' was computed
    notes: list[str] = field(default_factory=list)

    @property
    def damped(self) -> bool:
        return self.dashpots or self.damping.active

    @property
    def rayleigh(self):
        """(a1, a2) of global Rayleigh damping, or None."""
        return (self.damping.mass, self.damping.stiffness) if self.damping.active else None

    def get(self, method: str) -> Estimate:
        for e in self.estimates:
            if e.method == method:
                return e
        raise KeyError(method)

    def to_json(self) -> dict:
        """The documented JSON shape of ``demstep dt --json``."""
        return {"dim": self.dim, "n_particles": self.n_particles, "n_contacts": self.n_contacts,
                "m_min": self.m_min, "k_max": self.k_max, "rotation": self.rotation,
                "damped": self.damped,
                "damping": {"dashpots": self.dashpots, "mass": self.damping.mass,
                            "stiffness": self.damping.stiffness},
                "estimates": [{"method": e.method, "dt": e.dt, "alpha": e.alpha,
                               "conservative": e.conservative, "kind": e.kind,
                               "guarantee": (e.guarantee.to_json()
                                             if e.guarantee is not None else None)}
                              for e in self.estimates],
                "notes": self.notes}


def _damping(damping) -> GlobalDamping:
    if damping is None:
        return GlobalDamping()
    if isinstance(damping, GlobalDamping):
        return damping
    a1, a2 = damping
    return GlobalDamping.rayleigh(a1, a2)


def element_paper_dt(particles, contacts, rotation, mass_split="uniform", damping=None) -> float:
    """min over contacts of the paper's element steps [T] (eqs. 6-21); damped per axis
    as described in the module docstring. The paper's elements have no rolling or
    twisting springs: the contacts' ``k_r``, ``k_w`` (and ``c_r``, ``c_w``) are
    ignored, so with rolling resistance this is no bound of any kind."""
    d = _damping(damping)
    mass = element_mass(particles, contacts, mass_split)
    if not (contacts.damped or d.active):
        return float(dt_from_lambda(paper_element_lambda(contacts, mass, rotation).max()))
    c_m = mass.inv_m_i + mass.inv_m_j
    dts = [damped_dt(contacts.k_n * c_m, d.mass + (d.stiffness * contacts.k_n + contacts.c_n) * c_m),
           damped_dt(contacts.k_s * c_m, d.mass + (d.stiffness * contacts.k_s + contacts.c_t) * c_m)]
    if rotation:
        factor = 1.0 if contacts.dim == 2 else 1.0 - (contacts.normal**2).min(axis=1)
        w = factor * (contacts.arm_i**2 * mass.inv_I_i + contacts.arm_j**2 * mass.inv_I_j)
        dts.append(damped_dt(contacts.k_s * w, d.mass + (d.stiffness * contacts.k_s + contacts.c_t) * w))
    return float(np.min([x.min() for x in dts]))


def element_coupled_dt(particles, contacts, rotation, mass_split="uniform", damping=None,
                       bodies=None) -> float:
    """min over contacts of the coupled elements' steps [T]: a rigorous lower bound on the
    exact (damped) step for any partition of the masses
    (:func:`~demstep.timestep.elements.coupled_element_damped_dt`; with ``bodies``, the
    elements of :func:`~demstep.timestep.clumps.body_element_dt`)."""
    d = _damping(damping)
    if bodies is not None and bodies.n:
        dt = body_element_dt(particles, contacts, bodies, rotation, d.mass, d.stiffness).min()
    else:
        dt = coupled_element_damped_dt(contacts, element_mass(particles, contacts, mass_split),
                                       rotation, d.mass, d.stiffness).min()
    if d.mass > 0:
        dt = min(dt, 2.0 / d.mass)  # DOFs outside every element's coupling
    return float(dt)


def exact_dt(particles, contacts, rotation, damping=None, bodies=None) -> float:
    """The exact critical step [T] (damped when the contacts have dashpots or ``damping``
    is given; :func:`demstep.timestep.exact.exact_critical_step`): from the top root the
    solver found, with no proof that it is the largest (:func:`certified_dt` has one)."""
    return exact_critical_step(particles, contacts, rotation, _damping(damping),
                               bodies=bodies).dt


def certified_dt(particles, contacts, rotation, damping=None, bodies=None,
                 failure: float = FAILURE, seed: int | None = None) -> float:
    """The certified critical step [T]: the exact step with its guarantee (a proof on
    small systems, else probability >= 1 - ``failure`` over a random start drawn from
    ``seed``; :func:`demstep.timestep.exact.certify_step`)."""
    return exact_critical_step(particles, contacts, rotation, _damping(damping),
                               bodies=bodies, guarantee=True, failure=failure,
                               seed=seed).dt_certified


def nodal_dt(particles, contacts, rotation, damping=None, bodies=None) -> float:
    """YADE GlobalStiffnessTimeStepper's rule without safety factor [T]:
    sqrt(2) * sqrt(min over free DOFs of M_dd / K_dd), K_dd the summed contact
    stiffness of the DOF (translation and, with rotation, rotation: tangential springs
    at their arms plus the rolling and twisting springs, as YADE adds its rotational
    stiffness of cohesive contacts). Damped: :func:`damped_dt` (2 K_dd/M_dd,
    a1 + 2 (a2 K_dd + C_dd)/M_dd) per DOF."""
    d = _damping(damping)
    if bodies is not None and bodies.n:  # YADE's rule for clumps: members summed to the body

        kdiag = body_stiffness_diagonal(particles, contacts, bodies, rotation)
        cdiag = body_stiffness_diagonal(particles, contacts, bodies, rotation, "c")
        mdiag, free_owner = owner_mass_diagonal(particles, bodies, rotation)
        ok = free_owner[:, None] & (kdiag > 0)
        k = 2.0 * kdiag[ok] / mdiag[ok]
        c = d.mass + 2.0 * (d.stiffness * kdiag[ok] + cdiag[ok]) / mdiag[ok]
        return float(damped_dt(k, c).min())
    diag = stiffness_diagonal(particles, contacts, rotation)
    free = (inverse_sqrt_mass(particles, rotation) > 0) & (diag > 0)
    mass = lumped_mass(particles, rotation)[free]
    k = 2.0 * diag[free] / mass
    c = np.full_like(k, d.mass) + 2.0 * d.stiffness * diag[free] / mass
    if contacts.damped:
        nd = dofs_per_particle(particles.dim, rotation)
        cdiag = damping_diagonal_kernel(contacts, particles.n, nd, rotation).reshape(-1)
        c += 2.0 * cdiag[free] / mass
    return float(damped_dt(k, c).min())


def dashpot_ratio(contacts: ContactSet) -> float:
    """beta = max over contacts of c/k [T] (normal and tangential): the stiffness-
    proportional damping that bounds the dashpots (C <= beta K when c/k <= beta). The
    rolling and twisting viscous parts are left out: the rules that use beta
    (``itasca``, ``guidance``) have a translational frequency and no rotational spring."""
    ratios = [0.0]
    for c, k in ((contacts.c_n, contacts.k_n), (contacts.c_t, contacts.k_s)):
        on = k > 0
        if on.any():
            ratios.append(float((c[on] / k[on]).max()))
    return max(ratios)


def _rule_dt(alpha: float, m_min: float, k_max: float, beta: float, d: GlobalDamping,
             safety: float = 1.0) -> float:
    """``safety`` x the damped step of a rule alpha sqrt(m_min/K_max): eq. 28 at the rule's
    frequency omega = 2 / (alpha sqrt(m_min/K_max)) with the damping a1 + (a2 + beta)
    omega^2 of stiffness-proportional dashpots (:func:`dashpot_ratio`)."""
    omega2 = 4.0 * k_max / (alpha * alpha * m_min)
    return safety * float(damped_dt(omega2, d.mass + (d.stiffness + beta) * omega2))


def itasca_dt(m_min: float, k_max: float, beta: float = 0.0, damping=None) -> float:
    """sqrt(m_min / K_max) (Itasca 1998, quoted in the paper) [T]; damped as the module
    docstring says (``beta``: :func:`dashpot_ratio`)."""
    return _rule_dt(1.0, m_min, k_max, beta, _damping(damping))


#: the paper's safety factor in its guidance (0.17 = 0.75 x 0.221 in 3D)
GUIDANCE_SAFETY = 0.75


def guidance_dt(m_min: float, k_max: float, dim: int, beta: float = 0.0, damping=None) -> float:
    """The paper's recommendation 0.3 (2D) / 0.17 (3D) sqrt(m_min/K_max) [T]; damped:
    0.75 x the damped step of the critical estimate it derives from (0.4 / 0.227)."""
    return _rule_dt(GUIDANCE_ALPHA[dim] / GUIDANCE_SAFETY, m_min, k_max, beta,
                    _damping(damping), GUIDANCE_SAFETY)


_DENSEST = {2: "hex", 3: "fcc"}


def densest_packing_dt(dim: int, mass: float, k_n: float, k_t: float, c_n: float = 0.0,
                       c_t: float = 0.0, mass_damping: float = 0.0,
                       rotation: bool = True, k_r: float = 0.0, k_w: float = 0.0,
                       c_r: float = 0.0, c_w: float = 0.0, radius: float = 1.0) -> float:
    """The coupled element bound [T] of the densest packing of equal particles of
    ``mass`` (hexagonal disks, FCC spheres; uniform split) whose contacts have springs
    k_n, k_t [M/T^2], dashpots c_n, c_t [M/T] and global damping a1 = ``mass_damping``:
    the step to use before any contact has formed. With rolling resistance: rolling and
    twisting springs k_r, k_w [M L^2/T^2 per rad], viscous parts c_r, c_w [M L^2/T],
    for particles of ``radius`` [L] (their moment of inertia; without rolling springs
    the bound does not depend on it)."""
    lat = lattice(_DENSEST[dim], 1.0)
    x, box = lat.supercell(3)
    n = len(x)
    # lengths in units of the radius: arms 1, inertia factor m r^2 (the rolling springs
    # [M L^2/T^2] scaled by 1/r^2 to match)
    scale = 1.0 / (float(radius) ** 2)
    p = Particles(x, np.ones(n), np.full(n, mass), np.full(n, INERTIA_FACTOR[dim] * mass))
    c = find_contacts(p, k_n, k_t, periodic=box)
    c.c_n[:] = c_n
    c.c_t[:] = c_t
    if k_r or k_w or c_r or c_w:
        c.k_r[:] = k_r * scale
        c.k_w[:] = k_w * scale
        c.c_r[:] = c_r * scale
        c.c_w[:] = c_w * scale
    return element_coupled_dt(p, c, rotation, damping=GlobalDamping(mass_damping))


def densest_packing_alpha(dim: int, rotation: bool = True) -> float:
    """alpha of :func:`densest_packing_dt` without damping (1/3 in 2D and 2/sqrt(84),
    about 0.218, in 3D with rotation)."""
    return densest_packing_dt(dim, 1.0, 1.0, 1.0, rotation=rotation)


def estimate_time_steps(particles: Particles, contacts: ContactSet, rotation: bool = True,
                        mass_split: str = "uniform", damping=None, methods=None,
                        lattice=None, density: float | None = None,
                        materials: Materials | None = None, rayleigh=None,
                        v0: np.ndarray | None = None, bodies=None,
                        exact_tol: float | None = None, failure: float = FAILURE,
                        seed: int | None = None, low_memory: bool = False) -> TimeStepReport:
    """Every estimate for ``particles`` with ``contacts`` (their stiffnesses and dashpots).

    ``damping``: :class:`GlobalDamping` (or ``rayleigh`` = (a1, a2), the same thing).
    ``lattice`` (a :class:`demstep.packings.Lattice`) with ``density`` adds
    ``exact-periodic`` (uniform coefficients taken from the contacts). ``materials``
    adds the material rules. ``element-coupled`` always uses the uniform split, whose
    partition makes it a rigorous bound; ``element-paper`` uses ``mass_split``.
    ``v0`` is a start the exact damped iteration tries (not its certifying solves);
    ``exact_tol`` is the solver's relative residual, at most
    :data:`~demstep.timestep.eigen.MAX_CERTIFIED_TOL` (None:
    :data:`~demstep.timestep.eigen.EIGSH_TOL`, 1e-10; the step comes from an upper bound
    on the largest root found (see :mod:`demstep.timestep.eigen`), and lies at most about
    4 ``exact_tol`` below the critical one). With damping and without 'exact-undamped'
    in ``methods``, the undamped problem is solved only to start the damped iteration,
    to max(:data:`~demstep.timestep.exact.FIRST_TOL`, ``exact_tol``): ``report.exact``'s
    ``dt_undamped`` and ``lambda_undamped`` are then that loose solve's (still from an
    upper bound; its tolerance in ``report.exact.undamped_tol``, and a note says so).
    ``bodies``
    (:class:`~demstep.timestep.clumps.RigidBodies`): clumps (``element-paper`` and
    ``exact-periodic`` are not defined for them; m_min is the lightest free sphere or
    body). ``certified`` is the exact step with a guarantee
    (:func:`demstep.timestep.exact.certify_step`): a proof on small systems, else
    probability >= 1 - ``failure`` over a random start drawn from ``seed`` (None: fresh
    entropy, recorded). Every estimate names its guarantee (:func:`guarantee_of`).
    ``low_memory``: ``certified`` from the random-start checks alone, without the exact
    solver's Lanczos basis (:func:`demstep.timestep.exact.certified_without_basis`:
    three vectors instead of ~40); ``exact`` and ``exact-undamped`` are then not
    computed (a note says so) and there is no critical mode.
    """
    if contacts.n == 0:
        raise InputError("contacts: the assembly has no contacts (check radii, positions "
                         "and --contact-tol)")
    if particles.fixed.all():
        raise InputError("particles: every particle is fixed")
    if damping is not None and rayleigh is not None:
        raise InputError("damping: give either damping or rayleigh, not both")
    d = _damping(damping if damping is not None else rayleigh)
    damped = contacts.damped or d.active
    requested = None if methods is None else list(dict.fromkeys(methods))  # (each once)
    methods = list(METHODS if requested is None else requested)
    for m in methods:
        if m not in METHODS + RULES:
            raise InputError(f"method: unknown method {m!r}; choose from "
                             f"{', '.join(METHODS + RULES)}")
    report = TimeStepReport(particles.dim, particles.n, contacts.n, 0.0, 0.0, rotation,
                            mass_split, d, contacts.damped)
    if "exact-periodic" in methods and lattice is None:
        methods.remove("exact-periodic")
    if "exact-undamped" in methods and not damped:
        methods.remove("exact-undamped")
    if "exact-undamped" in methods and "exact" not in methods:
        # its solve gives the damped step too: shown, it is what 'conservative' is against
        methods.insert(methods.index("exact-undamped"), "exact")
        report.notes.append("exact: added (the damped step, the reference of "
                            "'conservative'; computed with exact-undamped)")
    has_bodies = bodies is not None and bodies.n > 0
    if has_bodies:
        for name in ("element-paper", "exact-periodic"):
            if name in methods:
                methods.remove(name)
                report.notes.append(f"{name}: not defined for clumps")
        free = (bodies.sphere_body < 0) & ~particles.fixed
        m_min = float(np.concatenate([particles.m[free], bodies.mass[~bodies.fixed]]).min())
    else:
        m_min = float(particles.m[~particles.fixed].min())
    k_max = contacts.k_max()
    if not k_max > 0:
        raise InputError("contacts: every normal stiffness is 0 (Hertz contacts take theirs "
                         "from the overlap, and these touch without one: give an overlap, "
                         "demstep dt --overlap)")
    beta = dashpot_ratio(contacts)
    if contacts.has_rolling and rotation:
        report.notes.append("rolling and twisting resistance: in exact, element-coupled and "
                            "nodal; element-paper is the paper's element without it")
    elif contacts.has_rolling:
        report.notes.append("rolling and twisting resistance: no part of the analysis, "
                            "rotation is locked")
    report.m_min, report.k_max = m_min, k_max
    dim = particles.dim
    exact = None
    if low_memory:
        for name in ("exact", "exact-undamped"):
            if name in methods:
                methods.remove(name)
                report.notes.append(f"{name}: not computed with low memory (the solver's "
                                    "basis); 'certified' comes from the random-start checks")
        if "certified" in methods:
            from demstep.timestep.exact import certified_without_basis

            exact = certified_without_basis(particles, contacts, rotation, d, bodies=bodies,
                                            failure=failure, seed=seed)
            report.exact = exact
    elif "exact" in methods or "exact-undamped" in methods or "certified" in methods:
        from demstep.timestep.exact import FIRST_TOL

        options = {} if exact_tol is None else {"tol": check_certified_tol("exact_tol",
                                                                           exact_tol)}
        if "exact-undamped" not in methods:
            # the undamped solve only starts the damped iteration (FIRST_TOL)
            options["undamped_tol"] = max(FIRST_TOL, options.get("tol", 0.0))
        exact = exact_critical_step(particles, contacts, rotation, d, v0=v0, bodies=bodies,
                                    guarantee="certified" in methods, failure=failure,
                                    seed=seed, **options)
        report.exact = exact
        if exact_tol is not None:
            report.notes.append(f"exact: solved to a relative residual of {exact_tol:g} (the "
                                "step certified, at most about 4x that below the critical one)")
        if exact.damped and exact.undamped_tol > options.get("tol", EIGSH_TOL):
            report.notes.append(f"exact: the undamped problem solved only to a relative "
                                f"residual of {exact.undamped_tol:g}, to start the damped "
                                "iteration (list exact-undamped for its step)")
    compute = {
        "certified": lambda: exact.dt_certified,
        "exact": lambda: exact.dt,
        "exact-undamped": lambda: exact.dt_undamped,
        "exact-periodic": lambda: _periodic_dt(lattice, contacts, density, rotation, d),
        "element-coupled": lambda: element_coupled_dt(particles, contacts, rotation, damping=d,
                                                      bodies=bodies),
        "element-paper": lambda: element_paper_dt(particles, contacts, rotation, mass_split, d),
        "nodal": lambda: nodal_dt(particles, contacts, rotation, d, bodies),
        "itasca": lambda: itasca_dt(m_min, k_max, beta, d),
        "guidance": lambda: guidance_dt(m_min, k_max, dim, beta, d),
    }
    for m in methods:
        if m in compute:
            dt = float(compute[m]())
            report.estimates.append(Estimate(m, dt, float(alpha_of(dt, m_min, k_max)),
                                             guarantee=guarantee_of(m, exact, rotation,
                                                                    mass_split)))
    if materials is not None:
        for name, dt in material_rules(particles, materials).items():
            if name in methods or set(methods) & set(RULES) == set():
                report.estimates.append(Estimate(name, dt, float(alpha_of(dt, m_min, k_max)),
                                                 kind="rule",
                                                 guarantee=guarantee_of(name, exact, rotation,
                                                                        mass_split)))
    if exact is not None:
        ref = exact.dt  # (with low memory: the certified step, there is no other)
        for e in report.estimates:
            e.conservative = bool(e.dt <= ref * (1.0 + CONSERVATIVE_RTOL))
    if requested is not None:
        shown = {e.method for e in report.estimates}
        for m in requested:
            if m not in shown and not any(n.startswith(f"{m}:") for n in report.notes):
                report.notes.append(f"{m}: does not apply here ({_why_not(m)})")
        if not report.estimates:
            raise InputError(f"methods: none of {', '.join(requested)} applies to this input "
                             f"({'; '.join(f'{m}: {_why_not(m)}' for m in requested)})")
    return report


def material_rules(particles: Particles, materials: Materials) -> dict:
    """The Rayleigh time, its usual fractions and the Hertz time [T] (when the impact
    velocity is known) of :mod:`demstep.timestep.rules`."""
    free = ~particles.fixed
    t_r = rayleigh_time(particles.r[free], materials.density[free], materials.youngs[free],
                        materials.poisson[free])
    out = {"rayleigh-time": t_r}
    for f in RAYLEIGH_FRACTIONS:
        out[f"rayleigh-{round(100 * f)}%"] = f * t_r
    if materials.impact_velocity is not None and materials.impact_velocity > 0:
        out["hertz-time"] = hertz_time(particles.m[free], particles.r[free],
                                       materials.e_star[free], materials.impact_velocity)
    return out


def guarantee_of(method: str, exact, rotation: bool, mass_split: str) -> Guarantee:
    """What ``method``'s step guarantees (``exact``: the ExactStep, when computed)."""
    from demstep.timestep.exact import ESTIMATE

    if method == "certified":
        return exact.guarantee
    if method == "exact-undamped" and exact.damped:
        return Guarantee("estimate", "the undamped step: above the damped critical one")
    if method in ("exact", "exact-undamped"):
        if exact.operator.size <= DENSE_LIMIT:
            return Guarantee("estimate", "dense eigensolver, to rounding ('certified' adds "
                             "the rounding bound)")
        return ESTIMATE
    if method == "exact-periodic":
        return Guarantee("estimate", "Bloch analysis of the infinite lattice, maximised "
                         "over a refined grid of wave vectors (no proof of the maximum)")
    if method == "element-coupled":
        return Guarantee("lower-bound", "Rayleigh's theorem on the coupled contact elements")
    if method == "element-paper":
        if not rotation and mass_split == "uniform":
            return Guarantee("lower-bound", "the paper's elements, translations only")
        return Guarantee("rule", "the paper's elements: no bound once rotation couples "
                         "or with a zoned mass split")
    if method == "nodal":
        return Guarantee("rule", "nodal stiffness rule (YADE's GlobalStiffnessTimeStepper)")
    return Guarantee("rule", "a fraction of a time scale of the contact or the material")


def _periodic_dt(lattice, contacts, density, rotation, damping: GlobalDamping):
    if density is None:
        raise InputError("density: needed for the exact-periodic estimate")
    lam, _ = bloch_lambda_max(lattice, float(contacts.k_n.max()), float(contacts.k_s.max()),
                              density, rotation, c_n=float(contacts.c_n.max()),
                              c_t=float(contacts.c_t.max()), damping=damping,
                              k_r=float(contacts.k_r.max()), k_w=float(contacts.k_w.max()),
                              c_r=float(contacts.c_r.max()), c_w=float(contacts.c_w.max()))
    return float(dt_from_lambda(lam))
