"""The meshcat server process, owned and cleaned up by harvest_qp (not by meshcat's atexit hook).

meshcat 0.3.2 starts its web/zmq server in a new session and only kills it from an
``atexit`` hook: after a SIGKILL or SIGTERM of the parent it keeps running, and the next
viewer silently moves to the next port. :class:`ViewerServer` instead

* starts the server (``_server_main.py``) itself, bound to ``host`` (127.0.0.1 by default);
* raises :class:`ViewerPortInUseError` when ``port`` is taken (no silent port walk);
* stops it on :meth:`close`, when garbage-collected, at interpreter exit (``weakref.finalize``),
  and -- through a watchdog in the child that polls its parent -- within about 0.2 s of the
  parent dying by any signal.

:class:`Connection` talks to it over zmq. It pipelines commands (a DEALER socket: send a
whole viewer frame, then collect the acknowledgements) instead of meshcat's one blocking
round trip per command (0.3 ms each, STACK_NOTES).
"""

from __future__ import annotations

import os
import selectors
import subprocess
import sys
import tempfile
import threading
import time
import weakref
from collections.abc import Sequence
from pathlib import Path

import zmq

from harvest_qp.exceptions import HarvestQPError, InvalidInputError

__all__ = ["ViewerError", "ViewerPortInUseError", "ViewerServer", "Connection"]

_SERVER_SCRIPT = Path(__file__).with_name("_server_main.py")
_EXIT_PORT_BUSY = 3


class ViewerError(HarvestQPError):
    """The viewer's server cannot be started or does not answer."""


class ViewerPortInUseError(ViewerError):
    """The requested web port is already taken (meshcat would silently use another one)."""


def _check_host_port(host: str, port: int) -> None:
    if not isinstance(host, str) or not host or any(c.isspace() for c in host):
        raise InvalidInputError(f"host must be a non-empty host name or address, got {host!r}")
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise InvalidInputError(f"port must be an integer in [1, 65535], got {port!r}")


class ViewerServer:
    """A meshcat web/zmq server in a child process that never outlives this process.

    Args:
        host: address the web page is served on (default 127.0.0.1: this machine only;
            ``0.0.0.0`` serves every interface).
        port: web port; a busy port raises :class:`ViewerPortInUseError`.
        start_timeout: how long to wait for the server to come up [s].
        verbose: print the URL once the server is up.

    Use as a context manager or call :meth:`close`.
    """

    def __init__(
        self, host: str = "127.0.0.1", port: int = 7000, *, start_timeout: float = 20.0, verbose: bool = True
    ) -> None:
        _check_host_port(host, port)
        self.host, self.port = host, port
        self._stderr = tempfile.TemporaryFile()
        # The child only needs meshcat, tornado and zmq: run the script by path so it does not
        # depend on how harvest_qp is importable from the child's working directory.
        self.process = subprocess.Popen(
            [sys.executable, "-u", str(_SERVER_SCRIPT), "--host", host, "--port", str(port),
             "--parent-pid", str(os.getpid())],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=self._stderr,
        )  # fmt: skip
        self._closed = False
        self._finalizer = weakref.finalize(self, _stop_process, self.process)
        try:
            lines = self._read_startup(start_timeout)
        except BaseException:
            self.close()
            raise
        self.zmq_url = lines["zmq_url"]
        self.web_url = lines["web_url"]
        # Drain stdout so a chatty server never blocks on a full pipe.
        threading.Thread(target=_drain, args=(self.process.stdout,), daemon=True).start()
        if verbose:
            print(f"harvest_qp viewer: open {self.web_url}", flush=True)

    @property
    def pid(self) -> int:
        """Process id of the server."""
        return self.process.pid

    def _read_startup(self, timeout: float) -> dict[str, str]:
        found: dict[str, str] = {}
        deadline = time.monotonic() + timeout
        buffer = b""
        with selectors.DefaultSelector() as selector:
            selector.register(self.process.stdout, selectors.EVENT_READ)
            while len(found) < 2:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ViewerError(f"the meshcat server did not start within {timeout} s")
                if selector.select(min(left, 0.1)):
                    chunk = os.read(self.process.stdout.fileno(), 4096)
                    buffer += chunk
                    while b"\n" in buffer:
                        line, buffer = buffer.split(b"\n", 1)
                        key, _, value = line.decode(errors="replace").strip().partition("=")
                        if key in ("zmq_url", "web_url"):
                            found[key] = value
                    if not chunk:
                        self.process.wait(timeout=5)
                if self.process.poll() is not None:
                    self._raise_exit_error()
        return found

    def _raise_exit_error(self) -> None:
        code = self.process.returncode
        self._stderr.seek(0)
        message = self._stderr.read().decode(errors="replace").strip()
        if code == _EXIT_PORT_BUSY:
            raise ViewerPortInUseError(
                f"port {self.port} on {self.host} is already in use; pass another port (e.g. --port "
                f"{self.port + 1}) or stop the program that holds it"
            )
        raise ViewerError(f"the meshcat server exited with code {code} while starting: {message[-2000:]}")

    @property
    def alive(self) -> bool:
        """True while the server process runs."""
        return self.process.poll() is None

    def close(self) -> None:
        """Stop the server process (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._finalizer()
        self._stderr.close()

    def __enter__(self) -> ViewerServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _drain(stream) -> None:
    try:
        while stream.read(4096):
            pass
    except (OSError, ValueError):
        pass


def _stop_process(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=3)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=3)
    for stream in (process.stdout,):
        if stream is not None:
            try:
                stream.close()
            except OSError:
                pass


class Connection:
    """Pipelined zmq client of a meshcat server.

    Args:
        zmq_url: the server's zmq address (``ViewerServer.zmq_url`` or ``tcp://127.0.0.1:6000``
            for a server started elsewhere).
        timeout: how long one batch may wait for the server's acknowledgements [s].
        batch: the server understands harvest_qp's ``batch`` command (a :class:`ViewerServer`):
            a whole frame goes in one message and one acknowledgement. Otherwise (any meshcat
            server) the commands are pipelined.
    """

    def __init__(self, zmq_url: str, *, timeout: float = 10.0, batch: bool = False) -> None:
        if not isinstance(zmq_url, str) or "://" not in zmq_url:
            raise InvalidInputError(f"zmq_url must look like 'tcp://127.0.0.1:6000', got {zmq_url!r}")
        self.zmq_url = zmq_url
        self.timeout = float(timeout)
        self._context = zmq.Context()
        self._socket = self._context.socket(zmq.DEALER)
        self._socket.setsockopt(zmq.LINGER, 0)
        self._socket.connect(zmq_url)
        self._lock = threading.Lock()
        self.batch = bool(batch)
        self.messages_sent = 0

    def send(self, messages: Sequence[tuple[bytes, bytes, bytes]]) -> None:
        """Send ``(command, path, msgpack data)`` messages, then wait for all their acknowledgements."""
        if not messages:
            return
        with self._lock:
            socket = self._socket
            if self.batch:
                frames = [b"", b"batch"]
                for message in messages:
                    frames.extend(message)
                socket.send_multipart(frames)
                self._collect(1)
            else:
                for command, path, data in messages:
                    socket.send_multipart((b"", command, path, data))
                self._collect(len(messages))
            self.messages_sent += len(messages)

    def request(self, command: bytes) -> bytes:
        """One request without arguments (``b"url"``, ``b"get_scene"``); returns the reply."""
        with self._lock:
            self._socket.send_multipart((b"", command))
            return self._collect(1)

    def _collect(self, n: int) -> bytes:
        reply = b""
        deadline = time.monotonic() + self.timeout
        for _ in range(n):
            left_ms = int(max(0.0, deadline - time.monotonic()) * 1000)
            if not self._socket.poll(left_ms, zmq.POLLIN):
                # The late replies would be mistaken for the next batch's: start a fresh socket.
                self._reconnect()
                raise ViewerError(f"the meshcat server at {self.zmq_url} did not answer within {self.timeout} s")
            frames = self._socket.recv_multipart()
            reply = frames[-1]
            if reply.startswith(b"error"):
                raise ViewerError(f"the meshcat server refused a command: {reply.decode(errors='replace')}")
        return reply

    def _reconnect(self) -> None:
        self._socket.close(linger=0)
        self._socket = self._context.socket(zmq.DEALER)
        self._socket.setsockopt(zmq.LINGER, 0)
        self._socket.connect(self.zmq_url)

    def close(self) -> None:
        """Close the socket (the server keeps running)."""
        with self._lock:
            self._socket.close(linger=0)
            self._context.term()
