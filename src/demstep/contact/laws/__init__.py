"""Contact laws: each law one module of this package, found by the registry; and the
generic contact functions the kernels call, resolved for the law being compiled.

The laws (each module's docstring gives its formulas):

* ``linear`` (:class:`LinearSpring`): F_n = K_n delta_n, tangential spring K_s;
* ``hertz`` (:class:`HertzMindlin`): Hertz normal force, Mindlin no-slip tangent
  stiffness, of one material;
* ``cohesive`` (:class:`CohesiveLinear`): F_n = K_n delta_n - f_c, a linear spring with a
  constant attraction while the particles touch.

Every module of this package but ``base`` is imported here, so its law registers
itself (:func:`~demstep.contact.laws.base.register`): a new law is a new module, nothing
else. The generic functions below (:func:`normal_force`, :func:`tangential_stiffness`,
:func:`coulomb_load`, :func:`dashpot_coefficients`, :func:`rolling_coefficients`,
:func:`needs_r_star`, and the array version :func:`contact_coefficients`) take a law's
parameter tuple: numba resolves them for its type when it compiles a kernel (one
compiled step per law, no branch on the law inside), and plain Python (the
``NUMBA_DISABLE_JIT`` runs, Python callers) looks the law up by the tuple's type.

The tangential spring is incremental: dF_t = -k_t du_t, rotated with the contact plane,
limited by Coulomb |F_t| <= mu N (N the law's :func:`coulomb_load`). Dashpots: F = -c
v_rel on the normal and tangential relative velocities, c given directly [M/T] or from
a coefficient of restitution e through the damping ratio beta = -ln e / sqrt(pi^2 +
ln^2 e): c = f beta sqrt(m* k), f the law's dashpot factor (2 for a linear spring; 2
sqrt(5/6) for Hertz, Tsuji et al. 1992 as in LIGGGHTS). The tangential dashpot acts
while the spring sticks and is scaled down so that spring plus dashpot stay within the
Coulomb limit (LIGGGHTS adds it unchecked).

Rolling and twisting resistance (Ai et al. 2011, "type C": elastic-plastic spring with
an optional viscous part), acting on the relative rotation of j w.r.t. i (the rolling
part perpendicular to n, the twisting part along n): incremental moments
dM_r = -k_r dphi_r, dM_w = -k_w dphi_w, limited to mu_r R* N and mu_w R* N, with
viscous moments -c_r omega_r, -c_w omega_w while the spring sticks (a coefficient mu_r
or mu_w of 0 with a stiffness: no limit, an elastic spring). Stiffness conventions:
``beta`` (default), k_r = beta_r k_t R*^2 and k_w = beta_w k_t R*^2 (k_t the tangent
tangential stiffness; YADE's CohFrictMat uses alphaKr ks r1 r2; LIGGGHTS' epsd2 is
beta_r = 1); ``epsd``, k_r = 2.25 k_sec mu_r^2 R*^2 (Iwashita & Oda 1998 as used by
LIGGGHTS' epsd model and Ai et al.; k_sec the secant normal stiffness F_n / delta as in
LIGGGHTS), k_w = 2.25 k_sec mu_w^2 R*^2. Viscous coefficients c = 2 eta sqrt(I_r k)
with I_r = 1/(1/(I_i + m_i r_i^2) + 1/(I_j + m_j r_j^2)) (a wall's term is zero), eta
the ``rolling_damping`` ratio. Disks roll about z and do not twist.
"""

from __future__ import annotations

import importlib
import math
import pkgutil

import numpy as np
from numba.extending import overload
from numba.np.unsafe.ndarray import to_fixed_tuple

from demstep._numba import njit
from demstep.contact.laws.base import (COMMON_FIELDS, LAWS, ROLL_BETA, ROLL_CONVENTIONS,
                                       ROLL_EPSD, ROLL_NONE, ContactLaw, LawKernels,
                                       RollingResistance, damping_ratio_from_restitution,
                                       law_class, law_of_params, rolling_inertia)


def _kernels(params_type) -> LawKernels:
    """The formulas of the law whose parameters have the (Python or numba) type."""
    return law_of_params(getattr(params_type, "instance_class", params_type)).kernels


# ------------------------------------------------------------ generic functions
def normal_force(params, delta, r_star):
    """Elastic normal force F_n [M L/T^2], tangent stiffness k_n [M/T^2] and stored
    energy [M L^2/T^2] at overlap ``delta`` [L] (> 0) and effective radius r_star [L]."""
    return _kernels(type(params)).normal_force(params, delta, r_star)


def tangential_stiffness(params, delta, r_star):
    """Tangential spring stiffness k_t [M/T^2] at overlap ``delta`` [L]."""
    return _kernels(type(params)).tangential_stiffness(params, delta, r_star)


def coulomb_load(params, f_n):
    """The normal load [M L/T^2] the Coulomb and rolling limits scale with, from the
    elastic normal force ``f_n``."""
    return _kernels(type(params)).coulomb_load(params, f_n)


def dashpot_factor(params):
    """f in c = f beta sqrt(m* k) (module docstring)."""
    return _kernels(type(params)).dashpot_factor


def secant_factor(params):
    """The secant normal stiffness F_n / delta over the tangent one."""
    return _kernels(type(params)).secant_factor


def needs_r_star(params):
    """Whether the law's formulas read the effective radius R*."""
    return _kernels(type(params)).needs_r_star


@overload(normal_force, inline="always")
def _normal_force(params, delta, r_star):
    impl = _kernels(params).normal_force
    return lambda params, delta, r_star: impl(params, delta, r_star)


@overload(tangential_stiffness, inline="always")
def _tangential_stiffness(params, delta, r_star):
    impl = _kernels(params).tangential_stiffness
    return lambda params, delta, r_star: impl(params, delta, r_star)


@overload(coulomb_load, inline="always")
def _coulomb_load(params, f_n):
    impl = _kernels(params).coulomb_load
    return lambda params, f_n: impl(params, f_n)


@overload(dashpot_factor, inline="always")
def _dashpot_factor(params):
    value = float(_kernels(params).dashpot_factor)
    return lambda params: value


@overload(secant_factor, inline="always")
def _secant_factor(params):
    value = float(_kernels(params).secant_factor)
    return lambda params: value


@overload(needs_r_star, inline="always")
def _needs_r_star(params):
    value = bool(_kernels(params).needs_r_star)
    return lambda params: value


def params_from_row(params, row):
    """The Params tuple of the law of ``params`` whose fields are the values ``row``
    (a float array in the tuple's field order): a wall's own parameters, kept as an
    array row (:meth:`~demstep.contact.laws.base.ContactLaw.wall_params`)."""
    return type(params)(*row)


@overload(params_from_row, inline="always")
def _params_from_row(params, row):
    cls = params.instance_class
    n = len(params)
    return lambda params, row: cls(*to_fixed_tuple(row, n))


@njit(inline="always")
def dashpot_coefficients(params, m_star, k_n, k_t):
    """Normal and tangential dashpot coefficients c_n, c_t [M/T]."""
    c_n = params.c_n
    c_t = params.c_t
    factor = dashpot_factor(params)
    if params.beta_n > 0.0:
        c_n += factor * params.beta_n * math.sqrt(m_star * k_n)
    if params.beta_t > 0.0:
        c_t += factor * params.beta_t * math.sqrt(m_star * k_t)
    return c_n, c_t


@njit(inline="always")
def rolling_coefficients(params, k_n, k_t, r_star, i_star):
    """Rolling and twisting spring stiffnesses k_r, k_w [M L^2/T^2 per rad] and
    viscous coefficients c_r, c_w [M L^2/T] of a contact with tangent stiffnesses k_n,
    k_t [M/T^2], effective radius r_star [L] and equivalent rotational inertia i_star
    [M L^2] (module docstring; zeros when the law has no rolling resistance). The epsd
    convention takes the secant normal stiffness F_n / delta, as LIGGGHTS' epsd model."""
    mode = params.roll_mode
    r2 = r_star * r_star
    if mode == ROLL_BETA:
        k_r = params.beta_r * k_t * r2
        k_w = params.beta_w * k_t * r2
    elif mode == ROLL_EPSD:
        k_sec = secant_factor(params) * k_n
        k_r = 2.25 * k_sec * params.mu_r * params.mu_r * r2
        k_w = 2.25 * k_sec * params.mu_w * params.mu_w * r2
    else:
        return 0.0, 0.0, 0.0, 0.0
    c_r = 0.0
    c_w = 0.0
    if params.eta_r > 0.0:
        c_r = 2.0 * params.eta_r * math.sqrt(i_star * k_r)
        c_w = 2.0 * params.eta_r * math.sqrt(i_star * k_w)
    return k_r, k_w, c_r, c_w


@njit
def contact_coefficients(params, delta, r_star, m_star):
    """Linearised coefficients of contacts at overlaps ``delta`` (C,) [L]: tangent
    stiffnesses k_n, k_t [M/T^2] and dashpot coefficients c_n, c_t [M/T], from the same
    scalar formulas as the engine's force (the time-step analysis of a state). Contacts
    with delta <= 0 get the coefficients at contact (zero stiffness for Hertz)."""
    c = delta.shape[0]
    k_n = np.empty(c)
    k_t = np.empty(c)
    c_n = np.empty(c)
    c_t = np.empty(c)
    for q in range(c):
        d = max(delta[q], 0.0)
        kn = normal_force(params, d, r_star[q])[1]
        kt = tangential_stiffness(params, d, r_star[q])
        k_n[q] = kn
        k_t[q] = kt
        c_n[q], c_t[q] = dashpot_coefficients(params, m_star[q], kn, kt)
    return k_n, k_t, c_n, c_t


# ---------------------------------------------------------------- the laws
for _module in pkgutil.iter_modules(__path__):
    if _module.name != "base":
        importlib.import_module(f"{__name__}.{_module.name}")



def __getattr__(name: str):
    """A registered law's class by its class name (``from demstep.contact.laws import
    LinearSpring``): the package names no law itself."""
    for cls in LAWS.values():
        if cls.__name__ == name:
            return cls
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
