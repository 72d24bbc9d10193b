"""Reliability of the files a run or an analysis reads (issue 41): a damaged history
does not block a restart, CSV fields over the csv module's limit, files checked before
they are read and then streamed, negative coordinates as option values, control
characters in names, devices given as files and a full disk.

Bad input gives one line naming the file (and line) or key and the value, a non-zero
exit status and writes nothing."""

import errno
import os
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, cli

from demstep.case import build_simulation, case_from_text, load_case
from demstep.errors import InputError
from demstep.io.atomic import write_text_atomic
from demstep.io.checkpoint import load_checkpoint
from demstep.io.formats import read_bond_csv, read_csv, read_liggghts_dump, read_yade_text
from demstep.io.history import read_history
from demstep.runner import run_case

#: a small 2D run: 300 steps, a history row every 25 steps, a checkpoint every 100
RUN = """
name = "small"
[particles]
generator = "lattice"
lattice = "hex"
radius = 1.0
size = [4, 3]
density = 1.0
[contact]
law = "linear"
k_n = 1.0e4
mu = 0.3
[box]
margin = 0.0
[timestep]
alpha = 0.1
[[stages]]
name = "squeeze"
steps = 300
damping = { local = 0.1 }
[stages.walls."y+"]
motion = "velocity"
velocity = [0.0, -0.01]
[output]
history_every = 25
checkpoint_every = 100
"""

#: a 2D case whose particles come from the file {path}
FILE_CASE = """
[particles]
generator = "file"
path = "{path}"
density = 1000.0
[contact]
law = "linear"
k_n = 1.0e6
[box]
margin = 0.0
[[stages]]
steps = 5
"""

#: four disks in a row along x, the first touching a wall at x = -5 (normal +x)
ROW = "x,y,r\n" + "".join(f"{-5.0 + 1.0 - 1e-3 + k * (2.0 - 1e-3)!r},0,1\n" for k in range(4))


def lines_of(text: str) -> list[str]:
    return text.splitlines(keepends=True)


# ============================================== 3. a damaged history.csv on restart
@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """The case file and the history of the run done without a stop."""
    folder = tmp_path_factory.mktemp("straight")
    case = folder / "small.toml"
    case.write_text(RUN)
    result = run_case(load_case(case), folder / "out", quiet=True)
    assert result.status == "completed"
    return case, (folder / "out" / "history.csv").read_text(encoding="utf-8")


def _append(data: bytes):
    return lambda text: text + data


def _garble_row(step: int):
    """Damage the row of ``step`` (its commas become semicolons)."""
    def damage(text: bytes) -> bytes:
        rows = text.split(b"\n")
        k = next(i for i, row in enumerate(rows) if row.startswith(b"%d," % step))
        rows[k] = rows[k].replace(b",", b";")
        return b"\n".join(rows)
    return damage


# (damage, damaged lines, the step whose row is lost)
DAMAGE = {
    "nul bytes appended": (_append(b"\0" * 200_000), 1, None),
    "nul bytes then a newline": (_append(b"\0" * 4096 + b"\n"), 1, None),
    "garbled rows appended": (_append(b"2#5,0.1,,x\n225,0.00"), 2, None),
    "invalid utf-8 appended": (_append(b"\xff\xfe\xfa 3\n"), 1, None),
    "a row before the checkpoint garbled": (_garble_row(50), 1, 50),
}


@pytest.mark.parametrize("kind", list(DAMAGE))
def test_restart_goes_on_from_a_damaged_history(tmp_path, straight, kind):
    """A power loss appends NUL bytes, a row is garbled or bytes are not UTF-8: the
    restart from the (good) checkpoint at step 100 keeps the history's good rows up to
    step 100, drops the damaged ones and those after it, says so in one warning
    naming the file, and ends with the history of the run done without a stop (less
    a row that was lost)."""
    case, expected = straight
    damage, n_damaged, lost = DAMAGE[kind]
    out = tmp_path / "out"
    stopped = run_case(load_case(case), out, quiet=True, max_steps=200)
    assert stopped.step == 200
    history = out / "history.csv"
    history.write_bytes(damage(history.read_bytes()))
    checkpoint = out / "checkpoints" / "step0000000100.npz"
    assert checkpoint.is_file()
    log_before = (out / "run.log").read_text(encoding="utf-8")

    result = run_case(load_case(case), out, quiet=True, restart=checkpoint)

    assert result.status == "completed"
    rows = lines_of(expected)
    if lost is not None:
        rows = [row for row in rows if not row.startswith(f"{lost},")]
        assert len(rows) == len(lines_of(expected)) - 1
    assert history.read_text(encoding="utf-8") == "".join(rows)
    steps = read_history(history)["step"]
    assert (np.diff(steps) > 0).all()
    log = (out / "run.log").read_text(encoding="utf-8")[len(log_before):]
    warnings = [line for line in log.splitlines() if " WARNING " in line]
    assert len(warnings) == 1, log
    assert str(history) in warnings[0] and f"{n_damaged} damaged line" in warnings[0]
    assert "step 100" in warnings[0]


def test_restart_from_the_command_line_with_a_damaged_history(tmp_path, straight, capsys):
    case, expected = straight
    out = tmp_path / "out"
    run_case(load_case(case), out, quiet=True, max_steps=200)
    history = out / "history.csv"
    with open(history, "ab") as fh:
        fh.write(b"\0" * 10_000)
    code, _, err = cli(["run", case, "--out", out, "--quiet", "--restart",
                        out / "checkpoints" / "step0000000100.npz"], capsys)
    assert code == 0, err
    assert history.read_text(encoding="utf-8") == expected
    warned = [line for line in err.splitlines() if "WARNING" in line]
    assert len(warned) == 1 and "history.csv" in warned[0] and "damaged" in warned[0]


def test_restart_still_refuses_a_history_of_other_columns(tmp_path, straight):
    """The history's header names other columns (another run's file): refused, as
    before, and left as it was."""
    case, _ = straight
    out = tmp_path / "out"
    run_case(load_case(case), out, quiet=True, max_steps=100)
    history = out / "history.csv"
    text = history.read_text(encoding="utf-8").replace("n_contacts", "contacts", 1)
    history.write_text(text, encoding="utf-8")
    with pytest.raises(InputError, match="history.csv: the history's columns do not match"):
        run_case(load_case(case), out, quiet=True,
                 restart=out / "checkpoints" / "step0000000100.npz")
    assert history.read_text(encoding="utf-8") == text


# ========================================== 5. a CSV field over the csv module's limit
#: a field longer than the csv module's limit (131072 characters), and one longer
#: than the longest line the readers take
FIELD_SIZES = [200_000, 3_000_000]


@pytest.mark.parametrize("size", FIELD_SIZES)
def test_csv_field_over_the_limit_from_dt_and_run(tmp_path, capsys, size):
    particles = tmp_path / "p.csv"
    particles.write_text(f"x,y,r\n0,0,1\n{'1' * size},0,1\n")
    code, out, err = cli(["dt", particles], capsys)
    assert_one_line_error(code, err, f"{particles}:3:")
    assert out == ""
    case = tmp_path / "case.toml"
    case.write_text(FILE_CASE.format(path="p.csv"))
    code, _, err = cli(["run", case, "--out", tmp_path / "out", "--quiet"], capsys)
    assert_one_line_error(code, err, "p.csv:3:")
    assert not (tmp_path / "out").exists()


def _read_body_file(path):
    case = (FILE_CASE.replace('generator = "file"\npath = "{path}"',
                              f'generator = "clumps"\nfile = "{path.name}"')
            + '[[clumps]]\nname = "pair"\nmembers = [[0.0, 0.0, 1.0], [0.0, 1.0, 1.0]]\n')
    return case_from_text(case, base_dir=path.parent, source="case.toml")


READERS = {
    "particles": (read_csv, "x,y,r\n0,0,1\n{big},0,1\n"),
    "bonds": (read_bond_csv, "i,j\n0,1\n{big},2\n"),
    "bodies": (_read_body_file, "x,y,template\n0,0,pair\n{big},0,pair\n"),
    "history": (read_history, "step,time\n0,0.0\n{big},1.0\n"),
}


@pytest.mark.parametrize("reader", list(READERS))
@pytest.mark.parametrize("size", FIELD_SIZES)
def test_every_csv_reader_names_the_file_and_line_of_a_huge_field(tmp_path, reader, size):
    read, text = READERS[reader]
    path = tmp_path / "f.csv"
    path.write_text(text.format(big="7" * size))
    with pytest.raises(InputError) as info:
        read(path)
    message = str(info.value)
    assert "\n" not in message and f"{path}:3:" in message, message


def test_a_large_binary_file_named_csv_is_one_line(tmp_path, capsys):
    """A blob of one line without NUL bytes or bad UTF-8 in it, named .csv."""
    blob = tmp_path / "blob.csv"
    blob.write_bytes(bytes(b for b in range(1, 128) if b not in b'\n\r,"') * 4000)
    code, _, err = cli(["dt", blob], capsys)
    assert_one_line_error(code, err, str(blob))


# ==================================== 11. files checked first, then read as a stream
#: size of the sparse files (they take no disk space)
SPARSE = 3 << 30
#: at most this many bytes may be read to refuse one (the file is 48 times larger)
READ_BUDGET = 64 << 20


def bytes_read() -> int:
    """Bytes this process has read so far (Linux: rchar of /proc/self/io)."""
    try:
        text = Path("/proc/self/io").read_text()
    except OSError:
        pytest.skip("needs /proc/self/io (Linux)")
    return int(re.search(r"^rchar:\s*(\d+)", text, re.MULTILINE).group(1))


def sparse(path: Path, head: bytes = b"") -> Path:
    """A file of SPARSE bytes: ``head`` then a hole (NUL bytes when read)."""
    path.write_bytes(head)
    os.truncate(path, SPARSE)
    return path


def refused_reading_little(argv, capsys, *words):
    before = bytes_read()
    code, out, err = cli(argv, capsys)
    read = bytes_read() - before
    assert_one_line_error(code, err, *words)
    assert read < READ_BUDGET, f"read {read} bytes to refuse the file"
    return err


@pytest.mark.parametrize("name", ["big.csv", "big.dump", "big.txt", "big"])
def test_a_sparse_file_is_refused_before_it_is_read(tmp_path, capsys, name):
    path = sparse(tmp_path / name)
    err = refused_reading_little(["dt", path], capsys, str(path), "not a text file")
    assert "NUL" in err


@pytest.mark.parametrize("name,head", [
    ("rows.csv", b"x,y,r\n" + b"0,0,1\n" * 20_000),
    ("rows.dump", b"ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n100000\nITEM: BOX BOUNDS ff ff ff\n"
                  b"0 10\n0 10\n0 10\nITEM: ATOMS id x y z radius\n"
                  + b"".join(b"%d 1 1 1 1\n" % k for k in range(1, 10_000))),
    ("rows.txt", b"0 0 0 1\n" * 20_000),
], ids=["csv", "dump", "yade"])
def test_text_followed_by_a_hole_is_refused_while_streaming(tmp_path, capsys, name, head):
    """The first block is text, the rest a hole: the reader stops at the first line of
    NUL bytes."""
    path = sparse(tmp_path / name, head)
    refused_reading_little(["dt", path], capsys, str(path))


def test_sparse_files_given_to_a_run(tmp_path, capsys):
    """A case whose particle file, or the case file itself, is a sparse file."""
    particles = sparse(tmp_path / "p.csv")
    case = tmp_path / "case.toml"
    case.write_text(FILE_CASE.format(path="p.csv"))
    refused_reading_little(["run", case, "--out", tmp_path / "out", "--quiet"], capsys,
                           str(particles), "not a text file")
    big_case = sparse(tmp_path / "big.toml")
    refused_reading_little(["run", big_case, "--out", tmp_path / "out", "--quiet"], capsys,
                           str(big_case))
    assert not (tmp_path / "out").exists()


def test_sparse_materials_and_bond_files(tmp_path, capsys):
    materials = sparse(tmp_path / "m.toml")
    (tmp_path / "p.csv").write_text(ROW)
    refused_reading_little(["dt", tmp_path / "p.csv", "--materials", materials], capsys,
                           str(materials))
    bonds = sparse(tmp_path / "b.csv")
    before = bytes_read()
    with pytest.raises(InputError, match=re.escape(f"{bonds}: not a text file")):
        read_bond_csv(bonds)
    assert bytes_read() - before < READ_BUDGET


@pytest.mark.parametrize("read,head", [
    (read_csv, b"x,y,r\n" + b"0,0,1\n" * 20_000),
    (read_bond_csv, b"i,j\n" + b"0,1\n" * 40_000),
    (read_liggghts_dump, b"ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n100000\nITEM: BOX BOUNDS ff "
                         b"ff ff\n0 10\n0 10\n0 10\nITEM: ATOMS id x y z radius\n"
                         + b"".join(b"%d 1 1 1 1\n" % k for k in range(1, 10_000))),
    (read_yade_text, b"0 0 0 1\n" * 20_000),
], ids=["csv", "bonds", "dump", "yade"])
def test_readers_stop_at_a_hole_after_text(tmp_path, read, head):
    """Past a first block of text, the readers stream: a hole (a power loss, a file
    being written) is refused at its first line, without reading the rest."""
    path = sparse(tmp_path / "f.data", head)
    before = bytes_read()
    with pytest.raises(InputError) as info:
        read(path)
    assert bytes_read() - before < READ_BUDGET
    message = str(info.value)
    assert "\n" not in message and f"{path}:" in message and "NUL" in message, message


def test_dumps_and_yade_files_still_read_after_streaming(tmp_path):
    """The streaming readers give what the files hold (several snapshots, comments,
    CRLF line ends)."""
    dump = tmp_path / "a.dump"
    snapshot = ("ITEM: TIMESTEP\n{t}\nITEM: NUMBER OF ATOMS\n2\nITEM: BOX BOUNDS pp ff ff\n"
                "0 10\n0 10\n0 10\nITEM: ATOMS id x y z radius\n2 {x} 1 1 1\n1 1 1 1 1\n")
    dump.write_text(snapshot.format(t=0, x=3) + "\n" + snapshot.format(t=10, x=4)
                    + snapshot.format(t=20, x=5))
    assert read_liggghts_dump(dump).x[:, 0].tolist() == [1, 5]
    assert read_liggghts_dump(dump, snapshot=0).x[:, 0].tolist() == [1, 3]
    assert read_liggghts_dump(dump, snapshot=-2).x[:, 0].tolist() == [1, 4]
    assert read_liggghts_dump(dump, timestep=10).timestep == 10
    assert read_liggghts_dump(dump).periodic.tolist() == [True, False, False]
    yade = tmp_path / "a.txt"
    yade.write_bytes(b"# a comment\r\n#format x_y_z_r\r\n0 0 0 1\r\n3 0 0 1.5 # two\r\n")
    data = read_yade_text(yade)
    assert data.x.tolist() == [[0, 0, 0], [3, 0, 0]] and data.r.tolist() == [1, 1.5]


# ================================================ 12. negative coordinates as values
def test_wall_with_a_negative_coordinate_as_the_next_argument(tmp_path, capsys):
    """``--wall -5,0:1,0`` (argparse took the value for an option: "expected one
    argument"; only ``--wall=-5,...`` worked): the same analysis as with '='."""
    path = tmp_path / "row.csv"
    path.write_text(ROW)
    base = ["dt", path, "--kn", "100", "--json", "--no-rotation"]
    code, spaced, err = cli(base + ["--wall", "-5,0:1,0"], capsys)
    assert code == 0, err
    code, joined, err = cli(base + ["--wall=-5,0:1,0"], capsys)
    assert code == 0, err
    assert spaced == joined
    assert '"n_contacts": 4' in spaced  # three pairs and the wall
    code, _, err = cli(base + ["--wall", "-5,0:1,0", "--wall", "-.1e2,-1:1,0"], capsys)
    assert code == 0, err
    code, _, err = cli(base + ["--wall", "-5,0:1,0,0"], capsys)
    assert_one_line_error(code, err, "wall:", "-5,0:1,0,0")


def test_help_says_how_to_give_negative_values(capsys):
    code, out, _ = cli(["dt", "--help"], capsys)
    assert code == 0
    wall_help = " ".join(out.split()).split("--wall SPEC")[-1].split("--radius", 1)[0]
    assert "--wall -1,0,0:1,0,0" in wall_help


# ======================================================================= cosmetic
@pytest.mark.parametrize("name", ["squeeze\nnow", "tab\there", "esc\x1b[31m", "line\u2028sep"])
def test_names_with_control_characters_are_refused(name):
    """A stage name with a newline split the log's lines."""
    text = RUN.replace('name = "squeeze"', f"name = {toml_string(name)}")
    with pytest.raises(InputError) as info:
        case_from_text(text, source="case.toml")
    message = str(info.value)
    assert "\n" not in message and "\u2028" not in message
    assert message.startswith("case.toml: stages[0].name: ") and repr(name) in message


def toml_string(text: str) -> str:
    return '"' + "".join(c if c.isprintable() else f"\\u{ord(c):04x}" for c in text) + '"'


def test_a_device_given_as_a_particle_file(tmp_path, capsys):
    """/dev/zero was reported as "no such file"."""
    if not Path("/dev/zero").exists():
        pytest.skip("no /dev/zero")
    code, _, err = cli(["dt", "/dev/zero"], capsys)
    assert_one_line_error(code, err, "/dev/zero", "not a regular file", "character device")
    code, _, err = cli(["dt", "/dev/zero", "--format", "csv"], capsys)
    assert_one_line_error(code, err, "/dev/zero", "not a regular file")
    case = tmp_path / "case.toml"
    case.write_text(FILE_CASE.format(path="/dev/zero"))
    code, _, err = cli(["run", case, "--out", tmp_path / "out", "--quiet"], capsys)
    assert_one_line_error(code, err, "particles.path:", "not a regular file", "'/dev/zero'")
    assert not (tmp_path / "out").exists()
    code, _, err = cli(["dt", "/dev/zero", "--format", "case"], capsys)
    assert_one_line_error(code, err, "/dev/zero", "not a regular file")
    sim = build_simulation(case_from_text(RUN))
    with pytest.raises(InputError, match="/dev/zero: a character device, not a checkpoint"):
        load_checkpoint(sim, "/dev/zero")


def _disk_full(*args):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_full_disk_names_the_file(tmp_path, capsys, monkeypatch):
    target = tmp_path / "a.txt"
    monkeypatch.setattr(os, "fsync", _disk_full)
    with pytest.raises(OSError) as info:
        write_text_atomic(target, "text")
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(target)
    assert not target.exists() and list(tmp_path.iterdir()) == []
    case = tmp_path / "small.toml"
    case.write_text(RUN)
    code, _, err = cli(["run", case, "--out", tmp_path / "out", "--quiet"], capsys)
    assert code == 1, err
    assert re.fullmatch(rf"demstep: error: No space left on device: "
                        rf"{re.escape(str(tmp_path / 'out'))}/\S+\n", err), err
