"""examples/liggghts_tutorials/conveyor.toml, LIGGGHTS' conveyor tutorial as a demstep
case: it reads the tutorial's own meshes (from Debian's liggghts-doc; skipped without
them) with the belt's surface velocity, the tutorial's Hertz material and its stream;
a short run drops spheres on the belt, which carries them towards -x as LIGGGHTS'
``surface_vel -4.5 0. 0.`` does. The whole comparison with LIGGGHTS is
validation/liggghts_tutorials.py (docs/validation-tutorials.md)."""

import tomllib
from pathlib import Path

import numpy as np
import pytest

from demstep.case import build_simulation, case_from_dict, load_case
from demstep.feed import BoxRegion

ROOT = Path(__file__).resolve().parent.parent
CASE = ROOT / "examples" / "liggghts_tutorials" / "conveyor.toml"
TUTORIAL = Path("/usr/share/doc/liggghts/examples/LIGGGHTS/Tutorials_public/conveyor")

pytestmark = pytest.mark.skipif(not (TUTORIAL / "meshes" / "conveyor.stl").is_file(),
                                reason="LIGGGHTS' conveyor tutorial is not installed "
                                       "(apt-get install liggghts-doc)")


def mesh_triangles(sim, k):
    """The corners (T, 3, 3) of mesh ``k`` of ``sim``."""
    return sim.meshes.tri[sim.meshes.tri_mesh == k].reshape(-1, 3, 3)


def test_the_case_reads_the_tutorials_meshes_material_and_stream():
    case = load_case(CASE)
    assert [m.name for m in case.meshes] == ["belt", "box"]
    for spec, name in zip(case.meshes, ["conveyor.stl", "box.stl"]):
        assert Path(spec.file) == TUTORIAL / "meshes" / name
    sim = build_simulation(case)
    # the belt: two triangles in z = 0, x from -0.1 to 0.5, 0.4 m wide, moving at -4.5 m/s
    belt = mesh_triangles(sim, 0)
    assert belt.shape == (2, 3, 3)
    np.testing.assert_allclose(belt.reshape(-1, 3).min(axis=0), [-0.1, -0.2, 0.0])
    np.testing.assert_allclose(belt.reshape(-1, 3).max(axis=0), [0.5, 0.2, 0.0])
    np.testing.assert_array_equal(sim.meshes.surface[0], [-4.5, 0.0, 0.0])
    np.testing.assert_array_equal(sim.meshes.vel, np.zeros((2, 3)))   # the triangles stay
    # the box: an open top, ten triangles (two per face, five faces)
    box = mesh_triangles(sim, 1)
    assert box.shape == (10, 3, 3)
    np.testing.assert_allclose(box.reshape(-1, 3).min(axis=0), [-0.5, -0.2, -0.2])
    np.testing.assert_allclose(box.reshape(-1, 3).max(axis=0), [0.5, 0.2, 0.2])
    assert not np.all(np.isclose(box[..., 2], 0.2), axis=1).any()   # no lid at z = 0.2
    assert np.all(np.isclose(box[..., 2], -0.2), axis=1).sum() == 2  # a floor at z = -0.2
    np.testing.assert_array_equal(sim.meshes.surface[1], [0.0, 0.0, 0.0])
    # LIGGGHTS' hertz with one material: E = 5 MPa, nu = 0.45, e = 0.3, mu = 0.5
    law = sim.law
    assert law.name == "hertz"
    assert (law.youngs_modulus, law.poisson_ratio) == (5.0e6, 0.45)
    assert (law.restitution, law.restitution_tangential, law.mu, law.mu_wall) == (0.3, 0.3, 0.5, 0.5)
    # the stream: 30 kg at 30 kg/s through the tutorial's face (z = 0.2) at 1 m/s down,
    # r = 15 and 25 mm holding 30 % and 70 % of the mass
    (stream,) = sim.feed.inserters
    assert (stream.mass_rate, stream.total_mass, stream.density) == (30.0, 30.0, 2500.0)
    np.testing.assert_array_equal(stream.velocity, [0.0, 0.0, -1.0])
    assert (sim.timestep.mode, sim.timestep.dt) == ("fixed", 1.0e-5)   # the tutorial's
    spec = case.insert[0]
    assert spec.radius.radii == [0.015, 0.025] and spec.radius.fractions == [0.3, 0.7]
    assert spec.radius.by == "mass"
    assert sum(s.duration for s in case.stages) == pytest.approx(1.4)   # 140,000 steps


@pytest.mark.slow  # (the tutorial run: `pytest -m slow`)
def test_spheres_dropped_on_the_belt_are_carried_towards_minus_x():
    """The case as it is but for the inserter: eight spheres put just over the middle of
    the belt, falling at 1 m/s, and 3,000 steps (30 ms). Each lands, bounces (restitution
    0.3), and leaves the impact moving towards -x, dragged by the belt's surface through
    friction (0.5); a belt without surface velocity would leave them at rest in x (checked
    by hand: with surface_velocity = 0 this test fails). The 3,000 steps take
    milliseconds; in a fresh process the Hertz step kernels are compiled first (about
    30 s: numba's cache misses them at every run, docs/validation-tutorials.md)."""
    data = tomllib.loads(CASE.read_text())
    data["insert"][0].update(
        region={"shape": "box", "lower": [0.1, -0.15, 0.0], "upper": [0.4, 0.15, 0.06]},
        mass_rate=None, total_mass=None, stop=None, fill_to=8, total=8, every=100, seed=4)
    data["insert"][0] = {k: v for k, v in data["insert"][0].items() if v is not None}
    data["stages"] = [{"name": "drop", "duration": 0.03}]
    data["output"] = {"history_every": 0, "vtk_every": 0, "checkpoint_every": 0}
    case = case_from_dict(data, base_dir=CASE.parent)
    sim = build_simulation(case)
    assert isinstance(sim.feed.inserters[0].region, BoxRegion)
    sim.run(steps=1000)
    assert len(sim.r) == 8
    assert sim.meshes.contacts[0] > 0                      # landing on the belt
    sim.run(steps=2000)
    x, v, r = np.asarray(sim.x), np.asarray(sim.v), np.asarray(sim.r)
    assert np.all(x[:, 2] > r - 0.002) and np.all(x[:, 2] < r + 0.01), x[:, 2] - r
    assert sim.meshes.contacts[1] == 0                     # the box is not touched
    assert np.all(v[:, 0] < -0.5), v[:, 0]                 # carried along the belt, -x
    assert np.all(v[:, 0] > -4.5), v[:, 0]                 # not faster than the belt
    assert np.abs(v[:, 1]).max() < 0.05 * np.abs(v[:, 0]).min()   # not across it
    assert np.all(x[:, 0] > -0.1)                          # still over the belt
