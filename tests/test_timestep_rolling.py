"""Rolling and twisting resistance in the time-step analysis.

Every reference here is written independently of the code under test, in plain numpy:
the global K and C assembled contact by contact from the definitions (slip at the
contact point Delta = u_j - u_i - (a_i theta_i + a_j theta_j) x n with springs
k_n n n^T + k_t (I - n n^T); the rolling element [[B, -B], [-B, B]] on the rotations
with B = k_r (I - n n^T) + k_w n n^T, k_r for disks), dense eigenvalues, the spectral
radius of the engine's one-step map, companion matrices of element pencils."""

import json
import math
import os
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from demstep.cli import main
from demstep.contact.laws import LinearSpring, rolling_coefficients, rolling_inertia
from demstep.timestep.contacts import ContactSet, find_contacts
from demstep.kernels.timestep_kernels import (contact_energies, contact_gram, contact_matvec,
                                              contact_quadratic_forms)
from demstep.packings import lattice
from demstep.particles import Particles
from demstep.timestep import estimate_time_steps
from demstep.timestep.assembly import assemble_stiffness, stiffness_diagonal
from demstep.timestep.clumps import RigidBodies, body_element_dt, body_stiffness_diagonal
from demstep.timestep.certificate import StepCertificate, added_contacts_bound
from demstep.timestep.damping import GlobalDamping
from demstep.timestep.elements import coupled_element_damped_dt, coupled_element_lambda
from demstep.timestep.estimates import element_coupled_dt, nodal_dt
from demstep.timestep.exact import ScaledContactOperator, exact_critical_step
from demstep.timestep.mass_split import element_mass
from demstep.walls import Wall

from conftest import contacts_now


# ------------------------------------------------------------------ references
def cross_matrix(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def strain_maps(n, arm_i, arm_j, dim, rotation, wall):
    """(slip map (3, 2 nd), relative-rotation map (3, 2 nd)) on the element DOFs
    (u_i, theta_i, u_j, theta_j): Delta = u_j - u_i + (a_i + a_j) [n]x theta (since
    -(a theta) x n = a n x theta), phi = theta_j - theta_i; a wall side is absent."""
    nrot = (1 if dim == 2 else 3) if rotation else 0
    nd = dim + nrot
    n3 = np.zeros(3)
    n3[:dim] = n
    Bd = np.zeros((3, 2 * nd))
    Bp = np.zeros((3, 2 * nd))
    for side, sign, arm in ((0, -1.0, arm_i), (1, 1.0, arm_j)):
        if side == 1 and wall:
            continue
        o = side * nd
        Bd[:dim, o:o + dim] = sign * np.eye(dim)
        if rotation:
            nx = cross_matrix(n3)
            if dim == 3:
                Bd[:, o + 3:o + 6] = arm * nx
                Bp[:, o + 3:o + 6] = sign * np.eye(3)
            else:
                Bd[:, o + 2] = arm * nx[:, 2]
                Bp[2, o + 2] = sign
    return Bd, Bp


def element_matrix(c, q, rotation, viscous=False):
    """The coupled element matrix (2 nd, 2 nd) of contact q: B_d^T D B_d + B_p^T R B_p."""
    dim = c.dim
    kn, kt, kr, kw = ((c.c_n, c.c_t, c.c_r, c.c_w) if viscous else (c.k_n, c.k_s, c.k_r, c.k_w))
    n3 = np.zeros(3)
    n3[:dim] = c.normal[q]
    P = np.outer(n3, n3)
    Bd, Bp = strain_maps(c.normal[q], c.arm_i[q], c.arm_j[q], dim, rotation, c.j[q] < 0)
    K = Bd.T @ (kn[q] * P + kt[q] * (np.eye(3) - P)) @ Bd
    if rotation:
        if dim == 3:
            R = kr[q] * (np.eye(3) - P) + kw[q] * P
        else:
            R = np.diag([0.0, 0.0, kr[q]])
        K = K + Bp.T @ R @ Bp
    return K


def dense_matrix(p, c, rotation, viscous=False):
    """Global K (or C_d with ``viscous``) [N nd, N nd], contact by contact."""
    dim = p.dim
    nd = dim + ((1 if dim == 2 else 3) if rotation else 0)
    K = np.zeros((p.n * nd, p.n * nd))
    for q in range(c.n):
        Ke = element_matrix(c, q, rotation, viscous)
        idx = list(range(c.i[q] * nd, c.i[q] * nd + nd))
        idx += list(range(c.j[q] * nd, c.j[q] * nd + nd)) if c.j[q] >= 0 else [-1] * nd
        for a, ga in enumerate(idx):
            for b, gb in enumerate(idx):
                if ga >= 0 and gb >= 0:
                    K[ga, gb] += Ke[a, b]
    return K


def mass_diagonal(p, rotation):
    nrot = (1 if p.dim == 2 else 3) if rotation else 0
    return np.concatenate([np.r_[[p.m[k]] * p.dim, [p.inertia[k]] * nrot] for k in range(p.n)])


def scaling(p, rotation):
    nrot = (1 if p.dim == 2 else 3) if rotation else 0
    s = 1.0 / np.sqrt(mass_diagonal(p, rotation))
    s[np.repeat(p.fixed, p.dim + nrot)] = 0.0
    return s


def dense_lambda(p, c, rotation):
    s = scaling(p, rotation)
    return np.linalg.eigvalsh(s[:, None] * dense_matrix(p, c, rotation) * s[None, :])[-1]


def amplification_threshold(p, c, rotation, damping):
    """Largest dt with spectral radius <= 1 of the engine's one-step map
    v' = v + dt M^-1 (-K x - C v), x' = x + dt v' (dense, bisection)."""
    K = dense_matrix(p, c, rotation)
    Cd = dense_matrix(p, c, rotation, viscous=True)
    m = mass_diagonal(p, rotation)
    nd = len(m) // p.n
    free = ~np.repeat(p.fixed, nd)
    K, Cd, m = K[np.ix_(free, free)], Cd[np.ix_(free, free)], m[free]
    C = damping.mass * np.diag(m) + damping.stiffness * K + Cd
    n = len(m)
    eye = np.eye(n)
    MK, MC = K / m[:, None], C / m[:, None]

    def rho(dt):
        G = np.block([[eye - dt * dt * MK, dt * (eye - dt * MC)], [-dt * MK, eye - dt * MC]])
        mu = np.linalg.eigvals(G)
        return np.abs(mu[np.abs(mu - 1.0) > 1e-5]).max()

    lo, hi = 0.0, 1.0
    while rho(hi) <= 1 + 1e-9:
        hi *= 2
    for _ in range(45):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if rho(mid) > 1 + 1e-9 else (mid, hi)
    return lo


def random_assembly(name, seed, walls=True, fixed=False, size=2, limit=10):
    """A jittered, slightly polydisperse block with walls and random springs, dashpots
    and rolling and twisting springs (k_w != k_r) with viscous parts."""
    rng = np.random.default_rng(seed)
    lat = lattice(name, 1.0)
    x = lat.block(size)[:limit]
    x = x + rng.normal(0, 0.01, x.shape)
    r = 1.0 + 0.05 * rng.random(len(x))
    p = Particles.from_density(x, r, 1.0 + rng.random())
    if fixed:
        p = Particles(p.x, p.r, p.m, p.inertia, fixed=np.arange(p.n) == 0)
    wall_list = []
    if walls:
        lo = (x - r[:, None]).min(axis=0)
        wall_list = [Wall(lo, np.eye(lat.dim)[k], name=f"w{k}") for k in range(lat.dim)]
    c = find_contacts(p, 1.0, contact_tol=0.08, walls=wall_list)
    n = c.n
    c = replace(c, k_n=rng.random(n) + 1, k_s=rng.random(n), c_n=0.3 * rng.random(n),
                c_t=0.3 * rng.random(n), k_r=0.2 + rng.random(n), k_w=0.1 + 0.5 * rng.random(n),
                c_r=0.2 * rng.random(n), c_w=0.2 * rng.random(n))
    assert c.has_rolling and (not walls or (c.j < 0).any())
    return p, c, rng


def no_rolling(c):
    return replace(c, k_r=0.0, k_w=0.0, c_r=0.0, c_w=0.0)


ASSEMBLIES = [("fcc", 0, False), ("sc", 1, True), ("hex", 2, False), ("square", 3, True)]


# ------------------------------------------------------------ ContactSet fields
def test_contact_set_fields_default_subset_concatenate():
    c = ContactSet([0, 1], [1, -1], [[1.0, 0, 0], [0, 0, 1.0]], [1.0, 1.0], [1.0, 0.0], 2.0, 1.0)
    assert not c.has_rolling and not c.damped
    for name in ("k_r", "k_w", "c_r", "c_w"):
        np.testing.assert_array_equal(getattr(c, name), np.zeros(2))
    c2 = replace(c, k_r=[3.0, 0.0], c_w=[0.0, 0.5])
    assert c2.has_rolling and c2.damped  # a twisting dashpot alone damps
    sub = c2.subset(np.array([False, True]))
    assert sub.k_r.tolist() == [0.0] and sub.c_w.tolist() == [0.5]
    both = ContactSet.concatenate([c2, c])
    assert both.k_r.tolist() == [3.0, 0.0, 0.0, 0.0] and both.c_w.tolist() == [0.0, 0.5, 0.0, 0.0]
    d = c2.dashpot_springs()
    assert d.k_r.tolist() == c2.c_r.tolist() and d.k_w.tolist() == c2.c_w.tolist()
    # 2D: only k_r and c_r count (disks do not twist)
    flat = ContactSet([0], [1], [[1.0, 0.0]], [1.0], [1.0], 1.0, 1.0, k_w=5.0)
    assert not flat.has_rolling



def test_contact_set_copies_leave_absent_coefficients_untouched():
    """Concatenating or selecting contacts without dashpots or rolling springs keeps
    those six arrays as zeros the system has not handed out (a copy of zeros costs its
    memory: 6 x 56 MB at 7e6 contacts); one part is returned itself; values as
    before. Measured in a fresh process whose arrays all come from the system (glibc's
    mmap threshold fixed), so that its growth counts exactly the pages written."""
    code = """
import os, numpy as np
from demstep.timestep.contacts import ContactSet
def rss():
    return int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
n = 500_000
rng = np.random.default_rng(0)
part = ContactSet(np.arange(n), np.arange(n) + 1, rng.normal(size=(n, 3)), np.ones(n),
                  np.ones(n), 2.0, 1.0)
assert ContactSet.concatenate([part]) is part
before = rss()
both = ContactSet.concatenate([part, part])
grown = rss() - before
before = rss()
half = both.subset(np.arange(0, 2 * n, 2))
print(grown, rss() - before, both.n, bool(both.damped or both.has_rolling),
      bool(np.array_equal(both.normal[n:], part.normal)), bool(np.array_equal(half.i, both.i[::2])),
      bool(half.c_n.any()), half.c_w.shape[0])
"""
    env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="131072")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    grown, grown_half, count, extra, same_normal, same_i, any_c_n, size = out.stdout.split()
    n = 500_000
    touched = 80  # bytes per contact written: i, j, normal, arms, k_n, k_s, wall
    assert int(grown) < touched * 2 * n + 48 * 2 * n / 4  # not the 48 bytes of the zeros
    assert int(grown_half) < touched * n + 48 * n / 4
    assert (count, extra, same_normal, same_i, any_c_n, size) == (
        str(2 * n), "False", "True", "True", "False", str(n))


# ------------------------------------------------------- products and assembly
@pytest.mark.parametrize("name,seed,fixed", ASSEMBLIES)
@pytest.mark.parametrize("rotation", [True, False])
def test_matrix_free_products_match_dense_assembly(name, seed, fixed, rotation):
    p, c, rng = random_assembly(name, seed, fixed=fixed)
    K = dense_matrix(p, c, rotation)
    C = dense_matrix(p, c, rotation, viscous=True)
    if not rotation:  # the rolling springs act on rotations only: nothing left of them
        np.testing.assert_array_equal(K, dense_matrix(p, no_rolling(c), False))
    nd = K.shape[0] // p.n
    x = rng.standard_normal((p.n, nd))
    scale = np.abs(K).max()
    k_r, k_w = (c.k_r, c.k_w)
    np.testing.assert_allclose(contact_matvec(c, c.k_n, c.k_s, rotation, x, k_r, k_w).reshape(-1),
                               K @ x.reshape(-1), rtol=1e-12, atol=1e-12 * scale)
    np.testing.assert_allclose(assemble_stiffness(p, c, rotation).toarray(), K,
                               rtol=1e-12, atol=1e-13 * scale)
    np.testing.assert_allclose(stiffness_diagonal(p, c, rotation), np.diag(K), rtol=1e-12)
    s = scaling(p, rotation)
    for threads in (1, 3):
        op = ScaledContactOperator(p, c, rotation, threads=threads)
        v = rng.standard_normal(op.size)
        np.testing.assert_allclose(op.stiffness(v), s * (K @ (s * v)), rtol=1e-11,
                                   atol=1e-12 * scale)
        np.testing.assert_allclose(op.dashpots(v), s * (C @ (s * v)), rtol=1e-11,
                                   atol=1e-12 * np.abs(C).max())
        # the pencil at sigma: (1 + sigma a2) K + sigma C
        op_d = ScaledContactOperator(p, c, rotation, GlobalDamping(0.0, 0.05), threads=threads)
        sigma = 1.7
        pencil = s[:, None] * ((1 + sigma * 0.05) * K + sigma * C) * s[None, :]
        np.testing.assert_allclose(op_d.pencil(sigma) @ v, pencil @ v, rtol=1e-11,
                                   atol=1e-12 * np.abs(pencil).max())
        np.testing.assert_allclose(op_d.dense_pencil(sigma), pencil, rtol=1e-11,
                                   atol=1e-13 * np.abs(pencil).max())
        # Rayleigh terms, Gram matrices and per-contact energies
        q = v / np.linalg.norm(v)
        kq, cq = op.rayleigh_terms(q)
        assert kq == pytest.approx(q @ (s * (K @ (s * q))), rel=1e-11)
        assert cq == pytest.approx(q @ (s * (C @ (s * q))), rel=1e-11)
        Y = rng.standard_normal((4, op.size))
        X = op.scale[None] * Y.reshape(4, *op.scale.shape)
        Kp, Cp = contact_gram(c, rotation, X, op._chunks, parallel=threads > 1)
        Ks, Cs = s[:, None] * K * s[None, :], s[:, None] * C * s[None, :]
        np.testing.assert_allclose(Kp, Y @ Ks @ Y.T, rtol=1e-11, atol=1e-11 * np.abs(Kp).max())
        np.testing.assert_allclose(Cp, Y @ Cs @ Y.T, rtol=1e-11, atol=1e-11 * np.abs(Cp).max())
    u = op.displacement(q)
    energy = contact_energies(c, c.k_n, c.k_s, rotation, u, c.k_r, c.k_w)
    assert energy.sum() == pytest.approx(0.5 * u.reshape(-1) @ K @ u.reshape(-1), rel=1e-11)
    assert contact_quadratic_forms(c, rotation, u)[0] == pytest.approx(2 * energy.sum(), rel=1e-11)
    share = op.mode_shares(q)[2]
    assert share.sum() == pytest.approx(1.0) and np.all(share >= 0)


def test_rolling_element_on_a_wall_acts_on_i_alone():
    """One sphere on a wall, only a rolling spring: the rotational block is B on theta_i,
    B = k_r (I - n n^T) + k_w n n^T (an explicit 3 x 3 check of the formula)."""
    p = Particles(np.zeros((1, 3)), np.ones(1), np.ones(1), np.full(1, 0.4))
    n = np.array([0.0, 0.6, 0.8])
    c = ContactSet([0], [-1], n[None], [1.0], [0.0], 0.0, 0.0, [0], k_r=2.0, k_w=0.5)
    K = assemble_stiffness(p, c, True).toarray()
    np.testing.assert_allclose(K[3:, 3:], 2.0 * (np.eye(3) - np.outer(n, n)) + 0.5 * np.outer(n, n),
                               rtol=1e-15, atol=1e-15)
    assert not K[:3].any() and not K[:, :3].any()


# ------------------------------------------------------------- exact steps
@pytest.mark.parametrize("name,seed,fixed", ASSEMBLIES)
def test_exact_undamped_step_with_rolling_is_the_dense_eigenvalue(name, seed, fixed):
    p, c, _ = random_assembly(name, seed, fixed=fixed)
    c = replace(c, c_n=0.0, c_t=0.0, c_r=0.0, c_w=0.0)
    lam = dense_lambda(p, c, True)
    for dense_limit in (10**6, 0):
        e = exact_critical_step(p, c, True, dense_limit=dense_limit)
        assert not e.damped
        assert e.lambda_undamped == pytest.approx(lam, rel=1e-9)
        assert e.dt == pytest.approx(2 / math.sqrt(lam), rel=1e-8)
        assert e.dt <= 2 / math.sqrt(lam) * (1 + 1e-12)


@pytest.mark.parametrize("name,seed,fixed", ASSEMBLIES)
@pytest.mark.parametrize("which", ["rolling-viscous", "all+global"])
def test_exact_damped_step_with_rolling_is_the_amplification_threshold(name, seed, fixed, which):
    p, c, _ = random_assembly(name, seed, fixed=fixed)
    if which == "rolling-viscous":  # the rolling and twisting viscous parts alone, strong
        c = replace(c, c_n=0.0, c_t=0.0, c_r=5 * c.c_r, c_w=5 * c.c_w)
        damping = GlobalDamping()
    else:
        damping = GlobalDamping(0.2, 0.01)
    reference = amplification_threshold(p, c, True, damping)
    for dense_limit in (10**6, 0):
        e = exact_critical_step(p, c, True, damping, dense_limit=dense_limit)
        assert e.damped
        assert e.dt == pytest.approx(reference, rel=1e-6)
        assert e.dt <= reference * (1 + 1e-9)
        assert e.dt < e.dt_undamped
    bound = ScaledContactOperator(p, c, True, damping).damping_bound()
    s = scaling(p, True)
    C = damping.mass * np.diag(np.where(s > 0, 1.0, 0.0)) + s[:, None] * (
        damping.stiffness * dense_matrix(p, c, True) + dense_matrix(p, c, True, True)) * s[None, :]
    assert np.linalg.eigvalsh(C)[-1] <= bound * (1 + 1e-12)


@pytest.mark.parametrize("name", ["fcc", "hex"])
def test_damping_bound_covers_the_rolling_dashpots(name):
    """Weak rolling springs with strong viscous parts: lambda_max(M^-1/2 C M^-1/2) (dense)
    stays below ScaledContactOperator.damping_bound (the closed form of the certifying
    step and of the certificate)."""
    p, c, rng = random_assembly(name, 21)
    c = replace(c, c_n=0.0, c_t=0.0, k_r=1e-3 * c.k_r, k_w=1e-3 * c.k_w,
                c_r=1.0 + rng.random(c.n), c_w=1.0 + rng.random(c.n))
    s = scaling(p, True)
    lam_c = np.linalg.eigvalsh(s[:, None] * dense_matrix(p, c, True, True) * s[None, :])[-1]
    assert lam_c > 0
    assert lam_c <= ScaledContactOperator(p, c, True).damping_bound() * (1 + 1e-12)


def test_rolling_springs_lower_the_exact_step_measurably():
    """FCC block of equal spheres, beta convention with beta_r = beta_w = 2 (k = beta k_t
    R*^2): the fastest mode turns rotational and the exact step drops by more than
    10 %, as the dense eigenvalue says; with beta_r = 0.01 it barely moves."""
    lat = lattice("fcc", 1.0)
    x = lat.block(2)
    p = Particles.from_density(x, np.ones(len(x)), 2.0)
    c = find_contacts(p, 1.0e3, 0.8e3)
    base = exact_critical_step(p, c, True)
    r_star = 0.5
    results = {}
    for beta in (0.01, 2.0):
        k = beta * c.k_s * r_star**2
        cr = replace(c, k_r=k, k_w=k)
        e = exact_critical_step(p, cr, True)
        assert e.dt == pytest.approx(2 / math.sqrt(dense_lambda(p, cr, True)), rel=1e-8)
        assert e.dt <= base.dt * (1 + 1e-12)
        results[beta] = e
    assert results[2.0].dt < 0.9 * base.dt
    assert results[0.01].dt > 0.995 * base.dt
    rot_share = results[2.0].operator.mode_shares(results[2.0].mode)[1].sum()
    assert rot_share > 0.5


# ------------------------------------------------------------- element bounds
@pytest.mark.parametrize("name,seed,fixed", ASSEMBLIES)
@pytest.mark.parametrize("rotation", [True, False])
@pytest.mark.parametrize("dominant", ["mixed", "twist", "rolling"])
def test_coupled_element_closed_forms_match_the_element_pencils(name, seed, fixed, rotation,
                                                                 dominant):
    p, c, _ = random_assembly(name, seed, fixed=fixed)
    if dominant == "twist":  # the twist axis (3D) sets the element's step
        c = replace(c, k_w=50 * c.k_w, c_w=20 * c.c_w)
    elif dominant == "rolling":
        c = replace(c, k_r=50 * c.k_r, c_r=20 * c.c_r)
    mass = element_mass(p, c)
    a1, a2 = 0.2, 0.03
    lam = coupled_element_lambda(c, mass, rotation)
    dt = coupled_element_damped_dt(c, mass, rotation, a1, a2)
    dt0 = coupled_element_damped_dt(replace(c, c_n=0.0, c_t=0.0, c_r=0.0, c_w=0.0), mass,
                                    rotation)
    nrot = (1 if p.dim == 2 else 3) if rotation else 0
    for q in range(c.n):
        with np.errstate(divide="ignore"):
            inv = np.r_[[mass.inv_m_i[q]] * p.dim, [mass.inv_I_i[q]] * nrot,
                        [mass.inv_m_j[q]] * p.dim, [mass.inv_I_j[q]] * nrot]
        keep = inv > 0
        if not keep.any():  # a fixed particle on a wall: nothing moves
            assert lam[q] == 0 and dt0[q] == np.inf
            continue
        K = element_matrix(c, q, rotation)[np.ix_(keep, keep)]
        Cd = element_matrix(c, q, rotation, viscous=True)[np.ix_(keep, keep)]
        w = inv[keep]
        A = np.sqrt(w)[:, None] * K * np.sqrt(w)[None, :]
        assert lam[q] == pytest.approx(np.linalg.eigvalsh(A)[-1], rel=1e-10)
        assert dt0[q] == pytest.approx(2 / math.sqrt(np.linalg.eigvalsh(A)[-1]), rel=1e-10)
        C = a1 * np.diag(1.0 / w) + a2 * K + Cd
        n = len(w)
        L = np.block([[np.zeros((n, n)), np.eye(n)], [K * w[:, None], C * w[:, None]]])
        ev = np.linalg.eigvals(L)
        sigma = ev[np.abs(ev.imag) < 1e-9 * np.abs(ev).max()].real.max()
        reference = min(2 / sigma, 2 / a1)
        assert dt[q] == pytest.approx(reference, rel=1e-9)
        assert dt[q] <= reference * (1 + 1e-12)  # the root from above: never a larger step
    if dominant != "mixed" and rotation and (dominant == "rolling" or p.dim == 3):
        # the rotational springs decide the element values of free contacts
        free = mass.inv_I_i > 0
        assert np.all(lam[free] > coupled_element_lambda(no_rolling(c), mass, True)[free])


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("name", ["fcc", "hex", "sc", "square"])
def test_element_and_nodal_with_rolling_against_exact(seed, name):
    p, c, _ = random_assembly(name, 10 * seed + len(name), walls=bool(seed % 2))
    scale = 10.0 ** (seed - 2)  # rolling springs from weak to dominant
    c = replace(c, k_r=scale * c.k_r, k_w=scale * c.k_w, c_r=scale * c.c_r, c_w=scale * c.c_w)
    for damping in (GlobalDamping(), GlobalDamping(0.05 * (seed % 3), 0.01 * (seed % 2))):
        cc = c if damping.active or seed % 2 else replace(c, c_n=0.0, c_t=0.0, c_r=0.0, c_w=0.0)
        exact = exact_critical_step(p, cc, True, damping).dt
        assert element_coupled_dt(p, cc, True, damping=damping) <= exact * (1 + 1e-9)
    # the nodal rule sums the rolling springs into the rotational stiffness
    K = dense_matrix(p, c, True)
    s = scaling(p, True)
    free = s > 0
    ref = math.sqrt(2.0) * np.sqrt(np.min(1.0 / (s[free] ** 2 * np.diag(K)[free])))
    assert nodal_dt(p, replace(c, c_n=0.0, c_t=0.0, c_r=0.0, c_w=0.0), True) == \
        pytest.approx(ref, rel=1e-12)


@pytest.mark.parametrize("name,seed,fixed", ASSEMBLIES)
def test_zero_rolling_springs_give_the_old_values_bit_for_bit(name, seed, fixed):
    """Contacts whose k_r, k_w, c_r, c_w are zero keep the element values of the
    analysis without rolling resistance exactly, whether or not other contacts roll;
    without any, every method gives exactly the same as without the fields."""
    p, c, _ = random_assembly(name, seed, fixed=fixed)
    off = np.arange(c.n) % 2 == 0
    half = replace(c, k_r=np.where(off, 0.0, c.k_r), k_w=np.where(off, 0.0, c.k_w),
                   c_r=np.where(off, 0.0, c.c_r), c_w=np.where(off, 0.0, c.c_w))
    old = no_rolling(c)
    mass = element_mass(p, c)
    for rotation in (True, False):
        np.testing.assert_array_equal(coupled_element_lambda(half, mass, rotation)[off],
                                      coupled_element_lambda(old, mass, rotation)[off])
        np.testing.assert_array_equal(
            coupled_element_damped_dt(half, mass, rotation, 0.1, 0.02)[off],
            coupled_element_damped_dt(old, mass, rotation, 0.1, 0.02)[off])
    plain = ContactSet(c.i, c.j, c.normal, c.arm_i, c.arm_j, c.k_n, c.k_s, c.wall, c.c_n, c.c_t)
    d = GlobalDamping(0.1)
    a = estimate_time_steps(p, old, damping=d)
    b = estimate_time_steps(p, plain, damping=d)
    assert [(e.method, e.dt) for e in a.estimates] == [(e.method, e.dt) for e in b.estimates]
    assert not any("rolling" in note for note in a.notes)


def test_paper_element_ignores_rolling_and_is_marked_by_the_exact_step():
    p, c, _ = random_assembly("fcc", 5, walls=False)
    c = replace(c, c_n=0.0, c_t=0.0, c_r=0.0, c_w=0.0, k_r=50 * c.k_r, k_w=50 * c.k_w)
    with_roll = estimate_time_steps(p, c)
    without = estimate_time_steps(p, no_rolling(c))
    assert with_roll.get("element-paper").dt == without.get("element-paper").dt
    exact = with_roll.get("exact").dt
    assert exact < 0.7 * without.get("exact").dt
    for e in with_roll.estimates:
        assert e.conservative == (e.dt <= exact * (1 + 1e-9))
    assert with_roll.get("element-paper").conservative is False
    assert with_roll.get("element-coupled").conservative is True
    assert any("rolling" in note for note in with_roll.notes)
    locked = estimate_time_steps(p, c, rotation=False)
    assert locked.get("exact").dt == estimate_time_steps(p, no_rolling(c), rotation=False).get("exact").dt


# --------------------------------------------------------------------- clumps
def dumbbell_assembly(seed, dim=3):
    """Three two-sphere bodies and three free spheres in a jittered block; rolling on."""
    rng = np.random.default_rng(seed)
    lat = lattice("sc" if dim == 3 else "square", 1.0)
    x = lat.block(2)[:8] if dim == 3 else lat.block(3)[:8]
    x = x + rng.normal(0, 0.01, x.shape)
    r = 1.03 + 0.05 * rng.random(len(x))
    body = np.array([0, 0, 1, 1, 2, 2, -1, -1] if dim == 3 else [0, 0, -1, 1, 1, -1, 2, 2])
    bodies = RigidBodies.from_members(x, r, body, 1.0)
    m = Particles.from_density(x, r, 1.0).m
    m[body >= 0] = bodies.mass[body[body >= 0]]
    p = Particles(x, r, m, 0.4 * m * r**2 if dim == 3 else 0.5 * m * r**2)
    c = find_contacts(p, 1.0, contact_tol=0.08)
    c = c.subset((body[c.i] < 0) | (body[c.i] != body[c.j]))
    n = c.n
    c = replace(c, k_n=rng.random(n) + 1, k_s=rng.random(n), k_r=0.5 + rng.random(n),
                k_w=0.2 + rng.random(n), c_r=0.2 * rng.random(n), c_w=0.1 * rng.random(n),
                c_n=0.2 * rng.random(n), c_t=0.2 * rng.random(n))
    return p, c, bodies


def body_reference(p, c, bodies):
    """Dense G^T K G, G^T C G and the owners' mass matrix (free spheres, then bodies)."""
    dim = p.dim
    nrot = 1 if dim == 2 else 3
    nd = dim + nrot
    free = np.flatnonzero(bodies.sphere_body < 0)
    n_owner = len(free) + bodies.n
    G = np.zeros((p.n * nd, n_owner * nd))
    M = np.zeros((n_owner * nd, n_owner * nd))
    for k, s in enumerate(free):
        G[s * nd:(s + 1) * nd, k * nd:(k + 1) * nd] = np.eye(nd)
        M[k * nd:(k + 1) * nd, k * nd:(k + 1) * nd] = np.diag([p.m[s]] * dim + [p.inertia[s]] * nrot)
    for s in np.flatnonzero(bodies.sphere_body >= 0):
        b = len(free) + bodies.sphere_body[s]
        a = bodies.arm[s]
        G[s * nd:s * nd + dim, b * nd:b * nd + dim] = np.eye(dim)
        if dim == 3:
            G[s * nd:s * nd + 3, b * nd + 3:b * nd + 6] = -cross_matrix(a)  # omega x a
            G[s * nd + 3:s * nd + 6, b * nd + 3:b * nd + 6] = np.eye(3)
        else:
            G[s * nd:s * nd + 2, b * nd + 2] = [-a[1], a[0]]
            G[s * nd + 2, b * nd + 2] = 1.0
    for b in range(bodies.n):
        o = (len(free) + b) * nd
        M[o:o + dim, o:o + dim] = bodies.mass[b] * np.eye(dim)
        M[o + dim:o + nd, o + dim:o + nd] = (bodies.inertia[b] if dim == 3
                                             else bodies.inertia[b][2:, 2:])
    K = G.T @ dense_matrix(p, c, True) @ G
    C = G.T @ dense_matrix(p, c, True, viscous=True) @ G
    return K, C, M


@pytest.mark.parametrize("seed,dim", [(1, 3), (2, 3), (3, 2)])
def test_clumps_with_rolling_exact_element_and_nodal(seed, dim):
    import scipy.linalg

    p, c, bodies = dumbbell_assembly(seed, dim)
    K, C, M = body_reference(p, c, bodies)
    lam = scipy.linalg.eigh(K, M, eigvals_only=True)[-1]
    undamped = replace(c, c_n=0.0, c_t=0.0, c_r=0.0, c_w=0.0)
    for dense_limit in (10**6, 0):
        e = exact_critical_step(p, undamped, True, bodies=bodies, dense_limit=dense_limit)
        assert e.dt == pytest.approx(2 / math.sqrt(lam), rel=1e-8)
    assert body_element_dt(p, undamped, bodies, True).min() <= e.dt * (1 + 1e-12)
    damped = exact_critical_step(p, c, True, GlobalDamping(0.05), bodies=bodies)
    assert body_element_dt(p, c, bodies, True, 0.05).min() <= damped.dt * (1 + 1e-9)
    assert damped.dt < e.dt
    # nodal rule: the owners' summed stiffness is the diagonal of G^T K G
    diag = body_stiffness_diagonal(p, c, bodies, True).reshape(-1)
    np.testing.assert_allclose(diag, np.diag(K), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(body_stiffness_diagonal(p, c, bodies, True, "c").reshape(-1),
                               np.diag(C), rtol=1e-12, atol=1e-14)
    # damping bound on lambda_max(M^-1/2 C M^-1/2)
    w, V = np.linalg.eigh(M)
    Mh = V @ np.diag(w ** -0.5) @ V.T
    bound = ScaledContactOperator(p, c, True, bodies=bodies).damping_bound()
    assert np.linalg.eigvalsh(Mh @ C @ Mh)[-1] <= bound * (1 + 1e-12)


def owner_element(p, c, bodies, q):
    """(K_o, M_o) of contact q on its owners' DOFs: the sphere element (independent
    reference above) mapped by each side's rigid-body map, and each owner's mass matrix
    divided by its number of contacts (the uniform partition); wall sides dropped."""
    dim = p.dim
    nrot = 1 if dim == 2 else 3
    nd = dim + nrot
    sb = bodies.sphere_body
    owner = np.where(sb < 0, -1 - np.arange(p.n), sb)  # free spheres: negative ids
    ends = np.concatenate([c.i, c.j[c.j >= 0]])
    counts = {o: int(np.sum(owner[ends] == o)) for o in np.unique(owner[ends])}
    sides = [c.i[q]] + ([c.j[q]] if c.j[q] >= 0 else [])
    Ke = element_matrix(c, q, True)[:len(sides) * nd, :len(sides) * nd]
    G = np.zeros((len(sides) * nd, len(sides) * nd))
    M = np.zeros((len(sides) * nd, len(sides) * nd))
    for k, sph in enumerate(sides):
        o = slice(k * nd, (k + 1) * nd)
        n_c = counts[owner[sph]]
        if sb[sph] < 0:
            G[o, o] = np.eye(nd)
            M[o, o] = np.diag([p.m[sph]] * dim + [p.inertia[sph]] * nrot) / n_c
            continue
        a = bodies.arm[sph]
        block = np.eye(nd)
        if dim == 3:
            block[:3, 3:] = -cross_matrix(a)
            inertia = bodies.inertia[sb[sph]]
        else:
            block[:2, 2] = [-a[1], a[0]]
            inertia = bodies.inertia[sb[sph]][2:, 2:]
        G[o, o] = block
        M[o, o] = np.block([[bodies.mass[sb[sph]] * np.eye(dim), np.zeros((dim, nrot))],
                            [np.zeros((nrot, dim)), inertia]]) / n_c
    return G.T @ Ke @ G, M, G


@pytest.mark.parametrize("seed,dim", [(1, 3), (3, 2)])
def test_body_elements_with_rolling_match_their_pencils(seed, dim):
    """Each contact element of an assembly with clumps, on its owners' DOFs with the
    uniform partition of their mass matrices (independent reference): its step
    undamped (2 / sqrt(lambda_max)) and damped (companion matrix) is body_element_dt's."""
    import scipy.linalg

    p, c, bodies = dumbbell_assembly(seed, dim)
    a1 = 0.05
    undamped = body_element_dt(p, replace(c, c_n=0.0, c_t=0.0, c_r=0.0, c_w=0.0), bodies, True)
    damped = body_element_dt(p, c, bodies, True, a1)
    for q in range(c.n):
        K, M, G = owner_element(p, c, bodies, q)
        Kc = owner_element(p, c.dashpot_springs(), bodies, q)[0]
        lam = scipy.linalg.eigh(K, M, eigvals_only=True)[-1]
        assert undamped[q] == pytest.approx(2 / math.sqrt(lam), rel=1e-9)
        C = a1 * M + Kc
        Minv = np.linalg.inv(M)
        n = len(M)
        L = np.block([[np.zeros((n, n)), np.eye(n)], [Minv @ K, Minv @ C]])
        ev = np.linalg.eigvals(L)
        sigma = ev[np.abs(ev.imag) < 1e-9 * np.abs(ev).max()].real.max()
        assert damped[q] == pytest.approx(2 / sigma, rel=1e-7)


# --------------------------------------------------------------- certificate
def test_turned_pair_with_rolling_moves_by_less_than_the_bound():
    """One 3D pair with rolling and twisting springs (k_w != k_r) and viscous parts,
    touching, its normal turned at the same distance (its arms unchanged): the spectral
    norm of the change of its mass-scaled element (dense, independent) stays below the
    certificate's drift; with isotropic translational springs and stiff rolling springs
    the drift without the rolling term is exceeded (the term is needed)."""
    rng = np.random.default_rng(11)
    ratios, exceeded = [], 0
    for trial in range(300):
        r = rng.uniform(0.3, 1.5, 2)
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        n2 = n + rng.uniform(0.01, 1.0) * rng.normal(size=3) / math.sqrt(3)
        n2 /= np.linalg.norm(n2)
        dist = 0.97 * r.sum()
        x, x2 = np.array([[0.0, 0, 0], dist * n]), np.array([[0.0, 0, 0], dist * n2])
        p = Particles.from_density(x, r, rng.uniform(0.5, 3))
        arms = r - 0.5 * (r.sum() - dist)
        k = rng.uniform(0.1, 10.0)
        iso = trial % 2 == 0
        k_n, k_t = (k, k) if iso else rng.uniform(0.1, 10.0, 2)
        k_r, k_w = rng.uniform(0.1, 10.0, 2) * (30.0 if iso else 1.0)
        base = ContactSet([0], [1], n[None], arms[:1], arms[1:], k_n, k_t, c_n=k_t, c_t=k_n,
                          k_r=k_r, k_w=k_w, c_r=0.3 * k_w, c_w=0.2 * k_r)
        turned = replace(base, normal=n2[None])
        cert = StepCertificate.from_estimate(1.0, 1.0, base, 1.0 / p.m, 1.0 / p.inertia,
                                             radius=r)
        plain = StepCertificate.from_estimate(1.0, 1.0, no_rolling(base), 1.0 / p.m,
                                              1.0 / p.inertia, radius=r)
        s = scaling(p, True)
        for viscous in (False, True):
            bound = cert.drift(x2, np.zeros(3))[viscous]
            without = plain.drift(x2, np.zeros(3))[viscous]
            change = s[:, None] * (dense_matrix(p, turned, True, viscous)
                                   - dense_matrix(p, base, True, viscous)) * s[None, :]
            norm = np.abs(np.linalg.eigvalsh(change)).max()
            ratios.append(norm / bound)
            exceeded += norm > without * (1 + 1e-12)
    assert max(ratios) <= 1.0 + 1e-12
    assert max(ratios) > 0.25
    assert exceeded > 0


def test_moved_assembly_with_rolling_stays_below_the_drifted_certificate():
    rng = np.random.default_rng(5)
    x = rng.uniform(0, 3.0, (30, 3))
    r = rng.uniform(0.45, 0.6, 30)
    p = Particles.from_density(x, r, 2.0)
    found = find_contacts(p, 1.0, contact_tol=0.25)
    found = found.subset(found.j >= 0)
    n = found.n
    assert n > 30
    k_n = rng.uniform(1.0, 3.0, n)
    ref = contacts_now(ContactSet(found.i, found.j, found.normal, r[found.i], r[found.j], k_n,
                                  0.4 * k_n, c_n=0.2 * np.sqrt(k_n), c_t=0.05 * np.sqrt(k_n),
                                  k_r=rng.uniform(0.5, 3.0, n), k_w=rng.uniform(0.0, 0.2, n),
                                  c_r=rng.uniform(0.0, 0.3, n), c_w=0.0),
                       x, r, apart=True)
    s = scaling(p, True)
    K = s[:, None] * dense_matrix(p, ref, True) * s[None, :]
    C = s[:, None] * dense_matrix(p, ref, True, True) * s[None, :]
    f = lambda sig, Kx, Cx: np.linalg.eigvalsh(sig * Cx + Kx)[-1] - sig * sig  # noqa: E731
    lo, hi = 0.0, 1.0
    while f(hi, K, C) > 0:
        hi *= 2
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(mid, K, C) > 0 else (lo, mid)
    sigma_c = hi
    lam_c = np.linalg.eigvalsh(C)[-1]
    cert = StepCertificate.from_estimate(sigma_c, lam_c, ref, 1.0 / p.m, 1.0 / p.inertia,
                                         radius=r)
    plain = StepCertificate.from_estimate(sigma_c, lam_c, no_rolling(ref), 1.0 / p.m,
                                          1.0 / p.inertia, radius=r)
    assert np.any(cert.factors[:, 6] > 0) and not plain.factors[:, 6:].any()
    for trial in range(10):
        moved = x + 0.05 * r[:, None] * rng.normal(size=(30, 3))
        now = contacts_now(ref, moved, r, apart=True)  # (apart: the estimate's arms, harder)
        K2 = s[:, None] * dense_matrix(p, now, True) * s[None, :]
        C2 = s[:, None] * dense_matrix(p, now, True, True) * s[None, :]
        drift = cert.drift(moved, np.zeros(3))
        for sigma in sigma_c * np.array([1.0, 1.2, 2.0]):
            assert np.linalg.eigvalsh(sigma * C2 + K2)[-1] <= cert.bound(sigma, drift) * (1 + 1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_added_contacts_bound_with_rolling(dim):
    """The bound of a group of added contacts: the group's lambda_max(M^-1/2 K M^-1/2)
    and of C (dense, the group alone) stay below it; without rolling it is the engine's
    formula max(k_n c_m, k_t (c_m + c_r)) over the group's elements."""
    p, c, _ = random_assembly("fcc" if dim == 3 else "hex", 7 + dim)
    group = c.subset(np.arange(c.n) % 3 == 0)
    add_k, add_c = added_contacts_bound(p, group, True)
    s = scaling(p, True)
    assert np.linalg.eigvalsh(s[:, None] * dense_matrix(p, group, True) * s[None, :])[-1] <= \
        add_k * (1 + 1e-12)
    assert np.linalg.eigvalsh(s[:, None] * dense_matrix(p, group, True, True) * s[None, :])[-1] <= \
        add_c * (1 + 1e-12)
    plain = no_rolling(group)
    mass = element_mass(p, plain)
    c_m = mass.inv_m_i + mass.inv_m_j
    c_r = plain.arm_i**2 * mass.inv_I_i + plain.arm_j**2 * mass.inv_I_j
    assert added_contacts_bound(p, plain, True) == (
        float(np.max(np.maximum(plain.k_n * c_m, plain.k_s * (c_m + c_r)))),
        float(np.max(np.maximum(plain.c_n * c_m, plain.c_t * (c_m + c_r)))))
    assert add_k > added_contacts_bound(p, plain, True)[0]


@pytest.mark.parametrize("dim", [2, 3])
def test_densest_packing_bound_with_rolling_scales_with_the_radius(dim):
    """densest_packing_dt with rolling springs for particles of radius R is the coupled
    element bound of the densest periodic packing of such particles (built here at
    radius R), and below the bound without rolling springs."""
    from demstep.packings import lattice as make_lattice
    from demstep.particles import INERTIA_FACTOR
    from demstep.timestep.estimates import densest_packing_dt

    R, m, k, k_r = 0.3, 2.0, 5.0, 40.0
    lat = make_lattice("hex" if dim == 2 else "fcc", R)
    x, box = lat.supercell(3)
    n = len(x)
    p = Particles(x, np.full(n, R), np.full(n, m), np.full(n, INERTIA_FACTOR[dim] * m * R * R))
    c = replace(find_contacts(p, k, 0.8 * k, periodic=box), k_r=k_r, k_w=0.5 * k_r)
    ref = element_coupled_dt(p, c, True)
    got = densest_packing_dt(dim, m, k, 0.8 * k, k_r=k_r, k_w=0.5 * k_r, radius=R)
    assert got == pytest.approx(ref, rel=1e-12)
    assert got < densest_packing_dt(dim, m, k, 0.8 * k)


# ------------------------------------------------------------- Bloch lattice
def test_bloch_with_rolling_bounds_the_supercell():
    """A periodic FCC supercell is a finite sample of the lattice's wave vectors: its
    exact step with uniform rolling springs is at least the Bloch step, and close."""
    from demstep.timestep.bloch import bloch_lambda_max

    lat = lattice("fcc", 1.0)
    x, box = lat.supercell(3)
    p = Particles.from_density(x, np.ones(len(x)), 1.0)
    c = find_contacts(p, 1.0, 0.7, periodic=box)
    k_r = 10.0 * 0.7 * 0.25  # beta_r = 10: the antiphase rotation becomes the fastest
    cr = replace(c, k_r=k_r, k_w=0.5 * k_r)
    lam, _ = bloch_lambda_max(lat, 1.0, 0.7, 1.0, True, k_r=k_r, k_w=0.5 * k_r)
    lam0, _ = bloch_lambda_max(lat, 1.0, 0.7, 1.0, True)
    assert lam > 1.05 * lam0
    exact = exact_critical_step(p, cr, True).dt
    assert exact >= 2 / math.sqrt(lam) * (1 - 1e-9)
    assert exact == pytest.approx(2 / math.sqrt(lam), rel=0.05)


# ----------------------------------------------------------- input and CLI
def run(argv, capsys):
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse errors
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def exact_of(data):
    return next(e["dt"] for e in data["estimates"] if e["method"] == "exact")


def test_cli_beta_convention_on_a_lattice(capsys):
    """`demstep dt --rolling-convention beta`: k_r = beta_r k_t R*^2, k_w = beta_w k_t
    R*^2 per contact; the exact step is the library's on contacts built by hand, and
    below the one without rolling resistance."""
    base = ["dt", "--lattice", "fcc", "--size", "2", "--kn", "1e6", "--ks", "8e5", "--json",
            "--radius", "1", "--density", "1000"]
    code, out, err = run(base, capsys)
    assert code == 0, err
    plain = json.loads(out)
    code, out, err = run(base + ["--rolling-convention", "beta", "--rolling-stiffness", "2",
                                 "--twisting-stiffness", "1"], capsys)
    assert code == 0, err
    data = json.loads(out)
    assert exact_of(data) < 0.95 * exact_of(plain)
    assert data["damped"] is False
    assert any("rolling" in n for n in data["notes"])
    for q in data["critical_mode"]["contacts"]:
        assert q["k_r"] == pytest.approx(2 * 8e5 * 0.25) and q["k_w"] == pytest.approx(8e5 * 0.25)
    lat = lattice("fcc", 1.0)
    p = Particles.from_density(lat.block(2), np.ones(len(lat.block(2))), 1000.0)
    c = find_contacts(p, 1e6, 8e5)
    c = replace(c, k_r=2 * 8e5 * 0.25, k_w=8e5 * 0.25)
    assert exact_of(data) == pytest.approx(exact_critical_step(p, c, True).dt, rel=1e-9)


def test_cli_epsd_convention_with_viscous_part_on_a_file(tmp_path, capsys):
    """epsd: k_r = 2.25 k_n mu_r^2 R*^2 (k_w from mu_w); the viscous ratio gives
    c = 2 eta sqrt(I* k): the step is damped, below the undamped one, and equals the
    library's exact step on contacts built from the law's formula."""
    f = tmp_path / "a.csv"
    f.write_text("x,y,z,r\n0,0,0,1\n2,0,0,1\n4,0,0,1\n1,1.7320508075688772,0,1\n"
                 "1,0.5773502691896258,1.632993161855452,1\n")
    args = ["dt", str(f), "--kn", "100", "--density", "3", "--json", "--rolling-convention",
            "epsd", "--rolling-friction", "0.4", "--twisting-friction", "0.2",
            "--rolling-damping", "0.3"]
    code, out, err = run(args, capsys)
    assert code == 0, err
    data = json.loads(out)
    assert data["damped"] is True
    exact = exact_of(data)
    undamped = next(e["dt"] for e in data["estimates"] if e["method"] == "exact-undamped")
    assert exact < undamped
    x = np.loadtxt(f, delimiter=",", skiprows=1)
    p = Particles.from_density(x[:, :3], x[:, 3], 3.0)
    c = find_contacts(p, 100.0)
    r_star = 0.5
    i_star = float(rolling_inertia(p.inertia[0], p.m[0], 1.0, p.inertia[0], p.m[0], 1.0))
    from demstep.contact.laws import LinearSpring

    params = LinearSpring(k_n=100.0, rolling_convention="epsd", rolling_friction=0.4,
                          twisting_friction=0.2, rolling_damping=0.3).params()
    k_r, k_w, c_r, c_w = rolling_coefficients(params, 100.0, 100.0, r_star, i_star)
    assert k_r == pytest.approx(2.25 * 100 * 0.16 * 0.25)
    assert c_r == pytest.approx(2 * 0.3 * math.sqrt(i_star * k_r))
    c = replace(c, k_r=k_r, k_w=k_w, c_r=c_r, c_w=c_w)
    assert exact == pytest.approx(exact_critical_step(p, c, True).dt, rel=1e-9)
    for q in data["critical_mode"]["contacts"]:
        assert q["k_r"] == pytest.approx(k_r) and q["k_w"] == pytest.approx(k_w)
    # the table shows the rolling springs of the contacts
    code, out, err = run([a for a in args if a != "--json"], capsys)
    assert code == 0, err
    assert "k_r" in out and "k_w" in out


def test_cli_hertz_with_rolling(capsys):
    base = ["dt", "--lattice", "hex", "--size", "3", "--youngs", "1e7", "--poisson", "0.3",
            "--overlap", "0.01", "--json", "--methods", "exact,element-coupled,nodal"]
    code, out, err = run(base, capsys)
    assert code == 0, err
    plain = json.loads(out)
    code, out, err = run(base + ["--rolling-convention", "beta", "--rolling-stiffness", "3"],
                         capsys)
    assert code == 0, err
    data = json.loads(out)
    assert exact_of(data) < exact_of(plain)
    assert next(e for e in data["estimates"] if e["method"] == "element-coupled")["conservative"]


@pytest.mark.parametrize("argv,option,value", [
    (["--rolling-stiffness", "1.5"], "rolling-stiffness", "1.5"),
    (["--rolling-convention", "epsd"], "rolling-friction", "0.0"),
    (["--rolling-convention", "beta", "--rolling-friction", "0.3"], "rolling-stiffness", "0.0"),
    (["--rolling-convention", "beta", "--rolling-stiffness", "-2"], "rolling-stiffness", "-2"),
    (["--rolling-convention", "beta", "--rolling-stiffness", "nan"], "rolling-stiffness", "nan"),
    (["--rolling-convention", "spring", "--rolling-stiffness", "1"], "rolling-convention",
     "spring"),
    (["--rolling-convention", "beta", "--rolling-stiffness", "1", "--rolling-damping", "x"],
     "rolling-damping", "x"),
])
def test_cli_bad_rolling_input_is_one_line_exit_2(argv, option, value, capsys):
    """One line on stderr naming the option and the value, exit status 2."""
    code, out, err = run(["dt", "--lattice", "sc", "--size", "2"] + argv, capsys)
    assert code == 2
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1
    assert option in lines[0] and value in lines[0]


def test_cli_case_file_refuses_rolling_options(tmp_path, capsys):
    case = tmp_path / "c.toml"
    case.write_text("")  # never read: the option check comes first
    code, out, err = run(["dt", str(case), "--rolling-convention", "beta"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "--rolling-convention" in err and "case" in err


def test_cli_case_file_with_rolling_resistance(tmp_path, capsys):
    """A case whose [contact] has rolling resistance: `demstep dt case.toml` takes the
    law's rolling springs (beta: k_r = beta_r k_t R*^2, disks: no twisting) and its
    exact step drops below the same case without them."""
    from pathlib import Path

    text = (Path(__file__).parent.parent / "examples" / "hex_biaxial_2d.toml").read_text()
    text = text.replace("size = [10, 6]", "size = [3, 2]")
    plain = tmp_path / "plain.toml"
    plain.write_text(text)
    rolled = tmp_path / "rolled.toml"
    rolled.write_text(text.replace('restitution = 0.5', 'restitution = 0.5\n'
                                   'rolling_convention = "beta"\nrolling_stiffness = 3.0\n'
                                   'rolling_damping = 0.2'))
    code, out, err = run(["dt", str(plain), "--json"], capsys)
    assert code == 0, err
    base = json.loads(out)
    code, out, err = run(["dt", str(rolled), "--json"], capsys)
    assert code == 0, err
    data = json.loads(out)
    assert any("rolling" in n for n in data["notes"])
    assert exact_of(data) < exact_of(base)
    for q in data["critical_mode"]["contacts"]:
        r_star = 0.5 if q["j"] is not None else 1.0
        assert q["k_r"] == pytest.approx(3.0 * q["k_t"] * r_star**2)


def test_fixed_particle_counts_as_a_wall_in_the_rolling_inertia():
    """I* of a contact with a fixed particle is the moving side's I + m r^2 alone (the
    engine's convention), so its viscous rolling part is 2 eta sqrt(I* k_r); between two
    free particles of radii 0.2 and 0.3, the harmonic combination of both."""
    from demstep.analysis_input import ContactModel, from_particles

    x = np.array([[0.0, 0, 0], [0.5, 0, 0]])
    radii = np.array([0.2, 0.3])  # radii other than 1: m r^2 is no m r
    p0 = Particles.from_density(x, radii, 1.0)
    p = Particles(p0.x, p0.r, p0.m, p0.inertia, fixed=np.array([True, False]))
    model = ContactModel("linear", parameters={"k_n": 100.0}, rolling_convention="beta", rolling_stiffness=1.0,
                         rolling_damping=0.5)
    c = from_particles(p, model).contacts
    assert c.n == 1
    r_star = 0.2 * 0.3 / 0.5
    assert c.k_r[0] == pytest.approx(100.0 * r_star**2, rel=1e-14)
    i_star = p.inertia[1] + p.m[1] * 0.3**2
    assert c.c_r[0] == pytest.approx(2 * 0.5 * math.sqrt(i_star * c.k_r[0]), rel=1e-14)
    # both free: I* = 1 / (1/(I_i + m_i r_i^2) + 1/(I_j + m_j r_j^2))
    c = from_particles(p0, model).contacts
    a_i, a_j = p0.inertia[0] + p0.m[0] * 0.2**2, p0.inertia[1] + p0.m[1] * 0.3**2
    i_star = 1.0 / (1.0 / a_i + 1.0 / a_j)
    assert c.c_r[0] == pytest.approx(2 * 0.5 * math.sqrt(i_star * c.k_r[0]), rel=1e-14)


def test_laws_with_rolling_reach_the_analysis_from_a_case_law_and_a_simulation():
    """A case's law (ContactLaw with rolling fields) becomes the ContactModel of `demstep
    dt`; the contacts of a Simulation get the law's rolling springs from their tangent
    stiffnesses when the engine's contact set has none."""
    from demstep.engine import Simulation, TimeStep
    from demstep.analysis_input import from_particles, from_simulation, model_from_law

    law = LinearSpring(k_n=1e4, k_s=6e3, rolling_convention="beta", rolling_stiffness=0.5,
                       twisting_stiffness=0.2, rolling_damping=0.1)
    model = model_from_law(law)
    assert model.rolling_convention == "beta" and model.rolling_stiffness == 0.5
    x = np.array([[0.0, 0, 0], [2.0, 0, 0], [1.0, 1.6, 0]])
    p = Particles.from_density(x, np.array([1.0, 1.0, 0.9]), 1.0)
    data = from_particles(p, model, contact_tol=0.2)
    c = data.contacts
    r_star = p.r[c.i] * p.r[c.j] / (p.r[c.i] + p.r[c.j])
    np.testing.assert_allclose(c.k_r, 0.5 * 6e3 * r_star**2, rtol=1e-14)
    np.testing.assert_allclose(c.k_w, 0.2 * 6e3 * r_star**2, rtol=1e-14)
    i_star = rolling_inertia(p.inertia[c.i], p.m[c.i], p.r[c.i], p.inertia[c.j], p.m[c.j],
                             p.r[c.j])
    np.testing.assert_allclose(c.c_r, 2 * 0.1 * np.sqrt(i_star * c.k_r), rtol=1e-14)
    overlap = p.x.copy()
    overlap[1, 0] = 1.95
    sim = Simulation(Particles(overlap, p.r, p.m, p.inertia), law, timestep=TimeStep.fixed(1e-4))
    sim.run(steps=1)
    got = from_simulation(sim, "test").contacts
    assert got.n >= 1 and got.has_rolling
    r_star = p.r[got.i] * p.r[got.j] / (p.r[got.i] + p.r[got.j])
    np.testing.assert_allclose(got.k_r, 0.5 * got.k_s * r_star**2, rtol=1e-14)
