"""Assembly files: particle centres and radii (and optionally masses).

CSV with a header ``x,y,r`` (2D) or ``x,y,z,r`` (3D) and an optional ``m`` column.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from demstep.errors import InputError


@dataclass
class AssemblyData:
    """Columns read from a file: x (N, dim) [L], r (N,) [L], m (N,) [M] or None."""

    x: np.ndarray
    r: np.ndarray
    m: np.ndarray | None = None
    source: str = ""


def read_assembly(path) -> AssemblyData:
    """Read an assembly file, choosing the format by extension (``.csv``)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return read_csv(path)
    raise InputError(f"{path}: unknown assembly format {suffix!r} (expected .csv)")


def _float(text, path, line, column):
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise InputError(f"{path}:{line}: column {column!r}: not a number: {text!r}") from None
    if not np.isfinite(value):
        raise InputError(f"{path}:{line}: column {column!r}: not finite: {text!r}")
    return value


def read_csv(path) -> AssemblyData:
    """CSV assembly with header x,y[,z],r[,m] (any column order, extra columns ignored)."""
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            if header is None:
                raise InputError(f"{path}: empty file")
            header = [h.strip().lower() for h in header]
            dim = 3 if "z" in header else 2
            needed = ["x", "y", "r"] if dim == 2 else ["x", "y", "z", "r"]
            missing = [c for c in needed if c not in header]
            if missing:
                raise InputError(f"{path}: missing column {missing[0]!r} (header must be "
                                 f"x,y,r or x,y,z,r, optional m; got {','.join(header)})")
            cols = needed + (["m"] if "m" in header else [])
            index = [header.index(c) for c in cols]
            rows, lines = [], []
            for line, row in enumerate(reader, start=2):
                if not row or all(not c.strip() for c in row):
                    continue
                if len(row) < len(header):
                    raise InputError(f"{path}:{line}: expected {len(header)} values, got {len(row)}")
                rows.append([_float(row[k], path, line, c) for k, c in zip(index, cols)])
                lines.append(line)
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    if not rows:
        raise InputError(f"{path}: no particles")
    data = np.array(rows)
    x, r = data[:, :dim], data[:, dim]
    bad = np.flatnonzero(r <= 0)
    if len(bad):
        raise InputError(f"{path}: column 'r': radius must be > 0, got {r[bad[0]]:g} "
                         f"(particle {bad[0]}, line {lines[bad[0]]})")
    m = None
    if "m" in cols:
        m = data[:, dim + 1]
        bad = np.flatnonzero(m <= 0)
        if len(bad):
            raise InputError(f"{path}: column 'm': mass must be > 0, got {m[bad[0]]:g} "
                             f"(particle {bad[0]}, line {lines[bad[0]]})")
    return AssemblyData(x, r, m, str(path))
