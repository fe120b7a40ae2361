"""Live viewing of a running episode without slowing the control loop.

:meth:`LiveViewer.observe` only stores the latest observation (a few microseconds); a worker
thread turns the latest one into a :class:`ViewerFrame` and has it drawn (by default in a
child process, :mod:`harvest_qp.viewer._drawer`), at most ``max_rate`` times per second.
Ticks that arrive while a frame is being drawn are skipped, never queued,
so a slow browser or server cannot hold the loop back. A drawing error (the server died)
stops the drawing and is kept in :attr:`LiveViewer.error`; it is never raised into the loop.

:class:`ViewedController` wraps any runner controller so that every tick is observed (and,
with ``realtime``, paced to wall-clock time) without touching the runner.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.viewer.frame import ViewerFrame, frame_from_observation

__all__ = ["LiveViewer", "ViewedController", "RealTimePacer", "wait_for_interrupt"]


class LiveViewer:
    """Observer of a control loop that draws into a :class:`~harvest_qp.viewer.MeshcatViewer`.

    Args:
        viewer: the viewer to draw into, from this process's worker thread (None: a new one
            with ``viewer_kwargs``, closed with this object).
        max_rate: frames drawn per second at most [Hz] (default 30).
        process: with ``viewer=None``, draw in a child process (default): the worker thread
            here only pickles the frame (and a new cloud, thinned) and waits, so the viewer's
            Python work (kinematics, packing, text panel) does not compete with the control
            loop for the GIL. False: draw in the worker thread.
        **viewer_kwargs: arguments of :class:`MeshcatViewer` (``vine``, ``host``, ``port``, ...).

    Use as a context manager, or call :meth:`close` (it draws the last observation first).
    """

    def __init__(self, viewer=None, *, max_rate: float = 30.0, process: bool = True, **viewer_kwargs: Any) -> None:
        if not isinstance(max_rate, (int, float)) or not np.isfinite(max_rate) or max_rate <= 0:
            raise InvalidInputError(f"max_rate must be a finite rate > 0 [Hz], got {max_rate!r}")
        from harvest_qp.viewer.viewer import MeshcatViewer

        self._own = viewer is None
        if viewer is not None:
            self.viewer = viewer
        elif process:
            from harvest_qp.viewer._drawer import ProcessDrawer

            self.viewer = ProcessDrawer(viewer_kwargs)
        else:
            self.viewer = MeshcatViewer(**viewer_kwargs)
        self.period = 1.0 / float(max_rate)
        self._latest: tuple[Any, ...] | None = None
        self._wake = threading.Event()
        self._stop = False
        self._busy = False
        self.error: BaseException | None = None
        self.frames_drawn = 0
        self.observed = 0
        self.draw_times: list[float] = []
        self._thread = threading.Thread(target=self._run, name="harvest_qp-viewer", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        """The viewer's web address."""
        return self.viewer.url

    def observe(self, obs: Any, extras: Mapping[str, Any] | None = None) -> None:
        """Record the latest observation (non-blocking; called from the control loop).

        Args:
            obs: a runner :class:`~harvest_qp.runtime.runner.Observation` (time, q, force, cloud), or a
                :class:`ViewerFrame`.
            extras: optional :class:`ViewerFrame` fields for this tick (``phase``, ``p_r``,
                ``v_c``, ...). Arrays are not copied: pass arrays the caller will not modify.
        """
        if isinstance(obs, ViewerFrame):
            self._latest = (obs, None)
        else:
            # q and force are tiny: copy them so a robot that reuses buffers cannot tear a frame.
            self._latest = (_Snapshot(obs.time, np.array(obs.q), np.array(obs.force), obs.cloud), extras)
        self.observed += 1
        self._wake.set()

    def flush(self, timeout: float = 10.0) -> bool:
        """Wait until the latest observation is drawn (or drawing failed); False on timeout [s]."""
        deadline = time.perf_counter() + timeout
        while self._latest is not None or self._busy:
            if self.error is not None or not self._thread.is_alive():
                return False
            if time.perf_counter() > deadline:
                return False
            time.sleep(0.002)
        return self.error is None

    def _run(self) -> None:
        next_draw = 0.0
        while True:
            self._wake.wait()
            if self._stop and self._latest is None:
                return
            wait = next_draw - time.perf_counter()
            if wait > 0 and not self._stop:
                time.sleep(wait)
            self._wake.clear()
            self._busy = True
            latest, self._latest = self._latest, None
            if latest is not None and self.error is None:
                try:
                    obs, extras = latest
                    frame = obs if isinstance(obs, ViewerFrame) else frame_from_observation(obs, extras)
                    t0 = time.perf_counter()
                    self.viewer.draw(frame, wall_time=t0)
                    self.draw_times.append(time.perf_counter() - t0)
                    self.frames_drawn += 1
                except BaseException as error:  # never reaches the control loop
                    self.error = error
            self._busy = False
            next_draw = time.perf_counter() + self.period
            if self._stop and self._latest is None:
                return

    def close(self) -> None:
        """Draw the last observation, stop the worker and close the viewer if this object made it."""
        if self._stop:
            return
        self._stop = True
        self._wake.set()
        self._thread.join(timeout=10.0)
        if self._own:
            self.viewer.close()

    def __enter__(self) -> LiveViewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Snapshot:
    __slots__ = ("time", "q", "force", "cloud")

    def __init__(self, time: float, q, force, cloud) -> None:
        self.time, self.q, self.force, self.cloud = time, q, force, cloud


class RealTimePacer:
    """Sleeps so that episode time does not run ahead of wall-clock time.

    Args:
        speed: episode seconds per wall-clock second (1 = real time).
    """

    def __init__(self, speed: float = 1.0) -> None:
        if not isinstance(speed, (int, float)) or not np.isfinite(speed) or speed <= 0:
            raise InvalidInputError(f"speed must be a finite factor > 0, got {speed!r}")
        self.speed = float(speed)
        self._start: tuple[float, float] | None = None

    def pace(self, episode_time: float) -> None:
        """Block until wall time has caught up with ``episode_time`` [s]."""
        now = time.perf_counter()
        if self._start is None:
            self._start = (now, float(episode_time))
            return
        due = self._start[0] + (episode_time - self._start[1]) / self.speed
        if due > now:
            time.sleep(due - now)


class ViewedController:
    """A runner controller that shows every tick in a :class:`LiveViewer`.

    ``step`` calls the wrapped controller, then ``viewer.observe(obs, extras(obs, command))``
    and, with a pacer, waits for wall-clock time. The wrapped controller's output is
    returned unchanged. (With ``log_timing`` the runner's ``controller_time`` then includes
    the observe call, a few microseconds, and the pacing sleep.)

    Args:
        controller: any object with ``reset(robot)`` and ``step(obs)``.
        viewer: the live viewer.
        extras: optional callable ``(obs, command) -> mapping`` of :class:`ViewerFrame` fields;
            by default the wrapped controller's ``viewer_extras()`` method if it has one.
        pacer: a :class:`RealTimePacer` for real-time display, or None (as fast as possible).
    """

    def __init__(
        self,
        controller: Any,
        viewer: LiveViewer,
        *,
        extras: Callable[[Any, Any], Mapping[str, Any]] | None = None,
        pacer: RealTimePacer | None = None,
    ) -> None:
        if not callable(getattr(controller, "step", None)) or not callable(getattr(controller, "reset", None)):
            raise InvalidInputError(f"controller must have reset(robot) and step(obs), got {type(controller).__name__}")
        if extras is None and callable(getattr(controller, "viewer_extras", None)):
            method = controller.viewer_extras

            def extras(obs: Any, command: Any) -> Mapping[str, Any]:
                return method()

        self.controller, self.viewer, self.extras, self.pacer = controller, viewer, extras, pacer

    def reset(self, robot: Any) -> None:
        self.controller.reset(robot)

    def step(self, obs: Any) -> Any:
        command = self.controller.step(obs)
        self.viewer.observe(obs, self.extras(obs, command) if self.extras is not None else None)
        if self.pacer is not None:
            self.pacer.pace(obs.time)
        return command

    def __getattr__(self, name: str) -> Any:  # expose the wrapped controller's attributes
        return getattr(self.controller, name)


def wait_for_interrupt(message: str) -> None:
    """Print ``message`` and block until Ctrl-C or SIGTERM (for a command that keeps a viewer open)."""
    import signal

    print(message, flush=True)
    previous = signal.getsignal(signal.SIGTERM)

    def stop(*_: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, previous)
