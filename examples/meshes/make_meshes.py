"""Writes the STL meshes of the examples (unit sizes; the case files scale and place
them with their ``transforms``):

* ``hopper.stl``: a square hopper, outlet corners on the circle of radius 0.25 in z = 0,
  top corners on radius 1 at z = 1 (8 triangles, open);
* ``plate.stl``: the unit square in z = 0 cut into 4 x 4 squares (32 triangles);
* ``drum.stl``: a closed cylinder of 32 side facets, radius 1, from z = 0 to z = 1 (128
  triangles).

    python examples/meshes/make_meshes.py
"""

from pathlib import Path

import meshio
import numpy as np

from demstep.mesh.shapes import cylinder, hopper, plane

HERE = Path(__file__).resolve().parent


def write(mesh, name):
    meshio.write_points_cells(str(HERE / name), np.asarray(mesh.vertices, dtype=float),
                              [("triangle", np.asarray(mesh.triangles))], file_format="stl",
                              binary=False)


if __name__ == "__main__":
    write(hopper(4), "hopper.stl")
    write(plane(4), "plate.stl")
    write(cylinder(32, caps=True), "drum.stl")
