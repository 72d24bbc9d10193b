"""Damping that enters the critical step (beyond the paper's eq. 28), in one place.

The engine (and LIGGGHTS' velocity Verlet) applies damping forces with the lagged
half-step velocity:

    v(n+1/2) = v(n-1/2) + dt M^-1 (-K x(n) - C v(n-1/2)),   x(n+1) = x(n) + dt v(n+1/2),

with C = a1 M + a2 K + C_d: global mass-proportional viscous damping a1 [1/T]
(:class:`GlobalDamping` ``mass``), stiffness-proportional damping a2 [T] (``stiffness``,
the Rayleigh form of eq. 26) and the contact dashpots C_d = sum over contacts of
B^T G B, G = diag(c_n, c_t[, c_t]) acting on the relative velocity of the contact point
(``ContactSet.c_n``/``c_t``). Local (Cundall) damping is not viscous: it scales the
resultant force down and is not part of the linear analysis.

Stability of that scheme (derivation in ``docs/damping.md``): with
P(dt) = M - (dt/2) C - (dt^2/4) K, the quantity
E = u^T (M/dt^2 - C/(2 dt) - K/4) u + y^T K y (u = x(n+1) - x(n), y their mean) does
not grow from step to step, so the scheme is stable while P(dt) is positive definite;
an eigenvalue of the one-step map can reach the unit circle only at -1 (where P is
singular) or on an undamped mode that C does not touch (also at -1). Hence

    dt_crit = 2 / sigma_max,  sigma_max = the largest sigma with
    det(sigma^2 M - sigma C - K) = 0 = max over q of (c_q + sqrt(c_q^2 + 4 k_q)) / 2,

c_q = q^T C q / q^T M q, k_q = q^T K q / q^T M q. For C proportional to K every mode
has its own damping ratio and this is eq. 28 for the fastest mode.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from demstep.errors import InputError


@dataclass(frozen=True)
class GlobalDamping:
    """Damping on every degree of freedom: ``mass`` = a1 [1/T] (force -a1 m v and torque
    -a1 I omega: the engine's global viscous damping, the a1 of Rayleigh damping) and
    ``stiffness`` = a2 [T] (C = a2 K, the a2 of Rayleigh damping)."""

    mass: float = 0.0
    stiffness: float = 0.0

    def __post_init__(self):
        for name, value in (("mass", self.mass), ("stiffness", self.stiffness)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise InputError(f"damping {name}: must be a finite number >= 0, got {value!r}")

    @property
    def active(self) -> bool:
        return self.mass > 0 or self.stiffness > 0

    @classmethod
    def rayleigh(cls, a1: float, a2: float) -> "GlobalDamping":
        return cls(float(a1), float(a2))
