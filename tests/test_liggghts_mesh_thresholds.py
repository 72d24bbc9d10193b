"""`demstep dt --mesh` (and `--wall`) against LIGGGHTS' own measured stability threshold
of packings held by walls (``validation/liggghts_mesh_thresholds.py``, LIGGGHTS 3.8.0;
its states, meshes and results are committed, LIGGGHTS is not needed here): a Hertz
packing pressed by a mesh lid into a 48-facet cylinder with a pyramid on its floor,
the meshes 100 times stiffer than the spheres, and a box of six plane walls of the
spheres' own material. See docs/validation-meshes.md."""

import json
import shlex
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "validation"))
RESULTS = ROOT / "validation" / "results"
CASES = [rec for name in ("liggghts_mesh_thresholds.json", "liggghts_plane_box_thresholds.json")
         for rec in json.loads((RESULTS / name).read_text())["cases"]]


def cli(command: str, capsys) -> dict:
    from demstep.cli import main

    code = main(shlex.split(command)[1:])  # (the recorded command starts with 'demstep')
    out, err = capsys.readouterr()
    assert code == 0, err
    data = json.loads(out)
    return {e["method"]: e["dt"] for e in data["estimates"]} | {"n_contacts": data["n_contacts"]}


@pytest.mark.slow
@pytest.mark.parametrize("rec", CASES, ids=[c["case"] for c in CASES])
def test_wall_contacts_bring_the_step_to_liggghts_threshold(rec, capsys, monkeypatch):
    """With the walls demstep's exact step is within 0.3 % of LIGGGHTS' threshold and its
    element-coupled bound below the bracket; without them the step lies above the
    bracket (the wall contacts are the critical ones or take part in the mode)."""
    monkeypatch.chdir(ROOT)
    lo, hi = rec["liggghts"]["bracket"]
    threshold = rec["liggghts"]["dt"]
    dem = rec["demstep"]
    with_walls = cli(dem["with_meshes"]["command"], capsys)
    assert with_walls["exact"] == pytest.approx(dem["with_meshes"]["exact"], rel=1e-6)
    assert with_walls["n_contacts"] == dem["with_meshes"]["n_contacts"]
    assert with_walls["exact"] == pytest.approx(threshold, rel=3e-3)
    assert with_walls["element-coupled"] <= lo
    if "with_planes" in dem:  # plane walls and the same planes as meshes agree
        planes = cli(dem["with_planes"]["command"], capsys)
        assert planes["exact"] == pytest.approx(with_walls["exact"], rel=1e-9)
    without = cli(dem["without_meshes"]["command"], capsys)
    assert without["exact"] > hi


@pytest.mark.slow
@pytest.mark.parametrize("rec", [c for c in CASES if c["rotation"]],
                         ids=[c["case"] for c in CASES if c["rotation"]])
def test_with_liggghts_wall_arm_the_step_falls_in_the_bracket(rec, monkeypatch):
    """demstep's arm of a wall contact is r - delta (the distance to the contact point),
    LIGGGHTS' is r - delta/2: with rotation that puts demstep's step up to 0.24 % above
    LIGGGHTS' threshold in the stiff container. With LIGGGHTS' arm (stiffnesses and
    dashpots unchanged) the exact step falls inside the measured bracket."""
    from liggghts_mesh_thresholds import exact_with_liggghts_wall_arm

    monkeypatch.chdir(ROOT)
    lo, hi = rec["liggghts"]["bracket"]
    dt = exact_with_liggghts_wall_arm(shlex.split(rec["demstep"]["with_meshes"]["command"])[1:])
    assert dt == pytest.approx(rec["demstep"]["with_meshes"]["exact_liggghts_wall_arm"], rel=1e-6)
    assert lo * (1 - 2e-4) <= dt <= hi * (1 + 2e-4)
