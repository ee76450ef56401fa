"""Executors that run many (sequence, parameter point) tasks: in-process, a process pool, or Ray.

Each task brings one sequence up to date in one run store. Isolation comes from the run store itself:
the per-sequence lock refuses two writers of the same ``runs/<seq>``, stages write into temporary
folders renamed into place, so a killed worker leaves the previous result and the next run cleans up.
A failing task reports its error and the others finish.
"""

from __future__ import annotations

import importlib
import os
import signal
import sys
import time
import traceback
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from multiprocessing import get_context
from multiprocessing.connection import wait as mp_wait
from pathlib import Path
from typing import Any

from rich.console import Console

from core.errors import UserError
from pipeline.config import Overrides, load_workflow
from pipeline.runner import Runner, StageOutcome, StagesFailed
from pipeline.sequences import SequenceInfo

EXECUTORS = ("local", "ray")


@dataclass(frozen=True)
class RunTask:
    """Bring ``targets`` of one sequence up to date in ``runs_dir``."""

    seq: SequenceInfo
    runs_dir: str
    targets: tuple[str, ...] = ("all",)
    force: tuple[str, ...] = ()
    overrides: Overrides = field(default_factory=dict)
    workflow: str = "default"
    #: other run stores whose results with matching keys may be reused (hard links) instead of rerun
    reuse_from: tuple[str, ...] = ()
    label: str = ""
    #: ``module:function`` returning the stage registry (tests and plugins use their own)
    registry: str = "pipeline.registry:load_stages"

    @property
    def name(self) -> str:
        return self.label or self.seq.name


@dataclass
class TaskResult:
    name: str
    seq: str
    runs_dir: str
    ok: bool
    outcomes: list[StageOutcome] = field(default_factory=list)
    error: str | None = None
    #: "user" (exit code 2) or "bug" (exit code 1)
    error_kind: str | None = None
    seconds: float = 0.0
    worker: str = ""


def run_task(task: RunTask, console: Console | None = None) -> TaskResult:
    """Execute one task; never raises for stage errors (they are returned in the result)."""
    t0 = time.perf_counter()
    worker = f"pid {os.getpid()}"
    try:
        module, _, func = task.registry.partition(":")
        registry = getattr(importlib.import_module(module), func)()
        runner = Runner(task.seq, Path(task.runs_dir), registry, load_workflow(task.workflow),
                        task.overrides, console or Console(stderr=True, quiet=True),
                        reuse_from=[Path(p) for p in task.reuse_from])
        outcomes = runner.run(task.targets, force=task.force)
        return TaskResult(task.name, task.seq.name, task.runs_dir, True, outcomes,
                          seconds=time.perf_counter() - t0, worker=worker)
    except StagesFailed as exc:
        kind = "user" if exc.user_error else "bug"
        detail = str(exc) if exc.user_error else f"{exc}\n" + "".join(traceback.format_exception(exc.first, limit=8))
        for o in exc.outcomes:
            o.error = None  # exceptions stay in the worker; the message travels
        return TaskResult(task.name, task.seq.name, task.runs_dir, False, exc.outcomes, error=detail,
                          error_kind=kind, seconds=time.perf_counter() - t0, worker=worker)
    except UserError as exc:
        return TaskResult(task.name, task.seq.name, task.runs_dir, False, error=str(exc), error_kind="user",
                          seconds=time.perf_counter() - t0, worker=worker)
    except Exception as exc:  # a bug in a stage: keep the traceback for the report
        tb = traceback.format_exc(limit=8)
        return TaskResult(task.name, task.seq.name, task.runs_dir, False, error=f"{exc!r}\n{tb}", error_kind="bug",
                          seconds=time.perf_counter() - t0, worker=worker)


ProgressFn = Callable[[TaskResult], None]


class Executor:
    """Maps :func:`run_task` over tasks; results come back in task order."""

    name = "inline"

    def run(self, tasks: Sequence[RunTask], on_done: ProgressFn | None = None) -> list[TaskResult]:
        results = []
        for task in tasks:
            res = run_task(task)
            if on_done:
                on_done(res)
            results.append(res)
        return results

    def close(self) -> None:
        pass


class LocalExecutor(Executor):
    """One spawned process per task, at most ``workers`` at a time.

    A process per task (rather than a shared pool) means a worker that dies (killed, out of memory)
    fails only its own task; the others finish.
    """

    name = "local"

    def __init__(self, workers: int | None = None, threads_per_worker: int | None = None) -> None:
        self.workers = max(1, workers or (os.cpu_count() or 1))
        #: BLAS / OpenMP threads in each worker: the cores shared out, so that parallel sequences do not
        #: oversubscribe the machine (each library would otherwise start one thread per core)
        self.threads = threads_per_worker or max(1, (os.cpu_count() or 1) // self.workers)

    def run(self, tasks: Sequence[RunTask], on_done: ProgressFn | None = None) -> list[TaskResult]:
        if self.workers == 1 or len(tasks) <= 1:
            return super().run(tasks, on_done)
        ctx = get_context("spawn")
        results: dict[int, TaskResult] = {}
        running: dict[int, tuple[Any, Any]] = {}  # index -> (process, receiving end)
        queue = list(enumerate(tasks))
        try:
            while queue or running:
                while queue and len(running) < self.workers:
                    i, task = queue.pop(0)
                    recv, send = ctx.Pipe(duplex=False)
                    proc = ctx.Process(target=_child, args=(task, send, self.threads),
                                       name=f"radar-pipeline:{task.name}")
                    running[i] = (proc, recv)
                    proc.start()
                    send.close()
                ready = mp_wait([proc.sentinel for proc, _ in running.values()])
                for i, (proc, recv) in list(running.items()):
                    if proc.sentinel not in ready:
                        continue
                    proc.join()
                    res = _receive(tasks[i], proc, recv)
                    del running[i]
                    results[i] = res
                    if on_done:
                        on_done(res)
        except KeyboardInterrupt:
            _stop(proc for proc, _ in running.values())
            raise
        return [results[i] for i in range(len(tasks))]


#: seconds a worker gets, after it is told to stop, to remove its temporary folder before it is killed
STOP_GRACE_S = 30.0


def _receive(task: RunTask, proc: Any, recv: Any) -> TaskResult:
    try:
        res: TaskResult | None = recv.recv() if recv.poll() else None
    except (EOFError, OSError):
        res = None
    recv.close()
    if res is None:
        code = proc.exitcode
        why = f"signal {-code}" if code is not None and code < 0 else f"exit code {code}"
        res = TaskResult(task.name, task.seq.name, task.runs_dir, False, error=f"worker died ({why})",
                         error_kind="bug", worker=f"pid {proc.pid}")
    return res


def _stop(procs: Iterable[Any]) -> None:
    """Ctrl-C in the driver: tell each worker to stop (SIGTERM, which a worker turns into KeyboardInterrupt, so
    the running stage removes its temporary folder and keeps its previous result) and wait for it."""
    procs = [p for p in procs if p.pid is not None]
    for proc in procs:
        if proc.is_alive():
            proc.terminate()
    deadline = time.monotonic() + STOP_GRACE_S
    for proc in procs:
        proc.join(max(0.0, deadline - time.monotonic()))
        if proc.is_alive():
            proc.kill()
            proc.join()


def _raise_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def _child(task: RunTask, conn: Any, threads: int = 0) -> None:
    from core.stage import blas_threads

    # Ctrl-C reaches the whole process group: the driver alone decides, and stops workers with SIGTERM
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _raise_interrupt)
    if threads > 0:  # libraries loaded from here on read these; those already loaded are limited below
        for var in THREAD_VARIABLES:
            os.environ[var] = str(threads)
    try:
        with blas_threads(threads):
            result = run_task(task)
    except KeyboardInterrupt:  # stopped by the driver: the runner has already cleaned up
        conn.close()
        sys.exit(130)
    conn.send(result)
    conn.close()


class RayExecutor(Executor):
    """Ray tasks, on an existing cluster (``address``) or a local instance started here.

    On a multi-node cluster every node must see the same ``runs/`` (shared storage) and the same data
    (``$COLORADAR_ROOT``, ``$RADAR_PIPELINE_CACHE``); see README.
    """

    name = "ray"

    def __init__(self, address: str | None = None, workers: int | None = None) -> None:
        try:
            import ray
        except ImportError:
            raise UserError("--executor ray needs Ray, not installed (the 'distributed' extra: pip install -e "
                            "'.[distributed]')") from None
        self.ray = ray
        self._started = False
        if not ray.is_initialized():
            kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
            if address:
                kwargs["address"] = address
            else:
                kwargs["num_cpus"] = workers or os.cpu_count() or 1
            # run workers from the same source tree and environment as this driver
            kwargs["runtime_env"] = {"env_vars": {k: v for k, v in os.environ.items()
                                                  if k.startswith(("RADAR_PIPELINE", "COLORADAR"))}}
            try:
                ray.init(**kwargs)
            except ConnectionError as exc:
                raise UserError(f"--ray-address {address}: cannot connect ({exc}); is the cluster up?") from None
            self._started = True

    def run(self, tasks: Sequence[RunTask], on_done: ProgressFn | None = None) -> list[TaskResult]:
        ray = self.ray
        remote = ray.remote(num_cpus=1, max_retries=0)(run_task)
        refs = {remote.remote(t): i for i, t in enumerate(tasks)}
        results: dict[int, TaskResult] = {}
        pending = list(refs)
        try:
            self._wait(tasks, refs, pending, results, on_done)
        except KeyboardInterrupt:
            for ref in pending:  # a cancelled task gets KeyboardInterrupt: its stage keeps its previous result
                ray.cancel(ref)
            raise
        return [results[i] for i in range(len(tasks))]

    def _wait(self, tasks: Sequence[RunTask], refs: dict[Any, int], pending: list[Any],
              results: dict[int, TaskResult], on_done: ProgressFn | None) -> None:
        ray = self.ray
        while pending:
            done, rest = ray.wait(pending, num_returns=1)
            pending[:] = rest
            for ref in done:
                i = refs[ref]
                try:
                    res = ray.get(ref)
                except Exception as exc:  # worker crashed
                    t = tasks[i]
                    res = TaskResult(t.name, t.seq.name, t.runs_dir, False, error=f"worker died: {exc!r}",
                                     error_kind="bug")
                results[i] = res
                if on_done:
                    on_done(res)

    def close(self) -> None:
        if self._started:
            self.ray.shutdown()


def make_executor(kind: str, workers: int | None = None, address: str | None = None) -> Executor:
    if kind == "local":
        return LocalExecutor(workers)
    if kind == "ray":
        return RayExecutor(address, workers)
    from pipeline.config import did_you_mean

    raise UserError(f"--executor {kind}: unknown executor{did_you_mean(kind, EXECUTORS)} (choose local or ray)")


def run_all(tasks: Iterable[RunTask], executor: Executor, on_done: ProgressFn | None = None) -> list[TaskResult]:
    try:
        return executor.run(list(tasks), on_done)
    finally:
        executor.close()
