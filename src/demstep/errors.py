import os

"""Exceptions that reach the user as one-line messages, and the range of magnitudes
every input number must lie in."""

#: numbers beyond these magnitudes (other than 0) are refused, in case files, options
#: and particle files alike: no consistent set of units needs them, and products of two
#: of them overflow (or underflow) float64
MAX_MAGNITUDE = 1.0e100
MIN_MAGNITUDE = 1.0e-100


def magnitude_problem(value: float) -> str | None:
    """None when ``value`` is 0 or between :data:`MIN_MAGNITUDE` and
    :data:`MAX_MAGNITUDE` in magnitude; else what is wrong with it."""
    if value == 0 or MIN_MAGNITUDE <= abs(value) <= MAX_MAGNITUDE:
        return None
    return (f"must be 0 or between {MIN_MAGNITUDE:g} and {MAX_MAGNITUDE:g} in magnitude (a "
            "non-physical magnitude in any consistent units)")


class InputError(ValueError):
    """Bad input (a file, an option or a parameter).

    The message names the field and the offending value; the command line prints it
    on one line and exits with status 2 without a traceback.
    """


class SimulationDiverged(RuntimeError):
    """The explicit integration became unstable (non-finite values, runaway energy)."""

    def __init__(self, message: str, step: int | None = None, checkpoint: str | None = None):
        super().__init__(message)
        self.step = step
        self.checkpoint = checkpoint


def missing_file(path, what: str = "file") -> InputError:
    """The InputError for ``path`` that is not an existing regular file, naming why:
    ``"<path>: a folder, not a <what>"`` or ``"<path>: no such <what>"``."""
    if os.path.isdir(path):
        return InputError(f"{path}: a folder, not a {what}")
    return InputError(f"{path}: no such {what}")
