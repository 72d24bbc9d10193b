"""Figures. Plotting reads saved results (reports, CSV histories), never a live run."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from demstep.io.atomic import atomic_path


def _pyplot():
    import matplotlib  # (deferred: a heavy import, loaded only when used)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # (deferred: a heavy import, loaded only when used)

    return plt


def save_figure(fig, path) -> Path:
    """Save atomically: a temporary file in the same folder, then rename."""
    path = Path(path)
    try:
        with atomic_path(path, suffix=path.suffix) as tmp:
            fig.savefig(tmp, dpi=130, bbox_inches="tight", format=path.suffix.lstrip(".") or "png")
    finally:
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


def plot_critical_step_table(table: dict, path) -> Path:
    """Figures 8/9 as grouped bars: alpha of each method per lattice."""
    plt = _pyplot()
    rows = table["rows"]
    cols = table["columns"]
    fig, ax = plt.subplots(figsize=(10, 4.2))
    width = 0.8 / len(cols)
    cmap = plt.get_cmap("tab10")
    for k, col in enumerate(cols):
        vals = [np.nan if r["alpha"][col] is None else r["alpha"][col] for r in rows]
        ax.bar(np.arange(len(rows)) + (k - len(cols) / 2 + 0.5) * width, vals, width,
               label=col, color=cmap(k % 10))
    ax.set_xticks(np.arange(len(rows)))
    ax.set_xticklabels([f"{r['lattice']}\n(nc={r['coordination']})" for r in rows])
    ax.set_ylabel(r"$\alpha = \Delta t_{crit} / \sqrt{m/K}$")
    ax.set_title("Critical time step of regular packings (paper Figs. 8, 9) beside exact values")
    ax.legend(ncol=4, fontsize=7, loc="upper right")
    ax.grid(axis="y", alpha=0.3)
    return save_figure(fig, path)


def _fcc_label(r):
    rot = "" if r.get("rotation", True) else ", rotation blocked"
    return f"alpha = {r['alpha']:.2f}{rot} ({r['status']})"


def plot_fcc_ratio(results, theory: float, path) -> Path:
    """Stress ratio sigma_zz / sigma_xx against axial strain (paper Fig. 11)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    for r in results:
        if "curves" not in r:
            continue
        c = r["curves"]
        ls = "-" if r.get("rotation", True) else "--"
        ax.plot(100 * np.asarray(c["strain"]), c["ratio"], ls, lw=1.2, label=_fcc_label(r))
    ax.axhline(theory, color="k", lw=1, ls=":", label=f"Thornton (1979): {theory:.2f}")
    ax.set_xlabel("axial strain [%]")
    ax.set_ylabel(r"$\sigma_{zz} / \sigma_{xx}$")
    ax.set_ylim(0, max(theory * 1.4, 1))
    ax.set_title("FCC plane-strain compression, mu = 0.3")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    return save_figure(fig, path)


def plot_fcc_energy(results, eps: float, path) -> Path:
    """Normalized energy difference (eq. 22) against axial strain (paper Fig. 12)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    for r in results:
        if "curves" not in r:
            continue
        c = r["curves"]
        err = np.maximum(np.asarray(c["energy_error"], dtype=float), 1e-12)
        ls = "-" if r.get("rotation", True) else "--"
        ax.semilogy(100 * np.asarray(c["strain"]), err, ls, lw=1.2, label=_fcc_label(r))
    ax.axhline(eps, color="r", lw=1, ls=":", label=f"limit {eps:g}")
    ax.set_xlabel("axial strain [%]")
    ax.set_ylabel("normalized energy difference (eq. 22)")
    ax.set_title("Energy balance of the FCC runs")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, which="both")
    return save_figure(fig, path)


def plot_stability(results, path) -> Path:
    """Measured stability threshold against each estimate, per specimen."""
    plt = _pyplot()
    ok = [r for r in results if "alpha_empirical" in r]
    fig, ax = plt.subplots(figsize=(8, 4.2))
    methods = ["exact", "element-coupled", "element-paper", "nodal"]
    markers = {"exact": "o", "element-coupled": "v", "element-paper": "s", "nodal": "^"}
    x = np.arange(len(ok))
    ax.bar(x, [r["alpha_empirical"] for r in ok], 0.6, color="0.85", label="measured threshold")
    for m in methods:
        ax.plot(x, [r["estimates"].get(m, np.nan) for r in ok], markers[m], label=m)
    ax.set_xticks(x)
    ax.set_xticklabels([r["lattice"] for r in ok])
    ax.set_ylabel(r"$\alpha$")
    ax.set_title("Smallest unstable alpha (bisection) against the estimates")
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    return save_figure(fig, path)


def plot_damping(results, path) -> Path:
    """Critical alpha of the damped FCC specimen against its restitution: measured
    threshold, damped and undamped exact steps, the element bound and the 20 %
    Rayleigh-time rule."""
    plt = _pyplot()
    ok = sorted((r for r in results if "alpha_empirical" in r), key=lambda r: -r["restitution"])
    fig, ax = plt.subplots(figsize=(7, 4))
    e = [r["restitution"] for r in ok]
    ax.plot(e, [r["alpha_empirical"] for r in ok], "ks", ms=8, mfc="none", label="measured threshold")
    ax.plot(e, [r["estimates"]["exact"] for r in ok], "o-", label="exact (damped)")
    ax.plot(e, [r["estimates"]["exact-undamped"] for r in ok], "--", color="0.5",
            label="exact without damping")
    ax.plot(e, [r["estimates"]["element-coupled"] for r in ok], "v:", label="element-coupled (damped)")
    ax.plot(e, [r["rayleigh_20"] for r in ok], "-.", color="tab:red", label="20 % Rayleigh time")
    ax.invert_xaxis()
    ax.set_xlabel("coefficient of restitution (normal and tangential dashpots)")
    ax.set_ylabel(r"$\alpha = \Delta t / \sqrt{m/K}$")
    ax.set_title("FCC specimen: damping and the critical step")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return save_figure(fig, path)


def plot_clumps(results, stability, path) -> Path:
    """Critical alpha (measured, exact, element bound, nodal rule) of the clump packings
    against their contacts per body, rotation free and locked; the FCC sphere specimen
    and the paper's 0.17 for reference."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    for rotation, marker in ((True, "o"), (False, "s")):
        rows = sorted((r for r in results if "alpha_empirical" in r and r["rotation"] == rotation),
                      key=lambda r: r["contacts_per_body"])
        if not rows:
            continue
        cn = [r["contacts_per_body"] for r in rows]
        tag = "rotation free" if rotation else "rotation locked"
        ax.plot(cn, [r["alpha_empirical"] for r in rows], marker, mfc="none", ms=9,
                color="k", label=f"measured ({tag})")
        ax.plot(cn, [r["estimates"]["exact"] for r in rows], marker + "-", ms=4,
                label=f"exact ({tag})")
        ax.plot(cn, [r["estimates"]["element-coupled"] for r in rows], marker + ":", ms=4,
                label=f"element bound ({tag})")
        for r in rows:
            ax.annotate(r["shape"], (r["contacts_per_body"], r["alpha_empirical"]),
                        textcoords="offset points", xytext=(4, 4), fontsize=7)
    sphere = next((r for r in stability if r.get("lattice") == "fcc-specimen"
                   and "alpha_empirical" in r), None)
    if sphere is not None:
        ax.plot([12], [sphere["alpha_empirical"]], "k*", ms=10, label="FCC spheres (measured)")
    ax.axhline(0.17, color="tab:red", ls="--", lw=1, label="paper's guidance 0.17")
    ax.set_xlabel("contacts per body")
    ax.set_ylabel(r"$\alpha = \Delta t / \sqrt{m_{body}/K}$")
    ax.set_title("Clump packings: the critical step")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    return save_figure(fig, path)
