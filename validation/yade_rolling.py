"""Rolling resistance side by side with YADE: spheres rolling to a stop on a rigid floor.

Three spheres (radii 10, 5, 20 mm, density 2500 kg/m^3, each in its own lane so that
they never touch) rest on a flat floor at their static overlap delta = m g / k_n, with
an initial velocity v0 along x and the spin of rolling without slip, under gravity,
with no damping of any kind. The rolling moment saturates at its limit and decelerates
each sphere uniformly until it stops: (m + I / b^2) dv/dt = -M / b, M = mu_r r F_n,

    a = mu_r g r / b / (1 + I / (m b^2)),  distance v0^2 / (2 a)   (I = 2/5 m r^2)

(the analytic value of tests/test_rolling_resistance.py), b the arm from the centre to
the contact point: r - delta in demstep (the floor plane), r - delta / 2 in YADE (its
box-sphere contact point lies mid-overlap). Each code starts with its own no-slip spin
v0 / b; the analytic values are given for both arms. The same case runs

* in YADE (``yade -n -x -j 1``, a subprocess: YADE has its own Python), the installed
  version, with ``CohFrictMat(momentRotationLaw=True, etaRoll, alphaKr)``,
  ``Ig2_Box_Sphere_ScGeom6D`` (a fixed box as the floor: ``Ig2_Wall_Sphere_ScGeom``
  makes a ScGeom, not the ScGeom6D the moment law needs, and YADE has no
  Ig2_Wall_Sphere_ScGeom6D), ``Ip2_CohFrictMat_CohFrictMat_CohFrictPhys`` and
  ``Law2_ScGeom6D_CohFrictPhys_CohesionMoment(always_use_moment_law=True,
  useIncrementalForm=True)`` (both default to False: without the first a contact that
  is not cohesive has no moment at all, without the second the moment is k_r times the
  total relative rotation, truncated, not an elastic-plastic spring), no cohesion
  (isCohesive=False), ``NewtonIntegrator(damping=0)``, O.dt fixed;
* in demstep with ``LinearSpring(rolling_convention="beta")`` and the mapped
  parameters, ``TimeStep.fixed`` with the same dt.

Parameter mapping (YADE 2023.02a, pkg/dem/CohesiveFrictionalContactLaw.cpp, checked on
the installed binary by the probe this script records, ``yade_probe`` in the JSON):

* YADE: k_n = 2 E1 R1 E2 R2 / (E1 R1 + E2 R2), k_s = the same with E_i nu_i (``poisson``
  is the ratio k_s / k_n here), k_r = alphaKr k_s R1 R2, rolling limit
  ``maxRollPl`` |F_n| with maxRollPl = min(etaRoll1 R1, etaRoll2 R2); for a box-sphere
  contact R1 = R2 = r (the box is "a projected virtual sphere of same radius").
  Each sphere gets its own floor box of its own material, so box and sphere share E:
  k_n = E r -> E = k_n / r, nu = k_s / k_n, so every sphere has the same k_n, k_s
  (demstep has one law for all).
* demstep (a wall: R* = r): k_r = beta_r k_s r^2 -> beta_r = alphaKr; limit
  mu_r r F_n -> mu_r = etaRoll; friction mu = tan(frictionAngle).
* Twisting: off in both (demstep beta_w = 0; YADE alphaKtw = 0 -> k_tw = 0).

Between two spheres the mapping is not a constant: YADE's limit arm is
min(r1, r2) and its stiffness arm r1 r2, demstep's R* = r1 r2 / (r1 + r2) in both
(equal spheres: mu_r = 2 etaRoll, beta_r = 4 alphaKr). The probe records a fixed
sphere-sphere pair to show it; the runs are floor contacts only.

Measured: the stopping distance (the peak of x - x0, refined by a parabola through the
three samples around the maximum) and the deceleration (least-squares slope of v_x over
10 % to 80 % of the analytic stopping time), per sphere and code; the rolling moment
at mid-roll over its limit; the largest slip |v_x - omega_y b| / v0. The roll
saturates the rolling spring within the first step, so it does not test k_r: a second
run with elastic rolling springs (YADE etaRoll = -1, demstep mu_r = 0) starts each
sphere in the slow rocking mode of (x, theta_y) and compares the periods with the
two-DOF value. Then YADE alone with its defaults (useIncrementalForm=False,
always_use_moment_law=False) and with demstep's spin v0 / (r - delta).

    python validation/yade_rolling.py                 # about 15 s in all
    python validation/yade_rolling.py --out validation/results/yade-rolling-YYYYMMDD.json
    python validation/yade_rolling.py --no-variants --steps-per-period 80 --out ...
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RHO = 2500.0
G = 9.81
K_N = 1.0e6          # [N/m]
K_S = 0.5 * K_N      # [N/m]
MU = 0.8             # Coulomb friction (no sliding: the roll needs far less)
MU_R = 0.05          # rolling friction: demstep mu_r = YADE etaRoll
BETA_R = 0.5         # rolling stiffness: demstep beta_r = YADE alphaKr
STEPS_PER_PERIOD = 40.0
SAMPLE_EVERY = 20    # steps between samples (both codes)
LANE = 0.1           # [m] y spacing of the spheres' lanes (no sphere-sphere contact)
# (radius [m], v0 [m/s])
CASES = [(0.01, 0.2), (0.005, 0.1), (0.02, 0.3)]


def sphere_mass(r):
    return RHO * 4.0 / 3.0 * math.pi * r**3


def analytic(r, v0, arm_overlap=1.0):
    """Rolling to a stop against the saturated moment, arm b = r - arm_overlap * delta
    (demstep: the floor plane, 1; YADE: its contact point mid-overlap, 0.5)."""
    m = sphere_mass(r)
    b = r - arm_overlap * m * G / K_N
    inertia = 0.4 * m * r * r
    a = MU_R * G * r / b / (1.0 + inertia / (m * b * b))
    return {"arm": b, "decel": a, "distance": v0 * v0 / (2.0 * a), "t_stop": v0 / a}


def time_step(steps_per_period=STEPS_PER_PERIOD):
    m_min = min(sphere_mass(r) for r, _ in CASES)
    return 2.0 * math.pi * math.sqrt(m_min / K_N) / steps_per_period


# ----------------------------------------------------------------------------- YADE
YADE_SCRIPT = r'''
# generated by validation/yade_rolling.py: run with  yade -n -x THIS_FILE
import json, math, time
P = json.loads(%(params)r)
O.reset()
O.dt = P["dt"]
kn, ks = P["k_n"], P["k_s"]
ids = []
for lane, r in enumerate(P["radii"]):
    y = lane * P["lane"]
    mat = CohFrictMat(young=kn / r, poisson=ks / kn, frictionAngle=math.atan(P["mu"]),
                      density=P["rho"], isCohesive=False, normalCohesion=0, shearCohesion=0,
                      momentRotationLaw=True, etaRoll=P["eta_roll"], alphaKr=P["beta_r"],
                      etaTwist=-1, alphaKtw=0, label="lane%%d" %% lane)
    O.materials.append(mat)
    half = 0.5 * P["lane"] - 2 * r  # box half-width in y: no sphere reaches a neighbour's box
    O.bodies.append(box((0.5, y, -0.01), (1.0, half, 0.01), fixed=True, material=mat))
    m = P["rho"] * 4.0 / 3.0 * math.pi * r ** 3
    delta = m * P["g"] / kn
    sid = O.bodies.append(sphere((0, y, r - delta), r, material=mat))
    O.bodies[sid].state.vel = Vector3(P["init"][lane][0], 0, 0)
    O.bodies[sid].state.angVel = Vector3(0, P["init"][lane][1], 0)
    ids.append(sid)
# probe: a fixed sphere-sphere pair (radii 10 and 5 mm) to record YADE's pair definitions
mat0 = O.materials[0]
p1 = O.bodies.append(sphere((0, -1.0, 0.5), 0.01, material=mat0, fixed=True))
p2 = O.bodies.append(sphere((0.0149, -1.0, 0.5), 0.005, material=mat0, fixed=True))

law = Law2_ScGeom6D_CohFrictPhys_CohesionMoment(always_use_moment_law=P["always"],
                                                useIncrementalForm=P["incremental"])
O.engines = [
    ForceResetter(),
    InsertionSortCollider([Bo1_Sphere_Aabb(), Bo1_Box_Aabb()]),
    InteractionLoop([Ig2_Sphere_Sphere_ScGeom6D(), Ig2_Box_Sphere_ScGeom6D()],
                    [Ip2_CohFrictMat_CohFrictMat_CohFrictPhys()], [law]),
    NewtonIntegrator(damping=0.0, gravity=(0, 0, -P["g"])),
    PyRunner(iterPeriod=P["every"], command="record()"),
]
rec = {"t": [], "x": [], "vx": [], "wy": [], "moment": [], "fn": [], "contacts": []}

def floor_interaction(sid):
    for i in O.bodies[sid].intrs():
        if isinstance(O.bodies[i.id1].shape, Box) or isinstance(O.bodies[i.id2].shape, Box):
            return i
    return None

def record():
    # PyRunner runs after NewtonIntegrator inside step O.iter: positions are at (O.iter + 1) dt
    rec["t"].append((O.iter + 1) * O.dt)
    xs, vs, ws, ms, fs, cs = [], [], [], [], [], []
    for sid in ids:
        st = O.bodies[sid].state
        xs.append(st.pos[0]); vs.append(st.vel[0]); ws.append(st.angVel[1])
        i = floor_interaction(sid)
        cs.append(0 if i is None else 1)
        ms.append(0.0 if i is None else i.phys.moment_bending.norm())
        fs.append(0.0 if i is None else i.phys.normalForce.norm())
    rec["x"].append(xs); rec["vx"].append(vs); rec["wy"].append(ws)
    rec["moment"].append(ms); rec["fn"].append(fs); rec["contacts"].append(cs)

x0 = [O.bodies[s].state.pos[0] for s in ids]
O.step()  # create the interactions, then probe their physics
probe = {"floor": [], "pair": None}
for lane, sid in enumerate(ids):
    i = floor_interaction(sid)
    ph, ge = i.phys, i.geom
    probe["floor"].append({"r": P["radii"][lane], "refR1": ge.refR1, "refR2": ge.refR2,
                           "kn": ph.kn, "ks": ph.ks, "kr": ph.kr, "ktw": ph.ktw,
                           "maxRollPl": ph.maxRollPl, "maxTwistPl": ph.maxTwistPl,
                           "tanphi": ph.tangensOfFrictionAngle,
                           "cohesionBroken": ph.cohesionBroken,
                           "momentRotationLaw": ph.momentRotationLaw,
                           "mass": O.bodies[sid].state.mass,
                           "inertia": O.bodies[sid].state.inertia[1]})
ip = O.interactions[p1, p2]
probe["pair"] = {"r1": 0.01, "r2": 0.005, "E": mat0.young, "refR1": ip.geom.refR1,
                 "refR2": ip.geom.refR2, "kn": ip.phys.kn, "ks": ip.phys.ks, "kr": ip.phys.kr,
                 "maxRollPl": ip.phys.maxRollPl}
O.interactions.erase(p1, p2)
O.bodies.erase(p2); O.bodies.erase(p1)
wall = time.time()
O.run(P["steps"] - 1, True)
wall = time.time() - wall
json.dump({"version": version, "x0": x0, "probe": probe, "rec": rec, "wall_s": wall,
           "steps": O.iter, "dt": O.dt}, open(P["out"], "w"))
'''


def roll_init(arm_overlap):
    """Initial (v_x, omega_y) of the spheres: v0 and the spin of rolling without slip at
    the arm r - arm_overlap delta (demstep's contact point on the floor plane: 1; YADE's,
    mid-overlap: 0.5)."""
    return [(v0, v0 / analytic(r, v0, arm_overlap)["arm"]) for r, v0 in CASES]


def run_yade(dt, steps, init, yade="yade", eta_roll=MU_R, always=True, incremental=True,
             every=SAMPLE_EVERY):
    """Run the YADE scene (spheres of CASES' radii, initial (v_x, omega_y) ``init``,
    etaRoll ``eta_roll``; ``always``, ``incremental``: the law's always_use_moment_law
    and useIncrementalForm, YADE's defaults both False); samples every ``every`` steps."""
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "yade_out.json")
        params = {"dt": dt, "k_n": K_N, "k_s": K_S, "mu": MU, "eta_roll": eta_roll,
                  "beta_r": BETA_R, "rho": RHO, "g": G, "lane": LANE,
                  "radii": [r for r, _ in CASES], "init": [list(q) for q in init],
                  "every": every, "steps": steps, "out": out, "always": always,
                  "incremental": incremental}
        script = os.path.join(tmp, "rolling.py")
        Path(script).write_text(YADE_SCRIPT % {"params": json.dumps(params)})
        t0 = time.time()
        res = subprocess.run([yade, "-n", "-x", "-j", "1", script], capture_output=True,
                             text=True, cwd=tmp)
        wall = time.time() - t0
        if res.returncode != 0 or not os.path.exists(out):
            sys.stderr.write(res.stdout[-3000:] + res.stderr[-3000:])
            raise RuntimeError(f"yade failed (exit {res.returncode})")
        data = json.loads(Path(out).read_text())
        log = re.sub(r"\x1b\[[0-9;]*m", "", res.stdout + res.stderr)
        warnings = [ln for ln in log.splitlines() if "WARN" in ln or "ERROR" in ln]
    data["wall_total_s"] = wall
    data["log_warnings"] = warnings[:20]
    rec = data["rec"]
    series = {k: np.asarray(rec[k], dtype=float) for k in rec}
    series["x"] = series["x"] - np.asarray(data["x0"])[None, :]
    return data, series


# -------------------------------------------------------------------------- demstep
def run_demstep(dt, steps, init, mu_r=MU_R, every=SAMPLE_EVERY):
    """The same scene in demstep: one floor wall, the spheres in their lanes, initial
    (v_x, omega_y) ``init``, rolling friction ``mu_r`` (0: an elastic rolling spring)."""
    from demstep.contact.laws import LinearSpring
    from demstep.engine import Simulation, TimeStep
    from demstep.particles import Particles
    from demstep.walls import Wall

    law = LinearSpring(k_n=K_N, k_s=K_S, mu=MU, rolling_convention="beta",
                       rolling_stiffness=BETA_R, rolling_friction=mu_r)
    n = len(CASES)
    r = np.array([c[0] for c in CASES])
    x = np.zeros((n, 3))
    x[:, 1] = np.arange(n) * LANE
    x[:, 2] = r - np.array([sphere_mass(ri) for ri in r]) * G / K_N
    p = Particles.from_density(x, r, RHO)
    floor = Wall(point=[0.0, 0.0, 0.0], normal=[0.0, 0.0, 1.0], name="floor")
    sim = Simulation(p, law, walls=[floor], gravity=[0.0, 0.0, -G], timestep=TimeStep.fixed(dt))
    for i, (v, w) in enumerate(init):
        sim.v[i, 0] = v
        sim.w[i, 1] = w
    x0 = sim.x[:, 0].copy()
    rec = {"t": [], "x": [], "vx": [], "wy": [], "moment": [], "fn": []}

    def record(s):
        rec["t"].append(s.time)
        rec["x"].append(s.x[:, 0] - x0)
        rec["vx"].append(s.v[:, 0].copy())
        rec["wy"].append(s.w[:, 1].copy())
        ws = s.wall_state
        mom = np.zeros(n)
        fn = np.zeros(n)
        for row in range(len(ws.p)):
            q = int(ws.p[row])
            if 0 <= q < n:
                mom[q] = max(mom[q], float(np.linalg.norm(ws.roll[row, :3])))
        fn[:] = s.law.k_n * np.maximum(r - s.x[:, 2], 0.0)
        rec["moment"].append(mom)
        rec["fn"].append(fn)

    sim.every(every, record)
    t0 = time.time()
    sim.run(steps=steps)
    wall = time.time() - t0
    series = {k: np.asarray(v, dtype=float) for k, v in rec.items()}
    info = {"steps": int(sim.step), "dt": float(sim.dt), "wall_s": wall,
            "mass": sim.m.tolist(), "inertia": sim.inertia.tolist(),
            "energy_balance_error": float(sim.ledger.balance_error())}
    return info, series


# -------------------------------------------------------------------------- analysis
def measure(series, i, r, v0, arm_overlap):
    """Stopping distance, fitted deceleration, moment / limit at mid-roll, slip error
    (no slip at the arm r - arm_overlap delta), position at the end of the run."""
    ref = analytic(r, v0, arm_overlap)
    t, x, v, w = series["t"], series["x"][:, i], series["vx"][:, i], series["wy"][:, i]
    k = int(np.argmax(x))
    peak = x[k]
    if 0 < k < len(x) - 1:  # vertex of the parabola through the three samples
        y0, y1, y2 = x[k - 1], x[k], x[k + 1]
        den = y0 - 2 * y1 + y2
        if den < 0:
            peak = y1 - 0.125 * (y2 - y0) ** 2 / den
    sel = (t >= 0.1 * ref["t_stop"]) & (t <= 0.8 * ref["t_stop"])
    slope = np.polyfit(t[sel], v[sel], 1)[0]
    mid = int(np.argmin(abs(t - 0.5 * ref["t_stop"])))
    limit = MU_R * r * series["fn"][mid, i]
    slip = np.abs(v[sel] - w[sel] * ref["arm"]).max() / v0
    return {"distance": float(peak), "t_peak": float(t[k]), "decel": float(-slope),
            "moment_over_limit_mid": float(series["moment"][mid, i] / limit),
            "max_slip_over_v0": float(slip), "x_end": float(x[-1]), "v_end": float(v[-1]),
            "t_end": float(t[-1])}


def rel(a, b):
    return a / b - 1.0


def tables(rows, dt):
    """Two markdown tables: stopping distance (with the start-up offset v0 dt / 2 of
    either code, relative to the distance) and deceleration."""
    out = ["| r [mm] | v0 [m/s] | analytic, b = r − δ [mm] | analytic, b = r − δ/2 [mm] "
           "| YADE [mm] | demstep [mm] | YADE / an.(r − δ/2) − 1 | demstep / an.(r − δ) − 1 "
           "| demstep / YADE − 1 | v0 dt / (2 d) |", "|" + "---|" * 10]
    for row in rows:
        an, ay, y, d = row["analytic"], row["analytic_yade_arm"], row["yade"], row["demstep"]
        out.append(
            f"| {row['r'] * 1e3:g} | {row['v0']:g} | {an['distance'] * 1e3:.6f} "
            f"| {ay['distance'] * 1e3:.6f} | {y['distance'] * 1e3:.6f} | {d['distance'] * 1e3:.6f} "
            f"| {rel(y['distance'], ay['distance']):+.1e} | {rel(d['distance'], an['distance']):+.1e} "
            f"| {rel(d['distance'], y['distance']):+.1e} "
            f"| {row['v0'] * dt / 2 / an['distance']:.1e} |")
    out += ["", "| r [mm] | v0 [m/s] | analytic, b = r − δ [m/s²] | analytic, b = r − δ/2 [m/s²] "
            "| YADE [m/s²] | demstep [m/s²] | YADE / an.(r − δ/2) − 1 | demstep / an.(r − δ) − 1 "
            "| demstep / YADE − 1 |", "|" + "---|" * 9]
    for row in rows:
        an, ay, y, d = row["analytic"], row["analytic_yade_arm"], row["yade"], row["demstep"]
        out.append(
            f"| {row['r'] * 1e3:g} | {row['v0']:g} | {an['decel']:.8f} | {ay['decel']:.8f} "
            f"| {y['decel']:.8f} | {d['decel']:.8f} "
            f"| {rel(y['decel'], ay['decel']):+.1e} | {rel(d['decel'], an['decel']):+.1e} "
            f"| {rel(d['decel'], y['decel']):+.1e} |")
    return "\n".join(out)


def check_probe(probe):
    """YADE's stiffnesses and limit arm against the mapping (module docstring)."""
    lines = []
    for f in probe["floor"]:
        r = f["r"]
        expect = {"refR1": r, "refR2": r, "kn": K_N, "ks": K_S, "kr": BETA_R * K_S * r * r,
                  "maxRollPl": MU_R * r, "tanphi": MU, "ktw": 0.0}
        for key, val in expect.items():
            ok = math.isclose(f[key], val, rel_tol=1e-9, abs_tol=1e-30)
            lines.append(f"floor r={r:g}: {key} = {f[key]:.9g} (mapping {val:.9g}) "
                         f"{'ok' if ok else 'MISMATCH'}")
    pr = probe["pair"]
    e, r1, r2 = pr["E"], pr["r1"], pr["r2"]
    kn = 2 * e * r1 * e * r2 / (e * r1 + e * r2)
    ks = kn * K_S / K_N
    expect = {"kn": kn, "ks": ks, "kr": BETA_R * ks * r1 * r2, "maxRollPl": MU_R * min(r1, r2)}
    rstar = r1 * r2 / (r1 + r2)
    for key, val in expect.items():
        ok = math.isclose(pr[key], val, rel_tol=1e-9)
        lines.append(f"pair r1={r1:g} r2={r2:g}: {key} = {pr[key]:.9g} (YADE formula {val:.9g}) "
                     f"{'ok' if ok else 'MISMATCH'}")
    lines.append(f"pair: demstep's limit arm R* = {rstar:.6g} vs YADE's min(r1, r2) = {min(r1, r2):g}; "
                 f"stiffness arm R*^2 = {rstar ** 2:.6g} vs YADE's r1 r2 = {r1 * r2:.6g}")
    return lines


# ------------------------------------------------------------------ elastic rocking
W_ROCK = 1e-3  # [rad/s] angular velocity amplitude of the rocking runs


def rocking_mode(r, arm_overlap):
    """The slow mode of a sphere on the floor with the tangential spring k_s and an
    elastic rolling spring k_r = beta_r k_s r^2 (no limit): the two-DOF system (x,
    theta_y) of tests/test_rolling_resistance.py, K = [[k_s, -a k_s], [-a k_s,
    a^2 k_s + k_r]], M = diag(m, I), arm a = r - arm_overlap delta. Returns its period
    and the initial (v_x, omega_y) of that mode with omega_y = W_ROCK."""
    m = sphere_mass(r)
    inertia = 0.4 * m * r * r
    a = r - arm_overlap * m * G / K_N
    k_r = BETA_R * K_S * r * r
    K = np.array([[K_S, -a * K_S], [-a * K_S, a * a * K_S + k_r]])
    lam, vec = np.linalg.eig(np.diag([1.0 / m, 1.0 / inertia]) @ K)
    j = int(np.argmin(lam.real))
    shape = vec[:, j].real / vec[1, j].real * W_ROCK
    return 2.0 * math.pi / math.sqrt(lam[j].real), (float(shape[0]), float(shape[1]))


def rocking_period(series, i):
    """Mean interval between upward zero crossings of x(t) - x0 (linear interpolation)."""
    t, x = series["t"], series["x"][:, i]
    up = np.flatnonzero((x[:-1] < 0) & (x[1:] >= 0))
    cross = t[up] - x[up] / (x[up + 1] - x[up]) * (t[up + 1] - t[up])
    return float(np.diff(cross).mean()) if len(cross) >= 2 else float("nan"), len(cross)


def rocking_table(rows):
    out = ["| r [mm] | k_r = β_r k_s r² [N m/rad] | analytic period, a = r − δ [ms] "
           "| analytic, a = r − δ/2 [ms] | YADE [ms] | demstep [ms] "
           "| YADE / an.(r − δ/2) − 1 | demstep / an.(r − δ) − 1 | demstep / YADE − 1 |",
           "|" + "---|" * 9]
    for q in rows:
        out.append(f"| {q['r'] * 1e3:g} | {q['k_r']:g} | {q['analytic'] * 1e3:.6f} "
                   f"| {q['analytic_yade_arm'] * 1e3:.6f} | {q['yade'] * 1e3:.6f} "
                   f"| {q['demstep'] * 1e3:.6f} | {rel(q['yade'], q['analytic_yade_arm']):+.1e} "
                   f"| {rel(q['demstep'], q['analytic']):+.1e} | {rel(q['demstep'], q['yade']):+.1e} |")
    return "\n".join(out)


def run_rocking(dt, yade):
    """Elastic rolling springs (YADE etaRoll < 0, demstep mu_r = 0): each code starts in
    its own slow mode; the periods against the analytic one."""
    modes_y = [rocking_mode(r, 0.5) for r, _ in CASES]
    modes_d = [rocking_mode(r, 1.0) for r, _ in CASES]
    steps = int(math.ceil(3.5 * max(p for p, _ in modes_d) / dt))
    ydata, yser = run_yade(dt, steps, [q for _, q in modes_y], yade, eta_roll=-1.0, every=1)
    _, dser = run_demstep(dt, steps, [q for _, q in modes_d], mu_r=0.0, every=1)
    rows = []
    for i, (r, _) in enumerate(CASES):
        py, ny = rocking_period(yser, i)
        pd, nd = rocking_period(dser, i)
        rows.append({"r": r, "k_r": BETA_R * K_S * r * r, "analytic": modes_d[i][0],
                     "analytic_yade_arm": modes_y[i][0], "yade": py, "demstep": pd,
                     "crossings": [ny, nd], "init_yade": modes_y[i][1], "init_demstep": modes_d[i][1],
                     "max_moment_yade": float(yser["moment"][:, i].max()),
                     "max_moment_demstep": float(dser["moment"][:, i].max())})
    return {"steps": steps, "rows": rows, "log_warnings": ydata["log_warnings"]}


VARIANTS = {  # YADE runs besides the matched one: (arm_overlap, always, incremental)
    "spin v0/(r - delta)": (1.0, True, True),
    "useIncrementalForm=False (YADE default)": (0.5, True, False),
    "always_use_moment_law=False (YADE default)": (0.5, False, True),
}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--yade", default="yade", help="the yade executable")
    ap.add_argument("--out", default=None, help="JSON results (default: print only)")
    ap.add_argument("--series", action="store_true",
                    help="store x(t), v_x(t) of the matched roll in the JSON (every 10th sample)")
    ap.add_argument("--steps-per-period", type=float, default=STEPS_PER_PERIOD,
                    help="dt = 2 pi sqrt(m_min / k_n) / this (both codes)")
    ap.add_argument("--no-variants", action="store_true",
                    help="skip the YADE runs with its defaults and demstep's initial spin")
    args = ap.parse_args(argv)

    dt = time_step(args.steps_per_period)
    t_end = 1.15 * max(analytic(r, v0)["t_stop"] for r, v0 in CASES)
    steps = int(math.ceil(t_end / dt))
    print(f"dt = {dt:.6g} s, {steps} steps ({t_end:.4g} s), samples every {SAMPLE_EVERY} steps")

    ydata, yser = run_yade(dt, steps, roll_init(0.5), args.yade)
    print(f"YADE {ydata['version']}: {ydata['steps']} steps, {ydata['wall_s']:.1f} s "
          f"({ydata['wall_total_s']:.1f} s with start-up)")
    probe_lines = check_probe(ydata["probe"])
    for ln in probe_lines:
        print("  " + ln)
    if ydata["log_warnings"]:
        print("  YADE log warnings:", *ydata["log_warnings"], sep="\n    ")
    dinfo, dser = run_demstep(dt, steps, roll_init(1.0))
    print(f"demstep: {dinfo['steps']} steps, {dinfo['wall_s']:.1f} s, "
          f"energy balance error {dinfo['energy_balance_error']:.2e}")

    rows = []
    for i, (r, v0) in enumerate(CASES):
        rows.append({"r": r, "v0": v0, "analytic": analytic(r, v0),
                     "analytic_yade_arm": analytic(r, v0, arm_overlap=0.5),
                     "yade": measure(yser, i, r, v0, 0.5), "demstep": measure(dser, i, r, v0, 1.0)})
        y, d = rows[-1]["yade"], rows[-1]["demstep"]
        print(f"  r = {r * 1e3:g} mm: moment / limit at mid-roll: YADE {y['moment_over_limit_mid']:.9f}, "
              f"demstep {d['moment_over_limit_mid']:.9f}; max slip / v0: YADE "
              f"{y['max_slip_over_v0']:.2e}, demstep {d['max_slip_over_v0']:.2e}; "
              f"YADE contact lost: {bool((yser['contacts'][:, i] == 0).any())}")
    # the trajectories: largest difference of x(t) between the codes
    # (YADE's samples interpolated linearly to demstep's sample times)
    dx = np.array([np.abs(np.interp(dser["t"], yser["t"], yser["x"][:, i]) - dser["x"][:, i])
                   [dser["t"] >= yser["t"][0]].max() for i in range(len(CASES))])
    print(f"  max |x_YADE(t) - x_demstep(t)| over the run [m]: {np.array2string(dx, precision=3)}")
    print()
    print(tables(rows, dt))

    rock = run_rocking(dt, args.yade)
    print(f"\nElastic rocking (no limit), {rock['steps']} steps sampled every step:\n")
    print(rocking_table(rock["rows"]))

    variants = {}
    if not args.no_variants:
        print("\nYADE variants (r [mm]: distance = peak of x - x0 [mm] / analytic(r - delta/2) - 1; "
              "fitted deceleration [m/s^2]; x at the end of the run [mm]):")
        for name, (arm, always, incr) in VARIANTS.items():
            vdata, vser = run_yade(dt, steps, roll_init(arm), args.yade, always=always,
                                   incremental=incr)
            res = []
            for i, (r, v0) in enumerate(CASES):
                m = measure(vser, i, r, v0, 0.5)
                m["distance_over_analytic_yade_arm"] = rel(m["distance"],
                                                           analytic(r, v0, 0.5)["distance"])
                res.append({"r": r, "v0": v0, **m})
            variants[name] = {"arm_overlap": arm, "always_use_moment_law": always,
                              "useIncrementalForm": incr, "rows": res,
                              "log_warnings": vdata["log_warnings"]}
            print(f"  {name}: " + "; ".join(
                f"{q['r'] * 1e3:g}: {q['distance'] * 1e3:.6f} ({q['distance_over_analytic_yade_arm']:+.1e}), "
                f"{q['decel']:.6f}, x_end {q['x_end'] * 1e3:.4f}" for q in res))
            if vdata["log_warnings"]:
                print("    YADE log:", vdata["log_warnings"][0][:160])

    if args.out:
        res = {"date": datetime.date.today().isoformat(),
               "yade_version": ydata["version"], "python": platform.python_version(),
               "command": " ".join(["python validation/yade_rolling.py",
                                    *(sys.argv[1:] if argv is None else argv)]),
               "parameters": {"rho": RHO, "g": G, "k_n": K_N, "k_s": K_S, "mu": MU,
                              "mu_r": MU_R, "beta_r": BETA_R, "dt": dt, "steps": steps,
                              "steps_per_period": args.steps_per_period,
                              "sample_every": SAMPLE_EVERY, "cases": CASES},
               "yade_mapping": {"young": [K_N / r for r, _ in CASES], "poisson": K_S / K_N,
                                "frictionAngle": math.atan(MU), "etaRoll": MU_R,
                                "alphaKr": BETA_R, "alphaKtw": 0.0, "etaTwist": -1.0,
                                "always_use_moment_law": True, "useIncrementalForm": True,
                                "initial_spin": "v0 / (r - delta/2)"},
               "demstep_law": {"k_n": K_N, "k_s": K_S, "mu": MU, "rolling_convention": "beta",
                               "rolling_stiffness": BETA_R, "rolling_friction": MU_R,
                               "initial_spin": "v0 / (r - delta)"},
               "yade_probe": ydata["probe"], "yade_probe_check": probe_lines,
               "yade_wall_s": ydata["wall_s"], "yade_log_warnings": ydata["log_warnings"],
               "demstep": dinfo, "max_dx_between_codes": dx.tolist(), "rows": rows,
               "rocking": rock, "yade_variants": variants}
        if args.series:
            res["series"] = {"every_steps": 10 * SAMPLE_EVERY,  # every 10th sample
                             "yade": {k: yser[k][::10].tolist() for k in ("t", "x", "vx")},
                             "demstep": {k: dser[k][::10].tolist() for k in ("t", "x", "vx")}}
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
        print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
