"""LAMMPS' pair granular as the certificate's springs and dashpots
(demstep.integrations.lammps_model), checked against what each formula means: the
tangent stiffness as the derivative of LAMMPS' force, Mindlin's ratio, the restitution
a Tsuji dashpot gives a linear spring, and the non-symmetric contact LAMMPS integrates
(its eigenvalues from a dense solver) against the certificate's symmetric arms."""

import math

import numpy as np
import pytest

from demstep.errors import InputError
from demstep.integrations.lammps_model import GranularModel, lammps_contacts, tsuji_alpha
from demstep.particles import Particles
from demstep.timestep.estimates import exact_dt

HERTZ = "hertz/material 5e7 0.2 0.3 tangential mindlin NULL 1.0 0.5"


def springs(text, r_star=0.25, m_star=100.0, delta=1e-3, wall=False):
    model = GranularModel.parse(text)
    out = model.springs(np.array([r_star]), np.array([m_star]), np.array([delta]), wall=wall)
    return {k: float(v[0]) for k, v in out.items()}


def test_the_normal_stiffness_is_the_derivative_of_lammps_force():
    """S_n = dF/d delta of F = 4/3 E* sqrt(R*) delta^(3/2) (hertz/material, E* of two
    equal materials) and F = kn sqrt(R* delta) delta (hertz), by finite differences."""
    e, nu, r_star, delta, h = 5e7, 0.3, 0.25, 1e-3, 1e-9
    e_star = 1.0 / (2.0 * (1.0 - nu**2) / e)
    force = lambda d: 4.0 / 3.0 * e_star * math.sqrt(r_star) * d**1.5  # noqa: E731
    slope = (force(delta + h) - force(delta - h)) / (2 * h)
    assert springs(HERTZ, r_star, 1.0, delta)["k_n"] == pytest.approx(slope, rel=1e-7)
    force = lambda d: 2e6 * math.sqrt(r_star * d) * d  # noqa: E731
    slope = (force(delta + h) - force(delta - h)) / (2 * h)
    assert springs("hertz 2e6 0 tangential linear_history 1e5 0 0.5", r_star, 1.0,
                   delta)["k_n"] == pytest.approx(slope, rel=1e-7)
    assert springs("hooke 3e5 0 tangential linear_history 1e5 0 0.5")["k_n"] == 3e5


def test_mindlin_null_has_mindlins_ratio_to_the_normal_stiffness():
    """k_t / k_n = 2 (1 - nu) / (2 - nu) for two spheres of one material (Mindlin)."""
    for nu in (0.2, 0.3, 0.45):
        s = springs(f"hertz/material 5e7 0.2 {nu} tangential mindlin NULL 1.0 0.5")
        assert s["k_s"] / s["k_n"] == pytest.approx(2 * (1 - nu) / (2 - nu), rel=1e-12)


def test_damping_models_scale_as_lammps_documents_them():
    a = math.sqrt(0.25 * 1e-3)
    base = "hooke 1e6 {eta} tangential linear_history 1e6 0.5 0.5 damping {model}"
    assert springs(base.format(eta=20.0, model="velocity"))["c_n"] == 20.0
    assert springs(base.format(eta=0.3, model="mass_velocity"))["c_n"] == pytest.approx(30.0)
    assert springs(base.format(eta=7.0, model="viscoelastic"))["c_n"] == pytest.approx(7 * a * 100)
    s = springs(base.format(eta=7.0, model="viscoelastic"))
    assert s["c_t"] == pytest.approx(0.5 * s["c_n"])  # xgammat: a ratio of gamma_n
    # the default damping is viscoelastic
    assert springs("hooke 1e6 7 tangential linear_history 1e6 1 0.5")["c_n"] == \
        pytest.approx(7 * a * 100)


def test_tsuji_on_a_linear_spring_gives_the_restitution_lammps_measured():
    """LAMMPS' tsuji with e = 0.5 on a hooke spring: a damping ratio alpha(e)/2, so a
    restitution of 0.58 (measured in LAMMPS: docs/validation-lammps.md)."""
    s = springs("hooke 1e6 0.5 tangential linear_history 1e6 0 0.5 damping tsuji", m_star=100.0)
    zeta = s["c_n"] / (2.0 * math.sqrt(100.0 * 1e6))
    assert zeta == pytest.approx(tsuji_alpha(0.5) / 2.0, rel=1e-12)
    restitution = math.exp(-math.pi * zeta / math.sqrt(1.0 - zeta**2))
    assert 0.575 < restitution < 0.585
    assert tsuji_alpha(1.0) == pytest.approx(0.0, abs=1e-3)  # elastic: no dashpot


def test_rolling_and_twisting_springs():
    a2 = 0.25 * 1e-3
    s = springs(HERTZ + " rolling sds 1e3 10 0.1 twisting marshall")
    assert s["k_r"] == pytest.approx(1e3 * 0.25**2)
    assert s["c_r"] == pytest.approx(10 * 0.25**2)
    assert s["k_w"] == pytest.approx(0.5 * s["k_s"] * a2)
    assert s["c_w"] == pytest.approx(0.5 * s["c_t"] * a2)
    s = springs(HERTZ + " twisting sds 3 2 0.1")
    assert (s["k_w"], s["c_w"], s["k_r"]) == (3.0, 2.0, 0.0)


def test_wall_constants_of_this_lammps_release():
    """fix wall/gran's hertz/material coefficient 4/3 E / (2 (1 - nu)) and mindlin NULL
    E (2 - nu)(1 + nu) / 4 x a (not the pair style's)."""
    e, nu, r, delta = 5e7, 0.3, 0.5, 1e-3
    a = math.sqrt(r * delta)
    s = springs(HERTZ, r, 1.0, delta, wall=True)
    assert s["k_n"] == pytest.approx(1.5 * 4.0 / 3.0 * e / (2 * (1 - nu)) * a)
    assert s["k_s"] == pytest.approx(e * (2 - nu) * (1 + nu) / 4.0 * a)


@pytest.mark.parametrize("text, named", [
    ("jkr 5e7 0.2 0.3 1.0 tangential linear_history 1e6 0 0.5", "jkr"),
    ("hooke 1e6 0 tangential mindlin_rescale 1e6 0 0.5", "mindlin_rescale"),
    ("hooke 1e6 0 tangential linear_history_classic 1e6 0 0.5", "linear_history_classic"),
    ("hooke 1e6 0 tangential mindlin NULL 0 0.5", "hertz/material"),
    ("hooke 1e6 0", "tangential"),
    ("hooke 1e6 0 tangential linear_history 1e6 0 0.5 damping coulomb", "coulomb"),
    ("hooke 1e6 0 tangential linear_history 1e6 0 0.5 rolling nohistory", "nohistory"),
    ("hooke 1e6 0 tangential linear_history 1e6 0 0.5 synchronized_verlet", "synchronized_verlet"),
    ("hooke abc 0 tangential linear_history 1e6 0 0.5", "abc"),
    ("hooke -1 0 tangential linear_history 1e6 0 0.5", "-1"),
    ("hertz/material 5e7 0.2 0.7 tangential linear_history 1e6 0 0.5", "0.7"),
    ("hooke 1e6 1.5 tangential linear_history 1e6 0 0.5 damping tsuji", "1.5"),
    ("hooke 1e6 0 tangential linear_history 1e6", "3 value"),
])
def test_what_the_certificate_does_not_cover_is_refused_by_name(text, named):
    with pytest.raises(InputError) as err:
        GranularModel.parse(text)
    assert named in str(err.value)
    assert "\n" not in str(err.value)


def test_one_contact_of_lammps_has_the_top_eigenvalue_of_the_geometric_mean_arms():
    """LAMMPS' slip velocity takes the radii r, its torques the arm r - delta/2: a
    non-symmetric stiffness. Built here dof by dof (two spheres, 12 dofs), its
    eigenvalues (dense, non-symmetric) against the certificate's exact step with the
    arms sqrt(r (r - delta/2))."""
    r = np.array([0.5, 0.3])
    m = 2500 * 4 / 3 * np.pi * r**3
    inertia = 0.4 * m * r**2
    delta = 0.02
    x = np.array([[0.0, 0.0, 0.0], [r.sum() - delta, 0.0, 0.0]])
    k_n, k_t = 1e6, 7e5
    model = GranularModel.parse(f"hooke {k_n} 0 tangential linear_history {k_t} 0 0.5")
    particles = Particles(x, r, m, inertia)
    contacts = lammps_contacts(particles, model)
    assert contacts.n == 1
    dt = exact_dt(particles, contacts, True)

    n = np.array([1.0, 0.0, 0.0])  # i -> j

    def cross(v):
        return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])

    # relative displacement of j's contact point w.r.t. i's, dofs (u_i, th_i, u_j, th_j):
    # slip: arms r; torques: arms r - delta/2 (as LAMMPS)
    def strain(arm_i, arm_j):
        b = np.zeros((3, 12))
        b[:, 0:3] = -np.eye(3)
        b[:, 3:6] = cross(arm_i * n)  # -(theta_i x arm n) = (arm n) x theta_i
        b[:, 6:9] = np.eye(3)
        b[:, 9:12] = cross(arm_j * n)  # theta_j x (-arm n)
        return b

    stiff = k_n * np.outer(n, n) + k_t * (np.eye(3) - np.outer(n, n))
    b_slip = strain(r[0], r[1])
    b_torque = strain(r[0] - delta / 2, r[1] - delta / 2)
    k = b_torque.T @ stiff @ b_slip
    assert not np.allclose(k, k.T)  # LAMMPS' contact is not symmetric
    mass = np.repeat([m[0], inertia[0], m[1], inertia[1]], 3)
    lam = np.linalg.eigvals(k / mass[:, None])
    assert np.abs(lam.imag).max() < 1e-9 * np.abs(lam.real).max()
    assert dt == pytest.approx(2.0 / math.sqrt(lam.real.max()), rel=1e-9)
    # the radii alone (demstep's other conventions) would not be it
    k_full = b_slip.T @ stiff @ b_slip
    lam_full = np.linalg.eigvals(k_full / mass[:, None]).real.max()
    assert abs(2.0 / math.sqrt(lam_full) / dt - 1.0) > 1e-4


def test_walls_take_the_full_radius_and_the_particles_mass():
    from demstep.walls import Wall

    r, m = np.array([0.5]), np.array([100.0])
    particles = Particles(np.array([[0.0, 0.0, 0.49]]), r, m, 0.4 * m * r**2)
    model = GranularModel.parse("hooke 1e6 0.1 tangential linear_history 1e6 1 0.5 "
                                "damping mass_velocity")
    c = lammps_contacts(particles, model, walls=[Wall([0, 0, 0], [0, 0, 1])])
    assert c.n == 1 and c.j[0] == -1
    assert c.arm_i[0] == 0.5 and c.c_n[0] == pytest.approx(0.1 * 100.0)
    assert np.allclose(c.normal[0], [0, 0, -1])


# ---------------------------------------------------------------- against LAMMPS itself
ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]
THRESHOLDS = ROOT / "validation" / "results" / "lammps_thresholds.json"


def _measured_cases():
    import json

    if not THRESHOLDS.exists():
        return []
    cases = json.loads(THRESHOLDS.read_text())["cases"]
    return sorted(name for name, c in cases.items() if c.get("threshold"))


@pytest.mark.parametrize("name", _measured_cases())
def test_the_exact_step_is_never_above_lammps_measured_threshold(name):
    """On every state whose threshold LAMMPS' own runs measured by bisection
    (validation/lammps_thresholds.py: periodic FCC at two overlaps, jammed polydisperse,
    a slab between fix wall/gran planes; linear and Hertz; the four dampings; rotation
    free and locked), the exact step of --lammps-model with the same pair_coeff text
    lies at most at the top of LAMMPS' bracket and at most 0.5 % below it, and the
    coupled element bound below it."""
    import ast
    import json
    import sys

    from demstep.analysis_input import from_file
    from demstep.timestep.estimates import element_coupled_dt

    sys.path.insert(0, str(ROOT / "validation"))
    from lammps_thresholds import pair_lines

    case = json.loads(THRESHOLDS.read_text())["cases"][name]
    p = case["parameters"]
    p = ast.literal_eval(p) if isinstance(p, str) else p
    text = pair_lines(p)[1].split("* *", 1)[1]
    walls = ["z-", "z+"] if case["state"].startswith("slab") else ()
    data = from_file(ROOT / case["dump"] if not case["dump"].startswith("/") else case["dump"],
                     None, lammps_model=GranularModel.parse(text), walls=walls)
    dt = exact_dt(data.particles, data.contacts, case["rotation"])
    low, high = case["threshold"]["bracket"]
    assert dt <= high
    assert dt >= 0.995 * low
    assert element_coupled_dt(data.particles, data.contacts, case["rotation"]) < dt


# ---------------------------------------------------------------- LAMMPS data files
DATA = """LAMMPS data file via write_data, version 29 Sep 2021

3 atoms
1 atom types

0 10 xlo xhi
-1 1 ylo yhi
0.0 2.0e+00 zlo zhi

Atoms # sphere

3 1 1.0 2000.0 9.5 0.0 1.0 -1 0 0
1 1 1.2 2500.0 1.0 0.0 1.0 0 0 0
2 2 0.8 2500.0 2.0 0.5 1.0 0 0 1

Velocities

1 0.1 0 0 0 0 1
2 0 0 0 0 0 0
3 0 0.2 0 0 0 0
"""


def test_a_lammps_data_file_of_atom_style_sphere(tmp_path):
    from demstep.io.formats import read_particle_file

    path = tmp_path / "state.data"
    path.write_text(DATA)
    d = read_particle_file(path)  # (recognised by its 'N atoms' header)
    assert d.ids.tolist() == [1, 2, 3] and d.types.tolist() == [1, 2, 1]
    assert np.allclose(d.r, [0.6, 0.4, 0.5])
    assert np.allclose(d.m, [2500 * np.pi / 6 * 1.2**3, 2500 * np.pi / 6 * 0.8**3,
                             2000 * np.pi / 6])
    # image flags unwrap with the box lengths
    assert np.allclose(d.x, [[1.0, 0.0, 1.0], [2.0, 0.5, 3.0], [-0.5, 0.0, 1.0]])
    assert np.allclose(d.v[2], [0, 0.2, 0]) and np.allclose(d.w[0], [0, 0, 1])
    assert np.allclose(d.box, [[0, 10], [-1, 1], [0, 2]])


@pytest.mark.parametrize("change, named", [
    (("Atoms # sphere", "Atoms # atomic"), "atomic"),
    (("0 10 xlo xhi\n", ""), "xlo xhi"),
    (("3 1 1.0 2000.0", "2 1 1.0 2000.0"), "id 2"),
    (("1 1 1.2 2500.0", "1 1 0 2500.0"), "diameter"),
    (("1 1 1.2 2500.0 1.0 0.0 1.0 0 0 0", "1 1 1.2 2500.0 1.0 0.0"), "Atoms (sphere)"),
    (("3 0 0.2 0 0 0 0\n", ""), "atom id 3"),
])
def test_bad_lammps_data_files_are_refused_in_one_line(tmp_path, change, named):
    from demstep.io.formats import read_particle_file

    path = tmp_path / "bad.data"
    path.write_text(DATA.replace(*change))
    with pytest.raises(InputError) as err:
        read_particle_file(path)
    assert named in str(err.value) and "\n" not in str(err.value)


def test_the_live_step_stays_in_its_band_without_going_back_and_forth():
    """LammpsCertifier.apply keeps LAMMPS' step within [safety / (1 + grow)^2, safety]
    times the certified one: a step above is lowered at once and a step far below
    raised, both to the band's middle; a step just set is left alone by the next checks
    of the same certificate (no back and forth), and moves again only when the
    certificate does (here without LAMMPS: the instance and the certificates are
    stand-ins)."""
    from demstep.integrations.lammps import Certificate, LammpsCertifier

    class Instance:
        def __init__(self, dt):
            self.dt, self.commands = dt, []

        def command(self, text):
            self.commands.append(text)
            self.dt = float(text.split()[1])

    lmp = Instance(0.9)
    cert = object.__new__(LammpsCertifier)
    cert.lmp, cert.safety, cert.grow, cert.history, cert.log = lmp, 0.8, 0.05, [], [].append
    certified = [1.0]
    cert.certify = lambda: Certificate(0, certified[0], "exact", lmp.dt, 10, 0.01, 0.0)
    middle = 0.8 / 1.05
    cert.apply()
    assert lmp.dt == pytest.approx(middle)  # lowered at once
    for _ in range(5):
        assert cert.apply().dt_set is None  # the same certificate: left alone
    assert len(lmp.commands) == 1
    certified[0] = 1.04  # (within the band: the step set is still allowed)
    assert cert.apply().dt_set is None
    certified[0] = 1.2  # the band's bottom 0.8 x 1.2 / 1.1025 = 0.871 > 0.762: raised
    cert.apply()
    assert lmp.dt == pytest.approx(1.2 * middle)
    assert cert.apply().dt_set is None
    certified[0] = 1.1  # top 0.88 < 0.914: lowered at once
    cert.apply()
    assert lmp.dt == pytest.approx(1.1 * middle)
    assert all(c.reason for c in cert.history if c.dt_set is not None)
