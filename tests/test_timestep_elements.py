"""Contact element matrices: the paper's (eqs. 6-21) and the coupled formulation."""

import numpy as np
import pytest

from demstep.contact.geometry import tangent_basis
from demstep.timestep.contacts import ContactSet
from demstep.timestep.elements import (
    coupled_element_lambda, coupled_element_matrices, coupled_strain_operator,
    element_lambda_numeric, paper_element_lambda, paper_element_matrices,
    paper_effective_radii, paper_element_mass, paper_local_stiffness, paper_transformation,
)
from demstep.timestep.mass_split import ElementMass

from conftest import random_unit


def random_contacts(rng, dim, c=40, walls=True):
    n = random_unit(rng, c, dim)
    arm_i = rng.uniform(0.3, 2.0, c)
    arm_j = rng.uniform(0.3, 2.0, c)
    j = np.arange(c) + c
    if walls:
        j[::5] = -1
        arm_j[::5] = 0.0
    k_n = rng.uniform(0.5, 3.0, c)
    k_s = rng.uniform(0.1, 3.0, c)
    cs = ContactSet(np.arange(c), j, n, arm_i, arm_j, k_n, k_s)
    mass = ElementMass(rng.uniform(0.2, 2, c), np.where(j < 0, 0.0, rng.uniform(0.2, 2, c)),
                       rng.uniform(0.2, 5, c), np.where(j < 0, 0.0, rng.uniform(0.2, 5, c)))
    return cs, mass


@pytest.mark.parametrize("dim", [2, 3])
def test_transformation_is_orthogonal(rng, dim):
    cs, _ = random_contacts(rng, dim)
    for rotation in (False, True):
        T = paper_transformation(cs.normal, rotation)
        eye = np.broadcast_to(np.eye(T.shape[1]), T.shape)
        assert np.allclose(T @ T.transpose(0, 2, 1), eye, atol=1e-14)


def test_2d_transformation_is_eq_8():
    theta = 0.37
    n = np.array([[np.cos(theta), np.sin(theta)]])
    c, s = np.cos(theta), np.sin(theta)
    eq8 = np.array([[c, s, 0, 0], [-s, c, 0, 0], [0, 0, c, s], [0, 0, -s, c]])
    assert np.allclose(paper_transformation(n, False)[0], eq8)
    eq10 = np.zeros((6, 6))
    eq10[np.ix_([0, 1, 3, 4], [0, 1, 3, 4])] = eq8
    eq10[2, 2] = eq10[5, 5] = 1.0
    assert np.allclose(paper_transformation(n, True)[0], eq10)


def test_eq6_local_stiffness_by_hand():
    kn, ks = 3.0, 2.0
    K = paper_local_stiffness(np.array([kn]), np.array([ks]), dim=2)[0]
    expected = np.array([[kn, 0, -kn, 0], [0, ks, 0, -ks], [-kn, 0, kn, 0], [0, -ks, 0, ks]])
    assert np.array_equal(K, expected)


@pytest.mark.parametrize("dim", [2, 3])
def test_paper_global_translation_stiffness_is_strut(rng, dim):
    """T^T K_local T equals the strut stiffness written in global axes:
    [[S, -S], [-S, S]] with S = K_n n n^T + K_s (I - n n^T)."""
    cs, mass = random_contacts(rng, dim)
    K, _ = paper_element_matrices(cs, mass, rotation=False)
    for c in range(cs.n):
        n = cs.normal[c]
        S = cs.k_n[c] * np.outer(n, n) + cs.k_s[c] * (np.eye(dim) - np.outer(n, n))
        assert np.allclose(K[c], np.block([[S, -S], [-S, S]]), atol=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_paper_similarity_eqs_20_21(rng, dim):
    """eig(M^-1 K_global) = eig(M^-1 K_local) because M_e is diagonal and T orthogonal."""
    cs, mass = random_contacts(rng, dim, walls=False)
    mass.inv_m_j[:] = mass.inv_m_i  # the paper's uniform elements: equal ends
    mass.inv_I_j[:] = mass.inv_I_i
    for rotation in (False, True):
        Kg, M = paper_element_matrices(cs, mass, rotation)
        ri = paper_effective_radii(cs.normal, cs.arm_i) if rotation else None
        rj = paper_effective_radii(cs.normal, cs.arm_j) if rotation else None
        Kl = paper_local_stiffness(cs.k_n, cs.k_s, ri, rj, dim=dim)
        for c in range(cs.n):
            a = np.sort(np.linalg.eigvals(Kg[c] / M[c][:, None]).real)
            b = np.sort(np.linalg.eigvals(Kl[c] / M[c][:, None]).real)
            assert np.allclose(a, b, atol=1e-9 * abs(b).max())


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("rotation", [False, True])
def test_paper_closed_form_lambda_matches_eigensolver(rng, dim, rotation):
    cs, mass = random_contacts(rng, dim)
    K, M = paper_element_matrices(cs, mass, rotation)
    assert np.allclose(paper_element_lambda(cs, mass, rotation), element_lambda_numeric(K, M),
                       rtol=1e-10)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("rotation", [False, True])
def test_coupled_closed_form_lambda_matches_eigensolver(rng, dim, rotation):
    cs, mass = random_contacts(rng, dim)
    K, M = coupled_element_matrices(cs, mass, rotation)
    assert np.allclose(coupled_element_lambda(cs, mass, rotation), element_lambda_numeric(K, M),
                       rtol=1e-10)


@pytest.mark.parametrize("dim", [2, 3])
def test_coupled_operator_gives_contact_point_slip(rng, dim):
    """B maps DOFs to Delta = u_j - u_i - (a_i th_i + a_j th_j) x n, evaluated directly."""
    cs, _ = random_contacts(rng, dim, walls=False)
    Bi, Bj = coupled_strain_operator(cs.normal, cs.arm_i, cs.arm_j, True)
    nr = 1 if dim == 2 else 3
    for c in range(cs.n):
        qi = rng.standard_normal(dim + nr)
        qj = rng.standard_normal(dim + nr)
        n = cs.normal[c]
        w = cs.arm_i[c] * qi[dim:] + cs.arm_j[c] * qj[dim:]
        if dim == 2:
            w_cross_n = w[0] * np.array([-n[1], n[0]])
        else:
            w_cross_n = np.cross(w, n)
        delta = qj[:dim] - qi[:dim] - w_cross_n
        local = Bi[c] @ qi + Bj[c] @ qj
        assert np.isclose(local[0], delta @ n)  # normal component
        R = tangent_basis(n[None])[0]
        assert np.allclose(local, R @ delta)  # every component in the local frame
        tang = delta - (delta @ n) * n  # the slip P delta, whatever the tangent basis
        assert np.isclose(np.linalg.norm(local[1:]), np.linalg.norm(tang))


def test_coupled_2d_local_matrix_by_hand():
    """T^T K_local T for the coupled 2D element equals B^T D B, with K_local written by
    hand from the slip s = v_j - v_i - a_i th_i - a_j th_j."""
    kn, ks, ai, aj = 2.0, 0.7, 1.3, 0.6
    theta = 1.1
    n = np.array([[np.cos(theta), np.sin(theta)]])
    cs = ContactSet([0], [1], n, [ai], [aj], kn, ks)
    mass = ElementMass(np.ones(1), np.ones(1), np.ones(1), np.ones(1))
    Kg, _ = coupled_element_matrices(cs, mass, True)
    b_s = np.array([0, -1, -ai, 0, 1, -aj])  # shear row over (u, v, th)_i, (u, v, th)_j
    b_n = np.array([-1, 0, 0, 1, 0, 0])
    K_local = kn * np.outer(b_n, b_n) + ks * np.outer(b_s, b_s)
    T = paper_transformation(n, True)[0]
    assert np.allclose(T.T @ K_local @ T, Kg[0], atol=1e-13)


def _eigenvalues(K, M_diag):
    """Sorted eigenvalues of M^-1 K for one element."""
    return np.sort(np.linalg.eigvals(K / M_diag[:, None]).real)


def _random_rotation(rng, dim):
    q, r = np.linalg.qr(rng.standard_normal((dim, dim)))
    return q * np.sign(np.diag(r))


@pytest.mark.parametrize("dim", [2, 3])
def test_eqs_20_21_rotation_and_rotation_sign_keep_eigenvalues(rng, dim):
    """Eqs. 20-21 with transformations that are not sign flips. The local element (the
    physical +K_s r_i r_j coupling of the rotations, built here by hand), the
    published one in global axes (T^T K T, -K_s r_i r_j) and that element turned by a
    further random rotation of the axes all have the eigenvalues of M^-1 K, with
    different masses at the two ends: M is isotropic per particle, so it commutes with
    rotations acting on each particle's translations. With a mass that is not
    isotropic the rotation changes the eigenvalues: the comparison can fail."""
    cs, mass = random_contacts(rng, dim, walls=False)
    assert not np.allclose(mass.inv_m_i, mass.inv_m_j)  # unequal ends
    K_global, M = paper_element_matrices(cs, mass, True)
    ri, rj = paper_effective_radii(cs.normal, cs.arm_i), paper_effective_radii(cs.normal, cs.arm_j)
    n_rot = ri.shape[1]
    nd = dim + n_rot
    checked = 0
    for c in range(cs.n):
        # the local element by hand: springs along (n, t[, t2]), rotational springs
        # K_s r^2 with the physical + coupling
        K_local = np.zeros((2 * nd, 2 * nd))
        for a in range(dim):
            k = cs.k_n[c] if a == 0 else cs.k_s[c]
            K_local[np.ix_([a, nd + a], [a, nd + a])] += k * np.array([[1, -1], [-1, 1]])
        for q in range(n_rot):
            a, b = dim + q, nd + dim + q
            ra, rb = ri[c, q], rj[c, q]
            K_local[np.ix_([a, b], [a, b])] += cs.k_s[c] * np.array([[ra * ra, ra * rb],
                                                                     [ra * rb, rb * rb]])
        Q = np.eye(2 * nd)
        R = _random_rotation(rng, dim)
        Q[:dim, :dim] = Q[nd:nd + dim, nd:nd + dim] = R
        K_turned = Q.T @ K_global[c] @ Q
        assert not np.allclose(K_turned, K_global[c])  # a transformation that does something
        expected = _eigenvalues(K_local, M[c])
        scale = abs(expected).max()
        for K in (K_global[c], K_turned):
            assert np.allclose(_eigenvalues(K, M[c]), expected, atol=1e-9 * scale)
        anisotropic = M[c].copy()
        anisotropic[0] *= 3.0  # m_x != m_y of particle i
        if not np.allclose(_eigenvalues(K_turned, anisotropic),
                           _eigenvalues(K_local, anisotropic), atol=1e-6 * scale):
            checked += 1
    assert checked > cs.n // 2


def test_paper_effective_radius_rhombic_upper_row():
    """Paper Fig. 4: rotation about the vertical axis, rhombic packing: r_eff = r for the
    in-plane contacts and r/sqrt(3) for the upper row."""
    r = 2.0
    layer = 2 * r * np.sqrt(2 / 3)
    upper = np.array([r, r / np.sqrt(3), layer])
    n = np.array([[1.0, 0, 0], upper / np.linalg.norm(upper)])
    reff = paper_effective_radii(n, np.array([r, r]))
    assert np.isclose(reff[0, 2], r)
    assert np.isclose(reff[1, 2], r / np.sqrt(3))


def test_element_mass_diagonal_is_eq_19():
    mass = ElementMass(np.array([1 / 2.0]), np.array([1 / 3.0]), np.array([1 / 5.0]),
                       np.array([1 / 7.0]))
    assert np.allclose(paper_element_mass(mass, 3, True)[0],
                       [2, 2, 2, 5, 5, 5, 3, 3, 3, 7, 7, 7])
    assert np.allclose(paper_element_mass(mass, 2, False)[0], [2, 2, 3, 3])


def test_optional_contact_fields_keep_shape_checks_and_do_not_alias_input():
    """Optional per-contact fields: an all-zero array is replaced by fresh zeros, but a
    wrong length is still an error, and a given array is copied, never shared."""
    n = np.array([[1.0, 0.0], [0.0, 1.0], [0.6, 0.8]])
    args = ([0, 1, 2], [1, 2, 3], n, [1.0] * 3, [1.0] * 3, 1.0, 1.0)
    with pytest.raises(ValueError):
        ContactSet(*args, c_n=np.zeros(2))
    given = np.array([0.0, 0.5, 0.0])
    zeros = np.zeros(3)
    cs = ContactSet(*args, c_n=given, k_r=zeros, c_w=0.25)
    given[1] = 7.0
    zeros[0] = 7.0
    assert cs.c_n.tolist() == [0.0, 0.5, 0.0]
    assert cs.k_r.tolist() == [0.0, 0.0, 0.0]
    assert cs.c_w.tolist() == [0.25] * 3
    assert cs.damped and not ContactSet(*args, c_t=zeros * 0).damped
