"""Material time scales that other DEM codes check the step against (Hertz contacts).

Neither looks at the assembly: they are computed per particle from its material and
size, so they can be far on either side of the real critical step. They are reported
beside it, each marked conservative or not.

* Rayleigh time (the period of a Rayleigh surface wave crossing a particle), as
  LIGGGHTS' ``fix check/timestep/gran`` computes it: T_R = pi r sqrt(rho / G) /
  (0.1631 nu + 0.8766), G = E / (2 (1 + nu)), the minimum over particles. Users step at
  10-30 % of it (EDEM's and LIGGGHTS' documentation suggest 20 %).
* Hertz time (the duration of a Hertzian impact), as the same LIGGGHTS fix computes
  it: T_H = 2.87 (m^2 / (R E*^2 v))^(1/5) with m the particle's mass, R = r / 2, E* the
  effective modulus of the pair and v the impact (largest relative) velocity.
"""

from __future__ import annotations

import numpy as np

#: the usual fractions of the Rayleigh time (EDEM, LIGGGHTS documentation)
RAYLEIGH_FRACTIONS = (0.1, 0.2, 0.3)
#: Rayleigh-wave speed factor fit, c_R / c_S ~ 0.1631 nu + 0.8766
RAYLEIGH_FIT = (0.1631, 0.8766)
#: the constant of the Hertz impact duration (Johnson 1985, as in LIGGGHTS)
HERTZ_TIME_FACTOR = 2.87


def shear_modulus(youngs, poisson):
    """G = E / (2 (1 + nu)) [M/(L T^2)]."""
    return np.asarray(youngs) / (2.0 * (1.0 + np.asarray(poisson)))


def rayleigh_time(radius, density, youngs, poisson) -> float:
    """min over particles of pi r sqrt(rho / G) / (0.1631 nu + 0.8766) [T]; arrays of
    radii [L], densities [M/L^3], Young's moduli [M/(L T^2)] and Poisson's ratios."""
    a, b = RAYLEIGH_FIT
    t = (np.pi * np.asarray(radius) * np.sqrt(np.asarray(density) / shear_modulus(youngs, poisson))
         / (a * np.asarray(poisson) + b))
    return float(np.min(t))


def hertz_time(mass, radius, e_star, velocity: float) -> float:
    """min over particles of 2.87 (m^2 / (R E*^2 v))^(1/5) with R = r / 2 [T]: masses [M],
    radii [L], effective moduli E* [M/(L T^2)], impact velocity ``velocity`` [L/T] > 0."""
    m = np.asarray(mass)
    t = HERTZ_TIME_FACTOR * (m * m / (0.5 * np.asarray(radius) * np.asarray(e_star) ** 2
                                      * float(velocity))) ** 0.2
    return float(np.min(t))
