"""demstep: explicit DEM for disks and spheres with a certified time step.

The time-step analysis follows O'Sullivan & Bray (2004), "Selecting a suitable time
step for discrete element simulations that use the central difference time
integration scheme", Engineering Computations 21:278-303, and extends it with a
coupled contact element, exact sparse and Bloch-wave eigenvalues and the estimates
DEM users know.
"""

from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("demstep")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0+unknown"

from demstep.errors import InputError  # noqa: E402

__all__ = ["__version__", "InputError"]
