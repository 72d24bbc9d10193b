"""``--scheduler`` pointing at something that is not a Dask scheduler: an SSH server, an
HTTP server (the dashboard's port), a server that stays silent or hangs up, nothing
listening, a host that does not resolve. Each gives one line naming the option and the
address, exit status 2 and no output folder, within the connection timeout; a real Dask
scheduler is still accepted.

The fake servers run in threads of this process on 127.0.0.1 (free ports); the sweep
runs in a subprocess with a time limit, so that a hang fails the test instead of the
suite."""

import http.server
import socket
import socketserver
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from demstep.errors import InputError
from demstep.sweep import cluster
from demstep.sweep.cluster import dask_client

SRC = str(Path(__file__).resolve().parents[1] / "src")

CASE = """
name = "tiny"
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
steps = 20
[stages.walls."y+"]
motion = "velocity"
velocity = [0.0, -0.01]
"""

#: connection timeout [s] of the sweep in the subprocess
TIMEOUT = 3.0
#: time limit [s] of the subprocess: a generous guard (imports on a busy machine), far
#: below the time a hang would take
LIMIT = 90.0

#: the sweep in a subprocess, with cluster.CONNECT_TIMEOUT set to argv[1]
SWEEP = ("import sys\n"
         "from demstep.sweep import cluster\n"
         "cluster.CONNECT_TIMEOUT = float(sys.argv[1])\n"
         "from demstep.cli.sweep import main\n"
         "sys.exit(main(sys.argv[2:]))\n")


@pytest.fixture
def case(tmp_path):
    path = tmp_path / "case.toml"
    path.write_text(CASE)
    return path


@pytest.fixture
def serve():
    """``serve(handler_class, server_class=ThreadingTCPServer)``: a server in a thread on
    127.0.0.1 (a free port); returns its tcp:// address. Handlers that wait do so on
    ``serve.stop`` (set at the end), and every server is shut down."""
    servers = []
    stop = threading.Event()

    def start(handler, server_class=socketserver.ThreadingTCPServer):
        server_class.daemon_threads = True
        server_class.allow_reuse_address = True
        server = server_class(("127.0.0.1", 0), handler)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        servers.append(server)
        return f"tcp://127.0.0.1:{server.server_address[1]}"

    start.stop = stop
    yield start
    stop.set()
    for server in servers:
        server.shutdown()
        server.server_close()


def run_sweep_cli(case, out, address, timeout=TIMEOUT):
    """``demstep sweep`` in a subprocess; (exit status, stderr, seconds)."""
    import os

    env = {**os.environ, "PYTHONPATH": SRC}
    start = time.monotonic()
    try:
        proc = subprocess.run(
            [sys.executable, "-c", SWEEP, str(timeout), "sweep", str(case), "--param",
             "contact.mu=0.1", "--out", str(out), "--scheduler", address],
            capture_output=True, text=True, timeout=LIMIT, env=env)
    except subprocess.TimeoutExpired:
        pytest.fail(f"demstep sweep --scheduler {address} hung (killed after {LIMIT:g} s)")
    return proc.returncode, proc.stderr.strip(), time.monotonic() - start


def assert_one_line(code, err, out, address, *words):
    assert code == 2, err
    assert len(err.splitlines()) == 1, err
    assert err.startswith("demstep: error: scheduler:"), err
    assert address in err, err
    for w in words:
        assert w in err, err
    assert not out.exists()


def _ssh_banner(stop):
    class Handler(socketserver.BaseRequestHandler):
        def handle(self):
            self.request.sendall(b"SSH-2.0-OpenSSH_9.2\r\n")
            stop.wait()
    return Handler


def _silent(stop):
    class Handler(socketserver.BaseRequestHandler):
        def handle(self):  # accept, read whatever comes, never answer
            self.request.settimeout(0.2)
            while not stop.is_set():
                try:
                    if not self.request.recv(4096):
                        return
                except socket.timeout:
                    pass
    return Handler


class _HangUp(socketserver.BaseRequestHandler):
    def handle(self):  # accept and close at once
        pass


class _Http(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):  # quiet
        pass


def test_ssh_server_is_one_line(case, tmp_path, serve):
    """An SSH server speaks first; Dask's comm read its banner as a frame length (numpy
    asked for 2.82 EiB, a 49-line traceback, exit 1)."""
    address = serve(_ssh_banner(serve.stop))
    out = tmp_path / "sweep"
    code, err, _ = run_sweep_cli(case, out, address)
    assert_one_line(code, err, out, address, "SSH server", "SSH-2.0-OpenSSH_9.2",
                    "not a Dask scheduler")


def test_http_server_is_one_line(case, tmp_path, serve):
    """An HTTP server (the dashboard's port 8787 given by mistake) hung the sweep with
    nothing printed."""
    address = serve(_Http, http.server.ThreadingHTTPServer)
    out = tmp_path / "sweep"
    code, err, _ = run_sweep_cli(case, out, address)
    assert_one_line(code, err, out, address, "HTTP server", "dashboard", "not a Dask scheduler")


def test_silent_server_is_one_line(case, tmp_path, serve):
    """A server that accepts and never answers hung the sweep (the handshake of Dask's
    comm has no timeout)."""
    address = serve(_silent(serve.stop))
    out = tmp_path / "sweep"
    code, err, _ = run_sweep_cli(case, out, address)
    assert_one_line(code, err, out, address, "did not answer as a Dask scheduler",
                    f"within {TIMEOUT:g} s")


def test_server_that_hangs_up_is_one_line(case, tmp_path, serve):
    """A server that accepts and closes at once: said 'Stream is closed' through a
    CommClosedError."""
    address = serve(_HangUp)
    out = tmp_path / "sweep"
    code, err, _ = run_sweep_cli(case, out, address)
    assert_one_line(code, err, out, address, "closed the connection", "not a Dask scheduler")


def test_nothing_listening_is_one_line(case, tmp_path):
    """Connection refused: said 'Timed out trying to connect' after the whole timeout."""
    with socket.socket() as s:  # a port that was free a moment ago: nothing listens
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    out = tmp_path / "sweep"
    code, err, _ = run_sweep_cli(case, out, address)
    assert_one_line(code, err, out, address, "cannot connect", "refused", "nothing listening")


def test_host_that_does_not_resolve_is_one_line(case, tmp_path):
    """A host name that does not resolve (.invalid never does): said 'Timed out trying
    to connect'."""
    address = "tcp://no-such-host.invalid:8786"
    out = tmp_path / "sweep"
    code, err, _ = run_sweep_cli(case, out, address)
    assert_one_line(code, err, out, address, "cannot connect", "'no-such-host.invalid'",
                    "does not resolve")


def test_real_scheduler_accepted_and_a_late_greeting_is_judged(serve):
    """A real Dask scheduler passes the probe and the client connects; a server silent
    past the first wait whose answer is a Dask greeting (a scheduler with a busy event
    loop) is accepted, one whose answer is an SSH banner is not (the old code had no
    probe and tried Dask's handshake on whatever answered)."""
    from distributed import LocalCluster
    from distributed.protocol.utils import pack_frames

    from demstep.sweep.cluster import probe_scheduler

    with LocalCluster(n_workers=0, processes=False, protocol="tcp", host="127.0.0.1",
                      scheduler_port=0, dashboard_address=None) as local:
        address = local.scheduler_address
        assert address.startswith("tcp://127.0.0.1:")
        probe_scheduler(address, 5.0)
        with dask_client(address) as client:
            assert client.scheduler_info()["address"] == address

    def late(answer):
        class Handler(socketserver.BaseRequestHandler):
            def handle(self):
                time.sleep(1.5)  # past the first wait of a 2 s probe: the probe asks
                self.request.sendall(answer)
                serve.stop.wait()
        return Handler

    body = pack_frames([b"\x80"])  # what a Dask comm writes: length, then the frames
    probe_scheduler(serve(late(struct.pack("<Q", len(body)) + body)), 2.0)
    with pytest.raises(InputError, match="SSH server"):
        probe_scheduler(serve(late(b"SSH-2.0-OpenSSH_9.2\r\n")), 2.0)


def test_client_failure_is_one_line(monkeypatch):
    """Whatever distributed.Client raises after the probe becomes the one-line
    InputError (the old code let anything but OSError, TimeoutError and ValueError
    through as a traceback)."""
    import distributed

    def broken(*args, **kwargs):
        raise RuntimeError("handshake went wrong\nsecond line")

    monkeypatch.setattr(cluster, "probe_scheduler", lambda address, timeout: None,
                        raising=False)
    monkeypatch.setattr(distributed, "Client", broken)
    with pytest.raises(InputError) as info:
        with dask_client("tcp://127.0.0.1:8786"):
            pass
    text = str(info.value)
    assert "\n" not in text
    assert text.startswith("scheduler: cannot connect to tcp://127.0.0.1:8786")
    assert "RuntimeError: handshake went wrong second line" in text
