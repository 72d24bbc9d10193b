"""examples/liggghts_tutorials/movingMeshGran.toml, LIGGGHTS' movingMeshGran tutorial as a
demstep case: the tutorial's bucket (read from Debian's liggghts-doc; skipped without
it) with its transforms, LIGGGHTS' hooke stiffnesses converted by its own formula, the
stages of the tutorial's runs (70,000 steps of 5e-5 s), the bucket no wall until the
stage that switches it on, then moved and turned about the y axis through the origin.
A short run checks that the switch works: a sphere pressed into the bucket has no
contact while the bucket is off and is pushed out once it is on, and the bucket then
moves and turns as the tutorial's. The whole comparison with LIGGGHTS is
validation/liggghts_tutorials.py (docs/validation-tutorials.md)."""

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from demstep.case import build_simulation, case_from_dict, load_case
from demstep.case.stages import apply_stage
from demstep.mesh import read_mesh

ROOT = Path(__file__).resolve().parent.parent
CASE = ROOT / "examples" / "liggghts_tutorials" / "movingMeshGran.toml"
TUTORIAL = Path("/usr/share/doc/liggghts/examples/LIGGGHTS/Tutorials_public/movingMeshGran")
TRANSFORMS = ("move -50. -250. 0. scale 0.002 rotate axis 0. 1. 0. angle 90. "
              "rotate axis 0. 0. 1. angle 90.")

pytestmark = pytest.mark.skipif(not (TUTORIAL / "meshes" / "bucket.stl").is_file(),
                                reason="LIGGGHTS' movingMeshGran tutorial is not installed "
                                       "(apt-get install liggghts-doc)")


def hooke_stiffness(r_star, m_star, youngs=5.0e6, poisson=0.45, v_c=2.0):
    """LIGGGHTS' hooke (normal_model_hooke.h), one material: E* = E / (2 (1 - nu^2))."""
    e_star = youngs / (2.0 * (1.0 - poisson ** 2))
    root = math.sqrt(r_star)
    return 16.0 / 15.0 * root * e_star * (15.0 * m_star * v_c ** 2 / (16.0 * root * e_star)) ** 0.2


def test_the_case_is_the_tutorial():
    case = load_case(CASE)
    r, density = 0.04, 2500.0
    m = density * 4.0 / 3.0 * math.pi * r ** 3
    k_pair, k_wall = hooke_stiffness(r / 2, m / 2), hooke_stiffness(r, m)
    # the contact: LIGGGHTS' hooke as linear springs, k_t = k_n, c_t = c_n from e = 0.9
    c = case.contact
    assert c.law == "linear"
    assert c.k_n == pytest.approx(k_pair, abs=0.5) and c.k_s == c.k_n           # 36,749 N/m
    assert (c.restitution, c.restitution_tangential, c.mu, c.mu_wall) == (0.9, 0.9, 0.05, 0.05)
    # the box of plane walls (they take the pair stiffness: no material of their own)
    assert case.box.lower == [-1.0, -0.5, -0.5] and case.box.upper == [1.0, 0.5, 0.5]
    # the bucket: the tutorial's file and transforms, the wall stiffness, off at first
    (bucket,) = case.meshes
    assert bucket.name == "bucket" and Path(bucket.file) == TUTORIAL / "meshes" / "bucket.stl"
    assert bucket.transforms.split() == TRANSFORMS.split()
    assert bucket.material["k_n"] == pytest.approx(k_wall, abs=0.5)              # 55,702 N/m
    assert bucket.material["k_s"] == bucket.material["k_n"]
    assert bucket.enabled is False
    assert k_wall / k_pair == pytest.approx(2 ** 0.6)    # R* and m* both twice the pair's
    # insert/pack: the region bc topped up to 1,500 every 2,000 steps, the last at 6,000
    (pack,) = case.insert
    assert pack.fill_to == 1500 and pack.every == 2000 and pack.radius == r
    assert pack.density == density and pack.velocity == [0.0, 0.0, -0.8]
    assert pack.region.lower == [-0.9, -0.4, -0.5] and pack.region.upper == [0.9, 0.4, 0.0]
    dt = case.timestep.dt
    assert dt == 5.0e-5
    assert 6000 * dt <= pack.stop < 8000 * dt
    # the stages: the tutorial's runs, 70,000 steps (3.5 s)
    steps = [s.steps for s in case.stages]
    assert steps == [8000, 21999, 1, 15000, 25000]
    assert sum(steps) == 70000 and sum(steps) * dt == pytest.approx(3.5)
    starts = np.cumsum([0] + steps[:-1])
    on = [k for k, s in enumerate(case.stages) if "bucket" in s.meshes
          and s.meshes["bucket"].enabled]
    assert on == [2] and starts[2] == 29999     # a wall for `run 30000 upto`'s one step
    translate, rotate = case.stages[3].meshes["bucket"], case.stages[4].meshes["bucket"]
    assert starts[3] == 30000 and translate.velocity == [-0.5, 0.0, -0.3]
    assert starts[4] == 45000 and rotate.velocity == [0.0, 0.0, 0.0]
    assert rotate.center == [0.0, 0.0, 0.0]
    np.testing.assert_allclose(rotate.omega, [0.0, 2.0 * math.pi / 2.0, 0.0], rtol=0, atol=1e-15)


def bucket_corners(sim):
    return np.asarray(sim.meshes.tri)[np.asarray(sim.meshes.tri_mesh) == 0].reshape(-1, 3, 3)


@pytest.mark.slow  # (a minute and more of the tutorial run: `pytest -m slow`)
def test_the_bucket_touches_nothing_until_its_stage_switches_it_on():
    """One sphere put 5 mm into the underside of the bucket's top plate (the insertion
    ignores a disabled mesh), the stages shortened to 10, 9, 1, 10 and 10 steps: no
    contact and no force on it while the bucket is off (it falls freely); the step after
    the switch, a contact pushes it down and the bucket up; then the bucket translates
    and turns about the y axis through the origin, as the tutorial's, to round-off."""
    data = tomllib.loads(CASE.read_text())
    top = 0.0791                                   # the plate's underside [m]
    z = top - 0.035                                # the centre: 5 mm of overlap
    data["insert"][0].update(
        region={"shape": "box", "lower": [0.30, 0.15, z - 0.04], "upper": [0.40, 0.25, z + 0.04]},
        fill_to=1, velocity=[0.0, 0.0, 0.0], every=1000)
    for stage, n in zip(data["stages"], [10, 9, 1, 10, 10]):
        stage["steps"] = n
    data["output"] = {"history_every": 0, "vtk_every": 0, "checkpoint_every": 0}
    case = case_from_dict(data, base_dir=CASE.parent)
    sim = build_simulation(case)
    dt, g = 5.0e-5, 9.81
    start = read_mesh(TUTORIAL / "meshes" / "bucket.stl", TRANSFORMS)
    np.testing.assert_allclose(bucket_corners(sim), start.vertices[start.triangles], atol=1e-12)

    apply_stage(sim, case, 0)
    sim.run(steps=10)
    assert len(sim.r) == 1
    assert top - float(sim.x[0, 2]) < 0.04 - 0.004        # pressed into the plate
    assert not sim.mesh_enabled[0]
    for k, n in ((0, 0), (1, 9)):
        if n:
            apply_stage(sim, case, k)
            sim.run(steps=n)
        assert sim.meshes.contacts[0] == 0
        np.testing.assert_array_equal(sim.mesh_force[0], 0.0)
    # free fall all along (19 steps; the velocity held half a step behind): the bucket
    # did nothing to it (its 5 mm overlap would give 0.02 m/s in one step)
    assert float(sim.v[0, 2]) == pytest.approx(-g * 18.5 * dt, rel=1e-9)
    np.testing.assert_array_equal(np.asarray(sim.v)[0, :2], 0.0)
    np.testing.assert_array_equal(np.asarray(sim.w)[0], 0.0)

    apply_stage(sim, case, 2)                        # the bucket is a wall
    assert sim.mesh_enabled[0]
    sim.run(steps=1)
    assert sim.meshes.contacts[0] >= 1
    assert sim.mesh_force[0][2] > 100.0              # k_wall x 5 mm ~ 280 N, upwards on it
    assert float(sim.v[0, 2]) < -g * 20 * dt - 0.01  # and the sphere pushed down

    apply_stage(sim, case, 3)                        # move/mesh linear -0.5 0 -0.3
    sim.run(steps=10)
    d = np.array([-0.5, 0.0, -0.3]) * 10 * dt
    np.testing.assert_allclose(bucket_corners(sim), start.vertices[start.triangles] + d,
                               atol=1e-12)
    apply_stage(sim, case, 4)                        # rotate origin 0 0 0 axis 0 1 0 period 2
    sim.run(steps=10)
    phi = math.pi * 10 * dt                          # right-handed about +y
    rot = np.array([[math.cos(phi), 0.0, math.sin(phi)], [0.0, 1.0, 0.0],
                    [-math.sin(phi), 0.0, math.cos(phi)]])
    np.testing.assert_allclose(bucket_corners(sim), (start.vertices[start.triangles] + d) @ rot.T,
                               atol=1e-12)
