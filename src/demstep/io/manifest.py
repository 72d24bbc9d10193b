"""What demstep wrote into an output folder, so that ``--overwrite`` removes exactly that.

A run (``demstep run``), the paper's job (``demstep paper``) and ``demstep plot`` list
every file they create in the folder's manifest, ``.demstep-written``: one path per line,
relative to the folder, recorded *before* the file is written (a process killed in
between leaves a name whose file does not exist, never a file the manifest misses).
Replacing the folder's results removes the files listed and the folders that are empty
afterwards; anything else in the folder (the user's own notes, a ``vtk/`` file of their
own, a folder given by mistake such as the current one) stays where it is.

Folders written by a demstep from before the manifest have none: there the files
removed are the top-level outputs by name and, inside the output folders, only files
whose names match the patterns demstep writes (``LEGACY_PATTERNS``).
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path, PurePosixPath
from typing import Iterable

log = logging.getLogger("demstep")

MANIFEST_NAME = ".demstep-written"

#: names demstep wrote in an output folder before it kept a manifest (folder -> pattern)
LEGACY_PATTERNS = {
    "vtk": re.compile(r"^(particles|contacts|walls|bodies)(_\d{10}\.vtu|\.pvd)$"),
    "checkpoints": re.compile(r"^(step\d{10}\.(npz|json)|demstep-[a-z]+-step\d+\.(npz|json))$"),
    "plots": re.compile(r"^[A-Za-z0-9_.-]+\.(png|pdf|svg)$"),
    "data": re.compile(r"^[A-Za-z0-9_.-]+\.(csv|json|npz)$"),
}


class OutputManifest:
    """The manifest of ``folder``: :meth:`record` paths before writing them."""

    def __init__(self, folder):
        self.folder = Path(folder)
        self.path = self.folder / MANIFEST_NAME
        self._known = set(read_manifest(self.folder) or ())

    def record(self, *paths) -> None:
        """Add ``paths`` (inside the folder; absolute or relative to it) to the manifest."""
        new = []
        for p in paths:
            rel = _relative(self.folder, p)
            if rel not in self._known:
                self._known.add(rel)
                new.append(rel)
        if new:
            # appended and flushed: each line is whole before the file it names exists
            with open(self.path, "a", encoding="utf-8") as fh:
                fh.write("".join(f"{rel}\n" for rel in new))
                fh.flush()

    def __call__(self, path) -> None:
        self.record(path)


def _relative(folder: Path, path) -> str:
    """``path`` (a path of a file in ``folder``, as the writer names it: ``folder / ...``
    or absolute) relative to ``folder``, in POSIX form."""
    rel = PurePosixPath(*Path(os.path.relpath(os.path.abspath(path),
                                              os.path.abspath(folder))).parts)
    if ".." in rel.parts or str(rel) in ("", "."):
        raise ValueError(f"{path}: not a path inside the output folder {folder}")
    return str(rel)


def read_manifest(folder) -> list[str] | None:
    """The paths the manifest of ``folder`` lists (None: the folder has none). Lines
    that could not name a file of the folder (absolute, ``..``, damaged) are skipped."""
    path = Path(folder) / MANIFEST_NAME
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        return None
    except OSError:
        return []
    out = []
    for line in text.splitlines():
        rel = PurePosixPath(line.strip())
        if line.strip() and not rel.is_absolute() and ".." not in rel.parts \
                and "\x00" not in line and "\ufffd" not in line:
            out.append(str(rel))
    return out


def remove_written(folder, top_level: Iterable[str]) -> list[Path]:
    """Remove what demstep wrote in ``folder``: the files its manifest lists, or, for a
    folder from before manifests, the files and folders named in ``top_level`` whose
    contents match :data:`LEGACY_PATTERNS` (a top-level file of that name is removed).
    Folders left empty are removed. Returns the files kept (not written by demstep)."""
    folder = Path(folder)
    listed = read_manifest(folder)
    dirs = set()
    if listed is not None:
        for rel in listed:
            path = folder / rel
            _unlink(path)
            for parent in Path(rel).parents:
                if str(parent) != ".":
                    dirs.add(folder / parent)
        _unlink(folder / MANIFEST_NAME)
    else:
        for name in top_level:
            path = folder / name
            if path.is_symlink() or path.is_file():
                _unlink(path)
            elif path.is_dir():
                pattern = LEGACY_PATTERNS.get(name)
                for child in path.iterdir():
                    if pattern is not None and pattern.match(child.name) \
                            and (child.is_file() or child.is_symlink()):
                        _unlink(child)
                dirs.add(path)
    kept = []
    for d in sorted(dirs, key=lambda p: len(p.parts), reverse=True):
        if d.is_symlink() or not d.is_dir():
            continue
        try:
            d.rmdir()
        except OSError:  # not empty: what is left is not demstep's
            kept += [p for p in d.rglob("*") if not p.is_dir()]
    return sorted(set(kept))


def _unlink(path: Path) -> None:
    """Remove a file or a symbolic link (never what a link points to)."""
    try:
        if path.is_symlink() or path.is_file():
            os.unlink(path)
    except FileNotFoundError:
        pass
