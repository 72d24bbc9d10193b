"""Atomic writes: a temporary file in the destination folder, then a rename, so that a
crash never leaves a half-written output behind.

Temporary files are created with mode 0666 less the process umask (as ``open`` does),
so results are as readable as any other file the user writes, and are named
``.<target name>.<8 hex digits>.tmp``. A process killed between creating one and the
rename (SIGKILL, power loss) leaves it behind; :func:`remove_orphans` deletes them
(the runner calls it on the folders it holds the lock of).
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
from pathlib import Path

from demstep.errors import InputError

#: names of the temporary files of :func:`atomic_path` (and of ``tempfile.mkstemp``,
#: which demstep used before: ``tmpXXXXXXXX<suffix>``)
TEMP_NAME = re.compile(r"^(\..+\.[0-9a-f]{8}\.tmp|tmp[A-Za-z0-9_]{8}(\.npz)?\.tmp)$")


def _create_temporary(folder: Path, name: str) -> Path:
    """Create an empty, new temporary file for ``name`` in ``folder`` (mode 0666 less
    the umask) and return its path."""
    for _ in range(100):
        tmp = folder / f".{name}.{secrets.token_hex(4)}.tmp"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        return tmp
    raise FileExistsError(f"cannot create a temporary file for {name} in {folder}")


#: characters a temporary name adds to its target's (``.`` + ``.<8 hex>.tmp``)
TEMP_NAME_EXTRA = 14


def check_name_lengths(path, key: str, is_file: bool = True) -> None:
    """Before anything is written: raise InputError when a part of ``path`` is longer
    than the file system takes (NAME_MAX bytes; the last part of a file's path with the
    :data:`TEMP_NAME_EXTRA` characters its temporary name adds) or the whole path longer
    than PATH_MAX: such a path would fail half-way, after folders were made."""
    path = Path(path).absolute()
    probe = path
    # (Path.exists raises OSError for a name too long rather than saying False)
    while not _exists(probe) and probe.parent != probe:
        probe = probe.parent
    try:
        name_max = os.pathconf(probe, "PC_NAME_MAX")
        path_max = os.pathconf(probe, "PC_PATH_MAX")
    except (OSError, ValueError):
        name_max, path_max = 255, 4096
    parts = path.parts[1:]
    for k, part in enumerate(parts):
        extra = TEMP_NAME_EXTRA if is_file and k == len(parts) - 1 else 0
        if len(part.encode()) + extra > name_max:
            raise InputError(f"{key}: the name {part[:40]!r}... is {len(part.encode())} bytes "
                             f"long; this file system takes at most {name_max - extra}")
    if len(str(path).encode()) + TEMP_NAME_EXTRA > path_max:
        raise InputError(f"{key}: the path is {len(str(path).encode())} bytes long; this file "
                         f"system takes at most {path_max - TEMP_NAME_EXTRA}")


def _exists(path) -> bool:
    """Whether ``path`` exists; False (not an OSError) when it cannot be looked up,
    e.g. a name longer than the file system takes."""
    try:
        os.stat(path)
    except (OSError, ValueError):
        return False
    return True


def check_writable(folder, key: str) -> None:
    """Before any work whose result goes into ``folder``: raise InputError naming the
    option ``key`` unless a file can be created there (or, when ``folder`` does not
    exist yet, in its nearest existing parent), by creating and deleting a temporary
    file. Catches what permission bits do not show (a virtual file system such as
    /proc, a read-only mount, root's writes refused)."""
    folder = Path(folder).absolute()
    probe = folder
    while not _exists(probe) and probe.parent != probe:
        probe = probe.parent
    try:
        tmp = _create_temporary(probe, "write-probe")
    except OSError as exc:
        where = "" if probe == folder else f" (nor in its parent {str(probe)!r})"
        raise InputError(f"{key}: cannot create a file in {str(folder)!r}{where} "
                         f"({exc.strerror or type(exc).__name__})") from None
    try:
        os.unlink(tmp)
    except OSError:
        pass


def naming(exc: OSError, path) -> OSError:
    """``exc`` (an error of writing ``path``, e.g. a full disk) as an OSError whose
    ``filename`` is ``path``: the write's own error names no file, or the temporary
    one, which is gone by the time the user reads the message."""
    if exc.errno is None:
        return exc
    return OSError(exc.errno, exc.strerror or os.strerror(exc.errno), str(path))


@contextlib.contextmanager
def atomic_path(path, suffix: str = ".tmp"):
    """Yield a temporary path beside ``path``; on success it replaces ``path``.
    An OSError while the temporary file is created, written (a full disk) or renamed
    is raised naming ``path`` (:func:`naming`), and the temporary file is removed.

    ``suffix`` is accepted for compatibility; the temporary file is always named
    ``.<name of path>.<random>.tmp`` (see :data:`TEMP_NAME`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        tmp = _create_temporary(path.parent, path.name)
    except OSError as exc:
        raise naming(exc, path) from exc
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as exc:
        raise naming(exc, path) from exc
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_text_atomic(path, text: str) -> Path:
    """Write ``text`` (UTF-8, newlines untranslated) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
    return Path(path)


def remove_orphans(*folders) -> list[Path]:
    """Delete the temporary files of interrupted atomic writes (:data:`TEMP_NAME`) in
    ``folders`` (not recursively; missing folders are skipped). Call it only on
    folders no other process is writing to (e.g. under a :class:`FolderLock`).
    Returns the files removed."""
    removed = []
    for folder in folders:
        folder = Path(folder)
        if not folder.is_dir():
            continue
        for entry in folder.iterdir():
            if TEMP_NAME.match(entry.name) and entry.is_file():
                try:
                    entry.unlink()
                    removed.append(entry)
                except FileNotFoundError:
                    pass
    return removed
