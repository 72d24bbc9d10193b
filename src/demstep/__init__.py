"""demstep: explicit DEM for disks and spheres with a certified time step.

The time-step analysis follows O'Sullivan & Bray (2004), "Selecting a suitable time
step for discrete element simulations that use the central difference time
integration scheme", Engineering Computations 21:278-303, and extends it with a
coupled contact element, exact sparse and Bloch-wave eigenvalues and the estimates
DEM users know.
"""

import os as _os
from importlib.metadata import PackageNotFoundError, version as _version

# numba's threading layer: OpenMP first (TBB's scheduler costs milliseconds per parallel
# region on small machines; measured on the settling benchmark, 2 threads: 4.1-4.7 s
# with TBB against 3.3-3.7 s with OpenMP). numba reads this when it is imported; set
# here, without importing numba, so that it holds for a script that imports demstep and
# then numba (demstep._numba sets it again if numba came first).
_os.environ.setdefault("NUMBA_THREADING_LAYER_PRIORITY", "omp workqueue tbb")

try:
    __version__ = _version("demstep")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0+unknown"

from demstep.errors import InputError  # noqa: E402

__all__ = ["__version__", "InputError"]
