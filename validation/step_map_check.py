"""Protocol check: the threshold of LIGGGHTS' *linearised* step map, beside the measured one.

    python validation/step_map_check.py [--cases PATTERN ...] [--verify]

Independent of demstep (numpy/scipy only): for every record of
``validation/results/liggghts_thresholds.json`` this builds, from the saved dump, the
stiffness K and dashpot matrix C that LIGGGHTS' contact laws have for small motions
about the static state, and the critical step of LIGGGHTS' integrator for them. If the
bisection protocol is sound, the measured bracket contains this value up to the
effects the linear model leaves out (the pre-stress "geometric" stiffness, of relative
size overlap / distance ~ 1e-3 here).

Linear model (SI units)
-----------------------
* Contacts: overlapping pairs under the minimum image; normal n from i to j; contact
  arms a_i = r_i - delta/2, a_j = r_j - delta/2 (LIGGGHTS' cri, crj). The relative
  contact-point displacement is B q with q = (u_i, theta_i, u_j, theta_j),
  B = [-I, [a_i n]x, I, [a_j n]x] (without rotation: [-I, I]).
* K = sum B^T (k_n n n^T + k_t (I - n n^T)) B, C likewise with (gamma_n, gamma_t).
  linear: k_n, k_t, gamma_n, gamma_t as given (absolute); Hertz, per contact:
  k_n = S_n = 2 Y* sqrt(R* delta) (tangent stiffness of 4/3 Y* sqrt(R*) delta^1.5),
  k_t = S_t = 8 G* sqrt(R* delta), gamma = 2 sqrt(5/6) beta sqrt(S m*), m* = mi mj /
  (mi + mj), gamma_t = 0 with tangential damping off.
* M = diag(m, m, m, I, I, I), I = 2/5 m r^2.
* LIGGGHTS' velocity Verlet evaluates the dashpots with the half-step velocity, i.e.
  M (x[n+1] - 2 x[n] + x[n-1]) / h^2 + C (x[n] - x[n-1]) / h + K x[n] = 0. Its
  instability is a real eigenvalue crossing -1, at the smallest h where
  4 M - 2 h C - h^2 K stops being positive definite (for one oscillator this is
  h = 2 (sqrt(1 + zeta^2) - zeta) / omega):  lambda_max(M^-1/2 (h^2 K + 2 h C) M^-1/2) = 4,
  solved by safeguarded Newton iteration (the left side increases with h).
  ``--verify`` checks it against the spectral radius of the full one-step map at
  h (1 -/+ 1e-4) for the small (fcc) cases.

Writes ``validation/results/step_map_check.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import math
import sys
from pathlib import Path

import numpy as np
import scipy.linalg as sl
import scipy.sparse as sp
import scipy.sparse.linalg as spla

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results"
sys.path.insert(0, str(HERE))

from liggghts_thresholds import read_dump  # noqa: E402


def contacts(state: dict):
    """Overlapping pairs of a dumped state: i, j, unit normals n (i -> j), arms
    a_i, a_j [m] and overlaps delta [m]."""
    x = np.stack([state["x"], state["y"], state["z"]], 1)
    r = state["radius"]
    box = state["box"][:, 1] - state["box"][:, 0]
    d = x[None, :, :] - x[:, None, :]
    d -= box * np.round(d / box)
    dist = np.sqrt((d * d).sum(-1))
    delta = r[:, None] + r[None, :] - dist
    iu = np.triu_indices(len(r), 1)
    sel = delta[iu] > 0
    i, j = iu[0][sel], iu[1][sel]
    dl = delta[i, j]
    n = d[i, j] / dist[i, j][:, None]
    return i, j, n, r[i] - 0.5 * dl, r[j] - 0.5 * dl, dl


def _skew(v):
    z = np.zeros(v.shape[:-1] + (3, 3))
    z[..., 0, 1], z[..., 0, 2] = -v[..., 2], v[..., 1]
    z[..., 1, 0], z[..., 1, 2] = v[..., 2], -v[..., 0]
    z[..., 2, 0], z[..., 2, 1] = -v[..., 1], v[..., 0]
    return z


def assemble(n_particles, i, j, n, ai, aj, kn, kt, rotation: bool) -> np.ndarray:
    """Dense global matrix sum B^T (kn nn + kt (I - nn)) B [N/m, N, N m] for per-contact
    kn, kt (arrays); DOFs per particle: 3 translations (+ 3 rotations)."""
    nd = 6 if rotation else 3
    c = len(i)
    nn = n[:, :, None] * n[:, None, :]
    D = kn[:, None, None] * nn + kt[:, None, None] * (np.eye(3) - nn)
    eye = np.broadcast_to(np.eye(3), (c, 3, 3))
    parts = [-eye] + ([_skew(ai[:, None] * n)] if rotation else []) + \
            [eye] + ([_skew(aj[:, None] * n)] if rotation else [])
    B = np.concatenate(parts, axis=2)                      # (c, 3, 2 nd)
    E = np.einsum("cki,ckl,clj->cij", B, D, B)            # (c, 2nd, 2nd)
    dof = np.concatenate([i[:, None] * nd + np.arange(nd), j[:, None] * nd + np.arange(nd)], 1)
    K = np.zeros((n_particles * nd, n_particles * nd))
    np.add.at(K, (dof[:, :, None], dof[:, None, :]), E)
    return K


def contact_coefficients(rec: dict, state: dict, i, j, delta):
    """Per-contact kn, kt, gamma_n, gamma_t of a record's law (see module docstring)."""
    p = rec["parameters"]
    c = len(i)
    if p["model"] == "linear":
        return (np.full(c, p["kn"]), np.full(c, p["kt"]), np.full(c, p["gamma_n"]),
                np.full(c, p["gamma_t"]))
    r, m = state["radius"], state["mass"]
    rs = r[i] * r[j] / (r[i] + r[j])
    ms = m[i] * m[j] / (m[i] + m[j])
    root = np.sqrt(rs * delta)
    sn, st = 2.0 * p["Y_star"] * root, 8.0 * p["G_star"] * root
    f = 2.0 * math.sqrt(5.0 / 6.0) * p["beta"]
    gn = f * np.sqrt(sn * ms)
    gt = f * np.sqrt(st * ms) if p["tangential_damping"] else np.zeros(c)
    return sn, st, gn, gt


def normal_force(rec: dict, state: dict, i, j, delta) -> np.ndarray:
    """Elastic normal force [N] of each contact of the static state."""
    p = rec["parameters"]
    if p["model"] == "linear":
        return p["kn"] * delta
    r = state["radius"]
    rs = r[i] * r[j] / (r[i] + r[j])
    return 4.0 / 3.0 * p["Y_star"] * np.sqrt(rs) * delta ** 1.5


def matrices(rec: dict, state: dict, geometric: bool = False):
    """(K, C, lumped mass diagonal) of a record's linearised model; with ``geometric``
    K includes the pre-stress term -(F_n / L) (I - n n^T) on the relative translation
    (the rotation of a loaded normal: softening for compressed contacts)."""
    i, j, n, ai, aj, delta = contacts(state)
    kn, kt, gn, gt = contact_coefficients(rec, state, i, j, delta)
    rot = rec["rotation"]
    npart = len(state["radius"])
    K = assemble(npart, i, j, n, ai, aj, kn, kt, rot)
    if geometric:
        geo = -normal_force(rec, state, i, j, delta) / (ai + aj)   # L = a_i + a_j
        nd = 6 if rot else 3
        Kg = assemble(npart, i, j, n, 0 * ai, 0 * aj, np.zeros_like(geo), geo, False)
        idx = (np.arange(npart)[:, None] * nd + np.arange(3)).reshape(-1)
        K[np.ix_(idx, idx)] += Kg
    C = assemble(npart, i, j, n, ai, aj, gn, gt, rot)
    m, r = state["mass"], state["radius"]
    cols = [m, m, m] + ([0.4 * m * r * r] * 3 if rot else [])
    return K, C, np.stack(cols, 1).reshape(-1)


def _top(A, v0=None):
    """Largest eigenpair of the symmetric matrix A (sparse Lanczos, dense fallback)."""
    try:
        w, v = spla.eigsh(sp.csr_matrix(A), k=1, which="LA", tol=1e-14, v0=v0, maxiter=20000)
        return float(w[0]), v[:, 0]
    except spla.ArpackNoConvergence:
        w, v = sl.eigh(A, subset_by_index=[len(A) - 1, len(A) - 1])
        return float(w[0]), v[:, 0]


def critical_step(K, C, mdiag) -> tuple[float, float]:
    """(damped, undamped) critical step [s] of the lagged-dashpot central difference."""
    s = 1.0 / np.sqrt(mdiag)
    A = K * s[:, None] * s[None, :]
    Bc = C * s[:, None] * s[None, :]
    lam, v = _top(A)
    h0 = 2.0 / math.sqrt(lam)
    if not np.any(Bc):
        return h0, h0
    lo, hi = 0.0, h0          # g(0) = -4 < 0 <= g(h0)
    h = h0
    for _ in range(100):
        mu, v = _top(h * h * A + 2.0 * h * Bc, v)
        g = mu - 4.0
        if g > 0:
            hi = h
        else:
            lo = h
        dg = float(v @ ((2.0 * h * A + 2.0 * Bc) @ v))
        newton = h - g / dg if dg > 0 else 0.5 * (lo + hi)
        h_new = newton if lo < newton < hi else 0.5 * (lo + hi)
        if abs(h_new - h) <= 1e-13 * h:
            h = h_new
            break
        h = h_new
    return h, h0


def spectral_radius(K, C, mdiag, h) -> float:
    """Spectral radius of the one-step map (x[n], v[n-1/2]) -> (x[n+1], v[n+1/2])."""
    mi = 1.0 / mdiag
    MK, MC = mi[:, None] * K, mi[:, None] * C
    eye = np.eye(len(mdiag))
    T = np.block([[eye - h * h * MK, h * (eye - h * MC)], [-h * MK, eye - h * MC]])
    return float(np.abs(np.linalg.eigvals(T)).max())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=RESULTS / "liggghts_thresholds.json")
    ap.add_argument("--cases", nargs="+", default=None)
    ap.add_argument("--verify", action="store_true",
                    help="check the criterion against the full step map (cases of <= 150 spheres)")
    ap.add_argument("--geometric", action="store_true",
                    help="include the pre-stress (geometric) stiffness of the normal forces")
    ap.add_argument("--out", type=Path, default=None,
                    help="default results/step_map_check.json (--geometric: step_map_check_geometric.json)")
    args = ap.parse_args(argv)
    report = json.loads(args.results.read_text())
    rows = []
    states = {}
    print(f"{'case':30s} {'measured [s]':>13s} {'bracket':>27s} {'step map':>13s} {'rel':>10s} "
          f"{'in':>3s} {'undamped map':>13s}")
    for rec in report["cases"]:
        if args.cases and not any(fnmatch.fnmatch(rec["case"], p) for p in args.cases):
            continue
        if rec["dump"] not in states:
            states[rec["dump"]] = read_dump(REPO / rec["dump"])
        st = states[rec["dump"]]
        K, C, md = matrices(rec, st, args.geometric)
        h, h0 = critical_step(K, C, md)
        lo, hi = rec["bracket"]
        row = {"case": rec["case"], "measured": rec["dt"], "bracket": [lo, hi], "step_map": h,
               "step_map_undamped": h0, "rel_diff": h / rec["dt"] - 1.0, "inside": bool(lo <= h <= hi)}
        if args.verify and len(st["radius"]) <= 150:
            row["rho_below"] = spectral_radius(K, C, md, h * (1 - 1e-4))
            row["rho_above"] = spectral_radius(K, C, md, h * (1 + 1e-4))
        rows.append(row)
        extra = (f"  rho(1-1e-4) = {row['rho_below']:.9f}, rho(1+1e-4) = {row['rho_above']:.9f}"
                 if "rho_below" in row else "")
        print(f"{rec['case']:30s} {rec['dt']:13.8g} [{lo:.7g}, {hi:.7g}] {h:13.8g} "
              f"{row['rel_diff']:+10.2e} {'yes' if row['inside'] else 'no':>3s} {h0:13.8g}{extra}",
              flush=True)
    out = args.out or RESULTS / ("step_map_check_geometric.json" if args.geometric
                                 else "step_map_check.json")
    out.write_text(json.dumps({"description": "threshold of LIGGGHTS' linearised step map "
                               "(validation/step_map_check.py) beside the measured one",
                               "geometric_stiffness": args.geometric, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
