"""The plan of a sweep: key paths into a case, values, runs (the product of --param
values, or a runs file) and their ids (see :mod:`demstep.sweep`)."""

from __future__ import annotations

import copy
import csv
import hashlib
import itertools
import json
import logging
import math
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from demstep.case import case_from_dict, check_stages
from demstep.errors import InputError
from demstep.io.history import columns_for
from demstep.io.textfile import read_small_text
from demstep.runner import case_hash
from demstep.sweep.cluster import one_line

#: longest run id before it is shortened and a hash appended
MAX_ID_LENGTH = 100

log = logging.getLogger("demstep")



# ==================================================================== key paths
_SEGMENT = re.compile(r'\s*(?:"([^"]*)"|([A-Za-z0-9_+\-]+))\s*')
_INDEX = re.compile(r"\s*\[\s*(\d+)\s*\]\s*")
_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def parse_key(text: str) -> tuple:
    """``'stages[1].walls."y+".velocity'`` -> ``('stages', 1, 'walls', 'y+', 'velocity')``."""
    parts: list = []
    pos = 0
    text = str(text)
    while True:
        m = _SEGMENT.match(text, pos)
        if not m or m.end() == pos:
            raise InputError(f"param: not a key path like contact.mu or stages[1].mu, "
                             f"got {text!r}")
        parts.append(m.group(1) if m.group(1) is not None else m.group(2))
        pos = m.end()
        while (mi := _INDEX.match(text, pos)) is not None:
            parts.append(int(mi.group(1)))
            pos = mi.end()
        if pos == len(text):
            return tuple(parts)
        if text[pos] != ".":
            raise InputError(f"param: not a key path like contact.mu or stages[1].mu, "
                             f"got {text!r}")
        pos += 1


def key_text(path: tuple) -> str:
    """The canonical text of a key path (quotes around names that are not bare)."""
    out = ""
    for p in path:
        if isinstance(p, int):
            out += f"[{p}]"
        else:
            name = p if _BARE.match(p) else f'"{p}"'
            out += name if not out else "." + name
    return out


def parse_value(text: str):
    """A TOML value (``0.1``, ``5``, ``true``, ``"a"``, ``[0.0, -1.0]``); a number Python
    reads (``.5``); anything else is the string itself."""
    text = str(text).strip()
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        pass
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
        if math.isfinite(value):
            return value
    except ValueError:
        pass
    return text


def value_text(value) -> str:
    """A value as TOML text on one line (``0.1``, ``true``, ``"hertz"``, ``[0.0, -1.0]``,
    ``{local = 0.1}``)."""
    import tomli_w  # (deferred: a heavy import, loaded only when used)

    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(value_text(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{key_text((k,))} = {value_text(v)}"
                               for k, v in value.items()) + "}"
    return tomli_w.dumps({"v": value}).strip()[len("v = "):]


def split_values(text: str) -> list[str]:
    """Split ``0.1,0.2,[0.0, -1.0],"a,b"`` at the commas outside brackets and quotes."""
    out, depth, quote, start = [], 0, None, 0
    for i, ch in enumerate(text):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append(text[start:i])
            start = i + 1
    out.append(text[start:])
    return [s.strip() for s in out]


def parse_param(text: str) -> tuple[tuple, list]:
    """``'contact.mu=0.1,0.2'`` -> ``(('contact', 'mu'), [0.1, 0.2])``."""
    key, sep, values = str(text).partition("=")
    if not sep or not key.strip():
        raise InputError(f"param: expected KEY=VALUE[,VALUE...], got {text!r}")
    path = parse_key(key.strip())
    parts = split_values(values)
    if any(p == "" for p in parts):
        raise InputError(f"param: {key_text(path)}: empty value in {values!r}")
    return path, [parse_value(p) for p in parts]


def set_key(data: dict, path: tuple, value) -> None:
    """Set ``value`` at ``path`` in a case dict, creating missing tables on the way
    (unknown keys are then refused by the schema); a list index must exist."""
    node = data
    for depth, part in enumerate(path):
        last = depth == len(path) - 1
        here = key_text(path[:depth + 1])
        if isinstance(part, int):
            if not isinstance(node, list):
                raise InputError(f"{here}: {key_text(path[:depth]) or 'the case'} is not a list")
            if part >= len(node):
                raise InputError(f"{here}: no such entry, the case has {len(node)}")
            if last:
                node[part] = value
            else:
                node = node[part]
            continue
        if not isinstance(node, dict):
            raise InputError(f"{here}: {key_text(path[:depth])} is not a table")
        if last:
            node[part] = value
        else:
            if part not in node:
                node[part] = [] if isinstance(path[depth + 1], int) else {}
            node = node[part]


# ======================================================================== runs
def _flatten(table: dict, prefix: tuple, out: dict):
    for name, value in table.items():
        path = parse_key(name) if not prefix else prefix + (name,)
        if isinstance(value, dict):
            _flatten(value, path, out)
        else:
            out[path] = value


def read_runs_file(path) -> list[dict]:
    """The runs of a CSV file (header: the keys; each cell a value, empty: not set;
    lines starting with # are skipped) or of a TOML file of ``[[runs]]`` tables
    (nested tables and dotted keys give key paths; ``"stages[1].mu" = 0.5``). Each run
    is a dict key path -> value."""
    path = Path(path)
    if not path.is_file():
        what = "a folder, not a file" if path.is_dir() else "no such file"
        raise InputError(f"runs: {what}, got {str(path)!r}")
    try:
        text = read_small_text(path, "runs file")
    except InputError as exc:
        raise InputError(f"runs: {exc}") from None
    runs: list[dict] = []
    if path.suffix.lower() == ".toml":
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise InputError(f"runs: {path}: not valid TOML ({str(exc).splitlines()[0]})") from None
        extra = [k for k in data if k != "runs"]
        if extra:
            raise InputError(f"runs: {path}: unknown key {extra[0]!r} (only [[runs]] tables)")
        tables = data.get("runs")
        if not isinstance(tables, list) or not tables \
                or not all(isinstance(t, dict) for t in tables):
            raise InputError(f"runs: {path}: expected one or more [[runs]] tables")
        for k, table in enumerate(tables):
            run: dict = {}
            _flatten(table, (), run)
            runs.append(run)
        return runs
    if path.suffix.lower() != ".csv":
        raise InputError(f"runs: expected a .csv or .toml file, got {str(path)!r}")
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    try:
        rows = list(csv.reader(lines))
    except csv.Error as exc:  # (a field longer than the csv module takes)
        raise InputError(f"runs: {path}: not a CSV file of runs ({exc})") from None
    if len(rows) < 2:
        raise InputError(f"runs: {path}: expected a header of keys and at least one row")
    header = [parse_key(h.strip()) for h in rows[0]]
    if len(set(header)) != len(header):
        raise InputError(f"runs: {path}: a key appears twice in the header")
    for line, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise InputError(f"runs: {path}: row {line}: expected {len(header)} values, "
                             f"got {len(row)}")
        runs.append({key: parse_value(cell) for key, cell in zip(header, row) if cell.strip()})
    return runs


def combine_runs(params: Sequence[tuple[tuple, list]] = (),
                 file_runs: Sequence[dict] | None = None) -> tuple[list[tuple], list[dict]]:
    """The swept keys (in order: the file's, then the params') and the runs: every
    file run combined with every element of the product of the params' values."""
    keys: list[tuple] = []
    for run in file_runs or []:
        keys += [k for k in run if k not in keys]
    for path, _ in params:
        if path in keys:
            raise InputError(f"param: {key_text(path)} given twice")
        keys.append(path)
    grid = [dict(zip([p for p, _ in params], combo))
            for combo in itertools.product(*[values for _, values in params])]
    runs = [{**base, **extra} for base in (file_runs or [{}]) for extra in grid]
    return keys, runs


_UNSAFE = re.compile(r"[^A-Za-z0-9._+=\-]+")


def _id_value(value) -> str:
    if isinstance(value, str):
        return value
    if isinstance(value, list):
        return ",".join(_id_value(v) for v in value)
    if isinstance(value, dict):
        return ",".join(f"{k}={_id_value(v)}" for k, v in value.items())
    return value_text(value)


def _id_key(path: tuple) -> str:
    return ".".join(str(p) for p in path)


def _digest(overrides: dict) -> str:
    text = json.dumps([[key_text(k), v] for k, v in overrides.items()], default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:8]


def run_id(overrides: dict) -> str:
    """A readable, file-system-safe folder name made of the overrides."""
    text = "__".join(f"{_id_key(k)}={_id_value(v)}" for k, v in overrides.items()) or "base"
    text = _UNSAFE.sub("_", text).strip("._") or "run"
    if len(text) > MAX_ID_LENGTH:
        text = text[: MAX_ID_LENGTH - 9].rstrip("._") + "_" + _digest(overrides)
    return text


# ==================================================================== the plan
@dataclass
class SweepRun:
    """One run of a sweep: its id, overrides (key path -> value) and case dict."""

    run_id: str
    overrides: dict
    data: dict
    case_sha256: str


@dataclass
class SweepPlan:
    """A validated sweep: the case, the swept keys and the runs."""

    case_path: Path
    case_text: str
    keys: list[tuple]
    runs: list[SweepRun]
    eps: float
    case_name: str

    @property
    def key_names(self) -> list[str]:
        return [key_text(k) for k in self.keys]


def plan_sweep(case_path, params: Sequence[str] = (), runs_file=None,
               peak: str | None = None) -> SweepPlan:
    """Parse the parameters, build every run's case dict and validate each as
    ``demstep run`` does before it writes (the schema, then the build of its simulation
    and every stage's changes: :func:`demstep.case.check_stages`), and that ``peak``,
    when given, is a column of each run's history; raises a one-line InputError naming
    the run, key and value of the first bad one."""
    case_path = Path(case_path)
    case_text = read_small_text(case_path, "case file")
    try:
        base = tomllib.loads(case_text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{case_path}: not valid TOML ({str(exc).splitlines()[0]})") from None
    parsed = [parse_param(p) for p in params]
    file_runs = read_runs_file(runs_file) if runs_file is not None else None
    if not parsed and not file_runs:
        raise InputError("sweep: give at least one --param KEY=VALUES or --runs FILE")
    keys, combos = combine_runs(parsed, file_runs)
    runs: list[SweepRun] = []
    first = None
    seen: dict[str, int] = {}
    for n, overrides in enumerate(combos, start=1):
        ordered = {k: overrides[k] for k in keys if k in overrides}
        label = ", ".join(f"{key_text(k)}={value_text(v)}" for k, v in ordered.items())
        where = f"run {n} of {len(combos)} ({label or 'no overrides'})"
        data = copy.deepcopy(base)
        try:
            for k, v in ordered.items():
                set_key(data, k, v)
            case = case_from_dict(copy.deepcopy(data), base_dir=case_path.resolve().parent,
                                  source=str(case_path))
            check_stages(case)
        except InputError as exc:
            raise InputError(f"sweep: {where}: {exc}") from None
        if peak is not None:
            check_peak_column(peak, case, where)
        first = first or case
        rid = run_id(ordered)
        if rid in seen:
            other = runs[seen[rid]]
            if other.overrides == ordered:
                raise InputError(f"sweep: {where}: the same as run {seen[rid] + 1}")
            rid = f"{rid[: MAX_ID_LENGTH - 9]}_{_digest(ordered)}"
        seen[rid] = len(runs)
        runs.append(SweepRun(rid, ordered, data, case_hash(case)))
    return SweepPlan(case_path, case_text, keys, runs, first.energy.eps, first.name)


def check_peak_column(peak: str, case, where: str) -> None:
    """InputError unless ``peak`` is a column of the history the run of ``case``
    writes (the runner adds ``stage``)."""
    if not case.output.history_every:
        raise InputError(f"peak: {where}: the case writes no history (output.history_every "
                         f"= 0), so there is no column {peak!r}")
    columns = columns_for(case.dim, case.wall_names(), case.periodic_axes(), ["stage"],
                          mesh_names=[m.name for m in case.meshes],
                          feed_names=([i.name for i in case.insert], [o.name for o in case.outlet]))
    if peak not in columns:
        walls = [c for c in columns if "." in c]
        hint = f"; its wall and box columns: {', '.join(walls)}" if walls else \
            "; it has no wall or box columns"
        raise InputError(f"peak: {where}: no history column {peak!r}{hint}")
