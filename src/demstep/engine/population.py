"""Particles entering and leaving a running Simulation.

:func:`add_particles` appends particles (insertion), :func:`remove_particles` takes
some out (an outlet). Everything that holds one row per particle follows: the
Spheres, ``fixed``, ``particles``, the particles' names (``source_index``: an
inserted particle gets the next unused id, and a removed particle's id is never
given again), the clumps' sphere map; the pair, particle-wall and particle-mesh
lists keep the history of the contacts that remain (renamed), and insertion
rebuilds the lists so that the new particles' neighbours are listed before their
first step.

The energy ledger accounts for what crosses the boundary with the particles: an
inserted particle brings its kinetic energy (``A_INSERTED``), a removed one takes
out its kinetic energy at the time of the ledger's last evaluation and the energy
stored in its contacts there (normal springs at their overlap, tangential,
rolling and twisting springs: ``A_REMOVED``), so W_ext keeps balancing the state
terms (:mod:`demstep.energy`). The state terms change at once by the same amounts,
so the ledger balances between steps too (a history row written right after an
insertion). Gravity needs no term: its work on a particle is counted while the
particle is in the system.

The 'auto' time step (:meth:`demstep.engine.auto_step.AutoStep.inserted`,
:meth:`~demstep.engine.auto_step.AutoStep.removed`): its certificate is kept. After a
removal what remains is a principal submatrix of what it bounded (Cauchy's
interlacing); after an insertion the new particles are in none of its contacts (the
matrices it bounded gain rows and columns of zeros), and their contacts are added
before the next step as any contact the estimate did not cover: by the bound on the
added group (Weyl's inequality), or by a new estimate when that bound leaves the
step uncertified.

A mesh wall switched on or off between runs (:func:`switch_mesh`) changes what takes
part too: switched off, its contacts end and the energy they store leaves with them
(``A_REMOVED``); switched on, the lists are rebuilt at once (its contacts act from
the next step), the energy of the overlaps it starts with comes in (``A_INSERTED``),
and the 'auto' certificate is estimated anew.

Clumps and bonds are not supported with a changing population (refused in one
line by the feed, :mod:`demstep.engine.feed`).
"""

from __future__ import annotations

import numpy as np

from demstep.contact.geometry import pair_geometry_arrays, wall_geometry_arrays
from demstep.contact.laws import normal_force, params_from_row
from demstep.energy import (A_INSERTED, A_REMOVED, E_KIN_R, E_KIN_T, E_STRAIN_N, E_STRAIN_R,
                            E_STRAIN_T)
from demstep.engine.meshes import mesh_contacts
from demstep.errors import InputError
from demstep.kernels import dem
from demstep.particles import Particles
from demstep.state import CONTACT_HISTORY, Meshes, Spheres


def _refuse_structures(sim, what: str):
    if sim.bodies.n:
        raise InputError(f"{what}: not supported with clumps (rigid bodies)")
    if sim.bonds.n:
        raise InputError(f"{what}: not supported with bonds")


def add_particles(sim, x, r, m, inertia, v=None, w=None, next_id: int | None = None) -> np.ndarray:
    """Append particles at ``x`` (K, dim or 3) [L] with radii ``r`` [L], masses ``m``
    [M], moments of inertia ``inertia`` [M L^2], velocities ``v`` [L/T] and angular
    velocities ``w`` [1/T] at the current time (default 0); ids from ``next_id`` on
    (default: one past the largest id). Returns their indices. The caller checks that
    they do not overlap anything (:mod:`demstep.engine.feed`)."""
    _refuse_structures(sim, "insertion")
    k = len(r)
    n0 = len(sim.r)
    if k == 0:
        return np.zeros(0, dtype=np.int64)
    x3 = np.zeros((k, 3))
    x = np.asarray(x, dtype=np.float64)
    x3[:, :x.shape[1]] = x
    v3 = np.zeros((k, 3))
    if v is not None:
        v = np.asarray(v, dtype=np.float64)
        v3[:] = v if v.shape[-1] == 3 else np.pad(v, [(0, 0)] * (v.ndim - 1) + [(0, 1)])
    w3 = np.zeros((k, 3))
    if w is not None:
        w3[:] = w
    if sim.dim == 2:
        v3[:, 2] = 0.0
        w3[:, :2] = 0.0
    if not sim.rotation:
        w3[:] = 0.0
    r = np.asarray(r, dtype=np.float64)
    m = np.asarray(m, dtype=np.float64)
    inertia = np.asarray(inertia, dtype=np.float64)
    # the energy they bring: in the ledger's state terms now (the ledger balances at
    # once, between steps too) and in the record of what came in
    # The arrays hold the positions at t + dt of the ledger's time t: a particle given
    # x, v there is a particle that was at x - dt v_h at t, v_h = v - dt/2 g its
    # half-step velocity (gravity alone acting, as the first step's half backward kick
    # has it), moving at v - dt g. The next step counts gravity's work over
    # [t, t + dt] on it and its kinetic energy at t + dt (1/2 m v^2): with the kinetic
    # energy at t counted as inserted the ledger balances exactly.
    # (Before the first step the ledger has not started: the first step counts what
    # is there then, these particles too, as the initial energy.)
    if not sim.first_step_pending:
        v_then = v3 - sim.dt_prev * sim.gravity
        kin_t = float(0.5 * np.sum(m * np.einsum("ij,ij->i", v_then, v_then)))
        kin_r = float(0.5 * np.sum(inertia * np.einsum("ij,ij->i", w3, w3)))
        sim.ledger.energy[E_KIN_T] += kin_t
        sim.ledger.energy[E_KIN_R] += kin_r
        sim.ledger.acc[A_INSERTED] += kin_t + kin_r
        v3 = v3 - 0.5 * sim.dt_prev * sim.gravity
    ids = sim.particle_ids()
    start = int(ids.max(initial=-1)) + 1 if next_id is None else int(next_id)
    new_ids = np.arange(start, start + k, dtype=np.int64)
    sp = sim.spheres
    grown = {"x": x3, "v": v3, "w": w3, "r": r, "m": m, "inertia": inertia,
             "x_ref": x3.copy()}
    sim.spheres = Spheres(**{
        f: np.ascontiguousarray(np.concatenate([getattr(sp, f), grown[f] if f in grown else
                                                np.zeros((k,) + getattr(sp, f).shape[1:])]))
        for f in Spheres._fields})
    sim.fixed = np.concatenate([sim.fixed, np.zeros(k, dtype=bool)])
    _sync_particles(sim)
    sim.source_index = np.concatenate([ids, new_ids])
    sim.bodies = sim.bodies._replace(sphere_body=np.full(n0 + k, -1, dtype=np.int64))
    sim.update_masses()
    _inserted(sim, n0)
    return np.arange(n0, n0 + k)


def remove_particles(sim, remove) -> tuple[int, float]:
    """Take the particles where ``remove`` (N,) is true out of ``sim``: their contacts
    go with them, the energy they take out into the ledger (module docstring).
    Returns (count, mass [M]) removed."""
    remove = np.asarray(remove, dtype=bool)
    if not remove.any():
        return 0, 0.0
    _refuse_structures(sim, "outlet")
    taken = energy_taken_out(sim, remove)
    for term, value in taken.items():  # (out of the state terms now, and on record)
        sim.ledger.energy[term] -= value
    sim.ledger.acc[A_REMOVED] += sum(taken.values())
    count, mass = int(remove.sum()), float(sim.m[remove].sum())
    keep = np.flatnonzero(~remove)
    inv = np.full(len(remove), -1, dtype=np.int64)
    inv[keep] = np.arange(len(keep))
    ids = sim.particle_ids()
    sp = sim.spheres
    sim.spheres = Spheres(**{f: np.ascontiguousarray(getattr(sp, f)[keep]) for f in Spheres._fields})
    sim.fixed = sim.fixed[keep]
    _sync_particles(sim)
    sim.source_index = ids[keep]
    sim.bodies = sim.bodies._replace(sphere_body=sim.bodies.sphere_body[keep])
    # the lists of what remains, in their order (renaming keeps i < j and the sorting)
    pairs = sim.pairs
    rows = (inv[pairs.i] >= 0) & (inv[pairs.j] >= 0)
    sim.pairs = pairs._replace(i=inv[pairs.i[rows]], j=inv[pairs.j[rows]], **{
        f: getattr(pairs, f)[rows] if len(getattr(pairs, f)) else getattr(pairs, f)
        for f in CONTACT_HISTORY})
    ws = sim.wall_state
    rows = inv[ws.p] >= 0
    sim.wall_state = ws._replace(p=inv[ws.p[rows]], wall=ws.wall[rows], **{
        f: getattr(ws, f)[rows] if len(getattr(ws, f)) else getattr(ws, f)
        for f in CONTACT_HISTORY})
    me = sim.meshes
    if len(me.cand_p):
        rows = inv[me.cand_p] >= 0
        sim.meshes = me._replace(cand_p=inv[me.cand_p[rows]], **{
            f: getattr(me, f)[rows] for f in ("cand_t", "cand_d") + Meshes.SLOTS})
    sim.pairs_changed()
    sim.auto.removed(keep, inv)  # (what is left keeps its certificate)
    return count, mass


def _sync_particles(sim):
    """``sim.particles`` from the Spheres and ``fixed`` (the particles now)."""
    sp = sim.spheres
    sim.particles = Particles.checked_already(sp.x[:, :sim.dim].copy(), sp.r, sp.m, sp.inertia,
                                              sim.fixed)


def _inserted(sim, n_old: int):
    """After particles were appended to the ``n_old`` there were: the pair loop's work
    space, the 'auto' certificate kept for the new set (its records re-keyed:
    :meth:`~demstep.engine.auto_step.AutoStep.inserted`), the lists rebuilt (they
    may renumber the particles: the certificate follows), then the new particles'
    contacts added to the certificate or a new estimate, before the next step."""
    sim.pairs_changed()
    kept = sim.auto.inserted(n_old)
    if sim.lists.built:
        sim.lists.rebuild()
    sim.auto.after_insertion(kept)


def energy_taken_out(sim, remove) -> dict:
    """The energy [M L^2/T^2] the particles ``remove`` hold at the time of the ledger's
    last evaluation t (the step's positions are at t + dt), by the ledger's state term
    it counts in: kinetic energy (translation, rotation) from the velocity at t (the
    half-step velocity less half a step of the last forces), and the energy stored
    in their contacts at the positions at t (normal springs at their overlap by the
    law; tangential, rolling and twisting springs from their history), pairs, walls
    and meshes."""
    sp = sim.spheres
    idx = np.flatnonzero(remove)
    h = 0.5 * sim.dt_prev
    moving = ~sim.fixed[idx]
    inv_m = np.where(moving, 1.0 / sp.m[idx], 0.0)[:, None]
    force = sp.force[idx] + sp.applied[idx] + sp.damp_force[idx, :3] + sp.damp_force[idx, 3:]
    v = sp.v[idx] - h * (force * inv_m + sim.gravity * moving[:, None])
    inv_i = np.where(moving & sim.rotation, 1.0 / sp.inertia[idx], 0.0)[:, None]
    torque = sp.torque[idx] + sp.damp_torque[idx, :3] + sp.damp_torque[idx, 3:]
    w = sp.w[idx] - h * torque * inv_i
    out = {E_KIN_T: 0.5 * float(np.sum(sp.m[idx] * np.einsum("ij,ij->i", v, v) * moving)),
           E_KIN_R: 0.5 * float(np.sum(sp.inertia[idx] * np.einsum("ij,ij->i", w, w)
                                       * (inv_i[:, 0] > 0))),
           E_STRAIN_N: 0.0, E_STRAIN_T: 0.0, E_STRAIN_R: 0.0}
    x_then = sp.x - sim.dt_prev * sp.v  # (x(t + dt) = x(t) + dt v(t + dt/2))
    params = sim.law.params()
    pairs = sim.pairs
    rows = np.flatnonzero(remove[pairs.i] | remove[pairs.j])
    if len(rows):
        i, j = pairs.i[rows], pairs.j[rows]
        delta = pair_geometry_arrays(x_then, sp.r, i, j, sim.periodic_len)[2]
        r_star = sp.r[i] * sp.r[j] / (sp.r[i] + sp.r[j])
        out[E_STRAIN_N] += _normal_energy(params, delta, r_star)
        out[E_STRAIN_T] += float(pairs.shear_energy[rows].sum())
        if len(pairs.roll):
            out[E_STRAIN_R] += float(pairs.roll[rows, dem.ROLL_ENERGY].sum())
    ws = sim.wall_state
    rows = np.flatnonzero(remove[ws.p])
    if len(rows):
        p, wall = ws.p[rows], ws.wall[rows]
        point_then = ws.point - sim.dt_prev * ws.vel
        delta = wall_geometry_arrays(x_then, sp.r, p, wall, point_then, ws.normal)[2]
        out[E_STRAIN_N] += _normal_energy(params, delta, sp.r[p])
        out[E_STRAIN_T] += float(ws.shear_energy[rows].sum())
        if len(ws.roll):
            out[E_STRAIN_R] += float(ws.roll[rows, dem.ROLL_ENERGY].sum())
    e_n, e_t, e_r = _mesh_contact_energy(sim, x_then, remove, None)
    out[E_STRAIN_N] += e_n
    out[E_STRAIN_T] += e_t
    out[E_STRAIN_R] += e_r
    return out


def _mesh_contact_energy(sim, x_then, of_particles, of_mesh) -> tuple[float, float, float]:
    """The energy [M L^2/T^2] stored in the mesh contacts of the particles where
    ``of_particles`` (N,) is true (None: all) with mesh ``of_mesh`` (None: every mesh),
    the particles at ``x_then``: (normal springs at their overlap by each mesh's law,
    tangential springs, rolling and twisting springs from their history)."""
    me = sim.meshes
    if not len(me.cand_p):
        return 0.0, 0.0, 0.0
    rows = np.ones(len(me.cand_p), dtype=bool)
    if of_particles is not None:
        rows &= of_particles[me.cand_p]
    if not rows.any():
        return 0.0, 0.0, 0.0
    params = sim.law.params()
    e_n = 0.0
    p, mesh, _, _, delta = mesh_contacts(me, x_then, sim.r)
    on = np.ones(len(p), dtype=bool) if of_particles is None else of_particles[p]
    if of_mesh is not None:
        on &= mesh == of_mesh
    for q, d, k in zip(p[on], delta[on], mesh[on]):
        e_n += _normal_energy(params_from_row(params, me.law[k]), np.array([d]), sim.r[[q]])
    rows &= me.active != 0
    if of_mesh is not None:
        rows &= me.slot_mesh == of_mesh
    e_r = float(me.roll[rows, dem.ROLL_ENERGY].sum()) if len(me.roll) else 0.0
    return e_n, float(me.etan[rows].sum()), e_r


def switch_mesh(sim, index: int, enabled: bool) -> None:
    """Switch mesh ``index`` of ``sim`` on (its contacts act from the next step: the
    lists are rebuilt now; the energy of the overlaps it starts with is brought into
    the run, ``A_INSERTED``) or off (its contacts end: their stored energy, at the
    ledger's last evaluation, leaves the ledger's state terms into ``A_REMOVED``, and
    their history is dropped). The 'auto' certificate is estimated anew either way
    (on: it did not cover the mesh; off: the contacts' rows changed)."""
    wall = sim.mesh_walls[index]
    enabled = bool(enabled)
    if wall.enabled == enabled:
        return
    wall.enabled = enabled
    if not sim.lists.built:  # (before the first step: the first build sees the flag)
        return
    if not enabled:
        x_then = sim.spheres.x - sim.dt_prev * sim.spheres.v
        e_n, e_t, e_r = _mesh_contact_energy(sim, x_then, None, index)
        sim.ledger.energy[E_STRAIN_N] -= e_n
        sim.ledger.energy[E_STRAIN_T] -= e_t
        sim.ledger.energy[E_STRAIN_R] -= e_r
        sim.ledger.acc[A_REMOVED] += e_n + e_t + e_r
        me = sim.meshes
        gone = (me.active != 0) & (me.slot_mesh == index)
        for f in Meshes.SLOTS:
            getattr(me, f)[gone] = 0
    sim.auto.forget()
    sim.lists.rebuild()
    if enabled:  # (the overlaps it starts with hold energy brought into the run)
        x_then = sim.spheres.x - sim.dt_prev * sim.spheres.v
        e_n, _, _ = _mesh_contact_energy(sim, x_then, None, index)
        sim.ledger.energy[E_STRAIN_N] += e_n
        sim.ledger.acc[A_INSERTED] += e_n
    sim.auto.resized()


def _normal_energy(params, delta, r_star) -> float:
    """The normal springs' stored energy [M L^2/T^2] at overlaps ``delta`` (those > 0)."""
    total = 0.0
    for d, rs in zip(delta, r_star):
        if d > 0.0:
            total += float(normal_force(params, float(d), float(rs))[2])
    return total


def adopt_particle_set(sim, data: dict, source: str):
    """Before a checkpoint of a run with insertion or outlets is restored: give ``sim``
    (built from the case, with the case's initial particles) the checkpoint's
    particle set (its radii, masses, fixed flags and ids), so that the restore's
    checks compare like with like. Arrays missing or not finite and positive are
    refused naming ``source`` and the array."""
    try:
        r = np.asarray(data["r"], dtype=np.float64).reshape(-1)
        fixed = np.asarray(data["fixed"], dtype=bool).reshape(-1)
        m = np.asarray(data["spheres.m"], dtype=np.float64).reshape(-1)
        inertia = np.asarray(data["spheres.inertia"], dtype=np.float64).reshape(-1)
        x = np.asarray(data["spheres.x"], dtype=np.float64)
    except KeyError as exc:
        raise InputError(f"{source}: a damaged checkpoint (array {exc.args[0]!r} missing)") from None
    n = len(r)
    for key, arr, shape in (("fixed", fixed, (n,)), ("spheres.m", m, (n,)),
                            ("spheres.inertia", inertia, (n,)), ("spheres.x", x, (n, 3))):
        if arr.shape != shape:
            raise InputError(f"{source}: array {key!r} has shape {arr.shape}, expected {shape}")
    for key, arr in (("r", r), ("spheres.m", m), ("spheres.inertia", inertia)):
        bad = ~(np.isfinite(arr) & (arr > 0))
        if bad.any():
            raise InputError(f"{source}: array {key!r} holds {arr[bad][0]!r} (row "
                             f"{int(np.flatnonzero(bad)[0])}): must be finite and > 0")
    ids = data.get("source_index")
    ids = np.arange(n, dtype=np.int64) if ids is None else np.asarray(ids, dtype=np.int64)
    if ids.shape != (n,) or len(np.unique(ids)) != n:
        raise InputError(f"{source}: array 'source_index' does not name {n} distinct particles")
    sim.spheres = Spheres.make(x.copy(), np.zeros((n, 3)), np.zeros((n, 3)), r.copy(), m.copy(),
                               inertia.copy())
    sim.fixed = fixed.copy()
    _sync_particles(sim)
    sim.source_index = ids
    sim.bodies = sim.bodies._replace(sphere_body=np.full(n, -1, dtype=np.int64))
    sim.pairs = sim.pairs._replace(i=np.zeros(0, dtype=np.int64), j=np.zeros(0, dtype=np.int64))
    sim.update_masses()
    sim.pairs_changed()
