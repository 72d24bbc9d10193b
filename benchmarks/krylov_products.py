"""Products with the operator that Krylov methods need for the largest eigenpair of an
FCC block (the clustered top spectrum of issue 15), each to the same explicit relative
residual |A y - theta y| <= tol theta:

* demstep's thick-restart Lanczos (:func:`demstep.timestep.eigen.top_eigenpair`);
* unrestarted block Lanczos with full reorthogonalisation (a numpy prototype here,
  block 1 = plain Lanczos), to see what restarts and blocks change;
* scipy's LOBPCG.

    python benchmarks/krylov_products.py [--side 12] [--tol 1e-10] [--blocks 1,2,3,4,6]
                                         [--lobpcg 4] [--top 12]

The prototype keeps every block and its image (memory: 2 x products x DOFs doubles) and
solves the projected problem each iteration: for small blocks only (side 20: 96,000
DOFs, minutes).
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def fcc_operator(side: int):
    """The mass-scaled stiffness operator of an FCC block (rotation on) and its size."""
    from demstep.timestep.contacts import find_contacts
    from demstep.packings import lattice
    from demstep.particles import Particles
    from demstep.timestep.exact import ScaledContactOperator

    x = lattice("fcc", 0.5).block(side)
    p = Particles.from_density(x, np.full(len(x), 0.5 * 1.001), 2000.0)
    contacts = find_contacts(p, 1e6)
    op = ScaledContactOperator(p, contacts, True)
    return op, len(x), contacts.n


def block_lanczos_products(apply, n: int, b: int, tol: float, max_blocks: int = 5000):
    """Products an unrestarted block Lanczos (full reorthogonalisation, Rayleigh-Ritz on
    the whole basis each iteration) needs until its top Ritz pair has a relative
    residual <= tol; returns (products, theta, relative residual)."""
    rng = np.random.default_rng(0)
    block = np.linalg.qr(rng.standard_normal((n, b)))[0].T.copy()
    basis, images = [], []
    for _ in range(max_blocks):
        basis.append(block)
        images.append(np.stack([apply(v) for v in block]))
        V, AV = np.concatenate(basis), np.concatenate(images)
        H = V @ AV.T
        theta, S = np.linalg.eigh(0.5 * (H + H.T))
        y, Ay = S[:, -1] @ V, S[:, -1] @ AV
        residual = np.linalg.norm(Ay - theta[-1] * y) / theta[-1]
        if residual <= tol:
            return len(V), float(theta[-1]), float(residual)
        W = images[-1].copy()
        for _ in range(2):
            W -= (W @ V.T) @ V
        block = np.linalg.qr(W.T)[0].T.copy()
    raise RuntimeError("block Lanczos did not converge")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--side", type=int, default=12)
    ap.add_argument("--tol", type=float, default=1e-10)
    ap.add_argument("--blocks", default="1,2,3,4,6")
    ap.add_argument("--lobpcg", default="4", help="LOBPCG block sizes ('' for none)")
    ap.add_argument("--top", type=int, default=12, help="eigenvalues listed (ARPACK)")
    args = ap.parse_args(argv)
    import scipy.sparse.linalg as spla

    from demstep.timestep.eigen import top_eigenpair

    op, n_spheres, n_contacts = fcc_operator(args.side)
    springs = op.springs(0.0)
    n = op.size

    def apply(v):
        return op.apply(np.ascontiguousarray(v), springs)

    print(f"FCC block side {args.side}: {n_spheres} spheres, {n_contacts} contacts, {n} DOFs")
    top = np.sort(spla.eigsh(op.pencil(0.0), k=args.top, which="LA", tol=1e-12,
                             return_eigenvectors=False))[::-1]
    print("top of the spectrum, (lambda_1 - lambda_k) / lambda_1:",
          " ".join(f"{g:.2e}" for g in (top[0] - top[1:]) / top[0]))
    t = time.perf_counter()
    pair = top_eigenpair(op.pencil(0.0), dense_limit=0, tol=args.tol)
    print(f"  demstep thick-restart Lanczos: {pair.matvecs} products "
          f"(relative residual {pair.residual / pair.value:.1e}, {time.perf_counter() - t:.1f} s)")
    for b in (int(s) for s in args.blocks.split(",") if s):
        products, theta, residual = block_lanczos_products(apply, n, b, args.tol)
        print(f"  block Lanczos, unrestarted, block {b}: {products} products "
              f"(relative residual {residual:.1e}, theta {theta:.15e})")
    for b in (int(s) for s in args.lobpcg.split(",") if s):
        count = [0]

        def matmat(X):
            X = np.asarray(X).reshape(n, -1)
            count[0] += X.shape[1]
            return np.stack([apply(X[:, k]) for k in range(X.shape[1])], axis=1)

        A = spla.LinearOperator((n, n), matvec=lambda v: matmat(v)[:, 0], matmat=matmat,
                                dtype=float)
        X0 = np.random.default_rng(0).standard_normal((n, b))
        w, V = spla.lobpcg(A, X0, largest=True, tol=args.tol * top[0], maxiter=20_000)
        y = V[:, np.argmax(w)] / np.linalg.norm(V[:, np.argmax(w)])
        Ay = apply(y)
        theta = y @ Ay
        print(f"  LOBPCG block {b}: {count[0]} products (relative residual "
              f"{np.linalg.norm(Ay - theta * y) / theta:.1e})")


if __name__ == "__main__":
    main()
