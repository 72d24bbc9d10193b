"""Figures. Plotting reads saved results (reports, CSV histories), never a live run."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path) -> Path:
    """Save atomically: a temporary file in the same folder, then rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=130, bbox_inches="tight", format=path.suffix.lstrip(".") or "png")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
        _pyplot().close(fig)
    return path


def plot_estimates(report, path, title: str | None = None) -> Path:
    """Bar chart of every method's alpha = dt / sqrt(m_min/K_max), the exact value drawn
    as a line; bars above it (unconservative) in red."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.8))
    names = [e.method for e in report.estimates]
    alphas = [e.alpha for e in report.estimates]
    colors = ["tab:red" if e.conservative is False else "tab:blue" for e in report.estimates]
    ax.bar(names, alphas, color=colors)
    for k, a in enumerate(alphas):
        ax.text(k, a, f"{a:.3f}", ha="center", va="bottom", fontsize=8)
    try:
        ax.axhline(report.get("exact").alpha, color="k", ls="--", lw=1, label="exact")
        ax.legend(loc="upper left")
    except KeyError:
        pass
    ax.set_ylabel(r"$\alpha = \Delta t / \sqrt{m_{min}/K_{max}}$")
    rot = "with rotation" if report.rotation else "translation only"
    ax.set_title(title or f"{report.dim}D, {report.n_particles} particles, "
                          f"{report.n_contacts} contacts, {rot}")
    ax.tick_params(axis="x", rotation=25)
    return save_figure(fig, path)
