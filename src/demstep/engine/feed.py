"""Insertion and outflow during a run: :class:`Inserter`, :class:`Outlet` and their
owner :class:`Feed` (``sim.feed``).

An inserter adds particles every ``every`` steps so that the count (``rate``
[1/T]) or the mass (``mass_rate`` [M/T]) inserted since ``start`` [T] follows the
rate, up to ``total`` particles or ``total_mass`` [M] and until ``stop`` [T]; or
(``fill_to``) so that its region holds that many particles again at each insertion
(as LIGGGHTS' ``insert/pack ... particles_in_region``). The
radii come from a :class:`~demstep.feed.distributions.RadiusDistribution` and are
drawn before they are placed; a particle is placed at a random point of the region
(wholly inside it) where it overlaps no particle, plane wall or mesh wall and no
particle placed before it in the same event, tried ``attempts`` times per event; a
particle that finds no room stays drawn and is tried again at the next event (so a
crowded region delays insertion instead of skewing the size distribution toward
small particles), and one warning says so. Inserted particles start with
``velocity`` [L/T], no rotation, the inserter's ``density`` [M/L^3] (2D: M/L^2).

An outlet removes, every ``every`` steps, the particles whose centre lies in its
region, whatever touches them; the mass and count removed are recorded.

What happens to the state, the energy ledger and the 'auto' step when particles
come and go: :mod:`demstep.engine.population`. The draws are reproducible from
``seed``, and the generators' state is checkpointed: a restart continues bit for bit.
"""

from __future__ import annotations

import json
import logging
import math
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from demstep.contact.geometry import minimum_image_arrays
from demstep.contact.laws.base import check_number
from demstep.engine.meshes import TriangleGrid, build_candidates
from demstep.engine.population import add_particles, remove_particles
from demstep.errors import InputError
from demstep.feed.distributions import RadiusDistribution
from demstep.feed.regions import FaceRegion, Region
from demstep.particles import particle_inertia, particle_mass

log = logging.getLogger("demstep")


def _steps(value, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise InputError(f"{what}: expected a number of steps >= 1, got {value!r}")
    return int(value)


@dataclass
class Inserter:
    """Particles inserted at a rate (module docstring)."""

    name: str
    region: Region
    radius: RadiusDistribution
    density: float
    rate: float | None = None
    mass_rate: float | None = None
    fill_to: int | None = None
    total: int | None = None
    total_mass: float | None = None
    start: float = 0.0
    stop: float = math.inf
    velocity: np.ndarray | None = None
    every: int = 1000
    seed: int = 0
    attempts: int = 50
    #: the most drawn particles tried in one event (the first ones drawn)
    TRY_AT_ONCE = 2000

    # state
    inserted: int = 0
    inserted_mass: float = 0.0
    pending: np.ndarray = field(default_factory=lambda: np.zeros(0))
    warned: bool = False
    #: particles drawn that found no room before ``stop``, never inserted
    dropped: int = 0

    def __post_init__(self):
        what = f"insert {self.name!r}"
        if sum(v is not None for v in (self.rate, self.mass_rate, self.fill_to)) != 1:
            raise InputError(f"{what}: give exactly one of rate (particles per unit time), "
                             f"mass_rate and fill_to")
        if self.fill_to is not None:
            if isinstance(self.fill_to, bool) or int(self.fill_to) != self.fill_to \
                    or self.fill_to < 1:
                raise InputError(f"{what}.fill_to: expected a count >= 1, got {self.fill_to!r}")
            if isinstance(self.region, FaceRegion):
                raise InputError(f"{what}.fill_to: a face has no inside to fill; use rate or "
                                 f"mass_rate")
            self.fill_to = int(self.fill_to)
        if self.rate is not None:
            self.rate = check_number(f"{what}.rate", self.rate)
        if self.mass_rate is not None:
            self.mass_rate = check_number(f"{what}.mass_rate", self.mass_rate)
        if self.total is not None and (isinstance(self.total, bool) or int(self.total) != self.total
                                       or self.total < 0):
            raise InputError(f"{what}.total: expected a count >= 0, got {self.total!r}")
        if self.total_mass is not None:
            self.total_mass = check_number(f"{what}.total_mass", self.total_mass)
        self.density = check_number(f"{what}.density", self.density)
        if self.density <= 0:
            raise InputError(f"{what}.density: must be > 0, got {self.density!r}")
        self.start = check_number(f"{what}.start", self.start)
        if self.stop != math.inf:  # (inf: no end)
            self.stop = check_number(f"{what}.stop", self.stop)
        if self.stop < self.start:
            raise InputError(f"{what}.stop: must be >= start = {self.start:g}, got {self.stop!r}")
        self.every = _steps(self.every, f"{what}.every")
        self.attempts = _steps(self.attempts, f"{what}.attempts")
        dim = self.region.dim
        v = np.zeros(3)
        if self.velocity is not None:
            vel = np.asarray(self.velocity, dtype=np.float64)
            if vel.shape != (dim,) or not np.isfinite(vel).all():
                raise InputError(f"{what}.velocity: expected {dim} finite numbers, got "
                                 f"{self.velocity!r}")
            v[:dim] = vel
        self.velocity = v
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise InputError(f"{what}.seed: expected an integer >= 0, got {self.seed!r}")
        self.rng = np.random.default_rng(int(self.seed))

    @property
    def dim(self) -> int:
        return self.region.dim

    def masses(self, r) -> np.ndarray:
        return particle_mass(r, self.density, self.dim)

    def target(self, time: float) -> tuple[float, float]:
        """(count, mass) [-, M] to have inserted by ``time`` [T] (inf: no limit of that kind)."""
        span = max(0.0, min(time, self.stop) - self.start) if time >= self.start else 0.0
        count, mass = math.inf, math.inf
        if self.rate is not None:
            count = math.floor(self.rate * span + 1e-9)
        if self.mass_rate is not None:
            mass = self.mass_rate * span
        if self.total is not None:
            count = min(count, self.total)
        if self.total_mass is not None:
            mass = min(mass, self.total_mass)
        return count, mass

    def draw(self, time: float, inside: int = 0):
        """Draw the radii that bring the count (``rate``) or the mass (``mass_rate``)
        drawn up to the target at ``time``, or the particles ``inside`` the region
        (``fill_to``) with those waiting up to ``fill_to``, appended to :attr:`pending`;
        by mass the drawn mass leads the target by less than one particle."""
        count, mass = self.target(time)
        have_m = self.inserted_mass + float(self.masses(self.pending).sum())
        if self.fill_to is not None:
            n_new = 0
            if self.start <= time <= self.stop:
                n_new = self.fill_to - inside - len(self.pending)
                if self.total is not None:
                    n_new = min(n_new, self.total - self.inserted - len(self.pending))
            new = self.radius.sample(self.rng, n_new) if n_new > 0 else np.zeros(0)
        elif self.rate is not None:
            n_new = int(count) - self.inserted - len(self.pending)
            new = self.radius.sample(self.rng, n_new) if n_new > 0 else np.zeros(0)
        else:
            parts, room = [], mass - have_m
            unit = self.density * self.radius.mean_volume()
            while room > 0:
                batch = self.radius.sample(self.rng, max(1, int(math.ceil(room / unit))))
                cum = np.cumsum(self.masses(batch))
                k = min(int(np.searchsorted(cum, room, side="left")) + 1, len(batch))
                parts.append(batch[:k])
                room -= float(cum[k - 1])
            new = np.concatenate(parts) if parts else np.zeros(0)
        if self.total_mass is not None and self.mass_rate is None and len(new):
            new = new[have_m + np.cumsum(self.masses(new)) <= self.total_mass * (1 + 1e-12)]
        if len(new):
            self.pending = np.concatenate([self.pending, new])

    def insert(self, sim) -> int:
        """One insertion event in ``sim``: draw, place, add. Returns how many were added.
        Nothing is inserted after ``stop``: the particles still waiting for room then
        are dropped (counted in :attr:`dropped`, said once), as LIGGGHTS ends an
        inserter that is unfixed."""
        if sim.time > self.stop + 0.5 * float(sim.dt or 0.0):
            if len(self.pending):
                self.dropped += len(self.pending)
                warnings.warn(f"demstep: insert {self.name!r}: {len(self.pending)} particle(s) "
                              f"that found no room by stop = {self.stop:g} are dropped (step "
                              f"{sim.step})", RuntimeWarning, stacklevel=2)
                self.pending = np.zeros(0)
            return 0
        inside = int(self.region.contains(sim.x).sum()) if self.fill_to is not None else 0
        self.draw(sim.time, inside)
        if len(self.pending) == 0:
            return 0
        extrude = None
        if isinstance(self.region, FaceRegion):
            extrude = self.velocity * self.every * float(sim.dt or 0.0)
        # (at most a few events' worth is tried at once: a region kept full does not
        # make every event try the whole backlog)
        tried = min(len(self.pending), self.TRY_AT_ONCE)
        x, placed = place(sim, self.region, self.pending[:tried], self.rng, self.attempts, extrude)
        placed = np.concatenate([placed, np.zeros(len(self.pending) - tried, dtype=bool)])
        r = self.pending[placed]
        if len(r):
            m = self.masses(r)
            add_particles(sim, x[placed[:tried]][:, :sim.dim], r, m, particle_inertia(m, r, self.dim),
                          v=np.repeat(self.velocity[None, :], len(r), axis=0),
                          next_id=sim.feed.next_id)
            sim.feed.next_id += len(r)
            self.inserted += len(r)
            self.inserted_mass += float(m.sum())
        self.pending = self.pending[~placed]
        if len(self.pending) and not self.warned:
            self.warned = True
            warnings.warn(f"demstep: insert {self.name!r}: {len(self.pending)} particle(s) found "
                          f"no room in the region at step {sim.step} (t = {sim.time:.6g}); they "
                          f"are tried again at the next insertions (a larger region, or a lower "
                          f"rate, keeps up)", RuntimeWarning, stacklevel=2)
        return len(r)

    def state(self) -> dict:
        return {"inserted": self.inserted, "inserted_mass": self.inserted_mass,
                "pending": self.pending.tolist(), "warned": self.warned,
                "dropped": self.dropped, "rng": self.rng.bit_generator.state}

    def restore(self, state: dict):
        self.inserted = int(state["inserted"])
        self.inserted_mass = float(state["inserted_mass"])
        self.pending = np.asarray(state["pending"], dtype=np.float64)
        self.warned = bool(state["warned"])
        self.dropped = int(state.get("dropped", 0))  # (before drops were counted: none)
        self.rng.bit_generator.state = state["rng"]


@dataclass
class Outlet:
    """Removes the particles whose centre lies in ``region``, every ``every`` steps."""

    name: str
    region: Region
    every: int = 100
    removed: int = 0
    removed_mass: float = 0.0

    def __post_init__(self):
        self.every = _steps(self.every, f"outlet {self.name!r}.every")
        if isinstance(self.region, FaceRegion):
            raise InputError(f"outlet {self.name!r}.shape: a mesh face cannot be an outlet; "
                             f"use a box, cylinder or sphere")

    def remove(self, sim) -> int:
        inside = self.region.contains(sim.x)
        count, mass = remove_particles(sim, inside)
        self.removed += count
        self.removed_mass += mass
        return count

    def state(self) -> dict:
        return {"removed": self.removed, "removed_mass": self.removed_mass}

    def restore(self, state: dict):
        self.removed = int(state["removed"])
        self.removed_mass = float(state["removed_mass"])


class Feed:
    """The inserters and outlets of a Simulation (``sim.feed``), acting between chunks
    of steps at the end of the run loop's turn (after the writers: a history row
    describes the state the steps reached), each on its own schedule of steps."""

    def __init__(self, sim):
        self.sim = sim
        self.inserters: list[Inserter] = []
        self.outlets: list[Outlet] = []
        #: the id the next inserted particle gets (ids are never given twice)
        self.next_id = int(sim.particle_ids().max(initial=-1)) + 1 if len(sim.r) else 0
        #: the step they last acted at (-1: not yet)
        self.last_step = -1
        #: the meshes' triangles binned for the placement's overlap check
        self.triangle_grid = TriangleGrid()

    def __bool__(self) -> bool:
        return bool(self.inserters or self.outlets)

    def add(self, item):
        """Add an :class:`Inserter` or :class:`Outlet` (their names unique)."""
        names = [i.name for i in self.inserters + self.outlets]
        if item.name in names:
            raise InputError(f"feed: the name {item.name!r} is used twice")
        if item.region.dim != self.sim.dim:
            raise InputError(f"{item.name!r}: a {item.region.dim}D region in a {self.sim.dim}D "
                             f"simulation")
        if self.sim.bodies.n:
            raise InputError(f"{item.name!r}: insertion and outlets are not supported with clumps")
        if self.sim.bonds.n:
            raise InputError(f"{item.name!r}: insertion and outlets are not supported with bonds")
        (self.inserters if isinstance(item, Inserter) else self.outlets).append(item)

    def steps_to_next(self, step: int) -> int:
        """Steps from ``step`` to the next event of any of them (a large number: none)."""
        out = 10 ** 12
        for item in self.inserters + self.outlets:
            out = min(out, item.every - step % item.every)
        return out

    def act(self):
        """The inserters and outlets due at this step act (outlets first), once per step."""
        sim = self.sim
        if sim.step == self.last_step:
            return
        self.last_step = sim.step
        for outlet in self.outlets:
            if sim.step % outlet.every == 0:
                outlet.remove(sim)
        for inserter in self.inserters:
            if sim.step % inserter.every == 0:
                inserter.insert(sim)

    def max_radius(self) -> float:
        """The largest radius an inserter can bring [L] (0: none)."""
        return max((i.radius.max for i in self.inserters), default=0.0)

    def min_mass(self) -> float:
        """The lightest particle an inserter can bring [M] (inf: none)."""
        return min((float(i.masses(np.array([i.radius.min]))[0]) for i in self.inserters),
                   default=math.inf)

    def state_dict(self) -> dict:
        state = {"next_id": self.next_id, "last_step": self.last_step,
                 "inserters": {i.name: i.state() for i in self.inserters},
                 "outlets": {o.name: o.state() for o in self.outlets}}
        return {"feed": np.frombuffer(json.dumps(state).encode(), dtype=np.uint8)}

    def load_state_dict(self, data: dict, source: str):
        if "feed" not in data:
            if self:
                raise InputError(f"{source}: the checkpoint has no insertion state (a run "
                                 f"without [[insert]] or [[outlet]])")
            return
        state = json.loads(bytes(np.asarray(data["feed"], dtype=np.uint8)).decode())
        self.next_id = int(state["next_id"])
        self.last_step = int(state["last_step"])
        for kind, items in (("inserters", self.inserters), ("outlets", self.outlets)):
            saved = state[kind]
            names = sorted(i.name for i in items)
            if sorted(saved) != names:
                raise InputError(f"{source}: the checkpoint's {kind} {sorted(saved)} are not "
                                 f"the case's {names}")
            for item in items:
                item.restore(saved[item.name])


def _periodic_tree(points, periodic_len, dim: int):
    """A k-d tree of ``points`` (N, dim) with the periodic axes wrapped (the other axes
    in a box too large for wrapping to matter), and the shift applied to them."""
    length = np.asarray(periodic_len[:dim], dtype=np.float64)
    if not (length > 0).any():
        return cKDTree(points), np.zeros(dim), None
    lo = points.min(axis=0) if len(points) else np.zeros(dim)
    hi = points.max(axis=0) if len(points) else np.zeros(dim)
    shift = np.where(length > 0, 0.0, -lo + 1.0)
    span = hi - lo
    box = np.where(length > 0, length, 4.0 * span + 4.0 + 1e3 * np.abs(hi - lo).max(initial=1.0))
    pts = points + shift
    pts = np.where(length > 0, np.mod(pts, np.where(length > 0, length, 1.0)), pts)
    return cKDTree(pts, boxsize=box), shift, box


def place(sim, region: Region, radii: np.ndarray, rng, attempts: int, extrude=None):
    """Positions (K, 3) [L] for spheres of ``radii`` in ``region`` overlapping nothing
    in ``sim`` (particles, plane walls, mesh walls) nor each other, and which found one
    (K,) bool; each tries up to ``attempts`` random positions."""
    dim = sim.dim
    k = len(radii)
    x = np.full((k, 3), np.nan)
    placed = np.zeros(k, dtype=bool)
    if len(sim.r):
        tree, shift, box = _periodic_tree(sim.x[:, :dim], sim.periodic_len, dim)
        r_max = float(sim.r.max())
    else:
        tree = None
    ws = sim.wall_state
    length = sim.periodic_len
    periodic = np.asarray(length[:dim]) > 0
    for _ in range(attempts):
        todo = np.flatnonzero(~placed)
        if len(todo) == 0:
            break
        r = radii[todo]
        cand = region.sample(rng, r, extrude)
        ok = np.isfinite(cand).all(axis=1)
        for axis in range(dim):  # (into the periodic box)
            if length[axis] > 0:
                cand[:, axis] = np.mod(cand[:, axis], length[axis])
        if tree is not None and ok.any():
            rows = np.flatnonzero(ok)
            q = cand[rows, :dim] + shift
            if box is not None:
                q = np.where(periodic, np.mod(q, np.where(periodic, length[:dim], 1.0)), q)
            near = tree.query_ball_point(q, r[rows] + r_max)
            counts = np.fromiter((len(a) for a in near), dtype=np.int64, count=len(rows))
            if counts.sum():
                who = np.repeat(np.arange(len(rows)), counts)
                other = np.fromiter((p for a in near for p in a), dtype=np.int64,
                                    count=int(counts.sum()))
                d = minimum_image_arrays(sim.x[other, :dim] - cand[rows[who], :dim], length)
                gap = np.sqrt(np.einsum("ij,ij->i", d, d)) - sim.r[other] - r[rows[who]]
                ok[rows[np.unique(who[gap < 0])]] = False
        if len(ws.point) and ok.any():
            dist = np.einsum("kwj,wj->kw", cand[:, None, :] - ws.point[None, :, :], ws.normal)
            ok &= np.all(dist >= r[:, None], axis=1) | ~np.isfinite(cand).all(axis=1)
        if sim.meshes.tri.shape[0] and ok.any():
            rows = np.flatnonzero(ok)
            hit, _ = build_candidates(sim.meshes, np.ascontiguousarray(cand[rows]),
                                      np.ascontiguousarray(r[rows]), 0.0, lambda p: p,
                                      sim.mesh_enabled, sim.feed.triangle_grid)
            ok[rows[np.unique(hit)]] = False
        # among themselves and those placed before them in this event, in order
        ok &= np.isfinite(cand).all(axis=1)
        rows = np.flatnonzero(ok)
        if len(rows) == 0:
            continue
        done = np.flatnonzero(placed)
        pts = np.concatenate([x[done], cand[rows]])
        rr = np.concatenate([radii[done], r[rows]])
        tree_new = _periodic_tree(pts[:, :dim], length, dim)[0]
        accepted = np.ones(len(pts), dtype=bool)
        close = np.array(sorted(tree_new.query_pairs(2.0 * float(rr.max()))), dtype=np.int64)
        if len(close):
            d = minimum_image_arrays(pts[close[:, 0], :dim] - pts[close[:, 1], :dim], length)
            overlap = np.sqrt(np.einsum("ij,ij->i", d, d)) < rr[close[:, 0]] + rr[close[:, 1]]
            for a, b in close[overlap]:
                if accepted[a]:  # (b > a: the earlier one stays; placed ones come first)
                    accepted[b] = False
        keep = accepted[len(done):]
        x[todo[rows[keep]]] = cand[rows[keep]]
        placed[todo[rows[keep]]] = True
    return x, placed
