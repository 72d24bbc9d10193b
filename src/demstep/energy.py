"""The energy ledger (paper eqs. 22-25) and its balance alarm.

State terms are recomputed every step: kinetic energy (translation and rotation, from
the mean of the two half-step velocities around t) and strain energy (normal and
tangential springs at t, and rolling and twisting springs). Accumulated terms are
summed step by step by the trapezoidal rule: work of body forces, applied forces, walls
and a deforming periodic box (external), and dissipation by friction, contact
dashpots, rolling and twisting resistance (plastic and viscous), local (Cundall) and
global viscous damping. The energy the
system holds when the ledger starts (or is reset) counts as external input.

    W_kin + W_int = W_ext,  W_int = W_strain + W_friction + W_damping,
    W_ext = boundary and body work + initial energy + inserted - removed energy,
    normalized difference = |W_kin + W_int - W_ext| / S(t)

The paper's eq. 22 divides by max(W_ext, W_int, W_kin) at time t. That scale can
vanish while the system is full of energy: a ball bouncing under gravity has all three
near zero at the top of each bounce (the work of gravity is paid back as it rises), a
harmonic oscillator under gravity at each turning point, and a cohesive contact holds a
negative stored energy, so W_int < 0. demstep therefore divides by the running maximum

    S(t) = max over s <= t of max(|W_ext(s)|, |W_int(s)|, W_kin(s)),

the largest energy the system has held or exchanged since the ledger started. Where the
input grows monotonically (the paper's compression tests, gravity settling, a wall
pressing), S(t) is eq. 22's own scale at t; where it oscillates, S stays at the size of
the oscillation instead of passing through zero. It never decreases, so a later
instability still shows: the energy it creates is counted in the imbalance and in
W_kin, and the error grows to order one as in eq. 22. The largest of the cumulative
magnitudes of every term was the other candidate; it grows without bound in an
oscillating run (2 m g h per bounce), so it would dilute a slowly growing instability
a little more with every period.

The divergence check (runaway kinetic energy) compares W_kin with the most energy the
system can have received: the running maximum of the energy supplied (W_ext, the
initial energy included) plus the energy a negative stored energy can release (-W_strain
when it is negative: cohesion). Without friction, dashpots or integration error
W_kin = W_ext - W_int can never exceed it, while a blow-up multiplies W_kin without
bound; the current W_ext, which the check used before, returns to zero at the top of
a bounce.

The ledger describes time t of the last force evaluation: after a step the positions
are already at t + dt (the kinetic energy at t needs v(t + dt/2)).

With the mean-velocity kinetic energy the difference is O((omega dt)^2) for a stable
linear run, exactly zero for free fall, and grows to order one as dt approaches the
critical step, which is what makes it an instability alarm.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from demstep._numba import njit
from demstep.errors import InputError

# The ledger's layout, shared with the compiled kernels (which import it from here).
#: accumulated terms (array ``EnergyLedger.acc``): work of body forces, applied forces,
#: walls; dissipation by friction, contact dashpots, local and global damping; the
#: energy held when the ledger started; work of a deforming periodic box; dissipation
#: by rolling and twisting resistance (plastic limit, viscous part); strain energy
#: released by parallel bonds as they broke
(A_BODY, A_APPLIED, A_WALLS, A_FRICTION, A_DASHPOT, A_LOCAL, A_GLOBAL, A_INITIAL, A_BOX,
 A_ROLLING, A_ROLLING_VISCOUS, A_BOND_BROKEN) = range(12)
#: running maxima kept in the same array, updated every step (:func:`update_peaks`):
#: the energy supplied (the divergence check's reference) and the balance's scale S(t)
A_PEAK_SUPPLIED, A_PEAK_SCALE = 12, 13
#: the energy inserted particles brought in and removed particles took out
#: (:mod:`demstep.engine.population`): added to and taken from the energy supplied
A_INSERTED, A_REMOVED = 14, 15
N_ACC = 16
#: state terms (array ``EnergyLedger.energy``): kinetic translation / rotation, strain
#: normal / tangential / rolling and twisting springs / parallel bonds
E_KIN_T, E_KIN_R, E_STRAIN_N, E_STRAIN_T, E_STRAIN_R, E_STRAIN_BOND = range(6)
N_ENERGY = 6

log = logging.getLogger("demstep")

#: the paper's tolerance on the normalized energy difference (eq. 22)
DEFAULT_EPS = 1e-2


# The ledger's sums, written once: the compiled step calls them, and so does
# :class:`EnergyLedger` (through their Python functions, ``_py``).
@njit(inline="always")
def energy_supplied(acc):
    """W_ext [M L^2/T^2]: work of body forces, applied forces, walls and the periodic
    box, the energy held when the ledger started, and the net energy particles
    carried across the boundary (inserted less removed)."""
    return (acc[A_BODY] + acc[A_APPLIED] + acc[A_WALLS] + acc[A_BOX] + acc[A_INITIAL]
            + acc[A_INSERTED] - acc[A_REMOVED])


@njit(inline="always")
def energy_stored(energy):
    """W_strain [M L^2/T^2]: the springs of the contacts (normal, tangential, rolling and
    twisting) and of the bonds; negative where a cohesive force holds the contact."""
    return energy[E_STRAIN_N] + energy[E_STRAIN_T] + energy[E_STRAIN_R] + energy[E_STRAIN_BOND]


@njit(inline="always")
def energy_dissipated(acc):
    """Friction, dashpots, local and global damping, rolling resistance and the strain
    energy of broken bonds [M L^2/T^2], accumulated."""
    return (acc[A_FRICTION] + acc[A_DASHPOT] + acc[A_LOCAL] + acc[A_GLOBAL] + acc[A_ROLLING]
            + acc[A_ROLLING_VISCOUS] + acc[A_BOND_BROKEN])


@njit(inline="always")
def energy_kinetic(energy):
    """W_kin [M L^2/T^2], translation and rotation."""
    return energy[E_KIN_T] + energy[E_KIN_R]


@njit(inline="always")
def update_peaks(acc, energy):
    """Carry the running maxima to the state now: the energy supplied, and the scale
    S = max(|W_ext|, |W_int|, W_kin) of the balance (module docstring)."""
    supplied = energy_supplied(acc)
    internal = energy_stored(energy) + energy_dissipated(acc)
    acc[A_PEAK_SUPPLIED] = max(acc[A_PEAK_SUPPLIED], supplied)
    acc[A_PEAK_SCALE] = max(acc[A_PEAK_SCALE], abs(supplied), abs(internal),
                            energy_kinetic(energy))


@njit(inline="always")
def runaway_reference(acc, energy):
    """The most kinetic energy [M L^2/T^2] the system can have received: the running
    maximum of the energy supplied, plus what a negative stored energy can release."""
    return max(acc[A_PEAK_SUPPLIED], 0.0) + max(-energy_stored(energy), 0.0)


def _py(kernel):
    """The Python function of a compiled formula (itself when numba is disabled)."""
    return getattr(kernel, "py_func", kernel)


class EnergyLedger:
    """Energies of a simulation [M L^2/T^2]; arrays shared with the compiled kernels."""

    def __init__(self):
        self.acc = np.zeros(N_ACC)
        self.energy = np.zeros(N_ENERGY)

    def reset(self):
        """Start a new balance from the current state: the energy held now becomes the
        initial input, accumulated terms and running maxima restart from it."""
        held = self.kinetic + self.strain
        self.acc[:] = 0.0
        self.acc[A_INITIAL] = held
        _py(update_peaks)(self.acc, self.energy)

    # state terms
    @property
    def kinetic_translational(self) -> float:
        return float(self.energy[E_KIN_T])

    @property
    def kinetic_rotational(self) -> float:
        return float(self.energy[E_KIN_R])

    @property
    def kinetic(self) -> float:
        return float(_py(energy_kinetic)(self.energy))

    @property
    def strain(self) -> float:
        return float(_py(energy_stored)(self.energy))

    # accumulated terms
    @property
    def friction(self) -> float:
        return float(self.acc[A_FRICTION])

    @property
    def damping(self) -> float:
        return float(self.acc[A_DASHPOT] + self.acc[A_LOCAL] + self.acc[A_GLOBAL])

    @property
    def rolling(self) -> float:
        """Dissipated by rolling and twisting resistance (plastic and viscous)."""
        return float(self.acc[A_ROLLING] + self.acc[A_ROLLING_VISCOUS])

    @property
    def bond_broken(self) -> float:
        """Strain energy released by bonds as they broke."""
        return float(self.acc[A_BOND_BROKEN])

    @property
    def inserted(self) -> float:
        """Brought in by inserted particles (their kinetic energy)."""
        return float(self.acc[A_INSERTED])

    @property
    def removed(self) -> float:
        """Taken out by removed particles (kinetic and contact energy)."""
        return float(self.acc[A_REMOVED])

    @property
    def internal(self) -> float:
        return self.strain + float(_py(energy_dissipated)(self.acc))

    @property
    def external(self) -> float:
        return float(_py(energy_supplied)(self.acc))

    def imbalance(self) -> float:
        """W_kin + W_int - W_ext (zero for a perfect ledger)."""
        return self.kinetic + self.internal - self.external

    def scale(self) -> float:
        """S(t), the running maximum of max(|W_ext|, |W_int|, W_kin) (module docstring;
        the terms now count too, for a ledger the step has not updated)."""
        return max(float(self.acc[A_PEAK_SCALE]), abs(self.external), abs(self.internal),
                   self.kinetic)

    def balance_error(self, floor: float = 0.0) -> float:
        """The normalized energy difference |W_kin + W_int - W_ext| / S(t) (eq. 22 with
        the running scale of the module docstring); NaN while S(t) <= ``floor`` (the
        energies are too small for the balance to mean anything: the energy monitor's
        floor), 0 when every term vanishes."""
        s = self.scale()
        if s <= floor and floor > 0.0:
            return math.nan
        return abs(self.imbalance()) / s if s > 0 else 0.0

    def as_dict(self, floor: float = 0.0) -> dict:
        """Every term by name, and ``energy_error`` as the monitor evaluates it
        (:meth:`balance_error` with the monitor's ``floor``: NaN below it)."""
        return {
            "kinetic_translational": self.kinetic_translational,
            "kinetic_rotational": self.kinetic_rotational,
            "strain_normal": float(self.energy[E_STRAIN_N]),
            "strain_tangential": float(self.energy[E_STRAIN_T]),
            "strain_rolling": float(self.energy[E_STRAIN_R]),
            "strain_bonds": float(self.energy[E_STRAIN_BOND]),
            "friction": self.friction,
            "rolling_plastic": float(self.acc[A_ROLLING]),
            "rolling_viscous": float(self.acc[A_ROLLING_VISCOUS]),
            "bond_broken": self.bond_broken,
            "damping_dashpot": float(self.acc[A_DASHPOT]),
            "damping_local": float(self.acc[A_LOCAL]),
            "damping_global": float(self.acc[A_GLOBAL]),
            "work_body": float(self.acc[A_BODY]),
            "work_applied": float(self.acc[A_APPLIED]),
            "work_walls": float(self.acc[A_WALLS]),
            "work_box": float(self.acc[A_BOX]),
            "initial": float(self.acc[A_INITIAL]),
            "external": self.external,
            "internal": self.internal,
            "energy_error": self.balance_error(floor),
        }


class EnergyBalanceError(RuntimeError):
    """The energy balance exceeded its tolerance and the monitor was set to stop;
    ``checkpoint`` is the path of the state saved then (if any)."""

    def __init__(self, message: str, checkpoint: str | None = None):
        super().__init__(message)
        self.checkpoint = checkpoint


@dataclass
class EnergyMonitor:
    """Checks the balance every ``every`` steps once its scale S(t) exceeds ``floor``
    [energy] (:meth:`EnergyLedger.balance_error`); ``action`` 'warn' logs (once per excursion) and records,
    'stop' ends the run (EnergyBalanceError, state saved)."""

    eps: float = DEFAULT_EPS
    every: int = 100
    action: str = "warn"
    floor: float | None = None
    #: (step, time [T], error) of each alarm raised by this object (not restored)
    alarms: list = field(default_factory=list)
    max_error: float = 0.0
    _alarmed: bool = False
    #: (step, time [T], error) of the first alarm of the run, kept across restarts
    first_alarm: tuple | None = None
    #: how many alarms (excursions above ``eps``) the run raised, kept across restarts
    n_alarms: int = 0

    @property
    def alarm(self) -> bool:
        """Whether the last evaluated error exceeded ``eps`` (the history's
        ``energy_alarm`` column)."""
        return self._alarmed

    def state(self) -> np.ndarray:
        """What a checkpoint keeps: [alarm, first alarm step, time, error, number of
        alarms] (step -1: no alarm yet). The monitor owns the run's alarm record: run.json
        reports it (:mod:`demstep.runner`), as of the step the state describes."""
        first = self.first_alarm if self.first_alarm is not None else (-1, 0.0, 0.0)
        return np.array([float(self._alarmed), *map(float, first), float(self.n_alarms)])

    def restore_state(self, values) -> None:
        """Restore :meth:`state` (a restart; older checkpoints without the number of
        alarms: the first alarm's only)."""
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        self._alarmed = bool(values[0])
        self.first_alarm = None
        if len(values) >= 4 and values[1] >= 0:
            self.first_alarm = (int(values[1]), float(values[2]), float(values[3]))
        self.n_alarms = (int(values[4]) if len(values) >= 5
                         else int(self.first_alarm is not None))

    def __post_init__(self):
        if self.action not in ("warn", "stop"):
            raise InputError(f"energy monitor action: must be warn or stop, got {self.action!r}")
        if not (self.eps > 0):
            raise InputError(f"energy monitor eps: must be > 0, got {self.eps!r}")
        if int(self.every) < 1:
            raise InputError(f"energy monitor every: must be >= 1, got {self.every!r}")

    def check(self, ledger: EnergyLedger, step: int, time: float, floor: float) -> float | None:
        """Returns the error if it was evaluated (the scale S(t) above ``floor``)."""
        err = ledger.balance_error(floor)
        if math.isnan(err) or (floor > 0.0 and ledger.scale() <= floor):
            return None
        self.max_error = max(self.max_error, err)
        if err > self.eps:
            if not self._alarmed:
                self.alarms.append((step, time, err))
                self.n_alarms += 1
                if self.first_alarm is None:
                    self.first_alarm = (step, time, err)
                log.warning("energy balance error %.3g exceeds %.3g at step %d (t = %.6g)",
                            err, self.eps, step, time)
                self._alarmed = True
            if self.action == "stop":
                raise EnergyBalanceError(f"energy balance error {err:.3g} exceeds {self.eps:g} at "
                                         f"step {step} (t = {time:.6g})")
        else:
            self._alarmed = False
        return err
