"""The linear law: F_n = K_n delta_n, and an incremental tangential spring K_s.

Tangent stiffnesses K_n and K_s [M/T^2] at every overlap (a contact starts with them);
the stored energy K_n delta_n^2 / 2; the Coulomb limit mu F_n; dashpots
c = 2 beta sqrt(m* K) from a restitution e (the damping ratio of a linear
spring-dashpot whose collision has that e).
"""

from __future__ import annotations

from dataclasses import dataclass
from demstep._numba import njit
from demstep.contact.laws.base import (ContactLaw, LawKernels, check_number, law_field,
                                       params_class, register)

Params = LinearParams = params_class("LinearParams", ("k_n", "k_s"), __name__)


@njit(inline="always")
def normal_force(params, delta, r_star):
    """(F_n, k_n, energy): K_n delta [M L/T^2], K_n [M/T^2], K_n delta^2 / 2."""
    k = params.k_n
    return k * delta, k, 0.5 * k * delta * delta


@njit(inline="always")
def tangential_stiffness(params, delta, r_star):
    """K_s [M/T^2]."""
    return params.k_s


@njit(inline="always")
def coulomb_load(params, f_n):
    """The elastic normal force itself."""
    return f_n


@register
@dataclass
class LinearSpring(ContactLaw):
    """Linear springs: ``k_n``, ``k_s`` [M/T^2] (k_s defaults to k_n)."""

    k_n: float = law_field(1.0e11, "M/T^2", "normal spring stiffness", gt=0)
    k_s: float | None = law_field(None, "M/T^2", "tangential spring stiffness (default k_n)",
                                  required=False, ge=0)

    name = "linear"
    Params = Params
    kernels = LawKernels(normal_force, tangential_stiffness, coulomb_load, dashpot_factor=2.0,
                         secant_factor=1.0, needs_r_star=False, nonlinear=False)
    cli = {"kn": "k_n", "ks": "k_s"}
    default = True
    liggghts_tangential = "c_n"  # (LIGGGHTS' hooke: c_t = c_n)

    def validate(self):
        super().validate()
        check_number("k_n", self.k_n, strict=True)
        if self.k_s is not None:
            check_number("k_s", self.k_s)

    def own_params(self) -> dict:
        return dict(k_n=float(self.k_n), k_s=float(self.k_n if self.k_s is None else self.k_s))

    def describe(self) -> str:
        return f"linear k_n = {self.k_n:g}, k_t = {self.k_n if self.k_s is None else self.k_s:g}"

    def stiffness_bound(self, r_max: float, overlap: float = 0.0) -> float:
        """Largest spring stiffness the law produces [M/T^2]."""
        return max(self.k_n, self.k_n if self.k_s is None else self.k_s)
