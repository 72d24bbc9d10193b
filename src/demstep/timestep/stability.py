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


def damped_dt(k, c):
    """Critical step of one damped mode of the central-difference scheme whose damping
    force uses the lagged half-step velocity [T] (the engine's and LIGGGHTS' form).

    ``k`` = omega^2 [1/T^2] and ``c`` = 2 zeta omega [1/T] are the mode's stiffness and
    damping per unit mass. The one-step map of x'' + c x' + k x = 0 has trace
    2 - a^2 - 2 zeta a and determinant 1 - 2 zeta a (a = omega dt); its Jury conditions
    give the paper's eq. 28, dt = (2/omega)(sqrt(1 + zeta^2) - zeta), written here as
    dt = 4 / (c + sqrt(c^2 + 4 k)) = 2 / sigma with sigma the larger root of
    sigma^2 - c sigma - k = 0, which stays finite for k = 0 (a damped free particle:
    dt = 2 / c) and c = 0 (dt = 2 / omega, eq. 3).
    """
    k = np.asarray(k, dtype=np.float64)
    c = np.asarray(c, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return 4.0 / (c + np.sqrt(c * c + 4.0 * k))


def damped_sigma(k, c):
    """sigma = (c + sqrt(c^2 + 4 k)) / 2 [1/T], the larger root of sigma^2 - c sigma - k:
    the damped counterpart of omega (dt_crit = 2 / sigma, :func:`damped_dt`)."""
    k = np.asarray(k, dtype=np.float64)
    c = np.asarray(c, dtype=np.float64)
    return 0.5 * (c + np.sqrt(c * c + 4.0 * k))


def rayleigh_damped_dt(dt_undamped, a1: float, a2: float):
    """Critical step with Rayleigh damping C = a1 M + a2 K (paper eqs. 26-28) [T].

    With omega_max = 2 / dt_undamped and damping ratio of the highest mode
    xi = a1 / (2 omega_max) + a2 omega_max / 2, dt = (2 / omega_max)(sqrt(1 + xi^2) - xi)
    (:func:`damped_dt` with c = 2 xi omega = a1 + a2 omega^2). ``a1`` [1/T] and ``a2``
    [T] must be >= 0. The bound holds for the central difference scheme whose damping
    force uses the lagged half-step velocity v(t - dt/2), which is what the demstep
    integrator does for global viscous damping and contact dashpots. The mode with the
    highest frequency is the most restrictive (dt decreases with omega for any a1, a2).
    """
    for name, v in (("rayleigh a1", a1), ("rayleigh a2", a2)):
        if not np.isfinite(v) or v < 0:
            raise InputError(f"{name}: must be a finite number >= 0, got {v!r}")
    omega2 = (2.0 / np.asarray(dt_undamped, dtype=np.float64)) ** 2
    return damped_dt(omega2, a1 + a2 * omega2)


#: the paper's guidance multipliers, which include a safety factor of 0.75
#: (O'Sullivan & Bray 2004, "Generalized equation for stability")
GUIDANCE_ALPHA = {2: 0.3, 3: 0.17}
