"""Rigid planar walls.

A wall is the plane through ``point`` with unit ``normal`` pointing into the domain
(towards the particles). A particle touches it when the distance from its centre to
the plane is below its radius.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from demstep.errors import InputError


@dataclass
class Wall:
    """A rigid plane. ``velocity`` [L/T] moves it (``motion='velocity'``); a servo wall
    (``motion='servo'``) moves along its normal to hold ``target_stress`` [M/(L T^2)]
    over ``area`` [L^2] (length in 2D; 0: the current box face) with gain
    ``servo_gain`` [L T / M] (0: automatic with ``servo_factor``) and the speed limit
    ``max_speed`` [L/T]. ``friction`` overrides the contact law's wall friction."""

    point: np.ndarray
    normal: np.ndarray
    name: str = "wall"
    motion: str = "fixed"
    velocity: np.ndarray = field(default=None)
    target_stress: float = 0.0
    area: float = 0.0
    servo_gain: float = 0.0
    servo_factor: float = 0.1
    max_speed: float = np.inf
    friction: float | None = None

    def __post_init__(self):
        self.point = np.asarray(self.point, dtype=np.float64).reshape(-1).copy()
        normal = np.asarray(self.normal, dtype=np.float64).reshape(-1)
        if normal.shape != self.point.shape or normal.shape[0] not in (2, 3):
            raise InputError(f"wall {self.name!r}: point and normal must both have 2 or 3 "
                             f"components, got {self.point.tolist()} and {normal.tolist()}")
        length = float(np.linalg.norm(normal))
        if not np.isfinite(length) or length == 0.0 or not np.isfinite(self.point).all():
            raise InputError(f"wall {self.name!r}: normal must be finite and non-zero, "
                             f"got {normal.tolist()}")
        self.normal = normal / length
        if self.velocity is None:
            self.velocity = np.zeros_like(self.point)
        self.velocity = np.asarray(self.velocity, dtype=np.float64).reshape(-1).copy()
        if self.motion not in ("fixed", "velocity", "servo"):
            raise InputError(f"wall {self.name!r}: motion must be fixed, velocity or servo, "
                             f"got {self.motion!r}")
        for key in ("target_stress", "area", "servo_gain", "servo_factor"):
            value = getattr(self, key)
            if not (np.isfinite(value) and value >= 0):
                raise InputError(f"wall {self.name!r}: {key} must be finite and >= 0, got {value!r}")
        if not (self.max_speed > 0):
            raise InputError(f"wall {self.name!r}: max_speed must be > 0, got {self.max_speed!r}")
        if self.friction is not None and not (np.isfinite(self.friction) and self.friction >= 0):
            raise InputError(f"wall {self.name!r}: friction must be finite and >= 0, got {self.friction!r}")

    @property
    def dim(self) -> int:
        return self.point.shape[0]

    def distance(self, x: np.ndarray) -> np.ndarray:
        """Signed distance [L] of points x (N, dim) from the plane (positive inside)."""
        return (np.asarray(x) - self.point) @ self.normal


def box_walls(lower, upper, names=None) -> list[Wall]:
    """The 2*dim fixed walls of the axis-aligned box [lower, upper], normals inward.

    Names are x-, x+, y-, y+[, z-, z+] unless given."""
    lower = np.asarray(lower, dtype=np.float64)
    upper = np.asarray(upper, dtype=np.float64)
    dim = lower.shape[0]
    if np.any(upper <= lower):
        raise InputError(f"box: upper corner {upper.tolist()} must exceed lower {lower.tolist()}")
    walls = []
    axes = "xyz"
    for k in range(dim):
        e = np.zeros(dim)
        e[k] = 1.0
        walls.append(Wall(lower.copy(), e, name=f"{axes[k]}-"))
        p = lower.copy()
        p[k] = upper[k]
        walls.append(Wall(p, -e, name=f"{axes[k]}+"))
    if names is not None:
        for w, nm in zip(walls, names):
            w.name = nm
    return walls
