"""Triangle meshes (demstep.mesh): reading STL (ASCII, binary) and OBJ, vertex merging,
transforms and their order, orientation repair, degenerate and duplicated triangles,
edge convexity, and the one-line errors for bad files."""

import warnings
from pathlib import Path

import numpy as np
import pytest

from demstep.errors import InputError
from demstep.mesh import (
    EdgeKind,
    MeshWarning,
    Move,
    Rotate,
    Scale,
    TriangleMesh,
    apply_transforms,
    mesh_from_arrays,
    parse_transforms,
    read_mesh,
)
from demstep.mesh import shapes

DATA = Path(__file__).resolve().parent / "data" / "meshes"
FIXTURES = [DATA / "hopper_ascii.stl", DATA / "hopper_binary.stl", DATA / "hopper.obj"]


# --- writers for the tests' own files -------------------------------------------------


def write_stl_ascii(path, corners, name="test"):
    """An ASCII STL of the facets ``corners`` (T, 3, 3) (facet normals left zero)."""
    lines = [f"solid {name}"]
    for tri in np.asarray(corners, dtype=float).tolist():
        lines += ["facet normal 0 0 0", "outer loop"]
        lines += [f"vertex {x!r} {y!r} {z!r}" for x, y, z in tri]
        lines += ["endloop", "endfacet"]
    lines.append(f"endsolid {name}")
    Path(path).write_text("\n".join(lines) + "\n")


def stl_binary_bytes(corners) -> bytes:
    corners = np.asarray(corners, dtype=float)
    record = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)), ("attr", "<u2")])
    data = np.zeros(len(corners), dtype=record)
    data["corners"] = corners
    return b"binary STL written by the tests".ljust(80) + np.uint32(len(corners)).tobytes() \
        + data.tobytes()


def write_obj(path, vertices, faces, extra=""):
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(vertices, dtype=float).tolist()]
    lines += ["f " + " ".join(str(i + 1) for i in face) for face in faces]
    Path(path).write_text(extra + "\n".join(lines) + "\n")


def canonical(mesh):
    """The triangles as sorted tuples of corner coordinates, each triangle's corners
    rotated (not reordered) to start at its smallest: equal for the same oriented
    surface whatever the vertex numbering."""
    out = []
    for tri in mesh.corners.tolist():
        tri = [tuple(p) for p in tri]
        k = tri.index(min(tri))
        out.append(tuple(tri[k:] + tri[:k]))
    return sorted(out)


def one_line(exc_info, *words):
    text = str(exc_info.value)
    assert "\n" not in text, text
    for word in words:
        assert word in text, text
    return text


# --- reading --------------------------------------------------------------------------


def test_fixtures_ascii_binary_obj_read_alike():
    """The three fixture files hold the same hopper: identical arrays, no warning
    (meshio's STL reader overflows a uint32 on ASCII headers: silenced)."""
    head = (DATA / "hopper_binary.stl").read_bytes()[:5]
    assert head == b"solid"  # a binary STL whose header looks like ASCII
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        meshes = [read_mesh(path) for path in FIXTURES]
    for path in FIXTURES:
        assert path.stat().st_size < 20_000
    first = meshes[0]
    for mesh in meshes[1:]:
        np.testing.assert_array_equal(mesh.vertices, first.vertices)
        np.testing.assert_array_equal(mesh.triangles, first.triangles)
    assert first.n_vertices == 8 and first.n_triangles == 8
    assert [m.name for m in meshes] == ["hopper_ascii", "hopper_binary", "hopper"]
    assert first.vertices.dtype == np.float64 and first.triangles.dtype == np.int64
    lo, hi = first.bounding_box()
    np.testing.assert_array_equal(lo, [-0.5, -0.5, 0.0])
    np.testing.assert_array_equal(hi, [0.5, 0.5, 1.0])
    # normals face the axis (inward and up), open at both ends
    towards_axis = -first.centroids[:, :2]
    assert np.all(np.einsum("ij,ij->i", first.normals[:, :2], towards_axis) > 0)
    assert np.all(first.normals[:, 2] > 0)
    kinds = first.edge_kinds()
    assert np.sum(kinds == EdgeKind.BOUNDARY) == 8
    assert np.sum(kinds == EdgeKind.CONCAVE) == 4  # the hopper's corners, seen from inside
    assert np.sum(kinds == EdgeKind.FLAT) == 4  # each side's diagonal
    assert not first.is_closed


def test_fixture_matches_its_generator():
    """The committed files are what tests/data/meshes/make_meshes.py writes."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_meshes", DATA / "make_meshes.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    mesh = read_mesh(DATA / "hopper.obj")
    np.testing.assert_array_equal(mesh.vertices, module.VERTICES)
    np.testing.assert_array_equal(mesh.triangles, module.TRIANGLES)


@pytest.mark.parametrize("binary", [False, True])
def test_stl_of_a_cube_reads_back_the_cube(tmp_path, binary):
    cube = shapes.cube(2.0)
    path = tmp_path / "cube.stl"
    if binary:
        path.write_bytes(stl_binary_bytes(cube.corners))
    else:
        write_stl_ascii(path, cube.corners)
    mesh = read_mesh(path)
    assert mesh.n_vertices == 8 and mesh.n_triangles == 12
    assert canonical(mesh) == canonical(cube)
    assert mesh.is_closed


def test_ascii_stl_with_a_byte_order_mark(tmp_path):
    path = tmp_path / "bom.stl"
    write_stl_ascii(path, shapes.square().corners)
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    assert canonical(read_mesh(path)) == canonical(shapes.square())


def test_stl_near_coincident_vertices_are_merged(tmp_path):
    """Facets whose shared corners differ by 1e-12 (a CAD export's rounding) share
    their edges after the merge; with merge_tol = 0 they do not."""
    plane = shapes.plane(3)
    corners = plane.corners + np.random.default_rng(1).uniform(-1e-12, 1e-12,
                                                                plane.corners.shape)
    path = tmp_path / "plane.stl"
    write_stl_ascii(path, corners)
    mesh = read_mesh(path)
    assert mesh.n_vertices == 16
    assert np.sum(mesh.edge_kinds() == EdgeKind.BOUNDARY) == 12
    assert np.sum(mesh.edge_kinds() == EdgeKind.FLAT) == 21
    apart = read_mesh(path, merge_tol=0.0)
    assert apart.n_vertices == 54
    assert np.all(apart.edge_kinds() == EdgeKind.BOUNDARY)


def test_merge_keeps_the_lowest_index_vertex():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1 + 1e-13, 0, 0], [1, 1, 0]], float)
    mesh = mesh_from_arrays(v, [[0, 1, 2], [3, 4, 2]])
    assert mesh.n_vertices == 4
    np.testing.assert_array_equal(mesh.vertices[1], [1, 0, 0])  # vertex 1 kept, 3 merged
    assert mesh.n_edges == 5  # the two triangles share the edge 1-2


def test_obj_quads_are_split_with_a_warning(tmp_path):
    cube = shapes.cube()
    faces = [[1, 5, 7, 3], [0, 2, 6, 4], [4, 6, 7, 5], [0, 1, 3, 2], [2, 3, 7, 6], [0, 4, 5, 1]]
    path = tmp_path / "cube.obj"
    write_obj(path, cube.vertices, faces)
    with pytest.warns(MeshWarning, match="split 6 quads"):
        mesh = read_mesh(path)
    assert mesh.n_triangles == 12 and mesh.is_closed
    assert np.all(np.einsum("ij,ij->i", mesh.normals, mesh.centroids) > 0)


def test_obj_vertex_colours_are_ignored(tmp_path):
    path = tmp_path / "square.obj"
    path.write_text("v 0 0 0 1 0 0\nv 1 0 0 1 0 0\nv 1 1 0 1 0 0\nf 1 2 3\n")
    mesh = read_mesh(path)
    np.testing.assert_array_equal(mesh.vertices, [[0, 0, 0], [1, 0, 0], [1, 1, 0]])


def test_other_meshio_formats_and_volume_cells(tmp_path):
    import meshio

    cube = shapes.cube()
    meshio.write(tmp_path / "cube.vtu", meshio.Mesh(cube.vertices, [("triangle", cube.triangles)]))
    assert canonical(read_mesh(tmp_path / "cube.vtu")) == canonical(cube)
    # a surface with a line cell (as Gmsh writes them) and a tetrahedron
    tetra = np.array([[0, 1, 2, 4]])
    meshio.write(tmp_path / "mixed.vtu", meshio.Mesh(
        cube.vertices, [("triangle", cube.triangles), ("line", np.array([[0, 1]])),
                        ("tetra", tetra)]))
    with pytest.warns(MeshWarning, match="ignored 1 tetra cells"):
        assert read_mesh(tmp_path / "mixed.vtu").n_triangles == 12
    meshio.write(tmp_path / "solid.vtu", meshio.Mesh(cube.vertices, [("tetra", tetra)]))
    with pytest.raises(InputError) as err:
        read_mesh(tmp_path / "solid.vtu")
    one_line(err, str(tmp_path / "solid.vtu"), "no triangles", "1 tetra")


# --- transforms -----------------------------------------------------------------------


def test_rotate_90_about_z_maps_x_to_y():
    x = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    y = Rotate((0, 0, 2), 90).apply(x)  # the axis need not be unit
    np.testing.assert_allclose(y, [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(Rotate((0, 0, 1), -90).apply(x)[0], [0, -1, 0], atol=1e-15)


def test_transform_order_matters():
    x = np.array([[1.0, 0, 0]])
    np.testing.assert_array_equal(apply_transforms(x, [Scale(2), Move((1, 0, 0))]), [[3, 0, 0]])
    np.testing.assert_array_equal(apply_transforms(x, [Move((1, 0, 0)), Scale(2)]), [[4, 0, 0]])
    a = apply_transforms(x, "move 1 0 0 rotate axis 0 0 1 angle 90")
    b = apply_transforms(x, "rotate axis 0 0 1 angle 90 move 1 0 0")
    np.testing.assert_allclose(a, [[0, 2, 0]], atol=1e-15)
    np.testing.assert_allclose(b, [[1, 1, 0]], atol=1e-15)


def test_parse_transforms_reads_liggghts_keywords_in_order():
    ops = parse_transforms("scale 0.001  move 0 0 0.5 rotate axis 1 0 0 angle 90")
    assert ops == [Scale(0.001), Move((0, 0, 0.5)), Rotate((1, 0, 0), 90)]


def test_read_mesh_applies_the_transforms_after_the_checks():
    mesh = read_mesh(FIXTURES[0], "scale 2 move 0 0 1")
    lo, hi = mesh.bounding_box()
    np.testing.assert_array_equal(lo, [-1, -1, 1])
    np.testing.assert_array_equal(hi, [1, 1, 3])
    turned = read_mesh(FIXTURES[1], [Rotate((1, 0, 0), 180)])
    assert np.all(turned.normals[:, 2] < 0)  # upside down: the normals follow the vertices


@pytest.mark.parametrize("text, words", [
    ("scale -1", ["scale", "must be > 0", "-1"]),
    ("scale 0", ["scale", "must be > 0"]),
    ("scale nan", ["scale", "not finite", "nan"]),
    ("scale 1e200", ["scale", "1e200"]),
    ("move 1 2", ["move", "expected 3"]),
    ("move 1 x 2", ["move", "not a number", "'x'"]),
    ("rotate axis 0 0 0 angle 90", ["rotate axis", "must not be zero"]),
    ("rotate axis 0 0 1", ["rotate", "'angle'", "the end"]),
    ("rotate 0 0 1 angle 90", ["rotate", "'axis'", "'0'"]),
    ("shear 1", ["unknown operation", "'shear'"]),
])
def test_bad_transforms_are_one_line_errors(text, words):
    with pytest.raises(InputError) as err:
        parse_transforms(text)
    one_line(err, *words)


def test_transform_beyond_the_magnitude_limit_is_refused():
    with pytest.raises(InputError) as err:
        shapes.cube(1e60).transformed([Scale(1e60)])
    one_line(err, "cube", "vertex 0", "after the transforms")


# --- orientation ----------------------------------------------------------------------


def test_cube_normals_point_outward():
    cube = shapes.cube()
    assert np.all(np.einsum("ij,ij->i", cube.normals, cube.centroids) > 0)
    # each normal is a coordinate axis, with the sign of its face
    np.testing.assert_allclose(np.abs(cube.normals).max(axis=1), 1.0)
    np.testing.assert_allclose(cube.areas, 0.5)
    assert cube.areas.sum() == pytest.approx(6.0)


def test_a_flipped_cube_face_is_turned_back():
    cube = shapes.cube()
    t = cube.triangles.copy()
    t[[0, 6]] = t[[0, 6]][:, [0, 2, 1]]  # the +z face, both triangles
    assert np.sum(np.einsum("ij,ij->i", TriangleMesh(cube.vertices, t).normals,
                            cube.centroids) < 0) == 2
    with pytest.warns(MeshWarning, match=r"re-oriented 2 triangle\(s\).*first: triangle 0"):
        mesh = mesh_from_arrays(cube.vertices, t, "cube")
    assert np.all(np.einsum("ij,ij->i", mesh.normals, mesh.centroids) > 0)
    np.testing.assert_array_equal(mesh.triangles, cube.triangles)


def test_consistent_inward_normals_are_kept():
    """A closed surface oriented inward throughout (a drum seen from inside) is left
    as it is: orientation is repaired for agreement, never forced outward."""
    inner = shapes.cube().flipped()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mesh = mesh_from_arrays(inner.vertices, inner.triangles)
    assert np.all(np.einsum("ij,ij->i", mesh.normals, mesh.centroids) < 0)
    assert np.all(mesh.edge_kinds() != EdgeKind.CONVEX)


def test_minority_is_flipped_in_each_part():
    plane = shapes.plane(2)  # 8 triangles, normals +z
    far = shapes.cube().flipped()  # a second part, consistently inward
    v = np.concatenate([plane.vertices, far.vertices + [5, 0, 0]])
    t = np.concatenate([plane.triangles, far.triangles + plane.n_vertices])
    t[[1, 2, 5]] = t[[1, 2, 5]][:, [0, 2, 1]]  # 3 of the plane's 8 flipped
    with pytest.warns(MeshWarning, match=r"re-oriented 3 triangle\(s\)"):
        mesh = mesh_from_arrays(v, t)
    assert mesh.n_parts() == 2
    np.testing.assert_allclose(mesh.normals[:8], [[0, 0, 1]] * 8)
    assert np.all(np.einsum("ij,ij->i", mesh.normals[8:], mesh.centroids[8:] - [5, 0, 0]) < 0)


def moebius(n=12, width=0.3):
    phi = 2 * np.pi * np.arange(n) / n
    def point(w):
        r = 1 + w * np.cos(phi / 2)
        return np.stack([r * np.cos(phi), r * np.sin(phi), w * np.sin(phi / 2)], axis=1)
    v = np.concatenate([point(width), point(-width)])  # a_i = i, b_i = n + i
    t = []
    for i in range(n):
        a0, b0 = i, n + i
        a1, b1 = ((i + 1, n + i + 1) if i + 1 < n else (n, 0))  # the half twist
        t += [[a0, a1, b1], [a0, b1, b0]]
    return v, np.array(t)


def test_a_moebius_strip_is_refused():
    v, t = moebius()
    with pytest.raises(InputError) as err:
        mesh_from_arrays(v, t, "strip")
    one_line(err, "strip: triangle", "not orientable")


# --- degenerate, duplicated and non-manifold triangles ----------------------------------


def test_degenerate_triangles_are_dropped_with_a_warning():
    cube = shapes.cube()
    v = np.concatenate([cube.vertices, [[0.0, -0.5, -0.5]]])  # midpoint of the edge 0-4
    t = np.concatenate([cube.triangles, [[0, 0, 3], [0, 8, 4], [1, 5, 7]]])
    t[[12, 13]] = t[[13, 12]]  # the zero-area one first: triangle 12
    with pytest.warns(MeshWarning) as record:
        mesh = mesh_from_arrays(v, t, "cube")
    messages = [str(w.message) for w in record]
    assert any("dropped 2 degenerate triangle(s) (first: triangle 12, area 0" in m
               for m in messages), messages
    assert any("dropped 1 duplicated triangle(s) (first: triangle 14" in m
               for m in messages), messages
    assert mesh.n_triangles == 12 and mesh.n_vertices == 8  # the midpoint is unused
    assert mesh.is_closed
    assert canonical(mesh) == canonical(cube)


def test_duplicates_in_either_orientation_are_dropped():
    cube = shapes.cube()
    t = np.concatenate([cube.triangles, cube.triangles[[3]], cube.triangles[[5]][:, [0, 2, 1]]])
    with pytest.warns(MeshWarning, match=r"dropped 2 duplicated triangle\(s\) \(first: "
                                         r"triangle 12"):
        mesh = mesh_from_arrays(cube.vertices, t)
    np.testing.assert_array_equal(mesh.triangles, cube.triangles)  # the first ones kept


def test_a_near_zero_area_sliver_is_degenerate():
    v = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1e-12, 0], [0, 1, 0]], float)
    with pytest.warns(MeshWarning, match="degenerate.*first: triangle 0, area 5e-13"):
        mesh = mesh_from_arrays(v, [[0, 1, 2], [0, 1, 3]])
    assert mesh.n_triangles == 1


def test_all_degenerate_is_an_error():
    with pytest.raises(InputError) as err:
        mesh_from_arrays([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2], [0, 0, 1]], "line")
    one_line(err, "line", "no triangles left", "all 2")


def test_non_manifold_edge_is_a_warning():
    """A baffle standing on a floor along one of its edges: three triangles share it."""
    square = shapes.square()
    v = np.concatenate([square.vertices, [[0.0, 0.0, 1.0]]])
    t = np.concatenate([square.triangles, [[0, 3, 4]]])  # on the diagonal 0-3
    with pytest.warns(MeshWarning, match=r"1 non-manifold edge.*triangles \[0, 1, 2\]"):
        mesh = mesh_from_arrays(v, t, "baffle")
    e = int(np.flatnonzero(mesh.edge_counts == 3)[0])
    np.testing.assert_array_equal(mesh.edges[e], [0, 3])
    assert mesh.edge_kinds()[e] == EdgeKind.NONMANIFOLD
    assert np.isnan(mesh.edge_angles[e])
    offsets, tris = mesh.edge_incidence()
    np.testing.assert_array_equal(tris[offsets[e]:offsets[e + 1]], [0, 1, 2])
    np.testing.assert_array_equal(mesh.edge_triangles[e], [0, 1])


# --- edges ----------------------------------------------------------------------------


def test_cube_edges_are_convex_at_90_degrees():
    cube = shapes.cube()
    assert cube.n_edges == 18
    kinds = cube.edge_kinds()
    angles = np.degrees(cube.edge_angles)
    convex = kinds == EdgeKind.CONVEX
    assert convex.sum() == 12
    np.testing.assert_allclose(angles[convex], 90.0)
    np.testing.assert_allclose(angles[kinds == EdgeKind.FLAT], 0.0, atol=1e-12)
    assert np.sum(kinds == EdgeKind.FLAT) == 6  # the faces' diagonals
    # flipped, every sharp edge is concave at -90
    inner = cube.flipped()
    np.testing.assert_allclose(np.degrees(inner.edge_angles)[convex], -90.0)
    assert np.all(inner.edge_kinds()[convex] == EdgeKind.CONCAVE)


def test_triangle_edges_and_edge_triangles_agree():
    for mesh in (shapes.cube(), shapes.pyramid(), shapes.plane(3), shapes.cylinder(7, caps=True)):
        t = mesh.triangles
        for k in range(3):
            pair = np.sort(np.stack([t[:, k], t[:, (k + 1) % 3]], axis=1), axis=1)
            np.testing.assert_array_equal(mesh.edges[mesh.triangle_edges[:, k]], pair)
        for e, (a, b) in enumerate(mesh.edge_triangles):
            assert e in mesh.triangle_edges[a]
            assert b == -1 or e in mesh.triangle_edges[b]
        assert np.all(mesh.edges[:, 0] < mesh.edges[:, 1])


def test_flat_plane_interior_edges_are_flat():
    n = 4
    plane = shapes.plane(n, size=2.0)
    assert plane.n_triangles == 2 * n * n and plane.n_vertices == (n + 1) ** 2
    assert plane.n_edges == 3 * n * n + 2 * n
    kinds = plane.edge_kinds()
    boundary = plane.edge_counts == 1
    assert boundary.sum() == 4 * n
    assert np.all(kinds[boundary] == EdgeKind.BOUNDARY)
    assert np.all(kinds[~boundary] == EdgeKind.FLAT)
    assert np.all(plane.edge_triangles[boundary, 1] == -1)
    assert plane.areas.sum() == pytest.approx(4.0)
    np.testing.assert_allclose(plane.normals, [[0, 0, 1]] * plane.n_triangles)


def test_flat_angle_decides_flat_or_convex():
    tube = shapes.cylinder(64)  # 5.625 deg between neighbouring facets
    sharp = tube.edge_angles[tube.edge_counts == 2]
    ring = np.abs(np.degrees(sharp) - 5.625) < 1e-9
    assert ring.sum() == 64
    kinds = tube.edge_kinds()[tube.edge_counts == 2]
    assert np.all(kinds[ring] == EdgeKind.CONVEX)
    assert np.all(tube.edge_kinds(flat_angle=np.radians(6))[tube.edge_counts == 2]
                  == EdgeKind.FLAT)


def test_shapes():
    pyramid = shapes.pyramid(2.0, 3.0)
    assert pyramid.n_triangles == 6 and pyramid.is_closed
    assert np.all(pyramid.edge_kinds()[pyramid.edge_counts == 2] != EdgeKind.CONCAVE)
    lo, hi = pyramid.bounding_box()
    np.testing.assert_array_equal(lo, [-1, -1, 0])
    np.testing.assert_array_equal(hi, [1, 1, 3])
    assert pyramid.areas[:2].sum() == pytest.approx(4.0)  # the base
    tube = shapes.cylinder(10, radius=2.0, height=3.0)
    assert tube.n_triangles == 20 and not tube.is_closed
    np.testing.assert_allclose(np.hypot(*tube.vertices[:, :2].T), 2.0)
    closed = shapes.cylinder(10, caps=True)
    assert closed.n_triangles == 40 and closed.is_closed
    centre = closed.vertices.mean(axis=0)
    assert np.all(np.einsum("ij,ij->i", closed.normals, closed.centroids - centre) > 0)
    assert shapes.square().n_triangles == 2
    np.testing.assert_allclose(shapes.square().centroids.mean(axis=0), 0.0, atol=1e-15)
    hopper = shapes.hopper(8)
    assert np.all(np.einsum("ij,ij->i", hopper.normals[:, :2], hopper.centroids[:, :2]) < 0)


def test_vertex_triangles():
    cube = shapes.cube()
    offsets, tris = cube.vertex_triangles()
    assert offsets[-1] == 36
    for v in range(cube.n_vertices):
        expected = np.flatnonzero((cube.triangles == v).any(axis=1))
        np.testing.assert_array_equal(tris[offsets[v]:offsets[v + 1]], expected)


def test_mesh_arrays_are_read_only():
    cube = shapes.cube()
    with pytest.raises(ValueError):
        cube.vertices[0, 0] = 5.0
    with pytest.raises(ValueError):
        cube.normals[0, 0] = 5.0


def test_summary_names_open_edges():
    text = read_mesh(FIXTURES[0]).summary()
    assert "hopper_ascii: 8 triangles" in text and "open (8 boundary edges)" in text
    assert "closed" in shapes.cube().summary()


# --- bad input: one line naming the file, the triangle and the value --------------------


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(InputError) as err:
        read_mesh(tmp_path / "none.stl")
    one_line(err, "none.stl", "no such mesh file")
    with pytest.raises(InputError) as err:
        read_mesh(tmp_path)
    one_line(err, str(tmp_path), "a folder")


def test_empty_file(tmp_path):
    path = tmp_path / "empty.stl"
    path.write_bytes(b"")
    with pytest.raises(InputError) as err:
        read_mesh(path)
    one_line(err, str(path), "empty file")


def test_binary_file_that_is_no_stl(tmp_path):
    path = tmp_path / "photo.stl"
    path.write_bytes(bytes(range(256)) * 3)  # 768 bytes, NUL bytes included
    n = int.from_bytes(bytes(range(80, 84)), "little")
    with pytest.raises(InputError) as err:
        read_mesh(path)
    one_line(err, str(path), "not a valid binary STL", f"counts {n} triangles",
             "the file has 768 bytes")


def test_truncated_binary_stl(tmp_path):
    path = tmp_path / "cut.stl"
    path.write_bytes((DATA / "hopper_binary.stl").read_bytes()[:-20])
    with pytest.raises(InputError) as err:
        read_mesh(path)
    one_line(err, str(path), "counts 8 triangles", "484 bytes", "has 464 bytes", "truncated")


def test_short_binary_and_text_that_is_no_stl(tmp_path):
    short = tmp_path / "short.stl"
    short.write_bytes(b"\0\1\2")
    with pytest.raises(InputError) as err:
        read_mesh(short)
    one_line(err, str(short), "not an STL file", "3 bytes")
    text = tmp_path / "notes.stl"
    text.write_text("hello, this is a text file\n" * 10)
    with pytest.raises(InputError) as err:
        read_mesh(text)
    one_line(err, str(text), "not an STL file", "'solid'")


def test_malformed_ascii_stl(tmp_path):
    path = tmp_path / "bad.stl"
    path.write_text("solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0\nvertex 1 0 0\n"
                    "vertex 0 1 0\nendloop\nendfacet\nendsolid x\n")
    with pytest.raises(InputError) as err:
        read_mesh(path)
    one_line(err, str(path), "cannot be read as STL")


def test_ascii_stl_without_facets_and_binary_stl_of_zero_triangles(tmp_path):
    path = tmp_path / "none.stl"
    path.write_text("solid x\nendsolid x\n")
    with pytest.raises(InputError) as err:
        read_mesh(path)
    one_line(err, str(path), "no triangles")
    path = tmp_path / "zero.stl"
    path.write_bytes(stl_binary_bytes(np.zeros((0, 3, 3))))
    with pytest.raises(InputError) as err:
        read_mesh(path)
    one_line(err, str(path), "no triangles")


@pytest.mark.parametrize("value, words", [("nan", ["not finite", "nan"]),
                                          ("-inf", ["not finite", "-inf"]),
                                          ("1e300", ["1e+300", "beyond 1e+100"])])
def test_bad_coordinate_names_the_triangle(tmp_path, value, words):
    cube = shapes.cube()
    corners = cube.corners.astype(object).tolist()
    path = tmp_path / "cube.stl"
    write_stl_ascii(path, corners)
    lines = path.read_text().splitlines()
    # triangle 3, corner 2: its z
    k = 1 + 3 * 7 + 2 + 2
    assert lines[k].startswith("vertex")
    x, y, _ = lines[k].split()[1:]
    lines[k] = f"vertex {x} {y} {value}"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as err:
        read_mesh(path)
    one_line(err, str(path), "triangle 3: corner 2", "z = ", *words)


def test_obj_index_errors(tmp_path):
    v = shapes.square().vertices
    path = tmp_path / "out.obj"
    write_obj(path, v, [[0, 1, 2], [0, 2, 7]])
    with pytest.raises(InputError) as err:
        read_mesh(path)
    one_line(err, str(path), "triangle 1", "vertex index 7 out of range", "0 to 3")
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\n")
    with pytest.raises(InputError) as err:
        read_mesh(path)
    one_line(err, str(path), "triangle 0", "-3", "relative (negative)")


def test_obj_unused_bad_vertex_and_no_faces(tmp_path):
    path = tmp_path / "inf.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv inf 0 0\nf 1 2 3\n")
    with pytest.raises(InputError) as err:
        read_mesh(path)
    one_line(err, str(path), "vertex 3 (used by no triangle)", "x = inf")
    path = tmp_path / "points.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(InputError) as err:
        read_mesh(path)
    one_line(err, str(path), "no triangles")


def test_binary_junk_named_obj(tmp_path):
    path = tmp_path / "junk.obj"
    path.write_bytes(bytes(range(128, 256)) * 4)
    with pytest.raises(InputError) as err:
        read_mesh(path)
    one_line(err, str(path), "cannot be read as OBJ")


def test_unknown_extension(tmp_path):
    path = tmp_path / "mesh.xyz"
    path.write_text("1 2 3\n")
    with pytest.raises(InputError) as err:
        read_mesh(path)
    one_line(err, str(path), "unknown mesh format", "'.xyz'")
    write_obj(tmp_path / "square.mesh3", shapes.square().vertices, shapes.square().triangles)
    assert read_mesh(tmp_path / "square.mesh3", file_format="obj").n_triangles == 2


def test_triangle_mesh_constructor_checks():
    v = shapes.square().vertices
    with pytest.raises(InputError) as err:
        TriangleMesh(v[:, :2], [[0, 1, 2]], "flat")
    one_line(err, "flat: vertices", "(4, 2)")
    with pytest.raises(InputError) as err:
        TriangleMesh(v, [[0, 1, 4]], "sq")
    one_line(err, "sq: triangle 0", "vertex index 4 out of range")
    with pytest.raises(InputError) as err:
        TriangleMesh(v, np.zeros((0, 3), dtype=int), "none")
    one_line(err, "none", "no triangles")
