"""numba settings in one place.

``fastmath`` stays off: the energy ledger must reproduce bit for bit between runs and
a restart must continue identically. One flag is allowed where a loop opts in
(:data:`CONTRACT`): fusing a multiply and an add into one instruction (FMA) that rounds
once instead of twice. It is deterministic (the same code gives the same bits on every
run and after a restart) and changes a result by at most its last bits per operation;
no reassociation, no approximate functions, NaN and infinities kept. ``cache=True``
keeps compiled kernels on disk so a second run starts computing at once. Setting ``NUMBA_DISABLE_JIT=1`` runs every kernel
as plain Python (the tests use this against slow numpy references).
"""

import functools
import hashlib
import os
import pickle
import types
import warnings
from pathlib import Path

import numba

# TBB's scheduler costs milliseconds per parallel region on small machines (measured:
# a 2-particle run 25x slower than with OpenMP); prefer OpenMP, then the work queue.
numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]

JIT_OPTIONS = dict(cache=True, fastmath=False, error_model="numpy", nogil=True)

#: the one fastmath flag a loop may opt in to: multiply-add contraction (FMA)
CONTRACT = {"contract": True}


#: whether compiled kernels can be cached on disk; set False (with one warning) the
#: first time numba finds no writable cache location
CACHE_AVAILABLE = True


def _cache_writable(dispatcher) -> bool:
    """Whether the cache location numba chose for ``dispatcher`` can be written (numba
    checks it for most locators when it chooses, not for modules in a zip archive)."""
    try:
        locator = dispatcher._cache._impl._locator
    except AttributeError:  # another numba version: trust its own checks
        return True
    try:
        locator.ensure_cache_path()
    except OSError:
        return False
    return True


#: the package's folder; and the folders and modules in it that hold no code numba
#: compiles and no global a kernel reads (the command line, cases, sweeps, experiments,
#: file formats, plots, the runner): the kernels' cache does not depend on them
PACKAGE_DIR = Path(__file__).resolve().parent
NOT_COMPILED = ("cli", "case", "sweep", "experiments", "io", "plotting.py",
                "plotting_run.py", "runner.py", "engine", "analysis_input.py",
                "packings.py", "walls.py")


def compiled_sources() -> list[Path]:
    """The package's source files a compiled kernel can depend on (all but
    :data:`NOT_COMPILED`), sorted. (os.walk, pruned: the caches' folders hold hundreds
    of files, which ``Path.rglob`` read at every start.)"""
    found = []
    for folder, subfolders, files in os.walk(PACKAGE_DIR):
        here = Path(folder)
        top = here == PACKAGE_DIR
        subfolders[:] = [d for d in subfolders if d != "__pycache__"
                         and not (top and d in NOT_COMPILED)]
        found += [here / f for f in files
                  if f.endswith(".py") and not (top and f in NOT_COMPILED)]
    return sorted(found)


@functools.lru_cache(maxsize=None)
def kernel_source_stamp() -> bytes:
    """SHA-256 of every file of :func:`compiled_sources` (names and contents): the
    freshness stamp of each kernel's on-disk cache entry. numba's own stamp is the
    hash of the kernel's own file only, so a cached kernel that inlines a function of
    another module (a contact law, a constant of the ledger) outlived a change of it,
    silently running the old code (found when the epsd rolling stiffness changed in
    the contact laws and the pair loop in kernels/dem.py kept the old one)."""
    digest = hashlib.sha256()
    for path in compiled_sources():
        digest.update(str(path.relative_to(PACKAGE_DIR)).encode())
        digest.update(path.read_bytes())
    return digest.digest()


class _PackageStamp:
    """Mixin of numba's source-backed cache locators: a kernel of this package is
    fresh while :func:`kernel_source_stamp` is unchanged."""

    def get_source_stamp(self):
        py_file = getattr(self, "_py_file", None)
        if py_file is not None and Path(py_file).resolve().is_relative_to(PACKAGE_DIR):
            return kernel_source_stamp()
        return super().get_source_stamp()


def _kernel_cache_class():
    """numba's FunctionCache with every locator stamped by :class:`_PackageStamp`
    (None when this numba's caching classes differ: numba's own cache then)."""
    try:
        from numba.core import caching

        impl = caching.FunctionCache._impl_class
        here = {"__module__": __name__}
        locators = [type("Stamped" + c.__name__.lstrip("_"), (_PackageStamp, c), dict(here))
                    for c in impl._locator_classes]
        stamped_impl = type("KernelCacheImpl", (impl,),
                            {**here, "_locator_classes": locators})
        return type("KernelCache", (caching.FunctionCache,),
                    {**here, "_impl_class": stamped_impl})
    except (ImportError, AttributeError, TypeError):
        return None


KERNEL_CACHE = _kernel_cache_class()


def _stale_safe(cache_file):
    """``cache_file`` (numba's index of a kernel's cache) reading an index it cannot
    unpickle as an empty one (a miss), instead of raising: an index written by an older
    demstep names types it no longer has (its signatures are pickled before the stamp
    that says the entry is stale can be compared; seen when the law parameters' type
    changed: "Can't get attribute 'LawParams'")."""
    load = cache_file._load_index

    def load_index():
        try:
            return load()
        except (AttributeError, ImportError, ModuleNotFoundError, EOFError, TypeError,
                ValueError, pickle.UnpicklingError):
            return {}

    cache_file._load_index = load_index
    return cache_file


def _with_package_cache(dispatcher):
    """The dispatcher (compiled with ``cache=True``) with its cache stamped by the
    package's compiled sources (:func:`kernel_source_stamp`), and an index left by an
    older version read as a miss (:func:`_stale_safe`)."""
    py_func = getattr(dispatcher, "py_func", None)  # (None: NUMBA_DISABLE_JIT, plain Python)
    if KERNEL_CACHE is not None and py_func is not None:
        dispatcher._cache = KERNEL_CACHE(py_func)
        cache_file = getattr(dispatcher._cache, "_cache_file", None)
        if cache_file is not None and hasattr(cache_file, "_load_index"):
            _stale_safe(cache_file)
    return dispatcher


def _compile(func, options: dict):
    """numba.njit(**options)(func); without the on-disk cache when numba has no
    writable place for it (a read-only installation without a writable home, a zip
    archive): numba then raises "cannot cache function ...: no locator available" at
    import, or fails to open its index file at the first call."""
    global CACHE_AVAILABLE
    if options.get("cache") and not CACHE_AVAILABLE:
        options = {**options, "cache": False}
    try:
        dispatcher = numba.njit(**options)(func)
        if options.get("cache"):
            dispatcher = _with_package_cache(dispatcher)
        if not options.get("cache") or _cache_writable(dispatcher):
            return dispatcher
    except RuntimeError as exc:
        if not options.get("cache") or "cannot cache" not in str(exc):
            raise
    CACHE_AVAILABLE = False
    warnings.warn("demstep: numba finds no writable cache location (set NUMBA_CACHE_DIR to "
                  "a writable folder); kernels are compiled at every start",
                  RuntimeWarning, stacklevel=3)
    return numba.njit(**{**options, "cache": False})(func)


def njit(*args, **kwargs):
    """``numba.njit`` with the package's options (``parallel`` opt-in per kernel)."""
    options = {**JIT_OPTIONS, **kwargs}
    if args and callable(args[0]):
        return _compile(args[0], options)
    return lambda func: _compile(func, options)


prange = numba.prange


def with_globals(func, name: str, overrides: dict):
    """A copy of the Python function ``func`` named ``name`` whose global names
    ``overrides`` resolve to other objects (e.g. the serial versions of the loops it
    calls), to be compiled on its own: numba compiles only what a version calls, and
    each copy has its own qualified name, so its own on-disk cache entry."""
    namespace = {**func.__globals__, **overrides} if overrides else func.__globals__
    copy = types.FunctionType(func.__code__, namespace, name, func.__defaults__,
                              func.__closure__)
    copy.__qualname__ = name
    copy.__doc__ = func.__doc__
    copy.__module__ = func.__module__
    return copy


def compile_parallel_and_serial(func, serial_globals: dict | None = None, **options):
    """Two compiled versions of one loop driver: threaded (prange) and serial, both
    with ``options`` (e.g. ``fastmath=CONTRACT``) on top of the package's; in the serial
    one the global names ``serial_globals`` resolve to other objects.

    The serial one is compiled from a copy of the function with its own qualified name,
    so the two never share an on-disk cache entry."""
    serial = with_globals(func, func.__name__ + "_serial", serial_globals or {})
    serial.__qualname__ = func.__qualname__ + "_serial"
    return njit(parallel=True, **options)(func), njit(**options)(serial)


#: whether :func:`warn_slow_threading_layer` has warned in this process
_LAYER_WARNED = False


def warn_slow_threading_layer():
    """Warn once when numba's threads run on TBB although OpenMP was preferred: numba
    chose its layer before this package was imported (``numba.set_num_threads`` or a
    parallel kernel ran first). Measured here: a settling run of 1e5 spheres on two
    threads 21-24 M particle-steps/s on TBB against 27-29 M on OpenMP."""
    global _LAYER_WARNED
    if _LAYER_WARNED or numba.get_num_threads() < 2:
        return
    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel kernel has run yet: the preference still applies
        return
    chosen = str(numba.config.THREADING_LAYER).lower()  # NUMBA_THREADING_LAYER
    if layer == "tbb" and chosen not in ("tbb", "threadsafe"):
        _LAYER_WARNED = True
        warnings.warn("demstep: numba runs its threads on TBB, chosen before demstep was "
                      "imported (import demstep before numba.set_num_threads, or set "
                      "NUMBA_THREADING_LAYER=omp): its parallel regions are much slower "
                      "here", RuntimeWarning, stacklevel=3)


def set_threads(n: int | None) -> int:
    """Set the number of numba threads (None: all); returns the number in use."""
    if n is not None:
        numba.set_num_threads(max(1, min(int(n), numba.config.NUMBA_NUM_THREADS)))
    return numba.get_num_threads()
