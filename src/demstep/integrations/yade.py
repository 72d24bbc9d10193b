"""The time step of a running YADE scene, certified by demstep.

YADE (https://yade-dem.org) runs its scripts in its own Python; inside it, a
:class:`YadeCertifier` reads the scene as it is (``O.bodies``, ``O.interactions``,
``O.engines``), gives every real interaction the springs and dashpots YADE's law
applies to it, and certifies the critical step of that state: the exact (damped)
critical step (:func:`demstep.timestep.exact.exact_critical_step`), or the coupled
element bound, lower but cheaper. Put it in ``O.engines`` as a ``PyRunner``::

    from demstep.integrations.yade import YadeCertifier
    cert = YadeCertifier(safety=0.8)
    O.engines = O.engines + [cert.engine(iterPeriod=100)]

Every ``iterPeriod`` steps the step is certified, and ``O.dt`` lowered at once when it
is above ``safety`` times the certified one (raised when it is more than a factor
(1 + grow)^2 below it); each change is logged with its reason. It replaces
``GlobalStiffnessTimeStepper`` (GSTS), whose nodal rule is no bound and knows no
dashpots: an active GSTS is refused (it would set ``O.dt`` itself).

What it reads (units are the scene's: YADE is SI by convention, so [L] m, [M] kg,
[T] s):

* bodies: spheres (``Sphere``: radius, ``state.mass``, ``state.inertia``), clumps
  (``Clump``: the body's mass, principal inertia and orientation; its members' arms),
  and fixed ``Wall``, ``Facet`` and ``Box`` bodies (contacts with them are contacts
  with a fixed wall). A body that is not ``dynamic``, or whose ``blockedDOFs`` are all
  of ``xyzXYZ``, is fixed (infinite mass); partly blocked DOFs are taken as free, which
  is conservative (a blocked DOF is an infinite mass: the certified step can only be
  lower than the constrained system's), and noted; when every free body has its
  rotations blocked (``XYZ``), rotation is locked;
* interactions (real ones, with ``ScGeom``/``ScGeom6D`` geometry): ``FrictPhys``
  (``Law2_ScGeom_FrictPhys_CundallStrack``: k_n = ``kn``, k_s = ``ks`` [N/m]),
  ``ViscElPhys`` (``Law2_ScGeom_ViscElPhys_Basic``: ``kn``, ``ks`` [N/m], dashpots
  ``cn``, ``cs`` [N s/m]), ``CohFrictPhys``
  (``Law2_ScGeom6D_CohFrictPhys_CohesionMoment``: ``kn``, ``ks``, and the rolling and
  twisting springs ``kr``, ``ktw`` [N m/rad] where the law applies them); a contact
  whose ``penetrationDepth`` is not positive carries no force (no spring) unless it is
  cohesive;
* the lever arms the law uses (measured on YADE 2023.02a, see ``docs/yade.md``): the
  tangential slip takes the full radius r where the geometry functor avoids ratcheting
  (``Ig2_Sphere_Sphere_ScGeom*`` ``avoidGranularRatcheting``, ``Ig2_Wall_Sphere_ScGeom``
  ``noRatch``), else the distance to the contact point; the torque takes r - delta/2
  (``CundallStrack`` with ``sphericalBodies``, or a periodic cell) or the distance to the
  contact point; ``ViscElPhys`` takes the distance to the contact point for both. When
  the two differ the certificate takes their geometric mean on both sides (as for
  LAMMPS, ``demstep.integrations.lammps_model.pair_arm``: exact for one contact);
* ``NewtonIntegrator.damping``, YADE's non-viscous (Cundall) damping d: it is not a
  dashpot. Each force and torque component is scaled by 1 - d sign(f v), so a force
  that opposes the motion is *amplified* by 1 + d. In the fastest mode (which reverses
  every step) it always opposes it, and the leapfrog scheme with forces (1 + d) K x is
  unstable above 2 / sqrt((1 + d) lambda_max): d lowers the critical step by
  sqrt(1 + d) (measured in YADE, ``docs/validation-yade.md``). The certificate
  therefore scales every spring and dashpot by 1 + d (``cundall="amplify"``, the
  default: the worst frozen case of the scaling, not a proof for the switching
  system); ``cundall="refuse"`` refuses d > 0 instead. Ignoring d is not offered: it
  is not conservative.

What the certificate does not model is refused in one line naming it (an
:class:`~demstep.errors.InputError`, which stops a run from a ``PyRunner``), never
certified as something else: another IPhys or IGeom class, a law functor it does not
know (or ``creep``), shapes other than those above, a dynamic wall, facet or box, an
active ``TimeStepper``, engines other than the neutral ones (:data:`NEUTRAL_ENGINES`)
and the kinematic ones on fixed bodies (:data:`KINEMATIC_ENGINES`), ``ViscElPhys``
rolling resistance ``mR``, ``densityScaling``. Between two certificates the state moves
on: the safety factor covers that drift (demstep's own 'auto' step carries a
certificate of it; this one does not).

YADE runs with the system Python (Debian: ``/usr/bin/python3``); demstep and its
dependencies must be importable there: a venv made with ``--system-site-packages`` from
that Python, with ``numpy<2`` (YADE's build), and ``python VENV yade`` (docs/yade.md).
:func:`yade_command` finds such a Python for a child process (tests, validation).
"""

from __future__ import annotations

import functools
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np

from demstep.errors import InputError
from demstep.integrations.stepping import band_change, check_settings, why

#: the IPhys classes the certificate models, with the law functor that must apply them
PHYS_LAWS = {"FrictPhys": "Law2_ScGeom_FrictPhys_CundallStrack",
             "ViscElPhys": "Law2_ScGeom_ViscElPhys_Basic",
             "CohFrictPhys": "Law2_ScGeom6D_CohFrictPhys_CohesionMoment"}
#: the IGeom classes it reads (normal, penetrationDepth, contactPoint)
GEOMS = {"ScGeom", "ScGeom6D"}
#: the geometry functors (their ratcheting flag: the slip velocity's arm is the radius)
GEOM_FUNCTORS = {"Ig2_Sphere_Sphere_ScGeom": "avoidGranularRatcheting",
                 "Ig2_Sphere_Sphere_ScGeom6D": "avoidGranularRatcheting",
                 "Ig2_Wall_Sphere_ScGeom": "noRatch",
                 "Ig2_Box_Sphere_ScGeom": None, "Ig2_Box_Sphere_ScGeom6D": None,
                 "Ig2_Facet_Sphere_ScGeom": None, "Ig2_Facet_Sphere_ScGeom6D": None}
#: the shape of the other body for each geometry functor
FUNCTOR_SHAPE = {"Sphere": "Ig2_Sphere_Sphere", "Wall": "Ig2_Wall_Sphere",
                 "Box": "Ig2_Box_Sphere", "Facet": "Ig2_Facet_Sphere"}
#: fixed bodies whose contacts are wall contacts
WALL_SHAPES = {"Wall", "Facet", "Box"}
#: engines that add no stiffness, damping or mass: the certificate is the same with them
NEUTRAL_ENGINES = {"ForceResetter", "InsertionSortCollider", "PyRunner", "GravityEngine",
                   "ForceEngine", "VTKRecorder", "SnapshotEngine", "TorqueRecorder",
                   "ForceRecorder", "qtRecorder", "Recorder", "SpatialQuickSortCollider",
                   "PeriodicEngine"}
#: engines that prescribe the motion of their ``ids``: certified on fixed bodies only
KINEMATIC_ENGINES = {"TranslationEngine", "RotationEngine", "HelixEngine",
                     "CombinedKinematicEngine", "HarmonicMotionEngine",
                     "HarmonicRotationEngine", "ServoPIDController", "InterpolatingHelixEngine"}
#: engines that set O.dt themselves
TIMESTEPPERS = {"GlobalStiffnessTimeStepper", "TimeStepper"}
#: how NewtonIntegrator.damping enters (module docstring)
CUNDALL_MODES = ("amplify", "refuse")
#: certifiers reachable from a PyRunner's command (by id)
REGISTRY: dict[int, "YadeCertifier"] = {}


class StepNotCertified(RuntimeError):
    """YADE's step cannot be certified now (the certificate could not be computed)."""


def _omega():
    """YADE's Omega (``O``): only inside YADE's Python."""
    try:
        from yade.wrapper import Omega
    except ImportError:
        raise ImportError("demstep.integrations.yade runs inside YADE (yade -x SCRIPT); "
                          "apt-get install yade, and see docs/yade.md") from None
    return Omega()


def _name(obj) -> str:
    return type(obj).__name__


# ----------------------------------------------------------------------------- scene
@dataclass
class YadeScene:
    """A YADE scene as the certificate takes it: ``particles`` (the spheres, clump
    members included; ``ids`` their YADE body ids), ``contacts`` (a
    :class:`~demstep.timestep.contacts.ContactSet`, each spring and dashpot already
    scaled by ``1 + cundall``), ``bodies`` (:class:`~demstep.timestep.clumps.RigidBodies`
    of the clumps, or None), ``rotation`` (False when every free body has its rotations
    blocked), ``cundall`` (NewtonIntegrator.damping), the contacts' ``overlaps`` [L] and
    the ``notes`` (what was taken conservatively)."""

    particles: object
    contacts: object
    bodies: object
    rotation: bool
    cundall: float
    overlaps: np.ndarray
    ids: np.ndarray
    periodic: bool
    notes: list = field(default_factory=list)


def _engines(O, cundall_mode: str):
    """(InteractionLoop, NewtonIntegrator) of ``O.engines``; every other engine neutral,
    kinematic on fixed bodies, or refused in one line naming it."""
    loops, newtons = [], []
    for e in O.engines:
        name = _name(e)
        if getattr(e, "dead", False):
            continue
        if name == "InteractionLoop":
            loops.append(e)
        elif name == "NewtonIntegrator":
            newtons.append(e)
        elif name in TIMESTEPPERS:
            if e.active:
                raise InputError(f"yade: engine {name} is active: it sets O.dt itself (remove "
                                 f"it or set active=False)")
            if getattr(e, "densityScaling", False):
                raise InputError(f"yade: {name} densityScaling=True scales the masses: not "
                                 f"certified")
        elif name in NEUTRAL_ENGINES or name.endswith("Collider"):
            continue
        elif name in KINEMATIC_ENGINES:
            for i in list(getattr(e, "ids", [])):
                b = O.bodies[i]
                if b is not None and b.dynamic:
                    raise InputError(f"yade: engine {name} moves body {i}, which is dynamic: "
                                     f"not certified (prescribed motion on fixed bodies only)")
        else:
            raise InputError(f"yade: engine {name} is not certified: the certificate does not "
                             f"model what it does")
    if len(loops) != 1 or len(newtons) != 1:
        raise InputError(f"yade: expected one InteractionLoop and one NewtonIntegrator, "
                         f"found {len(loops)} and {len(newtons)}")
    loop, newton = loops[0], newtons[0]
    laws = {}
    for f in loop.lawDispatcher.functors:
        name = _name(f)
        if name not in PHYS_LAWS.values():
            raise InputError(f"yade: law functor {name} is not certified")
        if getattr(f, "shear_creep", False) or getattr(f, "twist_creep", False):
            raise InputError(f"yade: {name} with shear_creep/twist_creep is not certified")
        laws[name] = f
    geoms = {}
    for f in loop.geomDispatcher.functors:
        name = _name(f)
        if name not in GEOM_FUNCTORS:
            raise InputError(f"yade: geometry functor {name} is not certified")
        geoms[name] = f
    d = float(newton.damping)
    if not (math.isfinite(d) and 0.0 <= d < 1.0):
        raise InputError(f"yade: NewtonIntegrator.damping {d!r} is not certified (0 <= d < 1)")
    if d > 0.0 and cundall_mode == "refuse":
        raise InputError(f"yade: NewtonIntegrator.damping = {d:g} (Cundall's non-viscous "
                         f"damping) is refused (cundall='refuse'; 'amplify' certifies it)")
    return laws, geoms, d


def _slip_radius_flag(geoms: dict, shape: str) -> bool:
    """Whether the geometry functor of a sphere's contact with ``shape`` takes the full
    radius for the slip velocity (its ratcheting flag)."""
    prefix = FUNCTOR_SHAPE[shape]
    for name, f in geoms.items():
        if name.startswith(prefix):
            flag = GEOM_FUNCTORS[name]
            return bool(flag and getattr(f, flag))
    return False


def read_scene(O=None, cundall_mode: str = "amplify") -> YadeScene:
    """The scene of YADE's ``O`` (default: the running one) as the certificate takes it
    (module docstring); what it does not model is refused in one line naming it."""
    from demstep.particles import Particles
    from demstep.timestep.clumps import RigidBodies
    from demstep.timestep.contacts import ContactSet

    if cundall_mode not in CUNDALL_MODES:
        raise InputError(f"cundall: must be one of {', '.join(CUNDALL_MODES)}, got "
                         f"{cundall_mode!r}")
    O = O or _omega()
    laws, geoms, d = _engines(O, cundall_mode)
    notes = []
    # --- bodies
    sphere_index = {}
    ids, x, r, m, inertia, fixed = [], [], [], [], [], []
    member_clump = []
    clumps = {}
    walls = set()
    rotation_free = False
    partly = []
    shapes = {}
    for b in O.bodies:
        if b is None:
            continue
        shape = _name(b.shape)
        shapes[b.id] = shape
        blocked = set(b.state.blockedDOFs)
        is_fixed = (not b.dynamic) or blocked >= set("xyzXYZ")
        if shape == "Clump":
            clumps[b.id] = b
        elif shape == "Sphere":
            sphere_index[b.id] = len(ids)
            ids.append(b.id)
            x.append(tuple(b.state.pos))
            r.append(float(b.shape.radius))
            if b.isClumpMember:
                member_clump.append(b.clumpId)
                mass = float(b.state.mass) or 1.0  # (unused: the clump's mass counts)
                fixed.append(False)
                m.append(mass)
                inertia.append(0.4 * mass * r[-1] ** 2)
                continue
            member_clump.append(-1)
            mass = float(b.state.mass)
            inert = min(b.state.inertia)
            if not is_fixed and not (mass > 0 and inert > 0):
                raise InputError(f"yade: body {b.id} (Sphere) has mass {mass!r} and inertia "
                                 f"{tuple(b.state.inertia)}: not certified")
            m.append(mass if mass > 0 else 1.0)
            inertia.append(inert if inert > 0 else 1.0)
            fixed.append(bool(is_fixed))
            if len(set(b.state.inertia)) > 1:
                notes.append(f"body {b.id}: a sphere with unequal inertia "
                             f"{tuple(b.state.inertia)}: the smallest taken")
        elif shape in WALL_SHAPES:
            if not is_fixed:
                raise InputError(f"yade: body {b.id} ({shape}) is dynamic: only fixed walls, "
                                 f"facets and boxes are certified")
            walls.add(b.id)
            continue
        else:
            raise InputError(f"yade: body {b.id} has shape {shape}: not certified")
        if shape in ("Sphere", "Clump") and not is_fixed:
            if blocked and blocked != set("XYZ"):
                partly.append(b.id)
            if not blocked >= set("XYZ"):
                rotation_free = True
    for b in clumps.values():
        if not ((not b.dynamic) or set(b.state.blockedDOFs) >= set("xyzXYZ")):
            blocked = set(b.state.blockedDOFs)
            if blocked and blocked != set("XYZ"):
                partly.append(b.id)
            if not blocked >= set("XYZ"):
                rotation_free = True
    if partly:
        notes.append(f"bodies {partly[:5]}{' ...' if len(partly) > 5 else ''}: partly "
                     f"blocked DOFs taken as free (conservative)")
    if not ids:
        raise InputError("yade: no spheres in the scene")
    x = np.array(x, dtype=np.float64)
    r = np.array(r, dtype=np.float64)
    particles = Particles(x, r, np.array(m), np.array(inertia), np.array(fixed))
    bodies = None
    member_clump = np.array(member_clump)
    if clumps:
        order = sorted(clumps)
        index = {cid: k for k, cid in enumerate(order)}
        sphere_body = np.array([index[c] if c >= 0 else -1 for c in member_clump])
        arm = np.zeros((len(ids), 3))
        mass, world, cfixed = [], [], []
        for cid in order:
            s = clumps[cid].state
            R = np.array(s.ori.toRotationMatrix(), dtype=np.float64).reshape(3, 3)
            world.append(R @ np.diag(np.array(tuple(s.inertia))) @ R.T)
            mass.append(float(s.mass))
            cfixed.append((not clumps[cid].dynamic)
                          or set(s.blockedDOFs) >= set("xyzXYZ"))
        members = np.flatnonzero(sphere_body >= 0)
        for k in members:
            arm[k] = x[k] - np.array(tuple(clumps[order[sphere_body[k]]].state.pos))
        bodies = RigidBodies(sphere_body, arm, np.array(mass), np.array(world),
                             np.array(cfixed))
    # --- interactions
    periodic = bool(O.periodic)
    hsize = np.array(O.cell.hSize, dtype=np.float64).reshape(3, 3) if periodic else None
    slip_full = {shape: _slip_radius_flag(geoms, shape) for shape in FUNCTOR_SHAPE}
    xs = [tuple(p) for p in x]
    # the torque's arm r - delta/2 (CundallStrack's sphericalBodies, or any periodic cell)
    spherical = {name: periodic or bool(getattr(f, "sphericalBodies", False))
                 for name, f in laws.items()}
    always_moment = {name: bool(getattr(f, "always_use_moment_law", False))
                     for name, f in laws.items()}
    rows = {k: [] for k in ("i", "j", "normal", "arm_i", "arm_j", "k_n", "k_s", "wall",
                            "c_n", "c_t", "k_r", "k_w", "overlap")}
    for inter in O.interactions:
        if not inter.isReal:
            continue
        geom, phys = inter.geom, inter.phys
        gname, pname = _name(geom), _name(phys)
        id1, id2 = inter.id1, inter.id2
        if gname not in GEOMS:
            raise InputError(f"yade: interaction ({id1}, {id2}): IGeom {gname} is not certified")
        if pname not in PHYS_LAWS:
            raise InputError(f"yade: interaction ({id1}, {id2}): IPhys {pname} is not certified")
        law_name = PHYS_LAWS[pname]
        if law_name not in laws:
            raise InputError(f"yade: interaction ({id1}, {id2}): {pname} without its law "
                             f"functor {law_name} is not certified")
        delta = float(geom.penetrationDepth)
        cohesive = pname == "CohFrictPhys" and not phys.cohesionBroken
        if not (delta > 0.0 or cohesive):
            continue  # (no force: no spring)
        side = []
        for bid in (id1, id2):
            if bid in sphere_index:
                side.append(sphere_index[bid])
            elif bid in walls:
                side.append(-1)
            else:
                raise InputError(f"yade: interaction ({id1}, {id2}): body {bid} is not a "
                                 f"sphere, wall, facet or box")
        if side[0] < 0 and side[1] < 0:
            continue  # (two fixed bodies)
        n = tuple(geom.normal)
        cp = tuple(geom.contactPoint)
        shift = (tuple(hsize @ np.array(tuple(inter.cellDist), dtype=np.float64))
                 if periodic else (0.0, 0.0, 0.0))
        other_shape = (shapes[id2], shapes[id1])
        arms = []
        for k, p in enumerate(side):
            if p < 0:
                arms.append(0.0)
                continue
            pos = xs[p]
            if k == 1:
                pos = (pos[0] + shift[0], pos[1] + shift[1], pos[2] + shift[2])
            to_cp = abs((cp[0] - pos[0]) * n[0] + (cp[1] - pos[1]) * n[1]
                        + (cp[2] - pos[2]) * n[2])
            rad = r[p]
            if pname == "ViscElPhys":
                slip, torque = to_cp, to_cp
            else:
                slip = rad if slip_full.get(other_shape[k], False) else to_cp
                torque = rad - 0.5 * delta if spherical[law_name] else to_cp
            arms.append(math.sqrt(slip * torque))
        kr = kw = cn = ct = 0.0
        if pname == "ViscElPhys":
            if phys.mR != 0.0:
                raise InputError(f"yade: interaction ({id1}, {id2}): ViscElPhys rolling "
                                 f"resistance mR = {phys.mR:g} is not certified")
            cn, ct = float(phys.cn), float(phys.cs)
            if not (math.isfinite(cn) and math.isfinite(ct)):
                raise InputError(f"yade: interaction ({id1}, {id2}): ViscElPhys cn, cs = "
                                 f"{cn!r}, {ct!r}: not certified")
        elif pname == "CohFrictPhys":
            if phys.momentRotationLaw and (not phys.cohesionBroken or always_moment[law_name]):
                kr, kw = float(phys.kr), float(phys.ktw)
        if side[0] >= 0 and side[1] >= 0:
            i, j, normal, ai, aj, wall = side[0], side[1], n, arms[0], arms[1], -1
        elif side[0] >= 0:
            i, j, normal, ai, aj, wall = side[0], -1, n, arms[0], 0.0, id2
        else:
            i, j, normal, ai, aj, wall = side[1], -1, (-n[0], -n[1], -n[2]), arms[1], 0.0, id1
        for key, value in (("i", i), ("j", j), ("normal", normal), ("arm_i", ai),
                           ("arm_j", aj), ("k_n", phys.kn), ("k_s", phys.ks), ("wall", wall),
                           ("c_n", cn), ("c_t", ct), ("k_r", kr), ("k_w", kw),
                           ("overlap", delta)):
            rows[key].append(value)
    c = len(rows["i"])
    scale = 1.0 + d
    contacts = ContactSet(
        np.array(rows["i"], dtype=np.int64), np.array(rows["j"], dtype=np.int64),
        np.array(rows["normal"], dtype=np.float64).reshape(c, 3),
        np.array(rows["arm_i"]), np.array(rows["arm_j"]),
        scale * np.array(rows["k_n"], dtype=np.float64),
        scale * np.array(rows["k_s"], dtype=np.float64),
        wall=np.array(rows["wall"], dtype=np.int64),
        c_n=scale * np.array(rows["c_n"]), c_t=scale * np.array(rows["c_t"]),
        k_r=scale * np.array(rows["k_r"]), k_w=scale * np.array(rows["k_w"]))
    if d > 0:
        notes.append(f"NewtonIntegrator.damping {d:g}: springs and dashpots x {scale:g}")
    return YadeScene(particles, contacts, bodies, rotation_free, d,
                     np.array(rows["overlap"], dtype=np.float64), np.array(ids), periodic,
                     notes)


def certified_step(scene: YadeScene, method: str = "exact") -> float:
    """The certified critical step [T] of ``scene``: ``method`` "exact" (the exact step,
    damped when there are dashpots, with its guarantee:
    :func:`demstep.timestep.estimates.certified_dt`) or "element" (the coupled element
    bound); inf without contacts."""
    from demstep.timestep.estimates import certified_dt, element_coupled_dt

    if scene.contacts.n == 0:
        return math.inf
    if method == "exact":
        return float(certified_dt(scene.particles, scene.contacts, scene.rotation,
                                  bodies=scene.bodies))
    return float(element_coupled_dt(scene.particles, scene.contacts, scene.rotation,
                                    bodies=scene.bodies))


# ----------------------------------------------------------------------------- certifier
@dataclass
class Certificate:
    """One certificate of a YADE scene: the certified critical step ``dt`` [s] (by
    ``method``), the step YADE had (``dt_yade``) and the one set after (``dt_set``;
    None when unchanged), the iteration ``O.iter``, the number of contacts, the largest
    overlap / radius, the seconds it took, and why the step changed."""

    step: int
    dt: float
    method: str
    dt_yade: float
    contacts: int
    max_overlap: float
    seconds: float
    dt_set: float | None = None
    reason: str = ""


@dataclass
class YadeCertifier:
    """Certifies (and sets) ``O.dt`` of the running YADE scene (module docstring).
    ``safety`` in (0, 1]: the step set is ``safety`` times the certified one;
    ``method``: "exact" or "element" (the coupled element bound); ``grow``: the
    hysteresis: ``O.dt`` is kept within [safety / (1 + grow)^2, safety] times the
    certified step, and one outside is set to safety / (1 + grow) times it; ``cundall``: how NewtonIntegrator.damping
    enters ("amplify": springs and dashpots x (1 + d); "refuse"); ``log``: a function
    taking each line (None: print); ``O``: YADE's Omega (None: the running one)."""

    safety: float = 0.8
    method: str = "exact"
    grow: float = 0.05
    cundall: str = "amplify"
    log: object = None
    O: object = None
    history: list = field(default_factory=list)

    def __post_init__(self):
        check_settings(self.safety, self.method, self.grow)
        if self.cundall not in CUNDALL_MODES:
            raise InputError(f"cundall: must be one of {', '.join(CUNDALL_MODES)}, got "
                             f"{self.cundall!r}")
        self._noted = set()

    @property
    def omega(self):
        return self.O or _omega()

    def certify(self) -> Certificate:
        """The certified critical step of the scene now (inf without contacts)."""
        start = time.perf_counter()
        O = self.omega
        scene = read_scene(O, self.cundall)
        for note in scene.notes:
            if note not in self._noted:
                self._noted.add(note)
                self._say(note)
        dt = certified_step(scene, self.method)
        if not (dt > 0.0) or math.isnan(dt):
            raise StepNotCertified(f"iteration {O.iter}: the certificate could not be computed "
                                   f"(got {dt!r})")
        c = scene.contacts
        r = scene.particles.r
        overlap = float(np.max(scene.overlaps / r[c.i], initial=0.0)) if c.n else 0.0
        return Certificate(int(O.iter), dt, self.method, float(O.dt), int(c.n), overlap,
                           time.perf_counter() - start)

    def _say(self, text: str):
        (self.log or print)(f"demstep: {text}")

    def apply(self) -> Certificate:
        """Certify, and keep ``O.dt`` within [safety / (1 + grow)^2, safety] times the
        certified step: a step outside is set to ``safety / (1 + grow)`` times it (the
        middle: a step that keeps falling or rising changes about every ``grow``).
        Without contacts the step is left as it is (nothing limits it)."""
        cert = self.certify()
        previous = self.history[-1] if self.history else None
        self.history.append(cert)
        if not math.isfinite(cert.dt):
            if previous is None or math.isfinite(previous.dt):
                self._say(f"iteration {cert.step}: no contacts: nothing limits the step, "
                          f"O.dt {cert.dt_yade:.6g} left as it is")
            return cert
        change = band_change(cert.dt_yade, cert.dt, self.safety, self.grow)
        if change is None:
            return cert
        target, reason = change
        cert.reason = reason + why(previous, cert)
        self.omega.dt = target
        cert.dt_set = target
        self._say(f"iteration {cert.step}: O.dt {cert.dt_yade:.6g} -> {target:.6g} "
                  f"({cert.reason})")
        return cert

    def engine(self, iterPeriod: int = 100, label: str = "demstep"):
        """A ``PyRunner`` for ``O.engines`` that calls :meth:`apply` every ``iterPeriod``
        iterations (and at the first); an error stops the run with its reason."""
        from yade.wrapper import PyRunner

        if not (isinstance(iterPeriod, int) and iterPeriod >= 1):
            raise InputError(f"iterPeriod: must be an integer >= 1, got {iterPeriod!r}")
        REGISTRY[id(self)] = self
        command = (f"__import__('demstep.integrations.yade', fromlist=['REGISTRY'])"
                   f".REGISTRY[{id(self)}].apply()")
        return PyRunner(command=command, iterPeriod=iterPeriod, initRun=True, label=label)


# ----------------------------------------------------------------------------- finding YADE
#: where tests and docs put the venv that YADE's Python uses (outside the repository)
DEFAULT_VENV = os.path.join(tempfile.gettempdir(), "demstep-yade-venv")

_CHECK = ("import demstep, numpy, scipy, numba, yade.wrapper\n"
          "print('DEMSTEP-YADE-OK', demstep.__file__)\n")


@functools.lru_cache(maxsize=None)
def yade_command(timeout: float = 60.0) -> tuple:
    """(command, reason): ``[python, yade, "-n", "-x"]`` that runs a YADE script in
    which demstep imports, or (None, why not). The Python is the first that works of
    ``$DEMSTEP_YADE_PYTHON``, this Python, ``DEFAULT_VENV``'s and ``/tmp/yvenv``'s,
    and the system ``python3`` (each tried by running YADE once: about 2 s)."""
    yade = os.environ.get("DEMSTEP_YADE") or shutil.which("yade")
    if not yade:
        return None, "yade is not installed (apt-get install yade)"
    candidates = [os.environ.get("DEMSTEP_YADE_PYTHON"), sys.executable,
                  os.path.join(DEFAULT_VENV, "bin", "python"), "/tmp/yvenv/bin/python",
                  shutil.which("python3")]
    tried = []
    with tempfile.TemporaryDirectory(prefix="demstep-yade-") as tmp:
        script = os.path.join(tmp, "check.py")
        with open(script, "w") as f:
            f.write(_CHECK)
        for py in dict.fromkeys(c for c in candidates if c):
            if not os.path.exists(py):
                continue
            try:
                res = subprocess.run([py, yade, "-n", "-x", script], capture_output=True,
                                     text=True, timeout=timeout, cwd=tmp,
                                     stdin=subprocess.DEVNULL)
            except (subprocess.TimeoutExpired, OSError) as e:
                tried.append(f"{py}: {type(e).__name__}")
                continue
            if "DEMSTEP-YADE-OK" in res.stdout:
                return (py, yade, "-n", "-x"), ""
            last = (res.stderr.strip().splitlines() or ["?"])[-1]
            tried.append(f"{py}: {last[:120]}")
    return None, ("no Python runs YADE with demstep (make a venv: docs/yade.md); tried "
                  + "; ".join(tried))


def run_yade(script: str, args=(), timeout: float = 120.0, cwd=None):
    """Run the YADE ``script`` (a path) in a child process with :func:`yade_command`:
    the CompletedProcess (stdout, stderr, returncode). RuntimeError when YADE with
    demstep is not available."""
    command, reason = yade_command()
    if command is None:
        raise RuntimeError(reason)
    return subprocess.run(list(command) + [str(script)] + [str(a) for a in args],
                          capture_output=True, text=True, timeout=timeout, cwd=cwd,
                          stdin=subprocess.DEVNULL)
