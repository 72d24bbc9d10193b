"""The paper's validation: FCC plane strain acceptance, stability thresholds, CLI JSON."""

import json
import math

import numpy as np
import pytest

from demstep.cli import main
from demstep.experiments.fcc_plane_strain import (
    FCCConfig, fcc_specimen, run_stage1, run_stage2, thornton_axisymmetric_ratio,
    thornton_peak_ratio,
)
from demstep.experiments.stability import STUDY_NAMES, stability_threshold


def test_thornton_formula():
    assert thornton_peak_ratio(0.3) == pytest.approx(4.88, abs=0.005)
    assert thornton_peak_ratio(0.0) == pytest.approx(2.0)
    assert thornton_axisymmetric_ratio(0.3) == pytest.approx(2 * 1.3 / 0.7)


def test_thornton_ratio_from_statics_of_the_sliding_contacts():
    """Independent check: stresses of the eight inclined contacts n = (+-1/2, +-1/2,
    +-1/sqrt2) sliding with friction against the mechanism eps_xx = -2 eps_zz."""
    mu = 0.3
    sigma = np.zeros((3, 3))
    for sx in (1, -1):
        for sy in (1, -1):
            for sz in (1, -1):
                d = np.array([sx, sy, sz * math.sqrt(2)])  # branch vector (units of r)
                n = d / 2.0
                du = np.diag([2.0, 0.0, -1.0]) @ d  # relative motion of the neighbour
                t = du - (du @ n) * n
                assert abs(du @ n) < 1e-12  # the mechanism slides without approach
                f = n - mu * t / np.linalg.norm(t)
                sigma += np.outer(f, d)
    assert sigma[2, 2] / sigma[0, 0] == pytest.approx(thornton_peak_ratio(mu), rel=1e-12)


def test_specimen_is_150_touching_spheres():
    cfg = FCCConfig()
    x, length, height = fcc_specimen(cfg)
    assert len(x) == 150
    from scipy.spatial.distance import pdist

    d = x[:, None, :] - x[None, :, :]
    d[..., :2] -= length * np.rint(d[..., :2] / length)
    dist = np.linalg.norm(d, axis=2)[np.triu_indices(len(x), 1)]
    assert dist.min() == pytest.approx(2 * cfg.radius)
    assert pdist(x).min() == pytest.approx(2 * cfg.radius)


@pytest.fixture(scope="module")
def stage1():

    cfg = FCCConfig(strain=0.004)
    sim = run_stage1(cfg)
    return sim, cfg


def _stage2(stage1, tmp_path, **kw):
    from demstep.experiments.fcc_plane_strain import build_fcc
    from demstep.io.checkpoint import load_checkpoint, save_checkpoint

    sim0, cfg0 = stage1
    path = tmp_path / "stage1.npz"
    save_checkpoint(sim0, path)
    cfg = FCCConfig(**{**cfg0.__dict__, **kw})
    sim = build_fcc(cfg)
    load_checkpoint(sim, path)
    return run_stage2(sim, cfg)


def test_stage1_isotropic_and_at_rest(stage1):
    from demstep.experiments.fcc_plane_strain import stresses

    sim, cfg = stage1
    for s in stresses(sim):
        assert s == pytest.approx(cfg.confining_stress, rel=5e-3)
    assert sim.ledger.kinetic < cfg.ke_tol * sim.ledger.strain


def test_alpha_005_reaches_thornton_peak(stage1, tmp_path):
    res = _stage2(stage1, tmp_path, alpha=0.05)
    assert res.status == "stable"
    assert res.max_energy_error < 1e-2
    assert res.peak_ratio == pytest.approx(thornton_peak_ratio(0.3), rel=0.03)


def test_alpha_045_flagged_by_energy_balance(stage1, tmp_path):
    res = _stage2(stage1, tmp_path, alpha=0.45)
    assert res.status in ("energy-warning", "unstable")
    assert res.max_energy_error > 1e-2
    # above the exact critical step with rotation of the specimen
    assert res.alpha_exact_rotation < 0.45 < res.alpha_exact_translation


def test_alpha_075_detected_unstable_and_stopped(stage1, tmp_path):
    res = _stage2(stage1, tmp_path, alpha=0.75)
    assert res.status == "unstable"
    assert "diverged" in res.message and "state saved" in res.message
    full_steps = math.ceil(0.004 / (1e-4 * res.dt))
    assert res.steps < full_steps  # stopped early


def test_alpha_035_above_exact_step_with_rotation(stage1, tmp_path):
    """The paper's 'correct' alpha = 0.35 exceeds the exact critical step once rotation
    couples to the tangential springs; blocked rotation makes it stable again."""
    free = _stage2(stage1, tmp_path, alpha=0.35)
    assert free.alpha_exact_rotation < 0.35
    assert free.max_energy_error > 1e-2
    blocked = _stage2(stage1, tmp_path, alpha=0.35, rotation=False)
    assert blocked.status == "stable" and blocked.max_energy_error < 1e-2
    assert blocked.peak_ratio == pytest.approx(thornton_peak_ratio(0.3), rel=0.03)


@pytest.mark.parametrize("name", ["square", "fcc"])
def test_measured_threshold_matches_exact(name):
    res = stability_threshold(name, rtol=5e-3, steps=2000)
    exact = res.estimates["exact"]
    assert res.alpha_empirical == pytest.approx(exact, rel=0.01)
    assert res.estimates["element-coupled"] < res.alpha_empirical  # rigorous bound
    assert res.estimates["itasca"] > res.alpha_empirical  # unconservative


@pytest.mark.parametrize("name", [n for n in STUDY_NAMES if n not in ("square", "fcc")])
def test_measured_threshold_matches_exact_all(name):
    res = stability_threshold(name, rtol=5e-3, steps=2000)
    assert res.alpha_empirical == pytest.approx(res.estimates["exact"], rel=0.01)


def run_cli(argv, capsys):
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def test_fcc_cli_json_shape(capsys, tmp_path):
    code, out, err = run_cli(["fcc", "--alpha", "0.75", "--strain", "0.002", "--json",
                              "--out", str(tmp_path / "fcc")], capsys)
    assert code == 0, err
    data = json.loads(out)
    assert list(data) == ["mu", "alpha", "peak_ratio", "theory", "max_energy_error", "status"]
    assert data["status"] == "unstable" and data["alpha"] == 0.75
    assert (tmp_path / "fcc" / "fcc_curves.csv").exists()
    assert (tmp_path / "fcc" / "fcc_stress_ratio.png").read_bytes()[:4] == b"\x89PNG"


def test_stability_cli_json_shape(capsys):
    code, out, err = run_cli(["stability", "--lattice", "hex", "--rtol", "0.01", "--steps",
                              "1500", "--json"], capsys)
    assert code == 0, err
    data = json.loads(out)
    assert list(data) == ["lattice", "alpha_empirical", "estimates"]
    assert set(data["estimates"]) == {"exact", "element-coupled", "element-paper", "nodal", "itasca"}


@pytest.mark.parametrize("argv,needle", [
    (["fcc", "--mu", "0.7"], "mu"),
    (["fcc", "--alpha", "-1"], "alpha"),
    (["stability", "--lattice", "diamond"], "unknown lattice"),
    (["paper", "--workers", "0"], "workers"),
    # a compression of 100 % or more (it ran on and on), a tolerance of 1 or more
    (["fcc", "--strain", "5"], "strain: must lie in (0, 1), got '5'"),
    (["fcc", "--strain", "1"], "strain: must lie in (0, 1), got '1'"),
    (["stability", "--lattice", "sc", "--rtol", "5"], "rtol: must lie in (0, 1), got '5'"),
])
def test_experiment_bad_options(capsys, argv, needle):
    code, out, err = run_cli(argv, capsys)
    assert code == 2 and needle in err and "Traceback" not in err


def test_paper_quick_end_to_end(tmp_path, capsys):
    out = tmp_path / "paper"
    code, stdout, err = run_cli(["paper", "--quick", "--out", str(out), "--quiet"], capsys)
    assert code == 0, err
    for name in ("report.md", "report.html", "summary.json", "critical_steps.png",
                 "fcc_stress_ratio.png", "fcc_energy_error.png", "stability.png",
                 "data/critical_steps.csv", "data/stability.json", "data/fcc_alpha_0.05.csv"):
        assert (out / name).exists(), name
    summary = json.loads((out / "summary.json").read_text())
    by_alpha = {(r["alpha"], r["rotation"]): r for r in summary["fcc"]}
    assert by_alpha[(0.05, True)]["status"] == "stable"
    assert by_alpha[(0.75, True)]["status"] == "unstable"
    assert by_alpha[(0.45, True)]["max_energy_error"] > 1e-2
    assert summary["version"] and summary["settings"]["quick"] is True
    for r in summary["stability"]:
        assert r["alpha_empirical"] == pytest.approx(r["estimates"]["exact"], rel=0.02)
    # damping and the critical step: measured thresholds on the damped exact step (the
    # quick bisection tolerance is 1 %), restitution 0.5 near 0.43 of the undamped step
    damping = {r["restitution"]: r for r in summary["damping"]}
    assert set(damping) == {1.0, 0.9, 0.5, 0.2} and (out / "damping.png").exists()
    for r in damping.values():
        assert r["alpha_empirical"] == pytest.approx(r["estimates"]["exact"], rel=0.02)
        assert r["estimates"]["element-coupled"] <= r["alpha_empirical"]
    half = damping[0.5]["estimates"]
    assert half["exact"] / half["exact-undamped"] == pytest.approx(0.43, abs=0.01)
    assert damping[0.2]["rayleigh_20"] > damping[0.2]["alpha_empirical"]  # the rule fails
    report = (out / "report.md").read_text()
    assert "Thornton" in report and "Resolved parameters" in report
    assert "Damping and the critical step" in report
    # clumps: every shape's measured threshold on its exact step, the body element
    # bound below it
    clumps = [r for r in summary["clumps"] if "alpha_empirical" in r]
    assert {r["members"] for r in clumps} == {2, 3, 4, 8} and len(clumps) == 8
    for r in clumps:
        assert r["alpha_empirical"] == pytest.approx(r["estimates"]["exact"], rel=0.02)
        assert r["estimates"]["element-coupled"] <= r["alpha_empirical"]
    assert "Clumps" in report and (out / "clumps.png").exists()


def test_engine_api_example_runs():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).parents[1] / "examples" / "engine_api.py"
    spec = importlib.util.spec_from_file_location("engine_api", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    sim = mod.main(steps=600)
    assert sim.step == 600 and sim.monitor.max_error < 1e-2


@pytest.mark.parametrize("args, words", [
    (["--scheduler", "tcp://127.0.0.1:1", "--workers", "3"], ["workers", "--scheduler", "3"]),
    (["--scheduler", "tcp://127.0.0.1:1"], ["scheduler: cannot connect to tcp://127.0.0.1:1"]),
    (["--scheduler", "localhost"], ["tcp://HOST:PORT"]),
])
def test_paper_with_a_bad_cluster_writes_nothing(tmp_path, capsys, monkeypatch, args, words):
    """`demstep paper` with --workers beside --scheduler, an unreachable scheduler or a
    malformed address: exit 2, one line, and no output folder (the unreachable one left
    data/ with the critical-step table and the first FCC stage after its timeout)."""
    from demstep.sweep import cluster

    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT", 1.0)
    out = tmp_path / "paper"
    try:
        code = main(["paper", "--out", str(out), "--quiet", *args])
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    for w in words:
        assert w in err
    assert not out.exists()
