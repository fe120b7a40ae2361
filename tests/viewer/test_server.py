"""The meshcat server process: localhost binding, busy ports, no orphans (checked in /proc)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from harvest_qp.exceptions import HarvestQPError, InvalidInputError
from harvest_qp.robot.description import HOME_Q
from harvest_qp.viewer import MeshcatViewer, ViewerError, ViewerFrame, ViewerPortInUseError, ViewerServer
from harvest_qp.viewer.replay import free_port

REPO = Path(__file__).resolve().parents[2]


def running(pid: int) -> bool:
    """True if ``pid`` exists and is not a zombie (a zombie has exited and only awaits reaping)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def wait_gone(pid: int, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not running(pid):
            return True
        time.sleep(0.05)
    return False


def listening_addresses(port: int) -> set[str]:
    """Local addresses (hex, as in /proc/net/tcp) in LISTEN state on ``port``."""
    out = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except FileNotFoundError:
            continue
        for line in lines:
            fields = line.split()
            address, hex_port = fields[1].split(":")
            if int(hex_port, 16) == port and fields[3] == "0A":  # 0A = LISTEN
                out.add(address)
    return out


def test_server_binds_localhost_only_and_stops_on_close():
    """The web port listens on 127.0.0.1 only (meshcat's own server listens on every interface).

    Catches: ``app.listen(port)`` without ``address=host`` (0.0.0.0 shows as 00000000 in
    /proc/net/tcp), a close() that leaves the process running.
    """
    port = free_port()
    server = ViewerServer(port=port, verbose=False)
    try:
        assert server.web_url == f"http://127.0.0.1:{port}/static/"
        assert listening_addresses(port) == {"0100007F"}, listening_addresses(port)
        with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
            s.sendall(b"GET /static/ HTTP/1.0\r\n\r\n")
            assert s.recv(64).startswith(b"HTTP/1.1 200")
    finally:
        server.close()
    assert wait_gone(server.pid), "the server still runs after close()"
    server.close()  # idempotent


def test_busy_port_raises_instead_of_moving():
    """A taken port raises ViewerPortInUseError naming it (meshcat would silently serve on port + 1).

    Catches: port walking (no error, another URL), a generic error without the port, a child
    left running after the failed start.
    """
    with socket.socket() as blocker:
        blocker.bind(("127.0.0.1", 0))
        blocker.listen()
        port = blocker.getsockname()[1]
        with pytest.raises(ViewerPortInUseError, match=f"port {port} .*already in use") as info:
            ViewerServer(port=port, verbose=False)
    assert isinstance(info.value, HarvestQPError)


def test_busy_port_error_from_the_drawing_process():
    """The default LiveViewer (drawing in a child) reports a busy port with the same error type."""
    from harvest_qp.viewer import LiveViewer

    with socket.socket() as blocker:
        blocker.bind(("127.0.0.1", 0))
        blocker.listen()
        port = blocker.getsockname()[1]
        with pytest.raises(ViewerPortInUseError, match=f"port {port} "):
            LiveViewer(port=port, verbose=False)


@pytest.mark.parametrize("host, port", [("127.0.0.1", 0), ("127.0.0.1", 70000), ("", 7000), ("127.0.0.1", "7000")])
def test_bad_host_or_port(host, port):
    with pytest.raises(InvalidInputError, match="host|port"):
        ViewerServer(host, port, verbose=False)


PARENT = textwrap.dedent(
    """
    import sys, time
    from harvest_qp.viewer import MeshcatViewer
    viewer = MeshcatViewer(None, port=int(sys.argv[1]), verbose=False)
    print(viewer.server.pid, flush=True)
    mode = sys.argv[2]
    if mode == "raise":
        raise RuntimeError("an error in the user's program")
    if mode == "wait":
        time.sleep(120)
    """
)


def _terminal_sigint() -> None:
    """Ctrl-C as in a terminal, also when pytest itself was started with SIGINT ignored (a job put in
    the background by a non-interactive shell): Python then leaves SIGINT ignored in its children."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.parametrize("mode", ["exit", "raise", "SIGINT", "SIGTERM", "SIGKILL"])
def test_no_orphan_server(mode):
    """Whatever ends the program (normal exit, an exception, Ctrl-C, SIGTERM, SIGKILL), the
    server process ends too, within a few seconds.

    Catches: relying on meshcat's atexit hook (SIGTERM/SIGKILL leave meshcat's server
    running, re-parented to PID 1), a server started in a new session that ignores its parent.
    Checked by hand: without the watchdog in ``_server_main.py`` the SIGTERM and SIGKILL cases fail.
    """
    port = free_port()
    wait = mode.startswith("SIG")
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT, str(port), "wait" if wait else mode],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(REPO)},
        preexec_fn=_terminal_sigint,
    )  # fmt: skip
    try:
        line = parent.stdout.readline().decode().strip()
        assert line.isdigit(), f"the parent did not start a viewer: {line!r} {parent.stderr.read()[-2000:]!r}"
        server_pid = int(line)
        if wait:
            assert running(server_pid)
            parent.send_signal(getattr(signal, mode))
        parent.wait(timeout=30)
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
    assert wait_gone(server_pid, 5.0), f"the meshcat server (pid {server_pid}) outlived its parent ({mode})"
    assert not listening_addresses(port), "the web port is still open"


def test_dead_server_gives_an_error_not_a_hang():
    """Drawing into a viewer whose server died raises ViewerError after the timeout.

    Catches: a REQ/REP socket that blocks forever when the server is gone.
    """
    with ViewerServer(port=free_port(), verbose=False) as server:
        viewer = MeshcatViewer(None, server=server)
        viewer.connection.timeout = 0.5
        server.process.kill()
        server.process.wait()
        with pytest.raises(ViewerError, match="did not answer"):
            viewer.draw(ViewerFrame(time=0.0, q=np.array(HOME_Q) + 0.1))
        viewer.close()


def test_live_viewer_draws_in_a_child_process_and_cleans_up():
    """The default LiveViewer draws in a child process; after close() neither it nor its
    server runs and the port is free. A dead drawing process becomes LiveViewer.error.

    Catches: frames never reaching the child (nothing drawn), a child or server left behind,
    an exception from a dead child raised into the loop.
    """
    from harvest_qp.runtime.runner import Observation
    from harvest_qp.viewer import LiveViewer

    port = free_port()
    live = LiveViewer(port=port, verbose=False)
    drawer = live.viewer.process.pid
    assert running(drawer) and listening_addresses(port) == {"0100007F"}
    for k in range(40):
        live.observe(Observation(time=0.002 * k, q=np.array(HOME_Q), qdot=np.zeros(12), force=np.zeros(3),
                                 cloud=None, new_cloud=False))  # fmt: skip
        time.sleep(0.002)
    assert live.flush(20.0) and live.frames_drawn >= 1
    live.close()
    assert wait_gone(drawer), "the drawing process outlived close()"
    deadline = time.monotonic() + 5
    while listening_addresses(port) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not listening_addresses(port), "the server outlived the drawing process"

    live = LiveViewer(port=free_port(), verbose=False)
    live.viewer.process.kill()
    live.viewer.process.wait()
    live.observe(Observation(time=0.0, q=np.array(HOME_Q), qdot=np.zeros(12), force=np.zeros(3), cloud=None,
                             new_cloud=False))  # fmt: skip
    assert live.flush(20.0) is False and isinstance(live.error, ViewerError)
    live.close()


PARENT_LIVE = textwrap.dedent(
    """
    import time, sys
    from harvest_qp.viewer import LiveViewer
    live = LiveViewer(port=int(sys.argv[1]), verbose=False)
    print(live.viewer.process.pid, flush=True)
    time.sleep(120)
    """
)


def test_no_orphan_drawing_process_after_sigkill():
    """SIGKILL of a program with a live viewer: the drawing process and its server both end.

    Catches: a drawing process that does not notice its parent's death (it would keep the
    server up). Two mechanisms end it: the socket's EOF and a getppid() watchdog; with the
    watchdog disabled by hand the test still passes (the EOF suffices).
    """
    port = free_port()
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT_LIVE, str(port)], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )  # fmt: skip
    try:
        line = parent.stdout.readline().decode().strip()
        assert line.isdigit(), f"no live viewer started: {line!r} {parent.stderr.read()[-2000:]!r}"
        drawer = int(line)
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=30)
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
    assert wait_gone(drawer, 5.0), "the drawing process outlived its parent"
    deadline = time.monotonic() + 5
    while listening_addresses(port) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not listening_addresses(port), "the server outlived the drawing process"
