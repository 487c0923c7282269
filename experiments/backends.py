"""Where the runs of a sweep execute: in this process, one after another, or as Ray tasks.

A backend takes :class:`Task` objects (a label, the resources one run needs and the item its
work function takes) and the work function, and yields one :class:`Outcome` per task as each
completes: the work's result, or a :class:`Failure` saying what went wrong. Both backends call
the work through the same wrapper (:func:`attempt`), so an exception inside a run is reported
the same way wherever it ran, and the rest of the sweep goes on.

:class:`SequentialBackend` runs the tasks in order in this process, as the runner always did.
:class:`RayBackend` submits every task at once to a Ray cluster -- a local one it starts, or
one it joins (``address="auto"`` or ``"ray://host:port"``) -- each declaring its CPUs (and a
GPU where its config asks for ``device=cuda``); inside a task torch uses as many threads as
the task has CPUs, so tasks sharing a machine do not oversubscribe its cores. A task whose
worker process dies is retried ``max_retries`` times, then reported; an exception raised by
the run itself is reported at once (rerunning the same config would raise it again). Ray is
optional (``pip install .[distributed]``): :func:`make_backend` says so when it is missing.
"""

from __future__ import annotations

import os
import pickle
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Generic, TypeVar

from motion.cli import one_line

__all__ = [
    "BACKENDS",
    "Backend",
    "BackendUnavailable",
    "Failure",
    "Outcome",
    "RayBackend",
    "SequentialBackend",
    "Task",
    "attempt",
    "make_backend",
]

W = TypeVar("W")  # the item a work function takes
R = TypeVar("R")  # what it returns

#: the values of ``--backend``
BACKENDS = ("sequential", "ray")
INSTALL_HINT = "pip install .[distributed]"


class BackendUnavailable(ValueError):
    """A backend that cannot run here (Ray not installed); the message says how to fix it."""


@dataclass(frozen=True)
class Task(Generic[W]):
    """One unit of a sweep: ``item`` is what the work function takes; ``index`` its place in
    the sweep (tables keep that order whatever order the tasks finish in); ``label`` names it
    in progress and errors; ``num_cpus`` / ``num_gpus`` what it asks of a Ray cluster (torch
    threads inside the task = ``num_cpus``; the sequential backend ignores both)."""

    index: int
    label: str
    item: W
    num_cpus: int = 1
    num_gpus: int = 0


@dataclass(frozen=True)
class Failure:
    """Why a task gave no result. ``summary``: one line (``ValueError: ...``, or ``the worker
    died: ...``); ``traceback``: the text of the traceback inside the run ("" when the worker
    died); ``exception``: the exception the run raised, when it could travel back (``None``
    when the worker died or the exception does not pickle)."""

    summary: str
    traceback: str = ""
    exception: BaseException | None = None
    worker_died: bool = False


@dataclass(frozen=True)
class Outcome(Generic[R]):
    """A finished task: ``result`` or ``failure`` (exactly one is set) and ``seconds``, the
    wall time of the work where it ran (0 when the worker died)."""

    task: Task
    result: R | None
    failure: Failure | None
    seconds: float


@dataclass(frozen=True)
class _Attempt(Generic[R]):
    result: R | None
    failure: Failure | None
    seconds: float


def attempt(work: Callable[[W], R], item: W, portable: bool = False) -> _Attempt[R]:
    """``work(item)``, timed, with an ``Exception`` it raises caught as a :class:`Failure`
    (``KeyboardInterrupt`` and ``SystemExit`` go through). ``portable``: the attempt is sent
    to another process, so an exception that does not pickle is left out (its summary and
    traceback still say what it was)."""
    start = time.perf_counter()
    try:
        result = work(item)
    except Exception as err:
        exception: BaseException | None = err
        if portable:
            try:
                pickle.loads(pickle.dumps(err))
            except Exception:
                exception = None
        failure = Failure(
            f"{type(err).__name__}: {one_line(err)}", traceback.format_exc(), exception
        )
        return _Attempt(None, failure, time.perf_counter() - start)
    return _Attempt(result, None, time.perf_counter() - start)


class Backend:
    """Runs tasks and yields their outcomes as they complete (a context manager: entering
    it connects to whatever runs the tasks, leaving it lets go)."""

    name = "backend"

    def __enter__(self) -> Backend:
        return self

    def __exit__(self, *exc) -> None:
        return None

    def slots(self, task: Task | None = None) -> int:
        """How many tasks like ``task`` run at once (an estimate on a cluster)."""
        return 1

    def run(self, tasks: Sequence[Task[W]], work: Callable[[W], R]) -> Iterator[Outcome[R]]:
        """One :class:`Outcome` per task, in the order they complete."""
        raise NotImplementedError


class SequentialBackend(Backend):
    """The tasks one after another in this process (its torch threads left as they are)."""

    name = "sequential"

    def run(self, tasks: Sequence[Task[W]], work: Callable[[W], R]) -> Iterator[Outcome[R]]:
        for task in tasks:
            done = attempt(work, task.item)
            yield Outcome(task, done.result, done.failure, done.seconds)


def _import_ray():
    try:
        import ray
    except ImportError as err:
        raise BackendUnavailable(
            f"--backend ray needs Ray, which is not installed ({one_line(err)}); "
            f"install it with: {INSTALL_HINT}"
        ) from None
    return ray


def _ray_task(work: Callable[[W], R], item: W, num_cpus: int, workdir: str) -> _Attempt[R]:
    """The body of a Ray task: torch threads = the task's CPUs; the driver's working folder
    when this machine has it (configs name files relative to it); then :func:`attempt`."""
    import torch

    from motion.runtime import retain_freed_memory

    torch.set_num_threads(max(1, num_cpus))
    retain_freed_memory()  # what the command line does in its own process
    if workdir and os.path.isdir(workdir):
        os.chdir(workdir)
    return attempt(work, item, portable=True)


class RayBackend(Backend):
    """The tasks on a Ray cluster, all submitted at once; outcomes as they complete.

    ``address``: ``None`` starts a local Ray on this machine (``num_cpus`` CPUs, default all
    of them) and stops it on leaving; ``"auto"`` joins the cluster this machine belongs to,
    ``"ray://host:port"`` one through Ray Client. Already connected (``ray.init`` called by
    the caller, e.g. a test fixture), it uses that connection and leaves it open.
    ``max_retries``: how many times a task whose worker process dies is rerun before it is
    reported as failed.
    """

    name = "ray"

    def __init__(self, address: str | None = None, num_cpus: int | None = None, max_retries=1):
        self.address, self.num_cpus, self.max_retries = address, num_cpus, max_retries
        self._ray = _import_ray()
        self._started = False

    def __enter__(self) -> RayBackend:
        ray = self._ray
        if not ray.is_initialized():
            if self.address is None:  # "local": never attach to a cluster by accident
                ray.init(address="local", num_cpus=self.num_cpus, include_dashboard=False)
            else:
                ray.init(address=self.address)
            self._started = True
        return self

    def __exit__(self, *exc) -> None:
        if self._started:
            self._ray.shutdown()
            self._started = False

    def _resources(self) -> dict[str, float]:
        return self._ray.cluster_resources()

    def slots(self, task: Task | None = None) -> int:
        cpus = self._resources().get("CPU", 1.0)
        return max(1, int(cpus // max(1, task.num_cpus if task else 1)))

    def _unfit(self, task: Task) -> Failure | None:
        """Why the cluster we started can never run ``task`` (a joined cluster may grow)."""
        if not self._started or self.address is not None:
            return None
        have = self._resources()
        for what, need in (("CPU", task.num_cpus), ("GPU", task.num_gpus)):
            if need > have.get(what, 0.0):
                return Failure(
                    f"the task asks for {need} {what}(s); the local Ray has "
                    f"{have.get(what, 0.0):g} (a GPU is asked for by device=cuda)"
                )
        return None

    def _died(self, err: Exception) -> Failure:
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        tries = f" (ran {self.max_retries + 1} times)" if self.max_retries else ""
        return Failure(
            f"the worker died{tries}: {type(err).__name__}: {' '.join(first.split())}",
            worker_died=True,
        )

    def run(self, tasks: Sequence[Task[W]], work: Callable[[W], R]) -> Iterator[Outcome[R]]:
        ray = self._ray
        remote = ray.remote(_ray_task)
        workdir = os.getcwd()
        pending = {}
        for task in tasks:
            unfit = self._unfit(task)
            if unfit is not None:
                yield Outcome(task, None, unfit, 0.0)
                continue
            ref = remote.options(
                num_cpus=task.num_cpus,
                num_gpus=task.num_gpus,
                max_retries=self.max_retries,
                retry_exceptions=False,
                name=task.label,
            ).remote(work, task.item, task.num_cpus, workdir)
            pending[ref] = task
        try:
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                for ref in ready:
                    task = pending.pop(ref)
                    try:
                        done = ray.get(ref)
                    except ray.exceptions.RayError as err:  # the worker or its node died
                        yield Outcome(task, None, self._died(err), 0.0)
                        continue
                    yield Outcome(task, done.result, done.failure, done.seconds)
        finally:  # interrupted (Ctrl-C) or abandoned: do not leave tasks running on a cluster
            for ref in pending:
                try:
                    ray.cancel(ref, force=True)
                except Exception:  # already finished, or the connection is gone
                    pass


def make_backend(name: str, address: str | None = None, num_cpus: int | None = None) -> Backend:
    """The backend called ``name`` (one of :data:`BACKENDS`). Raises
    :class:`BackendUnavailable` for ``ray`` without Ray installed, ``ValueError`` for an
    unknown name or an ``address`` given to the sequential backend."""
    if name == "ray":
        return RayBackend(address, num_cpus)
    if name == "sequential":
        if address is not None:
            raise ValueError(f"--address {address}: only with --backend ray")
        return SequentialBackend()
    raise ValueError(f"--backend must be one of {', '.join(BACKENDS)}; got {name!r}")
