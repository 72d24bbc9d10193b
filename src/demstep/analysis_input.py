"""What a time-step analysis reads: particles, their contacts with linearised
coefficients, and the damping, from particle files of other codes, lattices, demstep
case files and checkpoints (``demstep dt``).

The contact model turns each contact's geometry into the coefficients of
:class:`~demstep.timestep.contacts.ContactSet`:

* ``linear``: k_n, k_t [M/T^2] given;
* ``hertz``: tangent stiffnesses k_n = 2 E* sqrt(R* delta), k_t = 8 G* sqrt(R* delta)
  at each contact's overlap delta (or at least ``overlap`` x R*), with E*, G* from
  Young's moduli and Poisson's ratios per material, as LIGGGHTS' hertz model builds them
  (1/E* = (1 - nu_i^2)/E_i + (1 - nu_j^2)/E_j, 1/G* = 2 (2 - nu_i)(1 + nu_i)/E_i +
  2 (2 - nu_j)(1 + nu_j)/E_j; a wall has the particle's material, R* = r);

and its dashpots, by absolute coefficients gamma_n, gamma_t [M/T] (LIGGGHTS'
``absolute_damping``) or by a restitution coefficient e, through
beta = -ln e / sqrt(ln^2 e + pi^2), in one of two conventions:

* ``demstep`` (the engine's law): c_n = f beta sqrt(m* k_n), c_t = f beta_t sqrt(m* k_t)
  with beta_t from a tangential restitution (none by default); f = 2 (linear),
  2 sqrt(5/6) (Hertz, Tsuji et al. 1992);
* ``liggghts`` (LIGGGHTS 3.8): Hertz as above with beta_t = beta (``tangential_damping``
  on, its default); linear (``hooke``) c_n = 2 beta sqrt(m* k_n) and c_t = c_n; and the
  lever arm of a particle-wall contact (plane or mesh) is r - delta/2, as LIGGGHTS' surface
  model takes it for the contact point's velocity and the tangential force's torque
  (demstep's engine, and the ``demstep`` convention, take the distance from the centre
  to the contact point, r - delta: with rotation LIGGGHTS' longer arm stiffens the
  roll-and-slip mode of a sphere pressed into a wall, measured 0.24 % on the critical
  step of a packing in a stiff mesh container, docs/validation-meshes.md).

Rolling and twisting resistance (either model, :mod:`demstep.contact.laws`): per
contact k_r, k_w [M L^2/T^2 per rad] by the convention ``beta`` (k = beta k_t R*^2,
k_t the tangent tangential stiffness) or ``epsd`` (k = 2.25 k_n mu^2 R*^2, mu the
rolling or twisting friction, k_n the secant normal stiffness F_n / delta), and
viscous parts c = 2 eta sqrt(I* k) with I* = 1/(1/(I_i + m_i r_i^2) + 1/(I_j + m_j
r_j^2)) (a wall's term is zero).

Every coefficient formula is the engine's (:func:`demstep.contact.laws.contact_coefficients`,
:func:`demstep.contact.laws.rolling_coefficients`); only the LIGGGHTS choices of beta_t
and of the linear c_t are made here.
"""

from __future__ import annotations

import math
import shlex
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from demstep.case import apply_stage, build_simulation, load_case
from demstep.case.stages import create_bonds
from demstep.timestep import contacts as cs
from demstep.contact.laws import (ContactLaw, RollingResistance, contact_coefficients,
                                  damping_ratio_from_restitution, law_class)
from demstep.timestep.contacts import (DEFAULT_CONTACT_TOL, ContactSet, contact_effective_radius,
                                  contact_rolling_inertia, find_contacts)
from demstep.engine.meshes import touching_meshes
from demstep.errors import InputError, magnitude_problem
from demstep.io.checkpoint import load_checkpoint
from demstep.io.formats import read_particle_file
from demstep.io.textfile import not_a_file_message, not_a_file_reason, read_small_text
from demstep.kernels.timestep_kernels import rolling_coefficient_arrays
from demstep.mesh import TriangleMesh, read_mesh
from demstep.packings import SPATIAL_ORDER_MIN, inverse_order, lattice, spatial_order
from demstep.particles import Particles, particle_inertia, particle_mass
from demstep.runner import case_hash, find_checkpoint, read_state
from demstep.timestep.clumps import RigidBodies
from demstep.timestep.damping import GlobalDamping
from demstep.timestep.estimates import Materials
from demstep.walls import Wall

CONVENTIONS = ("demstep", "liggghts")


@dataclass
class Material:
    """Young's modulus [M/(L T^2)], Poisson's ratio, density [M/L^3] (None: from the
    particles' masses) of one particle type."""

    youngs: float
    poisson: float
    density: float | None = None

    def validate(self, where: str = ""):
        """One-line errors naming ``where`` (e.g. "material 2:"; "" for the options)."""
        where = f"{where} " if where else ""
        if not (math.isfinite(self.youngs) and self.youngs > 0):
            raise InputError(f"{where}youngs: must be finite and > 0, got {self.youngs!r}")
        if not (math.isfinite(self.poisson) and -1.0 < self.poisson < 0.5):
            raise InputError(f"{where}poisson: must lie in (-1, 0.5), got {self.poisson!r}")
        if self.density is not None and not (math.isfinite(self.density) and self.density > 0):
            raise InputError(f"{where}density: must be finite and > 0, got {self.density!r}")


@dataclass
class ContactModel(RollingResistance):
    """How contacts become coefficients (module docstring): the contact law ``model``
    (a name of :data:`demstep.contact.laws.LAWS`) with its own ``parameters`` (field
    name: value, e.g. {"k_n": 1e7}), or, for a law whose parameters are the particles'
    materials (Hertz), ``materials``: a particle type -> its :class:`Material` (type 1
    for files without a type column; the key None gives the material of every type).
    Dashpots by restitution or absolute coefficients, in the ``convention`` "demstep"
    or "liggghts". Rolling and twisting resistance as in
    :class:`demstep.contact.laws.ContactLaw`: ``rolling_convention`` ("beta", "epsd" or
    None: none), ``rolling_stiffness`` beta_r, ``twisting_stiffness`` beta_w,
    ``rolling_friction`` mu_r, ``twisting_friction`` mu_w, ``rolling_damping`` eta."""

    model: str = "linear"
    parameters: dict = field(default_factory=dict)
    materials: dict = field(default_factory=dict)
    restitution: float | None = None
    restitution_tangential: float | None = None
    gamma_n: float = 0.0
    gamma_t: float = 0.0
    tangential_damping: bool = True
    convention: str = "demstep"
    overlap: float = 0.0

    @property
    def law_class(self) -> type:
        return law_class(self.model, "model")

    def _law(self, **own) -> ContactLaw:
        """The law with the model's parameters (``own``: a material pair's instead) and
        its common settings, checked (messages name the ``demstep dt`` options)."""
        cls = self.law_class
        law = cls(**(self.parameters if not own else {}), **self.rolling_settings())
        try:
            law.validate()
        except InputError as exc:
            text = str(exc)
            for option, name in cls.cli.items():
                text = text.replace(f"{name}:", f"{option}:", 1) if text.startswith(name) else text
            for name in ROLLING_OPTIONS:
                text = text.replace(name, name.replace("_", "-"))
            raise InputError(text) from None
        return law

    def validate(self):
        cls = self.law_class
        if self.convention not in CONVENTIONS:
            raise InputError(f"convention: must be one of {', '.join(CONVENTIONS)}, got "
                             f"{self.convention!r}")
        if cls.uses_materials:
            if self.parameters:
                raise InputError(f"model: the {cls.name} model takes the materials' "
                                 f"properties, got {sorted(self.parameters)}")
            if not self.materials:
                options = " and ".join(f"--{o}" for o in cls.cli)
                raise InputError(f"{next(iter(cls.cli))}: the {cls.name} model needs both "
                                 f"{options} (or --materials)")
            for t, m in self.materials.items():
                m.validate("" if t is None else f"material {t}:")
        else:
            self._law()
        for name, v in (("restitution", self.restitution),
                        ("restitution-t", self.restitution_tangential)):
            if v is not None and not (math.isfinite(v) and 0.0 < v <= 1.0):
                raise InputError(f"{name}: must lie in (0, 1], got {v!r}")
        _non_negative("gamma-n", self.gamma_n)
        _non_negative("gamma-t", self.gamma_t)
        if self.convention == "liggghts" and cls.liggghts_tangential is None:
            raise InputError(f"convention: the {cls.name} model has no LIGGGHTS counterpart "
                             f"(use --convention demstep)")
        if (self.convention == "liggghts" and self.restitution is not None
                and (self.gamma_n or self.gamma_t)):
            raise InputError("restitution: the liggghts convention takes either --restitution "
                             "or --gamma-n/--gamma-t, not both")
        if self.restitution_tangential is not None and self.convention == "liggghts":
            raise InputError("restitution-t: the liggghts convention damps the tangential "
                             "direction with the normal restitution (use "
                             "--no-tangential-damping to switch it off)")
        if not (math.isfinite(self.overlap) and self.overlap >= 0):
            raise InputError(f"overlap: must be finite and >= 0, got {self.overlap!r}")
        self._rolling_law()

    def _rolling_law(self) -> RollingResistance:
        """The rolling-resistance settings, checked (messages name the options:
        rolling-stiffness, ...)."""
        rolling = RollingResistance(**self.rolling_settings())
        try:
            rolling.validate_rolling()
        except InputError as exc:
            text = str(exc)
            for name in ROLLING_OPTIONS:
                text = text.replace(name, name.replace("_", "-"))
            raise InputError(text) from None
        return rolling

    @property
    def has_rolling(self) -> bool:
        return self.rolling_convention is not None

    def material(self, t) -> Material:
        """The material of particle type ``t``."""
        return self.materials.get(int(t), self.materials.get(None))

    @property
    def _tangential_restitution(self) -> float | None:
        """The tangential restitution that sets a dashpot of its own (the demstep
        convention, as the engine's law: with or without a normal one), else None."""
        return self.restitution_tangential if self.convention == "demstep" else None

    @property
    def damped(self) -> bool:
        et = self._tangential_restitution
        return bool(self.gamma_n or self.gamma_t
                    or (self.restitution is not None and self.restitution < 1.0)
                    or (et is not None and et < 1.0 and self.tangential_damping))

    def describe(self) -> str:
        cls = self.law_class
        if cls.uses_materials:
            mats = "; ".join(("every type" if t is None else f"type {t}")
                             + f": E = {m.youngs:g}, nu = {m.poisson:g}"
                             for t, m in sorted(self.materials.items(), key=lambda kv: kv[0] or 0))
            text = f"{cls.name}: tangent stiffnesses at each overlap ({mats})"
        else:
            text = self._law().describe()
        if self.gamma_n or self.gamma_t:
            text += f"; dashpots gamma_n = {self.gamma_n:g}, gamma_t = {self.gamma_t:g} (absolute)"
        if self.restitution is not None and self.convention == "liggghts":
            tang = ("tangential dashpot " + ("on" if self.tangential_damping else "off"))
            form = ("c_t = c_n" if cls.liggghts_tangential == "c_n" else "c_t from k_t")
            text += (f"; dashpots from restitution {self.restitution:g}, LIGGGHTS "
                     f"convention ({tang}; {form})")
        elif self.restitution is not None or self._tangential_restitution is not None:
            et = self._tangential_restitution
            normal = ("none" if self.restitution is None else f"{self.restitution:g}")
            text += (f"; dashpots from restitution: normal {normal}, tangential "
                     + (f"{et:g}" if et is not None else "none")
                     + (" (added to the absolute ones)" if self.gamma_n or self.gamma_t else "")
                     + ", demstep convention")
        if self.rolling_convention == "beta":
            text += (f"; rolling resistance k_r = {self.rolling_stiffness:g} k_t R*^2, "
                     f"k_w = {self.twisting_stiffness:g} k_t R*^2")
        elif self.rolling_convention == "epsd":
            text += (f"; rolling resistance (epsd) k_r = 2.25 k_n R*^2 x "
                     f"{self.rolling_friction:g}^2, k_w = 2.25 k_n R*^2 x "
                     f"{self.twisting_friction:g}^2")
        if self.rolling_convention is not None and self.rolling_damping:
            text += f", viscous ratio {self.rolling_damping:g}"
        return text

    # -------------------------------------------------------------- coefficients
    def law_params(self, a: Material | None = None, b: Material | None = None):
        """The engine's parameter tuple of the model's law (for a law with materials,
        of a contact between materials ``a`` and ``b``), with the dashpots of the
        model's convention and its rolling resistance."""
        cls = self.law_class
        if cls.uses_materials:
            if a is None:  # (the material of every type, or the first given)
                a = self.materials.get(None) or next(iter(self.materials.values()))
            p = cls.Params(**cls.pair_params(a, a if b is None else b))
        else:
            law = self._law()
            p = cls.Params(**law.own_params())
        p = p._replace(c_n=float(self.gamma_n), c_t=float(self.gamma_t))
        if self.restitution is not None:
            beta = damping_ratio_from_restitution(self.restitution)
            p = p._replace(beta_n=beta)
            # liggghts: the normal ratio on k_t (hertz) or c_t = c_n (hooke, set after)
            if (self.convention == "liggghts" and self.tangential_damping
                    and cls.liggghts_tangential == "beta"):
                p = p._replace(beta_t=beta)
        if self._tangential_restitution is not None:  # (with a normal one or not)
            p = p._replace(beta_t=damping_ratio_from_restitution(self._tangential_restitution))
        if not self.tangential_damping:
            p = p._replace(c_t=0.0, beta_t=0.0)
        if self.has_rolling:
            p = p._replace(**self._rolling_law().rolling_params())
        return p

    def apply(self, contacts: ContactSet, particles: Particles, types: np.ndarray,
              wall_types: dict | None = None) -> ContactSet:
        """Fill the contacts' k_n, k_s, c_n, c_t (and k_r, k_w, c_r, c_w with rolling
        resistance) from the model and the geometry. A wall has the material of the
        particle touching it, or of the type ``wall_types[wall index]`` (a mesh given
        a type, as LIGGGHTS gives a mesh its own atom type)."""
        i, j = contacts.i, contacts.j
        wall = j < 0
        jj = np.where(wall, i, j)
        r_i, r_j = particles.r[i], particles.r[jj]
        r_star = contact_effective_radius(contacts, particles.r)
        dist = np.where(wall, contacts.arm_i, contacts.arm_i + contacts.arm_j)
        delta = np.where(wall, r_i - dist, r_i + r_j - dist)
        delta = np.maximum(delta, self.overlap * r_star)
        inv = np.where(particles.fixed, 0.0, 1.0 / particles.m)
        inv_sum = inv[i] + np.where(wall, 0.0, inv[jj])
        m_star = np.where(inv_sum > 0, 1.0 / np.where(inv_sum > 0, inv_sum, 1.0), particles.m[i])
        out = [np.zeros(contacts.n) for _ in range(8)]
        p = particles
        i_star = (contact_rolling_inertia(contacts, p.r, p.m, p.inertia, ~p.fixed)
                  if self.has_rolling else None)
        cls = self.law_class
        if not cls.uses_materials:  # (one group: views and plain copies, no masks)
            groups = [(slice(None), self.law_params())]
        else:
            ti, tj = types[i], types[jj]
            for w, t in (wall_types or {}).items():
                tj = np.where(wall & (contacts.wall == w), t, tj)
            groups = []
            for a in np.unique(ti):
                for b in np.unique(tj[ti == a]):
                    sel = (ti == a) & (tj == b)
                    groups.append((sel, self.law_params(self.material(a), self.material(b))))
        for sel, params in groups:
            coeffs = contact_coefficients(params, delta[sel], r_star[sel], m_star[sel])
            for k in range(4):
                out[k][sel] = coeffs[k]
            if i_star is not None:
                rolling = rolling_coefficient_arrays(params, coeffs[0], coeffs[1],
                                                     r_star[sel], i_star[sel])
                for k in range(4):
                    out[4 + k][sel] = rolling[k]
        k_n, k_t, c_n, c_t, k_r, k_w, c_r, c_w = out
        if (self.convention == "liggghts" and cls.liggghts_tangential == "c_n"
                and self.restitution is not None):
            c_t = c_n.copy() if self.tangential_damping else np.zeros_like(c_n)
        arm_i = contacts.arm_i
        if self.convention == "liggghts" and wall.any():  # (module docstring)
            arm_i = np.where(wall, r_i - 0.5 * np.maximum(r_i - contacts.arm_i, 0.0), arm_i)
        return ContactSet(contacts.i, contacts.j, contacts.normal, arm_i,
                          contacts.arm_j, k_n, k_t, contacts.wall, c_n, c_t, k_r, k_w, c_r, c_w)


#: the rolling-resistance fields of ContactModel and ContactLaw (option names with '-')
ROLLING_OPTIONS = RollingResistance.field_names()


def with_rolling(contacts: ContactSet, particles: Particles, params) -> ContactSet:
    """The contacts with the law's rolling and twisting springs (``params`` a law's Params tuple):
    :func:`demstep.timestep.contacts.with_rolling` with the particles' own masses and inertias."""
    p = particles
    return cs.with_rolling(contacts, p.r, p.m, p.inertia, ~p.fixed, params)


def effective_moduli(model: ContactModel, a: Material, b: Material) -> tuple[float, float]:
    """E*, G* [M/(L T^2)] of a contact between materials a and b by the model's law
    (module docstring)."""
    moduli = model.law_class.pair_params(a, b)
    return moduli["e_star"], moduli["g_star"]


def _positive(name, v):
    if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
        raise InputError(f"{name}: must be a finite number > 0, got {v!r}")


def _non_negative(name, v):
    if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
        raise InputError(f"{name}: must be a finite number >= 0, got {v!r}")


#: the keys of a [[material]] table of a materials file (type, youngs and poisson required)
MATERIAL_KEYS = ("type", "youngs", "poisson", "density")


def _material_number(where: str, key: str, value) -> float:
    """The number ``value`` of ``key`` in a materials file: a TOML integer or float (not
    a boolean or a string) within the magnitudes every input number must lie in."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{where}: {key} must be a number, got {value!r}")
    value = float(value)
    problem = magnitude_problem(value) if math.isfinite(value) else None
    if problem:
        raise InputError(f"{where}: {key} {problem}, got {value!r}")
    return value


def read_materials(path) -> dict:
    """Materials per particle type from a TOML file::

        [[material]]
        type = 1
        youngs = 7.0e10      # [M/(L T^2)]
        poisson = 0.25
        density = 2500.0     # [M/L^3], optional

    Only ``[[material]]`` tables at the top level, only these keys in them, numbers
    as TOML numbers (not strings, not booleans)."""
    path = Path(path)
    reason = not_a_file_reason(path)
    if reason is not None:
        raise InputError(f"materials: {not_a_file_message(reason)}, got {str(path)!r}")
    try:  # (checked before it is read: a regular text file of bounded size)
        text = read_small_text(path, "materials file", encoding="utf-8-sig")
    except InputError as exc:
        raise InputError(f"materials: {exc}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"materials: {path}: not valid TOML ({exc})") from None
    unknown = sorted(set(data) - {"material"})
    if unknown:
        raise InputError(f"materials: {path}: unknown key {unknown[0]!r} (a materials file holds "
                         f"[[material]] tables only)")
    rows = data.get("material")
    if not isinstance(rows, list) or not rows:
        raise InputError(f"materials: {path}: expected [[material]] tables with type, youngs, "
                         f"poisson")
    out = {}
    for k, row in enumerate(rows):
        where = f"materials: {path}: material {k + 1}"
        if not isinstance(row, dict):
            raise InputError(f"{where}: expected a table")
        unknown = set(row) - set(MATERIAL_KEYS)
        if unknown:
            raise InputError(f"{where}: unknown key {sorted(unknown)[0]!r}")
        for key in ("type", "youngs", "poisson"):
            if key not in row:
                raise InputError(f"{where}: missing key {key!r}")
        t = row["type"]
        if not isinstance(t, int) or isinstance(t, bool) or t < 1:
            raise InputError(f"{where}: type must be an integer >= 1, got {t!r}")
        if t in out:
            raise InputError(f"{where}: type {t} appears twice")
        density = row.get("density")
        mat = Material(_material_number(where, "youngs", row["youngs"]),
                       _material_number(where, "poisson", row["poisson"]),
                       None if density is None else _material_number(where, "density", density))
        mat.validate(f"{where}:")
        out[t] = mat
    return out


# ------------------------------------------------------------------------ inputs
@dataclass
class AnalysisInput:
    """Everything ``estimate_time_steps`` needs, and what was read (``notes``)."""

    particles: Particles
    contacts: ContactSet
    damping: GlobalDamping
    types: np.ndarray
    materials: Materials | None = None
    lattice: object = None
    density: float | None = None
    velocities: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)
    rotation: bool = True  # False: the state's own rotation lock
    simulation: object = None
    bodies: object = None  # RigidBodies of clumps, or None
    #: each particle's id for reports: its file row when a run reordered the particles
    #: (Simulation.source_index), None: its index
    ids: np.ndarray | None = None

    def particle_id(self, k: int) -> int:
        return int(k if self.ids is None else self.ids[k])


def periodic_lengths(box: np.ndarray, periodic: np.ndarray, x: np.ndarray, r: np.ndarray,
                     source: str) -> tuple[list, np.ndarray]:
    """Periodic lengths per axis (None: not periodic) of ``box`` (dim, 2) and the
    positions shifted into [0, L) on periodic axes. A particle outside the box by more
    than its radius, or a box shorter than two diameters, is an input error (particles
    of an MD-style dump may lie outside by less: they are wrapped)."""
    x = x.copy()
    lengths = []
    for a in range(x.shape[1]):
        if not periodic[a]:
            lengths.append(None)
            continue
        lo, hi = box[a]
        length = hi - lo
        if not (length > 4.0 * r.max()):
            raise InputError(f"{source}: box: the periodic length along {'xyz'[a]} ({length:g}) "
                             f"must exceed two particle diameters ({4 * r.max():g})")
        out = (x[:, a] < lo - r) | (x[:, a] > hi + r)
        if out.any():
            p = int(np.flatnonzero(out)[0])
            raise InputError(f"{source}: particle {p} at {'xyz'[a]} = {x[p, a]:g} lies outside "
                             f"the periodic box [{lo:g}, {hi:g}) by more than its radius")
        x[:, a] = np.mod(x[:, a] - lo, length)
        lengths.append(float(length))
    return lengths, x


def make_materials(model: ContactModel, particles: Particles, types: np.ndarray,
                   impact_velocity: float | None) -> Materials | None:
    """Per-particle material data for the rules (a law with materials only)."""
    if not model.law_class.uses_materials:
        return None
    mats = [model.material(t) for t in types]
    volume = (4.0 / 3.0 * np.pi * particles.r**3 if particles.dim == 3 else np.pi * particles.r**2)
    density = np.array([m.density if m.density is not None else np.nan for m in mats])
    density = np.where(np.isnan(density), particles.m / volume, density)
    e_star = np.array([effective_moduli(model, m, m)[0] for m in mats])
    return Materials(np.array([m.youngs for m in mats]), np.array([m.poisson for m in mats]),
                     density, e_star, impact_velocity)


def _impact_velocity(model: ContactModel, given: float | None, velocities) -> float | None:
    """The impact velocity of the Hertz time [L/T]: ``given``, else twice the largest
    particle speed (as LIGGGHTS), None without motion. Given with a model that is not
    Hertz: InputError (the Hertz time is the only estimate that reads it)."""
    if not model.law_class.uses_materials:
        if given is not None:
            raise InputError(f"impact-velocity: only used by the Hertz time of the hertz "
                             f"model; this input's contact model is {model.model}, got {given!r}")
        return None
    if given is None and velocities is not None and len(velocities):
        speed = float(np.linalg.norm(velocities, axis=1).max())
        return 2.0 * speed if speed > 0 else None
    return given


def check_types(model: ContactModel, types: np.ndarray, source: str):
    if not model.law_class.uses_materials:
        return
    missing = sorted(set(int(t) for t in np.unique(types)) - set(model.materials))
    if missing and None not in model.materials:
        raise InputError(f"{source}: column 'type': type {missing[0]} has no material "
                         f"(give it in --materials)")


@dataclass
class MeshInput:
    """A triangle-mesh wall of an analysis: the ``mesh`` and the particle type whose
    material it has (``type``; None: the material of the particle touching it)."""

    mesh: TriangleMesh
    type: int | None = None


def parse_mesh(spec: str) -> MeshInput:
    """A mesh wall written as LIGGGHTS' ``fix mesh/surface`` options: the file, then
    ``type T`` (its material: that of particle type T) and the transforms ``scale s``,
    ``move dx dy dz``, ``rotate axis ax ay az angle deg`` applied on load in order
    (quotes around a file name with spaces)."""
    try:
        words = shlex.split(spec)
    except ValueError as err:
        raise InputError(f"mesh: {err}, got {spec!r}") from None
    if not words:
        raise InputError(f"mesh: expected a mesh file, got {spec!r}")
    path, rest, mesh_type = words[0], [], None
    k = 1
    while k < len(words):
        if words[k] == "type":
            if k + 1 >= len(words) or not words[k + 1].isdigit() or int(words[k + 1]) < 1:
                got = words[k + 1] if k + 1 < len(words) else "nothing"
                raise InputError(f"mesh: type: expected a particle type (an integer >= 1), "
                                 f"got {got!r}")
            mesh_type = int(words[k + 1])
            k += 2
        else:
            rest.append(words[k])
            k += 1
    try:
        mesh = read_mesh(path, " ".join(rest))
    except InputError as err:
        raise InputError(f"mesh: {err}") from None
    return MeshInput(mesh, mesh_type)


def mesh_contacts_of(particles: Particles, meshes, first_wall: int,
                     contact_tol: float) -> ContactSet:
    """The particle-mesh contacts (MeshInput ``meshes``) touching within
    ``contact_tol`` as wall contacts, mesh k numbered wall ``first_wall`` + k: the
    normal towards the closest point of the surface, the arm the distance to it
    (:func:`demstep.engine.meshes.touching_meshes`, the engine's rule)."""
    if particles.dim != 3:
        raise InputError(f"mesh: triangle meshes bound 3D packings, the particles are "
                         f"{particles.dim}D")
    p, mk, normal, dist = touching_meshes([m.mesh for m in meshes], particles.x,
                                          particles.r, contact_tol)
    c = len(p)
    return ContactSet(p, np.full(c, -1), normal, dist, np.zeros(c), np.zeros(c), np.zeros(c),
                      first_wall + mk)


def from_particles(particles: Particles, model: ContactModel, types=None, periodic=None,
                   walls=(), contact_tol: float = DEFAULT_CONTACT_TOL,
                   damping: GlobalDamping | None = None, velocities=None,
                   impact_velocity: float | None = None, source: str = "particles",
                   notes=None, bodies=None, meshes=()) -> AnalysisInput:
    """Contacts from geometry (touching within ``contact_tol``) with the model's
    coefficients; with ``bodies`` (RigidBodies), none within a body; ``meshes``
    (:class:`MeshInput`) numbered as walls after ``walls``."""
    model.validate()
    types = np.ones(particles.n, dtype=np.int64) if types is None else np.asarray(types, np.int64)
    check_types(model, types, source)
    geometry = find_contacts(particles, 1.0, 1.0, contact_tol, walls=walls, periodic=periodic)
    wall_types = {}
    if meshes:
        geometry = ContactSet.concatenate([geometry, mesh_contacts_of(
            particles, meshes, len(walls), contact_tol)])
        for k, m in enumerate(meshes):
            if m.type is not None:
                if not model.law_class.uses_materials:
                    raise InputError(f"mesh: type {m.type}: the {model.law_class.name} law has "
                                     f"no materials (a mesh's contacts take the law's "
                                     f"stiffness)")
                check_types(model, np.array([m.type]), f"mesh {m.mesh.name}")
                wall_types[len(walls) + k] = m.type
    if bodies is not None and bodies.n:
        sb = bodies.sphere_body
        jj = np.maximum(geometry.j, 0)
        geometry = geometry.subset((geometry.j < 0) | (sb[geometry.i] < 0) | (sb[geometry.i] != sb[jj]))
    contacts = model.apply(geometry, particles, types, wall_types)
    impact_velocity = _impact_velocity(model, impact_velocity, velocities)
    out = AnalysisInput(particles, contacts, damping or GlobalDamping(), types,
                        make_materials(model, particles, types, impact_velocity),
                        velocities=velocities, notes=list(notes or []), bodies=bodies)
    out.notes.append("contacts: " + model.describe())
    for m in meshes:
        touching = int(np.count_nonzero(contacts.wall == len(walls) + meshes.index(m)))
        out.notes.append(f"mesh {m.mesh.name}: {len(m.mesh.triangles)} triangles, {touching} "
                         f"contacts" + (f", material of type {m.type}" if m.type else ""))
    if bodies is not None and bodies.n:
        out.notes.append(f"{bodies.n} clumps of {int((bodies.sphere_body >= 0).sum())} "
                         f"member spheres: six degrees of freedom each, the world inertia "
                         f"tensor of each union of members")
    return out


def from_file(path, model: ContactModel, fmt: str = "auto", density: float | None = None,
              box=None, periodic_axes=None, walls=(), contact_tol=DEFAULT_CONTACT_TOL,
              damping=None, impact_velocity=None, snapshot: int = -1,
              meshes=(), lammps_model=None) -> AnalysisInput:
    """A particle file (CSV, LIGGGHTS/LAMMPS dump, YADE text). ``box`` (dim, 2) and
    ``periodic_axes`` (a string of axis letters) override the file's box and flags.
    ``lammps_model`` (a :class:`~demstep.integrations.lammps_model.GranularModel`, with
    ``model`` None): the contacts' springs and dashpots as LAMMPS' ``pair_style
    granular`` computes them (pairs and plane walls; no meshes, no clumps)."""
    path = Path(path)
    data = read_particle_file(path, format=fmt, snapshot=snapshot)
    dim = data.dim
    notes = [f"read {path} ({data.x.shape[0]} particles, {dim}D)"]
    if lammps_model is not None:
        return _from_lammps_model(path, data, lammps_model, density, box, periodic_axes,
                                  walls, damping, notes)
    if data.m is None:
        if density is None and model.law_class.uses_materials and model.materials:
            dens = [m.density for m in model.materials.values()]
            if all(d is not None for d in dens):
                density = None  # per type below
        if density is None and not (model.law_class.uses_materials and _all_densities(model)):
            raise InputError(f"{path}: no mass column: give --density")
    types = data.types if data.types is not None else np.ones(len(data.r), dtype=np.int64)
    check_types(model, types, str(path))
    if data.m is not None:
        m = data.m
        notes.append("masses from the file's mass column")
    elif density is not None:
        m = particle_mass(data.r, density, dim)
    else:
        m = np.array([particle_mass(r, model.material(t).density, dim)
                      for r, t in zip(data.r, types)])
    box_arr, periodic, x, note = _box_and_periodic(path, data, box, periodic_axes)
    notes += note
    bodies = None
    body = data.extra.get("body")
    if body is not None and (body >= 0).any():
        rho = density
        if rho is None:  # the members' own density (a mass column)

            rho = float(np.median(m / particle_mass(data.r, 1.0, dim)))
        bodies = RigidBodies.from_members(x, data.r, body, rho)
        m = m.copy()
        members = bodies.sphere_body >= 0
        m[members] = bodies.mass[bodies.sphere_body[members]]  # contacts' effective masses
    inertia = particle_inertia(m, data.r, dim)
    particles = Particles(x, data.r, m, inertia)
    out = from_particles(particles, model, types, periodic, _walls(walls, box_arr, dim),
                         contact_tol, damping, data.v, impact_velocity, str(path), notes,
                         bodies, meshes)
    if bodies is None and particles.n >= SPATIAL_ORDER_MIN:
        _put_in_spatial_order(out)
    return out


def _box_and_periodic(path, data, box, periodic_axes):
    """The box (dim, 2) or None, the periodic lengths (None: no periodic axis), the
    positions (shifted into the box on periodic axes) and notes of a particle file read
    as ``data``, ``box`` and ``periodic_axes`` overriding the file's."""
    dim = data.dim
    box_arr = data.box
    flags = data.periodic if data.periodic is not None else np.zeros(dim, dtype=bool)
    if box is not None:
        box_arr = np.asarray(box, dtype=np.float64).reshape(-1, 2)
        if box_arr.shape != (dim, 2):
            raise InputError(f"box: expected {2 * dim} numbers (lo hi per axis) for {dim}D, "
                             f"got {box_arr.size}")
        if np.any(box_arr[:, 1] <= box_arr[:, 0]):
            raise InputError(f"box: every hi must exceed its lo, got {box_arr.tolist()}")
    if periodic_axes is not None:
        flags = np.array(["xyz"[a] in periodic_axes for a in range(dim)])
        bad = set(periodic_axes) - set("xyz"[:dim])
        if bad:
            raise InputError(f"periodic: axes must be among {', '.join('xyz'[:dim])}, got "
                             f"{','.join(sorted(bad))}")
    periodic, x, notes = None, data.x, []
    if flags.any():
        if box_arr is None:
            raise InputError(f"periodic: {path} has no box: give --box")
        periodic, x = periodic_lengths(box_arr, flags, x, data.r, str(path))
        notes.append("periodic along " + ", ".join(f"{'xyz'[a]} (L = {periodic[a]:g})"
                                                     for a in range(dim) if periodic[a]))
    return box_arr, periodic, x, notes


def _from_lammps_model(path, data, model, density, box, periodic_axes, walls, damping,
                       notes) -> AnalysisInput:
    """:func:`from_file` with LAMMPS' ``pair_style granular`` contacts
    (:func:`demstep.integrations.lammps_model.lammps_contacts`)."""
    from demstep.integrations.lammps_model import lammps_contacts

    if data.extra.get("body") is not None and (data.extra["body"] > 0).any():
        raise InputError(f"{path}: clumps (a body/mol column) are not certified with "
                         f"--lammps-model")
    if data.m is not None:
        m = data.m
        notes.append("masses from the file's mass column")
    elif density is not None:
        m = particle_mass(data.r, density, data.dim)
    else:
        raise InputError(f"{path}: no mass column: give --density")
    box_arr, periodic, x, note = _box_and_periodic(path, data, box, periodic_axes)
    notes += note
    particles = Particles(x, data.r, m, particle_inertia(m, data.r, data.dim))
    contacts = lammps_contacts(particles, model, periodic, _walls(walls, box_arr, data.dim))
    notes.append(model.describe() + f" ({contacts.n} contacts)")
    types = data.types if data.types is not None else np.ones(len(data.r), dtype=np.int64)
    out = AnalysisInput(particles, contacts, damping if damping is not None else GlobalDamping(),
                        types, velocities=data.v, notes=notes)
    if particles.n >= SPATIAL_ORDER_MIN:
        _put_in_spatial_order(out)
    return out


def _put_in_spatial_order(data: AnalysisInput) -> None:
    """Renumber the particles of ``data`` (read, checked and in contact, named by the
    file's rows in any message so far) in spatial order, the file's row of each kept in
    ``ids`` for the reports: the products of the exact step gather by index (1e5 dense
    spheres in random order: 5.0 s against 1.6 s in spatial order)."""
    p = data.particles
    order = spatial_order(p.x, 2.0 * float(p.r.max()))
    new_index = inverse_order(order)
    data.particles = p.take(order)
    data.contacts = data.contacts.renumbered(new_index)
    data.types = data.types[order]
    if data.velocities is not None:
        data.velocities = data.velocities[order]
    data.ids = order


def _all_densities(model: ContactModel) -> bool:
    return bool(model.materials) and all(m.density is not None for m in model.materials.values())


WALL_NAMES = ("x-", "x+", "y-", "y+", "z-", "z+")


def _walls(specs, box, dim: int) -> list:
    """Walls from specs: a box side ('x-', 'z+', ...: the plane of the box's bound, facing
    in) or 'px,py[,pz]:nx,ny[,nz]' (a point and the normal pointing into the packing)."""
    walls = []
    for spec in specs:
        if isinstance(spec, Wall):
            walls.append(spec)
            continue
        text = str(spec).strip()
        if text in WALL_NAMES[:2 * dim]:
            if box is None:
                raise InputError(f"wall: {text!r} needs a box (--box, or a dump's BOX BOUNDS)")
            a = "xyz".index(text[0])
            point = np.zeros(dim)
            normal = np.zeros(dim)
            point[a] = box[a, 0] if text[1] == "-" else box[a, 1]
            normal[a] = 1.0 if text[1] == "-" else -1.0
            walls.append(Wall(point, normal, name=text))
            continue
        try:
            p_text, n_text = text.split(":")
            point = np.array([float(v) for v in p_text.split(",")])
            normal = np.array([float(v) for v in n_text.split(",")])
        except ValueError:
            raise InputError(f"wall: expected a box side ({', '.join(WALL_NAMES[:2 * dim])}) or "
                             f"'px,py{',pz' if dim == 3 else ''}:nx,ny{',nz' if dim == 3 else ''}',"
                             f" got {text!r}") from None
        if point.shape != (dim,) or normal.shape != (dim,) or not np.isfinite(point).all() \
                or not np.isfinite(normal).all() or np.linalg.norm(normal) == 0:
            raise InputError(f"wall: {text!r}: need {dim} finite coordinates and a non-zero "
                             f"normal")
        walls.append(Wall(point, normal / np.linalg.norm(normal), name=text))
    return walls


def from_lattice(name: str, size: int, radius: float, density: float, model: ContactModel,
                 periodic: bool = False, contact_tol=DEFAULT_CONTACT_TOL, damping=None,
                 impact_velocity=None) -> AnalysisInput:
    lat = lattice(name, radius)
    if periodic:
        x, box = lat.supercell(size)
        lengths = list(box)
    else:
        x = lat.block(size)
        lengths = None
    particles = Particles.from_density(x, np.full(len(x), radius), density)
    out = from_particles(particles, model, None, lengths, (), contact_tol, damping, None,
                         impact_velocity, f"lattice {name}",
                         [f"{name} lattice, {len(x)} particles"
                          + (" (periodic supercell)" if periodic else "")])
    out.lattice = lat
    out.density = density
    return out


def from_simulation(sim, source: str, notes=None,
                    impact_velocity: float | None = None) -> AnalysisInput:
    """The contacts of a Simulation's current state (overlap > 0, walls included) with
    its law's coefficients and its global viscous damping (demstep convention). A
    Hertz law brings its materials (the Rayleigh and Hertz times: the impact velocity
    ``impact_velocity`` [L/T], default twice the largest particle speed)."""
    contacts = sim.contact_set()
    particles = sim.particles_now()
    if not sim.rotation:
        notes = list(notes or []) + ["rotation locked in the simulation"]
    model = model_from_law(sim.law)
    types = np.ones(particles.n, dtype=np.int64)
    materials = make_materials(model, particles, types,
                               _impact_velocity(model, impact_velocity, sim.v[:, :sim.dim]))
    return AnalysisInput(particles, contacts, GlobalDamping(mass=float(sim.damping.viscous)),
                         types, materials,
                         notes=list(notes or []) + [f"contacts of {source}: the engine's law "
                                                    f"({type(sim.law).__name__}, demstep "
                                                    f"convention)"],
                         bodies=sim.rigid_bodies(), ids=getattr(sim, "source_index", None))


def model_from_law(law, overlap: float = 0.0) -> ContactModel:
    """The :class:`ContactModel` (demstep convention) of an engine law."""
    common = dict(restitution=law.restitution, restitution_tangential=law.restitution_tangential,
                  gamma_n=float(law.damping_normal), gamma_t=float(law.damping_tangential),
                  convention="demstep", overlap=overlap)
    common.update(law.rolling_settings())
    own = {f.name: getattr(law, f.name) for f in law.own_fields()}
    if law.uses_materials:
        values = list(own.values())  # (the law's material: Young's modulus, Poisson's ratio)
        return ContactModel(law.name, materials={None: Material(*values)}, **common)
    return ContactModel(law.name, parameters=own, **common)


def from_case(path, stage: int = 1, contact_tol: float = DEFAULT_CONTACT_TOL,
              impact_velocity=None) -> AnalysisInput:
    """A demstep case file at its initial state, with the settings of stage ``stage``
    (1-based) applied: contacts touching within ``contact_tol``, the case's law, walls,
    periodic box and global damping. Touching contacts of a Hertz law are evaluated at
    the case's ``timestep.overlap`` (zero overlap has zero stiffness)."""
    case = load_case(path)
    if not 1 <= stage <= max(1, len(case.stages)):
        raise InputError(f"stage: must lie in [1, {max(1, len(case.stages))}], got {stage}")
    sim = build_simulation(case)
    if case.stages:
        apply_stage(sim, case, stage - 1)
    model = model_from_law(sim.law, overlap=float(case.timestep.overlap))
    periodic = [float(v) if v > 0 else None for v in sim.periodic_len[:sim.dim]]
    notes = [f"case {case.name} ({path}): initial state with stage {stage}'s settings, "
             f"{len(sim.r)} particles, {len(sim.walls)} walls"]
    if not sim.rotation:
        notes.append("rotation locked in the case")
    bond_stage = case.bond_stage()
    if bond_stage is not None and bond_stage < stage - 1:  # bonded at an earlier stage

        create_bonds(sim, case)
    out = from_particles(sim.particles_now(), model, None,
                         periodic if any(v is not None for v in periodic) else None,
                         sim.walls, contact_tol, GlobalDamping(mass=float(sim.damping.viscous)),
                         sim.v[:, :sim.dim], impact_velocity, str(path), notes,
                         sim.rigid_bodies())
    bonds = sim.bond_elements()
    if bonds:  # intact parallel bonds: elements of their own, beside the contacts
        out.contacts = ContactSet.concatenate([out.contacts] + bonds)
        out.notes.append(f"{bonds[0].n} parallel bonds (springs k^b A, bending k_n^b I, "
                         f"twisting k_s^b J)")
    out.rotation = sim.rotation
    out.ids = sim.source_index
    return out


def from_checkpoint(path, case_path=None, impact_velocity=None) -> AnalysisInput:
    """A checkpoint of a demstep run: its actual contacts and overlaps, with the law and
    damping of the stage it was written in. The case is the run folder's resolved
    ``case.toml`` (the checkpoint's folder's parent) unless ``case_path`` is given."""
    sim, case_changed = load_run(path, case_path)
    notes = [f"run state at step {sim.step}, t = {sim.time:g}, dt = {sim.dt:g}"]
    if case_changed:
        given = case_path if case_path is not None else "the run folder's case.toml"
        notes.append(f"case: {given} is not the case that wrote {path} (its law, damping "
                     "and walls are the ones analysed)")
    out = from_simulation(sim, f"checkpoint {path} (step {sim.step})", notes, impact_velocity)
    out.rotation = sim.rotation
    out.simulation = sim
    return out


def load_run(checkpoint, case_path=None):
    """(Simulation, case_changed): a Simulation restored from a checkpoint of a demstep
    run (with the stages that had started applied, as a restart does), and whether the
    case is not the one that wrote the checkpoint."""
    checkpoint = find_checkpoint(checkpoint)
    if case_path is None:
        case_path = checkpoint.resolve().parent.parent / "case.toml"
        if not case_path.is_file():
            raise InputError(f"case: no case.toml in the run folder of {checkpoint}: give --case")
    case = load_case(case_path)
    pos, state = read_state(checkpoint, key="checkpoint")
    sim = build_simulation(case)
    started = pos.stage + 1 if pos.stage_step > 0 else pos.stage
    for k in range(min(started, len(case.stages))):
        apply_stage(sim, case, k, fresh=False)
    load_checkpoint(sim, checkpoint)
    return sim, state.get("case_sha256") != case_hash(case)
