"""The seam between the engine and its compiled kernels: one interface, one module.

:class:`demstep.engine.Simulation` calls its kernels only through a backend object, so
that another implementation (a GPU one, say) can provide the same operations on the
bundles of :mod:`demstep.state` without touching the engine. A backend offers:

``build_pair_list(x, r, skin, periodic_len, expected_pairs, work)`` -> (i, j)
    the Verlet pairs within r_i + r_j + skin (minimum image), sorted by i; ``work``:
    the search's scratch kept by the caller between builds (None: its own);
``build_wall_list(x, r, point, normal, skin, expected_pairs, work)`` -> (p, wall)
    the particle-wall candidates within r + skin (``work`` as above);
``transfer_history(old_i, old_j, new_i, new_j, *history)`` -> history on the new list;
``pair_chunks(i, j, n, n_chunks)`` -> (chunks, spans): the work split of the pair loop;
``copy_positions(x, out)``: out[:] = x, the positions (N, 3) at a build of the lists;
``advance(n_steps, controls, spheres, bodies, pairs, bonds, walls, box, ledger, params)``
    -> (steps done, stop reason): whole steps in the documented order;
``pair_contact_forces(x, r, i, j, periodic_len, params, shear, dashpot, force, normal)``
    -> mask of touching pairs, filling their forces and normals (output only).

The ``cpu`` backend is the numba kernels of :mod:`demstep.kernels`.
"""

from __future__ import annotations

from demstep.errors import InputError
from demstep.kernels import dem, integration, neighbors


class CPUBackend:
    """The numba kernels (threaded with prange, or serial), compiled and cached."""

    name = "cpu"

    def __init__(self):
        self.build_pair_list = neighbors.build_pair_list
        self.build_wall_list = neighbors.build_wall_list
        self.transfer_history = neighbors.transfer_history
        self.pair_chunks = dem.pair_chunks
        self.copy_positions = integration.copy_positions
        self.advance = dem.advance
        self.pair_contact_forces = dem.pair_contact_forces


BACKENDS = {"cpu": CPUBackend}
_instances: dict = {}


def get_backend(name: str = "cpu"):
    """The backend called ``name`` (one instance per process)."""
    if name not in BACKENDS:
        raise InputError(f"backend: must be one of {', '.join(BACKENDS)}, got {name!r}")
    if name not in _instances:
        _instances[name] = BACKENDS[name]()
    return _instances[name]
