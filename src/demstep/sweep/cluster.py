"""Dask execution of independent tasks: a local or remote cluster, :func:`dask_map`
in order with failures recorded, and the wait for workers (see :mod:`demstep.sweep`)."""

from __future__ import annotations

import contextlib
import logging
import os
import platform
import re
import socket
import struct
import time as wallclock
import traceback
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Sequence

from demstep.errors import InputError

#: environment of local-cluster worker processes: one thread each for numba, OpenMP
#: and BLAS (the worker processes themselves use the cores)
WORKER_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "OPENBLAS_NUM_THREADS": "1"}
#: seconds to wait for an existing scheduler to answer
CONNECT_TIMEOUT = 20
#: seconds :func:`probe_scheduler` waits for a server's first words before it asks in
#: HTTP (at most half the timeout)
GREETING_WAIT = 5.0
#: largest first message [bytes] taken for a Dask handshake (it is about 60 bytes)
GREETING_MAX = 1 << 20

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


def one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def numba_one_thread() -> None:
    try:
        from demstep._numba import set_threads

        set_threads(1)
    except Exception:  # pragma: no cover - numba missing or unusable: nothing to limit
        pass


def _call_captured(func: Callable, item) -> TaskResult:
    """Run on a worker: ``func(item)`` with numba on one thread, exceptions captured."""
    numba_one_thread()
    try:
        return TaskResult(True, func(item))
    except Exception as exc:
        return TaskResult(False, None, one_line(exc), traceback.format_exc())


def worker_info(item=None) -> dict:
    """Where a task runs: host, process id and numba threads (check a cluster with
    ``dask_map(worker_info, range(4), scheduler=...)``)."""
    import numba  # (deferred: a heavy import, loaded only when used)

    return {"item": item, "host": platform.node(), "pid": os.getpid(),
            "numba_threads": numba.get_num_threads(),
            "NUMBA_NUM_THREADS": os.environ.get("NUMBA_NUM_THREADS")}


def check_scheduler_address(address: str) -> str:
    """``tcp://HOST:PORT`` (any protocol://, as distributed accepts); else InputError."""
    text = str(address).strip()
    if not re.match(r"^[a-z][a-z0-9+.-]*://\S+$", text):
        raise InputError(f"scheduler: expected an address like tcp://HOST:PORT, got {address!r}")
    return text


def probe_scheduler(address: str, timeout: float) -> None:
    """Check, with a plain socket and within ``timeout`` seconds, that a ``tcp://``
    address is a Dask scheduler before ``distributed.Client`` tries it: Dask's comm reads
    the first 8 bytes it receives as a frame length (an SSH banner made numpy allocate
    exabytes) and its handshake has no timeout (a silent server hung it). Raises
    InputError (one line: the address and what answered) unless the server sends a Dask
    handshake. Other protocols (tls://, ws://, ...) are not probed.

    A Dask scheduler writes its handshake as soon as it accepts a connection, before it
    reads anything; so nothing is sent until the server has been silent for
    :data:`GREETING_WAIT` seconds (at most half the timeout). Then ``HEAD / HTTP/1.0``
    asks whether it is an HTTP server (the dashboard's port). A scheduler whose event
    loop was blocked that long answers with its handshake and is accepted (it logs an
    error for the probe's bytes, which it reads as a frame length)."""
    from distributed.comm.addressing import (  # (deferred: a heavy import, loaded only when used)
        parse_address, parse_host_port)

    try:
        scheme, location = parse_address(address)
        if scheme != "tcp":
            return
        host, port = parse_host_port(location)
    except ValueError as exc:  # no port, or IPv6 without brackets
        raise InputError(f"scheduler: cannot use {address}: {exc}") from None
    start = wallclock.monotonic()
    deadline = start + timeout
    cannot = f"scheduler: cannot connect to {address}"
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except socket.gaierror as exc:
        raise InputError(f"{cannot}: host {host!r} does not resolve "
                         f"({exc.strerror or one_line(exc)})") from None
    except ConnectionRefusedError:
        raise InputError(f"{cannot}: connection refused (nothing listening on port "
                         f"{port} of {host})") from None
    except (socket.timeout, TimeoutError):
        raise InputError(f"{cannot}: no answer to the connection within {timeout:g} s") \
            from None
    except OSError as exc:
        raise InputError(f"{cannot}: {exc.strerror or one_line(exc)}") from None
    with sock:
        answer = _greeting(sock, start + min(GREETING_WAIT, timeout / 2))
        asked = False
        if answer == b"":  # silent so far: no Dask scheduler would be; ask in HTTP
            asked = True
            try:
                sock.sendall(b"HEAD / HTTP/1.0\r\n\r\n")
            except OSError:
                pass
            answer = _greeting(sock, deadline)
    if answer is None:
        raise InputError(f"scheduler: {address} closed the connection without a word, "
                         f"not a Dask scheduler")
    if answer == b"":
        asked_text = " (nor to an HTTP request)" if asked else ""
        raise InputError(f"scheduler: {address} did not answer as a Dask scheduler within "
                         f"{timeout:g} s{asked_text}")
    if _is_dask_handshake(answer):
        return
    first = answer.split(b"\n", 1)[0].strip()
    shown = repr(first[:60].decode("ascii", "backslashreplace"))
    if answer.startswith(b"SSH-"):
        what = f"an SSH server ({shown})"
    elif answer.startswith(b"HTTP/"):
        what = f"an HTTP server ({shown}; the dashboard?)"
    else:
        what = f"something else (its first bytes: {shown})"
    raise InputError(f"scheduler: {address} answered as {what}, not a Dask scheduler")


def _greeting(sock: socket.socket, until: float) -> bytes | None:
    """What the server sends first, read until ``until`` (monotonic time): a whole first
    Dask message, or the first chunk of anything else (8 bytes that are no plausible
    length: an SSH banner, an HTTP status line); b"" when it sent nothing, None when it
    closed the connection without sending anything."""
    data = b""
    while True:
        if len(data) >= 8:
            (size,) = struct.unpack("<Q", data[:8])
            if size > GREETING_MAX or len(data) >= 8 + size:
                return data
        left = until - wallclock.monotonic()
        if left <= 0:
            return data
        sock.settimeout(left)
        try:
            chunk = sock.recv(4096)
        except (socket.timeout, TimeoutError):
            return data
        except OSError:  # reset by the server
            return data or None
        if not chunk:
            return data or None
        data += chunk


def _is_dask_handshake(data: bytes) -> bool:
    """``data`` is a message as Dask's TCP comm writes it: its length (8 bytes, little
    endian), then frames packed by ``distributed.protocol.utils.pack_frames``."""
    from distributed.protocol.utils import \
        unpack_frames  # (deferred: a heavy import, loaded only when used)

    if len(data) < 16:
        return False
    (size,) = struct.unpack("<Q", data[:8])
    if not 8 < size <= GREETING_MAX or len(data) < 8 + size:
        return False
    body = data[8:8 + size]
    try:
        (count,) = struct.unpack("<Q", body[:8])
        if not 1 <= count <= (size - 8) // 8:
            return False
        frames = unpack_frames(body)
    except Exception:  # struct.error, AssertionError: not Dask's packing
        return False
    return len(frames) == count and sum(len(f) for f in frames) + 8 * (count + 1) == size


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int = 2):
    """A ``distributed.Client``: connected to the existing cluster at ``scheduler``
    (closed on exit; the cluster keeps running), or to a new
    ``LocalCluster(n_workers=workers, threads_per_worker=1, processes=True)`` whose
    workers run with :data:`WORKER_ENV` (shut down on exit). Raises InputError when
    the scheduler cannot be reached or the address is no Dask scheduler's
    (:func:`probe_scheduler`)."""
    from distributed import (Client,  # (deferred: a heavy import, loaded only when used)
                             LocalCluster)

    if scheduler:
        address = check_scheduler_address(scheduler)
        probe_scheduler(address, CONNECT_TIMEOUT)
        try:
            client = Client(address, timeout=CONNECT_TIMEOUT)
        except Exception as exc:  # whatever goes wrong here: the one-line input error
            raise InputError(f"scheduler: cannot connect to {address} ({one_line(exc)})") from None
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
    from distributed import as_completed  # (deferred: a heavy import, loaded only when used)

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
                result = TaskResult(False, None, one_line(exc), traceback.format_exc())
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


