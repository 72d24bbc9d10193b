"""Finnie's wear of mesh walls (``finnie_k``): each contact wears its triangle by
2 k |F| |v_rel| f(gamma) dt / A while the particle approaches or slides along it,
f(gamma) = sin(2 gamma) - 3 sin^2(gamma) up to tan(gamma) = 1/3, cos^2(gamma) / 3 beyond.
The kernel against a step-by-step numpy evaluation of the same law, the angle
function against its closed form, and the outputs (history.csv, VTK, checkpoints)."""

import math

import numpy as np
import pytest

from demstep.contact.laws import LinearSpring
from demstep.engine import Simulation, TimeStep
from demstep.engine.meshes import MeshWall
from demstep.kernels.meshes import finnie_shape
from demstep.mesh import mesh_from_arrays
from demstep.particles import Particles

R, DENSITY, K_FINNIE = 0.01, 2500.0, 3e-7


def two_triangles(size=1.0):
    """A square of side ``size`` in z = 0 cut along its diagonal, normals up."""
    h = size / 2
    v = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    return mesh_from_arrays(v, np.array([[0, 1, 2], [0, 2, 3]]), name="plate")


def thrown_at_plate(v0, mesh_velocity=(0.0, 0.0, 0.0), finnie_k=K_FINNIE):
    x = np.array([[0.2, -0.2, R + 0.002]])  # (over triangle 0, far from the diagonal)
    return Simulation(Particles.from_density(x, np.array([R]), DENSITY),
                      LinearSpring(k_n=5e4, mu=0.4, restitution=0.5),
                      meshes=[MeshWall(two_triangles(), name="plate", finnie_k=finnie_k,
                                       velocity=mesh_velocity)],
                      velocities=[list(v0)], gravity=[0, 0, -9.81],
                      timestep=TimeStep.fixed(2e-6))


def reference_rate(v_rel, force, area, k):
    """The law, written out with numpy: the particle's velocity relative to the plate
    v_rel, the contact force, the plate's normal +z (the contact normal from the
    sphere to the plate: -z)."""
    if -v_rel[2] < 0.0:  # (moving away from the plate)
        return 0.0
    speed = np.linalg.norm(v_rel)
    gamma = math.atan2(abs(v_rel[2]), math.hypot(v_rel[0], v_rel[1]))
    if math.tan(gamma) > 1.0 / 3.0:
        f = math.cos(gamma) ** 2 / 3.0
    else:
        f = math.sin(2 * gamma) - 3 * math.sin(gamma) ** 2
    return 2.0 * k * np.linalg.norm(force) * speed * f / area


@pytest.mark.parametrize("v0, mesh_velocity", [
    ((1.5, 0.4, -0.3), (0.0, 0.0, 0.0)),     # shallow: tan(gamma) < 1/3, cutting
    ((0.5, 0.0, -1.0), (0.0, 0.0, 0.0)),     # steep: the cos^2 / 3 branch
    ((0.2, 0.0, -0.4), (-0.6, 0.3, 0.0)),    # the plate slides under it: v_rel = v - u
])
def test_the_wear_of_an_impact_is_the_law_summed_step_by_step(v0, mesh_velocity):
    """A sphere thrown at a plate (sliding, bouncing, rolling): after every step the
    wear of the triangle under it grew by the law evaluated in numpy from the
    velocity the step's forces used (the half-step velocity before it), the plate's
    velocity, the contact force on the plate and the triangle's area; the other
    triangle wore nothing, and the branch of the law the impact takes was crossed."""
    sim = thrown_at_plate(v0, mesh_velocity)
    area = 0.5
    expected = 0.0
    worn_steps = 0
    u = np.asarray(mesh_velocity)
    for _ in range(6000):
        v_before = sim.v[0].copy()
        sim.run(steps=1)
        if sim.meshes.contacts[0]:
            rate = reference_rate(v_before - u, sim.mesh_force[0], area, K_FINNIE)
            expected += 2e-6 * rate
            worn_steps += rate > 0.0
    assert worn_steps > 50
    assert expected > 0.0
    assert sim.meshes.wear[0] == pytest.approx(expected, rel=1e-10)
    assert sim.meshes.wear[1] == 0.0
    assert sim.mesh_wear[0] == pytest.approx(expected * area, rel=1e-10)


def test_a_normal_impact_wears_nothing_and_wear_is_off_by_default():
    """Straight down (gamma = 90 degrees): f = cos^2(gamma) / 3 = 0 though the
    force is large (round-off only, against the wear of a throw at the same speed at
    30 degrees); and a plate without finnie_k tracks no wear."""
    down = thrown_at_plate((0.0, 0.0, -1.0))
    down.run(steps=6000)
    assert down.v[0, 2] > 0.0  # (it hit the plate and bounced)
    slanted = thrown_at_plate((math.cos(math.pi / 6), 0.0, -math.sin(math.pi / 6)))
    slanted.run(steps=6000)
    assert slanted.meshes.wear[0] > 0.0
    assert down.meshes.wear[0] < 1e-15 * slanted.meshes.wear[0]
    off = thrown_at_plate((1.5, 0.4, -0.3), finnie_k=0.0)
    off.run(steps=6000)
    assert np.all(off.meshes.wear == 0.0)  # (the same throw with it wears: above)


def test_finnie_shape_is_the_closed_form_and_continuous_at_tan_one_third():
    """f(gamma) at angles across both branches against its closed form, continuous
    where they meet (tan(gamma) = 1/3: 0.3 from both sides), largest near
    gamma = atan(2/3) / 2 = 16.8 degrees, 0 at grazing and normal incidence."""
    for deg in (0.0, 5.0, 12.0, 18.0, 18.5, 30.0, 60.0, 89.0, 90.0):
        g = math.radians(deg)
        closed = (math.sin(2 * g) - 3 * math.sin(g) ** 2 if math.tan(g) <= 1 / 3
                  else math.cos(g) ** 2 / 3)
        assert finnie_shape(math.sin(g), math.cos(g)) == pytest.approx(closed, abs=1e-15)
    g = math.atan(1 / 3)
    below, above = g * (1 - 1e-9), g * (1 + 1e-9)
    assert finnie_shape(math.sin(below), math.cos(below)) == pytest.approx(0.3, abs=1e-8)
    assert finnie_shape(math.sin(above), math.cos(above)) == pytest.approx(0.3, abs=1e-8)
    grid = np.radians(np.linspace(0.0, 90.0, 9001))
    f = np.array([finnie_shape(math.sin(a), math.cos(a)) for a in grid])
    assert math.degrees(grid[np.argmax(f)]) == pytest.approx(math.degrees(math.atan(2 / 3) / 2),
                                                             abs=0.02)
    assert f[0] == 0.0 and f[-1] == pytest.approx(0.0, abs=1e-30)


def test_wear_survives_a_restart_and_reaches_history_and_vtk(tmp_path):
    """The wear is part of the checkpointed state (a restart continues bit for bit),
    history.csv has each mesh's worn volume, the VTK frame each triangle's wear."""
    from demstep.io.checkpoint import load_checkpoint, save_checkpoint
    from demstep.io.history import columns_for, history_row
    from demstep.io.vtk import triangle_mesh

    a = thrown_at_plate((1.5, 0.4, -0.3))
    a.run(steps=4000)  # (it touches the plate from about step 3,300)
    save_checkpoint(a, tmp_path / "c.npz")
    assert a.meshes.wear[0] > 0.0
    a.run(steps=1500)
    b = thrown_at_plate((1.5, 0.4, -0.3))
    load_checkpoint(b, tmp_path / "c.npz")
    b.run(steps=1500)
    assert a.meshes.wear[0] > 0.0
    assert np.array_equal(a.meshes.wear, b.meshes.wear)
    cols = columns_for(3, [], "", mesh_names=["plate"])
    row = dict(zip(cols, history_row(a)))
    assert row["plate.wear"] == pytest.approx(a.meshes.wear[0] * 0.5, rel=1e-12)
    cells = triangle_mesh(a).cell_data
    assert np.array_equal(cells["wear"][0], a.meshes.wear)
    assert "wear" not in triangle_mesh(thrown_at_plate((1, 0, -1), finnie_k=0.0)).cell_data
