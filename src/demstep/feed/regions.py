"""Regions particles are inserted into or taken out of.

A region answers two questions: which centres lie inside it (:meth:`Region.contains`,
for outlets), and where a sphere of radius r can be placed wholly inside it
(:meth:`Region.sample`, for insertion: uniform over the region shrunk by r, so that
an inserted particle never pokes out of its region). In 2D (disks) regions use the
first two coordinates; a cylinder is 3D only.

* ``box``: ``lower``, ``upper`` corners [L];
* ``cylinder``: ``axis`` ('x', 'y' or 'z'), ``center`` (the two other coordinates)
  [L], ``radius`` [L], ``lower``/``upper`` along the axis [L];
* ``sphere``: ``center``, ``radius`` [L] (a circle in 2D);
* ``face``: the triangles of a mesh file (``file``, with LIGGGHTS-style ``transforms``;
  an insertion face, as a stream from an inlet; not a wall), extruded along the insertion velocity by the distance covered between two
  insertions: the volume that flows through the face in that time.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from demstep.errors import InputError
from demstep.mesh import read_mesh

AXES = {"x": 0, "y": 1, "z": 2}


def _vector(what: str, value, dim: int) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        v = np.zeros(0)
    if v.shape != (dim,) or not np.isfinite(v).all():
        raise InputError(f"{what}: expected {dim} finite numbers, got {value!r}")
    return v


class Region:
    """A region (module docstring). ``what`` names it in messages."""

    kind = ""

    def __init__(self, dim: int, what: str):
        self.dim = dim
        self.what = what

    def contains(self, x: np.ndarray) -> np.ndarray:
        """Whether each centre (N, >= dim) [L] lies inside (N,) bool."""
        raise NotImplementedError

    def sample(self, rng: np.random.Generator, r: np.ndarray, extrude=None) -> np.ndarray:
        """Centres (N, 3) [L] drawn uniformly where a sphere of radius ``r`` (N,) lies
        wholly inside; NaN rows where the region is too small for that radius."""
        raise NotImplementedError

    def volume(self) -> float:
        """Its volume [L^dim] (area in 2D)."""
        raise NotImplementedError


class BoxRegion(Region):
    kind = "box"

    def __init__(self, dim, what, lower, upper):
        super().__init__(dim, what)
        self.lower = _vector(f"{what}.lower", lower, dim)
        self.upper = _vector(f"{what}.upper", upper, dim)
        bad = np.flatnonzero(self.upper <= self.lower)
        if len(bad):
            k = int(bad[0])
            raise InputError(f"{what}.upper: must be above lower along {'xyz'[k]} "
                             f"({self.lower[k]:g}), got {self.upper[k]:g}")

    def contains(self, x):
        x = x[:, :self.dim]
        return np.all((x >= self.lower) & (x <= self.upper), axis=1)

    def sample(self, rng, r, extrude=None):
        n = len(r)
        out = np.zeros((n, 3))
        lo = self.lower + r[:, None]
        hi = self.upper - r[:, None]
        u = rng.uniform(0.0, 1.0, (n, self.dim))
        out[:, :self.dim] = lo + u * (hi - lo)
        out[np.any(hi < lo, axis=1)] = np.nan
        return out

    def volume(self):
        return float(np.prod(self.upper - self.lower))


class CylinderRegion(Region):
    kind = "cylinder"

    def __init__(self, dim, what, axis, center, radius, lower, upper):
        super().__init__(dim, what)
        if dim != 3:
            raise InputError(f"{what}.shape: a cylinder needs 3D (spheres); use a box in 2D")
        if axis not in AXES:
            raise InputError(f"{what}.axis: expected x, y or z, got {axis!r}")
        self.axis = AXES[axis]
        self.others = [k for k in range(3) if k != self.axis]
        self.center = _vector(f"{what}.center", center, 2)
        self.radius = float(_vector(f"{what}.radius", [radius], 1)[0])
        if self.radius <= 0:
            raise InputError(f"{what}.radius: must be > 0, got {radius!r}")
        self.lower = float(_vector(f"{what}.lower", [lower], 1)[0])
        self.upper = float(_vector(f"{what}.upper", [upper], 1)[0])
        if self.upper <= self.lower:
            raise InputError(f"{what}.upper: must be above lower ({self.lower:g}), got {upper!r}")

    def contains(self, x):
        a = x[:, self.axis]
        d = x[:, self.others] - self.center
        return (a >= self.lower) & (a <= self.upper) & (np.einsum("ij,ij->i", d, d)
                                                        <= self.radius ** 2)

    def sample(self, rng, r, extrude=None):
        n = len(r)
        out = np.zeros((n, 3))
        room = self.radius - r
        rho = np.sqrt(rng.uniform(0.0, 1.0, n)) * np.maximum(room, 0.0)
        phi = rng.uniform(0.0, 2.0 * math.pi, n)
        out[:, self.others[0]] = self.center[0] + rho * np.cos(phi)
        out[:, self.others[1]] = self.center[1] + rho * np.sin(phi)
        lo, hi = self.lower + r, self.upper - r
        out[:, self.axis] = lo + rng.uniform(0.0, 1.0, n) * (hi - lo)
        out[(room < 0) | (hi < lo)] = np.nan
        return out

    def volume(self):
        return math.pi * self.radius ** 2 * (self.upper - self.lower)


class SphereRegion(Region):
    kind = "sphere"

    def __init__(self, dim, what, center, radius):
        super().__init__(dim, what)
        self.center = _vector(f"{what}.center", center, dim)
        self.radius = float(_vector(f"{what}.radius", [radius], 1)[0])
        if self.radius <= 0:
            raise InputError(f"{what}.radius: must be > 0, got {radius!r}")

    def contains(self, x):
        d = x[:, :self.dim] - self.center
        return np.einsum("ij,ij->i", d, d) <= self.radius ** 2

    def sample(self, rng, r, extrude=None):
        n = len(r)
        out = np.zeros((n, 3))
        room = self.radius - r
        g = rng.normal(size=(n, self.dim))
        g /= np.linalg.norm(g, axis=1)[:, None]
        rho = rng.uniform(0.0, 1.0, n) ** (1.0 / self.dim) * np.maximum(room, 0.0)
        out[:, :self.dim] = self.center + g * rho[:, None]
        out[room < 0] = np.nan
        return out

    def volume(self):
        return math.pi * self.radius ** 2 if self.dim == 2 else \
            4.0 / 3.0 * math.pi * self.radius ** 3


class FaceRegion(Region):
    """The triangles ``tri`` (T, 9) [L] of an insertion face, extruded along the
    insertion velocity: a particle of radius r is placed at a point of the face
    (area-weighted) moved along the velocity by r plus a uniform fraction of the
    extrusion length (so that it clears the face and fills the volume that flows
    through it between two insertions)."""

    kind = "face"

    def __init__(self, dim, what, tri, mesh_name: str):
        super().__init__(dim, what)
        if dim != 3:
            raise InputError(f"{what}.shape: an insertion face needs 3D (spheres)")
        self.tri = np.asarray(tri, dtype=np.float64).reshape(-1, 9)
        self.mesh_name = mesh_name
        a, b, c = self.tri[:, 0:3], self.tri[:, 3:6], self.tri[:, 6:9]
        cross = np.cross(b - a, c - a)
        self.areas = 0.5 * np.linalg.norm(cross, axis=1)
        if self.areas.sum() <= 0:
            raise InputError(f"{what}.file: the face {mesh_name!r} has no area")
        self.normal = cross.sum(axis=0) / np.linalg.norm(cross.sum(axis=0))

    def contains(self, x):
        raise InputError(f"{self.what}: a mesh face cannot be an outlet; use a box, "
                         f"cylinder or sphere")

    def sample(self, rng, r, extrude=None):
        """``extrude`` (3,) [L]: the insertion velocity times the time between insertions."""
        n = len(r)
        k = rng.choice(len(self.areas), size=n, p=self.areas / self.areas.sum())
        u, v = rng.uniform(0.0, 1.0, n), rng.uniform(0.0, 1.0, n)
        flip = u + v > 1.0
        u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
        t = self.tri[k]
        p = t[:, 0:3] + u[:, None] * (t[:, 3:6] - t[:, 0:3]) + v[:, None] * (t[:, 6:9] - t[:, 0:3])
        ext = np.zeros(3) if extrude is None else np.asarray(extrude, dtype=np.float64)
        length = float(np.linalg.norm(ext))
        if length > 0.0:
            direction = ext / length
        else:  # (no velocity: off the face along its normal)
            direction = self.normal
        # clear the face by r along the direction (its normal component must be r)
        along = r / max(abs(float(direction @ self.normal)), 1e-12)
        return p + direction * (along + rng.uniform(0.0, 1.0, n) * length)[:, None]

    def volume(self):
        return float(self.areas.sum())


def region_from_spec(spec: dict, dim: int, what: str, base_dir=None) -> Region:
    """A region from a dict ``{shape = KIND, ...}`` (module docstring); a face's
    ``file`` is relative to ``base_dir`` (the case file's folder)."""
    if not isinstance(spec, dict):
        raise InputError(f"{what}: expected a table with 'shape', got {spec!r}")
    spec = dict(spec)
    shape = spec.pop("shape", None)
    keys = {"box": ("lower", "upper"), "cylinder": ("axis", "center", "radius", "lower", "upper"),
            "sphere": ("center", "radius"), "face": ("file", "transforms")}
    if shape not in keys:
        raise InputError(f"{what}.shape: expected box, cylinder, sphere or face, got {shape!r}")
    for key in spec:
        if key not in keys[shape]:
            raise InputError(f"{what}.{key}: unknown key for a {shape} (expected "
                             f"{', '.join(keys[shape])})")
    for key in keys[shape]:
        if key not in spec and key != "transforms":
            raise InputError(f"{what}.{key}: required for a {shape}")
    if shape == "box":
        return BoxRegion(dim, what, spec["lower"], spec["upper"])
    if shape == "cylinder":
        return CylinderRegion(dim, what, spec["axis"], spec["center"], spec["radius"],
                              spec["lower"], spec["upper"])
    if shape == "sphere":
        return SphereRegion(dim, what, spec["center"], spec["radius"])
    path = Path(base_dir or ".") / str(spec["file"])
    try:
        mesh = read_mesh(path, spec.get("transforms", ()))
    except InputError as err:
        raise InputError(f"{what}.file: {err}") from None
    return FaceRegion(dim, what, mesh.corners.reshape(-1, 9), str(spec["file"]))
