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
# the stiff mesh container (the plane-wall box of liggghts_plane_box_thresholds.json is
# the script's contrast; its numbers are in docs/validation-meshes.md)
CASES = json.loads((RESULTS / "liggghts_mesh_thresholds.json").read_text())["cases"]


def cli(command: str, capsys) -> dict:
    from demstep.cli import main

    code = main(shlex.split(command)[1:])  # (the recorded command starts with 'demstep')
    out, err = capsys.readouterr()
    assert code == 0, err
    data = json.loads(out)
    return {e["method"]: e["dt"] for e in data["estimates"]} | {"n_contacts": data["n_contacts"]}


@pytest.mark.parametrize("rec", CASES, ids=[c["case"] for c in CASES])
def test_wall_contacts_bring_the_step_to_liggghts_threshold(rec, capsys, monkeypatch):
    """With the walls (LIGGGHTS' conventions, its wall arm r - delta/2 included: a dump
    is read in them) demstep's exact step is never above LIGGGHTS' bracket and within
    0.3 % below it, its element-coupled bound below the bracket; without the walls the
    step lies above the bracket (the wall contacts are the critical ones or take part
    in the mode)."""
    monkeypatch.chdir(ROOT)
    lo, hi = rec["liggghts"]["bracket"]
    dem = rec["demstep"]
    with_walls = cli(dem["with_meshes"]["command"], capsys)
    assert with_walls["exact"] == pytest.approx(dem["with_meshes"]["exact"], rel=1e-6)
    assert with_walls["n_contacts"] == dem["with_meshes"]["n_contacts"]
    assert lo * (1 - 3e-3) <= with_walls["exact"] <= hi
    assert with_walls["element-coupled"] <= lo
    if "with_planes" in dem:  # plane walls and the same planes as meshes agree
        planes = cli(dem["with_planes"]["command"], capsys)
        assert planes["exact"] == pytest.approx(with_walls["exact"], rel=1e-9)
    without = cli(dem["without_meshes"]["command"], capsys)
    assert without["exact"] > hi


@pytest.mark.parametrize("rec", [c for c in CASES if c["rotation"]],
                         ids=[c["case"] for c in CASES if c["rotation"]])
def test_the_contact_point_arm_gives_a_longer_step(rec, monkeypatch):
    """demstep's engine takes the arm of a wall contact as r - delta (the distance to the
    contact point), LIGGGHTS r - delta/2: with rotation the shorter arm gives a longer
    step (the slip-roll mode is softer), above LIGGGHTS' bracket in the stiff container
    where a sphere is pressed 1.2 % of its radius into a facet."""
    from liggghts_mesh_thresholds import exact_with_contact_point_arm

    monkeypatch.chdir(ROOT)
    hi = rec["liggghts"]["bracket"][1]
    dem = rec["demstep"]["with_meshes"]
    dt = exact_with_contact_point_arm(shlex.split(dem["command"])[1:])
    assert dt == pytest.approx(dem["exact_contact_point_arm"], rel=1e-6)
    assert dt > dem["exact"]
    if rec["case"].startswith("mesh-"):
        assert dt > hi
