"""Insertion and outlets in case files: a run that starts empty and fills, its history
(particles, counts, masses, the energy in and out), a restart that continues bit for
bit through a changing particle set, demstep dt on its checkpoint, and bad [[insert]]
or [[outlet]] input refused in one line before anything is written."""

import numpy as np
import pytest
import tomli_w

from demstep.case import build_simulation, case_from_dict
from demstep.errors import InputError
from demstep.io.checkpoint import load_checkpoint
from demstep.io.history import read_history
from tests.conftest import assert_one_line_error, cli, snapshot

R, DENSITY, G = 0.001, 2500.0, 9.81
DT = 1e-5


def bin_case(**insert):
    """A 20 mm square bin (box walls) filled from a box above it at a count rate, with
    an outlet region taking what lies in the corner column x, y < 4 mm (every 500
    steps)."""
    spec = {"name": "feed", "region": {"shape": "box", "lower": [0.0, 0.0, 0.02],
                                       "upper": [0.02, 0.02, 0.03]},
            "radius": {"distribution": "uniform", "min": 0.8 * R, "max": R},
            "density": DENSITY, "rate": 20000.0, "total": 120,
            "velocity": [0.0, 0.0, -0.2], "every": 100, "seed": 7}
    spec.update(insert)
    return {
        "name": "bin", "gravity": [0.0, 0.0, -G],
        "particles": {"generator": "none"},
        "contact": {"law": "linear", "k_n": 2e3, "mu": 0.3, "restitution": 0.5},
        "box": {"lower": [0.0, 0.0, 0.0], "upper": [0.02, 0.02, 0.06]},
        "insert": [spec],
        "outlet": [{"name": "corner", "every": 500,
                    "region": {"shape": "box", "lower": [-1.0, -1.0, -1.0],
                               "upper": [0.004, 0.004, 1.0]}}],
        "timestep": {"dt": DT},
        "stages": [{"name": "fill", "duration": 0.06}],
        "output": {"history_every": 250, "checkpoint_every": 3000},
    }


def write(tmp_path, data, name="case.toml"):
    path = tmp_path / name
    path.write_text(tomli_w.dumps(data))
    return path


def test_a_bin_fills_from_empty_and_its_history_adds_up(tmp_path, capsys):
    code, _, err = cli(["run", write(tmp_path, bin_case()), "--out", tmp_path / "out",
                        "--quiet"], capsys)
    assert code == 0, err
    h = read_history(tmp_path / "out" / "history.csv")
    assert h["particles"][0] < 120 and h["feed.inserted"][-1] == 120
    # what is there is what came in less what went out, at every row
    assert np.array_equal(h["particles"], h["feed.inserted"] - h["corner.removed"])
    assert h["corner.removed"][-1] > 0
    # the count follows the rate (20,000/s, at the events every 100 steps) up to the total
    t_event = np.floor(h["step"] / 100) * 100 * DT
    assert np.array_equal(h["feed.inserted"], np.minimum(np.floor(20000 * t_event + 1e-9), 120))
    m_one = DENSITY * 4 / 3 * np.pi * np.array([0.8 * R, R]) ** 3
    per = h["feed.inserted_mass"][-1] / 120
    assert m_one[0] < per < m_one[1]
    assert h["energy_inserted"][-1] > 0 and h["energy_removed"][-1] > 0
    ok = np.isfinite(h["energy_error"])
    assert ok[-1] and h["energy_error"][ok].max() < 1e-2


def test_a_restart_through_a_changing_particle_set_is_bit_for_bit(tmp_path, capsys):
    case = write(tmp_path, bin_case())
    assert cli(["run", case, "--out", tmp_path / "a", "--quiet"], capsys)[0] == 0
    ckpt = tmp_path / "a" / "checkpoints" / "step0000003000.npz"
    assert cli(["run", case, "--out", tmp_path / "b", "--quiet", "--restart", ckpt],
               capsys)[0] == 0
    final = sorted((tmp_path / "a" / "checkpoints").glob("*.npz"))[-1]
    sims = []
    for run in ("a", "b"):
        sim = build_simulation(case_from_dict(bin_case(), base_dir=tmp_path))
        load_checkpoint(sim, tmp_path / run / "checkpoints" / final.name)
        sims.append(sim)
    a, b = sims
    assert len(a.r) > 0 and a.feed.outlets[0].removed > 0
    for name in ("x", "v", "w", "r"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(a.particle_ids(), b.particle_ids())
    ha = read_history(tmp_path / "a" / "history.csv")
    hb = read_history(tmp_path / "b" / "history.csv")
    later = ha["step"] > 3000
    assert np.array_equal(ha["step"][later], hb["step"])
    assert np.array_equal(ha["particles"][later], hb["particles"])
    assert np.array_equal(ha["energy_removed"][later], hb["energy_removed"])
    # demstep dt reads the checkpoint of a run whose particles came and went
    code, out, err = cli(["dt", final, "--case", case], capsys)
    assert code == 0, err
    assert "exact" in out


@pytest.mark.parametrize("change, words", [
    ({"insert": [{**bin_case()["insert"][0], "region": {"shape": "box", "lower": [0, 0, 1],
                                                         "upper": [1, 1, 0]}}]},
     ["insert[0].region.upper", "must be above lower"]),
    ({"insert": [{**bin_case()["insert"][0], "mass_rate": 1.0}]},
     ["insert[0]", "give exactly one of rate"]),
    ({"insert": [{**bin_case()["insert"][0],
                  "radius": {"distribution": "lognormal", "median": 0.001}}]},
     ["insert[0].radius.sigma"]),
    ({"insert": [{**bin_case()["insert"][0], "region": {"shape": "cone"}}]},
     ["insert[0].region"]),
    ({"outlet": [{"name": "feed", "region": {"shape": "sphere", "center": [0, 0, 0],
                                             "radius": 1.0}}]},
     ["outlet[0].name", "duplicate", "'feed'"]),
    ({"insert": []}, ["particles.generator", "add an [[insert]]"]),
    ({"insert": [{**bin_case()["insert"][0], "region": {"shape": "face", "file": "no.stl"}}]},
     ["insert[0].region.file", "no.stl"]),
])
def test_bad_insertion_input_is_one_line_and_writes_nothing(tmp_path, capsys, change, words):
    data = bin_case()
    data.update(change)
    case = write(tmp_path, data)
    before = snapshot(tmp_path)
    code, _, err = cli(["run", case, "--out", tmp_path / "out"], capsys)
    assert_one_line_error(code, err, *words)
    assert snapshot(tmp_path) == before


def test_a_case_without_insertion_resolves_as_before():
    data = bin_case()
    data["particles"] = {"generator": "grid", "count": [2, 2, 2], "spacing": 0.003,
                         "radius_min": R, "radius_max": R, "density": DENSITY}
    for key in ("insert", "outlet"):
        data.pop(key)
    resolved = case_from_dict(data).resolved()
    assert "insert" not in resolved and "outlet" not in resolved
