"""The boundaries of a Simulation: its rigid walls and its periodic box.

:func:`walls_bundle` makes the :class:`~demstep.state.Walls` bundle of a list of
:class:`~demstep.walls.Wall`; :func:`set_wall_motion` and :func:`set_box` change how a
wall or a periodic length moves between stages (fixed, prescribed, servo-controlled);
:func:`wall_stress`, :func:`extents` and :func:`love_stress` read the stresses the
boundaries carry. The servo control itself runs in the compiled step
(:func:`demstep.kernels.dem.advance`, stage 4).
"""

from __future__ import annotations

import math

import numpy as np

from demstep.errors import InputError
from demstep.kernels import dem
from demstep.state import ROLL_WIDTH, Walls

WALL_MOTIONS = {"fixed": dem.WALL_FIXED, "velocity": dem.WALL_VELOCITY, "servo": dem.WALL_SERVO}
BOX_MOTIONS = {"fixed": dem.BOX_FIXED, "rate": dem.BOX_RATE, "servo": dem.BOX_SERVO}


def walls_bundle(walls, dim: int, box_length, x, r, particle_id) -> Walls:
    """The Walls bundle of ``walls`` in ``dim`` dimensions, checked against the periodic
    ``box_length`` (3,) (a wall cannot cross a periodic axis) and the particles (centres
    ``x`` (N, 3) [L], radii ``r``; none may lie more than half inside a wall);
    ``particle_id(k)`` names particle k in messages."""
    for wall in walls:
        if wall.dim != dim:
            raise InputError(f"wall {wall.name!r}: has {wall.dim} components, the simulation {dim}")
        normal = np.asarray(wall.normal, dtype=np.float64)
        for k in np.flatnonzero(box_length[:dim] > 0):
            if abs(normal[k]) > 1e-12 * np.linalg.norm(normal):
                raise InputError(f"wall {wall.name!r}: its normal {normal.tolist()} has a "
                                 f"component along the periodic axis {'xyz'[k]} (a wall "
                                 "cannot cross a periodic box)")
    nw = len(walls)
    z3 = np.zeros((nw, 3))
    point, normal, vel = z3.copy(), z3.copy(), z3.copy()
    motion = np.zeros(nw, dtype=np.int64)
    servo = np.zeros((nw, 5))
    for k, wall in enumerate(walls):
        point[k, :dim] = wall.point
        normal[k, :dim] = wall.normal
        vel[k, :dim] = wall.velocity
        motion[k] = WALL_MOTIONS[wall.motion]
        servo[k] = (wall.target_stress, wall.servo_gain, wall.max_speed, wall.area,
                    wall.servo_factor)
    # axis-aligned walls bounding the specimen (used for loaded areas)
    box_lo = -np.ones(3, dtype=np.int64)
    box_hi = -np.ones(3, dtype=np.int64)
    for k in range(nw):
        axis = int(np.argmax(np.abs(normal[k])))
        if abs(abs(normal[k, axis]) - 1.0) < 1e-12:
            if normal[k, axis] > 0:
                box_lo[axis] = k
            else:
                box_hi[axis] = k
    if nw:
        dist = np.einsum("pwk,wk->pw", x[:, None, :] - point[None], normal)
        deep = dist < 0.5 * r[:, None]
        if deep.any():
            p, k = np.argwhere(deep)[0]
            raise InputError(f"wall {walls[k].name!r}: cuts deep into particle "
                             f"{particle_id(p)} "
                             f"(centre {dist[p, k]:.4g} from the wall, radius {r[p]:.4g})")
    z0 = np.zeros((0, 3))
    return Walls(point, normal, vel, np.zeros(nw), motion, servo, z3.copy(), z3.copy(),
                 z3.copy(), point.copy(), np.zeros(nw), np.zeros(nw, dtype=np.int64),
                 np.zeros(nw), box_lo, box_hi, np.zeros(0, dtype=np.int64),
                 np.zeros(0, dtype=np.int64), z0, z0.copy(), np.zeros(0),
                 np.zeros((0, ROLL_WIDTH)), np.zeros(0))


def set_box(sim, axis: int, motion: str = "fixed", rate: float = 0.0,
            target_stress: float = 0.0, servo_factor: float = 0.1, servo_gain: float = 0.0,
            max_speed: float = np.inf):
    """Motion of ``sim``'s periodic length along ``axis``: 'fixed'; 'rate' (dL/dt =
    ``rate`` [L/T]); 'servo' (hold the Love stress at ``target_stress`` [M/(L T^2)], gain
    as for servo walls: automatic with ``servo_factor`` unless ``servo_gain`` > 0). The
    work done by the changing box enters the ledger (``work_box``)."""
    if not (0 <= axis < sim.dim) or sim.periodic_len[axis] <= 0:
        raise InputError(f"box axis {axis}: not a periodic axis of this simulation")
    if motion not in BOX_MOTIONS:
        raise InputError(f"box motion: must be fixed, rate or servo, got {motion!r}")
    for name, value in (("target_stress", target_stress), ("servo_factor", servo_factor),
                        ("servo_gain", servo_gain)):
        if not (math.isfinite(value) and value >= 0):
            raise InputError(f"box {name}: must be finite and >= 0, got {value!r}")
    if not (max_speed > 0) or not math.isfinite(rate):
        raise InputError(f"box: max_speed must be > 0 and rate finite, got {max_speed!r}, {rate!r}")
    sim.box_motion[axis] = BOX_MOTIONS[motion]
    sim.box_servo[axis] = (target_stress, rate if motion == "rate" else servo_gain,
                           max_speed, 0.0, servo_factor)


def set_wall_motion(sim, index: int, motion: str, velocity=None, target_stress=None,
                    servo_gain=None, servo_factor=None, max_speed=None, area=None,
                    friction=None):
    """Change wall ``index`` of ``sim`` between stages: 'fixed', 'velocity' (``velocity``
    [L/T], dim components) or 'servo' (``target_stress`` [M/(L T^2)], ``servo_gain``,
    ``servo_factor``, ``max_speed``, ``area`` as in :class:`demstep.walls.Wall`);
    ``friction`` overrides the law's wall friction (takes effect at the next run)."""
    wall = sim.walls[index]
    if motion not in WALL_MOTIONS:
        raise InputError(f"wall {wall.name!r}: motion must be fixed, velocity or servo, got {motion!r}")
    if velocity is not None:
        vel = np.asarray(velocity, dtype=np.float64).reshape(-1)
        if vel.shape != (sim.dim,) or not np.isfinite(vel).all():
            raise InputError(f"wall {wall.name!r}: velocity must have {sim.dim} finite components")
        wall.velocity = vel
    columns = {"target_stress": dem.S_TARGET, "servo_gain": dem.S_GAIN,
               "servo_factor": dem.S_FACTOR, "area": dem.S_AREA}
    for key, value in (("target_stress", target_stress), ("servo_gain", servo_gain),
                       ("servo_factor", servo_factor), ("area", area)):
        if value is not None:
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"wall {wall.name!r}: {key} must be finite and >= 0, got {value!r}")
            setattr(wall, key, float(value))
            sim.servo[index, columns[key]] = float(value)
    if max_speed is not None:
        if not (max_speed > 0):
            raise InputError(f"wall {wall.name!r}: max_speed must be > 0, got {max_speed!r}")
        wall.max_speed = float(max_speed)
        sim.servo[index, dem.S_MAXSPEED] = float(max_speed)
    if friction is not None:
        if not (math.isfinite(friction) and friction >= 0):
            raise InputError(f"wall {wall.name!r}: friction must be finite and >= 0, got {friction!r}")
        wall.friction = float(friction)
    wall.motion = motion
    sim.wall_motion[index] = WALL_MOTIONS[motion]
    sim.wall_vel[index] = 0.0
    if motion == "velocity":
        sim.wall_vel[index, :sim.dim] = wall.velocity


def wall_stress(sim) -> np.ndarray:
    """Compressive normal stress on each wall [M/(L T^2)] (per unit thickness in 2D):
    the normal force the particles exert on the wall over its loaded area."""
    push = -np.einsum("wk,wk->w", sim.wall_force, sim.wall_normal)
    dem.wall_areas(sim.wall_point, sim.wall_normal, sim.servo, sim.box_lo, sim.box_hi,
                   sim.periodic_len, sim.dim, sim.wall_areas)
    return push / sim.wall_areas


def extents(sim) -> np.ndarray:
    """Specimen extents per axis [L] (periodic lengths or box-wall gaps; NaN unknown)."""
    out = np.empty(3)
    dem.box_extents(sim.wall_point, sim.box_lo, sim.box_hi, sim.periodic_len, sim.dim, out)
    return out[:sim.dim]


def love_stress(sim) -> np.ndarray:
    """Diagonal of the average stress from particle-particle contacts [M/(L T^2)]:
    sigma_kk = (1/V) sum over contacts of F_k d_k (Love-Weber; compression
    positive), V the box volume (area in 2D). Wall contacts are not included."""
    volume = float(np.prod(extents(sim)))
    return sim.box_state[0, :sim.dim] / volume
