"""Stages of a case: the changes applied when a stage starts, and the check that every
stage can start before a run writes anything."""

from __future__ import annotations

import math

import numpy as np

from demstep.case.build import apply_motion, build_simulation, build_timestep
from demstep.case.schema import AXES, Case
from demstep.contact.bonds import ParallelBonds
from demstep.errors import InputError
from demstep.io.formats import read_bond_csv
from demstep.kernels import dem
from demstep.packings import inverse_order


def apply_stage(sim, case: Case, k: int, fresh: bool = True) -> None:
    """Apply the changes of stage ``k`` at its start. ``fresh`` False replays them on
    a restart (the checkpoint then restores the state; the ledger is not reset)."""

    stage = case.stages[k]
    dim = sim.dim
    if stage.mu is not None:
        sim.law.mu = float(stage.mu)
    if stage.mu_wall is not None:
        sim.law.mu_wall = float(stage.mu_wall)
    if stage.damping is not None:
        if stage.damping.local is not None:
            sim.damping.local = float(stage.damping.local)
        if stage.damping.viscous is not None:
            sim.damping.viscous = float(stage.damping.viscous)
    if stage.gravity is not None:
        sim.gravity[:] = 0.0
        sim.gravity[:dim] = stage.gravity
    index = {w.name: i for i, w in enumerate(sim.walls)}
    for name, change in stage.walls.items():
        i = index[name]
        wall = sim.walls[i]
        apply_motion(wall, change)
        sim.set_wall_motion(i, wall.motion, velocity=change.velocity,
                            target_stress=wall.target_stress, servo_gain=wall.servo_gain,
                            servo_factor=wall.servo_factor, max_speed=wall.max_speed,
                            area=wall.area, friction=wall.friction)
    mesh_index = {m.name: i for i, m in enumerate(sim.mesh_walls)}
    for name, change in stage.meshes.items():
        sim.set_mesh_motion(mesh_index[name], velocity=change.velocity, omega=change.omega,
                            surface_velocity=change.surface_velocity,
                            friction=change.friction, enabled=change.enabled,
                            center=change.center)
    for axis, change in stage.periodic.items():
        sim.set_box(AXES.index(axis), change.motion,
                    rate=change.rate if change.rate is not None else 0.0,
                    target_stress=change.target_stress or 0.0, servo_factor=change.servo_factor,
                    servo_gain=change.servo_gain,
                    max_speed=change.max_speed if change.max_speed is not None else np.inf)
    if stage.timestep is not None:
        sim.timestep = build_timestep(stage.timestep)
        sim.timestep.validate()
        sim.dt = None  # chosen anew by the next run (a restart restores it)
    _check_servo_areas(sim, case, k)
    if fresh and case.bond_stage() == k:
        create_bonds(sim, case)
    if fresh and stage.reset_ledger:
        sim.ledger.reset()


def create_bonds(sim, case: Case) -> None:
    """Bonds of the case's ``[bonds]``: every pair within ``gap``, or the pairs of its
    ``file`` (a CSV with 0-based particle columns i, j)."""
    b = case.bonds
    params = ParallelBonds(b.normal_stiffness, b.shear_stiffness, b.tensile_strength,
                           b.shear_strength, b.radius_multiplier, b.gap)
    path = case.bond_file()
    pairs = None if path is None else read_bond_csv(path)
    if pairs is not None and sim.source_index is not None:
        pairs = np.asarray(pairs)
        n = len(sim.source_index)
        if (pairs.ndim == 2 and np.issubdtype(pairs.dtype, np.integer)
                and ((pairs >= 0) & (pairs < n)).all()):
            # the file's rows -> the reordered particles (invalid rows are left for
            # add_bonds to name as they are in the file)

            pairs = inverse_order(sim.source_index)[pairs]
    try:
        sim.add_bonds(params, pairs)
    except InputError as exc:
        raise InputError(str(exc).replace("bonds:", "bonds.file:" if path else "bonds:", 1)) from None


def _check_servo_areas(sim, case: Case, k: int) -> None:
    """A servo wall needs its loaded area: given, or from the opposite box walls or
    periodic lengths along the other axes (else its speed is NaN at the first step)."""
    servo = np.flatnonzero(sim.wall_motion == dem.WALL_SERVO)
    if not len(servo):
        return
    areas = np.empty(len(sim.walls))
    dem.wall_areas(sim.wall_point, sim.wall_normal, sim.servo, sim.box_lo, sim.box_hi,
                   sim.periodic_len, sim.dim, areas)
    for w in servo:
        if not (math.isfinite(areas[w]) and areas[w] > 0):
            prefix = f"{case.source}: " if case.source else ""
            raise InputError(f"{prefix}stages[{k}]: wall \"{sim.walls[w].name}\" is servo-controlled "
                             f"but its loaded area is unknown (no opposite box walls or "
                             f"periodic lengths along the other axes): give its area")


def check_stages(case: Case) -> None:
    """Build the case's simulation and apply every stage's changes in turn, so that
    what only shows when a stage starts (a servo wall without a loaded area, a box
    motion on an axis that is not periodic) is an InputError before a run writes."""
    sim = build_simulation(case)
    try:
        for k in range(len(case.stages)):
            apply_stage(sim, case, k)
    except InputError as exc:
        prefix = f"{case.source}: " if case.source else ""
        if str(exc).startswith(prefix):
            raise
        raise InputError(f"{prefix}{exc}") from None
