"""Figures of a finished (or running) case, drawn from its saved history CSV.

``demstep plot DIR`` writes into ``DIR/plots``:

* ``energies.png``: kinetic, strain, friction and damping energies and the external
  work against time [M L^2/T^2];
* ``energy_error.png``: the normalized energy difference (paper eq. 22) on a log
  scale with the paper's tolerance 1e-2;
* ``wall_stress.png``: the compressive normal stress on every wall and, with periodic
  axes, the Love stress of the contacts [M/(L T^2)];
* ``timestep.png``: dt and, for automatic steps, the critical-step estimate [T].

Stage boundaries are drawn as dotted vertical lines.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from demstep.energy import DEFAULT_EPS
from demstep.errors import InputError
from demstep.io.history import read_history
from demstep.io.manifest import OutputManifest
from demstep.plotting import _pyplot, save_figure


def _stage_lines(ax, h):
    if "stage" not in h or len(h["stage"]) < 2:
        return
    change = np.flatnonzero(np.diff(h["stage"]) != 0)
    for k in change:
        ax.axvline(h["time"][k + 1], color="0.6", lw=0.8, ls=":")


#: the history columns the figures read (checked before any is drawn)
HISTORY_COLUMNS = ("step", "time", "dt", "dt_estimate", "kinetic_translational",
                   "kinetic_rotational", "strain_normal", "strain_tangential", "friction",
                   "external", "energy_error")


def plot_run(out_dir) -> list[Path]:
    """Draw the run's figures from ``out_dir/history.csv`` into ``out_dir/plots``;
    returns the files written."""
    out_dir = Path(out_dir)
    path = out_dir / "history.csv" if out_dir.is_dir() else out_dir
    if not path.is_file():
        raise InputError(f"plot: no history.csv in {out_dir} (was output.history_every 0?)")
    h = read_history(path)
    missing = [c for c in HISTORY_COLUMNS if c not in h]
    if missing:
        raise InputError(f"plot: {path} is not a run's history: no column "
                         f"{', '.join(repr(c) for c in missing)}")
    if len(h["step"]) == 0:
        raise InputError(f"plot: {path} has no rows yet")
    folder = (path.parent / "plots")
    manifest = OutputManifest(path.parent)  # (--overwrite of the run removes them too)

    def save(fig, name):
        manifest.record(folder / name)
        return save_figure(fig, folder / name)

    plt = _pyplot()
    t = h["time"]
    written = []

    fig, ax = plt.subplots(figsize=(7, 4))
    kinetic = h["kinetic_translational"] + h["kinetic_rotational"]
    strain = h["strain_normal"] + h["strain_tangential"]
    damping = sum(h[k] for k in ("damping_dashpot", "damping_local", "damping_global") if k in h)
    for values, label in ((kinetic, "kinetic"), (strain, "strain"), (h["friction"], "friction"),
                          (damping, "damping"), (h["external"], "external work")):
        ax.plot(t, values, label=label)
    ax.set_xlabel("time [T]")
    ax.set_ylabel("energy [M L^2/T^2]")
    ax.legend(fontsize=8)
    _stage_lines(ax, h)
    ax.set_title("energy ledger")
    written.append(save(fig, "energies.png"))

    fig, ax = plt.subplots(figsize=(7, 4))
    err = np.where(h["energy_error"] > 0, h["energy_error"], np.nan)
    ax.semilogy(t, err, label="normalized energy difference (eq. 22)")
    ax.axhline(DEFAULT_EPS, color="r", ls="--", lw=1, label=f"{DEFAULT_EPS:g}")
    ax.set_xlabel("time [T]")
    ax.set_ylabel("|W_kin + W_int - W_ext| / max(...)")
    ax.legend(fontsize=8)
    _stage_lines(ax, h)
    written.append(save(fig, "energy_error.png"))

    stress_cols = [c for c in h if c.endswith(".stress") or c.startswith("love.")]
    fig, ax = plt.subplots(figsize=(7, 4))
    for c in stress_cols:
        label = c[: -len(".stress")] if c.endswith(".stress") else f"Love {c[5:]}"
        ax.plot(t, h[c], label=label, ls="--" if c.startswith("love.") else "-")
    if not stress_cols:
        ax.text(0.5, 0.5, "no walls", ha="center", va="center", transform=ax.transAxes)
    else:
        ax.legend(fontsize=8)
    ax.set_xlabel("time [T]")
    ax.set_ylabel("stress [M/(L T^2)]")
    _stage_lines(ax, h)
    written.append(save(fig, "wall_stress.png"))

    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(h["step"], h["dt"], label="dt")
    if np.isfinite(h["dt_estimate"]).any():
        ax.plot(h["step"], h["dt_estimate"], ls="--", label="critical step estimate")
    ax.set_xlabel("step")
    ax.set_ylabel("time step [T]")
    ax.legend(fontsize=8)
    written.append(save(fig, "timestep.png"))
    return written
