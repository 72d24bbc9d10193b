"""Particle state: rigid disks (2D) and spheres (3D) as a structure of arrays.

Units are any consistent set (the paper uses M, L, T). In 2D a disk's mass and
moment of inertia are per unit thickness.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from demstep.errors import InputError

#: moment of inertia factor I = factor * m r^2 (disk: 1/2, solid sphere: 2/5)
INERTIA_FACTOR = {2: 0.5, 3: 0.4}


def particle_mass(radius, density, dim: int):
    """Mass of disks (per unit thickness, rho pi r^2) or spheres (rho 4/3 pi r^3) [M]."""
    radius = np.asarray(radius, dtype=np.float64)
    if dim == 2:
        return density * np.pi * radius**2
    if dim == 3:
        return density * (4.0 / 3.0) * np.pi * radius**3
    raise InputError(f"dim must be 2 or 3, got {dim!r}")


def particle_inertia(mass, radius, dim: int):
    """Moment of inertia about a centroidal axis [M L^2]: disk m r^2/2, sphere 2/5 m r^2."""
    return INERTIA_FACTOR[dim] * np.asarray(mass, dtype=np.float64) * np.asarray(radius) ** 2


@dataclass
class Particles:
    """Positions ``x`` (N, dim) [L], radii ``r`` (N,) [L], masses ``m`` (N,) [M] and
    moments of inertia ``inertia`` (N,) [M L^2]; ``fixed`` (N,) bool marks particles
    held in place (infinite mass for the dynamics and the time-step analysis)."""

    x: np.ndarray
    r: np.ndarray
    m: np.ndarray
    inertia: np.ndarray
    fixed: np.ndarray = field(default=None)

    def __post_init__(self):
        self.x = np.ascontiguousarray(self.x, dtype=np.float64)
        self.r = np.ascontiguousarray(self.r, dtype=np.float64).reshape(-1)
        self.m = np.ascontiguousarray(self.m, dtype=np.float64).reshape(-1)
        self.inertia = np.ascontiguousarray(self.inertia, dtype=np.float64).reshape(-1)
        if self.fixed is None:
            self.fixed = np.zeros(len(self.r), dtype=bool)
        self.fixed = np.ascontiguousarray(self.fixed, dtype=bool).reshape(-1)
        validate_particles(self.x, self.r, self.m, self.inertia)
        if self.fixed.shape != self.r.shape:
            raise InputError(f"fixed: expected {len(self.r)} flags, got {self.fixed.shape[0]}")

    @classmethod
    def checked_already(cls, x, r, m, inertia, fixed) -> "Particles":
        """Particles of float64 arrays (and a bool ``fixed``) that were validated when
        they entered (a simulation's own state), taken as they are: no copies, no
        checks (1.5 ms at 1e5 particles, per time-step estimate of an 'auto' run)."""
        particles = object.__new__(cls)
        particles.x, particles.r, particles.m = x, r, m
        particles.inertia, particles.fixed = inertia, fixed
        return particles

    @classmethod
    def empty(cls, dim: int = 3) -> "Particles":
        """No particles, in ``dim`` dimensions: a run that fills by insertion
        (:mod:`demstep.feed`)."""
        if dim not in (2, 3):
            raise InputError(f"dim must be 2 or 3, got {dim!r}")
        return cls.checked_already(np.zeros((0, dim)), np.zeros(0), np.zeros(0), np.zeros(0),
                                   np.zeros(0, dtype=bool))

    @classmethod
    def from_density(cls, x, r, density: float, fixed=None) -> "Particles":
        """Particles of uniform ``density`` [M/L^3 in 3D, M/L^2 in 2D]."""
        x = np.asarray(x, dtype=np.float64)
        r = np.asarray(r, dtype=np.float64).reshape(-1)
        if x.ndim != 2 or x.shape[1] not in (2, 3):
            raise InputError(f"x: expected an (N, 2) or (N, 3) array, got shape {x.shape}")
        check_positive("density", density)
        validate_particles(x, r, None, None)
        dim = x.shape[1]
        with np.errstate(over="ignore", under="ignore", invalid="ignore"):
            m = particle_mass(r, density, dim)
            inertia = particle_inertia(m, r, dim)
        bad = ~(np.isfinite(m) & (m > 0) & np.isfinite(inertia) & (inertia > 0))
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise InputError(f"density: {density!r} with radius {r[k]:.3g} (particle {k}) "
                             f"gives a mass of {m[k]:.3g} and a moment of inertia of "
                             f"{inertia[k]:.3g}: not finite and positive")
        return cls(x=x, r=r, m=m, inertia=inertia, fixed=fixed)

    @property
    def dim(self) -> int:
        return self.x.shape[1]

    @property
    def n(self) -> int:
        return self.x.shape[0]

    def take(self, order) -> "Particles":
        """The particles in the order ``order`` (each new row's old row)."""
        return Particles(self.x[order], self.r[order], self.m[order], self.inertia[order],
                         self.fixed[order])

    def copy(self) -> "Particles":
        return Particles(self.x.copy(), self.r.copy(), self.m.copy(), self.inertia.copy(),
                         self.fixed.copy())


def check_positive(name: str, value) -> float:
    """Return ``value`` as float or raise InputError naming ``name`` if not finite > 0."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a positive number, got {value!r}") from None
    if not np.isfinite(v) or v <= 0.0:
        raise InputError(f"{name}: must be a finite positive number, got {value!r}")
    return v


def _first_bad(name: str, values: np.ndarray, bad: np.ndarray, what: str):
    k = int(np.flatnonzero(bad)[0])
    raise InputError(f"{name}: {what} at row {k}, got {values.reshape(len(values), -1)[k].tolist()}")


def validate_particles(x, r, m, inertia) -> None:
    """Raise InputError on shapes that disagree, non-finite values or radii/masses <= 0."""
    x = np.asarray(x)
    r = np.asarray(r)
    if x.ndim != 2 or x.shape[1] not in (2, 3):
        raise InputError(f"x: expected an (N, 2) or (N, 3) array, got shape {x.shape}")
    if r.shape != (x.shape[0],):
        raise InputError(f"r: expected {x.shape[0]} radii, got shape {r.shape}")
    if x.shape[0] == 0:
        raise InputError("particles: the assembly is empty")
    bad = ~np.isfinite(x).all(axis=1)
    if bad.any():
        _first_bad("x", x, bad, "non-finite coordinate")
    bad = ~np.isfinite(r)
    if bad.any():
        _first_bad("r", r, bad, "non-finite radius")
    bad = r <= 0
    if bad.any():
        _first_bad("r", r, bad, "radius must be > 0")
    for name, arr in (("m", m), ("inertia", inertia)):
        if arr is None:
            continue
        arr = np.asarray(arr)
        if arr.shape != r.shape:
            raise InputError(f"{name}: expected {len(r)} values, got shape {arr.shape}")
        bad = ~np.isfinite(arr) | (arr <= 0)
        if bad.any():
            _first_bad(name, arr, bad, "must be finite and > 0")
