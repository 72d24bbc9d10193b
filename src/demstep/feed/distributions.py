"""Radius distributions of inserted particles.

Each distribution draws radii [L] from a numpy ``Generator`` and knows its bounds
(the largest radius sizes the insertion's overlap search and the time step's
densest-packing bound before any inserted particle exists). Fractions are by number
unless ``by = "mass"``: then a class's share of the inserted mass (what a sieve
analysis gives; LIGGGHTS' discrete distributions are by mass), converted to number
fractions by dividing by each class's particle mass (r^3 in 3D, r^2 for disks).

* ``fixed``: one radius;
* ``uniform``: radii uniform in [min, max] by number, or with a uniform mass share
  per radius interval (``by = "mass"``: density proportional to r^-dim);
* ``discrete``: radii with their fractions;
* ``lognormal``: ln r normal with median ``median`` and shape ``sigma`` (by number,
  or the mass-weighted lognormal with ``by = "mass"``: the number median is then
  median exp(-dim sigma^2)), truncated to [min, max] (defaults: median exp(-+3 sigma)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from demstep.errors import InputError


def _positive(what: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = math.nan
    if not (math.isfinite(v) and v > 0):
        raise InputError(f"{what}: must be finite and > 0, got {value!r}")
    return v


@dataclass
class RadiusDistribution:
    """A radius distribution (module docstring): ``kind`` one of fixed, uniform,
    discrete, lognormal; ``radius`` (fixed), ``min``/``max`` (uniform; lognormal's
    truncation), ``radii``/``fractions`` (discrete), ``median``/``sigma`` (lognormal),
    ``by`` 'number' or 'mass', ``dim`` 2 or 3. ``what`` names it in messages."""

    kind: str
    dim: int = 3
    radius: float | None = None
    min: float | None = None
    max: float | None = None
    radii: list = field(default_factory=list)
    fractions: list = field(default_factory=list)
    median: float | None = None
    sigma: float | None = None
    by: str = "number"
    what: str = "radius"

    def __post_init__(self):
        w = self.what
        if self.by not in ("number", "mass"):
            raise InputError(f"{w}.by: expected 'number' or 'mass', got {self.by!r}")
        if self.kind == "fixed":
            self.radius = _positive(f"{w}.radius", self.radius)
            self.min = self.max = self.radius
        elif self.kind == "uniform":
            self.min = _positive(f"{w}.min", self.min)
            self.max = _positive(f"{w}.max", self.max)
            if self.max < self.min:
                raise InputError(f"{w}.max: must be >= min = {self.min:g}, got {self.max!r}")
        elif self.kind == "discrete":
            radii = [_positive(f"{w}.radii[{k}]", r) for k, r in enumerate(self.radii)]
            if not radii:
                raise InputError(f"{w}.radii: give at least one radius, got {self.radii!r}")
            fractions = self.fractions if len(self.fractions) else [1.0] * len(radii)
            if len(fractions) != len(radii):
                raise InputError(f"{w}.fractions: expected {len(radii)} values (one per "
                                 f"radius), got {len(fractions)}")
            for k, f in enumerate(fractions):
                if not (isinstance(f, (int, float)) and math.isfinite(f) and f >= 0):
                    raise InputError(f"{w}.fractions[{k}]: must be finite and >= 0, got {f!r}")
            if sum(fractions) <= 0:
                raise InputError(f"{w}.fractions: must not all be 0, got {list(fractions)}")
            self.radii = radii
            self.fractions = [float(f) for f in fractions]
            self.min, self.max = min(radii), max(radii)
        elif self.kind == "lognormal":
            self.median = _positive(f"{w}.median", self.median)
            self.sigma = _positive(f"{w}.sigma", self.sigma)
            number_median = self.median * (math.exp(-self.dim * self.sigma ** 2)
                                           if self.by == "mass" else 1.0)
            self.min = _positive(f"{w}.min", self.min if self.min is not None
                                 else number_median * math.exp(-3.0 * self.sigma))
            self.max = _positive(f"{w}.max", self.max if self.max is not None
                                 else number_median * math.exp(3.0 * self.sigma))
            if self.max <= self.min:
                raise InputError(f"{w}.max: must be > min = {self.min:g}, got {self.max!r}")
        else:
            raise InputError(f"{w}.distribution: expected fixed, uniform, discrete or "
                             f"lognormal, got {self.kind!r}")

    def number_fractions(self) -> np.ndarray:
        """Discrete: the number fraction of each radius (mass shares divided by the
        classes' particle masses)."""
        f = np.asarray(self.fractions, dtype=np.float64)
        if self.by == "mass":
            f = f / np.asarray(self.radii, dtype=np.float64) ** self.dim
        return f / f.sum()

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` radii [L] drawn by number (a mass-weighted distribution converted)."""
        if self.kind == "fixed":
            return np.full(n, self.radius)
        if self.kind == "discrete":
            return np.asarray(self.radii)[rng.choice(len(self.radii), size=n,
                                                     p=self.number_fractions())]
        if self.kind == "uniform":
            if self.by == "number" or self.min == self.max:
                return rng.uniform(self.min, self.max, n)
            # number density ~ r^-dim on [a, b]: inverse of its distribution function
            u = rng.uniform(0.0, 1.0, n)
            a, b, d = self.min, self.max, self.dim
            p = 1.0 - d
            return (a ** p + u * (b ** p - a ** p)) ** (1.0 / p)
        # lognormal, truncated: inverse transform on the truncated normal of ln r
        from scipy.stats import norm  # (deferred: scipy.stats is a slow import)

        mu = math.log(self.median) - (self.dim * self.sigma ** 2 if self.by == "mass" else 0.0)
        lo = norm.cdf((math.log(self.min) - mu) / self.sigma)
        hi = norm.cdf((math.log(self.max) - mu) / self.sigma)
        u = rng.uniform(lo, hi, n)
        return np.clip(np.exp(mu + self.sigma * norm.ppf(u)), self.min, self.max)

    def mean_volume(self) -> float:
        """The mean particle volume [L^dim] (per unit thickness for disks): the mass
        rate's conversion to a particle count (by sampling once for the continuous
        distributions, from a fixed seed)."""
        unit = math.pi if self.dim == 2 else 4.0 / 3.0 * math.pi
        if self.kind == "fixed":
            return unit * self.radius ** self.dim
        if self.kind == "discrete":
            return float(unit * np.dot(self.number_fractions(),
                                       np.asarray(self.radii) ** self.dim))
        r = self.sample(np.random.default_rng(12345), 200_000)
        return float(unit * np.mean(r ** self.dim))


def distribution_from_spec(spec, dim: int, what: str = "radius") -> RadiusDistribution:
    """A distribution from a number (a fixed radius) or a dict ``{distribution = KIND,
    ...}`` (the keys of :class:`RadiusDistribution`)."""
    if isinstance(spec, (int, float)) and not isinstance(spec, bool):
        return RadiusDistribution("fixed", dim=dim, radius=spec, what=what)
    if not isinstance(spec, dict):
        raise InputError(f"{what}: expected a radius or a table with 'distribution', got "
                         f"{spec!r}")
    spec = dict(spec)
    kind = spec.pop("distribution", None)
    allowed = {"radius", "min", "max", "radii", "fractions", "median", "sigma", "by"}
    for key in spec:
        if key not in allowed:
            raise InputError(f"{what}.{key}: unknown key (expected one of "
                             f"{', '.join(sorted(allowed))})")
    return RadiusDistribution(kind, dim=dim, what=what, **spec)
