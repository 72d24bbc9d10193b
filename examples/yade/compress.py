"""A packing compressed in YADE: a time step stable at the start is not stable once the
contacts multiply, and demstep's certificate keeps the run stable.

400 polydisperse spheres (radius 10 mm +- 30 %, 2500 kg/m^3, linear FrictPhys: young
1e8, poisson 0.3, friction 10 so that nothing slides, as in examples/lammps; no Cundall
damping) in a periodic cell are compressed by a constant cell velocity gradient
(O.cell.velGrad) from a loose cloud (solid fraction 0.40) to a dense packing. With
linear springs every contact has the same stiffness, but the critical step falls as the
coordination rises. Three runs of the same compression:

* A keeps 0.95 x the step demstep certifies once the first contacts have formed
  (a mean coordination of 1): it becomes unstable as the packing densifies (its kinetic energy
  explodes, or YADE stops on a body flying across the cell);
* B has demstep's engine in O.engines (``YadeCertifier(safety=0.8).engine(iterPeriod=50)``):
  it stays stable, and the log says when and why it changed O.dt;
* C uses GlobalStiffnessTimeStepper (its default timestepSafetyCoefficient 0.8, updated
  every 50 steps) instead: its steps are printed beside demstep's at the same strains.

    python VENV_PYTHON /usr/bin/yade -n -x -j 1 examples/yade/compress.py [--quiet]

(VENV_PYTHON: a Python that runs YADE and imports demstep: docs/yade.md; about a
minute in all.) With YADE's usual NewtonIntegrator damping 0.2 instead, run A at 0.95 x
the step certified with the damping (springs x 1.2) stayed stable here: in this
compressing packing the Cundall damping lowers YADE's threshold less than the worst
case the certificate assumes (docs/yade.md).
"""

import math
import sys

import numpy as np
from yade import pack, utils

from demstep.integrations.yade import YadeCertifier

N = 400
RATE = 0.6          # [1/s] compression rate per axis (velGrad = -RATE I)
DAMPING = 0.0       # NewtonIntegrator.damping (Cundall; see the docstring)
MU = 10.0           # friction coefficient (high: nothing slides, as in examples/lammps)
FIRST = N // 2      # contacts (a mean coordination of 1) when run A's step is certified
STRAIN = 0.20       # the strain at the end of each run (per axis)
EVERY = 50          # iterations between certificates (B) and GSTS updates (C)
QUIET = "--quiet" in sys.argv


def build():
    """The loose cloud in a periodic cell (the same for every run)."""
    O.reset()
    O.periodic = True
    mat = O.materials.append(FrictMat(young=1e8, poisson=0.3, frictionAngle=math.atan(MU),
                                      density=2500))
    volume = N * 4.0 / 3.0 * math.pi * 0.01 ** 3 * 1.09  # (the spread's <r^3>)
    L = (volume / 0.40) ** (1.0 / 3.0)
    sp = pack.SpherePack()
    sp.makeCloud((0, 0, 0), (L, L, L), rMean=0.01, rRelFuzz=0.3, num=N, periodic=True, seed=5)
    O.cell.hSize = Matrix3(L, 0, 0, 0, L, 0, 0, 0, L)
    sp.toSimulation(material=mat)
    O.engines = [ForceResetter(), InsertionSortCollider([Bo1_Sphere_Aabb()]),
                 InteractionLoop([Ig2_Sphere_Sphere_ScGeom()], [Ip2_FrictMat_FrictMat_FrictPhys()],
                                 [Law2_ScGeom_FrictPhys_CundallStrack()]),
                 NewtonIntegrator(damping=DAMPING)]
    O.cell.velGrad = Matrix3(-RATE, 0, 0, 0, -RATE, 0, 0, 0, -RATE)
    return L


def strain():
    return O.time * RATE


def kinetic():
    return sum(0.5 * b.state.mass * b.state.vel.squaredNorm() for b in O.bodies)


def contacts():
    return sum(1 for i in O.interactions if i.isReal and i.geom.penetrationDepth > 0)


def advance_to(target, chunk=200):
    """Run until the strain reaches ``target``; (ok, why not)."""
    while strain() < target:
        try:
            O.run(chunk, True)
        except Exception as exc:  # (YADE stops on a body that crossed half the cell)
            return False, str(exc).splitlines()[0]
        e = kinetic()
        if not math.isfinite(e) or e > 1e3:
            return False, f"kinetic energy {e:.3g} J"
    return True, ""


def say(*a):
    if not QUIET:
        print(*a, flush=True)


# ------------------------------------------------------------- the step at the start
build()
O.dt = 0.2 * utils.PWaveTimeStep()
while contacts() < FIRST:
    advance_to(strain() + 0.002, chunk=50)
start_cert = YadeCertifier(safety=1.0, log=lambda s: None).certify()
print(f"at strain {strain():.3f}: {start_cert.contacts} contacts, certified step "
      f"{start_cert.dt:.4g} s (exact, with damping {DAMPING}: springs x {1 + DAMPING})")

# ------------------------------------------------------------- A: a fixed step
build()
O.dt = 0.95 * start_cert.dt
ok, why = advance_to(STRAIN)
a_strain = strain()
print(f"A (fixed O.dt = 0.95 x that = {O.dt:.4g} s): "
      + ("stable to the end" if ok else f"UNSTABLE at strain {a_strain:.3f} ({why})"))

# ------------------------------------------------------------- B: demstep's engine
build()
O.dt = 0.2 * utils.PWaveTimeStep()
lines = []
cert = YadeCertifier(safety=0.8, log=lambda s: (lines.append(s), say(s)))
O.engines = O.engines + [cert.engine(iterPeriod=EVERY)]
ok_b, why_b = advance_to(STRAIN)
print(f"B (demstep every {EVERY} steps, safety 0.8): "
      + ("stable to the end" if ok_b else f"UNSTABLE at strain {strain():.3f} ({why_b})")
      + f"; {len(cert.history)} certificates, {sum(1 for c in cert.history if c.dt_set)} "
        f"changes of O.dt, {np.mean([c.seconds for c in cert.history]) * 1e3:.1f} ms each; "
        f"final O.dt {O.dt:.4g} s, certified {cert.history[-1].dt:.4g} s, "
        f"{cert.history[-1].contacts} contacts")

# ------------------------------------------------------------- C: GSTS
build()
O.engines = O.engines + [GlobalStiffnessTimeStepper(timeStepUpdateInterval=EVERY,
                                                    timestepSafetyCoefficient=0.8,
                                                    defaultDt=0.2 * utils.PWaveTimeStep(),
                                                    label="gsts")]
O.dt = 0.2 * utils.PWaveTimeStep()
gsts = []
marks = [0.04, 0.08, 0.12, 0.14, 0.16, 0.18, 0.20]
ok_c = True
for mark in marks:
    ok_c, why_c = advance_to(mark)
    if not ok_c:
        print(f"C (GSTS): UNSTABLE at strain {strain():.3f} ({why_c})")
        break
    gsts_engine = O.engines[-1]
    gsts_engine.active = False  # (the certifier refuses an active time stepper)
    probe = YadeCertifier(safety=1.0, log=lambda s: None).certify()
    gsts_engine.active = True
    gsts.append((mark, O.dt, probe.dt, probe.contacts))
if ok_c:
    print("C (GSTS 0.8, every 50 steps): stable to the end")
print(f"{'strain':>6s} {'contacts':>8s} {'GSTS O.dt':>10s} {'certified':>10s} "
      f"{'GSTS / certified':>16s}")
for mark, dt, certified, n in gsts:
    print(f"{mark:6.2f} {n:8d} {dt:10.4g} {certified:10.4g} {dt / certified:16.3f}")
