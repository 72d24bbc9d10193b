"""Transforms applied to a mesh on load, as LIGGGHTS' ``fix mesh/surface`` takes them:
``scale``, ``move`` and ``rotate``, applied **in the order given** (LIGGGHTS documents
the same: its operations are applied in the order they are specified).

* :class:`Scale` ``(factor)``: x -> factor x, about the origin; factor > 0 (a negative
  factor would mirror the mesh and turn its normals inside out).
* :class:`Move` ``(offset)``: x -> x + offset [L].
* :class:`Rotate` ``(axis, angle)``: about the axis through the origin, ``angle`` in
  degrees, right-hand rule (90 about +z maps +x to +y).

Order matters: ``[Scale(2), Move((1, 0, 0))]`` puts the point 1 at 3,
``[Move((1, 0, 0)), Scale(2)]`` puts it at 4. :func:`parse_transforms` reads the
LIGGGHTS keywords (``"scale 0.001 move 0 0 0.5 rotate axis 0 0 1 angle 90"``) into
the same list, in the order written.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from demstep.errors import MAX_MAGNITUDE, InputError, magnitude_problem


def _show(value) -> str:
    """``value`` as written in a message: numbers as plain floats (not np.float64(...))."""
    if isinstance(value, (int, float, np.integer, np.floating)):
        return repr(float(value))
    if isinstance(value, (tuple, list, np.ndarray)):
        return "(" + ", ".join(_show(v) for v in value) + ")"
    return repr(value)


def _number(value, what: str) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{what}: not a number: {_show(value)}") from None
    if not math.isfinite(x):
        raise InputError(f"{what}: not finite: {_show(value)}")
    problem = magnitude_problem(x)
    if problem:
        raise InputError(f"{what}: {problem}, got {_show(value)}")
    return x


def _vector(values, what: str) -> tuple[float, float, float]:
    try:
        items = list(values)
    except TypeError:
        raise InputError(f"{what}: expected 3 numbers, got {_show(values)}") from None
    if len(items) != 3:
        raise InputError(f"{what}: expected 3 numbers, got {_show(values)}")
    return tuple(_number(x, what) for x in items)


@dataclass(frozen=True)
class Scale:
    """Multiply every coordinate by ``factor`` (> 0), about the origin."""

    factor: float

    def __post_init__(self):
        f = _number(self.factor, "scale")
        if f <= 0:
            raise InputError(f"scale: the factor must be > 0 (a mirror turns the normals "
                             f"inside out), got {_show(self.factor)}")
        object.__setattr__(self, "factor", f)

    def apply(self, x: np.ndarray) -> np.ndarray:
        return x * self.factor


@dataclass(frozen=True)
class Move:
    """Translate by ``offset`` (dx, dy, dz) [L]."""

    offset: tuple[float, float, float]

    def __post_init__(self):
        object.__setattr__(self, "offset", _vector(self.offset, "move"))

    def apply(self, x: np.ndarray) -> np.ndarray:
        return x + np.asarray(self.offset)


@dataclass(frozen=True)
class Rotate:
    """Rotate by ``angle`` [deg] about ``axis`` (ax, ay, az; any non-zero length)
    through the origin, right-hand rule."""

    axis: tuple[float, float, float]
    angle: float

    def __post_init__(self):
        axis = _vector(self.axis, "rotate axis")
        if not np.linalg.norm(axis) > 0:
            raise InputError(f"rotate axis: must not be zero, got {_show(self.axis)}")
        object.__setattr__(self, "axis", axis)
        object.__setattr__(self, "angle", _number(self.angle, "rotate angle"))

    @property
    def rotation(self) -> Rotation:
        axis = np.asarray(self.axis) / np.linalg.norm(self.axis)
        return Rotation.from_rotvec(axis * math.radians(self.angle))

    def apply(self, x: np.ndarray) -> np.ndarray:
        return self.rotation.apply(x)


Transform = Scale | Move | Rotate


def parse_transforms(text: str) -> list[Transform]:
    """The operations written in LIGGGHTS' keywords, in order: ``scale s``,
    ``move dx dy dz``, ``rotate axis ax ay az angle deg``."""
    words = str(text).split()
    out: list[Transform] = []
    k = 0

    def take(n: int, what: str) -> list[str]:
        nonlocal k
        if k + n > len(words):
            raise InputError(f"transforms: {what}: expected {n} value(s) after "
                             f"{words[k - 1]!r}, got {words[k:]!r}")
        got = words[k:k + n]
        k += n
        return got

    def keyword(word: str):
        nonlocal k
        if k >= len(words) or words[k] != word:
            got = words[k] if k < len(words) else "the end"
            raise InputError(f"transforms: rotate: expected {word!r}, got {got!r}")
        k += 1

    while k < len(words):
        word = words[k]
        k += 1
        if word == "scale":
            out.append(Scale(take(1, "scale")[0]))
        elif word == "move":
            out.append(Move(take(3, "move")))
        elif word == "rotate":
            keyword("axis")
            axis = take(3, "rotate axis")
            keyword("angle")
            out.append(Rotate(axis, take(1, "rotate angle")[0]))
        else:
            raise InputError(f"transforms: unknown operation {word!r} (expected scale, move "
                             "or rotate)")
    return out


def apply_transforms(vertices: np.ndarray, transforms, where: str = "mesh") -> np.ndarray:
    """``vertices`` (V, 3) [L] after each of ``transforms`` in turn (a sequence of
    :class:`Scale`, :class:`Move`, :class:`Rotate`, or their text for
    :func:`parse_transforms`). A result beyond 1e100 in magnitude is an error naming
    ``where``."""
    if isinstance(transforms, str):
        transforms = parse_transforms(transforms)
    x = np.array(vertices, dtype=np.float64)
    for op in transforms:
        if not isinstance(op, (Scale, Move, Rotate)):
            raise InputError(f"transforms: expected Scale, Move or Rotate, got {op!r}")
        x = op.apply(x)
    problem = np.argwhere(~(np.abs(x) <= MAX_MAGNITUDE))
    if len(problem):
        v, axis = problem[0]
        raise InputError(f"{where}: vertex {v}: {'xyz'[axis]} = {float(x[v, axis])!r} after the "
                         f"transforms: beyond {MAX_MAGNITUDE:g} in magnitude")
    return x
