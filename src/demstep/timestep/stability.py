"""Stability of the central difference scheme: the formulas, each written once."""

from __future__ import annotations

import numpy as np

from demstep.errors import InputError


def dt_from_lambda(lambda_max):
    """Critical step dt_crit = 2 / omega_max with omega_max = sqrt(lambda_max) [T]
    (paper eqs. 2 and 3); lambda_max [1/T^2] is the largest eigenvalue of M^-1 K."""
    return 2.0 / np.sqrt(lambda_max)


def lambda_from_dt(dt):
    """Inverse of :func:`dt_from_lambda`: lambda_max = (2 / dt)^2 [1/T^2]."""
    return (2.0 / np.asarray(dt)) ** 2


def alpha_of(dt, m_min: float, k_max: float):
    """The paper's multiplier alpha = dt / sqrt(m_min / K_max) (dimensionless)."""
    return np.asarray(dt) / np.sqrt(m_min / k_max)


def rayleigh_damped_dt(dt_undamped, a1: float, a2: float):
    """Critical step with Rayleigh damping C = a1 M + a2 K (paper eqs. 26-28) [T].

    With omega_max = 2 / dt_undamped and damping ratio of the highest mode
    xi = a1 / (2 omega_max) + a2 omega_max / 2, dt = (2 / omega_max)(sqrt(1 + xi^2) - xi).
    ``a1`` [1/T] and ``a2`` [T] must be >= 0. The bound holds for the central
    difference scheme whose damping force uses the lagged half-step velocity
    v(t - dt/2), which is what the demstep integrator does for global viscous damping.
    """
    for name, v in (("rayleigh a1", a1), ("rayleigh a2", a2)):
        if not np.isfinite(v) or v < 0:
            raise InputError(f"{name}: must be a finite number >= 0, got {v!r}")
    omega = 2.0 / np.asarray(dt_undamped, dtype=np.float64)
    xi = a1 / (2.0 * omega) + a2 * omega / 2.0
    return (2.0 / omega) * (np.sqrt(1.0 + xi * xi) - xi)


#: the paper's guidance multipliers, which include a safety factor of 0.75
#: (O'Sullivan & Bray 2004, "Generalized equation for stability")
GUIDANCE_ALPHA = {2: 0.3, 3: 0.17}
