"""Readers and writers of other codes' particle files: CSV, LIGGGHTS dumps, YADE text."""

import re

import numpy as np
import pytest

from demstep.errors import InputError
from demstep.io.assembly_files import read_assembly
from demstep.io.formats import (
    detect_format, liggghts_timesteps, read_csv, read_liggghts_dump, read_particle_file,
    read_yade_text, write_csv, write_liggghts_dump, write_particle_file, write_yade_text,
)


def assembly(dim, n=17, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-5, 5, (n, dim)), rng.uniform(0.1, 0.9, n), rng.uniform(1, 3, n)


@pytest.mark.parametrize("dim", [2, 3])
def test_csv_round_trip(tmp_path, dim):
    x, r, m = assembly(dim)
    path = write_csv(tmp_path / "a.csv", x, r, m)
    data = read_csv(path)
    assert np.array_equal(data.x, x) and np.array_equal(data.r, r) and np.array_equal(data.m, m)
    data = read_csv(write_csv(tmp_path / "b.csv", x, r))
    assert data.m is None and data.dim == dim


@pytest.mark.parametrize("dim", [2, 3])
def test_liggghts_round_trip(tmp_path, dim):
    x, r, m = assembly(dim)
    v = np.random.default_rng(1).normal(size=(len(r), dim))
    path = tmp_path / "run.liggghts"
    write_liggghts_dump(path, x, r, m, v, timestep=100)
    write_liggghts_dump(path, x + 1.0, r, m, v, timestep=200, append=True)
    assert liggghts_timesteps(path) == [100, 200]
    last = read_liggghts_dump(path)
    first = read_liggghts_dump(path, snapshot=0)
    by_step = read_liggghts_dump(path, timestep=100)
    assert last.timestep == 200 and first.timestep == 100
    assert np.array_equal(first.x[:, :dim], x) and np.array_equal(by_step.x[:, :dim], x)
    assert np.array_equal(last.x[:, :dim], x + 1.0)
    assert np.array_equal(last.r, r) and np.array_equal(last.m, m)
    assert np.array_equal(last.v[:, :dim], v)
    assert list(last.ids) == list(range(1, len(r) + 1))


def test_liggghts_reads_liggghts_layout(tmp_path):
    """A dump as LIGGGHTS writes it: ids out of order, extra columns, scaled
    coordinates, diameters instead of radii."""
    text = """ITEM: TIMESTEP
5000
ITEM: NUMBER OF ATOMS
3
ITEM: BOX BOUNDS pp pp ff
0 10
-5 5
0 20
ITEM: ATOMS id type xs ys zs vx vy vz fx fy fz omegax omegay omegaz diameter mass
3 1 0.5 0.5 0.5 0 0 -1 0 0 0 0 0 0 2.0 4.0
1 2 0.1 0.2 0.25 1 0 0 0 0 0 0 0 1 1.0 0.5
2 1 0.9 0.8 0.75 0 1 0 0 0 0 0 1 0 1.5 1.7
"""
    path = tmp_path / "dump.custom"
    path.write_text(text)
    assert detect_format(path) == "liggghts"  # by content
    data = read_particle_file(path)
    assert list(data.ids) == [1, 2, 3]
    assert np.allclose(data.x, [[1.0, -3.0, 5.0], [9.0, 3.0, 15.0], [5.0, 0.0, 10.0]])
    assert np.allclose(data.r, [0.5, 0.75, 1.0])
    assert np.allclose(data.m, [0.5, 1.7, 4.0])
    assert np.allclose(data.w[0], [0, 0, 1])
    assert list(data.types) == [2, 1, 1]
    via_assembly = read_assembly(path)
    assert np.array_equal(via_assembly.x, data.x)


def test_liggghts_without_z_is_2d(tmp_path):
    path = tmp_path / "flat.dump"
    path.write_text("ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n2\nITEM: BOX BOUNDS pp pp pp\n"
                    "0 1\n0 1\n0 1\nITEM: ATOMS id x y radius\n1 0.1 0.2 0.05\n2 0.4 0.2 0.05\n")
    data = read_liggghts_dump(path)
    assert data.dim == 2 and np.allclose(data.x, [[0.1, 0.2], [0.4, 0.2]])


@pytest.mark.parametrize("dim", [2, 3])
def test_yade_round_trip(tmp_path, dim):
    x, r, _ = assembly(dim)
    path = write_yade_text(tmp_path / "spheres.txt", x, r)
    data = read_yade_text(path)
    assert np.array_equal(data.x, x) and np.array_equal(data.r, r) and data.m is None


def test_yade_export_with_comments_and_extra_columns(tmp_path):
    path = tmp_path / "export.yade"
    path.write_text("# exported by yade.export.text\n#format x_y_z_r_matId\n"
                    "0 0 0 1 0   # first\n\n2.0 0 0 1.0 3\n")
    data = read_yade_text(path)
    assert np.array_equal(data.x, [[0, 0, 0], [2, 0, 0]]) and np.array_equal(data.r, [1, 1])
    plain = tmp_path / "plain.txt"
    plain.write_text("# no format line\n1 2 3 0.5 7\n4 5 6 0.25 7\n")
    data = read_yade_text(plain)
    assert np.array_equal(data.x, [[1, 2, 3], [4, 5, 6]]) and np.array_equal(data.r, [0.5, 0.25])


@pytest.mark.parametrize("suffix,fmt", [(".csv", "csv"), (".liggghts", "liggghts"),
                                        (".dump", "liggghts"), (".txt", "yade"), (".yade", "yade")])
def test_dispatch_by_extension_round_trip(tmp_path, suffix, fmt):
    x, r, _ = assembly(3, seed=4)
    path = write_particle_file(tmp_path / f"p{suffix}", x, r)
    assert detect_format(path) == fmt
    data = read_assembly(path)
    assert np.array_equal(data.x, x) and np.array_equal(data.r, r)


def test_dispatch_by_content_without_known_extension(tmp_path):
    x, r, _ = assembly(3, seed=5)
    for name, writer in (("a.data", write_csv), ("b.data", write_yade_text),
                         ("c.data", write_liggghts_dump)):
        path = writer(tmp_path / name, x, r)
        assert np.array_equal(read_assembly(path).x, x)


BAD_FILES = [
    ("bad.csv", "x,y,z,r\n0,0,0,1\n1,0,abc,1\n", "bad.csv:3: column 'z'"),
    ("bad.csv", "x,y,z\n0,0,0\n", "bad.csv:1: missing column 'r'"),
    ("bad.csv", "x,y,r\n0,0,-1\n", "bad.csv:2: column 'r': radius must be > 0"),
    ("bad.txt", "0 0 0 1\n1 1 1 nan\n", "bad.txt:2: column 'r'"),
    ("bad.txt", "0 0 0 1\n1 1 1\n", "bad.txt:2: expected 4 values"),
    ("bad.txt", "# nothing\n", "bad.txt: no particles"),
    ("bad.dump", "ITEM: TIMESTEP\nzero\n", "bad.dump:2: TIMESTEP: not an integer"),
    ("bad.dump", "ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n2\nITEM: BOX BOUNDS pp pp pp\n"
                 "0 1\n0 1\n0 1\nITEM: ATOMS id x y z radius\n1 0 0 0 1\n", "bad.dump:10: expected 2 atom rows"),
    ("bad.dump", "ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n1\nITEM: BOX BOUNDS pp pp pp\n"
                 "0 1\n0 1\n0 1\nITEM: ATOMS id x y z\n1 0 0 0\n", "missing column 'radius'"),
    ("bad.dump", "ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n1\nITEM: BOX BOUNDS pp pp pp\n"
                 "0 1\n0 1\n0 1\nITEM: ATOMS id x y z radius\n1 0 0 x 1\n", "bad.dump:10: column 'z'"),
    ("bad.dump", "ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n2\nITEM: BOX BOUNDS pp pp pp\n"
                 "0 1\n0 1\n0 1\nITEM: ATOMS id x y z radius\n1 0 0 0 1\n1 2 0 0 1\n",
     "column 'id': duplicate id 1"),
    ("bad.dump", "ITEM: NUMBER OF ATOMS\n", "bad.dump:1: expected 'ITEM: TIMESTEP'"),
    # rows with more values than the columns (read misaligned or cut before)
    ("bad.csv", "x,y,z,r\n0,0,0,1\n1,0,0,1,7,8\n", "bad.csv:3: expected 4 values, got 6"),
    ("bad.dump", "ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n1\nITEM: BOX BOUNDS pp pp pp\n"
                 "0 1\n0 1\n0 1\nITEM: ATOMS id x y z radius\n1 0 9 0 0 1\n",
     "bad.dump:10: expected 5 values, got 6"),
    ("bad.txt", "0 0 1\n1 1 1 1\n", "bad.txt:2: expected 3 values (as line 1), got 4"),
    ("bad.dump", "ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n1\nITEM: BOX BOUNDS pp pp\n"
                 "0 1\n0 1\n0 1\nITEM: ATOMS id x y z radius\n1 0 0 0 1\n",
     "bad.dump:5: BOX BOUNDS: expected a boundary flag for each of x, y and z, got 'pp pp'"),
]


@pytest.mark.parametrize("name,text,expected", BAD_FILES)
def test_bad_files_give_one_line_naming_file_line_field(tmp_path, name, text, expected):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(InputError) as info:
        read_assembly(path)
    message = str(info.value)
    assert "\n" not in message
    assert expected in message


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_assembly(tmp_path / "nothing.csv")
    binary = tmp_path / "blob.txt"
    binary.write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(InputError, match="not a text file"):
        read_assembly(binary)


def test_snapshot_out_of_range(tmp_path):
    x, r, _ = assembly(3)
    path = write_liggghts_dump(tmp_path / "one.dump", x, r)
    with pytest.raises(InputError, match=r"snapshot: must lie in \[-1, 0\], got 3"):
        read_liggghts_dump(path, snapshot=3)
    with pytest.raises(InputError, match="no snapshot at TIMESTEP 7"):
        read_liggghts_dump(path, timestep=7)


@pytest.mark.parametrize("row,error", [
    ("1e-150,0,0,1", None),              # a tiny coordinate: harmless, read as given
    ("1e300,0,0,1", "column 'x': must be 0 or between 1e-100 and 1e+100"),
    ("0,0,0,1e-200", "column 'r': must be 0 or between 1e-100 and 1e+100"),
    ("0,0,0,1e101", "column 'r': must be 0 or between 1e-100 and 1e+100"),
])
def test_csv_values_beyond_any_units_are_refused_with_their_line(tmp_path, row, error):
    from demstep.io.formats import read_csv

    f = tmp_path / "p.csv"
    f.write_text(f"x,y,z,r\n5,5,5,1\n{row}\n")
    if error is None:
        assert read_csv(f).x[1, 0] == float(row.split(",")[0])
        return
    with pytest.raises(InputError, match=re.escape(f"p.csv:3: {error}")):
        read_csv(f)


def test_liggghts_box_with_hi_below_lo_is_refused_where_it_is_written(tmp_path):
    path = tmp_path / "flat.dump"
    path.write_text("ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n2\nITEM: BOX BOUNDS pp pp pp\n"
                    "0 1\n5 -5\n0 1\nITEM: ATOMS id x y radius\n1 0.1 0.2 0.05\n2 0.4 0.2 0.05\n")
    with pytest.raises(InputError, match=re.escape("flat.dump:7: BOX BOUNDS: yhi must exceed "
                                                   "ylo, got 5 -5")):
        read_liggghts_dump(path)


def test_csv_takes_radius_and_mass_for_r_and_m_and_refuses_a_column_twice(tmp_path):
    from demstep.io.formats import read_csv

    f = tmp_path / "p.csv"
    f.write_text("id,x,y,z,radius,mass\n7,0,0,0,1.5,2.5\n8,3,0,0,0.5,0.25\n")
    data = read_csv(f)
    assert data.r.tolist() == [1.5, 0.5] and data.m.tolist() == [2.5, 0.25]
    f.write_text("x,y,z,r,radius\n0,0,0,1,2\n")
    with pytest.raises(InputError, match=re.escape("p.csv:1: column 'r' given twice")):
        read_csv(f)


@pytest.mark.parametrize("column,value,error", [
    ("type", "1.5", "column 'type': expected an integer >= 1, got 1.5"),
    ("type", "0", "column 'type': expected an integer >= 1, got 0"),
    ("id", "2.5", "column 'id': expected an integer, got 2.5"),
])
def test_liggghts_integer_columns_are_integers(tmp_path, column, value, error):
    path = tmp_path / "d.dump"
    row = {"id": "2", "type": "1"}
    row[column] = value
    path.write_text("ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n2\nITEM: BOX BOUNDS pp pp pp\n"
                    "0 1\n0 1\n0 1\nITEM: ATOMS id type x y radius\n1 1 0.1 0.2 0.05\n"
                    f"{row['id']} {row['type']} 0.4 0.2 0.05\n")
    with pytest.raises(InputError, match=re.escape(f"d.dump:11: {error}")):
        read_liggghts_dump(path)


def test_a_spreadsheet_s_trailing_empty_cells_are_no_extra_values(tmp_path):
    """A CSV row ending in empty cells (a spreadsheet's export) reads like one without
    them; a row with extra values that are not empty is refused (above)."""
    path = tmp_path / "p.csv"
    path.write_text("x,y,r\n0,0,1,\n3,0,1,,\n")
    data = read_assembly(path)
    assert np.array_equal(data.x, [[0, 0], [3, 0]]) and np.array_equal(data.r, [1, 1])
