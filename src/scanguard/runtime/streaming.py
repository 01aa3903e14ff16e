"""A stream of work items handed to a process (or a thread) of its own, and its one result.

`ProcessStream` starts a worker process that builds a handler from a picklable `HandlerSpec`,
feeds it every item put into the stream, in order, and returns the handler's result when the
stream is closed. The caller goes on while the worker works: items go in batches to a writer
thread that pickles them into the worker's input pipe, so `put` costs the caller almost
nothing and never waits for the worker.

The worker is a fresh interpreter (``python -c``) that imports only what the spec needs: not
``multiprocessing``'s spawn, which imports the caller's main module again, so that a user's
script without an ``if __name__ == "__main__"`` guard would run itself a second time. It gets
the caller's ``sys.path`` first. Its log records are kept and re-emitted in the caller's
process with the result (its own logging is not configured). An error in the worker is
re-raised in the caller as a `StreamError` naming the worker and the error, as soon as the
caller next puts or waits; a worker that dies without a word (killed, out of memory) is
reported likewise. A worker whose caller dies reads the end of its input and exits.

A worker takes about a second to start (the interpreter, the imports, the compiled kernels
loaded from the cache), and a stream starts its worker with its first batch. `prestart_worker`
starts one ahead, while the caller still reads its input: the spare imports and warms what it is
told to, then waits for the stream that adopts it (the next `ProcessStream` to start); one never
adopted is killed by `discard_spare` (also at exit).

`ThreadStream` is the same for a handler that stays in the caller's process, on a thread of
its own (it holds what does not pickle, or shares objects with the caller).
"""

from __future__ import annotations

import atexit
import importlib
import logging
import os
import pickle
import queue
import subprocess
import sys
import threading
import traceback
from collections.abc import Callable, Sequence
from typing import IO, Any, Generic, Protocol, TypeVar

from scanguard.errors import ScanGuardError
from scanguard.runtime.executor import error_line

logger = logging.getLogger(__name__)

R = TypeVar("R", covariant=True)

#: The worker's program: the caller's sys.path, then `_worker` reads the warm-up, the spec and
#: the items.
_BOOT = (
    "import pickle, sys; sys.path[:] = pickle.load(sys.stdin.buffer); "
    "from scanguard.runtime.streaming import _worker; _worker()"
)

_spare: subprocess.Popen[bytes] | None = None  # a worker started ahead (`prestart_worker`)
_spare_lock = threading.Lock()


def _spawn() -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-c", _BOOT], stdin=subprocess.PIPE, stdout=subprocess.PIPE
    )


def prestart_worker(warm: Sequence[str] = ()) -> None:
    """Start a worker process now, for the next `ProcessStream` to adopt (see the module docstring).

    Args:
        warm: ``module`` or ``module:function`` names the worker imports (and calls, with no
            argument) while it waits: what its handler will need.
    """
    global _spare
    with _spare_lock:
        if _spare is not None:
            return
        process = _spawn()
        assert process.stdin is not None
        try:
            for value in (list(sys.path), tuple(warm)):
                pickle.dump(value, process.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            process.stdin.flush()
        except OSError:  # it could not start: the stream starts its own
            process.kill()
            process.wait()
            return
        _spare = process


def discard_spare() -> None:
    """Kill the worker `prestart_worker` started, unless a stream adopted it."""
    global _spare
    with _spare_lock:
        process, _spare = _spare, None
    if process is not None:
        process.kill()
        process.wait()
        for pipe in (process.stdin, process.stdout):
            if pipe is not None:
                pipe.close()


atexit.register(discard_spare)


def _adopt_spare() -> subprocess.Popen[bytes] | None:
    """The spare worker, if one is started and alive (it is then no longer the spare)."""
    global _spare
    with _spare_lock:
        process, _spare = _spare, None
    if process is not None and process.poll() is not None:  # it died: start afresh
        process.wait()
        return None
    return process


def _warm(name: str) -> None:
    """Import ``module`` (and call ``module:function``) for a worker's warm-up."""
    module, _, function = name.partition(":")
    loaded = importlib.import_module(module)
    if function:
        getattr(loaded, function)()


class StreamError(ScanGuardError):
    """The worker process of a `ProcessStream` failed or died."""


class Handler(Protocol[R]):
    """What a worker feeds: the items in batches, in order, then one result."""

    def feed(self, items: list[Any]) -> None:
        """The next batch of items, in the order they were put.

        A handler may work on a batch's items side by side, provided each has the effect it
        would have had in order (the instances of `scanguard.slam.detached` do).
        """

    def finish(self) -> R:
        """The result, after the last item (picklable)."""
        ...


def _abort_handler(handler: Any) -> None:
    """A handler's own ``abort`` where it has one (threads of its own to stop)."""
    stop = getattr(handler, "abort", None)
    if stop is not None:
        stop()


class HandlerSpec(Protocol[R]):
    """A picklable recipe of a handler, built in the worker process."""

    def build(self) -> Handler[R]:
        """The handler (called once, in the worker)."""
        ...


class _Keep(logging.Handler):
    """Keeps the worker's records, formatted, for the caller's process."""

    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        # formatted now: arguments of a record need not be picklable
        record.msg, record.args = record.getMessage(), None
        record.exc_info = record.exc_text = None
        self.records.append(record)


def _worker() -> None:
    """The worker's main: spec and level, batches until None, then the reply on its own fd."""
    # the reply goes through a copy of the original stdout; stray prints go to stderr
    reply = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    inbox = sys.stdin.buffer
    keep = _Keep()
    root = logging.getLogger()
    root.addHandler(keep)
    handler = None
    try:
        for name in pickle.load(inbox):  # what the handler will need, while the caller reads
            _warm(name)
        spec, level = pickle.load(inbox)
        root.setLevel(level)
        handler = spec.build()
        fed = 0
        while (batch := pickle.load(inbox)) is not None:
            handler.feed(batch)
            fed += len(batch)
            # how far it is, for the caller's progress while it waits
            pickle.dump(("fed", fed, []), reply, protocol=pickle.HIGHEST_PROTOCOL)
            reply.flush()
        message: tuple[str, Any, list[logging.LogRecord]] = ("done", handler.finish(), [])
    except BaseException as exc:  # everything goes back: the caller raises it
        message = ("error", (error_line(exc), traceback.format_exc()), [])
        if handler is not None:
            _abort_handler(handler)  # its threads stop before the process ends
    message = (message[0], message[1], keep.records)
    pickle.dump(message, reply, protocol=pickle.HIGHEST_PROTOCOL)
    reply.flush()
    sys.stdout.flush()
    sys.stderr.flush()
    # everything is sent: the interpreter's teardown (freeing a graph of thousands of nodes,
    # the solver's objects, ~0.25 s) would only hold the caller, which waits for the exit
    os._exit(0 if message[0] == "done" else 1)


class ProcessStream(Generic[R]):
    """Items fed to a handler in a worker process; see the module docstring.

    Args:
        spec: Builds the handler in the worker (picklable, with everything it needs).
        name: What the worker is, for errors and logs (``"comparison instances"``).
        batch: Items sent together (fewer, larger writes).

    The process starts with the first item: a stream never used leaves nothing behind.
    """

    def __init__(self, spec: HandlerSpec[R], name: str, *, batch: int = 16) -> None:
        self.name = name
        self._spec = spec
        self._batch_size = max(1, int(batch))
        self._batch: list[Any] = []
        self._outgoing: queue.Queue[list[Any] | None] = queue.Queue()
        self._process: subprocess.Popen[bytes] | None = None
        self._threads: list[threading.Thread] = []
        self._reply: tuple[str, Any, list[logging.LogRecord]] | None = None
        self._replied = threading.Event()
        self._closed = False
        #: Items put so far, and items the worker has fed to its handler.
        self.sent = 0
        self.fed = 0

    def _start(self) -> None:
        spare = _adopt_spare()
        self._process = spare if spare is not None else _spawn()
        stdin, stdout = self._process.stdin, self._process.stdout
        assert stdin is not None and stdout is not None
        boot: tuple[Any, ...] = () if spare is not None else (list(sys.path), ())
        first = (*boot, (self._spec, logging.getLogger().getEffectiveLevel()))
        self._threads = [
            threading.Thread(target=self._write, args=(stdin, first), daemon=True),
            threading.Thread(target=self._read, args=(stdout,), daemon=True),
        ]
        for t in self._threads:
            t.start()

    def _write(self, pipe: IO[bytes], first: tuple[Any, ...]) -> None:
        """The writer thread: the boot values (a spare has had its own), the batches, the end."""
        try:
            for value in first:
                pickle.dump(value, pipe, protocol=pickle.HIGHEST_PROTOCOL)
            while True:
                batch = self._outgoing.get()
                pickle.dump(batch, pipe, protocol=pickle.HIGHEST_PROTOCOL)
                if batch is None:
                    break
                pipe.flush()
            pipe.close()
        except (BrokenPipeError, OSError):  # the worker is gone: the reader says why
            pass

    def _read(self, pipe: IO[bytes]) -> None:
        """The reader thread: the worker's progress, then its one reply, or its death."""
        try:
            while (message := pickle.load(pipe))[0] == "fed":
                self.fed = int(message[1])
            self._reply = message
        except Exception:  # nothing readable came: the worker died
            assert self._process is not None
            code = self._process.wait()
            self._reply = ("error", (f"its process died (exit code {code})", ""), [])
        self._replied.set()

    def put(self, item: Any) -> None:
        """Hand one item to the worker (returns at once).

        Raises:
            StreamError: The worker already failed, or the stream was closed.
        """
        if self._closed:
            raise StreamError(f"{self.name}: the stream is closed")
        self._batch.append(item)
        self.sent += 1
        if len(self._batch) >= self._batch_size:
            self._flush()
            if self._replied.is_set():  # a reply before the end is an error
                self._finish()

    def _flush(self) -> None:
        if self._process is None:
            self._start()
        if self._batch:
            self._outgoing.put(self._batch)
            self._batch = []

    def result(self, progress: Callable[[int, int], None] | None = None, every: float = 5.0) -> R:
        """Close the stream and wait for the handler's result (its logs re-emitted here).

        Args:
            progress: Called with ``(fed, sent)`` every ``every`` seconds while it waits.
            every: Seconds between progress calls.

        Raises:
            StreamError: The worker failed or died.
        """
        if not self._closed:
            self._flush()
            self._outgoing.put(None)
            self._closed = True
        while not self._replied.wait(every):
            if progress is not None:
                progress(self.fed, self.sent)
        return self._finish()

    def _finish(self) -> R:
        self._replied.wait()
        assert self._reply is not None
        kind, value, records = self._reply
        for record in records:
            logging.getLogger(record.name).handle(record)
        self._reply = (kind, value, [])  # re-emitted once
        if kind == "error":
            line, trace = value
            if trace:
                logger.debug("%s failed:\n%s", self.name, trace)
            self.abort()
            raise StreamError(f"{self.name}: {line}")
        if self._process is not None:
            self._process.wait()
        return value

    def abort(self) -> None:
        """Stop the worker now (the caller failed or gave up); nothing more is read."""
        self._closed = True
        if self._process is None:
            return
        if self._process.poll() is None:
            self._process.kill()
        self._process.wait()
        self._outgoing.put(None)  # the writer thread ends

    @property
    def alive(self) -> bool:
        """Whether the worker process is running."""
        return self._process is not None and self._process.poll() is None


class ThreadStream(Generic[R]):
    """Items fed to a handler on a thread of this process; `ProcessStream`'s counterpart.

    The caller goes on while the thread works through the batches in order. At most
    ``pending`` batches wait: a caller far ahead of the handler waits for it rather than
    queue the whole recording. An error on the thread is raised again in the caller, as it
    was raised, at the next `put` or at `result`; the thread then reads the rest of its input
    without feeding it.

    Args:
        handler: What the thread feeds (built by the caller).
        name: What the thread is, for its name and for logs.
        batch: Items handed over together (one handoff, one wake-up per batch).
        pending: Batches that may wait for the thread.
    """

    def __init__(
        self, handler: Handler[R], name: str, *, batch: int = 16, pending: int = 4
    ) -> None:
        self.name = name
        self._handler = handler
        self._batch_size = max(1, int(batch))
        self._batch: list[Any] = []
        self._incoming: queue.Queue[list[Any] | None] = queue.Queue(max(1, int(pending)))
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._stop = False
        self._closed = False
        self._result: R | None = None
        #: Items put so far, and items the thread has fed to its handler.
        self.sent = 0
        self.fed = 0

    def _run(self) -> None:
        while (batch := self._incoming.get()) is not None:
            if self._error is not None or self._stop:
                continue  # drained: a caller blocked on a full queue goes on, and then raises
            try:
                self._handler.feed(batch)
                self.fed += len(batch)
            except BaseException as exc:  # the caller raises it
                self._error = exc
        if self._error is None and not self._stop:
            try:
                self._result = self._handler.finish()
            except BaseException as exc:
                self._error = exc

    def put(self, item: Any) -> None:
        """Hand one item to the thread (waits only while ``pending`` batches wait).

        Raises:
            StreamError: The stream was closed.
            BaseException: What the handler raised on an earlier item.
        """
        if self._closed:
            raise StreamError(f"{self.name}: the stream is closed")
        self._raise()
        self._batch.append(item)
        self.sent += 1
        if len(self._batch) >= self._batch_size:
            self._flush()

    def _flush(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
            self._thread.start()
        if self._batch:
            self._incoming.put(self._batch)
            self._batch = []

    def _raise(self) -> None:
        if self._error is not None:
            self.abort()
            raise self._error

    def result(self, progress: Callable[[int, int], None] | None = None, every: float = 5.0) -> R:
        """Close the stream and wait for the handler's result.

        Args:
            progress: Called with ``(fed, sent)`` every ``every`` seconds while it waits.
            every: Seconds between progress calls.

        Raises:
            BaseException: What the handler raised.
        """
        if not self._closed:
            self._flush()
            self._closed = True
            if self._thread is not None:
                self._incoming.put(None)
        while self._thread is not None and self._thread.is_alive():
            self._thread.join(every)
            if progress is not None and self._thread.is_alive():
                progress(self.fed, self.sent)
        if self._thread is None and not self._stop:  # nothing was ever put: its result now
            self._result = self._handler.finish()
            self._stop = True  # asked again: the same, not finished twice
        self._raise()
        return self._result  # type: ignore[return-value]

    def abort(self) -> None:
        """Stop feeding the handler and let the thread end (the caller failed or gave up)."""
        self._stop = True
        if not self._closed:
            self._closed = True
            self._batch = []
            if self._thread is not None:
                self._incoming.put(None)
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        _abort_handler(self._handler)

    @property
    def alive(self) -> bool:
        """Whether the thread is running."""
        return self._thread is not None and self._thread.is_alive()
