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

   12. (Python) insertion and outflow on their schedules (:mod:`demstep.engine.feed`): the
       particles leaving are removed with their contacts, the new ones placed where
       they touch nothing, the lists rebuilt and, in 'auto' mode, the step certified
       for the new set before its first step (:mod:`demstep.engine.population`)

The half-step velocity is initialised at the first step by a half backward kick,
v(-dt/2) = v(0) - dt/2 F(0)/m, so the given initial velocities are those at t = 0.
Disks (2D) are integrated in the plane z = 0 with rotation about z.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from demstep._numba import warn_slow_threading_layer
from demstep.backend import get_backend
from demstep.clumps import with_members
from demstep.contact.laws import ContactLaw, LinearSpring
from demstep.timestep.contacts import ContactSet
from demstep.energy import EnergyBalanceError, EnergyLedger, EnergyMonitor, runaway_reference
from demstep.engine import analysis, boundaries
from demstep.engine.auto_step import AutoStep
from demstep.engine.bonding import add_bonds, bond_stiffness_max
from demstep.engine.boundaries import walls_bundle
from demstep.engine.lists import NeighbourLists
from demstep.engine.meshes import mesh_law_rows, meshes_bundle, rotation_axis, set_mesh_motion
from demstep.engine.ordering import SpatialOrder, order_as, reorder
from demstep.engine.population import adopt_particle_set, switch_mesh
from demstep.engine.restore import SCALARS, checked_state, scalar_arrays
from demstep.engine.settings import Damping, TimeStep
from demstep.errors import InputError, SimulationDiverged
from demstep.engine.feed import Feed
from demstep.io.checkpoint import save_checkpoint
from demstep.kernels import dem
from demstep.kernels.clumps import member_velocities
from demstep.particles import Particles
from demstep.state import ROLL_WIDTH, Bodies, Bonds, Box, Controls, Ledger, Pairs, Spheres
from demstep.timestep.estimates import element_coupled_dt
from demstep.timestep.exact import exact_critical_step

log = logging.getLogger("demstep")


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
                 source_index=None, sort_every: int | None = None, meshes=(), feed=()):
        bodies = None
        self.n_free = particles.n if particles is not None else 0
        if clumps is not None:
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
        feed = list(feed)
        if skin is None:  # (no particles yet: the inserted ones' mean size)
            sizes = self.r if len(self.r) else np.array(
                [0.5 * (f.radius.min + f.radius.max) for f in feed if hasattr(f, "radius")] or [0.0])
            skin = 0.15 * float(sizes.mean())
        self.skin = float(skin)
        if not (math.isfinite(self.skin) and self.skin > 0):
            raise InputError(f"skin: must be finite and > 0, got {skin!r}")
        self.walls = list(walls)
        #: triangle-mesh walls (:class:`demstep.engine.meshes.MeshWall`), in one bundle
        self.mesh_walls = list(meshes)
        self.meshes = meshes_bundle(self.mesh_walls, self.law)
        self.wall_state = walls_bundle(self.walls, self.dim, self.box.length, self.x, self.r,
                                       self.particle_id)
        self.update_masses()
        self.backend = get_backend(backend)
        self.ledger = EnergyLedger()
        #: the compiled step's counters (names: :mod:`demstep.kernels.dem`, COUNT_*)
        self.counters = np.zeros(dem.N_COUNTERS)
        self.pairs = Pairs.empty(n)
        self.bonds = Bonds.empty()
        self.step = 0
        self.time = 0.0
        self.dt: float | None = None
        #: the step [T] of the last call of the compiled step (0 before the first)
        self.dt_prev = 0.0
        self._time_ref = (0, 0.0, None)  # (step, time, dt) when dt last changed
        #: the first step initialises the half-step velocities (a half backward kick)
        self.first_step_pending = True
        self._triggers: list[_Trigger] = []
        #: whether the damping forces of the last step (Spheres.damp_*) and the pair
        #: dashpot forces may be non-zero: not at the start; checkpoint restarts set them
        self.damping_history = False
        self.dashpot_history = False
        #: the energy below which the balance is not evaluated (:meth:`prepare`)
        self.energy_floor: float | None = None
        # the parts that act between chunks of steps, each owning its state
        self.lists = NeighbourLists(self)
        self.ordering = SpatialOrder(self, sort_every)
        self.auto = AutoStep(self)
        #: particles inserted and removed during the run (:mod:`demstep.engine.feed`)
        self.feed = Feed(self)
        for item in feed:
            self.feed.add(item)


    # ------------------------------------------------------------------ setup
    def particle_id(self, k: int) -> int:
        """How messages and outputs name particle ``k``: its input row when the
        particles were reordered (``source_index``), else k itself."""
        return int(k if self.source_index is None else self.source_index[k])

    def particle_ids(self) -> np.ndarray:
        """Every particle's name (:meth:`particle_id`) as an array (N,)."""
        if self.source_index is None:
            return np.arange(len(self.r), dtype=np.int64)
        return self.source_index

    def update_masses(self):
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
        self.update_masses()
        self.dt = None
        self.auto.certificate = None  # certified for the old masses

    def add_bonds(self, bonds, pairs=None) -> int:
        """Bond particles with parallel bonds (:func:`demstep.engine.bonding.add_bonds`);
        returns the number of bonds added."""
        return add_bonds(self, bonds, pairs)

    def reorder(self, order) -> None:
        """Renumber the particles: new particle k is old particle ``order[k]``
        (:func:`demstep.engine.ordering.reorder`)."""
        reorder(self, order)

    def pairs_changed(self):
        """The pair list was changed in place of a rebuild (renumbered, restored)."""
        self.lists.changed()

    @property
    def sort_every(self) -> int | None:
        """Steps between looks at the particles' order in memory (None: never;
        :class:`demstep.engine.ordering.SpatialOrder`)."""
        return self.ordering.every

    # ------------------------------------------------------------- time step
    @property
    def m_min(self) -> float:
        """The lightest free particle's or body's mass [M]."""
        free = ~self.fixed & (self.bodies.sphere_body < 0)
        masses = [self.m[free]]
        if self.bodies.n:
            masses.append(self.bodies.m[self.bodies.inv_m > 0])
        masses = np.concatenate(masses + [[self.feed.min_mass()]])
        return float(masses.min()) if np.isfinite(masses.min()) else float(self.m.min())

    def radius_max(self) -> float:
        """The largest radius [L] of the particles now and of those the feed can insert."""
        return max(float(self.r.max(initial=0.0)), self.feed.max_radius())

    def stiffness_max(self) -> float:
        """K_max for alpha: the law's largest stiffness (Hertz: at the TimeStep overlap),
        plus an intact bond's normal or shear stiffness k^b A (its springs add to the
        contact's: counted as their sum)."""
        k = float(self.law.stiffness_bound(self.radius_max(), self.timestep.overlap))
        return k + bond_stiffness_max(self)

    def contact_set(self, horizon: float | None = None, cover: dict | None = None) -> ContactSet:
        """The contacts as the time-step analysis takes them
        (:func:`demstep.engine.analysis.contact_set`)."""
        return analysis.contact_set(self, horizon, cover)

    def bond_elements(self) -> list:
        """The intact bonds as contact elements (:func:`demstep.engine.analysis.bond_elements`)."""
        return analysis.bond_elements(self)

    def particles_now(self, check: bool = True) -> Particles:
        """The particles now (:func:`demstep.engine.analysis.particles_now`)."""
        return analysis.particles_now(self, check)

    def rigid_bodies(self):
        """The clumps now (:func:`demstep.engine.analysis.rigid_bodies`), None without."""
        return analysis.rigid_bodies(self)

    def critical_dt(self, method: str = "exact", rotation: bool = True,
                    horizon: float | None = None, tol: float | None = None) -> float | None:
        """Critical step [T] by ``method`` ('exact' or 'element-coupled') of the contacts
        closed now, or with ``horizon`` [T] of every contact that can close within it
        (:meth:`contact_set`), with the law's dashpots and the global viscous damping
        (the damped step of :mod:`demstep.timestep.damping`); None without contacts.
        The damped iteration tries the 'auto' control's last critical mode as a start
        (the solves that certify start cold: demstep.timestep.exact.CHAIN_MIX);
        ``tol``: its relative residual (None: :data:`demstep.timestep.eigen.EIGSH_TOL`; a
        looser one certifies a step up to about 4 ``tol`` below the critical one,
        sooner). Nothing is recorded: the 'auto' control's estimates are
        :meth:`demstep.engine.auto_step.AutoStep.solve`."""
        if method not in ("exact", "element-coupled"):
            raise InputError(f"method: must be exact or element-coupled, got {method!r}")
        contacts = self.contact_set(horizon)
        if contacts.n == 0:
            return None
        rotation = rotation and self.rotation
        if method == "element-coupled":
            return element_coupled_dt(self.particles_now(check=False), contacts, rotation,
                                      damping=analysis.global_damping(self),
                                      bodies=self.rigid_bodies())
        extra = {} if tol is None else {"tol": float(tol)}
        return exact_critical_step(self.particles_now(check=False), contacts, rotation,
                                   analysis.global_damping(self), v0=self.auto.mode,
                                   bodies=self.rigid_bodies(), workspace=self.auto.workspace,
                                   **extra).dt

    def _choose_dt(self):
        """dt for the next steps: the TimeStep's fixed one, alpha sqrt(m_min / K_max), or
        'auto' (:meth:`demstep.engine.auto_step.AutoStep.propose_dt`)."""
        ts = self.timestep
        if ts.mode == "auto":
            self.auto.propose_dt(force=True)
            return
        self.auto.certified = None  # (an 'auto' mode after this one estimates anew)
        if ts.mode == "fixed":
            self.dt = float(ts.dt)
        else:
            self.dt = ts.alpha * math.sqrt(self.m_min / self.stiffness_max())

    def _check_motion_limit(self):
        """The divergence limit ``jump_limit`` must be > 0 (inf: none), and above the
        'auto' motion limit (else the control would choose steps the check stops)."""
        if not self.jump_limit > 0.0:  # (inf: no check)
            raise InputError(f"jump_limit: must be > 0, got {self.jump_limit!r}")
        ts = self.timestep
        if ts.mode == "auto" and not ts.motion < self.jump_limit:
            raise InputError(f"timestep motion: must be below jump_limit = {self.jump_limit:g} "
                             f"(the divergence check), got {ts.motion!r}")

    # 'auto': what the control reports, read and set through it
    dt_certified = property(lambda self: self.auto.certified,
                            lambda self, v: setattr(self.auto, "certified", v),
                            doc="'auto': the certified step [T], the ceiling of dt")
    dt_estimate = property(lambda self: self.auto.estimate,
                           doc="'auto': the certified critical step of the last estimate [T]")
    dt_horizon = property(lambda self: self.auto.horizon,
                          doc="'auto': the horizon [T] of the last estimate")
    n_dt_solves = property(lambda self: self.auto.n_solves,
                           doc="'auto': estimates by an exact solve")
    n_dt_element = property(lambda self: self.auto.n_element,
                            doc="'auto': 'exact' estimates the coupled element bound decided")
    n_dt_refreshes = property(lambda self: self.auto.n_refreshes,
                              doc="'auto': estimates the last certificate still gave")
    n_dt_estimates = property(lambda self: self.auto.n_estimates, doc="'auto': estimates")
    n_dt_extensions = property(lambda self: self.auto.n_extensions,
                               doc="'auto': contacts added to a certificate without an estimate")

    # ---------------------------------------------------------------- state
    #: the bundles whose STATE fields make the dynamic state (:meth:`state_dict`)
    BUNDLES = ("spheres", "bodies", "pairs", "bonds", "wall_state", "meshes", "box")

    def state_dict(self) -> dict:
        """The complete dynamic state as named arrays (what a checkpoint saves): the
        STATE fields of every bundle as ``bundle.field``, the ledger, gravity, radii and
        fixed flags (to check a restore), the scalars (step, time, dt, ...), the law's
        parameters, the energy monitor's alarm state, and the state of the parts that
        own some (the 'auto' control's ``ts_*``, the particles' order)."""
        if not self.lists.built:
            self.lists.rebuild()
        out = {}
        for name in self.BUNDLES:
            bundle = getattr(self, name)
            for f in bundle.STATE:
                out[f"{name}.{f}"] = getattr(bundle, f)
        out.update({"ledger.acc": self.ledger.acc, "ledger.energy": self.ledger.energy,
                    "ledger.counters": self.counters, "gravity": self.gravity, "r": self.r,
                    "fixed": self.fixed, "law": np.asarray(self.law.params()),
                    "monitor": self.monitor.state()})
        values = (self.step, self.time, self.dt, self.dt_prev, self.first_step_pending,
                  self.monitor.max_error, self.auto.next_update, self.auto.estimate,
                  *self._time_ref)
        out.update({f"scalars.{name}": np.array([np.nan if v is None else float(v)])
                    for name, v in zip(SCALARS, values)})
        out.update(self.auto.state_dict())
        if self.source_index is not None:  # the order of the arrays (sorted in a run)
            out["source_index"] = self.source_index
        out.update(self.ordering.state_dict())
        if self.feed:
            out.update(self.feed.state_dict())
        return out

    def load_state_dict(self, data: dict, source: str = "state"):
        """Restore :meth:`state_dict` into this Simulation (built from the same case:
        the same particles and walls, else InputError naming ``source``)."""
        needed = [f"{n}.{f}" for n in self.BUNDLES for f in getattr(self, n).STATE]
        needed += ["ledger.acc", "ledger.energy", "ledger.counters", "gravity", "r"]
        needed += [f"scalars.{name}" for name in SCALARS]
        data = scalar_arrays(data)
        for name in ("pairs", "wall_state"):  # checkpoints from before rolling resistance
            data.setdefault(f"{name}.roll", np.zeros((0, ROLL_WIDTH)))
        old_cover = "pairs.cover" not in data  # and from before the cover was tracked
        for name in ("pairs", "wall_state"):
            data.setdefault(f"{name}.cover", np.zeros(0))
        for f in Bonds.STATE:  # and from before bonds
            data.setdefault(f"bonds.{f}", getattr(Bonds.empty(), f))
        if not self.mesh_walls:  # and from before meshes (a case without meshes)
            for f in self.meshes.STATE:
                data.setdefault(f"meshes.{f}", getattr(self.meshes, f))
        data.setdefault("meshes.surface", np.zeros_like(self.meshes.surface))  # (and from
        # before surface velocities: none; before the 'auto' step covered meshes: none)
        data.setdefault("meshes.cover_ctl", np.array([0.0, np.inf, 0.0, 0.0]))
        data.setdefault("meshes.wear", np.zeros(len(self.meshes.tri)))  # (before wear)
        if "meshes.omega" in data:  # (before the axis was kept: omega's, z for none)
            data.setdefault("meshes.axis", np.array(
                [rotation_axis(om) for om in np.asarray(data["meshes.omega"]).reshape(-1, 3)]
            ).reshape(-1, 3))
        if "meshes.cand_p" in data:  # (before rolling resistance on meshes: none)
            data.setdefault("meshes.roll", np.zeros((len(data["meshes.cand_p"]), ROLL_WIDTH)))
        missing = [k for k in needed if k not in data]
        if missing:
            raise InputError(f"{source}: a damaged checkpoint (array {missing[0]!r} missing)")
        if self.feed:  # (particles came and went: the checkpoint's set)
            adopt_particle_set(self, data, source)
        data = checked_state(self, data, source)
        order_as(self, data.get("source_index"), source)
        if not np.array_equal(data["r"], self.r):
            raise InputError(f"{source}: the checkpoint's particles do not match the simulation")
        for name in self.BUNDLES:
            bundle = getattr(self, name)
            setattr(self, name, bundle._replace(**{
                f: np.ascontiguousarray(data[f"{name}.{f}"]) for f in bundle.STATE}))
        # (the candidates' distances at the build are not saved: every row is computed
        # until the next build, which gives the same forces)
        self.meshes = self.meshes._replace(cand_d=np.zeros(len(self.meshes.cand_p)))
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
        step, time, dt, dt_prev, first, max_err, next_dt, dt_est, t_step, t_time, t_dt = (
            float(data[f"scalars.{name}"][0]) for name in SCALARS)
        self.step = int(step)
        self.time = float(time)
        self.dt = None if np.isnan(dt) else float(dt)
        self.dt_prev = float(dt_prev)
        self.first_step_pending = bool(first)
        self.monitor.max_error = float(max_err)
        self._time_ref = (int(t_step), float(t_time), None if np.isnan(t_dt) else float(t_dt))
        self.ordering.load_state_dict(data, self.step)
        self.feed.load_state_dict(data, source)
        self.auto.load_state_dict({k: data[k] for k in data if k.startswith("ts_")}, source)
        self.auto.next_update = int(next_dt)
        self.auto.estimate = None if np.isnan(dt_est) else float(dt_est)
        if old_cover:
            self.auto.sync_cover(reset=False)
        self.damping_history = True  # restored damping forces of the last step
        self.dashpot_history = True  # and pair dashpot forces
        self.update_masses()
        self.lists.changed()
        self.lists.built = True
        self.energy_floor = None
        for t in self._triggers:  # the next multiple of each interval, as in an unbroken run
            t.next_step = (self.step // t.every + 1) * t.every
        return self

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
        r_mean = float(np.mean(self.r)) if len(self.r) else self.radius_max()
        scale = max(len(self.r), 1) * self.stiffness_max() * r_mean ** 2
        return 1e-8 * 0.5 * scale

    def prepare_lists(self):
        """Build the neighbour lists (contact history starts empty) if not built yet."""
        if not self.lists.built:
            self.lists.rebuild()

    def prepare(self):
        """Build neighbour lists and choose dt (done by run(); call to read sim.dt first)."""
        if self.energy_floor is None:
            self.energy_floor = self._energy_floor()
        self.prepare_lists()
        if self.timestep.mode == "auto":
            self.auto.prepare()
        self._check_motion_limit()
        if self.mesh_walls and self.law.params().has_rolling and self.timestep.mode == "auto":
            raise InputError("timestep mode 'auto': rolling resistance on mesh walls is not "
                             "followed by the certified step's drift cover yet (use mode "
                             "'fixed' with a step from demstep dt or sim.critical_dt(), which "
                             "include the mesh contacts' rolling springs)")
        if self.mesh_walls and self.bodies.n and self.timestep.mode == "auto":
            raise InputError("timestep mode 'auto': clumps with mesh walls are not covered by "
                             "the certified step yet (use mode 'fixed' with a step from "
                             "demstep dt --mesh, or 'alpha')")
        if self.dt is None or self.timestep.mode != "auto" or self.dt_certified is None:
            self._choose_dt()

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
        if self.feed:  # (events due at the first step: a run that starts empty)
            self.feed.act()
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
        if self.timestep.mode != "auto":
            self.auto.release()  # no contacts to watch for the 'auto' control
        params = self.law.params()
        self.lists.size_rolling_history(params.has_rolling)
        self.wall_mu[:] = [params.mu_wall if w.friction is None else w.friction for w in self.walls]
        self.meshes.law[:] = mesh_law_rows(self.mesh_walls, self.law)
        done = 0
        parallel = self.threaded()
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
            if self.feed:
                chunk = min(chunk, self.feed.steps_to_next(self.step))
            if self.timestep.mode == "auto":
                chunk = min(chunk, max(1, self.auto.next_update - self.step))
                cert = self.auto.certificate
                if cert is not None and cert.has_bodies:  # (clumps: a check at every step)
                    chunk = 1
            chunk = max(1, chunk)
            controls = Controls(
                dt=float(self.dt), dt_prev=float(self.dt_prev),
                first=bool(self.first_step_pending), skin=float(self.skin), dim=int(self.dim),
                gravity=self.gravity, local_damping=float(self.damping.local),
                viscous_damping=float(self.damping.viscous),
                store_damping=bool(damped or self.damping_history),
                store_dashpot=bool(dashpot or self.dashpot_history),
                jump_limit=float(self.jump_limit), runaway_factor=float(self.runaway_factor),
                energy_floor=float(self.energy_floor), parallel=bool(parallel),
                check_budget=(float(self.auto.check_budget) if self.timestep.mode == "auto"
                              else math.inf))
            self.pairs = self.lists.work_space(parallel)
            n_done, reason = self.backend.advance(
                chunk, controls, self.spheres, self.bodies, self.pairs, self.bonds, self.wall_state,
                self.meshes, self.box,
                Ledger(self.ledger.acc, self.ledger.energy, self.counters), params)
            self.first_step_pending = False
            # the damping forces of the last step are stored only while damping is on
            # (and once more after it is switched off, to clear them)
            self.damping_history = damped
            self.dashpot_history = dashpot
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
                self.lists.rebuild()
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
                self.auto.update()
            if self.feed:
                self.feed.act()
            if until is not None and self.step >= next_check:
                next_check = self.step + check_every
                if until(self):
                    break
        return done


    #: below this many particles the serial kernels are faster than threaded ones
    PARALLEL_MIN_PARTICLES = 5000

    def threaded(self) -> bool:
        """Whether the run takes the threaded kernels (``parallel``; automatic: from
        :data:`PARALLEL_MIN_PARTICLES` particles on, when numba has several threads)."""
        import numba  # (deferred: a heavy import, loaded only when used)

        if self.parallel is not None:
            return bool(self.parallel)
        return numba.get_num_threads() > 1 and len(self.r) >= self.PARALLEL_MIN_PARTICLES

    def contact_forces(self):
        """Pairs in contact now: (i, j) (C, 2), the force on j (C, 3) [M L/T^2] (elastic at
        the current positions plus the stored tangential spring and dashpot forces) and
        the unit normals (C, 3) from i to j."""
        if not self.lists.built or len(self.pi) == 0:
            return np.zeros((0, 2), dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3))
        force = np.zeros((len(self.pi), 3))
        normal = np.zeros((len(self.pi), 3))
        params = self.law.params()
        on = self.backend.pair_contact_forces(self.x, self.r, self.pi, self.pj, self.periodic_len,
                                              params, self.ft, self.fd,
                                              force, normal)
        return np.stack([self.pi[on], self.pj[on]], axis=1), force[on], normal[on]

    # ------------------------------------------------------------ divergence
    def _save_emergency(self, tag: str) -> str:
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
                dem.STOP_JUMP: f"a particle moved {self.counters[dem.COUNT_JUMP]:.3g} radii in one step "
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
        """Contacts at the last step: particle-particle, particle-wall and particle-mesh
        (the step counts the mesh contacts among the wall contacts)."""
        return int(self.counters[dem.COUNT_PAIR_CONTACTS] + self.counters[dem.COUNT_WALL_CONTACTS])

    def kinetic_energy(self) -> float:
        return self.ledger.kinetic

    # the boundaries (:mod:`demstep.engine.boundaries`)
    def set_box(self, axis: int, motion: str = "fixed", **settings):
        """How the periodic length along ``axis`` moves (:func:`~demstep.engine.boundaries.set_box`)."""
        boundaries.set_box(self, axis, motion, **settings)

    def set_wall_motion(self, index: int, motion: str, **settings):
        """How wall ``index`` moves (:func:`~demstep.engine.boundaries.set_wall_motion`)."""
        boundaries.set_wall_motion(self, index, motion, **settings)

    def wall_stress(self) -> np.ndarray:
        """Compressive normal stress on each wall [M/(L T^2)] (:func:`~demstep.engine.boundaries.wall_stress`)."""
        return boundaries.wall_stress(self)

    def extents(self) -> np.ndarray:
        """Specimen extents per axis [L] (:func:`~demstep.engine.boundaries.extents`)."""
        return boundaries.extents(self)

    def set_mesh_motion(self, index: int, enabled: bool | None = None, **settings):
        """How mesh ``index`` moves (:func:`~demstep.engine.meshes.set_mesh_motion`), and
        whether it has contacts (``enabled``: :func:`~demstep.engine.population.switch_mesh`)."""
        set_mesh_motion(self, index, **settings)
        if enabled is not None:
            switch_mesh(self, index, enabled)

    @property
    def mesh_wear(self) -> np.ndarray:
        """The wear accumulated on each mesh's triangles, times their areas, summed per
        mesh (M,) [L^3 with Finnie's coefficient in 1/pressure: a volume worn away];
        0 for a mesh that does not track wear (:mod:`demstep.kernels.meshes`)."""
        m = self.meshes
        corners = m.tri.reshape(-1, 3, 3)
        area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                             corners[:, 2] - corners[:, 0]), axis=1)
        return np.bincount(m.tri_mesh, weights=m.wear * area, minlength=m.n)

    @property
    def mesh_enabled(self) -> np.ndarray:
        """Whether each mesh wall has contacts (M,) bool."""
        return np.array([w.enabled for w in self.mesh_walls], dtype=bool)

    @property
    def mesh_force(self) -> np.ndarray:
        """The force the particles exert on each mesh wall (M, 3) [M L/T^2]."""
        return self.meshes.force

    @property
    def mesh_torque(self) -> np.ndarray:
        """Its torque about each mesh's centre (M, 3) [M L^2/T^2]."""
        return self.meshes.torque

    def love_stress(self) -> np.ndarray:
        """Average contact stress, diagonal [M/(L T^2)] (:func:`~demstep.engine.boundaries.love_stress`)."""
        return boundaries.love_stress(self)


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
