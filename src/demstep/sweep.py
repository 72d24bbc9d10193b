"""Parameter sweeps of a case on Dask, and :func:`dask_map`, the helper they run on.

A sweep runs one case many times with some keys changed (``demstep sweep``)::

    demstep sweep case.toml --param contact.mu=0.1,0.2,0.3 \\
        --param timestep.alpha=0.05,0.35,0.4 --out sweep/

Keys are dotted paths into the case schema (:mod:`demstep.case`): ``contact.mu``,
``timestep.alpha``, ``stages[1].mu``, ``stages[0].walls."y+".velocity``. Values are TOML
values (``0.1``, ``1e4``, ``true``, ``"hertz"``, ``[0.0, -9.81]``); text that is not
TOML is taken as a string. The runs are the cartesian product of the values, or the
rows of a CSV file (header: the keys) or the ``[[runs]]`` tables of a TOML file (both
combined with any ``--param``). Every run's case is validated before anything is
written.

The output folder holds::

    sweep.json       the sweep: case, keys, runs (id and overrides), options
    case.toml        a copy of the case file as given
    summary.csv      one row per run (see SUMMARY_COLUMNS), rewritten as runs finish
    summary.png      max energy error and peak value against the first key
    runs/<run-id>/   each run's folder, written by demstep.runner.run_case

A run id is made of the overrides, ``contact.mu=0.1__timestep.alpha=0.05`` (index
brackets become dots, characters other than letters, digits and ``._+=-`` become
``_``; a short hash is appended when it is longer than :data:`MAX_ID_LENGTH`).
Running the same sweep into the same folder again skips every run whose ``run.json``
says completed, diverged or energy_stop for the same resolved case and
``--max-steps`` (resume), and runs the others (failed, unfinished, changed) afresh.

The output folder is locked while a sweep writes into it (a second sweep into the
same folder is refused), and each run's folder while its run writes. While the
cluster has no worker the sweep says so (with the number of runs pending); after
``worker_timeout`` seconds without one it gives up the runs not done, marked
'unfinished' in summary.csv (run the sweep again to resume them).

Execution (:func:`dask_client`): a ``distributed.LocalCluster`` of ``workers`` worker
processes of one thread each, or an existing cluster given by its scheduler address.
Each task runs numba with one thread (:data:`WORKER_ENV` on a local cluster and
``numba.set_num_threads(1)`` in the task): the worker processes already share the
cores. Each run writes its own folder on the worker, so with a remote cluster the
output folder must be on a file system every worker and the client share.
"""

from __future__ import annotations

import contextlib
import copy
import csv
import hashlib
import io
import itertools
import json
import logging
import math
import os
import platform
import re
import sys
import threading
import time as wallclock
import tomllib
import traceback
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

from demstep.errors import InputError, missing_file

#: environment of local-cluster worker processes: one thread each for numba, OpenMP
#: and BLAS (the worker processes themselves use the cores)
WORKER_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "OPENBLAS_NUM_THREADS": "1"}
#: seconds to wait for an existing scheduler to answer
CONNECT_TIMEOUT = 20
#: longest run id before it is shortened and a hash appended
MAX_ID_LENGTH = 100
#: run statuses that count as finished (a resumed sweep does not run them again)
FINISHED = ("completed", "diverged", "energy_stop")
#: summary.csv columns before and after the swept keys
SUMMARY_LEAD = ("run_id",)
SUMMARY_TAIL = ("status", "max_energy_error", "peak_column", "peak", "final_step",
                "final_time", "wall_time_s", "error")

log = logging.getLogger("demstep")


# ============================================================== Dask execution
@dataclass
class TaskResult:
    """The outcome of one item of :func:`dask_map`: ``ok`` and the ``value`` returned,
    or ``ok`` False (``failed`` True) with ``error`` (one line, ``"ValueError: ..."``)
    and the worker's ``traceback``."""

    ok: bool
    value: Any = None
    error: str = ""
    traceback: str = ""
    #: the item was never finished: no worker served it within the time limit
    unfinished: bool = False

    @property
    def failed(self) -> bool:
        """``not ok``."""
        return not self.ok

    def unwrap(self):
        """The value, or a RuntimeError carrying the error of a failed item."""
        if not self.ok:
            raise RuntimeError(self.error)
        return self.value


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _numba_one_thread() -> None:
    try:
        from demstep._numba import set_threads

        set_threads(1)
    except Exception:  # pragma: no cover - numba missing or unusable: nothing to limit
        pass


def _call_captured(func: Callable, item) -> TaskResult:
    """Run on a worker: ``func(item)`` with numba on one thread, exceptions captured."""
    _numba_one_thread()
    try:
        return TaskResult(True, func(item))
    except Exception as exc:
        return TaskResult(False, None, _one_line(exc), traceback.format_exc())


def worker_info(item=None) -> dict:
    """Where a task runs: host, process id and numba threads (check a cluster with
    ``dask_map(worker_info, range(4), scheduler=...)``)."""
    import numba

    return {"item": item, "host": platform.node(), "pid": os.getpid(),
            "numba_threads": numba.get_num_threads(),
            "NUMBA_NUM_THREADS": os.environ.get("NUMBA_NUM_THREADS")}


def check_scheduler_address(address: str) -> str:
    """``tcp://HOST:PORT`` (any protocol://, as distributed accepts); else InputError."""
    text = str(address).strip()
    if not re.match(r"^[a-z][a-z0-9+.-]*://\S+$", text):
        raise InputError(f"scheduler: expected an address like tcp://HOST:PORT, got {address!r}")
    return text


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int = 2):
    """A ``distributed.Client``: connected to the existing cluster at ``scheduler``
    (closed on exit; the cluster keeps running), or to a new
    ``LocalCluster(n_workers=workers, threads_per_worker=1, processes=True)`` whose
    workers run with :data:`WORKER_ENV` (shut down on exit). Raises InputError when
    the scheduler cannot be reached."""
    from distributed import Client, LocalCluster

    if scheduler:
        address = check_scheduler_address(scheduler)
        try:
            client = Client(address, timeout=CONNECT_TIMEOUT)
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(f"scheduler: cannot connect to {address} ({_one_line(exc)})") from None
        try:
            yield client
        finally:
            client.close()
        return
    if not isinstance(workers, int) or isinstance(workers, bool) or workers < 1:
        raise InputError(f"workers: must be an integer >= 1, got {workers!r}")
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR,
                           env=dict(WORKER_ENV))
    try:
        client = Client(cluster)
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


#: default of ``worker_timeout``: seconds a sweep waits while no worker is connected
WORKER_TIMEOUT = 600.0
#: seconds between reports while no worker is connected
WAIT_REPORT_EVERY = 60.0


def map_on_client(client, func: Callable, items: Sequence,
                  progress: Callable | None = None, worker_timeout: float | None = None,
                  on_wait: Callable | None = None) -> list[TaskResult]:
    """:func:`dask_map` on an open client: one task per item, results in item order;
    ``progress(index, result)`` is called in this process as each item finishes.

    While the cluster has no worker, ``on_wait(pending, seconds)`` is called (at once,
    then every :data:`WAIT_REPORT_EVERY` seconds) with the number of items pending
    and how long no worker has been connected. After ``worker_timeout`` seconds
    without a worker (None: wait for ever) the items still pending are given up: their
    results have ``ok`` False, ``unfinished`` True and an error saying why."""
    from distributed import as_completed

    items = list(items)
    if not items:
        return []
    futures = [client.submit(_call_captured, func, item, pure=False) for item in items]
    index = {f.key: k for k, f in enumerate(futures)}
    results: list[TaskResult | None] = [None] * len(items)
    pending = set(index.values())
    queue = as_completed(futures)
    poll = 0.2 if worker_timeout is None else min(0.2, max(0.02, worker_timeout / 20))
    next_check = wallclock.monotonic()
    alone_since = None  # when the cluster was last seen without a worker
    next_report = 0.0
    while pending:
        batch = queue.next_batch(block=False)
        if not batch:
            wallclock.sleep(poll)
            now = wallclock.monotonic()
            if now < next_check:
                continue
            next_check = now + min(2.0, 10 * poll)
            if _worker_count(client) > 0:
                alone_since = None
                continue
            if alone_since is None:
                alone_since, next_report = now, now
            waited = now - alone_since
            if on_wait is not None and now >= next_report:
                on_wait(len(pending), waited)
                next_report = now + WAIT_REPORT_EVERY
            if worker_timeout is not None and waited >= worker_timeout:
                _give_up(client, futures, index, pending, results, progress, waited,
                         worker_timeout)
                break
            continue
        for future in batch:
            k = index[future.key]
            try:
                result = future.result()
            except Exception as exc:  # the task never returned: worker lost, unpicklable...
                result = TaskResult(False, None, _one_line(exc), traceback.format_exc())
            results[k] = result
            pending.discard(k)
            future.release()
            if progress is not None:
                progress(k, result)
    return results


def _worker_count(client) -> int:
    """Workers connected to the scheduler now (-1 when it cannot be asked)."""
    try:
        return len(client.nthreads())
    except Exception:  # the scheduler is unreachable: the client reconnects or fails
        return -1


def _give_up(client, futures, index, pending, results, progress, waited, limit):
    """Mark the pending items unfinished and cancel their tasks."""
    error = (f"NoWorkers: no Dask worker for {waited:.0f} s (worker timeout "
             f"{limit:g} s); not run")
    left = [f for f in futures if index[f.key] in pending]
    try:
        client.cancel(left)
    except Exception:  # nothing to cancel on a scheduler that is gone
        pass
    for k in sorted(pending):
        results[k] = TaskResult(False, None, error, unfinished=True)
        if progress is not None:
            progress(k, results[k])
    pending.clear()


def dask_map(func: Callable, items: Iterable, scheduler: str | None = None, workers: int = 2,
             progress: Callable | None = None, worker_timeout: float | None = None,
             on_wait: Callable | None = None) -> list[TaskResult]:
    """Run ``func(item)`` for every item on Dask; return a :class:`TaskResult` per item,
    in the order of ``items``.

    ``func`` must be importable on the workers (a top-level function of an installed
    module, not a lambda or a closure) and items and results must pickle. Each call
    runs with numba on one thread. An exception in ``func`` does not stop the others:
    its item's result has ``ok`` False and ``error`` (``"ValueError: ..."``).

    ``scheduler``: the address (``tcp://HOST:PORT``) of a running cluster; None starts
    a local cluster of ``workers`` single-threaded processes and shuts it down on
    return. ``progress(index, result)``: called in this process as each item finishes
    (in completion order). ``worker_timeout`` and ``on_wait``: as for
    :func:`map_on_client` (what happens while the cluster has no worker).

    Example::

        from demstep.sweep import dask_map

        results = dask_map(my_module.simulate, [0.1, 0.2, 0.4])
        for r in results:
            print(r.value if r.ok else r.error)

    A script calling it with a local cluster must guard its entry point with
    ``if __name__ == "__main__":`` (worker processes are spawned)."""
    items = list(items)
    if not items:
        return []
    with dask_client(scheduler, workers) as client:
        return map_on_client(client, func, items, progress, worker_timeout, on_wait)


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
    import tomli_w

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
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"runs: cannot read {path} ({_one_line(exc)})") from None
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
    rows = list(csv.reader(lines))
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


def plan_sweep(case_path, params: Sequence[str] = (), runs_file=None) -> SweepPlan:
    """Parse the parameters, build every run's case dict and validate each; raises a
    one-line InputError naming the run, key and value of the first bad one."""
    from demstep.case import case_from_dict
    from demstep.runner import case_hash

    case_path = Path(case_path)
    if not case_path.is_file():
        raise missing_file(case_path, "case file")
    try:
        case_text = case_path.read_text(encoding="utf-8")
        base = tomllib.loads(case_text)
    except UnicodeDecodeError:
        raise InputError(f"{case_path}: not a text file") from None
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
        except InputError as exc:
            raise InputError(f"sweep: {where}: {exc}") from None
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


# ============================================================ one run (worker)
@dataclass
class RunTask:
    """What a worker needs to run one case of a sweep (pickled to the worker)."""

    run_id: str
    overrides: list  # [(key text, value)]
    data: dict
    base_dir: str
    source: str
    run_dir: str
    max_steps: int | None = None
    peak: str | None = None
    log_level: str = "INFO"


def run_task(task: RunTask) -> dict:
    """Run one case of a sweep into ``task.run_dir`` (on a worker) and return its
    summary row. Any exception is recorded (status 'failed', in ``run.json`` too),
    never raised. The runner's console log is silenced; ``run.log`` keeps it."""
    from demstep.case import case_from_dict
    from demstep.runner import run_case

    _numba_one_thread()
    run_dir = Path(task.run_dir)
    start = wallclock.perf_counter()
    status, error, trace = "failed", "", ""
    try:
        case = case_from_dict(copy.deepcopy(task.data), base_dir=task.base_dir,
                              source=task.source)
        with _quiet_stderr():
            result = run_case(case, run_dir, quiet=True, log_level=task.log_level,
                              max_steps=task.max_steps, overwrite=True)
        status = result.status
        if status != "completed":
            error = " ".join(result.message.split())
    except Exception as exc:
        error, trace = _one_line(exc), traceback.format_exc()
    wall = wallclock.perf_counter() - start
    _record_run(run_dir, task, status, wall, error, trace)
    return summarize_run(run_dir, task.peak, status=status, error=error, wall_time=wall)


class _ThreadQuietStream:
    """A stand-in for ``sys.stderr`` that drops what the threads marked quiet write and
    passes everything else on (worker threads may run tasks side by side)."""

    def __init__(self, stream):
        self._stream = stream
        self._local = threading.local()

    def write(self, text):
        if getattr(self._local, "quiet", False):
            return len(text)
        return self._stream.write(text)

    def __getattr__(self, name):
        return getattr(self._stream, name)


@contextlib.contextmanager
def _quiet_stderr():
    """Silence this thread's writes to sys.stderr (the runner's console log: each run
    keeps its run.log) without touching the worker's other threads."""
    if not isinstance(sys.stderr, _ThreadQuietStream):
        sys.stderr = _ThreadQuietStream(sys.stderr)
    stream = sys.stderr
    stream._local.quiet = True
    try:
        yield
    finally:
        stream._local.quiet = False


def _record_run(run_dir: Path, task: RunTask, status: str, wall: float, error: str,
                trace: str) -> None:
    """Add the sweep's record to run.json (creating it for a run that failed early)."""
    from demstep.runner import _write_text

    path = run_dir / "run.json"
    info: dict = {}
    if path.is_file():
        try:
            info = json.loads(path.read_text(encoding="utf-8"))
        except ValueError:
            info = {}
    if status == "failed":
        info.update({"status": "failed", "message": error, "traceback": trace,
                     "max_steps": task.max_steps})
    info["sweep"] = {"run_id": task.run_id,
                     "overrides": {k: v for k, v in task.overrides},
                     "wall_time_s": wall, "host": platform.node(), "pid": os.getpid()}
    _write_text(path, json.dumps(info, indent=2, default=str) + "\n")


def default_peak_column(columns: Sequence[str]) -> str | None:
    """The top wall's stress (``y+.stress`` in 2D, ``z+.stress`` in 3D), else the first
    wall's stress, else the first Love stress; None when there is none."""
    for name in ("z+.stress", "y+.stress"):
        if name in columns:
            return name
    for c in columns:
        if c.endswith(".stress"):
            return c
    for c in columns:
        if c.startswith("love."):
            return c
    return None


def summarize_run(run_dir, peak: str | None = None, status: str | None = None,
                  error: str | None = None, wall_time: float | None = None) -> dict:
    """The summary of a run folder: status, max energy error of the history, peak of
    ``peak`` (default :func:`default_peak_column`), final step and time, wall time."""
    import numpy as np

    from demstep.io.history import read_history

    run_dir = Path(run_dir)
    info: dict = {}
    try:
        info = json.loads((run_dir / "run.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        pass
    row = {"status": status or info.get("status", "failed"),
           "max_energy_error": math.nan, "peak_column": peak or "", "peak": math.nan,
           "final_step": info.get("step", ""), "final_time": info.get("time", math.nan),
           "wall_time_s": wall_time if wall_time is not None
           else info.get("sweep", {}).get("wall_time_s", math.nan),
           "error": error if error is not None else
           ("" if info.get("status") == "completed" else info.get("message", ""))}
    monitor = _finite(info.get("max_energy_error"))  # the monitor's checks (run.json)
    if monitor > 0:
        row["max_energy_error"] = monitor
    history = run_dir / "history.csv"
    if history.is_file():
        try:
            h = read_history(history)
        except InputError as exc:
            row["error"] = row["error"] or str(exc)
            return row
        column = peak or default_peak_column(list(h))
        row["peak_column"] = column or ""
        if len(h.get("step", ())):
            err = h["energy_error"][np.isfinite(h["energy_error"])]
            if err.size:
                row["max_energy_error"] = max(float(np.max(np.abs(err))), monitor)
            if column in h:
                values = h[column][np.isfinite(h[column])]
                if values.size:
                    row["peak"] = float(values.max())
            if row["final_step"] == "":
                row["final_step"] = int(h["step"][-1])
                row["final_time"] = float(h["time"][-1])
    return row


def _finite(value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return 0.0
    return v if math.isfinite(v) else 0.0


def is_finished(run_dir, case_sha256: str, max_steps: int | None) -> bool:
    """Whether ``run_dir`` holds a finished run (completed, diverged, energy_stop) of
    this case (same resolved-case hash) and ``max_steps``."""
    try:
        info = json.loads((Path(run_dir) / "run.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return (info.get("status") in FINISHED and info.get("case_sha256") == case_sha256
            and info.get("max_steps") == max_steps)


# ===================================================================== summary
def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)
    return str(value)


def write_summary(path, plan: SweepPlan, rows: list[dict | None]) -> Path:
    """summary.csv: run_id, the swept keys, then :data:`SUMMARY_TAIL` (runs not yet
    finished have status 'pending')."""
    from demstep.runner import _write_text

    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow([*SUMMARY_LEAD, *plan.key_names, *SUMMARY_TAIL])
    for run, row in zip(plan.runs, rows):
        row = row or {"status": "pending"}
        values = [value_text(run.overrides[k]) if k in run.overrides else "" for k in plan.keys]
        writer.writerow([run.run_id, *values, *[_cell(row.get(c)) for c in SUMMARY_TAIL]])
    return _write_text(path, buf.getvalue())


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def plot_summary(path, plan: SweepPlan, rows: list[dict | None]) -> Path:
    """summary.png: max energy error (log scale, the monitor's limit drawn) and the peak
    value against the first swept key, one line per combination of the other keys;
    runs that did not complete are marked with a red x."""
    import numpy as np

    from demstep.plotting import _pyplot, save_figure

    plt = _pyplot()
    fig, (ax_err, ax_peak) = plt.subplots(1, 2, figsize=(11, 4.2))
    xkey = plan.keys[0] if plan.keys else None
    xs = [run.overrides.get(xkey) for run in plan.runs]
    numeric = all(_is_number(v) for v in xs)
    if numeric:
        xpos = [float(v) for v in xs]
    else:
        labels = list(dict.fromkeys(value_text(v) if v is not None else "-" for v in xs))
        xpos = [float(labels.index(value_text(v) if v is not None else "-")) for v in xs]
    groups: dict[str, list[int]] = {}
    for k, run in enumerate(plan.runs):
        label = ", ".join(f"{key_text(key)}={value_text(run.overrides[key])}"
                          for key in plan.keys[1:] if key in run.overrides)
        groups.setdefault(label, []).append(k)
    peak_column = next((r.get("peak_column") for r in rows if r and r.get("peak_column")), "")
    for label, members in groups.items():
        members = sorted(members, key=lambda k: xpos[k])
        x = np.array([xpos[k] for k in members])
        err = np.array([_float(rows[k], "max_energy_error") for k in members])
        peak = np.array([_float(rows[k], "peak") for k in members])
        err = np.where(err > 0, err, np.nan)
        bad = [i for i, k in enumerate(members)
               if rows[k] is None or rows[k].get("status") != "completed"]
        if bad:
            label = f"{label} ({len(bad)} not completed)" if label else \
                f"{len(bad)} not completed"
        line, = ax_err.plot(x, err, marker="o", label=label or None)
        ax_peak.plot(x, peak, marker="o", color=line.get_color(), label=label or None)
        if bad:
            ax_err.plot(x[bad], err[bad], "x", color="red", ms=9, mew=2)
            ax_peak.plot(x[bad], peak[bad], "x", color="red", ms=9, mew=2)
    ax_err.set_yscale("log")
    ax_err.axhline(plan.eps, color="r", ls="--", lw=1, label=f"limit {plan.eps:g}")
    ax_err.set_ylabel("max normalized energy error (eq. 22)")
    ax_peak.set_ylabel(f"peak {peak_column}" if peak_column else "peak")
    for ax in (ax_err, ax_peak):
        ax.set_xlabel(key_text(xkey) if xkey else "run")
        if not numeric:
            ax.set_xticks(range(len(labels)), labels, rotation=30, ha="right", fontsize=8)
        ax.grid(True, alpha=0.3)
    handles, _ = ax_err.get_legend_handles_labels()
    if 0 < len(handles) <= 13:
        ax_err.legend(fontsize=7)
    fig.suptitle(f"{plan.case_name}: sweep of {len(plan.runs)} runs (red x: not completed)",
                 fontsize=10)
    return save_figure(fig, path)


def _float(row: dict | None, key: str) -> float:
    if row is None:
        return math.nan
    try:
        return float(row.get(key))
    except (TypeError, ValueError):
        return math.nan


# ====================================================================== driver
@dataclass
class SweepResult:
    """What a sweep did: the plan, one summary row per run, the ids skipped (finished
    before) and the files written."""

    plan: SweepPlan
    rows: list[dict]
    skipped: list[str] = field(default_factory=list)
    summary_csv: Path | None = None
    summary_png: Path | None = None

    def count(self, status: str) -> int:
        return sum(1 for r in self.rows if r.get("status") == status)


def _check_out(out: Path) -> None:
    from demstep.io.lock import check_folder_creatable, folder_is_empty

    check_folder_creatable(out, "out")
    if out.is_dir() and not folder_is_empty(out) and not (out / "sweep.json").is_file():
        raise InputError(f"out: {out} exists, is not empty and holds no sweep (sweep.json)")


def _lock_out(out: Path):
    """Create ``out`` and lock it for this sweep (InputError when another process
    holds it); temporary files of interrupted writes are removed."""
    from demstep.io.atomic import remove_orphans
    from demstep.io.lock import FolderLock, make_folder

    make_folder(out, "out")
    lock = FolderLock(out, "out").acquire()
    remove_orphans(out)
    return lock


def _mark_unfinished(run_dir: Path, message: str) -> None:
    """A run given up for want of workers: if its folder says 'running' and no
    process holds it, record status 'unfinished' in its run.json."""
    from demstep.io.lock import FolderLock
    from demstep.runner import _write_text

    path = run_dir / "run.json"
    if not path.is_file():
        return
    try:
        lock = FolderLock(run_dir, "run").acquire()
    except InputError:  # a worker still runs it
        return
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
        if isinstance(info, dict) and info.get("status") == "running":
            info.update({"status": "unfinished", "message": message})
            _write_text(path, json.dumps(info, indent=2, default=str) + "\n")
    except (OSError, ValueError):
        pass
    finally:
        lock.release()


def run_sweep(case_path, out, params: Sequence[str] = (), runs_file=None,
              scheduler: str | None = None, workers: int = 2, max_steps: int | None = None,
              peak: str | None = None, log_level: str = "INFO",
              progress: Callable | None = None,
              worker_timeout: float | None = WORKER_TIMEOUT,
              on_wait: Callable | None = None) -> SweepResult:
    """Run a sweep of ``case_path`` into ``out`` (see the module docstring).

    Everything is validated (parameters, runs file, every run's case, the output
    folder, the scheduler connection) before anything is written. The output folder is
    locked while the sweep runs (a second sweep into it is an InputError), and each
    run's folder while the run writes. Runs already finished in ``out`` are skipped.
    ``progress(done, total, run_id, row, skipped)`` is called as each run finishes
    (first for each skipped run). While the cluster has no worker,
    ``on_wait(pending, seconds)`` reports it; after ``worker_timeout`` seconds [s]
    without a worker (None: no limit) the runs not done are marked 'unfinished'
    (summary.csv, and run.json of a run a lost worker had started) and the sweep
    returns. Returns a :class:`SweepResult`."""
    from demstep import __version__
    from demstep.runner import LOG_LEVELS, _write_text

    out = Path(out).resolve()
    if worker_timeout is not None and not (isinstance(worker_timeout, (int, float))
                                           and not isinstance(worker_timeout, bool)
                                           and 0 < worker_timeout < math.inf):
        raise InputError(f"worker-timeout: must be a finite number of seconds > 0, got "
                         f"{worker_timeout!r}")
    if max_steps is not None and (not isinstance(max_steps, int) or max_steps < 0):
        raise InputError(f"max-steps: must be an integer >= 0, got {max_steps!r}")
    if str(log_level).upper() not in LOG_LEVELS:
        raise InputError(f"log-level: must be one of {', '.join(LOG_LEVELS)}, got {log_level!r}")
    if scheduler:
        check_scheduler_address(scheduler)
    plan = plan_sweep(case_path, params, runs_file)
    _check_out(out)
    base_dir = str(plan.case_path.resolve().parent)
    rows: list[dict | None] = [None] * len(plan.runs)
    skipped: list[str] = []
    todo: list[int] = []
    for k, run in enumerate(plan.runs):
        run_dir = out / "runs" / run.run_id
        if is_finished(run_dir, run.case_sha256, max_steps):
            rows[k] = summarize_run(run_dir, peak)
            skipped.append(run.run_id)
        else:
            todo.append(k)

    def write_meta():
        meta = {"demstep_version": __version__, "case": str(plan.case_path.resolve()),
                "case_name": plan.case_name, "keys": plan.key_names,
                "runs": [{"run_id": r.run_id,
                          "overrides": {key_text(k): v for k, v in r.overrides.items()}}
                         for r in plan.runs],
                "max_steps": max_steps, "peak": peak, "scheduler": scheduler,
                "workers": None if scheduler else workers,
                "started": wallclock.strftime("%Y-%m-%dT%H:%M:%S%z")}
        _write_text(out / "sweep.json", json.dumps(meta, indent=2, default=str) + "\n")
        _write_text(out / "case.toml", plan.case_text)

    summary_csv = out / "summary.csv"
    count = {"done": 0}

    def report(k: int, skipped_run: bool):
        count["done"] += 1
        if progress is not None:
            progress(count["done"], len(plan.runs), plan.runs[k].run_id, rows[k], skipped_run)

    lock = None
    try:
        if todo:
            tasks = [RunTask(run_id=plan.runs[k].run_id,
                             overrides=[(key_text(key), v)
                                        for key, v in plan.runs[k].overrides.items()],
                             data=plan.runs[k].data, base_dir=base_dir,
                             source=str(plan.case_path),
                             run_dir=str(out / "runs" / plan.runs[k].run_id),
                             max_steps=max_steps, peak=peak, log_level=str(log_level).upper())
                     for k in todo]
            with dask_client(scheduler, workers) as client:  # connection errors: nothing written
                lock = _lock_out(out)
                write_meta()
                for k in range(len(plan.runs)):
                    if rows[k] is not None:
                        report(k, True)
                write_summary(summary_csv, plan, rows)

                def done(i, result: TaskResult):
                    k = todo[i]
                    if result.unfinished:
                        rows[k] = {"status": "unfinished", "peak_column": peak or "",
                                   "error": result.error}
                        _mark_unfinished(Path(tasks[i].run_dir), result.error)
                    else:
                        rows[k] = result.value if result.ok else {
                            "status": "failed", "peak_column": peak or "", "error": result.error}
                    write_summary(summary_csv, plan, rows)
                    report(k, False)

                map_on_client(client, run_task, tasks, progress=done,
                              worker_timeout=worker_timeout, on_wait=on_wait)
        else:
            lock = _lock_out(out)
            write_meta()
            for k in range(len(plan.runs)):
                report(k, True)
        final = [r if r is not None else {"status": "failed", "error": "no result"} for r in rows]
        write_summary(summary_csv, plan, final)
        png = None
        try:
            with warnings.catch_warnings():  # matplotlib on runs without data
                warnings.simplefilter("ignore", UserWarning)
                png = plot_summary(out / "summary.png", plan, final)
        except Exception as exc:  # a figure must not lose the sweep's results
            log.warning("sweep: summary.png not drawn (%s)", _one_line(exc))
    finally:
        if lock is not None:
            lock.release()
    return SweepResult(plan, final, skipped, summary_csv, png)
