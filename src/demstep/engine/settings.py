"""How a Simulation steps: its time-step control (:class:`TimeStep`) and its global
damping (:class:`Damping`), as users and case files give them."""

from __future__ import annotations

import math
from dataclasses import dataclass

from demstep.errors import InputError


@dataclass
class Damping:
    """Local non-viscous (Cundall) damping coefficient ``local`` (0 <= local < 1) and
    global mass-proportional viscous damping ``viscous`` = a1 [1/T] (force -a1 m v,
    torque -a1 I omega, on the lagged half-step velocity: eq. 28 applies)."""

    local: float = 0.0
    viscous: float = 0.0

    def validate(self):
        if not (0.0 <= self.local < 1.0):
            raise InputError(f"damping local: must lie in [0, 1), got {self.local!r}")
        if not (math.isfinite(self.viscous) and self.viscous >= 0.0):
            raise InputError(f"damping viscous: must be finite and >= 0, got {self.viscous!r}")


@dataclass
class TimeStep:
    """How dt is chosen.

    * ``mode='fixed'``: ``dt`` [T].
    * ``mode='alpha'``: dt = ``alpha`` sqrt(m_min / K_max) (the paper's multiplier; for
      Hertz K_max is the tangent stiffness at relative overlap ``overlap``).
    * ``mode='auto'``: dt = ``safety`` x the certified critical step by ``method``
      (``exact`` or ``element-coupled``) of every contact that can close before the
      next estimate (with local damping also x 1 / sqrt(1 + local), which stiffens
      the fastest mode), re-evaluated every ``every`` steps; growth is capped at ``growth``
      per update, decreases are immediate. Before contacts form, the coupled element
      bound of the densest packing (hex/FCC) is used. Between estimates the
      certificate follows contacts that close outside it and the turning of the
      normals (:mod:`demstep.timestep.certificate`); a scheduled 'exact' estimate keeps
      it, without a new solve, while it is within ``Simulation.AUTO_REFRESH_RTOL``
      (1 %) of the last critical mode's Rayleigh quotient. No exact solve either where
      it could not change dt: while the growth cap (or, for an estimate forced by a
      new contact, the rule that it only lowers dt) holds dt at or below ``safety`` x
      the kept certificate's step or the contacts' coupled element bound, that bound
      is the estimate (both are lower bounds on the exact step).
      The step taken is also held where no particle moves more than ``motion`` of its
      radius in a step (at its speed in the last step; before the first, at its
      initial velocity), as LAMMPS' ``fix dt/reset`` limits the distance per step: a
      free fall at the certified step of soft contacts would move particles by a large
      part of their radius per step (resolving contacts late, and stopped by the
      ``jump_limit`` divergence check). The certified step (:attr:`Simulation.dt_certified`)
      is the ceiling; the step returns to it as the motion slows.
    """

    mode: str = "alpha"
    dt: float | None = None
    alpha: float = 0.1
    safety: float = 0.8
    method: str = "exact"
    every: int = 500
    growth: float = 0.05
    overlap: float = 0.01
    motion: float = 0.1

    @classmethod
    def fixed(cls, dt: float) -> "TimeStep":
        return cls(mode="fixed", dt=dt)

    @classmethod
    def from_alpha(cls, alpha: float, overlap: float = 0.01) -> "TimeStep":
        return cls(mode="alpha", alpha=alpha, overlap=overlap)

    @classmethod
    def auto(cls, safety: float = 0.8, method: str = "exact", every: int = 500,
             growth: float = 0.05, overlap: float = 0.01, motion: float = 0.1) -> "TimeStep":
        return cls(mode="auto", safety=safety, method=method, every=every, growth=growth,
                   overlap=overlap, motion=motion)

    def validate(self):
        if self.mode not in ("fixed", "alpha", "auto"):
            raise InputError(f"timestep mode: must be fixed, alpha or auto, got {self.mode!r}")
        if self.mode == "fixed" and not (self.dt is not None and math.isfinite(self.dt) and self.dt > 0):
            raise InputError(f"timestep dt: must be finite and > 0, got {self.dt!r}")
        if self.mode == "alpha" and not (math.isfinite(self.alpha) and self.alpha > 0):
            raise InputError(f"timestep alpha: must be finite and > 0, got {self.alpha!r}")
        if self.mode == "auto":
            if not (0 < self.safety <= 1):
                raise InputError(f"timestep safety: must lie in (0, 1], got {self.safety!r}")
            if self.method not in ("exact", "element-coupled"):
                raise InputError(f"timestep method: must be exact or element-coupled, got {self.method!r}")
            if int(self.every) < 1:
                raise InputError(f"timestep every: must be >= 1, got {self.every!r}")
            if not (self.growth >= 0):
                raise InputError(f"timestep growth: must be >= 0, got {self.growth!r}")
            if not (self.motion > 0):  # (inf: no limit)
                raise InputError(f"timestep motion: must be > 0, got {self.motion!r}")
