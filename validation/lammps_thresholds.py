"""LAMMPS' own stability threshold of the time step (``pair granular``), by bisection,
beside demstep's certified step and the linearised map LAMMPS actually integrates.

    python validation/lammps_thresholds.py [--cases PATTERN ...] [--steps N] [--tol 1e-3]
        [--list] [--analysis-only] [--out FILE]

(default tol 2.5e-4: trials are cheap, ~1.5 s each for 108 spheres x 20000 steps)

Same experiment as ``validation/liggghts_thresholds.py`` (whose protocol, data-file
writer, dump reader, ``Runner`` and ``bisect_threshold`` are imported, not copied):
a static, pre-stressed, fully periodic packing gets a tiny random velocity and LAMMPS
(Debian's ``lmp``, 29 Sep 2021 stable, one serial process per trial) runs it at a
time step dt; the half-step kinetic energy decides stable / unstable (growth of the
second half over the first > 10, or E > 1e6 E(0)); dt is bisected to a relative
bracket of ``--tol`` and the stable end is confirmed with 2N steps.

What differs from the LIGGGHTS harness
--------------------------------------
* The input is LAMMPS' ``pair granular`` (``atom_style sphere``, ``comm_modify vel
  yes``, ``fix nve/sphere`` or ``fix nve`` with omega = 0 for rotation locked). LAMMPS'
  atom-style variables know no omega/torque, so the half-step energy reads them through
  ``compute property/atom``.
* ``liggghts_thresholds.run_liggghts`` is replaced (at import of this module) by
  :func:`run_lammps`, so the imported ``Runner.trial`` runs ``lmp``; the bracketing
  factor is 1.01 instead of 1.2 because every case starts at a model prediction
  (the non-symmetric linearised map below), which only saves trials: the bracket is
  still measured on both sides.
* States: ``slab`` (walls): see :func:`make_slab_state` (``lammps_slab_o1e-3.dump``;
  ``fix wall/gran granular`` with the pair's model, linear springs only).
  ``fcc`` 3 x 3 x 3 cubic FCC cells (108 spheres, box 4.5 m, d = 1.5/sqrt 2),
  radius d/2 (1 + o) with overlap o = 1e-3 and 1e-2 of d (``lammps_fcc_o1e-3.dump``,
  ``lammps_fcc_o1e-2.dump``, written by LAMMPS itself at rest); ``poly``: the jammed
  polydisperse states of the LIGGGHTS harness (``poly-linear.dump``,
  ``poly-hertz.dump``, relaxed with the same elastic normal laws, zero shear history).

Contact models (mu = 0.5, density 2500 kg/m^3)
---------------------------------------------
* linear: ``hooke kn eta`` + ``tangential linear_history kt xgammat mu``, kn = kt = 1e6.
* Hertz: ``hertz/material E eta nu`` + ``tangential mindlin NULL xgammat mu``
  (k_t = 8 G* a, as LIGGGHTS and demstep), E = 5e7, nu = 0.3.
* damping ``velocity`` / ``mass_velocity`` / ``viscoelastic`` / ``tsuji``; LAMMPS'
  dashpot is gamma_n = eta * {1, m*, a m*, sqrt(m* knfac)} (tsuji: eta = alpha(e) from
  the user's e), gamma_t = xgammat gamma_n; xgammat = 1 in damped cases. eta is chosen
  so that gamma_n is the dashpot of restitution 0.5 for the state's contact
  (linear: 2 beta sqrt(m* kn); Hertz: 2 sqrt(5/6) beta sqrt(m* S_n), S_n = 2 E* a);
  tsuji takes e = 0.5 as the user would (which is another dashpot).

demstep
-------
``python -m demstep.cli dt DUMP --json --model linear --kn --ks [--gamma-n --gamma-t]
[--no-rotation]`` (Hertz: ``--model hertz --youngs --poisson``), the dashpots passed as
absolute coefficients (the per-contact LAMMPS dashpot, uniform on every contact of the
FCC states; on ``poly`` only ``velocity`` damping is uniform, so only it is run there).

Linearised maps (numpy/scipy, dense; see docs/validation-lammps.md)
-----------------------------------------------------------------
K = sum_c B_t^T D B_s, C alike, where B_s maps the DOFs to the slip of the contact
point as LAMMPS computes it (rotation arms r_i, r_j: full radii) and B_t maps a contact
force to forces and torques (arms r - delta/2). Variants: ``sym`` (demstep: both arms
r - delta/2), ``nonsym`` (LAMMPS), ``geomean`` (symmetric, both arms sqrt(r (r -
delta/2))), ``full`` (symmetric, both arms r), each also with the pre-stress (geometric) stiffness -F_n/L (I - n n) of the
normal forces (``+geo``). Critical step of LAMMPS' velocity Verlet (dashpot on the
half-step velocity): the smallest h > 0 with det(h^2 K + 2 h C - 4 M) = 0 (a quadratic
eigenvalue problem, linearised and solved by ``scipy.linalg.eig``); undamped 2 /
sqrt(max Re eig(M^-1 K)). For the FCC cases the step map's spectral radius is checked at
h (1 -/+ 1e-4).

Writes ``validation/results/lammps_thresholds.json`` (records merged by case name).
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
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.linalg as sl

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
STATES = HERE / "states"
RESULTS = HERE / "results"
DEFAULT_OUT = RESULTS / "lammps_thresholds.json"
sys.path.insert(0, str(HERE))

import liggghts_thresholds as lt  # noqa: E402
from liggghts_thresholds import (  # noqa: E402
    DENSITY, DUMP_COLUMNS, beta_of, bisect_threshold, hertz_effective, pair_contacts,
    read_dump, sphere_mass, write_data)
from step_map_check import _skew  # noqa: E402

KN = KT = 1.0e6
MU = 0.5
YOUNGS, POISSON = 5.0e7, 0.3
E_TARGET = 0.5
FCC_CELL, FCC_CELLS = 1.5, 3
FCC_OVERLAPS = (1.0e-3, 1.0e-2)
DEFAULT_STEPS = 20_000
TOL = 2.5e-4
HINT_OFFSET = 1.0005       # the first trial at 1.0005 x the model's step (never exactly on it)
TRIAL_TIMEOUT = 600.0
SKIN = 0.05
QEP_MAX = 1000            # above this many DOFs the damped step by secant, not the QEP


# ---------------------------------------------------------------------------- LAMMPS
def lmp_exe() -> str:
    exe = shutil.which("lmp") or shutil.which("lmp_serial")
    if exe is None:
        raise SystemExit("lmp not found on PATH (apt-get install lammps)")
    return exe


def run_lammps(script: str, folder: Path, timeout: float = TRIAL_TIMEOUT) -> tuple[int, str]:
    """Run ``script`` serially with ``lmp`` in ``folder``: (exit code, stdout + stderr);
    a timeout gives -9. Installed as ``liggghts_thresholds.run_liggghts``."""
    (folder / "in.lmp").write_text(script)
    env = dict(os.environ, OMP_NUM_THREADS="1")
    try:
        proc = subprocess.run([lmp_exe(), "-in", "in.lmp", "-log", "log.lmp", "-echo", "none",
                               "-nocite"], cwd=folder, env=env, capture_output=True, text=True,
                              errors="replace", timeout=timeout)
        return proc.returncode, proc.stdout + proc.stderr
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout or b""
        return -9, out.decode(errors="replace") if isinstance(out, bytes) else out


lt.run_liggghts = run_lammps          # the imported Runner.trial runs LAMMPS
lt.BRACKET_FACTOR = 1.01              # cases start at a model prediction


def lammps_version() -> str:
    with tempfile.TemporaryDirectory() as tmp:
        _, out = run_lammps("units si\n", Path(tmp), timeout=60)
    m = re.search(r"LAMMPS \(([^)]*)\)", out)
    return m.group(1) if m else "unknown"


def tsuji_alpha(e: float) -> float:
    """LAMMPS' damping coefficient of ``damping tsuji`` from the user's e (its fit)."""
    c = (1.2728, -4.2783, 11.087, -22.348, 27.467, -18.022, 4.8218)
    return sum(ck * e ** k for k, ck in enumerate(c))


# ---------------------------------------------------------------------------- cases
@dataclass(frozen=True)
class Case:
    state: str            # 'fcc_o1e-3' | 'fcc_o1e-2' | 'poly-linear' | 'poly-hertz'
    model: str            # 'linear' | 'hertz'
    damping: str          # 'none' | 'velocity' | 'mass_velocity' | 'viscoelastic' | 'tsuji'
    rotation: bool

    @property
    def name(self) -> str:
        d = "undamped" if self.damping == "none" else f"{self.damping}-e{E_TARGET:g}"
        st = self.state if self.state[:3] in ("fcc", "sla") else "poly"
        return f"{st}-{self.model}-{d}-{'rot' if self.rotation else 'norot'}"


def all_cases() -> list[Case]:
    cases = []
    for o in ("1e-3", "1e-2"):
        st = f"fcc_o{o}"
        for model in ("linear", "hertz"):
            cases += [Case(st, model, "none", True), Case(st, model, "none", False)]
            damps = ("velocity", "mass_velocity", "viscoelastic", "tsuji") if o == "1e-3" \
                else ("velocity", "tsuji")
            cases += [Case(st, model, d, True) for d in damps]
            cases.append(Case(st, model, "velocity", False))
    st = "slab_o1e-3"
    cases += [Case(st, "linear", "none", True), Case(st, "linear", "none", False),
              Case(st, "linear", "velocity", True), Case(st, "linear", "mass_velocity", True)]
    for model in ("linear", "hertz"):
        st = f"poly-{model}"
        cases += [Case(st, model, "none", True), Case(st, model, "none", False)]
        if model == "linear":
            cases.append(Case(st, model, "velocity", True))
    return cases


def state_path(name: str) -> Path:
    lam = name.startswith("fcc") or name.startswith("slab")
    return STATES / (f"lammps_{name}.dump" if lam else f"{name}.dump")


def contact_table(state: dict) -> dict:
    """Overlapping pairs of a dumped state: i, j, unit normals n (i -> j), overlaps,
    distances, radii, effective radius and mass."""
    x = np.stack([state["x"], state["y"], state["z"]], 1)
    r, m = state["radius"], state["mass"]
    box = state["box"][:, 1] - state["box"][:, 0]
    walls = state["bounds"][2] != "pp"
    if walls:
        box = box.copy()
        box[2] = 1.0e12                 # walls at z = lo, hi: no periodic image in z
    i, j, delta = pair_contacts(x, r, box)
    d = x[j] - x[i]
    d -= box * np.round(d / box)
    dist = np.sqrt((d * d).sum(1))
    ct = {"i": i, "j": j, "n": d / dist[:, None], "delta": delta, "dist": dist, "r": r, "m": m,
          "rs": r[i] * r[j] / (r[i] + r[j]), "ms": m[i] * m[j] / (m[i] + m[j])}
    # wall contacts (flat walls z = lo, z = hi): sphere, normal from the sphere to the
    # wall, overlap; LAMMPS' wall contact: R* = r, m* = m_i, slip and torque arm r
    lo, hi = state["box"][2]
    wi, wn, wd = [], [], []
    if walls:
        for k in range(len(r)):
            for plane, nz in ((lo, -1.0), (hi, 1.0)):
                ov = r[k] - abs(x[k, 2] - plane)
                if ov > 0:
                    wi.append(k), wn.append([0.0, 0.0, nz]), wd.append(ov)
    ct["wall"] = {"i": np.array(wi, dtype=int), "n": np.array(wn).reshape(-1, 3),
                  "delta": np.array(wd)}
    return ct


def case_parameters(case: Case, ct: dict) -> dict:
    """LAMMPS coefficients of a case, and the per-contact stiffnesses and dashpots they
    give (arrays over the contacts of ``ct``)."""
    beta = beta_of(E_TARGET)
    a = np.sqrt(ct["rs"] * ct["delta"])          # LAMMPS' a = sqrt(R* delta)
    ms = ct["ms"]
    p = {"model": case.model, "damping": case.damping, "mu": MU, "rotation": case.rotation,
         "density": DENSITY}
    if case.model == "linear":
        kn = np.full(len(a), KN)
        kt = np.full(len(a), KT)
        knfac = kn
        target = 2.0 * beta * np.sqrt(ms * kn)
        p.update(kn=KN, kt=KT)
    else:
        ys, gs = hertz_effective(YOUNGS, POISSON)
        kn = 2.0 * ys * a                         # tangent of 4/3 E* sqrt(R*) delta^1.5
        kt = 8.0 * gs * a                         # mindlin NULL: 8 G* a
        knfac = 4.0 / 3.0 * ys * a                # LAMMPS' knfac (secant F/delta)
        target = 2.0 * math.sqrt(5.0 / 6.0) * beta * np.sqrt(ms * kn)
        p.update(E=YOUNGS, nu=POISSON, E_star=ys, G_star=gs)
    unit = {"none": np.zeros_like(a), "velocity": np.ones_like(a), "mass_velocity": ms,
            "viscoelastic": a * ms, "tsuji": np.sqrt(ms * knfac)}[case.damping]
    if case.damping == "none":
        eta, xgt = 0.0, 0.0
    elif case.damping == "tsuji":
        eta, xgt = tsuji_alpha(E_TARGET), 1.0
        p["tsuji_e"] = E_TARGET
    else:
        # one coefficient for the whole state: the mean over the contacts (exact on fcc)
        eta, xgt = float(np.mean(target / unit)), 1.0
    gn = eta * unit
    p.update(eta_n=(E_TARGET if case.damping == "tsuji" else eta), eta_effective=eta,
             xgammat=xgt, m_ref=float(sphere_mass(ct["r"].mean())))
    p["per_contact"] = {"kn": kn, "kt": kt, "gamma_n": gn, "gamma_t": xgt * gn}
    w = ct["wall"]
    if len(w["i"]):
        if case.model != "linear":
            raise ValueError("walls: linear springs only here")
        mw = ct["m"][w["i"]]
        aw = np.sqrt(ct["r"][w["i"]] * w["delta"])
        uw = {"none": 0 * mw, "velocity": 1 + 0 * mw, "mass_velocity": mw,
              "viscoelastic": aw * mw, "tsuji": np.sqrt(mw * KN)}[case.damping]
        p["wall_per_contact"] = {"kn": np.full(len(mw), KN), "kt": np.full(len(mw), KT),
                                 "gamma_n": eta * uw, "gamma_t": xgt * eta * uw}
        p["wall_gamma_n"] = float(np.mean(eta * uw))
    p["gamma_n_uniform"] = bool(np.ptp(gn) <= 1e-12 * max(1e-300, float(np.abs(gn).max())))
    p["gamma_n"] = float(gn.mean()) if len(gn) else 0.0
    p["gamma_t"] = xgt * p["gamma_n"]
    return p


def pair_lines(p: dict) -> list[str]:
    damp = "velocity" if p["damping"] == "none" else p["damping"]
    eta = p["eta_n"]
    if p["model"] == "linear":
        coeff = (f"hooke {p['kn']!r} {eta!r} tangential linear_history {p['kt']!r} "
                 f"{p['xgammat']!r} {p['mu']!r}")
    else:
        coeff = (f"hertz/material {p['E']!r} {eta!r} {p['nu']!r} tangential mindlin NULL "
                 f"{p['xgammat']!r} {p['mu']!r}")
    return ["pair_style granular", f"pair_coeff * * {coeff} damping {damp}"]


def header_lines(data_file: str, boundary: str = "p p p") -> list[str]:
    return ["units si", "atom_style sphere", "atom_modify map array", f"boundary {boundary}",
            "newton off", "comm_modify vel yes", f"read_data {data_file}",
            f"neighbor {SKIN!r} bin", "neigh_modify delay 0"]


def trial_lines(dt: float, steps: int, rotation: bool) -> list[str]:
    """As ``liggghts_thresholds.trial_lines``, with LAMMPS' per-atom properties."""
    h = repr(0.5 * dt)
    expr = f"0.5*mass*((vx+{h}*fx/mass)^2+(vy+{h}*fy/mass)^2+(vz+{h}*fz/mass)^2)"
    if rotation:
        inertia = "(0.4*mass*c_pw[7]*c_pw[7])"
        expr += ("+0.5*{I}*((c_pw[1]+{h}*c_pw[4]/{I})^2+(c_pw[2]+{h}*c_pw[5]/{I})^2"
                 "+(c_pw[3]+{h}*c_pw[6]/{I})^2)").format(I=inertia, h=h)
    integ = "nve/sphere" if rotation else "nve"
    chunks = max(1, math.ceil(steps / lt.CHUNK))
    return [
        f"fix integr all {integ}",
        "compute erot all erotate/sphere",
        "compute pw all property/atom omegax omegay omegaz tqx tqy tqz radius",
        f"variable ehalf_atom atom {expr}",
        "compute ehalf all reduce sum v_ehalf_atom",
        "variable etot equal c_ehalf",
        f"timestep {dt!r}",
        "thermo_style custom step atoms c_ehalf ke c_erot",
        "thermo_modify lost ignore norm no format float %.17g",
        f"thermo {lt.SAMPLE}",
        "run 0",
        'print "SETUP_OK"',
        f"variable limit equal ${{etot}}*{lt.BLOWUP!r}",
        f"variable k loop {chunks}",
        "label chunk",
        f"run {lt.CHUNK} pre no post no",
        'if "${etot} > ${limit}" then "jump SELF done"',
        "next k",
        "jump SELF chunk",
        "label done",
        'print "RUN_END"',
    ]


def wall_lines(p: dict, lo: float, hi: float) -> list[str]:
    """``fix wall/gran granular`` planes z = lo and z = hi with the pair's model."""
    coeff = pair_lines(p)[1].split(None, 3)[3]
    return [f"fix walls all wall/gran granular {coeff} zplane {float(lo)!r} {float(hi)!r}"]


class LammpsRunner(lt.Runner):
    """The LIGGGHTS harness' Runner (perturbed data file written once, fixed seed; its
    ``trial`` parses the thermo output) with a LAMMPS input."""

    def script(self, dt: float, steps: int) -> str:
        walls = self.state["bounds"][2] != "pp"
        extra = wall_lines(self.params, *self.state["box"][2]) if walls else []
        return "\n".join(header_lines("perturbed.data", "p p f" if walls else "p p p")
                         + pair_lines(self.params) + extra
                         + trial_lines(dt, steps, self.case.rotation)) + "\n"


# ---------------------------------------------------------------------------- states
def make_fcc_state(overlap: float, name: str, workdir: Path) -> Path:
    """FCC supercell written as a data file, dumped by LAMMPS at rest (run 0)."""
    a = FCC_CELL
    basis = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]]) * a
    g = np.stack(np.meshgrid(*[np.arange(FCC_CELLS)] * 3, indexing="ij"), -1).reshape(-1, 3) * a
    x = (g[:, None, :] + basis[None, :, :]).reshape(-1, 3)
    d = a / math.sqrt(2.0)
    r = np.full(len(x), 0.5 * d * (1.0 + overlap))
    box = [a * FCC_CELLS] * 3
    folder = workdir / f"state-{name}"
    folder.mkdir(parents=True, exist_ok=True)
    write_data(folder / "state.data", x, r, box)
    p = {"model": "linear", "damping": "none", "eta_n": 0.0, "kn": KN, "kt": KT, "xgammat": 0.0,
         "mu": MU}
    lines = header_lines("state.data") + pair_lines(p) + [
        "fix integr all nve/sphere", "timestep 1e-4",
        f"dump dstate all custom 1 state.dump {DUMP_COLUMNS}",
        'dump_modify dstate sort id format line "%d %d' + " %.17g" * 11 + '"',
        "run 0"]
    rc, out = run_lammps("\n".join(lines) + "\n", folder)
    if rc != 0:
        raise RuntimeError(f"{name}: LAMMPS failed ({rc}):\n{out[-3000:]}")
    dest = state_path(name)
    shutil.copy(folder / "state.dump", dest)
    st = read_dump(dest)
    side = st["box"][:, 1] - st["box"][:, 0]
    if not np.array_equal(side, np.asarray(box, float)):
        raise RuntimeError(f"{name}: dump box {side} is not {box}")
    return dest


def make_slab_state(overlap: float, name: str, workdir: Path) -> Path:
    """FCC slab: 3 x 3 cubic cells in x, y (periodic, 4.5 m), 6 (001) layers in z between
    two flat walls. Pair overlap ``overlap`` d; linear springs: a bottom sphere's 4 upper
    neighbours push it down with 4 kn delta / sqrt 2, so the wall overlap is 2 sqrt 2 delta
    (an equilibrium of linear springs only)."""
    a = FCC_CELL
    d = a / math.sqrt(2.0)
    r0 = 0.5 * d * (1.0 + overlap)
    delta = 2.0 * r0 - d
    dw = 2.0 * math.sqrt(2.0) * delta
    layers = 2 * FCC_CELLS
    pts = []
    for k in range(layers):
        off = 0.0 if k % 2 == 0 else 0.5 * a
        for ix in range(FCC_CELLS):
            for iy in range(FCC_CELLS):
                for bx, by in ((0.0, 0.0), (0.5 * a, 0.5 * a)):
                    pts.append([(ix * a + bx + off) % (a * FCC_CELLS),
                                iy * a + by, r0 - dw + 0.5 * a * k])
    x = np.array(pts)
    r = np.full(len(x), r0)
    top = float(x[:, 2].max() + r0 - dw)
    box = [a * FCC_CELLS, a * FCC_CELLS, top]
    folder = workdir / f"state-{name}"
    folder.mkdir(parents=True, exist_ok=True)
    write_data(folder / "state.data", x, r, box)
    p = {"model": "linear", "damping": "none", "eta_n": 0.0, "kn": KN, "kt": KT, "xgammat": 0.0,
         "mu": MU}
    lines = header_lines("state.data", "p p f") + pair_lines(p) + wall_lines(p, 0.0, top) + [
        "fix integr all nve/sphere", "timestep 1e-4",
        f"dump dstate all custom 1 state.dump {DUMP_COLUMNS} fx fy fz",
        'dump_modify dstate sort id format line "%d %d' + " %.17g" * 14 + '"',
        "run 0"]
    rc, out = run_lammps("\n".join(lines) + "\n", folder)
    if rc != 0:
        raise RuntimeError(f"{name}: LAMMPS failed ({rc}):\n{out[-3000:]}")
    st = read_dump(folder / "state.dump")
    fres = np.sqrt(st["fx"] ** 2 + st["fy"] ** 2 + st["fz"] ** 2).max()
    if fres > 1e-9 * KN * delta:
        raise RuntimeError(f"{name}: not an equilibrium (residual force {fres:g} N)")
    dest = state_path(name)
    shutil.copy(folder / "state.dump", dest)
    return dest


# ---------------------------------------------------------------------------- linearised maps
def assemble(npart, ct, kn, kt, rotation, arm_t, arm_s):
    """Dense sum_c B_t^T D B_s; ``arm_t``/``arm_s``: (ai, aj) of the torque and the slip
    rows (B = [-I, [a_i n]x, I, [a_j n]x], n from i to j)."""
    i, j, n = ct["i"], ct["j"], ct["n"]
    nd = 6 if rotation else 3
    c = len(i)
    nn = n[:, :, None] * n[:, None, :]
    D = kn[:, None, None] * nn + kt[:, None, None] * (np.eye(3) - nn)
    eye = np.broadcast_to(np.eye(3), (c, 3, 3))

    def B(arms):
        ai, aj = arms
        parts = [-eye] + ([_skew(ai[:, None] * n)] if rotation else []) + \
                [eye] + ([_skew(aj[:, None] * n)] if rotation else [])
        return np.concatenate(parts, axis=2)

    E = np.einsum("cki,ckl,clj->cij", B(arm_t), D, B(arm_s))
    dof = np.concatenate([i[:, None] * nd + np.arange(nd), j[:, None] * nd + np.arange(nd)], 1)
    K = np.zeros((npart * nd, npart * nd))
    np.add.at(K, (dof[:, :, None], dof[:, None, :]), E)
    return K


def _wall_blocks(npart, i, n, kn, kt, rotation, arm):
    """Dense sum over wall contacts of B^T D B, B = [-I, [arm n]x] on sphere i."""
    nd = 6 if rotation else 3
    c = len(i)
    nn = n[:, :, None] * n[:, None, :]
    D = kn[:, None, None] * nn + kt[:, None, None] * (np.eye(3) - nn)
    eye = np.broadcast_to(np.eye(3), (c, 3, 3))
    B = np.concatenate([-eye] + ([_skew(arm[:, None] * n)] if rotation else []), axis=2)
    E = np.einsum("cki,ckl,clj->cij", B, D, B)
    dof = i[:, None] * nd + np.arange(nd)
    K = np.zeros((npart * nd, npart * nd))
    np.add.at(K, (dof[:, :, None], dof[:, None, :]), E)
    return K


def normal_force(case: Case, p: dict, ct: dict) -> np.ndarray:
    if case.model == "linear":
        return KN * ct["delta"]
    return 4.0 / 3.0 * p["E_star"] * np.sqrt(ct["rs"]) * ct["delta"] ** 1.5


def model_matrices(case: Case, p: dict, ct: dict, variant: str, geometric: bool):
    """(K, C, mass diagonal) of a variant: 'sym' (arms r - delta/2, demstep) | 'nonsym'
    (LAMMPS: slip arms r, torque arms r - delta/2) | 'geomean' (both sqrt(r (r -
    delta/2))) | 'full' (both r)."""
    r, i, j, dl = ct["r"], ct["i"], ct["j"], ct["delta"]
    half = (r[i] - 0.5 * dl, r[j] - 0.5 * dl)
    full = (r[i], r[j])
    if variant == "sym":
        at, as_ = half, half
    elif variant == "full":
        at, as_ = full, full
    elif variant == "nonsym":
        at, as_ = half, full
    else:
        gm = (np.sqrt(half[0] * full[0]), np.sqrt(half[1] * full[1]))
        at, as_ = gm, gm
    pc = p["per_contact"]
    npart = len(r)
    rot = case.rotation
    K = assemble(npart, ct, pc["kn"], pc["kt"], rot, at, as_)
    if geometric:
        geo = -normal_force(case, p, ct) / ct["dist"]
        Kg = assemble(npart, ct, np.zeros_like(geo), geo, False, (0 * dl, 0 * dl), (0 * dl, 0 * dl))
        nd = 6 if rot else 3
        idx = (np.arange(npart)[:, None] * nd + np.arange(3)).reshape(-1)
        K[np.ix_(idx, idx)] += Kg
    C = assemble(npart, ct, pc["gamma_n"], pc["gamma_t"], rot, at, as_)
    w = ct["wall"]
    if len(w["i"]):
        # sphere i against a fixed wall: B = [-I, [arm n]x] (n from the sphere to the wall);
        # LAMMPS: slip and torque arm r (symmetric); demstep's 'sym' (liggghts
        # convention): r - delta/2; 'full', 'nonsym', 'geomean': r.
        rw = r[w["i"]]
        arm = rw - 0.5 * w["delta"] if variant == "sym" else rw
        wp = p["wall_per_contact"]
        for mat, kk, ks in ((K, wp["kn"], wp["kt"]), (C, wp["gamma_n"], wp["gamma_t"])):
            mat += _wall_blocks(npart, w["i"], w["n"], kk, ks, rot, arm)
    m = ct["m"]
    cols = [m, m, m] + ([0.4 * m * r * r] * 3 if rot else [])
    return K, C, np.stack(cols, 1).reshape(-1)


def critical_step(K, C, mdiag) -> dict:
    """Smallest h > 0 with det(h^2 K + 2 h C - 4 M) = 0, and what the undamped
    eigenvalues of M^-1 K look like (largest real part, largest |imaginary part|)."""
    mi = 1.0 / mdiag
    lam = sl.eigvals(mi[:, None] * K)
    top = float(lam.real.max())
    out = {"lambda_max": top, "imag_max": float(np.abs(lam.imag).max()),
           "h_undamped": 2.0 / math.sqrt(top)}
    if not np.any(C):
        out["h"] = out["h_undamped"]
        return out
    n = len(mdiag)
    if n > QEP_MAX:
        out["h"] = _damped_step_secant(K, C, mdiag, out["h_undamped"])
        return out
    Z, I = np.zeros((n, n)), np.eye(n)
    A = np.block([[Z, I], [4.0 * np.diag(mdiag), -2.0 * C]])
    Bm = np.block([[I, Z], [Z, K]])
    h = sl.eigvals(A, Bm)
    h = h[np.isfinite(h)]
    real = h[(np.abs(h.imag) <= 1e-9 * np.abs(h)) & (h.real > 0)].real
    out["h"] = float(real.min())
    return out


def _damped_step_secant(K, C, mdiag, h_undamped: float, rtol: float = 1e-10) -> float:
    """Large states: the smallest h with max Re eig(M^-1 (h^2 K + 2 h C)) = 4 (real
    eigenvalue), by a bracketed secant / bisection on [0, h_undamped] (g(0) = -4 < 0,
    g(h_undamped) >= 0 since C adds a positive semi-definite part)."""
    mi = 1.0 / mdiag
    MK, MC = mi[:, None] * K, mi[:, None] * C

    def g(h):
        lam = sl.eigvals(h * h * MK + 2.0 * h * MC)
        return float(lam.real.max()) - 4.0

    lo, glo, hi, ghi = 0.0, -4.0, h_undamped, g(h_undamped)
    side = 0
    h = hi
    for _ in range(80):                      # Illinois variant of regula falsi
        h = hi - ghi * (hi - lo) / (ghi - glo)
        gh = g(h)
        if gh > 0:
            hi, ghi = h, gh
            if side == 1:
                glo *= 0.5
            side = 1
        else:
            lo, glo = h, gh
            if side == -1:
                ghi *= 0.5
            side = -1
        if abs(gh) <= 1e-12 * 4.0 or (hi - lo) <= rtol * hi:
            break
    return float(h)


def spectral_radius(K, C, mdiag, h) -> float:
    mi = 1.0 / mdiag
    MK, MC = mi[:, None] * K, mi[:, None] * C
    eye = np.eye(len(mdiag))
    T = np.block([[eye - h * h * MK, h * (eye - h * MC)], [-h * MK, eye - h * MC]])
    return float(np.abs(np.linalg.eigvals(T)).max())


def analyse(case: Case, p: dict, ct: dict, verify: bool) -> dict:
    res = {}
    for variant in ("sym", "nonsym", "geomean", "full"):
        for geo in (False, True):
            if not case.rotation and variant != "sym":
                continue               # no rotation: the arms do not enter
            K, C, md = model_matrices(case, p, ct, variant, geo)
            cs = critical_step(K, C, md)
            key = variant + ("+geo" if geo else "")
            if verify and variant == "nonsym":
                cs["radius_below"] = spectral_radius(K, C, md, cs["h"] * (1 - 1e-4))
                cs["radius_above"] = spectral_radius(K, C, md, cs["h"] * (1 + 1e-4))
            res[key] = cs
    return res


# ---------------------------------------------------------------------------- demstep
def demstep_args(case: Case, p: dict, dump: Path) -> list[str]:
    args = ["dt", str(dump), "--json"]
    if not case.rotation:
        args.append("--no-rotation")
    if case.model == "linear":
        args += ["--model", "linear", "--kn", repr(KN), "--ks", repr(KT)]
    else:
        args += ["--model", "hertz", "--youngs", repr(YOUNGS), "--poisson", repr(POISSON)]
    if case.damping != "none":
        args += ["--gamma-n", repr(p["gamma_n"]), "--gamma-t", repr(p["gamma_t"])]
    if case.state.startswith("slab"):
        args += ["--wall", "z-", "--wall", "z+"]
    return args


def run_demstep(args: list[str]) -> tuple[dict | None, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO / "src") + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.run([sys.executable, "-m", "demstep.cli", *args], capture_output=True,
                          text=True, cwd=REPO, env=env, timeout=900)
    if proc.returncode != 0:
        return None, proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else "failed"
    data = json.loads(proc.stdout)
    return {e["method"]: e["dt"] for e in data["estimates"]}, ""


# ---------------------------------------------------------------------------- main
def _clean(obj):
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items() if k not in ("per_contact", "wall_per_contact")}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    return obj


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=["*"], help="fnmatch patterns of case names")
    ap.add_argument("--steps", type=int, default=DEFAULT_STEPS)
    ap.add_argument("--tol", type=float, default=TOL)
    ap.add_argument("--list", action="store_true")
    ap.add_argument("--analysis-only", action="store_true",
                    help="no LAMMPS trials: the linearised maps and demstep only")
    ap.add_argument("--regen-states", action="store_true")
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--markdown", action="store_true", help="also print the doc's table")
    args = ap.parse_args(argv)

    cases = [c for c in all_cases() if any(fnmatch.fnmatch(c.name, pat) for pat in args.cases)]
    if args.list:
        print("\n".join(c.name for c in cases))
        return 0

    def log(msg):
        print(msg, flush=True)

    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="lammps_thresholds_"))
    workdir.mkdir(parents=True, exist_ok=True)
    for o in FCC_OVERLAPS:
        name = f"fcc_o{o:.0e}".replace("e-0", "e-")
        if (args.regen_states or not state_path(name).exists()) and any(c.state == name for c in cases):
            log(f"state {name}: {make_fcc_state(o, name, workdir)}")

    if (args.regen_states or not state_path("slab_o1e-3").exists()) and \
            any(c.state == "slab_o1e-3" for c in cases):
        log(f"state slab_o1e-3: {make_slab_state(1.0e-3, 'slab_o1e-3', workdir)}")

    report = json.loads(args.out.read_text()) if args.out.exists() else {"cases": {}}
    report["lammps_version"] = lammps_version()
    report["protocol"] = {"steps": args.steps, "tol": args.tol, "growth_factor": lt.GROWTH_FACTOR,
                          "blowup": lt.BLOWUP, "sample": lt.SAMPLE, "chunk": lt.CHUNK,
                          "perturbation": lt.PERTURBATION, "bracket_factor": lt.BRACKET_FACTOR,
                          "skin": SKIN}
    for case in cases:
        dump = state_path(case.state)
        st = read_dump(dump)
        ct = contact_table(st)
        p = case_parameters(case, ct)
        t0 = time.perf_counter()
        an = analyse(case, p, ct, verify=not case.state.startswith("poly"))
        ds, why = run_demstep(demstep_args(case, p, dump))
        rec = {"case": case.name, "state": case.state, "dump": str(dump.relative_to(REPO)),
               "n": int(len(st["radius"])), "contacts": int(len(ct["i"])),
               "overlap_rel_mean": float((ct["delta"] / (2 * ct["r"].mean())).mean()),
               "rotation": case.rotation, "parameters": p, "model_steps": an,
               "demstep": ds, "demstep_error": why or None,
               "demstep_args": demstep_args(case, p, dump)}
        key = "nonsym+geo" if case.rotation else "sym+geo"
        hint = an[key]["h"] * HINT_OFFSET
        log(f"{case.name}: map {hint:.9g}, demstep exact {ds.get('exact') if ds else why}")
        if not args.analysis_only:
            runner = LammpsRunner(case, p, st, workdir, seed=20261207)
            res = bisect_threshold(runner, hint, args.steps, args.tol, log)
            rec.update(threshold=res, perturbation=runner.perturbation,
                       trials=[t.as_dict() for t in runner.trials])
        elif case.name in report["cases"] and "threshold" in report["cases"][case.name]:
            old = report["cases"][case.name]
            rec.update(threshold=old["threshold"], perturbation=old.get("perturbation"),
                       trials=old.get("trials"))
        rec["wall_s"] = time.perf_counter() - t0
        report["cases"][case.name] = _clean(rec)
        args.out.write_text(json.dumps(report, indent=1) + "\n")
    print_table(report, [c.name for c in cases])
    if args.markdown:
        print(markdown_table(report, [c.name for c in cases]))
    return 0


def _pct(a, b):
    return f"{(a / b - 1) * 100:+.3f} %"


def markdown_table(report: dict, names: list[str]) -> str:
    """The tables of docs/validation-lammps.md."""
    rows = ["| case | LAMMPS bracket [s] | demstep exact [s] | (exact - thr) / thr | "
            "element-coupled [s] (below?) | map nonsym+geo | map sym+geo | geomean+geo vs nonsym+geo |",
            "|---|---|---|---|---|---|---|---|"]
    for name in names:
        rec = report["cases"].get(name)
        if rec is None or "threshold" not in rec:
            continue
        th, ds, ms = rec["threshold"], rec.get("demstep") or {}, rec["model_steps"]
        lo, hi = th["bracket"]
        ex, el = ds.get("exact"), ds.get("element-coupled")
        ns = ms.get("nonsym+geo", ms["sym+geo"])["h"]
        inb = lambda v: " (in)" if lo <= v <= hi else (" (above)" if v > hi else " (below)")  # noqa: E731
        gm = (_pct(ms["geomean+geo"]["h"], ms["nonsym+geo"]["h"]) if "geomean+geo" in ms
              else "n/a (no rotation)")
        rows.append(f"| {name} | {lo:.7g} - {hi:.7g} | {ex:.7g} | {_pct(ex, th['dt'])} | "
                    f"{el:.5g} ({'yes' if el < lo else 'NO'}) | {ns:.7g}{inb(ns)} | "
                    f"{ms['sym+geo']['h']:.7g}{inb(ms['sym+geo']['h'])} | {gm} |")
    return "\n".join(rows)


def print_table(report: dict, names: list[str]) -> None:
    print(f"{'case':40s} {'LAMMPS bracket':>27s} {'exact':>11s} {'gap':>8s} {'elem':>10s} "
          f"{'nonsym+geo':>11s} {'geomean+geo':>11s} {'sym+geo':>11s}")
    for name in names:
        rec = report["cases"].get(name)
        if rec is None:
            continue
        th = rec.get("threshold")
        ds = rec.get("demstep") or {}
        ms = rec["model_steps"]
        br = f"{th['bracket'][0]:.7g}-{th['bracket'][1]:.7g}" if th else "-"
        ex = ds.get("exact")
        gap = f"{(ex / th['dt'] - 1) * 100:+.3f}%" if (th and ex) else "-"
        get = lambda k: f"{ms[k]['h']:.7g}" if k in ms else "-"  # noqa: E731
        print(f"{name:40s} {br:>27s} {ex if ex is None else f'{ex:.7g}':>11} {gap:>8s} "
              f"{ds.get('element-coupled', float('nan')):10.5g} {get('nonsym+geo'):>11s} "
              f"{get('geomean+geo'):>11s} {get('sym+geo'):>11s}")


if __name__ == "__main__":
    sys.exit(main())
