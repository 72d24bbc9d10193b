"""The run history: one CSV row every N steps.

Columns, in order:

* ``step``, ``time`` [T], ``dt`` [T] (the step in use; in 'auto' mode below the
  certified one where the motion limit holds it), ``dt_estimate`` [T] (the
  certified step of the last estimate of ``TimeStep(mode='auto')``, a lower bound on
  the critical step: the exact one, or a cheaper bound where the growth cap made the
  exact solve unable to change dt; NaN otherwise);
* every term of the energy ledger [M L^2/T^2] (:meth:`EnergyLedger.as_dict`), which
  ends with ``energy_error`` (the normalized difference of the paper's eq. 22);
* ``energy_alarm``: 1 when the energy monitor's last check (every ``energy.every``
  steps) found the error above its ``eps``, else 0 (run.json records the first alarm);
* ``n_contacts`` (particle-particle, particle-wall and particle-mesh);
* per wall ``NAME.fx``, ``NAME.fy``(, ``NAME.fz``) the force the particles exert on
  the wall [M L/T^2] (2D: per unit thickness), ``NAME.stress`` its compressive normal
  stress [M/(L T^2)] (:meth:`Simulation.wall_stress`; NaN when the loaded area is
  unknown) and ``NAME.x``, ``NAME.y``(, ``NAME.z``) the position of its reference
  point [L];
* per mesh wall ``NAME.fx``, ``NAME.fy``, ``NAME.fz`` the force the particles exert on
  the mesh [M L/T^2], ``NAME.tx``, ``NAME.ty``, ``NAME.tz`` its torque about the mesh's
  centre [M L^2/T^2] (the torque a drum's motor must supply, negated),
  ``NAME.contacts`` the particles touching it and ``NAME.wear`` the volume worn away
  (Finnie's wear of each triangle times its area, summed [L^3]; 0 unless the mesh
  tracks wear: :attr:`Simulation.mesh_wear`);
* with insertion or outlets (:mod:`demstep.feed`): ``particles`` (the count now),
  ``energy_inserted`` and ``energy_removed`` [M L^2/T^2] (the ledger's terms for what
  particles brought in and took out), per inserter ``NAME.inserted`` (count),
  ``NAME.inserted_mass`` [M] and ``NAME.pending`` (drawn, waiting for room), per outlet
  ``NAME.removed`` and ``NAME.removed_mass`` [M] (cumulative);
* with periodic axes: ``box.Lx`` ... the current periodic lengths [L] and ``love.xx``,
  ``love.yy``(, ``love.zz``) the Love-Weber stress of the contacts [M/(L T^2)]
  (:meth:`Simulation.love_stress`; NaN along an axis of unknown extent);
* any extra columns given to the writer (the runner adds ``stage``).

Floats are written with ``repr`` (shortest round-trip form), so a history read back
is bit-identical to the values of the run. A writer is a callable that plugs into
``sim.every(n, writer)``.

On a restart the writer keeps the rows of the existing file up to the checkpoint's
step. A file damaged by a crash or a power loss (NUL bytes appended, a row cut short
or garbled, bytes that are not UTF-8) does not stop the restart: the well-formed rows
up to that step are kept, the damaged lines dropped, and one warning on the
``demstep`` logger names the file and what was dropped. A file whose header names
other columns (another run's history) is refused.
"""

from __future__ import annotations

import csv
import logging
import math
from pathlib import Path
from typing import Callable

import numpy as np

from demstep.energy import EnergyLedger
from demstep.io.atomic import write_text_atomic
from demstep.io.textfile import MAX_LINE, csv_rows, open_text
from demstep.errors import InputError

AXES = "xyz"

log = logging.getLogger(__name__)


def history_columns(sim, extra: dict | None = None) -> list[str]:
    """Column names of the history of ``sim`` (plus the keys of ``extra``)."""
    return columns_for(sim.dim, [wall.name for wall in sim.walls],
                       "".join(_periodic_axes(sim)), extra,
                       love=hasattr(sim, "love_stress"),
                       mesh_names=[m.name for m in getattr(sim, "mesh_walls", ())],
                       feed_names=_feed_names(sim))


def _feed_names(sim) -> tuple:
    feed = getattr(sim, "feed", None)
    if not feed:
        return (), ()
    return [i.name for i in feed.inserters], [o.name for o in feed.outlets]


def columns_for(dim: int, wall_names, periodic_axes: str, extra=None,
                love: bool = True, mesh_names=(), feed_names=((), ())) -> list[str]:
    """Column names of the history of a ``dim``-dimensional run with the walls
    ``wall_names`` (in the simulation's order) and the periodic axes ``periodic_axes``
    (e.g. "xz"), the mesh walls ``mesh_names``, the inserters' and outlets' names
    ``feed_names`` (two lists), plus ``extra`` (names, or a dict of them): known before the run is
    built (``demstep sweep`` checks its ``--peak`` against them)."""
    cols = ["step", "time", "dt", "dt_estimate"]
    cols += list(EnergyLedger().as_dict())
    cols.append("energy_alarm")
    cols.append("n_contacts")
    for name in wall_names:
        cols += [f"{name}.f{a}" for a in AXES[:dim]]
        cols.append(f"{name}.stress")
        cols += [f"{name}.{a}" for a in AXES[:dim]]
    for name in mesh_names:
        cols += [f"{name}.f{a}" for a in AXES]
        cols += [f"{name}.t{a}" for a in AXES]
        cols.append(f"{name}.contacts")
        cols.append(f"{name}.wear")
    inserters, outlets = feed_names
    if len(inserters) or len(outlets):
        cols += ["particles", "energy_inserted", "energy_removed"]
        for name in inserters:
            cols += [f"{name}.inserted", f"{name}.inserted_mass", f"{name}.pending"]
        for name in outlets:
            cols += [f"{name}.removed", f"{name}.removed_mass"]
    cols += [f"box.L{a}" for a in periodic_axes]
    if periodic_axes and love:
        cols += [f"love.{a}{a}" for a in AXES[:dim]]
    cols += list(extra or ())
    return cols


def _periodic_axes(sim) -> list[str]:
    return [AXES[k] for k in range(sim.dim) if sim.periodic_len[k] > 0]


def history_row(sim, extra: dict | None = None) -> list:
    """The values of one history row for the current state of ``sim``."""
    nan = math.nan
    row = [sim.step, float(sim.time), nan if sim.dt is None else float(sim.dt),
           nan if sim.dt_estimate is None else float(sim.dt_estimate)]
    # energy_error as the monitor evaluates it: NaN while the energies are below its floor
    row += [float(v) for v in sim.ledger.as_dict(float(sim.energy_floor or 0.0)).values()]
    row.append(int(sim.monitor.alarm))
    row.append(sim.n_contacts)
    if sim.walls:
        with np.errstate(divide="ignore", invalid="ignore"):
            stress = sim.wall_stress()
        for k in range(len(sim.walls)):
            row += [float(v) for v in sim.wall_force[k, : sim.dim]]
            row.append(float(stress[k]))
            row += [float(v) for v in sim.wall_point[k, : sim.dim]]
    if getattr(sim, "mesh_walls", ()):
        wear = sim.mesh_wear
    for k in range(len(getattr(sim, "mesh_walls", ()))):
        row += [float(v) for v in sim.mesh_force[k]]
        row += [float(v) for v in sim.mesh_torque[k]]
        row.append(int(sim.meshes.contacts[k]))
        row.append(float(wear[k]))
    feed = getattr(sim, "feed", None)
    if feed:
        row += [len(sim.r), sim.ledger.inserted, sim.ledger.removed]
        for item in feed.inserters:
            row += [item.inserted, item.inserted_mass, len(item.pending)]
        for item in feed.outlets:
            row += [item.removed, item.removed_mass]
    periodic = _periodic_axes(sim)
    row += [float(sim.periodic_len[AXES.index(a)]) for a in periodic]
    if periodic and hasattr(sim, "love_stress"):
        with np.errstate(divide="ignore", invalid="ignore"):
            row += [float(v) for v in sim.love_stress()]
    row += [fn(sim) for fn in (extra or {}).values()]
    return row


def _text(value) -> str:
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    return str(value)


class HistoryWriter:
    """Append history rows to a CSV file.

    ``extra`` maps additional column names to functions of the simulation. With
    ``resume_after_step`` (a restart) an existing file keeps its rows up to that step
    and new rows are appended; otherwise the file is started afresh."""

    def __init__(self, path, sim, extra: dict[str, Callable] | None = None,
                 resume_after_step: int | None = None):
        self.path = Path(path)
        self.extra = dict(extra or {})
        self.columns = history_columns(sim, self.extra)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if resume_after_step is not None and self.path.exists():
            self._truncate(resume_after_step)
        else:
            _write_atomically(self.path, ",".join(self.columns) + "\n")
        self._fh = open(self.path, "a", newline="", encoding="utf-8")
        self._csv = csv.writer(self._fh, lineterminator="\n")
        self.last_step = None

    def _truncate(self, step: int):
        """Keep the well-formed rows of the file up to ``step``, drop the others (module
        docstring); InputError when its header names other columns."""
        kept, damaged, later = [], [], 0
        with open(self.path, "rb") as fh:
            lines = _raw_lines(fh)
            header = _row(next(lines, None), None)
            if header is not None and header != self.columns:
                raise InputError(f"{self.path}: the history's columns do not match this run")
            for number, raw in enumerate(lines, start=2):
                row = _row(raw, len(self.columns))
                if row is None:
                    damaged.append(number)
                elif int(row[0]) <= step:
                    kept.append(",".join(row) + "\n")
                else:
                    later += 1
        _write_atomically(self.path, ",".join(self.columns) + "\n" + "".join(kept))
        if damaged or header is None:
            what = []
            if header is None:
                what.append("a damaged header rewritten")
            if damaged:
                shown = ", ".join(map(str, damaged[:5])) + (", ..." if len(damaged) > 5 else "")
                what.append(f"{len(damaged)} damaged line{'s' if len(damaged) > 1 else ''} "
                            f"dropped (line{'s' if len(damaged) > 1 else ''} {shown})")
            log.warning("%s: %s; it keeps its %d good rows up to the checkpoint's step %d%s",
                        self.path, " and ".join(what), len(kept), step,
                        f" and drops the {later} after it" if later else "")

    def write(self, sim):
        """Write one row for the current state (once per step)."""
        if self.last_step == sim.step:
            return
        try:
            self._csv.writerow([_text(v) for v in history_row(sim, self.extra)])
            self._fh.flush()
        except OSError as exc:  # (a full disk: name the file)
            if exc.filename is None:
                raise OSError(exc.errno, exc.strerror, str(self.path)) from exc
            raise
        self.last_step = sim.step

    __call__ = write

    def close(self):
        if not self._fh.closed:
            self._fh.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_history(path) -> dict[str, np.ndarray]:
    """Columns of a history CSV as float arrays, keyed by column name."""
    path = Path(path)
    with open_text(path, "history file", newline="") as fh:
        reader = csv_rows(fh)
        header = next(reader, None)
        if not header:
            raise InputError(f"{path}: empty history file")
        rows = []
        for line, row in enumerate(reader, start=2):
            if not row:
                continue
            if len(row) != len(header):
                raise InputError(f"{path}:{line}: expected {len(header)} values, got "
                                 f"{len(row)}")
            try:
                rows.append([float(v) for v in row])
            except ValueError:
                bad = next(i for i, v in enumerate(row) if not _is_float(v))
                raise InputError(f"{path}:{line}: column {header[bad]!r}: not a number: "
                                 f"{row[bad]!r}") from None
    data = np.array(rows, dtype=np.float64).reshape(len(rows), len(header))
    return {name: data[:, k] for k, name in enumerate(header)}


def _is_float(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def _raw_lines(fh):
    """The lines of the binary file ``fh`` as bytes with their line ends, read one at a
    time; None for a line longer than MAX_LINE bytes (skipped without holding it)."""
    while line := fh.readline(MAX_LINE + 1):
        if len(line) > MAX_LINE and not line.endswith(b"\n"):
            while line and not line.endswith(b"\n"):
                line = fh.readline(MAX_LINE + 1)
            yield None
        else:
            yield line


def _row(raw: bytes | None, width: int | None) -> list[str] | None:
    """The fields of the history line ``raw`` when it is whole (ends with a line end),
    UTF-8 text without NUL bytes, one CSV row and, when ``width`` is given, a row of
    ``width`` numbers with an integer step first; else None (a damaged line)."""
    if raw is None or not raw.endswith(b"\n") or b"\0" in raw:
        return None
    try:
        fields = next(csv.reader([raw.decode("utf-8").rstrip("\r\n")]), [])
    except (UnicodeDecodeError, csv.Error):
        return None
    if width is None:
        return fields
    if len(fields) != width:
        return None
    try:
        int(fields[0])
        for value in fields:
            float(value)
    except ValueError:
        return None
    return fields


def _write_atomically(path: Path, text: str):
    write_text_atomic(path, text)
