"""The paper's Figures 8 and 9: element estimates for regular packings beside exact values.

Every configuration is the infinite lattice: element estimates use a periodic supercell
(every particle has its full coordination, as for the paper's central particle) and
the exact values come from the Bloch-wave analysis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from demstep.timestep.contacts import find_contacts
from demstep.packings import LATTICE_NAMES, lattice
from demstep.particles import Particles
from demstep.timestep.bloch import bloch_lambda_max
from demstep.timestep.estimates import element_coupled_dt, element_paper_dt
from demstep.timestep.stability import dt_from_lambda

#: minima published by O'Sullivan & Bray (2004), in units of sqrt(m/K), Kn = Ks = K
PAPER_MINIMA = {
    ("2D", "translation", "uniform"): 0.577,
    ("2D", "rotation", "uniform"): 0.408,
    ("3D", "translation", "uniform"): 0.408,
    ("3D", "rotation", "uniform"): 0.258,
    ("3D", "translation", "zoned"): 0.348,
    ("3D", "rotation", "zoned"): 0.221,
}
#: the paper's FCC translation-only zoned value ("about 0.37")
PAPER_FCC_TRANSLATION_ZONED = 0.37

COLUMNS = (
    ("paper", False, "uniform"), ("paper", True, "uniform"),
    ("paper", False, "zoned"), ("paper", True, "zoned"),
    ("coupled", False, "uniform"), ("coupled", True, "uniform"),
    ("exact-periodic", False, None), ("exact-periodic", True, None),
)


@dataclass
class PaperRow:
    lattice: str
    dim: int
    coordination: int
    alpha: dict  # (formulation, rotation, split) -> alpha = dt / sqrt(m/K)


def column_label(formulation, rotation, split) -> str:
    """Short column names: T = translation only, R = with rotation."""
    name = {"paper": "paper", "coupled": "coupled", "exact-periodic": "exact"}[formulation]
    return f"{name}-{'R' if rotation else 'T'}" + (f"-{split}" if split else "")


def paper_table(k_n: float = 1.0, k_s: float | None = None) -> list[PaperRow]:
    """alpha values of every column of :data:`COLUMNS` for every lattice (K = max(Kn, Ks))."""
    k_s = k_n if k_s is None else k_s
    k_max = max(k_n, k_s)
    rows = []
    for name in LATTICE_NAMES:
        lat = lattice(name, 1.0)
        x, box = lat.supercell(3)
        particles = Particles.from_density(x, np.full(len(x), lat.radius), 1.0)
        contacts = find_contacts(particles, k_n, k_s, periodic=box)
        unit = np.sqrt(particles.m[0] / k_max)
        alpha = {}
        for formulation, rotation, split in COLUMNS:
            if split == "zoned" and lat.dim == 2:
                alpha[(formulation, rotation, split)] = None
                continue
            if formulation == "paper":
                dt = element_paper_dt(particles, contacts, rotation, split)
            elif formulation == "coupled":
                dt = element_coupled_dt(particles, contacts, rotation, split)
            else:
                lam, _ = bloch_lambda_max(lat, k_n, k_s, 1.0, rotation)
                dt = dt_from_lambda(lam)
            alpha[(formulation, rotation, split)] = float(dt / unit)
        rows.append(PaperRow(name, lat.dim, lat.coordination, alpha))
    return rows


def minima(rows: list[PaperRow]) -> dict:
    """The paper's minima recomputed: min over configurations per (dim, motion, split)."""
    out = {}
    for (dim_label, motion, split) in PAPER_MINIMA:
        dim = 2 if dim_label == "2D" else 3
        key = ("paper", motion == "rotation", split)
        out[(dim_label, motion, split)] = min(r.alpha[key] for r in rows if r.dim == dim)
    return out


def format_table(rows: list[PaperRow]) -> str:
    """Plain-text table (alpha values) followed by the paper's minima beside ours."""
    labels = [column_label(*c) for c in COLUMNS]
    width = max(len(s) for s in labels) + 2
    head = f"{'lattice':<9}{'nc':>4}" + "".join(f"{s:>{width}}" for s in labels)
    lines = ["Critical time step alpha = dt / sqrt(m/K) (paper Figs. 8, 9; Kn = Ks = K)",
             "T: translation only, R: with rotation; paper: element-paper (eqs. 6-19), "
             "coupled: element-coupled, exact: Bloch-wave exact-periodic", head,
             "-" * len(head)]
    for r in rows:
        cells = "".join(f"{'-' if r.alpha[c] is None else format(r.alpha[c], '.4f'):>{width}}"
                        for c in COLUMNS)
        lines.append(f"{r.lattice:<9}{r.coordination:>4}{cells}")
    lines += ["", "Minima over configurations (element-paper) against the published values:"]
    for key, ours in minima(rows).items():
        paper = PAPER_MINIMA[key]
        lines.append(f"  {' '.join(key):<26} paper {paper:.3f}  demstep {ours:.4f}  "
                     f"({100 * (ours - paper) / paper:+.2f} %)")
    return "\n".join(lines)


def table_json(rows: list[PaperRow]) -> dict:
    return {
        "columns": [column_label(*c) for c in COLUMNS],
        "rows": [{"lattice": r.lattice, "dim": r.dim, "coordination": r.coordination,
                  "alpha": {column_label(*c): r.alpha[c] for c in COLUMNS}} for r in rows],
        "minima": [{"case": " ".join(k), "paper": PAPER_MINIMA[k], "demstep": v}
                   for k, v in minima(rows).items()],
    }
