"""A Simulation's state as the time-step analysis takes it.

:mod:`demstep.timestep` knows particles, contact sets and rigid bodies, never the
engine. These functions read a Simulation's bundles and hand them over in that form:
the contacts with their linearised coefficients (:func:`contact_set`), the particles
now, the clumps at their current orientation, the global damping; and the keys under
which the 'auto' step's records name pairs and wall contacts.
"""

from __future__ import annotations

import numpy as np

from demstep.clumps import quat_to_matrix
from demstep.contact.bonds import bond_springs
from demstep.contact.geometry import pair_geometry_arrays, wall_geometry_arrays
from demstep.contact.laws import contact_coefficients, params_from_row
from demstep.timestep.contacts import ContactSet, with_rolling
from demstep.engine.meshes import mesh_contacts
from demstep.kernels import dem
from demstep.kernels.integration import reach_speed as _reach_speed_kernel
from demstep.particles import Particles
from demstep.timestep.clumps import RigidBodies
from demstep.timestep.damping import GlobalDamping

#: an empty record of covered contacts: (keys, overlaps)
NO_COVER = (np.zeros(0, dtype=np.int64), np.zeros(0))


def pair_keys(n: int, i, j):
    """The keys of the pairs (i, j), i < j, of ``n`` particles in the 'auto' step's
    records of covered contacts: i n + j."""
    return i * n + j


def walls_per_key(sim) -> int:
    """The base of the particle-wall keys (:func:`wall_keys`): the number of walls."""
    return max(1, len(sim.walls))


def wall_keys(base: int, p, w):
    """The keys of the particle-wall contacts (p, w) in the records of covered
    contacts: p ``base`` + w (``base``: :func:`walls_per_key`)."""
    return p * base + w


def sorted_keys(keys, values):
    """``keys`` sorted (stable) with their ``values``."""
    order = np.argsort(keys, kind="stable")
    return keys[order], values[order]


def contact_set(sim, horizon: float | None = None, cover: dict | None = None) -> ContactSet:
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
    coefficients assumed (:meth:`demstep.engine.auto_step.AutoStep.contacts_covered`)."""
    params = sim.law.params()
    if horizon is not None:
        speed = reach_speed(sim, horizon)
    parts = []
    if len(sim.pi):
        d, dist, delta, arm_i, arm_j, _ = pair_geometry_arrays(sim.x, sim.r, sim.pi, sim.pj,
                                                               sim.periodic_len)
        on = delta > 0 if horizon is None else np.ones(len(delta), dtype=bool)
        i, j = sim.pi[on], sim.pj[on]
        if horizon is None:
            delta_eval = delta[on]
            ai, aj = arm_i[on], arm_j[on]
        else:  # apart: the radii (the arms it will close with, at most)
            r_star = sim.r[i] * sim.r[j] / (sim.r[i] + sim.r[j])
            delta_eval = reachable_overlap(sim, delta, horizon * (speed[i] + speed[j]), r_star)
            touching = delta > 0.0
            ai = np.where(touching, arm_i, sim.r[i])
            aj = np.where(touching, arm_j, sim.r[j])
        parts.append(_pairs_part(sim, i, j, d[on], dist[on], ai, aj, delta_eval, params))
        if cover is not None:
            cover["pairs"] = sorted_keys(pair_keys(len(sim.r), i, j), delta_eval)
    if len(sim.wp):
        _, dist, delta, _ = wall_geometry_arrays(sim.x, sim.r, sim.wp, sim.ww,
                                                 sim.wall_point, sim.wall_normal)
        if horizon is None:
            on = delta > 0
            delta_eval = delta[on]
        else:
            on = np.ones(len(delta), dtype=bool)
            delta_eval = reachable_overlap(
                sim, delta, horizon * (speed[sim.wp] + wall_speeds(sim, sim.ww)),
                sim.r[sim.wp])
        p, wi, dist = sim.wp[on], sim.ww[on], dist[on]
        arm = dist if horizon is None else np.where(delta[on] > 0.0, dist, sim.r[p])
        parts.append(_walls_part(sim, p, wi, arm, delta_eval, params))
        if cover is not None:
            cover["walls"] = sorted_keys(wall_keys(walls_per_key(sim), p, wi), delta_eval)
    mesh_parts = []
    if len(sim.meshes.cand_p):
        if horizon is None:
            mesh_parts.append(meshes_part(sim.meshes, sim.x, sim.r, sim.m, sim.dim,
                                          len(sim.walls), params, sim.inertia, sim.inv_m > 0))
        else:
            part, caps = meshes_within(sim, horizon, speed, params)
            mesh_parts.append(part)
            if cover is not None:
                cover["meshes"] = caps
    return with_rolling_and_bonds(sim, parts, params, mesh_parts)


def meshes_within(sim, horizon: float, speed, params) -> tuple[ContactSet, np.ndarray]:
    """The particle-mesh contacts that can close within ``horizon`` [T] (the particles'
    reach speeds ``speed`` [L/T]) as wall elements (:func:`meshes_part`): those of each
    sphere grown by its reach h (s + the meshes' largest speed) (twice, at most the
    skin; the engine's one-per-surface rule), the normals and distances of the
    geometry now (the arm: the distance when touching, the radius when apart), each
    mesh's law at the overlap it can reach (:func:`reachable_overlap`); and those
    overlaps [L] (C,), the overlap each covered contact is covered at."""
    meshes = sim.meshes
    reach = horizon * (speed + mesh_speed(meshes))
    grown = sim.r + np.minimum(2.0 * reach, sim.skin)
    p, mk, normal, dist, _ = mesh_contacts(meshes, sim.x, grown)
    delta = sim.r[p] - dist
    overlaps = reachable_overlap(sim, delta, reach[p], sim.r[p])
    arm = np.where(delta > 0.0, dist, sim.r[p])
    # (a linear law's contacts are covered at any overlap, as the pairs')
    caps = overlaps if sim.law.nonlinear else np.full(len(p), np.inf)
    return _mesh_elements(meshes, p, mk, normal, arm, overlaps, sim.r, sim.m, sim.dim,
                          len(sim.walls), params, sim.inertia, sim.inv_m > 0), caps


def mesh_speed(meshes) -> float:
    """The largest speed [L/T] of a point of a moving mesh: |v| + |omega| times the
    largest distance of its corners from its centre (0 without moving meshes)."""
    out = 0.0
    corners = meshes.tri.reshape(-1, 3, 3)
    for k in range(meshes.n):
        spin = float(np.linalg.norm(meshes.omega[k]))
        far = 0.0
        if spin > 0.0:
            own = corners[meshes.tri_mesh == k].reshape(-1, 3)
            far = float(np.linalg.norm(own - meshes.center[k], axis=1).max(initial=0.0))
        out = max(out, float(np.linalg.norm(meshes.vel[k])) + spin * far)
    return out


def contact_elements(sim, i, j, pair_overlaps, p, w, wall_overlaps) -> ContactSet:
    """The pairs (i, j) and the wall contacts (particle p, wall w) as a ContactSet at
    their geometry now (normals, arms), with the law's coefficients at the overlaps
    given [L] (and its rolling and twisting springs; no bonds)."""
    params = sim.law.params()
    parts = []
    if len(i):
        d, dist, _, ai, aj, _ = pair_geometry_arrays(sim.x, sim.r, i, j, sim.periodic_len)
        parts.append(_pairs_part(sim, i, j, d, dist, ai, aj, pair_overlaps, params))
    if len(p):
        _, _, _, arm = wall_geometry_arrays(sim.x, sim.r, p, w, sim.wall_point,
                                            sim.wall_normal)
        parts.append(_walls_part(sim, p, w, arm, wall_overlaps, params))
    return with_rolling(_joined(sim, parts), sim.r, sim.m, sim.inertia, sim.inv_m > 0, params)


def _pairs_part(sim, i, j, d, dist, arm_i, arm_j, overlaps, params) -> ContactSet:
    """Pairs (i, j) with branch vectors ``d`` and distances ``dist`` [L], the arms
    given, the law's coefficients at ``overlaps`` [L] (the pair's reduced mass: a fixed
    end's partner's whole mass)."""
    r_star = sim.r[i] * sim.r[j] / (sim.r[i] + sim.r[j])
    inv = sim.inv_m[i] + sim.inv_m[j]
    m_star = np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), sim.m[i])
    kn, kt, cn, ct = coefficients(params, overlaps, r_star, m_star)
    return ContactSet(i, j, (d / dist[:, None])[:, :sim.dim], arm_i, arm_j, kn, kt,
                      c_n=cn, c_t=ct)


def _walls_part(sim, p, w, arm, overlaps, params) -> ContactSet:
    """Particle-wall contacts (p, w) with the arms given, the law's coefficients at
    ``overlaps`` [L] (R* = r, m* = m)."""
    kn, kt, cn, ct = coefficients(params, overlaps, sim.r[p], sim.m[p])
    return ContactSet(p, np.full(len(p), -1), -sim.wall_normal[w][:, :sim.dim], arm,
                      np.zeros(len(p)), kn, kt, w, c_n=cn, c_t=ct)


def meshes_part(meshes, x, r, m, dim: int, first_wall: int, params, inertia=None,
                moving=None) -> ContactSet:
    """The particle-mesh contacts touching at positions ``x`` [L] (one per surface,
    :func:`demstep.engine.meshes.mesh_contacts`; radii ``r``, masses ``m``) as wall
    elements, mesh k numbered wall ``first_wall`` + k: the arm the distance from the
    centre to the closest point, R* = r, m* = m, and each mesh's own law parameters
    (its material; the rows ``meshes.law``, of the law of ``params``); with the
    particles' moments of ``inertia`` and which are ``moving`` (N,), a law's rolling
    and twisting springs (:func:`_mesh_elements`)."""
    p, mk, normal, dist, delta = mesh_contacts(meshes, x, r)
    return _mesh_elements(meshes, p, mk, normal, dist, delta, r, m, dim, first_wall, params,
                          inertia, moving)


def _mesh_elements(meshes, p, mk, normal, arm, overlaps, r, m, dim, first_wall,
                   params, inertia=None, moving=None) -> ContactSet:
    """Particle-mesh contacts (particle ``p``, mesh ``mk``, ``normal`` from the particle
    to the mesh, ``arm`` [L]) as wall elements numbered ``first_wall`` + mesh, with each
    mesh's law (the rows ``meshes.law`` of the law of ``params``) at ``overlaps`` [L],
    R* = r, m* = m; and, given ``inertia`` and ``moving`` (N,) and a law with rolling
    resistance, each contact's rolling and twisting springs by its mesh's law
    (:func:`demstep.timestep.contacts.with_rolling`: the kernels' mesh contacts carry
    them, the mesh the body that does not move)."""
    c = len(p)
    kn, kt, cn, ct = (np.empty(c) for _ in range(4))
    rolling = inertia is not None and params.has_rolling and c > 0
    roll = np.zeros((4, c)) if rolling else None
    wall_ids = first_wall + mk
    for k in np.unique(mk):
        on = mk == k
        pm = params_from_row(params, meshes.law[k])
        kn[on], kt[on], cn[on], ct[on] = coefficients(pm, overlaps[on], r[p[on]], m[p[on]])
        if rolling:
            part = with_rolling(ContactSet(p[on], np.full(int(on.sum()), -1),
                                           normal[on, :dim], arm[on], np.zeros(int(on.sum())),
                                           kn[on], kt[on], wall_ids[on]), r, m, inertia,
                                moving, pm)
            roll[:, on] = part.k_r, part.k_w, part.c_r, part.c_w
    extra = dict(zip(("k_r", "k_w", "c_r", "c_w"), roll)) if rolling else {}
    return ContactSet(p, np.full(c, -1), normal[:, :dim], arm, np.zeros(c), kn, kt,
                      wall_ids, c_n=cn, c_t=ct, **extra)


def _joined(sim, parts) -> ContactSet:
    if parts:
        return ContactSet.concatenate(parts)
    return ContactSet(np.zeros(0), np.zeros(0), np.zeros((0, sim.dim)), np.zeros(0),
                      np.zeros(0), 0.0, 0.0)


def wall_speeds(sim, walls) -> np.ndarray:
    """The speeds [L/T] of the ``walls`` (indices): servo walls at their speed limit."""
    speed = np.linalg.norm(sim.wall_vel[walls], axis=1)
    return np.maximum(speed, np.where(sim.wall_motion[walls] == dem.WALL_SERVO,
                                      np.minimum(sim.servo[walls, dem.S_MAXSPEED], 1e300),
                                      0.0))


def reachable_overlap(sim, delta, reach, r_star) -> np.ndarray:
    """The overlap [L] an 'auto' estimate covers contacts at (their coefficients;
    the cover the pair loops compare with): from the overlap ``delta`` now (negative
    apart), ``reach`` = h (s_i + s_j) [L] the distance the two ends cover within the
    horizon h (:func:`contact_set`), twice (a margin for speeding up), at most the
    skin; a non-linear law's at least the TimeStep's relative ``overlap`` x
    ``r_star``."""
    out = np.maximum(delta, 0.0) + np.minimum(2.0 * reach, sim.skin)
    if sim.law.nonlinear:
        out = np.maximum(out, sim.timestep.overlap * r_star)
    return out


def with_rolling_and_bonds(sim, parts, params, mesh_parts=()) -> ContactSet:
    """The contact parts as one ContactSet with the law's rolling and twisting
    springs (:func:`demstep.timestep.contacts.with_rolling`, the kernels' rule for fixed
    particles), then the ``mesh_parts`` (with their own rolling springs, by each mesh's
    law: :func:`_mesh_elements`), then the intact bonds as elements of their own."""
    contacts = with_rolling(_joined(sim, parts), sim.r, sim.m, sim.inertia, sim.inv_m > 0,
                            params)
    rest = list(mesh_parts) + bond_elements(sim)
    return ContactSet.concatenate([contacts] + rest) if rest else contacts


def bond_elements(sim) -> list:
    """The intact parallel bonds of ``sim`` as contact elements (a list of one
    ContactSet, or none): springs k_n^b A, k_s^b A at the bond point (arms to the middle
    of the gap), bending k_n^b I and twisting k_s^b J on the relative rotation
    (:func:`demstep.contact.bonds.bond_springs`)."""
    bonds = sim.bonds
    on = bonds.intact == 1
    if not on.any():
        return []
    i, j = bonds.i[on], bonds.j[on]
    d, dist, _, ai, aj, _ = pair_geometry_arrays(sim.x, sim.r, i, j, sim.periodic_len)
    kn, ks, kr, kw = bond_springs(bonds.radius[on], bonds.k_n[on], bonds.k_s[on], sim.dim)
    return [ContactSet(i, j, (d / dist[:, None])[:, :sim.dim], ai, aj, kn, ks,
                       k_r=kr, k_w=kw)]


def reach_speed(sim, horizon: float) -> np.ndarray:
    """Per particle, |v| + h |a| [L/T] (a from the last contact and applied forces and
    gravity; zero for fixed particles)."""
    out = np.empty(len(sim.r))
    _reach_speed_kernel(sim.v, sim.force, sim.applied_force, sim.inv_m,
                        np.ascontiguousarray(sim.gravity, dtype=np.float64), float(horizon),
                        out)
    return out


def coefficients(params, delta, r_star, m_star):
    """k_n, k_t [M/T^2], c_n, c_t [M/T] of contacts at overlaps ``delta`` (the law of
    the parameters ``params``)."""
    return contact_coefficients(params, np.ascontiguousarray(delta, float),
                                np.ascontiguousarray(r_star, float),
                                np.ascontiguousarray(m_star, float))


def particles_now(sim, check: bool = True) -> Particles:
    """Current particles (positions, current masses after any scaling); ``check``
    False: without validating them again (the 'auto' control's estimates)."""
    x = sim.x[:, :sim.dim].copy()
    if not check:
        return Particles.checked_already(x, sim.r, sim.m, sim.inertia, sim.fixed)
    return Particles(x, sim.r, sim.m, sim.inertia, sim.fixed)


def rigid_bodies(sim):
    """The clumps in the form the time-step analysis takes
    (:class:`demstep.timestep.clumps.RigidBodies`: members' arms and the bodies' world
    inertia tensors at the current orientation), or None without clumps."""
    b = sim.bodies
    if not b.n:
        return None

    R = quat_to_matrix(b.q)
    arm = np.zeros((len(sim.r), 3))
    arm[b.member] = np.einsum("mij,mj->mi", R[b.sphere_body[b.member]], b.offset)
    inertia = np.einsum("bij,bj,bkj->bik", R, b.inertia, R)
    return RigidBodies(b.sphere_body, arm, b.m.copy(), inertia, b.inv_m == 0)


def global_damping(sim) -> GlobalDamping:
    """The global mass-proportional viscous damping a1 [1/T] of the run."""
    return GlobalDamping(mass=float(sim.damping.viscous))
