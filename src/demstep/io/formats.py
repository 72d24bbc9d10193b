"""Other codes' particle files: readers and writers.

Three text formats carry particle centres [L] and radii [L]:

* **CSV** (demstep's own): header ``x,y,r`` (2D) or ``x,y,z,r`` (3D), optional ``m``
  column (mass [M]), ``type`` (material, >= 1) and ``body`` (the clump a sphere belongs
  to, -1: a free sphere); any column order, extra columns ignored.
* **LIGGGHTS / LAMMPS** ``dump custom`` text files: repeated snapshots of::

      ITEM: TIMESTEP
      1000
      ITEM: NUMBER OF ATOMS
      150
      ITEM: BOX BOUNDS pp pp ff
      0.0 200.0
      0.0 200.0
      0.0 400.0
      ITEM: ATOMS id type x y z radius vx vy vz mass

  Positions from ``x y z`` (or unwrapped ``xu yu zu``, or scaled ``xs ys zs`` mapped
  through the box bounds), the radius from ``radius`` (or ``diameter``), optional
  ``mass``, velocities ``vx vy vz``, angular velocities ``omegax omegay omegaz`` and
  the clump of each sphere ``body`` (or LAMMPS' molecule id ``mol``, 0: none).
  Rows are sorted by ``id``. A dump without a ``z`` column is read as 2D. A column
  read twice is refused.
* **LAMMPS data files** (``write_data``) of ``atom_style sphere``: :func:`read_lammps_data`.
* **YADE** text exports (``yade.export.text``, read by ``ymport.text``): one particle
  per line, ``x y z r`` separated by blanks, further columns (e.g. a material id)
  ignored, ``#`` starts a comment. A ``#format x_y_z_r...`` header names the columns
  (x, y, z, r, matId and, last, attrs; each once). demstep also writes and reads 2D
  files as ``x y r`` (header ``#format x_y_r``); YADE itself is 3D only.

Numbers are finite and within the magnitudes of :mod:`demstep.errors`, written without
underscores (Python would read ``1_0`` as 10); integer columns (ids, types, bodies)
below 2^53 in magnitude, where float64 stops resolving integers. Every reader raises
:class:`~demstep.errors.InputError` with one line naming the file, the line and the
field at fault. Files are checked before they are parsed and then read line by line
(:mod:`demstep.io.textfile`): a file that is not a regular file or whose first block
is not text is refused at once, a line of NUL bytes or longer than
:data:`~demstep.io.textfile.MAX_LINE` characters where it starts.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from demstep.io.atomic import naming, write_text_atomic
from demstep.io.textfile import csv_rows, open_text
from demstep.errors import MAX_MAGNITUDE, MIN_MAGNITUDE, InputError, magnitude_problem

#: format names understood by :func:`read_particle_file` / :func:`write_particle_file`
FORMATS = ("csv", "liggghts", "yade", "lammps-data")

_EXTENSIONS = {
    ".csv": "csv",
    ".liggghts": "liggghts", ".dump": "liggghts", ".lammpstrj": "liggghts",
    ".txt": "yade", ".yade": "yade", ".spheres": "yade",
}


@dataclass
class ParticleData:
    """Particles read from a file: centres ``x`` (N, dim) [L], radii ``r`` (N,) [L],
    masses ``m`` (N,) [M] or None, velocities ``v`` (N, dim) [L/T] or None, angular
    velocities ``w`` (N, 3) [1/T] or None; LIGGGHTS ids/types, the dump's time step
    number and box bounds (dim, 2) [L] when the file has them, and which box axes are
    periodic (``periodic`` (dim,) bool: the dump's ``pp`` boundary flags)."""

    x: np.ndarray
    r: np.ndarray
    m: np.ndarray | None = None
    v: np.ndarray | None = None
    w: np.ndarray | None = None
    ids: np.ndarray | None = None
    types: np.ndarray | None = None
    timestep: int | None = None
    box: np.ndarray | None = None
    periodic: np.ndarray | None = None
    source: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def dim(self) -> int:
        return self.x.shape[1]


# --------------------------------------------------------------------- helpers

#: the columns whose values must lie within the magnitudes of
#: :func:`demstep.errors.magnitude_problem` at both ends (others: only below its largest)
SIZE_COLUMNS = ("r", "radius", "diameter", "m", "mass")


def _number(text: str, path, line: int, column: str) -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise InputError(f"{path}:{line}: column {column!r}: not a number: {text!r}") from None
    if "_" in text:  # (Python reads 1_0 as 10; no other code writes it)
        raise InputError(f"{path}:{line}: column {column!r}: not a number (an underscore): "
                         f"{text!r}")
    if not math.isfinite(value):
        raise InputError(f"{path}:{line}: column {column!r}: not finite: {text!r}")
    # every value at most MAX_MAGNITUDE; sizes and masses also at least MIN_MAGNITUDE (a
    # velocity of 1e-150 in a dump of a packing at rest is harmless, a radius is not).
    # Called per value of a file: compared inline, the message built only on failure
    size = abs(value)
    if size > MAX_MAGNITUDE or (0.0 < size < MIN_MAGNITUDE and column in SIZE_COLUMNS):
        raise InputError(f"{path}:{line}: column {column!r}: {magnitude_problem(value)}, "
                         f"got {text!r}")
    return value


def _integer(text: str, path, line: int, column: str) -> int:
    try:
        value = int(text)
    except (TypeError, ValueError):
        raise InputError(f"{path}:{line}: {column}: not an integer: {text!r}") from None
    if "_" in text:  # (Python reads 1_0 as 10)
        raise InputError(f"{path}:{line}: {column}: not an integer (an underscore): {text!r}")
    return value


def _check_positive(values, path, lines, column: str, what: str):
    bad = np.flatnonzero(~(values > 0))
    if len(bad):
        k = bad[0]
        raise InputError(f"{path}:{lines[k]}: column {column!r}: {what} must be > 0, "
                         f"got {values[k]:g}")


def _write_text_atomically(path, text: str) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(path, text)


def _columns(x, r) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(x, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64).reshape(-1)
    if x.ndim != 2 or x.shape[1] not in (2, 3) or x.shape[0] != r.shape[0]:
        raise InputError(f"x: expected an (N, 2) or (N, 3) array matching {r.shape[0]} radii, "
                         f"got shape {x.shape}")
    return x, r


# ------------------------------------------------------------------------ CSV

#: column names a CSV may use for demstep's own (as LIGGGHTS and spreadsheets name them)
CSV_ALIASES = {"radius": "r", "mass": "m"}
#: the optional columns a CSV's particles take (the others are ignored)
CSV_OPTIONAL = ("m", "type", "body")


def read_csv(path) -> ParticleData:
    """CSV with header x,y[,z],r[,m][,type][,body] (``radius`` and ``mass`` taken for r
    and m; any column order; other columns ignored, a column given twice refused)."""
    path = Path(path)
    with open_text(path, encoding="utf-8-sig", newline="") as fh:  # -sig: spreadsheet BOM
        reader = csv_rows(fh)
        header = next(reader, None)
        if header is None:
            raise InputError(f"{path}: empty file")
        header = [CSV_ALIASES.get(h.strip().lower(), h.strip().lower()) for h in header]
        twice = [c for c in ("x", "y", "z", "r") + CSV_OPTIONAL if header.count(c) > 1]
        if twice:
            raise InputError(f"{path}:1: column {twice[0]!r} given twice (radius/mass "
                             f"count as r/m; got {','.join(header)})")
        dim = 3 if "z" in header else 2
        needed = ["x", "y", "r"] if dim == 2 else ["x", "y", "z", "r"]
        missing = [c for c in needed if c not in header]
        if missing:
            raise InputError(f"{path}:1: missing column {missing[0]!r} (header must be "
                             f"x,y,r or x,y,z,r, optional m; got {','.join(header)})")
        cols = needed + [c for c in CSV_OPTIONAL if c in header]
        index = [header.index(c) for c in cols]
        rows, lines = [], []
        texts = {c: [] for c in ("type", "body") if c in cols}  # (for messages)
        text_index = {c: header.index(c) for c in texts}
        for line, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            while len(row) > len(header) and not row[-1].strip():
                row = row[:-1]  # (trailing empty cells of a spreadsheet's export)
            if len(row) != len(header):
                raise InputError(f"{path}:{line}: expected {len(header)} values, got {len(row)}")
            rows.append([_number(row[k], path, line, c) for k, c in zip(index, cols)])
            lines.append(line)
            for c, kept in texts.items():
                kept.append(row[text_index[c]].strip())
    if not rows:
        raise InputError(f"{path}: no particles")
    data = np.array(rows)
    x, r = data[:, :dim], data[:, dim]
    _check_positive(r, path, lines, "r", "radius")
    m = None
    if "m" in cols:
        m = data[:, cols.index("m")]
        _check_positive(m, path, lines, "m", "mass")
    types = _integer_column(data, cols, "type", path, lines, 1, texts.get("type"))
    out = ParticleData(np.ascontiguousarray(x), r.copy(), m, types=types, source=str(path))
    body = _integer_column(data, cols, "body", path, lines, -1, texts.get("body"))
    if body is not None:
        out.extra["body"] = body
    return out


def read_bond_csv(path) -> np.ndarray:
    """Bond list: CSV with header i,j (0-based particle indices; other named columns
    ignored, every row as many values as the header); returns pairs (K, 2)."""
    path = Path(path)
    with open_text(path, encoding="utf-8-sig", newline="") as fh:
        reader = csv_rows(fh)
        header = [h.strip().lower() for h in (next(reader, None) or [])]
        missing = [c for c in ("i", "j") if c not in header]
        if missing:
            raise InputError(f"{path}:1: missing column {missing[0]!r} (header must name "
                             f"i and j; got {','.join(header) or 'nothing'})")
        twice = [c for c in ("i", "j") if header.count(c) > 1]
        if twice:
            raise InputError(f"{path}:1: column {twice[0]!r} given twice (got "
                             f"{','.join(header)})")
        ci, cj = header.index("i"), header.index("j")
        pairs = []
        for line, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            while len(row) > len(header) and not row[-1].strip():
                row = row[:-1]  # (trailing empty cells of a spreadsheet's export)
            if len(row) != len(header):
                raise InputError(f"{path}:{line}: expected {len(header)} values, got {len(row)}")
            pairs.append((_integer(row[ci].strip(), path, line, "column 'i'"),
                          _integer(row[cj].strip(), path, line, "column 'j'")))
    if not pairs:
        raise InputError(f"{path}: no bonds")
    return np.array(pairs, dtype=np.int64)


def _integer_column(data, cols, name, path, lines, minimum, texts=None):
    """An optional integer column (``type``: >= 1; ``body``: the clump of each sphere,
    -1 for a free sphere) or None."""
    if name not in cols:
        return None
    return _check_integers(data[:, cols.index(name)], name, path, lines, minimum, texts)


#: integer columns (ids, types, bodies) must lie below this in magnitude: float64, which
#: the readers parse every column into, resolves every integer up to it (2^53), and
#: 2^53 + 1 reads as 2^53 (two ids then look alike)
MAX_EXACT_INTEGER = 2**53


def _check_integers(values, name, path, lines, minimum=None, texts=None) -> np.ndarray:
    """``values`` of the column ``name`` (read from ``lines`` of ``path``) as int64 when
    each is an integer (>= ``minimum`` when given) below 2^53 in magnitude (so that the
    float64 it was read into holds it exactly); else an InputError naming the line, the
    column and the value (``texts[k]``: the text of row k, when given)."""
    huge = ~(np.abs(values) < MAX_EXACT_INTEGER)
    bad = huge | (values != np.round(values))
    if minimum is not None:
        bad |= values < minimum
    bad = np.flatnonzero(bad)
    if len(bad):
        k = bad[0]
        need = "an integer" if minimum is None else f"an integer >= {minimum}"
        if huge[k]:
            need += (f" below 2^53 = {MAX_EXACT_INTEGER} in magnitude (float64 resolves no "
                     f"larger integers)")
        got = texts[k] if texts is not None else repr(float(values[k]))
        raise InputError(f"{path}:{lines[k]}: column {name!r}: expected {need}, got {got}")
    return values.astype(np.int64)


def write_csv(path, x, r, m=None, body=None) -> Path:
    """Write particles as CSV (header x,y,r or x,y,z,r, plus m and body (clump ids) if
    given), atomically."""
    x, r = _columns(x, r)
    names = ["x", "y", "z"][: x.shape[1]] + ["r"]
    cols = [x, r[:, None]]
    if m is not None:
        names.append("m")
        cols.append(np.asarray(m, dtype=np.float64).reshape(-1, 1))
    data = np.hstack(cols)
    lines = [",".join(names + (["body"] if body is not None else []))]
    bodies = [""] * len(data) if body is None else [f",{int(b)}" for b in body]
    lines += [",".join(repr(float(v)) for v in row) + tail for row, tail in zip(data, bodies)]
    return _write_text_atomically(path, "\n".join(lines) + "\n")


# ------------------------------------------------------------------- LIGGGHTS

@dataclass
class _Snapshot:
    timestep: int
    box: np.ndarray
    periodic: np.ndarray  # (3,) bool: 'pp' flags
    columns: list[str]
    rows: list[str] | None  # (None: not kept, a snapshot not asked for)
    first_line: int  # line number of the first atom row


class _Lines:
    """The lines of a text file one at a time, without their line ends: ``next()``
    gives the next one or None at the end; ``number`` is the number of the last line
    read (at the end: the number of lines)."""

    def __init__(self, fh):
        self._fh = fh
        self.number = 0

    def next(self) -> str | None:
        text = next(self._fh, None)
        if text is None:
            return None
        self.number += 1
        return text.rstrip("\r\n")


def _liggghts_snapshots(path, snapshot: int | None = None,
                        timestep: int | None = None) -> list[_Snapshot]:
    """Every snapshot of a dump, read as a stream: the atom rows are kept only for the
    snapshot asked for (by position ``snapshot`` (negative: from the end) or by
    ``timestep``, the last snapshot at it); neither: for none."""
    path = Path(path)
    snaps: list[_Snapshot] = []

    def expect(text: str | None, number: int, item: str) -> str:
        if text is None:
            raise InputError(f"{path}:{number}: expected 'ITEM: {item}', got end of file")
        text = text.strip()
        if not text.upper().startswith(f"ITEM: {item}"):
            raise InputError(f"{path}:{number}: expected 'ITEM: {item}', got {text[:40]!r}")
        return text

    def keep(index: int, step: int) -> bool:
        if timestep is not None:
            return step == timestep
        return snapshot is not None and (snapshot < 0 or index == snapshot)

    with open_text(path) as fh:
        lines = _Lines(fh)
        while True:
            text = lines.next()
            while text is not None and not text.strip():
                text = lines.next()
            if text is None:
                break
            k = lines.number  # (the line of ITEM: TIMESTEP)
            expect(text, k, "TIMESTEP")
            value = lines.next()
            if value is None:
                raise InputError(f"{path}:{k + 1}: TIMESTEP: missing value")
            step = _integer(value.strip(), path, k + 1, "TIMESTEP")
            expect(lines.next(), k + 2, "NUMBER OF ATOMS")
            value = lines.next()
            if value is None:
                raise InputError(f"{path}:{k + 3}: NUMBER OF ATOMS: missing value")
            n_atoms = _integer(value.strip(), path, k + 3, "NUMBER OF ATOMS")
            if n_atoms < 0:
                raise InputError(f"{path}:{k + 3}: NUMBER OF ATOMS: must be >= 0, got {n_atoms}")
            bounds = expect(lines.next(), k + 4, "BOX BOUNDS").split()[3:]
            if bounds[:3] == ["xy", "xz", "yz"]:
                raise InputError(f"{path}:{k + 4}: BOX BOUNDS: a triclinic box "
                                 f"({' '.join(bounds)}) is not supported; write the dump from "
                                 f"an orthogonal box")
            if 0 < len(bounds) < 3:
                raise InputError(f"{path}:{k + 4}: BOX BOUNDS: expected a boundary flag for "
                                 f"each of x, y and z, got {' '.join(bounds)!r}")
            flags = bounds[:3] if bounds else ["ff", "ff", "ff"]
            for a, flag in enumerate(flags):
                if len(flag) != 2 or any(f not in "pfsm" for f in flag) \
                        or (("p" in flag) and flag != "pp"):
                    raise InputError(f"{path}:{k + 4}: BOX BOUNDS: boundary flag of "
                                     f"{'xyz'[a]} must be pp, or two of f, s, m, got {flag!r}")
            periodic = np.array([flag == "pp" for flag in flags])
            box = np.zeros((3, 2))
            for a in range(3):
                number = k + 5 + a
                text = lines.next()
                if text is None:
                    raise InputError(f"{path}:{number}: BOX BOUNDS: expected 3 lines of bounds")
                parts = text.split()
                if len(parts) < 2:
                    raise InputError(f"{path}:{number}: BOX BOUNDS: expected 'lo hi', got "
                                     f"{text.strip()!r}")
                box[a] = [_number(parts[0], path, number, f"box {'xyz'[a]}lo"),
                          _number(parts[1], path, number, f"box {'xyz'[a]}hi")]
                if not box[a, 1] > box[a, 0]:
                    raise InputError(f"{path}:{number}: BOX BOUNDS: {'xyz'[a]}hi must exceed "
                                     f"{'xyz'[a]}lo, got {parts[0]} {parts[1]}")
            header = expect(lines.next(), k + 8, "ATOMS")
            columns = header.split()[2:]
            if not columns:
                raise InputError(f"{path}:{k + 8}: ITEM: ATOMS: no column names")
            rows: list[str] | None = [] if keep(len(snaps), step) else None
            for count in range(n_atoms):
                text = lines.next()
                if text is None:
                    raise InputError(f"{path}:{lines.number}: expected {n_atoms} atom rows "
                                     f"after line {k + 8}, the file ends after {count}")
                if rows is not None:
                    rows.append(text)
            if rows is not None:
                # (only the snapshot asked for keeps its rows: the last one at the
                # timestep, the |snapshot| last ones for a negative position)
                kept = [s for s in snaps if s.rows is not None]
                if timestep is not None:
                    drop = kept
                elif snapshot is not None and snapshot < 0:
                    drop = kept[:max(0, len(kept) + 1 + snapshot)]
                else:
                    drop = []
                for s in drop:
                    s.rows = None
            snaps.append(_Snapshot(step, box, periodic, [c.lower() for c in columns], rows,
                                   k + 9))
    if not snaps:
        raise InputError(f"{path}: no snapshot (expected 'ITEM: TIMESTEP')")
    return snaps


def liggghts_timesteps(path) -> list[int]:
    """The TIMESTEP of every snapshot in a LIGGGHTS dump file."""
    return [s.timestep for s in _liggghts_snapshots(path)]


def read_liggghts_dump(path, snapshot: int = -1, timestep: int | None = None) -> ParticleData:
    """Read one snapshot of a LIGGGHTS ``dump custom`` file: by position ``snapshot``
    (0 first, -1 last, the default) or by its ``timestep`` number."""
    path = Path(path)
    snaps = _liggghts_snapshots(path, snapshot, timestep)
    if timestep is not None:
        found = [s for s in snaps if s.timestep == timestep]
        if not found:
            raise InputError(f"{path}: timestep: no snapshot at TIMESTEP {timestep} "
                             f"(have {', '.join(str(s.timestep) for s in snaps[:10])})")
        snap = found[-1]
    else:
        if not -len(snaps) <= snapshot < len(snaps):
            raise InputError(f"{path}: snapshot: must lie in [{-len(snaps)}, {len(snaps) - 1}], "
                             f"got {snapshot}")
        snap = snaps[snapshot]
    cols = snap.columns
    if not snap.rows:
        raise InputError(f"{path}:{snap.first_line - 1}: no particles in the snapshot")

    def pick(*names):
        for nm in names:
            if nm in cols:
                return nm
        return None

    axes = []
    scaled = []
    for a in "xyz":
        nm = pick(a, f"{a}u", f"{a}s", f"{a}su")
        if nm is None and a != "z":
            raise InputError(f"{path}:{snap.first_line - 1}: ITEM: ATOMS: missing column {a!r}")
        if nm is not None:
            axes.append(nm)
            scaled.append(nm.endswith("s") or nm.endswith("su"))
    radius_col = pick("radius", "diameter")
    if radius_col is None:
        raise InputError(f"{path}:{snap.first_line - 1}: ITEM: ATOMS: missing column 'radius' "
                         f"(or 'diameter')")
    wanted = axes + [radius_col]
    optional = [c for c in ("id", "type", "mass", "vx", "vy", "vz", "omegax", "omegay", "omegaz",
                            "body", "mol") if c in cols]
    twice = [c for c in wanted + optional if cols.count(c) > 1]
    if twice:
        raise InputError(f"{path}:{snap.first_line - 1}: ITEM: ATOMS: column {twice[0]!r} given "
                         f"twice")
    index = {c: cols.index(c) for c in wanted + optional}
    data = {c: np.empty(len(snap.rows)) for c in index}
    lines = np.arange(snap.first_line, snap.first_line + len(snap.rows))
    for row_k, text in enumerate(snap.rows):
        parts = text.split()
        line = snap.first_line + row_k
        if len(parts) != len(cols):
            raise InputError(f"{path}:{line}: expected {len(cols)} values, got {len(parts)}")
        for c, i in index.items():
            data[c][row_k] = _number(parts[i], path, line, c)
    dim = len(axes)
    x = np.empty((len(snap.rows), dim))
    for a, (nm, s) in enumerate(zip(axes, scaled)):
        lo, hi = snap.box[a]
        x[:, a] = lo + data[nm] * (hi - lo) if s else data[nm]
    r = data[radius_col] * (0.5 if radius_col == "diameter" else 1.0)
    _check_positive(r, path, lines, radius_col, "radius")
    for name, minimum in (("id", None), ("type", 1), ("body", -1), ("mol", None)):
        if name in data:
            column = index[name]
            texts = _LazyColumn(snap.rows, column)
            _check_integers(data[name], name, path, lines, minimum, texts)
    order = np.argsort(data["id"], kind="stable") if "id" in data else np.arange(len(r))
    if "id" in data:
        ids = data["id"][order]
        dup = np.flatnonzero(np.diff(ids) == 0)
        if len(dup):
            raise InputError(f"{path}:{lines[order[dup[0] + 1]]}: column 'id': duplicate id "
                             f"{int(ids[dup[0]])}")
    m = None
    if "mass" in data:
        m = data["mass"]
        _check_positive(m, path, lines, "mass", "mass")
        m = m[order]
    v = None
    if all(c in data for c in ("vx", "vy", "vz")[:dim]):
        v = np.stack([data[c] for c in ("vx", "vy", "vz")[:dim]], axis=1)[order]
    w = None
    if all(c in data for c in ("omegax", "omegay", "omegaz")):
        w = np.stack([data[c] for c in ("omegax", "omegay", "omegaz")], axis=1)[order]
    out = ParticleData(
        np.ascontiguousarray(x[order]), r[order].copy(), m, v, w,
        ids=data["id"][order].astype(np.int64) if "id" in data else None,
        types=data["type"][order].astype(np.int64) if "type" in data else None,
        timestep=snap.timestep, box=snap.box[:dim].copy(), periodic=snap.periodic[:dim].copy(),
        source=str(path))
    body_col = "body" if "body" in data else ("mol" if "mol" in data else None)
    if body_col is not None:
        # the clump of each sphere (LAMMPS' molecule id: 0 means none)
        body = data[body_col][order].astype(np.int64)
        out.extra["body"] = np.where(body <= 0, -1, body) if body_col == "mol" else body
    return out


class _LazyColumn:
    """The text of one column of dump rows, split only for the row asked for (an error
    message's value)."""

    def __init__(self, rows, column):
        self.rows, self.column = rows, column

    def __getitem__(self, k):
        return self.rows[k].split()[self.column]


def format_liggghts_snapshot(x, r, m=None, v=None, timestep: int = 0, box=None, ids=None,
                             types=None, periodic=None, body=None) -> str:
    """One ``dump custom`` snapshot as text: columns ``id type x y z radius`` then
    ``mass``, ``vx vy vz`` and ``body`` (clump ids) when given. 2D data is written with
    z = 0. ``box`` (dim, 2) [L] defaults to the particles' bounding box (centre -/+
    radius); ``periodic`` (a bool or one per axis) marks periodic axes ``pp`` in BOX
    BOUNDS, the others ``ff`` (and z of 2D data)."""
    x, r = _columns(x, r)
    n, dim = x.shape
    x3 = np.zeros((n, 3))
    x3[:, :dim] = x
    if box is None:
        box = np.stack([(x - r[:, None]).min(axis=0), (x + r[:, None]).max(axis=0)], axis=1)
    box = np.asarray(box, dtype=np.float64).reshape(-1, 2)
    box3 = np.zeros((3, 2))
    box3[:, 1] = 1.0
    box3[: box.shape[0]] = box
    if dim == 2 and box.shape[0] == 2:
        box3[2] = (-0.5, 0.5)
    ids = np.arange(1, n + 1) if ids is None else np.asarray(ids, dtype=np.int64)
    types = np.ones(n, dtype=np.int64) if types is None else np.asarray(types, dtype=np.int64)
    names = ["id", "type", "x", "y", "z", "radius"]
    cols = [x3, r[:, None]]
    if m is not None:
        names.append("mass")
        cols.append(np.asarray(m, dtype=np.float64).reshape(n, 1))
    if v is not None:
        v3 = np.zeros((n, 3))
        v3[:, :dim] = np.asarray(v, dtype=np.float64).reshape(n, -1)[:, :dim]
        names += ["vx", "vy", "vz"]
        cols.append(v3)
    if body is not None:
        names.append("body")
        cols.append(np.asarray(body, dtype=np.float64).reshape(n, 1))
    data = np.hstack(cols)
    flags = np.zeros(3, dtype=bool)
    if periodic is not None:
        flags[:dim] = np.broadcast_to(np.asarray(periodic, dtype=bool), (dim,))
    out = ["ITEM: TIMESTEP", str(int(timestep)), "ITEM: NUMBER OF ATOMS", str(n),
           "ITEM: BOX BOUNDS " + " ".join("pp" if f else "ff" for f in flags)]
    out += [f"{lo!r} {hi!r}" for lo, hi in box3.tolist()]
    out.append("ITEM: ATOMS " + " ".join(names))
    last = len(names) - 2 - (1 if body is not None else 0)  # float columns before body
    for i, t, row in zip(ids.tolist(), types.tolist(), data.tolist()):
        text = " ".join(repr(float(vv)) for vv in row[:last])
        if body is not None:
            text += f" {int(row[-1])}"
        out.append(f"{i} {t} {text}")
    return "\n".join(out) + "\n"


def write_liggghts_dump(path, x, r, m=None, v=None, timestep: int = 0, box=None, ids=None,
                        types=None, append: bool = False, periodic=None, body=None) -> Path:
    """Write (or, with ``append``, add) one snapshot to a LIGGGHTS dump file
    (:func:`format_liggghts_snapshot`)."""
    text = format_liggghts_snapshot(x, r, m, v, timestep, box, ids, types, periodic, body)
    path = Path(path)
    if append and path.exists():
        try:
            with open(path, "a", encoding="utf-8") as fh:
                fh.write(text)
        except OSError as exc:  # (a full disk: name the file)
            raise naming(exc, path) from exc
        return path
    return _write_text_atomically(path, text)


# ----------------------------------------------------------------------- YADE

#: the fields of a YADE ``#format`` header (yade.export.textExt: x_y_z_r, x_y_z_r_matId,
#: x_y_z_r_attrs; demstep's 2D files: x_y_r); ``attrs``, last, stands for any number of
#: further columns
YADE_FIELDS = ("x", "y", "z", "r", "matid", "attrs")


def _yade_format(spec: str, path, line: int) -> list[str]:
    """The fields of the ``#format`` header ``spec`` (lower case), each known and given
    once, x, y and r among them; else an InputError naming the line and the header."""
    fmt = [c.strip().lower() for c in spec.split("_") if c.strip()]
    for k, name in enumerate(fmt):
        if name not in YADE_FIELDS or (name == "attrs" and k != len(fmt) - 1):
            raise InputError(f"{path}:{line}: #format: unknown field {name!r} (fields: x, y, z, "
                             f"r, matId, and attrs last), got {spec!r}")
        if fmt.count(name) > 1:
            raise InputError(f"{path}:{line}: #format: field {name!r} given twice, got {spec!r}")
    if "r" not in fmt or "x" not in fmt or "y" not in fmt:
        raise InputError(f"{path}:{line}: #format: must name x, y and r columns, got {spec!r}")
    return fmt


def read_yade_text(path) -> ParticleData:
    """A YADE text export: ``x y z r`` per line (``x y r`` for demstep's 2D files),
    ``#`` comments, extra columns ignored (every row has as many values as the first);
    ``#format x_y_z_r...`` names the columns (:data:`YADE_FIELDS`, each once)."""
    path = Path(path)
    fmt = None
    rows, numbers = [], []
    ncols = None
    with open_text(path) as lines:
        for line_no, text in enumerate(lines, start=1):
            stripped = text.strip()
            if stripped.startswith("#"):
                body = stripped.lstrip("#").strip()
                if body.lower().startswith("format") and fmt is None and not rows:
                    spec = body[len("format"):].strip()
                    fmt = _yade_format(spec, path, line_no)
                continue
            if not stripped:
                continue
            parts = stripped.split("#", 1)[0].split()
            if fmt is None and ncols is None:
                ncols = len(parts)
                if ncols < 3:
                    raise InputError(f"{path}:{line_no}: expected 'x y z r' (or 'x y r'), "
                                     f"got {len(parts)} values")
            rows.append(parts)
            numbers.append(line_no)
    if not rows:
        raise InputError(f"{path}: no particles")
    if fmt is not None:
        names = ["x", "y"] + (["z"] if "z" in fmt else []) + ["r"]
        index = [fmt.index(c) for c in names]
        width = len(fmt) - (1 if fmt[-1] == "attrs" else 0)
        for parts, line_no in zip(rows, numbers):
            if len(parts) < width:
                raise InputError(f"{path}:{line_no}: expected {width} values (#format "
                                 f"{spec}), got {len(parts)}")
    else:
        names = ["x", "y", "r"] if ncols == 3 else ["x", "y", "z", "r"]
        index = list(range(len(names)))
        width = len(names)
    data = np.empty((len(rows), len(names)))
    count = max(width, len(rows[0]))  # (extra columns ignored, but in every row alike)
    for k, (parts, line_no) in enumerate(zip(rows, numbers)):
        if len(parts) != count:
            raise InputError(f"{path}:{line_no}: expected {count} values (as line "
                             f"{numbers[0]}), got {len(parts)}")
        for c, (i, nm) in enumerate(zip(index, names)):
            data[k, c] = _number(parts[i], path, line_no, nm)
    dim = len(names) - 1
    r = data[:, dim].copy()
    _check_positive(r, path, numbers, "r", "radius")
    return ParticleData(np.ascontiguousarray(data[:, :dim]), r, source=str(path))


def write_yade_text(path, x, r) -> Path:
    """Write particles as a YADE text export (``#format x_y_z_r``; 2D: ``x_y_r``)."""
    x, r = _columns(x, r)
    dim = x.shape[1]
    header = "#format x_y_z_r" if dim == 3 else "#format x_y_r"
    data = np.hstack([x, r[:, None]])
    lines = [header] + [" ".join(repr(float(v)) for v in row) for row in data]
    return _write_text_atomically(path, "\n".join(lines) + "\n")


# ------------------------------------------------------------ LAMMPS data files
#: the header keywords of a LAMMPS data file that name a box bound
_DATA_BOUNDS = {"xlo xhi": 0, "ylo yhi": 1, "zlo zhi": 2}
#: a LAMMPS data file's count of atoms (its header, after the title line)
_DATA_ATOMS = re.compile(r"^\d+\s+atoms\s*(#.*)?$")
#: the sections of a LAMMPS data file demstep reads; the others are skipped
_DATA_SECTIONS = ("Atoms", "Velocities")
#: every section name a data file may hold (to know where a section ends)
_DATA_ALL_SECTIONS = ("Atoms", "Velocities", "Masses", "Bonds", "Angles", "Dihedrals",
                      "Impropers", "Ellipsoids", "Lines", "Triangles", "Bodies",
                      "Pair Coeffs", "PairIJ Coeffs", "Bond Coeffs", "Angle Coeffs",
                      "Dihedral Coeffs", "Improper Coeffs")


def read_lammps_data(path) -> ParticleData:
    """A LAMMPS data file (``write_data``, ``read_data``) of ``atom_style sphere``: the
    ``Atoms`` section's rows ``id type diameter density x y z`` (optionally ``ix iy iz``
    image flags, applied with the box lengths), the box from its ``xlo xhi`` lines,
    masses = density x pi d^3 / 6, and the ``Velocities`` section's ``id vx vy vz wx wy
    wz`` when present; rows sorted by id. Periodicity is not in the file (it is the
    input script's ``boundary``): give it as ``--periodic``. An ``Atoms`` section of
    another style (its ``# style`` comment) is refused in one line."""
    path = Path(path)
    box = np.full((3, 2), np.nan)
    section = None
    rows, numbers, vel = [], [], {}
    with open_text(path) as lines:
        for line_no, text in enumerate(lines, start=1):
            if line_no == 1:  # (the title line)
                continue
            body = text.split("#", 1)[0].strip()
            if not body:
                continue
            head = body.split()
            if body in _DATA_ALL_SECTIONS:
                section = body
                if body == "Atoms":
                    style = text.split("#", 1)[1].strip() if "#" in text else "sphere"
                    if style != "sphere":
                        raise InputError(f"{path}:{line_no}: Atoms section of atom_style "
                                         f"{style!r}; demstep reads atom_style sphere")
                continue
            if section is None:
                for key, axis in _DATA_BOUNDS.items():
                    if body.endswith(key) and len(head) == 4:
                        box[axis] = [_number(head[0], path, line_no, key.split()[0]),
                                     _number(head[1], path, line_no, key.split()[1])]
                continue
            if section == "Atoms":
                if len(head) not in (7, 10):
                    raise InputError(f"{path}:{line_no}: Atoms (sphere): expected 'id type "
                                     f"diameter density x y z [ix iy iz]', got {len(head)} "
                                     f"values")
                rows.append(head)
                numbers.append(line_no)
            elif section == "Velocities":
                if len(head) != 7:
                    raise InputError(f"{path}:{line_no}: Velocities (sphere): expected 'id vx "
                                     f"vy vz wx wy wz', got {len(head)} values")
                vel[_integer(head[0], path, line_no, "id")] = [
                    _number(v, path, line_no, c) for v, c in zip(head[1:], ("vx", "vy", "vz",
                                                                            "wx", "wy", "wz"))]
    if not rows:
        raise InputError(f"{path}: no Atoms section (a LAMMPS data file of atom_style sphere)")
    if np.isnan(box).any():
        missing = [k for k, a in _DATA_BOUNDS.items() if np.isnan(box[a]).any()]
        raise InputError(f"{path}: no '{missing[0]}' line (the box)")
    n = len(rows)
    ids = np.empty(n, dtype=np.int64)
    types = np.empty(n, dtype=np.int64)
    d = np.empty(n)
    rho = np.empty(n)
    x = np.empty((n, 3))
    for k, (head, line_no) in enumerate(zip(rows, numbers)):
        ids[k] = _integer(head[0], path, line_no, "id")
        types[k] = _integer(head[1], path, line_no, "type")
        d[k] = _number(head[2], path, line_no, "diameter")
        rho[k] = _number(head[3], path, line_no, "density")
        x[k] = [_number(v, path, line_no, c) for v, c in zip(head[4:7], "xyz")]
        if len(head) == 10:
            image = [_integer(v, path, line_no, c) for v, c in zip(head[7:], ("ix", "iy", "iz"))]
            x[k] += np.array(image) * (box[:, 1] - box[:, 0])
    _check_positive(d, path, numbers, "diameter", "diameter (a point particle has none)")
    _check_positive(rho, path, numbers, "density", "density")
    dup = np.flatnonzero(np.bincount(ids - ids.min()) > 1) if n else []
    if len(dup):
        raise InputError(f"{path}: atom id {int(dup[0] + ids.min())} appears twice")
    order = np.argsort(ids, kind="stable")
    r = 0.5 * d[order]
    m = rho[order] * np.pi / 6.0 * d[order] ** 3
    v = w = None
    if vel:
        missing = [int(i) for i in ids if int(i) not in vel]
        if missing:
            raise InputError(f"{path}: Velocities has no row for atom id {missing[0]}")
        table = np.array([vel[int(i)] for i in ids[order]])
        v, w = table[:, :3].copy(), table[:, 3:].copy()
    return ParticleData(np.ascontiguousarray(x[order]), r, m, v, w, ids=ids[order],
                        types=types[order], box=box, periodic=None, source=str(path))


# ------------------------------------------------------------------- dispatch

def detect_format(path) -> str:
    """The format of ``path``: by extension (.csv; .liggghts/.dump/.lammpstrj;
    .txt/.yade/.spheres), else by content: a first line 'ITEM:' is a LIGGGHTS dump, a
    line 'N atoms' among the first lines after the title a LAMMPS data file, a comma in
    the first line CSV, else YADE text."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in _EXTENSIONS:
        return _EXTENSIONS[suffix]
    head = []
    with open_text(path) as lines:
        for text in lines:
            if text.strip():
                head.append(text.strip())
            if len(head) >= 4:
                break
    first = head[0] if head else ""
    if first.upper().startswith("ITEM:"):
        return "liggghts"
    if any(_DATA_ATOMS.match(line) for line in head[1:]):
        return "lammps-data"
    if "," in first:
        return "csv"
    return "yade"


def read_particle_file(path, format: str = "auto", snapshot: int = -1) -> ParticleData:
    """Read a particle file of any supported ``format`` ('auto' detects it)."""
    path = Path(path)
    if format == "auto":
        format = detect_format(path)
    if format == "csv":
        return read_csv(path)
    if format == "liggghts":
        return read_liggghts_dump(path, snapshot=snapshot)
    if format == "yade":
        return read_yade_text(path)
    if format == "lammps-data":
        return read_lammps_data(path)
    raise InputError(f"format: must be auto, {', '.join(FORMATS)}, got {format!r}")


def write_particle_file(path, x, r, m=None, format: str = "auto") -> Path:
    """Write particles in ``format`` ('auto': from the extension, CSV if unknown)."""
    path = Path(path)
    if format == "auto":
        format = _EXTENSIONS.get(path.suffix.lower(), "csv")
    if format == "lammps-data":
        raise InputError(f"{path}: format lammps-data is read only (LAMMPS writes it: "
                         f"write_data)")
    if format == "csv":
        return write_csv(path, x, r, m)
    if format == "liggghts":
        return write_liggghts_dump(path, x, r, m)
    if format == "yade":
        return write_yade_text(path, x, r)
    raise InputError(f"format: must be auto, {', '.join(FORMATS)}, got {format!r}")
