"""Reading triangle meshes from files: STL (ASCII and binary), OBJ, and whatever else
meshio reads that holds triangle (or quad) cells (VTK, VTU, Gmsh, PLY, OFF, ...).

The file is parsed by meshio's reader for its format (chosen by extension, or
``file_format``); the mesh then goes through :func:`~demstep.mesh.surface.mesh_from_arrays`
(checks, repairs, transforms). Before meshio sees an STL file its kind is decided
here: binary when its size is exactly 84 + 50 N bytes for the N triangles its header
counts, else ASCII when it is text starting with ``solid``; anything else (a
truncated binary STL, a binary file that is no STL) is refused with the sizes.

Every failure is one line of :class:`~demstep.errors.InputError` naming the file.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import numpy as np

from demstep.errors import InputError
from demstep.io.textfile import FIRST_BLOCK, check_regular_file
from demstep.mesh.surface import AREA_TOL, MERGE_TOL, MeshWarning, TriangleMesh, mesh_from_arrays

log = logging.getLogger("demstep")

#: cells without area, ignored without a word (Gmsh and VTK files carry them)
_IGNORED_CELLS = ("vertex", "line", "line3")


def read_mesh(path, transforms=(), *, name: str | None = None, file_format: str | None = None,
              merge_tol: float = MERGE_TOL, area_tol: float = AREA_TOL) -> TriangleMesh:
    """The checked :class:`TriangleMesh` in the file ``path``.

    ``transforms``: :class:`~demstep.mesh.transforms.Scale`, ``Move``, ``Rotate``
    operations applied in order after the checks (or their LIGGGHTS text, e.g.
    ``"scale 0.001 rotate axis 1 0 0 angle 90"``). ``name``: the mesh's name (default:
    the file name without its extension). ``file_format``: a meshio format name
    ("stl", "obj", "vtk", "gmsh", ...) when the extension does not tell. ``merge_tol``
    and ``area_tol``: see :func:`~demstep.mesh.surface.mesh_from_arrays`. Units are the
    file's (none is assumed); binary STL coordinates are float32 in the file.

    Quad cells are split into two triangles along their shorter diagonal (one
    :class:`~demstep.mesh.surface.MeshWarning`); triangles are numbered in messages by
    their place among the triangles read (0-based, file order, a split quad giving two).
    """
    path = check_regular_file(path, "mesh file")
    if path.stat().st_size == 0:
        raise InputError(f"{path}: empty file")
    fmt = file_format or _format_of(path)
    if fmt == "stl":
        _check_stl(path)
    raw = _read_meshio(path, fmt)
    vertices, triangles = _triangles(raw, path, fmt)
    mesh = mesh_from_arrays(vertices, triangles, name if name is not None else path.stem,
                            transforms=transforms, merge_tol=merge_tol, area_tol=area_tol,
                            source=str(path))
    if log.isEnabledFor(logging.INFO):
        log.info("%s", mesh.summary())
    return mesh


def _format_of(path: Path) -> str | list[str]:
    """The meshio format (or the candidates, tried in order) for ``path``'s extension."""
    import meshio

    ext = ""
    for suffix in reversed(path.suffixes):  # ".vol.gz" before ".gz"
        ext = (suffix + ext).lower()
        if ext in meshio.extension_to_filetypes:
            found = meshio.extension_to_filetypes[ext]
            return found[0] if len(found) == 1 else list(found)
    raise InputError(f"{path}: unknown mesh format (extension {path.suffix!r}); use .stl, "
                     ".obj, .vtk, .vtu, .msh, .ply, .off or give file_format")


def _check_stl(path: Path) -> None:
    """Refuse an STL file that is neither a binary STL of the right size nor text
    starting with 'solid' (meshio would misread it)."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(FIRST_BLOCK)
    if size >= 84:
        n = int.from_bytes(head[80:84], "little")
        if size == 84 + 50 * n:
            return  # binary
    if b"\0" not in head:
        if head.removeprefix(b"\xef\xbb\xbf").lstrip().startswith(b"solid"):  # (a BOM)
            return  # ASCII
        raise InputError(f"{path}: not an STL file (text that does not start with 'solid')")
    if size < 84:
        raise InputError(f"{path}: not an STL file (binary, {size} bytes: shorter than the "
                         "84-byte header of a binary STL)")
    raise InputError(f"{path}: not a valid binary STL: its header counts {n} triangles "
                     f"(84 + 50 x {n} = {84 + 50 * n} bytes) but the file has {size} bytes "
                     "(truncated, or not an STL file)")


def _read_meshio(path: Path, fmt: str | list[str]):
    """meshio's reader for ``fmt`` on ``path`` (each candidate in turn), its failures
    as one line. meshio.read is not used: on some errors it prints and exits."""
    import meshio

    formats = fmt if isinstance(fmt, list) else [fmt]
    error = None
    for name in formats:
        module = getattr(meshio, name.replace("-", "_"), None)
        reader = getattr(module, "read", None)
        if reader is None:
            raise InputError(f"{path}: file_format {name!r}: not a format meshio reads")
        try:
            # (meshio's STL reader multiplies an ASCII file's bytes 80-84 as a uint32)
            with np.errstate(over="ignore"):
                return reader(str(path))
        except MemoryError:
            raise
        except Exception as exc:  # noqa: BLE001 (a parser of arbitrary files: any type)
            error = (name, exc)
    name, exc = error
    what = " ".join(str(exc).split()) or type(exc).__name__
    if len(what) > 200:
        what = what[:200] + "..."
    raise InputError(f"{path}: cannot be read as {name.upper() if name in ('stl', 'obj') else name}"
                     f" ({what})") from None


def _triangles(raw, path: Path, fmt) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3), triangles (T, 3)) from a meshio mesh: triangle cells as
    they are, quads split, cells without area ignored, others ignored with a warning
    (or an error when nothing else is there)."""
    points = np.asarray(raw.points)
    if points.size and (points.ndim != 2 or points.shape[1] < 3):
        raise InputError(f"{path}: vertices have {points.shape[-1]} coordinates; a mesh wall "
                         "needs 3")
    points = points.reshape(-1, points.shape[-1] if points.ndim == 2 else 3)[:, :3]
    parts, n_quads, other = [], 0, {}
    for block in raw.cells:
        data = np.asarray(block.data)
        kind = block.type
        if kind == "polygon" and data.ndim == 2 and data.shape[1] in (3, 4):
            kind = "triangle" if data.shape[1] == 3 else "quad"
        if kind == "triangle":
            parts.append(data)
        elif kind == "quad":
            parts.append(_split_quads(points, data))
            n_quads += len(data)
        elif kind not in _IGNORED_CELLS:
            other[kind] = other.get(kind, 0) + len(data)
    found = ", ".join(f"{n} {kind}" for kind, n in other.items())
    if not parts or sum(len(p) for p in parts) == 0:
        raise InputError(f"{path}: no triangles (an empty mesh)"
                         + (f"; found only {found} cells" if other else ""))
    if other:
        warnings.warn(f"demstep: {path}: ignored {found} cells (only triangles and quads make "
                      "a wall)", MeshWarning, stacklevel=3)
    if n_quads:
        warnings.warn(f"demstep: {path}: split {n_quads} quads into two triangles each (along "
                      "the shorter diagonal)", MeshWarning, stacklevel=3)
    triangles = np.concatenate(parts).astype(np.int64)
    if fmt == "obj" and (triangles < 0).any():
        k, c = np.argwhere(triangles < 0)[0]
        raise InputError(f"{path}: triangle {k}: vertex index {triangles[k, c] + 1} (as "
                         "written): relative (negative) and zero OBJ indices are not supported")
    return points, triangles


def _split_quads(points, quads) -> np.ndarray:
    """(2 Q, 3): each quad (a, b, c, d) as two triangles of the same orientation, cut
    along its shorter diagonal (a-c or b-d)."""
    q = quads.astype(np.int64)
    if q.size and (q.min() < 0 or q.max() >= len(points)):
        return np.stack([q[:, [0, 1, 2]], q[:, [0, 2, 3]]], axis=1).reshape(-1, 3)  # refused later
    p = points[q]
    ac = np.sum((p[:, 2] - p[:, 0]) ** 2, axis=1)
    bd = np.sum((p[:, 3] - p[:, 1]) ** 2, axis=1)
    use_bd = (bd < ac)[:, None]
    first = np.where(use_bd, q[:, [0, 1, 3]], q[:, [0, 1, 2]])
    second = np.where(use_bd, q[:, [1, 2, 3]], q[:, [0, 2, 3]])
    return np.stack([first, second], axis=1).reshape(-1, 3)
