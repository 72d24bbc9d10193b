"""Writes the mesh fixtures of tests/test_mesh_io.py (run from anywhere; the files are
committed, so this only documents how they were made):

* hopper_ascii.stl, hopper_binary.stl, hopper.obj: the same open square hopper of 8
  triangles, outlet [-0.125, 0.125]^2 at z = 0, top [-0.5, 0.5]^2 at z = 1 [m], normals
  facing the axis. Every coordinate is a dyadic fraction, exact in float32, so the three
  files hold the same numbers. The binary file's 80-byte header starts with "solid", as
  some CAD exporters write it (a reader must not take it for ASCII).
"""

from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

# outlet corners 0-3, top corners 4-7, counter-clockwise seen from above
VERTICES = np.array([[-0.125, -0.125, 0], [0.125, -0.125, 0], [0.125, 0.125, 0],
                     [-0.125, 0.125, 0], [-0.5, -0.5, 1], [0.5, -0.5, 1], [0.5, 0.5, 1],
                     [-0.5, 0.5, 1]], dtype=np.float64)
# side k: outlet k, k+1 and top k+1, k, ordered so that the normals face the axis
TRIANGLES = np.array([[0, 4, 5], [0, 5, 1], [1, 5, 6], [1, 6, 2],
                      [2, 6, 7], [2, 7, 3], [3, 7, 4], [3, 4, 0]])
# renumbered in the order the facets first use the vertices (the order an STL reader
# finds them in), so that the OBJ file reads to the same arrays as the STL files
_FIRST = TRIANGLES.ravel()[np.sort(np.unique(TRIANGLES.ravel(), return_index=True)[1])]
VERTICES = VERTICES[_FIRST]
TRIANGLES = np.argsort(_FIRST)[TRIANGLES]


def normals():
    p = VERTICES[TRIANGLES]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return n / np.linalg.norm(n, axis=1)[:, None]


def write_ascii(path):
    lines = ["solid hopper"]
    for tri, n in zip(TRIANGLES, normals()):
        lines.append(f"  facet normal {n[0]:.6e} {n[1]:.6e} {n[2]:.6e}")
        lines.append("    outer loop")
        lines += [f"      vertex {x!r} {y!r} {z!r}" for x, y, z in VERTICES[tri].tolist()]
        lines += ["    endloop", "  endfacet"]
    lines.append("endsolid hopper")
    Path(path).write_text("\n".join(lines) + "\n")


def write_binary(path):
    record = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)), ("attr", "<u2")])
    data = np.zeros(len(TRIANGLES), dtype=record)
    data["normal"] = normals()
    data["corners"] = VERTICES[TRIANGLES]
    header = b"solid hopper, binary (a CAD-style header)".ljust(80, b" ")
    with open(path, "wb") as fh:
        fh.write(header + np.uint32(len(TRIANGLES)).tobytes() + data.tobytes())


def write_obj(path):
    lines = ["# open square hopper, 8 triangles"]
    lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in VERTICES.tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in TRIANGLES.tolist()]
    Path(path).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    write_ascii(HERE / "hopper_ascii.stl")
    write_binary(HERE / "hopper_binary.stl")
    write_obj(HERE / "hopper.obj")
