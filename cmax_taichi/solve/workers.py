"""The local engine of :mod:`cmax_taichi.solve.batch`: long-lived worker processes that die with their
driver, and a driver that knows which task each worker holds.

Why not :class:`concurrent.futures.ProcessPoolExecutor`: when one of its processes dies, the executor
breaks and fails every pending task, without saying which task the dead process held. Here each worker
has its own pipe; the driver sends it one task at a time, so a death is charged to the task that worker
held (it is retried up to ``max_restarts`` times) and the others go on, on the surviving workers or on
a fresh one.

Workers are started with ``spawn`` (a fresh interpreter; Taichi does not survive ``fork``). Each
worker asks the kernel to kill it when its parent dies (``prctl(PR_SET_PDEATHSIG, SIGKILL)`` on Linux)
and also watches its parent from a thread (every 0.5 s, for the other systems): a driver killed with
SIGKILL leaves no worker behind. Workers ignore SIGINT: on Ctrl-C (which reaches the whole process
group) the driver decides, and stops them.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection, wait
from typing import Any

__all__ = ["die_with_parent", "run_ray", "run_tasks"]

_PR_SET_PDEATHSIG = 1
_STOP_SECONDS = 5.0  # how long a worker gets to leave after it is told to


def die_with_parent(parent_pid: int) -> None:
    """Make this process end when the process ``parent_pid`` (its parent) ends, however it ends."""
    with contextlib.suppress(OSError, AttributeError, TypeError):
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent_pid:  # the parent died before the request: go now
        os._exit(1)

    def watch() -> None:
        while True:
            time.sleep(0.5)
            if os.getppid() != parent_pid:
                os._exit(1)

    threading.Thread(target=watch, name="cmax-taichi parent watch", daemon=True).start()


class _Stopped(BaseException):
    """SIGTERM in a worker (the driver's :meth:`_Worker.stop` of a busy worker)."""


def _raise_stopped(signum, frame) -> None:
    raise _Stopped()


def _worker_main(conn: Connection, parent_pid: int, make: Callable[[], Any]) -> None:
    """A worker: ``make()`` builds its state once (Taichi, kernels); then ``(i, call, args, kwargs)``
    tasks are run as ``call(state, *args, **kwargs)`` and answered ``(i, result)``.

    SIGTERM unwinds the worker instead of ending it where it stands: a checkpoint being written
    (``outputs.atomic_path``) removes its temporary file, and the worker ends quietly with exit code
    143. SIGTERM's default action left a ``.checkpoint.json.*.tmp`` in ``OUT`` when the driver's stop
    hit a worker between creating it and renaming it (2 of 4 SIGTERMs of a two-worker batch here)."""
    die_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _raise_stopped)
    try:
        _serve(conn, make)
    except _Stopped:
        sys.exit(128 + signal.SIGTERM)


def _serve(conn: Connection, make: Callable[[], Any]) -> None:
    try:
        state = make()
    except Exception as exc:  # e.g. a plugin that fails in a fresh interpreter: said, not a silent death
        conn.send(("failed", f"{type(exc).__name__}: {exc}"))
        return
    conn.send(("ready", os.getpid()))  # tasks come only after this: a death before is a start-up failure
    while True:
        try:
            task = conn.recv()
        except (EOFError, OSError):
            return
        if task is None:
            return
        i, call, args, kwargs = task
        try:
            answer = (i, call(state, *args, **kwargs), None)
        except Exception as exc:  # a task's own error is its answer
            answer = (i, None, f"{type(exc).__name__}: {exc}")
        conn.send(answer)


class _Worker:
    def __init__(self, context, make: Callable[[], Any]) -> None:
        self.conn, child = context.Pipe()
        self.process = context.Process(
            target=_worker_main, args=(child, os.getpid(), make), name="cmax-taichi batch worker", daemon=True
        )
        self.process.start()
        child.close()
        self.task: int | None = None
        self.ready = False  # its state is built: it takes tasks

    def stop(self) -> None:
        """Ask the worker to leave; terminate it (then kill it) if it does not."""
        with contextlib.suppress(OSError, BrokenPipeError):
            self.conn.send(None)
        self.process.join(_STOP_SECONDS if self.task is None else 0.1)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(_STOP_SECONDS)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        self.conn.close()


def run_tasks(
    tasks: Sequence[tuple[Callable, tuple, dict]],
    workers: int,
    make: Callable[[], Any],
    max_restarts: int,
    on_poll: Callable[[int], None] = lambda done: None,
    failed: Callable[[int, str], Any] = lambda i, error: error,
) -> dict[int, Any]:
    """Run ``tasks`` (``(call, args, kwargs)``, ``call(state, *args, **kwargs)``) on ``workers`` spawned
    processes; returns ``{task index: result}``.

    A task whose worker dies is retried on a fresh worker up to ``max_restarts`` times, then answered
    ``failed(i, error)``; the death of a worker charges only the task it held. A task that raises is
    answered ``failed(i, error)`` at once. ``make`` (picklable) builds each worker's state; when it
    raises (a plugin that fails in a fresh interpreter), every task left is answered with that error.
    ``on_poll(done)`` runs about twice a second (progress). On any exit (an error, KeyboardInterrupt,
    SystemExit), every worker is stopped before this returns or raises.
    """
    context = multiprocessing.get_context("spawn")
    queue = deque(range(len(tasks)))
    deaths = [0] * len(tasks)
    results: dict[int, Any] = {}
    pool: list[_Worker] = []
    idle_deaths = 0  # workers that died holding no task (e.g. at start-up)
    try:
        while len(results) < len(tasks):
            while queue and len(pool) < min(workers, len(tasks) - len(results)):
                pool.append(_Worker(context, make))
            for worker in pool:
                if worker.ready and worker.task is None and queue:
                    i = queue.popleft()
                    call, args, kwargs = tasks[i]
                    try:
                        worker.conn.send((i, call, args, kwargs))
                    except (OSError, BrokenPipeError):  # the worker is gone: it is replaced below
                        queue.appendleft(i)
                        continue
                    except Exception as exc:  # arguments that do not pickle
                        results[i] = failed(i, f"{type(exc).__name__}: {exc}")
                        continue
                    worker.task = i
            ready = set(wait([w.conn for w in pool] + [w.process.sentinel for w in pool], timeout=0.5))
            for worker in list(pool):
                answered = False
                if worker.conn in ready or worker.process.sentinel in ready:
                    try:
                        if worker.conn.poll():
                            message = worker.conn.recv()
                            if message[0] == "ready":
                                worker.ready = answered = True
                            elif message[0] == "failed":  # its state could not be built: nor will the next's
                                for i in list(queue):
                                    results[i] = failed(i, f"the worker could not start: {message[1]}")
                                queue.clear()
                                answered = True
                            else:
                                i, value, error = message
                                results[i] = value if error is None else failed(i, error)
                                worker.task, answered = None, True
                    except (EOFError, OSError):
                        pass
                if answered or worker.process.is_alive():
                    continue
                pool.remove(worker)  # dead: charge its task, if it held one
                worker.stop()
                code = worker.process.exitcode
                if worker.task is None:
                    idle_deaths += 0 if worker.ready else 1
                    if idle_deaths > max_restarts + 2:  # they die at start-up: no task can run
                        error = (
                            f"worker processes die at start-up (exit code {code}; a script that calls "
                            "batch.run must guard its entry point with if __name__ == '__main__':)"
                        )
                        for i in list(queue):
                            results[i] = failed(i, error)
                        queue.clear()
                    continue
                i = worker.task
                deaths[i] += 1
                if deaths[i] > max_restarts:
                    error = f"worker process died {deaths[i]} time(s) on it (exit code {code})"
                    results[i] = failed(i, f"{error}; max_restarts={max_restarts}")
                else:
                    queue.appendleft(i)  # resumes from its checkpoint on a fresh worker
            on_poll(len(results))
    finally:
        for worker in pool:
            worker.stop()
    return results


def run_ray(
    tasks: Sequence[tuple[tuple, dict]],
    workers: int,
    worker_class: type,
    worker_args: tuple,
    max_restarts: int,
    address: str | None,
    on_poll: Callable[[int], None] = lambda done: None,
    failed: Callable[[int, str], Any] = lambda i, error: error,
) -> dict[int, Any]:
    """Run ``tasks`` (``(args, kwargs)`` of ``worker_class.estimate``) on ``workers`` Ray actors of
    ``worker_class(*worker_args)``; returns ``{task index: result}``.

    Ray restarts a dead actor and retries its task (``max_restarts``, ``max_task_retries``); when they
    are used up, that task is answered ``failed(i, error)`` and a fresh actor takes the next ones. The
    actors are owned by this driver (not detached): Ray ends them when the driver ends, however it ends.
    Without ``address`` (and ``$RAY_ADDRESS``) a local Ray instance with ``workers`` CPUs is started and
    shut down at the end.
    """
    try:
        import ray
    except ImportError:
        raise ImportError(
            'engine="ray" needs Ray: pip install "cmax-taichi[ray]" (or pip install ray)'
        ) from None

    started = False
    if not ray.is_initialized():
        if address is None and not os.environ.get("RAY_ADDRESS"):
            # a new local instance sized to the workers, even when a cluster runs on this machine
            ray.init(address="local", num_cpus=workers, include_dashboard=False, log_to_driver=False)
        else:  # the given cluster (or $RAY_ADDRESS, as ray.init reads it)
            ray.init(address=address, log_to_driver=False)
        started = True
    try:
        actor_class = ray.remote(num_cpus=1, max_restarts=max_restarts, max_task_retries=max_restarts)(
            worker_class
        )
        actors = [actor_class.remote(*worker_args) for _ in range(min(workers, len(tasks)))]
        queue = list(range(len(tasks)))
        running: dict[Any, tuple[int, Any]] = {}
        results: dict[int, Any] = {}
        idle = list(actors)
        while queue or running:
            while queue and idle:
                actor = idle.pop()
                i = queue.pop(0)
                args, kwargs = tasks[i]
                running[actor.estimate.remote(*args, **kwargs)] = (i, actor)
            finished, _ = ray.wait(list(running), num_returns=1, timeout=0.5)
            for ref in finished:
                i, actor = running.pop(ref)
                try:
                    results[i] = ray.get(ref)
                    idle.append(actor)
                except ray.exceptions.RayActorError as exc:  # restarts used up: a fresh actor goes on
                    error = f"worker died (after {max_restarts} restarts): {str(exc).splitlines()[0]}"
                    results[i] = failed(i, error)
                    idle.append(actor_class.remote(*worker_args))
                except ray.exceptions.RayError as exc:  # e.g. arguments that do not pickle
                    results[i] = failed(i, f"{type(exc).__name__}: {str(exc).splitlines()[0]}")
                    idle.append(actor)
            on_poll(len(results))
        for actor in idle:  # every actor is idle now (dead ones were replaced)
            ray.kill(actor)
        return results
    finally:
        if started:
            ray.shutdown()
