"""Checkpoints: the complete dynamic state of a Simulation in one .npz file.

Writes are atomic (a temporary file in the same folder, then rename), so a crash never
leaves a corrupt checkpoint. A restart restores the state into a Simulation built
from the same case and continues bit for bit as the uninterrupted run would have:
positions, half-step velocities, contact and wall history, the Verlet lists and their
reference positions, wall state, the energy ledger, step, time and time step.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from demstep.errors import InputError
from demstep.io.atomic import atomic_path

FORMAT_VERSION = 2

_ARRAYS = ("x", "v", "w", "m", "inertia", "applied_force", "gravity", "fd_prev", "td_prev",
           "pi", "pj", "ft", "fd", "etan", "wp", "ww", "wft", "wfd", "wetan", "x_ref",
           "wall_point", "wall_force", "wall_force_prev", "wall_disp_prev",
           "wall_ref", "servo", "counters", "wall_vel", "wall_k", "periodic_len", "box_motion",
           "box_servo", "box_ref", "box_state", "wall_motion")


def save_checkpoint(sim, path) -> Path:
    """Write ``sim``'s state to ``path`` (.npz) atomically."""
    from demstep import __version__

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not sim._pairs_built:
        sim._rebuild()
    data = {name: getattr(sim, name) for name in _ARRAYS}
    data.update(acc=sim.ledger.acc, energy=sim.ledger.energy, r=sim.r, fixed=sim.fixed,
                scalars=np.array([sim.step, sim.time, np.nan if sim.dt is None else sim.dt,
                                  sim.dt_prev, float(sim._first), sim.monitor.max_error,
                                  float(sim._next_dt_update),
                                  np.nan if sim.dt_estimate is None else sim.dt_estimate,
                                  float(sim._time_ref[0]), sim._time_ref[1],
                                  np.nan if sim._time_ref[2] is None else sim._time_ref[2]]),
                law=sim.law.params(), format=np.array([FORMAT_VERSION]),
                monitor=sim.monitor.state(),
                **sim.timestep_state(),
                version=np.array([__version__]))
    with atomic_path(path, suffix=".npz.tmp") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **data)
            fh.flush()
            os.fsync(fh.fileno())
    return path


#: the first bytes of an .npz file (a zip archive)
_ZIP_MAGIC = b"PK\x03\x04"


def read_checkpoint_arrays(path) -> dict:
    """Every array of the checkpoint ``path``, read and decompressed; InputError with
    one line saying why when it is not a readable demstep checkpoint (a folder, a
    missing file, another kind of file, a damaged or truncated archive)."""
    import zipfile
    import zlib

    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: a folder, not a checkpoint file (.npz)")
    if not path.is_file():
        raise InputError(f"{path}: no such checkpoint file")
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(_ZIP_MAGIC))
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if head != _ZIP_MAGIC:
        kind = "an empty file" if not head else (
            "a JSON file (the run state beside a checkpoint?)" if head[:1] in (b"{", b"[")
            else "not a zip archive")
        raise InputError(f"{path}: not a demstep checkpoint (.npz): {kind}")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError) as exc:
        text = " ".join(str(exc).split())
        raise InputError(f"{path}: a damaged or truncated checkpoint "
                         f"({type(exc).__name__}: {text})") from None
    if "format" not in arrays or arrays["format"].shape != (1,) \
            or int(arrays["format"][0]) != FORMAT_VERSION:
        raise InputError(f"{path}: not a demstep checkpoint (format {FORMAT_VERSION})")
    missing = [name for name in _ARRAYS + ("acc", "energy", "r", "scalars")
               if name not in arrays]
    if missing:
        raise InputError(f"{path}: a damaged checkpoint (array {missing[0]!r} missing)")
    return arrays


def load_checkpoint(sim, path):
    """Restore the state saved in ``path`` into ``sim`` (built from the same case)."""
    path = Path(path)
    data = read_checkpoint_arrays(path)
    if data["r"].shape != sim.r.shape or not np.array_equal(data["r"], sim.r):
        raise InputError(f"{path}: the checkpoint's particles do not match the simulation")
    if data["wall_point"].shape != sim.wall_point.shape:
        raise InputError(f"{path}: the checkpoint's walls do not match the simulation")
    if data["scalars"].shape != (11,):
        raise InputError(f"{path}: a damaged checkpoint (scalars of shape "
                         f"{data['scalars'].shape})")
    for name in _ARRAYS:
        setattr(sim, name, np.ascontiguousarray(data[name]))
    sim._damping_history = True  # restored damping forces of the last step
    sim._dashpot_history = True  # and pair dashpot forces
    sim.ledger.acc[:] = data["acc"]
    sim.ledger.energy[:] = data["energy"]
    step, time, dt, dt_prev, first, max_err, next_dt, dt_est, t_step, t_time, t_dt = data["scalars"]
    if "monitor" in data:  # whether the energy monitor is in alarm (later than format 2.0)
        sim.monitor.restore_state(data["monitor"])
    sim.restore_timestep_state({k: data[k] for k in data if k.startswith("ts_")})
    sim.step = int(step)
    sim.time = float(time)
    sim.dt = None if np.isnan(dt) else float(dt)
    sim.dt_prev = float(dt_prev)
    sim._first = bool(first)
    sim.monitor.max_error = float(max_err)
    sim._next_dt_update = int(next_dt)
    sim.dt_estimate = None if np.isnan(dt_est) else float(dt_est)
    sim._time_ref = (int(t_step), float(t_time), None if np.isnan(t_dt) else float(t_dt))
    sim._update_masses()
    sim._chunks = None
    sim._pairs_built = True
    sim.energy_floor = None
    for t in sim._triggers:  # the next multiple of each interval, as in an unbroken run
        t.next_step = (sim.step // t.every + 1) * t.every
    return sim
