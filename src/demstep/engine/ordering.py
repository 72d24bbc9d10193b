"""The particles' order in memory: re-sorting them in spatial order during a run, and
renumbering everything that names particles when their order changes.

Every pair's data is gathered by index: a packing in random order runs up to 2.5x
slower than in spatial order (rows of cells, :func:`demstep.packings.spatial_order`).
:class:`SpatialOrder` (``sim.ordering``) looks at the order at the first build of the
neighbour lists and every ``sort_every`` steps after, and sorts when that brings the
pairs' ends closer in memory; :func:`reorder` renames the particles in every bundle.
"""

from __future__ import annotations

import warnings

import numpy as np

from demstep.errors import InputError
from demstep.kernels import dem
from demstep.packings import SPATIAL_ORDER_MIN, inverse_order, spatial_order
from demstep.particles import Particles
from demstep.state import CONTACT_HISTORY, Meshes, Pairs


class SpatialOrder:
    """When ``sim``'s particles are sorted (``every`` [steps], None: never; module
    docstring). State: the step of the last look (``last_sort``, checkpointed), whether
    the order was checked for the one-time warning, and how many sorts were done."""

    #: the first pair list of at least N/2 pairs warns when fewer than this share of its
    #: pairs lie within N/100 of each other in memory (from SPATIAL_ORDER_MIN particles
    #: on): in random order about 2 %; in spatial order most of them (the pairs along a
    #: row of cells and between rows; those between layers may be a layer apart)
    ORDER_WARN_CLOSE = 0.2

    #: a sort is done when it brings the pairs' ends closer in memory by at least this
    #: much: the mean of log2(1 + |j - i|) over the new pair list falls by this (1: the
    #: typical distance halves). Spheres settling in columns were faster in their
    #: column order (j = i + 1) than in rows of cells (3.4 % slower sorted every 100
    #: steps); a random order of a dense packing gets 2.6x faster (benchmarks/resort.py)
    SORT_GAIN = 1.0

    def __init__(self, sim, every: int | None):
        if every is not None and (isinstance(every, bool) or not isinstance(
                every, (int, np.integer)) or every < 1):
            raise InputError(f"sort_every: expected a number of steps >= 1 or None, got "
                             f"{every!r}")
        self.sim = sim
        self.every = None if every is None else int(every)
        #: the step of the last look at the order
        self.last_sort = 0
        #: whether the order was looked at for the warning (:meth:`check`)
        self.checked = False
        #: sorts done in this process
        self.n_sorts = 0

    def after_build(self, first: bool):
        """At a build of the neighbour lists (``first``: the first one): the warning
        about a random order when the particles are never sorted, or a sort when due."""
        sim = self.sim
        if self.every is None:
            if not self.checked:
                self.check(sim.pairs.i, sim.pairs.j)
        elif first or sim.step - self.last_sort >= self.every:
            self.sort()

    def check(self, pi, pj):
        """Warn (once, at the first pair list of N/2 pairs or more) when the particles
        are in random order: every pair's data is gathered by index, and a packing in
        random order runs 2.5x slower than in spatial order (benchmarks/RESULTS.md)."""
        n = len(self.sim.r)
        if n < SPATIAL_ORDER_MIN:
            self.checked = True
            return
        if len(pi) < n // 2:
            return
        self.checked = True
        close = float(np.mean(pj - pi < max(64, n // 100)))
        if close < self.ORDER_WARN_CLOSE:
            warnings.warn(f"demstep: the {n} particles are in random order (only "
                          f"{close:.0%} of the pairs lie within {max(64, n // 100)} places of "
                          f"each other in memory); put them in spatial order first "
                          f"(x[demstep.packings.spatial_order(x, 2 * r.max())]): up to 2.5x "
                          f"faster", RuntimeWarning, stacklevel=5)

    def sort(self):
        """At a rebuild (the new lists built): put the particles in spatial order (rows
        of cells of side 2 r_max, as ``demstep run`` orders a particle file) when that
        brings the pairs closer in memory by :data:`SORT_GAIN`."""
        sim = self.sim
        self.last_sort = sim.step
        pi, pj = sim.pairs.i, sim.pairs.j
        if len(pi) == 0:  # (nothing to gather: the order does not matter)
            return
        order = spatial_order(sim.x[:, :sim.dim], 2.0 * float(sim.r.max()))
        inv = inverse_order(order)
        now = float(np.mean(np.log2(1.0 + (pj - pi))))
        sorted_ = float(np.mean(np.log2(1.0 + np.abs(inv[pj] - inv[pi]))))
        if sorted_ <= now - self.SORT_GAIN:
            reorder(sim, order)
            self.n_sorts += 1

    def state_dict(self) -> dict:
        return {"last_sort": np.array([self.last_sort])}

    def load_state_dict(self, data: dict, step: int):
        """Inverse of :meth:`state_dict` (older checkpoints: the last look at ``step``)."""
        self.last_sort = int(np.asarray(data.get("last_sort", [step])).reshape(-1)[0])


def reorder(sim, order) -> None:
    """Renumber the particles of ``sim``: new particle k is old particle ``order[k]`` (a
    permutation of 0..N-1). Everything that names particles follows: the state of
    every particle, ``fixed``, ``particles``, ``source_index`` (composed, so that
    messages and outputs keep naming particles by their input row), the clumps'
    members, the pair and wall lists with their history, the bonds, and the 'auto'
    step's cover, critical mode and certificate. A pair or bond whose ends swap
    keeps i < j: what it stores as acting on j (tangential spring and dashpot
    forces, rolling, viscous and bending moments, bond shear) changes sign; what
    acts along the normal (normal force, twisting moment) does not, the normal
    turning with it. Index arrays and views the caller holds are not renumbered."""
    n = len(sim.r)
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
    scratch = np.empty(max(a.size for a in sim.spheres))
    for a in sim.spheres:
        rows = scratch[:a.size].reshape(a.shape)
        np.take(a, order, axis=0, out=rows)
        a[...] = rows
    sim.fixed = sim.fixed[order]
    p = sim.particles
    sim.particles = Particles.checked_already(p.x[order], p.r[order], p.m[order],
                                              p.inertia[order], p.fixed[order])
    sim.source_index = order if sim.source_index is None else sim.source_index[order]
    bodies = sim.bodies
    sim.bodies = bodies._replace(member=inv[bodies.member],
                                 sphere_body=bodies.sphere_body[order])
    sim.pairs = renumbered_pairs(sim.pairs, inv)
    ws = sim.wall_state
    p = inv[ws.p]
    rows = np.lexsort((ws.wall, p))
    sim.wall_state = ws._replace(p=p[rows], wall=ws.wall[rows], **{
        f: getattr(ws, f)[rows] if len(getattr(ws, f)) else getattr(ws, f)
        for f in CONTACT_HISTORY})
    meshes = sim.meshes
    if len(meshes.cand_p):  # a sphere's rows stay together and in their order
        p = inv[meshes.cand_p]
        rows = np.lexsort((np.arange(len(p)), p))
        sim.meshes = meshes._replace(cand_p=p[rows], **{
            f: getattr(meshes, f)[rows] for f in ("cand_t", "cand_d") + Meshes.SLOTS})
    bonds = sim.bonds
    if bonds.n:
        i, j, sign = ends_in_order(inv[bonds.i], inv[bonds.j])
        sim.bonds = bonds._replace(i=i, j=j, shear=bonds.shear * sign, bend=bonds.bend * sign)
    sim.auto.renumber(order, inv)
    sim.pairs_changed()


def renumbered_pairs(pairs: Pairs, inv: np.ndarray) -> Pairs:
    """The pair list with particle p renamed inv[p], i < j kept (history on j
    negated where the ends swap) and sorted by (i, j) again."""
    lo, hi, sign = ends_in_order(inv[pairs.i], inv[pairs.j])
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


def ends_in_order(i, j):
    """Pairs or bonds renamed (i, j) put back in i < j order: (lo, hi, sign), ``sign``
    (P, 1) -1 where the ends swapped (what a pair stores as acting on j changes sign)."""
    swap = i > j
    return np.where(swap, j, i), np.where(swap, i, j), np.where(swap, -1.0, 1.0)[:, None]


def order_as(sim, source_index, source: str):
    """Renumber the particles as a checkpoint's (its ``source_index``: the input row
    of each of its particles; a run that sorted them saved them in another order
    than this Simulation, built from the case, has)."""
    if source_index is None:
        return
    target = np.asarray(source_index)
    current = (np.arange(len(sim.r)) if sim.source_index is None
               else np.asarray(sim.source_index))
    if target.shape != current.shape or not np.issubdtype(target.dtype, np.integer) \
            or not np.array_equal(np.sort(target), np.sort(current)):
        raise InputError(f"{source}: the checkpoint's particles do not match the simulation")
    if np.array_equal(target, current):
        return
    # (input rows are a permutation of 0..N-1: where each row is now)
    reorder(sim, inverse_order(current)[target])
