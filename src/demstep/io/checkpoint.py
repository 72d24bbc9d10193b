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
                **sim.timestep_state(),
                version=np.array([__version__]))
    with atomic_path(path, suffix=".npz.tmp") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **data)
            fh.flush()
            os.fsync(fh.fileno())
    return path


def load_checkpoint(sim, path):
    """Restore the state saved in ``path`` into ``sim`` (built from the same case)."""
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable checkpoint ({exc})") from None
    with data:
        if "format" not in data or int(data["format"][0]) != FORMAT_VERSION:
            raise InputError(f"{path}: not a demstep checkpoint (format {FORMAT_VERSION})")
        if data["r"].shape != sim.r.shape or not np.array_equal(data["r"], sim.r):
            raise InputError(f"{path}: the checkpoint's particles do not match the simulation")
        if data["wall_point"].shape != sim.wall_point.shape:
            raise InputError(f"{path}: the checkpoint's walls do not match the simulation")
        for name in _ARRAYS:
            setattr(sim, name, np.ascontiguousarray(data[name]))
        sim._damping_history = True  # restored damping forces of the last step
        sim._dashpot_history = True  # and pair dashpot forces
        sim.ledger.acc[:] = data["acc"]
        sim.ledger.energy[:] = data["energy"]
        step, time, dt, dt_prev, first, max_err, next_dt, dt_est, t_step, t_time, t_dt = data["scalars"]
        sim.restore_timestep_state({k: data[k] for k in data.files if k.startswith("ts_")})
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
