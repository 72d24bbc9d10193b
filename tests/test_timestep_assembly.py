"""Global sparse K and M, exact eigenvalues against dense references, Bloch waves."""

import numpy as np
import pytest
import scipy.linalg

from demstep.timestep.contacts import find_contacts
from demstep.packings import lattice
from demstep.particles import Particles
from demstep.timestep.assembly import (
    assemble_stiffness, inverse_sqrt_mass, lumped_mass, scaled_stiffness, stiffness_diagonal,
)
from demstep.timestep.bloch import DynamicalMatrix
from demstep.timestep.eigen import lambda_max
from demstep.timestep.elements import coupled_element_matrices, dofs_per_particle
from demstep.timestep.estimates import exact_dt
from demstep.timestep.mass_split import element_mass

from conftest import random_polydisperse


def dense_stiffness(particles, contacts, rotation):
    """Slow reference: scatter every element matrix into a dense K."""
    nd = dofs_per_particle(particles.dim, rotation)
    K = np.zeros((particles.n * nd, particles.n * nd))
    Ke, _ = coupled_element_matrices(contacts, element_mass(particles, contacts), rotation)
    for c in range(contacts.n):
        i, j = contacts.i[c], contacts.j[c]
        di = np.arange(i * nd, (i + 1) * nd)
        K[np.ix_(di, di)] += Ke[c][:nd, :nd]
        if j >= 0:
            dj = np.arange(j * nd, (j + 1) * nd)
            K[np.ix_(di, dj)] += Ke[c][:nd, nd:]
            K[np.ix_(dj, di)] += Ke[c][nd:, :nd]
            K[np.ix_(dj, dj)] += Ke[c][nd:, nd:]
    return K


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("rotation", [False, True])
def test_sparse_stiffness_equals_dense_scatter(dim, rotation):
    p, c = random_polydisperse(3 + dim, dim, n=27, walls=True)
    K = assemble_stiffness(p, c, rotation).toarray()
    assert np.allclose(K, dense_stiffness(p, c, rotation), rtol=1e-12, atol=1e-12)
    assert np.allclose(K, K.T)
    assert np.allclose(stiffness_diagonal(p, c, rotation), np.diag(K), rtol=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_rigid_body_motions_are_zero_modes(dim, rng):
    """A rigid translation and a rigid rotation of a free assembly store no energy."""
    p, c = random_polydisperse(11, dim, n=27)
    K = assemble_stiffness(p, c, True).toarray()
    nd = dofs_per_particle(dim, True)
    q = np.zeros((p.n, nd))
    q[:, :dim] = rng.standard_normal(dim)
    assert np.abs(K @ q.reshape(-1)).max() < 1e-12 * np.abs(K).max()
    omega = rng.standard_normal(1 if dim == 2 else 3)
    q = np.zeros((p.n, nd))
    if dim == 2:
        q[:, 0] = -omega[0] * p.x[:, 1]
        q[:, 1] = omega[0] * p.x[:, 0]
    else:
        q[:, :3] = np.cross(omega, p.x)
    q[:, dim:] = omega
    assert np.abs(K @ q.reshape(-1)).max() < 1e-10 * np.abs(K).max() * np.abs(p.x).max()


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("rotation", [False, True])
def test_sparse_eigensolver_equals_dense_eigh(dim, rotation):
    p, c = random_polydisperse(5 * dim, dim, n=64, walls=True, fixed=True)
    A = scaled_stiffness(p, c, rotation)
    dense = scipy.linalg.eigh(A.toarray(), eigvals_only=True)[-1]
    sparse = lambda_max(A, dense_limit=0)  # force ARPACK
    assert sparse == pytest.approx(dense, rel=1e-9)
    # and the generalised problem K x = lambda M x, fixed particles' DOFs removed
    nd = dofs_per_particle(dim, rotation)
    free = np.repeat(~p.fixed, nd)
    K = assemble_stiffness(p, c, rotation).toarray()[np.ix_(free, free)]
    M = np.diag(lumped_mass(p, rotation)[free])
    assert dense == pytest.approx(scipy.linalg.eigh(K, M, eigvals_only=True)[-1], rel=1e-10)


def test_single_spring_against_wall_gives_2_sqrt_m_over_k():
    from demstep.walls import Wall

    m, k = 3.0, 7.0
    p = Particles(np.array([[0.0, 1.0]]), np.array([1.0]), np.array([m]), np.array([1.0]))
    c = find_contacts(p, k, k, walls=[Wall([0.0, 0.0], [0.0, 1.0])])
    assert c.n == 1
    assert exact_dt(p, c, rotation=False) == pytest.approx(2 * np.sqrt(m / k), rel=1e-12)


def test_two_body_spring_gives_2_sqrt_meff_over_k():
    m1, m2, k = 2.0, 5.0, 3.0
    p = Particles(np.array([[0.0, 0, 0], [2.0, 0, 0]]), np.array([1.0, 1.0]),
                  np.array([m1, m2]), np.array([1.0, 1.0]))
    c = find_contacts(p, k, 0.0)
    m_eff = m1 * m2 / (m1 + m2)
    assert exact_dt(p, c, rotation=False) == pytest.approx(2 * np.sqrt(m_eff / k), rel=1e-12)


@pytest.mark.parametrize("name", ["square", "hex", "sc", "bcc", "fcc", "rhombic"])
@pytest.mark.parametrize("rotation", [False, True])
def test_bloch_equals_periodic_supercell(name, rotation):
    """The supercell's eigenvalues are the Bloch eigenvalues at the commensurate k."""
    lat = lattice(name, 1.0)
    size = 3
    x, box = lat.supercell(size)
    p = Particles.from_density(x, np.full(len(x), 1.0), 1.0)
    c = find_contacts(p, 1.0, 0.6, periodic=box)
    assert np.all(c.count_per_particle(p.n) == lat.coordination)
    super_eigs = np.sort(scipy.linalg.eigh(scaled_stiffness(p, c, rotation).toarray(),
                                           eigvals_only=True))
    dm = DynamicalMatrix(lat, 1.0, 0.6, 1.0, rotation)
    ks = np.stack(np.meshgrid(*[np.arange(size) / size] * lat.dim, indexing="ij"), -1)
    bloch_eigs = np.sort(np.linalg.eigvalsh(dm(ks.reshape(-1, lat.dim))).reshape(-1))
    assert np.allclose(super_eigs, bloch_eigs, atol=1e-9 * super_eigs.max())
    lam_inf, _ = dm.lambda_max()
    assert lam_inf >= super_eigs.max() * (1 - 1e-12)


@pytest.mark.parametrize("name,expected", [("square", 8.0), ("fcc", 16.0), ("sc", 12.0),
                                           ("bcc", 16.0)])
def test_bloch_translation_only_analytic(name, expected):
    """With K_n = K_s the lattice is isotropic: D(k) = K sum_R (1 - cos k.R) I, whose
    maximum over k is 2 x (number of neighbours reaching phase pi): square 8, sc 12,
    bcc 16 (all 8 at k=(2pi/a)(1,0,0)... in bcc the H point), fcc 16 (X point)."""
    lat = lattice(name, 1.0)
    dm = DynamicalMatrix(lat, 1.0, 1.0, 1.0, False)
    lam, _ = dm.lambda_max()
    assert lam * dm.mass == pytest.approx(expected, rel=1e-9)


def test_inverse_sqrt_mass_zero_on_fixed():
    p, _ = random_polydisperse(2, 3, n=8, fixed=True)
    s = inverse_sqrt_mass(p, True).reshape(p.n, 6)
    assert np.all(s[p.fixed] == 0) and np.all(s[~p.fixed] > 0)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("rotation", [True, False])
def test_inverse_sqrt_mass_is_the_lumped_mass_to_the_minus_half(dim, rotation):
    """Per DOF 1 / sqrt of the lumped mass (masses on translations, inertias on
    rotations), zero on the fixed particles; written into a given array alike."""
    p, _ = random_polydisperse(3, dim, n=12, fixed=True)
    expect = 1.0 / np.sqrt(lumped_mass(p, rotation))
    nd = len(expect) // p.n
    expect[np.repeat(p.fixed, nd)] = 0.0
    np.testing.assert_array_equal(inverse_sqrt_mass(p, rotation), expect)
    out = np.full(len(expect), np.nan)
    assert inverse_sqrt_mass(p, rotation, out) is out
    np.testing.assert_array_equal(out, expect)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("tol", [0.0, 1e-6, 0.05])
def test_compiled_contact_search_finds_the_k_d_trees_contacts(dim, tol):
    """Large assemblies search their contacts with the engine's cell list instead of
    scipy's k-d tree: the same contacts in the same order, for touching lattice
    neighbours (tol 0: a distance exactly r_i + r_j) and polydisperse gaps within tol."""
    from demstep.timestep.contacts import _pair_contacts
    from demstep.packings import jittered_polydisperse

    for x, r in ((lattice("fcc" if dim == 3 else "hex", 0.5).block(6), None),
                 jittered_polydisperse(400, dim, seed=3, jitter=0.08, spread=0.3,
                                       overlap=0.0)):
        r = np.full(len(x), 0.5) if r is None else r
        tree = _pair_contacts(x, r, tol, None, compiled_min=len(x) + 1)
        cells = _pair_contacts(x, r, tol, None, compiled_min=0)
        assert tree.n > 0
        for field in ("i", "j", "normal", "arm_i", "arm_j"):
            np.testing.assert_array_equal(getattr(cells, field), getattr(tree, field),
                                          err_msg=field)
