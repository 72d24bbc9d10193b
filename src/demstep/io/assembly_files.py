"""Assembly files: particle centres and radii (and optionally masses).

Formats (readers and writers live in :mod:`demstep.io.formats`):

* CSV with a header ``x,y,r`` (2D) or ``x,y,z,r`` (3D) and an optional ``m`` column;
* LIGGGHTS ``dump custom`` text files (the last snapshot);
* YADE text exports (``x y z r`` per line, ``#`` comments).

The format is chosen by extension (.csv; .liggghts, .dump, .lammpstrj; .txt, .yade,
.spheres) or, for other names, by content (a first line starting with ``ITEM:`` is a
LIGGGHTS dump, a comma makes CSV, anything else is read as YADE text).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from demstep.io.formats import read_csv as read_csv_particles, read_particle_file
from demstep.io.textfile import check_regular_file


@dataclass
class AssemblyData:
    """Columns read from a file: x (N, dim) [L], r (N,) [L], m (N,) [M] or None."""

    x: np.ndarray
    r: np.ndarray
    m: np.ndarray | None = None
    source: str = ""


def read_assembly(path, format: str = "auto") -> AssemblyData:
    """Read an assembly file; ``format`` 'auto' chooses by extension, then content."""
    path = check_regular_file(path)
    data = read_particle_file(path, format=format)
    return AssemblyData(data.x, data.r, data.m, data.source)


def read_csv(path) -> AssemblyData:
    """CSV assembly with header x,y[,z],r[,m] (any column order, extra columns ignored)."""
    data = read_csv_particles(path)
    return AssemblyData(data.x, data.r, data.m, data.source)
