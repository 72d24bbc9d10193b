"""Contact laws: each formula once, as scalar numba functions, plus parameter classes.

Sign conventions (DESIGN.md 1.1). For a contact between i and j (or i and a wall),
n is the unit normal from i towards j, delta_n = r_i + r_j - |x_j - x_i| > 0 the
overlap. Forces are those acting on j (the wall); i receives the opposite.

* Linear: F_n = K_n delta_n; tangential spring dF_t = -K_s du_t with the Coulomb
  limit |F_t| <= mu F_n.
* Hertz-Mindlin (no-slip): F_n = 4/3 E* sqrt(R*) delta^(3/2), tangent stiffnesses
  k_n = 2 E* sqrt(R* delta), k_t = 8 G* sqrt(R* delta) (Mindlin & Deresiewicz without
  micro-slip), 1/E* = 2 (1 - nu^2)/E and 1/G* = 2 (2 - nu)/G for one material;
  walls are rigid-flat of the same material (R* = r_i).

Dashpots: F = -c v_rel on the normal and tangential relative velocity, with c given
directly [M/T] or from a coefficient of restitution e through the damping ratio
beta = -ln e / sqrt(pi^2 + ln^2 e): c = 2 beta sqrt(m* k) (linear) and
c = 2 sqrt(5/6) beta sqrt(m* k_tangent) (Hertz, Tsuji et al. 1992 as in LIGGGHTS).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from demstep._numba import njit
from demstep.errors import InputError

LAW_LINEAR = 0
LAW_HERTZ = 1

class LawParams(NamedTuple):
    """A law's parameters as the kernels read them, by name (float64 each): ``law``
    (LAW_LINEAR or LAW_HERTZ), springs ``k_n``, ``k_s`` [M/T^2], friction ``mu``,
    Hertz moduli ``e_star``, ``g_star`` [M/(L T^2)], absolute dashpots ``c_n``, ``c_t``
    [M/T], dashpot damping ratios ``beta_n``, ``beta_t`` (from restitution) and the
    wall friction ``mu_wall``. A tuple of scalars: loop invariants the compiler hoists
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

    @property
    def has_dashpots(self) -> bool:
        return self.c_n > 0 or self.c_t > 0 or self.beta_n > 0 or self.beta_t > 0

    @classmethod
    def from_array(cls, values) -> "LawParams":
        return cls(*(float(v) for v in values))


# positions in LawParams (checkpoints store it as an array)
P_LAW, P_KN, P_KS, P_MU, P_ESTAR, P_GSTAR, P_CN, P_CT, P_BETA_N, P_BETA_T, P_MU_WALL = range(11)
N_PARAMS = len(LawParams._fields)


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


def _check(name, value, minimum=0.0, strict=False):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a number, got {value!r}") from None
    if not math.isfinite(v) or v < minimum or (strict and v == minimum):
        rel = ">" if strict else ">="
        raise InputError(f"{name}: must be finite and {rel} {minimum:g}, got {value!r}")
    return v


@dataclass
class ContactLaw:
    """Common contact parameters: friction ``mu`` (particle-particle), ``mu_wall``
    (None: same as mu), dashpots by coefficient (``damping_normal``,
    ``damping_tangential`` [M/T]) or by ``restitution`` (normal) and
    ``restitution_tangential``."""

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

    def params(self) -> LawParams:
        self.validate()
        return LawParams(
            law=float(self.law_id), mu=float(self.mu),
            mu_wall=float(self.mu if self.mu_wall is None else self.mu_wall),
            c_n=float(self.damping_normal), c_t=float(self.damping_tangential),
            beta_n=(0.0 if self.restitution is None
                    else damping_ratio_from_restitution(self.restitution)),
            beta_t=(0.0 if self.restitution_tangential is None
                    else damping_ratio_from_restitution(self.restitution_tangential)))


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
