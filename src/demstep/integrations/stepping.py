"""What the live certifiers (LAMMPS, YADE) share: their settings' checks, the band that
keeps a peer code's step below the certified one without moving it back and forth, and
the reason logged with each change."""

from __future__ import annotations

import math

from demstep.errors import InputError

#: the methods a live certifier takes: the exact (certified) step or the element bound
METHODS = ("exact", "element")


def check_settings(safety, method, grow):
    """InputError naming the setting when ``safety`` is not in (0, 1], ``method`` not one
    of :data:`METHODS` or ``grow`` negative."""
    if not (isinstance(safety, (int, float)) and 0.0 < safety <= 1.0):
        raise InputError(f"safety: must lie in (0, 1], got {safety!r}")
    if method not in METHODS:
        raise InputError(f"method: must be 'exact' or 'element', got {method!r}")
    if not (isinstance(grow, (int, float)) and grow >= 0.0):
        raise InputError(f"grow: must be >= 0, got {grow!r}")


def band_change(dt_now: float, certified: float, safety: float, grow: float):
    """The step [T] to set and why, or None: the step is kept within [safety / (1 +
    grow)^2, safety] times the ``certified`` one; ``dt_now`` above the band is lowered at
    once and one below it raised, both to the band's middle, safety / (1 + grow) times
    the certified step (a step just set is not moved back at the next check; a step
    that keeps falling or rising changes about every ``grow``)."""
    top = safety * certified
    if dt_now > top:
        return top / (1.0 + grow), f"above {safety:g} x the certified step"
    if dt_now * (1.0 + grow) ** 2 < top:
        return top / (1.0 + grow), "the certified step allows a longer one"
    return None


def why(previous, cert) -> str:
    """What changed since the ``previous`` certificate (None, or one without a finite
    step: the first): the certified step, the contacts and the largest overlap."""
    if previous is None or not math.isfinite(previous.dt):
        return (f": certified {cert.dt:.6g} ({cert.method}), {cert.contacts} contacts, "
                f"largest overlap {cert.max_overlap:.3g} r")
    return (f": certified {previous.dt:.6g} -> {cert.dt:.6g} ({cert.method}), contacts "
            f"{previous.contacts} -> {cert.contacts}, largest overlap "
            f"{previous.max_overlap:.3g} -> {cert.max_overlap:.3g} r")
