"""The typer app, its global options and the one error boundary of every command.

Heavy modules (torch, rosbags, matplotlib) are imported inside the commands so that
``scanguard --help`` stays fast.

Every command runs inside `guarded`, the one error boundary: an expected failure
(`ScanGuardError`, `OSError`, out of memory) becomes one line ``error: <path>: <problem>``
with exit code 1, and Ctrl-C becomes exit code 130; the output layer (`scanguard.fsutil`)
makes sure nothing half-written is left behind either way.
"""

from __future__ import annotations

import errno
import functools
import logging
import os
from collections.abc import Callable
from typing import Any, NoReturn, TypeVar

import typer
from rich.console import Console

from scanguard import __version__
from scanguard.cli.usage import UnixTyper
from scanguard.errors import ScanGuardError

app = UnixTyper(
    name="scanguard",
    help="Detect faulty 2D LiDAR scan matches with a CNN and keep SLAM honest.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # plain help: flags look like flags, readable in any width
)
console = Console()
err_console = Console(stderr=True)
logger = logging.getLogger("scanguard.cli")

F = TypeVar("F", bound=Callable[..., Any])

#: Exit code of a run stopped with Ctrl-C (128 + SIGINT), as shells report it.
EXIT_INTERRUPTED = 130

_OS_PROBLEMS = {
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.ENOSPC: "no space left on device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EEXIST: "already exists",
    errno.EISDIR: "is a directory",
    errno.ENOTDIR: "not a directory",
    errno.EROFS: "read-only file system",
    errno.ENOENT: "no such file or directory",
    errno.ENAMETOOLONG: "file name too long",
    errno.ENOTEMPTY: "directory not empty",
    errno.EMFILE: "too many open files",
    errno.EIO: "input/output error",
}


def printable(text: str, limit: int = 1000) -> str:
    """``text`` on one line: control characters escaped, at most ``limit`` characters."""
    out = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)
    return out if len(out) <= limit else out[: limit - 1] + "…"


def os_error_text(exc: OSError) -> str:
    """``<path>: <problem>`` for an `OSError` (``<problem>`` alone when it names no path)."""
    problem = _OS_PROBLEMS.get(exc.errno or -1) or exc.strerror or str(exc) or type(exc).__name__
    if exc.filename is None:
        from scanguard.fsutil.numba_cache import numba_cache_failure

        cache = numba_cache_failure(exc)  # numba's cache writes name no file
        return problem if cache is None else f"{cache}: {problem} (the numba cache folder)"
    where = os.fsdecode(exc.filename) if isinstance(exc.filename, bytes) else str(exc.filename)
    if exc.filename2 is not None:
        where = f"{where} -> {exc.filename2}"
    return f"{where}: {problem}"


def _caused_by_interrupt(exc: BaseException) -> bool:
    """Whether a `KeyboardInterrupt` is in ``exc``'s chain (numba's ``SystemError`` wraps it)."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def fail(message: str) -> NoReturn:
    """Print ``error: <message>`` (one line, on stderr) and exit with code 1."""
    from rich.markup import escape

    err_console.print(
        f"[bold red]error:[/bold red] {escape(printable(message))}",
        highlight=False,
        soft_wrap=True,
    )
    raise typer.Exit(1)


class _Signals:
    """SIGINT/SIGTERM during a command: remembered, and raised where that is safe.

    The signal raises `KeyboardInterrupt` as Python's default does, except inside an LLVM
    callback (numba compiling a kernel), where an exception is swallowed or crashes the
    process: there the signal is re-sent a moment later. ``received`` stays set, so an
    error that a swallowed interrupt turns into (numba: ``no compiled object yet``) still
    ends as an interruption.
    """

    def __init__(self) -> None:
        self.received: int | None = None
        self._previous: dict[int, Any] = {}
        self._active = False

    def __enter__(self) -> _Signals:
        import signal
        import threading

        self.received = None
        self._active = True
        if threading.current_thread() is not threading.main_thread():
            return self
        for sig, default in (
            (signal.SIGINT, signal.default_int_handler),
            (signal.SIGTERM, signal.SIG_DFL),
        ):
            if signal.getsignal(sig) is default:  # never replace someone else's handler
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        import signal

        self._active = False
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}

    def _resend(self, signum: int) -> None:
        if self._active:  # the command may have ended meanwhile
            os.kill(os.getpid(), signum)

    def _handle(self, signum: int, frame: Any) -> None:
        import threading

        self.received = signum
        f = frame
        while f is not None:
            if "llvmlite" in f.f_code.co_filename:
                retry = threading.Timer(0.05, self._resend, (signum,))
                retry.daemon = True
                retry.start()
                return
            f = f.f_back
        raise KeyboardInterrupt

    def exit_code(self) -> int:
        """130 for Ctrl-C (SIGINT), 143 for SIGTERM."""
        return 128 + (self.received or 2)


def _interrupted(signals: _Signals | None = None) -> NoReturn:
    code = EXIT_INTERRUPTED if signals is None else signals.exit_code()
    what = "terminated" if code == 143 else "interrupted"
    err_console.print(
        f"[yellow]{what}[/yellow]: stopped, no partial output was kept", highlight=False
    )
    raise typer.Exit(code)


def guarded(fn: F) -> F:
    """The CLI's error boundary: one line on stderr and exit 1 for expected errors.

    `ScanGuardError`, `OSError` (permission, no space, exists, is a directory, ...) and
    `MemoryError` become ``error: <path>: <problem>`` with exit code 1; Ctrl-C (also when
    numba wraps it in a ``SystemError`` or swallows it while compiling) becomes exit code 130
    and SIGTERM 143, after the output layer has removed its temporaries. Anything else is a
    bug and keeps its traceback.
    """

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        signals = _Signals()
        try:
            with signals:
                return fn(*args, **kwargs)
        except (typer.Exit, typer.Abort, typer.TyperException):
            raise
        except KeyboardInterrupt:
            _interrupted(signals)
        except ScanGuardError as exc:
            if signals.received or _caused_by_interrupt(exc):
                _interrupted(signals)
            logger.debug("%s", type(exc).__name__, exc_info=True)
            fail(str(exc))
        except OSError as exc:
            if signals.received or _caused_by_interrupt(exc):
                _interrupted(signals)
            logger.debug("%s", type(exc).__name__, exc_info=True)
            fail(os_error_text(exc))
        except MemoryError as exc:
            detail = f" ({exc})" if str(exc) else ""
            fail(f"out of memory{detail}: use a smaller input or smaller settings")
        except Exception as exc:
            if signals.received or _caused_by_interrupt(exc):
                _interrupted(signals)
            raise

    return wrapper  # type: ignore[return-value]


def _version_callback(value: bool) -> None:
    if value:
        console.print(f"scanguard {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(
        False, "--version", callback=_version_callback, is_eager=True, help="Show the version."
    ),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Debug logging."),
) -> None:
    """Detect faulty 2D LiDAR scan matches (global options)."""
    from scanguard.logging_utils import configure_logging

    configure_logging(verbose)
