"""The case schema: what loads, what is refused (one line naming the key and the
value), the resolved dump, and how stages change a simulation."""

import copy
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from demstep.case import (
    apply_stage, build_simulation, case_from_dict, case_from_text, dump_case, load_case,
)
from demstep.errors import InputError
from demstep.kernels import dem

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
HEX = tomllib.loads((EXAMPLES / "hex_biaxial_2d.toml").read_text())


def mutated(change):
    data = copy.deepcopy(HEX)
    change(data)
    return data


def setitem(path, value):
    def change(data):
        node = data
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
    return change


def delitem(path):
    def change(data):
        node = data
        for key in path[:-1]:
            node = node[key]
        del node[path[-1]]
    return change


REFUSED = [
    (setitem(("contact", "mu"), -1), "contact.mu: input should be greater than or equal to 0, got -1"),
    (setitem(("contact", "mu"), "x"), "contact.mu: input should be a valid number, got 'x'"),
    (setitem(("contact", "mu"), True), "contact.mu: input should be a valid number, got True"),
    (setitem(("contact", "youngs_modulus"), 1e9), "contact.youngs_modulus: unknown key"),
    (delitem(("contact", "k_n")), "contact.k_n: required key is missing"),
    (delitem(("contact", "law")), "contact.law: required key is missing"),
    (setitem(("contact", "law"), "hooke"), "contact.law: must be one of 'cohesive', 'hertz', 'linear', got 'hooke'"),
    (setitem(("contact", "restitution"), 1.5), "contact.restitution"),
    (setitem(("particles", "radius"), 0), "particles.radius: input should be greater than 0, got 0"),
    (setitem(("particles", "density"), -2650.0), "particles.density"),
    (setitem(("particles", "density"), float("nan")), "particles.density: input should be a finite number"),
    (setitem(("particles", "density"), float("inf")), "particles.density: input should be a finite number"),
    (setitem(("particles", "lattice"), "cubic"), "particles.lattice"),
    (setitem(("particles", "size"), [1.5, 2]), "particles.size[0]: input should be a valid integer, got 1.5"),
    (setitem(("particles", "size"), [1, 2, 3]), "particles.size: expected 2 components for a 2D case"),
    (setitem(("particles", "size"), 10**6), "particles.size: more than 2000000 particles"),
    (setitem(("particles", "generator"), "random"), "particles.generator: must be one of"),
    (setitem(("timestep", "dt"), -1), "timestep.dt: input should be greater than 0, got -1"),
    (setitem(("timestep", "dt"), 1e-3), "timestep.alpha: not used with mode = 'fixed'"),
    (setitem(("timestep", "mode"), "auto"), "timestep.alpha: not used with mode = 'auto'"),
    (setitem(("energy", "x\ny"), 2), 'energy."x\\ny": unknown key'),
    (setitem(("contact", "twisting_stiffness"), 0.5),
     "contact.twisting_stiffness: disks do not twist (a 2D case), got 0.5"),
    (setitem(("stages", 1, "check_every"), 10),
     "stages[1].check_every: only used with until_kinetic_below, got 10"),
    (setitem(("timestep", "safety"), 0.8),
     "timestep.safety: only used with mode = 'auto' (the mode is 'alpha'), got 0.8"),
    (setitem(("timestep",), {"method": "exact", "every": 100}),
     "timestep.method: only used with mode = 'auto' (the mode is 'alpha'), got 'exact'"),
    (setitem(("timestep",), {"dt": 1e-3, "growth": 0.1}),
     "timestep.growth: only used with mode = 'auto' (the mode is 'fixed'), got 0.1"),
    (setitem(("timestep",), {"dt": 1e-3, "motion": 0.2}),
     "timestep.motion: only used with mode = 'auto' (the mode is 'fixed'), got 0.2"),
    (setitem(("timestep",), {"mode": "auto", "motion": 0.0}),
     "timestep.motion: input should be greater than 0, got 0.0"),
    (setitem(("timestep",), {"mode": "auto", "motion": 0.3}),
     "timestep motion: must be below jump_limit = 0.25 (the divergence check), got 0.3"),
    (setitem(("energy", "action"), "panic"), "energy.action"),
    (setitem(("damping",), {"local": 1.0}), "damping.local: input should be less than 1"),
    (setitem(("stages", 1, "walls", "y+", "velocity"), [0, 1, 2]),
     'stages[1].walls."y+".velocity: expected 2 components'),
    (setitem(("stages", 1, "walls", "top"), {"motion": "fixed"}), 'stages[1].walls."top": no such wall'),
    (setitem(("stages", 0, "steps"), 10), "stages[0]: give exactly one of steps, duration or until"),
    (setitem(("stages", 1, "max_steps"), 10), "stages[1].max_steps: only used with until"),
    (setitem(("stages",), []), "stages: list should have at least 1 item"),
    (delitem(("stages",)), "stages: required key is missing"),
    (setitem(("gravity",), [0, 0, -1]), "gravity: expected 2 components for a 2D case"),
    (setitem(("foo",), 1), "foo: unknown key"),
    (setitem(("box", "lower"), [0, 0]), "box: give both lower and upper"),
    (setitem(("box", "walls"), {"q+": {"motion": "fixed"}}), 'box.walls."q+": no such box wall'),
    (setitem(("walls",), [{"name": "x-", "point": [0, 0], "normal": [1, 0]}]),
     "walls[0].name: duplicate wall name, got 'x-'"),
    (setitem(("walls",), [{"name": "w", "point": [0, 0], "normal": [0, 0]}]), "walls[0].normal: must be non-zero"),
    (setitem(("walls",), [{"name": "w", "point": [0, 0], "normal": [1, 0], "motion": "velocity"}]),
     "walls[0].velocity: required with motion = 'velocity'"),
    (setitem(("stages", 1, "walls", "x+"), {"motion": "velocity"}), "velocity: required"),
    (setitem(("output", "vtk_every"), -5), "output.vtk_every"),
    (setitem(("periodic",), {"z": 10.0}), "periodic.z: a 2D case has no z axis"),
    (setitem(("particles",), 5), "particles: input should be a valid dictionary"),
    (setitem(("particles",), {"generator": "file", "path": "nothing.csv", "density": 1.0}),
     "particles.path: no such file, got 'nothing.csv'"),
]


@pytest.mark.parametrize("change,expected", REFUSED, ids=[e for _, e in REFUSED])
def test_refused_with_one_line_naming_key_and_value(change, expected):
    with pytest.raises(InputError) as info:
        case = case_from_dict(mutated(change), base_dir=EXAMPLES, source="case.toml")
        build_simulation(case)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("case.toml: ")
    assert expected in message


def test_walls_cutting_into_particles_refused_at_build():
    data = mutated(setitem(("walls",), [{"name": "cut", "point": [5.0, 5.0], "normal": [1.0, 0.0]}]))
    case = case_from_dict(data, base_dir=EXAMPLES, source="case.toml")
    with pytest.raises(InputError, match=r"^case.toml: wall 'cut': cuts deep into particle"):
        build_simulation(case)


def test_not_toml_and_missing_file(tmp_path):
    with pytest.raises(InputError, match=r"^case: not valid TOML"):
        case_from_text("a = [")
    with pytest.raises(InputError, match="no such case file"):
        load_case(tmp_path / "missing.toml")


@pytest.mark.parametrize("example", sorted(EXAMPLES.glob("*.toml")), ids=lambda p: p.stem)
def test_resolved_case_round_trips(tmp_path, example):
    case = load_case(example)
    path = tmp_path / "resolved.toml"
    path.write_text(dump_case(case))
    again = load_case(path)
    # the same case, its files named by absolute paths (the resolved case is read from
    # the run folder on a restart, not from the case file's)
    assert again.resolved() == case.resolved()
    assert dump_case(again) == dump_case(case)


def test_file_generator_relative_path_and_masses(tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "p.csv").write_text("x,y,r,m\n0,0,1,2.0\n2,0,1,3.0\n")
    text = """
[particles]
generator = "file"
path = "data/p.csv"
[contact]
law = "linear"
k_n = 10.0
[[stages]]
steps = 1
"""
    (tmp_path / "c.toml").write_text(text)
    case = load_case(tmp_path / "c.toml")
    sim = build_simulation(case)
    assert np.array_equal(sim.m, [2.0, 3.0])  # masses from the file
    assert case.resolved()["particles"]["path"] == str((tmp_path / "data" / "p.csv").resolve())
    (tmp_path / "data" / "q.csv").write_text("x,y,r\n0,0,1\n")
    (tmp_path / "d.toml").write_text(text.replace("p.csv", "q.csv"))
    with pytest.raises(InputError, match="particles.density: required"):
        load_case(tmp_path / "d.toml")


def test_grid_generator_and_fixed_selection():
    text = """
[particles]
generator = "grid"
count = [4, 3, 2]
spacing = 3.0
radius_min = 0.5
radius_max = 1.2
jitter = 0.1
seed = 3
density = 1.0
fixed = { indices = [0], lower = [0.0, 0.0, 0.0], upper = [100.0, 100.0, 3.0] }
[contact]
law = "hertz"
youngs_modulus = 1.0e6
poisson_ratio = 0.3
[[stages]]
steps = 1
"""
    sim = build_simulation(case_from_text(text))
    assert len(sim.r) == 24 and sim.r.min() >= 0.5 and sim.r.max() <= 1.2
    assert sim.fixed.sum() == 12  # the bottom layer (z = 1.5 +- 0.3)
    d = np.linalg.norm(sim.x[:, None] - sim.x[None], axis=-1) + np.eye(24) * 1e9
    assert (d >= sim.r[:, None] + sim.r[None]).all()  # no initial overlap
    with pytest.raises(InputError, match="particles.spacing: particles could overlap"):
        case_from_text(text.replace("spacing = 3.0", "spacing = 2.0"))


def test_stage_changes_reach_the_simulation():
    case = load_case(EXAMPLES / "hex_biaxial_2d.toml")
    sim = build_simulation(case)
    names = [w.name for w in sim.walls]
    assert names == ["x-", "x+", "y-", "y+"]
    assert (sim.wall_motion == dem.WALL_FIXED).all()
    apply_stage(sim, case, 0)
    assert (sim.wall_motion == dem.WALL_SERVO).all()
    assert (sim.servo[:, dem.S_TARGET] == 300.0).all()
    assert sim.damping.local == 0.2 and sim.law.mu == 0.0
    apply_stage(sim, case, 1)
    top, bottom = names.index("y+"), names.index("y-")
    assert sim.wall_motion[top] == dem.WALL_VELOCITY and sim.wall_vel[top].tolist() == [0, -0.01, 0]
    assert sim.wall_motion[bottom] == dem.WALL_FIXED and not sim.wall_vel[bottom].any()
    assert sim.wall_motion[names.index("x+")] == dem.WALL_SERVO
    assert sim.law.mu == 0.5 and sim.damping.local == 0.0


def test_stage_gravity_and_ledger_reset():
    text = tomli_w.dumps(mutated(setitem(("stages", 1, "gravity"), [0.0, -9.81])))
    case = case_from_text(text, base_dir=EXAMPLES)
    sim = build_simulation(case)
    apply_stage(sim, case, 0)
    sim.run(steps=50)
    assert sim.ledger.external > 0
    apply_stage(sim, case, 1)
    assert sim.gravity.tolist() == [0.0, -9.81, 0.0]
    held = sim.ledger.kinetic + sim.ledger.strain
    assert sim.ledger.external == pytest.approx(held)  # reset_ledger: the balance restarts


FCC = tomllib.loads((EXAMPLES / "fcc_plane_strain.toml").read_text())


@pytest.mark.parametrize("path,value,expected", [
    (("stages", 0, "periodic", "z"), {"motion": "fixed"},
     "stages[0].periodic.z: not a periodic axis of the case (periodic: x, y)"),
    (("stages", 0, "periodic", "x"), {"motion": "rate"}, "stages[0].periodic.x.rate: required"),
    (("stages", 0, "periodic", "x"), {"motion": "servo"},
     "stages[0].periodic.x.target_stress: required"),
    (("stages", 0, "periodic", "x"), {"motion": "shear"}, "stages[0].periodic.x.motion"),
    (("stages", 1, "timestep"), {"alpha": 0.1, "dt": 1e-3}, "stages[1].timestep.alpha: not used"),
    (("stages", 1, "timestep"), {"mode": "fixed"}, "stages[1].timestep.dt: required"),
])
def test_periodic_and_timestep_stage_changes_refused(path, value, expected):
    data = copy.deepcopy(FCC)
    setitem(path, value)(data)
    with pytest.raises(InputError) as info:
        case_from_dict(data, source="fcc.toml")
    assert expected in str(info.value) and "\n" not in str(info.value)


def test_periodic_and_timestep_stage_changes_reach_the_simulation():
    case = load_case(EXAMPLES / "fcc_plane_strain.toml")
    sim = build_simulation(case)
    assert (sim.box_motion == dem.BOX_FIXED).all()
    apply_stage(sim, case, 0)
    assert sim.box_motion[:2].tolist() == [dem.BOX_SERVO, dem.BOX_SERVO]
    assert sim.box_servo[0, dem.S_TARGET] == 1.0e6 and sim.box_servo[0, dem.S_MAXSPEED] == 0.77
    sim.run(steps=20)
    dt_stage1 = sim.dt
    apply_stage(sim, case, 1)
    assert sim.box_motion[:2].tolist() == [dem.BOX_SERVO, dem.BOX_FIXED]
    assert sim.timestep.mode == "alpha" and sim.timestep.alpha == 0.1 and sim.dt is None
    sim.prepare()
    assert sim.dt == dt_stage1


def test_lattice_clip_gives_the_4x4_3x3_layout():
    text = """
[particles]
generator = "lattice"
lattice = "fcc"
radius = 20.0
size = [4, 4, 6]
clip_upper = [120.0, 120.0, 400.0]
density = 2000.0
[contact]
law = "linear"
k_n = 1.0e11
[box]
[[stages]]
steps = 1
"""
    sim = build_simulation(case_from_text(text))
    layers = np.unique(np.round(sim.x[:, 2], 6))
    counts = [int(np.sum(np.isclose(sim.x[:, 2], z))) for z in layers]
    assert len(sim.r) == 150 and counts == [16, 9] * 6
    assert sim.wall_point[0, 0] == -20.0 and sim.wall_point[1, 0] == 140.0  # touching walls
    with pytest.raises(InputError, match="no lattice site inside the clip box"):
        build_simulation(case_from_text(text.replace("clip_upper = [120.0", "clip_upper = [-50.0")))


def test_a_periodic_axis_has_no_walls_across_it():
    """[box] with [periodic] x gives only the walls of the other axes (x- and x+ would
    cut the periodic box: the run diverged); a stage or [box.walls] naming x- is
    refused as no such wall, and a wall across a periodic axis is refused with its name
    and the axis, in a case and in the Python API."""
    from demstep.contact.laws import LinearSpring
    from demstep.engine import Simulation
    from demstep.particles import Particles
    from demstep.walls import Wall, box_walls

    text = """
name = "p"
stages = [{ name = "s1", steps = 20 }]
[particles]
generator = "lattice"
lattice = "hex"
radius = 1.0
size = [4, 3]
density = 1000.0
[periodic]
x = 8.0
[contact]
law = "linear"
k_n = 1e6
[box]
margin = 0.0
"""
    case = case_from_text(text)
    assert case.wall_names() == ["y-", "y+"]
    sim = build_simulation(case)
    assert [w.name for w in sim.walls] == ["y-", "y+"]
    sim.run(steps=20)
    with pytest.raises(InputError, match=r'box.walls."x-": no such box wall \(have y-, y\+\)'):
        case_from_text(text + '[box.walls."x-"]\nmotion = "velocity"\nvelocity = [1.0, 0.0]\n')
    crossing = text + ('[[walls]]\nname = "slope"\npoint = [0.0, 0.0]\n'
                       'normal = [0.1, 1.0]\n')
    with pytest.raises(InputError, match="wall 'slope': its normal .* periodic axis x"):
        build_simulation(case_from_text(crossing))
    p = Particles.from_density(np.array([[1.0, 1.0], [3.0, 1.0]]), np.ones(2), 1.0)
    with pytest.raises(InputError, match="wall 'x-': its normal .* periodic axis x"):
        Simulation(p, LinearSpring(k_n=1e3), walls=box_walls([0, 0], [4, 4]),
                   periodic=[4.0, None])
    Simulation(p, LinearSpring(k_n=1e3), walls=[Wall([0, 0], [0, 1], name="floor")],
               periodic=[4.0, None])
