"""LIGGGHTS' own stability threshold of the time step, measured by bisection.

    python validation/liggghts_thresholds.py [--quick] [--cases PATTERN ...]
        [--steps N] [--tol 1e-3] [--regen-states] [--states-only] [--list] [--out FILE]

For every case of a matrix (packing x contact model x damping x rotation) this script
runs LIGGGHTS (serially, one process per trial) from a static, pre-stressed, fully
periodic packing with a tiny random velocity, and finds by bisection on the time step
the largest dt at which the motion stays bounded: LIGGGHTS' *measured* critical time
step. demstep's certified prediction for the same state (``demstep dt DUMP ...``) is
compared with it by ``validation/compare_liggghts.py``.

Outputs
-------
* ``validation/states/*.dump``: LIGGGHTS' own ``dump custom`` of each static state
  (columns ``id type x y z radius mass vx vy vz omegax omegay omegaz``, %.17g, box
  ``pp pp pp``), written *before* any perturbation, at rest.
* ``validation/results/liggghts_thresholds.json``: one record per case (model and all
  its parameters, dump path, threshold and bracket, steps, LIGGGHTS version, wall
  time, every trial). Records are merged by case name into an existing file, so that a
  run with ``--cases`` updates only those cases.

Packings (SI units; all ``boundary p p p``, no gravity, no walls)
-----------------------------------------------------------------
* ``fcc``: 3 x 3 x 3 cubic FCC cells of side 1.5 m (108 spheres, nearest-neighbour
  distance d = 1.5/sqrt(2)), radius d/2 (1 + 1e-3): every one of the 12 neighbour
  contacts per sphere overlaps by 1e-3 d. By symmetry it is an equilibrium of any
  central contact law (linear and Hertz alike). The box side 4.5 m is written exactly
  by LIGGGHTS' dump header (see "quirks").
* ``poly``: 250 spheres, radii uniform in [0.8, 1.2] x 0.5 m, inserted at random at a
  solid fraction of 0.2, then compressed *in LIGGGHTS* (``fix deform``, frictionless,
  contact dashpots plus ``fix viscous``) to a solid fraction of 0.648 (slightly above
  jamming) and relaxed with that strong damping until the kinetic energy is below
  1e-18 J; velocities are then zeroed and the state dumped. Frictionless preparation
  leaves no tangential (history) force, so the state is an equilibrium also with
  friction and zero shear history, which is what a restart from the dump has.
  Rattlers (spheres outside the 4-core of the contacts with overlap >= MARGIN) are
  removed and the rest relaxed again: an overdamped rattler pushed out of a contact
  approaches zero overlap exponentially and stops at an overlap of ~1e-15 m, a contact
  any perturbation opens and closes (non-linear; seen as E/E(0) up to 15 in stable
  runs before this was done). A seed is accepted when no pair has |gap| < MARGIN mean
  diameters (else the next seed). The Hertz cases use their own state ``poly-hertz``,
  relaxed from the linear one with the Hertz law (an equilibrium of linear springs is
  not one of Hertz contacts) and cleaned the same way.

Contact models (mu = 0.5, density 2500 kg/m^3)
---------------------------------------------
* ``linear``: ``model hooke/stiffness tangential history absolute_damping on``,
  kn = kt = 1e6 N/m; dashpots given as absolute coefficients [N s/m]
  ``gamman_abs``/``gammat_abs``, chosen for a restitution e of the *mean pair*:
  gamma = 2 beta sqrt(m* kn), m* = m_ref / 2, m_ref the mass of a sphere of the
  packing's mean radius, beta = -ln e / sqrt(ln^2 e + pi^2). Damping variants:
  ``undamped``; ``n`` (normal dashpot only: ``tangential_damping off``,
  gammat_abs = 0); ``nt`` (normal and tangential dashpots, gamma_t = gamma_n since
  kt = kn); e = 0.5 and 0.9.
* ``hertz``: ``model hertz tangential history``, E = 5e7 Pa, nu = 0.3,
  ``coefficientRestitution`` e (0.5, 0.9), tangential damping on (LIGGGHTS default).
* Rotation ``rot`` (``fix nve/sphere``) or ``norot`` (``fix nve`` with every angular
  velocity set to 0: ``fix nve`` leaves omega untouched, so it stays 0 and the torques
  are ignored; the harness checks that the rotational energy stays exactly 0).

Protocol of one trial, and why N and the growth factor are what they are
------------------------------------------------------------------------
The saved state is turned into a LAMMPS data file (positions at full precision, the
same box) with a random velocity on every sphere that has a contact (a sphere without
contact would only drift), normal with standard deviation A r0 sqrt(kn / m_ref),
A = 1e-9 (displacements of ~1e-9 r0), zero total momentum, and with rotation an
angular velocity of the same scale / r. Every state has no pair with |gap| below
MARGIN = 1e-5 mean diameters, so even an amplitude grown a hundredfold neither opens
nor closes a contact, and no contact slides. The same perturbation (fixed seed per
case) is used for every dt of a case, so the verdicts are monotone in dt.

The observed quantity is E = the kinetic energy of the *half-step* velocities,
v[n+1/2] = v[n] + (dt/2) f[n]/m and w[n+1/2] = w[n] + (dt/2) tq[n]/I, computed at the
end of each step from LIGGGHTS' v, f, omega, torque (atom-style variable, summed by
``compute reduce``), sampled every 10 steps (thermo). A trial is *unstable* when
(a) some sample has E > B E(0), B = 1e6 (LIGGGHTS also checks this every 500 steps and
stops early), or (b) after N steps, max E over the second half > F x max E over the
first half, F = 10, or (c) E is not finite, atoms are lost, or LIGGGHTS dies after its
set-up. Otherwise it is *stable*.

* Why half-step velocities: near the threshold the critical mode flips sign every step
  (step-map eigenvalue ~ -1), so its full-step velocity v[n] = (v[n-1/2] + v[n+1/2])/2
  nearly cancels. In a damped case (eigenvalue -(1 + c eps)) LIGGGHTS' own kinetic
  energy sees the critical mode reduced by (c eps / 2)^2 ~ 1e-8, which delays the
  verdict by ~18 e-folds of growth (a first version using ``ke`` put strongly damped
  thresholds up to 5e-4 too high).
* Why growth between the halves and not E > F E(0): the half-step energy of a stable
  run can exceed E(0) transiently. Undamped, each mode keeps the leapfrog invariant
  v[n+1/2]^2 + w^2 x[n] x[n+1]; started at x = 0 its half-step velocity grows through
  -w^2 x[n] x[n+1] by up to 1 + 1/(2 eps') for a mode at a relative distance eps'
  below the threshold; lightly damped near-critical modes do the same by ~(2/g)^2,
  g = dt c/m per step. The FCC's top frequency is highly degenerate (its critical
  modes hold ~14 % of E(0)), so E/E(0) reached 137 in stable runs 4e-4 below the
  threshold, and a criterion E > 100 E(0) put fcc-linear-undamped-norot one bisection
  step too low. A bounded run has the same maximum in both halves (late growth
  ~ 1 undamped, << 1 damped; the transient peak lies in the first half); an unstable
  one grows. B = 1e6 only catches fast blow-ups early: the transients above stay far
  below it (they would need eps' < 5e-7 or g < 2e-3; the lightest dashpot here,
  e = 0.9 normal only, has g ~ 0.02).
* Why every 10 steps and not only at the chunk ends: above the threshold with
  mu = 0.5, the growing mode makes contacts slide once E/E(0) ~ 1e10; sliding
  dissipates it and leaves the contacts at the Coulomb limit (no tangential stiffness),
  after which E decays again. A check every 500 steps missed such spikes (a first
  version of this harness put the threshold of fcc-linear-n-e0.9-norot 9.7 % too high).
* Number of steps N = 20000 (default). Just above the threshold, dt = dt_c (1 + eps):
  undamped, the critical eigenvalue of the step map leaves the unit circle at -1 as
  -(1 + sqrt(8 eps)), so eps = 1e-6 already grows E by e^(2 sqrt(8e-6) N) ~ e^110.
  With dashpots the crossing is a single real eigenvalue -(1 + c eps), slow: for one
  damped oscillator under LIGGGHTS' scheme (the dashpot sees the half-step velocity)
  c = (W + 2 zeta) / zeta >= 2, W = w dt_c; the matrix's strongly damped cases show
  c ~ 3. The critical mode holds a share s ~ 1/(6 n) of E(0) (n spheres) and must
  end above F E(0), so the verdict flips once 2 c eps N > ln(F / s) ~ 10: the upward
  bias of the bracket is eps ~ 10 / (2 c N) ~ 1e-4 at N = 2e4 and c = 3, a tenth of
  the bisection tolerance. This is checked for every case: after the bisection, the
  stable end of the bracket is run again with 2N steps; if it turns unstable, the
  bisection is redone below it with 2N (then 4N, ...).
* Bracketing starts at a hint (0.3 sqrt(m_min / k_max), k_max the largest contact
  stiffness, tangent stiffness for Hertz; for a damped linear case the measured
  undamped threshold of the same packing and rotation) and moves by factors of 1.2
  until the threshold is bracketed; bisection (geometric mid-points) stops when
  hi / lo - 1 <= tol = 1e-3. The reported threshold is sqrt(lo hi).

Quirks of LIGGGHTS 3.8.0 met here (see also the report in docs/validation-liggghts.md)
-------------------------------------------------------------------------------------
* ``dump custom`` writes the BOX BOUNDS with %g (6 significant digits) whatever
  ``dump_modify format`` says. Box sides are therefore chosen with <= 6 significant
  digits (4.5 m, and a 4-digit side for ``poly``), and the harness checks that the
  dump header reproduces the simulated box exactly.
* ``fix nve`` (no rotation) does not zero angular velocities, it freezes them: an
  initial omega keeps entering the tangential relative velocity. Rotation is locked
  only if omega starts at 0.
* The property names of ``hooke/stiffness`` in ``fix property/global`` are ``kn``,
  ``kt``, ``gamman_abs``, ``gammat_abs`` (with ``absolute_damping on``).
* Re-reading a state from a data file resets the tangential (shear) history to 0.
* Velocity Verlet evaluates the contact forces after the first half kick, so the
  dashpots see the half-step velocity; the damped threshold is where
  4 M - 2 dt C - dt^2 K stops being positive definite (see step_map_check.py).
* Every ``run`` (also with ``pre no``) first re-evaluates the forces with the setup
  flag on: the contact history is not advanced and the dashpots see the full-step
  velocity. In that evaluation a contact with a zero shear history takes the
  non-sliding branch even at mu = 0 (the test is kt |shear| > mu |Fn|, 0 > 0), so its
  tangential dashpot acts: frictionless Hertz relaxations in chunks spun the spheres
  up (no spin damping from ``fix viscous``); the preparation therefore runs without
  tangential dashpot. In the threshold runs this happens once per 500-step chunk and
  is harmless (the measured thresholds match the linearised step map).
* ``thermo`` ``ke`` uses the full-step velocities (blind to the critical mode, see
  above); ``read_data`` silently misreads malformed numbers (``np.float64(3.0)`` as a
  box bound gave 0.5): data files are written with %.17g.

Every run is serial (one process, OMP_NUM_THREADS=1).
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
STATES = HERE / "states"
RESULTS = HERE / "results"
DEFAULT_OUT = RESULTS / "liggghts_thresholds.json"

# ---------------------------------------------------------------------------- constants
DENSITY = 2500.0          # kg/m^3
KN = KT = 1.0e6           # N/m, linear springs
MU = 0.5                  # friction coefficient in the threshold runs
YOUNGS = 5.0e7            # Pa, Hertz
POISSON = 0.3
R0 = 0.5                  # m, (mean) radius
FCC_CELL = 1.5            # m, cubic FCC cell side
FCC_CELLS = 3             # 3^3 cells -> 108 spheres, box 4.5 m
FCC_OVERLAP = 1.0e-3      # overlap / nearest-neighbour distance
POLY_N = 250
POLY_RANGE = (0.8, 1.2)   # radii uniform in this range x R0
POLY_PHI0 = 0.20          # solid fraction of the random insertion
POLY_PHI = 0.648          # target solid fraction after compression (above jamming)
POLY_SEED = 20261130
RELAX_KE_TOL = 1.0e-18    # J, total kinetic energy at which relaxation stops
MARGIN = 1.0e-5           # no pair of a state may have |gap| < MARGIN x mean diameter

PERTURBATION = 1.0e-9     # velocity std = PERTURBATION * R0 * sqrt(kn / m_ref)
GROWTH_FACTOR = 10.0      # unstable when max E over the 2nd half > F x max over the 1st half
BLOWUP = 1.0e6            # unstable at once when E > BLOWUP E(0) (LIGGGHTS stops early)
CHUNK = 500               # steps between the early-stop checks inside LIGGGHTS
SAMPLE = 10               # steps between energy samples (thermo output)
DEFAULT_STEPS = 20_000
TOL = 1.0e-3              # relative width of the final bracket
BRACKET_FACTOR = 1.2
MAX_DOUBLINGS = 3         # N, 2N, 4N, 8N at most
TRIAL_TIMEOUT = 600.0     # s

RESTITUTIONS = (0.5, 0.9)


def beta_of(e: float) -> float:
    """Damping ratio of a linear pair oscillator with restitution e (dimensionless)."""
    ln = math.log(e)
    return -ln / math.sqrt(ln * ln + math.pi * math.pi)


def sphere_mass(r, density=DENSITY):
    """Mass [kg] of spheres of radius r [m]."""
    return density * 4.0 / 3.0 * math.pi * np.asarray(r, dtype=float) ** 3


def hertz_effective(E: float, nu: float) -> tuple[float, float]:
    """Y* and G* [Pa] of two spheres of one material (LIGGGHTS' Yeff, Geff)."""
    return E / (2.0 * (1.0 - nu * nu)), E / (4.0 * (2.0 - nu) * (1.0 + nu))


# ---------------------------------------------------------------------------- cases
@dataclass(frozen=True)
class Case:
    """One cell of the matrix. ``damping``: 'none', 'n' (normal dashpot only) or 'nt'
    (normal and tangential) for linear; 'nt' for Hertz (its tangential damping on)."""

    packing: str            # 'fcc' | 'poly'
    model: str              # 'linear' | 'hertz'
    damping: str            # 'none' | 'n' | 'nt'
    restitution: float | None
    rotation: bool

    @property
    def name(self) -> str:
        d = "undamped" if self.damping == "none" else f"{self.damping}-e{self.restitution:g}"
        if self.model == "hertz":
            d = f"e{self.restitution:g}"
        return f"{self.packing}-{self.model}-{d}-{'rot' if self.rotation else 'norot'}"

    @property
    def state(self) -> str:
        """Name of the static state (file validation/states/<state>.dump)."""
        if self.packing == "fcc":
            return "fcc"
        return f"poly-{self.model}"


def all_cases() -> list[Case]:
    """The full matrix, undamped cases first (their thresholds seed the damped ones)."""
    cases = []
    for packing in ("fcc", "poly"):
        for rot in (True, False):
            cases.append(Case(packing, "linear", "none", None, rot))
        for rot in (True, False):
            for damping in ("n", "nt"):
                for e in RESTITUTIONS:
                    cases.append(Case(packing, "linear", damping, e, rot))
        for e in RESTITUTIONS:
            cases.append(Case(packing, "hertz", "nt", e, True))
    return cases


QUICK_CASES = ("fcc-linear-undamped-rot", "fcc-linear-n-e0.5-rot", "fcc-hertz-e0.5-rot")


def case_parameters(case: Case, m_ref: float) -> dict:
    """Every model parameter of a case (SI), as stored in the JSON record and as passed
    to LIGGGHTS. ``m_ref`` [kg]: the mass of a sphere of the packing's mean radius."""
    p = {"model": case.model, "density": DENSITY, "mu": MU, "rotation": case.rotation,
         "restitution": case.restitution, "m_ref": m_ref, "m_star": 0.5 * m_ref}
    if case.model == "linear":
        beta = beta_of(case.restitution) if case.restitution is not None else 0.0
        gn = 2.0 * beta * math.sqrt(0.5 * m_ref * KN)
        gt = gn * math.sqrt(KT / KN) if case.damping == "nt" else 0.0
        p.update(kn=KN, kt=KT, beta=beta, gamma_n=gn, gamma_t=gt, absolute_damping=True,
                 tangential_damping=case.damping == "nt", E=None, nu=None,
                 liggghts_model="hooke/stiffness")
        if case.damping == "none":
            p.update(gamma_n=0.0, gamma_t=0.0, tangential_damping=False)
    else:
        ys, gs = hertz_effective(YOUNGS, POISSON)
        p.update(E=YOUNGS, nu=POISSON, Y_star=ys, G_star=gs, beta=beta_of(case.restitution),
                 tangential_damping=True, kn=None, kt=None, gamma_n=None, gamma_t=None,
                 liggghts_model="hertz",
                 gamma_note="Hertz: gamma_n = 2 sqrt(5/6) beta sqrt(Sn m*), gamma_t = 2 sqrt(5/6) "
                            "beta sqrt(St m*), per contact (Sn = 2 Y* sqrt(R* delta), "
                            "St = 8 G* sqrt(R* delta), m* = mi mj / (mi + mj))")
    return p


# ---------------------------------------------------------------------------- LIGGGHTS I/O
def liggghts_exe() -> str:
    exe = shutil.which("liggghts")
    if exe is None:
        raise SystemExit("liggghts not found on PATH")
    return exe


def run_liggghts(script: str, folder: Path, timeout: float = TRIAL_TIMEOUT) -> tuple[int, str]:
    """Run ``script`` serially in ``folder``; return (exit code, stdout + stderr).
    A timeout counts as exit code -9."""
    (folder / "in.lmp").write_text(script)
    env = dict(os.environ, OMP_NUM_THREADS="1")
    try:
        proc = subprocess.run([liggghts_exe(), "-in", "in.lmp", "-log", "log.lmp", "-echo", "none"],
                              cwd=folder, env=env, capture_output=True, text=True, errors="replace",
                              timeout=timeout)
        return proc.returncode, proc.stdout + proc.stderr
    except subprocess.TimeoutExpired as exc:
        out = (exc.stdout or b"")
        out = out.decode(errors="replace") if isinstance(out, bytes) else out
        return -9, out


def liggghts_version() -> str:
    """The banner of the installed LIGGGHTS, e.g. 'LIGGGHTS-PUBLIC 3.8.0, compiled ...'."""
    with tempfile.TemporaryDirectory() as tmp:
        _, out = run_liggghts("units si\n", Path(tmp), timeout=60)
    m = re.search(r"LIGGGHTS \(Version ([^)]*)\)", out)
    return m.group(1) if m else "unknown"


def write_data(path: Path, x, r, box, v=None, w=None, title="demstep validation",
               lo=(0.0, 0.0, 0.0), atom_types: int = 1):
    """LAMMPS data file for ``atom_style granular``: rows 'id type diameter density x y z'
    at %.17g (every sphere of type 1); box [lo, lo + L) per axis; ``atom_types`` types
    declared (a mesh wall of type 2 needs 2); a Velocities section 'id vx vy vz wx wy wz'
    when v is given (w defaults to 0)."""
    n = len(x)
    lines = [title, "", f"{n} atoms", f"{atom_types} atom types", ""]
    for k, a in enumerate("xyz"):
        lines.append(f"{float(lo[k])!r} {float(lo[k]) + float(box[k])!r} {a}lo {a}hi")
    lines += ["", "Atoms", ""]
    for i in range(n):
        lines.append("%d 1 %.17g %.17g %.17g %.17g %.17g" % (i + 1, 2.0 * r[i], DENSITY, *x[i]))
    if v is not None:
        w = np.zeros((n, 3)) if w is None else w
        lines += ["", "Velocities", ""]
        for i in range(n):
            lines.append("%d %.17g %.17g %.17g %.17g %.17g %.17g" % (i + 1, *v[i], *w[i]))
    path.write_text("\n".join(lines) + "\n")


DUMP_COLUMNS = "id type x y z radius mass vx vy vz omegax omegay omegaz"


def dump_lines(name: str, filename: str, extra: str = "") -> list[str]:
    """Commands for a one-shot full-precision ``dump custom`` (written at the next
    ``run 0``)."""
    cols = DUMP_COLUMNS + (" " + extra if extra else "")
    fmt = " ".join(["%d", "%d"] + ["%.17g"] * (len(cols.split()) - 2))
    return [f"dump {name} all custom 1 {filename} {cols}",
            f'dump_modify {name} sort id format "{fmt}"']


def read_dump(path: Path) -> dict:
    """Last snapshot of a ``dump custom`` file: columns by name (sorted by id), 'box'
    (3, 2) and 'bounds' (the BOX BOUNDS flags)."""
    lines = Path(path).read_text().splitlines()
    start = max(i for i, s in enumerate(lines) if s.startswith("ITEM: TIMESTEP"))
    n = int(lines[start + 3])
    bounds = lines[start + 4].split()[3:]
    box = np.array([[float(t) for t in lines[start + 5 + k].split()[:2]] for k in range(3)])
    cols = lines[start + 8].split()[2:]
    data = np.array([[float(t) for t in s.split()] for s in lines[start + 9:start + 9 + n]])
    data = data[np.argsort(data[:, cols.index("id")])]
    out = {c: data[:, k] for k, c in enumerate(cols)}
    out.update(box=box, bounds=bounds, n=n)
    return out


def model_lines(params: dict, mu: float | None = None) -> list[str]:
    """pair_style and material properties of a case (``params`` from case_parameters;
    ``mu`` overrides the friction, e.g. 0 for the frictionless preparation)."""
    mu = params["mu"] if mu is None else mu
    if params["model"] == "linear":
        td = "on" if params["tangential_damping"] else "off"
        return [
            "pair_style gran model hooke/stiffness tangential history absolute_damping on "
            f"tangential_damping {td}",
            "pair_coeff * *",
            f"fix m1 all property/global kn peratomtypepair 1 {params['kn']!r}",
            f"fix m2 all property/global kt peratomtypepair 1 {params['kt']!r}",
            f"fix m3 all property/global gamman_abs peratomtypepair 1 {params['gamma_n']!r}",
            f"fix m4 all property/global gammat_abs peratomtypepair 1 {params['gamma_t']!r}",
            f"fix m5 all property/global coefficientFriction peratomtypepair 1 {mu!r}",
        ]
    td = "on" if params["tangential_damping"] else "off"
    return [
        f"pair_style gran model hertz tangential history tangential_damping {td}",
        "pair_coeff * *",
        f"fix m1 all property/global youngsModulus peratomtype {params['E']!r}",
        f"fix m2 all property/global poissonsRatio peratomtype {params['nu']!r}",
        f"fix m3 all property/global coefficientRestitution peratomtypepair 1 {params['restitution']!r}",
        f"fix m4 all property/global coefficientFriction peratomtypepair 1 {mu!r}",
    ]


def header_lines(data_file: str, skin: float, boundary: str = "p p p") -> list[str]:
    return [
        "atom_style granular",
        "atom_modify map array",
        f"boundary {boundary}",
        "newton off",
        "communicate single vel yes",
        "units si",
        f"read_data {data_file}",
        f"neighbor {skin!r} bin",
        "neigh_modify delay 0",
    ]


# ---------------------------------------------------------------------------- geometry
def pair_contacts(x, r, box) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Overlapping pairs (i < j) under the minimum image in the periodic box (3,) [m]:
    indices i, j and overlaps delta = r_i + r_j - |x_i - x_j| > 0 [m]."""
    box = np.asarray(box, dtype=float)
    d = x[None, :, :] - x[:, None, :]
    d -= box * np.round(d / box)
    dist = np.sqrt((d * d).sum(-1))
    delta = r[:, None] + r[None, :] - dist
    iu = np.triu_indices(len(x), 1)
    sel = delta[iu] > 0
    return iu[0][sel], iu[1][sel], delta[iu][sel]


def state_summary(state: dict) -> dict:
    """Contact statistics of a saved state (overlaps relative to the mean diameter)."""
    x = np.stack([state["x"], state["y"], state["z"]], 1)
    r = state["radius"]
    box = state["box"][:, 1] - state["box"][:, 0]
    i, j, delta = pair_contacts(x, r, box)
    n = len(r)
    z_count = np.bincount(np.concatenate([i, j]), minlength=n)
    dmean = 2.0 * r.mean()
    return {"n": int(n), "box": box.tolist(), "contacts": int(len(i)),
            "mean_coordination": 2.0 * len(i) / n,
            "rattlers": int((z_count == 0).sum()),
            "mean_coordination_non_rattlers": float(2.0 * len(i) / max(1, (z_count > 0).sum())),
            "solid_fraction": float(sphere_mass(r, 1.0).sum() / np.prod(box)),
            "overlap_rel_mean": float(delta.mean() / dmean) if len(delta) else 0.0,
            "overlap_rel_max": float(delta.max() / dmean) if len(delta) else 0.0,
            "overlap_rel_min": float(delta.min() / dmean) if len(delta) else 0.0,
            "r_min": float(r.min()), "r_max": float(r.max()), "r_mean": float(r.mean()),
            "m_min": float(state["mass"].min()), "max_speed": float(np.abs(
                np.stack([state["vx"], state["vy"], state["vz"]], 1)).max())}


# ---------------------------------------------------------------------------- states
def _dump_at_rest_lines(dump_file: str, diag_file: str) -> list[str]:
    """Zero every velocity, then write the state dump and a force diagnostic (run 0)."""
    return ["velocity all set 0.0 0.0 0.0",
            "set group all omegax 0.0 omegay 0.0 omegaz 0.0",
            *dump_lines("dstate", dump_file),
            f"dump ddiag all custom 1 {diag_file} id fx fy fz",
            'dump_modify ddiag sort id format "%d %.17g %.17g %.17g"',
            "run 0",
            "undump dstate",
            "undump ddiag"]


def _check_state(dump_path: Path, diag_path: Path | None, box, name: str) -> dict:
    """Check a freshly written state dump (BOX BOUNDS pp pp pp and exactly the
    simulated box) and summarise it, with the largest residual force [N] from the
    force dump of the same step."""
    st = read_dump(dump_path)
    if st["bounds"] != ["pp", "pp", "pp"]:
        raise RuntimeError(f"{name}: BOX BOUNDS flags {st['bounds']}, expected pp pp pp")
    side = st["box"][:, 1] - st["box"][:, 0]
    if not (np.all(st["box"][:, 0] == 0.0) and np.array_equal(side, np.asarray(box, float))):
        raise RuntimeError(f"{name}: the dump header box {st['box'].tolist()} is not the simulated "
                           f"[0, {list(box)}] (LIGGGHTS writes it with %g: use <= 6 digits)")
    summary = state_summary(st)
    if diag_path is not None:
        f = read_dump(diag_path)
        fres = np.sqrt(f["fx"] ** 2 + f["fy"] ** 2 + f["fz"] ** 2)
        summary["residual_force_max"] = float(fres.max())
        summary["residual_force_rel"] = None  # filled by the caller (needs the law)
    return summary


def make_fcc_state(folder: Path) -> dict:
    """The pre-compressed FCC supercell, dumped by LIGGGHTS at rest (run 0)."""
    a = FCC_CELL
    basis = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]]) * a
    g = np.stack(np.meshgrid(*[np.arange(FCC_CELLS)] * 3, indexing="ij"), -1).reshape(-1, 3) * a
    x = (g[:, None, :] + basis[None, :, :]).reshape(-1, 3)
    d = a / math.sqrt(2.0)
    r = np.full(len(x), 0.5 * d * (1.0 + FCC_OVERLAP))
    box = [a * FCC_CELLS] * 3
    folder.mkdir(parents=True, exist_ok=True)
    write_data(folder / "fcc.data", x, r, box)
    params = case_parameters(Case("fcc", "linear", "none", None, True), float(sphere_mass(r[0])))
    lines = header_lines("fcc.data", 0.1 * R0) + model_lines(params) + [
        "fix integr all nve/sphere", "timestep 1e-4"] + _dump_at_rest_lines("state.dump", "diag.dump")
    rc, out = run_liggghts("\n".join(lines) + "\n", folder)
    if rc != 0:
        raise RuntimeError(f"fcc state: LIGGGHTS failed ({rc}):\n{out[-3000:]}")
    return {"box": box, "dump": folder / "state.dump", "diag": folder / "diag.dump",
            "prep": {"cells": FCC_CELLS, "cell": a, "overlap_rel": FCC_OVERLAP}}


def _random_insertion(n, r, box, rng) -> np.ndarray:
    """Random sequential insertion of non-overlapping spheres (periodic box), largest
    first."""
    order = np.argsort(-r)
    x = np.empty((n, 3))
    placed = []
    for k in order:
        for _ in range(100_000):
            p = rng.random(3) * box
            if placed:
                q = x[placed]
                d = q - p
                d -= box * np.round(d / box)
                if np.any((d * d).sum(1) < (r[placed] + r[k]) ** 2 * 1.0001):
                    continue
            x[k] = p
            placed.append(k)
            break
        else:
            raise RuntimeError("random insertion failed: lower POLY_PHI0")
    return x


def _round_side(side: float, digits: int = 4) -> float:
    """A box side with ``digits`` significant digits (exact in LIGGGHTS' %g header)."""
    return float(f"{side:.{digits}g}")


def _relax_lines(ke_tol: float, chunk: int, max_chunks: int) -> list[str]:
    """Run in chunks until the kinetic energy [J] is below ``ke_tol``, at most
    ``max_chunks`` chunks; print RELAXED only if it is."""
    return [
        "compute erot all erotate/sphere",
        "variable etot equal ke+c_erot",
        "thermo_style custom step atoms ke c_erot lx",
        "thermo_modify lost error norm no format float %.17g",
        f"thermo {chunk}",
        f"variable rk loop {max_chunks}",
        "label relax",
        f"run {chunk}",
        f'if "${{etot}} < {ke_tol!r}" then "jump SELF relaxed"',
        "next rk",
        "jump SELF relax",
        "label relaxed",
        f'if "${{etot}} < {ke_tol!r}" then "print RELAXED"',
    ]


def _relax_run(folder: Path, x, r, side: float, law: str, pre: list[str] = ()) -> dict:
    """One LIGGGHTS preparation run in ``folder``: read the spheres (at rest), run the
    ``pre`` commands (e.g. a compression), relax with the frictionless ``law``
    ('linear' or 'hertz'), a strong normal dashpot (restitution 0.1) and ``fix viscous``
    until E < RELAX_KE_TOL, zero the velocities and dump the state (run 0)."""
    folder.mkdir(parents=True, exist_ok=True)
    write_data(folder / "start.data", x, r, [side] * 3)
    m_ref = float(sphere_mass(r.mean()))
    m_min = float(sphere_mass(r.min()))
    case = Case("poly", law, "nt" if law == "hertz" else "n", 0.1, True)
    # no tangential dashpot: with mu = 0 LIGGGHTS still applies it while a contact's
    # shear history is exactly 0, which spins spheres up (fix viscous damps no spin)
    params = {**case_parameters(case, m_ref), "tangential_damping": False}
    dt = 0.1 * math.sqrt(m_min / KN)
    # viscous damping ~critical for a mode at 5 % of a typical frequency sqrt(6 kn / m)
    gamma_visc = 2.0 * m_ref * 0.05 * math.sqrt(6.0 * KN / m_ref)
    lines = header_lines("start.data", 0.2 * R0) + model_lines(params, mu=0.0) + [
        "fix integr all nve/sphere",
        f"fix visc all viscous {gamma_visc!r}",
        f"timestep {dt!r}",
        *pre,
    ] + _relax_lines(RELAX_KE_TOL, 5000, 100) + _dump_at_rest_lines("state.dump", "diag.dump")
    rc, out = run_liggghts("\n".join(lines) + "\n", folder, timeout=1800)
    if rc != 0 or "RELAXED" not in out:
        raise RuntimeError(f"{folder.name}: LIGGGHTS preparation failed ({rc}):\n{out[-3000:]}")
    steps = re.findall(r"^\s*(\d+)\s+\d+\s+[-+0-9.eE]+", out, flags=re.M)
    return {"box": [side] * 3, "dump": folder / "state.dump", "diag": folder / "diag.dump",
            "law": law, "prep": {"dt": dt, "gamma_viscous": gamma_visc, "friction": 0.0,
                                 "contact_damping": f"{law}, restitution 0.1, normal dashpot only",
                                 "relax_ke_tol": RELAX_KE_TOL,
                                 "steps": int(steps[-1]) if steps else 0}}


def _positions(state: dict) -> np.ndarray:
    return np.stack([state["x"], state["y"], state["z"]], 1)


def marginal_pairs(state: dict, margin: float = MARGIN) -> int:
    """Number of pairs whose gap or overlap is below ``margin`` x the mean diameter:
    contacts the perturbation could open, or near-contacts it could close."""
    x, r = _positions(state), state["radius"]
    box = state["box"][:, 1] - state["box"][:, 0]
    d = x[None, :, :] - x[:, None, :]
    d -= box * np.round(d / box)
    gap = np.sqrt((d * d).sum(-1)) - r[:, None] - r[None, :]
    iu = np.triu_indices(len(r), 1)
    return int((np.abs(gap[iu]) < margin * 2.0 * r.mean()).sum())


def backbone(state: dict, margin: float = MARGIN) -> np.ndarray:
    """Mask of the spheres of the 4-core of the firm-contact graph (overlap >= margin x
    mean diameter): a frictionless sphere needs >= 4 contacts to be held in 3D; the
    others are rattlers (resting at ~zero force, often at an overlap of 1e-15)."""
    x, r = _positions(state), state["radius"]
    box = state["box"][:, 1] - state["box"][:, 0]
    i, j, delta = pair_contacts(x, r, box)
    firm = delta >= margin * 2.0 * r.mean()
    i, j = i[firm], j[firm]
    keep = np.ones(len(r), bool)
    while True:
        ok = keep[i] & keep[j]
        deg = np.bincount(np.concatenate([i[ok], j[ok]]), minlength=len(r))
        drop = keep & (deg < 4)
        if not drop.any():
            return keep
        keep &= ~drop


def _clean(folder: Path, res: dict, log) -> dict | None:
    """Remove rattlers (non-backbone spheres) and relax again until no pair is
    marginal; None when a marginal pair lies inside the backbone."""
    removed = 0
    for round_ in range(5):
        st = read_dump(res["dump"])
        if marginal_pairs(st) == 0:
            res["prep"]["rattlers_removed"] = removed
            return res
        keep = backbone(st)
        if keep.all():
            log(f"    marginal pair inside the backbone ({marginal_pairs(st)} pairs): rejected")
            return None
        removed += int((~keep).sum())
        log(f"    removing {int((~keep).sum())} rattlers and relaxing again")
        prep = res["prep"]
        res = _relax_run(folder / f"{res['law']}-clean{round_}", _positions(st)[keep],
                         st["radius"][keep], res["box"][0], res["law"])
        res["prep"] = {**prep, "clean_steps": res["prep"]["steps"]}
    return None


def make_poly_states(folder: Path, log, phi: float = POLY_PHI) -> dict:
    """'poly-linear' and 'poly-hertz': for seeds POLY_SEED, POLY_SEED + 1, ...: random
    insertion (Python), compression with ``fix deform`` and relaxation in LIGGGHTS
    (linear), rattlers removed; then relaxation of that state with Hertz contacts,
    rattlers removed. The first seed whose two states have no marginal pair wins."""
    rejected = []
    for seed in range(POLY_SEED, POLY_SEED + 20):
        rng = np.random.default_rng(seed)
        r = R0 * rng.uniform(*POLY_RANGE, size=POLY_N)
        vol = float(sphere_mass(r, 1.0).sum())
        side0 = _round_side((vol / POLY_PHI0) ** (1 / 3))
        side = _round_side((vol / phi) ** (1 / 3))
        x = _random_insertion(POLY_N, r, np.array([side0] * 3), rng)
        log(f"  poly seed {seed}: {POLY_N} spheres, side {side0} -> {side}")
        compress = [
            f"fix comp all deform 1 x final 0.0 {side!r} y final 0.0 {side!r} z final 0.0 {side!r} remap x",
            "thermo_style custom step atoms ke lx",
            "thermo 5000",
            "run 30000",
            "unfix comp",
            # deform ends at side up to rounding: set it exactly (a change of ~1 ulp)
            f"change_box all x final 0.0 {side!r} y final 0.0 {side!r} z final 0.0 {side!r} "
            "remap units box",
        ]
        lin = _relax_run(folder / f"seed{seed}" / "linear", x, r, side0, "linear", compress)
        lin["box"] = [side] * 3
        lin = _clean(folder / f"seed{seed}", lin, log)
        if lin is None:
            rejected.append({"seed": seed, "reason": "marginal pair in the linear backbone"})
            continue
        st = read_dump(lin["dump"])
        her = _relax_run(folder / f"seed{seed}" / "hertz", _positions(st), st["radius"], side, "hertz")
        her = _clean(folder / f"seed{seed}", her, log)
        if her is None:
            rejected.append({"seed": seed, "reason": "marginal pair in the Hertz backbone"})
            continue
        common = {"n_inserted": POLY_N, "radius_range": [R0 * POLY_RANGE[0], R0 * POLY_RANGE[1]],
                  "seed": seed, "phi_insert": POLY_PHI0, "side_insert": side0, "phi_target": phi,
                  "side": side, "compression_steps": 30000, "margin": MARGIN,
                  "rejected_seeds": rejected}
        lin["prep"] = {**common, **lin["prep"]}
        her["prep"] = {**common, **her["prep"], "from": "poly-linear"}
        return {"poly-linear": lin, "poly-hertz": her}
    raise RuntimeError(f"no clean poly packing in 20 seeds: {rejected}")


def _mean_normal_force(state: dict, law: str) -> float:
    """Mean elastic normal force [N] over the contacts of a state."""
    x = np.stack([state["x"], state["y"], state["z"]], 1)
    r = state["radius"]
    box = state["box"][:, 1] - state["box"][:, 0]
    i, j, delta = pair_contacts(x, r, box)
    if law == "linear":
        fn = KN * delta
    else:
        ys, _ = hertz_effective(YOUNGS, POISSON)
        rs = r[i] * r[j] / (r[i] + r[j])
        fn = 4.0 / 3.0 * ys * np.sqrt(rs) * delta ** 1.5
    return float(fn.mean())


def build_states(names: set[str], regen: bool, log) -> dict:
    """Make (or reuse) the states in validation/states/; return their summaries."""
    STATES.mkdir(parents=True, exist_ok=True)
    meta_path = STATES / "states.json"
    meta = json.loads(meta_path.read_text()) if meta_path.exists() else {}

    def missing(name):
        return regen or name not in meta or not (STATES / f"{name}.dump").exists()

    todo = {}
    with tempfile.TemporaryDirectory(prefix="lig-states-") as tmp:
        folder = Path(tmp)
        t0 = time.perf_counter()
        if "fcc" in names and missing("fcc"):
            todo["fcc"] = make_fcc_state(folder / "fcc")
            todo["fcc"]["law"] = "linear"
        if names & {"poly-linear", "poly-hertz"} and (missing("poly-linear") or missing("poly-hertz")):
            todo.update(make_poly_states(folder, log))
        for name, res in todo.items():
            summary = _check_state(res["dump"], res["diag"], res["box"], name)
            st = read_dump(res["dump"])
            summary["residual_force_rel"] = summary["residual_force_max"] / _mean_normal_force(st, res["law"])
            summary["marginal_pairs"] = marginal_pairs(st)
            summary["law"] = res["law"]
            summary["preparation"] = res["prep"]
            target = STATES / f"{name}.dump"
            shutil.copyfile(res["dump"], target)
            summary["dump"] = str(target.relative_to(REPO))
            meta[name] = summary
            log(f"state {name}: {summary['n']} spheres, Z = {summary['mean_coordination']:.3f} "
                f"({summary['rattlers']} rattlers), overlap/d mean {summary['overlap_rel_mean']:.3g} "
                f"min {summary['overlap_rel_min']:.3g} max {summary['overlap_rel_max']:.3g}, "
                f"residual |F|/<Fn> {summary['residual_force_rel']:.2g}")
        if todo:
            built = time.perf_counter() - t0
            for name in todo:
                meta[name]["build_wall_s"] = built  # of the batch that built it
            log(f"states built in {built:.1f} s")
            meta_path.write_text(json.dumps(meta, indent=1) + "\n")
    return meta


# ---------------------------------------------------------------------------- trials
@dataclass
class Trial:
    """One LIGGGHTS run at time step dt [s] for up to ``steps`` steps."""

    dt: float
    steps: int
    unstable: bool
    reason: str
    steps_run: int
    energy_ratio: float        # max E / E(0) seen (inf when not finite)
    late_growth: float         # max E over the 2nd half / max E over the 1st half
    growth_per_step: float | None  # d ln(amplitude)/d step over the last 200 steps
    max_rot_energy: float
    wall_s: float

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        for k in ("energy_ratio", "late_growth", "growth_per_step"):
            if d[k] is not None and not math.isfinite(d[k]):
                d[k] = str(d[k])
        return d


THERMO_RE = re.compile(r"^\s*(\d+)\s+(\d+)\s+(\S+)\s+(\S+)\s+(\S+)\s*$", re.M)


def half_step_energy_lines(half_dt: float, rotation: bool) -> list[str]:
    """Commands defining ``c_ehalf``: the kinetic energy [J] of the half-step velocities
    v[n+1/2] = v[n] + (dt/2) f[n]/m (and w[n+1/2] = w[n] + (dt/2) tq[n]/I, I = 2/5 m r^2,
    with rotation), computed at the end of step n from v, f (omega, torque). Near the
    threshold the critical mode alternates in sign every step, so its full-step
    velocity v[n] = (v[n-1/2] + v[n+1/2])/2 nearly vanishes: LIGGGHTS' own kinetic
    energy is almost blind to it (by (c eps / 2)^2 ~ 1e-8 in the damped cases)."""
    h = repr(half_dt)
    trans = (f"0.5*mass*((vx+{h}*fx/mass)^2+(vy+{h}*fy/mass)^2+(vz+{h}*fz/mass)^2)")
    expr = trans
    if rotation:
        inertia = "(0.4*mass*r*r)"
        expr += (f"+0.5*{inertia}*((omegax+{h}*tqx/{inertia})^2+(omegay+{h}*tqy/{inertia})^2"
                 f"+(omegaz+{h}*tqz/{inertia})^2)")
    return [f"variable ehalf_atom atom {expr}", "compute ehalf all reduce sum v_ehalf_atom"]


def _float(s: str) -> float:
    try:
        return float(s)
    except ValueError:
        return float("nan")


def trial_lines(dt: float, steps: int, rotation: bool) -> list[str]:
    """The commands of one trial after the set-up (state, contact model, walls): the
    integrator, the half-step energy, LIGGGHTS' set-up (``run 0``, SETUP_OK) and the
    ``steps`` steps in chunks of CHUNK, stopping early when E > BLOWUP E(0) (RUN_END)."""
    integ = "nve/sphere" if rotation else "nve"
    chunks = max(1, math.ceil(steps / CHUNK))
    return [
        f"fix integr all {integ}",
        "compute erot all erotate/sphere",
        *half_step_energy_lines(0.5 * dt, rotation),
        "variable etot equal c_ehalf",
        f"timestep {dt!r}",
        "thermo_style custom step atoms c_ehalf ke c_erot",
        "thermo_modify lost ignore norm no format float %.17g",
        f"thermo {SAMPLE}",
        "run 0",
        'print "SETUP_OK"',
        f"variable limit equal ${{etot}}*{BLOWUP!r}",
        f"variable k loop {chunks}",
        "label chunk",
        f"run {CHUNK} pre no post no",
        'if "${etot} > ${limit}" then "jump SELF done"',
        "next k",
        "jump SELF chunk",
        "label done",
        'print "RUN_END"',
    ]


class Runner:
    """Trials of one case: the perturbed data file is written once (fixed seed), only
    dt and N change."""

    def __init__(self, case: Case, params: dict, state: dict, workdir: Path, seed: int):
        self.case, self.params, self.state = case, params, state
        self.folder = workdir / case.name
        self.folder.mkdir(parents=True, exist_ok=True)
        x = np.stack([state["x"], state["y"], state["z"]], 1)
        r = state["radius"]
        self.n = len(r)
        box = state["box"][:, 1] - state["box"][:, 0]
        i, j, _ = pair_contacts(x, r, box)
        touching = np.bincount(np.concatenate([i, j]), minlength=self.n) > 0
        rng = np.random.default_rng(seed)
        m = state["mass"]
        sigma = PERTURBATION * R0 * math.sqrt(KN / params["m_ref"])
        v = rng.normal(0.0, sigma, size=(self.n, 3)) * touching[:, None]
        v[touching] -= (m[touching, None] * v[touching]).sum(0) / m[touching].sum()
        w = np.zeros((self.n, 3))
        if case.rotation:
            w = rng.normal(0.0, sigma, size=(self.n, 3)) / r[:, None] * touching[:, None]
        self.perturbation = {"seed": seed, "velocity_std": sigma, "perturbed": int(touching.sum()),
                             "rattlers_at_rest": int((~touching).sum())}
        write_data(self.folder / "perturbed.data", x, r, box, v, w)
        self.trials: list[Trial] = []

    def script(self, dt: float, steps: int) -> str:
        lines = header_lines("perturbed.data", 0.1 * R0) + model_lines(self.params) + \
            trial_lines(dt, steps, self.case.rotation)
        return "\n".join(lines) + "\n"

    def trial(self, dt: float, steps: int) -> Trial:
        t0 = time.perf_counter()
        rc, out = run_liggghts(self.script(dt, steps), self.folder)
        wall = time.perf_counter() - t0
        if "SETUP_OK" not in out:
            raise RuntimeError(f"{self.case.name}: LIGGGHTS set-up failed (exit {rc}):\n{out[-3000:]}")
        found = THERMO_RE.findall(out)
        rows = [(int(s), int(a), _float(eh), _float(e)) for s, a, eh, k, e in found]
        if not rows:
            raise RuntimeError(f"{self.case.name}: no thermo output:\n{out[-3000:]}")
        e0 = rows[0][2]
        energies = np.array([eh for _, _, eh, _ in rows])
        finite = np.all(np.isfinite(energies))
        ratio = float(np.nanmax(energies) / e0) if finite else float("inf")
        steps_run = max(s for s, *_ in rows)
        lost = any(a < self.n for _, a, _, _ in rows)
        max_rot = float(np.nanmax([e for *_, e in rows]))
        step_arr = np.array([st for st, *_ in rows])
        late_growth = float("inf")
        if finite:
            first = energies[step_arr <= steps // 2]
            second = energies[step_arr > steps // 2]
            late_growth = float(second.max() / first.max()) if len(second) and first.max() > 0 else 0.0
        growth = None
        if finite and np.all(energies > 0):
            # amplitude growth rate per step: slope of ln(E)/2 over the last 200 steps
            steps_arr = np.array([s for s, *_ in rows], dtype=float)
            last = steps_arr >= steps_arr[-1] - 200
            if last.sum() >= 3 and np.ptp(steps_arr[last]) > 0:
                growth = float(0.5 * np.polyfit(steps_arr[last], np.log(energies[last]), 1)[0])
        if not finite:
            unstable, reason = True, "energy not finite"
        elif lost:
            unstable, reason = True, "atoms lost"
        elif ratio > BLOWUP:
            unstable, reason = True, f"E exceeded {BLOWUP:g} E(0)"
        elif rc != 0 or "RUN_END" not in out:
            unstable, reason = True, f"LIGGGHTS stopped after set-up (exit {rc})"
        elif steps_run < steps:
            raise RuntimeError(f"{self.case.name}: only {steps_run} of {steps} steps, no verdict")
        elif late_growth > GROWTH_FACTOR:
            unstable, reason = True, f"max E of the 2nd half > {GROWTH_FACTOR:g} x that of the 1st"
        else:
            unstable, reason = False, "bounded"
        if not self.case.rotation and max_rot != 0.0:
            raise RuntimeError(f"{self.case.name}: rotation locked but rotational energy {max_rot:g}")
        t = Trial(dt, steps, unstable, reason, steps_run, ratio, late_growth, growth, max_rot, wall)
        self.trials.append(t)
        return t


def bisect_threshold(runner: Runner, hint: float, steps: int, tol: float, log) -> dict:
    """Bracket and bisect the threshold; then confirm the stable end with 2N steps
    (doubling N and bisecting again below it while it turns unstable)."""
    def verdict(dt, n):
        t = runner.trial(dt, n)
        log(f"    dt = {dt:.9g}  N = {n:6d}: {'UNSTABLE' if t.unstable else 'stable  '} "
            f"(E/E0 max {t.energy_ratio:.3g}, late growth {t.late_growth:.3g}, {t.steps_run} steps, "
            f"{t.wall_s:.1f} s)")
        return t.unstable

    lo = hi = None
    dt = hint
    if verdict(dt, steps):
        hi = dt
        while lo is None:
            dt /= BRACKET_FACTOR
            if verdict(dt, steps):
                hi = dt
            else:
                lo = dt
    else:
        lo = dt
        while hi is None:
            dt *= BRACKET_FACTOR
            if verdict(dt, steps):
                hi = dt
            else:
                lo = dt
    n = steps
    checks = []
    for _ in range(MAX_DOUBLINGS + 1):
        while hi / lo - 1.0 > tol:
            mid = math.sqrt(lo * hi)
            if verdict(mid, n):
                hi = mid
            else:
                lo = mid
        still_stable = not verdict(lo, 2 * n)
        checks.append({"dt": lo, "steps": 2 * n, "stable": still_stable})
        if still_stable:
            break
        # the stable end was only slow to grow: redo below it with 2N
        hi, n = lo, 2 * n
        lo = None
        dt = hi
        while lo is None:
            dt /= 1.0 + 10 * tol
            if verdict(dt, n):
                hi = dt
            else:
                lo = dt
    else:
        raise RuntimeError(f"{runner.case.name}: threshold still moving after {MAX_DOUBLINGS} doublings of N")
    return {"dt": math.sqrt(lo * hi), "bracket": [lo, hi], "rel_width": hi / lo - 1.0,
            "steps": n, "checks": checks}


def rough_hint(case: Case, params: dict, state: dict) -> float:
    """0.3 sqrt(m_min / k_max) [s]: k_max the largest contact stiffness (tangent
    stiffness for Hertz, at the largest overlap)."""
    m_min = float(state["mass"].min())
    if case.model == "linear":
        kmax = max(params["kn"], params["kt"])
    else:
        x = np.stack([state["x"], state["y"], state["z"]], 1)
        r = state["radius"]
        box = state["box"][:, 1] - state["box"][:, 0]
        i, j, delta = pair_contacts(x, r, box)
        rs = r[i] * r[j] / (r[i] + r[j])
        root = np.sqrt(rs * delta)
        kmax = float(max((2 * params["Y_star"] * root).max(), (8 * params["G_star"] * root).max()))
    return 0.3 * math.sqrt(m_min / kmax)


# ---------------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help=f"smoke test: only {', '.join(QUICK_CASES)}, N = 2000, tol 1e-2; "
                         "results to liggghts_thresholds.quick.json")
    ap.add_argument("--cases", nargs="+", default=None,
                    help="case names or glob patterns (e.g. 'fcc-*' '*-undamped-*')")
    ap.add_argument("--steps", type=int, default=None, help=f"N (default {DEFAULT_STEPS})")
    ap.add_argument("--tol", type=float, default=None, help=f"relative bracket width (default {TOL:g})")
    ap.add_argument("--regen-states", action="store_true", help="rebuild the saved states")
    ap.add_argument("--list", action="store_true", help="list the case names and exit")
    ap.add_argument("--states-only", action="store_true",
                    help="build (with --regen-states: rebuild) the states of the selected cases, no thresholds")
    ap.add_argument("--out", type=Path, default=None, help="JSON results file")
    ap.add_argument("--keep", action="store_true", help="keep the LIGGGHTS work folders")
    args = ap.parse_args(argv)

    cases = all_cases()
    if args.list:
        print("\n".join(c.name for c in cases))
        return 0
    steps = args.steps or (2000 if args.quick else DEFAULT_STEPS)
    tol = args.tol or (1e-2 if args.quick else TOL)
    out_path = args.out or (RESULTS / "liggghts_thresholds.quick.json" if args.quick else DEFAULT_OUT)
    if args.cases:
        cases = [c for c in cases if any(fnmatch.fnmatch(c.name, p) for p in args.cases)]
    elif args.quick:
        cases = [c for c in cases if c.name in QUICK_CASES]
    if not cases:
        raise SystemExit("no case matches --cases")

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    t_start = time.perf_counter()
    version = liggghts_version()
    log(f"LIGGGHTS {version}; {len(cases)} cases, N = {steps}, tol = {tol:g}")
    meta = build_states({c.state for c in cases}, args.regen_states, log)
    if args.states_only:
        return 0

    RESULTS.mkdir(parents=True, exist_ok=True)
    report = json.loads(out_path.read_text()) if out_path.exists() else {}
    records = {r["case"]: r for r in report.get("cases", [])}
    workdir = Path(tempfile.mkdtemp(prefix="lig-thresholds-"))
    try:
        for k, case in enumerate(cases):
            t0 = time.perf_counter()
            state = read_dump(STATES / f"{case.state}.dump")
            params = case_parameters(case, float(sphere_mass(state["radius"].mean())))
            undamped = Case(case.packing, "linear", "none", None, case.rotation).name
            if case.model == "linear" and case.damping != "none" and undamped in records:
                hint, hint_from = records[undamped]["dt"], undamped
            else:
                hint, hint_from = rough_hint(case, params, state), "0.3 sqrt(m_min/k_max)"
            log(f"[{k + 1}/{len(cases)}] {case.name}: start at {hint:.6g} ({hint_from})")
            seed = zlib.crc32(case.name.encode())  # fixed per case, independent of the run
            runner = Runner(case, params, state, workdir, seed)
            res = bisect_threshold(runner, hint, steps, tol, log)
            wall = time.perf_counter() - t0
            hi_trials = [t for t in runner.trials if t.unstable and t.dt == res["bracket"][1]]
            rec = {
                "case": case.name, "packing": case.packing, "state": case.state,
                "dump": meta[case.state]["dump"], "model": case.model, "damping": case.damping,
                "rotation": case.rotation, "parameters": params,
                "dt": res["dt"], "bracket": res["bracket"], "rel_width": res["rel_width"],
                "steps": res["steps"], "steps_requested": steps, "n_check": res["checks"],
                "growth_per_step_at_hi": hi_trials[-1].growth_per_step if hi_trials else None,
                "growth_factor": GROWTH_FACTOR, "blowup": BLOWUP, "chunk": CHUNK, "tolerance": tol,
                "perturbation": runner.perturbation, "start": hint, "start_from": hint_from,
                "trials": [t.as_dict() for t in runner.trials],
                "liggghts_version": version, "wall_s": wall,
            }
            records[case.name] = rec
            log(f"    -> {case.name}: dt_c = {res['dt']:.9g} in [{res['bracket'][0]:.9g}, "
                f"{res['bracket'][1]:.9g}] ({len(runner.trials)} runs, {wall:.1f} s)")
            order = [c.name for c in all_cases()]
            report = {
                "description": "LIGGGHTS' measured critical time step (bisection), see "
                               "validation/liggghts_thresholds.py",
                "liggghts_version": version,
                "protocol": {"growth_factor": GROWTH_FACTOR, "blowup": BLOWUP, "chunk": CHUNK,
                             "sample": SAMPLE,
                             "observable": "kinetic energy of the half-step velocities",
                             "margin": MARGIN, "tolerance": tol,
                             "perturbation": PERTURBATION, "default_steps": DEFAULT_STEPS,
                             "bracket_factor": BRACKET_FACTOR, "units": "SI (m, kg, s, N)"},
                "states": meta,
                "cases": sorted(records.values(), key=lambda r: order.index(r["case"])
                                if r["case"] in order else len(order)),
            }
            out_path.write_text(json.dumps(report, indent=1) + "\n")
    finally:
        if args.keep:
            log(f"work folders kept in {workdir}")
        else:
            shutil.rmtree(workdir, ignore_errors=True)
    total = time.perf_counter() - t_start
    report["last_run"] = {"cases": [c.name for c in cases], "wall_s": total, "steps": steps, "tol": tol}
    out_path.write_text(json.dumps(report, indent=1) + "\n")
    print_table(report, [c.name for c in cases])
    log(f"total wall time {total:.1f} s; results in {out_path}")
    return 0


def print_table(report: dict, names: list[str]) -> None:
    """Plain-text table of the measured thresholds of ``names``."""
    print(f"{'case':32s} {'dt_c [s]':>14s} {'bracket':>31s} {'N':>6s} {'runs':>5s} {'wall s':>7s}")
    for rec in report["cases"]:
        if rec["case"] not in names:
            continue
        lo, hi = rec["bracket"]
        print(f"{rec['case']:32s} {rec['dt']:14.8g} [{lo:.8g}, {hi:.8g}] {rec['steps']:6d} "
              f"{len(rec['trials']):5d} {rec['wall_s']:7.1f}")


if __name__ == "__main__":
    sys.exit(main())
