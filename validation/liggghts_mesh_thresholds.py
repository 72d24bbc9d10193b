"""LIGGGHTS' stability threshold of a packing held by triangle-mesh walls, beside
demstep's certified step with and without the mesh contacts.

    python validation/liggghts_mesh_thresholds.py [--quick] [--cases PATTERN ...]
        [--steps N] [--tol 1e-3] [--regen-states] [--states-only] [--out FILE] [--keep]

What is run
-----------
A container of four STL meshes (written with meshio from ``demstep.mesh.shapes`` into
``validation/states/mesh/``), every one of material type 2, 100 times stiffer than the
spheres (type 1):

* ``cylinder48.stl``: a tube of 48 side facets (96 triangles) around the z axis, its
  corners on the circle of radius CYL_RADIUS, normals inward;
* ``floor.stl``: a square plate of 2 triangles in z = 0;
* ``pyramid.stl``: the 4 sloping faces of a square pyramid standing on the floor at
  the axis (its base, which would lie in the floor, left out);
* ``lid.stl``: a square plate of 2 triangles written in z = 0, placed by
  ``move 0 0 Z`` (LIGGGHTS' ``fix mesh/surface`` keyword, the same words given to
  ``demstep dt --mesh``).

The packing is prepared *in LIGGGHTS* (Hertz, frictionless, normal dashpots of
restitution 0.1 and ``fix viscous``; no tangential dashpot, see the quirks of
``liggghts_thresholds.py``): polydisperse spheres (radii uniform in [0.8, 1.2] x R0)
inserted at random in the tube settle on the floor and the pyramid under a weak gravity
(stage A1); gravity is switched off and the lid (``fix move/mesh``) comes down from just
above the bed until the particles push it (``fix mesh/surface/stress``), then in steps
of 2.5 mm, each followed by a pause at rest, until they push it with ``lid_force`` at
the end of a pause (A2: a lid driven continuously measures the drag and the waves of
the moving bed, not the static force); the lid is then fixed at that height Z
(recomputed as the start height minus speed x dt x steps moved, and given to both
codes) and the packing relaxed until the kinetic energy is below 1e-18 J (B). Rattlers
(spheres outside the 4-core of the firm contacts, particle-mesh contacts included) are
removed and A2 + B repeated, also when the static lid force has fallen below half the
target, until no contact or near contact (pair or particle-mesh) has |gap| < MARGIN
mean diameters; a seed whose backbone has one is rejected (the next seed). The
relaxation's ``fix viscous`` is a tenth of ``liggghts_thresholds.py``'s: a frictionless
packing in the 48-facet tube can creep as a whole about the axis (a slow rigid rotation
held back only by the facets' corners and the pyramid), which a strong viscous force
slows down without stopping. The state is dumped by LIGGGHTS at rest (``validation/states/mesh-container.dump``,
%.17g, BOX BOUNDS ``ff ff ff``): a static, pre-stressed equilibrium without gravity,
held by the cylinder, floor, pyramid and lid.

The threshold of each case is measured exactly as ``liggghts_thresholds.py`` does for
its periodic states (its ``Runner`` judges each trial and its ``bisect_threshold``
brackets and bisects; the protocol, the half-step kinetic energy observable and why N
and the growth factor are what they are: see its docstring), with the meshes as
``fix wall/gran model hertz tangential history mesh`` walls and friction 0.5 on every
contact. Cases: Hertz undamped (``coefficientRestitution`` 1) with rotation free
(``fix nve/sphere``) and locked (``fix nve``, spins zero), and restitution 0.5
(LIGGGHTS' dashpots, tangential damping on) with rotation.

Then ``demstep dt DUMP --materials mats.toml --model hertz --mesh 'F type 2' ...``
(``--no-rotation``, ``--restitution 0.5`` as the case) certifies the step (a) with the
four meshes and (b) without any mesh. Contacts are counted in both codes: LIGGGHTS'
``compute wall/gran/local id`` and ``compute pair/gran/local id`` dumped at the state
(one row per contact it computes), demstep's from the notes of its JSON and, contact
by contact, from ``demstep.engine.meshes.touching_meshes`` (the rule ``demstep dt``
uses); a particle-mesh pair the two codes count differently is listed with its
geometry. Where the critical mode sits: demstep's JSON (``critical_mode``) and, for
LIGGGHTS, the per-atom half-step kinetic energy at the end of an unstable run 1 %
above the bracket (the growing mode dominates it). ``demstep dt`` reads a LIGGGHTS dump
in LIGGGHTS' convention, whose lever arm of a wall contact is r - delta/2 (its default
surface model); with rotation, demstep's exact step is also recomputed through its API
with the arm of demstep's own engine, the distance to the contact point, r - delta
(``exact_with_contact_point_arm``), which puts it above LIGGGHTS' threshold.

``--container box``: the plane-wall contrast, the same preparation in a box of six
plane walls (meshes of two triangles in LIGGGHTS) of the spheres' own material (type 1);
demstep is run with the six planes as ``--wall`` (and with them as ``--mesh``, and
without). State ``validation/states/plane-box.dump``, results
``validation/results/liggghts_plane_box_thresholds.json``.

LIGGGHTS 3.8.0 quirks met here: ``hard_particles yes`` is needed for the meshes'
E = 5e9 Pa in SI units; ``run N pre no`` aborts (the message lost in the MPI abort)
once a ``fix move/mesh`` is active, so the lid loop uses ``run N post no``; the force
of ``fix mesh/surface/stress`` is reported doubled on a run's set-up step, so it is
read only after a step.

``--quick``: a smaller container (about 120 spheres), N = 4000, tol 1e-2, the state
built in a temporary folder; about a minute. Results: ``validation/results/
liggghts_mesh_thresholds.json`` (``.quick.json`` with --quick), docs in
``docs/validation-meshes.md``.

Every LIGGGHTS run is serial (one process, OMP_NUM_THREADS=1).
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import math
import os
import re
import shutil
import sys
import tempfile
import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path
from types import SimpleNamespace

import meshio
import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(REPO / "src"))
os.environ["PYTHONPATH"] = os.pathsep.join(
    [str(REPO / "src")] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])

import liggghts_thresholds as lt  # noqa: E402
from compare_liggghts import estimates_by_method, run_cli  # noqa: E402
from liggghts_thresholds import (BLOWUP, DENSITY, GROWTH_FACTOR, KN, MARGIN, MU,  # noqa: E402
                                 PERTURBATION, POISSON, R0, RELAX_KE_TOL, YOUNGS, beta_of,
                                 read_dump, run_liggghts, sphere_mass)

from demstep.engine.meshes import touching_meshes  # noqa: E402
from demstep.mesh import read_mesh, shapes  # noqa: E402

STATES = HERE / "states"
MESH_DIR = STATES / "mesh"
RESULTS = HERE / "results"
DEFAULT_OUT = RESULTS / "liggghts_mesh_thresholds.json"
DOC = REPO / "docs" / "validation-meshes.md"

MESH_YOUNGS = 100.0 * YOUNGS   # Pa, the meshes' material (type 2)
MESH_NAMES = ("cylinder48", "floor", "pyramid", "lid")  # the container's (set by configure)
MESH_TYPE = 2                  # their material (set by configure)
BOX_NAMES = ("xlo", "xhi", "ylo", "yhi", "floor", "lid")
CYL_FACETS = 48
RADII = (0.8, 1.2)             # x R0, uniform
PHI_INSERT = 0.30              # solid fraction of the random insertion in the tube
SETTLE_G = 2.0                 # m/s^2, gravity of stage A1 only
LID_SPEED = 0.02               # m/s
LID_CHECK = 20                 # steps between the checks of the lid force (approach)
PRESS_MOVE = 100               # steps of lid motion per pressing cycle (2.5 mm)
PRESS_REST = 1500              # steps at rest after each
RELAX_CHUNKS = 40              # at most 40 x 5000 steps of relaxation (see "creep")
MAX_ROUNDS = 10                # press-relax-clean rounds per seed
RELAX_VISCOUS = 0.1            # fix viscous of the relaxation / that of liggghts_thresholds


@dataclass(frozen=True)
class Setup:
    """The container and its packing."""

    name: str
    n_insert: int
    cyl_radius: float      # m, corners of the 48 facets on this circle (box: half its side)
    pyr_base: float        # m
    pyr_height: float      # m
    lid_force: float       # N, the lid stops when the particles push it this hard
    seed: int
    kind: str = "cylinder"  # or "box": six plane walls of the particles' material


FULL = Setup("mesh-container", 400, 4.0, 3.0, 1.5, 2.0e5, 20261207)
QUICK = Setup("mesh-container-quick", 120, 2.5, 2.0, 1.0, 8.0e4, 20261207)
BOX = Setup("plane-box", 300, 3.0, 0.0, 0.0, 1.5e5, 20261207, "box")


def configure(setup: Setup) -> None:
    """The container's mesh names and material type (module globals of this script)."""
    global MESH_NAMES, MESH_TYPE
    if setup.kind == "box":
        MESH_NAMES, MESH_TYPE = BOX_NAMES, 1
    else:
        MESH_NAMES, MESH_TYPE = ("cylinder48", "floor", "pyramid", "lid"), 2


def wall_youngs() -> float:
    """Young's modulus of the container's material [Pa]."""
    return MESH_YOUNGS if MESH_TYPE == 2 else YOUNGS


def box_planes(setup: Setup, lid_z: float) -> list[str]:
    """``demstep dt --wall`` of the box's six planes (point:normal into the packing), in
    the order of BOX_NAMES."""
    a = setup.cyl_radius
    return [f"{-a!r},0,0:1,0,0", f"{a!r},0,0:-1,0,0", f"0,{-a!r},0:0,1,0", f"0,{a!r},0:0,-1,0",
            "0,0,0:0,0,1", f"0,0,{lid_z!r}:0,0,-1"]

CASES = (  # (name, restitution or None, rotation)
    ("mesh-hertz-undamped-rot", None, True),
    ("mesh-hertz-undamped-norot", None, False),
    ("mesh-hertz-e0.5-rot", 0.5, True),
)


# ---------------------------------------------------------------------------- meshes
def _inscribed(setup: Setup) -> float:
    """Radius of the circle inscribed in the 48-gon [m] (box: half its side)."""
    if setup.kind == "box":
        return setup.cyl_radius
    return setup.cyl_radius * math.cos(math.pi / CYL_FACETS)


def tube_height(setup: Setup) -> float:
    """Height of the tube [m]: the random insertion at PHI_INSERT fits in it."""
    r = R0 * np.array(RADII)
    mean_r3 = (r[1] ** 4 - r[0] ** 4) / (4 * (r[1] - r[0]))
    vol = setup.n_insert * 4 / 3 * math.pi * mean_r3
    area = (math.pi if setup.kind != "box" else 4.0) * (_inscribed(setup) - 1.2 * R0) ** 2
    return float(math.ceil(vol / PHI_INSERT / area + 2.0))


def write_meshes(setup: Setup, folder: Path) -> dict:
    """The four STL files (ASCII, meshio) of the container in ``folder``; their paths."""
    folder.mkdir(parents=True, exist_ok=True)
    h = tube_height(setup)
    plate = 2.0 * setup.cyl_radius + 1.0
    pyr = shapes.pyramid(setup.pyr_base, setup.pyr_height)
    sides = np.asarray(pyr.triangles)[np.asarray(pyr.normals)[:, 2] > 0]  # drop the base
    cyl = shapes.cylinder(CYL_FACETS, setup.cyl_radius, h).flipped()
    floor = shapes.square(plate)
    lid = shapes.square(plate).flipped()
    meshes = {"cylinder48": (cyl.vertices, cyl.triangles), "floor": (floor.vertices, floor.triangles),
              "pyramid": (pyr.vertices, sides), "lid": (lid.vertices, lid.triangles)}
    if setup.kind == "box":  # four side plates (squares of 2 triangles) facing the inside
        a = setup.cyl_radius
        u = np.array([-1, 1, 1, -1], float) * (a + 0.5)    # along the wall
        w = np.array([0, 0, 1, 1], float) * h              # up
        tri = np.array([[0, 1, 2], [0, 2, 3]])
        meshes = {
            "xlo": (np.column_stack([np.full(4, -a), u, w]), tri[:, ::-1]),
            "xhi": (np.column_stack([np.full(4, a), u, w]), tri),
            "ylo": (np.column_stack([u, np.full(4, -a), w]), tri),
            "yhi": (np.column_stack([u, np.full(4, a), w]), tri[:, ::-1]),
            "floor": (floor.vertices, floor.triangles), "lid": (lid.vertices, lid.triangles)}
    paths = {}
    for name, (v, t) in meshes.items():
        path = folder / f"{name}.stl"
        meshio.write_points_cells(str(path), np.asarray(v, float), [("triangle", np.asarray(t))],
                                  file_format="stl", binary=False)
        paths[name] = path
    return paths


def box_of(setup: Setup) -> tuple[np.ndarray, np.ndarray]:
    """Simulation box (lo, side) [m]: the tube with 1 m to spare on every side."""
    h = tube_height(setup)
    lo = np.array([-setup.cyl_radius - 1.0, -setup.cyl_radius - 1.0, -1.0])
    side = np.array([2 * setup.cyl_radius + 2.0, 2 * setup.cyl_radius + 2.0, h + 2.0])
    return lo, side


def mesh_specs(paths: dict, lid_z: float | None, rel_to: Path | None = None) -> dict:
    """The ``fix mesh/surface`` words of every mesh (also ``demstep dt --mesh``): the
    file, ``type 2`` and, for the lid, ``move 0 0 Z``. Meshes without a lid_z: no lid."""
    out = {}
    for name in MESH_NAMES:
        if name == "lid" and lid_z is None:
            continue
        p = paths[name]
        p = p.relative_to(rel_to) if rel_to is not None else p
        spec = f"{p} type {MESH_TYPE}"
        if name == "lid":
            spec += f" move 0.0 0.0 {lid_z!r}"
        out[name] = spec
    return out


def demstep_meshes(paths: dict, lid_z: float) -> list:
    """The meshes as demstep reads them (the same words as LIGGGHTS)."""
    out = []
    for name, spec in mesh_specs(paths, lid_z).items():
        words = spec.split()
        rest = " ".join(words[3:])  # after 'FILE type T'
        out.append(read_mesh(words[0], rest))
    return out


# ---------------------------------------------------------------------------- LIGGGHTS input
def model_params(restitution: float | None, mu: float = MU, tangential_damping: bool = True) -> dict:
    """Hertz parameters of both materials (type 1 spheres, type 2 meshes)."""
    e = 1.0 if restitution is None else restitution
    return {"model": "hertz", "E": [YOUNGS, MESH_YOUNGS], "nu": [POISSON, POISSON],
            "restitution": e, "beta": beta_of(e) if e < 1 else 0.0, "mu": mu,
            "tangential_damping": tangential_damping, "density": DENSITY,
            "liggghts_model": "hertz"}


def model_lines(params: dict, mu: float | None = None) -> list[str]:
    """pair_style and the two materials' properties (``mu`` overrides the friction)."""
    mu = params["mu"] if mu is None else mu
    td = "on" if params["tangential_damping"] else "off"
    e = params["restitution"]
    return [
        f"pair_style gran model hertz tangential history tangential_damping {td}",
        "pair_coeff * *",
        "fix m1 all property/global youngsModulus peratomtype "
        + " ".join(repr(float(v)) for v in params["E"]),
        "fix m2 all property/global poissonsRatio peratomtype "
        + " ".join(repr(float(v)) for v in params["nu"]),
        f"fix m3 all property/global coefficientRestitution peratomtypepair 2 {e!r} {e!r} {e!r} {e!r}",
        f"fix m4 all property/global coefficientFriction peratomtypepair 2 {mu!r} {mu!r} {mu!r} {mu!r}",
    ]


def wall_lines(paths: dict, lid_z: float | None, params: dict, stress_lid: bool = False) -> list[str]:
    """The meshes (``fix mesh/surface``; the lid ``mesh/surface/stress`` when its force
    is wanted) and their ``fix wall/gran``."""
    specs = mesh_specs(paths, lid_z)
    lines = []
    for name, spec in specs.items():
        style = "mesh/surface/stress" if (name == "lid" and stress_lid) else "mesh/surface"
        lines.append(f"fix {name} all {style} file {spec}")
    td = "on" if params["tangential_damping"] else "off"
    lines.append(f"fix walls all wall/gran model hertz tangential history mesh n_meshes {len(specs)} "
                 f"meshes {' '.join(specs)} tangential_damping {td}")
    return lines


def header(data_file: str) -> list[str]:
    """Set-up of every run: the box not periodic; ``hard_particles yes`` (LIGGGHTS
    refuses Young's moduli above 1e9 Pa in SI units without it: the meshes' 5e9)."""
    return lt.header_lines(data_file, 0.1 * R0, "f f f") + ["hard_particles yes"]


# ---------------------------------------------------------------------------- preparation
def random_insertion(setup: Setup, rng) -> tuple[np.ndarray, np.ndarray]:
    """Non-overlapping spheres at random in the tube (clear of the pyramid), largest
    first: centres (n, 3), radii (n,) [m]."""
    n = setup.n_insert
    r = np.sort(R0 * rng.uniform(*RADII, size=n))[::-1]
    h = tube_height(setup) - 1.0
    rin = _inscribed(setup)
    half = max(0.5 * setup.pyr_base, 1e-12)
    x = np.empty((n, 3))
    for k in range(n):
        for _ in range(200_000):
            if setup.kind == "box":
                xy = (rin - 1.05 * r[k]) * (2 * rng.random(2) - 1)
            else:
                rho = (rin - 1.05 * r[k]) * math.sqrt(rng.random())
                phi = 2 * math.pi * rng.random()
                xy = rho * np.array([math.cos(phi), math.sin(phi)])
            p = np.array([xy[0], xy[1], r[k] + (h - 2 * r[k]) * rng.random()])
            m = max(abs(p[0]), abs(p[1]))
            ground = setup.pyr_height * (1 - m / half) if m < half else 0.0
            if p[2] - ground < 1.5 * r[k] or p[2] < 1.05 * r[k]:
                continue
            if k and np.any(((x[:k] - p) ** 2).sum(1) < (r[:k] + r[k]) ** 2 * 1.0001):
                continue
            x[k] = p
            break
        else:
            raise RuntimeError("random insertion failed: lower PHI_INSERT")
    return x, r


def prep_dt(r_min: float) -> float:
    """Time step of the preparation [s]: a tenth of sqrt(m_min / k) for a sphere of
    radius r_min pressed 1 % of its radius into a mesh."""
    e_star = 1.0 / ((1 - POISSON ** 2) / YOUNGS + (1 - POISSON ** 2) / wall_youngs())
    k = 2.0 * e_star * math.sqrt(r_min * 0.01 * r_min)
    return 0.1 * math.sqrt(float(sphere_mass(r_min)) / k)


def gamma_viscous(m_ref: float) -> float:
    """``fix viscous`` coefficient [N s/m] of the relaxations (as liggghts_thresholds)."""
    return 2.0 * m_ref * 0.05 * math.sqrt(6.0 * KN / m_ref)


def _prep_params() -> dict:
    return model_params(0.1, mu=0.0, tangential_damping=False)


def _write_state_data(path: Path, setup: Setup, x, r, v=None, w=None):
    lo, side = box_of(setup)
    lt.write_data(path, x, r, side, v, w, lo=lo, atom_types=2)


def _dump_only_lines(name: str) -> list[str]:
    return [*lt.dump_lines("dpos", name), "run 0", "undump dpos"]


def stage_settle(setup: Setup, paths: dict, folder: Path, x, r, log) -> dict:
    """A1: settle under SETTLE_G onto the floor and the pyramid (no lid)."""
    folder.mkdir(parents=True, exist_ok=True)
    _write_state_data(folder / "start.data", setup, x, r)
    params = _prep_params()
    m_ref = float(sphere_mass(R0))
    dt = prep_dt(float(r.min()))
    g = gamma_viscous(m_ref)
    lines = header("start.data") + model_lines(params) + wall_lines(paths, None, params) + [
        "fix integr all nve/sphere",
        f"fix grav all gravity {SETTLE_G!r} vector 0.0 0.0 -1.0",
        f"fix visc all viscous {0.1 * g!r}",
        f"timestep {dt!r}",
        "thermo_style custom step atoms ke",
        "thermo_modify lost error norm no",
        "thermo 2000",
        "run 12000",
        "unfix visc",
        f"fix visc all viscous {g!r}",
        "run 8000",
    ] + _dump_only_lines("settled.dump")
    rc, out = run_liggghts("\n".join(lines) + "\n", folder, timeout=1800)
    if rc != 0:
        raise RuntimeError(f"settling: LIGGGHTS failed ({rc}):\n{out[-3000:]}")
    log(f"    settled ({(folder / 'settled.dump').stat().st_size} bytes)")
    return {"dt": dt, "gravity": SETTLE_G, "gamma_viscous": [0.1 * g, g], "steps": [12000, 8000]}


def stage_press(setup: Setup, paths: dict, folder: Path, st: dict, log,
                lid_start: float | None = None) -> tuple[float, dict]:
    """A2: no gravity; the lid comes down (from just above the bed, or from
    ``lid_start``) at LID_SPEED under a weak ``fix viscous`` until the particles push
    it with a twentieth of ``lid_force`` (the approach), then in steps of
    PRESS_MOVE steps of motion, each followed by PRESS_REST steps at rest under the
    relaxation's damping, until they push it with ``lid_force`` at the end of a rest (a
    lid pushed on continuously measures the drag and the waves of the moving bed, far
    above the static force). Returns its height Z [m] and a record."""
    x, r = lt._positions(st), st["radius"]
    _write_state_data(folder / "press.data", setup, x, r)
    params = _prep_params()
    dt = prep_dt(float(r.min()))
    g = gamma_viscous(float(sphere_mass(R0)))
    first = lid_start is None
    z0 = float(np.round((x[:, 2] + r).max() + 0.1, 3)) if first else lid_start
    unload = 3000 if first else 1  # (at least 1 step: LIGGGHTS' set-up step doubles f_lid)
    touch = 0.05 * setup.lid_force
    lines = header("press.data") + model_lines(params) + wall_lines(paths, z0, params, True) + [
        "fix integr all nve/sphere",
        f"fix visc all viscous {0.1 * g!r}",
        f"timestep {dt!r}",
        "thermo_style custom step atoms ke f_lid[3]",
        "thermo_modify lost error norm no",
        "thermo 1000",
        f"run {unload}",
        "variable fz equal abs(f_lid[3])",
        "variable s equal step",
        f'if "${{fz}} > {touch!r}" then "jump SELF approached"',
        f"fix mv all move/mesh mesh lid linear 0.0 0.0 {-LID_SPEED!r}",
        "variable a loop 200000",
        "label approach",
        f"run {LID_CHECK} post no",  # ('pre no' aborts with fix move/mesh)
        f'if "${{fz}} > {touch!r}" then "jump SELF touched"',
        "next a",
        "jump SELF approach",
        "label touched",
        "unfix mv",
        'print "APPROACH_END ${s}"',
        "label approached",
        "unfix visc",
        f"fix visc all viscous {g!r}",
        "variable q loop 2000",
        "label press",
        f"fix mv all move/mesh mesh lid linear 0.0 0.0 {-LID_SPEED!r}",
        f"run {PRESS_MOVE} post no",
        "unfix mv",
        'print "MOVED"',
        f"run {PRESS_REST} post no",
        f'if "${{fz}} > {setup.lid_force!r}" then "jump SELF pressed"',
        "next q",
        "jump SELF press",
        "label pressed",
        'print "LID_STOP ${fz}"',
    ] + _dump_only_lines("pressed.dump")
    rc, out = run_liggghts("\n".join(lines) + "\n", folder, timeout=1800)
    m = re.search(r"^LID_STOP (\S+)", out, re.M)
    if rc != 0 or not m:
        raise RuntimeError(f"pressing: LIGGGHTS failed ({rc}):\n{out[-3000:]}")
    a = re.search(r"^APPROACH_END (\d+)", out, re.M)
    approach = int(a.group(1)) - unload if a else 0
    cycles = len(re.findall(r"^MOVED", out, re.M))
    moved = approach + PRESS_MOVE * cycles
    z = float(z0 - LID_SPEED * dt * moved)
    log(f"    lid from z = {z0:.6f} down {LID_SPEED * dt * moved:.4f} m ({approach} steps, then "
        f"{cycles} x {PRESS_MOVE}) to {z:.6f}, pushed with {float(m.group(1)):.3g} N")
    return z, {"lid_start": z0, "lid_speed": LID_SPEED, "approach_steps": approach,
               "press_cycles": cycles, "press_move": PRESS_MOVE, "press_rest": PRESS_REST,
               "lid_steps": moved, "unload_steps": unload, "lid_force_target": setup.lid_force,
               "lid_force_at_stop": float(m.group(1)), "dt": dt}


def stage_relax(setup: Setup, paths: dict, folder: Path, x, r, lid_z: float) -> dict:
    """B: relax with the lid fixed at ``lid_z`` until E < RELAX_KE_TOL; dump at rest."""
    folder.mkdir(parents=True, exist_ok=True)
    _write_state_data(folder / "relax.data", setup, x, r)
    params = _prep_params()
    dt = prep_dt(float(r.min()))
    g = RELAX_VISCOUS * gamma_viscous(float(sphere_mass(R0)))
    lines = header("relax.data") + model_lines(params) + wall_lines(paths, lid_z, params) + [
        "fix integr all nve/sphere",
        f"fix visc all viscous {g!r}",
        f"timestep {dt!r}",
    ] + lt._relax_lines(RELAX_KE_TOL, 5000, RELAX_CHUNKS) + [
        "variable ke_end equal ${etot}", 'print "KE_END ${ke_end}"',
    ] + lt._dump_at_rest_lines("state.dump", "diag.dump")
    rc, out = run_liggghts("\n".join(lines) + "\n", folder, timeout=1800)
    m = re.search(r"^KE_END (\S+)", out, re.M)
    if rc != 0 or not m:
        raise RuntimeError(f"{folder.name}: relaxation failed ({rc}):\n{out[-3000:]}")
    steps = re.findall(r"^\s*(\d+)\s+\d+\s+[-+0-9.eE]+", out, flags=re.M)
    return {"dump": folder / "state.dump", "diag": folder / "diag.dump",
            "steps": int(steps[-1]) if steps else 0, "dt": dt, "ke_end": float(m.group(1)),
            "relaxed": "RELAXED" in out}


# ---------------------------------------------------------------------------- geometry
def contacts_of(st: dict, meshes, tol_gap: float = 0.0):
    """Pairs (i, j, overlap) and particle-mesh contacts (particle, mesh, overlap) of a
    state by demstep's rule, near contacts with a gap below ``tol_gap`` [m] included."""
    x, r = lt._positions(st), st["radius"]
    d = x[None] - x[:, None]
    gap = np.sqrt((d * d).sum(-1)) - r[:, None] - r[None]
    iu = np.triu_indices(len(r), 1)
    sel = gap[iu] < tol_gap
    i, j, dp = iu[0][sel], iu[1][sel], -gap[iu][sel]
    p, mk, _, dist = touching_meshes(meshes, x, r, tol_gap / float(r.min()))
    dw = r[p] - dist
    keep = dw > -tol_gap
    return (i, j, dp), (p[keep], mk[keep], dw[keep])


def backbone(st: dict, meshes, margin: float = MARGIN) -> np.ndarray:
    """Mask of the 4-core of the firm contacts (overlap >= margin x mean diameter), the
    particle-mesh contacts counting as fixed neighbours."""
    dmean = 2.0 * st["radius"].mean()
    (i, j, dp), (p, _, dw) = contacts_of(st, meshes)
    firm = dp >= margin * dmean
    i, j = i[firm], j[firm]
    walls = np.bincount(p[dw >= margin * dmean], minlength=len(st["radius"]))
    keep = np.ones(len(st["radius"]), bool)
    while True:
        ok = keep[i] & keep[j]
        deg = np.bincount(np.concatenate([i[ok], j[ok]]), minlength=len(keep)) + walls
        drop = keep & (deg < 4)
        if not drop.any():
            return keep
        keep &= ~drop


def marginal(st: dict, meshes, margin: float = MARGIN) -> int:
    """Number of pairs and particle-mesh contacts with |gap| < margin mean diameters."""
    tol = margin * 2.0 * st["radius"].mean()
    (_, _, dp), (_, _, dw) = contacts_of(st, meshes, tol)
    return int((np.abs(dp) < tol).sum() + (np.abs(dw) < tol).sum())


def summary(st: dict, meshes) -> dict:
    (i, j, dp), (p, mk, dw) = contacts_of(st, meshes)
    n = len(st["radius"])
    dmean = 2.0 * st["radius"].mean()
    z = np.bincount(np.concatenate([i, j, p]), minlength=n)
    return {"n": int(n), "pair_contacts": int(len(i)), "mesh_contacts": int(len(p)),
            "mesh_contacts_per_mesh": {MESH_NAMES[k]: int((mk == k).sum()) for k in range(len(meshes))},
            "mean_coordination_with_meshes": float(z.mean()), "rattlers": int((z == 0).sum()),
            "overlap_rel_pairs": [float(dp.mean() / dmean), float(dp.min() / dmean), float(dp.max() / dmean)],
            "overlap_rel_mesh": [float(dw.mean() / dmean), float(dw.min() / dmean), float(dw.max() / dmean)],
            "r_min": float(st["radius"].min()), "r_max": float(st["radius"].max()),
            "m_min": float(st["mass"].min()), "bounds": st["bounds"]}


def mean_normal_force(st: dict, meshes) -> float:
    """Mean Hertz normal force [N] over the pair and particle-mesh contacts."""
    (i, j, dp), (p, _, dw) = contacts_of(st, meshes)
    r = st["radius"]
    e11 = 1.0 / (2 * (1 - POISSON ** 2) / YOUNGS)
    e12 = 1.0 / ((1 - POISSON ** 2) / YOUNGS + (1 - POISSON ** 2) / wall_youngs())
    fp = 4 / 3 * e11 * np.sqrt(r[i] * r[j] / (r[i] + r[j])) * dp ** 1.5
    fw = 4 / 3 * e12 * np.sqrt(r[p]) * dw ** 1.5
    return float(np.concatenate([fp, fw]).mean())


def lid_force(st: dict, meshes) -> float:
    """Static force [N] of the particles on the lid (the last mesh): the Hertz normal
    forces of its contacts."""
    (_, _, _), (p, mk, dw) = contacts_of(st, meshes)
    sel = mk == len(meshes) - 1
    e12 = 1.0 / ((1 - POISSON ** 2) / YOUNGS + (1 - POISSON ** 2) / wall_youngs())
    return float((4 / 3 * e12 * np.sqrt(st["radius"][p[sel]]) * dw[sel] ** 1.5).sum())


def build_state(setup: Setup, folder: Path, paths: dict, log) -> dict:
    """A1, A2, B and the cleaning; the first seed whose state is clean wins."""
    rejected = []
    for seed in range(setup.seed, setup.seed + 10):
        t0 = time.perf_counter()
        rng = np.random.default_rng(seed)
        x, r = random_insertion(setup, rng)
        log(f"  seed {seed}: {len(r)} spheres inserted in a tube of height {tube_height(setup)} m")
        work = folder / f"seed{seed}"
        a1 = stage_settle(setup, paths, work, x, r, log)
        st = read_dump(work / "settled.dump")
        lid_z, removed, rounds, presses = None, 0, [], []
        for round_ in range(MAX_ROUNDS):
            # press (again: a packing without its rattlers has lost some pressure), relax
            folder_r = work / f"round{round_}"
            folder_r.mkdir(parents=True, exist_ok=True)
            lid_z, a2 = stage_press(setup, paths, folder_r, st, log, lid_z)
            presses.append(a2)
            st = read_dump(folder_r / "pressed.dump")
            meshes = demstep_meshes(paths, lid_z)
            res = stage_relax(setup, paths, folder_r / "relax", lt._positions(st), st["radius"], lid_z)
            rounds.append({k: res[k] for k in ("steps", "ke_end", "relaxed")})
            log(f"    relaxed {res['steps']} steps: kinetic energy {res['ke_end']:.3g} J, "
                f"{len(st['radius'])} spheres")
            st = read_dump(res["dump"])
            bad = marginal(st, meshes)
            f_lid = lid_force(st, meshes)
            rounds[-1]["lid_force"] = f_lid
            if bad == 0 and f_lid >= 0.5 * setup.lid_force:
                break
            if bad == 0:  # the packing crept into a denser one: press again
                log(f"    static lid force {f_lid:.3g} N < half the target: pressing again")
                continue
            keep = backbone(st, meshes)
            if keep.all():
                log(f"    {bad} marginal contacts inside the backbone: seed rejected")
                rejected.append({"seed": seed, "reason": "marginal contact in the backbone"})
                st = None
                break
            if keep.sum() < 0.5 * setup.n_insert:
                rejected.append({"seed": seed, "reason": "the backbone lost half the spheres"})
                st = None
                break
            removed += int((~keep).sum())
            log(f"    {bad} marginal contacts: removing {int((~keep).sum())} rattlers")
            st = {k: (v[keep] if isinstance(v, np.ndarray) and v.shape[:1] == keep.shape else v)
                  for k, v in st.items()}
        else:
            rejected.append({"seed": seed, "reason": f"not clean after {MAX_ROUNDS} rounds"})
            st = None
        if st is None:
            continue
        diag = read_dump(res["diag"])
        fres = np.sqrt(diag["fx"] ** 2 + diag["fy"] ** 2 + diag["fz"] ** 2)
        summ = summary(st, meshes)
        summ.update(residual_force_max=float(fres.max()),
                    residual_force_rel=float(fres.max() / mean_normal_force(st, meshes)),
                    lid_z=lid_z, seed=seed,
                    rattlers_removed=removed, rejected_seeds=rejected,
                    preparation={"settle": a1, "press": presses, "relax": rounds,
                                 "relax_ke_tol": RELAX_KE_TOL, "friction": 0.0,
                                 "contact_damping": "hertz, restitution 0.1, normal dashpot only",
                                 "margin": MARGIN},
                    setup=asdict(setup), tube_height=tube_height(setup),
                    build_wall_s=time.perf_counter() - t0, dump_file=str(res["dump"]))
        return summ
    raise RuntimeError(f"no clean packing in 10 seeds: {rejected}")


# ---------------------------------------------------------------------------- trials
class MeshRunner(lt.Runner):
    """Trials of one case on the mesh-held state (LIGGGHTS verdicts by
    ``liggghts_thresholds.Runner.trial``); ``final_dump`` set: the trial also dumps
    every atom's half-step kinetic energy at its end (``final.dump``)."""

    def __init__(self, name: str, rotation: bool, params: dict, state: dict, setup: Setup,
                 paths: dict, lid_z: float, workdir: Path, seed: int):
        self.case = SimpleNamespace(name=name, rotation=rotation)
        self.params, self.state, self.setup, self.paths, self.lid_z = params, state, setup, paths, lid_z
        self.folder = workdir / name
        self.folder.mkdir(parents=True, exist_ok=True)
        x, r = lt._positions(state), state["radius"]
        self.n = len(r)
        (i, j, _), (p, _, _) = contacts_of(state, demstep_meshes(paths, lid_z))
        touching = np.bincount(np.concatenate([i, j, p]), minlength=self.n) > 0
        rng = np.random.default_rng(seed)
        m = state["mass"]
        m_ref = float(sphere_mass(R0))
        sigma = PERTURBATION * R0 * math.sqrt(KN / m_ref)
        v = rng.normal(0.0, sigma, size=(self.n, 3)) * touching[:, None]
        v[touching] -= (m[touching, None] * v[touching]).sum(0) / m[touching].sum()
        w = np.zeros((self.n, 3))
        if rotation:
            w = rng.normal(0.0, sigma, size=(self.n, 3)) / r[:, None] * touching[:, None]
        self.perturbation = {"seed": seed, "velocity_std": sigma, "perturbed": int(touching.sum()),
                             "rattlers_at_rest": int((~touching).sum())}
        _write_state_data(self.folder / "perturbed.data", setup, x, r, v, w)
        self.trials = []
        self.final_dump = False

    def script(self, dt: float, steps: int) -> str:
        lines = header("perturbed.data") + model_lines(self.params) + \
            wall_lines(self.paths, self.lid_z, self.params) + lt.trial_lines(dt, steps, self.case.rotation)
        if self.final_dump:
            lines += ["dump dfin all custom 1 final.dump id v_ehalf_atom",
                      'dump_modify dfin sort id format "%d %.17g"', "run 0", "undump dfin"]
        return "\n".join(lines) + "\n"


def hint_dt(state: dict, meshes) -> float:
    """A start for the bracketing [s]: min over contacts of sqrt(m* / k_t), k_t the
    Hertz tangent shear stiffness 8 G* sqrt(R* delta) (walls: R* = r, m* = m)."""
    (i, j, dp), (p, _, dw) = contacts_of(state, meshes)
    r, m = state["radius"], state["mass"]
    g1 = 2 * (2 - POISSON) * (1 + POISSON) / YOUNGS
    g2 = 2 * (2 - POISSON) * (1 + POISSON) / wall_youngs()
    kp = 8 / (2 * g1) * np.sqrt(r[i] * r[j] / (r[i] + r[j]) * dp)
    kw = 8 / (g1 + g2) * np.sqrt(r[p] * dw)
    mp = m[i] * m[j] / (m[i] + m[j])
    return float(min(np.sqrt(mp / kp).min(), np.sqrt(m[p] / kw).min()))


def liggghts_mode(runner: MeshRunner, dt: float, steps: int, st: dict, meshes, log) -> dict:
    """The particles holding most of the half-step kinetic energy at the end of an
    unstable run at ``dt`` (the growing mode)."""
    runner.final_dump = True
    try:
        t = runner.trial(dt, steps)
    finally:
        runner.final_dump = False
    runner.trials.pop()  # not part of the bisection
    d = read_dump(runner.folder / "final.dump")
    e = d["v_ehalf_atom"]
    share = e / e.sum()
    top = np.argsort(-share)[:6]
    log(f"    LIGGGHTS' growing mode at dt = {dt:.6g} ({t.reason}): "
        + ", ".join(f"id {int(d['id'][k])} {share[k]:.2f}" for k in top[:4]))
    return {"dt": dt, "unstable": t.unstable, "reason": t.reason, "energy_ratio": t.energy_ratio,
            "particles": [particle_info(st, meshes, int(k), float(share[k])) for k in top]}


# ---------------------------------------------------------------------------- contacts
def liggghts_contacts(setup: Setup, paths: dict, lid_z: float, st: dict, folder: Path) -> dict:
    """LIGGGHTS' own contact list at the state: ``compute wall/gran/local id`` (mesh,
    triangle, particle per contact) and ``compute pair/gran/local id``."""
    folder.mkdir(parents=True, exist_ok=True)
    _write_state_data(folder / "count.data", setup, lt._positions(st), st["radius"])
    params = model_params(None)
    lines = header("count.data") + model_lines(params) + wall_lines(paths, lid_z, params) + [
        "fix integr all nve/sphere",
        "timestep 1e-6",
        "compute cw all wall/gran/local id",
        "compute cp all pair/gran/local id",
        "dump dw all local 1 walls.local c_cw[1] c_cw[2] c_cw[3]",
        "dump dp all local 1 pairs.local c_cp[1] c_cp[2] c_cp[3]",
        "run 0",
    ]
    rc, out = run_liggghts("\n".join(lines) + "\n", folder)
    if rc != 0:
        raise RuntimeError(f"contact count: LIGGGHTS failed ({rc}):\n{out[-3000:]}")

    def rows(name):
        text = (folder / name).read_text().splitlines()
        k = max(i for i, s in enumerate(text) if s.startswith("ITEM: ENTRIES"))
        data = [s.split() for s in text[k + 1:] if s.strip()]
        return np.array(data, dtype=float).reshape(-1, 3)

    w, p = rows("walls.local"), rows("pairs.local")
    ids = st["id"].astype(int)
    index = {int(v): k for k, v in enumerate(ids)}
    wall = [(index[int(pid)], int(mid), int(tid)) for mid, tid, pid in w]
    return {"wall": wall, "pairs": int(len(p)),
            "per_mesh": {MESH_NAMES[k]: int(sum(1 for _, m, _ in wall if m == k))
                         for k in range(len(MESH_NAMES))}}


def particle_info(st: dict, meshes, k: int, share: float | None = None) -> dict:
    """Where particle (row) k is: id, radius, position, its particle-mesh contacts."""
    x, r = lt._positions(st), st["radius"]
    p, mk, _, dist = touching_meshes(meshes, x[k:k + 1], r[k:k + 1], 1e-6)
    info = {"row": k, "id": int(st["id"][k]), "radius": float(r[k]),
            "x": [round(float(v), 4) for v in x[k]],
            "rho": round(float(np.hypot(x[k, 0], x[k, 1])), 4),
            "mesh_contacts": [{"mesh": MESH_NAMES[int(m)], "overlap": float(r[k] - d)}
                              for m, d in zip(mk, dist)]}
    if share is not None:
        info["share"] = share
    return info


def compare_contacts(st: dict, meshes, lig: dict) -> dict:
    """Particle-mesh contacts per (particle, mesh) in both codes; the pairs that differ,
    with their geometry."""
    x, r = lt._positions(st), st["radius"]
    p, mk, normal, dist = touching_meshes(meshes, x, r, 1e-6)
    dem = {}
    for a, b in zip(p, mk):
        dem[(int(a), int(b))] = dem.get((int(a), int(b)), 0) + 1
    lg = {}
    tris = {}
    for a, b, t in lig["wall"]:
        lg[(a, b)] = lg.get((a, b), 0) + 1
        tris.setdefault((a, b), []).append(t)
    diffs = []
    for key in sorted(set(dem) | set(lg)):
        if dem.get(key, 0) != lg.get(key, 0):
            a, b = key
            mesh = meshes[b]
            tri_info = []
            for t in tris.get(key, []):
                pt, kind = closest_points(x[a], np.asarray(mesh.corners)[t])
                tri_info.append({"triangle": t,
                                 "normal": [round(float(v), 4) for v in np.asarray(mesh.normals)[t]],
                                 "overlap": float(r[a] - np.linalg.norm(pt[0] - x[a])),
                                 "closest_on": ("face", "edge", "corner")[int(kind[0])]})
            diffs.append({"particle": particle_info(st, meshes, a), "mesh": MESH_NAMES[b],
                          "liggghts": lg.get(key, 0), "demstep": dem.get(key, 0),
                          "liggghts_triangles": tri_info})
    reach = triangles_within(st, meshes)
    multi = [h for h in reach if len(h["triangles"]) > 1]
    straddle = [h | {"demstep": dem.get((h["particle"], MESH_NAMES.index(h["mesh"])), 0),
                     "liggghts": lg.get((h["particle"], MESH_NAMES.index(h["mesh"])), 0)}
                for h in multi]
    return {"demstep_total": int(len(p)), "liggghts_total": int(len(lig["wall"])),
            "patches_reaching_several_triangles": straddle,
            "demstep_per_mesh": {MESH_NAMES[k]: int((mk == k).sum()) for k in range(len(meshes))},
            "liggghts_per_mesh": lig["per_mesh"], "differences": diffs}


def closest_points(q, c):
    """Closest points of triangles to points (independent of demstep; Ericson's
    region test): ``q`` (K, 3), corners ``c`` (K, 3, 3) -> points (K, 3) and where
    they lie: 0 inside the face, 1 on an edge, 2 on a corner."""
    q, c = np.atleast_2d(q).astype(float), np.asarray(c, float).reshape(-1, 3, 3)
    a, b, cc = c[:, 0], c[:, 1], c[:, 2]
    ab, ac, ap = b - a, cc - a, q - a
    dot = lambda u, v: (u * v).sum(1)  # noqa: E731
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp, cp = q - b, q - cc
    d3, d4, d5, d6 = dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    out = np.empty_like(q)
    kind = np.zeros(len(q), int)
    done = np.zeros(len(q), bool)

    def put(mask, pts, k):
        m = mask & ~done
        out[m] = pts[m]
        kind[m] = k
        done[m] = True

    put((d1 <= 0) & (d2 <= 0), a, 2)
    put((d3 >= 0) & (d4 <= d3), b, 2)
    put((d6 >= 0) & (d5 <= d6), cc, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + (d1 / (d1 - d3))[:, None] * ab, 1)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + (d2 / (d2 - d6))[:, None] * ac, 1)
        put((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
            b + ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[:, None] * (cc - b), 1)
        den = 1.0 / (va + vb + vc)
        put(np.ones(len(q), bool), a + (vb * den)[:, None] * ab + (vc * den)[:, None] * ac, 0)
    return out, kind


def triangles_within(st: dict, meshes, tol: float = 1e-6) -> list[dict]:
    """Every (particle, mesh) whose sphere reaches a triangle of the mesh (closest
    point within r (1 + tol)): the triangles reached and where their closest points
    lie. A patch reaching several triangles of one surface straddles an edge or a
    corner: the case where the codes' rules (one contact per surface; LIGGGHTS' edge
    owners) could count differently."""
    x, r = lt._positions(st), st["radius"]
    out = []
    for mk, mesh in enumerate(meshes):
        corners = np.asarray(mesh.corners)
        for k in range(len(r)):
            q = np.repeat(x[k:k + 1], len(corners), 0)
            pts, kind = closest_points(q, corners)
            d = np.sqrt(((pts - x[k]) ** 2).sum(1))
            hit = np.flatnonzero(d < r[k] * (1 + tol))
            if len(hit):
                out.append({"particle": k, "mesh": MESH_NAMES[mk], "triangles": hit.tolist(),
                            "closest_on": [("face", "edge", "corner")[int(kind[t])] for t in hit],
                            "overlaps": [float(r[k] - d[t]) for t in hit]})
    return out


# ---------------------------------------------------------------------------- demstep
def _shown(path: Path) -> str:
    """A path relative to the repository when inside it (the commands recorded)."""
    try:
        return str(path.relative_to(REPO))
    except ValueError:
        return str(path)


def demstep_args(dump: Path, mats: Path, specs: dict | None, restitution, rotation: bool) -> list[str]:
    """``demstep dt`` of a case (run from the repository root)."""
    args = ["dt", _shown(dump), "--json", "--model", "hertz", "--materials", _shown(mats)]
    if restitution is not None:
        args += ["--restitution", repr(restitution)]
    if not rotation:
        args.append("--no-rotation")
    for spec in (specs or {}).values():
        args += ["--mesh", spec]
    return args


def exact_with_contact_point_arm(argv: list[str]) -> float:
    """demstep's exact step of ``demstep dt`` ``argv`` (through its Python API, from
    the repository root) with the lever arm of every particle-wall contact taken as
    demstep's engine takes it, the distance from the centre to the contact point,
    r - delta, instead of LIGGGHTS' r - delta/2 (the liggghts convention of a dump);
    stiffnesses and dashpots unchanged."""
    from dataclasses import replace

    from demstep.cli import build_parser
    from demstep.cli.dt import load_input
    from demstep.timestep import estimate_time_steps

    cwd = os.getcwd()
    os.chdir(REPO)
    try:
        args = build_parser().parse_args(argv)
        data = load_input(args)
    finally:
        os.chdir(cwd)
    c = data.contacts
    r = data.particles.r[c.i]
    arm = np.where((c.j < 0) & (c.arm_i < r), 2.0 * c.arm_i - r, c.arm_i)  # r - delta
    rotation = data.rotation if args.rotation is None else (args.rotation and data.rotation)
    report = estimate_time_steps(data.particles, replace(c, arm_i=arm), rotation=rotation,
                                 damping=data.damping, methods=["exact"], materials=data.materials,
                                 bodies=data.bodies)
    return float(report.exact.dt)


def write_materials(path: Path) -> None:
    path.write_text(
        "# particles (type 1) and meshes (type 2) of validation/liggghts_mesh_thresholds.py\n"
        f"[[material]]\ntype = 1\nyoungs = {YOUNGS!r}\npoisson = {POISSON!r}\ndensity = {DENSITY!r}\n\n"
        f"[[material]]\ntype = 2\nyoungs = {MESH_YOUNGS!r}\npoisson = {POISSON!r}\ndensity = {DENSITY!r}\n")


def mode_summary(data: dict, st: dict, meshes, n_walls_before: int = 0) -> dict:
    """demstep's critical mode: its top particles (where, which meshes they touch) and
    contacts (walls named)."""
    cm = data.get("critical_mode") or {}
    parts = [particle_info(st, meshes, int(p["index"]), float(p["share"]))
             | {"translation": p.get("translation"), "rotation": p.get("rotation")}
             for p in cm.get("particles", [])[:6]]
    cons = []
    for c in cm.get("contacts", [])[:6]:
        w = c.get("wall")
        cons.append({"i": c["i"], "j": c["j"],
                     "wall": None if w is None else MESH_NAMES[int(w) - n_walls_before],
                     "k_n": c["k_n"], "k_t": c["k_t"], "share": c["share"]})
    return {"participation": cm.get("participation"), "particles": parts, "contacts": cons}


# ---------------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small container, N = 4000, tol 1e-2")
    ap.add_argument("--cases", nargs="+", default=None, help="case names or glob patterns")
    ap.add_argument("--steps", type=int, default=None, help=f"N (default {lt.DEFAULT_STEPS})")
    ap.add_argument("--tol", type=float, default=None, help=f"relative bracket width (default {lt.TOL:g})")
    ap.add_argument("--regen-states", action="store_true", help="rebuild the meshes and the state")
    ap.add_argument("--states-only", action="store_true", help="build the state, no thresholds")
    ap.add_argument("--out", type=Path, default=None, help="JSON results file")
    ap.add_argument("--keep", action="store_true", help="keep the LIGGGHTS work folders")
    ap.add_argument("--container", choices=("cylinder", "box"), default="cylinder",
                    help="box: the contrast case, six plane walls of the particles' own material "
                         "(demstep dt with --wall, and --mesh)")
    args = ap.parse_args(argv)

    setup = QUICK if args.quick else (BOX if args.container == "box" else FULL)
    configure(setup)
    steps = args.steps or (4000 if args.quick else lt.DEFAULT_STEPS)
    tol = args.tol or (1e-2 if args.quick else lt.TOL)
    out_path = args.out or (RESULTS / "liggghts_mesh_thresholds.quick.json" if args.quick else
                            DEFAULT_OUT if setup.kind != "box" else RESULTS / "liggghts_plane_box_thresholds.json")
    cases = [(c[0].replace("mesh-", "box-") if setup.kind == "box" else c[0], *c[1:]) for c in CASES]
    cases = [c for c in cases if not args.cases or any(fnmatch.fnmatch(c[0], p) for p in args.cases)]

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    t_start = time.perf_counter()
    version = lt.liggghts_version()
    workdir = Path(tempfile.mkdtemp(prefix="lig-mesh-"))
    keep_dir = (MESH_DIR if setup.kind != "box" else STATES / setup.name) if not args.quick \
        else workdir / "meshes"
    dump_path = (STATES / f"{setup.name}.dump") if not args.quick else workdir / f"{setup.name}.dump"
    meta_path = keep_dir / "state.json"
    mats = keep_dir / "materials.toml"
    try:
        if args.regen_states or not meta_path.exists() or not dump_path.exists():
            log(f"LIGGGHTS {version}; building {setup.name}")
            paths = write_meshes(setup, keep_dir)
            write_materials(mats)
            meta = build_state(setup, workdir / "prep", paths, log)
            shutil.copyfile(meta.pop("dump_file"), dump_path)
            meta["dump"] = _shown(dump_path)
            meta["meshes"] = {k: _shown(v) for k, v in paths.items()}
            meta["liggghts_version"] = version
            meta_path.write_text(json.dumps(meta, indent=1) + "\n")
            log(f"state {setup.name}: {meta['n']} spheres, {meta['pair_contacts']} pairs, "
                f"{meta['mesh_contacts']} particle-mesh contacts {meta['mesh_contacts_per_mesh']}, "
                f"lid at {meta['lid_z']:.6f} m, residual |F| max {meta['residual_force_max']:.3g} N "
                f"({meta['build_wall_s']:.0f} s)")
        else:
            meta = json.loads(meta_path.read_text())
            paths = {k: REPO / v for k, v in meta["meshes"].items()}
            log(f"LIGGGHTS {version}; reusing {_shown(dump_path)}")
        if args.states_only:
            return 0
        lid_z = meta["lid_z"]
        st = read_dump(dump_path)
        meshes = demstep_meshes(paths, lid_z)
        specs = mesh_specs(paths, lid_z, None if args.quick else REPO)

        lig = liggghts_contacts(setup, paths, lid_z, st, workdir / "count")
        contacts = compare_contacts(st, meshes, lig)
        contacts["liggghts_pairs"] = lig["pairs"]
        log(f"particle-mesh contacts: LIGGGHTS {contacts['liggghts_total']} "
            f"{contacts['liggghts_per_mesh']}, demstep {contacts['demstep_total']} "
            f"{contacts['demstep_per_mesh']}; {len(contacts['differences'])} (particle, mesh) "
            f"pairs differ; LIGGGHTS pairs {lig['pairs']}")

        records = []
        hint = hint_dt(st, meshes)
        for k, (name, e, rot) in enumerate(cases):
            t0 = time.perf_counter()
            params = model_params(e)
            log(f"[{k + 1}/{len(cases)}] {name}: start at {hint:.6g}")
            runner = MeshRunner(name, rot, params, st, setup, paths, lid_z, workdir,
                                zlib.crc32(name.encode()))
            res = lt.bisect_threshold(runner, hint, steps, tol, log)
            mode = liggghts_mode(runner, 1.01 * res["bracket"][1], steps, st, meshes, log)
            lig_rec = {"dt": res["dt"], "bracket": res["bracket"], "rel_width": res["rel_width"],
                       "steps": res["steps"], "n_check": res["checks"],
                       "perturbation": runner.perturbation, "start": hint,
                       "trials": [t.as_dict() for t in runner.trials], "growing_mode": mode,
                       "wall_s": time.perf_counter() - t0}
            dem = {}
            runs = [("with_meshes", specs, None), ("without_meshes", None, None)]
            if setup.kind == "box":
                runs.append(("with_planes", None, box_planes(setup, lid_z)))
            for label, sp, planes in runs:
                a = demstep_args(dump_path, mats, sp, e, rot)
                for w in planes or ():
                    a.append(f"--wall={w}")
                t1 = time.perf_counter()
                data, why = run_cli([sys.executable, "-m", "demstep.cli"], a)
                if data is None:
                    raise RuntimeError(f"{name}: demstep dt failed: {why}")
                est = estimates_by_method(data)
                notes = [s for s in data.get("notes", []) if s.startswith("mesh ")]
                dem[label] = {"command": "demstep " + " ".join(
                                  f"'{w}'" if " " in w else w for w in a),
                              "exact": est.get("exact"), "exact_undamped": est.get("exact-undamped"),
                              "element_coupled": est.get("element-coupled"),
                              "n_contacts": data.get("n_contacts"), "mesh_notes": notes,
                              "critical_mode": mode_summary(data, st, meshes),
                              "wall_s": time.perf_counter() - t1}
            if rot:
                t1 = time.perf_counter()
                dem["with_meshes"]["exact_contact_point_arm"] = exact_with_contact_point_arm(
                    demstep_args(dump_path, mats, specs, e, rot))
                log(f"    demstep exact with its engine's wall arm r - delta: "
                    f"{dem['with_meshes']['exact_contact_point_arm']:.7g} "
                    f"({time.perf_counter() - t1:.0f} s)")
            lo, hi = res["bracket"]
            w, wo = dem["with_meshes"], dem["without_meshes"]
            rec = {"case": name, "restitution": e, "rotation": rot, "parameters": params,
                   "liggghts": lig_rec, "demstep": dem,
                   "ratio_exact_with_meshes": w["exact"] / res["dt"],
                   "ratio_element_with_meshes": w["element_coupled"] / res["dt"],
                   "ratio_exact_without_meshes": wo["exact"] / res["dt"],
                   "exact_with_meshes_below_bracket_top": w["exact"] <= hi,
                   "element_below_bracket": w["element_coupled"] <= lo,
                   "without_meshes_above_bracket": wo["exact"] > hi}
            if "with_planes" in dem:
                rec["ratio_exact_with_planes"] = dem["with_planes"]["exact"] / res["dt"]
            records.append(rec)
            log(f"    -> LIGGGHTS {res['dt']:.7g} [{lo:.7g}, {hi:.7g}]; demstep with meshes "
                f"{w['exact']:.7g} ({rec['ratio_exact_with_meshes'] - 1:+.3%}), element "
                f"{w['element_coupled']:.7g}; without {wo['exact']:.7g} "
                f"({rec['ratio_exact_without_meshes'] - 1:+.3%})")
            report = {
                "description": "LIGGGHTS' measured critical time step of a packing held by "
                               "triangle-mesh walls, and demstep dt with and without the "
                               "meshes; see validation/liggghts_mesh_thresholds.py",
                "liggghts_version": version, "state": meta, "contacts": contacts,
                "materials": _shown(mats),
                "mesh_specs": specs,
                "protocol": {"growth_factor": GROWTH_FACTOR, "blowup": BLOWUP, "chunk": lt.CHUNK,
                             "sample": lt.SAMPLE, "steps": steps, "tolerance": tol,
                             "perturbation": PERTURBATION, "margin": MARGIN,
                             "observable": "kinetic energy of the half-step velocities"},
                "cases": records,
            }
            RESULTS.mkdir(parents=True, exist_ok=True)
            out_path.write_text(json.dumps(report, indent=1) + "\n")
    finally:
        if args.keep:
            log(f"work folders kept in {workdir}")
        else:
            shutil.rmtree(workdir, ignore_errors=True)
    report["wall_s"] = time.perf_counter() - t_start
    out_path.write_text(json.dumps(report, indent=1) + "\n")
    print_table(report)
    log(f"total wall time {report['wall_s']:.1f} s; results in {out_path}")
    return 0


def print_table(report: dict) -> None:
    print(f"{'case':28s} {'LIGGGHTS bracket [s]':>28s} {'dS exact+mesh':>14s} {'ratio':>8s} "
          f"{'element':>11s} {'dS no mesh':>12s} {'ratio':>8s}")
    for rec in report["cases"]:
        lo, hi = rec["liggghts"]["bracket"]
        w, wo = rec["demstep"]["with_meshes"], rec["demstep"]["without_meshes"]
        print(f"{rec['case']:28s} [{lo:.7g}, {hi:.7g}] {w['exact']:14.7g} "
              f"{rec['ratio_exact_with_meshes']:8.4f} {w['element_coupled']:11.5g} "
              f"{wo['exact']:12.7g} {rec['ratio_exact_without_meshes']:8.4f}")


if __name__ == "__main__":
    sys.exit(main())
