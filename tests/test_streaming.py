"""`ProcessStream` and `ThreadStream`: items fed to a worker in order, its result, errors, logs."""

from __future__ import annotations

import logging
import os
import signal
from dataclasses import dataclass, field

import pytest

from scanguard.runtime import streaming
from scanguard.runtime.streaming import (
    ProcessStream,
    StreamError,
    ThreadStream,
    discard_spare,
    prestart_worker,
)


@dataclass
class _Sum:
    """Sums its items; fails on a negative one; logs every tenth."""

    seen: list[int] = field(default_factory=list)

    def feed(self, items: list[int]) -> None:
        for item in items:
            if item < 0:
                raise ValueError(f"negative item {item}")
            if item % 10 == 0:
                logging.getLogger("tests.stream").warning("item %d", item)
            self.seen.append(item)

    def finish(self) -> tuple[int, list[int], int]:
        return sum(self.seen), self.seen, os.getpid()


@dataclass(frozen=True)
class _SumSpec:
    def build(self) -> _Sum:
        return _Sum()


@dataclass
class _Slow(_Sum):
    def feed(self, items: list[int]) -> None:
        import time

        time.sleep(0.01 * len(items))
        super().feed(items)


@dataclass(frozen=True)
class _SlowSpec:
    def build(self) -> _Slow:
        return _Slow()


@dataclass(frozen=True)
class _Suicide:
    """A handler whose process dies without a word on its first item."""

    def build(self) -> _Suicide:
        return self

    def feed(self, items: list[int]) -> None:
        os.kill(os.getpid(), signal.SIGKILL)

    def finish(self) -> None:
        return None


_WARMED: list[int] = []  # in a worker: the pid of each warm-up that ran there


def _warm_here() -> None:
    _WARMED.append(os.getpid())


@dataclass
class _Warmed(_Sum):
    def finish(self) -> tuple[int, list[int], int]:  # type: ignore[override]
        return sum(self.seen), list(_WARMED), os.getpid()


@dataclass(frozen=True)
class _WarmedSpec:
    def build(self) -> _Warmed:
        return _Warmed()


def test_a_worker_started_ahead_is_warmed_and_the_next_stream_adopts_it():
    discard_spare()  # one an earlier test (a run that failed early) left behind
    prestart_worker((f"{__name__}:_warm_here", "json"))
    spare = streaming._spare
    assert spare is not None and spare.poll() is None
    prestart_worker(())  # one spare at a time: the first stays
    assert streaming._spare is spare
    stream = ProcessStream(_WarmedSpec(), "warmed", batch=4)
    for k in range(1, 11):
        stream.put(k)
    total, warmed, pid = stream.result()
    assert total == 55 and pid == spare.pid and warmed == [pid]  # warmed once, before its work
    assert streaming._spare is None  # adopted
    cold = ProcessStream(_WarmedSpec(), "cold", batch=4)
    cold.put(1)
    total, warmed, other = cold.result()
    assert total == 1 and other != pid and warmed == []  # a stream with no spare starts its own


def test_a_spare_worker_never_adopted_is_killed():
    prestart_worker(())
    spare = streaming._spare
    assert spare is not None
    discard_spare()
    assert spare.poll() is not None and streaming._spare is None
    discard_spare()  # none left: nothing to do
    stream = ProcessStream(_SumSpec(), "summer", batch=2)
    stream.put(2)
    assert stream.result()[0] == 2


def test_every_item_reaches_the_worker_in_order_and_its_logs_come_back(caplog):
    stream = ProcessStream(_SumSpec(), "summer", batch=7)
    assert not stream.alive  # nothing started before the first item
    with caplog.at_level(logging.WARNING, logger="tests.stream"):
        for k in range(1, 101):
            stream.put(k)
        total, seen, pid = stream.result()
    assert total == 5050 and seen == list(range(1, 101))
    assert pid != os.getpid()  # another process did the work
    assert [r.getMessage() for r in caplog.records if r.name == "tests.stream"] == [
        f"item {k}" for k in range(10, 101, 10)
    ]
    assert stream.result()[0] == 5050  # asked again: the same, no wait
    with pytest.raises(StreamError, match="closed"):
        stream.put(1)


def test_an_error_in_the_worker_is_raised_here_in_one_line():
    stream = ProcessStream(_SumSpec(), "summer", batch=1)
    stream.put(3)
    stream.put(-2)
    with pytest.raises(StreamError, match=r"^summer: ValueError: negative item -2$"):
        for _ in range(10_000):  # the error surfaces at a later put, or at the end
            stream.put(1)
        stream.result()
    assert not stream.alive


def test_a_worker_that_dies_is_reported():
    stream = ProcessStream(_Suicide(), "doomed", batch=1)
    stream.put(1)
    with pytest.raises(StreamError, match=r"doomed: its process died \(exit code -9\)"):
        stream.result()


def test_an_aborted_stream_stops_its_worker():
    stream = ProcessStream(_SumSpec(), "summer", batch=1)
    stream.put(1)
    assert stream.alive
    stream.abort()
    assert not stream.alive
    ProcessStream(_SumSpec(), "never used").abort()  # nothing started: nothing to stop


def test_the_wait_reports_how_far_the_worker_is():
    stream = ProcessStream(_SlowSpec(), "slow", batch=4)
    for k in range(1, 101):
        stream.put(k)
    seen: list[tuple[int, int]] = []
    total, _, _ = stream.result(lambda fed, sent: seen.append((fed, sent)), every=0.05)
    assert total == 5050
    assert seen, "a second of work, and no progress reported"
    assert all(sent == 100 and 0 <= fed <= 100 for fed, sent in seen)
    assert [f for f, _ in seen] == sorted(f for f, _ in seen)  # it only goes forward
    assert stream.fed == stream.sent == 100


def test_a_thread_stream_feeds_its_handler_in_order_on_another_thread():
    import threading

    seen_on: set[str] = set()

    class _Where(_Sum):
        def feed(self, items: list[int]) -> None:
            seen_on.add(threading.current_thread().name)
            super().feed(items)

    stream = ThreadStream(_Where(), "summer", batch=7, pending=2)
    assert not stream.alive  # nothing started before the first batch
    for k in range(1, 101):
        stream.put(k)
    total, seen, pid = stream.result()
    assert total == 5050 and seen == list(range(1, 101))
    assert pid == os.getpid() and seen_on == {"summer"}  # this process, its own thread
    assert stream.result()[0] == 5050  # asked again: the same
    assert stream.fed == stream.sent == 100 and not stream.alive
    with pytest.raises(StreamError, match="closed"):
        stream.put(1)
    assert ThreadStream(_Sum(), "never used").result() == (0, [], os.getpid())


def test_a_thread_stream_raises_the_handlers_own_error_here():
    stream = ThreadStream(_Sum(), "summer", batch=1, pending=1)
    stream.put(3)
    stream.put(-2)
    # the error surfaces at a later put (a full queue does not hang: the thread drains it)
    with pytest.raises(ValueError, match=r"^negative item -2$"):
        for _ in range(10_000):
            stream.put(1)
        stream.result()
    assert not stream.alive
    failing = ThreadStream(_Sum(), "summer", batch=5)
    for k in (1, 2, -3):
        failing.put(k)
    with pytest.raises(ValueError, match="negative item -3"):
        failing.result()


def test_a_thread_stream_holds_its_caller_when_batches_pile_up():
    import time

    stream = ThreadStream(_Slow(), "slow", batch=1, pending=2)
    t0 = time.perf_counter()
    for k in range(1, 21):
        stream.put(k)
    waited = time.perf_counter() - t0
    # 20 items of 10 ms each, at most 2 waiting and 1 in hand: the caller waited for ~17
    assert waited > 0.1
    seen: list[tuple[int, int]] = []
    total, _, _ = stream.result(lambda fed, sent: seen.append((fed, sent)), every=0.005)
    assert total == 210
    assert all(sent == 20 and 0 <= fed <= 20 for fed, sent in seen)


def test_an_aborted_thread_stream_feeds_nothing_more():
    stream = ThreadStream(_Slow(), "slow", batch=1, pending=50)
    for k in range(1, 41):
        stream.put(k)
    stream.abort()
    assert not stream.alive
    assert len(stream._handler.seen) < 40  # the rest was dropped, not fed
    ThreadStream(_Sum(), "never used").abort()  # nothing started: nothing to stop
