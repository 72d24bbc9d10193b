"""The certified 'auto' time step of a Simulation: estimates, cover, drift, motion limit.

:class:`AutoStep` is attached to every :class:`~demstep.engine.Simulation` as
``sim.auto`` and acts while its ``timestep.mode`` is 'auto'. Between chunks of steps
the Simulation asks it:

* :meth:`AutoStep.propose_dt` -- a new estimate, when one is due: ``safety`` x the
  certified critical step of every contact that can close before the next estimate
  (the exact step, the damped one, or the coupled element bound; the horizon of
  ``timestep.every`` steps), growth capped, decreases immediate, and the motion limit
  on top;
* :meth:`AutoStep.accept` -- whether the step still holds after the steps just taken:
  every contact closed or closing is covered (or can be added to the certificate,
  :meth:`AutoStep.certify_added`), and the covered contacts' normals have not turned
  beyond the certificate's drift budget (:mod:`demstep.timestep.certificate`);
* :meth:`AutoStep.update` -- the two together, as the run loop calls them.

Its state (the certificate, the critical mode, the record of covered contacts and of
those added since the estimate, the drift budgets, the schedule) is declared in
:meth:`AutoStep.__init__` and saved and restored by :meth:`AutoStep.state_dict` and
:meth:`AutoStep.load_state_dict` (keys ``ts_*`` of a checkpoint); the clumps' turn
budget is not saved: a restart checks the drift at its first step instead
(:meth:`AutoStep.load_state_dict`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from demstep.contact.geometry import pair_geometry_arrays, wall_geometry_arrays
from demstep.contact.laws import LAWS, params_from_row
from demstep.timestep.contacts import ContactSet
from demstep.engine.analysis import (NO_COVER, coefficients, contact_elements, global_damping,
                                     pair_keys, sorted_keys, wall_keys, walls_per_key)
from demstep.engine.meshes import no_mesh_cover
from demstep.errors import InputError
from demstep.kernels import dem
from demstep.kernels.meshes import mesh_cover_check
from demstep.kernels.timestep_kernels import rolling_coefficient_arrays
from demstep.particles import INERTIA_FACTOR
from demstep.scratch import Workspace
from demstep.timestep.certificate import (BodyPose, StepCertificate, added_contacts_bound,
                                          cover_limits, merge_cover, mesh_added_bound,
                                          uncovered_pairs, uncovered_walls)
from demstep.timestep.clumps import body_element_dt, likely_stiffest_elements
from demstep.timestep.estimates import densest_packing_dt, element_coupled_dt
from demstep.timestep.exact import ScaledContactOperator, exact_critical_step
from demstep.timestep.stability import damped_sigma


def any_uncovered(masks) -> bool:
    """Whether :meth:`AutoStep.uncovered` found a contact beyond the cover."""
    return bool(masks[0].any() or masks[1].any() or masks[2] is not None)


class AutoStep:
    """The 'auto' time-step control of ``sim`` (module docstring)."""

    def __init__(self, sim):
        self.sim = sim
        #: the certified step [T], the ceiling of dt (None: no estimate yet)
        self.certified: float | None = None
        #: the certified critical step of the last estimate [T]
        self.estimate: float | None = None
        #: the horizon [T] of the last estimate: contacts that can close within it
        self.horizon: float | None = None
        #: the step at which the next scheduled estimate is due
        self.next_update = 0
        #: the last estimate's certificate (:class:`StepCertificate`)
        self.certificate: StepCertificate | None = None
        #: the last critical mode (the warm start of the next solve)
        self.mode: np.ndarray | None = None
        #: what the last exact estimate guarantees
        #: (:class:`~demstep.timestep.guarantee.Guarantee`: a proof on small systems,
        #: else a failure probability with the seed of its random start; None: none yet,
        #: or an element-coupled estimate, a rigorous lower bound)
        self.guarantee = None
        #: the contacts the last estimate covered ({'pairs': (keys, overlaps), 'walls':
        #: ...}; None before the first estimate): :attr:`cover`
        self._cover: dict | None = None
        #: the contacts added to the certificate since its estimate, as one record
        #: (:meth:`certify_added`; {} none yet, None not known: an older checkpoint)
        self.added: dict | None = None
        #: per particle, how many mesh contacts the certificate's added group holds for
        #: it and at what overlap [L] (N, 2) (:meth:`certify_added`; None: no certificate)
        self.mesh_added: np.ndarray | None = None
        #: how far [L] the pairs' ends may move relative to each other before the next
        #: check of the drift (:meth:`renew_drift_budget`)
        self.check_budget = math.inf
        #: with clumps: how far the bodies may turn before that check, and their
        #: orientations at the last one (None: none known, the next step checks; not
        #: saved, :meth:`load_state_dict`)
        self.turn_budget = 0.0
        self.check_q: np.ndarray | None = None
        #: the solver's scratch arrays, kept from one estimate to the next
        self.workspace = Workspace(huge_pages=False)
        #: how many estimates: in all, by an exact solve, decided by the coupled element
        #: bound, kept from the last certificate, and contacts added without an estimate
        self.n_estimates = 0
        self.n_solves = 0
        self.n_element = 0
        self.n_refreshes = 0
        self.n_extensions = 0

    def pair_keys(self, i, j):
        """The keys of the pairs (i, j), i < j, in the records of covered contacts."""
        return pair_keys(len(self.sim.r), i, j)

    @property
    def walls_per_key(self) -> int:
        """The base of the particle-wall keys (:meth:`wall_keys`): the number of walls."""
        return walls_per_key(self.sim)

    def wall_keys(self, p, w):
        """The keys of the particle-wall contacts (p, w) in the records of covered
        contacts."""
        return wall_keys(self.walls_per_key, p, w)

    def new_pairs_closing(self, cover, wall_cover) -> bool:
        """At a rebuild, with the 'auto' control's cover tracked (``cover``,
        ``wall_cover`` per pair and wall pair of the new lists): whether a pair not
        covered (a new one) is closed already or closing in the next step (as
        :func:`demstep.kernels.dem.closing_beyond_cover` looks at the pairs the steps
        know at the positions they end with; those the rebuild brought they have not
        seen)."""
        sim = self.sim
        found = False
        ws = sim.wall_state
        # (no cover tracked, no 'auto' estimate: nothing looked at; the moves of the new
        # pairs' particles only: a rebuild comes every few steps in a fast flow, and all
        # N of them were 2 ms of a 9 ms rebuild at 1e5)
        if len(cover) and len(cover) == len(sim.pairs.i):
            new = cover == 0.0
            if new.any():
                i, j = sim.pairs.i[new], sim.pairs.j[new]
                (move_i, move_j), boundary = self.step_moves(np.stack([i, j]))
                delta = pair_geometry_arrays(sim.x, sim.r, i, j, sim.periodic_len)[2]
                found = bool((delta + move_i + move_j + boundary > 0.0).any())
        if not found and len(wall_cover) and len(wall_cover) == len(ws.p):
            new = wall_cover == 0.0
            if new.any():
                p = ws.p[new]
                move, boundary = self.step_moves(p)
                delta = wall_geometry_arrays(sim.x, sim.r, p, ws.wall[new], ws.point,
                                             ws.normal)[2]
                found = bool((delta + move + boundary > 0.0).any())
        return found

    def renumber(self, order: np.ndarray, inv: np.ndarray):
        """The particles renumbered (new particle k is old ``order[k]``, ``inv`` the
        inverse; :func:`demstep.engine.ordering.reorder`): the cover's keys, the certificate
        (:meth:`demstep.timestep.certificate.StepCertificate.renumber`) and the
        critical mode (a warm start: dropped with clumps, whose modes are per body)."""
        sim = self.sim
        n = len(order)
        base = self.walls_per_key

        def pairs(keys):
            a, b = inv[keys // n], inv[keys % n]
            return self.pair_keys(np.minimum(a, b), np.maximum(a, b)), slice(None)

        self._rekey(pairs, lambda keys: (self.wall_keys(inv[keys // base], keys % base),
                                         slice(None)))
        cert = self.certificate
        if cert is not None:
            cert.renumber(order, inv)
        if self.mesh_added is not None and len(self.mesh_added) == n:
            self.mesh_added = np.ascontiguousarray(self.mesh_added[order])
        self.sync_mesh_cover()
        mode = self.mode
        if mode is not None:
            self.mode = (None if sim.bodies.n or mode.size % n
                             else mode.reshape(n, -1)[order].reshape(-1))

    def removed(self, keep: np.ndarray, inv: np.ndarray):
        """Particles were taken out (:func:`demstep.engine.population.remove_particles`:
        ``keep`` the old rows kept, in order, ``inv`` each old row's new one or -1): the
        certificate keeps the contacts between what remains, renamed, and holds without
        a new estimate (:meth:`demstep.timestep.certificate.StepCertificate.remove`:
        removing particles only lowers the largest eigenvalue); the records of covered
        and added contacts and the critical mode are renamed alike. The drift is checked
        at once (a new estimate if it fails)."""
        sim = self.sim
        n_old, n = len(inv), len(keep)
        base = self.walls_per_key

        def pairs(keys):
            a, b = inv[keys // n_old], inv[keys % n_old]
            ok = (a >= 0) & (b >= 0)
            return pair_keys(n, a[ok], b[ok]), ok  # (the order kept: a < b still)

        def walls(keys):
            p = inv[keys // base]
            ok = p >= 0
            return wall_keys(base, p[ok], (keys % base)[ok]), ok

        self._rekey(pairs, walls)
        if self.certificate is not None:
            self.certificate.remove(keep, inv)
        if self.mesh_added is not None:
            self.mesh_added = np.ascontiguousarray(self.mesh_added[keep])
        mode = self.mode
        if mode is not None:
            self.mode = (None if mode.size % n_old or n == 0
                         else mode.reshape(n_old, -1)[keep].reshape(-1))
        self.sync_cover()
        if sim.timestep.mode == "auto" and sim.dt is not None and sim.lists.built \
                and not self.renew_drift_budget():
            self.propose_dt(force=True, scheduled=False)

    def inserted(self, n_old: int) -> bool:
        """Particles were appended (rows ``n_old`` on; :func:`demstep.engine.population.
        add_particles`), before the lists are rebuilt: the certificate is kept
        (:meth:`demstep.timestep.certificate.StepCertificate.extend`: the new particles
        are in none of its contacts), the records of covered and added pairs re-keyed
        for the new count, the per-particle records grown with empty rows; the new
        particles' contacts are then added as any contact the estimate did not cover
        (:meth:`after_insertion`). Returns whether a certificate was kept (False: none,
        or one with clumps, which insertion does not support)."""
        sim = self.sim
        cert = self.certificate
        n = len(sim.r)
        if cert is None or cert.has_bodies or n_old == 0:
            self.forget()
            return False
        # (the key i n + j of a pair depends on n; a wall contact's does not)
        self._rekey(lambda keys: (pair_keys(n, keys // n_old, keys % n_old), slice(None)),
                    lambda keys: (keys, slice(None)))
        new = slice(n_old, n)
        inv_I = sim.inv_I[new] if sim.rotation else np.zeros(n - n_old)
        cert.extend(sim.r[new], sim.inv_m[new], inv_I)
        if self.mesh_added is not None:
            self.mesh_added = np.concatenate([self.mesh_added, np.zeros((n - n_old, 2))])
        mode = self.mode
        if mode is not None:
            self.mode = (None if mode.size % n_old else np.concatenate(
                [mode.reshape(n_old, -1), np.zeros((n - n_old, mode.size // n_old))]).reshape(-1))
        return True

    def after_insertion(self, kept: bool):
        """After an insertion's lists are built: with the certificate kept
        (:meth:`inserted`), the pair loops' cover synced to the new lists and the
        contacts closing now that it does not cover added or a new estimate made
        (:meth:`accept`), before the next step; else (:meth:`resized`) a new estimate."""
        sim = self.sim
        if not kept:
            self.resized()
            return
        self.sync_cover(reset=False)
        if sim.timestep.mode == "auto" and sim.dt is not None and sim.lists.built \
                and not self.accept():
            self.propose_dt(force=True, scheduled=False)

    def _rekey(self, pairs, walls):
        """The records of covered and added contacts (``_cover``, ``added``: keys and
        overlaps) renamed: ``pairs(keys)`` and ``walls(keys)`` give the new keys of a
        record's pairs or wall contacts and which of them are kept (a mask or a slice);
        the keys sorted again with their overlaps."""
        for attr in ("_cover", "added"):
            record = getattr(self, attr)
            if not record:
                continue
            renamed = {}
            for name, (keys, assumed) in record.items():
                keys, assumed = np.asarray(keys, np.int64), np.asarray(assumed)
                keys, ok = (pairs if name == "pairs" else walls)(keys)
                renamed[name] = sorted_keys(keys, assumed[ok])
            setattr(self, attr, renamed)

    def forget(self):
        """Drop what names particles by index (the certificate, the critical mode, the
        records of covered contacts): before the lists of a changed particle set are
        built (their rebuild may renumber the particles)."""
        self.certificate = None
        self.mode = None
        self.added = {}
        self.mesh_added = None
        if self._cover is not None:
            self.cover = {}

    def resized(self):
        """The particle set changed (:mod:`demstep.engine.population`): the certificate,
        the critical mode and the records of covered contacts name particles by index
        and are dropped; in 'auto' mode a new estimate at once (before the next step)
        covers every contact the new set can close within its horizon. It may only
        lower the certified step (an estimate at least as large leaves the step
        certified for the old set, which the new one does not need more than)."""
        sim = self.sim
        self.forget()
        if sim.timestep.mode == "auto" and sim.dt is not None and sim.lists.built:
            self.propose_dt(force=True, scheduled=False)

    def record_certificate(self, sigma, lam_c, contacts, bodies, mesh_caps=None):
        """The certificate of an estimate (root ``sigma``, Lambda_C ``lam_c``) of the
        ``contacts`` (:func:`demstep.engine.analysis.contact_set`), the mesh contacts
        among them covered at the overlaps ``mesh_caps`` [L] (in their order)."""
        sim = self.sim
        inv_I = sim.inv_I if sim.rotation else np.zeros_like(sim.inv_I)
        # (contact_set puts the intact bonds last)
        bond = np.arange(contacts.n) >= contacts.n - int(np.count_nonzero(sim.bonds.intact == 1))
        mesh = contacts.wall >= len(sim.walls)
        b = sim.bodies
        self.added = {}  # (contacts added to this certificate: none yet)
        self.certificate = cert = StepCertificate.from_estimate(
            sigma, lam_c, contacts.subset(~mesh) if mesh.any() else contacts, sim.inv_m,
            inv_I, inputs=self.inputs(), radius=sim.r, bond=bond[~mesh],
            sphere_body=b.sphere_body if b.n else None, body_q=b.q.copy() if b.n else None)
        if mesh.any():
            near = contacts.subset(mesh)
            p = near.i
            cert.mesh_p = np.ascontiguousarray(p, dtype=np.int64)
            cert.mesh_k = np.ascontiguousarray(near.wall - len(sim.walls), dtype=np.int64)
            cert.mesh_ref = np.ascontiguousarray(np.column_stack([
                near.normal, near.arm_i, near.k_n, near.k_s, near.c_n, near.c_t,
                np.asarray(mesh_caps, dtype=np.float64), sim.inv_m[p], inv_I[p]]))
        self.mesh_added = np.zeros((len(sim.r), 2)) if sim.mesh_walls else None
        self.sync_mesh_cover()

    def sync_mesh_cover(self, limit: float | None = None):
        """The Meshes bundle's cover rows (:class:`demstep.state.Meshes`: what the kernels
        compare each sphere's mesh contacts with, :mod:`demstep.kernels.meshes`) from the
        certificate's covered mesh contacts and the added group, followed while there is
        a cover (an estimate) and mesh walls; ``limit`` [1/T^2]: the mesh drift at which
        the steps stop for a check (None: kept)."""
        sim = self.sim
        if not sim.mesh_walls:
            return
        me = sim.meshes
        ctl = me.cover_ctl
        if self._cover is None or self.mesh_added is None \
                or len(self.mesh_added) != len(sim.r):
            fresh = no_mesh_cover()
            fresh["cover_ctl"][2:] = ctl[2:]  # (the meshes' last move)
            sim.meshes = me._replace(**fresh)
            return
        cert = self.certificate
        n = len(sim.r)
        if cert is None:  # (a cover without a certificate: any mesh contact is beyond it)
            self.mesh_added = np.zeros((n, 2))
        if cert is not None and len(cert.mesh_p):
            order = np.argsort(cert.mesh_p, kind="stable")
            start = np.zeros(n + 1, dtype=np.int64)
            np.cumsum(np.bincount(cert.mesh_p, minlength=n), out=start[1:])
            rows = dict(cover_mesh=np.ascontiguousarray(cert.mesh_k[order]),
                        cover_ref=np.ascontiguousarray(cert.mesh_ref[order]))
        else:
            start = np.zeros(n + 1, dtype=np.int64)
            rows = dict(cover_mesh=np.zeros(0, np.int64), cover_ref=np.zeros((0, 11)))
        ctl = ctl.copy()
        ctl[0] = self.certified_sigma() if sim.dt is not None else 0.0
        if limit is not None:
            ctl[1] = limit
        sim.meshes = me._replace(cover_start=start, cover_extra=np.ascontiguousarray(
            self.mesh_added), cover_ctl=ctl, **rows)

    @property
    def meshes_followed(self) -> bool:
        """Whether the kernels follow the mesh contacts' cover (an estimate, mesh walls)."""
        sim = self.sim
        return bool(sim.mesh_walls) and len(sim.meshes.cover_start) == len(sim.r) + 1

    def mesh_check(self, steps: float = 0.0):
        """((D_K [1/T^2], D_C [1/T]), short, need): the mesh contacts' drift now, how
        many spheres have contacts beyond the cover and the added group now or within
        ``steps`` steps at the velocities now, and per sphere (N, 2) how many of its
        contacts the cover does not hold and at what overlap [L]
        (:func:`demstep.kernels.meshes.mesh_cover_check`)."""
        sim = self.sim
        need = np.zeros((len(sim.r), 2))
        if not self.meshes_followed:
            return (0.0, 0.0), 0, need
        dt = float(sim.dt) if sim.dt is not None else 0.0
        _, boundary = self.step_moves(np.zeros(0, dtype=np.int64))
        d_k, d_c, short = mesh_cover_check(sim.x, sim.v, sim.r, sim.meshes, float(steps),
                                           float(steps) * boundary, dt, need)
        return (float(d_k), float(d_c)), int(short), need

    def mesh_added_bound(self, added: np.ndarray) -> tuple[float, float]:
        """Bounds on lambda_max(K^), lambda_max(C^) of the mesh contacts of the added
        group ``added`` (N, 2): per particle so many contacts at most at that overlap,
        each with the stiffest mesh's law there (:func:`mesh_added_bound
        <demstep.timestep.certificate.mesh_added_bound>`)."""
        sim = self.sim
        on = added[:, 0] > 0
        if not on.any():
            return 0.0, 0.0
        p = np.flatnonzero(on)
        params = sim.law.params()
        top = np.zeros((4, len(p)))
        at = added[p, 1] if sim.law.nonlinear else sim.r[p]  # (linear: any overlap)
        for k in range(sim.meshes.n):
            top = np.maximum(top, np.stack(coefficients(
                params_from_row(params, sim.meshes.law[k]), at, sim.r[p], sim.m[p])))
        inv_I = sim.inv_I if sim.rotation else np.zeros_like(sim.inv_I)
        return mesh_added_bound(added[p, 0], *top, sim.r[p], sim.inv_m[p], inv_I[p])

    def drift(self, cert, mesh_drift=None) -> tuple[float, float]:
        """The drift (D_K, D_C) of the certificate ``cert`` at the state now
        (:meth:`demstep.timestep.certificate.StepCertificate.drift`), the mesh contacts'
        included (``mesh_drift``: theirs, if :meth:`mesh_check` gave it already)."""
        sim = self.sim
        d_k, d_c = cert.drift(sim.x, sim.periodic_len, (sim.wall_point, sim.wall_normal),
                              self.body_pose() if cert.has_bodies else None)
        if mesh_drift is None and self.meshes_followed:
            mesh_drift = self.mesh_check()[0]
        if mesh_drift is not None:
            d_k, d_c = d_k + mesh_drift[0], d_c + mesh_drift[1]
        return d_k, d_c

    def body_pose(self):
        """The clumps now as the certificate's drift takes them
        (:class:`demstep.timestep.certificate.BodyPose`)."""
        sim = self.sim
        b = sim.bodies
        offset = np.zeros((len(sim.r), 3))
        offset[b.member] = b.offset
        inv_I = np.array(b.inv_I, dtype=np.float64)
        if sim.dim == 2:  # (disks turn about z only)
            inv_I[:, :2] = 0.0
        if not sim.rotation:
            inv_I[:] = 0.0
        return BodyPose(b.sphere_body, offset, b.q, b.inv_m, inv_I)

    def inputs(self) -> np.ndarray:
        """What an 'auto' estimate depends on besides the geometry, the masses and the
        bonds (changing those drops the certificate where they change): the law's kind,
        springs and dashpots (its parameters, the law's ``Params`` tuple,
        without the friction limits, which the analysis does not use: sliding contacts
        count as sticking ones) and the global viscous damping a1 [1/T]. A certificate
        made with other inputs certifies nothing now (a stage that changes the damping
        or the law, a user who sets ``sim.law``): :meth:`prepare` then has dt chosen
        anew."""
        sim = self.sim
        params = sim.law.params()._replace(mu=0.0, mu_wall=0.0, mu_r=0.0, mu_w=0.0)
        kind = float(list(LAWS).index(sim.law.name))
        return np.array((kind,) + tuple(params) + (float(sim.damping.viscous),))

    def densest_packing_dt(self) -> float:
        """The damped coupled element bound of the densest packing of the lightest
        particles with the law's largest stiffness (Hertz: at the TimeStep overlap) and
        its dashpots: the step before any contact can form."""
        sim = self.sim
        params = sim.law.params()
        r = sim.radius_max()
        m = sim.m_min
        b = sim.bodies
        if b.n:  # a body's contact point is at most its extent from its centre
            arm = np.linalg.norm(sim.rigid_bodies().arm, axis=1).max() + r
            m = min(m, float(np.min(1.0 / (1.0 / b.m + arm * arm / b.inertia.min(axis=1)))))
        # a wall contact (R* = r_max) at the TimeStep overlap: the law's stiffness_max()
        kn, kt, cn, ct = coefficients(params,
                                            np.array([sim.timestep.overlap * r]),
                                            np.array([r]), np.array([0.5 * m]))
        rolling = {}
        if params.has_rolling:  # such a contact's rolling springs (R* = r_max: stiffer than
            # a pair's), the equivalent inertia of two of the lightest particles

            i_star = 0.5 * (INERTIA_FACTOR[sim.dim] + 1.0) * m * r * r
            rolling = dict(zip(("k_r", "k_w", "c_r", "c_w"), (
                float(v[0]) for v in rolling_coefficient_arrays(params, kn, kt, np.array([r]),
                                                                np.array([i_star])))))
        return densest_packing_dt(sim.dim, m, kn[0], kt[0], cn[0], ct[0],
                                  sim.damping.viscous, sim.rotation, radius=r, **rolling)

    def propose_dt(self, force: bool = False, scheduled: bool = True) -> float:
        """The step [T] for the next steps, ``sim.dt`` set to it: ``safety`` x the
        certified critical step of every contact that can close before the next estimate
        (:meth:`solve` with the horizon of ``every`` steps), dashpots and global damping
        included; growth capped, decreases immediate; the motion limit on top
        (:meth:`motion_limited_dt`). A new estimate only when one is due (``force``:
        now). :meth:`accept` forces one as soon as a contact closes that the last one did
        not include (``scheduled`` False: it may only lower dt and leaves the schedule
        of the regular estimates alone)."""
        sim = self.sim
        ts = sim.timestep
        if sim.dt is None:  # (a reset: no step certified either)
            self.certified = None
        if not force and sim.dt is not None and sim.step < self.next_update:
            return sim.dt
        fallback = self.densest_packing_dt()
        certified = self.certified
        horizon = int(ts.every) * (certified if certified is not None else
                                   ts.safety * fallback)
        self.horizon = horizon
        estimate = None
        prepared = None  # the contact set a refused shortcut built, for the new estimate
        if scheduled and certified is not None:
            estimate, prepared = self.refreshed_estimate(horizon)
        if (estimate is None and sim.lists.built and certified is not None
                and ts.method == "exact"):
            estimate, prepared = self.element_estimate(horizon, scheduled, prepared)
        if estimate is None and sim.lists.built:
            estimate = self.solve(ts.method, horizon, self.solve_tol(certified), prepared)
            if estimate is not None and ts.method == "exact":
                self.n_solves += 1
        if estimate is None or not math.isfinite(estimate):
            # (no contact can close, or none moves anything: a fixed particle on a
            # wall has an infinite critical step; free flight takes the fallback)
            estimate = fallback
        self.estimate = estimate
        self.n_estimates += 1
        target = ts.safety * self.local_damping_factor() * estimate
        if certified is None or target < certified:
            certified = target
        elif scheduled:
            certified = min(target, certified * (1.0 + ts.growth))
        self.certified = certified
        sim.dt = self.motion_limited_dt()
        if scheduled:
            self.next_update = sim.step + int(ts.every)
        self.renew_drift_budget()  # (dt or the certificate changed)
        return sim.dt

    def update(self):
        """After a chunk of steps: a new estimate when one is scheduled, or when the step
        no longer holds (:meth:`accept`: it may only lower dt then); else the step the
        motion limit allows (:meth:`limit_motion`)."""
        if self.sim.step >= self.next_update:
            self.propose_dt(force=True)
        elif not self.accept():
            self.propose_dt(force=True, scheduled=False)
        else:
            self.limit_motion()

    def prepare(self):
        """Before a run: a certificate made with other inputs (:meth:`inputs`: a stage
        changed the law or the damping, a user set ``sim.law``) certifies nothing now,
        and the step is chosen anew."""
        if self.certificate is not None and not self.certificate.made_with(self.inputs()):
            self.certificate = None
            self.sim.dt = None

    def release(self):
        """The mode is no longer 'auto': nothing to watch (the pair loops stop counting
        contacts beyond the cover)."""
        self.certified = None
        if self.cover is not None:
            self.cover = None

    def solve(self, method: str, horizon: float, tol: float, prepared=None) -> float | None:
        """A new estimate: the critical step [T] by ``method`` ('exact' or
        'element-coupled') of every contact that can close within ``horizon`` [T], with
        the dashpots and the global damping (None without contacts); the contacts it
        covers, the critical mode and the certificate recorded. ``tol``: the relative
        residual of an exact solve; ``prepared``: the (ContactSet, cover) of
        :func:`demstep.engine.analysis.contact_set` at this state and horizon, if built
        already."""
        sim = self.sim
        if prepared is None:
            cover = {}
            prepared = (sim.contact_set(horizon, cover), cover)
        contacts, cover = prepared
        mesh_caps = cover.pop("meshes", None)
        self.certificate = None
        self.cover = cover
        if contacts.n == 0:
            return None
        if method == "element-coupled":
            return self.element_coupled_dt(contacts, sim.rotation, keep=lambda dt: True,
                                           mesh_caps=mesh_caps)[0]
        bodies = sim.rigid_bodies()
        # the step certified with its guarantee (the random-start check of
        # demstep.timestep.guarantee on large systems), not the solver's own bound
        result = exact_critical_step(sim.particles_now(check=False), contacts, sim.rotation,
                                     global_damping(sim), v0=self.mode, bodies=bodies,
                                     workspace=self.workspace, tol=float(tol), guarantee=True)
        self.mode = result.mode
        self.guarantee = result.guarantee
        self.record_certificate(2.0 / result.dt_certified, result.operator.damping_bound(),
                                contacts, bodies, mesh_caps)
        return result.dt_certified

    #: 'auto': the step held by the motion limit sits this far below it (so that it is
    #: not changed at every chunk of steps while the particles speed up or slow down)
    MOTION_SLACK = 0.05

    def motion_rate(self) -> float:
        """How fast the fastest particle moves in radii per unit time [1/T]: from the
        kernels' largest |v| dt / r of the last step (``COUNT_JUMP``), or before the
        first step from the initial velocities (clump members' are their bodies' V +
        omega x arm from the start: :func:`demstep.kernels.clumps.member_velocities`)."""
        sim = self.sim
        if not sim.first_step_pending and sim.dt_prev > 0.0:
            return float(sim.counters[dem.COUNT_JUMP]) / sim.dt_prev
        speed = np.sqrt(np.einsum("ij,ij->i", sim.v, sim.v))
        return float(np.max(speed / sim.r, initial=0.0))

    def motion_limit(self) -> float:
        """The step [T] at which the fastest particle would move ``timestep.motion`` of
        its radius (:meth:`_motion_rate`; inf: nothing moves)."""
        sim = self.sim
        rate = self.motion_rate()
        return sim.timestep.motion / rate if rate > 0.0 else math.inf

    def motion_limited_dt(self) -> float:
        """The step [T] to take: the certified one (:attr:`dt_certified`), or less where
        a particle would move more than ``timestep.motion`` of its radius in a step at
        its speed now (:meth:`_motion_rate`). While the limit holds the step, it is
        kept within :data:`MOTION_SLACK` below the limit, and changed only when the limit
        leaves that band."""
        sim = self.sim
        certified = self.certified
        limit = self.motion_limit()
        if limit >= certified * (1.0 + self.MOTION_SLACK):
            return certified
        dt = sim.dt
        if dt is not None and limit / (1.0 + self.MOTION_SLACK) <= dt <= min(limit, certified):
            return dt
        return min(certified, limit / (1.0 + self.MOTION_SLACK))

    def limit_motion(self):
        """'auto', between estimates: the step the motion limit allows now
        (:meth:`_motion_limited_dt`). A smaller step keeps the certificate and its drift
        budget (made for a larger one); a larger one (at most the certified step)
        checks the budget anew, and a new estimate follows if the certificate fails."""
        sim = self.sim
        if self.certified is None or sim.dt is None:
            return
        dt = self.motion_limited_dt()
        if dt == sim.dt:
            return
        raised = dt > sim.dt or self.meshes_followed  # (the kernels' mesh drift is at sigma)
        sim.dt = dt
        if raised and not self.renew_drift_budget():
            self.propose_dt(force=True, scheduled=False)

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

    def solve_tol(self, certified: float | None) -> float:
        """The relative residual of an 'auto' exact solve: :data:`AUTO_MOTION_TOL` when
        the motion limit (:meth:`_motion_limit`) is at least :data:`AUTO_MOTION_MARGIN`
        below the ``certified`` step [T] of the last estimate, else
        :data:`AUTO_EXACT_TOL`."""
        if certified is not None and self.motion_limit() < certified * (
                1.0 - self.AUTO_MOTION_MARGIN):
            return self.AUTO_MOTION_TOL
        return self.AUTO_EXACT_TOL

    #: 'auto': a scheduled estimate keeps the last certificate (with the drift of its
    #: normals and the contacts added since) instead of a new solve when the step it
    #: certifies is within this of the last critical mode's Rayleigh quotient now, a
    #: lower bound on the root (so dt is at most this far below a new solve's)
    AUTO_REFRESH_RTOL = 1e-2

    def refreshed_estimate(self, horizon: float):
        """(dt, prepared): the critical step [T] the last certificate still gives (every
        closed contact covered, the drift followed), when a new estimate could not give
        a different dt: the growth cap already holds dt below ``safety`` x that step, or
        (the exact method) it is within :data:`AUTO_REFRESH_RTOL` of the best a new
        estimate could give; else None. And the (ContactSet, cover) it built for
        ``horizon``, if it got that far (None otherwise), for a new estimate of the same
        state to take instead of building it again."""
        sim = self.sim
        cert = self.certificate
        if cert is None or not cert.bounded or not sim.lists.built:
            return None, None
        masks = self.uncovered()
        if masks is None or any_uncovered(masks):
            return None, None
        sigma_up = cert.smallest_sigma(self.drift(cert))
        if self.estimate_cannot_change_dt(2.0 / sigma_up, scheduled=True):
            self.n_refreshes += 1
            return 2.0 / sigma_up, None
        mode = self.mode
        if mode is None or sim.timestep.method != "exact":
            return None, None
        cover = {}
        contacts = sim.contact_set(horizon, cover)
        prepared = (contacts, cover)
        if contacts.n == 0:
            return None, prepared
        op = ScaledContactOperator(sim.particles_now(check=False), contacts, sim.rotation,
                                   global_damping(sim), None,
                                   workspace=self.workspace)
        if op.size != mode.size:
            return None, prepared
        sigma_lo = float(damped_sigma(*op.rayleigh_terms(mode / np.linalg.norm(mode))))
        # (sigma_lo > sigma_up: the certificate does not hold; a new estimate is due)
        if not sigma_lo <= sigma_up <= sigma_lo * (1.0 + self.AUTO_REFRESH_RTOL):
            return None, prepared
        self.n_refreshes += 1
        return 2.0 / sigma_up, prepared

    def estimate_cannot_change_dt(self, estimate: float, scheduled: bool) -> bool:
        """Whether a certified step ``estimate`` [T] (a lower bound on the critical one)
        already decides dt, so that the exact step, at least as large, would give the
        same: the growth cap (a ``scheduled`` estimate) or the rule that a forced one
        only lowers dt holds dt at or below ``safety`` x ``estimate``."""
        sim = self.sim
        ts = sim.timestep
        return (ts.safety * self.local_damping_factor() * estimate
                >= self.certified * ((1.0 + ts.growth) if scheduled else 1.0))

    def local_damping_factor(self) -> float:
        """1 / sqrt(1 + local): what local (Cundall) damping takes off the certified
        step. Its force -local |F| sign(v) takes the sign of the lagged half-step velocity,
        which in the fastest (period-two) mode is that of the displacement: it adds
        local |F| to the restoring force, a stiffness (1 + local) K for that mode
        (measured: unstable from 0.90 and 0.78 of the undamped step at local 0.3 and
        0.7, against 0.877 and 0.767). The 'auto' step is safety x this x the certified
        step of K and C; a root sigma_0 of (K, C) gives sqrt(1 + local) sigma_0 for
        ((1 + local) K, C), since lambda_max(s C + (1 + local) K) <= (1 + local)
        lambda_max(s / sqrt(1 + local) C + K) (C >= 0)."""
        sim = self.sim
        return 1.0 / math.sqrt(1.0 + float(sim.damping.local))

    def certified_sigma(self) -> float:
        """The root [1/T] the last certificate (of K and C) must reach for dt to hold
        with local damping: 2 / (dt sqrt(1 + local)) (:meth:`_local_damping_factor`)."""
        sim = self.sim
        return 2.0 * self.local_damping_factor() / sim.dt

    def element_estimate(self, horizon: float, scheduled: bool, prepared=None):
        """(dt, prepared) for an 'exact' estimate that may not need its solve: the
        coupled element bound [T] of every contact that can close within ``horizon`` (a
        rigorous lower bound on the exact step, from one pass over the contacts) when
        it already decides dt (:meth:`_estimate_cannot_change_dt`); it is then recorded
        as the certificate in the solve's place. Else None, and the (ContactSet, cover)
        built (or the ``prepared`` one taken) for the exact solve."""
        sim = self.sim
        if prepared is None:
            cover = {}
            prepared = (sim.contact_set(horizon, cover), cover)
        contacts, cover = prepared
        if contacts.n == 0:
            return None, prepared
        keep = lambda dt: self.estimate_cannot_change_dt(dt, scheduled)  # noqa: E731
        if self.element_bound_falls_short(contacts, keep):
            return None, prepared
        dt, kept = self.element_coupled_dt(contacts, sim.rotation, keep=keep,
                                           mesh_caps=cover.get("meshes"))
        if not kept:
            return None, prepared
        cover.pop("meshes", None)
        self.cover = cover
        self.n_element += 1
        return dt, None

    #: 'auto' with clumps: the elements an element estimate looks at first (twice this
    #: many: :func:`demstep.timestep.clumps.likely_stiffest_elements`)
    ELEMENT_SCREEN = 32

    def element_bound_falls_short(self, contacts, keep) -> bool:
        """With clumps, whose element bound solves a small dense eigenproblem per
        contact: whether it cannot be kept (``keep(dt)`` false), decided on an upper
        bound on it, the smallest step of the elements likeliest to be the stiffest
        (:func:`demstep.timestep.clumps.likely_stiffest_elements`). False: not decided
        (to be computed in full)."""
        sim = self.sim
        bodies = sim.rigid_bodies()
        if bodies is None or contacts.n <= 4 * self.ELEMENT_SCREEN:
            return False

        p = sim.particles_now(check=False)
        d = global_damping(sim)
        rows = likely_stiffest_elements(p, contacts, bodies, sim.rotation,
                                        self.ELEMENT_SCREEN)
        dt = float(body_element_dt(p, contacts, bodies, sim.rotation, d.mass, d.stiffness,
                                   rows).min())
        if d.mass > 0:
            dt = min(dt, 2.0 / d.mass)  # (as element_coupled_dt)
        return not keep(dt)

    def element_coupled_dt(self, contacts, rotation: bool, keep,
                           mesh_caps=None) -> tuple[float, bool]:
        """(dt, kept): the coupled element bound dt [T] of ``contacts`` now (a rigorous
        lower bound on their exact step, :func:`demstep.timestep.estimates.element_coupled_dt`),
        with the global damping and the clumps; recorded as the 'auto' control's
        certificate when ``kept = keep(dt)`` is true (its mesh contacts covered at the
        overlaps ``mesh_caps``)."""
        sim = self.sim
        p = sim.particles_now(check=False)
        damping = global_damping(sim)
        bodies = sim.rigid_bodies()
        dt = element_coupled_dt(p, contacts, rotation, damping=damping, bodies=bodies)
        kept = bool(keep(dt))
        if kept:
            op = ScaledContactOperator(p, contacts, rotation, damping, bodies,
                                       workspace=self.workspace)
            self.record_certificate(2.0 / dt, op.damping_bound(), contacts, bodies, mesh_caps)
        return dt, kept

    def state_dict(self) -> dict:
        """Arrays of the 'auto' time-step control that a restart needs to continue bit for
        bit (the last critical mode, a start of the damped iteration, and the contacts the
        last estimate covered), keyed ``ts_*``; not the clumps' turn budget, which a
        restart sets anew (:meth:`load_state_dict`)."""
        out = {}
        mode = self.mode
        if mode is not None:
            out["ts_mode"] = mode
        cert = self.certificate
        if cert is not None:
            out.update(cert.state())
        for name, (keys, assumed) in (self.cover or {}).items():
            out[f"ts_cover_{name}_keys"] = keys
            out[f"ts_cover_{name}_overlap"] = assumed
        added = self.added
        if cert is not None and added is not None:  # (None: not known, not saved)
            out["ts_added_known"] = np.array([1.0])
            for name, (keys, assumed) in added.items():
                out[f"ts_added_{name}_keys"] = keys
                out[f"ts_added_{name}_overlap"] = assumed
        if cert is not None and self.mesh_added is not None:
            out["ts_mesh_added"] = self.mesh_added
        if out:
            out["ts_check_budget"] = np.array([self.check_budget])
        if self.certified is not None:  # (the motion limit may hold dt below it)
            out["ts_dt_certified"] = np.array([self.certified])
        return out

    def check_added_record(self, data: dict, fail):
        """The record of added contacts of a checkpoint (:meth:`timestep_state`): per
        kind, integer keys naming pairs i < j of the particles or particle-wall contacts
        (:meth:`_pair_keys`, :meth:`_wall_keys`) and one finite overlap each; raises
        ``fail(key, what)``."""
        sim = self.sim
        n, base = len(sim.r), self.walls_per_key
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
    def restored_added_record(data: dict) -> dict | None:
        """The record of the contacts added to the certificate since its estimate
        (:meth:`timestep_state`, checked by :meth:`_check_added_record`; None: not known,
        so not used: a checkpoint from before it was saved)."""
        if "ts_added_known" not in data:
            return None
        return {name: (np.asarray(data[f"ts_added_{name}_keys"], dtype=np.int64),
                       np.asarray(data[f"ts_added_{name}_overlap"], dtype=np.float64))
                for name in ("pairs", "walls") if f"ts_added_{name}_keys" in data}

    def load_state_dict(self, data: dict, source: str = "state"):
        """Inverse of :meth:`state_dict` (after the Simulation's own state: the step
        ``sim.dt`` is checked against the certified one; errors name ``source``)."""
        sim = self.sim
        self.mode = np.array(data["ts_mode"]) if "ts_mode" in data else None
        self.certificate = StepCertificate.from_state(data) if "ts_cert" in data else None
        cover = {}
        for name in ("pairs", "walls"):
            if f"ts_cover_{name}_keys" in data:
                cover[name] = (np.array(data[f"ts_cover_{name}_keys"]),
                               np.array(data[f"ts_cover_{name}_overlap"]))
        # (the pair loops' cover arrays are part of the saved state: not synced here)
        self._cover = cover if cover or "ts_mode" in data else None
        self.added = self.restored_added_record(data)
        mesh_added = data.get("ts_mesh_added")
        self.mesh_added = None
        if mesh_added is not None:
            mesh_added = np.asarray(mesh_added, dtype=np.float64)
            if mesh_added.shape != (len(sim.r), 2) or not np.isfinite(mesh_added).all() \
                    or (mesh_added < 0).any():
                raise InputError(f"{source}: ts_mesh_added: expected ({len(sim.r)}, 2) finite "
                                 f"numbers >= 0, got shape {mesh_added.shape}")
            self.mesh_added = mesh_added
        elif self.certificate is not None and sim.mesh_walls:
            self.mesh_added = np.zeros((len(sim.r), 2))
        budget = np.asarray(data.get("ts_check_budget", [0.0]), dtype=np.float64).reshape(-1)
        if budget.size != 1 or not budget[0] >= 0.0:  # (older checkpoints: checked at once)
            raise InputError(f"ts_check_budget: expected one number >= 0, got {budget}")
        self.check_budget = float(budget[0])
        # The clumps' turn budget is not saved (nor read from checkpoints that have it,
        # ts_turn_budget, ts_check_q): with no orientations of a last check the first
        # step after the restart checks the drift (turned_since_check is inf) and sets
        # both budgets from the state then. The run goes on as it would have: a check
        # fails exactly when the certificate no longer certifies dt at the state of the
        # check, and between checks the budgets keep it certified, so when the drift is
        # checked changes no step (with clumps every step is a chunk of its own: the
        # check budget places no chunk end either); it costs one check.
        self.turn_budget, self.check_q = 0.0, None
        # (older checkpoints: dt was the certified step)
        certified = np.asarray(data.get("ts_dt_certified", [np.nan if sim.dt is None else sim.dt]),
                               dtype=np.float64).reshape(-1)
        if certified.size != 1 or not (np.isnan(certified[0]) or certified[0] > 0.0):
            raise InputError(f"ts_dt_certified: expected one number > 0, got {certified}")
        self.certified = (None if sim.timestep.mode != "auto" or np.isnan(certified[0])
                          else float(certified[0]))
        if self.certified is not None and not (sim.dt is not None and sim.dt <= self.certified):
            raise InputError(f"{source}: the step dt = {sim.dt!r} is above the certified "
                             f"one ts_dt_certified = {self.certified!r}")
        self.sync_mesh_cover()  # (the kernels' rows; the drift limit is part of the state)

    @staticmethod
    def check_certificate_state(data, numbers, in_range, finite, fail, n, n_walls, n_bodies):
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
            kb = AutoStep.check_body_certificate(data, numbers, in_range, finite, fail, n,
                                                    n_walls, n_bodies)
        in_range("ts_cert_pairs", n, "particle", pairs[:2])
        in_range("ts_cert_walls", n, "particle", walls[0])
        in_range("ts_cert_walls", n_walls, "wall", walls[1])
        if "ts_cert_meshes" in data:
            meshes = numbers("ts_cert_meshes")
            if meshes.size % 2:
                raise fail("ts_cert_meshes", f"has shape {meshes.shape}, expected (2, contacts)")
            meshes = meshes.reshape(2, -1)
            in_range("ts_cert_meshes", n, "particle", meshes[0])
            ref = numbers("ts_cert_mesh_ref")
            if ref.size != 11 * meshes.shape[1]:
                raise fail("ts_cert_mesh_ref", f"has shape {ref.shape}, expected "
                                               f"({meshes.shape[1]}, 11)")
            finite("ts_cert_mesh_ref", nan_only=True)  # (inf: covered at any overlap)
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
    def check_body_certificate(data, numbers, in_range, finite, fail, n, n_walls,
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

    def uncovered(self, steps: float = 0.0):
        """Masks over the pair and wall lists of the closed contacts the last 'auto'
        estimate did not cover (or covered at a smaller overlap than they have now,
        for a non-linear law), and the mesh contacts' need of the added group (N, 2)
        (:meth:`mesh_check`; None when no sphere needs more than it holds); None when
        there was no estimate. ``steps`` > 0: those closing so within that many steps
        at the velocities now too (:meth:`_step_moves`)."""
        sim = self.sim
        cover = self.cover
        if cover is None:
            return None
        move, boundary = self.step_moves()
        move *= steps
        boundary *= steps
        nonlinear = sim.law.nonlinear  # a non-linear law stiffer than assumed
        none = (np.zeros(0, dtype=np.int64), np.zeros(0))
        known, assumed = cover.get("pairs", none)
        pair_mask = uncovered_pairs(sim.x, sim.r, sim.pi, sim.pj, sim.periodic_len,
                                    known, assumed, nonlinear, move, boundary)
        known, assumed = cover.get("walls", none)
        wall_mask = uncovered_walls(sim.x, sim.r, sim.wp, sim.ww, sim.wall_point,
                                    sim.wall_normal, self.walls_per_key,
                                    np.asarray(known, dtype=np.int64),
                                    np.asarray(assumed, dtype=np.float64), nonlinear,
                                    move, boundary)
        mesh_need = None
        if self.meshes_followed:
            _, short, need = self.mesh_check(steps)
            mesh_need = need if short else None
        return pair_mask, wall_mask, mesh_need

    def step_moves(self, particles=None) -> tuple[np.ndarray, float]:
        """(move, boundary) [L]: how far each particle (or each of the indices
        ``particles``) moves in a step of dt at its velocity now, |v| dt, and how far
        the walls and the periodic box moved in the last step (as
        :func:`demstep.kernels.dem.closing_beyond_cover` takes them)."""
        sim = self.sim
        dt = float(sim.dt) if sim.dt is not None else 0.0
        move = dt * np.linalg.norm(sim.v if particles is None else sim.v[particles], axis=-1)
        boundary = (float(np.sqrt((sim.wall_state.disp_prev ** 2).sum(axis=1)).max(initial=0.0))
                    + float(np.abs(sim.box.sums[5]).sum()) + float(sim.meshes.cover_ctl[2]))
        return move, boundary

    @property
    def cover(self) -> dict | None:
        """The contacts the last 'auto' estimate covered: {'pairs': (keys, overlaps),
        'walls': ...}, keys sorted (None before the first estimate). Setting it syncs
        the pair loops' cover arrays (:meth:`_sync_cover`)."""
        return self._cover

    @cover.setter
    def cover(self, cover: dict | None):
        self._cover = cover
        self.sync_cover()

    def sync_cover(self, reset: bool = True):
        """Each pair's and wall pair's cover (``pairs.cover``, ``wall_state.cover``: the
        largest overlap [L] the last estimate covered it at; any overlap with the linear
        law; 0 when not covered) from the record of the contacts it covered, for the pair
        loops to count the contacts that close beyond it; none tracked without a record.
        ``reset``: the count starts again (the record has just been checked)."""
        sim = self.sim
        cover = self.cover
        if cover is None:
            sim.pairs = sim.pairs._replace(cover=np.zeros(0))
            sim.wall_state = sim.wall_state._replace(cover=np.zeros(0))
        else:
            nonlinear = sim.law.nonlinear
            ws = sim.wall_state
            sim.pairs = sim.pairs._replace(cover=cover_limits(
                self.pair_keys(sim.pairs.i, sim.pairs.j), *cover.get("pairs", NO_COVER),
                nonlinear))
            sim.wall_state = ws._replace(cover=cover_limits(
                self.wall_keys(ws.p, ws.wall), *cover.get("walls", NO_COVER),
                nonlinear))
        self.sync_mesh_cover()
        if reset:
            sim.counters[dem.COUNT_UNCOVERED] = 0.0

    def uncovered_now(self):
        """:meth:`_uncovered`, the contacts to add to the certificate before the next
        step: skipped (none) when the steps counted no contact closed beyond its cover
        since the last check (:func:`demstep.kernels.dem._advance` looks at the
        positions each step ends with, and a rebuild at its new pairs). The cover is
        synced after a check."""
        sim = self.sim
        if self.cover is None:
            return None
        tracked = (len(sim.pairs.cover) == len(sim.pairs.i)
                   and len(sim.wall_state.cover) == len(sim.wall_state.p)
                   and (not sim.mesh_walls or self.meshes_followed))
        if tracked and sim.counters[dem.COUNT_UNCOVERED] == 0:
            return (np.zeros(len(sim.pairs.i), dtype=bool),
                    np.zeros(len(sim.wall_state.p), dtype=bool), None)
        return self.uncovered(self.LOOKAHEAD_STEPS)

    #: 'auto': a check finds the contacts closing beyond their cover within this many
    #: steps at the velocities now (the steps look one ahead), and covers them that far
    #: ahead (a non-linear law's stiffness taken there), so that a contact pressing on
    #: is not found again at the next step
    LOOKAHEAD_STEPS = 3

    def accept(self) -> bool:
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
        sim = self.sim
        masks = self.uncovered_now()
        if masks is None:
            return False
        if any_uncovered(masks):
            covered = self.certify_added(*masks)
            if covered:
                self.sync_cover()
            return covered
        if sim.counters[dem.COUNT_UNCOVERED]:
            self.sync_cover()
        cert = self.certificate
        if cert is None or sim.dt is None:
            return True
        if not cert.bounded:
            return False
        if dem.drift_used(sim.counters) <= self.check_budget and (
                not cert.has_bodies or self.turned_since_check() <= self.turn_budget):
            return True
        return self.renew_drift_budget()

    #: 'auto' with clumps: the most the bodies may turn (|dR - I|) and the pairs' ends
    #: move relative to each other (this fraction of the smallest radius) between two
    #: checks of the drift (the look-ahead's lever arms take them at these caps: small
    #: caps keep its bound close to the drift now, which it stands for at each check)
    BODY_TURN_CAP = 0.02

    BODY_MOVE_CAP = 0.02

    def turned_since_check(self) -> float:
        """How far the bodies turned since the last check of the drift: the largest
        |dR - I| = 2 sin(theta / 2), twice the vector part of q q_check^* (over the
        two lengths)."""
        sim = self.sim
        q, p = sim.bodies.q, self.check_q
        if p is None:
            return math.inf
        vec = p[:, :1] * q[:, 1:] - q[:, :1] * p[:, 1:] - np.cross(q[:, 1:], p[:, 1:])
        size = np.linalg.norm(q, axis=1) * np.linalg.norm(p, axis=1)
        return float(np.max(2.0 * np.linalg.norm(vec, axis=1) / size, initial=0.0))

    #: 'auto' with bonds: the budget of relative motion between checks of the drift is
    #: at most this fraction of the smallest radius (the bound on a bond's arms takes
    #: it; a contact's arms are at most the radii, whatever the motion)
    DRIFT_BUDGET_CAP = 0.1

    def renew_drift_budget(self) -> bool:
        """Check the drift of the 'auto' certificate now (whether it still certifies dt,
        :meth:`demstep.timestep.certificate.StepCertificate.certifies`) and, if it does,
        set the budget: how far [L] the pairs' ends may move relative to each other
        before the next check with dt still certified at every position on the way
        (:meth:`~demstep.timestep.certificate.StepCertificate.drift_budget`; the
        kernels add up how far they can have moved, ``DRIFT_SUM``, and end their
        chunk of steps there). No checks are counted in steps: a quasi-static packing
        goes a long way between them, a fast flow checks often, and no drift relies on
        the slack of the safety factor. False (a new estimate is due) when the
        certificate fails now."""
        sim = self.sim
        cert = self.certificate
        sim.counters[dem.DRIFT_SUM] = 0.0
        sim.counters[dem.DRIFT_OFFSET], sim.counters[dem.DRIFT_WALL_OFFSET] = \
            sim.lists.moved_since_build()
        if cert is None or sim.dt is None or not cert.bounded:
            self.check_budget = math.inf
            self.sync_mesh_cover(limit=math.inf)
            return True
        sigma = self.certified_sigma()
        if cert.has_bodies:  # the bodies' turn budgeted too (looked at after every step)
            self.check_q = sim.bodies.q.copy()
            self.check_budget, self.turn_budget = cert.body_budgets(
                sigma, sim.x, sim.periodic_len, (sim.wall_point, sim.wall_normal),
                self.body_pose(), self.BODY_MOVE_CAP * float(sim.r.min(initial=math.inf)),
                self.BODY_TURN_CAP)
            if self.check_budget > 0.0 or self.turn_budget > 0.0:
                return True  # (room left at the look-ahead's bound, above the drift now)
            return cert.certifies(sigma, self.drift(cert))
        mesh_drift = self.mesh_check()[0] if self.meshes_followed else None
        drift = self.drift(cert, mesh_drift)
        if not cert.certifies(sigma, drift):
            self.check_budget = 0.0
            return False
        cap = (self.DRIFT_BUDGET_CAP * float(sim.r.min(initial=math.inf))
               if cert.pair_bond.any() else math.inf)
        reserved = 0.0
        if self.meshes_followed:
            # the mesh contacts' drift is measured at every step (the kernels' k + sigma
            # c); a quarter of the room left is reserved for its growth, and the steps
            # stop for a check once it has used half of that
            m_k, m_c = mesh_drift
            room = sigma * sigma - cert.bound(sigma, drift)
            now = m_k + sigma * m_c
            reserved = now + self.MESH_DRIFT_SHARE * room
            self.sync_mesh_cover(limit=now + 0.5 * self.MESH_DRIFT_SHARE * room)
        self.check_budget = cert.drift_budget(
            sigma, sim.x, sim.periodic_len, (sim.wall_point, sim.wall_normal), cap,
            reserved=reserved)
        return True

    #: 'auto' with mesh walls: the share of the room a check leaves (sigma^2 minus the
    #: certificate's bound now) that the mesh contacts' drift may take before the next
    MESH_DRIFT_SHARE = 0.25

    def contacts_covered(self) -> bool:
        """Whether every contact closed now was part of the last 'auto' estimate, at no
        larger overlap than it assumed (False also when there was no estimate)."""
        masks = self.uncovered()
        return masks is not None and not any_uncovered(masks)

    def certify_added(self, pair_mask, wall_mask, mesh_need=None) -> bool:
        """Whether dt stays certified with the uncovered contacts added, without a new
        estimate (:mod:`demstep.timestep.certificate`): the added contacts count by the
        largest of their elements with each particle's whole mass, k + sigma c
        (Rayleigh's theorem on them alone, Weyl's inequality for the sum), on top of the
        last estimate's certificate and the drift of its normals. If dt stays certified
        the cover and the certificate are extended to them (True). Else False: a full
        estimate is due. Mesh contacts beyond the cover (``mesh_need``: per particle how
        many, at what overlap; None: none) enlarge the added group of mesh contacts
        (:meth:`mesh_added_bound`), by the same rule."""
        sim = self.sim
        cert = self.certificate
        if cert is None or sim.dt is None:
            return False
        sigma = self.certified_sigma()
        if mesh_need is not None:
            if self.mesh_added is None:
                return False
            if not sim.law.nonlinear:  # (a linear law's: covered at any overlap)
                mesh_need = mesh_need.copy()
                mesh_need[:, 1] = np.where(mesh_need[:, 0] > 0.0, np.inf, 0.0)
            mesh_added = np.maximum(self.mesh_added, mesh_need)
            m_k, m_c = self.mesh_added_bound(mesh_added)
            if sigma * sigma < cert.bound(sigma, self.drift(cert), added=(
                    cert.add_k + m_k - cert.mesh_add_k, cert.add_c + m_c - cert.mesh_add_c)):
                return False
            cert.mesh_add_k, cert.mesh_add_c = m_k, m_c
            self.mesh_added = mesh_added
            self.sync_mesh_cover()
            if not (pair_mask.any() or wall_mask.any()):
                self.n_extensions += 1
                return self.renew_drift_budget()
        added, overlaps = self.contacts_of(pair_mask, wall_mask)
        if added.n == 0:
            return True
        # the longest arms the contacts can have (they lengthen as a contact opens)
        added = replace(added, arm_i=sim.r[added.i].copy(),
                        arm_j=np.where(added.j >= 0, sim.r[np.maximum(added.j, 0)], 0.0))
        particles, bodies = sim.particles_now(check=False), sim.rigid_bodies()
        add_k, add_c = added_contacts_bound(particles, added, sim.rotation, bodies)
        # Weyl: this group on top of the groups added before
        add_k, add_c = cert.add_k + add_k, cert.add_c + add_c
        keys = {}
        for name, mask in (("pairs", pair_mask), ("walls", wall_mask)):
            if mask.any():
                keys[name] = (self.pair_keys(sim.pi[mask], sim.pj[mask]) if name == "pairs"
                              else self.wall_keys(sim.wp[mask], sim.ww[mask]))
        record = self.added
        if record is not None:  # or all the contacts added since the estimate as one group
            record = dict(record)
            for name, k in keys.items():
                record[name] = merge_cover(*record.get(name, NO_COVER), k, overlaps[name])
            union_k, union_c = added_contacts_bound(particles, self.added_contacts(record),
                                                    sim.rotation, bodies)
            add_k, add_c = min(add_k, union_k), min(add_c, union_c)
        drift = self.drift(cert)
        if sigma * sigma < cert.bound(sigma, drift, added=(add_k, add_c)):
            return False
        cert.set_added(add_k, add_c)
        self.added = record
        # certified at sigma for the enlarged set: extend the cover
        cover = self.cover
        for name, k in keys.items():
            cover[name] = merge_cover(*cover.get(name, NO_COVER), k, overlaps[name])
        self.n_extensions += 1
        return self.renew_drift_budget()

    def added_contacts(self, record: dict) -> ContactSet:
        """The contacts of a record of added ones ({'pairs': (keys, overlaps), 'walls':
        ...}, as the cover's) as a ContactSet for :func:`added_contacts_bound
        <demstep.timestep.certificate.added_contacts_bound>`: the coefficients of the
        overlaps recorded, the normals of the geometry now, the longest arms (the radii)."""
        sim = self.sim
        pairs, walls = record.get("pairs", NO_COVER), record.get("walls", NO_COVER)
        n, base = len(sim.r), self.walls_per_key
        keys = np.asarray(pairs[0], dtype=np.int64)
        wkeys = np.asarray(walls[0], dtype=np.int64)
        added = contact_elements(sim, keys // n, keys % n, np.asarray(pairs[1], dtype=float),
                                       wkeys // base, wkeys % base,
                                       np.asarray(walls[1], dtype=float))
        return replace(added, arm_i=sim.r[added.i].copy(),
                       arm_j=np.where(added.j >= 0, sim.r[np.maximum(added.j, 0)], 0.0))

    def contacts_of(self, pair_mask, wall_mask) -> tuple[ContactSet, dict]:
        """The pairs and wall contacts selected by the masks (closed or not) as a
        ContactSet at their current geometry, with the coefficients of the overlap they
        reach in LOOKAHEAD_STEPS steps at the velocities now (:meth:`_step_moves`; if
        they go on, the steps find them again and they are added again); and those
        overlaps [L], {'pairs': (P,), 'walls': (W,)}."""
        sim = self.sim
        overlaps = {}
        move, boundary = self.step_moves()
        move *= self.LOOKAHEAD_STEPS
        boundary *= self.LOOKAHEAD_STEPS
        i, j = sim.pi[pair_mask], sim.pj[pair_mask]
        p, wi = sim.wp[wall_mask], sim.ww[wall_mask]
        if len(i):
            delta = pair_geometry_arrays(sim.x, sim.r, i, j, sim.periodic_len)[2]
            overlaps["pairs"] = np.maximum(delta, 0.0) + move[i] + move[j] + boundary
        if len(p):
            delta = wall_geometry_arrays(sim.x, sim.r, p, wi, sim.wall_point,
                                         sim.wall_normal)[2]
            overlaps["walls"] = np.maximum(delta, 0.0) + move[p] + boundary
        return contact_elements(sim, i, j, overlaps.get("pairs"), p, wi,
                                      overlaps.get("walls")), overlaps
