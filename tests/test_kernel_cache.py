"""The compiled kernels' on-disk cache follows every source file a kernel can depend
on, not only the kernel's own file (numba's stamp): a cached kernel that inlines a
function of another module must not outlive a change of that function."""

import ast
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

from demstep import _numba

KERNEL_MARK = re.compile(r"\bnjit\b|\bcompile_parallel_and_serial\b|\bprange\b")


def _module_file(name: str) -> Path | None:
    path = _numba.PACKAGE_DIR.joinpath(*name.split(".")[1:])
    for candidate in (path.with_suffix(".py"), path / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _package_imports(path: Path) -> set[Path]:
    """The package's modules ``path`` imports anywhere in it (a module, or a name of a
    module that is itself a module)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        names = []
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        for name in names:
            if name.split(".")[0] == "demstep" and (f := _module_file(name)) is not None:
                found.add(f.resolve())
    return found


def test_the_stamp_covers_every_module_a_kernel_can_read():
    """Every module that defines a kernel, and every module of the package those import
    (transitively), is among the stamped sources."""
    stamped = {p.resolve() for p in _numba.compiled_sources()}
    every = [p.resolve() for p in _numba.PACKAGE_DIR.rglob("*.py")]
    kernels = {p for p in every if KERNEL_MARK.search(p.read_text(encoding="utf-8"))}
    assert len(kernels) >= 8  # dem, neighbors, bodies, bonds, laws, ...
    closure, todo = set(kernels), list(kernels)
    while todo:
        for module in _package_imports(todo.pop()) - closure:
            closure.add(module)
            todo.append(module)
    missing = sorted(str(p.relative_to(_numba.PACKAGE_DIR)) for p in closure - stamped)
    assert missing == []
    # and the exclusions are real: the command line is not stamped
    assert (_numba.PACKAGE_DIR / "cli" / "dt.py").resolve() not in stamped


def test_a_kernel_uses_the_package_stamp():
    from demstep.kernels import dem

    locator = dem.integrate._cache._impl._locator
    assert locator.get_source_stamp() == _numba.kernel_source_stamp()


CHILD = """
import numpy as np
from demstep.contact.laws import LinearSpring
from demstep.kernels.timestep_kernels import rolling_coefficient_arrays
law = LinearSpring(k_n=1.0e4, rolling_convention="epsd", rolling_friction=0.5)
k_r = rolling_coefficient_arrays(law.params(), np.ones(1), np.ones(1), np.ones(1), np.ones(1))[0]
print(repr(float(k_r[0])))
"""


def test_a_cached_kernel_follows_a_change_of_an_inlined_function(tmp_path):
    """A copy of the package: a kernel of kernels/timestep_kernels.py that inlines the
    rolling stiffness of contact/laws/, run, cached; the formula changed in laws/ only;
    the next process must compute the new value (with numba's own stamp it
    loaded the stale kernel and printed the old one)."""
    copy = tmp_path / "src" / "demstep"
    shutil.copytree(_numba.PACKAGE_DIR, copy,
                    ignore=shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc"))
    env = {**os.environ, "PYTHONPATH": str(tmp_path / "src"),
           "NUMBA_CACHE_DIR": str(tmp_path / "cache")}

    def k_r():
        out = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True,
                             text=True, check=True, cwd=tmp_path)
        return float(out.stdout.strip().splitlines()[-1])

    before = k_r()
    assert before == 2.25 * 1.0 * 0.5**2 * 1.0  # k_r = 2.25 k_n mu_r^2 R*^2, all ones
    assert any((tmp_path / "cache").rglob("*.nbi"))  # cached
    laws = copy / "contact" / "laws" / "__init__.py"
    text = laws.read_text(encoding="utf-8")
    assert text.count("k_r = 2.25 * k_sec") == 1
    laws.write_text(text.replace("k_r = 2.25 * k_sec", "k_r = 3.0 * k_sec"), encoding="utf-8")
    assert k_r() == 3.0 * 1.0 * 0.5**2 * 1.0
