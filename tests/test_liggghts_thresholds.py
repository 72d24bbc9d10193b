"""demstep's exact (damped) step against LIGGGHTS' own measured stability threshold.

The states are LIGGGHTS' own dumps and the thresholds its own bisections on its time
step (``validation/liggghts_thresholds.py``, LIGGGHTS 3.8.0, committed with their
results): periodic FCC and random polydisperse packings, linear springs undamped, with
normal and with normal and tangential dashpots at two restitutions, rotation free and
locked, and Hertz-Mindlin with LIGGGHTS' restitution convention. LIGGGHTS is not needed
to run this test; re-running the harness re-measures the thresholds."""

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "validation"))
RESULTS = json.loads((ROOT / "validation" / "results" / "liggghts_thresholds.json").read_text())
CASES = RESULTS["cases"]


@pytest.mark.parametrize("rec", CASES, ids=[c["case"] for c in CASES])
def test_exact_step_predicts_liggghts_threshold(rec, capsys, monkeypatch):
    from compare_liggghts import cli_arguments

    from demstep.cli import main

    monkeypatch.chdir(ROOT)
    code = main(cli_arguments(rec))
    out, err = capsys.readouterr()
    assert code == 0, err
    data = json.loads(out)
    est = {e["method"]: e["dt"] for e in data["estimates"]}
    lo, hi = rec["bracket"]
    # within 0.2 % of the measured threshold (LIGGGHTS also counts the pre-stress of the
    # loaded contacts, which lowers its threshold by up to 0.1 % here)
    assert est["exact"] == pytest.approx(rec["dt"], rel=2e-3)
    # the coupled element bound is rigorous: below the measured threshold
    assert est["element-coupled"] <= lo
    if rec["damping"] != "none":
        assert data["damped"]
