"""The Simulation: particles, a contact law, walls, time-step control, and the loop.

The order of one step, documented here only (:func:`demstep.kernels.dem.advance` runs
steps 1-8 in compiled code, numbered as here; :meth:`Simulation.run` does the rest
between its calls)::

    1. contact forces of the Verlet pairs at x(t), their tangential slip from the
       lagged half-step velocities (du = dt v(t - dt/2) at the contact point), summed
       per particle (one buffer per thread, then reduced); with rolling resistance,
       the pairs' rolling and twisting moments (same lagged angular velocities) into
       the same buffers before the reduction
    2. particle-wall contact forces, the force on each wall; then their rolling and
       twisting moments
    3. boundary work over the last step (walls, a deforming periodic box; trapezoid)
    4. servo walls set their velocity from the stress error; periodic lengths their
       rate (prescribed, or servo on the Love stress)
    5. central-difference update with body force, applied forces, local and global
       damping (on v(t - dt/2)): v(t + dt/2) = v(t - dt/2) + dt F(t)/m,
       x(t + dt) = x(t) + dt v(t + dt/2), and omega with torque / I; the particles'
       terms of the energy ledger
    6. walls move, periodic lengths change
    7. energy ledger: state terms at t (kinetic from the mean of the two half-step
       velocities, strain), accumulated work and dissipation over [t - dt, t]
    8. divergence checks (non-finite values, a particle jumping, runaway kinetic
       energy); 'auto': contacts closed beyond the last certificate's cover at the
       new positions, or closing in the next step, and the drift budget; the
       neighbour lists expire after skin / 2 of motion: return
    9. (Python) rebuild expired lists, carrying the contact history over
   10. (Python) energy balance monitor; writers and callbacks on their triggers
   11. (Python) 'auto' time step: a new estimate when scheduled (every N steps; the
       last certificate is kept instead when it is still as good), or when a contact
       closed (or is closing) that the last estimate did not cover and its
       certificate cannot absorb (found by step 8, and after every rebuild), before
       any force of it acts; or when the covered contacts turned too far (checked
       whenever the pairs' ends may have moved as far as the certificate's drift
       budget allows; with clumps at every step;
       :mod:`demstep.timestep.certificate`)

The half-step velocity is initialised at the first step by a half backward kick,
v(-dt/2) = v(0) - dt/2 F(0)/m, so the given initial velocities are those at t = 0.
Disks (2D) are integrated in the plane z = 0 with rotation about z.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from demstep._numba import warn_slow_threading_layer
from demstep.backend import get_backend
from demstep.contact.geometry import pair_geometry_arrays, wall_geometry_arrays
from demstep.contact.laws import ContactLaw, LinearSpring
from demstep.contacts import ContactSet, with_rolling
from demstep.energy import (A_ROLLING, E_STRAIN_R, EnergyBalanceError, EnergyLedger, EnergyMonitor,
                            runaway_reference)
from demstep.errors import InputError, SimulationDiverged
from demstep.kernels import dem
from demstep.packings import SPATIAL_ORDER_MIN, inverse_order, spatial_order
from demstep.particles import Particles
from demstep.state import (CONTACT_HISTORY, ROLL_WIDTH, Bodies, Bonds, Box, Controls, Ledger,
                            Pairs, Spheres, Walls)
from demstep.walls import Wall

log = logging.getLogger("demstep")


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


def _sorted_keys(keys, values):
    order = np.argsort(keys, kind="stable")
    return keys[order], values[order]


def _ends_in_order(i, j):
    """Pairs or bonds renamed (i, j) put back in i < j order: (lo, hi, sign), ``sign``
    (P, 1) -1 where the ends swapped (what a pair stores as acting on j changes sign)."""
    swap = i > j
    return np.where(swap, j, i), np.where(swap, i, j), np.where(swap, -1.0, 1.0)[:, None]


@dataclass
class _Trigger:
    every: int
    callback: Callable
    next_step: int


def _as3(a, n=None):
    """Embed (N, 2) or (2,) data into 3D with z = 0."""
    a = np.asarray(a, dtype=np.float64)
    if a.shape[-1] == 3:
        return np.ascontiguousarray(a.copy())
    out = np.zeros(a.shape[:-1] + (3,))
    out[..., :2] = a
    return out


_NO_COVER = (np.zeros(0, dtype=np.int64), np.zeros(0))


class Simulation:
    """An explicit DEM simulation of disks (2D) or spheres (3D).

    Parameters
    ----------
    particles : Particles (positions [L], radii [L], masses [M], inertia [M L^2], fixed)
    law : ContactLaw (LinearSpring or HertzMindlin); its ``mu`` may be changed between runs
    walls : rigid walls (fixed, moving at ``velocity`` or servo-controlled)
    gravity : body acceleration [L/T^2] (dim components)
    periodic : box lengths per axis, None for non-periodic axes (box [0, L))
    damping : Damping
    timestep : TimeStep
    velocities, angular_velocities : initial values at t = 0 [L/T], [1/T]
    skin : Verlet skin [L] (default 0.15 x mean radius)
    energy : EnergyMonitor (eps, interval, warn or stop)
    jump_limit : divergence when a particle moves more than this fraction of its radius
        in one step
    runaway_factor : divergence when the kinetic energy exceeds this multiple of the
        most energy the system can have received (the peak of the energy supplied, plus
        what a negative stored energy can release; :mod:`demstep.energy`; 0 disables)
    checkpoint_dir : where the state is saved on divergence (default: a temporary folder)
    rotation : False locks every particle's rotation (translation only)
    parallel : threaded kernels (True), serial (False), or automatic (None: threaded
        from PARALLEL_MIN_PARTICLES particles on when numba has more than one thread)
    backend : the kernels' implementation (:mod:`demstep.backend`; "cpu": numba)
    source_index : the input row of each particle when the caller put them in another
        order (:func:`demstep.packings.spatial_order`: ``demstep run`` does so for a
        particle file); messages and outputs name particles by it (:meth:`particle_id`)
    sort_every : look at the particles' order in memory at the first build of the
        neighbour lists and again at the first rebuild at least this many steps after
        the last look, and re-sort them along rows of cells
        (:func:`demstep.packings.spatial_order`) when that brings the pairs' ends closer
        in memory (:data:`SORT_GAIN`) (None: never; ``demstep run``: every 1000 steps by
        default). The indices of ``x``, ``v``, ... then change (:meth:`reorder`);
        ``source_index`` keeps each particle's input row

    The state lives in the bundles of :mod:`demstep.state` (``spheres``, ``bodies``,
    ``pairs``, ``wall_state``, ``box``, and the ``ledger``); the familiar names (``x``,
    ``v``, ``pi``, ``wall_point``, ``periodic_len``, ...) are views of their fields
    (:data:`STATE_NAMES`).
    """

    def __init__(self, particles: Particles, law: ContactLaw | None = None, walls=(),
                 gravity=None, periodic=None, damping: Damping | None = None,
                 timestep: TimeStep | None = None, velocities=None, angular_velocities=None,
                 skin: float | None = None, energy: EnergyMonitor | None = None,
                 jump_limit: float = 0.25, runaway_factor: float = 10.0,
                 checkpoint_dir: str | os.PathLike | None = None, rotation: bool = True,
                 parallel: bool | None = None, backend: str = "cpu", clumps=None,
                 clump_velocities=None, clump_angular_velocities=None, clump_fixed=None,
                 source_index=None, sort_every: int | None = None):
        bodies = None
        if clumps is not None:
            from demstep.clumps import with_members

            free = particles
            particles, bodies, self.n_free = with_members(
                free, clumps, rotation, clump_fixed, clump_velocities, clump_angular_velocities)
            if (velocities is not None or angular_velocities is not None) and self.n_free == 0:
                raise InputError("velocities: give the bodies' as clump_velocities")
            if velocities is not None:
                velocities = np.concatenate([_as3(velocities), np.zeros((particles.n - self.n_free, 3))])
            if angular_velocities is not None:
                av = np.asarray(angular_velocities, dtype=np.float64)
                pad = np.zeros((particles.n - self.n_free,) + av.shape[1:])
                angular_velocities = np.concatenate([av, pad])
        elif particles is None:
            raise InputError("particles: give particles, clumps or both")
        self.particles = particles
        self.dim = particles.dim
        self.clumps = clumps
        self.source_index = None
        if source_index is not None:
            source_index = np.asarray(source_index, dtype=np.int64)
            if source_index.shape != (particles.n,):
                raise InputError(f"source_index: expected {particles.n} rows, got "
                                 f"{source_index.shape}")
            self.source_index = source_index
        if sort_every is not None and (isinstance(sort_every, bool) or not isinstance(
                sort_every, (int, np.integer)) or sort_every < 1):
            raise InputError(f"sort_every: expected a number of steps >= 1 or None, got "
                             f"{sort_every!r}")
        self.sort_every = None if sort_every is None else int(sort_every)
        self._last_sort = 0  # the step of the last sort (sort_every)
        self.law = law if law is not None else LinearSpring()
        self.law.validate()
        self.damping = damping if damping is not None else Damping()
        self.damping.validate()
        self.timestep = timestep if timestep is not None else TimeStep()
        self.timestep.validate()
        self.monitor = energy if energy is not None else EnergyMonitor()
        self.rotation = bool(rotation)
        self.parallel = parallel
        self.jump_limit = float(jump_limit)
        self._check_motion_limit()
        self.runaway_factor = float(runaway_factor)
        self.checkpoint_dir = checkpoint_dir
        n = particles.n
        x = _as3(particles.x)
        v = np.zeros((n, 3)) if velocities is None else _as3(velocities)
        w = np.zeros((n, 3))
        if angular_velocities is not None:
            av = np.asarray(angular_velocities, dtype=np.float64)
            if self.dim == 2:
                w[:, 2] = av.reshape(n)
            else:
                w[:] = av.reshape(n, 3)
        for name, arr in (("velocities", v), ("angular_velocities", w)):
            if arr.shape != (n, 3) or not np.isfinite(arr).all():
                raise InputError(f"{name}: expected {n} finite vectors")
        self.fixed = particles.fixed
        v[self.fixed] = 0.0
        w[self.fixed] = 0.0
        self.spheres = Spheres.make(x, v, w, particles.r, particles.m.copy(),
                                    particles.inertia.copy())
        self.bodies = Bodies.empty(n) if bodies is None else bodies
        if bodies is not None:  # members move with their bodies from the first step
            from demstep.kernels.bodies import member_velocities

            member_velocities(self.bodies.x, self.bodies.q, self.bodies.v, self.bodies.L,
                              self.bodies.inv_I, self.bodies.start, self.bodies.member,
                              self.bodies.offset, v, w)
        self.gravity = np.zeros(3) if gravity is None else _as3(gravity)
        if self.gravity.shape != (3,) or not np.isfinite(self.gravity).all():
            raise InputError(f"gravity: expected {self.dim} finite components, got {gravity!r}")
        length = np.zeros(3)
        if periodic is not None:
            if len(periodic) != self.dim:
                raise InputError(f"periodic: expected {self.dim} entries, got {list(periodic)}")
            for k, value in enumerate(periodic):
                if value is not None:
                    if not (math.isfinite(value) and value > 0):
                        raise InputError(f"periodic: box length along {'xyz'[k]} must be > 0, got {value!r}")
                    length[k] = float(value)
        box_servo = np.zeros((3, 5))
        box_servo[:, dem.S_MAXSPEED] = np.inf
        self.box = Box(length, np.zeros(3, dtype=np.int64), box_servo, length.copy(),
                       np.zeros((6, 3)))
        self.skin = 0.15 * float(self.r.mean()) if skin is None else float(skin)
        if not (math.isfinite(self.skin) and self.skin > 0):
            raise InputError(f"skin: must be finite and > 0, got {skin!r}")
        self._set_walls(list(walls))
        self._update_masses()
        self.backend = get_backend(backend)
        self.ledger = EnergyLedger()
        self.counters = np.zeros(dem.N_COUNTERS)
        self._check_budget = math.inf  # 'auto': see _renew_drift_budget
        self._turn_budget = 0.0  # (with clumps; and the bodies' orientations then:)
        self._check_q = None
        self.pairs = Pairs.empty(n)
        self._neighbour_work = None  # the pair search's scratch, kept between rebuilds
        self._last_rebuild = 0  # the step of the last rebuild
        self.bonds = Bonds.empty()
        self.step = 0
        self.time = 0.0
        self.dt = None
        self.dt_certified = None  # 'auto': the certified step [T], the ceiling of dt
        self.dt_estimate = None  # the certified step of the last 'auto' estimate [T]
        self.n_dt_solves = 0  # 'auto' estimates by an exact solve
        self.n_dt_element = 0  # 'exact' estimates the coupled element bound decided
        self.n_dt_refreshes = 0  # 'auto' estimates the last certificate still gave
        self.dt_prev = 0.0
        self._time_ref = (0, 0.0, None)  # (step, time, dt) when dt last changed
        self._first = True
        self._triggers: list[_Trigger] = []
        # work space of the pair loop (see _work_space)
        self._geo_store = np.empty((0, 4))
        self._chunks_for = None
        # whether the damping forces of the last step (Spheres.damp_*) and the pair
        # dashpot forces may be non-zero: not at the start; checkpoint restarts set them
        self._damping_history = False
        self._dashpot_history = False
        self._pairs_built = False
        self._order_checked = False  # whether the particle order was looked at (_check_order)
        self._next_dt_update = 0
        self.energy_floor = None

    # ------------------------------------------------------------------ setup
    def particle_id(self, k: int) -> int:
        """How messages and outputs name particle ``k``: its input row when the
        particles were reordered (``source_index``), else k itself."""
        return int(k if self.source_index is None else self.source_index[k])

    def _set_walls(self, walls: list[Wall]):
        for wall in walls:
            if wall.dim != self.dim:
                raise InputError(f"wall {wall.name!r}: has {wall.dim} components, the simulation {self.dim}")
            normal = np.asarray(wall.normal, dtype=np.float64)
            for k in np.flatnonzero(self.box.length[:self.dim] > 0):
                if abs(normal[k]) > 1e-12 * np.linalg.norm(normal):
                    raise InputError(f"wall {wall.name!r}: its normal {normal.tolist()} has a "
                                     f"component along the periodic axis {'xyz'[k]} (a wall "
                                     "cannot cross a periodic box)")
        self.walls = walls
        nw = len(walls)
        z3 = np.zeros((nw, 3))
        point, normal, vel = z3.copy(), z3.copy(), z3.copy()
        motion = np.zeros(nw, dtype=np.int64)
        servo = np.zeros((nw, 5))
        for k, wall in enumerate(walls):
            point[k, :self.dim] = wall.point
            normal[k, :self.dim] = wall.normal
            vel[k, :self.dim] = wall.velocity
            motion[k] = {"fixed": dem.WALL_FIXED, "velocity": dem.WALL_VELOCITY,
                         "servo": dem.WALL_SERVO}[wall.motion]
            servo[k] = (wall.target_stress, wall.servo_gain, wall.max_speed, wall.area,
                        wall.servo_factor)
        # axis-aligned walls bounding the specimen (used for loaded areas)
        box_lo = -np.ones(3, dtype=np.int64)
        box_hi = -np.ones(3, dtype=np.int64)
        for k in range(nw):
            axis = int(np.argmax(np.abs(normal[k])))
            if abs(abs(normal[k, axis]) - 1.0) < 1e-12:
                if normal[k, axis] > 0:
                    box_lo[axis] = k
                else:
                    box_hi[axis] = k
        z0 = np.zeros((0, 3))
        self.wall_state = Walls(point, normal, vel, np.zeros(nw), motion, servo, z3.copy(),
                                z3.copy(), z3.copy(), point.copy(), np.zeros(nw),
                                np.zeros(nw, dtype=np.int64), np.zeros(nw), box_lo, box_hi,
                                np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64),
                                z0, z0.copy(), np.zeros(0), np.zeros((0, ROLL_WIDTH)),
                                np.zeros(0))
        if nw:
            dist = np.einsum("pwk,wk->pw", self.x[:, None, :] - point[None], normal)
            deep = dist < 0.5 * self.r[:, None]
            if deep.any():
                p, k = np.argwhere(deep)[0]
                raise InputError(f"wall {walls[k].name!r}: cuts deep into particle "
                                 f"{self.particle_id(p)} "
                                 f"(centre {dist[p, k]:.4g} from the wall, radius {self.r[p]:.4g})")

    def _update_masses(self):
        self.inv_m[:] = np.where(self.fixed, 0.0, 1.0 / self.m)
        self.inv_I[:] = np.where(self.fixed | (not self.rotation), 0.0, 1.0 / self.inertia)
        b = self.bodies
        if b.n:
            b.inv_m[:] = np.where(b.inv_m > 0, 1.0 / b.m, 0.0)
            b.inv_I[:] = np.where(b.inv_I > 0, 1.0 / b.inertia, 0.0)

    def scale_mass(self, factor: float):
        """Density (mass) scaling for quasi-static runs: multiply every mass and moment of
        inertia by ``factor``; the critical step grows by sqrt(factor)."""
        if not (math.isfinite(factor) and factor > 0):
            raise InputError(f"mass scaling factor: must be finite and > 0, got {factor!r}")
        self.m *= factor
        self.inertia *= factor
        self.bodies.m[:] *= factor
        self.bodies.inertia[:] *= factor
        self.bodies.L[:] *= factor
        self._update_masses()
        self.dt = None
        self._dt_cert = None  # certified for the old masses

    # ---------------------------------------------------------- neighbour lists
    def _rebuild(self):
        """New neighbour lists (particles wrapped into the periodic box first), the
        contact history carried over to them. Small systems (the serial kernels) build
        them on one thread: a parallel region costs more than the work (and far more on
        a loaded machine)."""
        import numba

        threads = numba.get_num_threads()
        if threads > 1 and not self._parallel():
            numba.set_num_threads(1)
        try:
            self._rebuild_lists()
        finally:
            numba.set_num_threads(threads)

    #: the first pair list of at least N/2 pairs warns when fewer than this share of its
    #: pairs lie within N/100 of each other in memory (from SPATIAL_ORDER_MIN particles
    #: on): in random order about 2 %; in spatial order most of them (the pairs along a
    #: row of cells and between rows; those between layers may be a layer apart)
    ORDER_WARN_CLOSE = 0.2

    #: the neighbour search keeps its scratch (:class:`~demstep.scratch.Workspace`)
    #: for the next rebuild when this one comes at most this many steps after the last
    KEEP_SCRATCH_STEPS = 100

    def _check_order(self, pi, pj):
        """Warn (once, at the first pair list of N/2 pairs or more) when the particles
        are in random order: every pair's data is gathered by index, and a packing in
        random order runs 2.5x slower than in spatial order (benchmarks/RESULTS.md)."""
        n = len(self.r)
        if n < SPATIAL_ORDER_MIN:
            self._order_checked = True
            return
        if len(pi) < n // 2:
            return
        self._order_checked = True
        close = float(np.mean(pj - pi < max(64, n // 100)))
        if close < self.ORDER_WARN_CLOSE:
            warnings.warn(f"demstep: the {n} particles are in random order (only "
                          f"{close:.0%} of the pairs lie within {max(64, n // 100)} places of "
                          f"each other in memory); put them in spatial order first "
                          f"(x[demstep.packings.spatial_order(x, 2 * r.max())]): up to 2.5x "
                          f"faster", RuntimeWarning, stacklevel=4)

    def _displacements(self) -> tuple[float, float]:
        """(D, B) [L] now: the largest displacement of a particle from its position at
        the last rebuild, and how far the walls and the periodic box moved since then
        (as the kernels' boundary move); (-1, 0) before the first build."""
        if not self._pairs_built:
            return -1.0, 0.0
        d = self.x - self.x_ref
        moved = float(np.sqrt(np.einsum("ij,ij->i", d, d).max(initial=0.0)))
        ws = self.wall_state
        walls = float(np.sqrt(((ws.point - ws.ref) ** 2).sum(axis=1)).max(initial=0.0))
        return moved, walls + float(np.abs(self.box.length - self.box.ref).sum())

    def _rebuild_lists(self):
        be = self.backend
        c = self.counters  # the drift's displacement bound (dem.drift_used): each
        if c[dem.DRIFT_OFFSET] >= 0.0:  # path goes through its reference at each rebuild
            if self._pairs_built:  # (the kernels' D and B of the last step: its positions)
                c[dem.DRIFT_OFFSET] += c[dem.DRIFT_NOW]
                c[dem.DRIFT_WALL_OFFSET] += c[dem.DRIFT_WALL_NOW]
            else:
                c[dem.DRIFT_OFFSET] = -1.0
        for k in range(3):
            if self.periodic_len[k] > 0:
                np.mod(self.x[:, k], self.periodic_len[k], out=self.x[:, k])
        bodies = self.bodies
        if bodies.n:  # bodies wrapped, their members placed exactly on them
            from demstep.kernels.bodies import place_members

            for k in range(3):
                if self.periodic_len[k] > 0:
                    np.mod(bodies.x[:, k], self.periodic_len[k], out=bodies.x[:, k])
            place_members(bodies.x, bodies.q, bodies.start, bodies.member, bodies.offset,
                          self.x, self.periodic_len)
        built = self._pairs_built
        old, ws = self.pairs, self.wall_state
        if self._neighbour_work is None:
            from demstep.scratch import Workspace

            self._neighbour_work = Workspace()
        work = self._neighbour_work
        # the scratch is kept only while rebuilds come often (not after the first build;
        # a dense, quasi-static run rebuilds rarely: there it would be memory held for
        # nothing, and it was 100 MB more at the peak of a dense 1e6 run)
        if not built or self.step - self._last_rebuild > self.KEEP_SCRATCH_STEPS:
            self._neighbour_work = None
        self._last_rebuild = self.step
        pi, pj = be.build_pair_list(self.x, self.r, self.skin, self.periodic_len,
                                    expected_pairs=len(old.i) if built else None, work=work)
        wp, ww = be.build_wall_list(self.x, self.r, ws.point, ws.normal, self.skin,
                                    expected_pairs=len(ws.p) if built else None, work=work)
        del work  # (dropped now when not kept: before the history is carried over)
        if bodies.n:  # no contacts within a body
            sb = bodies.sphere_body
            keep = (sb[pi] < 0) | (sb[pi] != sb[pj])
            pi, pj = pi[keep], pj[keep]
        if not self._order_checked and self.sort_every is None:
            self._check_order(pi, pj)
        if self._dashpot_history:
            shear, dashpot, energy = be.transfer_history(old.i, old.j, pi, pj, old.shear,
                                                         old.dashpot, old.shear_energy)
        else:  # no dashpot forces to carry: zeros the kernels never touch
            shear, energy = be.transfer_history(old.i, old.j, pi, pj, old.shear, old.shear_energy)
            dashpot = np.zeros((len(pi), 3))
        roll, cover = old.roll, old.cover
        rolling = getattr(self, "_rolling_history", False)
        if len(roll) or rolling:  # (new pairs: zeros; also when there were no pairs)
            roll, = be.transfer_history(old.i, old.j, pi, pj, roll)
        if len(cover):  # new pairs: not covered (0)
            cover, = be.transfer_history(old.i, old.j, pi, pj, cover)
        self.pairs = old._replace(i=pi, j=pj, shear=shear, dashpot=dashpot, shear_energy=energy,
                                  roll=roll, cover=cover)
        self._chunks_for = None
        wshear, wdash, wenergy = be.transfer_history(ws.p, ws.wall, wp, ww, ws.shear,
                                                     ws.dashpot, ws.shear_energy)
        wroll, wcover = ws.roll, ws.cover
        if len(wroll) or rolling:
            wroll, = be.transfer_history(ws.p, ws.wall, wp, ww, wroll)
        if len(wcover):
            wcover, = be.transfer_history(ws.p, ws.wall, wp, ww, wcover)
        self.wall_state = ws._replace(p=wp, wall=ww, shear=wshear, dashpot=wdash,
                                      shear_energy=wenergy, roll=wroll, cover=wcover)
        if self._new_pairs_closing(cover, wcover):
            self.counters[3] += 1.0  # (the 'auto' control covers them before the next step)
        if self.sort_every is not None and (
                not built or self.step - self._last_sort >= self.sort_every):
            self._sort_particles()
        be.copy_positions(self.x, self.x_ref)
        self.wall_state.ref[:] = self.wall_state.point
        self.box.ref[:] = self.box.length
        self.counters[dem.DRIFT_NOW] = self.counters[dem.DRIFT_WALL_NOW] = 0.0
        self._pairs_built = True
        self.n_rebuilds = getattr(self, "n_rebuilds", 0) + 1

    def _new_pairs_closing(self, cover, wall_cover) -> bool:
        """At a rebuild, with the 'auto' control's cover tracked (``cover``,
        ``wall_cover`` per pair and wall pair of the new lists): whether a pair not
        covered (a new one) is closed already or closing in the next step (as
        :func:`demstep.kernels.dem.closing_beyond_cover` looks at the pairs the steps
        know at the positions they end with; those the rebuild brought they have not
        seen)."""
        found = False
        ws = self.wall_state
        # (no cover tracked, no 'auto' estimate: nothing looked at; the moves of the new
        # pairs' particles only: a rebuild comes every few steps in a fast flow, and all
        # N of them were 2 ms of a 9 ms rebuild at 1e5)
        if len(cover) and len(cover) == len(self.pairs.i):
            new = cover == 0.0
            if new.any():
                i, j = self.pairs.i[new], self.pairs.j[new]
                (move_i, move_j), boundary = self._step_moves(np.stack([i, j]))
                delta = pair_geometry_arrays(self.x, self.r, i, j, self.periodic_len)[2]
                found = bool((delta + move_i + move_j + boundary > 0.0).any())
        if not found and len(wall_cover) and len(wall_cover) == len(ws.p):
            new = wall_cover == 0.0
            if new.any():
                p = ws.p[new]
                move, boundary = self._step_moves(p)
                delta = wall_geometry_arrays(self.x, self.r, p, ws.wall[new], ws.point,
                                             ws.normal)[2]
                found = bool((delta + move + boundary > 0.0).any())
        return found

    #: a sort is done when it brings the pairs' ends closer in memory by at least this
    #: much: the mean of log2(1 + |j - i|) over the new pair list falls by this (1: the
    #: typical distance halves). Spheres settling in columns were faster in their
    #: column order (j = i + 1) than in rows of cells (3.4 % slower sorted every 100
    #: steps); a random order of a dense packing gets 2.6x faster (benchmarks/resort.py)
    SORT_GAIN = 1.0

    def _sort_particles(self):
        """At a rebuild (the new lists built): put the particles in spatial order (rows
        of cells of side 2 r_max, as ``demstep run`` orders a particle file) when that
        brings the pairs closer in memory by :data:`SORT_GAIN`."""
        self._last_sort = self.step
        pi, pj = self.pairs.i, self.pairs.j
        if len(pi) == 0:  # (nothing to gather: the order does not matter)
            return
        order = spatial_order(self.x[:, :self.dim], 2.0 * float(self.r.max()))
        inv = inverse_order(order)
        now = float(np.mean(np.log2(1.0 + (pj - pi))))
        sorted_ = float(np.mean(np.log2(1.0 + np.abs(inv[pj] - inv[pi]))))
        if sorted_ <= now - self.SORT_GAIN:
            self.reorder(order)
            self.n_sorts = getattr(self, "n_sorts", 0) + 1

    def reorder(self, order) -> None:
        """Renumber the particles: new particle k is old particle ``order[k]`` (a
        permutation of 0..N-1). Everything that names particles follows: the state of
        every particle, ``fixed``, ``particles``, ``source_index`` (composed, so that
        messages and outputs keep naming particles by their input row), the clumps'
        members, the pair and wall lists with their history, the bonds, and the 'auto'
        step's cover, critical mode and certificate. A pair or bond whose ends swap
        keeps i < j: what it stores as acting on j (tangential spring and dashpot
        forces, rolling, viscous and bending moments, bond shear) changes sign; what
        acts along the normal (normal force, twisting moment) does not, the normal
        turning with it. Index arrays and views the caller holds are not renumbered."""
        n = len(self.r)
        order = np.asarray(order)
        seen = np.zeros(n, dtype=bool)
        if order.shape == (n,) and np.issubdtype(order.dtype, np.integer) and (
                n == 0 or (order.min() >= 0 and order.max() < n)):
            seen[order] = True
        if not seen.all():
            raise InputError(f"order: expected a permutation of 0..{n - 1}, got "
                             f"{order.dtype} of shape {order.shape}")
        order = order.astype(np.int64)
        inv = inverse_order(order)
        # the particles' arrays permuted in place through one scratch array (fresh
        # memory for all of them cost half the time in page faults: 21 ms at 1e5)
        scratch = np.empty(max(a.size for a in self.spheres))
        for a in self.spheres:
            rows = scratch[:a.size].reshape(a.shape)
            np.take(a, order, axis=0, out=rows)
            a[...] = rows
        self.fixed = self.fixed[order]
        p = self.particles
        self.particles = Particles.checked_already(p.x[order], p.r[order], p.m[order],
                                                   p.inertia[order], p.fixed[order])
        self.source_index = order if self.source_index is None else self.source_index[order]
        bodies = self.bodies
        self.bodies = bodies._replace(member=inv[bodies.member],
                                      sphere_body=bodies.sphere_body[order])
        self.pairs = self._renumbered_pairs(self.pairs, inv)
        ws = self.wall_state
        p = inv[ws.p]
        rows = np.lexsort((ws.wall, p))
        self.wall_state = ws._replace(p=p[rows], wall=ws.wall[rows], **{
            f: getattr(ws, f)[rows] if len(getattr(ws, f)) else getattr(ws, f)
            for f in CONTACT_HISTORY})
        bonds = self.bonds
        if bonds.n:
            i, j, sign = _ends_in_order(inv[bonds.i], inv[bonds.j])
            self.bonds = bonds._replace(i=i, j=j, shear=bonds.shear * sign,
                                        bend=bonds.bend * sign)
        self._renumber_timestep_state(order, inv)
        self._chunks_for = None

    @staticmethod
    def _renumbered_pairs(pairs: Pairs, inv: np.ndarray) -> Pairs:
        """The pair list with particle p renamed inv[p], i < j kept (history on j
        negated where the ends swap) and sorted by (i, j) again."""
        lo, hi, sign = _ends_in_order(inv[pairs.i], inv[pairs.j])
        rows = np.lexsort((hi, lo))
        roll = pairs.roll
        if len(roll):
            roll = roll.copy()
            for col in (dem.ROLL_M, dem.ROLL_VISCOUS):  # moments on j (3); twist along n
                roll[:, col:col + 3] *= sign
            roll = roll[rows]
        return pairs._replace(i=lo[rows], j=hi[rows], shear=(pairs.shear * sign)[rows],
                              dashpot=(pairs.dashpot * sign)[rows],
                              shear_energy=pairs.shear_energy[rows], roll=roll,
                              cover=pairs.cover[rows] if len(pairs.cover) else pairs.cover)

    def _pair_keys(self, i, j):
        """The keys of the pairs (i, j), i < j, in the 'auto' step's record of covered
        contacts: i N + j."""
        return i * len(self.r) + j

    @property
    def _walls_per_key(self) -> int:
        """The base of the particle-wall keys (:meth:`_wall_keys`): the number of walls."""
        return max(1, len(self.walls))

    def _wall_keys(self, p, w):
        """The keys of the particle-wall contacts (p, w) in the record of covered
        contacts: p W + w."""
        return p * self._walls_per_key + w

    def _renumber_timestep_state(self, order: np.ndarray, inv: np.ndarray):
        """:meth:`reorder` for the 'auto' control: the cover's keys, the certificate
        (:meth:`demstep.timestep.certificate.StepCertificate.renumber`) and the
        critical mode (a warm start: dropped with clumps, whose modes are per body)."""
        n = len(order)
        for attr in ("_cover_record", "_added_record"):  # (same form: keys and overlaps)
            record = self.__dict__.get(attr)
            if not record:
                continue
            renamed = {}
            for name, (keys, assumed) in record.items():
                if name == "pairs":
                    a, b = inv[keys // n], inv[keys % n]
                    keys = self._pair_keys(np.minimum(a, b), np.maximum(a, b))
                else:
                    base = self._walls_per_key
                    keys = self._wall_keys(inv[keys // base], keys % base)
                rows = np.argsort(keys, kind="stable")
                renamed[name] = (keys[rows], np.asarray(assumed)[rows])
            setattr(self, attr, renamed)
        cert = getattr(self, "_dt_cert", None)
        if cert is not None:
            cert.renumber(order, inv)
        mode = getattr(self, "_dt_mode", None)
        if mode is not None:
            self._dt_mode = (None if self.bodies.n or mode.size % n
                             else mode.reshape(n, -1)[order].reshape(-1))

    # ------------------------------------------------------------- time step
    @property
    def m_min(self) -> float:
        """The lightest free particle's or body's mass [M]."""
        free = ~self.fixed & (self.bodies.sphere_body < 0)
        masses = [self.m[free]]
        if self.bodies.n:
            masses.append(self.bodies.m[self.bodies.inv_m > 0])
        masses = np.concatenate(masses)
        return float(masses.min()) if len(masses) else float(self.m.min())

    def stiffness_max(self) -> float:
        """K_max for alpha: the law's largest stiffness (Hertz: at the TimeStep overlap),
        or an intact bond's normal or shear stiffness k^b A if larger (its springs add
        to the contact's: counted as their sum)."""
        k = float(self.law.stiffness_bound(float(self.r.max()), self.timestep.overlap))
        bonds = self.bonds
        if bonds.n and bonds.intact.any():
            from demstep.contact.bonds import bond_springs

            on = bonds.intact == 1
            kn, ks, _, _ = bond_springs(bonds.radius[on], bonds.k_n[on], bonds.k_s[on], self.dim)
            k += float(max(kn.max(), ks.max()))
        return k

    def contact_set(self, horizon: float | None = None, cover: dict | None = None) -> ContactSet:
        """The contacts in the form the time-step analysis takes, walls included, with
        their linearised coefficients: tangent stiffnesses and dashpot coefficients from
        the law (:func:`demstep.contact.laws.contact_coefficients`); positions projected
        to ``dim``.

        ``horizon`` None: the contacts closed now (overlap > 0). ``horizon`` [T]: every
        pair that can close before the lists are rebuilt, that is every pair of the
        neighbour lists (gap below the skin when they were built; a pair that comes
        closer triggers a rebuild first), with a non-linear law's stiffness at the
        overlap it can reach within the horizon: delta + 2 h (s_i + s_j), s = |v| + h |a|
        the distance a particle covers at its current velocity and acceleration (twice:
        a margin for speeding up; servo walls at their speed limit; at most the skin),
        and at least the TimeStep's relative ``overlap`` x R*.
        Normals are those of the current geometry, arms too for the contacts touching
        now, the radii for those apart (the arms a contact closes with, at most; how far
        arms and normals move later the certificate's drift follows,
        :mod:`demstep.timestep.certificate`). ``cover`` (a dict) receives, for 'pairs'
        and 'walls', the sorted keys of the contacts included and the overlaps their
        coefficients assumed (see :meth:`_contacts_covered`)."""
        dim = self.dim
        params = self.law.params()
        law_id = int(params.law)
        if horizon is not None:
            speed = self._reach_speed(horizon)
        parts = []
        if len(self.pi):
            d, dist, delta, arm_i, arm_j, _ = pair_geometry_arrays(self.x, self.r, self.pi,
                                                                   self.pj, self.periodic_len)
            if horizon is None:
                on = delta > 0
                delta_eval = delta[on]
            else:
                on = np.ones(len(delta), dtype=bool)
            i, j, d, dist = self.pi[on], self.pj[on], d[on], dist[on]
            arm_i, arm_j = arm_i[on], arm_j[on]
            r_star = self.r[i] * self.r[j] / (self.r[i] + self.r[j])
            if horizon is not None:
                delta_eval = self._reachable_overlap(delta, horizon * (speed[i] + speed[j]),
                                                     r_star)
            inv = self.inv_m[i] + self.inv_m[j]
            m_star = np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), self.m[i])
            kn, kt, cn, ct = self._coefficients(law_id, params, delta_eval, r_star, m_star)
            if horizon is None:
                ai, aj = arm_i, arm_j
            else:  # apart: the radii (the arms it will close with, at most)
                touching = delta[on] > 0.0
                ai = np.where(touching, arm_i, self.r[i])
                aj = np.where(touching, arm_j, self.r[j])
            parts.append(ContactSet(i, j, (d / dist[:, None])[:, :dim], ai, aj, kn, kt,
                                    c_n=cn, c_t=ct))
            if cover is not None:
                cover["pairs"] = _sorted_keys(self._pair_keys(i, j), delta_eval)
        if len(self.wp):
            _, dist, delta, _ = wall_geometry_arrays(self.x, self.r, self.wp, self.ww,
                                                     self.wall_point, self.wall_normal)
            if horizon is None:
                on = delta > 0
                delta_eval = delta[on]
            else:
                on = np.ones(len(delta), dtype=bool)
                delta_eval = self._reachable_overlap(
                    delta, horizon * (speed[self.wp] + self._wall_speeds(self.ww)),
                    self.r[self.wp])
            p, wi, dist = self.wp[on], self.ww[on], dist[on]
            kn, kt, cn, ct = self._coefficients(law_id, params, delta_eval, self.r[p], self.m[p])
            arm = dist if horizon is None else np.where(delta[on] > 0.0, dist, self.r[p])
            parts.append(ContactSet(p, np.full(len(p), -1), -self.wall_normal[wi][:, :dim],
                                    arm, np.zeros(len(p)), kn, kt, wi, c_n=cn, c_t=ct))
            if cover is not None:
                cover["walls"] = _sorted_keys(self._wall_keys(p, wi), delta_eval)
        return self._with_rolling_and_bonds(parts, params)

    def _wall_speeds(self, walls) -> np.ndarray:
        """The speeds [L/T] of the ``walls`` (indices): servo walls at their speed limit."""
        speed = np.linalg.norm(self.wall_vel[walls], axis=1)
        return np.maximum(speed, np.where(self.wall_motion[walls] == dem.WALL_SERVO,
                                          np.minimum(self.servo[walls, dem.S_MAXSPEED], 1e300),
                                          0.0))

    def _reachable_overlap(self, delta, reach, r_star) -> np.ndarray:
        """The overlap [L] an 'auto' estimate covers contacts at (their coefficients;
        the cover the pair loops compare with): from the overlap ``delta`` now (negative
        apart), ``reach`` = h (s_i + s_j) [L] the distance the two ends cover within the
        horizon h (:meth:`contact_set`), twice (a margin for speeding up), at most the
        skin; a non-linear law's at least the TimeStep's relative ``overlap`` x
        ``r_star``."""
        out = np.maximum(delta, 0.0) + np.minimum(2.0 * reach, self.skin)
        if self.law.law_id != 0:
            out = np.maximum(out, self.timestep.overlap * r_star)
        return out

    def _with_rolling_and_bonds(self, parts, params) -> ContactSet:
        """The contact parts as one ContactSet with the law's rolling and twisting
        springs (:func:`demstep.contacts.with_rolling`, the kernels' rule for fixed
        particles), then the intact bonds as elements of their own."""
        contacts = (ContactSet.concatenate(parts) if parts else
                    ContactSet(np.zeros(0), np.zeros(0), np.zeros((0, self.dim)), np.zeros(0),
                               np.zeros(0), 0.0, 0.0))
        contacts = with_rolling(contacts, self.r, self.m, self.inertia, self.inv_m > 0, params)
        bonds = self.bond_elements()
        return ContactSet.concatenate([contacts] + bonds) if bonds else contacts

    def bond_elements(self) -> list:
        """The intact parallel bonds as contact elements (a list of one ContactSet, or
        none): springs k_n^b A, k_s^b A at the bond point (arms to the middle of the gap),
        bending k_n^b I and twisting k_s^b J on the relative rotation
        (:func:`demstep.contact.bonds.bond_springs`)."""
        bonds = self.bonds
        on = bonds.intact == 1
        if not on.any():
            return []
        from demstep.contact.bonds import bond_springs

        i, j = bonds.i[on], bonds.j[on]
        d, dist, _, ai, aj, _ = pair_geometry_arrays(self.x, self.r, i, j, self.periodic_len)
        kn, ks, kr, kw = bond_springs(bonds.radius[on], bonds.k_n[on], bonds.k_s[on], self.dim)
        return [ContactSet(i, j, (d / dist[:, None])[:, :self.dim], ai, aj, kn, ks,
                           k_r=kr, k_w=kw)]

    def _reach_speed(self, horizon: float) -> np.ndarray:
        """Per particle, |v| + h |a| [L/T] (a from the last contact and applied forces and
        gravity; zero for fixed particles)."""
        from demstep.kernels.integration import reach_speed

        out = np.empty(len(self.r))
        reach_speed(self.v, self.force, self.applied_force, self.inv_m,
                    np.ascontiguousarray(self.gravity, dtype=np.float64), float(horizon), out)
        return out

    @staticmethod
    def _coefficients(law_id, params, delta, r_star, m_star):
        """k_n, k_t [M/T^2], c_n, c_t [M/T] of contacts at overlaps ``delta``."""
        from demstep.contact.laws import contact_coefficients

        return contact_coefficients(law_id, params, np.ascontiguousarray(delta, float),
                                    np.ascontiguousarray(r_star, float),
                                    np.ascontiguousarray(m_star, float))

    def particles_now(self, check: bool = True) -> Particles:
        """Current particles (positions, current masses after any scaling); ``check``
        False: without validating them again (the 'auto' control's estimates)."""
        x = self.x[:, :self.dim].copy()
        if not check:
            return Particles.checked_already(x, self.r, self.m, self.inertia, self.fixed)
        return Particles(x, self.r, self.m, self.inertia, self.fixed)

    def critical_dt(self, method: str = "exact", rotation: bool = True,
                    horizon: float | None = None, tol: float | None = None,
                    _record: bool = False, _contacts=None) -> float | None:
        """Critical step [T] by ``method`` ('exact' or 'element-coupled') of the contacts
        closed now, or with ``horizon`` [T] of every contact that can close within it
        (:meth:`contact_set`), with the law's dashpots and the global viscous damping
        (the damped step of :mod:`demstep.timestep.damping`); None without contacts.
        The damped iteration tries the last critical mode as a start (the solves that
        certify start cold: demstep.timestep.exact.CHAIN_MIX); ``tol``: its
        relative residual (None: :data:`demstep.timestep.eigen.EIGSH_TOL`; a looser one
        certifies a step up to about 4 ``tol`` below the critical one, sooner).
        (``_record``: the 'auto' control keeps the contacts covered and the mode;
        ``_contacts``: (ContactSet, cover) of :meth:`contact_set` with this ``horizon``
        at this state, already built.)"""
        from demstep.timestep.exact import exact_critical_step

        if method not in ("exact", "element-coupled"):
            raise InputError(f"method: must be exact or element-coupled, got {method!r}")
        if _contacts is not None:
            contacts, cover = _contacts
        else:
            cover = {}
            contacts = self.contact_set(horizon, cover)
        if _record:
            self._dt_cover = cover
            self._dt_cert = None
        if contacts.n == 0:
            return None
        rotation = rotation and self.rotation
        if method == "element-coupled":
            return self._element_coupled_dt(contacts, rotation, keep=lambda dt: _record)[0]
        p = self.particles_now(check=False)
        damping = self._global_damping()
        bodies = self.rigid_bodies()
        mode = getattr(self, "_dt_mode", None)
        extra = {} if tol is None else {"tol": float(tol)}
        result = exact_critical_step(p, contacts, rotation, damping, v0=mode, bodies=bodies,
                                     workspace=self._solver_workspace(), **extra)
        if _record:
            self._dt_mode = result.mode
            self._record_certificate(2.0 / result.dt, result.operator.damping_bound(),
                                     contacts, bodies)
        return result.dt

    def _solver_workspace(self):
        """The time-step analysis' scratch arrays (Lanczos basis, product buffers), kept
        from one estimate to the next (:class:`demstep.scratch.Workspace`)."""
        ws = getattr(self, "_dt_workspace", None)
        if ws is None:
            from demstep.scratch import Workspace

            ws = self._dt_workspace = Workspace(huge_pages=False)
        return ws

    def _record_certificate(self, sigma, lam_c, contacts, bodies):
        from demstep.timestep.certificate import StepCertificate

        inv_I = self.inv_I if self.rotation else np.zeros_like(self.inv_I)
        # (contact_set puts the intact bonds last)
        bond = np.arange(contacts.n) >= contacts.n - int(np.count_nonzero(self.bonds.intact == 1))
        b = self.bodies
        self._added_record = {}  # (contacts added to this certificate: none yet)
        self._dt_cert = StepCertificate.from_estimate(
            sigma, lam_c, contacts, self.inv_m, inv_I, inputs=self.certificate_inputs(),
            radius=self.r, bond=bond, sphere_body=b.sphere_body if b.n else None,
            body_q=b.q.copy() if b.n else None)

    def _drift(self, cert) -> tuple[float, float]:
        """The drift (D_K, D_C) of the certificate ``cert`` at the state now
        (:meth:`demstep.timestep.certificate.StepCertificate.drift`)."""
        return cert.drift(self.x, self.periodic_len, (self.wall_point, self.wall_normal),
                          self._body_pose() if cert.has_bodies else None)

    def _body_pose(self):
        """The clumps now as the certificate's drift takes them
        (:class:`demstep.timestep.certificate.BodyPose`)."""
        from demstep.timestep.certificate import BodyPose

        b = self.bodies
        offset = np.zeros((len(self.r), 3))
        offset[b.member] = b.offset
        inv_I = np.array(b.inv_I, dtype=np.float64)
        if self.dim == 2:  # (disks turn about z only)
            inv_I[:, :2] = 0.0
        if not self.rotation:
            inv_I[:] = 0.0
        return BodyPose(b.sphere_body, offset, b.q, b.inv_m, inv_I)

    def certificate_inputs(self) -> np.ndarray:
        """What an 'auto' estimate depends on besides the geometry, the masses and the
        bonds (changing those drops the certificate where they change): the law's kind,
        springs and dashpots (its parameters, :class:`demstep.contact.laws.LawParams`,
        without the friction limits, which the analysis does not use: sliding contacts
        count as sticking ones) and the global viscous damping a1 [1/T]. A certificate
        made with other inputs certifies nothing now (a stage that changes the damping
        or the law, a user who sets ``sim.law``): :meth:`prepare` then has dt chosen
        anew."""
        params = self.law.params()._replace(mu=0.0, mu_wall=0.0, mu_r=0.0, mu_w=0.0)
        return np.array(tuple(params) + (float(self.damping.viscous),))

    def rigid_bodies(self):
        """The clumps in the form the time-step analysis takes
        (:class:`demstep.timestep.bodies.RigidBodies`: members' arms and the bodies' world
        inertia tensors at the current orientation), or None without clumps."""
        b = self.bodies
        if not b.n:
            return None
        from demstep.clumps import quat_to_matrix
        from demstep.timestep.bodies import RigidBodies

        R = quat_to_matrix(b.q)
        arm = np.zeros((len(self.r), 3))
        arm[b.member] = np.einsum("mij,mj->mi", R[b.sphere_body[b.member]], b.offset)
        inertia = np.einsum("bij,bj,bkj->bik", R, b.inertia, R)
        return RigidBodies(b.sphere_body, arm, b.m.copy(), inertia, b.inv_m == 0)

    def _global_damping(self):
        from demstep.timestep.damping import GlobalDamping

        return GlobalDamping(mass=float(self.damping.viscous))

    def _densest_packing_dt(self) -> float:
        """The damped coupled element bound of the densest packing of the lightest
        particles with the law's largest stiffness (Hertz: at the TimeStep overlap) and
        its dashpots: the step before any contact can form."""
        from demstep.timestep.estimates import densest_packing_dt

        params = self.law.params()
        r = float(self.r.max())
        m = self.m_min
        b = self.bodies
        if b.n:  # a body's contact point is at most its extent from its centre
            arm = np.linalg.norm(self.rigid_bodies().arm, axis=1).max() + r
            m = min(m, float(np.min(1.0 / (1.0 / b.m + arm * arm / b.inertia.min(axis=1)))))
        # a wall contact (R* = r_max) at the TimeStep overlap: the law's stiffness_max()
        kn, kt, cn, ct = self._coefficients(int(params.law), params,
                                            np.array([self.timestep.overlap * r]),
                                            np.array([r]), np.array([0.5 * m]))
        rolling = {}
        if params.has_rolling:  # such a contact's rolling springs (R* = r_max: stiffer than
            # a pair's), the equivalent inertia of two of the lightest particles
            from demstep.kernels.timestep_kernels import rolling_coefficient_arrays
            from demstep.particles import INERTIA_FACTOR

            i_star = 0.5 * (INERTIA_FACTOR[self.dim] + 1.0) * m * r * r
            rolling = dict(zip(("k_r", "k_w", "c_r", "c_w"), (
                float(v[0]) for v in rolling_coefficient_arrays(params, kn, kt, np.array([r]),
                                                                np.array([i_star])))))
        return densest_packing_dt(self.dim, m, kn[0], kt[0], cn[0], ct[0],
                                  self.damping.viscous, self.rotation, radius=r, **rolling)

    def _choose_dt(self, force: bool = False, scheduled: bool = True):
        """dt for the next steps. 'auto': ``safety`` x the critical step of every contact
        that can close before the next estimate (:meth:`critical_dt` with the horizon of
        ``every`` steps), dashpots and global damping included; growth capped, decreases
        immediate. :meth:`_contacts_covered` forces a new estimate as soon as a contact
        closes that the last one did not include (``scheduled`` False: it may only lower
        dt and leaves the schedule of the regular estimates alone)."""
        ts = self.timestep
        if ts.mode != "auto":  # (an 'auto' mode after this one estimates anew)
            self.dt_certified = None
        if ts.mode == "fixed":
            self.dt = float(ts.dt)
        elif ts.mode == "alpha":
            self.dt = ts.alpha * math.sqrt(self.m_min / self.stiffness_max())
        else:
            if self.dt is None:  # (a reset: no step certified either)
                self.dt_certified = None
            if not force and self.dt is not None and self.step < self._next_dt_update:
                return
            fallback = self._densest_packing_dt()
            certified = self.dt_certified
            horizon = int(ts.every) * (certified if certified is not None else
                                       ts.safety * fallback)
            self.dt_horizon = horizon
            estimate = None
            prepared = None  # the contact set a refused shortcut built, for the new estimate
            if scheduled and certified is not None:
                estimate, prepared = self._refreshed_estimate(horizon)
            if (estimate is None and self._pairs_built and certified is not None
                    and ts.method == "exact"):
                estimate, prepared = self._element_estimate(horizon, scheduled, prepared)
            if estimate is None and self._pairs_built:
                estimate = self.critical_dt(ts.method, horizon=horizon,
                                            tol=self._auto_tol(certified), _record=True,
                                            _contacts=prepared)
                if estimate is not None and ts.method == "exact":
                    self.n_dt_solves += 1
            if estimate is None or not math.isfinite(estimate):
                # (no contact can close, or none moves anything: a fixed particle on a
                # wall has an infinite critical step; free flight takes the fallback)
                estimate = fallback
            self.dt_estimate = estimate
            self.n_dt_estimates = getattr(self, "n_dt_estimates", 0) + 1
            target = ts.safety * self._local_damping_factor() * estimate
            if certified is None or target < certified:
                certified = target
            elif scheduled:
                certified = min(target, certified * (1.0 + ts.growth))
            self.dt_certified = certified
            self.dt = self._motion_limited_dt()
            if scheduled:
                self._next_dt_update = self.step + int(ts.every)
            self._renew_drift_budget()  # (dt or the certificate changed)

    #: 'auto': the step held by the motion limit sits this far below it (so that it is
    #: not changed at every chunk of steps while the particles speed up or slow down)
    MOTION_SLACK = 0.05

    def _check_motion_limit(self):
        """The divergence limit ``jump_limit`` must be > 0 (inf: none), and above the
        'auto' motion limit (else the control would choose steps the check stops)."""
        if not self.jump_limit > 0.0:  # (inf: no check)
            raise InputError(f"jump_limit: must be > 0, got {self.jump_limit!r}")
        ts = self.timestep
        if ts.mode == "auto" and not ts.motion < self.jump_limit:
            raise InputError(f"timestep motion: must be below jump_limit = {self.jump_limit:g} "
                             f"(the divergence check), got {ts.motion!r}")

    def _motion_rate(self) -> float:
        """How fast the fastest particle moves in radii per unit time [1/T]: from the
        kernels' largest |v| dt / r of the last step (``counters[2]``), or before the
        first step from the initial velocities (clump members' are their bodies' V +
        omega x arm from the start: :func:`demstep.kernels.bodies.member_velocities`)."""
        if not self._first and self.dt_prev > 0.0:
            return float(self.counters[2]) / self.dt_prev
        speed = np.sqrt(np.einsum("ij,ij->i", self.v, self.v))
        return float(np.max(speed / self.r, initial=0.0))

    def _motion_limit(self) -> float:
        """The step [T] at which the fastest particle would move ``timestep.motion`` of
        its radius (:meth:`_motion_rate`; inf: nothing moves)."""
        rate = self._motion_rate()
        return self.timestep.motion / rate if rate > 0.0 else math.inf

    def _motion_limited_dt(self) -> float:
        """The step [T] to take: the certified one (:attr:`dt_certified`), or less where
        a particle would move more than ``timestep.motion`` of its radius in a step at
        its speed now (:meth:`_motion_rate`). While the limit holds the step, it is
        kept within :data:`MOTION_SLACK` below the limit, and changed only when the limit
        leaves that band."""
        certified = self.dt_certified
        limit = self._motion_limit()
        if limit >= certified * (1.0 + self.MOTION_SLACK):
            return certified
        dt = self.dt
        if dt is not None and limit / (1.0 + self.MOTION_SLACK) <= dt <= min(limit, certified):
            return dt
        return min(certified, limit / (1.0 + self.MOTION_SLACK))

    def _limit_motion(self):
        """'auto', between estimates: the step the motion limit allows now
        (:meth:`_motion_limited_dt`). A smaller step keeps the certificate and its drift
        budget (made for a larger one); a larger one (at most the certified step)
        checks the budget anew, and a new estimate follows if the certificate fails."""
        if self.dt_certified is None or self.dt is None:
            return
        dt = self._motion_limited_dt()
        if dt == self.dt:
            return
        raised = dt > self.dt
        self.dt = dt
        if raised and not self._renew_drift_budget():
            self._choose_dt(force=True, scheduled=False)

    #: 'auto': the relative residual of the exact solves. The step stays certified (an
    #: upper bound on the largest root, whatever the residual); it is at most about
    #: 4e-6 below the critical step instead of 4e-9, far inside the safety factor, for
    #: 40 % fewer products (a settling run of 1e5 spheres: 30 against 52)
    AUTO_EXACT_TOL = 1e-6

    #: 'auto': the relative residual of the exact solves while the motion limit holds
    #: the step at least :data:`AUTO_MOTION_MARGIN` below the certified one (landing
    #: clumps: 24 % fewer products, about 10 % of the run, measured). Their step is as
    #: certified as any (the solver certifies from a cold start up to a residual of
    #: 1e-3: demstep.timestep.eigen.MAX_CERTIFIED_TOL), at most about 8e-4 below the
    #: critical one instead of 8e-6: the step the motion limit takes does not reach it;
    #: once the limit lifts, the next tight estimate (forced or scheduled) gets it back
    AUTO_MOTION_TOL = 1e-4
    AUTO_MOTION_MARGIN = 0.05

    def _auto_tol(self, certified: float | None) -> float:
        """The relative residual of an 'auto' exact solve: :data:`AUTO_MOTION_TOL` when
        the motion limit (:meth:`_motion_limit`) is at least :data:`AUTO_MOTION_MARGIN`
        below the ``certified`` step [T] of the last estimate, else
        :data:`AUTO_EXACT_TOL`."""
        if certified is not None and self._motion_limit() < certified * (
                1.0 - self.AUTO_MOTION_MARGIN):
            return self.AUTO_MOTION_TOL
        return self.AUTO_EXACT_TOL

    #: 'auto': a scheduled estimate keeps the last certificate (with the drift of its
    #: normals and the contacts added since) instead of a new solve when the step it
    #: certifies is within this of the last critical mode's Rayleigh quotient now, a
    #: lower bound on the root (so dt is at most this far below a new solve's)
    AUTO_REFRESH_RTOL = 1e-2

    def _refreshed_estimate(self, horizon: float):
        """(dt, prepared): the critical step [T] the last certificate still gives (every
        closed contact covered, the drift followed), when a new estimate could not give
        a different dt: the growth cap already holds dt below ``safety`` x that step, or
        (the exact method) it is within :data:`AUTO_REFRESH_RTOL` of the best a new
        estimate could give; else None. And the (ContactSet, cover) it built for
        ``horizon``, if it got that far (None otherwise), for a new estimate of the same
        state to take instead of building it again."""
        cert = getattr(self, "_dt_cert", None)
        if cert is None or not cert.bounded or not self._pairs_built:
            return None, None
        masks = self._uncovered()
        if masks is None or masks[0].any() or masks[1].any():
            return None, None
        sigma_up = cert.smallest_sigma(self._drift(cert))
        if self._estimate_cannot_change_dt(2.0 / sigma_up, scheduled=True):
            self.n_dt_refreshes += 1
            return 2.0 / sigma_up, None
        mode = getattr(self, "_dt_mode", None)
        if mode is None or self.timestep.method != "exact":
            return None, None
        cover = {}
        contacts = self.contact_set(horizon, cover)
        prepared = (contacts, cover)
        if contacts.n == 0:
            return None, prepared
        from demstep.timestep.exact import ScaledContactOperator
        from demstep.timestep.stability import damped_sigma

        op = ScaledContactOperator(self.particles_now(check=False), contacts, self.rotation,
                                   self._global_damping(), None,
                                   workspace=self._solver_workspace())
        if op.size != mode.size:
            return None, prepared
        sigma_lo = float(damped_sigma(*op.rayleigh_terms(mode / np.linalg.norm(mode))))
        # (sigma_lo > sigma_up: the certificate does not hold; a new estimate is due)
        if not sigma_lo <= sigma_up <= sigma_lo * (1.0 + self.AUTO_REFRESH_RTOL):
            return None, prepared
        self.n_dt_refreshes += 1
        return 2.0 / sigma_up, prepared

    def _estimate_cannot_change_dt(self, estimate: float, scheduled: bool) -> bool:
        """Whether a certified step ``estimate`` [T] (a lower bound on the critical one)
        already decides dt, so that the exact step, at least as large, would give the
        same: the growth cap (a ``scheduled`` estimate) or the rule that a forced one
        only lowers dt holds dt at or below ``safety`` x ``estimate``."""
        ts = self.timestep
        return (ts.safety * self._local_damping_factor() * estimate
                >= self.dt_certified * ((1.0 + ts.growth) if scheduled else 1.0))

    def _local_damping_factor(self) -> float:
        """1 / sqrt(1 + local): what local (Cundall) damping takes off the certified
        step. Its force -local |F| sign(v) takes the sign of the lagged half-step velocity,
        which in the fastest (period-two) mode is that of the displacement: it adds
        local |F| to the restoring force, a stiffness (1 + local) K for that mode
        (measured: unstable from 0.90 and 0.78 of the undamped step at local 0.3 and
        0.7, against 0.877 and 0.767). The 'auto' step is safety x this x the certified
        step of K and C; a root sigma_0 of (K, C) gives sqrt(1 + local) sigma_0 for
        ((1 + local) K, C), since lambda_max(s C + (1 + local) K) <= (1 + local)
        lambda_max(s / sqrt(1 + local) C + K) (C >= 0)."""
        return 1.0 / math.sqrt(1.0 + float(self.damping.local))

    def _certified_sigma(self) -> float:
        """The root [1/T] the last certificate (of K and C) must reach for dt to hold
        with local damping: 2 / (dt sqrt(1 + local)) (:meth:`_local_damping_factor`)."""
        return 2.0 * self._local_damping_factor() / self.dt

    def _element_estimate(self, horizon: float, scheduled: bool, prepared=None):
        """(dt, prepared) for an 'exact' estimate that may not need its solve: the
        coupled element bound [T] of every contact that can close within ``horizon`` (a
        rigorous lower bound on the exact step, from one pass over the contacts) when
        it already decides dt (:meth:`_estimate_cannot_change_dt`); it is then recorded
        as the certificate in the solve's place. Else None, and the (ContactSet, cover)
        built (or the ``prepared`` one taken) for the exact solve."""
        if prepared is None:
            cover = {}
            prepared = (self.contact_set(horizon, cover), cover)
        contacts, cover = prepared
        if contacts.n == 0:
            return None, prepared
        keep = lambda dt: self._estimate_cannot_change_dt(dt, scheduled)  # noqa: E731
        if self._element_bound_falls_short(contacts, keep):
            return None, prepared
        dt, kept = self._element_coupled_dt(contacts, self.rotation, keep=keep)
        if not kept:
            return None, prepared
        self._dt_cover = cover
        self.n_dt_element += 1
        return dt, None

    #: 'auto' with clumps: the elements an element estimate looks at first (twice this
    #: many: :func:`demstep.timestep.bodies.likely_stiffest_elements`)
    ELEMENT_SCREEN = 32

    def _element_bound_falls_short(self, contacts, keep) -> bool:
        """With clumps, whose element bound solves a small dense eigenproblem per
        contact: whether it cannot be kept (``keep(dt)`` false), decided on an upper
        bound on it, the smallest step of the elements likeliest to be the stiffest
        (:func:`demstep.timestep.bodies.likely_stiffest_elements`). False: not decided
        (to be computed in full)."""
        bodies = self.rigid_bodies()
        if bodies is None or contacts.n <= 4 * self.ELEMENT_SCREEN:
            return False
        from demstep.timestep.bodies import body_element_dt, likely_stiffest_elements

        p = self.particles_now(check=False)
        d = self._global_damping()
        rows = likely_stiffest_elements(p, contacts, bodies, self.rotation,
                                        self.ELEMENT_SCREEN)
        dt = float(body_element_dt(p, contacts, bodies, self.rotation, d.mass, d.stiffness,
                                   rows).min())
        if d.mass > 0:
            dt = min(dt, 2.0 / d.mass)  # (as element_coupled_dt)
        return not keep(dt)

    def _element_coupled_dt(self, contacts, rotation: bool, keep) -> tuple[float, bool]:
        """(dt, kept): the coupled element bound dt [T] of ``contacts`` now (a rigorous
        lower bound on their exact step, :func:`demstep.timestep.estimates.element_coupled_dt`),
        with the global damping and the clumps; recorded as the 'auto' control's
        certificate when ``kept = keep(dt)`` is true."""
        from demstep.timestep.estimates import element_coupled_dt
        from demstep.timestep.exact import ScaledContactOperator

        p = self.particles_now(check=False)
        damping = self._global_damping()
        bodies = self.rigid_bodies()
        dt = element_coupled_dt(p, contacts, rotation, damping=damping, bodies=bodies)
        kept = bool(keep(dt))
        if kept:
            op = ScaledContactOperator(p, contacts, rotation, damping, bodies,
                                       workspace=self._solver_workspace())
            self._record_certificate(2.0 / dt, op.damping_bound(), contacts, bodies)
        return dt, kept

    def _size_rolling_history(self, rolling: bool):
        """Rolling-resistance history rows for every pair and wall pair while the law
        has rolling resistance (zeros for new ones), none otherwise: switching it off
        releases the stored energy into the ledger's rolling dissipation. Rebuilds of
        the lists keep a row per pair while it is on (also from an empty list), and the
        pair loop's work space (its rolling geometry) is sized anew after a change."""
        self._rolling_history = bool(rolling)
        for name in ("pairs", "wall_state"):
            bundle = getattr(self, name)
            n = len(bundle.i) if name == "pairs" else len(bundle.p)
            if rolling and len(bundle.roll) != n:
                setattr(self, name, bundle._replace(roll=np.zeros((n, ROLL_WIDTH))))
            elif not rolling and len(bundle.roll):
                self.ledger.acc[A_ROLLING] += float(bundle.roll[:, dem.ROLL_ENERGY].sum())
                self.ledger.energy[E_STRAIN_R] = 0.0
                setattr(self, name, bundle._replace(roll=np.zeros((0, ROLL_WIDTH))))
            else:
                continue
            if name == "pairs":
                self._chunks_for = None

    def add_bonds(self, bonds, pairs=None) -> int:
        """Bond particles with parallel bonds of parameters ``bonds``
        (:class:`demstep.contact.bonds.ParallelBonds`): the given ``pairs`` (K, 2) of
        particle indices, or every pair whose surfaces are at most ``bonds.gap`` apart
        (touching and overlapping pairs included; minimum image across periodic axes;
        never two spheres of one clump; a pair listed twice is an error). Pairs already
        bonded by an intact bond are skipped. Returns the number of bonds added."""
        from demstep.contact.bonds import bond_candidates

        bonds.validate()
        n = len(self.r)
        if pairs is None:
            i, j = bond_candidates(self.x, self.r, bonds.gap, self.periodic_len, self.dim)
        else:
            pairs = np.asarray(pairs)
            if pairs.ndim != 2 or pairs.shape[1] != 2 or not np.issubdtype(pairs.dtype, np.integer):
                raise InputError(f"bonds: pairs must be an integer array (K, 2), got shape "
                                 f"{pairs.shape} of {pairs.dtype}")
            bad = (pairs < 0) | (pairs >= n)
            if bad.any():
                raise InputError(f"bonds: particle index {pairs[bad][0]} outside 0..{n - 1}")
            if (pairs[:, 0] == pairs[:, 1]).any():
                k = int(np.flatnonzero(pairs[:, 0] == pairs[:, 1])[0])
                raise InputError(f"bonds: pair {k} bonds particle "
                                 f"{self.particle_id(pairs[k, 0])} to itself")
            i, j = np.minimum(pairs[:, 0], pairs[:, 1]), np.maximum(pairs[:, 0], pairs[:, 1])
            _, first, counts = np.unique(self._pair_keys(i, j), return_index=True,
                                         return_counts=True)
            if (counts > 1).any():
                k = int(first[np.flatnonzero(counts > 1)[0]])
                raise InputError(f"bonds: pair ({self.particle_id(i[k])}, "
                                 f"{self.particle_id(j[k])}) is listed twice (in either order)")
            d, dist, delta, *_ = pair_geometry_arrays(self.x, self.r, i, j, self.periodic_len)
            far = -delta > bonds.gap * (1 + 1e-12)
            if far.any():
                k = int(np.flatnonzero(far)[0])
                raise InputError(f"bonds: pair ({self.particle_id(i[k])}, "
                                 f"{self.particle_id(j[k])}) is {-delta[k]:.6g} apart, beyond "
                                 f"the gap {bonds.gap:g}")
        sb = self.bodies.sphere_body
        keep = (sb[i] < 0) | (sb[i] != sb[j])
        old = self.bonds
        intact = old.intact == 1
        keep &= ~np.isin(i * n + j, old.i[intact] * n + old.j[intact])
        i, j = i[keep], j[keep]
        radius = bonds.radius_multiplier * np.minimum(self.r[i], self.r[j])
        new = Bonds.make(i, j, radius, bonds.normal_stiffness, bonds.k_s, bonds.tensile_strength,
                         bonds.shear_strength)
        self.bonds = Bonds(*(np.concatenate([getattr(old, f), getattr(new, f)])
                             for f in Bonds._fields))
        if len(i) and self.timestep.mode != "fixed":
            self._dt_cert = None  # stiffer now: alpha and 'auto' choose the step anew
            self.dt = None
        return len(i)

    # ---------------------------------------------------------------- state
    #: the bundles whose STATE fields make the dynamic state (:meth:`state_dict`)
    BUNDLES = ("spheres", "bodies", "pairs", "bonds", "wall_state", "box")

    def state_dict(self) -> dict:
        """The complete dynamic state as named arrays (what a checkpoint saves): the
        STATE fields of every bundle as ``bundle.field``, the ledger, gravity, radii and
        fixed flags (to check a restore), the scalars (step, time, dt, ...), the law's
        parameters, the energy monitor's alarm state and the 'auto' time-step state."""
        if not self._pairs_built:
            self._rebuild()
        out = {}
        for name in self.BUNDLES:
            bundle = getattr(self, name)
            for f in bundle.STATE:
                out[f"{name}.{f}"] = getattr(bundle, f)
        out.update({"ledger.acc": self.ledger.acc, "ledger.energy": self.ledger.energy,
                    "ledger.counters": self.counters, "gravity": self.gravity, "r": self.r,
                    "fixed": self.fixed, "law": np.asarray(self.law.params()),
                    "monitor": self.monitor.state()})
        out["scalars"] = np.array([
            self.step, self.time, np.nan if self.dt is None else self.dt, self.dt_prev,
            float(self._first), self.monitor.max_error, float(self._next_dt_update),
            np.nan if self.dt_estimate is None else self.dt_estimate,
            float(self._time_ref[0]), self._time_ref[1],
            np.nan if self._time_ref[2] is None else self._time_ref[2]])
        out.update(self.timestep_state())
        if self.source_index is not None:  # the order of the arrays (sorted in a run)
            out["source_index"] = self.source_index
        out["last_sort"] = np.array([self._last_sort])
        return out

    def load_state_dict(self, data: dict, source: str = "state"):
        """Restore :meth:`state_dict` into this Simulation (built from the same case:
        the same particles and walls, else InputError naming ``source``)."""
        needed = [f"{n}.{f}" for n in self.BUNDLES for f in getattr(self, n).STATE]
        needed += ["ledger.acc", "ledger.energy", "ledger.counters", "gravity", "r", "scalars"]
        data = dict(data)
        for name in ("pairs", "wall_state"):  # checkpoints from before rolling resistance
            data.setdefault(f"{name}.roll", np.zeros((0, ROLL_WIDTH)))
        old_cover = "pairs.cover" not in data  # and from before the cover was tracked
        for name in ("pairs", "wall_state"):
            data.setdefault(f"{name}.cover", np.zeros(0))
        for f in Bonds.STATE:  # and from before bonds
            data.setdefault(f"bonds.{f}", getattr(Bonds.empty(), f))
        missing = [k for k in needed if k not in data]
        if missing:
            raise InputError(f"{source}: a damaged checkpoint (array {missing[0]!r} missing)")
        data = self._checked_state(data, source)
        self._order_as(data.get("source_index"), source)
        if not np.array_equal(data["r"], self.r):
            raise InputError(f"{source}: the checkpoint's particles do not match the simulation")
        for name in self.BUNDLES:
            bundle = getattr(self, name)
            setattr(self, name, bundle._replace(**{
                f: np.ascontiguousarray(data[f"{name}.{f}"]) for f in bundle.STATE}))
        self.ledger.acc[:] = 0.0  # older checkpoints: fewer terms (a prefix of the layout)
        self.ledger.energy[:] = 0.0
        self.ledger.acc[:len(data["ledger.acc"])] = data["ledger.acc"]
        self.ledger.energy[:len(data["ledger.energy"])] = data["ledger.energy"]
        self.counters[:] = 0.0  # older checkpoints: the first three
        self.counters[:len(data["ledger.counters"])] = data["ledger.counters"]
        if len(data["ledger.counters"]) <= dem.DRIFT_OFFSET:  # (from before the
            self.counters[dem.DRIFT_OFFSET] = -1.0  # displacement bound: unknown)
        self.gravity = np.ascontiguousarray(data["gravity"], dtype=np.float64)
        if "monitor" in data:
            self.monitor.restore_state(data["monitor"])
        self.restore_timestep_state({k: data[k] for k in data if k.startswith("ts_")})
        if old_cover:
            self._sync_cover(reset=False)
        step, time, dt, dt_prev, first, max_err, next_dt, dt_est, t_step, t_time, t_dt = \
            np.asarray(data["scalars"], dtype=np.float64)
        self.step = int(step)
        self._last_sort = int(np.asarray(data.get("last_sort", [step]))[0])
        self.time = float(time)
        self.dt = None if np.isnan(dt) else float(dt)
        # (older checkpoints: dt was the certified step)
        certified = np.asarray(data.get("ts_dt_certified", [np.nan if self.dt is None else dt]),
                               dtype=np.float64).reshape(-1)
        if certified.size != 1 or not (np.isnan(certified[0]) or certified[0] > 0.0):
            raise InputError(f"ts_dt_certified: expected one number > 0, got {certified}")
        self.dt_certified = (None if self.timestep.mode != "auto" or np.isnan(certified[0])
                             else float(certified[0]))
        if self.dt_certified is not None and not (self.dt is not None
                                                  and self.dt <= self.dt_certified):
            raise InputError(f"{source}: the step dt = {self.dt!r} is above the certified "
                             f"one ts_dt_certified = {self.dt_certified!r}")
        self.dt_prev = float(dt_prev)
        self._first = bool(first)
        self.monitor.max_error = float(max_err)
        self._next_dt_update = int(next_dt)
        self.dt_estimate = None if np.isnan(dt_est) else float(dt_est)
        self._time_ref = (int(t_step), float(t_time), None if np.isnan(t_dt) else float(t_dt))
        self._damping_history = True  # restored damping forces of the last step
        self._dashpot_history = True  # and pair dashpot forces
        self._update_masses()
        self._chunks_for = None
        self._pairs_built = True
        self.energy_floor = None
        for t in self._triggers:  # the next multiple of each interval, as in an unbroken run
            t.next_step = (self.step // t.every + 1) * t.every
        return self

    #: fields of the pair and particle-wall lists: one row per listed contact (``roll``
    #: and ``cover`` may have none: no rolling resistance, no cover tracked)
    _LIST_FIELDS = {"pairs": ("i", "j") + CONTACT_HISTORY,
                    "wall_state": ("p", "wall") + CONTACT_HISTORY}
    #: the scalars (:meth:`state_dict`) that are NaN when unset: dt, dt_estimate, the
    #: reference dt
    _NAN_SCALARS = (2, 7, 10)

    def _checked_state(self, data: dict, source: str) -> dict:
        """``data`` (a :meth:`state_dict` read back) checked before anything is restored:
        every per-particle, per-wall and per-body array has the shape this Simulation
        (built from the same case) has, every pair, wall-contact and bond array as many
        rows as its list has, indices lie in range and values are finite (the compiled
        kernels do not check bounds: a short array would be read past its end). Raises
        an InputError naming ``source``, the array's key and the shape or value; returns
        the arrays as contiguous arrays of the engine's types."""
        n, n_walls = len(self.r), len(self.wall_state.point)
        data = dict(data)
        # another case's checkpoint: say so, not which array differs first
        for key, like, what in (("r", self.r, "particles"), ("wall_state.point",
                                self.wall_state.point, "walls"), ("bodies.x", self.bodies.x,
                                "bodies")):
            shape = np.shape(data[key])
            if shape != like.shape:
                raise InputError(f"{source}: the checkpoint's {what} do not match the "
                                 f"simulation ({shape[0] if shape else 0} in the checkpoint, "
                                 f"{len(like)} in the case)")

        def fail(key, what):
            return InputError(f"{source}: checkpoint array {key!r} {what}")

        def numbers(key, like=None):
            a = np.asarray(data[key])
            kinds = "iu" if like is not None and like.dtype.kind in "iu" else "fiu"
            if a.dtype.kind not in kinds:
                what = "integers" if kinds == "iu" else "numbers"
                raise fail(key, f"holds {a.dtype} values, not {what}")
            if like is not None:
                a = np.ascontiguousarray(a, dtype=like.dtype)
            data[key] = a
            return a

        def shaped(key, shape, count=""):
            a = data[key]
            if a.shape != tuple(shape):
                raise fail(key, f"has shape {a.shape}, expected {tuple(shape)}{count}")

        def in_range(key, top, what, a=None):
            a = data[key] if a is None else a
            if a.size and (a.min() < 0 or a.max() >= top):
                value = a.min() if a.min() < 0 else a.max()
                raise fail(key, f"holds the {what} index {int(value)}, outside 0..{top - 1}")

        def finite(key, nan_only=False):
            a = data[key]
            if a.dtype.kind == "f":
                bad = np.isnan(a) if nan_only else ~np.isfinite(a)
                if bad.any():
                    at = np.unravel_index(int(np.argmax(bad)), a.shape)
                    raise fail(key, f"holds the non-finite value {a[at]} at {list(map(int, at))}")

        counts = {"spheres": f" ({n} particles)", "wall_state": f" ({n_walls} walls)",
                  "bodies": f" ({self.bodies.n} bodies)", "box": ""}
        for name in self.BUNDLES:
            bundle = getattr(self, name)
            lists = self._LIST_FIELDS.get(name, ())
            if name == "bonds":
                lists = bundle.STATE
            if lists:
                head = f"{name}.{lists[0]}"
                rows = len(numbers(head, getattr(bundle, lists[0])).reshape(-1))
            for f in bundle.STATE:
                key = f"{name}.{f}"
                like = getattr(bundle, f)
                a = numbers(key, like)
                if f in lists:
                    expected = (rows,) + like.shape[1:]
                    optional = f in ("roll", "cover") and a.shape[0] == 0
                    if not optional:
                        shaped(key, expected, f" (as many rows as {head}: {rows})")
                    elif a.shape[1:] != like.shape[1:]:
                        raise fail(key, f"has shape {a.shape}, expected {expected}")
                else:
                    shaped(key, like.shape, counts[name])
                # (inf is a value of: unused servo limits, the cover of a contact covered
                # at any overlap, a bond without a strength limit)
                finite(key, nan_only=f in ("servo", "cover", "sigma_c", "tau_c"))
        for key in ("pairs.i", "pairs.j", "wall_state.p", "bonds.i", "bonds.j"):
            in_range(key, n, "particle")
        in_range("wall_state.wall", n_walls, "wall")
        for key, like in (("ledger.acc", self.ledger.acc), ("ledger.energy", self.ledger.energy),
                          ("ledger.counters", self.counters)):
            a = numbers(key, like)  # (older checkpoints: a prefix of the layout)
            if a.ndim != 1 or len(a) > len(like):
                raise fail(key, f"has shape {a.shape}, expected at most ({len(like)},)")
            finite(key)
        numbers("gravity", self.gravity)
        shaped("gravity", self.gravity.shape)
        finite("gravity")
        scalars = numbers("scalars").astype(np.float64)
        data["scalars"] = scalars
        shaped("scalars", (11,))
        for k, value in enumerate(scalars):
            if not (math.isfinite(value) or (k in self._NAN_SCALARS and math.isnan(value))):
                raise fail("scalars", f"holds the non-finite value {value} at [{k}]")
        if scalars[0] < 0 or scalars[1] < 0:
            raise fail("scalars", f"holds a negative step or time, got step {scalars[0]:g}, "
                                  f"time {scalars[1]:g}")
        for key in ("monitor", "last_sort"):
            if key in data:
                a = numbers(key).reshape(-1)
                if a.size == 0:
                    raise fail(key, "is empty")
                finite(key)
        if "ts_cert" in data:
            self._check_certificate_state(data, numbers, in_range, finite, fail, n, n_walls,
                                          self.bodies.n)
        self._check_added_record(data, fail)
        return data

    @staticmethod
    def _check_certificate_state(data, numbers, in_range, finite, fail, n, n_walls, n_bodies):
        """The 'auto' time step's certificate of a checkpoint (:meth:`timestep_state`):
        the covered pairs' and wall contacts' indices in range and their rows, as
        :meth:`demstep.timestep.certificate.StepCertificate.from_state` reads them, and
        with clumps the bodies' and their contacts' rows."""
        values = numbers("ts_cert").reshape(-1)
        finite("ts_cert", nan_only=True)
        if len(values) < 5 or "ts_cert_particles" not in data \
                or "ts_cert_coefficients" not in data:
            return  # (restored unbounded: the run estimates anew)
        pairs = numbers("ts_cert_pairs")
        walls = numbers("ts_cert_walls")
        if pairs.ndim != 2 or pairs.shape[0] != 3:
            raise fail("ts_cert_pairs", f"has shape {pairs.shape}, expected (3, pairs)")
        if walls.size % 2:
            raise fail("ts_cert_walls", f"has shape {walls.shape}, expected (2, contacts)")
        k, kw = pairs.shape[1], walls.size // 2
        walls = walls.reshape(2, -1)
        kb = 0
        if "ts_cert_body_q" in data:
            kb = Simulation._check_body_certificate(data, numbers, in_range, finite, fail, n,
                                                    n_walls, n_bodies)
        in_range("ts_cert_pairs", n, "particle", pairs[:2])
        in_range("ts_cert_walls", n, "particle", walls[0])
        in_range("ts_cert_walls", n_walls, "wall", walls[1])
        for key, size, shape in (("ts_cert_normal", None, None),
                                 ("ts_cert_coefficients", 8 * k, f"({k}, 8)"),
                                 ("ts_cert_wall_factors", 3 * kw, f"({kw}, 3)"),
                                 ("ts_cert_particles", 3 * n if k or kw or kb else None,
                                  f"({n}, 3)")):
            a = numbers(key)
            if key == "ts_cert_normal":
                if a.size and (a.ndim != 2 or a.shape[0] != k or a.shape[1] not in (2, 3)) \
                        or not a.size and k:
                    raise fail(key, f"has shape {a.shape}, expected ({k}, 2 or 3)")
            elif size is not None and a.size != size:
                raise fail(key, f"has shape {a.shape}, expected {shape}")
            finite(key)

    @staticmethod
    def _check_body_certificate(data, numbers, in_range, finite, fail, n, n_walls,
                                n_bodies) -> int:
        """The clumps' rows of a checkpoint's certificate
        (:meth:`demstep.timestep.certificate.StepCertificate.state`): the bodies'
        orientations one per body, the contacts' spheres, walls and bond flags in range,
        their arms, normals and coefficients finite. Returns the number of contacts."""
        q = numbers("ts_cert_body_q")
        finite("ts_cert_body_q")
        if q.ndim != 2 or q.shape != (n_bodies, 4):
            raise fail("ts_cert_body_q", f"has shape {q.shape}, expected ({n_bodies}, 4)")
        rows = numbers("ts_cert_body_pairs", np.zeros(0, dtype=np.int64))
        if rows.ndim != 2 or rows.shape[1] != 4:
            raise fail("ts_cert_body_pairs", f"has shape {rows.shape}, expected (contacts, 4)")
        kb = rows.shape[0]
        in_range("ts_cert_body_pairs", n, "particle", rows[:, 0])
        in_range("ts_cert_body_pairs", n + 1, "particle", rows[:, 1] + 1)
        in_range("ts_cert_body_pairs", n_walls + 1, "wall", rows[:, 2] + 1)
        if np.any((rows[:, 1] < 0) == (rows[:, 2] < 0)) or np.any((rows[:, 3] != 0) & (rows[:, 3] != 1)):
            raise fail("ts_cert_body_pairs", "holds a row that is neither a pair nor a wall "
                                             "contact, or a bond flag other than 0 or 1")
        for key, width in (("ts_cert_body_ref", 5), ("ts_cert_body_coef", 8)):
            a = numbers(key)
            if a.size != width * kb:
                raise fail(key, f"has shape {a.shape}, expected ({kb}, {width})")
            finite(key)
        dim = numbers("ts_cert_body_dim").reshape(-1)
        if dim.size != 1 or dim[0] not in (2, 3):
            raise fail("ts_cert_body_dim", f"holds {dim.tolist()}, expected [2] or [3]")
        return kb

    def _order_as(self, source_index, source: str):
        """Renumber the particles as a checkpoint's (its ``source_index``: the input row
        of each of its particles; a run that sorted them saved them in another order
        than this Simulation, built from the case, has)."""
        if source_index is None:
            return
        target = np.asarray(source_index)
        current = (np.arange(len(self.r)) if self.source_index is None
                   else np.asarray(self.source_index))
        if target.shape != current.shape or not np.issubdtype(target.dtype, np.integer) \
                or not np.array_equal(np.sort(target), np.sort(current)):
            raise InputError(f"{source}: the checkpoint's particles do not match the simulation")
        if np.array_equal(target, current):
            return
        # (input rows are a permutation of 0..N-1: where each row is now)
        self.reorder(inverse_order(current)[target])

    def timestep_state(self) -> dict:
        """Arrays of the 'auto' time-step control that a restart needs to continue bit for
        bit (the last critical mode, a start of the damped iteration, and the contacts the
        last estimate covered), keyed ``ts_*``."""
        out = {}
        mode = getattr(self, "_dt_mode", None)
        if mode is not None:
            out["ts_mode"] = mode
        cert = getattr(self, "_dt_cert", None)
        if cert is not None:
            out.update(cert.state())
        for name, (keys, assumed) in (getattr(self, "_dt_cover", None) or {}).items():
            out[f"ts_cover_{name}_keys"] = keys
            out[f"ts_cover_{name}_overlap"] = assumed
        added = self.__dict__.get("_added_record")
        if cert is not None and added is not None:  # (None: not known, not saved)
            out["ts_added_known"] = np.array([1.0])
            for name, (keys, assumed) in added.items():
                out[f"ts_added_{name}_keys"] = keys
                out[f"ts_added_{name}_overlap"] = assumed
        if out:
            out["ts_check_budget"] = np.array([self._check_budget])
            if cert is not None and cert.has_bodies and self._check_q is not None:
                out["ts_turn_budget"] = np.array([self._turn_budget])
                out["ts_check_q"] = self._check_q
        if self.dt_certified is not None:  # (the motion limit may hold dt below it)
            out["ts_dt_certified"] = np.array([self.dt_certified])
        return out

    def _check_added_record(self, data: dict, fail):
        """The record of added contacts of a checkpoint (:meth:`timestep_state`): per
        kind, integer keys naming pairs i < j of the particles or particle-wall contacts
        (:meth:`_pair_keys`, :meth:`_wall_keys`) and one finite overlap each; raises
        ``fail(key, what)``."""
        n, base = len(self.r), self._walls_per_key
        for name in ("pairs", "walls"):
            key = f"ts_added_{name}_keys"
            if key not in data:
                continue
            keys = np.asarray(data[key])
            overlap = np.asarray(data.get(f"ts_added_{name}_overlap", np.zeros(0)))
            if keys.ndim != 1 or keys.dtype.kind not in "iu" or overlap.shape != keys.shape \
                    or not np.isfinite(overlap).all():
                raise fail(key, f"has {keys.dtype} keys of shape {keys.shape} and overlaps of "
                                f"shape {overlap.shape}, expected integer keys and one finite "
                                f"overlap each")
            keys = keys.astype(np.int64)
            first, second = (keys // n, keys % n) if name == "pairs" else (keys // base,
                                                                           keys % base)
            bad = (keys < 0) | (first >= n) | ((first >= second) if name == "pairs" else False)
            if bad.any():
                what = "pair of particles i < j" if name == "pairs" else "particle and wall"
                raise fail(key, f"holds the key {int(keys[bad][0])}, no {what} ({n} "
                                f"particles, {base} walls)")

    @staticmethod
    def _restored_added_record(data: dict) -> dict | None:
        """The record of the contacts added to the certificate since its estimate
        (:meth:`timestep_state`, checked by :meth:`_check_added_record`; None: not known,
        so not used: a checkpoint from before it was saved)."""
        if "ts_added_known" not in data:
            return None
        return {name: (np.asarray(data[f"ts_added_{name}_keys"], dtype=np.int64),
                       np.asarray(data[f"ts_added_{name}_overlap"], dtype=np.float64))
                for name in ("pairs", "walls") if f"ts_added_{name}_keys" in data}

    def restore_timestep_state(self, data: dict):
        """Inverse of :meth:`timestep_state`."""
        self._dt_mode = np.array(data["ts_mode"]) if "ts_mode" in data else None
        from demstep.timestep.certificate import StepCertificate

        self._dt_cert = StepCertificate.from_state(data) if "ts_cert" in data else None
        cover = {}
        for name in ("pairs", "walls"):
            if f"ts_cover_{name}_keys" in data:
                cover[name] = (np.array(data[f"ts_cover_{name}_keys"]),
                               np.array(data[f"ts_cover_{name}_overlap"]))
        # (the pair loops' cover arrays are part of the saved state: not synced here)
        self._cover_record = cover if cover or "ts_mode" in data else None
        self._added_record = self._restored_added_record(data)
        budget = np.asarray(data.get("ts_check_budget", [0.0]), dtype=np.float64).reshape(-1)
        if budget.size != 1 or not budget[0] >= 0.0:  # (older checkpoints: checked at once)
            raise InputError(f"ts_check_budget: expected one number >= 0, got {budget}")
        self._check_budget = float(budget[0])
        self._turn_budget, self._check_q = 0.0, None  # (older checkpoints: checked at once)
        if "ts_turn_budget" in data and "ts_check_q" in data:
            turn = np.asarray(data["ts_turn_budget"], dtype=np.float64).reshape(-1)
            q = np.asarray(data["ts_check_q"], dtype=np.float64)
            if turn.size != 1 or not turn[0] >= 0.0:
                raise InputError(f"ts_turn_budget: expected one number >= 0, got {turn}")
            if q.shape != self.bodies.q.shape or not np.isfinite(q).all():
                raise InputError(f"ts_check_q: expected {self.bodies.q.shape[0]} finite "
                                 f"orientations (bodies, 4), got shape {q.shape}")
            self._turn_budget, self._check_q = float(turn[0]), q

    def _uncovered(self, steps: float = 0.0):
        """Masks over the pair and wall lists of the closed contacts the last 'auto'
        estimate did not cover (or covered at a smaller overlap than they have now,
        for a non-linear law); None when there was no estimate. ``steps`` > 0: those
        closing so within that many steps at the velocities now too
        (:meth:`_step_moves`)."""
        cover = getattr(self, "_dt_cover", None)
        if cover is None:
            return None
        from demstep.timestep.certificate import uncovered_pairs, uncovered_walls

        move, boundary = self._step_moves()
        move *= steps
        boundary *= steps
        nonlinear = self.law.law_id != 0  # a non-linear law stiffer than assumed
        none = (np.zeros(0, dtype=np.int64), np.zeros(0))
        known, assumed = cover.get("pairs", none)
        pair_mask = uncovered_pairs(self.x, self.r, self.pi, self.pj, self.periodic_len,
                                    known, assumed, nonlinear, move, boundary)
        known, assumed = cover.get("walls", none)
        wall_mask = uncovered_walls(self.x, self.r, self.wp, self.ww, self.wall_point,
                                    self.wall_normal, self._walls_per_key,
                                    np.asarray(known, dtype=np.int64),
                                    np.asarray(assumed, dtype=np.float64), nonlinear,
                                    move, boundary)
        return pair_mask, wall_mask

    def _step_moves(self, particles=None) -> tuple[np.ndarray, float]:
        """(move, boundary) [L]: how far each particle (or each of the indices
        ``particles``) moves in a step of dt at its velocity now, |v| dt, and how far
        the walls and the periodic box moved in the last step (as
        :func:`demstep.kernels.dem.closing_beyond_cover` takes them)."""
        dt = float(self.dt) if self.dt is not None else 0.0
        move = dt * np.linalg.norm(self.v if particles is None else self.v[particles], axis=-1)
        boundary = (float(np.sqrt((self.wall_state.disp_prev ** 2).sum(axis=1)).max(initial=0.0))
                    + float(np.abs(self.box.sums[5]).sum()))
        return move, boundary

    @property
    def _dt_cover(self) -> dict | None:
        """The contacts the last 'auto' estimate covered: {'pairs': (keys, overlaps),
        'walls': ...}, keys sorted (None before the first estimate). Setting it syncs
        the pair loops' cover arrays (:meth:`_sync_cover`)."""
        return self.__dict__.get("_cover_record")

    @_dt_cover.setter
    def _dt_cover(self, cover: dict | None):
        self._cover_record = cover
        self._sync_cover()

    def _sync_cover(self, reset: bool = True):
        """Each pair's and wall pair's cover (``pairs.cover``, ``wall_state.cover``: the
        largest overlap [L] the last estimate covered it at; any overlap with the linear
        law; 0 when not covered) from the record of the contacts it covered, for the pair
        loops to count the contacts that close beyond it; none tracked without a record.
        ``reset``: the count starts again (the record has just been checked)."""
        cover = self._dt_cover
        if cover is None:
            self.pairs = self.pairs._replace(cover=np.zeros(0))
            self.wall_state = self.wall_state._replace(cover=np.zeros(0))
        else:
            from demstep.timestep.certificate import cover_limits

            nonlinear = self.law.law_id != 0
            ws = self.wall_state
            self.pairs = self.pairs._replace(cover=cover_limits(
                self._pair_keys(self.pairs.i, self.pairs.j), *cover.get("pairs", _NO_COVER),
                nonlinear))
            self.wall_state = ws._replace(cover=cover_limits(
                self._wall_keys(ws.p, ws.wall), *cover.get("walls", _NO_COVER),
                nonlinear))
        if reset:
            self.counters[3] = 0.0

    def _uncovered_now(self):
        """:meth:`_uncovered`, the contacts to add to the certificate before the next
        step: skipped (none) when the steps counted no contact closed beyond its cover
        since the last check (:func:`demstep.kernels.dem._advance` looks at the
        positions each step ends with, and a rebuild at its new pairs). The cover is
        synced after a check."""
        if getattr(self, "_dt_cover", None) is None:
            return None
        tracked = (len(self.pairs.cover) == len(self.pairs.i)
                   and len(self.wall_state.cover) == len(self.wall_state.p))
        if tracked and self.counters[3] == 0:
            return np.zeros(len(self.pairs.i), dtype=bool), np.zeros(len(self.wall_state.p),
                                                                      dtype=bool)
        return self._uncovered(self.LOOKAHEAD_STEPS)

    #: 'auto': a check finds the contacts closing beyond their cover within this many
    #: steps at the velocities now (the steps look one ahead), and covers them that far
    #: ahead (a non-linear law's stiffness taken there), so that a contact pressing on
    #: is not found again at the next step
    LOOKAHEAD_STEPS = 3

    def _still_certified(self) -> bool:
        """The check of the 'auto' control between estimates: False when there was no
        estimate, or when a contact is closed that the last one did not cover
        (:meth:`_uncovered_now`) and :meth:`_certify_added` cannot add it, or when the
        covered contacts' normals turned so far that the certificate no longer holds at
        dt (:mod:`demstep.timestep.certificate`; checked once the pairs' ends may have
        moved as far as its drift budget allows, :meth:`_renew_drift_budget`: the
        certificate holds at every step in between; with clumps, also once the bodies
        may have turned as far as it allows, looked at after every step). A certificate
        restored without what its drift needs asks for a new estimate. The steps look for
        contacts closed beyond their cover at the positions they end with; the lists
        are compared with the record only when they found some."""
        masks = self._uncovered_now()
        if masks is None:
            return False
        if masks[0].any() or masks[1].any():
            covered = self._certify_added(*masks)
            if covered:
                self._sync_cover()
            return covered
        if self.counters[3]:
            self._sync_cover()
        cert = getattr(self, "_dt_cert", None)
        if cert is None or self.dt is None:
            return True
        if not cert.bounded:
            return False
        if dem.drift_used(self.counters) <= self._check_budget and (
                not cert.has_bodies or self._turned_since_check() <= self._turn_budget):
            return True
        return self._renew_drift_budget()

    #: 'auto' with clumps: the most the bodies may turn (|dR - I|) and the pairs' ends
    #: move relative to each other (this fraction of the smallest radius) between two
    #: checks of the drift (the look-ahead's lever arms take them at these caps: small
    #: caps keep its bound close to the drift now, which it stands for at each check)
    BODY_TURN_CAP = 0.02
    BODY_MOVE_CAP = 0.02

    def _turned_since_check(self) -> float:
        """How far the bodies turned since the last check of the drift: the largest
        |dR - I| = 2 sin(theta / 2), twice the vector part of q q_check^* (over the
        two lengths)."""
        q, p = self.bodies.q, self._check_q
        if p is None:
            return math.inf
        vec = p[:, :1] * q[:, 1:] - q[:, :1] * p[:, 1:] - np.cross(q[:, 1:], p[:, 1:])
        size = np.linalg.norm(q, axis=1) * np.linalg.norm(p, axis=1)
        return float(np.max(2.0 * np.linalg.norm(vec, axis=1) / size, initial=0.0))

    #: 'auto' with bonds: the budget of relative motion between checks of the drift is
    #: at most this fraction of the smallest radius (the bound on a bond's arms takes
    #: it; a contact's arms are at most the radii, whatever the motion)
    DRIFT_BUDGET_CAP = 0.1

    def _renew_drift_budget(self) -> bool:
        """Check the drift of the 'auto' certificate now (whether it still certifies dt,
        :meth:`demstep.timestep.certificate.StepCertificate.certifies`) and, if it does,
        set the budget: how far [L] the pairs' ends may move relative to each other
        before the next check with dt still certified at every position on the way
        (:meth:`~demstep.timestep.certificate.StepCertificate.drift_budget`; the
        kernels add up how far they can have moved, ``counters[4]``, and end their
        chunk of steps there). No checks are counted in steps: a quasi-static packing
        goes a long way between them, a fast flow checks often, and no drift relies on
        the slack of the safety factor. False (a new estimate is due) when the
        certificate fails now."""
        cert = getattr(self, "_dt_cert", None)
        self.counters[dem.DRIFT_SUM] = 0.0
        self.counters[dem.DRIFT_OFFSET], self.counters[dem.DRIFT_WALL_OFFSET] = \
            self._displacements()
        if cert is None or self.dt is None or not cert.bounded:
            self._check_budget = math.inf
            return True
        sigma = self._certified_sigma()
        if cert.has_bodies:  # the bodies' turn budgeted too (looked at after every step)
            self._check_q = self.bodies.q.copy()
            self._check_budget, self._turn_budget = cert.body_budgets(
                sigma, self.x, self.periodic_len, (self.wall_point, self.wall_normal),
                self._body_pose(), self.BODY_MOVE_CAP * float(self.r.min(initial=math.inf)),
                self.BODY_TURN_CAP)
            if self._check_budget > 0.0 or self._turn_budget > 0.0:
                return True  # (room left at the look-ahead's bound, above the drift now)
            return cert.certifies(sigma, self._drift(cert))
        if not cert.certifies(sigma, self._drift(cert)):
            self._check_budget = 0.0
            return False
        cap = (self.DRIFT_BUDGET_CAP * float(self.r.min(initial=math.inf))
               if cert.pair_bond.any() else math.inf)
        self._check_budget = cert.drift_budget(
            sigma, self.x, self.periodic_len, (self.wall_point, self.wall_normal), cap)
        return True

    def _contacts_covered(self) -> bool:
        """Whether every contact closed now was part of the last 'auto' estimate, at no
        larger overlap than it assumed (False also when there was no estimate)."""
        masks = self._uncovered()
        return masks is not None and not (masks[0].any() or masks[1].any())

    def _certify_added(self, pair_mask, wall_mask) -> bool:
        """Whether dt stays certified with the uncovered contacts added, without a new
        estimate (:mod:`demstep.timestep.certificate`): the added contacts count by the
        largest of their elements with each particle's whole mass, k + sigma c
        (Rayleigh's theorem on them alone, Weyl's inequality for the sum), on top of the
        last estimate's certificate and the drift of its normals. If dt stays certified
        the cover and the certificate are extended to them (True). Else False: a full
        estimate is due."""
        cert = getattr(self, "_dt_cert", None)
        if cert is None or self.dt is None:
            return False
        sigma = self._certified_sigma()
        added, overlaps = self._contacts_of(pair_mask, wall_mask)
        if added.n == 0:
            return True
        # the longest arms the contacts can have (they lengthen as a contact opens)
        added = replace(added, arm_i=self.r[added.i].copy(),
                        arm_j=np.where(added.j >= 0, self.r[np.maximum(added.j, 0)], 0.0))
        from demstep.timestep.certificate import added_contacts_bound, merge_cover

        particles, bodies = self.particles_now(check=False), self.rigid_bodies()
        add_k, add_c = added_contacts_bound(particles, added, self.rotation, bodies)
        # Weyl: this group on top of the groups added before
        add_k, add_c = cert.add_k + add_k, cert.add_c + add_c
        keys = {}
        for name, mask in (("pairs", pair_mask), ("walls", wall_mask)):
            if mask.any():
                keys[name] = (self._pair_keys(self.pi[mask], self.pj[mask]) if name == "pairs"
                              else self._wall_keys(self.wp[mask], self.ww[mask]))
        record = self.__dict__.get("_added_record")
        if record is not None:  # or all the contacts added since the estimate as one group
            record = dict(record)
            for name, k in keys.items():
                record[name] = merge_cover(*record.get(name, _NO_COVER), k, overlaps[name])
            union_k, union_c = added_contacts_bound(particles, self._added_contacts(record),
                                                    self.rotation, bodies)
            add_k, add_c = min(add_k, union_k), min(add_c, union_c)
        drift = self._drift(cert)
        if sigma * sigma < cert.bound(sigma, drift, added=(add_k, add_c)):
            return False
        cert.set_added(add_k, add_c)
        self._added_record = record
        # certified at sigma for the enlarged set: extend the cover
        cover = self._dt_cover
        for name, k in keys.items():
            cover[name] = merge_cover(*cover.get(name, _NO_COVER), k, overlaps[name])
        self.n_dt_extensions = getattr(self, "n_dt_extensions", 0) + 1
        return self._renew_drift_budget()

    def _added_contacts(self, record: dict) -> ContactSet:
        """The contacts of a record of added ones ({'pairs': (keys, overlaps), 'walls':
        ...}, as the cover's) as a ContactSet for :func:`added_contacts_bound
        <demstep.timestep.certificate.added_contacts_bound>`: the coefficients of the
        overlaps recorded, the normals of the geometry now, the longest arms (the radii)."""
        pairs, walls = record.get("pairs", _NO_COVER), record.get("walls", _NO_COVER)
        n, base = len(self.r), self._walls_per_key
        keys = np.asarray(pairs[0], dtype=np.int64)
        wkeys = np.asarray(walls[0], dtype=np.int64)
        added = self._contact_elements(keys // n, keys % n, np.asarray(pairs[1], dtype=float),
                                       wkeys // base, wkeys % base,
                                       np.asarray(walls[1], dtype=float))
        return replace(added, arm_i=self.r[added.i].copy(),
                       arm_j=np.where(added.j >= 0, self.r[np.maximum(added.j, 0)], 0.0))

    def _contacts_of(self, pair_mask, wall_mask) -> tuple[ContactSet, dict]:
        """The pairs and wall contacts selected by the masks (closed or not) as a
        ContactSet at their current geometry, with the coefficients of the overlap they
        reach in LOOKAHEAD_STEPS steps at the velocities now (:meth:`_step_moves`; if
        they go on, the steps find them again and they are added again); and those
        overlaps [L], {'pairs': (P,), 'walls': (W,)}."""
        overlaps = {}
        move, boundary = self._step_moves()
        move *= self.LOOKAHEAD_STEPS
        boundary *= self.LOOKAHEAD_STEPS
        i, j = self.pi[pair_mask], self.pj[pair_mask]
        p, wi = self.wp[wall_mask], self.ww[wall_mask]
        if len(i):
            delta = pair_geometry_arrays(self.x, self.r, i, j, self.periodic_len)[2]
            overlaps["pairs"] = np.maximum(delta, 0.0) + move[i] + move[j] + boundary
        if len(p):
            delta = wall_geometry_arrays(self.x, self.r, p, wi, self.wall_point,
                                         self.wall_normal)[2]
            overlaps["walls"] = np.maximum(delta, 0.0) + move[p] + boundary
        return self._contact_elements(i, j, overlaps.get("pairs"), p, wi,
                                      overlaps.get("walls")), overlaps

    def _contact_elements(self, i, j, pair_overlaps, p, w, wall_overlaps) -> ContactSet:
        """The pairs (i, j) and the wall contacts (particle p, wall w) as a ContactSet at
        their geometry now (normals, arms), with the law's coefficients at the overlaps
        given [L] (and its rolling and twisting springs)."""
        dim = self.dim
        params = self.law.params()
        law_id = int(params.law)
        parts = []
        if len(i):
            d, dist, _, ai, aj, _ = pair_geometry_arrays(self.x, self.r, i, j,
                                                         self.periodic_len)
            r_star = self.r[i] * self.r[j] / (self.r[i] + self.r[j])
            inv = self.inv_m[i] + self.inv_m[j]
            m_star = np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), self.m[i])
            kn, kt, cn, ct = self._coefficients(law_id, params, pair_overlaps, r_star, m_star)
            parts.append(ContactSet(i, j, (d / dist[:, None])[:, :dim], ai, aj, kn, kt,
                                    c_n=cn, c_t=ct))
        if len(p):
            _, dist, _, arm = wall_geometry_arrays(self.x, self.r, p, w, self.wall_point,
                                                   self.wall_normal)
            kn, kt, cn, ct = self._coefficients(law_id, params, wall_overlaps, self.r[p],
                                                self.m[p])
            parts.append(ContactSet(p, np.full(len(p), -1), -self.wall_normal[w][:, :dim],
                                    arm, np.zeros(len(p)), kn, kt, w, c_n=cn, c_t=ct))
        if not parts:
            return ContactSet(np.zeros(0), np.zeros(0), np.zeros((0, dim)), np.zeros(0),
                              np.zeros(0), 0.0, 0.0)
        return with_rolling(ContactSet.concatenate(parts), self.r, self.m, self.inertia,
                            self.inv_m > 0, params)

    # --------------------------------------------------------------- running
    def every(self, n: int, callback: Callable[["Simulation"], None]):
        """Call ``callback(sim)`` every ``n`` steps (writers, monitors, user code)."""
        if int(n) < 1:
            raise InputError(f"every: interval must be >= 1, got {n!r}")
        self._triggers.append(_Trigger(int(n), callback, self.step + int(n)))

    def _energy_floor(self) -> float:
        if self.monitor.floor is not None:
            return float(self.monitor.floor)
        # strain energy of every particle at an overlap of 1e-4 radius, springs at K_max
        scale = len(self.r) * self.stiffness_max() * float(np.mean(self.r)) ** 2
        return 1e-8 * 0.5 * scale

    def prepare_lists(self):
        """Build the neighbour lists (contact history starts empty) if not built yet."""
        if not self._pairs_built:
            self._rebuild()

    def prepare(self):
        """Build neighbour lists and choose dt (done by run(); call to read sim.dt first)."""
        if self.energy_floor is None:
            self.energy_floor = self._energy_floor()
        if not self._pairs_built:
            self._rebuild()
        cert = getattr(self, "_dt_cert", None)
        if (self.timestep.mode == "auto" and cert is not None
                and not cert.made_with(self.certificate_inputs())):
            self._dt_cert = None  # made with another law or damping
            self.dt = None
        self._check_motion_limit()
        if self.dt is None or self.timestep.mode != "auto" or self.dt_certified is None:
            self._choose_dt(force=True)

    def run(self, steps: int | None = None, until: Callable[["Simulation"], bool] | None = None,
            duration: float | None = None, max_steps: int | None = None,
            check_every: int = 100, progress=None):
        """Advance ``steps`` steps, or a simulated ``duration`` [T], or until ``until(sim)``
        is true (checked every ``check_every`` steps, at most ``max_steps``). Returns the
        number of steps done.

        Raises SimulationDiverged (state saved) when the run blows up and
        EnergyBalanceError when the energy monitor is set to stop."""
        if sum(a is not None for a in (steps, until, duration)) != 1:
            raise InputError("run: give exactly one of steps, duration or until")
        self.prepare()
        if duration is not None:
            if not (math.isfinite(duration) and duration >= 0):
                raise InputError(f"run: duration must be finite and >= 0, got {duration!r}")
            if self.timestep.mode != "auto":
                steps = int(math.ceil(duration / self.dt - 1e-9))
            else:
                t_end = self.time + duration
                until = lambda s: s.time >= t_end * (1 - 1e-12)  # noqa: E731
                check_every = 1
        budget = steps if steps is not None else (max_steps if max_steps is not None else 10**12)
        if budget < 0:
            raise InputError(f"run: steps must be >= 0, got {budget}")
        if self.timestep.mode != "auto" and self._dt_cover is not None:
            self._dt_cover = None  # no contacts to watch for the 'auto' control
        params = self.law.params()
        law_id = int(params.law)
        self._size_rolling_history(params.has_rolling)
        self.wall_mu[:] = [params.mu_wall if w.friction is None else w.friction for w in self.walls]
        done = 0
        parallel = self._parallel()
        if parallel:
            warn_slow_threading_layer()
        damped = self.damping.local > 0.0 or self.damping.viscous > 0.0
        dashpot = params.has_dashpots
        next_check = self.step + check_every
        while done < budget:
            chunk = budget - done
            for t in self._triggers:
                chunk = min(chunk, t.next_step - self.step)
            chunk = min(chunk, self.monitor.every - self.step % self.monitor.every)
            if until is not None:
                chunk = min(chunk, next_check - self.step)
            if self.timestep.mode == "auto":
                chunk = min(chunk, max(1, self._next_dt_update - self.step))
                cert = getattr(self, "_dt_cert", None)
                if cert is not None and cert.has_bodies:  # (clumps: a check at every step)
                    chunk = 1
            chunk = max(1, chunk)
            controls = Controls(
                float(self.dt), float(self.dt_prev), bool(self._first), float(self.skin),
                int(self.dim), self.gravity, float(self.damping.local),
                float(self.damping.viscous), bool(damped or self._damping_history),
                bool(dashpot or self._dashpot_history), float(self.jump_limit),
                float(self.runaway_factor), float(self.energy_floor), bool(parallel),
                float(self._check_budget) if self.timestep.mode == "auto" else math.inf)
            self.pairs = self._work_space(parallel)
            n_done, reason = self.backend.advance(
                chunk, controls, self.spheres, self.bodies, self.pairs, self.bonds, self.wall_state,
                self.box,
                Ledger(self.ledger.acc, self.ledger.energy, self.counters), law_id, params)
            self._first = False
            # the damping forces of the last step are stored only while damping is on
            # (and once more after it is switched off, to clear them)
            self._damping_history = damped
            self._dashpot_history = dashpot
            self.dt_prev = self.dt
            # time from the last change of dt, so that it does not depend on where runs
            # are split (a restart continues bit for bit)
            if self.dt != self._time_ref[2]:
                self._time_ref = (self.step, self.time, self.dt)
            self.step += n_done
            self.time = self._time_ref[1] + (self.step - self._time_ref[0]) * self.dt
            done += n_done
            if progress is not None:
                progress(self, n_done)
            if reason in (dem.STOP_NONFINITE, dem.STOP_RUNAWAY, dem.STOP_JUMP):
                self._diverged(reason)
            if reason == dem.STOP_REBUILD:
                self._rebuild()
            if self.step % self.monitor.every == 0:
                try:
                    self.monitor.check(self.ledger, self.step, self.time, self.energy_floor)
                except EnergyBalanceError as exc:
                    path = self._save_emergency("energy")
                    raise EnergyBalanceError(f"{exc}; state saved to {path}", checkpoint=path) from None
            for t in self._triggers:
                if self.step >= t.next_step:
                    t.callback(self)
                    t.next_step = self.step + t.every
            if self.timestep.mode == "auto":
                if self.step >= self._next_dt_update:
                    self._choose_dt(force=True)
                elif not self._still_certified():
                    self._choose_dt(force=True, scheduled=False)
                else:
                    self._limit_motion()
            if until is not None and self.step >= next_check:
                next_check = self.step + check_every
                if until(self):
                    break
        return done

    #: below this many particles the serial kernels are faster than threaded ones
    PARALLEL_MIN_PARTICLES = 5000

    def _work_space(self, parallel: bool) -> Pairs:
        """The pair list with its work space: chunks (one per thread, about equal numbers
        of pairs), the particle range of each (:func:`dem.pair_chunks`), the band
        buffers (chunks, rows, 3) for the forces and torques a chunk adds to particles
        beyond its own (:func:`dem._pair_loop`) and, for rolling resistance, the pair
        geometry (P, 4); rebuilt when the pair list or the thread count changes. The
        band buffers and the geometry keep their memory across rebuilds while it is
        large enough (fresh pages cost a fault each)."""
        import numba

        n_chunks = numba.get_num_threads() if parallel else 1
        if self._chunks_for == n_chunks:
            return self.pairs
        pairs = self.pairs
        n_pairs = len(pairs.i)
        n = len(self.r)
        chunks, spans = self.backend.pair_chunks(pairs.i, pairs.j, n, n_chunks)
        rows = dem.band_rows(spans, n)
        force_band, torque_band = pairs.force_band, pairs.torque_band
        if force_band.shape[0] != n_chunks or force_band.shape[1] < rows:
            shape = (n_chunks, int(1.25 * rows) + 64 if n_chunks > 1 else 0, 3)
            force_band = np.zeros(shape)
            torque_band = np.zeros(shape)
        # the pair geometry is kept for the rolling-resistance loop only
        n_geo = n_pairs if pairs.roll.shape[0] > 0 else 0
        if len(self._geo_store) < n_geo:
            self._geo_store = np.empty((int(1.25 * n_geo) + 64, 4))
        self._chunks_for = n_chunks
        return pairs._replace(chunks=chunks, spans=spans, force_band=force_band,
                              torque_band=torque_band, geo=self._geo_store[:n_geo])

    def contact_forces(self):
        """Pairs in contact now: (i, j) (C, 2), the force on j (C, 3) [M L/T^2] (elastic at
        the current positions plus the stored tangential spring and dashpot forces) and
        the unit normals (C, 3) from i to j."""
        if not self._pairs_built or len(self.pi) == 0:
            return np.zeros((0, 2), dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3))
        force = np.zeros((len(self.pi), 3))
        normal = np.zeros((len(self.pi), 3))
        params = self.law.params()
        on = self.backend.pair_contact_forces(self.x, self.r, self.pi, self.pj, self.periodic_len,
                                              int(params.law), params, self.ft, self.fd,
                                              force, normal)
        return np.stack([self.pi[on], self.pj[on]], axis=1), force[on], normal[on]

    def _parallel(self) -> bool:
        import numba

        if self.parallel is not None:
            return bool(self.parallel)
        return numba.get_num_threads() > 1 and len(self.r) >= self.PARALLEL_MIN_PARTICLES

    # ------------------------------------------------------------ divergence
    def _save_emergency(self, tag: str) -> str:
        from demstep.io.checkpoint import save_checkpoint

        folder = Path(self.checkpoint_dir) if self.checkpoint_dir else Path(tempfile.gettempdir())
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"demstep-{tag}-step{self.step}.npz"
        save_checkpoint(self, path)
        return str(path)

    def _diverged(self, reason):
        what = {dem.STOP_NONFINITE: "non-finite positions or energies",
                dem.STOP_RUNAWAY: f"runaway kinetic energy ({self.ledger.kinetic:.4g}, more than "
                                  f"{self.runaway_factor:g} x the most energy supplied, "
                                  f"{runaway_reference(self.ledger.acc, self.ledger.energy):.4g})",
                dem.STOP_JUMP: f"a particle moved {self.counters[2]:.3g} radii in one step "
                               f"(limit {self.jump_limit:g})"}[reason]
        est = ""
        try:
            crit = self.critical_dt("element-coupled")
            if crit:
                est = f"; the coupled element bound on the critical step is {crit:.4g}"
        except Exception:  # the state may be non-finite
            pass
        path = self._save_emergency("diverged")
        raise SimulationDiverged(f"simulation diverged at step {self.step} (t = {self.time:.6g}, "
                                 f"dt = {self.dt:.4g}): {what}{est}; state saved to {path}",
                                 step=self.step, checkpoint=path)

    # ---------------------------------------------------------------- output
    @property
    def n_contacts(self) -> int:
        return int(self.counters[0] + self.counters[1])

    def wall_stress(self) -> np.ndarray:
        """Compressive normal stress on each wall [M/(L T^2)] (per unit thickness in 2D):
        the normal force the particles exert on the wall over its loaded area."""
        push = -np.einsum("wk,wk->w", self.wall_force, self.wall_normal)
        dem.wall_areas(self.wall_point, self.wall_normal, self.servo, self.box_lo, self.box_hi,
                       self.periodic_len, self.dim, self.wall_areas)
        return push / self.wall_areas

    def kinetic_energy(self) -> float:
        return self.ledger.kinetic

    def set_box(self, axis: int, motion: str = "fixed", rate: float = 0.0,
                target_stress: float = 0.0, servo_factor: float = 0.1, servo_gain: float = 0.0,
                max_speed: float = np.inf):
        """Motion of the periodic length along ``axis``: 'fixed'; 'rate' (dL/dt = ``rate``
        [L/T]); 'servo' (hold the Love stress at ``target_stress`` [M/(L T^2)], gain as for
        servo walls: automatic with ``servo_factor`` unless ``servo_gain`` > 0). The work
        done by the changing box enters the ledger (``work_box``)."""
        if not (0 <= axis < self.dim) or self.periodic_len[axis] <= 0:
            raise InputError(f"box axis {axis}: not a periodic axis of this simulation")
        modes = {"fixed": dem.BOX_FIXED, "rate": dem.BOX_RATE, "servo": dem.BOX_SERVO}
        if motion not in modes:
            raise InputError(f"box motion: must be fixed, rate or servo, got {motion!r}")
        for name, value in (("target_stress", target_stress), ("servo_factor", servo_factor),
                            ("servo_gain", servo_gain)):
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"box {name}: must be finite and >= 0, got {value!r}")
        if not (max_speed > 0) or not math.isfinite(rate):
            raise InputError(f"box: max_speed must be > 0 and rate finite, got {max_speed!r}, {rate!r}")
        self.box_motion[axis] = modes[motion]
        self.box_servo[axis] = (target_stress, rate if motion == "rate" else servo_gain,
                                max_speed, 0.0, servo_factor)

    def set_wall_motion(self, index: int, motion: str, velocity=None, target_stress=None,
                        servo_gain=None, servo_factor=None, max_speed=None, area=None,
                        friction=None):
        """Change wall ``index`` between stages: 'fixed', 'velocity' (``velocity`` [L/T],
        dim components) or 'servo' (``target_stress`` [M/(L T^2)], ``servo_gain``,
        ``servo_factor``, ``max_speed``, ``area`` as in :class:`demstep.walls.Wall`);
        ``friction`` overrides the law's wall friction (takes effect at the next run)."""
        wall = self.walls[index]
        modes = {"fixed": dem.WALL_FIXED, "velocity": dem.WALL_VELOCITY, "servo": dem.WALL_SERVO}
        if motion not in modes:
            raise InputError(f"wall {wall.name!r}: motion must be fixed, velocity or servo, got {motion!r}")
        if velocity is not None:
            vel = np.asarray(velocity, dtype=np.float64).reshape(-1)
            if vel.shape != (self.dim,) or not np.isfinite(vel).all():
                raise InputError(f"wall {wall.name!r}: velocity must have {self.dim} finite components")
            wall.velocity = vel
        columns = {"target_stress": dem.S_TARGET, "servo_gain": dem.S_GAIN,
                   "servo_factor": dem.S_FACTOR, "area": dem.S_AREA}
        for key, value in (("target_stress", target_stress), ("servo_gain", servo_gain),
                           ("servo_factor", servo_factor), ("area", area)):
            if value is not None:
                if not (math.isfinite(value) and value >= 0):
                    raise InputError(f"wall {wall.name!r}: {key} must be finite and >= 0, got {value!r}")
                setattr(wall, key, float(value))
                self.servo[index, columns[key]] = float(value)
        if max_speed is not None:
            if not (max_speed > 0):
                raise InputError(f"wall {wall.name!r}: max_speed must be > 0, got {max_speed!r}")
            wall.max_speed = float(max_speed)
            self.servo[index, dem.S_MAXSPEED] = float(max_speed)
        if friction is not None:
            if not (math.isfinite(friction) and friction >= 0):
                raise InputError(f"wall {wall.name!r}: friction must be finite and >= 0, got {friction!r}")
            wall.friction = float(friction)
        wall.motion = motion
        self.wall_motion[index] = modes[motion]
        self.wall_vel[index] = 0.0
        if motion == "velocity":
            self.wall_vel[index, :self.dim] = wall.velocity

    def extents(self) -> np.ndarray:
        """Specimen extents per axis [L] (periodic lengths or box-wall gaps; NaN unknown)."""
        out = np.empty(3)
        dem.box_extents(self.wall_point, self.box_lo, self.box_hi, self.periodic_len, self.dim, out)
        return out[:self.dim]

    def love_stress(self) -> np.ndarray:
        """Diagonal of the average stress from particle-particle contacts [M/(L T^2)]:
        sigma_kk = (1/V) sum over contacts of F_k d_k (Love-Weber; compression
        positive), V the box volume (area in 2D). Wall contacts are not included."""
        volume = float(np.prod(self.extents()))
        return self.box_state[0, :self.dim] / volume


#: the familiar names of the state: views of the bundles' fields (name: (bundle, field))
STATE_NAMES = {
    **{f: ("spheres", f) for f in ("x", "v", "w", "r", "m", "inertia", "inv_m", "inv_I",
                                     "force", "torque", "x_ref")},
    "applied_force": ("spheres", "applied"), "fd_prev": ("spheres", "damp_force"),
    "td_prev": ("spheres", "damp_torque"),
    "pi": ("pairs", "i"), "pj": ("pairs", "j"), "ft": ("pairs", "shear"),
    "fd": ("pairs", "dashpot"), "etan": ("pairs", "shear_energy"),
    "wp": ("wall_state", "p"), "ww": ("wall_state", "wall"), "wft": ("wall_state", "shear"),
    "wfd": ("wall_state", "dashpot"), "wetan": ("wall_state", "shear_energy"),
    "wall_point": ("wall_state", "point"), "wall_normal": ("wall_state", "normal"),
    "wall_vel": ("wall_state", "vel"), "wall_mu": ("wall_state", "mu"),
    "wall_motion": ("wall_state", "motion"), "servo": ("wall_state", "servo"),
    "wall_force": ("wall_state", "force"), "wall_force_prev": ("wall_state", "force_prev"),
    "wall_disp_prev": ("wall_state", "disp_prev"), "wall_ref": ("wall_state", "ref"),
    "wall_areas": ("wall_state", "areas"), "wall_contacts": ("wall_state", "contacts"),
    "wall_k": ("wall_state", "k_sum"), "box_lo": ("wall_state", "box_lo"),
    "box_hi": ("wall_state", "box_hi"),
    "periodic_len": ("box", "length"), "box_motion": ("box", "motion"),
    "box_servo": ("box", "servo"), "box_ref": ("box", "ref"), "box_state": ("box", "sums"),
}


def _state_view(bundle: str, field: str) -> property:
    def get(self):
        return getattr(getattr(self, bundle), field)

    def put(self, value):
        setattr(self, bundle, getattr(self, bundle)._replace(**{field: value}))

    return property(get, put, doc=f"``{bundle}.{field}``")


for _name, (_bundle, _field) in STATE_NAMES.items():
    setattr(Simulation, _name, _state_view(_bundle, _field))
