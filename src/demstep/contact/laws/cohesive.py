"""A linear spring with a constant cohesion: F_n = K_n delta_n - f_c while the particles
touch (delta_n > 0), nothing apart.

The attraction f_c [M L/T^2] acts from the first touch to the separation (no pull-off
beyond contact, unlike JKR: a contact opens where the overlap returns to zero). The
stored energy K_n delta^2 / 2 - f_c delta is negative for overlaps below 2 f_c / K_n:
the energy ledger scales the balance by the largest energy held or exchanged, not by
the energy held now (:mod:`demstep.energy`), and the divergence check counts what the
negative stored energy can release. The Coulomb limit and the rolling limits scale
with the repulsive part K_n delta (>= 0), not with F_n, which is negative while the
cohesion wins: friction then still holds the contact. Tangent stiffnesses K_n and K_s
as the linear law's; the time-step analysis uses them (the constant force adds no
stiffness; the pre-stress of a contact pulled in tension is not modelled). Dashpots
c = 2 beta sqrt(m* K) as the linear law's.
"""

from __future__ import annotations

from dataclasses import dataclass
from demstep._numba import njit
from demstep.contact.laws.base import (ContactLaw, LawKernels, check_number, law_field,
                                       params_class, register)

Params = CohesiveParams = params_class("CohesiveParams", ("k_n", "k_s", "cohesion"), __name__)


@njit(inline="always")
def normal_force(params, delta, r_star):
    """(F_n, k_n, energy): K_n delta - f_c [M L/T^2], K_n [M/T^2],
    K_n delta^2 / 2 - f_c delta [M L^2/T^2]."""
    k = params.k_n
    f_c = params.cohesion
    return k * delta - f_c, k, (0.5 * k * delta - f_c) * delta


@njit(inline="always")
def tangential_stiffness(params, delta, r_star):
    """K_s [M/T^2]."""
    return params.k_s


@njit(inline="always")
def coulomb_load(params, f_n):
    """The repulsive part K_n delta = F_n + f_c (>= 0)."""
    return max(f_n + params.cohesion, 0.0)


@register
@dataclass
class CohesiveLinear(ContactLaw):
    """Linear springs ``k_n``, ``k_s`` [M/T^2] (k_s defaults to k_n) with a constant
    attraction ``cohesion`` f_c [M L/T^2] while the particles touch."""

    k_n: float = law_field(1.0e11, "M/T^2", "normal spring stiffness", gt=0)
    k_s: float | None = law_field(None, "M/T^2", "tangential spring stiffness (default k_n)",
                                  required=False, ge=0)
    cohesion: float = law_field(0.0, "M L/T^2", "constant attraction f_c while touching",
                                ge=0)

    name = "cohesive"
    Params = Params
    kernels = LawKernels(normal_force, tangential_stiffness, coulomb_load, dashpot_factor=2.0,
                         secant_factor=1.0, needs_r_star=False, nonlinear=False)
    cli = {"kn": "k_n", "ks": "k_s", "cohesion": "cohesion"}

    def validate(self):
        super().validate()
        check_number("k_n", self.k_n, strict=True)
        if self.k_s is not None:
            check_number("k_s", self.k_s)
        check_number("cohesion", self.cohesion)

    def own_params(self) -> dict:
        return dict(k_n=float(self.k_n), k_s=float(self.k_n if self.k_s is None else self.k_s),
                    cohesion=float(self.cohesion))

    def describe(self) -> str:
        return (f"cohesive linear k_n = {self.k_n:g}, k_t = "
                f"{self.k_n if self.k_s is None else self.k_s:g}, cohesion f_c = {self.cohesion:g}")

    def stiffness_bound(self, r_max: float, overlap: float = 0.0) -> float:
        """Largest spring stiffness the law produces [M/T^2]."""
        return max(self.k_n, self.k_n if self.k_s is None else self.k_s)
