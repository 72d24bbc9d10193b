"""The minimum image, written once (demstep.contact.geometry) and called everywhere.

The compiled scalar :func:`minimum_image` and the numpy :func:`minimum_image_arrays`
against a slow plain-Python reference of the rule (bit for bit, zeros' signs
included) and against exact rational arithmetic (a nearest image), on random
separations, negative ones, exact half-box ties and non-periodic axes; and a scan of
the package's source that fails when a module other than contact/geometry.py computes
a minimum image of its own."""

import ast
import math
import re
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from demstep.contact.geometry import image_count, minimum_image, minimum_image_arrays

SRC = Path(__file__).resolve().parent.parent / "src" / "demstep"
GEOMETRY = SRC / "contact" / "geometry.py"


def reference_minimum_image(d: float, length: float) -> tuple[float, float]:
    """(wrapped component, image count) by the documented rule, in plain Python floats:
    the count is d times the inverse length rounded half to even (Python's ``round``)
    with the sign of a zero kept (as C's rint), 0 for a non-periodic axis (length 0)."""
    inverse = 1.0 / length if length > 0.0 else 0.0
    q = d * inverse
    n = math.copysign(float(round(q)), q)
    return d - length * n, n


def bits(values) -> list[int]:
    """The IEEE bit patterns of float64 values (-0.0 and +0.0 differ)."""
    return np.asarray(values, dtype=np.float64).view(np.int64).ravel().tolist()


def separations(seed: int, n: int = 3000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Separations [L] and box lengths [L], (n, 3) each: random in [-3.5 L, 3.5 L]
    (both signs), half-box ties (k + 1/2) L, multiples k L, tiny values and signed
    zeros; lengths with and without an exact inverse, and 0 (not periodic). Returns
    (d, lengths, tie): ``tie`` marks the components that are exact ties (those of
    lengths whose (k + 1/2) L rounds are near ties only)."""
    rng = np.random.default_rng(seed)
    length_sets = np.array([[3.0, 0.7, 0.0], [2.5, 0.0, 1.0 / 3.0], [4.0, 0.375, 6.1],
                            [0.0, 0.0, 0.0], [10.0, 1e-3, 7.25]])
    lengths = length_sets[rng.integers(0, len(length_sets), n)]
    scale = np.where(lengths > 0, lengths, 1.0)
    d = rng.uniform(-3.5, 3.5, (n, 3)) * scale
    kind = rng.integers(0, 4, (n, 3))
    k = rng.integers(-2, 2, (n, 3)).astype(float)  # ties' images within 2 L: n L exact
    d = np.where(kind == 0, (k + 0.5) * scale, d)
    d = np.where(kind == 1, (k - 1.0) * scale, d)
    d = np.where(kind == 2, rng.choice([-0.0, 0.0, -1e-300, 5e-324], (n, 3)), d)
    tie = np.array([[kind[c, a] == 0 and lengths[c, a] > 0 and Fraction(float(d[c, a]))
                     == (Fraction(int(2 * k[c, a]) + 1, 2)) * Fraction(float(lengths[c, a]))
                     for a in range(3)] for c in range(n)])
    assert tie.sum() > n // 10  # (exact ties in every box with a short length)
    return d, lengths, tie


def test_minimum_image_scalar_and_arrays_equal_a_plain_python_reference():
    d, lengths, _ = separations(1)
    want = [[reference_minimum_image(float(d[c, a]), float(lengths[c, a])) for a in range(3)]
            for c in range(len(d))]
    want_d = [[w[0] for w in row] for row in want]
    want_n = [[w[1] for w in row] for row in want]
    got = [minimum_image(*d[c], *lengths[c]) for c in range(len(d))]
    assert bits([g[:3] for g in got]) == bits(want_d)
    assert bits([g[3:] for g in got]) == bits(want_n)
    assert bits([[image_count(d[c, a], lengths[c, a]) for a in range(3)]
                 for c in range(len(d))]) == bits(want_n)
    # the arrays version, one box per call (rows of equal lengths), 3 and 2 columns
    for box in np.unique(lengths, axis=0):
        rows = np.all(lengths == box, axis=1)
        before = d[rows].copy()
        for dim in (3, 2):
            wrapped = minimum_image_arrays(d[rows][:, :dim], box)
            assert bits(wrapped) == bits(np.array(want_d)[rows][:, :dim])
        assert bits(d[rows]) == bits(before)  # the input is not modified


def test_minimum_image_is_a_nearest_image_in_exact_arithmetic():
    """The count n is a nearest integer to q = d / L up to the rounding of d (1/L):
    |q - n| <= 1/2 + 2^-51 |q| (the product's two roundings: 2^-52 |q|); the wrapped
    component d - L n, rounded twice more, is at most L/2 + L (|q| + |n| + 1) 2^-52;
    at an exact half-box tie either neighbour may be taken and the wrapped component
    is exactly +-L/2; along a non-periodic axis nothing moves."""
    d, lengths, tie = separations(2)
    for c in range(len(d)):
        out = minimum_image(*d[c], *lengths[c])
        for a in range(3):
            length, n, wrapped = lengths[c, a], out[3 + a], out[a]
            if length == 0.0:
                assert n == 0.0 and wrapped == d[c, a]
                continue
            q = Fraction(float(d[c, a])) / Fraction(float(length))
            assert n == int(n) and abs(q - Fraction(n)) <= Fraction(1, 2) + abs(q) / 2**51
            if tie[c, a]:
                assert abs(wrapped) == 0.5 * length
            else:
                exact_l = Fraction(float(length))
                assert abs(Fraction(float(wrapped))) <= exact_l / 2 + exact_l * (
                    abs(q) + abs(Fraction(n)) + 1) / 2**52


def test_the_replaced_forms_give_the_same_bits_off_ties():
    """The forms case/build.py (np.rint(d / L)) and contact/bonds.py (np.round(d / L))
    used agree with the rule (d times 1/L) on separations away from half-box ties: the
    pairs they wrap are within a third of the box (the neighbour search's cells), so
    their results are unchanged. (At an exact tie the division and the product by the
    inverse can round to different, equally near, images: the same |d|.)"""
    rng = np.random.default_rng(3)
    for length in (3.0, 0.7, 1.0 / 3.0, 6.1, 7.25e-4):
        d = (rng.integers(-2, 3, 100000) + rng.uniform(-1 / 3, 1 / 3, 100000)) * length
        new = minimum_image_arrays(d[:, None], [length])[:, 0]
        assert bits(d - length * np.rint(d / length)) == bits(new)
        assert bits(d - length * np.round(d / length)) == bits(new)
    for length in (3.0, 2.5, 7.25, 0.375):  # exact ties (k + 1/2) L: both images |d| = L/2
        ties = (np.arange(-2, 2) + 0.5) * length
        new = np.abs(minimum_image_arrays(ties[:, None], [length])[:, 0])
        assert bits(new) == bits(np.abs(ties - length * np.rint(ties / length))) == bits(
            np.full(4, 0.5 * length))


# ------------------------------------------------------------------ one place only
ROUNDING = {"rint", "round", "around"}
TRUNCATING = {"floor", "ceil", "trunc", "fix", "int"}
LENGTH = re.compile(r"periodic|len|box|inv", re.IGNORECASE)


def _identifiers(node) -> set[str]:
    """Names and attribute names in ``node``, called functions' names left out."""
    called = {id(n.func) for n in ast.walk(node) if isinstance(n, ast.Call)}
    return {n.id if isinstance(n, ast.Name) else n.attr for n in ast.walk(node)
            if isinstance(n, (ast.Name, ast.Attribute)) and id(n) not in called}


def _by_length(node) -> bool:
    """Whether ``node`` divides by, or multiplies with, something named like a box
    length or its inverse."""
    for b in ast.walk(node):
        if isinstance(b, ast.BinOp) and isinstance(b.op, (ast.Div, ast.Mult)):
            operands = [b.right] if isinstance(b.op, ast.Div) else [b.left, b.right]
            if any(LENGTH.search(i) for o in operands for i in _identifiers(o)):
                return True
    return False


def _half(node, shift: bool = False) -> bool:
    """Whether ``node`` holds 0.5 * (length-like) or (length-like) / 2, or (``shift``)
    adds or subtracts 0.5."""
    for b in ast.walk(node):
        if isinstance(b, ast.BinOp):
            consts = [o.value for o in (b.left, b.right) if isinstance(o, ast.Constant)]
            if shift and isinstance(b.op, (ast.Add, ast.Sub)) and 0.5 in consts:
                return True
            if ((isinstance(b.op, ast.Mult) and 0.5 in consts)
                    or (isinstance(b.op, ast.Div) and 2 in consts)) and any(
                        LENGTH.search(i) for i in _identifiers(b)):
                return True
    return False


def own_minimum_images(source: str) -> list[str]:
    """Where ``source`` computes a minimum image without contact/geometry.py: uses of
    ``image_count``; rint/round/around of a quotient or product by a length (also
    through a variable assigned one, or an imported alias); floor/ceil/trunc/int of one
    shifted by 0.5; math.remainder; a modulo or a comparison against half a length."""
    tree = ast.parse(source)
    alias = {a.asname or a.name: a.name for n in ast.walk(tree)
             if isinstance(n, ast.ImportFrom) for a in n.names}
    assigned = {}
    for n in ast.walk(tree):
        if isinstance(n, (ast.Assign, ast.AugAssign, ast.AnnAssign)) and n.value is not None:
            for t in n.targets if isinstance(n, ast.Assign) else [n.target]:
                if isinstance(t, ast.Name):
                    assigned.setdefault(t.id, []).append(n.value)

    def quotient(arg) -> bool:
        return _by_length(arg) or any(
            _by_length(v) for i in _identifiers(arg) for v in assigned.get(i, []))

    found = []
    for n in ast.walk(tree):
        name = (n.id if isinstance(n, ast.Name) else n.attr if isinstance(n, ast.Attribute)
                else n.name if isinstance(n, ast.alias) else None)
        if name in ("image_count", "_image_count"):
            found.append(f"line {getattr(n, 'lineno', '?')}: {name}")
        if isinstance(n, ast.Call):
            f = n.func.id if isinstance(n.func, ast.Name) else getattr(n.func, "attr", "")
            f = alias.get(f, f)
            if f in ROUNDING and any(quotient(a) for a in n.args):
                found.append(f"line {n.lineno}: {f} of a quotient by a length")
            if f in TRUNCATING and any(quotient(a) and _half(a, shift=True) for a in n.args):
                found.append(f"line {n.lineno}: {f} of a quotient by a length + 0.5")
            if f == "remainder" and ast.unparse(n.func).startswith("math"):
                found.append(f"line {n.lineno}: math.remainder")
            if f in ("mod", "remainder", "fmod") and any(_half(a) for a in n.args):
                found.append(f"line {n.lineno}: {f} shifted by half a length")
        if isinstance(n, ast.Compare) and any(_half(c) for c in [n.left, *n.comparators]):
            found.append(f"line {n.lineno}: comparison against half a length")
    return found


#: the forms the five copies had before they were replaced, and others a new copy
#: could take; each must be found
OWN_MINIMUM_IMAGES = [
    "d0 -= len0 * image_count(d0, len0)",  # kernels/neighbors.py
    "d0 -= periodic_len[0] * image_count(d0, periodic_len[0])",  # timestep/certificate.py
    "d[:, axis] -= length * np.rint(d[:, axis] / length)",  # case/build.py
    "d[:, k] -= periodic_len[k] * np.round(d[:, k] / periodic_len[k])",  # contact/bonds.py
    "from demstep.contact.geometry import image_count",
    "d -= box * np.around(d * inv_box)",
    "from numpy import rint as nearest\nd -= L_box * nearest(d / L_box)",
    "q = d / length\nd -= length * np.rint(q)",
    "d -= length * round(d / length)",
    "d -= length * math.floor(d / length + 0.5)",
    "d = math.remainder(d, length)",
    "d = np.mod(d + 0.5 * length, length) - 0.5 * length",
    "if d > length / 2:\n    d -= length",
    "if d0 >= 0.5 * len0:\n    d0 -= len0",
]

#: what the package does legitimately with periodic lengths and rounding; none found
NOT_MINIMUM_IMAGES = [
    "np.mod(x[:, axis], sim.periodic_len[axis], out=x[:, axis])",  # positions into the box
    "value = value - periodic_len[j] * math.floor(value / periodic_len[j])",  # the same
    "ck = int(np.floor((x[p, k] - lo[k]) * inv_cell[k]))",  # a cell index
    "bad = huge | (values != np.round(values))",
    "side = max(2, int(round(n_target ** (1.0 / dim))))",
    "d0, d1, d2 = minimum_image(d0, d1, d2, len0, len1, len2)[:3]",
    "d = minimum_image_arrays(x[pj] - x[pi], sim.periodic_len)",
    "if periodic_len[k] > 0 and ncell[k] <= 3:\n    pass",
]


@pytest.mark.parametrize("source", OWN_MINIMUM_IMAGES)
def test_the_scan_finds_a_minimum_image_of_its_own(source):
    assert own_minimum_images(source)


@pytest.mark.parametrize("source", NOT_MINIMUM_IMAGES)
def test_the_scan_leaves_other_code_alone(source):
    assert own_minimum_images(source) == []


def test_no_module_but_geometry_computes_a_minimum_image():
    """Every minimum image goes through contact/geometry.py (minimum_image,
    minimum_image_arrays, pair_geometry). What this scan cannot see: a copy under names
    unlike a length's (``np.rint(d / s)``), a quotient passed through a helper function
    or another module, a loop subtracting the length until |d| <= L/2 under such names."""
    files = sorted(SRC.rglob("*.py"))
    assert GEOMETRY in files and len(files) > 50
    found = {str(p.relative_to(SRC)): own_minimum_images(p.read_text()) for p in files
             if p != GEOMETRY}
    assert {k: v for k, v in found.items() if v} == {}
    assert own_minimum_images(GEOMETRY.read_text())  # the rule itself is found there
