"""examples/liggghts_tutorials/chute_wear.toml, LIGGGHTS' chute_wear tutorial as a
demstep case: it reads the tutorial's own trough and inlet face (from Debian's
liggghts-doc; skipped without them), the tutorial's Hertz material, its stream of two
sizes at 0.1 kg/s and Finnie's wear on the trough (k_finnie 1.0); a short run lets the
first packets fall onto the trough and wear it. The whole comparison with LIGGGHTS is
validation/liggghts_chute_wear.py (docs/validation-wear.md)."""

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from demstep.case import build_simulation, case_from_dict, load_case
from demstep.feed import BoxRegion
from demstep.io.history import read_history
from demstep.runner import run_case

ROOT = Path(__file__).resolve().parent.parent
CASE = ROOT / "examples" / "liggghts_tutorials" / "chute_wear.toml"
TUTORIAL = Path("/usr/share/doc/liggghts/examples/LIGGGHTS/Tutorials_public/chute_wear")

pytestmark = pytest.mark.skipif(not (TUTORIAL / "meshes" / "simple_chute.stl").is_file(),
                                reason="LIGGGHTS' chute_wear tutorial is not installed "
                                       "(apt-get install liggghts-doc)")

DENSITY = 2500.0
M_BIG = DENSITY * 4.0 / 3.0 * math.pi * 0.0025 ** 3    # the heavier sphere [kg]


def test_the_case_reads_the_tutorials_trough_material_stream_and_wear():
    case = load_case(CASE)
    (chute,) = case.meshes
    assert chute.name == "chute"
    assert Path(chute.file) == TUTORIAL / "meshes" / "simple_chute.stl"
    assert chute.finnie_k == 1.0                                   # k_finnie ... 1.0
    sim = build_simulation(case)
    tri = sim.meshes.tri.reshape(-1, 3, 3)
    assert tri.shape == (1616, 3, 3)                               # the STL as it is
    np.testing.assert_allclose(tri.reshape(-1, 3).min(axis=0), [-0.36141, -0.149899, -0.243301])
    np.testing.assert_allclose(tri.reshape(-1, 3).max(axis=0), [0.05, 0.149899, 0.0259808])
    np.testing.assert_array_equal(sim.meshes.wear_k, [1.0])
    # LIGGGHTS' hertz with tangential history, one material: E = 5 MPa, nu = 0.45,
    # restitution 0.3 (both dashpots), friction 0.5 on spheres and the trough
    law = sim.law
    assert law.name == "hertz"
    assert (law.youngs_modulus, law.poisson_ratio) == (5.0e6, 0.45)
    assert (law.restitution, law.restitution_tangential, law.mu, law.mu_wall) == (0.3, 0.3, 0.5, 0.5)
    # the stream: 0.1 kg/s through the tutorial's face (z = 0.05) at 1 m/s down, r = 1.5
    # and 2.5 mm holding 30 % and 70 % of the mass, at most 6,000 particles; packets every
    # 100 steps (the tutorial's every 1,000: the case's header says why)
    (stream,) = sim.feed.inserters
    assert (stream.mass_rate, stream.density, stream.total, stream.every) == (0.1, DENSITY, 6000, 100)
    np.testing.assert_array_equal(stream.velocity, [0.0, 0.0, -1.0])
    face = stream.region.tri.reshape(-1, 3, 3)
    np.testing.assert_allclose(face[..., 2], 0.05)
    np.testing.assert_allclose(face.reshape(-1, 3).min(axis=0)[:2], [-0.035, -0.035])
    np.testing.assert_allclose(face.reshape(-1, 3).max(axis=0)[:2], [0.0, 0.035])
    spec = case.insert[0]
    assert spec.radius.radii == [0.0015, 0.0025] and spec.radius.fractions == [0.3, 0.7]
    assert spec.radius.by == "mass"
    # the tutorial's box (boundary f f f, lost atoms ignored): outlets outside it
    lost = sim.feed.outlets
    assert all(isinstance(o.region, BoxRegion) for o in lost)
    inside = np.array([[-0.499, -0.199, -0.399], [0.099, 0.199, 0.149], [-0.2, 0.0, -0.3]])
    outside = np.array([[-0.501, 0, 0], [0.101, 0, 0], [0, -0.201, 0], [0, 0.201, 0], [0, 0, -0.401]])
    assert not any(o.region.contains(inside).any() for o in lost)
    assert all(any(o.region.contains(p[None])[0] for o in lost) for p in outside)
    # the step, and 100,000 of them: 1 s
    assert (sim.timestep.mode, sim.timestep.dt) == ("fixed", 1.0e-5)
    assert sum(s.duration for s in case.stages) == pytest.approx(100_000 * 1.0e-5)
    assert case.output.history_every == 1000


@pytest.mark.slow  # (a minute and more of the tutorial run: `pytest -m slow`)
def test_the_first_packets_fall_onto_the_trough_and_wear_it(tmp_path):
    """The case as it is, run for 0.15 s (15,000 steps; history every 500). The stream
    inserts 0.1 kg/s: at each row the mass inserted follows the rate, within one
    packet behind (0.1 g every 1 ms) and less than one sphere ahead (mass by mass). The
    first packets (from t = 1 ms, just below the face, 1 m/s down) fall 0.15 m onto the
    trough: the first contact, and the first wear, come between 0.100 s and 0.110 s (free
    fall), not before; from then on the trough's worn volume (``chute.wear``) is
    positive and never decreases. Without ``finnie_k`` it would stay 0."""
    data = tomllib.loads(CASE.read_text())
    data["stages"] = [{"name": "flow", "duration": 0.15}]
    data["output"] = {"history_every": 500, "vtk_every": 0, "checkpoint_every": 0}
    case = case_from_dict(data, base_dir=CASE.parent)
    run_case(case, tmp_path / "out", quiet=True)
    h = read_history(tmp_path / "out" / "history.csv")
    t = np.asarray(h["time"])
    assert t[-1] == pytest.approx(0.15)
    # the stream: 0.1 kg/s, nothing waiting, nothing lost yet
    lead = np.asarray(h["stream.inserted_mass"]) - 0.1 * t
    assert np.all(lead >= -0.1 * 0.001) and np.all(lead < M_BIG), lead
    assert np.all(np.asarray(h["stream.pending"]) == 0)
    np.testing.assert_array_equal(h["particles"], h["stream.inserted"])
    assert h["particles"][-1] > 150
    # the wear: none before the first packet lands, then growing
    wear = np.asarray(h["chute.wear"])
    touching = np.asarray(h["chute.contacts"]) > 0
    first = int(np.argmax(wear > 0.0))
    assert wear[first] > 0.0
    assert 0.100 < t[first] <= 0.110, t[first]
    assert not touching[:first].any() or t[np.argmax(touching)] > 0.100
    assert np.all(wear[:first] == 0.0)
    assert np.all(np.diff(wear) >= 0.0)
    assert wear[-1] > 10.0 * wear[first]
    assert touching[first:].sum() >= 3     # (impacts last ~0.6 ms: few rows catch one)
