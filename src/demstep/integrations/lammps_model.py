"""LAMMPS' ``pair_style granular`` (the 29 Sep 2021 release) as the springs and dashpots
the certificate takes.

A :class:`GranularModel` is read from the text of a ``pair_coeff * *`` line as a LAMMPS
user writes it (after the two type wildcards), for example::

    hertz/material 5e7 0.5 0.3 tangential mindlin NULL 1.0 0.5 damping tsuji
    hooke 1e6 20 tangential linear_history 1e6 0.5 0.5 damping mass_velocity

and gives, for the contacts of a state, the quantities of a
:class:`~demstep.timestep.contacts.ContactSet`: the tangent normal stiffness S_n, the
tangential stiffness k_t, the dashpots gamma_n and gamma_t, the rolling and twisting
springs and dashpots, and the lever arms, each as LAMMPS computes it
(``docs/lammps.md`` has the formulas and where they come from). Notation: R* = r_i r_j /
(r_i + r_j), m* = m_i m_j / (m_i + m_j), delta the overlap, a = sqrt(R* delta) (every
model), E* = 1 / ((1 - nu^2)/E + (1 - nu^2)/E) = E / (2 (1 - nu^2)) for one material.

* normal: ``hooke kn eta`` (S_n = kn), ``hertz kn eta`` (F = kn a delta: S_n = 3/2 kn a),
  ``hertz/material E eta nu`` and ``dmt E eta nu w`` (F = 4/3 E* a delta (- 4 pi w R*):
  S_n = 2 E* a); ``jkr`` is refused (its force is not a closed form in delta);
* ``damping``: gamma_n = eta (``velocity``), eta m* (``mass_velocity``), eta a m*
  (``viscoelastic``, LAMMPS' default), alpha(e) sqrt(m* knfac) (``tsuji``, e the user's
  number, knfac = kn, kn a or 4/3 E* a: :func:`tsuji_alpha`);
* ``tangential``: ``linear_nohistory xgammat mu`` (no spring), ``linear_history kt
  xgammat mu`` (k_t = kt), ``mindlin kt xgammat mu`` (k_t = kt a; ``NULL``: 8 G* a with
  G* = E / (4 (2 - nu)(1 + nu)) for one material); gamma_t = xgammat gamma_n;
* ``rolling sds kR gammaR muR``: a rotational spring kR R*^2 and dashpot gammaR R*^2 on
  the relative rotation across the normal; ``twisting marshall`` (k = k_t a^2 / 2,
  dashpot gamma_t a^2 / 2) or ``twisting sds k gamma mu``, about the normal;
* lever arms: the slip velocity takes the radii r, the torque the arm r - delta/2, a
  stiffness that is not symmetric; the certificate takes the geometric mean
  sqrt(r (r - delta/2)) on both sides (:func:`pair_arm`, exact for one contact: the
  coupling enters through the product of the two arms). Walls (``fix wall/gran
  granular``): R* = r, m* = m, the full radius as the arm, and this release's wall
  constants (``hertz/material``: 4/3 E / (2 (1 - nu)); ``mindlin NULL``:
  E (2 - nu)(1 + nu) / 4 x a).

Sub-models and keywords the certificate does not cover are refused in one line naming
them (never certified as something else).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from demstep.errors import InputError

#: normal models: their number of coefficients
NORMAL_MODELS = {"hooke": 2, "hertz": 2, "hertz/material": 3, "dmt": 4}
DAMPING_MODELS = ("velocity", "mass_velocity", "viscoelastic", "tsuji")
#: tangential models: their number of coefficients
TANGENTIAL_MODELS = {"linear_nohistory": 2, "linear_history": 3, "mindlin": 3}
#: what LAMMPS has and the certificate does not model, with the reason given
REFUSED = {
    "jkr": "the JKR normal force is not a closed form in the overlap",
    "linear_history_classic": "its history is not rotated into the tangent plane",
    "mindlin_rescale": "its history is rescaled with the contact radius",
    "mindlin/force": "its history is a force, not a displacement",
    "mindlin_rescale/force": "its history is a force rescaled with the contact radius",
}


def tsuji_alpha(e: float) -> float:
    """LAMMPS' ``damping tsuji`` coefficient alpha(e) (a polynomial fit for Hertz
    contacts): gamma_n = alpha sqrt(m* knfac)."""
    return (1.2728 - 4.2783 * e + 11.087 * e**2 - 22.348 * e**3 + 27.467 * e**4
            - 18.022 * e**5 + 4.8218 * e**6)


def pair_arm(r, delta):
    """The certificate's lever arm [L] of a particle of radius ``r`` in a LAMMPS pair
    contact of overlap ``delta``: sqrt(r (r - delta/2)), the geometric mean of the slip
    velocity's radius r and the torque's arm r - delta/2."""
    return np.sqrt(r * (r - 0.5 * delta))


def _number(token: str, what: str, allow_null: bool = False) -> float:
    if allow_null and token == "NULL":
        return math.nan
    try:
        value = float(token)
    except ValueError:
        raise InputError(f"lammps model: {what} must be a number, got {token!r}") from None
    if not math.isfinite(value):
        raise InputError(f"lammps model: {what} must be finite, got {token!r}")
    return value


@dataclass(frozen=True)
class GranularModel:
    """One ``pair_coeff`` line of LAMMPS' ``pair_style granular`` (module docstring):
    the normal model and its coefficients, the damping model, the tangential model and
    its coefficients (``kt`` NaN for ``mindlin NULL``), rolling (kR, gammaR, muR) or
    None, twisting "marshall", (k, gamma, mu) or None."""

    normal: str
    normal_coeffs: tuple
    tangential: str
    tangential_coeffs: tuple
    damping: str = "viscoelastic"
    rolling: tuple | None = None
    twisting: object = None
    limit_damping: bool = False

    @classmethod
    def parse(cls, text: str) -> "GranularModel":
        """The model of a ``pair_coeff * *`` text (without the wildcards)."""
        tokens = str(text).split()
        if tokens[:2] == ["*", "*"]:
            tokens = tokens[2:]
        if not tokens:
            raise InputError("lammps model: empty; expected e.g. 'hooke 1e6 0.5 tangential "
                             "linear_history 1e6 1.0 0.5'")
        name = cls._known("normal", tokens.pop(0), NORMAL_MODELS)
        normal = tuple(_number(t, f"{name} coefficient {k + 1}")
                       for k, t in enumerate(cls._take(tokens, NORMAL_MODELS[name], name)))
        fields = {"damping": "viscoelastic", "rolling": None, "twisting": None,
                  "limit_damping": False}
        tangential = None
        while tokens:
            key = tokens.pop(0)
            if key == "damping":
                model = cls._take(tokens, 1, "damping")[0]
                if model not in DAMPING_MODELS:
                    raise InputError(f"lammps model: damping {model!r} is not one of "
                                     f"{', '.join(DAMPING_MODELS)}")
                fields["damping"] = model
            elif key == "tangential":
                model = cls._known("tangential", cls._take(tokens, 1, "tangential")[0],
                                   TANGENTIAL_MODELS)
                values = cls._take(tokens, TANGENTIAL_MODELS[model], f"tangential {model}")
                tangential = (model, tuple(
                    _number(t, f"tangential {model} coefficient {k + 1}",
                            allow_null=(model == "mindlin" and k == 0))
                    for k, t in enumerate(values)))
            elif key == "rolling":
                model = cls._take(tokens, 1, "rolling")[0]
                if model != "sds":
                    raise InputError(f"lammps model: rolling {model!r} is not certified "
                                     f"(certified: sds)")
                fields["rolling"] = tuple(_number(t, f"rolling sds coefficient {k + 1}")
                                          for k, t in enumerate(cls._take(tokens, 3, "rolling sds")))
            elif key == "twisting":
                model = cls._take(tokens, 1, "twisting")[0]
                if model == "marshall":
                    fields["twisting"] = "marshall"
                elif model == "sds":
                    fields["twisting"] = tuple(
                        _number(t, f"twisting sds coefficient {k + 1}")
                        for k, t in enumerate(cls._take(tokens, 3, "twisting sds")))
                else:
                    raise InputError(f"lammps model: twisting {model!r} is not certified "
                                     f"(certified: marshall, sds)")
            elif key == "limit_damping":
                fields["limit_damping"] = True
            elif key == "cutoff":  # the neighbour cutoff only: no force beyond contact
                _number(cls._take(tokens, 1, "cutoff")[0], "cutoff")
            else:
                raise InputError(f"lammps model: keyword {key!r} is not certified (known: "
                                 f"damping, tangential, rolling, twisting, limit_damping, "
                                 f"cutoff)")
        if tangential is None:
            raise InputError("lammps model: 'tangential' is missing (LAMMPS requires it)")
        model = cls(name, normal, tangential[0], tangential[1], **fields)
        model._check()
        return model

    @staticmethod
    def _known(kind: str, name: str, certified) -> str:
        """``name`` when it is one of the ``certified`` models of ``kind``; a model
        LAMMPS has and the certificate does not (:data:`REFUSED`), or an unknown one,
        refused in one line."""
        if name in REFUSED:
            raise InputError(f"lammps model: {kind} model {name!r} is not certified "
                             f"({REFUSED[name]})")
        if name not in certified:
            raise InputError(f"lammps model: unknown {kind} model {name!r} (certified: "
                             f"{', '.join(certified)})")
        return name

    @staticmethod
    def _take(tokens: list, count: int, what: str) -> list:
        if len(tokens) < count:
            raise InputError(f"lammps model: {what} needs {count} value(s), got "
                             f"{len(tokens)}")
        taken = tokens[:count]
        del tokens[:count]
        return taken

    def _check(self):
        n = self.normal_coeffs
        if n[0] <= 0:
            raise InputError(f"lammps model: {self.normal} stiffness must be > 0, got {n[0]!r}")
        if n[1] < 0:
            raise InputError(f"lammps model: {self.normal} damping coefficient must be >= 0, "
                             f"got {n[1]!r}")
        if self.normal in ("hertz/material", "dmt") and not -1.0 < n[2] < 0.5:
            raise InputError(f"lammps model: {self.normal} Poisson's ratio must lie in "
                             f"(-1, 0.5), got {n[2]!r}")
        if self.damping == "tsuji" and not 0.0 < n[1] <= 1.0:
            raise InputError(f"lammps model: damping tsuji takes a restitution in (0, 1] "
                             f"as the normal damping coefficient, got {n[1]!r}")
        t = self.tangential_coeffs
        if self.tangential == "mindlin" and math.isnan(t[0]) and self.normal not in (
                "hertz/material", "dmt"):
            raise InputError(f"lammps model: tangential mindlin NULL needs a material normal "
                             f"model (hertz/material or dmt), got {self.normal!r}")
        if any(v < 0 for v in t if not math.isnan(v)):
            raise InputError(f"lammps model: tangential {self.tangential} coefficients must "
                             f"be >= 0, got {t!r}")
        if self.rolling is not None and min(self.rolling) < 0:
            raise InputError(f"lammps model: rolling sds coefficients must be >= 0, got "
                             f"{self.rolling!r}")
        if isinstance(self.twisting, tuple) and min(self.twisting) < 0:
            raise InputError(f"lammps model: twisting sds coefficients must be >= 0, got "
                             f"{self.twisting!r}")

    @property
    def rolling_or_twisting(self) -> bool:
        return self.rolling is not None or self.twisting is not None

    def describe(self) -> str:
        """One line for a report."""
        parts = [self.normal + " " + " ".join(f"{v:g}" for v in self.normal_coeffs),
                 "damping " + self.damping,
                 "tangential " + self.tangential + " " + " ".join(
                     "NULL" if math.isnan(v) else f"{v:g}" for v in self.tangential_coeffs)]
        if self.rolling is not None:
            parts.append("rolling sds " + " ".join(f"{v:g}" for v in self.rolling))
        if self.twisting == "marshall":
            parts.append("twisting marshall")
        elif self.twisting is not None:
            parts.append("twisting sds " + " ".join(f"{v:g}" for v in self.twisting))
        return "LAMMPS pair granular: " + ", ".join(parts)

    def springs(self, r_star, m_star, delta, wall: bool = False) -> dict:
        """The contacts' springs and dashpots as LAMMPS computes them, for effective
        radii ``r_star`` [L], effective masses ``m_star`` [M] and overlaps ``delta`` [L]
        (arrays of one length; ``wall``: contacts of ``fix wall/gran granular``, with
        r_star the particle's radius and m_star its mass): a dict of arrays k_n (the
        tangent normal stiffness dF/d delta), k_s, c_n, c_t [M/T^2, M/T] and k_r, c_r,
        k_w, c_w [M L^2/T^2, M L^2/T] (ContactSet's fields)."""
        r_star = np.asarray(r_star, dtype=np.float64)
        m_star = np.asarray(m_star, dtype=np.float64)
        delta = np.maximum(np.asarray(delta, dtype=np.float64), 0.0)
        a = np.sqrt(r_star * delta)
        c0, eta = self.normal_coeffs[0], self.normal_coeffs[1]
        if self.normal == "hooke":
            s_n = np.full_like(a, c0)
            knfac = s_n
        elif self.normal == "hertz":
            s_n = 1.5 * c0 * a
            knfac = c0 * a
        else:  # hertz/material, dmt: the modulus paired with itself
            nu = self.normal_coeffs[2]
            e_star = c0 / (2.0 * (1.0 - nu)) if wall else c0 / (2.0 * (1.0 - nu * nu))
            s_n = 2.0 * e_star * a
            knfac = 4.0 / 3.0 * e_star * a
        if self.damping == "velocity":
            c_n = np.full_like(a, eta)
        elif self.damping == "mass_velocity":
            c_n = eta * m_star
        elif self.damping == "viscoelastic":
            c_n = eta * a * m_star
        else:  # tsuji: eta is the restitution
            c_n = tsuji_alpha(eta) * np.sqrt(m_star * knfac)
        t = self.tangential_coeffs
        xgammat = t[0] if self.tangential == "linear_nohistory" else t[1]
        if self.tangential == "linear_nohistory":
            k_s = np.zeros_like(a)
        elif self.tangential == "linear_history":
            k_s = np.full_like(a, t[0])
        elif not math.isnan(t[0]):  # mindlin kt: kt a
            k_s = t[0] * a
        else:  # mindlin NULL: from the normal model's material
            e_mod, nu = self.normal_coeffs[0], self.normal_coeffs[2]
            if wall:
                k_s = e_mod * (2.0 - nu) * (1.0 + nu) / 4.0 * a
            else:
                k_s = 2.0 * e_mod / ((2.0 - nu) * (1.0 + nu)) * a
        c_t = xgammat * c_n
        zero = np.zeros_like(a)
        k_r = c_r = k_w = c_w = zero
        if self.rolling is not None:
            k_r = self.rolling[0] * r_star**2
            c_r = self.rolling[1] * r_star**2
        if self.twisting == "marshall":
            k_w = 0.5 * k_s * a**2
            c_w = 0.5 * c_t * a**2
        elif self.twisting is not None:
            k_w = np.full_like(a, self.twisting[0])
            c_w = np.full_like(a, self.twisting[1])
        return {"k_n": s_n, "k_s": k_s, "c_n": c_n, "c_t": c_t, "k_r": k_r, "c_r": c_r,
                "k_w": k_w, "c_w": c_w}


def lammps_contacts(particles, model: GranularModel, periodic=None, walls=(),
                    with_overlaps: bool = False):
    """The contacts of ``particles`` (:class:`~demstep.particles.Particles`, 3D) under
    ``model``, as a :class:`~demstep.timestep.contacts.ContactSet`: the pairs that
    overlap (LAMMPS' rule: centre distance below r_i + r_j; ``periodic``: box lengths
    per axis, None for an axis that is not, the box starting at 0) and the contacts
    with plane ``walls`` (:class:`~demstep.walls.Wall`, LAMMPS' ``fix wall/gran
    granular`` with the same sub-models), with LAMMPS' springs, dashpots and the
    certificate's arms (:func:`pair_arm`; the radius at a wall). A fixed particle's
    partner takes the other's mass as m*, as LAMMPS does for a frozen atom.
    ``with_overlaps``: (contacts, their overlaps [L])."""
    from demstep.contact.geometry import pair_geometry_arrays
    from demstep.timestep.contacts import ContactSet, _pair_contacts

    x, r, m = particles.x, particles.r, particles.m
    if x.shape[1] != 3:
        raise InputError("lammps model: 3D particles only (LAMMPS' 2d granular runs are "
                         "not certified)")
    base = _pair_contacts(x, r, 0.0, periodic)
    box = np.array([0.0 if v is None else float(v) for v in (periodic or (None,) * 3)])
    x_box = np.mod(x, np.where(box > 0, box, np.inf)) if periodic is not None else x
    i, j = base.i, base.j
    branch, dist, delta, _, _, _ = pair_geometry_arrays(np.ascontiguousarray(x_box), r, i, j,
                                                        box)
    touching = delta > 0.0
    i, j, branch, dist, delta = i[touching], j[touching], branch[touching], dist[touching], \
        delta[touching]
    mass = np.where(particles.fixed, np.inf, m)
    m_i, m_j = mass[i], mass[j]
    with np.errstate(invalid="ignore", divide="ignore"):
        m_star = np.where(np.isinf(m_i), m_j, np.where(np.isinf(m_j), m_i,
                                                       m_i * m_j / (m_i + m_j)))
    r_star = r[i] * r[j] / (r[i] + r[j])
    parts = [ContactSet(i, j, branch / dist[:, None], pair_arm(r[i], delta),
                        pair_arm(r[j], delta), **model.springs(r_star, m_star, delta))]
    overlaps = [delta]
    for w_index, wall in enumerate(walls):
        d = wall.distance(x)
        p = np.flatnonzero(d < r)
        if np.any(d[p] <= 0):
            raise InputError(f"wall {wall.name!r}: particle {int(p[d[p] <= 0][0])} centre lies "
                             f"on or behind the wall")
        wall_delta = r[p] - d[p]
        springs = model.springs(r[p], m[p], wall_delta, wall=True)
        parts.append(ContactSet(p, np.full(len(p), -1), np.broadcast_to(-wall.normal, (len(p), 3)),
                                r[p], np.zeros(len(p)), wall=np.full(len(p), w_index),
                                **springs))
        overlaps.append(wall_delta)
    contacts = ContactSet.concatenate(parts)
    return (contacts, np.concatenate(overlaps)) if with_overlaps else contacts
