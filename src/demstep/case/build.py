"""Building a Simulation from a validated case: particles, law, walls, time step, and
the checks of the initial state (see :mod:`demstep.case.schema` for the keys)."""

from __future__ import annotations

import math

import numpy as np

from demstep.case.schema import (AXES, MAX_COORDINATE_RADII, MAX_INITIAL_OVERLAP, MAX_MAGNITUDE,
                                 MIN_MAGNITUDE, Case, TimestepSection, WallMotion, clump_templates,
                                 feed_items, read_body_file)
from demstep.clumps import clumps_from_members, expand, place, random_quaternions
from demstep.contact.geometry import minimum_image_arrays
from demstep.contact.laws import RollingResistance, law_class
from demstep.energy import EnergyMonitor
from demstep.engine import Damping, Simulation, TimeStep
from demstep.engine.meshes import MeshWall
from demstep.errors import InputError
from demstep.io.formats import read_particle_file
from demstep.kernels.neighbors import build_pair_list
from demstep.mesh import read_mesh
from demstep.packings import SPATIAL_ORDER_MIN, lattice as make_lattice, spatial_order
from demstep.particles import Particles, particle_inertia
from demstep.walls import Wall, box_walls


# -------------------------------------------------------------------- building
def generate_particles(case: Case, with_body: bool = False):
    """Positions (N, dim) [L], radii (N,) [L] and masses (N,) [M] or None of the case
    (and, ``with_body``, the clump of each sphere from a file's body column, or None).
    The "clumps" generator gives its member spheres."""
    p = case.particles
    dim = case.dim
    m = None
    body = None
    if p.generator == "clumps":
        x, r, body_of = expand(_clump_set(case))[:3]
        return (x, r, None, body_of) if with_body else (x, r, None)
    if p.generator == "none":  # (filled by insertion)
        out = np.zeros((0, dim)), np.zeros(0), None
        return out + (None,) if with_body else out
    if p.generator == "lattice":
        lat = make_lattice(p.lattice, p.radius)
        sizes = p.size if isinstance(p.size, list) else [p.size] * dim
        grid = np.stack(np.meshgrid(*[np.arange(s) for s in sizes], indexing="ij"), -1)
        origins = grid.reshape(-1, dim) * lat.cell
        x = (origins[:, None, :] + lat.basis[None]).reshape(-1, dim)
        if p.origin is not None:
            x = x + np.asarray(p.origin)
        keep = np.ones(len(x), dtype=bool)
        tol = 1e-9 * p.radius
        if p.clip_lower is not None:
            keep &= (x >= np.asarray(p.clip_lower) - tol).all(axis=1)
        if p.clip_upper is not None:
            keep &= (x <= np.asarray(p.clip_upper) + tol).all(axis=1)
        x = x[keep]
        if len(x) == 0:
            raise InputError(f"particles.clip_lower: no lattice site inside the clip box "
                             f"[{p.clip_lower}, {p.clip_upper}]")
        r = np.full(len(x), p.radius)
    elif p.generator == "grid":
        rng = np.random.default_rng(p.seed)
        grid = np.stack(np.meshgrid(*[np.arange(c, dtype=float) for c in p.count],
                                    indexing="ij"), -1).reshape(-1, dim)
        x = p.spacing * (grid + 0.5 + p.jitter * rng.uniform(-1.0, 1.0, grid.shape))
        if p.origin is not None:
            x = x + np.asarray(p.origin)
        r = rng.uniform(p.radius_min, p.radius_max, len(x))
    else:
        data = read_particle_file(case.particle_file(), p.format, p.snapshot)
        x, r, m = data.x, data.r, data.m
        body = data.extra.get("body")
    out = np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(r), m
    return out + (body,) if with_body else out


def mass_and_density(path, key: str, density) -> InputError:
    """The error for a particle file with masses (a mass column: CSV ``m``, a dump's
    ``mass``) given together with a density (``key``: ``particles.density`` of a case,
    ``density`` of ``demstep dt --density``): neither ``demstep run`` nor ``demstep dt``
    chooses one of the two silently."""
    return InputError(f"{key}: the particle file {path} has a mass column (m) too; keep one "
                      f"of the two (the file's masses or the density), got {density!r}")


def _particles(case: Case, x, r, m):
    """Particles of the case's spheres (masses from the file, or from the density)."""
    p = case.particles
    fixed = _fixed_flags(case, x)
    if m is None:
        try:
            return Particles.from_density(x, r, p.density, fixed=fixed)
        except InputError as exc:
            if str(exc).startswith("density:"):
                raise InputError(f"particles.{exc}") from None
            raise
    return Particles(x, r, m, particle_inertia(m, r, x.shape[1]), fixed)


def _clump_set(case: Case):
    """The bodies of ``generator = "clumps"``: the templates in turn on the grid."""
    p = case.particles
    templates = clump_templates(case)
    dim = case.dim
    q = None
    if p.file is not None:
        pos, names, q = read_body_file(case)
        order = sorted(set(names))
        chosen = [templates[name] for name in order]
        kind = np.array([order.index(name) for name in names], dtype=np.int64)
    else:
        grid = np.stack(np.meshgrid(*[np.arange(c, dtype=float) for c in p.count],
                                    indexing="ij"), -1).reshape(-1, dim)
        pos = p.spacing * (grid + 0.5)
        chosen = [templates[name] for name in p.templates]
        kind = np.arange(len(pos)) % len(chosen)
    if p.origin is not None:
        pos = pos + np.asarray(p.origin)
    if q is None:
        if p.orientation == "random":
            q = random_quaternions(len(pos), np.random.default_rng(p.seed), dim)
        else:
            q = np.tile([1.0, 0.0, 0.0, 0.0], (len(pos), 1))
    return place(chosen, kind, pos, q, p.density)


def _fixed_flags(case: Case, x: np.ndarray) -> np.ndarray:
    flags = np.zeros(len(x), dtype=bool)
    sel = case.particles.fixed
    if sel is None:
        return flags
    for i in sel.indices:
        if i >= len(x):
            raise InputError(f"particles.fixed.indices: index beyond the {len(x)} particles, got {i}")
        flags[i] = True
    if sel.lower is not None:
        flags |= ((x >= np.asarray(sel.lower)) & (x <= np.asarray(sel.upper))).all(axis=1)
    return flags


def build_law(case: Case):
    """The contact law object of the case."""
    c = case.contact
    cls = law_class(c.law)
    common = dict(mu=c.mu, mu_wall=c.mu_wall, damping_normal=c.damping_normal,
                  damping_tangential=c.damping_tangential, restitution=c.restitution,
                  restitution_tangential=c.restitution_tangential,
                  **{name: getattr(c, name) for name in RollingResistance.field_names()})
    return cls(**{f.name: getattr(c, f.name) for f in cls.own_fields()}, **common)


def apply_motion(wall, motion: WallMotion):
    """Set a Wall's motion settings (before the Simulation exists)."""
    if motion.motion is not None:
        wall.motion = motion.motion
    if motion.velocity is not None:
        wall.velocity = np.asarray(motion.velocity, dtype=np.float64)
    for key in ("target_stress", "servo_gain", "servo_factor", "max_speed", "area", "friction"):
        value = getattr(motion, key)
        if value is not None and hasattr(wall, key):
            setattr(wall, key, float(value))


def build_timestep(ts: TimestepSection):
    """The engine's TimeStep for a (resolved) [timestep] section."""
    return TimeStep(mode=ts.mode, dt=ts.dt, alpha=ts.alpha if ts.alpha is not None else 0.1,
                    safety=ts.safety, method=ts.method, every=ts.every, growth=ts.growth,
                    overlap=ts.overlap, motion=ts.motion)


def build_walls(case: Case, x: np.ndarray, r: np.ndarray) -> list:
    """The walls of the case: box walls first (x-, x+, ...), then [[walls]]."""
    walls = []
    if case.box is not None:
        b = case.box
        if b.lower is not None:
            lower, upper = np.asarray(b.lower), np.asarray(b.upper)
        else:
            lower = (x - r[:, None]).min(axis=0) - b.margin
            upper = (x + r[:, None]).max(axis=0) + b.margin
        periodic = case.periodic_axes()  # (no box wall across a periodic axis)
        walls = [w for w in box_walls(lower, upper) if w.name[0] not in periodic]
        for w in walls:
            if w.name in b.walls:
                apply_motion(w, b.walls[w.name])
    for spec in case.walls:
        w = Wall(np.asarray(spec.point), np.asarray(spec.normal), name=spec.name)
        apply_motion(w, spec)
        walls.append(w)
    return walls


def build_meshes(case: Case, law) -> list[MeshWall]:
    """The mesh walls of the case's [[meshes]]: each file read, checked and transformed
    (:func:`demstep.mesh.read_mesh`), with its material checked against ``law``."""
    walls = []
    for k, spec in enumerate(case.meshes):
        key = f"meshes[{k}]"
        try:
            mesh = read_mesh(case.mesh_file(k), spec.transforms, name=spec.name,
                             file_format=spec.format)
        except InputError as err:
            raise InputError(f"{key}.file: {err}") from None
        try:
            law.wall_params(spec.material or None, spec.friction)
        except InputError as err:
            raise InputError(f"{key}.{err}") from None
        zero = [0.0, 0.0, 0.0]
        walls.append(MeshWall(mesh, name=spec.name, mu=spec.friction,
                              material=dict(spec.material) or None,
                              velocity=spec.velocity or zero, omega=spec.omega or zero,
                              surface_velocity=spec.surface_velocity or zero,
                              center=spec.center or zero, enabled=spec.enabled,
                              finnie_k=spec.finnie_k))
    return walls


def build_simulation(case: Case, checkpoint_dir=None):
    """A Simulation of the case at t = 0 (stage changes are applied by the runner,
    :func:`apply_stage`). Raises InputError (prefixed with the case file) when the
    particles, walls or parameters do not make a valid simulation."""
    try:
        return _build_simulation(case, checkpoint_dir)
    except InputError as exc:
        prefix = f"{case.source}: " if case.source else ""
        if str(exc).startswith(prefix):
            raise
        raise InputError(f"{prefix}{exc}") from None


def _build_simulation(case: Case, checkpoint_dir):
    p = case.particles
    clumps = clump_fixed = body = None
    if p.generator == "clumps":
        clumps = _clump_set(case)
        clump_fixed = _fixed_flags(case, clumps.x)
        particles = None
        x = r = None
    else:
        x, r, m, body = generate_particles(case, with_body=True)
        if m is not None and p.density is not None:
            raise mass_and_density(case.particle_file(), "particles.density", p.density)
    if clumps is None and body is not None and (body >= 0).any():
        if p.density is None:
            raise InputError("particles.density: clumps need a density (the mass properties "
                             "of their members' union)")
        clumps = clumps_from_members(x[body >= 0], r[body >= 0], body[body >= 0], p.density)
        free = body < 0
        x, r, m = x[free], r[free], (None if m is None else m[free])
        clump_fixed = np.zeros(clumps.n, dtype=bool)
    source_index = None
    if p.generator == "none":
        particles = Particles.checked_already(x, r, np.zeros(0), np.zeros(0),
                                              np.zeros(0, dtype=bool))
    elif x is not None and len(x) == 0:
        particles = None
    elif x is not None:
        particles = _particles(case, x, r, m)
        if p.generator == "file" and clumps is None and len(x) >= SPATIAL_ORDER_MIN:
            # a file's particles in spatial order: the engine gathers every pair's data
            # by index, and other codes number particles as they inserted them (2.5x on
            # a dense packing in random order); messages and outputs keep the file's rows
            source_index = spatial_order(x, 2.0 * float(r.max()))
            particles = particles.take(source_index)
            x, r = particles.x, particles.r
    if clumps is not None:
        xm, rm = expand(clumps)[:2]
        x = xm if x is None or len(x) == 0 else np.concatenate([x, xm])
        r = rm if r is None or len(r) == 0 else np.concatenate([r, rm])
    periodic = None
    if case.periodic is not None:
        periodic = [getattr(case.periodic, a) for a in AXES[: case.dim]]
        if all(v is None for v in periodic):
            periodic = None
    timestep = build_timestep(case.timestep)
    en = case.energy
    law = build_law(case)
    sim = Simulation(
        particles, law, walls=build_walls(case, x, r), meshes=build_meshes(case, law),
        gravity=case.gravity,
        periodic=periodic, damping=Damping(case.damping.local, case.damping.viscous),
        timestep=timestep, skin=case.numerics.skin,
        energy=EnergyMonitor(eps=en.eps, every=en.every, action=en.action, floor=en.floor),
        jump_limit=case.numerics.jump_limit, runaway_factor=case.numerics.runaway_factor,
        checkpoint_dir=checkpoint_dir, rotation=case.rotation, clumps=clumps,
        clump_fixed=clump_fixed, source_index=source_index,
        sort_every=case.numerics.sort_every or None,
        feed=[item for _, item in feed_items(case)])
    if case.mass_scaling != 1.0:
        sim.scale_mass(case.mass_scaling)
    check_initial_state(sim, case.numerics.max_initial_overlap)
    return sim


def check_initial_state(sim, max_overlap: float = MAX_INITIAL_OVERLAP) -> None:
    """Refuse an initial state the engine cannot integrate meaningfully (InputError):

    * coordinates beyond :data:`MAX_COORDINATE_RADII` smallest radii from the origin
      (float64 no longer resolves the contacts);
    * a periodic length shorter than the neighbour search needs (three cells of
      2 r_max + skin);
    * coincident centres, or two particles overlapping by more than ``max_overlap``
      of the smaller radius (pairs of fixed particles are exempt);
    * masses, moments of inertia, stiffness, the time step or the energy scale that
      are not finite and positive (e.g. a density whose masses overflow).
    """
    if len(sim.r) == 0:  # (a run filled by insertion: the scales of what it inserts)
        _check_scales(sim)
        return
    r_min = float(sim.r.min())
    far = np.abs(sim.x).max(axis=1)
    k = int(np.argmax(far))
    if far[k] > MAX_COORDINATE_RADII * r_min:
        raise InputError(f"particles: particle {sim.particle_id(k)} lies at {far[k]:.3g} from "
                         f"the origin, more "
                         f"than {MAX_COORDINATE_RADII:g} x the smallest radius "
                         f"({r_min:.3g}): float64 cannot resolve its contacts")
    x = sim.x.copy()
    for axis in range(3):
        if sim.periodic_len[axis] > 0:
            np.mod(x[:, axis], sim.periodic_len[axis], out=x[:, axis])
    pi, pj = build_pair_list(x, sim.r, sim.skin, sim.periodic_len)
    if len(pi):
        d = minimum_image_arrays(x[pj] - x[pi], sim.periodic_len)
        dist = np.linalg.norm(d, axis=1)
        r_i, r_j = sim.r[pi], sim.r[pj]
        relative = (r_i + r_j - dist) / np.minimum(r_i, r_j)
        free = ~(sim.fixed[pi] & sim.fixed[pj])
        sb = sim.bodies.sphere_body
        free &= (sb[pi] < 0) | (sb[pi] != sb[pj])  # members of one body overlap by design
        same = free & (dist <= 1e-12 * (r_i + r_j))
        if same.any():
            q = int(np.flatnonzero(same)[0])
            raise InputError(f"particles: particles {sim.particle_id(pi[q])} and "
                             f"{sim.particle_id(pj[q])} have coincident "
                             f"centres at {x[pi[q], :sim.dim].tolist()}")
        heavy = free & (relative > max_overlap)
        if heavy.any():
            q = int(np.flatnonzero(heavy)[0])
            raise InputError(f"particles: particles {sim.particle_id(pi[q])} and "
                             f"{sim.particle_id(pj[q])} overlap by "
                             f"{relative[q]:.3g} of the smaller radius at the start (centres "
                             f"{dist[q]:.4g} apart, radii {r_i[q]:.4g} and {r_j[q]:.4g}), "
                             f"more than numerics.max_initial_overlap = {max_overlap:g} "
                             f"(raise it to accept such an overlap)")
    _check_scales(sim)


def _check_scales(sim) -> None:
    """Masses, inertia, stiffness, time step and energies finite and > 0."""
    with np.errstate(all="ignore"):
        for name, values in (("mass", sim.m), ("moment of inertia", sim.inertia)):
            bad = ~(np.isfinite(values) & (values > 0))
            if bad.any():
                k = int(np.flatnonzero(bad)[0])
                raise InputError(f"particles.density: the {name} of particle "
                                 f"{sim.particle_id(k)} is "
                                 f"{values[k]:.3g} (radius {sim.r[k]:.3g}): not a finite "
                                 f"positive number")
        k_max = sim.stiffness_max()
        m_min = sim.m_min
        dt_scale = math.sqrt(m_min / k_max) if k_max > 0 else math.inf
        energy = float(k_max * np.float64(sim.radius_max()) ** 2 * max(len(sim.r), 1))
    if not (math.isfinite(k_max) and k_max > 0):
        raise InputError(f"contact: the largest contact stiffness is {k_max:.3g}: not a finite "
                         f"positive number")
    low, high = MIN_MAGNITUDE ** 2, MAX_MAGNITUDE ** 2
    if not (low <= dt_scale <= high and low <= energy <= high):
        raise InputError(f"contact: stiffness {k_max:.3g} with the smallest mass "
                         f"{m_min:.3g} and the largest radius {sim.radius_max():.3g} "
                         f"gives a time scale sqrt(m/K) = {dt_scale:.3g} and energies of "
                         f"{energy:.3g}, outside [{low:g}, {high:g}]: "
                         f"choose consistent units")


