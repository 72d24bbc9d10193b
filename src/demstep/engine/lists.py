"""The neighbour lists of a Simulation: the Verlet pair list and the particle-wall
list, their rebuild with the contact history carried over, and the pair loop's work
space.

A pair enters the list when its gap is below the skin; the lists expire once some
particle, wall or the periodic box has moved half the skin since they were built (the
compiled step watches it and returns, :data:`demstep.kernels.dem.STOP_REBUILD`).
:class:`NeighbourLists` (``sim.lists``) rebuilds them and owns what a rebuild keeps:
the pair search's scratch (while rebuilds come often), the chunks of the pair loop and
its band buffers.
"""

from __future__ import annotations

import numba
import numpy as np

from demstep.energy import A_ROLLING, E_STRAIN_R
from demstep.engine.meshes import TriangleGrid, build_candidates, carry_slots
from demstep.kernels import dem
from demstep.kernels.clumps import place_members
from demstep.scratch import Workspace
from demstep.state import ROLL_WIDTH, Pairs


class NeighbourLists:
    """The neighbour lists of ``sim`` (module docstring). ``built``: whether they have
    been built (a restart restores built lists)."""

    #: the neighbour search keeps its scratch (:class:`~demstep.scratch.Workspace`)
    #: for the next rebuild when this one comes at most this many steps after the last
    KEEP_SCRATCH_STEPS = 100

    def __init__(self, sim):
        self.sim = sim
        #: whether the lists have been built
        self.built = False
        #: the step of the last rebuild, and rebuilds done in this process
        self.last_rebuild = 0
        self.n_rebuilds = 0
        #: the pair search's scratch, kept between rebuilds that come often
        self.scratch: Workspace | None = None
        #: whether rolling-resistance history rows are kept for every pair
        self.rolling = False
        #: the thread count the pair loop's work space was made for (None: to be made)
        self._chunks_for: int | None = None
        #: the rolling loop's pair geometry (P, 4), kept across rebuilds while large enough
        self._geo_store = np.empty((0, 4))
        #: the meshes' triangles binned in a grid, kept while they do not move
        self.triangle_grid = TriangleGrid()

    def rebuild(self):
        """New neighbour lists (particles wrapped into the periodic box first), the
        contact history carried over to them. Small systems (the serial kernels) build
        them on one thread: a parallel region costs more than the work (and far more on
        a loaded machine)."""
        threads = numba.get_num_threads()
        if threads > 1 and not self.sim.threaded():
            numba.set_num_threads(1)
        try:
            self._rebuild()
        finally:
            numba.set_num_threads(threads)

    def moved_since_build(self) -> tuple[float, float]:
        """(D, B) [L] now: the largest displacement of a particle from its position at
        the last rebuild, and how far the walls and the periodic box moved since then
        (as the kernels' boundary move); (-1, 0) before the first build."""
        sim = self.sim
        if not self.built:
            return -1.0, 0.0
        d = sim.x - sim.x_ref
        moved = float(np.sqrt(np.einsum("ij,ij->i", d, d).max(initial=0.0)))
        ws = sim.wall_state
        walls = float(np.sqrt(((ws.point - ws.ref) ** 2).sum(axis=1)).max(initial=0.0))
        return moved, walls + float(np.abs(sim.box.length - sim.box.ref).sum())

    def _rebuild(self):
        sim = self.sim
        be = sim.backend
        c = sim.counters  # the drift's displacement bound (dem.drift_used): each
        if c[dem.DRIFT_OFFSET] >= 0.0:  # path goes through its reference at each rebuild
            if self.built:  # (the kernels' D and B of the last step: its positions)
                c[dem.DRIFT_OFFSET] += c[dem.DRIFT_NOW]
                c[dem.DRIFT_WALL_OFFSET] += c[dem.DRIFT_WALL_NOW]
            else:
                c[dem.DRIFT_OFFSET] = -1.0
        for k in range(3):
            if sim.periodic_len[k] > 0:
                np.mod(sim.x[:, k], sim.periodic_len[k], out=sim.x[:, k])
        bodies = sim.bodies
        if bodies.n:  # bodies wrapped, their members placed exactly on them
            for k in range(3):
                if sim.periodic_len[k] > 0:
                    np.mod(bodies.x[:, k], sim.periodic_len[k], out=bodies.x[:, k])
            place_members(bodies.x, bodies.q, bodies.start, bodies.member, bodies.offset,
                          sim.x, sim.periodic_len)
        built = self.built
        old, ws = sim.pairs, sim.wall_state
        if self.scratch is None:
            self.scratch = Workspace()
        work = self.scratch
        # the scratch is kept only while rebuilds come often (not after the first build;
        # a dense, quasi-static run rebuilds rarely: there it would be memory held for
        # nothing, and it was 100 MB more at the peak of a dense 1e6 run)
        if not built or sim.step - self.last_rebuild > self.KEEP_SCRATCH_STEPS:
            self.scratch = None
        self.last_rebuild = sim.step
        pi, pj = be.build_pair_list(sim.x, sim.r, sim.skin, sim.periodic_len,
                                    expected_pairs=len(old.i) if built else None, work=work)
        wp, ww = be.build_wall_list(sim.x, sim.r, ws.point, ws.normal, sim.skin,
                                    expected_pairs=len(ws.p) if built else None, work=work)
        del work  # (dropped now when not kept: before the history is carried over)
        if bodies.n:  # no contacts within a body
            sb = bodies.sphere_body
            keep = (sb[pi] < 0) | (sb[pi] != sb[pj])
            pi, pj = pi[keep], pj[keep]
        if sim.dashpot_history:
            shear, dashpot, energy = be.transfer_history(old.i, old.j, pi, pj, old.shear,
                                                         old.dashpot, old.shear_energy)
        else:  # no dashpot forces to carry: zeros the kernels never touch
            shear, energy = be.transfer_history(old.i, old.j, pi, pj, old.shear, old.shear_energy)
            dashpot = np.zeros((len(pi), 3))
        roll, cover = old.roll, old.cover
        if len(roll) or self.rolling:  # (new pairs: zeros; also when there were no pairs)
            roll, = be.transfer_history(old.i, old.j, pi, pj, roll)
        if len(cover):  # new pairs: not covered (0)
            cover, = be.transfer_history(old.i, old.j, pi, pj, cover)
        sim.pairs = old._replace(i=pi, j=pj, shear=shear, dashpot=dashpot, shear_energy=energy,
                                 roll=roll, cover=cover)
        self._chunks_for = None
        wshear, wdash, wenergy = be.transfer_history(ws.p, ws.wall, wp, ww, ws.shear,
                                                     ws.dashpot, ws.shear_energy)
        wroll, wcover = ws.roll, ws.cover
        if len(wroll) or self.rolling:
            wroll, = be.transfer_history(ws.p, ws.wall, wp, ww, wroll)
        if len(wcover):
            wcover, = be.transfer_history(ws.p, ws.wall, wp, ww, wcover)
        sim.wall_state = ws._replace(p=wp, wall=ww, shear=wshear, dashpot=wdash,
                                     shear_energy=wenergy, roll=wroll, cover=wcover)
        if sim.meshes.tri.shape[0] > 0:  # the triangles near each sphere, slots carried
            cand_p, cand_t, cand_d = build_candidates(
                sim.meshes, sim.x, sim.r, sim.skin, sim.particle_id, sim.mesh_enabled,
                self.triangle_grid, with_distance=True)
            sim.meshes = carry_slots(sim.meshes, cand_p, cand_t, cand_d)
            sim.meshes.moved[0] = 0.0
        if sim.auto.new_pairs_closing(cover, wcover):
            sim.counters[dem.COUNT_UNCOVERED] += 1.0  # (covered before the next step)
        sim.ordering.after_build(first=not built)
        be.copy_positions(sim.x, sim.x_ref)
        sim.wall_state.ref[:] = sim.wall_state.point
        sim.box.ref[:] = sim.box.length
        sim.counters[dem.DRIFT_NOW] = sim.counters[dem.DRIFT_WALL_NOW] = 0.0
        self.built = True
        self.n_rebuilds += 1

    def size_rolling_history(self, rolling: bool):
        """Rolling-resistance history rows for every pair and wall pair while the law
        has rolling resistance (zeros for new ones), none otherwise: switching it off
        releases the stored energy (the mesh contacts' too) into the ledger's rolling
        dissipation. Rebuilds of
        the lists keep a row per pair while it is on (also from an empty list), and the
        pair loop's work space (its rolling geometry) is sized anew after a change."""
        sim = self.sim
        self.rolling = bool(rolling)
        for name in ("pairs", "wall_state"):
            bundle = getattr(sim, name)
            n = len(bundle.i) if name == "pairs" else len(bundle.p)
            if rolling and len(bundle.roll) != n:
                setattr(sim, name, bundle._replace(roll=np.zeros((n, ROLL_WIDTH))))
            elif not rolling and len(bundle.roll):
                sim.ledger.acc[A_ROLLING] += float(bundle.roll[:, dem.ROLL_ENERGY].sum())
                sim.ledger.energy[E_STRAIN_R] = 0.0
                setattr(sim, name, bundle._replace(roll=np.zeros((0, ROLL_WIDTH))))
            else:
                continue
            if name == "pairs":
                self._chunks_for = None
        roll = sim.meshes.roll  # (mesh contacts: a row per slot always, zeros without it)
        if not rolling and len(roll) and roll[:, dem.ROLL_ENERGY].any():
            sim.ledger.acc[A_ROLLING] += float(roll[:, dem.ROLL_ENERGY].sum())
            sim.ledger.energy[E_STRAIN_R] = 0.0
            roll[:] = 0.0

    def changed(self):
        """The pair list changed (renumbered, restored): its work space is made anew."""
        self._chunks_for = None

    def work_space(self, threaded: bool) -> Pairs:
        """The pair list with its work space: chunks (one per thread, about equal numbers
        of pairs), the particle range of each (:func:`dem.pair_chunks`), the band
        buffers (chunks, rows, 3) for the forces and torques a chunk adds to particles
        beyond its own (:func:`dem._pair_loop`) and, for rolling resistance, the pair
        geometry (P, 4); made anew when the pair list or the thread count changes. The
        band buffers and the geometry keep their memory across rebuilds while it is
        large enough (fresh pages cost a fault each)."""
        sim = self.sim
        n_chunks = numba.get_num_threads() if threaded else 1
        if self._chunks_for == n_chunks:
            return sim.pairs
        pairs = sim.pairs
        n_pairs = len(pairs.i)
        n = len(sim.r)
        chunks, spans = sim.backend.pair_chunks(pairs.i, pairs.j, n, n_chunks)
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
