"""Fuzz the case loader: random mutations of valid case files (keys deleted, types
changed, numbers negated or scaled, unknown keys added) either load, build a
Simulation and apply every stage, or raise InputError with a one-line message naming
the file; never another exception."""

import copy
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from demstep.case import apply_stage, build_simulation, load_case
from demstep.errors import InputError

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"

FILE_CASE = """
name = "from-file"
[particles]
generator = "file"
path = "packing.csv"
density = 2650.0
fixed = { indices = [0, 1] }
[contact]
law = "hertz"
youngs_modulus = 1.0e7
poisson_ratio = 0.3
mu = 0.2
restitution = 0.8
[[walls]]
name = "floor"
point = [0.0, 0.0, -1.0]
normal = [0.0, 0.0, 1.0]
[periodic]
x = 8.0
[timestep]
mode = "auto"
every = 50
[[stages]]
steps = 10
gravity = [0.0, 0.0, -9.81]
[stages.walls.floor]
motion = "servo"
target_stress = 10.0
area = 48.0
[output]
vtk_every = 5
"""


def base_cases():
    cases = [tomllib.loads((EXAMPLES / f"{name}.toml").read_text())
             for name in ("fcc_plane_strain", "hex_biaxial_2d", "polydisperse_settling_3d")]
    cases.append(tomllib.loads(FILE_CASE))
    return cases


BASES = base_cases()


def paths(node, prefix=()):
    if isinstance(node, dict):
        for key, value in node.items():
            yield prefix + (key,)
            yield from paths(value, prefix + (key,))
    elif isinstance(node, list):
        for k, value in enumerate(node):
            yield prefix + (k,)
            yield from paths(value, prefix + (k,))


def parent_of(data, path):
    node = data
    for item in path[:-1]:
        node = node[item]
    return node


VALUES = st.one_of(
    st.integers(-3, 20), st.sampled_from([0, -1, 2**40, 1e300, -1e-300, 0.0]),
    st.floats(allow_nan=True, allow_infinity=True), st.booleans(), st.text(max_size=6),
    st.lists(st.integers(-2, 6), max_size=4), st.lists(st.floats(-50, 50), max_size=4),
    st.dictionaries(st.text(min_size=1, max_size=5), st.integers(-2, 5), max_size=2),
    st.sampled_from(["linear", "hertz", "lattice", "grid", "file", "servo", "velocity",
                     "fixed", "auto", "alpha", "stop", "fcc", "hex"]),
)

OPS = ("delete", "replace", "negate", "zero", "scale", "unknown")


def mutate(data, draw):
    all_paths = list(paths(data))
    if not all_paths:
        return
    path = draw(st.sampled_from(all_paths))
    op = draw(st.sampled_from(OPS))
    parent = parent_of(data, path)
    key = path[-1]
    value = parent[key]
    if op == "delete":
        del parent[key]
    elif op == "replace":
        parent[key] = draw(VALUES)
    elif op in ("negate", "zero", "scale"):
        def change(v):
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                return v
            if op == "negate":
                return -v
            if op == "zero":
                return type(v)(0)
            return v * 1000 if isinstance(v, int) else v * 1.0e3
        if isinstance(value, list):
            parent[key] = [change(v) for v in value]
        else:
            parent[key] = change(value)
    else:
        target = value if isinstance(value, dict) else parent if isinstance(parent, dict) else None
        if target is not None:
            target[draw(st.sampled_from(["colour", "kn", "Mu", "steps", "extra_key"]))] = 1.0


@pytest.fixture(scope="module")
def case_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz")
    rng = np.random.default_rng(0)
    rows = ["x,y,z,r"]
    for i in range(3):
        for j in range(3):
            rows.append(f"{1 + 2 * i},{1 + 2 * j},{rng.uniform(0, 0.1)},{rng.uniform(0.9, 1.0)}")
    (folder / "packing.csv").write_text("\n".join(rows) + "\n")
    return folder


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_mutated_cases_load_or_raise_input_error(case_dir, data):
    base = copy.deepcopy(data.draw(st.sampled_from(BASES)))
    for _ in range(data.draw(st.integers(1, 3))):
        mutate(base, data.draw)
    try:
        text = tomli_w.dumps(base)
    except (TypeError, ValueError):
        assume(False)
    path = case_dir / "case.toml"
    path.write_text(text)
    try:
        case = load_case(path)
        sim = build_simulation(case)
        for k in range(len(case.stages)):
            apply_stage(sim, case, k)
    except InputError as exc:
        message = str(exc)
        assert message and "\n" not in message, message
        assert message.startswith(str(path)), message
        return
    assert sim.particles.n >= 1
    assert all(math.isfinite(v) for v in sim.x.ravel())


#: what each base case must build: particles, dimension, walls, fixed particles, stages
BASE_EXPECTED = {"fcc_plane_strain": (150, 3, 2, 0, 2), "hex_biaxial_2d": (120, 2, 4, 0, 2),
                 "polydisperse_settling_3d": (200, 3, 6, 0, 2), "from-file": (9, 3, 1, 2, 1)}


def test_every_base_case_is_valid(case_dir):
    """Each base case builds the simulation it describes, and every stage runs."""
    assert sorted(b["name"] for b in BASES) == sorted(BASE_EXPECTED)
    for base in BASES:
        path = case_dir / "case.toml"
        path.write_text(tomli_w.dumps(base))
        case = load_case(path)
        sim = build_simulation(case)
        n, dim, walls, fixed, stages = BASE_EXPECTED[base["name"]]
        assert (sim.particles.n, sim.dim, len(sim.walls)) == (n, dim, walls), base["name"]
        assert int(sim.fixed.sum()) == fixed and len(case.stages) == stages
        for k in range(len(case.stages)):
            apply_stage(sim, case, k)
            sim.run(steps=20)
        assert sim.step == 20 * stages and sim.dt > 0
        assert np.isfinite(sim.x).all() and np.isfinite(sim.ledger.energy).all()
