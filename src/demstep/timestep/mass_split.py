"""Lumped element masses: each particle's mass and inertia split among its contacts.

Paper eqs. 16-19 ("uniform") and Figure 7 ("zoned"). The split is a partition: the
shares of a particle sum to its mass and inertia, which is what makes the element
eigenvalues an upper bound on the assembly's (Rayleigh, eq. 4).

Shares are returned as reciprocals (1/m', 1/I'), so fixed particles and the far side
of wall contacts (infinite mass) are exactly 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from demstep.timestep.contacts import ContactSet
from demstep.errors import InputError
from demstep.particles import Particles

MASS_SPLITS = ("uniform", "zoned")

#: height of the two cutting planes of the zoned split, as a fraction of the radius:
#: z = +/- r sin(22.5 deg). The paper gives its Figure 7 as a drawing only, without the
#: planes' heights; this choice reproduces its zoned minima (0.348 and 0.221 sqrt(m/K),
#: rhombic; about 0.37 for FCC without rotation). A reconstruction, not the paper's
#: statement: docs/time-step-elements.md, "Where the zoned split's cutting planes are".
ZONE_CUT = np.sin(np.radians(22.5))


def cap_fraction(cut: float = ZONE_CUT) -> float:
    """Volume fraction of the spherical cap above the plane z = cut * r."""
    return (1.0 - cut) ** 2 * (2.0 + cut) / 4.0


@dataclass
class ElementMass:
    """Reciprocal lumped masses (C,) [1/M] and inertias (C,) [1/(M L^2)] of both ends of
    each contact element; zero for walls and fixed particles."""

    inv_m_i: np.ndarray
    inv_m_j: np.ndarray
    inv_I_i: np.ndarray
    inv_I_j: np.ndarray


def element_mass(particles: Particles, contacts: ContactSet, split: str = "uniform",
                 axis: int = -1, counts: np.ndarray | None = None) -> ElementMass:
    """Split each particle's mass and inertia among its contacts.

    ``uniform`` (eqs. 16-19): m_i / nc_i and I_i / nc_i on each contact.

    ``zoned`` (Figure 7, 3D only): the sphere is cut by two planes normal to ``axis``
    (default z, the loading axis) at +/- r sin(22.5 deg). A contact belongs to the
    upper, central or lower row by the height of its contact point. The upper cap's
    share goes equally to the upper-row contacts; the upper half of the central zone
    equally to the upper- and central-row contacts; the lower half and the lower cap
    likewise with the lower row. (The paper says the central zone is shared by the
    upper and central rows, 8 contacts in FCC, 9 in rhombic; splitting it in halves
    keeps the partition symmetric and gives the central row exactly the paper's share.)
    A zone with no contact to take it is shared by all the particle's contacts.

    ``counts`` (uniform split): the particles' numbers of contacts when ``contacts`` is
    a part of the assembly's contacts (the shares are of all of them).
    """
    if split not in MASS_SPLITS:
        raise InputError(f"mass-split: must be one of {', '.join(MASS_SPLITS)}, got {split!r}")
    n = particles.n
    pp = contacts.j >= 0
    ends = np.concatenate([contacts.i, contacts.j[pp]])
    if split == "uniform":
        if counts is None:
            counts = contacts.count_per_particle(n)
        share = 1.0 / counts[ends]
    else:
        share = _zoned_share(particles, contacts, ends, pp, axis)
    inv_m = 1.0 / (particles.m[ends] * share)
    inv_I = 1.0 / (particles.inertia[ends] * share)
    free = ~particles.fixed[ends]
    inv_m, inv_I = inv_m * free, inv_I * free
    c = contacts.n
    inv_m_j = np.zeros(c)
    inv_I_j = np.zeros(c)
    inv_m_j[pp] = inv_m[c:]
    inv_I_j[pp] = inv_I[c:]
    return ElementMass(inv_m[:c].copy(), inv_m_j, inv_I[:c].copy(), inv_I_j)


def _zoned_share(particles, contacts, ends, pp, axis):
    if particles.dim != 3:
        raise InputError("mass-split: 'zoned' is defined for 3D spheres only (paper Fig. 7), "
                         f"got dim={particles.dim}")
    n = particles.n
    height = np.concatenate([contacts.arm_i * contacts.normal[:, axis],
                             -contacts.arm_j[pp] * contacts.normal[pp, axis]])
    cut = ZONE_CUT * particles.r[ends]
    row = np.where(height > cut, 0, np.where(height < -cut, 2, 1))  # upper, central, lower
    counts = np.stack([np.bincount(ends[row == k], minlength=n) for k in range(3)], axis=1)
    total = counts.sum(axis=1)
    f = cap_fraction()
    half_central = 0.5 * (1.0 - 2.0 * f)

    def portion(mass, receivers):
        """(per-particle share to each receiving contact, share to every contact if none)"""
        nrec = counts[:, receivers].sum(axis=1)
        to_receiver = np.where(nrec > 0, mass / np.maximum(nrec, 1), 0.0)
        to_all = np.where(nrec > 0, 0.0, mass / np.maximum(total, 1))
        return to_receiver, to_all

    up_cap, up_cap_all = portion(f, [0])
    low_cap, low_cap_all = portion(f, [2])
    up_half, up_half_all = portion(half_central, [0, 1])
    low_half, low_half_all = portion(half_central, [1, 2])
    everyone = up_cap_all + low_cap_all + up_half_all + low_half_all
    table = np.stack([up_cap + up_half, up_half + low_half, low_cap + low_half], axis=1)
    return table[ends, row] + everyone[ends]
