"""What every contact law shares: the common parameters (friction, dashpots, rolling and
twisting resistance), the law's parameter tuple, and the registry of laws.

A law is one module of this package (:mod:`demstep.contact.laws.linear`, ...). It
defines a :class:`ContactLaw` subclass decorated with :func:`register`, which declares

* ``name``: the value of ``law`` in a case file and of ``demstep dt --model``;
* its own parameters as dataclass fields, each with ``metadata`` giving its unit, its
  meaning and the pydantic type a case file checks it with (:func:`law_field`), and
  ``cli``: the ``demstep dt`` options that set them;
* ``Params``: its parameter tuple (:func:`params_class`: the common fields and its own),
  what the compiled kernels read;
* ``kernels``: its scalar formulas (:class:`LawKernels`): the elastic normal force with
  its tangent stiffness and stored energy, the tangential stiffness, the normal load the
  Coulomb limit scales with, the dashpot factor, the secant factor of the epsd rolling
  stiffness, whether the force reads R*, whether its stiffness depends on the overlap;
* ``stiffness_bound`` (the alpha time step's K_max) and ``validate``.

Nothing outside the law's module names it: the kernels call the generic functions of
:mod:`demstep.contact.laws`, which numba resolves for the law's ``Params`` type when it
compiles a step (one compiled step per law), the case schema and ``demstep dt`` find
laws in :data:`LAWS`.

Sign conventions: for a contact between i and j (or i and a wall), n is the unit normal
from i towards j, delta_n = r_i + r_j - |x_j - x_i| > 0 the overlap; forces are those
acting on j (the wall), i receives the opposite.
"""

from __future__ import annotations

import math
from collections import namedtuple
from dataclasses import dataclass, field, fields, replace
from typing import Callable, ClassVar, NamedTuple

import numpy as np

from demstep.errors import InputError

# rolling-resistance stiffness conventions (Params.roll_mode)
ROLL_NONE = 0
ROLL_BETA = 1
ROLL_EPSD = 2
ROLL_CONVENTIONS = {"beta": ROLL_BETA, "epsd": ROLL_EPSD}

#: the fields every law's Params has, read by the kernels by name: friction ``mu`` and
#: ``mu_wall``, absolute dashpots ``c_n``, ``c_t`` [M/T], dashpot damping ratios
#: ``beta_n``, ``beta_t`` (from restitution), rolling and twisting resistance:
#: ``roll_mode`` (ROLL_NONE, ROLL_BETA, ROLL_EPSD), stiffness factors ``beta_r``,
#: ``beta_w``, friction coefficients ``mu_r``, ``mu_w`` (moment limits mu R* F_n) and
#: the viscous damping ratio ``eta_r``
COMMON_FIELDS = ("mu", "mu_wall", "c_n", "c_t", "beta_n", "beta_t", "roll_mode", "beta_r",
                 "beta_w", "mu_r", "mu_w", "eta_r")


class _ParamsMixin:
    @property
    def has_rolling(self) -> bool:
        return self.roll_mode != ROLL_NONE

    @property
    def has_dashpots(self) -> bool:
        return self.c_n > 0 or self.c_t > 0 or self.beta_n > 0 or self.beta_t > 0


def params_class(name: str, own: tuple, module: str) -> type:
    """The parameter tuple of a law: :data:`COMMON_FIELDS` and the law's ``own`` fields
    (float64 each, 0 by default). A tuple of scalars: loop invariants the compiler
    hoists (an array might alias the arrays the loops write; measured 10x slower). Each
    law's tuple is a type of its own, so numba compiles a step for each law.

    The class must be bound to ``name`` in ``module`` (the law's module): numba's cache
    of compiled steps keys them by their argument types, which name this class by its
    module and name; a class found there matches in the next process, so a run loads the
    compiled steps instead of compiling them again (about 15 s per step kernel)."""
    names = COMMON_FIELDS + tuple(own)
    base = namedtuple(f"_{name}", names, defaults=(0.0,) * len(names))
    base.__module__ = module
    return type(name, (_ParamsMixin, base), {"__slots__": (), "__module__": module})


class LawKernels(NamedTuple):
    """A law's scalar formulas (numba functions, inlined in the compiled loops):

    * ``normal_force(params, delta, r_star) -> (F_n, k_n, energy)``: elastic normal force
      [M L/T^2], tangent stiffness [M/T^2] and stored energy [M L^2/T^2] at overlap
      ``delta`` [L] > 0 and effective radius ``r_star`` [L];
    * ``tangential_stiffness(params, delta, r_star) -> k_t`` [M/T^2];
    * ``coulomb_load(params, f_n) -> N`` [M L/T^2]: the normal load the Coulomb limit
      mu N and the rolling limits mu_r R* N scale with (>= 0), from the elastic force;
    * ``dashpot_factor``: c = factor x beta sqrt(m* k) for a damping ratio beta;
    * ``secant_factor``: the secant normal stiffness F_n / delta over the tangent k_n
      (LIGGGHTS' epsd rolling stiffness takes the secant);
    * ``needs_r_star``: whether the formulas read R*;
    * ``nonlinear``: whether the stiffness depends on the overlap (the 'auto' step then
      covers a contact at the overlap it can reach)."""

    normal_force: Callable
    tangential_stiffness: Callable
    coulomb_load: Callable
    dashpot_factor: float
    secant_factor: float
    needs_r_star: bool
    nonlinear: bool


def law_field(default, unit: str, doc: str, required: bool = True, **bounds):
    """A law parameter: a dataclass field with its ``unit``, its meaning ``doc``, whether
    a case file must give it (``required``; else ``default``, None: derived) and the
    ``bounds`` of its value (gt, ge, lt, le, as pydantic's), which a case file checks."""
    return field(default=default, metadata={"unit": unit, "doc": doc, "required": required,
                                            "bounds": bounds})


def check_number(name, value, minimum=0.0, strict=False, allow_inf=False) -> float:
    """``value`` as a float, or InputError naming ``name``: finite (or +inf with
    ``allow_inf``) and >= ``minimum`` (> with ``strict``)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a number, got {value!r}") from None
    finite = math.isfinite(v) or (allow_inf and v == math.inf)
    if not finite or v < minimum or (strict and v == minimum):
        rel = ">" if strict else ">="
        what = "" if allow_inf else "finite and "
        raise InputError(f"{name}: must be {what}{rel} {minimum:g}, got {value!r}")
    return v


def damping_ratio_from_restitution(e: float) -> float:
    """beta = -ln e / sqrt(pi^2 + ln^2 e): the damping ratio of a linear spring-dashpot
    whose collision has coefficient of restitution e (0 < e <= 1)."""
    if not (0.0 < e <= 1.0):
        raise InputError(f"restitution: must lie in (0, 1], got {e!r}")
    if e == 1.0:
        return 0.0
    ln = math.log(e)
    return -ln / math.sqrt(math.pi**2 + ln**2)


def rolling_inertia(inertia_i, m_i, r_i, inertia_j=None, m_j=None, r_j=None):
    """Equivalent rotational inertia of rolling contacts [M L^2] (arrays or scalars):
    1 / (1/(I_i + m_i r_i^2) + 1/(I_j + m_j r_j^2)); a side with zero inertia and mass
    (a fixed particle: pass zeros) or a wall (j None) adds nothing."""
    def inverse(inertia, m, r):
        a = np.asarray(inertia, dtype=float) + np.asarray(m, dtype=float) * np.asarray(r) ** 2
        return np.where(a > 0, 1.0 / np.where(a > 0, a, 1.0), 0.0)

    inv = inverse(inertia_i, m_i, r_i)
    if inertia_j is not None:
        inv = inv + inverse(inertia_j, m_j, r_j)
    return np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), 0.0)


@dataclass(kw_only=True)
class RollingResistance:
    """The rolling and twisting resistance settings (:mod:`demstep.contact.laws`),
    shared by the engine's laws and ``demstep dt``'s contact model:
    ``rolling_convention`` "beta" or "epsd" (None: none), stiffness factors
    ``rolling_stiffness`` beta_r and ``twisting_stiffness`` beta_w, moment limits
    ``rolling_friction`` mu_r and ``twisting_friction`` mu_w, viscous damping ratio
    ``rolling_damping``."""

    rolling_convention: str | None = None
    rolling_stiffness: float = 0.0
    twisting_stiffness: float = 0.0
    rolling_friction: float = 0.0
    twisting_friction: float = 0.0
    rolling_damping: float = 0.0

    @classmethod
    def field_names(cls) -> tuple:
        return tuple(f.name for f in fields(RollingResistance))

    def rolling_settings(self) -> dict:
        return {name: getattr(self, name) for name in self.field_names()}

    def validate_rolling(self):
        for name in ("rolling_stiffness", "twisting_stiffness", "rolling_friction",
                     "twisting_friction", "rolling_damping"):
            check_number(name, getattr(self, name))
        conv = self.rolling_convention
        if conv is None:
            for name in ("rolling_stiffness", "twisting_stiffness", "rolling_friction",
                         "twisting_friction", "rolling_damping"):
                if getattr(self, name) > 0:
                    raise InputError(f"{name}: given without rolling_convention (\"beta\": "
                                     f"k_r = beta_r k_t R*^2, or \"epsd\": 2.25 k_n mu_r^2 R*^2), "
                                     f"got {name} = {getattr(self, name)!r}")
        elif conv not in ROLL_CONVENTIONS:
            raise InputError(f"rolling_convention: expected one of {sorted(ROLL_CONVENTIONS)}, "
                             f"got {conv!r}")
        elif conv == "beta" and self.rolling_stiffness <= 0 and self.twisting_stiffness <= 0:
            raise InputError("rolling_stiffness: rolling_convention \"beta\" needs a stiffness "
                             f"factor > 0, got {self.rolling_stiffness!r}")
        elif conv == "epsd" and self.rolling_friction <= 0:
            raise InputError("rolling_friction: rolling_convention \"epsd\" needs mu_r > 0 "
                             f"(k_r = 2.25 k_n mu_r^2 R*^2), got {self.rolling_friction!r}")

    def rolling_params(self) -> dict:
        """The rolling fields of a Params tuple."""
        return dict(roll_mode=float(ROLL_CONVENTIONS.get(self.rolling_convention, ROLL_NONE)),
                    beta_r=float(self.rolling_stiffness),
                    beta_w=float(self.twisting_stiffness),
                    mu_r=float(self.rolling_friction), mu_w=float(self.twisting_friction),
                    eta_r=float(self.rolling_damping))


#: the registered laws by name (:func:`register`), in the order they were registered
LAWS: dict[str, type] = {}
#: each law's Params type -> its law class
_BY_PARAMS: dict[type, type] = {}


def register(cls):
    """Class decorator: make the law ``cls`` known by its ``name``."""
    if cls.name in LAWS and LAWS[cls.name] is not cls:
        raise ValueError(f"contact law {cls.name!r} registered twice")
    LAWS[cls.name] = cls
    _BY_PARAMS[cls.Params] = cls
    return cls


def law_class(name: str, key: str = "law") -> type:
    """The registered law called ``name``; InputError naming ``key`` and the known laws."""
    try:
        return LAWS[name]
    except (KeyError, TypeError):
        raise InputError(f"{key}: must be one of {', '.join(LAWS)}, got {name!r}") from None


def law_of_params(params_type: type) -> type:
    """The law whose parameter tuple type is ``params_type``."""
    try:
        return _BY_PARAMS[params_type]
    except KeyError:
        raise TypeError(f"{params_type.__name__}: not the parameters of a registered contact "
                        f"law") from None


@dataclass
class ContactLaw(RollingResistance):
    """A contact law's common parameters: friction ``mu`` (particle-particle),
    ``mu_wall`` (None: same as mu), dashpots by coefficient (``damping_normal``,
    ``damping_tangential`` [M/T]) or by ``restitution`` (normal) and
    ``restitution_tangential``; rolling and twisting resistance
    (:class:`RollingResistance`). Subclasses are the laws (module docstring)."""

    mu: float = 0.0
    mu_wall: float | None = None
    damping_normal: float = 0.0
    damping_tangential: float = 0.0
    restitution: float | None = None
    restitution_tangential: float | None = None

    #: the law's name (case files, ``demstep dt --model``); its parameter tuple type; its
    #: formulas; the ``demstep dt`` options setting its own fields (option: field)
    name: ClassVar[str] = ""
    Params: ClassVar[type] = None
    kernels: ClassVar[LawKernels] = None
    cli: ClassVar[dict] = {}
    #: ``demstep dt``'s default model (one law)
    default: ClassVar[bool] = False
    #: whether the law's parameters are those of the particles' materials (per particle
    #: type in ``demstep dt``: Young's modulus, Poisson's ratio; :meth:`pair_params`)
    uses_materials: ClassVar[bool] = False
    #: how LIGGGHTS' counterpart of the law damps the tangential direction from a
    #: restitution (``demstep dt --convention liggghts``): "c_n" (c_t = c_n), "beta"
    #: (the normal damping ratio on k_t), None (no LIGGGHTS counterpart)
    liggghts_tangential: ClassVar[str | None] = None

    def validate(self):
        check_number("mu", self.mu)
        if self.mu_wall is not None:
            check_number("mu_wall", self.mu_wall)
        check_number("damping_normal", self.damping_normal)
        check_number("damping_tangential", self.damping_tangential)
        for name in ("restitution", "restitution_tangential"):
            v = getattr(self, name)
            if v is not None:
                damping_ratio_from_restitution(check_number(name, v, 0.0, strict=True))
        self.validate_rolling()

    @classmethod
    def own_fields(cls) -> tuple:
        """The law's own parameters (dataclass fields beyond the common ones)."""
        common = {f.name for f in fields(ContactLaw)}
        return tuple(f for f in fields(cls) if f.name not in common)

    def common_params(self) -> dict:
        """The common fields of the Params tuple."""
        return dict(
            mu=float(self.mu), mu_wall=float(self.mu if self.mu_wall is None else self.mu_wall),
            c_n=float(self.damping_normal), c_t=float(self.damping_tangential),
            beta_n=(0.0 if self.restitution is None
                    else damping_ratio_from_restitution(self.restitution)),
            beta_t=(0.0 if self.restitution_tangential is None
                    else damping_ratio_from_restitution(self.restitution_tangential)),
            **self.rolling_params())

    def own_params(self) -> dict:
        """The law's own fields of its Params tuple (the law's formulas read them)."""
        raise NotImplementedError

    @classmethod
    def pair_params(cls, a, b) -> dict:
        """A law with materials (:attr:`uses_materials`): its own Params fields for a
        contact between materials ``a`` and ``b`` (objects with ``youngs`` [M/(L T^2)]
        and ``poisson``)."""
        raise NotImplementedError(f"the {cls.name} law has no materials")

    def wall_params(self, material: dict | None = None, mu: float | None = None):
        """The Params tuple of contacts with a wall of its own ``material`` (a dict of
        the law's own parameters, None: the particles' law unchanged) and friction
        ``mu`` (None: ``mu_wall``). A linear law's stiffnesses are the contact's: the
        wall's values replace the particles'. A law with materials pairs the wall's
        material with the particles' (:meth:`wall_material_params`)."""
        own = {f.name for f in self.own_fields()}
        material = dict(material or {})
        for key, value in material.items():
            if key not in own:
                raise InputError(f"material.{key}: not a parameter of the {self.name} law "
                                 f"(it has {', '.join(sorted(own)) or 'none'})")
        if material and self.uses_materials:
            missing = sorted(own - set(material))
            if missing:
                raise InputError(f"material.{missing[0]}: the {self.name} law pairs the "
                                 f"wall's material with the particles': give it")
            replace(self, **material).validate()
            values = self.wall_material_params(material)
        else:
            values = replace(self, **material).own_params()
        params = self.params()._replace(**values)
        if mu is not None:
            params = params._replace(mu_wall=check_number("mu", mu))
        return params

    def wall_material_params(self, material: dict) -> dict:
        """A law with materials: its own Params fields for contacts of its particles
        with a wall of ``material`` (the law's own parameters)."""
        raise NotImplementedError(f"the {self.name} law has no materials")

    def describe(self) -> str:
        """The law's own parameters in one line."""
        return f"{self.name} " + ", ".join(f"{f.name} = {getattr(self, f.name)!r}"
                                            for f in self.own_fields())

    def params(self):
        """The Params tuple the kernels read (validated first)."""
        self.validate()
        return self.Params(**self.common_params(), **self.own_params())

    @property
    def nonlinear(self) -> bool:
        return self.kernels.nonlinear

    def stiffness_bound(self, r_max: float, overlap: float) -> float:
        """The largest tangent stiffness [M/T^2] of a contact of a particle of radius
        ``r_max`` [L] against a wall at relative overlap ``overlap`` (delta / r)."""
        raise NotImplementedError
