"""What every subcommand of the ``demstep`` command line shares: the parser that
reports bad usage on one line (exit 2), number types for options, and
:func:`run_parser`, which turns InputError and other failures into one line and an exit
status. Subcommand modules import only this module (no import cycles)."""

from __future__ import annotations

import argparse
import math
import re
import sys

from demstep.errors import InputError, magnitude_problem


def _parsed(name: str, text: str, kind=float, what: str = "a number"):
    """``text`` as a ``kind`` (float or int), else the option's one-line error (also for
    underscores, which Python reads: 1_0 is 10)."""
    try:
        if "_" in text:
            raise ValueError
        return kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{name}: not {what}: {text!r}") from None


def positive(name):
    def parse(text):
        v = _parsed(name, text)
        if not (v > 0 and v < float("inf")):
            raise argparse.ArgumentTypeError(f"{name}: must be a finite positive number, got {text!r}")
        return v
    return parse


def fraction(name):
    """An option ``name`` in (0, 1): a relative tolerance, a compressive strain."""
    def parse(text):
        v = positive(name)(text)
        if not v < 1.0:
            raise argparse.ArgumentTypeError(f"{name}: must lie in (0, 1), got {text!r}")
        return v
    return parse


def non_negative(name):
    def parse(text):
        v = _parsed(name, text)
        if not (v >= 0 and v < float("inf")):
            raise argparse.ArgumentTypeError(f"{name}: must be a finite number >= 0, got {text!r}")
        return v
    return parse


def positive_int(name):
    def parse(text):
        v = _parsed(name, text, int, "an integer")
        if v < 1:
            raise argparse.ArgumentTypeError(f"{name}: must be >= 1, got {text!r}")
        return v
    return parse


def number(name, minimum=None, strict=False):
    """A number option ``name``: finite, and >= ``minimum`` (> with ``strict``)."""

    def parse(text):
        v = _parsed(name, text)
        if not math.isfinite(v) or (minimum is not None and (v < minimum or (strict and v == minimum))):
            rel = ">" if strict else ">="
            bound = "" if minimum is None else f" {rel} {minimum:g}"
            raise argparse.ArgumentTypeError(f"{name}: must be a finite number{bound}, "
                                             f"got {text!r}")
        problem = magnitude_problem(v)
        if problem:
            raise argparse.ArgumentTypeError(f"{name}: {problem}, got {text!r}")
        return v
    return parse


#: a number as written on the command line (exponent forms, inf and nan included)
_NUMBER = r"((\d+\.?\d*|\.\d+)(e[+-]?\d+)?|inf|infinity|nan)"

#: an option's value that starts with a minus sign: a negative number (exponent forms
#: and -inf included) or numbers separated by commas and colons that start with one (a
#: point and a normal: ``--wall -0.03562,0,0:1,0,0``). argparse (through Python 3.13.0
#: at least) took ``-1e-5`` and ``-0.03562,0,0:1,0,0`` for options and said "expected
#: one argument" instead of passing them to the option's check, which names option and
#: value. No option of demstep looks like one, so such a token is always a value
NEGATIVE_VALUE = re.compile(rf"^-{_NUMBER}([,:][+-]?{_NUMBER})*$", re.IGNORECASE)


class Parser(argparse.ArgumentParser):
    """The parser of ``demstep`` and its subcommands: bad usage on one line (exit 2),
    and values that start with a minus sign followed by a number (``--kn -3``,
    ``--box -5 5``, ``--wall -1,0,0:1,0,0``) taken as values, not as unknown options
    (:data:`NEGATIVE_VALUE`); ``--option=value`` works too."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        # (argparse reads a token matching this as a value when the parser has no
        # option that looks like a negative number itself)
        self._negative_number_matcher = NEGATIVE_VALUE

    def error(self, message):  # one line, exit 2
        self.exit(2, f"demstep: error: {message}\n")


def run_parser(parser: argparse.ArgumentParser, argv=None) -> int:
    """Parse ``argv`` and run the chosen subcommand: InputError -> one line, exit 2;
    an operating-system error (disk full, no permission) -> one line, exit 1;
    Ctrl-C -> exit 130; a closed standard output (``| head``) -> quiet exit 141 as for
    the Unix tools killed by SIGPIPE."""
    args = parser.parse_args(argv)
    try:
        status = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe fails here, not at exit
        return status
    except BrokenPipeError:
        return _stdout_closed()
    except InputError as exc:
        print(f"demstep: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("demstep: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:
        where = f": {exc.filename}" if getattr(exc, "filename", None) else ""
        print(f"demstep: error: {exc.strerror or type(exc).__name__}{where}", file=sys.stderr)
        return 1


#: exit status after the reader of standard output went away (128 + SIGPIPE)
EXIT_BROKEN_PIPE = 141


def _stdout_closed() -> int:
    """Standard output is a pipe whose reader has gone: stop quietly. Point the file
    descriptor at /dev/null so that the interpreter's final flush does not fail again
    (https://docs.python.org/3/library/signal.html#note-on-sigpipe)."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass
    return EXIT_BROKEN_PIPE




def subcommand_parser(*adders) -> argparse.ArgumentParser:
    """A ``demstep`` parser with only the subcommands that ``adders`` register
    (standalone use of one subcommand module, and tests)."""
    parser = Parser(prog="demstep", description="Explicit DEM with a certified time step.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True
    for add in adders:
        add(sub)
    return parser
