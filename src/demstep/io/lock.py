"""Exclusive locks on output folders, so that two processes never write into one.

A :class:`FolderLock` holds ``fcntl.flock`` on the file ``FOLDER/.demstep.lock``; the
operating system releases it when the process ends in any way (SIGKILL included), so
a lock is never stale. The file holds the process id and host of its holder, for the
message a second process gets. The holder deletes it before unlocking, so a finished
run leaves no lock file; a process that opened the file and locked it after that
finds that its file is no longer the one at the path (another inode, or none) and
starts again, so two processes never both hold "the" lock (the usual protocol for
deletable lock files). A killed process leaves the file, unlocked: the next one takes
it. On systems without ``fcntl`` (Windows) folders are not locked.
"""

from __future__ import annotations

import logging
import os
import platform
from pathlib import Path

from demstep.errors import InputError
from demstep.io.atomic import check_name_lengths

try:  # POSIX
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

#: the lock file in every folder demstep writes a run or a sweep into
LOCK_NAME = ".demstep.lock"
#: times :meth:`FolderLock.acquire` opens the lock file anew when it was deleted between
#: opening and locking (a holder releasing it) before it gives up
LOCK_ATTEMPTS = 100

log = logging.getLogger("demstep")


class FolderLock:
    """An exclusive lock on ``folder`` (which must exist). ``key`` names the option
    in messages (``out``). Use as a context manager or call :meth:`acquire` and
    :meth:`release`."""

    def __init__(self, folder, key: str = "out"):
        self.folder = Path(folder)
        self.key = key
        self.path = self.folder / LOCK_NAME
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> "FolderLock":
        """Take the lock at once or raise InputError naming the process holding it."""
        if self._fd is not None:
            return self
        for _ in range(LOCK_ATTEMPTS):
            fd = self._open_locked()
            if fd is not None:
                break
        else:
            raise InputError(f"{self.key}: cannot lock {self.folder}: its lock file "
                             f"{LOCK_NAME} changed under each of {LOCK_ATTEMPTS} attempts")
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()} {platform.node()}\n".encode(), 0)
        except OSError:
            pass  # the holder's id is only for messages
        self._fd = fd
        return self

    def _open_locked(self) -> int | None:
        """The lock file open and locked, or None when the file was deleted (by the
        holder releasing it) between opening and locking: the caller opens anew."""
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise InputError(f"{self.key}: cannot write into {self.folder} "
                             f"({exc.strerror or exc})") from None
        if fcntl is None:
            return fd
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_holder(fd)
            os.close(fd)
            raise InputError(f"{self.key}: {self.folder} is in use by another demstep "
                             f"process{holder}; wait for it to end or choose another "
                             f"folder") from None
        except OSError as exc:  # a file system without locks (some network mounts)
            log.warning("%s: cannot lock %s (%s); continuing without a lock", self.key,
                        self.folder, exc.strerror or exc)
            return fd
        try:
            ours = _is_file_at(fd, self.path)
        except OSError as exc:
            os.close(fd)
            raise InputError(f"{self.key}: cannot lock {self.folder} "
                             f"({exc.strerror or exc})") from None
        if not ours:
            os.close(fd)
            return None
        return fd

    def release(self) -> None:
        """Delete the lock file (while still holding it), then unlock."""
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        if fcntl is None:  # no lock; an open file cannot be deleted there (Windows)
            os.close(fd)
            _unlink_quietly(self.path)
            return
        try:
            # only our own file: if it was deleted by hand while we held it, another
            # process may hold a new one at the path
            if _is_file_at(fd, self.path):
                _unlink_quietly(self.path)
        except OSError:
            pass  # the lock is released below anyway
        try:
            fcntl.flock(fd, fcntl.LOCK_UN)
        except OSError:
            pass  # closing the file releases the lock anyway
        finally:
            os.close(fd)

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()


def _is_file_at(fd: int, path: Path) -> bool:
    """Whether the open file ``fd`` is the file at ``path`` (False when none is)."""
    mine = os.fstat(fd)
    try:
        there = os.stat(path)
    except FileNotFoundError:
        return False
    return (mine.st_dev, mine.st_ino) == (there.st_dev, there.st_ino)


def _unlink_quietly(path: Path) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass  # gone already, or a read-only folder


def _read_holder(fd: int) -> str:
    try:
        text = os.pread(fd, 200, 0).decode("utf-8", "replace").split()
    except OSError:
        return ""
    if len(text) >= 2 and text[0].isdigit():
        return f" (pid {text[0]} on {text[1]})"
    return ""


def folder_is_empty(folder) -> bool:
    """Whether ``folder`` holds nothing but its lock file."""
    return not any(p.name != LOCK_NAME for p in Path(folder).iterdir())


def make_folder(folder, key: str = "out") -> Path:
    """Create ``folder`` (and its parents) or raise a one-line InputError naming
    ``key`` and the reason (a parent is a file, no permission, a read-only or virtual
    file system)."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise InputError(f"{key}: not a folder, got {str(folder)!r}") from None
    except OSError as exc:
        raise InputError(f"{key}: cannot create the folder {str(folder)!r} "
                         f"({exc.strerror or type(exc).__name__})") from None
    if not folder.is_dir():
        raise InputError(f"{key}: not a folder, got {str(folder)!r}")
    return folder


def check_folder_creatable(folder, key: str = "out") -> None:
    """Before anything is written: raise InputError when ``folder`` cannot be a
    writable folder (it is a file, a parent is a file, the nearest existing parent is
    not writable), or is given as an empty name (an unset shell variable: ``--out ""``
    would mean the current folder). Creating it may still fail (a virtual file system
    such as /proc): :func:`make_folder` reports that."""
    if isinstance(folder, str) and not folder.strip():
        raise InputError(f"{key}: an empty folder name, got {folder!r} (an unset shell "
                         f"variable?); give the folder to write into ('.' for this one)")
    folder = Path(folder)
    check_name_lengths(folder, key, is_file=False)
    try:
        if folder.exists() and not folder.is_dir():
            raise InputError(f"{key}: not a folder, got {str(folder)!r}")
        probe = folder
        while not probe.exists() and probe.parent != probe:
            probe = probe.parent
        if probe.exists() and not probe.is_dir():
            raise InputError(f"{key}: {str(probe)!r} is a file, not a folder, so "
                             f"{str(folder)!r} cannot be made")
        writable = os.access(probe, os.W_OK | os.X_OK)
    except OSError as exc:
        raise InputError(f"{key}: cannot access {str(folder)!r} "
                         f"({exc.strerror or type(exc).__name__})") from None
    if not writable:
        what = "" if probe == folder else f" (its parent {str(probe)!r} is not writable)"
        raise InputError(f"{key}: cannot write into {str(folder)!r}{what}")
