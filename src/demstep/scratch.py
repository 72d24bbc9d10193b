"""Scratch arrays kept between calls: memory the process has not touched yet costs a page
fault per page at its first write, and the kernel does not serve two threads' faults in
parallel. Measured on this project's machine: a neighbour build at 1e6 spheres spent
half its time so (53 -> 29 ms on two threads with its scratch kept), and the 'auto'
estimates of a settling run 0.16 of a 0.54 s solve writing fresh Lanczos rows.

One :class:`Workspace` is held by whoever calls again: the engine keeps one for its
time-step estimates (:mod:`demstep.timestep.eigen`) and one for its neighbour search
(:mod:`demstep.kernels.neighbors`).
"""

from __future__ import annotations

import math
import mmap

import numpy as np

#: a :class:`Workspace` without huge pages maps arrays of this many bytes or more itself
SMALL_PAGES_MIN = 1 << 22


class Workspace:
    """Named scratch arrays, uninitialised, kept from one call to the next.

    ``array(name, shape, dtype)`` reuses the memory of the last array of that name when
    its size matches (``grow``: when it is large enough; it then grows by
    :attr:`GROWTH` when it must, for arrays whose size changes from call to call;
    ``spare``: the array comes longer than asked along its last axis when there is
    room, for buffers that use all of it).

    ``huge_pages`` False: arrays of :data:`SMALL_PAGES_MIN` bytes or more are mapped
    with transparent huge pages refused (madvise MADV_NOHUGEPAGE; numpy asks for them
    on large arrays). In a running simulation, whose memory is fragmented, the kernel
    compacted memory to find each 2 MB page at the first write: 2 ms per MB, measured
    (a settling run of 1e5 spheres: its 'auto' estimates took 0.95 s against 0.67 s
    with small pages). A fresh process finds huge pages free and solves slightly
    faster with them (1.8 against 2.0 s, the exact step of a dense 1e5 packing), so
    one-off solves keep numpy's default."""

    GROWTH = 1.25

    def __init__(self, huge_pages: bool = True):
        self._flat: dict[str, np.ndarray] = {}
        self.huge_pages = huge_pages

    def array(self, name: str, shape: tuple, dtype=np.float64, grow: bool = False,
              spare: bool = False) -> np.ndarray:
        """The array ``name`` of ``shape`` and ``dtype``, uninitialised."""
        shape = tuple(int(s) for s in shape)
        size = math.prod(shape)
        flat = self._flat.get(name)
        if flat is None or flat.size < size or flat.dtype != dtype or (
                not grow and flat.size != size):
            self._flat.pop(name, None)  # (its memory goes before the new one comes)
            flat = self._flat[name] = self._new(
                int(self.GROWTH * size) + 64 if grow else size, np.dtype(dtype))
        if spare:
            lead = math.prod(shape[:-1])
            last = flat.size // max(lead, 1)
            return flat[:lead * last].reshape(shape[:-1] + (last,))
        return flat[:size].reshape(shape)

    def _new(self, size: int, dtype: np.dtype) -> np.ndarray:
        nbytes = size * dtype.itemsize
        madvise = getattr(mmap, "MADV_NOHUGEPAGE", None)
        if self.huge_pages or nbytes < SMALL_PAGES_MIN or madvise is None:
            return np.empty(size, dtype=dtype)
        buf = mmap.mmap(-1, nbytes)
        buf.madvise(madvise)
        return np.frombuffer(buf, dtype=dtype)

    def release(self, *names: str):
        """Forget the arrays ``names`` (their memory goes once nothing else holds them)."""
        for name in names:
            self._flat.pop(name, None)
