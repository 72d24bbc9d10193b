"""Bad input in case files and in the files they read (clump body files, bond lists,
particle files, materials files) is refused with one line naming the key (or the
file, line and column) and the value; the command line exits 2 without a traceback
and writes nothing."""

import re
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, cli as run_cli

from demstep.case import build_simulation, case_from_text, dump_case, load_case
from demstep.errors import InputError
from demstep.io.formats import read_bond_csv, read_csv, read_liggghts_dump, read_yade_text
from demstep.analysis_input import read_materials

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"

#: a small valid 2D case (9 disks in a box)
BASE = """
[particles]
generator = "lattice"
lattice = "hex"
radius = 1.0
size = [3, 3]
density = 1000.0

[contact]
law = "linear"
k_n = 1.0e6

[box]
margin = 0.0

[[stages]]
steps = 5
"""

#: a 2D case of two-disk clumps listed in a body file ``b.csv``
CLUMPS = """
[particles]
generator = "clumps"
file = "b.csv"
density = 1000.0

[[clumps]]
name = "pair"
members = [[0.0, 0.0, 1.0], [0.0, 1.0, 1.0]]

[contact]
law = "linear"
k_n = 1.0e6

[box]
margin = 0.0

[[stages]]
steps = 5
"""

#: a 2D case with a periodic x axis (for [stages.periodic.x])
PERIODIC = BASE.replace("size = [3, 3]", "size = [10, 3]").replace(
    "[box]\nmargin = 0.0", "[periodic]\nx = 20.0")

#: a 2D case with the lone wall "w" below the disks (for wall motions)
WALL = BASE.replace("[box]\nmargin = 0.0", """[[walls]]
name = "w"
point = [0.0, -1.0]
normal = [0.0, 1.0]""")

#: a LIGGGHTS dump of two atoms; {cols} the ATOMS columns, {a} and {b} the rows
DUMP = ("ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n2\nITEM: BOX BOUNDS ff ff ff\n"
        "0 10\n0 10\n0 10\nITEM: ATOMS {cols}\n{a}\n{b}\n")




def cli(argv, capsys):
    """Exit status and stderr of the command line run in this process."""
    code, _, err = run_cli(argv, capsys)
    return code, err


def run_case(tmp_path, capsys, text, files=None):
    """``demstep run`` of the case ``text`` (with ``files``, name -> content, beside
    it) into tmp_path/out: (exit status, stderr)."""
    for name, content in (files or {}).items():
        (tmp_path / name).write_text(content)
    case = tmp_path / "case.toml"
    case.write_text(text)
    return cli(["run", case, "--out", tmp_path / "out", "--max-steps", "0", "--quiet"], capsys)


def refused(text, tmp_path=None, files=None) -> str:
    """The one-line InputError of loading the case ``text`` (files beside it)."""
    base = tmp_path if tmp_path is not None else Path.cwd()
    for name, content in (files or {}).items():
        (base / name).write_text(content)
    with pytest.raises(InputError) as info:
        case_from_text(text, base_dir=base, source="case.toml")
    message = str(info.value)
    assert "\n" not in message and message.startswith("case.toml: "), message
    return message


# ------------------------------------------------------------------- 1. 2D clumps
def test_2d_body_file_refuses_a_turn_out_of_the_plane(tmp_path, capsys):
    """A 2D body file row turned about x (qx = 0.7071) put the members of a clump on top
    of each other; it is refused naming the file, the line, qx and its value, and the
    run writes nothing."""
    code, err = run_case(tmp_path, capsys, CLUMPS, {
        "b.csv": "x,y,template,qw,qx,qy,qz\n0,0,pair,1,0,0,0\n5,0,pair,0.7071,0.7071,0,0\n"})
    assert_one_line_error(code, err, "b.csv:3:", "'qx'", "qx = 0.7071", "about z")
    assert not (tmp_path / "out").exists()


def test_2d_body_file_takes_turns_about_z(tmp_path):
    """Turns about z (qx = qy = 0, also within rounding of a unit quaternion) load, and
    the clumps are placed as turned: the first body (qw = qz = 0.7071, a quarter turn)
    has its template's members (0, 0) and (0, 1) at its position plus those offsets
    turned by 90 degrees about z, the second (qx = 1e-17, qy = -1e-17 beside qw = 1)
    its members at its position plus the offsets unturned."""
    (tmp_path / "b.csv").write_text("x,y,template,qw,qx,qy,qz\n0,0,pair,0.7071,0,0,0.7071\n"
                                    "5,0,pair,1,1e-17,-1e-17,0\n")
    sim = build_simulation(case_from_text(CLUMPS, base_dir=tmp_path, source="case.toml"))
    offsets = np.array([[0.0, 0.0], [0.0, 1.0]])  # the template "pair"'s members
    for body, (position, angle) in enumerate((([0.0, 0.0], 2 * np.arctan2(0.7071, 0.7071)),
                                              ([5.0, 0.0], 0.0))):
        c, s = np.cos(angle), np.sin(angle)
        expected = np.asarray(position) + offsets @ np.array([[c, s], [-s, c]])
        members = sim.x[sim.bodies.sphere_body == body]
        assert len(members) == 2 and not members[:, 2:].any()  # (2D: z stays 0)
        np.testing.assert_allclose(members[np.lexsort(members[:, :2].T[::-1])][:, :2],
                                   expected[np.lexsort(expected.T[::-1])], rtol=0, atol=1e-12)


# ---------------------------------------------------------- 4. huge integer columns
@pytest.mark.parametrize("cols,a,b,expected", [
    ("id type x y z radius", "1e30 1 1 1 1 0.5", "2 1 3 1 1 0.5", "d.dump:10: column 'id'"),
    ("id type x y z radius mol", "1 1 1 1 1 0.5 1e30", "2 1 3 1 1 0.5 0",
     "d.dump:10: column 'mol'"),
    ("id type x y z radius", "9007199254740993 1 1 1 1 0.5", "9007199254740992 1 3 1 1 0.5",
     "d.dump:10: column 'id'"),
], ids=["id-1e30", "mol-1e30", "ids-above-2^53"])
def test_dump_integer_columns_beyond_2_53_are_refused(tmp_path, cols, a, b, expected):
    """An id or mol of 1e30 became INT64_MIN (after a RuntimeWarning); ids 2^53 + 1 and
    2^53 read as the same float and were called duplicates. Each is refused naming the
    line, the column and the value as written, without a warning."""
    path = tmp_path / "d.dump"
    path.write_text(DUMP.format(cols=cols, a=a, b=b))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError) as info:
            read_liggghts_dump(path)
    message = str(info.value)
    value = a.split()[cols.split().index(expected.split("'")[1])]
    assert expected in message and f"got {value}" in message and "2^53" in message
    assert "duplicate" not in message


def test_dump_ids_just_below_2_53_are_distinct(tmp_path):
    """Ids up to 2^53 - 1 are read exactly (and are not duplicates)."""
    path = tmp_path / "d.dump"
    path.write_text(DUMP.format(cols="id type x y z radius", a="9007199254740991 1 1 1 1 0.5",
                                b="9007199254740990 1 3 1 1 0.5"))
    data = read_liggghts_dump(path)
    assert data.ids.tolist() == [9007199254740990, 9007199254740991]


def test_csv_body_of_1e30_is_refused(tmp_path, capsys):
    """A particle CSV's body column of 1e30 (it became INT64_MIN) is refused naming the
    line, the column and the value; the run writes nothing."""
    text = BASE.replace('generator = "lattice"\nlattice = "hex"\nradius = 1.0\nsize = [3, 3]',
                        'generator = "file"\npath = "p.csv"')
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code, err = run_case(tmp_path, capsys, text,
                             {"p.csv": "x,y,r,body\n0,0,1,1e30\n5,0,1,-1\n"})
    assert_one_line_error(code, err, "p.csv:2:", "column 'body'", "got 1e30")
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------ 7. keys the mode does not read
REFUSED_UNUSED = [
    (BASE.replace("margin = 0.0", 'margin = 0.0\n[box.walls."y+"]\nmotion = "servo"\n'
                  'target_stress = 1.0\nvelocity = [0.0, -1.0]'),
     "box.walls.\"y+\".velocity: only used with motion = 'velocity' (the motion is 'servo'), "
     "got [0.0, -1.0]"),
    (BASE.replace("margin = 0.0", 'margin = 0.0\n[box.walls."y+"]\nmotion = "fixed"\n'
                  'velocity = [0.0, -1.0]'),
     "box.walls.\"y+\".velocity: only used with motion = 'velocity' (the motion is 'fixed'), "
     "got [0.0, -1.0]"),
    (BASE.replace("margin = 0.0", 'margin = 0.0\n[box.walls."y+"]\nmotion = "velocity"\n'
                  'velocity = [0.0, -1.0]\nservo_gain = 2.0'),
     "box.walls.\"y+\".servo_gain: only used with motion = 'servo' (the motion is 'velocity'), "
     "got 2.0"),
    (WALL + '[stages.walls.w]\nmotion = "velocity"\nvelocity = [0.0, 1.0]\narea = 4.0\n',
     "stages[0].walls.\"w\".area: only used with motion = 'servo' (the motion is 'velocity'), "
     "got 4.0"),
    (PERIODIC + '[stages.periodic.x]\nmotion = "fixed"\nrate = 1.0\n',
     "stages[0].periodic.x.rate: only used with motion = 'rate' (the motion is 'fixed'), got 1.0"),
    (PERIODIC + '[stages.periodic.x]\nmotion = "rate"\nrate = 1.0\ntarget_stress = 5.0\n',
     "stages[0].periodic.x.target_stress: only used with motion = 'servo' (the motion is "
     "'rate'), got 5.0"),
    (PERIODIC + '[stages.periodic.x]\nmotion = "rate"\nrate = 1.0\nservo_factor = 0.2\n',
     "stages[0].periodic.x.servo_factor: only used with motion = 'servo'"),
    (BASE + "\n[timestep]\noverlap = 0.5\n",
     "timestep.overlap: only used with a law whose stiffness depends on the overlap (the "
     "linear law's does not), got 0.5"),
    (BASE.replace("steps = 5", "steps = 5\n[stages.timestep]\nalpha = 0.1\noverlap = 0.02"),
     "stages[0].timestep.overlap: only used with a law whose stiffness depends"),
    (BASE.replace("k_n = 1.0e6", "k_n = 1.0e6\nrestitution = 0.5\ndamping_normal = 3.0"),
     "contact.damping_normal: give the normal dashpot by restitution or by damping_normal, "
     "not both (they would add up; restitution is 0.5), got 3.0"),
    (BASE.replace("k_n = 1.0e6", "k_n = 1.0e6\nrestitution_tangential = 0.5\n"
                  "damping_tangential = 2.0"),
     "contact.damping_tangential: give the tangential dashpot by restitution_tangential or by "
     "damping_tangential, not both"),
]


@pytest.mark.parametrize("text,expected", REFUSED_UNUSED,
                         ids=[e.split(":")[0] for _, e in REFUSED_UNUSED])
def test_keys_the_chosen_mode_does_not_read_are_refused(text, expected):
    """A wall velocity with motion servo or fixed, servo keys on a velocity wall, a
    periodic rate with motion fixed or servo keys with motion rate, timestep.overlap
    with the linear law, and a dashpot given both by restitution and by coefficient
    (summed) were accepted and ignored (or added up); each is refused naming the key
    and the value."""
    assert expected in refused(text)


def test_a_stage_velocity_on_a_servo_wall_is_refused():
    """A stage that sets the velocity of a wall an earlier stage made servo-controlled
    (without changing its motion) is refused: the servo wall ignores it."""
    text = WALL + ('[stages.walls.w]\nmotion = "servo"\ntarget_stress = 1.0\narea = 4.0\n'
                   '[[stages]]\nsteps = 5\n[stages.walls.w]\nvelocity = [0.0, 1.0]\n')
    assert ("stages[1].walls.\"w\".velocity: only used with motion = 'velocity' (the motion is "
            "'servo'), got [0.0, 1.0]") in refused(text)


@pytest.mark.parametrize("change,body,expected", [
    (("density = 1000.0", 'density = 1000.0\ntemplates = ["pair"]'),
     "x,y,template\n0,0,pair\n5,0,pair\n",
     "particles.templates: not used with a file (its column 'template' names the template of "
     "each body), got ['pair']"),
    (("density = 1000.0", 'density = 1000.0\norientation = "fixed"'),
     "x,y,template,qw,qx,qy,qz\n0,0,pair,1,0,0,0\n5,0,pair,1,0,0,0\n",
     "particles.orientation: not used with a file that has the orientation columns qw, qx, qy, "
     "qz, got 'fixed'"),
    (("density = 1000.0", "density = 1000.0\nseed = 3"),
     "x,y,template,qw,qx,qy,qz\n0,0,pair,1,0,0,0\n5,0,pair,1,0,0,0\n",
     "particles.seed: not used with a file that has the orientation columns qw, qx, qy, qz, "
     "got 3"),
    (("density = 1000.0", 'density = 1000.0\norientation = "fixed"\nseed = 3'),
     "x,y,template\n0,0,pair\n5,0,pair\n",
     "particles.seed: only used with orientation = 'random', got 3"),
], ids=["templates", "orientation", "seed", "seed-fixed"])
def test_clump_file_keys_it_does_not_read_are_refused(tmp_path, change, body, expected):
    """templates, orientation and seed beside a body file that names each body's
    template and orientation were ignored; they are refused naming the key and value
    (seed and orientation stay allowed with a file without orientation columns)."""
    assert expected in refused(CLUMPS.replace(*change), tmp_path, {"b.csv": body})
    (tmp_path / "b.csv").write_text("x,y,template\n0,0,pair\n5,0,pair\n")
    case_from_text(CLUMPS.replace("density = 1000.0", "density = 1000.0\nseed = 3"),
                   base_dir=tmp_path)


def test_snapshot_on_a_csv_is_refused(tmp_path):
    """particles.snapshot picks a snapshot of a LIGGGHTS dump; on a CSV it was ignored,
    now refused naming the key, the format and the value."""
    text = BASE.replace('generator = "lattice"\nlattice = "hex"\nradius = 1.0\nsize = [3, 3]',
                        'generator = "file"\npath = "p.csv"\nsnapshot = 3')
    message = refused(text, tmp_path, {"p.csv": "x,y,r\n0,0,1\n3,0,1\n"})
    assert "particles.snapshot: only used with a LIGGGHTS dump (the file is csv), got 3" in message


def test_keys_a_mode_reads_still_load_and_the_resolved_case_reloads(tmp_path):
    """The keys the chosen mode reads load (overlap with Hertz, a dump's snapshot, the
    servo keys of a servo axis); the resolved case of each example leaves out the
    defaults its choices do not read, so it loads again to the same case."""
    hertz = BASE.replace('law = "linear"\nk_n = 1.0e6',
                         'law = "hertz"\nyoungs_modulus = 1e9\npoisson_ratio = 0.3')
    case_from_text(hertz + "\n[timestep]\noverlap = 0.02\n")
    (tmp_path / "p.dump").write_text(DUMP.format(cols="id type x y z radius",
                                                 a="1 1 1 1 1 0.5", b="2 1 3 1 1 0.5"))
    case_from_text(BASE.replace('generator = "lattice"\nlattice = "hex"\nradius = 1.0\n'
                                'size = [3, 3]', 'generator = "file"\npath = "p.dump"\n'
                                'snapshot = 0').replace("[box]\nmargin = 0.0", ""),
                   base_dir=tmp_path)
    case_from_text(PERIODIC + '[stages.periodic.x]\nmotion = "servo"\ntarget_stress = 1.0\n'
                   'servo_gain = 0.5\nservo_factor = 0.2\nmax_speed = 1.0\n')
    for example in sorted(EXAMPLES.glob("*.toml")):
        case = load_case(example)
        text = dump_case(case)
        data = tomllib.loads(text)
        assert "overlap" not in data["timestep"] or case.contact.law == "hertz"
        path = tmp_path / f"{example.stem}.toml"
        path.write_text(text)
        again = load_case(path)
        assert again.resolved() == case.resolved() and dump_case(again) == text


def test_restitution_with_damping_normal_refused_by_the_command_line(tmp_path, capsys):
    """`demstep run` of a case with restitution and damping_normal (summed): one line,
    exit 2, no output folder."""
    code, err = run_case(tmp_path, capsys, BASE.replace(
        "k_n = 1.0e6", "k_n = 1.0e6\nrestitution = 0.5\ndamping_normal = 3.0"))
    assert_one_line_error(code, err, "contact.damping_normal", "not both", "got 3.0")
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------- 8. fixed box order
def test_fixed_box_lower_above_upper_is_refused():
    """[particles.fixed] lower = [10, 10], upper = [0, 0] fixed nothing; it is refused
    naming the key and both corners (lower == upper stays allowed)."""
    text = BASE.replace("[contact]", "[particles.fixed]\nlower = [10.0, 10.0]\n"
                        "upper = [0.0, 0.0]\n\n[contact]")
    assert ("particles.fixed.upper: must be >= lower [10.0, 10.0] on every axis, got [0.0, 0.0]"
            in refused(text))
    case_from_text(text.replace("lower = [10.0, 10.0]", "lower = [-5.0, 0.0]")
                   .replace("upper = [0.0, 0.0]", "upper = [5.0, 0.0]"))


# ------------------------------------------------------------------ 9. magnitudes
@pytest.mark.parametrize("old,new,key,value", [
    ("k_n = 1.0e6", "k_n = 1.0e6\n[bonds]\nnormal_stiffness = 1e6\ntensile_strength = 1e300",
     "bonds.tensile_strength", "1e+300"),
    ("k_n = 1.0e6", "k_n = 1.0e6\n[bonds]\nnormal_stiffness = 1e6\nshear_strength = 1e-300",
     "bonds.shear_strength", "1e-300"),
    ('law = "linear"\nk_n = 1.0e6', 'law = "hertz"\nyoungs_modulus = 1e9\npoisson_ratio = 1e-200',
     "contact.poisson_ratio", "1e-200"),
    ("k_n = 1.0e6", "k_n = 1.0e6\nrestitution = 1e-300", "contact.restitution", "1e-300"),
    ('generator = "lattice"\nlattice = "hex"\nradius = 1.0\nsize = [3, 3]',
     'generator = "grid"\ncount = [3, 3]\nspacing = 3.0\nradius_min = 0.5\nradius_max = 1.0\n'
     'jitter = 1e-300', "particles.jitter", "1e-300"),
], ids=["tensile_strength", "shear_strength", "poisson_ratio", "restitution", "jitter"])
def test_documented_magnitudes_hold_for_every_number(old, new, key, value):
    """Numbers beyond 1e-100..1e100 in magnitude (1e300, 1e-200, 1e-300) were accepted
    for bond strengths, Poisson's ratio, restitution and jitter; refused naming the key
    and the value."""
    message = refused(BASE.replace(old, new))
    assert f"{key}: must be 0 or between 1e-100 and 1e+100 in magnitude" in message
    assert message.endswith(f"got {value}")


@pytest.mark.parametrize("member,key,value", [
    ("[1e300, 0.0, 1.0]", "clumps[0].members[1][0]", "1e+300"),
    ("[0.0, 1.0, 1e-300]", "clumps[0].members[1][2]", "1e-300"),
], ids=["coordinate", "radius"])
def test_clump_member_values_are_range_checked(tmp_path, member, key, value):
    """A member coordinate of 1e300 (an overflow warning, then a misleading 'not one
    rigid body') and a member radius of 1e-300 ('inertia: must be finite and > 0 at row
    1') are refused naming the member's entry and the value."""
    text = CLUMPS.replace("[0.0, 1.0, 1.0]]", member + "]")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        message = refused(text, tmp_path, {"b.csv": "x,y,template\n0,0,pair\n5,0,pair\n"})
    assert f"{key}: must be 0 or between" in message and message.endswith(f"got {value}")
    assert "inertia" not in message


# ------------------------------------------------------------- 10. extra columns
def test_bond_file_row_with_extra_values_is_refused(tmp_path, capsys):
    """A bond file with header i,j and a row 0,1,5,6 was read as the pair (0, 1); it
    is refused naming the line and the count (a spreadsheet's trailing empty cells
    stay allowed); the run writes nothing."""
    text = BASE + "\n[bonds]\nnormal_stiffness = 1e6\nfile = \"bonds.csv\"\n"
    code, err = run_case(tmp_path, capsys, text, {"bonds.csv": "i,j\n0,1,5,6\n"})
    assert_one_line_error(code, err, "bonds.csv:2: expected 2 values, got 4")
    assert not (tmp_path / "out").exists()
    (tmp_path / "ok.csv").write_text("i,j\n0,1,,\n")
    assert read_bond_csv(tmp_path / "ok.csv").tolist() == [[0, 1]]


@pytest.mark.parametrize("content,expected", [
    ("i,j,i\n0,1,2\n", "b.csv:1: column 'i' given twice"),
    ("i,j\n0,1_0\n", "b.csv:2: column 'j': not an integer (an underscore): '1_0'"),
], ids=["column-twice", "underscore"])
def test_bond_file_header_and_numbers(tmp_path, content, expected):
    """A bond column named twice and an index written 1_0 (int() reads it as 10) are
    refused naming the line, the column and the value."""
    (tmp_path / "b.csv").write_text(content)
    with pytest.raises(InputError, match=re.escape(expected)):
        read_bond_csv(tmp_path / "b.csv")


def test_body_file_row_with_extra_values_is_refused(tmp_path):
    """A clump body file row with more values than its header was read from its first
    columns; refused naming the line."""
    message = refused(CLUMPS, tmp_path, {"b.csv": "x,y,template\n0,0,pair,9,9\n5,0,pair\n"})
    assert "b.csv:2: expected 3 values, got 5" in message


def test_dump_with_a_column_twice_is_refused(tmp_path):
    """A LIGGGHTS dump naming x twice used the first; refused as the CSV reader does,
    naming the ATOMS line and the column."""
    path = tmp_path / "d.dump"
    path.write_text(DUMP.format(cols="id type x y z radius x", a="1 1 1 1 1 0.5 7",
                                b="2 1 3 1 1 0.5 9"))
    with pytest.raises(InputError, match=re.escape("d.dump:9: ITEM: ATOMS: column 'x' given "
                                                   "twice")):
        read_liggghts_dump(path)


@pytest.mark.parametrize("header,expected", [
    ("#format x_y_z_r_r", "a.txt:1: #format: field 'r' given twice, got 'x_y_z_r_r'"),
    ("#format x_y_z_rr", "a.txt:1: #format: unknown field 'rr'"),
    ("#format x_y_attrs_z_r", "a.txt:1: #format: unknown field 'attrs'"),
], ids=["repeated", "unknown", "attrs-not-last"])
def test_yade_format_fields_known_and_once(tmp_path, header, expected):
    """YADE '#format x_y_z_r_r' was accepted (and unknown fields ignored); repeated and
    unknown fields are refused naming the line and the header. YADE's own formats
    (x_y_z_r, x_y_z_r_matId, x_y_z_r_attrs) still read."""
    path = tmp_path / "a.txt"
    path.write_text(f"{header}\n0 0 0 1 2\n3 0 0 1 2\n")
    with pytest.raises(InputError, match=re.escape(expected)):
        read_yade_text(path)
    for fmt, rows in (("x_y_z_r", "0 0 0 1\n3 0 0 1\n"),
                      ("x_y_z_r_matId", "0 0 0 1 7\n3 0 0 1 7\n"),
                      ("x_y_z_r_attrs", "0 0 0 1 5 6\n3 0 0 1 5 6\n")):
        path.write_text(f"#format {fmt}\n{rows}")
        assert read_yade_text(path).r.tolist() == [1.0, 1.0]


@pytest.mark.parametrize("name,content,expected", [
    ("p.csv", "x,y,r\n1_0,0,1\n", "p.csv:2: column 'x': not a number (an underscore): '1_0'"),
    ("p.txt", "0 0 0 1\n3 0 0 1_0\n", "p.txt:2: column 'r': not a number (an underscore): '1_0'"),
    ("p.dump", DUMP.format(cols="id type x y z radius", a="1 1 1_0 1 1 0.5", b="2 1 3 1 1 0.5"),
     "p.dump:10: column 'x': not a number (an underscore): '1_0'"),
], ids=["csv", "yade", "liggghts"])
def test_underscores_in_file_numbers_are_refused(tmp_path, name, content, expected):
    """Python's float() reads '1_0' as 10; no code writes such a number: refused naming
    the line, the column and the text."""
    from demstep.io.formats import read_particle_file

    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(InputError, match=re.escape(expected)):
        read_particle_file(path)


# ------------------------------------------------------------ 11. materials files
@pytest.mark.parametrize("text,expected", [
    ("[[material]]\ntype = 1\nyoungs = true\npoisson = 0.3\n",
     "material 1: youngs must be a number, got True"),
    ('[[material]]\ntype = 1\nyoungs = "7e10"\npoisson = 0.3\n',
     "material 1: youngs must be a number, got '7e10'"),
    ("[[material]]\ntype = 1\nyoungs = 7e10\npoisson = 0.3\ndensity = false\n",
     "material 1: density must be a number, got False"),
    ("densty = 3\n[[material]]\ntype = 1\nyoungs = 7e10\npoisson = 0.3\n",
     "unknown key 'densty'"),
    ("[[material]]\ntype = 1\nyoungs = 7e10\npoisson = 1e-200\n",
     "material 1: poisson must be 0 or between 1e-100 and 1e+100 in magnitude"),
], ids=["bool", "string", "density-bool", "top-level-typo", "magnitude"])
def test_materials_file_numbers_and_keys(tmp_path, text, expected):
    """`dt --materials`: youngs = true was read as E = 1, youngs = "7e10" accepted and a
    misspelled top-level key ignored; each is refused naming the key and the value."""
    path = tmp_path / "m.toml"
    path.write_text(text)
    with pytest.raises(InputError, match=re.escape(expected)):
        read_materials(path)
    path.write_text("[[material]]\ntype = 1\nyoungs = 70000000000\npoisson = 0.25\n"
                    "density = 2500\n")
    mat = read_materials(path)[1]
    assert (mat.youngs, mat.poisson, mat.density) == (7e10, 0.25, 2500.0)


def test_materials_file_bool_refused_by_the_command_line(tmp_path, capsys):
    """`demstep dt FILE --materials M` with youngs = true: one line, exit 2."""
    (tmp_path / "p.csv").write_text("x,y,r\n0,0,1\n2,0,1\n")
    (tmp_path / "m.toml").write_text("[[material]]\ntype = 1\nyoungs = true\npoisson = 0.3\n")
    code, err = cli(["dt", tmp_path / "p.csv", "--density", "1000", "--materials",
                     tmp_path / "m.toml"], capsys)
    assert_one_line_error(code, err, "youngs must be a number, got True")


# -------------------------------------------------------- 17. numbers of body files
@pytest.mark.parametrize("value", ["nan", "1e400", "1e300"])
def test_body_file_numbers_are_finite_and_in_range(tmp_path, capsys, value):
    """NaN or 1e400 in a clump body file gave a wall error ('normal must be finite') and
    1e300 one about a wall cutting into a particle; each is refused naming the file,
    line, column and value; the run writes nothing."""
    code, err = run_case(tmp_path, capsys, CLUMPS,
                         {"b.csv": f"x,y,template\n{value},0,pair\n5,0,pair\n"})
    assert_one_line_error(code, err, "b.csv:2: column 'x'", repr(value))
    assert "wall" not in err
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------- 18. messages naming keys
def test_servo_wall_area_must_be_positive():
    """A servo wall with area = 0 is refused by the schema naming the key and value."""
    text = WALL + ('[stages.walls.w]\nmotion = "servo"\ntarget_stress = 1.0\narea = 0.0\n')
    assert "stages[0].walls.w.area: input should be greater than 0, got 0.0" in refused(text)


@pytest.mark.parametrize("text,expected", [
    (BASE + '\n[bonds]\nnormal_stiffness = 1e6\nfile = "nob.csv"\n',
     "bonds.file: no such file, got 'nob.csv'"),
    (CLUMPS.replace("members = [[0.0, 0.0, 1.0], [0.0, 1.0, 1.0]]", 'file = "nom.csv"'),
     "clumps[0].file: no such file, got 'nom.csv'"),
    (CLUMPS.replace('file = "b.csv"', 'file = "nob.csv"'),
     "particles.file: no such file, got 'nob.csv'"),
], ids=["bonds.file", "clumps.file", "particles.file"])
def test_missing_files_name_their_key(tmp_path, text, expected):
    """A missing bond list or clump template file was named by its path alone; the
    message now names the key and the value given."""
    assert expected in refused(text, tmp_path, {"b.csv": "x,y,template\n0,0,pair\n5,0,pair\n"})


def test_yade_rows_shorter_than_the_format_name_the_format(tmp_path):
    """'#format x_y_z_r' with rows of 3 values said 'expected 4 values (as line 2)' on
    line 2 itself; the message names the format and the line."""
    path = tmp_path / "a.txt"
    path.write_text("#format x_y_z_r\n0 0 0\n3 0 0\n")
    with pytest.raises(InputError, match=re.escape("a.txt:2: expected 4 values (#format "
                                                   "x_y_z_r), got 3")):
        read_yade_text(path)


def test_particle_csv_integer_column_names_its_text(tmp_path):
    """The CSV type column's message names the value as written (not a rounded float)."""
    (tmp_path / "p.csv").write_text("x,y,r,type\n0,0,1,1\n5,0,1,9007199254740993\n")
    with pytest.raises(InputError, match=re.escape("p.csv:3: column 'type': expected an "
                                                   "integer >= 1 below 2^53")) as info:
        read_csv(tmp_path / "p.csv")
    assert str(info.value).endswith("got 9007199254740993")
