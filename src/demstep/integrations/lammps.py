"""The time step of a running LAMMPS instance, certified by demstep.

LAMMPS (``pair_style granular``) runs from Python through its ``lammps`` module; a
:class:`LammpsCertifier` reads the atoms (positions, radii, masses) of the instance,
finds the contacts, gives them LAMMPS' springs and dashpots
(:mod:`demstep.integrations.lammps_model`, from the same ``pair_coeff`` text the input
uses) and certifies the critical step of that state: the exact (damped) critical step
(:func:`demstep.timestep.exact.exact_critical_step`), or the coupled element bound,
lower but cheaper. Two ways to use it:

* a Python-driven run, :meth:`LammpsCertifier.run`: LAMMPS advances ``every`` steps at
  a time (``run N pre no post no``) and between them the step is certified, and
  lowered at once when it is above ``safety`` times the certified one (raised only
  when it is below that by more than (1 + ``grow``)^2); each change is logged with its
  reason;
* a check from inside a run, ``fix python/invoke N end_of_step FUNC`` calling
  :meth:`LammpsCertifier.check`: LAMMPS (29 Sep 2021) allows no command during a run,
  so the step cannot be changed there; a step above ``safety`` times the certified one
  stops the run with the reason (:class:`StepNotCertified`).

What the certificate does not cover is refused in one line naming it, never certified
as something else: an atom style without radius and per-atom mass, a triclinic box, a
2d run, a fix whose physics it does not model (``fix viscous``, ``fix rigid``,
``fix freeze``, thermostats, ...), ``fix wall/gran`` without its planes, an integrator
other than ``fix nve/sphere`` (rotation) or ``fix nve`` (rotation locked). Between two
certificates the state moves on: the safety factor covers that drift (demstep's own
'auto' step carries a certificate of it; this one does not).

Debian: ``apt-get install lammps python3-lammps liblammps-dev`` (the module loads
``liblammps.so``, which the -dev package provides); :func:`load_lammps` finds Debian's
module from another Python too.
"""

from __future__ import annotations

import math
import os
import re
import sys
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np

from demstep.errors import InputError
from demstep.integrations.lammps_model import GranularModel, lammps_contacts
from demstep.integrations.stepping import band_change, check_settings, why

#: where Debian's python3-lammps puts the module
DEBIAN_DIST_PACKAGES = "/usr/lib/python3/dist-packages"

#: fixes that neither add forces nor change masses: the certificate is the same with them
NEUTRAL_FIXES = {"gravity", "deform", "python/invoke", "print", "ave/time", "ave/atom",
                 "ave/chunk", "ave/histo", "ave/correlate", "ave/spatial", "momentum",
                 "store/state", "DUMMY", "NEIGH_HISTORY", "halt", "balance", "dt/reset"}
#: fixes that integrate: rotation free or locked
INTEGRATORS = {"nve/sphere": True, "nve": False}

#: a fix line of LAMMPS' ``info fixes``: Fix[  1]:  ID,  style = STYLE,  group = GROUP
_FIX_LINE = re.compile(r"^Fix\[\s*\d+\]:\s*(\S+?),\s*style\s*=\s*(\S+?),\s*group\s*=\s*(\S+)")


class StepNotCertified(RuntimeError):
    """LAMMPS' step is above the certified one (times the safety factor) during a run."""


def load_lammps():
    """The ``lammps`` Python module: the one this Python has, else Debian's
    (python3-lammps), appended to the path (so that this Python's own packages keep
    precedence). An ImportError names what to install."""
    try:
        import lammps
    except ImportError:
        if os.path.isdir(os.path.join(DEBIAN_DIST_PACKAGES, "lammps")):
            sys.path.append(DEBIAN_DIST_PACKAGES)
            import lammps
        else:
            raise ImportError("demstep.integrations.lammps needs LAMMPS' Python module: "
                              "apt-get install lammps python3-lammps liblammps-dev") from None
    return lammps


def lammps_fixes(lmp) -> list[tuple[str, str, str]]:
    """(id, style, group) of every fix of ``lmp`` (from ``info fixes``; a command, so not
    during a run)."""
    with tempfile.TemporaryDirectory(prefix="demstep-lammps-") as folder:
        path = os.path.join(folder, "fixes.txt")
        lmp.command(f"info fixes out overwrite {path}")
        with open(path) as f:
            return [m.groups() for m in map(_FIX_LINE.match, f.read().splitlines()) if m]


@dataclass
class LammpsState:
    """The atoms of a LAMMPS instance as the certificate takes them: Particles (ordered
    by atom id), the periodic lengths per axis (None: not periodic; positions shifted
    into [0, L)), the box's lower corner and the atom ids."""

    particles: object
    periodic: list | None
    box_lo: np.ndarray
    ids: np.ndarray


def read_state(lmp) -> LammpsState:
    """The atoms of ``lmp`` (all ranks', by ``gather_atoms``): positions, radii and
    per-atom masses (``atom_style sphere``), sorted by id; refused in one line for what
    the certificate does not take."""
    from demstep.particles import Particles

    if lmp.extract_setting("dimension") != 3:
        raise InputError("lammps: a 2d run is not certified (3d only)")
    if not lmp.extract_setting("rmass_flag") or not lmp.extract_setting("radius_flag"):
        raise InputError("lammps: the atom style has no per-atom radius and mass (use "
                         "atom_style sphere)")
    lo, hi, xy, yz, xz, periodicity, _ = lmp.extract_box()
    if any(t != 0.0 for t in (xy, yz, xz)):
        raise InputError(f"lammps: a triclinic box (tilts {xy}, {yz}, {xz}) is not certified")
    n = int(lmp.get_natoms())
    if n == 0:
        raise InputError("lammps: no atoms")
    x = np.ctypeslib.as_array(lmp.gather_atoms("x", 1, 3)).reshape(n, 3).copy()
    r = np.ctypeslib.as_array(lmp.gather_atoms("radius", 1, 1)).copy()
    m = np.ctypeslib.as_array(lmp.gather_atoms("rmass", 1, 1)).copy()
    ids = np.ctypeslib.as_array(lmp.gather_atoms("id", 0, 1)).copy()
    order = np.argsort(ids, kind="stable")
    x, r, m, ids = x[order], r[order], m[order], ids[order]
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    periodic = None
    if any(periodicity):
        periodic = [float(hi[k] - lo[k]) if periodicity[k] else None for k in range(3)]
        x = x - lo
        for k in range(3):
            if periodicity[k]:
                x[:, k] = np.mod(x[:, k], hi[k] - lo[k])
    else:
        x = x - lo
    particles = Particles(x, r, m, 0.4 * m * r * r)
    return LammpsState(particles, periodic, lo, ids)


@dataclass
class Certificate:
    """One certificate of a LAMMPS state: the certified critical step ``dt`` [T] (by
    ``method``), the step LAMMPS had (``dt_lammps``) and the one set after
    (``dt_set``; None when unchanged), the timestep number, the number of contacts and
    the largest overlap / radius, the seconds it took, and why the step changed."""

    step: int
    dt: float
    method: str
    dt_lammps: float
    contacts: int
    max_overlap: float
    seconds: float
    dt_set: float | None = None
    reason: str = ""


@dataclass
class LammpsCertifier:
    """Certifies (and sets) the step of the LAMMPS instance ``lmp`` (a ``lammps.lammps``)
    whose ``pair_style granular`` uses the ``pair_coeff * *`` text ``model`` (module
    docstring). ``safety`` in (0, 1]: the step set is ``safety`` times the certified
    one; ``method``: "exact" or "element" (the coupled element bound); ``walls``:
    :class:`~demstep.walls.Wall` planes of the input's ``fix wall/gran granular`` (their
    coordinates as LAMMPS has them, normals into the packing) and ``wall_model`` their
    ``fix wall/gran`` text (None: ``model``); ``grow``: the step is kept within
    [safety / (1 + grow)^2, safety] times the certified one, and set to safety / (1 +
    grow) times it when it leaves that band (:meth:`apply`); ``log``: a
    function taking each line (None: print)."""

    lmp: object
    model: str
    safety: float = 0.8
    method: str = "exact"
    walls: tuple = ()
    wall_model: str | None = None
    grow: float = 0.05
    log: object = None
    history: list = field(default_factory=list)

    def __post_init__(self):
        check_settings(self.safety, self.method, self.grow)
        self.granular = GranularModel.parse(self.model)
        self.wall_granular = (self.granular if self.wall_model is None
                              else GranularModel.parse(self.wall_model))
        self.rotation = self._check_fixes()

    # ------------------------------------------------------------------ checks
    def _check_fixes(self) -> bool:
        """Whether rotation is free (fix nve/sphere) or locked (fix nve); every other
        fix either neutral or refused in one line naming it."""
        integrators = []
        walls = []
        for fix_id, style, _group in lammps_fixes(self.lmp):
            base = style.split("/kk")[0].split("/omp")[0]
            if base in INTEGRATORS:
                integrators.append((fix_id, base))
            elif base == "wall/gran":
                walls.append(fix_id)
            elif base.startswith("NEIGH_HISTORY") or base in NEUTRAL_FIXES:
                continue
            else:
                raise InputError(f"lammps: fix {fix_id!r} (style {style}) is not certified: "
                                 f"the certificate does not model what it does")
        if len(integrators) != 1:
            found = ", ".join(f"{i} ({s})" for i, s in integrators) or "none"
            raise InputError(f"lammps: expected one integrator fix, nve/sphere or nve, found "
                             f"{found}")
        if walls and not self.walls:
            raise InputError(f"lammps: fix {walls[0]!r} (wall/gran) needs its planes: give "
                             f"walls=[Wall(point, normal), ...] (and wall_model=TEXT)")
        return INTEGRATORS[integrators[0][1]]

    # ------------------------------------------------------------------ certificate
    def certify(self) -> Certificate:
        """The certified critical step of the instance's state now."""
        from demstep.timestep.contacts import ContactSet
        from demstep.timestep.estimates import certified_dt, element_coupled_dt
        from demstep.walls import Wall

        start = time.perf_counter()
        state = read_state(self.lmp)
        walls = [Wall(np.asarray(w.point, dtype=np.float64) - state.box_lo, w.normal, name=w.name)
                 for w in self.walls]
        contacts, overlap = lammps_contacts(state.particles, self.granular, state.periodic,
                                            with_overlaps=True)
        if walls:  # (the walls' contacts with their own fix's coefficients)
            wall_contacts, wall_overlap = lammps_contacts(
                state.particles, self.wall_granular, state.periodic, walls, with_overlaps=True)
            at_wall = wall_contacts.j < 0
            contacts = ContactSet.concatenate([contacts, wall_contacts.subset(at_wall)])
            overlap = np.concatenate([overlap, wall_overlap[at_wall]])
        step = int(self.lmp.extract_global("ntimestep"))
        dt_lammps = float(self.lmp.extract_global("dt"))
        if contacts.n == 0:
            raise StepNotCertified(f"step {step}: no contacts: the contact dynamics sets no "
                                   f"limit, and the certificate gives no step")
        r = state.particles.r
        if self.method == "exact":
            dt = certified_dt(state.particles, contacts, self.rotation)
        else:
            dt = element_coupled_dt(state.particles, contacts, self.rotation)
        if not (math.isfinite(dt) and dt > 0.0):
            raise StepNotCertified(f"step {step}: the certificate could not be computed "
                                   f"(got {dt!r})")
        return Certificate(step, float(dt), self.method, dt_lammps, int(contacts.n),
                           float(np.max(overlap / r[contacts.i], initial=0.0)),
                           time.perf_counter() - start)

    def _say(self, text: str):
        (self.log or print)(f"demstep: {text}")

    def check(self):
        """From ``fix python/invoke``: certify, and stop the run (StepNotCertified)
        when LAMMPS' step is above ``safety`` times the certified one."""
        cert = self.certify()
        self.history.append(cert)
        if cert.dt_lammps > self.safety * cert.dt:
            raise StepNotCertified(
                f"step {cert.step}: timestep {cert.dt_lammps:.6g} is above {self.safety:g} x "
                f"the certified {cert.dt:.6g} ({cert.method}, {cert.contacts} contacts, "
                f"largest overlap {cert.max_overlap:.3g} r)")
        return cert

    def apply(self) -> Certificate:
        """Between runs: certify and keep LAMMPS' step within the band [safety / (1 +
        grow)^2, safety] times the certified one; a step outside it (above: at once;
        below: the certified step allows a longer one) is set to the band's middle,
        safety / (1 + grow) times the certified step (a step set there is not moved
        again until the certificate changes by a factor 1 + grow: no back and forth)."""
        cert = self.certify()
        previous = self.history[-1] if self.history else None
        self.history.append(cert)
        change = band_change(cert.dt_lammps, cert.dt, self.safety, self.grow)
        if change is None:
            return cert
        target, reason = change
        cert.reason = reason + why(previous, cert)
        self.lmp.command(f"timestep {target!r}")
        cert.dt_set = target
        self._say(f"step {cert.step}: timestep {cert.dt_lammps:.6g} -> {target:.6g} "
                  f"({cert.reason})")
        return cert

    def run(self, steps: int, every: int):
        """Advance ``steps`` steps, ``every`` at a time, the step certified and set
        (:meth:`apply`) before each part. Returns the certificates of this call."""
        if not (isinstance(steps, int) and steps >= 0):
            raise InputError(f"steps: must be an integer >= 0, got {steps!r}")
        if not (isinstance(every, int) and every >= 1):
            raise InputError(f"every: must be an integer >= 1, got {every!r}")
        out = []
        done = 0
        first = int(self.lmp.extract_global("ntimestep"))
        while done < steps:
            out.append(self.apply())
            chunk = min(every, steps - done)
            # start/stop: fixes that ramp (fix deform) see one run of ``steps`` steps
            self.lmp.command(f"run {chunk} start {first} stop {first + steps} "
                             f"pre {'yes' if done == 0 else 'no'} post no")
            done += chunk
        return out
