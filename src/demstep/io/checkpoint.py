"""Checkpoints: the complete dynamic state of a Simulation in one .npz file.

Writes are atomic (a temporary file in the same folder, then rename), so a crash never
leaves a corrupt checkpoint. A restart restores the state into a Simulation built
from the same case and continues bit for bit as the uninterrupted run would have:
positions, half-step velocities, contact and wall history, the Verlet lists and their
reference positions, wall state, the energy ledger, step, time and time step.
"""

from __future__ import annotations

import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from demstep import __version__
from demstep.errors import InputError
from demstep.io.atomic import atomic_path
from demstep.io.textfile import not_a_file_reason

#: format 4: the state of the bundles of :mod:`demstep.state` and of the Simulation's
#: parts (``Simulation.state_dict``), its scalars by name; format 3 (the scalars in one
#: array) still loads
FORMAT_VERSION = 4
READABLE_FORMATS = (3, 4)


def save_checkpoint(sim, path) -> Path:
    """Write ``sim.state_dict()`` to ``path`` (.npz) atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = dict(sim.state_dict())
    data.update(format=np.array([FORMAT_VERSION]), version=np.array([__version__]))
    with atomic_path(path, suffix=".npz.tmp") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **data)
            fh.flush()
            os.fsync(fh.fileno())
    return path


#: the first bytes of an .npz file (a zip archive)
_ZIP_MAGIC = b"PK\x03\x04"


def read_checkpoint_arrays(path) -> dict:
    """Every array of the checkpoint ``path``, read and decompressed; InputError with
    one line saying why when it is not a readable demstep checkpoint (a folder, a
    missing file, another kind of file, a damaged or truncated archive)."""
    path = Path(path)
    reason = not_a_file_reason(path)
    if reason == "a folder":
        raise InputError(f"{path}: a folder, not a checkpoint file (.npz)")
    if reason == "no such file":
        raise InputError(f"{path}: no such checkpoint file")
    if reason is not None:
        raise InputError(f"{path}: {reason}, not a checkpoint file (.npz)")
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(_ZIP_MAGIC))
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if head != _ZIP_MAGIC:
        kind = "an empty file" if not head else (
            "a JSON file (the run state beside a checkpoint?)" if head[:1] in (b"{", b"[")
            else "not a zip archive")
        raise InputError(f"{path}: not a demstep checkpoint (.npz): {kind}")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError) as exc:
        text = " ".join(str(exc).split())
        raise InputError(f"{path}: a damaged or truncated checkpoint "
                         f"({type(exc).__name__}: {text})") from None
    if "format" not in arrays or arrays["format"].shape != (1,) \
            or int(arrays["format"][0]) not in READABLE_FORMATS:
        raise InputError(f"{path}: not a demstep checkpoint (format "
                         f"{' or '.join(map(str, READABLE_FORMATS))})")
    missing = [name for name in ("r", "scalars" if int(arrays["format"][0]) == 3
                                 else "scalars.step", "spheres.x", "wall_state.point")
               if name not in arrays]
    if missing:
        raise InputError(f"{path}: a damaged checkpoint (array {missing[0]!r} missing)")
    return arrays


def load_checkpoint(sim, path):
    """Restore the state saved in ``path`` into ``sim`` (built from the same case)."""
    path = Path(path)
    return sim.load_state_dict(read_checkpoint_arrays(path), source=str(path))
