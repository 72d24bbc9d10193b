"""Reading the text files users give (particle files, dumps, YADE exports, bond and body
lists, histories, case and materials files): checked first, then streamed.

* The path must name a regular file: a folder, a device (``/dev/zero``), a pipe or a
  socket is refused with one line saying which.
* The first :data:`FIRST_BLOCK` bytes must be text: no NUL byte (a binary file, or a
  sparse file's hole left by a power loss) and valid UTF-8. Such a file is refused at
  once, whatever its size.
* The rest is read line by line (:func:`open_text`), never whole: a line longer than
  :data:`MAX_LINE` characters or holding a NUL byte stops the reading with one line
  naming the file and the line. CSV readers take their rows through :func:`csv_rows`,
  which turns the csv module's errors (a field longer than its limit of 131072
  characters) into the same kind of line.
* Files that must be parsed whole (TOML) are read by :func:`read_small_text`, which
  refuses files larger than :data:`MAX_WHOLE_FILE` before reading them.

Every failure is an :class:`~demstep.errors.InputError` of one line naming the file.
"""

from __future__ import annotations

import codecs
import csv
import io
import os
import stat
from pathlib import Path

from demstep.errors import InputError

#: bytes checked before anything is parsed (a file shorter than this is checked whole)
FIRST_BLOCK = 64 * 1024
#: the longest line (in characters) the readers take: far above any row of the formats
#: read (a row of a dump with 50 columns is about 1 KB), so that a file without line
#: ends is refused before it fills the memory
MAX_LINE = 1 << 20
#: the largest file read whole (case and materials files)
MAX_WHOLE_FILE = 64 << 20

_LONG_LINE = (f"a line longer than {MAX_LINE} characters (the most a line of an input file "
              f"may have)")

_KINDS = ((stat.S_ISCHR, "character device"), (stat.S_ISBLK, "block device"),
          (stat.S_ISFIFO, "named pipe"), (stat.S_ISSOCK, "socket"))


def not_a_file_reason(path) -> str | None:
    """None when ``path`` is an existing regular file (or a link to one); else why
    not: ``"no such file"``, ``"a folder"``, ``"a character device"`` (/dev/zero),
    ``"a named pipe"``, ...; or ``"cannot be read (<reason>)"`` when it cannot be
    looked up (e.g. a name longer than the file system takes)."""
    try:
        mode = os.stat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return "no such file"
    except (OSError, ValueError) as exc:
        return f"cannot be read ({getattr(exc, 'strerror', None) or exc})"
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "a folder"
    kind = next((name for test, name in _KINDS if test(mode)), "special file")
    return f"a {kind}"


def not_a_file_message(reason: str, what: str = "file") -> str:
    """The words for :func:`not_a_file_reason` ``reason`` of a ``what`` ("no such
    case file", "a folder, not a case file", "a character device, not a regular
    file")."""
    if reason == "no such file":
        return f"no such {what}"
    if reason == "a folder":
        return f"a folder, not a {what}"
    if reason.startswith("cannot"):
        return reason
    return f"{reason}, not a regular file"


def check_regular_file(path, what: str = "file") -> Path:
    """``path`` as a Path when it is an existing regular file; else InputError
    ``"<path>: <why>"`` (:func:`not_a_file_message`), or ``"<what>: cannot read
    '<path>' (<why>)"`` when it cannot be looked up."""
    reason = not_a_file_reason(path)
    if reason is not None and reason.startswith("cannot"):  # (the path may be very long)
        raise InputError(f"{what}: cannot read {str(path)!r} {reason[len('cannot be read '):]}")
    if reason is not None:
        raise InputError(f"{path}: {not_a_file_message(reason, what)}")
    return Path(path)


def check_text_start(path, head: bytes, what: str = "file", final: bool = False):
    """Raise InputError naming ``path`` when ``head`` (the first bytes of the file;
    ``final``: the whole file) is not UTF-8 text without NUL bytes."""
    nul = head.find(b"\0")
    if nul >= 0:
        raise InputError(f"{path}: not a text {what} (a NUL byte at byte {nul})")
    try:
        codecs.getincrementaldecoder("utf-8")().decode(head, final)
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a text {what} (byte {exc.start} is not UTF-8)") from None


class TextLines:
    """The lines of a checked text file, read one at a time (an iterator of str with
    their line ends); ``number`` is the number of the line last read (1-based). Use
    as a context manager, or call :meth:`close`."""

    def __init__(self, path, fh, what: str):
        self.path, self.what = path, what
        self._fh = fh
        self.number = 0

    def __iter__(self):
        return self

    def __next__(self) -> str:
        try:
            line = self._fh.readline(MAX_LINE + 1)
        except UnicodeDecodeError:
            raise InputError(f"{self.path}:{self.number + 1}: not a text {self.what} "
                             "(not UTF-8)") from None
        except OSError as exc:
            raise InputError(f"{self.path}: cannot read ({exc.strerror or exc})") from None
        if not line:
            raise StopIteration
        self.number += 1
        if "\0" in line:
            raise InputError(f"{self.path}:{self.number}: not a text {self.what} (NUL bytes "
                             f"on this line)")
        if len(line) > MAX_LINE and line[-1] not in "\r\n":
            raise InputError(f"{self.path}:{self.number}: {_LONG_LINE}")
        return line

    def close(self):
        self._fh.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def open_text(path, what: str = "file", encoding: str = "utf-8",
              newline: str | None = None) -> TextLines:
    """Open the user's text file ``path`` for reading line by line, after checking
    that it is a regular file whose first block is text (module docstring). A
    ``newline=""`` reading (csv) keeps the line ends as written."""
    path = check_regular_file(path, what)
    try:
        raw = open(path, "rb")
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    try:
        head = raw.read(FIRST_BLOCK)
        check_text_start(path, head, what, final=len(head) < FIRST_BLOCK)
        raw.seek(0)
    except OSError as exc:
        raw.close()
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except InputError:
        raw.close()
        raise
    fh = io.TextIOWrapper(raw, encoding=encoding, newline=newline)
    return TextLines(path, fh, what)


def csv_rows(lines: TextLines):
    """The rows of a CSV file read through ``lines`` (:func:`open_text` with
    ``newline=""``), as :func:`csv.reader` gives them; its errors (a field longer than
    the csv module's limit, a bad quote) as one InputError naming the file and line."""
    reader = csv.reader(lines)
    while True:
        try:
            row = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            why = (f"a field longer than {csv.field_size_limit()} characters (the csv "
                   f"module's limit)" if "field limit" in str(exc) else f"not CSV ({exc})")
            raise InputError(f"{lines.path}:{lines.number}: {why}") from None
        yield row


def read_small_text(path, what: str = "file", encoding: str = "utf-8",
                    limit: int = MAX_WHOLE_FILE) -> str:
    """The whole text of a file that can only be parsed whole (TOML): a regular file
    of at most ``limit`` bytes, UTF-8 without NUL bytes; else one InputError naming
    the file."""
    path = check_regular_file(path, what)
    try:
        size = os.stat(path).st_size
        if size > limit:
            raise InputError(f"{path}: {size} bytes, too large for a {what} (at most "
                             f"{limit})")
        with open(path, "rb") as fh:
            data = fh.read(limit + 1)
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if len(data) > limit:  # (grown since it was looked at)
        raise InputError(f"{path}: more than {limit} bytes, too large for a {what}")
    check_text_start(path, data, what, final=True)
    return data.decode(encoding)


def count_lines(path, what: str = "file") -> int:
    """The number of lines of the text file ``path`` (an upper bound on its rows),
    counted in chunks without holding the file; refuses, as :func:`open_text`, a
    file that is no regular file, has a NUL byte or a line longer than
    :data:`MAX_LINE` characters (counted from its bytes: UTF-8 takes at most 4 a
    character)."""
    path = check_regular_file(path, what)
    lines, offset, line_start = 0, 0, 0
    try:
        with open(path, "rb") as fh:
            head = fh.read(FIRST_BLOCK)
            check_text_start(path, head, what, final=len(head) < FIRST_BLOCK)
            chunk = head
            while chunk:
                nul = chunk.find(b"\0")
                if nul >= 0:
                    line = lines + 1 + chunk.count(b"\n", 0, nul)
                    raise InputError(f"{path}:{line}: not a text {what} (a NUL byte at byte "
                                     f"{offset + nul})")
                ends = chunk.count(b"\n")
                if ends:
                    line_start = offset + chunk.rindex(b"\n") + 1
                lines += ends
                offset += len(chunk)
                if offset - line_start > 4 * MAX_LINE:
                    raise InputError(f"{path}:{lines + 1}: {_LONG_LINE}")
                chunk = fh.read(1 << 22)
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    return max(1, lines + (offset > line_start))
