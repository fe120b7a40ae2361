"""A drawing process for :class:`harvest_qp.viewer.LiveViewer`: the viewer's Python work off the loop's GIL.

:class:`ProcessDrawer` starts ``python -m harvest_qp.viewer._drawer`` with one end of a socket
pair; the child builds a :class:`MeshcatViewer` (which starts its own server) and draws the
frames it receives. The parent only pickles a small frame (q, force, markers) and, when a new
camera frame arrives, the thinned cloud. The child exits when the socket closes or its parent
is gone (polled every 0.2 s), and its server follows it (the server's own watchdog).
"""

from __future__ import annotations

import dataclasses
import math
import os
import socket
import subprocess
import sys
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.viewer.server import ViewerError, ViewerPortInUseError

_SAME = "same"


class ProcessDrawer:
    """``draw(frame)`` in a child process; same interface as :class:`MeshcatViewer` for :class:`LiveViewer`.

    Args:
        viewer_kwargs: arguments of :class:`MeshcatViewer` (``vine`` may be an ``MjModel``: it pickles).
        start_timeout: how long the child may take to start its viewer [s].
        timeout: how long one frame may take [s].
    """

    def __init__(self, viewer_kwargs: dict[str, Any], *, start_timeout: float = 60.0, timeout: float = 20.0) -> None:
        parent_sock, child_sock = socket.socketpair()
        self.timeout = timeout
        package_root = str(Path(__file__).resolve().parents[2])
        env = dict(os.environ)
        env["PYTHONPATH"] = package_root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "harvest_qp.viewer._drawer", str(child_sock.fileno()), str(os.getpid())],
            pass_fds=(child_sock.fileno(),), env=env, stdin=subprocess.DEVNULL,
        )  # fmt: skip
        child_sock.close()
        self._conn = Connection(parent_sock.detach())
        self.max_cloud_points = int(viewer_kwargs.get("max_cloud_points", 10000))
        self._last_cloud_key: Any = object()
        self.url = ""
        try:
            self._conn.send(viewer_kwargs)
            reply = self._receive(start_timeout)
            if reply[0] != "ready":
                if reply[1].startswith("ViewerPortInUseError: "):  # keep the type for the caller
                    raise ViewerPortInUseError(reply[1].split(": ", 1)[1])
                if reply[1].startswith("InvalidInputError: "):
                    raise InvalidInputError(reply[1].split(": ", 1)[1])
                raise ViewerError(f"the drawing process could not start the viewer: {reply[1]}")
            self.url = reply[1]
        except BaseException:
            self.close()
            raise

    def _receive(self, timeout: float):
        if not self._conn.poll(timeout):
            raise ViewerError(f"the drawing process did not answer within {timeout} s")
        try:
            return self._conn.recv()
        except EOFError:
            raise ViewerError(f"the drawing process exited (code {self.process.poll()})") from None

    def draw(self, frame, *, wall_time: float | None = None) -> None:
        """Send ``frame`` to the child and wait until it is drawn."""
        payload: Any = None
        if frame.cloud_points is not None:
            key = frame.cloud_key if frame.cloud_key is not None else id(frame.cloud_points)
            if key == self._last_cloud_key:
                payload = _SAME
            else:
                # Thin here: pickling 10k points instead of the camera's 45k.
                stride = max(1, int(math.ceil(len(frame.cloud_points) / self.max_cloud_points)))
                payload = (
                    np.asarray(frame.cloud_points, dtype=np.float32)[::stride],
                    np.asarray(frame.cloud_labels)[::stride],
                    key,
                )
                self._last_cloud_key = key
            frame = dataclasses.replace(frame, cloud_points=None, cloud_labels=None)
        try:
            self._conn.send((frame, payload, wall_time))
        except OSError as error:
            raise ViewerError(f"the drawing process is gone (code {self.process.poll()}): {error}") from None
        reply = self._receive(self.timeout)
        if reply[0] != "ok":
            raise ViewerError(f"the drawing process failed: {reply[1]}")

    def close(self) -> None:
        """Stop the child (and with it its server)."""
        try:
            self._conn.send(None)
        except (OSError, ValueError):
            pass
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.terminate()
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._conn.close()


def _main(fd: int, parent_pid: int) -> int:
    import signal

    from harvest_qp.viewer.viewer import MeshcatViewer

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when drawing stops
    conn = Connection(fd)
    kwargs = conn.recv()
    try:
        viewer = MeshcatViewer(**kwargs)
    except BaseException as error:
        conn.send(("error", f"{type(error).__name__}: {error}"))
        return 1
    conn.send(("ready", viewer.url))
    cloud = None
    try:
        while True:
            if not conn.poll(0.2):
                if os.getppid() != parent_pid:
                    return 0
                continue
            try:
                message = conn.recv()
            except EOFError:
                return 0
            if message is None:
                return 0
            frame, payload, wall_time = message
            try:
                if isinstance(payload, tuple):  # a new cloud; _SAME reuses the last one
                    cloud = payload
                if payload is not None and cloud is not None:
                    frame = dataclasses.replace(frame, cloud_points=cloud[0], cloud_labels=cloud[1], cloud_key=cloud[2])
                viewer.draw(frame, wall_time=wall_time)
                conn.send(("ok",))
            except Exception as error:  # report, keep serving
                conn.send(("error", f"{type(error).__name__}: {error}"))
    finally:
        viewer.close()


if __name__ == "__main__":
    sys.exit(_main(int(sys.argv[1]), int(sys.argv[2])))
