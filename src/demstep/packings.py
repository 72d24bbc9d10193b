"""Regular lattices of equal disks/spheres and random polydisperse assemblies.

Each lattice is described by an orthorhombic cell (its conventional cell, possibly
with several particles) so that a finite block, a periodic supercell and the
Bloch-wave analysis all use one description. In every lattice nearest neighbours
touch exactly (centre distance 2r).

========  ===  ==============================================================
name      dim  description (coordination number)
========  ===  ==============================================================
square    2    square array (4)
hex       2    hexagonal array, densest disks (6)
sc        3    simple cubic (6)
bcc       3    body-centred cubic (8)
fcc       3    face-centred cubic with square layers normal to z, in-layer
               neighbours along x and y (12); the layout of Thornton (1979)
rhombic   3    rhombic / hexagonal close packing, hexagonal layers normal to
               z stacked ABAB (12)
========  ===  ==============================================================
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from demstep.errors import InputError

SQRT2, SQRT3 = np.sqrt(2.0), np.sqrt(3.0)


@dataclass(frozen=True)
class Lattice:
    """A lattice of equal particles of ``radius`` [L]: orthorhombic ``cell`` lengths
    (dim,) and ``basis`` positions (nb, dim) inside the cell."""

    name: str
    dim: int
    radius: float
    cell: np.ndarray
    basis: np.ndarray
    coordination: int

    def block(self, size: int) -> np.ndarray:
        """Positions (size^dim * nb, dim) of a finite block of size^dim cells."""
        size = _check_size(size)
        grid = np.stack(np.meshgrid(*[np.arange(size)] * self.dim, indexing="ij"), -1)
        origins = grid.reshape(-1, self.dim) * self.cell
        return (origins[:, None, :] + self.basis[None, :, :]).reshape(-1, self.dim)

    def supercell(self, size: int) -> tuple[np.ndarray, np.ndarray]:
        """Positions of a periodic supercell of size^dim cells and its box lengths."""
        return self.block(size), self.cell * _check_size(size)


LATTICE_NAMES = ("square", "hex", "sc", "bcc", "fcc", "rhombic")
LATTICE_DIM = {"square": 2, "hex": 2, "sc": 3, "bcc": 3, "fcc": 3, "rhombic": 3}


def lattice(name: str, radius: float = 1.0) -> Lattice:
    """The lattice ``name`` (one of :data:`LATTICE_NAMES`) of particles of ``radius``."""
    r = float(radius)
    if not np.isfinite(r) or r <= 0:
        raise InputError(f"radius: must be a finite positive number, got {radius!r}")
    d = 2.0 * r  # centre distance of touching neighbours
    if name == "square":
        cell, basis, nc = [d, d], [[0, 0]], 4
    elif name == "hex":
        cell, basis, nc = [d, SQRT3 * d], [[0, 0], [r, SQRT3 * r]], 6
    elif name == "sc":
        cell, basis, nc = [d, d, d], [[0, 0, 0]], 6
    elif name == "bcc":
        a = 2.0 * d / SQRT3
        cell, basis, nc = [a, a, a], [[0, 0, 0], [a / 2, a / 2, a / 2]], 8
    elif name == "fcc":
        layer = SQRT2 * r  # spacing of the square layers
        cell, basis, nc = [d, d, 2 * layer], [[0, 0, 0], [r, r, layer]], 12
    elif name == "rhombic":
        layer = d * np.sqrt(2.0 / 3.0)  # spacing of the hexagonal layers
        cell = [d, SQRT3 * d, 2 * layer]
        basis = [[0, 0, 0], [r, SQRT3 * r, 0],
                 [r, r / SQRT3, layer], [0, r / SQRT3 + SQRT3 * r, layer]]
        nc = 12
    else:
        raise InputError(f"lattice: unknown lattice {name!r}; choose one of "
                         f"{', '.join(LATTICE_NAMES)}")
    return Lattice(name, LATTICE_DIM[name], r, np.array(cell, float), np.array(basis, float), nc)


def _check_size(size) -> int:
    try:
        s = int(size)
    except (TypeError, ValueError):
        raise InputError(f"size: expected a positive integer, got {size!r}") from None
    if s < 1 or s != size:
        raise InputError(f"size: expected a positive integer, got {size!r}")
    return s


def jittered_polydisperse(n_target: int, dim: int, seed: int = 0, jitter: float = 0.05,
                          spread: float = 0.1, overlap: float = 0.02):
    """A random polydisperse assembly in contact, cheap to make at any size.

    Particles sit on a jittered simple cubic/square grid of spacing 1 (jitter as a
    fraction of the spacing); radii are 0.5 (1 + overlap) (1 + U(-spread, spread)) so
    that neighbours overlap by various amounts and some lose contact. Returns
    positions (n, dim) and radii (n,), with n the nearest cube/square to ``n_target``.
    """
    rng = np.random.default_rng(seed)
    side = max(2, int(round(n_target ** (1.0 / dim))))
    grid = np.stack(np.meshgrid(*[np.arange(side, dtype=float)] * dim, indexing="ij"), -1)
    x = grid.reshape(-1, dim) + rng.uniform(-jitter, jitter, (side**dim, dim))
    r = 0.5 * (1.0 + overlap) * (1.0 + rng.uniform(-spread, spread, side**dim))
    return x, r


#: assemblies from this many particles on are put in spatial order when read from a
#: file for a run (:func:`spatial_order`; below, the order is kept: nothing to gain)
SPATIAL_ORDER_MIN = 1000


def spatial_order(x: np.ndarray, cell: float) -> np.ndarray:
    """A permutation of the particles at ``x`` (N, dim) [L] that puts neighbours in space
    near each other in memory: by cubic cells of side ``cell`` [L] (e.g. the neighbour
    search's, 2 r_max + skin), in rows along x, then y, then z (x fastest), stable
    within a cell.

    The engine keeps the order it is given, and every pair's data is gathered by
    particle index: on a packing in random order (another code's file, particles
    numbered as they were inserted) a step of the dense 1e5-sphere benchmark took 2.5x
    as long as in lattice order (benchmarks/results/history-2026-11-30.md, fourth
    session). Rows of cells put a particle's
    neighbours at three steady offsets (along x, one row, one layer), which the pair
    loop reads as three forward streams: measured faster than a Morton (Z-curve) order
    of the same cells (dense 6.2 against 5.2 M particle-steps/s, settling 17.7 against
    15.8 M). LAMMPS and LIGGGHTS sort their atoms by bins likewise (``atom_modify
    sort``)."""
    x = np.asarray(x, dtype=np.float64)
    if len(x) == 0:
        return np.zeros(0, dtype=np.int64)
    if not (np.isfinite(cell) and cell > 0):
        raise InputError(f"cell: must be finite and > 0, got {cell!r}")
    cells = np.floor((x - x.min(axis=0)) / cell)
    return np.lexsort(tuple(cells[:, k] for k in range(x.shape[1])))  # last key first


def inverse_order(order) -> np.ndarray:
    """The new index of each old particle of a renumbering in which new particle k is
    old particle ``order[k]`` (a permutation of 0..N-1)."""
    order = np.asarray(order)
    inverse = np.empty(len(order), dtype=np.int64)
    inverse[order] = np.arange(len(order))
    return inverse
