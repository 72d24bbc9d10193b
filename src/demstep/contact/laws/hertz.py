"""Hertz-Mindlin (no slip) contact of one material.

F_n = 4/3 E* sqrt(R*) delta^(3/2) with tangent stiffness k_n = 2 E* sqrt(R* delta) and
stored energy 8/15 E* sqrt(R*) delta^(5/2); tangential stiffness k_t = 8 G* sqrt(R*
delta) (Mindlin & Deresiewicz without micro-slip); 1/E* = 2 (1 - nu^2)/E and
1/G* = 2 (2 - nu)/G for one material; walls are flat (R* = r_i), of the particles'
material unless a wall has its own (mesh walls: then E*, G* pair the two materials). Dashpots c = 2 sqrt(5/6) beta sqrt(m* k) (Tsuji et al. 1992, as LIGGGHTS).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from demstep._numba import njit
from demstep.contact.laws.base import (ContactLaw, LawKernels, check_number, law_field,
                                       params_class, register)
from demstep.errors import InputError

Params = HertzParams = params_class("HertzParams", ("e_star", "g_star"), __name__)


class _Material(NamedTuple):
    youngs: float
    poisson: float


@njit(inline="always")
def normal_force(params, delta, r_star):
    """(F_n, k_n, energy) [M L/T^2, M/T^2, M L^2/T^2] at overlap ``delta`` [L]."""
    e_star = params.e_star
    root = math.sqrt(r_star * delta)
    return (4.0 / 3.0) * e_star * root * delta, 2.0 * e_star * root, \
        (8.0 / 15.0) * e_star * root * delta * delta


@njit(inline="always")
def tangential_stiffness(params, delta, r_star):
    """8 G* sqrt(R* delta) [M/T^2]."""
    return 8.0 * params.g_star * math.sqrt(r_star * delta)


@njit(inline="always")
def coulomb_load(params, f_n):
    """The elastic normal force itself."""
    return f_n


@register
@dataclass
class HertzMindlin(ContactLaw):
    """Hertz normal and Mindlin no-slip tangential contact of one material: Young's
    modulus ``youngs_modulus`` [M/(L T^2)], Poisson's ratio ``poisson_ratio``."""

    youngs_modulus: float = law_field(7.0e10, "M/(L T^2)", "Young's modulus", gt=0)
    poisson_ratio: float = law_field(0.25, "-", "Poisson's ratio", gt=-1, lt=0.5)

    name = "hertz"
    Params = Params
    kernels = LawKernels(normal_force, tangential_stiffness, coulomb_load,
                         dashpot_factor=2.0 * math.sqrt(5.0 / 6.0), secant_factor=2.0 / 3.0,
                         needs_r_star=True, nonlinear=True)
    cli = {"youngs": "youngs_modulus", "poisson": "poisson_ratio"}
    uses_materials = True
    liggghts_tangential = "beta"  # (LIGGGHTS' hertz: the normal damping ratio on k_t)

    def validate(self):
        super().validate()
        check_number("youngs_modulus", self.youngs_modulus, strict=True)
        nu = check_number("poisson_ratio", self.poisson_ratio, -1.0, strict=True)
        if nu >= 0.5:
            raise InputError(f"poisson_ratio: must be < 0.5, got {self.poisson_ratio!r}")

    @property
    def e_star(self) -> float:
        """E* = E / (2 (1 - nu^2)) [M/(L T^2)]: two spheres of this material."""
        return self.youngs_modulus / (2.0 * (1.0 - self.poisson_ratio**2))

    @property
    def g_star(self) -> float:
        """G* = G / (2 (2 - nu)) [M/(L T^2)], G = E / (2 (1 + nu))."""
        shear = self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))
        return shear / (2.0 * (2.0 - self.poisson_ratio))

    def own_params(self) -> dict:
        return dict(e_star=float(self.e_star), g_star=float(self.g_star))

    @classmethod
    def pair_params(cls, a, b) -> dict:
        """E*, G* [M/(L T^2)] of a contact between materials ``a`` and ``b`` (Young's
        moduli ``youngs``, Poisson's ratios ``poisson``), as LIGGGHTS' hertz model builds
        them: 1/E* = (1 - nu_a^2)/E_a + (1 - nu_b^2)/E_b, 1/G* = 2 (2 - nu_a)(1 + nu_a)/E_a
        + 2 (2 - nu_b)(1 + nu_b)/E_b (a wall has the particle's material, R* = r)."""
        e_star = 1.0 / ((1 - a.poisson**2) / a.youngs + (1 - b.poisson**2) / b.youngs)
        g_star = 1.0 / (2 * (2 - a.poisson) * (1 + a.poisson) / a.youngs
                        + 2 * (2 - b.poisson) * (1 + b.poisson) / b.youngs)
        return dict(e_star=float(e_star), g_star=float(g_star))

    def wall_material_params(self, material: dict) -> dict:
        """E*, G* of contacts with a wall of Young's modulus and Poisson's ratio
        ``material`` (:meth:`pair_params` of the particles' material and the wall's)."""
        return self.pair_params(_Material(self.youngs_modulus, self.poisson_ratio),
                                _Material(material["youngs_modulus"],
                                          material["poisson_ratio"]))

    def stiffness_bound(self, r_max: float, overlap: float) -> float:
        """Largest tangent stiffness at relative overlap ``overlap`` (delta / r) of a
        particle of radius r_max against a wall (R* = r_max) [M/T^2]."""
        root = math.sqrt(r_max * overlap * r_max)  # R* = r_max: a wall contact
        return max(2.0 * self.e_star * root, 8.0 * self.g_star * root)
