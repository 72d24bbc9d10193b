"""Writes ``drum.stl``, the drum of ``examples/rotating_drum_validation.toml`` and of
``validation/drum_repose.py``: a closed cylinder of 64 side facets (corners on the
circle of radius 50 mm), 20 mm long, its axis along y, centred on the origin, normals
inward (towards the particles); 256 triangles, in metres, read by both codes as it is.

    python validation/drum/make_drum.py
"""

from pathlib import Path

import meshio
import numpy as np

from demstep.mesh import Move, Rotate
from demstep.mesh.shapes import cylinder

HERE = Path(__file__).resolve().parent
RADIUS = 0.05     # [m]
LENGTH = 0.02     # [m]
FACETS = 64

if __name__ == "__main__":
    mesh = cylinder(FACETS, radius=RADIUS, height=LENGTH, caps=True).flipped()
    # (z from -L/2 to L/2, then the axis turned from z onto y: 90 degrees about x maps
    # z to -y, so the cylinder lies along y, centred)
    mesh = mesh.transformed([Move((0.0, 0.0, -LENGTH / 2)), Rotate((1.0, 0.0, 0.0), 90.0)])
    meshio.write_points_cells(str(HERE / "drum.stl"), np.asarray(mesh.vertices, dtype=float),
                              [("triangle", np.asarray(mesh.triangles))], file_format="stl",
                              binary=False)
