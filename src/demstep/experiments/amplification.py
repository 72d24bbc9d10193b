"""The engine's own one-step map, linearised: its amplification matrix and stability limit.

A run whose contacts stay closed and stick is a linear system to first order about a
state at rest: one engine step maps the state

    s(n) = (x(n), v(n - 1/2), w(n - 1/2), f_t(n - 1))

(positions, half-step velocities and spins of the free spheres, the tangential spring
force of every pair in its tangent plane) to s(n + 1) by a matrix A(dt), the
amplification matrix. It is built here from the engine itself: every column is one
call of :meth:`Simulation.run` with ``steps=1`` from the base state perturbed along a
unit vector (central differences, so the second-order terms cancel); nothing of the
update is re-derived. The run is stable for small perturbations exactly while the
spectral radius of A(dt) is at most 1.

For the lagged dashpot the engine applies (forces at t from v(t - dt/2)) and its
incremental tangential spring, the one-degree-of-freedom map on (x, v) is

    [[1 - dt^2 k/m, dt (1 - dt c/m)], [-dt k/m, 1 - dt c/m]],

trace 2 - dt^2 k/m - dt c/m, determinant 1 - dt c/m; Jury's conditions hold up to
dt = 4 / (c/m + sqrt((c/m)^2 + 4 k/m)) = 2 / s, s the larger root of
m s^2 - c s - k = 0: the certificate's step (docs/damping.md). The critical eigenvalue
leaves the unit disc through -1 (docs/damping.md), away from the cluster at +1.

Eigenvalues at +1 belong to motions that cost no force: rigid translations and
rotations (Jordan blocks, whose computed eigenvalues scatter by the square root of
the rounding) and the invariant f_t + k_t u_t of every tangential spring;
:func:`spectral_radius` leaves out the cluster within ``exclude`` of +1 when asked.

Only spheres and pair contacts (no walls, bonds, clumps or rolling springs: their
history is not part of the state here).
"""

from __future__ import annotations

import numpy as np

from demstep.engine import TimeStep
from demstep.contact.geometry import minimum_image_arrays
from demstep.errors import InputError


def _normals(sim) -> np.ndarray:
    """Unit normals i -> j of the pairs, periodic images taken into account."""
    x = np.asarray(sim.x)
    d = minimum_image_arrays(x[sim.pj] - x[sim.pi], _lengths(sim, x.shape[1]))
    return d / np.linalg.norm(d, axis=1)[:, None]


def _lengths(sim, dim: int) -> np.ndarray:
    """The periodic lengths per axis [L] (0: not periodic), ``dim`` of them."""
    length = np.zeros(dim)
    given = np.asarray(sim.periodic_len, dtype=float).ravel()[:dim]
    length[:len(given)] = np.where(given > 0, given, 0.0)
    return length


def _tangents(n: np.ndarray, dim: int) -> list:
    """Unit vectors spanning each pair's tangent plane: one (in-plane) in 2D, two in 3D."""
    if dim == 2:
        return [np.stack([-n[:, 1], n[:, 0], np.zeros(len(n))], axis=1)]
    helper = np.where(np.abs(n[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1)[:, None]
    return [t1, np.cross(n, t1)]


class EngineMap:
    """The one-step map of a :class:`Simulation` about its current state (which should
    be at rest: an equilibrium whose contacts all stick). Coordinates are scaled so
    that one unit is the smallest overlap (positions), that overlap per step
    (velocities, spins times the radius) and K_max times it (tangential forces): the
    eigenvalues do not depend on the scaling, the finite differences do."""

    def __init__(self, sim, rel_step: float = 1e-5):
        if sim.bonds.i.shape[0] or sim.bodies.m.shape[0] or len(sim.walls) or sim.mesh_walls:
            raise InputError("amplification matrix: spheres and pair contacts only")
        if sim.law.params().has_rolling:
            raise InputError("amplification matrix: no rolling springs (their history is "
                             "not part of the state)")
        self.sim = sim
        sim.prepare()
        if sim.first_step_pending:  # (the first step initialises the half-step velocities)
            sim.run(steps=1)
        self.dim = sim.dim
        self.free = np.flatnonzero(np.asarray(sim.inv_m) > 0.0)
        self.pairs = (np.array(sim.pi), np.array(sim.pj))
        self.base = self._read()
        x = np.asarray(sim.x)
        gap = sim.r[self.pairs[0]] + sim.r[self.pairs[1]] - self._distances(x)
        if len(gap) == 0 or gap.min() <= 0.0:
            raise InputError("amplification matrix: every pair must overlap")
        scale_x = float(gap.min())
        n = _normals(sim)
        self.tangents = _tangents(n, self.dim)
        self.normals = n
        dt = float(sim.dt)
        self.rel_step = rel_step
        self.scales = {"x": scale_x, "v": scale_x / dt, "w": scale_x / dt / float(np.max(sim.r)),
                       "ft": scale_x * float(sim.stiffness_max())}

    def _distances(self, x):
        d = minimum_image_arrays(x[self.pairs[1]] - x[self.pairs[0]],
                                 _lengths(self.sim, x.shape[1]))
        return np.linalg.norm(d, axis=1)

    def _read(self) -> dict:
        s = self.sim
        return {"x": np.array(s.x), "v": np.array(s.v), "w": np.array(s.w),
                "ft": np.array(s.ft)}

    def coordinates(self) -> list:
        """(array, row, direction) of every coordinate of the state vector."""
        axes = np.eye(3)
        trans = axes[:self.dim]
        spins = axes[2:] if self.dim == 2 else axes
        out = [(name, p, e) for name in ("x", "v") for p in self.free for e in trans]
        out += [("w", p, e) for p in self.free for e in spins]
        out += [("ft", k, t[k]) for k in range(len(self.pairs[0])) for t in self.tangents]
        return out

    def _vector(self, state: dict, coords) -> np.ndarray:
        return np.array([np.dot(state[name][row], e) / self.scales[name]
                         for name, row, e in coords])

    def step(self, dt: float, state: dict) -> dict:
        """One engine step of length ``dt`` from ``state`` (arrays x, v, w, ft)."""
        s = self.sim
        s.timestep = TimeStep.fixed(float(dt))
        s.dt = s.dt_prev = float(dt)
        s.x[:] = state["x"]
        s.v[:] = state["v"]
        s.w[:] = state["w"]
        s.ft[:] = state["ft"]
        s.run(steps=1)
        if not (np.array_equal(s.pi, self.pairs[0]) and np.array_equal(s.pj, self.pairs[1])):
            raise RuntimeError("amplification matrix: the pair list changed during a step")
        return self._read()

    def matrix(self, dt: float) -> np.ndarray:
        """A(dt) in the scaled coordinates of :meth:`coordinates`."""
        coords = self.coordinates()
        h = self.rel_step
        cols = []
        for name, row, e in coords:
            out = []
            for sign in (1.0, -1.0):
                state = {k: v.copy() for k, v in self.base.items()}
                state[name][row] += sign * h * self.scales[name] * e
                out.append(self._vector(self.step(dt, state), coords))
            cols.append((out[0] - out[1]) / (2.0 * h))
        self.step(dt, self.base)  # (leave the simulation at its base state, moved one step)
        self.sim.x[:] = self.base["x"]
        self.sim.v[:] = self.base["v"]
        self.sim.w[:] = self.base["w"]
        self.sim.ft[:] = self.base["ft"]
        return np.array(cols).T


def spectral_radius(a: np.ndarray, exclude: float = 0.0) -> float:
    """The largest |eigenvalue| of ``a``, leaving out those within ``exclude`` of +1
    (the motions that cost no force: module docstring)."""
    mu = np.linalg.eigvals(a)
    if exclude > 0.0:
        mu = mu[np.abs(mu - 1.0) > exclude]
    return float(np.max(np.abs(mu))) if len(mu) else 0.0


def map_threshold(engine_map, lo: float, hi: float, rtol: float = 1e-7,
                  exclude: float = 1e-3, tol: float = 1e-9) -> float:
    """The step at which the spectral radius of the engine's map (without the cluster
    at +1, :func:`spectral_radius`) exceeds 1 + ``tol``, by bisection in [lo, hi]
    (``engine_map``: anything with a ``matrix(dt)`` method)."""
    def unstable(dt):
        return spectral_radius(engine_map.matrix(dt), exclude) > 1.0 + tol

    if unstable(lo) or not unstable(hi):
        raise RuntimeError(f"map threshold: the bracket [{lo:.6g}, {hi:.6g}] does not "
                           "contain the threshold")
    while hi / lo - 1.0 > rtol:
        mid = 0.5 * (lo + hi)
        if unstable(mid):
            hi = mid
        else:
            lo = mid
    return 0.5 * (lo + hi)
