"""Triangle-mesh walls: the mesh (:class:`TriangleMesh`, its normals, edges and their
convexity), reading it from STL, OBJ and other files (:func:`read_mesh`) with its checks
and repairs, the transforms applied on load (:class:`Scale`, :class:`Move`,
:class:`Rotate`, in the order given) and small meshes built in code
(:mod:`demstep.mesh.shapes`). See ``docs/meshes.md``."""

from demstep.mesh.read import read_mesh
from demstep.mesh.surface import (
    AREA_TOL,
    FLAT_ANGLE,
    MERGE_TOL,
    EdgeKind,
    MeshWarning,
    TriangleMesh,
    mesh_from_arrays,
)
from demstep.mesh.transforms import Move, Rotate, Scale, apply_transforms, parse_transforms

__all__ = [
    "AREA_TOL",
    "FLAT_ANGLE",
    "MERGE_TOL",
    "EdgeKind",
    "MeshWarning",
    "Move",
    "Rotate",
    "Scale",
    "TriangleMesh",
    "apply_transforms",
    "mesh_from_arrays",
    "parse_transforms",
    "read_mesh",
]
