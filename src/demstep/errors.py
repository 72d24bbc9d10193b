"""Exceptions that reach the user as one-line messages."""


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
    import os

    if os.path.isdir(path):
        return InputError(f"{path}: a folder, not a {what}")
    return InputError(f"{path}: no such {what}")
