"""Where episodes run: K local processes (the default) or Ray tasks.

Both engines call :func:`run_episode` on the worker side, so an episode's row depends on
its seed alone, never on the engine, the worker count or the order episodes finish in.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import pickle
import secrets
import shutil
import signal
import sys
import tempfile
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from multiprocessing.connection import wait as wait_for
from typing import Any

from harvest_qp.exceptions import HarvestQPError
from harvest_qp.sweep.results import normalize_metrics
from harvest_qp.sweep.stats import STATUS_DIED, STATUS_ERROR, STATUS_OK, STATUS_TIMEOUT

#: The ``error`` text of an episode whose process exited; the same for every engine
#: (Ray does not report the exit code; the local engine prints it on stderr).
WORKER_DIED_MESSAGE = "WorkerDied: the process running this episode exited before returning its metrics"

Outcome = dict[str, Any]
OnOutcome = Callable[[Outcome], None]


class MissingDependencyError(HarvestQPError, ImportError):
    """An optional dependency of the requested feature is not installed; the message names the fix."""


class SweepEngineError(HarvestQPError):
    """The engine itself failed (not one episode): the episode cannot be loaded in a worker, Ray cannot start."""


def run_episode(episode: Callable[[int], Mapping[str, Any]], seed: int) -> Outcome:
    """Run one episode and describe what happened; never raises for a failing episode.

    Returns:
        ``{"seed", "status", "error", "wall_time_s", "metrics", "traceback"}``: status ``ok`` with
        the flattened metrics, or ``error`` with ``"ExceptionType: message"`` (on one line) and
        the traceback; ``wall_time_s`` is the episode's wall-clock time [s] in its worker.
    """
    start = time.perf_counter()
    try:
        metrics = normalize_metrics(episode(seed))
    except (Exception, SystemExit) as exc:  # SystemExit: an episode calling sys.exit() is one bad episode
        message = " / ".join(line.strip() for line in str(exc).splitlines() if line.strip())
        return {
            "seed": seed,
            "status": STATUS_ERROR,
            "error": f"{type(exc).__name__}: {message}" if message else type(exc).__name__,
            "wall_time_s": time.perf_counter() - start,
            "metrics": {},
            "traceback": traceback.format_exc(),
        }
    return {
        "seed": seed,
        "status": STATUS_OK,
        "error": None,
        "wall_time_s": time.perf_counter() - start,
        "metrics": metrics,
        "traceback": None,
    }


def lost_outcome(seed: int, status: str, message: str) -> Outcome:
    """The row of an episode whose process died or was killed (no metrics, no wall time)."""
    return {"seed": seed, "status": status, "error": message, "wall_time_s": None, "metrics": {}, "traceback": None}


def _timeout_message(timeout: float) -> str:
    return f"Timeout: the episode ran longer than {timeout:g} s and its process was stopped"


# ----------------------------------------------------------------------------------------------
# Local processes
# ----------------------------------------------------------------------------------------------


def _worker_main(conn: Any, episode_bytes: bytes) -> None:
    """A worker process: load the episode once, then run the seeds the parent sends, one at a time."""
    # Ctrl-C reaches the whole process group: the parent alone decides to stop (unfinished seeds
    # are simply not recorded and run again on resume), so the worker ignores it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        episode = pickle.loads(episode_bytes)
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which stops the sweep
        conn.send(("load_error", f"{type(exc).__name__}: {exc}"))
        return
    conn.send(("ready", os.getpid()))
    while True:
        try:
            seed = conn.recv()
        except (EOFError, OSError):  # the parent went away: exit instead of lingering as an orphan
            return
        if seed is None:
            return
        conn.send(("outcome", run_episode(episode, seed)))


class _Worker:
    def __init__(self, context: Any, episode_bytes: bytes) -> None:
        self.conn, child_conn = context.Pipe(duplex=True)
        self.process = context.Process(target=_worker_main, args=(child_conn, episode_bytes), name="harvest-qp-sweep")
        self.process.start()
        child_conn.close()
        self.seed: int | None = None
        self.started = 0.0
        self.ready = False

    def stop(self, *, kill: bool = False) -> None:
        if kill:
            with contextlib.suppress(Exception):
                self.process.kill()
        elif self.process.is_alive():
            with contextlib.suppress(Exception):
                self.conn.send(None)
        self.process.join(timeout=5.0)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(timeout=5.0)
        with contextlib.suppress(Exception):
            self.conn.close()


def run_local(
    episode: Callable[[int], Mapping[str, Any]],
    seeds: Sequence[int],
    on_outcome: OnOutcome,
    *,
    workers: int,
    episode_timeout: float | None = None,
    log: Callable[[str], None] = lambda _: None,
) -> None:
    """Run ``seeds`` in ``workers`` worker processes, calling ``on_outcome`` as each finishes.

    The parent hands one seed at a time to each idle worker, so it always knows which seed a
    worker is running: a worker that dies (``os._exit``, a segfault, the OOM killer) is recorded
    as that seed's failure and replaced, and the other episodes go on. (``ProcessPoolExecutor``
    cannot do this: one dead worker breaks the whole pool and fails every pending episode.)
    """
    if not seeds:
        return
    episode_bytes = pickle.dumps(episode)
    context = _process_context(episode)
    pending = deque(seeds)
    pool: list[_Worker] = []
    try:
        pool = [_Worker(context, episode_bytes) for _ in range(min(workers, len(seeds)))]
        while pending or any(w.seed is not None for w in pool):
            for worker in pool:
                if worker.ready and worker.seed is None and pending:
                    seed = pending.popleft()
                    try:
                        worker.conn.send(seed)
                    except OSError:  # it died while idle: the seed goes back to the queue
                        pending.appendleft(seed)
                        continue
                    worker.seed, worker.started = seed, time.monotonic()
            waiting = {w.conn: w for w in pool} | {w.process.sentinel: w for w in pool}
            ready = wait_for(list(waiting), timeout=_poll_interval(pool, episode_timeout))
            for worker in {id(waiting[h]): waiting[h] for h in ready}.values():
                _service(worker, on_outcome, log)
            if episode_timeout is not None:
                now = time.monotonic()
                for worker in pool:
                    if worker.seed is not None and now - worker.started > episode_timeout:
                        log(f"seed {worker.seed}: stopped after {episode_timeout:g} s")
                        on_outcome(lost_outcome(worker.seed, STATUS_TIMEOUT, _timeout_message(episode_timeout)))
                        worker.seed = None
                        worker.stop(kill=True)
            alive = []
            for worker in pool:
                if worker.process.is_alive():
                    alive.append(worker)
                    continue
                if worker.seed is not None or not worker.ready:  # died after the wait above returned
                    _service(worker, on_outcome, log)
                worker.stop()  # reap it and close its pipe
                if pending:
                    alive.append(_Worker(context, episode_bytes))
            pool = alive
    finally:  # also on Ctrl-C or an engine error: a worker still running an episode is killed at once
        for worker in pool:
            worker.stop(kill=worker.seed is not None)


def _process_context(episode: Callable[..., Any]) -> Any:
    """Where workers come from: a fork server where the platform has one, else fresh interpreters.

    Never a plain ``fork`` of the caller: the caller may hold MuJoCo, numba or BLAS threads,
    which a fork copies in an undefined state. The fork server is a clean single-threaded
    process started once per Python process (Python 3.14's default on Linux); it imports this
    module and the episode's module once, so a new or replacement worker starts in
    milliseconds instead of re-importing harvest_qp (seconds on a loaded 2-core machine).
    The preload list only takes effect when the server first starts; later sweeps in the
    same process reuse it and import what they need in the worker.
    """
    if "forkserver" not in multiprocessing.get_all_start_methods():  # Windows
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    preload = [__name__]
    module = getattr(getattr(episode, "func", episode), "__module__", None)  # functools.partial -> its function
    if isinstance(module, str) and module not in ("__main__", "__mp_main__", "builtins"):
        preload.append(module)
    context.set_forkserver_preload(preload)
    return context


def _poll_interval(pool: list[_Worker], episode_timeout: float | None) -> float | None:
    if episode_timeout is None:
        return None
    now = time.monotonic()
    left = [episode_timeout - (now - w.started) for w in pool if w.seed is not None]
    return max(0.01, min(left)) if left else None


def _service(worker: _Worker, on_outcome: OnOutcome, log: Callable[[str], None]) -> None:
    """Read what a worker sent, or record that it died."""
    try:
        while worker.conn.poll():
            kind, payload = worker.conn.recv()
            if kind == "ready":
                worker.ready = True
            elif kind == "load_error":
                raise SweepEngineError(
                    f"episode: the worker process could not load the episode function ({payload}); "
                    "it must be a module-level function (or a functools.partial of one) importable "
                    "from a fresh interpreter"
                )
            elif kind == "outcome":
                worker.seed = None
                on_outcome(payload)
        if worker.process.is_alive():
            return
    except (EOFError, OSError):
        pass  # the pipe closed: the process is dead or dying
    worker.process.join(timeout=5.0)
    if worker.seed is not None:
        log(f"seed {worker.seed}: worker process died (exit code {worker.process.exitcode})")
        on_outcome(lost_outcome(worker.seed, STATUS_DIED, WORKER_DIED_MESSAGE))
        worker.seed = None
    elif not worker.ready:
        raise SweepEngineError(
            f"a sweep worker process exited while starting (exit code {worker.process.exitcode}); "
            "see the messages above on stderr"
        )


# ----------------------------------------------------------------------------------------------
# Ray
# ----------------------------------------------------------------------------------------------

#: One token per driver process: Ray caches the token it loaded, so a second local instance in
#: the same process must be started with the same one.
_LOCAL_RAY_TOKEN = secrets.token_hex(32)


def import_ray() -> Any:
    """``ray``, or :class:`MissingDependencyError` naming the fix."""
    try:
        import ray
    except ImportError as exc:
        raise MissingDependencyError(
            f"engine='ray' needs Ray, which is not installed ({exc}); install the cluster extra: "
            "pip install -e \".[cluster]\" (or pip install 'ray>=2.60')"
        ) from exc
    return ray


@contextlib.contextmanager
def _scoped_environ(changes: Mapping[str, str]) -> Iterator[None]:
    """Set environment variables for the block (Ray's local processes inherit them), then restore them."""
    watched = set(changes) | {"RAY_AUTH_MODE"}  # ray.init sets RAY_AUTH_MODE=token in this process
    saved = {name: os.environ.get(name) for name in watched}
    os.environ.update(changes)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


@contextlib.contextmanager
def ray_session(
    *, workers: int | None, address: str | None, init_kwargs: Mapping[str, Any] | None = None
) -> Iterator[Any]:
    """A connected Ray, shut down afterwards (unless the caller had already connected one).

    Without ``address``: a private local instance with ``workers`` CPUs, no dashboard, its
    session files in a temporary folder that is removed afterwards, and a random
    authentication token passed through the environment (so nothing is written to
    ``~/.ray``); no Ray process outlives the sweep. Its workers get the driver's
    ``sys.path``, so episodes defined in modules the driver can import (tests, scripts)
    load there too.

    With ``address`` (``HOST:PORT`` of a running cluster's head, or ``auto``): the cluster's
    own token settings apply (``RAY_AUTH_TOKEN`` or ``~/.ray/auth_token``), and every node
    must have the same harvest_qp (and the episode's module) installed.
    """
    ray = import_ray()
    if ray.is_initialized():
        yield ray
        return
    kwargs: dict[str, Any] = dict(init_kwargs or {})
    if address:
        try:
            ray.init(address=address, **kwargs)
        except Exception as exc:
            raise SweepEngineError(_connect_error_message(address, exc)) from exc
        try:
            yield ray
        finally:
            ray.shutdown()
        return
    temp_dir = tempfile.mkdtemp(prefix="hqray-")  # short: Ray's socket paths must fit in 107 bytes
    env = {"PYTHONPATH": os.pathsep.join(p for p in sys.path if p and os.path.isdir(p))}
    if "RAY_AUTH_TOKEN" not in os.environ and "RAY_AUTH_TOKEN_PATH" not in os.environ:
        env["RAY_AUTH_TOKEN"] = _LOCAL_RAY_TOKEN
    kwargs.setdefault("num_cpus", workers or os.cpu_count() or 1)
    kwargs.setdefault("include_dashboard", False)
    kwargs.setdefault("_temp_dir", temp_dir)
    try:
        with _scoped_environ(env):
            try:
                ray.init(**kwargs)
            except Exception as exc:
                with contextlib.suppress(Exception):
                    ray.shutdown()
                raise SweepEngineError(f"engine='ray': could not start a local Ray instance: {exc}") from exc
            try:
                yield ray
            finally:
                ray.shutdown()
    finally:
        shutil.rmtree(temp_dir, ignore_errors=True)


def _connect_error_message(address: str, exc: BaseException) -> str:
    """Why ``ray.init(address=...)`` failed, with the fix for the common case of token authentication."""
    causes = [exc]
    while causes[-1].__cause__ is not None and len(causes) < 5:
        causes.append(causes[-1].__cause__)
    text = " <- ".join(str(c).strip().splitlines()[0] if str(c).strip() else type(c).__name__ for c in causes)
    message = f"address: cannot connect to the Ray cluster at {address!r}: {text}"
    if any("InvalidAuthToken" in str(c) or type(c).__name__ == "AuthenticationError" for c in causes):
        message += (
            ". The cluster uses token authentication and Ray turns it on by itself only for address='auto': "
            "set RAY_AUTH_MODE=token and RAY_AUTH_TOKEN (or ~/.ray/auth_token) to the cluster's token"
        )
    elif "Failed to connect" in text:
        message += ". Use the address `ray start --head` printed (the node's IP, which may not be 127.0.0.1)"
    return message


def run_ray(
    episode: Callable[[int], Mapping[str, Any]],
    seeds: Sequence[int],
    on_outcome: OnOutcome,
    *,
    workers: int | None = None,
    address: str | None = None,
    episode_timeout: float | None = None,
    init_kwargs: Mapping[str, Any] | None = None,
    log: Callable[[str], None] = lambda _: None,
) -> None:
    """Run ``seeds`` as Ray tasks (one CPU each, never retried), calling ``on_outcome`` as each finishes.

    ``workers`` caps the tasks in flight (on a cluster: how many CPUs the sweep may take);
    without it, the cluster's CPU count when the sweep starts. ``episode_timeout`` counts from a
    task's submission, which is then close to its start (plus a worker's start-up on first use).
    A task whose worker dies is recorded like a dead local worker. Retries are off
    (``max_retries=0``): a seed that kills its worker would do it again.
    """
    if not seeds:
        return
    with ray_session(workers=workers, address=address, init_kwargs=init_kwargs) as ray:
        task = ray.remote(num_cpus=1, max_retries=0)(run_episode)
        episode_ref = ray.put(episode)
        pending = deque(seeds)
        in_flight: dict[Any, tuple[int, float]] = {}
        # No more tasks in flight than CPUs: a queued task would otherwise use up its timeout waiting.
        limit = workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
        while pending or in_flight:
            while pending and len(in_flight) < limit:
                seed = pending.popleft()
                in_flight[task.remote(episode_ref, seed)] = (seed, time.monotonic())
            timeout = None
            if episode_timeout is not None:
                oldest = min(started for _, started in in_flight.values())
                timeout = max(0.01, episode_timeout - (time.monotonic() - oldest))
            done, _ = ray.wait(list(in_flight), num_returns=1, timeout=timeout)
            for ref in done:
                seed, _ = in_flight.pop(ref)
                on_outcome(_ray_outcome(ray, ref, seed, log))
            if episode_timeout is not None:
                now = time.monotonic()
                for ref, (seed, started) in list(in_flight.items()):
                    if now - started > episode_timeout:
                        with contextlib.suppress(Exception):
                            ray.cancel(ref, force=True)
                        del in_flight[ref]
                        log(f"seed {seed}: stopped after {episode_timeout:g} s")
                        on_outcome(lost_outcome(seed, STATUS_TIMEOUT, _timeout_message(episode_timeout)))


def _ray_outcome(ray: Any, ref: Any, seed: int, log: Callable[[str], None]) -> Outcome:
    try:
        return ray.get(ref)
    except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError, ray.exceptions.LocalRayletDiedError):
        log(f"seed {seed}: Ray worker died")
        return lost_outcome(seed, STATUS_DIED, WORKER_DIED_MESSAGE)
    except ray.exceptions.RayTaskError as exc:
        # run_episode catches the episode's exceptions; this is Ray failing to run it at all,
        # e.g. the episode's module is missing on the node.
        raise SweepEngineError(f"engine='ray': a task failed outside the episode (seed {seed}): {exc}") from exc
    except ray.exceptions.RayError as exc:
        log(f"seed {seed}: Ray lost the task ({type(exc).__name__})")
        return lost_outcome(seed, STATUS_DIED, WORKER_DIED_MESSAGE)


def default_workers() -> int:
    """CPUs this process may use (``sched_getaffinity`` where it exists)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return max(1, os.cpu_count() or 1)


__all__ = [
    "MissingDependencyError",
    "SweepEngineError",
    "WORKER_DIED_MESSAGE",
    "default_workers",
    "import_ray",
    "lost_outcome",
    "ray_session",
    "run_episode",
    "run_local",
    "run_ray",
]
