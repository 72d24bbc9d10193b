"""Case files: a whole simulation described in TOML, validated before anything runs.

Units are any consistent set (M, L, T; the paper's Table I uses K = 1e11, density
2000, radius 20). Every key is listed below with its unit; keys not listed are errors.

Top level
---------
``name`` (str), ``description`` (str): labels for the run. Names (of the case, stages,
walls and clump templates) are 1 to 64 characters without control characters (a
newline would split the log's lines and the history's header).
``gravity`` = [gx, gy(, gz)]: body acceleration [L/T^2], one entry per dimension
(default zero).
``rotation`` (bool, default true): false locks every particle's rotation.
``mass_scaling`` (default 1): multiply every mass and moment of inertia (density
scaling for quasi-static runs; the critical step grows by its square root).

``[periodic]``: ``x``, ``y``, ``z`` = box length [L] of each periodic axis (box
[0, L)); omitted axes are not periodic.

``[particles]``: ``generator`` chooses how particles are made, ``density`` [M/L^3]
(3D) or [M/L^2] (2D disks, per unit thickness).

* ``generator = "lattice"``: ``lattice`` (square, hex, sc, bcc, fcc, rhombic; see
  :mod:`demstep.packings`), ``radius`` [L], ``size`` (cells per axis: an integer or a
  list, one per dimension), ``origin`` [L] (shift), ``clip_lower``/``clip_upper`` [L]
  (keep only centres inside this box, after the shift; e.g. 12 FCC layers of 4x4 and
  3x3 spheres from a 4x4x6 block clipped to x, y <= 6 r).
* ``generator = "grid"``: polydisperse random particles on a jittered grid of
  ``count`` (points per axis) with ``spacing`` [L], radii uniform in
  [``radius_min``, ``radius_max``] [L], ``jitter`` (fraction of the spacing, < 0.5),
  ``seed``, ``origin`` [L]. Particles never overlap at start (checked).
* ``generator = "file"``: ``path`` (relative to the case file) of a CSV, LIGGGHTS dump
  or YADE text file (:mod:`demstep.io.formats`), ``format`` (auto, csv, liggghts,
  yade), ``snapshot`` (LIGGGHTS dumps only: 0 first, -1 last). ``density`` may be
  omitted when the file has masses. From 1000 spheres on the run holds them in spatial
  order (2.5x faster on a file in random order); indices (``fixed.indices``, bond
  files), messages and the VTK ``id`` still count the file's rows (0-based, after
  LIGGGHTS' sort by id).

* ``generator = "clumps"``: rigid bodies of several spheres (:mod:`demstep.clumps`):
  ``templates`` (names of ``[[clumps]]`` shapes, used in turn), ``count`` (bodies per
  axis), ``spacing`` [L], ``origin`` [L], ``orientation`` ("random": uniform, from
  ``seed``; "fixed"), ``density``. The mass, centre of mass and inertia tensor of each
  body are those of the union of its members (overlaps counted once).
  Or a ``file`` of bodies (instead of ``templates``, ``count`` and ``spacing``): a CSV
  x, y[, z], template[, qw, qx, qy, qz] (with the orientation columns, no
  ``orientation`` and ``seed``; 2D: turns about z only, qx = qy = 0).
* a ``file`` with a ``body`` column (CSV ``body``, dump ``body`` or ``mol``) makes the
  spheres that share an id >= 0 one clump (its members as they lie).

* ``generator = "none"``: no particles at the start (``dim`` 2 or 3, default 3); the
  run fills by ``[[insert]]`` (required then). ``[box]`` needs ``lower`` and ``upper``.

``[[clumps]]``: clump shapes: ``name``, ``members`` = [[x, y, (z,) r], ...] [L] in the
template's frame (or ``file``, a CSV x,y[,z],r relative to the case file). The members
must touch or overlap one another (one rigid body), radii > 0.

``[particles.fixed]``: particles held in place: ``indices`` (0-based) and/or the box
``lower``/``upper`` [L] (lower <= upper on every axis; every centre inside is fixed).

``[contact]``: ``law``, one of the contact laws (:mod:`demstep.contact.laws`: "linear"
with ``k_n``, ``k_s`` [M/T^2], k_s defaulting to k_n; "hertz" with ``youngs_modulus``
[M/(L T^2)] and ``poisson_ratio``; each law's module lists its own keys), and for every
law ``mu``
(particle-particle friction), ``mu_wall`` (default mu), dashpots by ``restitution``
(normal, in (0, 1]) and ``restitution_tangential`` or by coefficients
``damping_normal``/``damping_tangential`` [M/T] (one or the other for each direction:
both would add up); rolling and twisting resistance
(:mod:`demstep.contact.laws`, Ai et al. 2011 type C): ``rolling_convention`` "beta"
(k_r = ``rolling_stiffness`` k_t R*^2, k_w = ``twisting_stiffness`` k_t R*^2) or
"epsd" (k = 2.25 k_n mu^2 R*^2, k_n the secant F_n / delta), limits ``rolling_friction`` mu_r and
``twisting_friction`` mu_w (moments up to mu R* F_n; 0 with a stiffness: no limit),
viscous damping ratio ``rolling_damping``.

``[bonds]``: parallel bonds (Potyondy & Cundall 2004, :mod:`demstep.contact.bonds`)
created at the start of ``stage`` (its name or 1-based number; default 1) between every
pair whose surfaces are at most ``gap`` [L] apart, or between the pairs of ``file`` (a
CSV with 0-based particle columns i, j, relative to the case file):
``normal_stiffness``, ``shear_stiffness`` [M/(L^2 T^2)] per unit area (shear defaults
to normal), ``tensile_strength``, ``shear_strength`` [M/(L T^2)] (default inf),
``radius_multiplier`` (bond radius / smaller particle radius, default 1).

``[[walls]]``: ``name``, ``point`` [L], ``normal`` (into the domain), ``motion``
(fixed, velocity, servo), ``velocity`` [L/T], ``target_stress`` [M/(L T^2)] (2D:
force per unit length), ``servo_gain`` [L T/M] (omitted: automatic, correcting
``servo_factor`` of the stress error per step at the current contact stiffness),
``max_speed`` [L/T], ``area`` [L^2] (> 0; 2D: length; omitted: from the opposite box
walls), ``friction`` (mu of this wall). A key the motion does not read is an error
(``velocity``: velocity walls only; ``target_stress``, ``servo_gain``, ``servo_factor``,
``max_speed``, ``area``: servo walls only).

``[[meshes]]`` (3D only): triangle-mesh walls (:mod:`demstep.mesh`,
:mod:`demstep.engine.meshes`): ``name``, ``file`` (STL ASCII or binary, OBJ, or what
meshio reads, relative to the case file), ``format`` (a meshio format name when the
extension does not tell), ``transforms`` (applied on load, in LIGGGHTS' words: ``"scale
0.001 move 0 0 0.1 rotate axis 0 0 1 angle 45"``), ``friction`` (mu of its contacts;
default the law's ``mu_wall``), ``material`` (a table of the contact law's own
parameters for the mesh: Hertz ``youngs_modulus`` and ``poisson_ratio``, paired with the
particles'; linear ``stiffness_normal``, ... for its contacts; omitted: the particles'),
its motion ``velocity`` [L/T] (a translation) and ``omega`` [1/T] (a rotation vector:
axis times rate) about ``center`` [L] (which moves with the translation), and
``surface_velocity`` [L/T] (a conveyor belt: its contacts see the surface move while
its triangles stay; LIGGGHTS' ``surface_vel``), ``enabled`` (default true; false: the
mesh is there, moves and is written out, but has no contacts, as a LIGGGHTS
``fix mesh/surface`` no ``fix wall/gran`` names yet), ``finnie_k`` [L T^2/M] (Finnie's
wear coefficient, an inverse pressure; > 0: each triangle accumulates its wear,
written to the VTK output and, times the areas, to history.csv; LIGGGHTS' ``wear
finnie`` with ``k_finnie``).
``[stages.meshes."name"]`` changes ``velocity``, ``omega``, ``surface_velocity``,
``friction`` or ``enabled`` from a stage on, and ``center`` [L] (where the centre of
rotation is now, in the case's frame; only while the mesh has not turned: LIGGGHTS'
``move/mesh rotate origin ...`` after a translation).

``[[insert]]``: particles inserted during the run (:mod:`demstep.feed`,
``docs/insertion.md``): ``name``, ``region`` (a table: ``shape = "box"`` with ``lower``,
``upper`` [L]; ``"cylinder"`` with ``axis`` (x, y, z), ``center`` (the two other
coordinates) [L], ``radius`` [L], ``lower``, ``upper`` along the axis [L]; ``"sphere"``
with ``center``, ``radius`` [L]; ``"face"`` with ``file`` (a mesh file, relative to the
case file: an inlet, not a wall) and ``transforms``), ``radius`` (a number [L], or a
table ``distribution = "uniform"`` (``min``, ``max``), ``"discrete"`` (``radii``,
``fractions``), ``"lognormal"`` (``median``, ``sigma``, optional ``min``/``max``
truncation; default median exp(-+3 sigma)), each with ``by`` = "number" (default) or
"mass"), ``density`` [M/L^3] (2D: M/L^2), exactly one of ``rate`` [1/T],
``mass_rate`` [M/T] and ``fill_to`` (a count: the region topped up to it at each
insertion; not with a face), optional ``total`` (count) and ``total_mass`` [M], ``start`` and
``stop`` [T], ``velocity`` [L/T], ``every`` (steps between insertions, default 1000),
``seed``, ``attempts`` (random positions tried per particle and insertion, default 50).
A particle is placed only where it overlaps no particle, wall or mesh; one that finds
no room waits for the next insertion (a warning says so). Not with clumps or bonds.

``[[outlet]]``: ``name``, ``region`` (box, cylinder or sphere, as above), ``every``
(steps, default 100): the particles whose centre lies in the region are removed, their
count and mass recorded in ``history.csv`` and the energy they take out in the ledger.

``[box]``: the 2 x dim axis-aligned walls named x-, x+, y-, y+(, z-, z+), none across a
periodic axis (with ``[periodic] x``, no x- and x+): corners
``lower``/``upper`` [L], or (both omitted) the particles' extents plus ``margin`` [L].
``[box.walls."z+"]`` sets a box wall's motion with the keys of ``[[walls]]`` (except
name, point and normal).

``[damping]``: ``local`` (Cundall, in [0, 1)), ``viscous`` (global mass-proportional
a1 [1/T]).

``[timestep]``: ``mode`` = "fixed" (``dt`` [T]), "alpha" (dt = ``alpha``
sqrt(m_min/K_max), default alpha 0.1) or "auto" (``safety`` x the critical step by
``method`` exact|element-coupled, re-evaluated ``every`` steps, growth capped at
``growth`` per update, and held where no particle moves more than ``motion`` of its
radius in a step, default 0.1, below ``[numerics] jump_limit``); ``overlap`` is the
relative overlap at which Hertz K_max is taken (Hertz law only). ``mode`` may be omitted: "fixed" when ``dt`` is given, else
"alpha".

``[energy]``: the balance monitor (paper eq. 22): ``eps`` (default 1e-2), ``every``
[steps], ``action`` = "warn" | "stop", ``floor`` [M L^2/T^2] (energies below it are
not checked; default: automatic).

``[numerics]``: ``skin`` [L] (Verlet skin; default 0.15 x mean radius), ``jump_limit``
(divergence when a particle moves this fraction of its radius in one step),
``runaway_factor`` (divergence when kinetic energy exceeds this multiple of the most
energy supplied so far; 0 disables), ``max_initial_overlap`` (the largest overlap of two particles at
the start, as a fraction of the smaller radius; default 0.05; pairs of fixed particles
are exempt; coincident centres are always an error), ``sort_every`` [steps] (the
particles are put in spatial order in memory again at the first neighbour-list rebuild
this many steps after the last sort, as particles that travel scatter their neighbours
in memory; default 1000; 0: never; outputs name particles by their input row whatever
their order).

``[[stages]]`` (at least one), run in order: ``name``, and exactly one of ``steps``,
``duration`` [T] or ``until_kinetic_below`` [M L^2/T^2] (checked every
``check_every`` steps, at most ``max_steps``; without it at most 1,000,000 steps, with a
warning when the stage starts). Changes applied at the start of the
stage: ``mu``, ``mu_wall``, ``damping = {local, viscous}``, ``gravity`` [L/T^2],
``[stages.walls."name"]`` (motion, velocity, target_stress, servo_gain, servo_factor,
max_speed, area, friction), ``[stages.periodic.x]`` (how a periodic length changes:
``motion`` fixed|rate|servo, ``rate`` [L/T] (rate only), ``target_stress`` [M/(L T^2)]
on the Love stress, ``servo_gain`` [L T/M] or ``servo_factor``, ``max_speed`` [L/T]
(servo only)),
``[stages.timestep]`` (a new [timestep] section from this stage on), ``reset_ledger``
(start a new energy balance from the current state).

``[output]``: ``history_every`` [steps] (CSV history; 0 none), ``vtk_every`` [steps]
(VTK frames; 0 none), ``vtk_contacts`` (write the contact network), ``checkpoint_every``
[steps] (0: only on interruption and at the end), ``checkpoint_keep`` (how many of the
newest checkpoints stay in the folder, counted across restarts, of every kind but the
states saved when a run failed; 0 keeps all).

Every number must be 0 or lie between 1e-100 and 1e100 in magnitude
(:data:`MIN_MAGNITUDE`, :data:`MAX_MAGNITUDE`): no consistent set of units needs more,
and products of such numbers overflow float64. The particles' initial state is checked
when the simulation is built (:func:`check_initial_state`): coordinates float64 can
resolve at the scale of the radii, no heavy overlaps, periodic lengths that hold the
particles, and finite masses, stiffnesses, time step and energies.

Errors (unknown keys, keys the chosen mode does not read, wrong types, non-physical
values) raise
:class:`~demstep.errors.InputError` with one line naming the key path (e.g.
``contact.mu``) and the value.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
import unicodedata
from pathlib import Path
from typing import Annotated, Literal, Union

import numpy as np
from pydantic import (AfterValidator, BaseModel, ConfigDict, Field, PrivateAttr, ValidationError,
                      create_model)

from demstep.clumps import ClumpTemplate
# (MIN_MAGNITUDE, MAX_MAGNITUDE: the case files' range, documented above, one for all input)
from demstep.contact.laws import LAWS, law_class
from demstep.errors import MAX_MAGNITUDE, MIN_MAGNITUDE, InputError, magnitude_problem
from demstep.io.formats import _number, detect_format, read_csv, read_particle_file
from demstep.io.textfile import (csv_rows, not_a_file_message, not_a_file_reason, open_text,
                                 read_small_text)
from demstep.feed import distribution_from_spec, region_from_spec
from demstep.mesh import parse_transforms
from demstep.packings import LATTICE_DIM, lattice as make_lattice

#: the largest assembly a case file may generate (a guard against typos in ``size``)
MAX_PARTICLES = 2_000_000

AXES = "xyz"

#: default of numerics.max_initial_overlap: the largest initial overlap of two
#: particles, as a fraction of the smaller radius
MAX_INITIAL_OVERLAP = 0.05
#: coordinates must lie within this many smallest radii of the origin: float64 then
#: resolves positions to 2e-7 of a radius (at 1e300 the whole contact vanishes in rounding)
MAX_COORDINATE_RADII = 1.0e9


def _magnitude(value: float) -> float:
    problem = magnitude_problem(value)
    if problem:
        raise ValueError(problem)
    return value


# ------------------------------------------------------------------ field types
Real = Annotated[float, AfterValidator(_magnitude)]
Positive = Annotated[float, Field(gt=0), AfterValidator(_magnitude)]
NonNegative = Annotated[float, Field(ge=0), AfterValidator(_magnitude)]
PositiveInt = Annotated[int, Field(ge=1)]
NonNegativeInt = Annotated[int, Field(ge=0)]
Vector = Annotated[list[Real], Field(min_length=2, max_length=3)]


def _printable(name: str) -> str:
    """``name`` when it has no control character (newline, tab, escape, line or
    paragraph separator)."""
    bad = next((c for c in name if unicodedata.category(c) in ("Cc", "Zl", "Zp")), None)
    if bad is not None:
        raise ValueError(f"must not hold control characters ({bad!r})")
    return name


Name = Annotated[str, Field(min_length=1, max_length=64), AfterValidator(_printable)]


def Bounded(**bounds):
    """A float within ``bounds`` (pydantic's gt, ge, lt, le) and within the magnitudes
    every number of a case must lie in."""
    return Annotated[float, Field(**bounds), AfterValidator(_magnitude)]


class _Section(BaseModel):
    """Strict sections: unknown keys, wrong types and non-finite numbers are errors."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False,
                              validate_default=False)


# -------------------------------------------------------------------- particles
class FixedSelection(_Section):
    """Particles held in place: by 0-based ``indices`` and/or the box [lower, upper] [L]."""

    indices: list[NonNegativeInt] = []
    lower: Vector | None = None
    upper: Vector | None = None


class _ParticlesBase(_Section):
    fixed: FixedSelection | None = None


class LatticeParticles(_ParticlesBase):
    """A block of a regular lattice (all particles of ``radius`` [L])."""

    generator: Literal["lattice"]
    lattice: Literal["square", "hex", "sc", "bcc", "fcc", "rhombic"]
    radius: Positive
    size: PositiveInt | list[PositiveInt]
    density: Positive
    origin: Vector | None = None
    clip_lower: Vector | None = None
    clip_upper: Vector | None = None


class GridParticles(_ParticlesBase):
    """Polydisperse particles on a jittered grid (random radii, no initial overlap)."""

    generator: Literal["grid"]
    count: Annotated[list[PositiveInt], Field(min_length=2, max_length=3)]
    spacing: Positive
    radius_min: Positive
    radius_max: Positive
    density: Positive
    jitter: Bounded(ge=0, lt=0.5) = 0.0
    seed: NonNegativeInt = 0
    origin: Vector | None = None


class FileParticles(_ParticlesBase):
    """Particles read from a CSV, LIGGGHTS dump or YADE text file."""

    generator: Literal["file"]
    path: Annotated[str, Field(min_length=1)]
    format: Literal["auto", "csv", "liggghts", "yade"] = "auto"
    snapshot: int = -1
    density: Positive | None = None


class ClumpParticles(_ParticlesBase):
    """Clumps (rigid bodies of the ``[[clumps]]`` templates) on a grid of ``count`` body
    positions [L] ``spacing`` apart, the templates taken in turn (``templates``: their
    names), each turned by a random orientation (``orientation = "random"``, from
    ``seed``) or not ("fixed"); or listed in a CSV ``file`` (columns x, y[, z] [L] of
    the template's origin, ``template`` (a name) and optionally the orientation
    ``qw, qx, qy, qz``). ``fixed`` selects bodies (by index or centre)."""

    generator: Literal["clumps"]
    templates: list[Name] = []
    count: Annotated[list[PositiveInt], Field(min_length=2, max_length=3)] | None = None
    spacing: Positive | None = None
    file: str | None = None
    density: Positive
    orientation: Literal["random", "fixed"] = "random"
    seed: NonNegativeInt = 0
    origin: Vector | None = None


class NoParticles(_ParticlesBase):
    """No particles at the start: the run fills by ``[[insert]]`` (in ``dim`` dimensions)."""

    generator: Literal["none"]
    dim: Literal[2, 3] = 3


ParticlesSection = Annotated[Union[LatticeParticles, GridParticles, FileParticles, ClumpParticles,
                                   NoParticles],
                             Field(discriminator="generator")]


class BondsSection(_Section):
    """Parallel bonds created at the start of a stage (:mod:`demstep.contact.bonds`)."""

    normal_stiffness: Positive
    shear_stiffness: NonNegative | None = None
    tensile_strength: Positive = math.inf  # (the default: no limit)
    shear_strength: Positive = math.inf
    radius_multiplier: Positive = 1.0
    gap: NonNegative = 0.0
    file: str | None = None
    stage: Annotated[str, Field(min_length=1)] | Annotated[int, Field(ge=1)] = 1


class ClumpTemplateSpec(_Section):
    """A clump shape: ``name`` and its ``members``, rows of centre and radius
    [x, y, (z,) r] [L] in the template's frame, or a CSV ``file`` (x,y[,z],r) relative
    to the case file."""

    name: Name
    members: list[Annotated[list[Real], Field(min_length=3, max_length=4)]] = []
    file: str | None = None


# ---------------------------------------------------------------------- contact
class _ContactBase(_Section):
    mu: NonNegative = 0.0
    mu_wall: NonNegative | None = None
    restitution: Bounded(gt=0, le=1) | None = None
    restitution_tangential: Bounded(gt=0, le=1) | None = None
    damping_normal: NonNegative = 0.0
    damping_tangential: NonNegative = 0.0
    rolling_convention: Literal["beta", "epsd"] | None = None
    rolling_stiffness: NonNegative = 0.0
    twisting_stiffness: NonNegative = 0.0
    rolling_friction: NonNegative = 0.0
    twisting_friction: NonNegative = 0.0
    rolling_damping: NonNegative = 0.0


def _law_section(cls) -> type:
    """The [contact] section of the law ``cls`` (:data:`demstep.contact.laws.LAWS`):
    ``law`` = its name and its own parameters, checked by their bounds."""
    fields = {"law": (Literal[cls.name], ...)}
    for f in cls.own_fields():
        meta = f.metadata
        kind = Bounded(**meta["bounds"])
        fields[f.name] = (kind, ...) if meta["required"] else (kind | None, f.default)
    return create_model(f"{cls.__name__}Contact", __base__=_ContactBase,
                        __doc__=f"The {cls.name} law: {(cls.__doc__ or '').strip()}", **fields)


#: the [contact] section of each registered law, by law name
LAW_SECTIONS = {name: _law_section(cls) for name, cls in LAWS.items()}
ContactSection = Annotated[Union[tuple(LAW_SECTIONS.values())], Field(discriminator="law")]


# ------------------------------------------------------------------------ walls
class WallMotion(_Section):
    """How a wall moves; omitted keys keep their value (or the default)."""

    motion: Literal["fixed", "velocity", "servo"] | None = None
    velocity: Vector | None = None
    target_stress: NonNegative | None = None
    servo_gain: Positive | None = None
    servo_factor: Positive | None = None
    max_speed: Positive | None = None
    area: Positive | None = None
    friction: NonNegative | None = None


class WallSpec(WallMotion):
    """A rigid plane through ``point`` [L] with ``normal`` pointing into the domain."""

    name: Name
    point: Vector
    normal: Vector


class BoxSection(_Section):
    """Axis-aligned box walls x-, x+, y-, y+(, z-, z+)."""

    lower: Vector | None = None
    upper: Vector | None = None
    margin: NonNegative = 0.0
    walls: dict[str, WallMotion] = {}


class MeshMotion(_Section):
    """How a mesh moves, whether it has contacts, its friction, the centre it turns
    about; omitted keys keep their value."""

    velocity: Vector | None = None
    omega: Vector | None = None
    surface_velocity: Vector | None = None
    friction: NonNegative | None = None
    enabled: bool | None = None
    center: Vector | None = None


class MeshSpec(MeshMotion):
    """A triangle-mesh wall read from ``file`` with ``transforms``, its contact
    ``material`` and its motion about ``center``."""

    name: Name
    file: str
    format: Annotated[str, Field(min_length=1, max_length=32)] | None = None
    transforms: Annotated[str, Field(max_length=4096)] = ""
    material: dict[Annotated[str, Field(max_length=64)], Real] = {}
    enabled: bool = True
    finnie_k: NonNegative = 0.0


# --------------------------------------------------------- insertion, outflow
class BoxShape(_Section):
    shape: Literal["box"]
    lower: Vector
    upper: Vector


class CylinderShape(_Section):
    shape: Literal["cylinder"]
    axis: Literal["x", "y", "z"]
    center: Annotated[list[Real], Field(min_length=2, max_length=2)]
    radius: Positive
    lower: Real
    upper: Real


class SphereShape(_Section):
    shape: Literal["sphere"]
    center: Vector
    radius: Positive


class FaceShape(_Section):
    shape: Literal["face"]
    file: Annotated[str, Field(min_length=1)]
    transforms: Annotated[str, Field(max_length=4096)] = ""


RegionShape = Annotated[Union[BoxShape, CylinderShape, SphereShape, FaceShape],
                        Field(discriminator="shape")]


class RadiusSpec(_Section):
    """A radius distribution (:mod:`demstep.feed.distributions`)."""

    distribution: Literal["uniform", "discrete", "lognormal"]
    min: Positive | None = None
    max: Positive | None = None
    radii: list[Positive] = []
    fractions: list[NonNegative] = []
    median: Positive | None = None
    sigma: Positive | None = None
    by: Literal["number", "mass"] = "number"


class InsertSpec(_Section):
    """Particles inserted at a rate (:mod:`demstep.engine.feed`)."""

    name: Name
    region: RegionShape
    radius: Positive | RadiusSpec
    density: Positive
    rate: Positive | None = None
    mass_rate: Positive | None = None
    fill_to: PositiveInt | None = None
    total: NonNegativeInt | None = None
    total_mass: Positive | None = None
    start: NonNegative = 0.0
    stop: NonNegative | None = None
    velocity: Vector | None = None
    every: PositiveInt = 1000
    seed: NonNegativeInt = 0
    attempts: PositiveInt = 50


class OutletSpec(_Section):
    """Particles removed where their centre lies in ``region``, every ``every`` steps."""

    name: Name
    region: Union[BoxShape, CylinderShape, SphereShape] = Field(discriminator="shape")
    every: PositiveInt = 100


class PeriodicSection(_Section):
    """Box length [L] of each periodic axis."""

    x: Positive | None = None
    y: Positive | None = None
    z: Positive | None = None


# --------------------------------------------------------------- integration
class DampingSection(_Section):
    local: Bounded(ge=0, lt=1) = 0.0
    viscous: NonNegative = 0.0


class DampingChange(_Section):
    local: Bounded(ge=0, lt=1) | None = None
    viscous: NonNegative | None = None


class TimestepSection(_Section):
    mode: Literal["fixed", "alpha", "auto"] | None = None
    dt: Positive | None = None
    alpha: Positive | None = None
    safety: Bounded(gt=0, le=1) = 0.8
    method: Literal["exact", "element-coupled"] = "exact"
    every: PositiveInt = 500
    growth: NonNegative = 0.05
    overlap: Positive = 0.01
    motion: Positive = 0.1


class EnergySection(_Section):
    eps: Positive = 1.0e-2
    every: PositiveInt = 100
    action: Literal["warn", "stop"] = "warn"
    floor: Positive | None = None


class NumericsSection(_Section):
    skin: Positive | None = None
    jump_limit: Positive = 0.25
    runaway_factor: NonNegative = 10.0
    max_initial_overlap: NonNegative = MAX_INITIAL_OVERLAP
    sort_every: NonNegativeInt = 1000


class BoxAxisMotion(_Section):
    """How the length of one periodic axis changes: 'fixed', 'rate' (dL/dt = ``rate``
    [L/T]) or 'servo' (hold the Love stress at ``target_stress`` [M/(L T^2)], with
    ``servo_gain`` [L T/M] or, when it is 0 or omitted, the automatic gain correcting
    ``servo_factor`` of the error per step; at most ``max_speed`` [L/T])."""

    motion: Literal["fixed", "rate", "servo"]
    rate: Real | None = None
    target_stress: NonNegative | None = None
    servo_gain: NonNegative = 0.0
    servo_factor: Positive = 0.1
    max_speed: Positive | None = None


class Stage(_Section):
    """One stage: how long it runs and what changes at its start."""

    name: Name | None = None
    steps: NonNegativeInt | None = None
    duration: NonNegative | None = None
    until_kinetic_below: Positive | None = None
    check_every: PositiveInt = 100
    max_steps: PositiveInt | None = None
    mu: NonNegative | None = None
    mu_wall: NonNegative | None = None
    damping: DampingChange | None = None
    gravity: Vector | None = None
    walls: dict[str, WallMotion] = {}
    meshes: dict[str, MeshMotion] = {}
    periodic: dict[str, BoxAxisMotion] = {}
    timestep: TimestepSection | None = None
    reset_ledger: bool = False


class OutputSection(_Section):
    history_every: NonNegativeInt = 100
    vtk_every: NonNegativeInt = 0
    vtk_contacts: bool = True
    checkpoint_every: NonNegativeInt = 0
    checkpoint_keep: NonNegativeInt = 3


class Case(_Section):
    """A validated case (see the module docstring for every key)."""

    name: Name = "demstep-run"
    description: str = ""
    gravity: Vector | None = None
    rotation: bool = True
    mass_scaling: Positive = 1.0
    periodic: PeriodicSection | None = None
    particles: ParticlesSection
    clumps: list[ClumpTemplateSpec] = []
    contact: ContactSection
    bonds: BondsSection | None = None
    walls: list[WallSpec] = []
    meshes: list[MeshSpec] = []
    insert: list[InsertSpec] = []
    outlet: list[OutletSpec] = []
    box: BoxSection | None = None
    damping: DampingSection = Field(default_factory=DampingSection)
    timestep: TimestepSection = Field(default_factory=TimestepSection)
    energy: EnergySection = Field(default_factory=EnergySection)
    numerics: NumericsSection = Field(default_factory=NumericsSection)
    stages: Annotated[list[Stage], Field(min_length=1)]
    output: OutputSection = Field(default_factory=OutputSection)

    _base_dir: Path = PrivateAttr(default_factory=Path.cwd)
    _source: str = PrivateAttr(default="")
    _dim: int | None = PrivateAttr(default=None)

    @property
    def base_dir(self) -> Path:
        """Folder relative paths in the case are taken from (the case file's)."""
        return self._base_dir

    @property
    def source(self) -> str:
        """Where the case came from (file path) for messages."""
        return self._source

    @property
    def dim(self) -> int:
        """Spatial dimension (2 or 3)."""
        if self._dim is None:
            self._dim = _particle_dim(self)
        return self._dim

    def stage_label(self, k: int) -> str:
        """Display name of stage k."""
        name = self.stages[k].name
        return name if name else f"stage {k + 1}"

    def periodic_axes(self) -> str:
        """The periodic axes, e.g. "x" or "xz" ("" none)."""
        p = self.periodic
        return "" if p is None else "".join(a for a in AXES[:self.dim]
                                            if getattr(p, a) is not None)

    def wall_names(self) -> list[str]:
        """Names of every wall, in the order the Simulation holds them."""
        names = (box_wall_names(self.dim, self.periodic_axes()) if self.box is not None
                 else [])
        return names + [w.name for w in self.walls]

    def resolved(self) -> dict:
        """The case with every default filled in and paths made absolute (for TOML)."""
        data = self.model_dump(mode="python", exclude_none=True)
        for stage in data["stages"]:
            if stage.get("until_kinetic_below") is None:
                stage.pop("check_every", None)  # (read with until_kinetic_below only)
        for section in [data.get("timestep")] + [st.get("timestep") for st in data["stages"]]:
            if section is not None and section.get("mode") != "auto":
                for name in AUTO_ONLY:  # (the mode does not read them)
                    section.pop(name, None)
        for _, path, _, _, _ in _unused_keys(self):  # (the case's choices do not read them)
            node = data
            for item in path[:-1]:
                node = node[item] if isinstance(node, list) else node.get(item, {})
            if isinstance(node, dict):
                node.pop(path[-1], None)
        if self.particles.generator == "file":
            data["particles"]["path"] = str(self.particle_file())
        if self.particles.generator == "clumps" and self.particles.file is not None:
            data["particles"]["file"] = str(_relative(self, self.particles.file).resolve())
        for k, spec in enumerate(self.clumps):
            if spec.file is not None:
                data["clumps"][k]["file"] = str(_relative(self, spec.file).resolve())
        if self.bond_file() is not None:
            data["bonds"]["file"] = str(self.bond_file())
        for k, spec in enumerate(self.meshes):
            data["meshes"][k]["file"] = str(self.mesh_file(k))
        for k, spec in enumerate(self.insert):
            if spec.region.shape == "face":
                data["insert"][k]["region"]["file"] = str(_relative(self, spec.region.file).resolve())
        for key in ("insert", "outlet"):  # (a case without them resolves as before)
            if not data.get(key):
                data.pop(key, None)
        # a case without meshes resolves as it did before meshes existed (its hash, which
        # a restart compares with the checkpoint's case, stays the same)
        if not data.get("meshes"):
            data.pop("meshes", None)
        for stage in data["stages"]:
            if not stage.get("meshes"):
                stage.pop("meshes", None)
        return data

    def mesh_file(self, k: int) -> Path:
        """Absolute path of the file of ``meshes[k]``."""
        return _relative(self, self.meshes[k].file).resolve()

    def bond_stage(self) -> int | None:
        """Index of the stage at whose start the bonds are created (None: no bonds)."""
        if self.bonds is None:
            return None
        ref = self.bonds.stage
        if isinstance(ref, int):
            if ref > len(self.stages):
                raise InputError(f"bonds.stage: there are {len(self.stages)} stages, got {ref}")
            return ref - 1
        names = [st.name for st in self.stages]
        if ref not in names:
            raise InputError(f"bonds.stage: no stage named {ref!r}")
        return names.index(ref)

    def bond_file(self) -> Path | None:
        """Absolute path of the bond list (None: bonds by gap)."""
        if self.bonds is None or self.bonds.file is None:
            return None
        p = Path(self.bonds.file).expanduser()
        return p if p.is_absolute() else (self._base_dir / p).resolve()

    def particle_file(self) -> Path:
        """Absolute path of the particle file (generator = 'file')."""
        p = Path(self.particles.path).expanduser()
        return p if p.is_absolute() else (self._base_dir / p).resolve()


def box_wall_names(dim: int, periodic: str = "") -> list[str]:
    """Names of the box walls in :func:`demstep.walls.box_walls` order, without those
    across the ``periodic`` axes (e.g. "x")."""
    return [f"{a}{s}" for a in AXES[:dim] if a not in periodic for s in "-+"]


# ------------------------------------------------------------ error messages
_BARE_KEY = re.compile(r"^[A-Za-z0-9_]+$")
_DISCRIMINATORS = ("generator", "law")


def _quoted(key: str) -> str:
    """A TOML key that is not bare, quoted as TOML writes it (control characters
    escaped: an error stays one line)."""
    return json.dumps(key, ensure_ascii=False)


def _key_path(loc, data) -> str:
    """'contact.mu', 'walls[0].normal', 'stages[1].walls."z+".velocity' from a pydantic
    error location, skipping the union tags pydantic inserts."""
    parts: list[str] = []
    node = data
    for pos, item in enumerate(loc):
        last = pos == len(loc) - 1
        if isinstance(node, dict) and isinstance(item, str):
            if any(node.get(d) == item for d in _DISCRIMINATORS) and not last:
                continue  # discriminated-union tag, e.g. 'lattice' in particles.lattice.radius
            if item in node or last:
                parts.append(item if _BARE_KEY.match(item) else _quoted(item))
                node = node.get(item)
            continue
        if isinstance(node, list) and isinstance(item, int):
            parts.append(f"[{item}]")
            node = node[item] if 0 <= item < len(node) else None
            continue
        # a tag of a plain union ('int', 'list[int]') or a path into a scalar
    text = ""
    for p in parts:
        text += p if p.startswith("[") or not text else "." + p
    return text or "(top level)"


def _short(value, limit: int = 60) -> str:
    text = repr(value).replace("\n", " ")
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _validation_message(exc: ValidationError, data) -> str:
    errors = exc.errors()
    # the most specific error first (unions report one error per alternative)
    err = max(errors, key=lambda e: len(e["loc"]))
    kind = err["type"]
    key = _key_path(err["loc"], data)
    ctx = err.get("ctx") or {}
    if kind == "missing":
        return f"{key}: required key is missing"
    if kind == "extra_forbidden":
        return f"{key}: unknown key"
    if kind == "union_tag_not_found":
        disc = str(ctx.get("discriminator", "")).strip("'")
        return f"{key}.{disc}: required key is missing"
    if kind == "union_tag_invalid":
        disc = str(ctx.get("discriminator", "")).strip("'")
        return (f"{key}.{disc}: must be one of {ctx.get('expected_tags')}, "
                f"got {_short(ctx.get('tag'))}")
    msg = err["msg"]
    for prefix in ("Value error, ", "Assertion failed, "):
        if msg.startswith(prefix):
            msg = msg[len(prefix):]
    msg = msg[:1].lower() + msg[1:]
    return f"{key}: {msg}, got {_short(err.get('input'))}".replace("\n", " ")


# --------------------------------------------------------------------- loading
def load_case(path) -> Case:
    """Read and validate a TOML case file (schema, physics and dimensions)."""
    path = Path(path)
    text = read_small_text(path, "case file")
    return case_from_text(text, base_dir=path.resolve().parent, source=str(path))


def case_from_text(text: str, base_dir=None, source: str = "case") -> Case:
    """Validate a case given as TOML text (relative paths from ``base_dir``)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{source}: not valid TOML ({str(exc).splitlines()[0]})") from None
    return case_from_dict(data, base_dir=base_dir, source=source)


def case_from_dict(data: dict, base_dir=None, source: str = "case") -> Case:
    """Validate a case given as a dict (as parsed from TOML)."""
    try:
        case = Case.model_validate(data)
    except ValidationError as exc:
        raise InputError(f"{source}: {_validation_message(exc, data)}") from None
    case._base_dir = Path(base_dir) if base_dir is not None else Path.cwd()
    case._source = source
    try:
        check_case(case)
    except InputError as exc:
        raise InputError(f"{source}: {exc}") from None
    return case


def dump_case(case: Case) -> str:
    """The resolved case as TOML text."""
    import tomli_w  # (deferred: a heavy import, loaded only when used)

    return tomli_w.dumps(case.resolved())


# ------------------------------------------------------------------ semantics
def _need_len(key: str, vec, dim: int):
    if vec is not None and len(vec) != dim:
        raise InputError(f"{key}: expected {dim} components for a {dim}D case, got {vec}")


def _particle_dim(case: Case) -> int:
    p = case.particles
    if p.generator == "none":
        return p.dim
    if p.generator == "lattice":
        return LATTICE_DIM[p.lattice]
    if p.generator == "grid" or (p.generator == "clumps" and p.file is None):
        return len(p.count or [0, 0, 0])
    if p.generator == "clumps":
        return len(read_body_file(case)[0][0])

    path = _case_file("particles.path", p.path, case.particle_file())
    return read_particle_file(path, p.format, p.snapshot).dim


def _case_file(key: str, given: str, path: Path) -> Path:
    """``path`` (the file ``given`` for the key ``key``, resolved against the case
    file's folder) when it is an existing regular file; else an InputError naming the
    key and the value given."""
    reason = not_a_file_reason(path)
    if reason is not None:
        raise InputError(f"{key}: {not_a_file_message(reason)}, got {given!r}")
    return path


def _relative(case: Case, given: str) -> Path:
    path = Path(given).expanduser()
    return path if path.is_absolute() else case.base_dir / path


#: in 2D a body turns only about z: the x and y components of its unit quaternion must
#: be 0 up to this rounding
QUATERNION_2D_TOL = 1.0e-12


def read_body_file(case: Case):
    """The ``particles.file`` of the clumps generator: (positions (B, dim) [L],
    template names (B,), orientations (B, 4) or None). Numbers as in particle files
    (:func:`demstep.io.formats._number`: finite, within the magnitudes); every row has
    as many values as the header; in 2D (no z column) orientations about z only."""
    path = _case_file("particles.file", case.particles.file, _relative(case, case.particles.file))
    with open_text(path, encoding="utf-8-sig", newline="") as fh:  # (read as a stream)
        return _read_bodies(path, csv_rows(fh))


def _read_bodies(path, rows):
    """The body file ``path`` from its CSV ``rows`` (an iterator; read_body_file)."""
    first = next(rows, None)
    if first is None:
        raise InputError(f"particles.file: {path}: empty file")
    header = [h.strip().lower() for h in first]
    axes = ["x", "y", "z"] if "z" in header else ["x", "y"]
    for col in axes + ["template"]:
        if col not in header:
            raise InputError(f"{path}:1: missing column {col!r} (header x,y[,z],template"
                             f"[,qw,qx,qy,qz])")
    quat = [c for c in ("qw", "qx", "qy", "qz") if c in header]
    if quat and len(quat) != 4:
        raise InputError(f"{path}:1: the orientation needs all of qw, qx, qy, qz")
    twice = [c for c in axes + ["template"] + quat if header.count(c) > 1]
    if twice:
        raise InputError(f"{path}:1: column {twice[0]!r} given twice (got {','.join(header)})")
    pos, names, qs, lines = [], [], [], []
    for line, row in enumerate(rows, start=2):
        if not row or all(not c.strip() for c in row):
            continue
        while len(row) > len(header) and not row[-1].strip():
            row = row[:-1]  # (trailing empty cells of a spreadsheet's export)
        if len(row) != len(header):
            raise InputError(f"{path}:{line}: expected {len(header)} values, got {len(row)}")
        pos.append([_number(row[header.index(a)], path, line, a) for a in axes])
        if quat:
            qs.append([_number(row[header.index(c)], path, line, c) for c in quat])
        names.append(row[header.index("template")].strip())
        lines.append(line)
    if not pos:
        raise InputError(f"{path}: no bodies")
    q = None
    if quat:
        q = np.array(qs)
        norms = np.linalg.norm(q, axis=1)
        if not (np.isfinite(norms).all() and (norms > 0).all()):
            k = int(np.flatnonzero(~(np.isfinite(norms) & (norms > 0)))[0])
            raise InputError(f"{path}:{lines[k]}: columns 'qw', 'qx', 'qy', 'qz': the orientation "
                             f"must be a non-zero quaternion, got {qs[k]}")
        q = q / norms[:, None]
        if len(axes) == 2:
            tilted = np.flatnonzero(np.abs(q[:, 1:3]).max(axis=1) > QUATERNION_2D_TOL)
            if len(tilted):
                k = int(tilted[0])
                raise InputError(f"{path}:{lines[k]}: columns 'qx', 'qy': a 2D body turns only "
                                 f"about z (qx = qy = 0), got qx = {qs[k][1]!r}, "
                                 f"qy = {qs[k][2]!r}")
    return np.array(pos), names, q


def clump_templates(case: Case) -> dict:
    """The ``[[clumps]]`` shapes by name (:class:`demstep.clumps.ClumpTemplate`)."""
    out = {}
    for k, spec in enumerate(case.clumps):
        where = f"clumps[{k}]"
        if spec.name in out:
            raise InputError(f"{where}.name: a second template named {spec.name!r}")
        if spec.file is not None:
            if spec.members:
                raise InputError(f"{where}: give members or file, not both")

            data = read_csv(_case_file(f"{where}.file", spec.file, _relative(case, spec.file)))
            centers, radii = data.x, data.r
        else:
            rows = spec.members
            if not rows:
                raise InputError(f"{where}.members: a clump needs at least one member")
            widths = {len(row) for row in rows}
            if len(widths) != 1:
                raise InputError(f"{where}.members: every row needs the same length, got "
                                 f"{sorted(widths)}")
            arr = np.array(rows, dtype=np.float64)
            centers, radii = arr[:, :-1], arr[:, -1]
        try:
            out[spec.name] = ClumpTemplate(spec.name, centers, radii)
        except InputError as exc:
            raise InputError(f"{where}: {exc}") from None
    return out


def feed_items(case: Case) -> list:
    """The case's inserters and outlets (:mod:`demstep.feed`) as (key, item), built and
    checked; an error names the key (``insert[0].region.lower: ...``)."""
    # (deferred: the engine's kernels are a heavy import, loaded only when used)
    from demstep.engine.feed import Inserter, Outlet

    dim = case.dim
    items = []
    for k, spec in enumerate(case.insert):
        key = f"insert[{k}]"
        try:
            region = region_from_spec(spec.region.model_dump(), dim, f"{key}.region",
                                      base_dir=case.base_dir)
            radius = spec.radius if isinstance(spec.radius, float) else \
                spec.radius.model_dump(exclude_none=True)
            dist = distribution_from_spec(radius, dim, f"{key}.radius")
            item = Inserter(spec.name, region, dist, spec.density, rate=spec.rate,
                            mass_rate=spec.mass_rate, fill_to=spec.fill_to, total=spec.total,
                            total_mass=spec.total_mass, start=spec.start,
                            stop=math.inf if spec.stop is None else spec.stop,
                            velocity=spec.velocity, every=spec.every, seed=spec.seed,
                            attempts=spec.attempts)
        except InputError as err:
            text = str(err).replace(f"insert {spec.name!r}", key, 1)
            raise InputError(text if text.startswith(key) else f"{key}.{text}") from None
        items.append((key, item))
    for k, spec in enumerate(case.outlet):
        key = f"outlet[{k}]"
        region = region_from_spec(spec.region.model_dump(), dim, f"{key}.region")
        items.append((key, Outlet(spec.name, region, every=spec.every)))
    return items


def check_case(case: Case) -> None:
    """Cross-field checks the schema cannot express; raises InputError naming the key."""
    p = case.particles
    dim = case.dim
    templates = clump_templates(case)
    if p.generator == "clumps":
        if p.file is None:
            if p.count is None or p.spacing is None or not p.templates:
                raise InputError("particles: the clumps generator needs templates, count and "
                                 "spacing, or a file")
            _need_len("particles.count", p.count, dim)
        else:
            if p.count is not None or p.spacing is not None:
                raise InputError("particles.file: give either a file or count and spacing")
            names = sorted(set(read_body_file(case)[1]))
            p_templates = names
            for name in names:
                if name not in templates:
                    raise InputError(f"particles.file: column 'template': no [[clumps]] template "
                                     f"named {name!r} (have {', '.join(templates) or 'none'})")
        for name in (p.templates if p.file is None else p_templates):
            if name not in templates:
                raise InputError(f"particles.templates: no [[clumps]] template named {name!r} "
                                 f"(have {', '.join(templates) or 'none'})")
            if templates[name].dim != dim:
                raise InputError(f"clumps: template {name!r} is {templates[name].dim}D, the "
                                 f"case {dim}D")
        if p.file is None and (math.prod(p.count) * max(templates[n].n_members for n in p.templates)
                               > MAX_PARTICLES):
            raise InputError(f"particles.count: more than {MAX_PARTICLES} member spheres")
    # particles
    if p.generator == "lattice":
        if isinstance(p.size, list):
            _need_len("particles.size", p.size, dim)

        nb = len(make_lattice(p.lattice, p.radius).basis)
        sizes = p.size if isinstance(p.size, list) else [p.size] * dim
        if nb * math.prod(sizes) > MAX_PARTICLES:
            raise InputError(f"particles.size: more than {MAX_PARTICLES} particles, got {p.size}")
        for key in ("origin", "clip_lower", "clip_upper"):
            _need_len(f"particles.{key}", getattr(p, key), dim)
    elif p.generator == "grid":
        if math.prod(p.count) > MAX_PARTICLES:
            raise InputError(f"particles.count: more than {MAX_PARTICLES} particles, got {p.count}")
        _need_len("particles.origin", p.origin, dim)
        if p.radius_min > p.radius_max:
            raise InputError(f"particles.radius_min: must not exceed radius_max "
                             f"({p.radius_max!r}), got {p.radius_min!r}")
        gap = p.spacing * (1.0 - 2.0 * p.jitter)
        if gap < 2.0 * p.radius_max:
            raise InputError(f"particles.spacing: particles could overlap; need spacing x "
                             f"(1 - 2 jitter) >= 2 radius_max = {2 * p.radius_max:g}, "
                             f"got {p.spacing!r}")
    elif p.generator == "file" and p.density is None:
        if read_particle_file(case.particle_file(), p.format, p.snapshot).m is None:
            raise InputError("particles.density: required (the file has no masses), got nothing")
    if p.fixed is not None:
        _need_len("particles.fixed.lower", p.fixed.lower, dim)
        _need_len("particles.fixed.upper", p.fixed.upper, dim)
        if (p.fixed.lower is None) != (p.fixed.upper is None):
            raise InputError("particles.fixed: give both lower and upper, or neither")
        if p.fixed.lower is not None:
            for k in range(dim):
                if not p.fixed.upper[k] >= p.fixed.lower[k]:
                    raise InputError(f"particles.fixed.upper: must be >= lower {p.fixed.lower} "
                                     f"on every axis, got {p.fixed.upper}")
    if case.bonds is not None and case.bonds.file is not None:
        _case_file("bonds.file", case.bonds.file, case.bond_file())
    # global vectors
    _need_len("gravity", case.gravity, dim)
    if case.periodic is not None and dim == 2 and case.periodic.z is not None:
        raise InputError(f"periodic.z: a 2D case has no z axis, got {case.periodic.z!r}")
    _resolve_timestep("timestep", case.timestep)
    if dim == 2:
        for name in ("twisting_stiffness", "twisting_friction"):
            if getattr(case.contact, name):
                raise InputError(f"contact.{name}: disks do not twist (a 2D case), got "
                                 f"{getattr(case.contact, name)!r}")
    # walls
    names = box_wall_names(dim, case.periodic_axes()) if case.box is not None else []
    if case.box is not None:
        b = case.box
        _need_len("box.lower", b.lower, dim)
        _need_len("box.upper", b.upper, dim)
        if (b.lower is None) != (b.upper is None):
            raise InputError("box: give both lower and upper, or neither (particle extents)")
        if b.lower is not None:
            if b.margin:
                raise InputError(f"box.margin: only used without lower/upper, got {b.margin!r}")
            for k in range(dim):
                if not b.upper[k] > b.lower[k]:
                    raise InputError(f"box.upper: must exceed lower {b.lower} on every axis, "
                                     f"got {b.upper}")
        for wname, motion in b.walls.items():
            if wname not in names:
                raise InputError(f"box.walls.\"{wname}\": no such box wall (have "
                                 f"{', '.join(names)})")
            _check_motion(f'box.walls."{wname}"', motion, WallMotion(), dim, initial=True)
    for k, w in enumerate(case.walls):
        key = f"walls[{k}]"
        if w.name in names:
            raise InputError(f"{key}.name: duplicate wall name, got {w.name!r}")
        names.append(w.name)
        _need_len(f"{key}.point", w.point, dim)
        _need_len(f"{key}.normal", w.normal, dim)
        if not math.hypot(*w.normal) > 0:
            raise InputError(f"{key}.normal: must be non-zero, got {w.normal}")
        _check_motion(key, w, WallMotion(), dim, initial=True)
    # meshes
    if case.meshes and dim != 3:
        raise InputError(f"meshes[0]: triangle meshes bound 3D cases, the case is {dim}D")
    for k, spec in enumerate(case.meshes):
        key = f"meshes[{k}]"
        if spec.name in names:
            raise InputError(f"{key}.name: duplicate wall name, got {spec.name!r}")
        names.append(spec.name)
        _case_file(f"{key}.file", spec.file, case.mesh_file(k))
        for vec in ("velocity", "omega", "center", "surface_velocity"):
            _need_len(f"{key}.{vec}", getattr(spec, vec), 3)
        try:
            parse_transforms(spec.transforms)
        except InputError as err:
            raise InputError(f"{key}.{err}") from None
    # insertion and outflow (each built once: its own checks, errors named by key)
    if p.generator == "none" and not case.insert:
        raise InputError("particles.generator: 'none' starts without particles; add an "
                         "[[insert]] to fill the run")
    if (case.insert or case.outlet) and (p.generator == "clumps" or case.bonds is not None):
        what = "clumps" if p.generator == "clumps" else "bonds"
        key = "insert[0]" if case.insert else "outlet[0]"
        raise InputError(f"{key}: insertion and outlets are not supported with {what}")
    if p.generator == "none" and case.box is not None and case.box.lower is None:
        raise InputError("box: give lower and upper (no particles to take the extents of)")
    feed_names: list[str] = []
    for key, item in feed_items(case):
        if item.name in feed_names:
            raise InputError(f"{key}.name: duplicate insert/outlet name, got {item.name!r}")
        feed_names.append(item.name)
    # stages: replay the wall changes so every stage's resulting state is checked
    state: dict[str, WallMotion] = {}
    for w in case.walls:
        state[w.name] = w
    if case.box is not None:
        for nm in box_wall_names(dim, case.periodic_axes()):
            state[nm] = case.box.walls.get(nm, WallMotion())
    axis_of = {m.name: (None if m.omega is None or not any(m.omega)
                        else np.asarray(m.omega) / np.linalg.norm(m.omega)) for m in case.meshes}
    for k, stage in enumerate(case.stages):
        key = f"stages[{k}]"
        given = [n for n in ("steps", "duration", "until_kinetic_below")
                 if getattr(stage, n) is not None]
        if len(given) != 1:
            raise InputError(f"{key}: give exactly one of steps, duration or "
                             f"until_kinetic_below, got {given or 'none'}")
        if stage.max_steps is not None and stage.until_kinetic_below is None:
            raise InputError(f"{key}.max_steps: only used with until_kinetic_below, "
                             f"got {stage.max_steps!r}")
        if "check_every" in stage.model_fields_set and stage.until_kinetic_below is None:
            raise InputError(f"{key}.check_every: only used with until_kinetic_below, "
                             f"got {stage.check_every!r}")
        _need_len(f"{key}.gravity", stage.gravity, dim)
        if stage.timestep is not None:
            _resolve_timestep(f"{key}.timestep", stage.timestep)
        periodic_axes = [a for a in AXES[:dim]
                         if case.periodic is not None and getattr(case.periodic, a) is not None]
        for axis, change in stage.periodic.items():
            akey = f"{key}.periodic.{axis}" if _BARE_KEY.match(axis) else f'{key}.periodic.{_quoted(axis)}'
            if axis not in periodic_axes:
                raise InputError(f"{akey}: not a periodic axis of the case (periodic: "
                                 f"{', '.join(periodic_axes) or 'none'})")
            if change.motion == "rate" and change.rate is None:
                raise InputError(f"{akey}.rate: required with motion = 'rate'")
            if change.motion == "servo" and change.target_stress is None:
                raise InputError(f"{akey}.target_stress: required with motion = 'servo'")
        for mname, change in stage.meshes.items():
            mkey = f"{key}.meshes.{_quoted(mname)}"
            if mname not in axis_of:
                raise InputError(f"{mkey}: no such mesh (have "
                                 f"{', '.join(axis_of) or 'none'})")
            for vec in ("velocity", "omega", "surface_velocity", "center"):
                _need_len(f"{mkey}.{vec}", getattr(change, vec), 3)
            if change.center is not None and axis_of[mname] is not None:
                raise InputError(f"{mkey}.center: the centre of a mesh that has turned stays "
                                 f"where it is (it may be set until the mesh first turns), "
                                 f"got {change.center}")
            if change.omega is not None and any(change.omega):
                axis = np.asarray(change.omega) / np.linalg.norm(change.omega)
                if axis_of[mname] is not None and not np.allclose(axis, axis_of[mname],
                                                                  rtol=0, atol=1e-12):
                    raise InputError(f"{mkey}.omega: a mesh keeps the axis it turns about "
                                     f"(a new rate about it, or 0), got {change.omega}")
                axis_of[mname] = axis
        for wname, change in stage.walls.items():
            if wname not in state:
                raise InputError(f"{key}.walls.\"{wname}\": no such wall (have "
                                 f"{', '.join(state) or 'none'})")
            state[wname] = _check_motion(f'{key}.walls."{wname}"', change, state[wname], dim,
                                         initial=False)
    for key, _, section, name, reason in _unused_keys(case):
        if name in section.model_fields_set:
            raise InputError(f"{key}: {reason}, got {getattr(section, name)!r}")


#: the keys of a periodic axis' change each motion reads (motion = 'fixed': none)
BOX_MOTION_KEYS = {"rate": ("rate",),
                   "servo": ("target_stress", "servo_gain", "servo_factor", "max_speed")}
#: the keys of a wall's motion each motion reads (friction: every motion)
WALL_MOTION_KEYS = {"velocity": ("velocity",),
                    "servo": ("target_stress", "servo_gain", "servo_factor", "max_speed", "area")}


def _unused_keys(case: Case) -> list:
    """(key, path in :meth:`Case.resolved`, section, field, why) of every key the case's
    choices (contact law, dashpots, file format, clump file, periodic motions) do not
    read, or would add to one given another way. Given, :func:`check_case` refuses it
    (a case that sets it means something it would not get); the resolved case leaves
    out their defaults. (Walls: :func:`_check_motion`; the 'auto' timestep keys:
    :func:`_resolve_timestep`.)"""
    out = []
    c = case.contact
    for value, name, other in (("restitution", "damping_normal", "normal"),
                               ("restitution_tangential", "damping_tangential", "tangential")):
        if getattr(c, value) is not None:
            out.append((f"contact.{name}", ("contact", name), c, name,
                        f"give the {other} dashpot by {value} or by {name}, not both (they "
                        f"would add up; {value} is {getattr(c, value)!r})"))
    if not law_class(c.law).kernels.nonlinear:
        sections = [("timestep", ("timestep",), case.timestep)]
        sections += [(f"stages[{k}].timestep", ("stages", k, "timestep"), st.timestep)
                     for k, st in enumerate(case.stages) if st.timestep is not None]
        for key, path, ts in sections:
            out.append((f"{key}.overlap", path + ("overlap",), ts, "overlap",
                        f"only used with a law whose stiffness depends on the overlap (the "
                        f"{c.law} law's does not)"))
    p = case.particles
    if p.generator == "file":
        fmt = _file_format(case)
        if fmt != "liggghts":
            out.append(("particles.snapshot", ("particles", "snapshot"), p, "snapshot",
                        f"only used with a LIGGGHTS dump (the file is {fmt})"))
    if p.generator == "clumps":
        if p.file is not None:
            out.append(("particles.templates", ("particles", "templates"), p, "templates",
                        "not used with a file (its column 'template' names the template of "
                        "each body)"))
            if read_body_file(case)[2] is not None:
                for name in ("orientation", "seed"):
                    out.append((f"particles.{name}", ("particles", name), p, name,
                                "not used with a file that has the orientation columns qw, "
                                "qx, qy, qz"))
        if p.orientation == "fixed":
            out.append(("particles.seed", ("particles", "seed"), p, "seed",
                        "only used with orientation = 'random'"))
    for k, stage in enumerate(case.stages):
        for axis, change in stage.periodic.items():
            akey = (f"stages[{k}].periodic.{axis}" if _BARE_KEY.match(axis)
                    else f"stages[{k}].periodic.{_quoted(axis)}")
            for motion, names in BOX_MOTION_KEYS.items():
                if change.motion != motion:
                    for name in names:
                        out.append((f"{akey}.{name}", ("stages", k, "periodic", axis, name),
                                    change, name, f"only used with motion = {motion!r} (the "
                                    f"motion is {change.motion!r})"))
    return out


def _file_format(case: Case) -> str:
    """The format of the particle file of ``generator = "file"`` (csv, liggghts, yade)."""
    p = case.particles
    return p.format if p.format != "auto" else detect_format(case.particle_file())


#: the [timestep] keys only the 'auto' mode reads
AUTO_ONLY = ("safety", "method", "every", "growth", "motion")


def _resolve_timestep(key: str, ts: "TimestepSection") -> None:
    """Fill in ``mode`` (and the default alpha) and refuse keys the mode does not use
    (the 'auto' keys without mode = 'auto' too: a case that meant the certified step
    and forgot the mode ran on alpha)."""
    if ts.mode is None:
        ts.mode = "fixed" if ts.dt is not None else "alpha"
    if ts.mode != "auto":
        for name in AUTO_ONLY:
            if name in ts.model_fields_set:
                raise InputError(f"{key}.{name}: only used with mode = 'auto' (the mode is "
                                 f"{ts.mode!r}), got {getattr(ts, name)!r}")
    if ts.mode == "fixed" and ts.dt is None:
        raise InputError(f"{key}.dt: required with mode = 'fixed'")
    if ts.mode == "fixed" and ts.alpha is not None:
        raise InputError(f"{key}.alpha: not used with mode = 'fixed', got {ts.alpha!r}")
    if ts.mode == "alpha":
        if ts.dt is not None:
            raise InputError(f"{key}.dt: not used with mode = 'alpha' (give dt or alpha), "
                             f"got {ts.dt!r}")
        if ts.alpha is None:
            ts.alpha = 0.1
    if ts.mode == "auto":
        for name in ("dt", "alpha"):
            if getattr(ts, name) is not None:
                raise InputError(f"{key}.{name}: not used with mode = 'auto', "
                                 f"got {getattr(ts, name)!r}")


def _merged(before: WallMotion, change: WallMotion) -> WallMotion:
    data = {k: v for k, v in before.model_dump().items() if k in WallMotion.model_fields}
    data.update({k: v for k, v in change.model_dump().items()
                 if v is not None and k in WallMotion.model_fields})
    return WallMotion(**data)


def _check_motion(key: str, change: WallMotion, before: WallMotion, dim: int,
                  initial: bool) -> WallMotion:
    """Check one wall's motion settings (merged over ``before``); returns the merge."""
    _need_len(f"{key}.velocity", change.velocity, dim)
    merged = _merged(before, change)
    motion = merged.motion or "fixed"
    if motion == "velocity" and merged.velocity is None:
        raise InputError(f"{key}.velocity: required with motion = 'velocity'")
    if motion == "velocity" and not initial and change.motion == "velocity" \
            and change.velocity is None:
        raise InputError(f"{key}.velocity: required when motion changes to 'velocity'")
    if motion == "servo":
        if merged.target_stress is None:
            raise InputError(f"{key}.target_stress: required with motion = 'servo'")
    for used_by, names in WALL_MOTION_KEYS.items():
        for name in names:
            if motion != used_by and getattr(change, name) is not None:
                raise InputError(f"{key}.{name}: only used with motion = {used_by!r} (the "
                                 f"motion is {motion!r}), got {getattr(change, name)!r}")
    return merged


