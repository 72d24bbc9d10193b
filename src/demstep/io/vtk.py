"""VTK output for ParaView / PyVista: particles, contact network and walls per frame,
with ``.pvd`` collection files that make each a time series.

Each frame writes up to three unstructured-grid files (``.vtu``, via meshio):

* ``particles_STEP.vtu``: one vertex per particle centre [L] with point data
  ``radius`` [L], ``mass`` [M], ``velocity`` [L/T] (the central-difference half-step
  velocity), ``angular_velocity`` [1/T], ``force`` [M L/T^2] and ``torque``
  [M L^2/T^2] (contact forces of the last force evaluation), ``fixed`` (0/1) and
  ``id``. Disks (2D) lie in the plane z = 0. In ParaView: Glyph, sphere, scale by
  ``radius`` (scale factor 2: the glyph's default size is a diameter of 1).
* ``contacts_STEP.vtu``: a line between the centres of each pair in contact, with cell
  data ``normal_force`` [M L/T^2] (compression positive) and ``force`` (the force on
  the second particle). Pairs that touch across a periodic boundary are left out.
  A frame without contacts holds one zero-length line (meshio cannot read back a grid
  without cells).
* ``walls_STEP.vtu``: each wall as a quad (3D) or a line (2D) spanning the specimen,
  with cell data ``force`` (exerted by the particles), ``stress``, ``velocity`` and
  ``wall_id``.
* ``meshes_STEP.vtu`` (mesh walls only): the triangles of every mesh where they are
  now, with cell data ``force`` (the force the particles exert on the triangle
  [M L/T^2], the sum of the contacts it holds), ``pressure`` (its normal component over
  the triangle's area [M/(L T^2)], positive when the particles push along the normal as
  stored, whichever side they are on) and ``mesh_id`` (the mesh's place in the case).
* ``bodies_STEP.vtu`` (clumps only): one vertex per body at its centre of mass with its
  velocity, angular momentum, mass, principal moments and axes (:func:`body_mesh`); the
  particles' ``body`` point data says which body each member sphere belongs to.

``particles.pvd``, ``contacts.pvd``, ``walls.pvd`` (and ``meshes.pvd``, ``bodies.pvd``) list the frames with their
simulated times [T]; they are rewritten atomically after every frame.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from demstep.clumps import quat_to_matrix
from demstep.contact.geometry import pair_geometry_arrays
from demstep.errors import InputError
from demstep.io.atomic import atomic_path, write_text_atomic

SERIES = ("particles", "contacts", "walls", "meshes", "bodies")
_FRAME = re.compile(r"_(\d+)\.vtu$")


def _meshio():
    import meshio  # (deferred: a heavy import, loaded only when used)

    return meshio


def particle_ids(sim) -> np.ndarray:
    """Each sphere's id (N,): its input row when the particles were reordered
    (``sim.source_index``: ``demstep run`` puts a file's particles in spatial order),
    else its index."""
    if hasattr(sim, "particle_ids"):
        return sim.particle_ids()
    source = getattr(sim, "source_index", None)
    if source is not None and len(source) == len(sim.r):
        return np.asarray(source, dtype=np.int64)
    return np.arange(len(sim.r), dtype=np.int64)


def particle_mesh(sim):
    """Particles as vertices with their state as point data."""
    meshio = _meshio()
    n = len(sim.r)
    return meshio.Mesh(
        np.array(sim.x, dtype=np.float64), [("vertex", np.arange(n).reshape(-1, 1))],
        point_data={
            "radius": np.array(sim.r, dtype=np.float64),
            "mass": np.array(sim.m, dtype=np.float64),
            "velocity": np.array(sim.v, dtype=np.float64),
            "angular_velocity": np.array(sim.w, dtype=np.float64),
            "force": np.array(sim.force, dtype=np.float64),
            "torque": np.array(sim.torque, dtype=np.float64),
            "fixed": sim.fixed.astype(np.int32),
            "id": particle_ids(sim),
            "body": np.array(sim.bodies.sphere_body, dtype=np.int64),
        })


def body_mesh(sim):
    """Clumps as vertices at their centres of mass, with point data ``velocity`` [L/T],
    ``angular_momentum`` [M L^2/T], ``mass`` [M], the principal ``moments`` [M L^2] and
    the principal axes ``axis_1``, ``axis_2``, ``axis_3`` (unit vectors, world frame;
    in ParaView: Glyph, arrows, orientation by an axis)."""
    meshio = _meshio()
    b = sim.bodies
    R = quat_to_matrix(b.q)
    return meshio.Mesh(
        np.array(b.x, dtype=np.float64), [("vertex", np.arange(b.n).reshape(-1, 1))],
        point_data={"velocity": np.array(b.v), "angular_momentum": np.array(b.L),
                    "mass": np.array(b.m), "moments": np.array(b.inertia),
                    "axis_1": np.ascontiguousarray(R[:, :, 0]),
                    "axis_2": np.ascontiguousarray(R[:, :, 1]),
                    "axis_3": np.ascontiguousarray(R[:, :, 2]),
                    "id": np.arange(b.n, dtype=np.int64)})


def contact_lines(sim):
    """Pairs in contact (i, j) (C, 2), their normal force (C,) [M L/T^2] (compression
    positive) and force on j (C, 3); pairs across periodic boundaries left out."""
    pairs, force, normal = sim.contact_forces()  # (none before the lists are built)
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0), np.zeros((0, 3))
    i, j = pairs[:, 0], pairs[:, 1]
    images = pair_geometry_arrays(sim.x, sim.r, i, j, sim.periodic_len)[5]
    wrapped = np.any(images != 0, axis=1)
    f_n = np.einsum("ck,ck->c", force, normal)
    keep = ~wrapped
    return np.stack([i[keep], j[keep]], axis=1), f_n[keep], force[keep]


def contact_mesh(sim):
    """The contact network as lines between centres."""
    meshio = _meshio()
    lines, f_n, force = contact_lines(sim)
    if len(lines) == 0:
        lines, f_n, force = np.zeros((1, 2), dtype=np.int64), np.zeros(1), np.zeros((1, 3))
    return meshio.Mesh(np.array(sim.x, dtype=np.float64), [("line", lines)],
                       cell_data={"normal_force": [f_n], "force": [force]})


def _extent(sim) -> tuple[np.ndarray, np.ndarray]:
    """The box the walls are drawn across [L]: the particles, the walls' reference
    points and the meshes' corners, padded by 2 % (a run that starts empty: the
    walls and meshes alone; nothing with a size at all: a box of 1 about them)."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    if len(sim.r):
        lo = (sim.x - sim.r[:, None]).min(axis=0)
        hi = (sim.x + sim.r[:, None]).max(axis=0)
    parts = [sim.wall_point] if len(sim.walls) else []
    meshes = getattr(sim, "meshes", None)
    if meshes is not None and len(meshes.tri):
        parts.append(meshes.tri.reshape(-1, 3))
    for points in parts:
        lo = np.minimum(lo, points.min(axis=0))
        hi = np.maximum(hi, points.max(axis=0))
    if not np.all(np.isfinite(lo)):
        lo, hi = np.zeros(3), np.zeros(3)
    span = float(np.max(hi - lo))
    pad = 0.02 * span if span > 0 else 0.5
    lo, hi = lo - pad, hi + pad
    if sim.dim == 2:
        lo[2], hi[2] = 0.0, 0.0
    return lo, hi


def wall_geometry(sim) -> tuple[np.ndarray, np.ndarray]:
    """Corner points and cells (quads in 3D, lines in 2D) of every wall, spanning the
    specimen's extent."""
    lo, hi = _extent(sim)
    centre = 0.5 * (lo + hi)
    half = 0.5 * float(np.linalg.norm(hi - lo))
    points, cells = [], []
    for k in range(len(sim.walls)):
        n = sim.wall_normal[k]
        p = sim.wall_point[k]
        axis = int(np.argmax(np.abs(n)))
        aligned = abs(abs(n[axis]) - 1.0) < 1e-12
        if sim.dim == 2:
            t = np.array([-n[1], n[0], 0.0])
            if aligned:
                other = 1 - axis
                a = p.copy()
                b = p.copy()
                a[other], b[other] = lo[other], hi[other]
                corners = [a, b]
            else:
                c = centre - np.dot(centre - p, n) * n
                corners = [c - half * t, c + half * t]
        else:
            if aligned:
                u, v = [ax for ax in range(3) if ax != axis]
                corners = []
                for cu, cv in ((lo[u], lo[v]), (hi[u], lo[v]), (hi[u], hi[v]), (lo[u], hi[v])):
                    q = p.copy()
                    q[u], q[v] = cu, cv
                    corners.append(q)
            else:
                helper = np.eye(3)[int(np.argmin(np.abs(n)))]
                t1 = np.cross(n, helper)
                t1 /= np.linalg.norm(t1)
                t2 = np.cross(n, t1)
                c = centre - np.dot(centre - p, n) * n
                corners = [c + half * (s1 * t1 + s2 * t2)
                           for s1, s2 in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        start = len(points)
        points += corners
        cells.append(list(range(start, start + len(corners))))
    return np.array(points, dtype=np.float64).reshape(-1, 3), np.array(cells, dtype=np.int64)


def wall_mesh(sim):
    """Walls as quads (3D) or lines (2D) with force, stress and velocity."""
    meshio = _meshio()
    points, cells = wall_geometry(sim)
    with np.errstate(divide="ignore", invalid="ignore"):
        stress = np.array(sim.wall_stress(), dtype=np.float64)
    kind = "quad" if sim.dim == 3 else "line"
    return meshio.Mesh(points, [(kind, cells)], cell_data={
        "force": [np.array(sim.wall_force, dtype=np.float64)],
        "stress": [np.nan_to_num(stress, nan=0.0)],
        "velocity": [np.array(sim.wall_vel, dtype=np.float64)],
        "wall_id": [np.arange(len(sim.walls), dtype=np.int64)],
    })


def triangle_forces(meshes) -> np.ndarray:
    """The force the particles exert on each triangle of the Meshes bundle ``meshes``
    (T, 3) [M L/T^2] at the last force evaluation: the sum of the forces of the contacts
    it holds (its active slots' ``fslot``)."""
    out = np.zeros((len(meshes.tri), 3))
    on = meshes.active == 1
    for k in range(3):
        out[:, k] = np.bincount(meshes.slot_tri[on], weights=meshes.fslot[on, k],
                                minlength=len(meshes.tri))
    return out


def triangle_mesh(sim):
    """The mesh walls' triangles where they are now, with the force on each (and the
    wear of each when a mesh tracks it)."""
    meshio = _meshio()
    m = sim.meshes
    corners = m.tri.reshape(-1, 3, 3)
    force = triangle_forces(m)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area2 = np.linalg.norm(normal, axis=1)  # twice the area
    pressure = 2.0 * np.einsum("ij,ij->i", force, normal) / (area2 * area2)
    cells = {"force": [force], "pressure": [pressure],
             "mesh_id": [np.asarray(m.tri_mesh, dtype=np.int64)]}
    if np.any(m.wear_k > 0.0):  # (Finnie's wear of each triangle [L])
        cells["wear"] = [np.array(m.wear, dtype=np.float64)]
    return meshio.Mesh(m.tri.reshape(-1, 3),
                       [("triangle", np.arange(3 * len(m.tri), dtype=np.int64).reshape(-1, 3))],
                       cell_data=cells)


def write_mesh(path, mesh) -> Path:
    """Write a meshio mesh as .vtu atomically."""
    meshio = _meshio()
    path = Path(path)
    with atomic_path(path, suffix=".vtu") as tmp:
        meshio.write(tmp, mesh, file_format="vtu")
    return path


def write_pvd(path, entries) -> Path:
    """Write a ParaView collection: ``entries`` are (time [T], file relative to the
    .pvd's folder) pairs."""
    path = Path(path)
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    coll = ET.SubElement(root, "Collection")
    for time, file in entries:
        ET.SubElement(coll, "DataSet", timestep=repr(float(time)), group="", part="0",
                      file=str(file))
    ET.indent(root)
    text = '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
    return write_text_atomic(path, text)


def read_pvd(path) -> list[tuple[float, str]]:
    """The (time, file) entries of a .pvd collection."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise InputError(f"{path}: not a readable .pvd file ({exc})") from None
    out = []
    for ds in root.iter("DataSet"):
        try:
            out.append((float(ds.attrib["timestep"]), ds.attrib["file"]))
        except (KeyError, ValueError):
            raise InputError(f"{path}: DataSet: needs timestep and file attributes") from None
    return out


class VtkWriter:
    """Write VTK frames into ``folder``: particles, the contact network (``contacts``)
    and walls (when the simulation has any), each with its .pvd time series. A callable
    that plugs into ``sim.every(n, writer)``.

    ``resume_after_step`` (a restart) keeps the frames already listed up to that step.
    ``on_write(path)`` is called before each file is written (an output manifest,
    :mod:`demstep.io.manifest`)."""

    def __init__(self, folder, contacts: bool = True, resume_after_step: int | None = None,
                 on_write=None):
        self.folder = Path(folder)
        self.contacts = bool(contacts)
        self.on_write = on_write
        self.entries: dict[str, list[tuple[float, str]]] = {s: [] for s in SERIES}
        self.last_step = None
        if resume_after_step is not None:
            for series in SERIES:
                pvd = self.folder / f"{series}.pvd"
                if pvd.exists():
                    self.entries[series] = [
                        (t, f) for t, f in read_pvd(pvd)
                        if _FRAME.search(f) and int(_FRAME.search(f).group(1)) <= resume_after_step]

    def write(self, sim) -> list[Path]:
        """Write the frame of the current step (once per step)."""
        if self.last_step == sim.step:
            return []
        self.folder.mkdir(parents=True, exist_ok=True)
        written = []
        meshes = {"particles": particle_mesh}
        if self.contacts:
            meshes["contacts"] = contact_mesh
        if len(sim.walls):
            meshes["walls"] = wall_mesh
        if len(sim.meshes.tri):
            meshes["meshes"] = triangle_mesh
        if sim.bodies.n:
            meshes["bodies"] = body_mesh
        for series, make in meshes.items():
            name = f"{series}_{sim.step:010d}.vtu"
            if self.on_write is not None:
                self.on_write(self.folder / name)
                self.on_write(self.folder / f"{series}.pvd")
            written.append(write_mesh(self.folder / name, make(sim)))
            entries = [e for e in self.entries[series] if e[1] != name]
            entries.append((float(sim.time), name))
            self.entries[series] = entries
            write_pvd(self.folder / f"{series}.pvd", entries)
        self.last_step = sim.step
        return written

    __call__ = write
