"""Parallel bonds of a Simulation: adding them, their stiffness for the time step.

The bonds' state is the :class:`~demstep.state.Bonds` bundle (``sim.bonds``, a list kept
until they break, apart from the Verlet list); their forces are computed in the
compiled step (:mod:`demstep.kernels.bonds`), and they enter the time-step analysis as
contact elements (:func:`demstep.engine.analysis.bond_elements`). Here: :func:`add_bonds`
(from a gap or a list of pairs, checked) and :func:`bond_stiffness_max`.
"""

from __future__ import annotations

import numpy as np

from demstep.contact.bonds import bond_candidates, bond_springs
from demstep.contact.geometry import pair_geometry_arrays
from demstep.engine.analysis import pair_keys
from demstep.errors import InputError
from demstep.state import Bonds


def add_bonds(sim, bonds, pairs=None) -> int:
    """Bond particles of ``sim`` with parallel bonds of parameters ``bonds``
    (:class:`demstep.contact.bonds.ParallelBonds`): the given ``pairs`` (K, 2) of
    particle indices, or every pair whose surfaces are at most ``bonds.gap`` apart
    (touching and overlapping pairs included; minimum image across periodic axes;
    never two spheres of one clump; a pair listed twice is an error). Pairs already
    bonded by an intact bond are skipped. Returns the number of bonds added."""
    bonds.validate()
    n = len(sim.r)
    name = sim.particle_id
    if pairs is None:
        i, j = bond_candidates(sim.x, sim.r, bonds.gap, sim.periodic_len, sim.dim)
    else:
        pairs = np.asarray(pairs)
        if pairs.ndim != 2 or pairs.shape[1] != 2 or not np.issubdtype(pairs.dtype, np.integer):
            raise InputError(f"bonds: pairs must be an integer array (K, 2), got shape "
                             f"{pairs.shape} of {pairs.dtype}")
        bad = (pairs < 0) | (pairs >= n)
        if bad.any():
            raise InputError(f"bonds: particle index {pairs[bad][0]} outside 0..{n - 1}")
        if (pairs[:, 0] == pairs[:, 1]).any():
            k = int(np.flatnonzero(pairs[:, 0] == pairs[:, 1])[0])
            raise InputError(f"bonds: pair {k} bonds particle {name(pairs[k, 0])} to itself")
        i, j = np.minimum(pairs[:, 0], pairs[:, 1]), np.maximum(pairs[:, 0], pairs[:, 1])
        _, first, counts = np.unique(pair_keys(n, i, j), return_index=True,
                                     return_counts=True)
        if (counts > 1).any():
            k = int(first[np.flatnonzero(counts > 1)[0]])
            raise InputError(f"bonds: pair ({name(i[k])}, {name(j[k])}) is listed twice (in "
                             f"either order)")
        d, dist, delta, *_ = pair_geometry_arrays(sim.x, sim.r, i, j, sim.periodic_len)
        far = -delta > bonds.gap * (1 + 1e-12)
        if far.any():
            k = int(np.flatnonzero(far)[0])
            raise InputError(f"bonds: pair ({name(i[k])}, {name(j[k])}) is {-delta[k]:.6g} "
                             f"apart, beyond the gap {bonds.gap:g}")
    sb = sim.bodies.sphere_body
    keep = (sb[i] < 0) | (sb[i] != sb[j])
    old = sim.bonds
    intact = old.intact == 1
    keep &= ~np.isin(pair_keys(n, i, j), pair_keys(n, old.i[intact], old.j[intact]))
    i, j = i[keep], j[keep]
    radius = bonds.radius_multiplier * np.minimum(sim.r[i], sim.r[j])
    new = Bonds.make(i, j, radius, bonds.normal_stiffness, bonds.k_s, bonds.tensile_strength,
                     bonds.shear_strength)
    sim.bonds = Bonds(*(np.concatenate([getattr(old, f), getattr(new, f)])
                        for f in Bonds._fields))
    if len(i) and sim.timestep.mode != "fixed":
        sim.auto.certificate = None  # stiffer now: alpha and 'auto' choose the step anew
        sim.dt = None
    return len(i)


def bond_stiffness_max(sim) -> float:
    """The largest normal or shear stiffness k^b A [M/T^2] of an intact bond (0: none)."""
    bonds = sim.bonds
    on = bonds.intact == 1
    if not on.any():
        return 0.0
    kn, ks, _, _ = bond_springs(bonds.radius[on], bonds.k_n[on], bonds.k_s[on], sim.dim)
    return float(max(kn.max(), ks.max()))
