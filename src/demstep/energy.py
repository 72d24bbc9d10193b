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
    normalized difference = |W_kin + W_int - W_ext| / max(W_ext, W_int, W_kin)   (eq. 22)

The ledger describes time t of the last force evaluation: after a step the positions
are already at t + dt (the kinetic energy at t needs v(t + dt/2)).

With the mean-velocity kinetic energy the difference is O((omega dt)^2) for a stable
linear run, exactly zero for free fall, and grows to order one as dt approaches the
critical step, which is what makes it an instability alarm.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from demstep.errors import InputError

# The ledger's layout, shared with the compiled kernels (which import it from here).
#: accumulated terms (array ``EnergyLedger.acc``): work of body forces, applied forces,
#: walls; dissipation by friction, contact dashpots, local and global damping; the
#: energy held when the ledger started; work of a deforming periodic box; dissipation
#: by rolling and twisting resistance (plastic limit, viscous part); strain energy
#: released by parallel bonds as they broke
(A_BODY, A_APPLIED, A_WALLS, A_FRICTION, A_DASHPOT, A_LOCAL, A_GLOBAL, A_INITIAL, A_BOX,
 A_ROLLING, A_ROLLING_VISCOUS, A_BOND_BROKEN) = range(12)
N_ACC = 12
#: state terms (array ``EnergyLedger.energy``): kinetic translation / rotation, strain
#: normal / tangential / rolling and twisting springs / parallel bonds
E_KIN_T, E_KIN_R, E_STRAIN_N, E_STRAIN_T, E_STRAIN_R, E_STRAIN_BOND = range(6)
N_ENERGY = 6

log = logging.getLogger("demstep")

#: the paper's tolerance on the normalized energy difference (eq. 22)
DEFAULT_EPS = 1e-2


class EnergyLedger:
    """Energies of a simulation [M L^2/T^2]; arrays shared with the compiled kernels."""

    def __init__(self):
        self.acc = np.zeros(N_ACC)
        self.energy = np.zeros(N_ENERGY)

    def reset(self):
        """Start a new balance from the current state: the energy held now becomes the
        initial input, accumulated terms restart at zero."""
        held = self.kinetic + self.strain
        self.acc[:] = 0.0
        self.acc[A_INITIAL] = held

    # state terms
    @property
    def kinetic_translational(self) -> float:
        return float(self.energy[E_KIN_T])

    @property
    def kinetic_rotational(self) -> float:
        return float(self.energy[E_KIN_R])

    @property
    def kinetic(self) -> float:
        return self.kinetic_translational + self.kinetic_rotational

    @property
    def strain(self) -> float:
        return float(self.energy[E_STRAIN_N] + self.energy[E_STRAIN_T] + self.energy[E_STRAIN_R]
                     + self.energy[E_STRAIN_BOND])

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
    def internal(self) -> float:
        return self.strain + self.friction + self.damping + self.rolling + self.bond_broken

    @property
    def external(self) -> float:
        return float(self.acc[A_BODY] + self.acc[A_APPLIED] + self.acc[A_WALLS] + self.acc[A_BOX]
                     + self.acc[A_INITIAL])

    def imbalance(self) -> float:
        """W_kin + W_int - W_ext (zero for a perfect ledger)."""
        return self.kinetic + self.internal - self.external

    def scale(self) -> float:
        return max(self.external, self.internal, self.kinetic)

    def balance_error(self) -> float:
        """Normalized energy difference of eq. 22 (0 when all terms vanish)."""
        s = self.scale()
        return abs(self.imbalance()) / s if s > 0 else 0.0

    def as_dict(self) -> dict:
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
            "energy_error": self.balance_error(),
        }


class EnergyBalanceError(RuntimeError):
    """The energy balance exceeded its tolerance and the monitor was set to stop;
    ``checkpoint`` is the path of the state saved then (if any)."""

    def __init__(self, message: str, checkpoint: str | None = None):
        super().__init__(message)
        self.checkpoint = checkpoint


@dataclass
class EnergyMonitor:
    """Checks eq. 22 every ``every`` steps once max(W_ext, W_int, W_kin) exceeds
    ``floor`` [energy]; ``action`` 'warn' logs (once per excursion) and records,
    'stop' ends the run (EnergyBalanceError, state saved)."""

    eps: float = DEFAULT_EPS
    every: int = 100
    action: str = "warn"
    floor: float | None = None
    alarms: list = field(default_factory=list)
    max_error: float = 0.0
    _alarmed: bool = False
    #: (step, time [T], error) of the first alarm of the run, kept across restarts
    first_alarm: tuple | None = None

    @property
    def alarm(self) -> bool:
        """Whether the last evaluated error exceeded ``eps`` (the history's
        ``energy_alarm`` column)."""
        return self._alarmed

    def state(self) -> np.ndarray:
        """What a checkpoint keeps: [alarm, first alarm step, time, error] (step -1:
        no alarm yet)."""
        first = self.first_alarm if self.first_alarm is not None else (-1, 0.0, 0.0)
        return np.array([float(self._alarmed), *map(float, first)])

    def restore_state(self, values) -> None:
        """Restore :meth:`state` (a restart)."""
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        self._alarmed = bool(values[0])
        if len(values) >= 4 and values[1] >= 0:
            self.first_alarm = (int(values[1]), float(values[2]), float(values[3]))

    def __post_init__(self):
        if self.action not in ("warn", "stop"):
            raise InputError(f"energy monitor action: must be warn or stop, got {self.action!r}")
        if not (self.eps > 0):
            raise InputError(f"energy monitor eps: must be > 0, got {self.eps!r}")
        if int(self.every) < 1:
            raise InputError(f"energy monitor every: must be >= 1, got {self.every!r}")

    def check(self, ledger: EnergyLedger, step: int, time: float, floor: float) -> float | None:
        """Returns the error if it was evaluated (energies above the floor)."""
        if ledger.scale() <= floor:
            return None
        err = ledger.balance_error()
        self.max_error = max(self.max_error, err)
        if err > self.eps:
            if not self._alarmed:
                self.alarms.append((step, time, err))
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
