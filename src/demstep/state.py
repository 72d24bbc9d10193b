"""The simulation state as typed bundles of arrays: what the compiled step takes.

Each bundle is a named tuple of float64/int64 arrays (C-contiguous, 3 components per
vector: disks live in the plane z = 0), so the compiled kernels read its fields by
name and numba types it once. A Simulation owns one bundle of each kind; a bundle is
immutable as a tuple (its arrays are written in place), and ``_replace`` makes a new
one when an array changes size (a neighbour-list rebuild).

``STATE`` of each bundle lists the fields that define the state (checkpoints save them,
:meth:`demstep.engine.Simulation.state_dict`); the other fields are work space rebuilt
from them.

=========== ====================================================================
``Spheres``  the member spheres: what contact detection and contact laws see
``Bodies``   rigid bodies made of member spheres (clumps): pose, momenta, mass
             properties and the member map; empty when every body is one sphere
``Pairs``    the Verlet pair list with each pair's contact history
``Bonds``    parallel bonds between particles (their own list, kept until they break)
``Walls``    rigid planes, their motion and servo state, and the particle-wall list
``Meshes``   triangle-mesh walls, their motion and outputs, and their contact slots
``Box``      the periodic box: lengths, their motion and the boundary sums
``Ledger``   the energy ledger's arrays (layout: :mod:`demstep.energy`) and counters
``Controls`` the scalars of one call of the step: dt, damping, limits, switches
=========== ====================================================================
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

#: columns of a rolling-resistance history row (:func:`demstep.kernels.rolling.rolling_response`)
ROLL_WIDTH = 8


class Spheres(NamedTuple):
    """Member spheres, N of them: centres ``x`` [L], half-step velocities ``v`` [L/T]
    and angular velocities ``w`` [1/T], radii ``r`` [L], masses ``m`` [M] and moments of
    inertia ``inertia`` [M L^2] with their reciprocals (zero: fixed, or rotation
    locked), contact ``force`` [M L/T^2] and ``torque`` [M L^2/T^2] of the last
    evaluation, ``applied`` forces, positions ``x_ref`` when the lists were built, and
    the damping force and torque of the last step ``damp_force``/``damp_torque`` (N, 6:
    local, then global; for the trapezoidal ledger)."""

    x: np.ndarray
    v: np.ndarray
    w: np.ndarray
    r: np.ndarray
    m: np.ndarray
    inertia: np.ndarray
    inv_m: np.ndarray
    inv_I: np.ndarray
    force: np.ndarray
    torque: np.ndarray
    applied: np.ndarray
    x_ref: np.ndarray
    damp_force: np.ndarray
    damp_torque: np.ndarray

    STATE = ("x", "v", "w", "m", "inertia", "applied", "x_ref", "damp_force", "damp_torque")

    @classmethod
    def make(cls, x, v, w, r, m, inertia) -> "Spheres":
        n = len(r)
        # fresh zeros, not copies of one: pages of zeros never written stay out of
        # memory (the applied forces of a run without any: 2.4 MB at 1e5 spheres)
        return cls(x, v, w, r, m, inertia, np.zeros(n), np.zeros(n), np.zeros((n, 3)),
                   np.zeros((n, 3)), np.zeros((n, 3)), x.copy(), np.zeros((n, 6)),
                   np.zeros((n, 6)))


class Bodies(NamedTuple):
    """Rigid bodies of several member spheres (clumps), B of them. Pose: centre of mass
    ``x`` [L] and orientation quaternion ``q`` (B, 4) (w, x, y, z: body to world);
    momenta: half-step velocity ``v`` [L/T] and angular momentum ``L`` [M L^2/T] (world
    frame); mass ``m`` [M], principal moments ``inertia`` (B, 3) [M L^2] with their
    reciprocals (``inv_m`` zero: fixed; ``inv_I`` zero: rotation locked); ``force`` and
    ``torque`` summed from the members; members ``start`` (B + 1,) into ``member``
    (the member sphere indices) and ``offset`` (M, 3) [L], each member's centre in the
    body frame. ``sphere_body`` (N,) the body of each sphere (-1: a free sphere)."""

    x: np.ndarray
    q: np.ndarray
    v: np.ndarray
    L: np.ndarray
    m: np.ndarray
    inertia: np.ndarray
    inv_m: np.ndarray
    inv_I: np.ndarray
    force: np.ndarray
    torque: np.ndarray
    applied: np.ndarray
    start: np.ndarray
    member: np.ndarray
    offset: np.ndarray
    sphere_body: np.ndarray
    damp_force: np.ndarray
    damp_torque: np.ndarray

    STATE = ("x", "q", "v", "L", "m", "inertia", "applied", "damp_force", "damp_torque")

    @classmethod
    def empty(cls, n_spheres: int) -> "Bodies":
        z3 = np.zeros((0, 3))
        return cls(z3, np.zeros((0, 4)), z3.copy(), z3.copy(), np.zeros(0), z3.copy(),
                   np.zeros(0), z3.copy(), z3.copy(), z3.copy(), z3.copy(),
                   np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64), z3.copy(),
                   np.full(n_spheres, -1, dtype=np.int64), np.zeros((0, 6)), np.zeros((0, 6)))

    @property
    def n(self) -> int:
        return len(self.m)


#: the per-contact history of the pair and the particle-wall lists (:class:`Pairs`,
#: :class:`Walls`), one row per listed contact
CONTACT_HISTORY = ("shear", "dashpot", "shear_energy", "roll", "cover")


class Pairs(NamedTuple):
    """The Verlet pair list, P pairs (i < j in index, sorted by i) with their history:
    tangential spring force on j ``shear`` (P, 3) [M L/T^2], dashpot force on j
    ``dashpot`` (P, 3), stored tangential energy ``shear_energy`` (P,) [M L^2/T^2].
    Work space: pair ``chunks`` (one per thread, cut at particle starts), their
    particle ``spans``, the band buffers ``force_band``/``torque_band`` (chunks, rows, 3)
    for what a chunk adds to particles past its own (see
    :func:`demstep.kernels.dem._pair_loop`; no rows with one chunk), and ``geo`` (P, 4), the
    unit normals and distances of the first pass of the pair loop. ``roll`` (P, 8): the
    rolling and twisting resistance history (columns: :data:`demstep.kernels.rolling.ROLL_M`
    ...), (0, 8) when the law has none. ``cover`` (P,): the largest overlap [L] the last
    certified 'auto' time step covered each pair at (0: not covered; from the record of
    the contacts it covered, carried over by rebuilds), (0,) when not tracked."""

    i: np.ndarray
    j: np.ndarray
    shear: np.ndarray
    dashpot: np.ndarray
    shear_energy: np.ndarray
    chunks: np.ndarray
    spans: np.ndarray
    force_band: np.ndarray
    torque_band: np.ndarray
    geo: np.ndarray
    roll: np.ndarray
    cover: np.ndarray

    STATE = ("i", "j") + CONTACT_HISTORY

    @classmethod
    def empty(cls, n: int) -> "Pairs":
        z3 = np.zeros((0, 3))
        return cls(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), z3, z3.copy(),
                   np.zeros(0), np.zeros(2, dtype=np.int64), np.array([[0, n]], dtype=np.int64),
                   np.zeros((1, 0, 3)), np.zeros((1, 0, 3)), np.empty((0, 4)),
                   np.zeros((0, ROLL_WIDTH)), np.zeros(0))


class Bonds(NamedTuple):
    """Parallel bonds (:mod:`demstep.contact.bonds`), B of them: particles ``i``, ``j``
    (B,), bond ``radius`` [L], stiffnesses per unit area ``k_n``, ``k_s``
    [M/(L^2 T^2)], strengths ``sigma_c``, ``tau_c`` [M/(L T^2)], ``intact`` (1, or 0
    once broken), and the state: normal force on j along n ``normal`` [M L/T^2],
    shear force on j ``shear`` (B, 3), twisting moment on j along n ``twist``
    [M L^2/T^2], bending moment on j ``bend`` (B, 3), strain ``energy`` [M L^2/T^2]."""

    i: np.ndarray
    j: np.ndarray
    radius: np.ndarray
    k_n: np.ndarray
    k_s: np.ndarray
    sigma_c: np.ndarray
    tau_c: np.ndarray
    intact: np.ndarray
    normal: np.ndarray
    shear: np.ndarray
    twist: np.ndarray
    bend: np.ndarray
    energy: np.ndarray

    STATE = ("i", "j", "radius", "k_n", "k_s", "sigma_c", "tau_c", "intact", "normal", "shear",
             "twist", "bend", "energy")

    @classmethod
    def make(cls, i, j, radius, k_n, k_s, sigma_c, tau_c) -> "Bonds":
        b = len(i)
        full = lambda v: np.broadcast_to(np.asarray(v, dtype=np.float64), (b,)).copy()  # noqa: E731
        return cls(np.asarray(i, dtype=np.int64), np.asarray(j, dtype=np.int64), full(radius),
                   full(k_n), full(k_s), full(sigma_c), full(tau_c), np.ones(b, dtype=np.int64),
                   np.zeros(b), np.zeros((b, 3)), np.zeros(b), np.zeros((b, 3)), np.zeros(b))

    @classmethod
    def empty(cls) -> "Bonds":
        z = np.zeros(0)
        return cls.make(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), z, z, z, z, z)

    @property
    def n(self) -> int:
        return len(self.i)


class Walls(NamedTuple):
    """W rigid planes through ``point`` [L] with unit ``normal`` pointing into the
    packing, velocity ``vel`` [L/T], friction ``mu``, ``motion`` (fixed / velocity /
    servo, :mod:`demstep.kernels.dem`), ``servo`` (W, 5) parameters; the force the
    particles exert ``force`` [M L/T^2] (and of the last step ``force_prev``, with the
    last displacement ``disp_prev``), positions ``ref`` when the lists were built,
    loaded ``areas`` [L^2], touching ``contacts`` and their summed ``k_sum`` [M/T^2];
    ``box_lo``/``box_hi`` (3,): the axis-aligned walls bounding the specimen (-1: none).
    The particle-wall list: particle ``p``, wall ``wall`` and each pair's history
    ``shear``, ``dashpot``, ``shear_energy``, ``roll`` and ``cover`` (as :class:`Pairs`)."""

    point: np.ndarray
    normal: np.ndarray
    vel: np.ndarray
    mu: np.ndarray
    motion: np.ndarray
    servo: np.ndarray
    force: np.ndarray
    force_prev: np.ndarray
    disp_prev: np.ndarray
    ref: np.ndarray
    areas: np.ndarray
    contacts: np.ndarray
    k_sum: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    p: np.ndarray
    wall: np.ndarray
    shear: np.ndarray
    dashpot: np.ndarray
    shear_energy: np.ndarray
    roll: np.ndarray
    cover: np.ndarray

    STATE = ("point", "vel", "motion", "servo", "force", "force_prev", "disp_prev", "ref",
             "k_sum", "p", "wall") + CONTACT_HISTORY


class Meshes(NamedTuple):
    """Triangle-mesh walls (:mod:`demstep.engine.meshes`): T triangles of M meshes and
    the candidate list of K (particle, triangle) rows with their contact slots
    (:mod:`demstep.kernels.meshes`).

    Triangles: corners now ``tri`` (T, 9) [L] and as read ``tri0``, vertex ids ``vid``
    (T, 3) (shared by the triangles of a mesh), the mesh of each ``tri_mesh`` (T,).
    Meshes: ``motion`` (M,) (0 fixed, 1 moving), velocity ``vel`` (M, 3) [L/T], angular
    velocity ``omega`` (M, 3) [1/T] about ``center`` (M, 3) [L] (moving with the mesh),
    the unit ``axis`` (M, 3) of the rotation (omega's direction, kept when omega is set
    to 0: the corners follow from the total turn about it),
    a surface velocity ``surface`` (M, 3) [L/T] (a conveyor belt: the contacts see the
    surface move, the triangles stay),
    the translation ``shift`` (M, 3) [L] and the turn ``turn`` (M,) [rad] since the
    start, the parameters of each mesh's contacts ``law`` (M, F) (a row of the law's
    Params tuple: the mesh's material and friction); outputs: the force the particles exert ``force`` (M, 3), its
    torque about the centre ``torque`` (M, 3), the power the mesh puts into the
    particles now and at the last step ``power``, ``power_prev`` (M,) [M L^2/T^3],
    touching particles ``contacts``; ``moved`` (1,): how far a corner moved since the
    lists were built [L]. Candidates: ``cand_p``, ``cand_t`` (K,) and each one's distance
    at the build ``cand_d`` (K,) [L] (rows farther than the sphere and the meshes have
    moved since are not computed; zeros: every row is; not saved); slots: ``active``
    (K,), their mesh ``slot_mesh`` and triangle ``slot_tri`` (K,), contact normal
    ``normal`` (K, 3), tangential spring and dashpot forces ``shear``, ``dashpot``
    (K, 3), stored tangential energy ``etan`` (K,), the contact's force on the mesh
    ``fslot`` (K, 3) [M L/T^2] (for the per-triangle output) and its rolling-resistance
    history ``roll`` (K, ROLL_WIDTH) (zeros without rolling resistance). Wear: each mesh's Finnie
    coefficient ``wear_k`` (M,) [L T^2/M] (0: not tracked) and the wear accumulated on
    each triangle ``wear`` (T,) [L with k in 1/pressure] (:mod:`demstep.kernels.meshes`).

    The 'auto' step's cover of the mesh contacts (:mod:`demstep.kernels.meshes`; set by
    :meth:`demstep.engine.auto_step.AutoStep.sync_mesh_cover`, empty when not followed):
    per particle the rows ``cover_start`` (N + 1,) of its covered contacts, each with
    its mesh ``cover_mesh`` (Q,) and ``cover_ref`` (Q, 11): the reference normal (3),
    arm [L], k_n, k_t [M/T^2], c_n, c_t [M/T], the overlap covered [L], the particle's
    inverse mass and moment of inertia; per particle ``cover_extra`` (N, 2): how many
    contacts the certificate's added group holds for it and at what overlap;
    ``cover_ctl`` (4,): the certified root sigma [1/T], the mesh drift at which the
    steps stop for a check [1/T^2], the meshes' largest move in the last step [L], and
    the step [T]; ``cover_out`` (3,): after each step, the largest drift of a particle's
    mesh contacts [1/T^2], and the contacts found beyond the cover."""

    tri: np.ndarray
    tri0: np.ndarray
    vid: np.ndarray
    tri_mesh: np.ndarray
    motion: np.ndarray
    vel: np.ndarray
    omega: np.ndarray
    axis: np.ndarray
    surface: np.ndarray
    center: np.ndarray
    shift: np.ndarray
    turn: np.ndarray
    law: np.ndarray
    force: np.ndarray
    torque: np.ndarray
    power: np.ndarray
    power_prev: np.ndarray
    contacts: np.ndarray
    moved: np.ndarray
    cand_p: np.ndarray
    cand_t: np.ndarray
    cand_d: np.ndarray
    active: np.ndarray
    slot_mesh: np.ndarray
    slot_tri: np.ndarray
    normal: np.ndarray
    shear: np.ndarray
    dashpot: np.ndarray
    etan: np.ndarray
    fslot: np.ndarray
    roll: np.ndarray
    cover_start: np.ndarray
    cover_mesh: np.ndarray
    cover_ref: np.ndarray
    cover_extra: np.ndarray
    cover_ctl: np.ndarray
    cover_out: np.ndarray
    wear_k: np.ndarray
    wear: np.ndarray

    #: the fields of a contact slot: one row per candidate, carried with it
    SLOTS = ("active", "slot_mesh", "slot_tri", "normal", "shear", "dashpot", "etan", "fslot",
             "roll")
    STATE = ("tri", "vel", "omega", "axis", "surface", "center", "shift", "turn", "law", "force", "torque",
             "power", "power_prev", "moved", "cand_p", "cand_t", "cover_ctl", "wear") + SLOTS

    @property
    def n(self) -> int:
        return len(self.motion)


class Box(NamedTuple):
    """The periodic box: ``length`` (3,) [L] (0: not periodic), per-axis ``motion``
    (fixed / rate / servo) and ``servo`` (3, 5) parameters (the rate [L/T] in the gain
    column), lengths ``ref`` when the lists were built, and ``sums`` (6, 3): virial,
    crossing sum, crossing contacts, their k_n sum, the previous crossing sum and the
    last change of length (see :func:`demstep.kernels.dem.advance`)."""

    length: np.ndarray
    motion: np.ndarray
    servo: np.ndarray
    ref: np.ndarray
    sums: np.ndarray

    STATE = ("length", "motion", "servo", "ref", "sums")


class Ledger(NamedTuple):
    """The energy ledger's arrays, laid out by :mod:`demstep.energy`: accumulated terms
    ``acc`` and state terms ``energy``; ``counters`` (9,): particle-particle contacts,
    particle-wall contacts, the largest jump |v| dt / r of the last step, the
    contacts counted closed beyond their cover since the engine last reset it, the
    distance [L] the pairs' ends may have moved relative to each other since the last
    check of the drift, summed step by step, and the terms of its displacement bound
    (:func:`demstep.kernels.dem.drift_used`; :func:`demstep.kernels.dem.advance`)."""

    acc: np.ndarray
    energy: np.ndarray
    counters: np.ndarray

    STATE = ("acc", "energy", "counters")


class Controls(NamedTuple):
    """Scalars of one call of the compiled step: ``dt`` and the previous step
    ``dt_prev`` [T], ``first`` (initialise the half-step velocities), Verlet ``skin``
    [L], ``dim``, ``gravity`` (3,) [L/T^2], local and global viscous damping,
    whether the last step's damping and dashpot forces must be kept (``store_*``),
    divergence limits, the ledger's energy floor, and ``parallel``."""

    dt: float
    dt_prev: float
    first: bool
    skin: float
    dim: int
    gravity: np.ndarray
    local_damping: float
    viscous_damping: float
    store_damping: bool
    store_dashpot: bool
    jump_limit: float
    runaway_factor: float
    energy_floor: float
    parallel: bool
    #: 'auto': how far [L] the pairs' ends may move relative to each other from the
    #: last check of the drift before the next one (+inf: none due)
    check_budget: float = float("inf")
