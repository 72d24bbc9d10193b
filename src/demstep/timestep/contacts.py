"""Contact sets: which particles touch, along which normal, with which stiffness.

A :class:`ContactSet` is what the time-step analysis needs of an assembly: for each
contact the particle indices, the unit normal from particle ``i`` towards ``j`` (or
towards the wall), the arms from each centre to the contact point, the normal and
tangential stiffnesses and dashpots, and (optional) the rolling and twisting springs
and their viscous parts. It is built from geometry (:func:`find_contacts`) or by the
engine from its live contact list.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from demstep.contact.geometry import pair_geometry_arrays
from demstep.contact.laws import rolling_inertia
from demstep.errors import InputError
from demstep.kernels.neighbors import build_pair_list
from demstep.kernels.timestep_kernels import rolling_coefficient_arrays
from demstep.particles import Particles

#: default relative tolerance for "touching" contacts found from geometry
DEFAULT_CONTACT_TOL = 1e-6
#: the optional rolling-resistance fields of a ContactSet (default 0)
ROLLING_FIELDS = ("k_r", "k_w", "c_r", "c_w")
#: the optional per-contact coefficients (default 0: untouched zeros when absent)
OPTIONAL_FIELDS = ("c_n", "c_t") + ROLLING_FIELDS


@dataclass
class ContactSet:
    """Contacts (C of them). ``j`` is -1 for a particle-wall contact (``wall`` gives the
    wall index, else -1). ``normal`` (C, dim) is the unit vector from i towards j or the
    wall; ``arm_i``/``arm_j`` [L] are the distances from the centres to the contact
    point (``arm_j`` = 0 at walls); ``k_n``/``k_s`` [M/T^2] the spring stiffnesses;
    ``c_n``/``c_t`` [M/T] the dashpots (default 0).

    Rolling and twisting resistance (:mod:`demstep.contact.laws`, default 0): springs
    ``k_r`` (rolling) and ``k_w`` (twisting) [M L^2/T^2 per rad] and their viscous
    coefficients ``c_r``, ``c_w`` [M L^2/T], acting on the relative rotation
    phi = theta_j - theta_i (a wall does not rotate): the moment on j is
    -(k_r (I - n n^T) + k_w n n^T) phi, i's the opposite; for disks (2D) phi is the z
    rotation and the moment -k_r phi (no twisting: ``k_w`` and ``c_w`` are ignored).
    They act on rotational degrees of freedom only, so an analysis with rotation
    locked ignores them."""

    i: np.ndarray
    j: np.ndarray
    normal: np.ndarray
    arm_i: np.ndarray
    arm_j: np.ndarray
    k_n: np.ndarray
    k_s: np.ndarray
    wall: np.ndarray | None = None
    c_n: np.ndarray | None = None
    c_t: np.ndarray | None = None
    k_r: np.ndarray | None = None
    k_w: np.ndarray | None = None
    c_r: np.ndarray | None = None
    c_w: np.ndarray | None = None

    def __post_init__(self):
        c = len(self.i)
        self.i = np.asarray(self.i, dtype=np.int64)
        self.j = np.asarray(self.j, dtype=np.int64)
        self.normal = np.asarray(self.normal, dtype=np.float64)
        if self.normal.ndim != 2:
            self.normal = self.normal.reshape(c, -1)
        self.arm_i = np.asarray(self.arm_i, dtype=np.float64)
        self.arm_j = np.asarray(self.arm_j, dtype=np.float64)
        self.k_n = np.broadcast_to(np.asarray(self.k_n, dtype=np.float64), (c,)).copy()
        self.k_s = np.broadcast_to(np.asarray(self.k_s, dtype=np.float64), (c,)).copy()
        if self.wall is None:
            self.wall = np.full(c, -1, dtype=np.int64)
        self.wall = np.asarray(self.wall, dtype=np.int64)
        for name in OPTIONAL_FIELDS:
            value = getattr(self, name)
            # absent or all zero: zeros the system hands out untouched (no memory until
            # written: 6 x 46 MB at 6e6 contacts without dashpots or rolling resistance)
            if value is not None:
                value = np.broadcast_to(np.asarray(value, dtype=np.float64), (c,))
            setattr(self, name, value.copy() if value is not None and value.any()
                    else np.zeros(c))

    #: the per-contact arrays, in constructor order
    FIELDS = ("i", "j", "normal", "arm_i", "arm_j", "k_n", "k_s", "wall", "c_n", "c_t",
              "k_r", "k_w", "c_r", "c_w")

    @property
    def n(self) -> int:
        return len(self.i)

    @property
    def dim(self) -> int:
        return self.normal.shape[1]

    @property
    def damped(self) -> bool:
        """Whether any contact has a dashpot (translational, rolling or twisting)."""
        return bool(self.n and (self.c_n.any() or self.c_t.any() or self.c_r.any()
                                or self.c_w.any()))

    @property
    def has_rolling(self) -> bool:
        """Whether any contact has a rolling or twisting spring or viscous coefficient
        (in 2D: k_r or c_r only, disks do not twist)."""
        if not self.n:
            return False
        if self.dim == 2:
            return bool(self.k_r.any() or self.c_r.any())
        return bool(self.k_r.any() or self.k_w.any() or self.c_r.any() or self.c_w.any())

    def dashpot_springs(self) -> "ContactSet":
        """The same contacts with the viscous coefficients in place of the springs
        (k_n, k_s, k_r, k_w := c_n, c_t, c_r, c_w): their 'stiffness' matrix is the
        damping matrix C_d [M/T] (the dashpots act on the same relative motions)."""
        return replace(self, k_n=self.c_n, k_s=self.c_t, k_r=self.c_r, k_w=self.c_w)

    def subset(self, keep) -> "ContactSet":
        """The contacts selected by ``keep`` (a boolean mask, an index array or a slice);
        optional coefficients that are all zero stay untouched zeros (no memory until
        written). A slice takes views: the constructor copies only the part's springs
        and its non-zero optional coefficients, without a pass over the whole set's."""
        if isinstance(keep, slice):
            return ContactSet(*(getattr(self, f)[keep] for f in self.FIELDS))
        return ContactSet(*(None if _all_zero_optional(f, [self]) else getattr(self, f)[keep]
                            for f in self.FIELDS))

    def renumbered(self, new_index: np.ndarray) -> "ContactSet":
        """The same contacts on renumbered particles: particle p becomes
        ``new_index[p]`` (walls stay -1), the contacts sorted by their new i (stable)."""
        i = new_index[self.i]
        j = np.where(self.j >= 0, new_index[np.maximum(self.j, 0)], self.j)
        order = np.argsort(i, kind="stable")
        moved = self.subset(order)
        moved.i, moved.j = i[order], j[order]
        return moved

    @property
    def is_wall(self) -> np.ndarray:
        return self.j < 0

    def count_per_particle(self, n_particles: int) -> np.ndarray:
        """Number of contacts of each particle (wall contacts included)."""
        counts = np.bincount(self.i, minlength=n_particles)
        pp = self.j >= 0
        counts += np.bincount(self.j[pp], minlength=n_particles)
        return counts

    def k_max(self) -> float:
        """Largest spring stiffness, max over contacts of max(k_n, k_s) [M/T^2]."""
        if self.n == 0:
            raise InputError("contacts: the assembly has no contacts")
        return float(max(self.k_n.max(), self.k_s.max()))

    @classmethod
    def concatenate(cls, parts: list["ContactSet"]) -> "ContactSet":
        """The contacts of ``parts`` in order: one part is returned itself (not copied);
        optional coefficients that are all zero in every part stay untouched zeros (a
        copy of zeros is memory: 6 x 56 MB at 7e6 contacts)."""
        parts = [p for p in parts if p.n > 0] or parts[:1]
        if len(parts) == 1:
            return parts[0]
        return cls(*(None if _all_zero_optional(f, parts) else
                     np.concatenate([getattr(p, f) for p in parts]) for f in cls.FIELDS))


def _all_zero_optional(field: str, parts) -> bool:
    """Whether ``field`` is an optional coefficient (dashpots, rolling) that is zero in
    every one of ``parts`` (reading untouched zeros costs no memory)."""
    return field in OPTIONAL_FIELDS and not any(getattr(p, field).any() for p in parts)


def find_contacts(particles: Particles, k_n: float, k_s: float | None = None,
                  contact_tol: float = DEFAULT_CONTACT_TOL, walls=(),
                  periodic=None) -> ContactSet:
    """Contacts of an assembly from its geometry.

    Two particles touch when their centre distance is at most (r_i + r_j)(1 + tol); a
    particle touches a wall when its centre is within r (1 + tol) of the plane.
    ``periodic`` is a sequence of box lengths per axis (None for a non-periodic axis);
    periodic axes use the minimum image and the box [0, L). Stiffnesses are uniform
    (``k_s`` defaults to ``k_n``).
    """
    if k_s is None:
        k_s = k_n
    if not np.isfinite(contact_tol) or contact_tol < 0:
        raise InputError(f"contact-tol: must be a finite number >= 0, got {contact_tol!r}")
    x, r = particles.x, particles.r
    dim = particles.dim
    parts = [_pair_contacts(x, r, contact_tol, periodic)]
    for w_index, wall in enumerate(walls):
        if wall.dim != dim:
            raise InputError(f"wall {wall.name!r}: has {wall.dim} components, particles {dim}")
        d = wall.distance(x)
        touching = np.flatnonzero(d <= r * (1.0 + contact_tol))
        if np.any(d[touching] <= 0):
            k = touching[d[touching] <= 0][0]
            raise InputError(f"wall {wall.name!r}: particle {k} centre lies on or behind the wall")
        nrm = np.broadcast_to(-wall.normal, (len(touching), dim))
        parts.append(ContactSet(touching, np.full(len(touching), -1), nrm, d[touching],
                                np.zeros(len(touching)), 0.0, 0.0,
                                np.full(len(touching), w_index)))
    contacts = ContactSet.concatenate(parts)
    contacts.k_n[:] = k_n
    contacts.k_s[:] = k_s
    return contacts


#: assemblies from this many particles (not periodic) search their pairs with the
#: engine's threaded cell list (:func:`demstep.kernels.neighbors.build_pair_list`)
#: instead of scipy's k-d tree: 1,024,000 FCC spheres 0.21 s against 2.1-2.5 s for the
#: tree, its query and the sort (benchmarks/results/history-2026-12-04.md, 22nd
#: session); smaller ones keep the tree, so
#: that a small analysis does not wait for the search to compile on a fresh machine
COMPILED_SEARCH_MIN = 100_000


def _pair_contacts(x, r, tol, periodic, compiled_min: int | None = None) -> ContactSet:
    """Pairs within (r_i + r_j)(1 + ``tol``), sorted by (i, j), as a ContactSet without
    springs; by the compiled cell list from ``compiled_min`` particles
    (:data:`COMPILED_SEARCH_MIN` when None) unless ``periodic``."""
    from scipy.spatial import cKDTree  # imported here: the engine does not need it

    n, dim = x.shape
    cutoff = 2.0 * r.max() * (1.0 + tol)
    # the searches' reach, a hair beyond: a pair at (r_i + r_j)(1 + tol) whose distance
    # a search rounds up is still a candidate (the filter below decides, the same for
    # both searches: touching lattice neighbours at tol = 0 are kept)
    reach = 2.0 * r.max() * (1.0 + tol + 1e-6)
    if compiled_min is None:
        compiled_min = COMPILED_SEARCH_MIN
    pairs = None
    if periodic is not None:
        if len(periodic) != dim:
            raise InputError(f"periodic: expected {dim} box lengths, got {list(periodic)}")
        lo = x.min(axis=0)
        span = x.max(axis=0) - lo
        box = np.empty(dim)
        shifted = x - lo
        for k, length in enumerate(periodic):
            if length is None:
                box[k] = 4.0 * (span[k] + cutoff) + 1.0  # large: never wraps
            else:
                box[k] = float(length)
                if box[k] <= 2 * cutoff:
                    raise InputError(f"periodic: box length {length} along axis {k} is not "
                                     f"larger than two contact distances ({2 * cutoff:g})")
                shifted[:, k] = np.mod(x[:, k], box[k])
        tree = cKDTree(shifted, boxsize=box)
        pairs = tree.query_pairs(reach, output_type="ndarray")
        lengths = np.array([0.0 if v is None else float(v) for v in periodic])
    elif n >= compiled_min:
        x3 = np.zeros((n, 3))
        x3[:, :dim] = x
        # candidates |x_j - x_i| < r_i + r_j + skin: all within (r_i + r_j)(1 + tol),
        # with the same slack as the reach
        skin = 2.0 * float(r.max()) * (tol + 1e-6)
        i, j = build_pair_list(x3, r, skin, np.zeros(3), expected_pairs=3 * (dim - 1) * n)
        shifted, lengths = x, np.zeros(dim)
    else:
        tree = cKDTree(x)
        pairs = tree.query_pairs(reach, output_type="ndarray")
        shifted, lengths = x, np.zeros(dim)
    if pairs is not None:
        i, j = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)
        order = np.lexsort((j, i))
        i, j = i[order], j[order]
        x3 = np.zeros((n, 3))
        x3[:, :dim] = shifted
    box3 = np.zeros(3)
    box3[:dim] = lengths
    d, dist, _, arm_i, arm_j, _ = pair_geometry_arrays(x3, r, i, j, box3)
    keep = dist <= (r[i] + r[j]) * (1.0 + tol)
    if not keep.all():  # (a lattice keeps every candidate: no copies)
        i, j, d, dist = i[keep], j[keep], d[keep], dist[keep]
        arm_i, arm_j = arm_i[keep], arm_j[keep]
    if np.any(dist <= 0):
        k = int(np.flatnonzero(dist <= 0)[0])
        raise InputError(f"particles: particles {i[k]} and {j[k]} have the same centre")
    return ContactSet(i, j, d[:, :dim] / dist[:, None], arm_i, arm_j, 0.0, 0.0)


def contact_effective_radius(contacts: ContactSet, r: np.ndarray) -> np.ndarray:
    """R* (C,) [L]: r_i r_j / (r_i + r_j) for pairs, r_i at walls (radii ``r``)."""
    wall = contacts.j < 0
    r_i = r[contacts.i]
    r_j = r[np.where(wall, contacts.i, contacts.j)]
    return np.where(wall, r_i, r_i * r_j / (r_i + r_j))


def contact_rolling_inertia(contacts: ContactSet, r, m, inertia, moving) -> np.ndarray:
    """I* (C,) [M L^2] of every contact: 1 / (1/(I_i + m_i r_i^2) + 1/(I_j + m_j r_j^2))
    (:func:`demstep.contact.laws.rolling_inertia`) over the particles that move
    (``moving``); a wall or a fixed particle adds nothing, as in the engine's kernels."""
    i, j = contacts.i, contacts.j
    jj = np.maximum(j, 0)
    inertia = np.where(moving, inertia, 0.0)
    m = np.where(moving, m, 0.0)
    side_j = j >= 0
    return rolling_inertia(inertia[i], m[i], r[i], np.where(side_j, inertia[jj], 0.0),
                           np.where(side_j, m[jj], 0.0), r[jj])


def with_rolling(contacts: ContactSet, r, m, inertia, moving, params) -> ContactSet:
    """The contacts with their rolling and twisting springs k_r, k_w and viscous parts
    c_r, c_w from their k_n, k_s (tangent stiffnesses), by the law ``params`` (a
    law's Params tuple; :func:`demstep.contact.laws.rolling_coefficients`): R* from the radii
    ``r``, the equivalent rotational inertia from the masses ``m`` and ``inertia`` of
    the particles that move (``moving``: a fixed particle, like a wall, adds nothing;
    the engine's kernels use the same rule). Unchanged without rolling resistance."""
    if not params.has_rolling or contacts.n == 0:
        return contacts
    from dataclasses import replace

    k_r, k_w, c_r, c_w = rolling_coefficient_arrays(
        params, contacts.k_n, contacts.k_s, contact_effective_radius(contacts, r),
        contact_rolling_inertia(contacts, r, m, inertia, moving))
    return replace(contacts, k_r=k_r, k_w=k_w, c_r=c_r, c_w=c_w)
