"""Run independent tasks on a local process pool or on a Ray cluster.

An `Executor` maps a top-level (picklable) function over items and yields ``(item, Outcome)``
in input order; a failing item is reported with its one-line error and the others go on.
`LocalExecutor` uses a ``concurrent.futures.ProcessPoolExecutor`` (spawn start method; one
worker runs in-process), `RayExecutor` Ray tasks (the optional extra
``pip install 'scanguard[scale]'``; ``ray`` is imported only when it is used).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar

from scanguard.errors import ConfigError, ScanGuardError

logger = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")

#: One-line error of ``--executor ray`` without Ray installed.
RAY_MISSING = "--executor ray needs the optional extra: pip install 'scanguard[scale]'"
#: Executor names of ``--executor``.
EXECUTORS = ("local", "ray")


@dataclass(frozen=True)
class Outcome(Generic[R]):
    """What one task gave: its value, or the one-line error it failed with.

    Attributes:
        value: The function's return value (None when it failed).
        error: One-line error message (None when it succeeded).
    """

    value: R | None = None
    error: str | None = None

    @property
    def ok(self) -> bool:
        """Whether the task succeeded."""
        return self.error is None


def error_line(exc: BaseException) -> str:
    """A one-line description of ``exc`` (the message of a `ScanGuardError` as it is)."""
    text = str(exc) if isinstance(exc, ScanGuardError) else f"{type(exc).__name__}: {exc}"
    return " ".join(text.split()) or type(exc).__name__


def _call(fn: Callable[[T], R], item: T) -> Outcome[R]:
    """Run ``fn(item)``; an exception becomes a failed `Outcome` (top-level: spawn-safe)."""
    try:
        return Outcome(value=fn(item))
    except Exception as exc:
        logger.debug("task %r failed", item, exc_info=True)
        return Outcome(error=error_line(exc))


class Executor(Protocol):
    """Runs a function over items; results in input order, failures isolated."""

    def map(self, fn: Callable[[T], R], items: Iterable[T]) -> Iterator[tuple[T, Outcome[R]]]:
        """Yield ``(item, outcome)`` for every item, in input order.

        Args:
            fn: A top-level (picklable) function of one item.
            items: The work items (picklable).
        """
        ...


class LocalExecutor:
    """A local process pool (``workers == 1``: in this process, one item after the other).

    A worker process that dies (killed, out of memory, a crash in native code) breaks the
    pool, and every item still in it with it. Those items are run again, each in a fresh
    process of its own (``workers`` at a time), so a killed worker costs only its own item:
    an item whose own process dies ``retries`` times more is reported as failed.

    Args:
        workers: Worker processes (>= 1).
        retries: Runs in a process of its own for an item hit by a dead worker (>= 0).
    """

    def __init__(self, workers: int = 1, retries: int = 1) -> None:
        if workers < 1:
            raise ConfigError(f"--workers must be >= 1, got {workers}")
        if retries < 0:
            raise ConfigError(f"retries must be >= 0, got {retries}")
        self.workers = workers
        self.retries = retries

    def map(self, fn: Callable[[T], R], items: Iterable[T]) -> Iterator[tuple[T, Outcome[R]]]:
        """See `Executor.map`."""
        todo = list(items)
        if self.workers == 1 or len(todo) <= 1:
            for item in todo:
                yield item, _call(fn, item)
            return
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        ctx = multiprocessing.get_context("spawn")
        done: dict[int, Outcome[R]] = {}
        hit: list[int] = []  # items of a pool that broke
        shown = 0
        with ProcessPoolExecutor(max_workers=min(self.workers, len(todo)), mp_context=ctx) as pool:
            futures = [pool.submit(_call, fn, item) for item in todo]
            for k, fut in enumerate(futures):
                try:
                    done[k] = fut.result()
                except BrokenProcessPool:
                    hit.append(k)
                except Exception as exc:  # unpicklable item or result
                    done[k] = Outcome(error=f"worker failed: {error_line(exc)}")
                while shown in done:
                    yield todo[shown], done.pop(shown)
                    shown += 1
        if hit:
            logger.warning(
                "a worker process died; %d task(s) run again, each in a process of its own",
                len(hit),
            )
        for start in range(0, len(hit), self.workers):
            chunk = hit[start : start + self.workers]
            for k, outcome in zip(chunk, self._isolated(fn, [todo[k] for k in chunk]), strict=True):
                done[k] = outcome
            while shown in done:
                yield todo[shown], done.pop(shown)
                shown += 1

    def _isolated(self, fn: Callable[[T], R], items: list[T]) -> list[Outcome[R]]:
        """Run each item in a single-process pool of its own (concurrently), with retries."""
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        ctx = multiprocessing.get_context("spawn")
        outcomes: list[Outcome[R] | None] = [None] * len(items)
        left = list(range(len(items)))
        for attempt in range(self.retries):
            pools = [ProcessPoolExecutor(max_workers=1, mp_context=ctx) for _ in left]
            try:
                futures = [p.submit(_call, fn, items[k]) for p, k in zip(pools, left, strict=True)]
                again = []
                for k, fut in zip(left, futures, strict=True):
                    try:
                        outcomes[k] = fut.result()
                    except BrokenProcessPool as exc:
                        again.append(k)
                        outcomes[k] = Outcome(error=f"worker failed: {error_line(exc)}")
                    except Exception as exc:
                        outcomes[k] = Outcome(error=f"worker failed: {error_line(exc)}")
                left = again
            finally:
                for p in pools:
                    p.shutdown()
            if not left:
                break
            logger.info("attempt %d: %d task(s) lost their worker again", attempt + 2, len(left))
        return [
            o if o is not None else Outcome(error="worker failed: its process died")
            for o in outcomes
        ]


class RayExecutor:
    """Ray tasks, on a local Ray instance or on an existing cluster.

    Args:
        address: Address of a running cluster (``ray start --head``), or None for a local
            instance started here.
        workers: CPUs of a local instance (None: all); ignored with ``address``.

    Raises:
        ConfigError: Ray is not installed.
    """

    def __init__(self, address: str | None = None, workers: int | None = None) -> None:
        try:
            import ray
        except ImportError:
            raise ConfigError(RAY_MISSING) from None
        self._ray = ray
        self.address = address
        self.workers = workers

    def map(self, fn: Callable[[T], R], items: Iterable[T]) -> Iterator[tuple[T, Outcome[R]]]:
        """See `Executor.map`."""
        ray = self._ray
        todo = list(items)
        if not ray.is_initialized():
            if self.address is not None:
                ray.init(address=self.address)
            else:
                ray.init(num_cpus=self.workers)
        task = ray.remote(num_cpus=1)(_call)
        refs = [task.remote(fn, item) for item in todo]
        for item, ref in zip(todo, refs, strict=True):
            try:
                outcome: Outcome[R] = ray.get(ref)
            except Exception as exc:  # a lost worker or node (RayError)
                outcome = Outcome(error=f"worker failed: {error_line(exc)}")
            yield item, outcome


def side_by_side(pool: ThreadPoolExecutor, calls: Iterable[Callable[[], None]]) -> None:
    """Run ``calls`` on ``pool`` and wait for all of them; then the first error, if any.

    Every call finishes before an error is raised, so no call is left running on state the
    caller goes on to read (a run's back-end instances updating side by side).
    """
    futures = [pool.submit(call) for call in calls]
    wait(futures)
    for f in futures:
        f.result()


def available_cpus() -> int:
    """CPUs this process may run on (its affinity where the platform tells it)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def cap_workers(workers: int) -> int:
    """``workers`` capped at `available_cpus`, with a warning when it is more.

    More worker processes than CPUs only add memory (each holds a model and a recording)
    and time slicing: ``-j 6`` on a 2-core machine ran 6 workers in 3.8 GB.
    """
    cpus = available_cpus()
    if workers > cpus:
        logger.warning(
            "--workers %d is more than the %d CPU(s) of this machine; using %d", workers, cpus, cpus
        )
        return cpus
    return workers


def make_executor(name: str, *, address: str | None = None, workers: int | None = None) -> Any:
    """The executor of ``--executor name`` (checked before any work).

    A local executor runs at most `available_cpus` workers (`cap_workers`).

    Raises:
        ConfigError: Unknown name, ``--address`` without Ray, or Ray not installed.
    """
    if name == "local":
        if address is not None:
            raise ConfigError("--address is only used with --executor ray")
        return LocalExecutor(1 if workers is None else cap_workers(workers))
    if name == "ray":
        if workers is not None and workers < 1:
            raise ConfigError(f"--workers must be >= 1, got {workers}")
        return RayExecutor(address=address, workers=workers)
    raise ConfigError(f"--executor must be one of {', '.join(EXECUTORS)}, not {name!r}")
