"""The certificate inside a running YADE scene (demstep.integrations.yade): what it reads
is what YADE computes, its step is demstep's exact step of the same contacts (and a
dense eigen-solve of an independently assembled matrix), YADE's own stability
threshold lies just above it, what it does not model is refused by name and stops
the run, and as an engine it sets O.dt. Every YADE run is a child process
(``python yade -n -x``: YADE has its own Python; :func:`yade_command` finds one that
imports demstep); skipped without YADE."""

import json
import math
import os
import tempfile
import textwrap

import numpy as np
import pytest

from demstep.integrations.yade import run_yade, yade_command
from demstep.timestep.guarantee import CLAIM_SLACK

#: the child's prelude: a periodic FCC block (3 x 3 x 3 cells, 108 spheres of radius
#: d/2 (1 + OVERLAP), d = a / sqrt 2, a = 1 m) at rest by symmetry, each sphere's mass
#: and inertia scaled by a random factor in [0.5, 2] (the geometry, hence the forces,
#: stay symmetric), a tiny random velocity and spin; or a walled slab
PRELUDE = r'''
import json, math, sys, time
import numpy as np
from yade import utils
from demstep.errors import InputError
from demstep.integrations.yade import YadeCertifier, read_scene, certified_step
OUT = {}

def done():
    print("RESULT " + json.dumps(OUT), flush=True)

LAWS = {
    "frict": (lambda: FrictMat(young=1e7, poisson=0.5, frictionAngle=1.5, density=2500),
              lambda: [Ig2_Sphere_Sphere_ScGeom(), Ig2_Wall_Sphere_ScGeom(),
                       Ig2_Box_Sphere_ScGeom(), Ig2_Facet_Sphere_ScGeom()],
              lambda: [Ip2_FrictMat_FrictMat_FrictPhys()],
              lambda: [Law2_ScGeom_FrictPhys_CundallStrack()]),
    "viscel": (lambda: ViscElMat(kn=5e6, ks=2.5e6, cn=2e3, cs=1e3, frictionAngle=1.5,
                                 density=2500),
               lambda: [Ig2_Sphere_Sphere_ScGeom()],
               lambda: [Ip2_ViscElMat_ViscElMat_ViscElPhys()],
               lambda: [Law2_ScGeom_ViscElPhys_Basic()]),
    "coh": (lambda: CohFrictMat(young=1e7, poisson=0.5, frictionAngle=1.5, density=2500,
                                momentRotationLaw=True, alphaKr=0.5, alphaKtw=0.5,
                                etaRoll=-1, etaTwist=-1, isCohesive=False),
            lambda: [Ig2_Sphere_Sphere_ScGeom6D()],
            lambda: [Ip2_CohFrictMat_CohFrictMat_CohFrictPhys()],
            lambda: [Law2_ScGeom6D_CohFrictPhys_CohesionMoment(always_use_moment_law=True,
                                                               useIncrementalForm=True)]),
    "mindlin": (lambda: FrictMat(young=1e7, poisson=0.3, frictionAngle=0.5, density=2500),
                lambda: [Ig2_Sphere_Sphere_ScGeom()],
                lambda: [Ip2_FrictMat_FrictMat_MindlinPhys()],
                lambda: [Law2_ScGeom_MindlinPhys_Mindlin()]),
}


def engines(law, damping=0.0, extra=()):
    mat, ig, ip, lw = LAWS[law]
    return [ForceResetter(),
            InsertionSortCollider([Bo1_Sphere_Aabb(), Bo1_Wall_Aabb(), Bo1_Box_Aabb(),
                                   Bo1_Facet_Aabb()]),
            InteractionLoop(ig(), ip(), lw()), NewtonIntegrator(damping=damping)] + list(extra)


def fcc(law="frict", damping=0.0, overlap=0.01, seed=1, n=3):
    O.reset()
    rng = np.random.default_rng(seed)
    mat = O.materials.append(LAWS[law][0]())
    O.periodic = True
    O.cell.hSize = Matrix3(n, 0, 0, 0, n, 0, 0, 0, n)
    d = 1.0 / math.sqrt(2.0)
    for i in range(n):
        for j in range(n):
            for k in range(n):
                for b in ((0, 0, 0), (0.5, 0.5, 0), (0.5, 0, 0.5), (0, 0.5, 0.5)):
                    p = [i + b[0] + 0.25, j + b[1] + 0.25, k + b[2] + 0.25]
                    bid = O.bodies.append(sphere(Vector3(*p), d / 2 * (1 + overlap),
                                                 material=mat))
                    s = O.bodies[bid].state
                    f = 0.5 + 1.5 * rng.random()
                    s.mass *= f
                    s.inertia = s.inertia * f
                    s.vel = Vector3(*(1e-5 * rng.standard_normal(3)))
                    s.angVel = Vector3(*(1e-5 * rng.standard_normal(3)))
    O.engines = engines(law, damping)
    O.dt = 1e-9
    O.run(1, True)


def slab(law="frict"):
    """Spheres on a Wall floor, against a fixed Box and under a Facet roof, touching
    each other: every kind of contact the certificate reads."""
    O.reset()
    mat = O.materials.append(LAWS[law][0]())
    r = 0.5
    for k in range(4):
        O.bodies.append(sphere((k * 0.98, 0, 0), r, material=mat))
    O.bodies.append(sphere((0.49, 0.0, 0.85), 0.5, material=mat))
    O.bodies.append(utils.wall(-0.49, axis=2, material=mat))
    O.bodies.append(utils.box((-0.99, 0, 0), (0.5, 1, 1), fixed=True, material=mat))
    O.bodies.append(utils.facet([(-3, -3, 1.34), (6, -3, 1.34), (1, 6, 1.34)], material=mat))
    O.engines = engines(law)
    O.dt = 1e-9
    O.run(1, True)


def energy():
    return sum(0.5 * b.state.mass * b.state.vel.squaredNorm()
               + 0.5 * b.state.inertia[0] * b.state.angVel.squaredNorm() for b in O.bodies)


ENERGIES = []
def record():
    ENERGIES.append(energy())


def grows(dt, steps=1000, **kw):
    """Whether the FCC block run at dt becomes unstable: energy beyond 1e6 x the start
    or the second half's largest above 10 x the first half's."""
    fcc(**kw)
    O.dt = dt
    del ENERGIES[:]
    O.engines = O.engines + [PyRunner(command="record()", iterPeriod=10)]
    O.run(steps, True)
    e = ENERGIES
    h = len(e) // 2
    return (not all(math.isfinite(v) for v in e)) or max(e) > 1e6 * e[0] \
        or max(e[h:]) > 10 * max(e[:h])
'''


def child(body: str, timeout: float = 120.0) -> dict:
    """Runs ``body`` after :data:`PRELUDE` in YADE, in its own process; the OUT dict it
    printed with ``done()``. Skips the test without YADE (or a Python for it)."""
    command, reason = yade_command()
    if command is None:
        pytest.skip(reason)
    with tempfile.TemporaryDirectory(prefix="demstep-yade-test-") as tmp:
        script = os.path.join(tmp, "scene.py")
        with open(script, "w") as f:
            f.write(PRELUDE + textwrap.dedent(body))
        proc = run_yade(script, timeout=timeout, cwd=tmp)
    line = next((x for x in proc.stdout.splitlines() if x.startswith("RESULT ")), None)
    assert line is not None, (proc.returncode, proc.stdout[-3000:], proc.stderr[-3000:])
    return json.loads(line[7:])


def test_contacts_read_are_yades_springs_and_arms():
    """Every real interaction with an overlap becomes one contact with YADE's own kn, ks
    (which are its Ip2 formula 2 E1 R1 E2 R2 / (E1 R1 + E2 R2), ks = nu kn for one
    material); wall, box and facet contacts are wall contacts of the sphere with the
    normal towards the wall (``wall``: its body id); the arms are sqrt(slip arm x torque arm) of the law."""
    got = child("""
    slab()
    sc = read_scene(O)
    c = sc.contacts
    OUT["n"] = c.n
    OUT["yade"] = [[i.id1, i.id2, i.phys.kn, i.phys.ks, i.geom.refR1, i.geom.refR2,
                    i.geom.penetrationDepth, list(i.geom.normal),
                    type(O.bodies[i.id1].shape).__name__] for i in O.interactions if i.isReal]
    OUT["young"], OUT["poisson"] = O.materials[0].young, O.materials[0].poisson
    OUT["ids"] = sc.ids.tolist()
    for k in ("i", "j", "wall", "k_n", "k_s", "arm_i", "arm_j", "normal"):
        OUT[k] = getattr(c, k).tolist()
    done()
    """)
    young, nu = got["young"], got["poisson"]
    assert got["n"] == len(got["yade"]) == 11  # 5 pairs, 4 floor, 1 box, 1 facet
    ids = got["ids"]
    seen = set()
    for id1, id2, kn, ks, r1, r2, delta, normal, shape1 in got["yade"]:
        # YADE's own Ip2_FrictMat_FrictMat_FrictPhys formula, from its reference radii
        assert kn == pytest.approx(2 * young * r1 * young * r2 / (young * r1 + young * r2))
        assert ks == pytest.approx(nu * kn)
        sphere = id2 if shape1 != "Sphere" else id1
        k = next(k for k in range(got["n"])
                 if ids[got["i"][k]] == sphere and
                 (got["wall"][k] == id1 if shape1 != "Sphere" else got["j"][k] >= 0 and ids[got["j"][k]] == id2))
        seen.add(k)
        assert got["k_n"][k] == kn and got["k_s"][k] == ks
        r = 0.5
        if shape1 == "Sphere":
            assert got["normal"][k] == pytest.approx(normal)
            assert got["arm_i"][k] == pytest.approx(math.sqrt(r * (r - delta / 2)))
            assert got["arm_j"][k] == pytest.approx(math.sqrt(r * (r - delta / 2)))
        else:
            assert got["normal"][k] == pytest.approx([-v for v in normal])
            slip = r if shape1 == "Wall" else r - delta / 2   # Wall: noRatch
            assert got["arm_i"][k] == pytest.approx(math.sqrt(slip * (r - delta / 2)))
            assert got["arm_j"][k] == 0.0
    assert len(seen) == got["n"]
    assert {s for *_, s in got["yade"]} == {"Sphere", "Wall", "Box", "Facet"}


def _independent_dt(got):
    """The critical step of the raw YADE data, from a dense matrix assembled here
    (numpy only: 6 DOFs per sphere, springs along n and in the tangent plane, arms
    sqrt(r (r - delta/2)) on the FCC block's sphere-sphere contacts), and demstep's
    certified step of the same contacts built here."""
    from demstep.particles import Particles
    from demstep.timestep.contacts import ContactSet
    from demstep.timestep.estimates import certified_dt

    m, inertia, r = (np.array(got[k]) for k in ("m", "inertia", "r"))
    index = {b: k for k, b in enumerate(got["ids"])}
    rows = got["pairs"]
    n = len(m)
    K = np.zeros((6 * n, 6 * n))
    ci, cj, normals, arms, kn, ks = [], [], [], [], [], []
    for id1, id2, k_n, k_s, delta, normal in rows:
        i, j = index[id1], index[id2]
        nv = np.array(normal)
        a_i = math.sqrt(r[i] * (r[i] - delta / 2))
        a_j = math.sqrt(r[j] * (r[j] - delta / 2))
        # relative displacement of the contact point (j minus i): B u
        X = lambda v: np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
        # (u_i, w_i, u_j, w_j): omega_j x (-a_j n) = (a_j n) x omega_j, -(omega_i x a_i n)
        B = np.hstack([-np.eye(3), X(a_i * nv), np.eye(3), X(a_j * nv)])
        D = k_n * np.outer(nv, nv) + k_s * (np.eye(3) - np.outer(nv, nv))
        dofs = np.r_[6 * i:6 * i + 6, 6 * j:6 * j + 6]
        K[np.ix_(dofs, dofs)] += B.T @ D @ B
        ci.append(i), cj.append(j), normals.append(nv), arms.append((a_i, a_j))
        kn.append(k_n), ks.append(k_s)
    mdiag = np.repeat(np.stack([m, m, m, inertia, inertia, inertia], axis=1).reshape(-1), 1)
    s = 1.0 / np.sqrt(mdiag)
    lam = np.linalg.eigvalsh(s[:, None] * K * s[None, :]).max()
    dense = 2.0 / math.sqrt(lam)
    arms = np.array(arms)
    contacts = ContactSet(ci, cj, np.array(normals), arms[:, 0], arms[:, 1], kn, ks)
    particles = Particles(np.array(got["x"]), r, m, inertia)
    return dense, certified_dt(particles, contacts, True)


def test_the_certified_step_is_demsteps_and_a_dense_solves():
    """On the FCC block (masses varied), the certifier's step equals demstep's certified
    step of the contacts built here from YADE's raw interactions and the dense eigen-solve of
    a matrix assembled here; a Cundall damping d multiplies the step by 1/sqrt(1 + d)
    (undamped contacts); rotation blocked everywhere locks it; the element bound lies
    below."""
    got = child("""
    fcc()
    cert = YadeCertifier(safety=1.0)
    OUT["dt"] = cert.certify().dt
    OUT["element"] = YadeCertifier(method="element").certify().dt
    OUT["ids"] = [b.id for b in O.bodies]
    OUT["m"] = [b.state.mass for b in O.bodies]
    OUT["inertia"] = [b.state.inertia[0] for b in O.bodies]
    OUT["r"] = [b.shape.radius for b in O.bodies]
    OUT["x"] = [list(b.state.pos) for b in O.bodies]
    OUT["pairs"] = [[i.id1, i.id2, i.phys.kn, i.phys.ks, i.geom.penetrationDepth,
                     list(i.geom.normal)] for i in O.interactions if i.isReal]
    O.engines[3].damping = 0.2
    OUT["cundall"] = cert.certify().dt
    O.engines[3].damping = 0.0
    for b in O.bodies:
        b.state.blockedDOFs = "XYZ"
    OUT["locked"] = cert.certify().dt
    done()
    """)
    assert len(got["pairs"]) == 648
    dense, certified = _independent_dt(got)
    assert got["dt"] == pytest.approx(certified, rel=1e-7)
    # the certified step: the dense one less at most the random-start check's slack
    assert dense * (1 - CLAIM_SLACK) <= got["dt"] <= dense
    assert got["cundall"] == pytest.approx(got["dt"] / math.sqrt(1.2), rel=1e-7)
    assert got["element"] < got["dt"]
    assert got["locked"] > 1.05 * got["dt"]


def test_yades_threshold_lies_just_above_the_certified_step():
    """YADE itself (leapfrog, no damping of any kind; FrictPhys, and ViscElPhys with its
    dashpots) runs the FCC block stably at 0.95 x the certified step and blows up at
    1.05 x; with NewtonIntegrator.damping = 0.2 it runs stably at the certified step,
    which is 1/sqrt(1.2) of the undamped one."""
    got = child("""
    for law in ("frict", "viscel"):
        fcc(law)
        dt = YadeCertifier(safety=1.0).certify().dt
        OUT[law] = [dt, grows(0.95 * dt, law=law), grows(1.05 * dt, law=law)]
    fcc("frict", damping=0.2)
    dt = YadeCertifier(safety=1.0).certify().dt
    OUT["cundall"] = [dt, grows(dt, law="frict", damping=0.2)]
    done()
    """)
    for law in ("frict", "viscel"):
        dt, stable_below, unstable_above = got[law]
        assert not stable_below, law
        assert unstable_above, law
    assert not got["cundall"][1]


#: (scene, what the refusal names): another IPhys, an active time stepper, an engine
#: with physics of its own, a dynamic wall, Cundall damping with cundall="refuse"
REFUSED = [
    ('fcc("mindlin")', "MindlinPhys"),
    ('fcc(); O.engines = O.engines + [GlobalStiffnessTimeStepper(active=True)]',
     "GlobalStiffnessTimeStepper"),
    ('fcc(); O.engines = O.engines[:3] + [LinearDragEngine(ids=[0], nu=0.1), O.engines[3]]',
     "LinearDragEngine"),
    ('slab(); O.bodies[5].dynamic = True', "Wall"),
    ('fcc(); O.engines[3].damping = 0.2; kw["cundall"] = "refuse"', "damping"),
]


def test_what_it_does_not_model_is_refused_by_name():
    body = "OUT['errors'] = []\n"
    for setup, _ in REFUSED:
        body += textwrap.dedent(f"""
        kw = {{}}
        {setup}
        try:
            YadeCertifier(**kw).certify()
            OUT["errors"].append(None)
        except InputError as exc:
            OUT["errors"].append(str(exc))
        """)
    got = child(body + "done()\n")
    for (setup, named), error in zip(REFUSED, got["errors"]):
        assert error is not None and named in error and "\n" not in error, (setup, error)


def test_as_an_engine_it_sets_o_dt_and_a_refusal_stops_the_run():
    """In O.engines the PyRunner lowers a step that is too long at once (with its reason
    in the log) and raises one that is far too short; a model it does not know stops
    O.run with the refusal."""
    got = child("""
    fcc()
    lines = []
    cert = YadeCertifier(safety=0.8, log=lines.append)
    certified = cert.certify().dt
    O.dt = 2.0 * certified
    O.engines = O.engines + [cert.engine(iterPeriod=50)]
    O.run(120, True)
    OUT["after_long"] = O.dt / certified
    O.dt = 0.1 * certified
    O.run(60, True)
    OUT["after_short"] = O.dt / certified
    OUT["log"] = lines
    OUT["changes"] = [c.dt_set for c in cert.history if c.dt_set]
    fcc("mindlin")
    O.engines = O.engines + [YadeCertifier().engine(iterPeriod=10)]
    try:
        O.run(20, True)
        OUT["stopped"] = None
    except Exception as exc:
        OUT["stopped"] = str(exc)
    OUT["iter"] = O.iter
    done()
    """)
    assert got["after_long"] == pytest.approx(0.8 / 1.05, rel=1e-6)
    assert got["after_short"] == pytest.approx(0.8 / 1.05, rel=1e-6)
    assert len(got["changes"]) == 2
    assert "above 0.8 x the certified step" in got["log"][0]
    assert "allows a longer one" in got["log"][1]
    assert got["stopped"] is not None and "MindlinPhys" in got["stopped"]
    assert got["iter"] < 20
