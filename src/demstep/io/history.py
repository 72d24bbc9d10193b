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
* ``n_contacts`` (particle-particle plus particle-wall);
* per wall ``NAME.fx``, ``NAME.fy``(, ``NAME.fz``) the force the particles exert on
  the wall [M L/T^2] (2D: per unit thickness), ``NAME.stress`` its compressive normal
  stress [M/(L T^2)] (:meth:`Simulation.wall_stress`; NaN when the loaded area is
  unknown) and ``NAME.x``, ``NAME.y``(, ``NAME.z``) the position of its reference
  point [L];
* with periodic axes: ``box.Lx`` ... the current periodic lengths [L] and ``love.xx``,
  ``love.yy``(, ``love.zz``) the Love-Weber stress of the contacts [M/(L T^2)]
  (:meth:`Simulation.love_stress`; NaN along an axis of unknown extent);
* any extra columns given to the writer (the runner adds ``stage``).

Floats are written with ``repr`` (shortest round-trip form), so a history read back
is bit-identical to the values of the run. A writer is a callable that plugs into
``sim.every(n, writer)``.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Callable

import numpy as np

from demstep.energy import EnergyLedger
from demstep.io.atomic import write_text_atomic
from demstep.io.textfile import csv_rows, open_text
from demstep.errors import InputError

AXES = "xyz"


def history_columns(sim, extra: dict | None = None) -> list[str]:
    """Column names of the history of ``sim`` (plus the keys of ``extra``)."""
    return columns_for(sim.dim, [wall.name for wall in sim.walls],
                       "".join(_periodic_axes(sim)), extra,
                       love=hasattr(sim, "love_stress"))


def columns_for(dim: int, wall_names, periodic_axes: str, extra=None,
                love: bool = True) -> list[str]:
    """Column names of the history of a ``dim``-dimensional run with the walls
    ``wall_names`` (in the simulation's order) and the periodic axes ``periodic_axes``
    (e.g. "xz"), plus ``extra`` (names, or a dict of them): known before the run is
    built (``demstep sweep`` checks its ``--peak`` against them)."""
    cols = ["step", "time", "dt", "dt_estimate"]
    cols += list(EnergyLedger().as_dict())
    cols.append("energy_alarm")
    cols.append("n_contacts")
    for name in wall_names:
        cols += [f"{name}.f{a}" for a in AXES[:dim]]
        cols.append(f"{name}.stress")
        cols += [f"{name}.{a}" for a in AXES[:dim]]
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
    row += [float(v) for v in sim.ledger.as_dict().values()]
    row.append(int(sim.monitor.alarm))
    row.append(sim.n_contacts)
    if sim.walls:
        with np.errstate(divide="ignore", invalid="ignore"):
            stress = sim.wall_stress()
        for k in range(len(sim.walls)):
            row += [float(v) for v in sim.wall_force[k, : sim.dim]]
            row.append(float(stress[k]))
            row += [float(v) for v in sim.wall_point[k, : sim.dim]]
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
        with open(self.path, newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            if header != self.columns:
                raise InputError(f"{self.path}: the history's columns do not match this run")
            kept = [row for row in reader if row and int(row[0]) <= step]
        text = ",".join(self.columns) + "\n" + "".join(",".join(r) + "\n" for r in kept)
        _write_atomically(self.path, text)

    def write(self, sim):
        """Write one row for the current state (once per step)."""
        if self.last_step == sim.step:
            return
        self._csv.writerow([_text(v) for v in history_row(sim, self.extra)])
        self._fh.flush()
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


def _write_atomically(path: Path, text: str):
    write_text_atomic(path, text)
