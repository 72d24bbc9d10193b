"""Contact laws: each formula once, as scalar numba functions, plus parameter classes.

Sign conventions (also in docs/time-step-elements.md). For a contact between i and j
(or i and a wall), n is the unit normal from i towards j, delta_n = r_i + r_j -
|x_j - x_i| > 0 the overlap. Forces are those acting on j (the wall); i receives the
opposite.

* Linear: F_n = K_n delta_n; tangential spring dF_t = -K_s du_t with the Coulomb
  limit |F_t| <= mu F_n.
* Hertz-Mindlin (no-slip): F_n = 4/3 E* sqrt(R*) delta^(3/2), tangent stiffnesses
  k_n = 2 E* sqrt(R* delta), k_t = 8 G* sqrt(R* delta) (Mindlin & Deresiewicz without
  micro-slip), 1/E* = 2 (1 - nu^2)/E and 1/G* = 2 (2 - nu)/G for one material;
  walls are rigid-flat of the same material (R* = r_i).

Rolling and twisting resistance (Ai et al. 2011, "type C": elastic-plastic spring with
an optional viscous part), acting on the relative rotation of j w.r.t. i (the rolling
part perpendicular to n, the twisting part along n): incremental moments
dM_r = -k_r dphi_r, dM_w = -k_w dphi_w, limited to mu_r R* F_n and mu_w R* F_n (F_n
the elastic normal force), with viscous moments -c_r omega_r, -c_w omega_w while the
spring sticks (a coefficient mu_r or mu_w of 0 with a stiffness: no limit, an elastic
spring). Stiffness conventions: ``beta`` (default), k_r = beta_r k_t R*^2 and
k_w = beta_w k_t R*^2 (k_t the tangent tangential stiffness; YADE's CohFrictMat uses
alphaKr ks r1 r2; LIGGGHTS' epsd2 is beta_r = 1); ``epsd``, k_r = 2.25 k_n mu_r^2 R*^2
(Iwashita & Oda 1998 as used by LIGGGHTS' epsd model and Ai et al.; k_n the secant
normal stiffness F_n / delta as in LIGGGHTS: 4/3 E* sqrt(R* delta) for Hertz), k_w =
2.25 k_n mu_w^2 R*^2. Viscous coefficients
c = 2 eta sqrt(I_r k) with I_r = 1/(1/(I_i + m_i r_i^2) + 1/(I_j + m_j r_j^2)) (a
wall's term is zero), eta the ``rolling_damping`` ratio. Disks roll about z and do not
twist.

Dashpots: F = -c v_rel on the normal and tangential relative velocity, with c given
directly [M/T] or from a coefficient of restitution e through the damping ratio
beta = -ln e / sqrt(pi^2 + ln^2 e): c = 2 beta sqrt(m* k) (linear) and
c = 2 sqrt(5/6) beta sqrt(m* k_tangent) (Hertz, Tsuji et al. 1992 as in LIGGGHTS).
The tangential dashpot acts while the spring sticks and is scaled down so that spring
plus dashpot stay within the Coulomb limit mu F_n (LIGGGHTS adds it unchecked).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np

from demstep._numba import njit
from demstep.errors import InputError

LAW_LINEAR = 0
LAW_HERTZ = 1

# rolling-resistance stiffness conventions (LawParams.roll_mode)
ROLL_NONE = 0
ROLL_BETA = 1
ROLL_EPSD = 2
ROLL_CONVENTIONS = {"beta": ROLL_BETA, "epsd": ROLL_EPSD}

class LawParams(NamedTuple):
    """A law's parameters as the kernels read them, by name (float64 each): ``law``
    (LAW_LINEAR or LAW_HERTZ), springs ``k_n``, ``k_s`` [M/T^2], friction ``mu``,
    Hertz moduli ``e_star``, ``g_star`` [M/(L T^2)], absolute dashpots ``c_n``, ``c_t``
    [M/T], dashpot damping ratios ``beta_n``, ``beta_t`` (from restitution), the
    wall friction ``mu_wall``; rolling and twisting resistance: ``roll_mode``
    (ROLL_NONE, ROLL_BETA, ROLL_EPSD), stiffness factors ``beta_r``, ``beta_w``,
    friction coefficients ``mu_r``, ``mu_w`` (moment limits mu R* F_n) and the viscous
    damping ratio ``eta_r`` (rolling and twisting). A tuple of scalars: loop invariants the compiler hoists
    (an array might alias the arrays the loops write; measured 10x slower)."""

    law: float = 0.0
    k_n: float = 0.0
    k_s: float = 0.0
    mu: float = 0.0
    e_star: float = 0.0
    g_star: float = 0.0
    c_n: float = 0.0
    c_t: float = 0.0
    beta_n: float = 0.0
    beta_t: float = 0.0
    mu_wall: float = 0.0
    roll_mode: float = 0.0
    beta_r: float = 0.0
    beta_w: float = 0.0
    mu_r: float = 0.0
    mu_w: float = 0.0
    eta_r: float = 0.0

    @property
    def has_rolling(self) -> bool:
        return self.roll_mode != ROLL_NONE

    @property
    def has_dashpots(self) -> bool:
        return self.c_n > 0 or self.c_t > 0 or self.beta_n > 0 or self.beta_t > 0


@njit(inline="always")
def normal_force(law, params, delta, r_star):
    """Elastic normal force F_n [M L/T^2], tangent stiffness k_n [M/T^2] and stored
    energy [M L^2/T^2] at overlap ``delta`` [L] (> 0) and effective radius r_star [L]."""
    if law == LAW_LINEAR:
        k = params.k_n
        return k * delta, k, 0.5 * k * delta * delta
    e_star = params.e_star
    root = math.sqrt(r_star * delta)
    return (4.0 / 3.0) * e_star * root * delta, 2.0 * e_star * root, \
        (8.0 / 15.0) * e_star * root * delta * delta


@njit(inline="always")
def tangential_stiffness(law, params, delta, r_star):
    """Tangential spring stiffness k_t [M/T^2]: K_s (linear) or 8 G* sqrt(R* delta)."""
    if law == LAW_LINEAR:
        return params.k_s
    return 8.0 * params.g_star * math.sqrt(r_star * delta)


@njit(inline="always")
def dashpot_coefficients(law, params, m_star, k_n, k_t):
    """Normal and tangential dashpot coefficients c_n, c_t [M/T]."""
    c_n = params.c_n
    c_t = params.c_t
    factor = 2.0 if law == LAW_LINEAR else 2.0 * math.sqrt(5.0 / 6.0)
    if params.beta_n > 0.0:
        c_n += factor * params.beta_n * math.sqrt(m_star * k_n)
    if params.beta_t > 0.0:
        c_t += factor * params.beta_t * math.sqrt(m_star * k_t)
    return c_n, c_t


@njit(inline="always")
def rolling_coefficients(params, k_n, k_t, r_star, i_star):
    """Rolling and twisting spring stiffnesses k_r, k_w [M L^2/T^2 per rad] and
    viscous coefficients c_r, c_w [M L^2/T] of a contact with tangent stiffnesses k_n,
    k_t [M/T^2], effective radius r_star [L] and equivalent rotational inertia i_star
    [M L^2] (see the module docstring; zeros when the law has no rolling resistance).
    The epsd convention takes the secant normal stiffness F_n / delta, as LIGGGHTS'
    epsd model: k_n for the linear law, 2/3 k_n for Hertz."""
    mode = params.roll_mode
    r2 = r_star * r_star
    if mode == ROLL_BETA:
        k_r = params.beta_r * k_t * r2
        k_w = params.beta_w * k_t * r2
    elif mode == ROLL_EPSD:
        # k_n of LIGGGHTS' epsd: the secant F_n / delta, 2/3 of the tangent for Hertz
        k_sec = (2.0 / 3.0) * k_n if params.law == LAW_HERTZ else k_n
        k_r = 2.25 * k_sec * params.mu_r * params.mu_r * r2
        k_w = 2.25 * k_sec * params.mu_w * params.mu_w * r2
    else:
        return 0.0, 0.0, 0.0, 0.0
    c_r = 0.0
    c_w = 0.0
    if params.eta_r > 0.0:
        c_r = 2.0 * params.eta_r * math.sqrt(i_star * k_r)
        c_w = 2.0 * params.eta_r * math.sqrt(i_star * k_w)
    return k_r, k_w, c_r, c_w


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



@njit
def contact_coefficients(law, params, delta, r_star, m_star):
    """Linearised coefficients of contacts at overlaps ``delta`` (C,) [L]: tangent
    stiffnesses k_n, k_t [M/T^2] and dashpot coefficients c_n, c_t [M/T], from the same
    scalar formulas as the engine's force (the time-step analysis of a state). Contacts
    with delta <= 0 get the coefficients at contact (zero stiffness for Hertz)."""
    c = delta.shape[0]
    k_n = np.empty(c)
    k_t = np.empty(c)
    c_n = np.empty(c)
    c_t = np.empty(c)
    for q in range(c):
        d = max(delta[q], 0.0)
        kn = normal_force(law, params, d, r_star[q])[1]
        kt = tangential_stiffness(law, params, d, r_star[q])
        k_n[q] = kn
        k_t[q] = kt
        c_n[q], c_t[q] = dashpot_coefficients(law, params, m_star[q], kn, kt)
    return k_n, k_t, c_n, c_t


def damping_ratio_from_restitution(e: float) -> float:
    """beta = -ln e / sqrt(pi^2 + ln^2 e): the damping ratio of a linear spring-dashpot
    whose collision has coefficient of restitution e (0 < e <= 1)."""
    if not (0.0 < e <= 1.0):
        raise InputError(f"restitution: must lie in (0, 1], got {e!r}")
    if e == 1.0:
        return 0.0
    ln = math.log(e)
    return -ln / math.sqrt(math.pi**2 + ln**2)


def _check(name, value, minimum=0.0, strict=False, allow_inf=False):
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


@dataclass(kw_only=True)
class RollingResistance:
    """The rolling and twisting resistance settings (module docstring), shared by the
    engine's laws and ``demstep dt``'s contact model: ``rolling_convention`` "beta" or
    "epsd" (None: none), stiffness factors ``rolling_stiffness`` beta_r and
    ``twisting_stiffness`` beta_w, moment limits ``rolling_friction`` mu_r and
    ``twisting_friction`` mu_w, viscous damping ratio ``rolling_damping``."""

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


@dataclass
class ContactLaw(RollingResistance):
    """Common contact parameters: friction ``mu`` (particle-particle), ``mu_wall``
    (None: same as mu), dashpots by coefficient (``damping_normal``,
    ``damping_tangential`` [M/T]) or by ``restitution`` (normal) and
    ``restitution_tangential``. Rolling and twisting resistance (module docstring):
    ``rolling_convention`` "beta" (stiffness factors ``rolling_stiffness`` beta_r and
    ``twisting_stiffness`` beta_w: k = beta k_t R*^2) or "epsd" (k = 2.25 k_n mu^2
    R*^2), moment limits by ``rolling_friction`` mu_r and ``twisting_friction`` mu_w
    (mu R* F_n), viscous damping ratio ``rolling_damping``."""

    mu: float = 0.0
    mu_wall: float | None = None
    damping_normal: float = 0.0
    damping_tangential: float = 0.0
    restitution: float | None = None
    restitution_tangential: float | None = None

    law_id = -1

    def validate(self):
        _check("mu", self.mu)
        if self.mu_wall is not None:
            _check("mu_wall", self.mu_wall)
        _check("damping_normal", self.damping_normal)
        _check("damping_tangential", self.damping_tangential)
        for name in ("restitution", "restitution_tangential"):
            v = getattr(self, name)
            if v is not None:
                damping_ratio_from_restitution(_check(name, v, 0.0, strict=True))
        for name in ("rolling_stiffness", "twisting_stiffness", "rolling_friction",
                     "twisting_friction", "rolling_damping"):
            _check(name, getattr(self, name))
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

    def params(self) -> LawParams:
        self.validate()
        return LawParams(
            law=float(self.law_id), mu=float(self.mu),
            mu_wall=float(self.mu if self.mu_wall is None else self.mu_wall),
            c_n=float(self.damping_normal), c_t=float(self.damping_tangential),
            beta_n=(0.0 if self.restitution is None
                    else damping_ratio_from_restitution(self.restitution)),
            beta_t=(0.0 if self.restitution_tangential is None
                    else damping_ratio_from_restitution(self.restitution_tangential)),
            roll_mode=float(ROLL_CONVENTIONS.get(self.rolling_convention, ROLL_NONE)),
            beta_r=float(self.rolling_stiffness), beta_w=float(self.twisting_stiffness),
            mu_r=float(self.rolling_friction), mu_w=float(self.twisting_friction),
            eta_r=float(self.rolling_damping))


@dataclass
class LinearSpring(ContactLaw):
    """Linear springs: ``k_n``, ``k_s`` [M/T^2] (k_s defaults to k_n)."""

    k_n: float = 1.0e11
    k_s: float | None = None
    law_id = LAW_LINEAR

    def validate(self):
        super().validate()
        _check("k_n", self.k_n, strict=True)
        if self.k_s is not None:
            _check("k_s", self.k_s)

    def params(self) -> LawParams:
        return super().params()._replace(
            k_n=float(self.k_n), k_s=float(self.k_n if self.k_s is None else self.k_s))

    def stiffness_bound(self, r_max: float, overlap: float = 0.0) -> float:
        """Largest spring stiffness the law produces [M/T^2]."""
        return max(self.k_n, self.k_n if self.k_s is None else self.k_s)


@dataclass
class HertzMindlin(ContactLaw):
    """Hertz normal and Mindlin no-slip tangential contact of one material: Young's
    modulus ``youngs_modulus`` [M/(L T^2)], Poisson's ratio ``poisson_ratio``."""

    youngs_modulus: float = 7.0e10
    poisson_ratio: float = 0.25
    law_id = LAW_HERTZ

    def validate(self):
        super().validate()
        _check("youngs_modulus", self.youngs_modulus, strict=True)
        nu = _check("poisson_ratio", self.poisson_ratio, -1.0, strict=True)
        if nu >= 0.5:
            raise InputError(f"poisson_ratio: must be < 0.5, got {self.poisson_ratio!r}")

    @property
    def e_star(self) -> float:
        return self.youngs_modulus / (2.0 * (1.0 - self.poisson_ratio**2))

    @property
    def g_star(self) -> float:
        shear = self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))
        return shear / (2.0 * (2.0 - self.poisson_ratio))

    def params(self) -> LawParams:
        return super().params()._replace(e_star=float(self.e_star), g_star=float(self.g_star))

    def stiffness_bound(self, r_max: float, overlap: float) -> float:
        """Largest tangent stiffness at relative overlap ``overlap`` (delta / r) of a
        particle of radius r_max against a wall (R* = r_max) [M/T^2]."""
        root = math.sqrt(r_max * overlap * r_max)  # R* = r_max: a wall contact
        return max(2.0 * self.e_star * root, 8.0 * self.g_star * root)
