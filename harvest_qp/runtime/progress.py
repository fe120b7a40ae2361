"""A progress line for ``harvest-qp run`` on a terminal: simulated time, phase, real-time factor.

It wraps the episode's controller like the viewer does (it only observes ``step``), and draws at
most a few times per wall-clock second, so it costs nothing measurable in the 2 ms tick.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any, TextIO


class ProgressController:
    """Forwards ``reset``/``step`` to ``controller`` and rewrites one status line on ``stream``.

    Args:
        controller: the episode's controller (``reset(robot)``, ``step(obs) -> Command``; ``phase``
            is shown when it has one).
        stream: where the line goes (default: standard error).
        duration: the episode's length [s], shown as the total.
        every: wall-clock seconds [s] between two redraws.
        clock: the wall clock [s] (default :func:`time.perf_counter`).
    """

    def __init__(self, controller: Any, *, stream: TextIO | None = None, duration: float | None = None,
                 every: float = 0.25, clock: Callable[[], float] = time.perf_counter) -> None:
        self.controller = controller
        self.clock = clock
        self.stream = stream if stream is not None else sys.stderr
        self.duration = duration
        self.every = every
        self._wall0: float | None = None
        self._next_draw = 0.0
        self.lines_drawn = 0

    def __getattr__(self, name: str) -> Any:
        return getattr(self.controller, name)  # metrics, figures and the viewer read the controller

    def reset(self, robot: Any) -> None:
        self._wall0 = self.clock()
        self._next_draw = self._wall0
        self.controller.reset(robot)

    def step(self, obs: Any) -> Any:
        command = self.controller.step(obs)
        now = self.clock()
        if now >= self._next_draw:
            self._next_draw = now + self.every
            self.draw(float(obs.time), now - (self._wall0 or now))
        return command

    def draw(self, sim_time: float, wall: float) -> None:
        """Rewrite the line: ``t 12.3 / 50.0 s  phase bimanual  3.9x real time``."""
        phase = getattr(self.controller, "phase", None)
        phase_text = f"  phase {phase.name.lower()}" if hasattr(phase, "name") else ""
        total = f" / {self.duration:.1f}" if self.duration is not None else ""
        factor = f"  {sim_time / wall:.1f}x real time" if wall >= 0.5 else ""  # not before it means something
        self.stream.write(f"\r  t {sim_time:5.1f}{total} s{phase_text}{factor}   ")
        self.stream.flush()
        self.lines_drawn += 1

    def finish(self) -> None:
        """End the line (call once after the episode) so later output starts on a new line."""
        if self.lines_drawn:
            self.stream.write("\n")
            self.stream.flush()


def wants_progress(stream: TextIO | None = None) -> bool:
    """True when ``stream`` (default: standard error) is a terminal."""
    stream = stream if stream is not None else sys.stderr
    isatty = getattr(stream, "isatty", None)
    return bool(isatty and isatty())
