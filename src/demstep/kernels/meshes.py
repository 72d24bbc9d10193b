"""Triangle-mesh walls: the contacts of spheres with the triangles of meshes.

A sphere touches a mesh where the closest point of one of its triangles lies within its
radius (:func:`demstep.contact.triangles.triangle_contact`). On a tessellated surface a
sphere finds several triangles at once; the rule that makes it one contact:

* an edge or vertex contact is dropped when another contact of the same sphere with a
  triangle of the same mesh that holds the same edge or vertex lies closer to the
  centre (the closest point of that triangle is nearer; on a flat or convex surface the
  face contact of the triangle the centre lies over), or as close and on a lower-numbered
  triangle (a centre right over a shared edge or vertex: one contact, the edge's or
  vertex's owner decided once by the triangle numbers);
* a genuine corner (a concave groove: two faces each nearest on their own) keeps a
  contact per face, and a convex edge or vertex a centre lies beyond keeps one contact.

The contacts of a sphere with a mesh live in the rows of the candidate list that
belong to that sphere (the list is sorted by particle, and a sphere cannot have more
contacts than candidate triangles): each row is a *slot* with the contact's normal and
history (tangential spring and dashpot forces, stored tangential energy). At every
step the new contacts of a sphere are matched to its slots on the same mesh by their
normals (the closest normal, within :data:`MATCH_COS`): the tangential history is
carried from triangle to triangle as the sphere rolls or slides across the edges of a
tessellated surface (rotated into the new tangent plane, as a pair's), and a slot no
contact takes has ended (its stored energy is dissipated, as a pair's that opens).

Moving meshes: every triangle of a mesh moves rigidly with it; the mesh's velocity at a
point q is v + omega x (q - c), c its rotation centre (carried with v). The force and
torque (about c) the particles exert on each mesh are summed, and the power the mesh
puts into the particles, whose trapezoid over each step is the mesh's work in the
energy ledger.

Wear (Finnie's erosion law, in the form LIGGGHTS' ``mesh/surface/stress ... wear
finnie`` integrates): a mesh with a coefficient k > 0 accumulates on each triangle, at
every step and for every contact on it whose particle approaches the surface or moves
along it (v_rel . n >= 0, n the contact normal towards the mesh, v_rel the particle
centre's velocity less the mesh's at the contact point),
2 k |F| |v_rel| f(gamma) dt / A, with |F| the contact force, A the triangle's area and
gamma the angle between v_rel and the triangle's plane: f = sin(2 gamma) -
3 sin^2(gamma) while tan(gamma) <= 1/3, cos^2(gamma) / 3 beyond (:func:`finnie_rate`).
"""

from __future__ import annotations

import math

import numpy as np

from demstep._numba import compile_parallel_and_serial, njit, prange
from demstep.contact.laws import params_from_row
from demstep.contact.laws.base import ROLL_NONE
from demstep.kernels.rolling import rolling_contact
from demstep.contact.triangles import FACE, closest_point_on_triangle, triangle_contact
from demstep.kernels.response import contact_response
from demstep.kernels.turn_factor import turn_factor

#: two contacts of a sphere with a mesh at consecutive steps are the same contact when
#: their normals are within this angle (cosine: 45 degrees): a sphere rolling over a
#: convex edge turns its normal continuously; two faces of a groove stay apart
MATCH_COS = math.cos(math.pi / 4)
#: contacts of a sphere with a mesh whose distances to the centre differ by less than
#: this fraction of its radius are as close (a centre over a shared edge or vertex)
SAME_DISTANCE = 1e-9
#: the most candidate triangles one sphere may have (more: the mesh is far finer than
#: the particles; refused when the lists are built)
MAX_CANDIDATES = 256


@njit(inline="always")
def _holds(vid, t, va, vb):
    """Whether triangle t has vertex va (and vb, when vb >= 0)."""
    ha = vid[t, 0] == va or vid[t, 1] == va or vid[t, 2] == va
    if vb < 0:
        return ha
    hb = vid[t, 0] == vb or vid[t, 1] == vb or vid[t, 2] == vb
    return ha and hb


@njit(inline="always")
def _feature_vertices(vid, t, feature):
    """The vertices (va, vb) of feature ``feature`` of triangle t (vb = -1 for a vertex,
    both -1 for the face)."""
    if feature == 1:
        return vid[t, 0], vid[t, 1]
    if feature == 2:
        return vid[t, 1], vid[t, 2]
    if feature == 3:
        return vid[t, 2], vid[t, 0]
    if feature >= 4:
        return vid[t, feature - 4], -1
    return -1, -1


@njit(inline="always")
def _sphere_rows_end(cand_p, s):
    """The end of the candidate rows of the sphere of row ``s`` (rows sorted by particle)."""
    p = cand_p[s]
    e = s
    while e < cand_p.shape[0] and cand_p[e] == p:
        e += 1
    return e


@njit(inline="always")
def _sphere_contacts(x, r, p, s, n, cand_t, tri, vid, tri_mesh, g, feat, keep, cand_d,
                     beyond, moved):
    """The contacts of sphere ``p`` with its ``n`` candidate triangles (rows s ... s + n
    - 1 of ``cand_t``): per row k, ``g[k]`` = (delta, unit normal from the triangle to
    the centre (3), distance to the closest point, the closest point (3)), the feature
    touched ``feat[k]`` and ``keep[k]``: whether the row is one of the sphere's contacts
    after the one-contact-per-surface rule (module docstring). A row whose distance at
    the lists' build ``cand_d`` exceeds ``beyond`` [L] is not computed: the sphere and
    the mesh have moved ``moved`` [L] at most since, so it is farther than ``beyond`` -
    ``moved`` now; its delta is given as the bound r - that (the rest of its ``g`` is
    not read: it is kept by no rule)."""
    px, py, pz, rp = x[p, 0], x[p, 1], x[p, 2], r[p]
    for k in range(n):
        if cand_d[s + k] > beyond:
            g[k, 0] = rp - (cand_d[s + k] - moved)
            feat[k] = FACE
            continue
        t = cand_t[s + k]
        (delta, nx, ny, nz, dist, qx, qy, qz, feature) = triangle_contact(
            px, py, pz, rp, tri[t, 0], tri[t, 1], tri[t, 2], tri[t, 3], tri[t, 4],
            tri[t, 5], tri[t, 6], tri[t, 7], tri[t, 8])
        g[k, 0], g[k, 1], g[k, 2], g[k, 3], g[k, 4] = delta, nx, ny, nz, dist
        g[k, 5], g[k, 6], g[k, 7] = qx, qy, qz
        feat[k] = feature
    _one_per_surface(s, n, cand_t, vid, tri_mesh, g, feat, keep, rp, 0.0)


@njit(inline="always")
def _one_per_surface(s, n, cand_t, vid, tri_mesh, g, feat, keep, rp, reach):
    """``keep[k]``: whether candidate row k of a sphere of radius ``rp`` (its geometry
    ``g``, ``feat`` from :func:`_sphere_contacts`) is one of its contacts after the
    one-contact-per-surface rule, for the sphere grown by ``reach`` [L] (0: the
    contacts now; the rule looks at the distances only, which growing leaves alone)."""
    for k in range(n):
        keep[k] = g[k, 0] + reach > 0.0
    # an edge or vertex contact that a closer contact of a triangle holding the same
    # edge or vertex covers is dropped
    tol = SAME_DISTANCE * rp
    for k in range(n):
        if not keep[k] or feat[k] == FACE:
            continue
        tk = cand_t[s + k]
        va, vb = _feature_vertices(vid, tk, feat[k])
        for j in range(n):
            if j == k or not keep[j]:
                continue
            tj = cand_t[s + j]
            if tri_mesh[tj] != tri_mesh[tk] or not _holds(vid, tj, va, vb):
                continue
            if g[j, 4] < g[k, 4] - tol or (g[j, 4] <= g[k, 4] + tol and (
                    feat[j] == FACE or tj < tk)):
                keep[k] = False
                break


#: the columns of ``Meshes.cover_ref`` (:class:`demstep.state.Meshes`): the reference
#: normal (3), arm, springs k_n, k_t, dashpots c_n, c_t, the overlap covered, the
#: particle's inverse mass and inverse moment of inertia
REF_ARM, REF_KN, REF_KT, REF_CN, REF_CT, REF_CAP, REF_INV_M, REF_INV_I = 3, 4, 5, 6, 7, 8, 9, 10


@njit(inline="always")
def _matched_drift(g, k, ref, row, w_k, w_c):
    """The drift bound of a touching contact (row k of ``g``) against the covered
    contact ``ref[row]`` it stands for: the turn |n - n_ref| times the turn factor at the
    arm now, plus the arm term (:mod:`demstep.timestep.certificate`, a wall element: one
    particle), of the coefficients ``w_k`` x the springs + ``w_c`` x the dashpots (1, 0:
    the springs' [1/T^2]; 0, 1: the dashpots' [1/T]; 1, sigma: both at the root sigma;
    the bound is linear in them)."""
    t0 = -g[k, 1] - ref[row, 0]
    t1 = -g[k, 2] - ref[row, 1]
    t2 = -g[k, 3] - ref[row, 2]
    turn = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    a, a_ref = g[k, 4], ref[row, REF_ARM]
    inv_m, inv_i = ref[row, REF_INV_M], ref[row, REF_INV_I]
    arm_term = abs(a - a_ref) * math.sqrt(inv_i) * (math.sqrt(inv_m + a * a * inv_i)
                                                    + math.sqrt(inv_m + a_ref * a_ref * inv_i))
    b_n = w_k * ref[row, REF_KN] + w_c * ref[row, REF_CN]
    b_t = w_k * ref[row, REF_KT] + w_c * ref[row, REF_CT]
    out = arm_term * b_t
    if turn > 0.0:
        out += turn * turn_factor(inv_m, a * a * inv_i, b_n, b_t, False)
    return out


@njit(inline="always")
def _sphere_cover(p, s, n, cand_t, vid, tri_mesh, g, feat, keep, near, rp, reach,
                  cover_start, cover_mesh, cover_ref, cover_extra, sigma, split, taken, out):
    """The 'auto' step's cover of sphere ``p``'s mesh contacts (its ``n`` candidate rows
    from row ``s``, their geometry ``g``, ``feat``; ``keep`` its contacts now): each
    contact now, then each the sphere grown by ``reach`` [L] finds (those closing within
    the look-ahead), is matched to a covered contact of the same mesh (the closest
    reference normal, not taken yet) whose overlap covered is at least its overlap +
    ``reach``; the others count on the certificate's added group (``cover_extra[p]``:
    how many, at what overlap). ``out`` receives the drift of the matched contacts now
    (:func:`_matched_drift` at the root ``sigma`` [1/T^2]), how many found no covered
    contact and the largest overlap + reach among those [L], and with ``split`` the
    drift of the springs [1/T^2] and of the dashpots [1/T] apart. Returns whether the
    added group is too small for them (the contacts are not covered)."""
    _one_per_surface(s, n, cand_t, vid, tri_mesh, g, feat, near, rp, reach)
    q0 = cover_start[p]
    nq = min(cover_start[p + 1] - q0, taken.shape[0])
    for q in range(nq):
        taken[q] = False
    drift = 0.0
    drift_k = 0.0
    drift_c = 0.0
    extra = 0
    extra_cap = 0.0
    for phase in range(2):  # touching first (their drift counts), then those near
        for k in range(n):
            if (phase == 0 and not keep[k]) or (phase == 1 and (keep[k] or not near[k])):
                continue
            mk = tri_mesh[cand_t[s + k]]
            best = -1
            best_cos = -2.0
            for q in range(nq):
                row = q0 + q
                if taken[q] or cover_mesh[row] != mk:
                    continue
                cos = -(g[k, 1] * cover_ref[row, 0] + g[k, 2] * cover_ref[row, 1]
                        + g[k, 3] * cover_ref[row, 2])
                if cos > best_cos:
                    best_cos = cos
                    best = q
            need = max(g[k, 0], 0.0) + reach
            if best >= 0 and need <= cover_ref[q0 + best, REF_CAP]:
                taken[best] = True
                if phase == 0:
                    drift += _matched_drift(g, k, cover_ref, q0 + best, 1.0, sigma)
                    if split:
                        drift_k += _matched_drift(g, k, cover_ref, q0 + best, 1.0, 0.0)
                        drift_c += _matched_drift(g, k, cover_ref, q0 + best, 0.0, 1.0)
            else:
                extra += 1
                extra_cap = max(extra_cap, need)
    out[0] = drift
    out[1] = extra
    out[2] = extra_cap
    out[3] = drift_k
    out[4] = drift_c
    return extra > cover_extra[p, 0] or (extra > 0 and extra_cap > cover_extra[p, 1])


@njit
def mesh_cover_check(x, v, r, meshes, steps, boundary, dt, need):
    """The 'auto' step's cover of every sphere's mesh contacts at the positions ``x``
    (:func:`_sphere_cover`), looking ``steps`` steps of ``dt`` [T] ahead at the
    velocities ``v`` plus the boundaries' move ``boundary`` [L]: the largest drift of a
    sphere's contacts, of the springs [1/T^2] and of the dashpots [1/T] (each a bound
    at any root, :func:`_matched_drift`), and how many spheres need more of the added
    group than it holds; ``need`` (N, 2) receives per sphere how many of its contacts
    need it and at what overlap [L] (zeros: none)."""
    cand_p, cand_t = meshes.cand_p, meshes.cand_t
    n_cand = cand_p.shape[0]
    g = np.empty((MAX_CANDIDATES, 9))
    feat = np.empty(MAX_CANDIDATES, dtype=np.int64)
    keep = np.empty(MAX_CANDIDATES, dtype=np.bool_)
    near = np.empty(MAX_CANDIDATES, dtype=np.bool_)
    taken = np.empty(MAX_CANDIDATES, dtype=np.bool_)
    out = np.empty(5)
    need[:] = 0.0
    drift_k = 0.0
    drift_c = 0.0
    short = 0
    sigma = meshes.cover_ctl[0]
    s = 0
    while s < n_cand:
        p = cand_p[s]
        e = _sphere_rows_end(cand_p, s)
        _sphere_contacts(x, r, p, s, e - s, cand_t, meshes.tri, meshes.vid, meshes.tri_mesh,
                         g, feat, keep, meshes.cand_d, np.inf, 0.0)  # (every row computed)
        speed = math.sqrt(v[p, 0] ** 2 + v[p, 1] ** 2 + v[p, 2] ** 2)
        reach = steps * speed * dt + boundary
        if _sphere_cover(p, s, e - s, cand_t, meshes.vid, meshes.tri_mesh, g, feat, keep, near,
                         r[p], reach, meshes.cover_start, meshes.cover_mesh, meshes.cover_ref,
                         meshes.cover_extra, sigma, True, taken, out):
            short += 1
        drift_k = max(drift_k, out[3])
        drift_c = max(drift_c, out[4])
        need[p, 0] = out[1]
        need[p, 1] = out[2]
        s = e
    return drift_k, drift_c, short


@njit
def mesh_contact_geometry(x, r, cand_p, cand_t, cand_d, tri, vid, tri_mesh):
    """The contacts of the spheres with the meshes now, by the engine's rule (one per
    surface; no history): for each, its candidate row (C,), overlap delta [L], unit
    normal from the sphere to the mesh (C, 3) and distance from the centre to the
    closest point [L]. ``cand_p``, ``cand_t``: candidate rows sorted by particle (every
    row computed: ``cand_d``, their distances at the build, only sized like them)."""
    n_cand = cand_p.shape[0]
    rows = np.empty(n_cand, dtype=np.int64)
    delta = np.empty(n_cand)
    normal = np.empty((n_cand, 3))
    dist = np.empty(n_cand)
    g = np.empty((MAX_CANDIDATES, 9))
    feat = np.empty(MAX_CANDIDATES, dtype=np.int64)
    keep = np.empty(MAX_CANDIDATES, dtype=np.bool_)
    c = 0
    s = 0
    while s < n_cand:
        p = cand_p[s]
        e = _sphere_rows_end(cand_p, s)
        _sphere_contacts(x, r, p, s, e - s, cand_t, tri, vid, tri_mesh, g, feat, keep,
                         cand_d, np.inf, 0.0)  # (every row computed)
        for k in range(e - s):
            if keep[k]:
                rows[c] = s + k
                delta[c] = g[k, 0]
                normal[c, 0] = -g[k, 1]
                normal[c, 1] = -g[k, 2]
                normal[c, 2] = -g[k, 3]
                dist[c] = g[k, 4]
                c += 1
        s = e
    return rows[:c], delta[:c], normal[:c], dist[:c]


@njit(inline="always")
def finnie_shape(sin_g, cos_g):
    """Finnie's angle function f(gamma) of the impact angle gamma between the
    particle's velocity and the surface (its sine and cosine): sin(2 gamma) -
    3 sin^2(gamma) up to tan(gamma) = 1/3 (ductile cutting, largest near 16.8 degrees),
    cos^2(gamma) / 3 beyond (0 at normal impact)."""
    if cos_g <= 1e-12 or 3.0 * sin_g > cos_g:
        return cos_g * cos_g / 3.0
    return 2.0 * sin_g * cos_g - 3.0 * sin_g * sin_g


@njit(inline="always")
def finnie_rate(tri, t, vx, vy, vz, nx, ny, nz, f_mag, k):
    """The rate [L/T with k in 1/pressure] at which a contact wears triangle ``t`` of
    ``tri`` (T, 9): 2 k |F| |v_rel| f(gamma) / A (module docstring), ``v`` the
    particle's velocity relative to the mesh at the contact point [L/T], ``n`` the
    contact normal towards the mesh, ``f_mag`` |F| [M L/T^2], ``k`` Finnie's coefficient
    [L T^2/M]; 0 when the particle moves away from the surface."""
    if vx * nx + vy * ny + vz * nz < 0.0:
        return 0.0
    speed = math.sqrt(vx * vx + vy * vy + vz * vz)
    if speed <= 1e-300:
        return 0.0
    ax, ay, az = tri[t, 3] - tri[t, 0], tri[t, 4] - tri[t, 1], tri[t, 5] - tri[t, 2]
    bx, by, bz = tri[t, 6] - tri[t, 0], tri[t, 7] - tri[t, 1], tri[t, 8] - tri[t, 2]
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    twice_area = math.sqrt(cx * cx + cy * cy + cz * cz)
    ux, uy, uz = cx / twice_area, cy / twice_area, cz / twice_area
    vn = vx * ux + vy * uy + vz * uz
    sin_g = min(abs(vn) / speed, 1.0)
    tx, ty, tz = vx - vn * ux, vy - vn * uy, vz - vn * uz
    cos_g = min(math.sqrt(tx * tx + ty * ty + tz * tz) / speed, 1.0)
    return 4.0 * k * f_mag * speed * finnie_shape(sin_g, cos_g) / twice_area


@njit(inline="always")
def _run_boundary(cand_p, q):
    """The first row of the sphere whose rows hold row ``q`` (rows sorted by sphere;
    the row count when ``q`` is past the end): where a run of spheres starts."""
    n = cand_p.shape[0]
    if q >= n:
        return n
    while q > 0 and cand_p[q - 1] == cand_p[q]:
        q -= 1
    return q


def _mesh_loop(sph, meshes, params, dt, n_chunks):
    """Contact forces of the Spheres ``sph`` on the triangles of the Meshes ``meshes``
    (:mod:`demstep.state`; module docstring). The fields it reads, by their names here:

    ``cand_p``, ``cand_t`` (K,): the candidate (particle, triangle) rows, sorted by
    particle; ``tri`` (T, 9) the triangles' corners now [L], ``vid`` (T, 3) their vertex
    ids (shared by the triangles of a mesh), ``tri_mesh`` (T,) their mesh; per mesh M:
    velocity ``mesh_vel`` [L/T], angular velocity ``mesh_omega`` [1/T] about the centre
    ``mesh_center`` [L], surface velocity ``mesh_surface`` [L/T] (added to the velocity
    of the contact point, the triangles staying where they are), its law's parameters ``mesh_law`` (M, F) (the rows of
    :func:`~demstep.contact.laws.params_from_row`: its material, its friction mu_wall);
    ``params`` the particles' law's parameters (the type);
    ``dt`` the step that produced x (slip increments). The slots (one per row, module
    docstring): ``active`` (K,) 1 when the row holds a contact, its ``slot_mesh`` and
    ``slot_tri`` (the triangle it is on), contact normal ``slot_normal`` (K, 3) (from the sphere to the mesh), tangential
    spring and dashpot forces on the mesh ``shear``, ``dashpot`` (K, 3), stored
    tangential energy ``etan`` (K,), the contact's force on the mesh ``fslot`` (K, 3)
    [M L/T^2]; updated in place. Meshes whose Finnie coefficient ``wear_k`` (M,) is
    positive add each contact's wear over the step to their triangles' ``wear`` (T,)
    (module docstring). Adds the contact forces and
    torques to ``force``, ``torque`` (N, 3); writes per mesh the force the particles
    exert ``mesh_force``, its torque about the centre ``mesh_torque``, the power the
    mesh puts into the particles ``mesh_power`` [M L^2/T^3] and the touching spheres
    ``mesh_contacts``. A law with rolling resistance (``params.roll_mode``) gives each
    contact rolling and twisting springs, the mesh the body j turning at its omega, its
    history in ``roll`` (K, ROLL_WIDTH) carried with the slot (:mod:`demstep.kernels.rolling`).
    Compiled twice (:data:`mesh_forces`, threaded over ``n_chunks`` runs of spheres,
    each run's rows its own spheres'; :data:`mesh_forces_serial`): the per-mesh sums
    and the wear are reduced after the runs, in row order. Returns (strain_n,
    strain_t, friction, dashpot, rolling strain, rolling plastic and viscous
    dissipation)."""
    x, v, w, r, m, force, torque = sph.x, sph.v, sph.w, sph.r, sph.m, sph.force, sph.torque
    cand_p, cand_t, tri, vid, tri_mesh = (meshes.cand_p, meshes.cand_t, meshes.tri, meshes.vid,
                                          meshes.tri_mesh)
    mesh_vel, mesh_omega, mesh_center, mesh_law = meshes.vel, meshes.omega, meshes.center, meshes.law
    mesh_surface = meshes.surface
    active, slot_mesh, slot_tri, slot_normal = (meshes.active, meshes.slot_mesh, meshes.slot_tri,
                                                meshes.normal)
    shear, dashpot, etan, fslot = meshes.shear, meshes.dashpot, meshes.etan, meshes.fslot
    wear_k, wear = meshes.wear_k, meshes.wear
    roll = meshes.roll
    x_ref, cand_d, mesh_moved = sph.x_ref, meshes.cand_d, meshes.moved[0]
    rolling = params.roll_mode != ROLL_NONE
    inertia = sph.inertia
    mesh_force, mesh_torque = meshes.force, meshes.torque
    mesh_power, mesh_contacts = meshes.power, meshes.contacts
    n_cand = cand_p.shape[0]
    n_mesh = mesh_force.shape[0]
    # the 'auto' step's cover, followed when set for these spheres
    cover_start, cover_ctl, cover_out = meshes.cover_start, meshes.cover_ctl, meshes.cover_out
    track = cover_start.shape[0] == x.shape[0] + 1
    lookahead = 2.0 * cover_ctl[3]  # (twice a step's move: the look-ahead of the pairs')
    wear_on = False
    for mk in range(n_mesh):
        if wear_k[mk] > 0.0:
            wear_on = True
    # per run: the sums returned, the largest drift and the contacts beyond the cover;
    # per run and mesh: force (3), torque (3), power, touching spheres; per row: wear
    sums = np.zeros((n_chunks, 9))
    per_mesh = np.zeros((n_chunks, n_mesh, 8))
    wear_row = np.zeros(n_cand if wear_on else 0)
    for ch in prange(n_chunks):
        near = np.empty(MAX_CANDIDATES, dtype=np.bool_)
        taken_ref = np.empty(MAX_CANDIDATES, dtype=np.bool_)
        cover_row = np.empty(5)
        # one sphere's candidates: geometry, kept flags, and its old slots
        g = np.empty((MAX_CANDIDATES, 9))
        feat = np.empty(MAX_CANDIDATES, dtype=np.int64)
        keep = np.empty(MAX_CANDIDATES, dtype=np.bool_)
        old = np.empty((MAX_CANDIDATES, 11))
        old_roll = np.empty((MAX_CANDIDATES, roll.shape[1]))
        old_mesh = np.empty(MAX_CANDIDATES, dtype=np.int64)
        taken = np.empty(MAX_CANDIDATES, dtype=np.bool_)
        new_of = np.empty(MAX_CANDIDATES, dtype=np.int64)
        run = per_mesh[ch]
        e_n = 0.0
        e_t = 0.0
        d_fric = 0.0
        d_dash = 0.0
        er_s = 0.0
        dr_p = 0.0
        dr_v = 0.0
        drift_max = 0.0
        n_short = 0
        s = _run_boundary(cand_p, (n_cand * ch) // n_chunks)
        s_end = _run_boundary(cand_p, (n_cand * (ch + 1)) // n_chunks)
        while s < s_end:
            p = cand_p[s]
            e = _sphere_rows_end(cand_p, s)
            n = e - s
            px, py, pz, rp = x[p, 0], x[p, 1], x[p, 2], r[p]
            # 1-2. each candidate triangle's contact, one per surface
            # rows that were beyond the contact (and the cover's look-ahead) at the build
            # by more than the sphere and the meshes have moved since are not computed
            dx, dy, dz = px - x_ref[p, 0], py - x_ref[p, 1], pz - x_ref[p, 2]
            moved = math.sqrt(dx * dx + dy * dy + dz * dz) + mesh_moved
            beyond = rp + moved + (lookahead * math.sqrt(v[p, 0] ** 2 + v[p, 1] ** 2
                                                           + v[p, 2] ** 2)
                                   + 2.0 * cover_ctl[2] if track else 0.0)
            _sphere_contacts(x, r, p, s, n, cand_t, tri, vid, tri_mesh, g, feat, keep,
                             cand_d, beyond, moved)
            if track:  # the contacts now and those closing in the next step, covered?
                speed = math.sqrt(v[p, 0] ** 2 + v[p, 1] ** 2 + v[p, 2] ** 2)
                reach = lookahead * speed + 2.0 * cover_ctl[2]
                if _sphere_cover(p, s, n, cand_t, vid, tri_mesh, g, feat, keep, near, rp, reach,
                                 cover_start, meshes.cover_mesh, meshes.cover_ref,
                                 meshes.cover_extra, cover_ctl[0], False, taken_ref, cover_row):
                    n_short += 1
                drift_max = max(drift_max, cover_row[0])
            # 3. the old slots of this sphere
            n_old = 0
            for k in range(n):
                row = s + k
                if active[row] == 1:
                    old[n_old, 0] = slot_normal[row, 0]
                    old[n_old, 1] = slot_normal[row, 1]
                    old[n_old, 2] = slot_normal[row, 2]
                    old[n_old, 3] = shear[row, 0]
                    old[n_old, 4] = shear[row, 1]
                    old[n_old, 5] = shear[row, 2]
                    old[n_old, 6] = dashpot[row, 0]
                    old[n_old, 7] = dashpot[row, 1]
                    old[n_old, 8] = dashpot[row, 2]
                    old[n_old, 9] = etan[row]
                    if rolling:
                        for c in range(roll.shape[1]):
                            old_roll[n_old, c] = roll[row, c]
                    old_mesh[n_old] = slot_mesh[row]
                    taken[n_old] = False
                    n_old += 1
            # 4. each kept contact takes the old slot of its mesh with the closest normal
            for k in range(n):
                new_of[k] = -1
                if not keep[k]:
                    continue
                mk = tri_mesh[cand_t[s + k]]
                best = MATCH_COS
                for o in range(n_old):
                    if taken[o] or old_mesh[o] != mk:
                        continue
                    cos = -(g[k, 1] * old[o, 0] + g[k, 2] * old[o, 1] + g[k, 3] * old[o, 2])
                    if cos > best:
                        best = cos
                        new_of[k] = o
                if new_of[k] >= 0:
                    taken[new_of[k]] = True
            # 5. slots no contact took have ended: their stored energy is released, and the
            # last half step of their spring and dashpot work (as a pair that opens: the
            # relative velocity at the contact point, at the arm r along the old normal)
            for o in range(n_old):
                if taken[o]:
                    continue
                mk = old_mesh[o]
                nx, ny, nz = old[o, 0], old[o, 1], old[o, 2]
                vix = v[p, 0] + rp * (w[p, 1] * nz - w[p, 2] * ny)
                viy = v[p, 1] + rp * (w[p, 2] * nx - w[p, 0] * nz)
                viz = v[p, 2] + rp * (w[p, 0] * ny - w[p, 1] * nx)
                cx = px + rp * nx - mesh_center[mk, 0]
                cy = py + rp * ny - mesh_center[mk, 1]
                cz = pz + rp * nz - mesh_center[mk, 2]
                ux = mesh_vel[mk, 0] + mesh_surface[mk, 0] + mesh_omega[mk, 1] * cz - mesh_omega[mk, 2] * cy
                uy = mesh_vel[mk, 1] + mesh_surface[mk, 1] + mesh_omega[mk, 2] * cx - mesh_omega[mk, 0] * cz
                uz = mesh_vel[mk, 2] + mesh_surface[mk, 2] + mesh_omega[mk, 0] * cy - mesh_omega[mk, 1] * cx
                pm = params_from_row(params, mesh_law[mk])
                (_, _, _, _, _, c_fric, c_dash, _, _, _, _, _, _, _, _, _) = contact_response(
                    pm, pm.mu_wall, nx, ny, nz, -1.0, rp, m[p], ux - vix, uy - viy,
                    uz - viz, dt, old[o, 3], old[o, 4], old[o, 5], old[o, 6], old[o, 7],
                    old[o, 8], old[o, 9])
                d_fric += c_fric
                d_dash += c_dash
                if rolling:  # (its rolling and twisting springs released, as a pair's)
                    _, _, _, _, _, r_p, r_v = rolling_contact(
                        pm, old_roll[o], nx, ny, nz, -1.0, rp, inertia[p], m[p], rp, 0.0, 0.0,
                        0.0, mesh_omega[mk, 0] - w[p, 0], mesh_omega[mk, 1] - w[p, 1],
                        mesh_omega[mk, 2] - w[p, 2], dt)
                    dr_p += r_p
                    dr_v += r_v
            # 6. the forces, written into this sphere's rows from its first one
            row = s
            for k in range(n):
                if not keep[k]:
                    continue
                t = cand_t[s + k]
                mk = tri_mesh[t]
                delta, dist = g[k, 0], g[k, 4]
                # the contact normal points from the sphere to the mesh
                nx, ny, nz = -g[k, 1], -g[k, 2], -g[k, 3]
                qx, qy, qz = g[k, 5], g[k, 6], g[k, 7]
                pm = params_from_row(params, mesh_law[mk])
                o = new_of[k]
                if o >= 0:
                    ox, oy, oz = old[o, 3], old[o, 4], old[o, 5]
                    fdx, fdy, fdz = old[o, 6], old[o, 7], old[o, 8]
                    e_old = old[o, 9]
                else:
                    ox, oy, oz, fdx, fdy, fdz, e_old = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
                a = dist  # the arm: from the centre to the contact point on the triangle
                vix = v[p, 0] + a * (w[p, 1] * nz - w[p, 2] * ny)
                viy = v[p, 1] + a * (w[p, 2] * nx - w[p, 0] * nz)
                viz = v[p, 2] + a * (w[p, 0] * ny - w[p, 1] * nx)
                # the mesh's velocity at the contact point
                cx = qx - mesh_center[mk, 0]
                cy = qy - mesh_center[mk, 1]
                cz = qz - mesh_center[mk, 2]
                ux = mesh_vel[mk, 0] + mesh_surface[mk, 0] + mesh_omega[mk, 1] * cz - mesh_omega[mk, 2] * cy
                uy = mesh_vel[mk, 1] + mesh_surface[mk, 1] + mesh_omega[mk, 2] * cx - mesh_omega[mk, 0] * cz
                uz = mesh_vel[mk, 2] + mesh_surface[mk, 2] + mesh_omega[mk, 0] * cy - mesh_omega[mk, 1] * cx
                (fx, fy, fz, c_en, c_et, c_fric, c_dash, _, _, tx, ty, tz, ndx, ndy, ndz,
                 e_new) = contact_response(
                    pm, pm.mu_wall, nx, ny, nz, delta, rp, m[p], ux - vix, uy - viy,
                    uz - viz, dt, ox, oy, oz, fdx, fdy, fdz, e_old)
                active[row] = 1
                slot_mesh[row] = mk
                slot_tri[row] = t
                slot_normal[row, 0] = nx
                slot_normal[row, 1] = ny
                slot_normal[row, 2] = nz
                shear[row, 0] = tx
                shear[row, 1] = ty
                shear[row, 2] = tz
                dashpot[row, 0] = ndx
                dashpot[row, 1] = ndy
                dashpot[row, 2] = ndz
                etan[row] = e_new
                fslot[row, 0] = fx
                fslot[row, 1] = fy
                fslot[row, 2] = fz
                if rolling:  # rolling and twisting resistance: the mesh is j, it turns at omega
                    for c in range(roll.shape[1]):
                        roll[row, c] = old_roll[o, c] if o >= 0 else 0.0
                    touched, mx, my, mz, e_r, r_p, r_v = rolling_contact(
                        pm, roll[row], nx, ny, nz, delta, rp, inertia[p], m[p], rp, 0.0, 0.0, 0.0,
                        mesh_omega[mk, 0] - w[p, 0], mesh_omega[mk, 1] - w[p, 1],
                        mesh_omega[mk, 2] - w[p, 2], dt)
                    if touched:
                        torque[p, 0] -= mx
                        torque[p, 1] -= my
                        torque[p, 2] -= mz
                        run[mk, 3] += mx
                        run[mk, 4] += my
                        run[mk, 5] += mz
                        run[mk, 6] -= (mx * mesh_omega[mk, 0] + my * mesh_omega[mk, 1]
                                           + mz * mesh_omega[mk, 2])
                        er_s += e_r
                        dr_p += r_p
                        dr_v += r_v
                if wear_k[mk] > 0.0:
                    wear_row[row] = dt * finnie_rate(
                        tri, t, v[p, 0] - ux, v[p, 1] - uy, v[p, 2] - uz, nx, ny, nz,
                        math.sqrt(fx * fx + fy * fy + fz * fz), wear_k[mk])
                row += 1
                force[p, 0] -= fx
                force[p, 1] -= fy
                force[p, 2] -= fz
                torque[p, 0] -= a * (ny * fz - nz * fy)
                torque[p, 1] -= a * (nz * fx - nx * fz)
                torque[p, 2] -= a * (nx * fy - ny * fx)
                run[mk, 0] += fx
                run[mk, 1] += fy
                run[mk, 2] += fz
                run[mk, 3] += cy * fz - cz * fy
                run[mk, 4] += cz * fx - cx * fz
                run[mk, 5] += cx * fy - cy * fx
                run[mk, 6] -= fx * ux + fy * uy + fz * uz
                run[mk, 7] += 1.0
                e_n += c_en
                e_t += c_et
                d_fric += c_fric
                d_dash += c_dash
            for q in range(row, e):
                active[q] = 0
                fslot[q, 0] = 0.0
                fslot[q, 1] = 0.0
                fslot[q, 2] = 0.0
                if rolling:
                    for c in range(roll.shape[1]):
                        roll[q, c] = 0.0
            s = e
        sums[ch, 0] = e_n
        sums[ch, 1] = e_t
        sums[ch, 2] = d_fric
        sums[ch, 3] = d_dash
        sums[ch, 4] = er_s
        sums[ch, 5] = dr_p
        sums[ch, 6] = dr_v
        sums[ch, 7] = drift_max
        sums[ch, 8] = n_short
    mesh_force[:] = 0.0
    mesh_torque[:] = 0.0
    mesh_power[:] = 0.0
    mesh_contacts[:] = 0
    for ch in range(n_chunks):
        for mk in range(n_mesh):
            for k in range(3):
                mesh_force[mk, k] += per_mesh[ch, mk, k]
                mesh_torque[mk, k] += per_mesh[ch, mk, 3 + k]
            mesh_power[mk] += per_mesh[ch, mk, 6]
            mesh_contacts[mk] += int(per_mesh[ch, mk, 7])
    if wear_on:  # (in row order: as one run would add them)
        for row in range(n_cand):
            if wear_row[row] != 0.0:
                wear[slot_tri[row]] += wear_row[row]
    cover_out[0] = sums[:, 7].max() if n_chunks > 0 else 0.0
    cover_out[1] = 0.0
    cover_out[2] = sums[:, 8].sum()
    return (sums[:, 0].sum(), sums[:, 1].sum(), sums[:, 2].sum(), sums[:, 3].sum(),
            sums[:, 4].sum(), sums[:, 5].sum(), sums[:, 6].sum())
#: the mesh contacts' loop, threaded over runs of spheres and serial
mesh_forces, mesh_forces_serial = compile_parallel_and_serial(_mesh_loop)


@njit
def move_meshes(tri, tri0, tri_mesh, motion, mesh_vel, mesh_omega, mesh_axis, mesh_center,
                mesh_shift, mesh_turn, dt):
    """Move the meshes over a step of ``dt`` [T]: a mesh that moves (``motion`` 1)
    translates by v dt (its centre with it) and turns by |omega| dt about its axis
    ``mesh_axis`` (the unit axis of its rotation, kept when omega is set to 0) through
    its centre; its triangles' corners ``tri`` are recomputed from their
    positions as read ``tri0`` with the total shift and turn (no drift of round-off).
    Returns the largest distance [L] a corner moved."""
    n_mesh = motion.shape[0]
    for mk in range(n_mesh):
        if motion[mk] == 0:
            continue
        for k in range(3):
            mesh_shift[mk, k] += dt * mesh_vel[mk, k]
            mesh_center[mk, k] += dt * mesh_vel[mk, k]
        om = math.sqrt(mesh_omega[mk, 0] ** 2 + mesh_omega[mk, 1] ** 2 + mesh_omega[mk, 2] ** 2)
        mesh_turn[mk] += om * dt
    moved = 0.0
    for t in range(tri.shape[0]):
        mk = tri_mesh[t]
        if motion[mk] == 0:
            continue
        ang = mesh_turn[mk]
        kx, ky, kz = mesh_axis[mk, 0], mesh_axis[mk, 1], mesh_axis[mk, 2]
        c, sn = math.cos(ang), math.sin(ang)
        # the centre as read: the centre now minus the shift
        ox = mesh_center[mk, 0] - mesh_shift[mk, 0]
        oy = mesh_center[mk, 1] - mesh_shift[mk, 1]
        oz = mesh_center[mk, 2] - mesh_shift[mk, 2]
        for corner in range(3):
            b = 3 * corner
            px, py, pz = tri0[t, b] - ox, tri0[t, b + 1] - oy, tri0[t, b + 2] - oz
            # Rodrigues: p cos + (k x p) sin + k (k . p)(1 - cos)
            kp = kx * px + ky * py + kz * pz
            rx = px * c + (ky * pz - kz * py) * sn + kx * kp * (1.0 - c)
            ry = py * c + (kz * px - kx * pz) * sn + ky * kp * (1.0 - c)
            rz = pz * c + (kx * py - ky * px) * sn + kz * kp * (1.0 - c)
            nxp = rx + mesh_center[mk, 0]
            nyp = ry + mesh_center[mk, 1]
            nzp = rz + mesh_center[mk, 2]
            d = math.sqrt((nxp - tri[t, b]) ** 2 + (nyp - tri[t, b + 1]) ** 2
                          + (nzp - tri[t, b + 2]) ** 2)
            moved = max(moved, d)
            tri[t, b] = nxp
            tri[t, b + 1] = nyp
            tri[t, b + 2] = nzp
    return moved


@njit
def triangle_distances(x, p, tri, t):
    """|x_p - q| [L], q the closest point of triangle t (corners ``tri[t]`` (9,)) to the
    centre of particle p, for the pairs (p, t) (C,)."""
    out = np.empty(p.shape[0])
    for k in range(p.shape[0]):
        a, b = p[k], t[k]
        qx, qy, qz, _ = closest_point_on_triangle(
            x[a, 0], x[a, 1], x[a, 2], tri[b, 0], tri[b, 1], tri[b, 2], tri[b, 3],
            tri[b, 4], tri[b, 5], tri[b, 6], tri[b, 7], tri[b, 8])
        out[k] = math.sqrt((x[a, 0] - qx) ** 2 + (x[a, 1] - qy) ** 2 + (x[a, 2] - qz) ** 2)
    return out


@njit
def _triangle_cell_range(tri, t, lo, cell, ncell, reach):
    """The cells (per axis: first, last) that the box of triangle t grown by ``reach``
    [L] covers, clipped to the grid; empty (first > last) when it misses the grid."""
    first = np.empty(3, dtype=np.int64)
    last = np.empty(3, dtype=np.int64)
    for k in range(3):
        a = min(tri[t, k], tri[t, 3 + k], tri[t, 6 + k]) - reach
        b = max(tri[t, k], tri[t, 3 + k], tri[t, 6 + k]) + reach
        first[k] = max(int(math.floor((a - lo[k]) / cell)), 0)
        last[k] = min(int(math.floor((b - lo[k]) / cell)), ncell[k] - 1)
    return first, last


@njit
def _cell_of(x, p, lo, cell, ncell):
    """The cell of the centre of particle p in the grid (``lo``, ``cell``, ``ncell``),
    -1 outside it."""
    c = 0
    for k in range(3):
        f = (x[p, k] - lo[k]) / cell
        if not (f >= 0.0 and f < ncell[k]):
            return -1
        c = c * ncell[k] + min(int(f), ncell[k] - 1)
    return c


@njit
def triangle_grid(tri, use, lo, cell, ncell, reach):
    """The triangles near each cell of a grid of ``ncell`` (3,) cells of side ``cell``
    [L] from ``lo``: every triangle t with ``use[t]`` is listed in each cell whose
    centre lies within ``reach`` + half the cell's diagonal of it (so every point of
    the cell within ``reach`` of t finds it), in triangle order. Returns (start
    (C + 1,), triangles (E,)): the list of cell c is triangles[start[c]:start[c + 1]]."""
    n_cells = ncell[0] * ncell[1] * ncell[2]
    limit = reach + 0.5 * cell * math.sqrt(3.0)
    limit2 = limit * limit
    start = np.zeros(n_cells + 1, dtype=np.int64)
    fill = np.empty(0, dtype=np.int64)
    out = np.empty(0, dtype=np.int64)
    for sweep in range(2):  # count, then fill
        for t in range(tri.shape[0]):
            if not use[t]:
                continue
            first, last = _triangle_cell_range(tri, t, lo, cell, ncell, reach)
            for i in range(first[0], last[0] + 1):
                cx = lo[0] + (i + 0.5) * cell
                for j in range(first[1], last[1] + 1):
                    cy = lo[1] + (j + 0.5) * cell
                    for k in range(first[2], last[2] + 1):
                        cz = lo[2] + (k + 0.5) * cell
                        qx, qy, qz, _ = closest_point_on_triangle(
                            cx, cy, cz, tri[t, 0], tri[t, 1], tri[t, 2], tri[t, 3],
                            tri[t, 4], tri[t, 5], tri[t, 6], tri[t, 7], tri[t, 8])
                        if (cx - qx) ** 2 + (cy - qy) ** 2 + (cz - qz) ** 2 > limit2:
                            continue
                        c = (i * ncell[1] + j) * ncell[2] + k
                        if sweep == 0:
                            start[c + 1] += 1
                        else:
                            out[fill[c]] = t
                            fill[c] += 1
        if sweep == 0:
            for c in range(n_cells):
                start[c + 1] += start[c]
            fill = start[:-1].copy()
            out = np.empty(start[n_cells], dtype=np.int64)
    return start, out


@njit(inline="always")
def _cell_hits(x, r, skin, tri, p, c, start, cell_tri, cand_p, cand_t, cand_d, at, write):
    """The triangles of cell c's list within r + ``skin`` of particle p: their number,
    written (with the distance) from ``at`` on when ``write``."""
    limit = r[p] + skin
    found = 0
    for q in range(start[c], start[c + 1]):
        t = cell_tri[q]
        qx, qy, qz, _ = closest_point_on_triangle(
            x[p, 0], x[p, 1], x[p, 2], tri[t, 0], tri[t, 1], tri[t, 2], tri[t, 3],
            tri[t, 4], tri[t, 5], tri[t, 6], tri[t, 7], tri[t, 8])
        d2 = (x[p, 0] - qx) ** 2 + (x[p, 1] - qy) ** 2 + (x[p, 2] - qz) ** 2
        if d2 < limit * limit:
            if write:
                cand_p[at + found] = p
                cand_t[at + found] = t
                cand_d[at + found] = math.sqrt(d2)
            found += 1
    return found


@njit(parallel=True)
def grid_candidates(x, r, skin, tri, lo, cell, ncell, start, cell_tri):
    """Every (particle, triangle) pair whose distance (centre to the triangle's closest
    point) is below r + ``skin`` [L], each particle looking at the triangles its cell
    lists (:func:`triangle_grid`, built with a reach of at least r + skin). Returns
    (cand_p, cand_t, cand_d), sorted by particle then triangle, cand_d the distance [L]."""
    n = x.shape[0]
    cell_of = np.empty(n, dtype=np.int64)
    counts = np.zeros(n + 1, dtype=np.int64)
    none = np.empty(0, dtype=np.int64)
    no_d = np.empty(0)
    for p in prange(n):
        c = _cell_of(x, p, lo, cell, ncell)
        cell_of[p] = c
        if c >= 0:
            counts[p + 1] = _cell_hits(x, r, skin, tri, p, c, start, cell_tri, none, none,
                                       no_d, 0, False)
    for p in range(n):
        counts[p + 1] += counts[p]
    cand_p = np.empty(counts[n], dtype=np.int64)
    cand_t = np.empty(counts[n], dtype=np.int64)
    cand_d = np.empty(counts[n])
    for p in prange(n):
        if cell_of[p] >= 0 and counts[p + 1] > counts[p]:
            _cell_hits(x, r, skin, tri, p, cell_of[p], start, cell_tri, cand_p, cand_t,
                       cand_d, counts[p], True)
    return cand_p, cand_t, cand_d
