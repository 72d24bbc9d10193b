import math
from dataclasses import replace

import numpy as np
import pytest

from demstep.timestep.contacts import find_contacts
from demstep.packings import jittered_polydisperse
from demstep.particles import Particles
from demstep.walls import Wall


def random_unit(rng, n, dim):
    v = rng.standard_normal((n, dim))
    return v / np.linalg.norm(v, axis=1)[:, None]


def random_polydisperse(seed: int, dim: int, n: int = 30, walls: bool = False, fixed: bool = False,
                        kn_spread: bool = True):
    """A small polydisperse assembly in contact, with varied stiffnesses and masses."""
    rng = np.random.default_rng(seed)
    x, r = jittered_polydisperse(n, dim, seed=seed, jitter=0.08, spread=0.15, overlap=0.08)
    density = rng.uniform(0.5, 3.0, len(r))  # per-particle density: masses vary independently
    p = Particles.from_density(x, r, 1.0)
    p.m *= density
    p.inertia *= density
    if fixed:
        p.fixed[rng.integers(0, p.n)] = True
    wall_list = []
    if walls:
        lo = x.min(axis=0)
        e = np.zeros(dim)
        e[0] = 1.0
        wall_list.append(Wall(lo - e * 0.48, e, name="x-"))
    c = find_contacts(p, 1.0, 1.0, walls=wall_list)
    if kn_spread:
        c.k_n[:] = rng.uniform(0.5, 2.0, c.n)
        c.k_s[:] = c.k_n * rng.uniform(0.2, 1.0, c.n)
    return p, c


def _warm_serial():
    """The serial step kernels, the exact step's and the contact forces' (one part of
    the warm-up)."""
    sim = _warm_simulation(parallel=False)
    sim.critical_dt("exact")
    sim.contact_forces()


def _warm_parallel():
    """The threaded step kernels (the other part)."""
    _warm_simulation(parallel=True)


def _warm_simulation(parallel: bool):
    from demstep.engine import Simulation

    x = np.array([[1.0, 1.0, 1.0], [2.9, 1.0, 1.0]])
    p = Particles.from_density(x, np.ones(2), 1.0)
    sim = Simulation(p, walls=[Wall([0, 0, 0], [0, 0, 1], name="floor")],
                     periodic=[None, 12.0, None], parallel=parallel)
    sim.run(steps=2)
    return sim


@pytest.fixture(scope="session", autouse=True)
def compiled_kernels(tmp_path_factory, worker_id):
    """Compile the engine's kernels (or load them from numba's cache) once, before the
    first test. On a cold cache this takes one to two minutes, which would otherwise
    be charged to whichever test happens to run first (``--durations`` then blames
    it); here it shows as the setup of the first test.

    With pytest-xdist's workers, the two parts (about 50 s each on a cold cache) are
    compiled one by each worker at the same time, each part under a lock in the
    workers' common temporary folder; a worker then takes the other part's lock, which
    waits for the other worker to finish compiling it, and loads it from the cache
    (before, both workers compiled everything: twice the work in the same wall time)."""
    parts = [_warm_serial, _warm_parallel]
    if worker_id == "master":  # (no workers)
        for part in parts:
            part()
        return
    import fcntl

    shared = tmp_path_factory.getbasetemp().parent
    first = int(worker_id.removeprefix("gw")) % len(parts)
    for part in parts[first:] + parts[:first]:
        with open(shared / f"warm-up-{part.__name__}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # (released when the file closes)
            part()


def oscillation_period(times, values):
    """Mean period [T] of a sampled oscillation: the spacing of its downward zero
    crossings, each placed by linear interpolation between samples (NaN with fewer than
    two crossings, which no approx comparison accepts)."""
    t, v = np.asarray(times), np.asarray(values)
    down = np.flatnonzero((v[:-1] > 0) & (v[1:] <= 0))
    crossings = t[down] + v[down] / (v[down] - v[down + 1]) * (t[down + 1] - t[down])
    return float(np.diff(crossings).mean()) if len(crossings) >= 2 else math.nan


@pytest.fixture
def rng():
    return np.random.default_rng(20260122)


def contacts_now(ref, x, r, bond=None, apart=False):
    """The elements of the covered ``ref`` at the positions ``x`` now, as the engine has
    them: the touching pairs (and the bonds, ``bond`` true, touching or not) with their
    normals and arms from the geometry; pairs apart have no element, or with ``apart``
    one at their new normal and their estimate's arms (the drift bounds that too: a
    harder test, which also shows that the drift is needed). Every other field of
    ``ref`` (springs, dashpots, rolling) is kept. With ``ref``'s arms the radii and
    ``apart``, the elements an estimate of ``x`` covers (the engine's contact set)."""
    d = x[ref.j] - x[ref.i]
    dist = np.linalg.norm(d, axis=1)
    on = dist < r[ref.i] + r[ref.j]
    if bond is not None:
        on |= bond
    half = 0.5 * (r[ref.i] + r[ref.j] - dist)
    now = replace(ref, normal=d / dist[:, None], arm_i=np.where(on, r[ref.i] - half, ref.arm_i),
                  arm_j=np.where(on, r[ref.j] - half, ref.arm_j))
    return now if apart else now.subset(on)


def cli(argv, capsys):
    """Exit status, stdout and stderr of the command line run in this process."""
    from demstep.cli import main as cli_main

    try:
        code = cli_main([str(a) for a in argv])
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code, err, *words):
    """Exit status 2, one line 'demstep: error: ...' holding every one of ``words``."""
    assert code == 2, err
    assert err.startswith("demstep: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    for word in words:
        assert word in err, err


def snapshot(folder):
    """Every file under ``folder`` with its bytes (to show nothing was written)."""
    from pathlib import Path

    folder = Path(folder)
    return {str(p.relative_to(folder)): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}



#: test files that run a peer code (LAMMPS, YADE) installed by .ci/run in the background
PEER_TEST_FILES = ("test_lammps_live.py", "test_yade_live.py")


def pytest_collection_modifyitems(config, items):
    """The peer codes' live tests run last: .ci/run installs LAMMPS and YADE in the
    background while the rest of the suite runs (stable sort: the order within each
    group is kept)."""
    items.sort(key=lambda item: item.path.name in PEER_TEST_FILES)


def wait_for_peer_install(timeout: float = 900.0):
    """Block until .ci/run's background install of the peer codes is over, when it
    announced one (``$DEMSTEP_PEERS_READY``, a file it writes at the end, with the
    install's outcome); without it, nothing to wait for. The tests then skip or run as
    what is installed allows."""
    import os
    import time

    marker = os.environ.get("DEMSTEP_PEERS_READY")
    if not marker:
        return
    end = time.monotonic() + timeout
    while not os.path.exists(marker) and time.monotonic() < end:
        time.sleep(2.0)


@pytest.fixture(scope="module", autouse=True)
def _peers_installed(request):
    if request.node.path.name in PEER_TEST_FILES:
        wait_for_peer_install()
