"""`RunLoop`'s incremental API: `begin` / `feed` / `finish` is `run`, scan for scan."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from scanguard.apps.loop_setup import build_instances, scan_pairs
from scanguard.errors import ConfigError
from scanguard.geometry import relative
from scanguard.matching import get_matcher
from scanguard.slam.config import RunConfig
from scanguard.slam.grid import chain
from scanguard.slam.loop import RunLoop, instance_gates
from tests.helpers import make_sequence, room_segments
from tests.test_run import AlignmentDetector


@pytest.fixture(scope="module")
def room():
    rng = np.random.default_rng(5)
    steps = np.tile([0.06, 0.01, 0.02], (10, 1)) + rng.normal(0, 0.004, (10, 3))
    return make_sequence(room_segments(), steps)


@pytest.fixture(scope="module")
def wheels(room):
    """Drifting wheel odometry of ``room``: its reference steps, each a little off."""
    rng = np.random.default_rng(6)
    ref = np.asarray(room.reference)
    steps = relative(ref[:-1], ref[1:]) * (1.0 + rng.normal(0, 0.05, (len(ref) - 1, 3)))
    return chain(ref[0], steps)


def _parts(seq, cfg: RunConfig, gates=("none", "cnn"), n_scans: int = 0):
    """The instances (``n_scans``: worker processes where the config allows) and the pairs."""
    detector = AlignmentDetector()
    instances = build_instances(
        cfg,
        instance_gates(cfg, list(gates), detector, None),
        detector,
        laser_offset=seq.laser_offset,
        start=np.zeros(3),
        range_max=None,
        n_scans=n_scans,
    )
    return instances, scan_pairs(cfg, get_matcher(cfg.matcher), detector, None, seq.laser_offset)


def _loop(seq, cfg: RunConfig, odometry) -> RunLoop:
    instances, pairs = _parts(seq, cfg)
    return RunLoop(instances, pairs, cfg, odometry=odometry, start=np.zeros(3))


@pytest.mark.parametrize("motion", ["fused", "odometry"])
@pytest.mark.parametrize("with_odometry", [True, False])
def test_a_stream_fed_scan_by_scan_is_the_whole_run(room, wheels, motion, with_odometry):
    cfg = RunConfig(backend="frontend", motion=motion)
    odom = wheels if with_odometry else None
    whole = _loop(room, cfg, odom)
    res = whole.run(room.scans)
    stream = _loop(room, cfg, [] if with_odometry else None)
    stream.begin()  # length unknown: the per-scan arrays grow
    steps = [stream.feed(s, None if odom is None else odom[k]) for k, s in enumerate(room.scans)]
    got = stream.finish()
    assert [s.reason for s in steps] == [s.reason for s in res.steps]
    assert [s.accepted for s in got.steps] == [s.accepted for s in res.steps]
    for g in ("none", "cnn"):
        np.testing.assert_array_equal(got.wanted[g], res.wanted[g])
        assert got.backend_seconds[g].shape == (len(room),)
        np.testing.assert_array_equal(
            stream.instances[g].backend.trajectory(), whole.instances[g].backend.trajectory()
        )
    assert got.counts == res.counts
    assert got.motion == res.motion
    assert len(got.steps) == len(room)


def test_feed_refuses_odometry_the_loop_was_not_built_for(room):
    cfg = RunConfig(backend="frontend")
    loop = _loop(room, cfg, None)
    loop.begin()
    with pytest.raises(ConfigError, match="odometry"):
        loop.feed(room.scans[0], np.zeros(3))
    streamed = _loop(room, cfg, [])
    streamed.begin()
    with pytest.raises(ConfigError, match="odometry"):
        streamed.feed(room.scans[0])


@pytest.mark.parametrize("with_odometry", [True, False])
def test_instances_on_threads_give_what_they_give_one_after_the_other(room, wheels, with_odometry):
    odom = wheels if with_odometry else None
    got = {}
    for threads in (1, 2):
        cfg = RunConfig(backend="graph", instance_threads=threads)
        cfg.graph.minimum_travel_distance = 0.0  # a node on every scan: work on each one
        loop = _loop(room, cfg, odom)
        res = loop.run(room.scans)
        assert loop._pool is None  # finish stopped the threads
        got[threads] = (res, {g: i.backend.trajectory() for g, i in loop.instances.items()})
    (one, traj1), (two, traj2) = got[1], got[2]
    assert [s.accepted for s in one.steps] == [s.accepted for s in two.steps]
    for g in ("none", "cnn"):
        np.testing.assert_array_equal(traj1[g], traj2[g])  # bit for bit
    assert one.counts == two.counts and one.motion == two.motion


def test_the_instance_threads_resolve_per_back_end():
    import os

    assert RunConfig(backend="gmapping").instance_workers(3) == 1  # its particles use the cores
    assert RunConfig(backend="graph").instance_workers(3) == min(3, os.cpu_count() or 1)
    assert RunConfig(backend="graph").instance_workers(1) == 1
    assert RunConfig(backend="gmapping", instance_threads=2).instance_workers(3) == 2
    assert RunConfig(backend="graph", instance_threads=8).instance_workers(3) == 3


def _finished_view(backend) -> dict:
    """What the writers read of an instance, timings left out (they are the only difference)."""
    out = {
        "name": backend.name,
        "trajectory": backend.trajectory(),
        "used": backend.used(),
        "pose": backend.pose,
        "stats": {
            k: v
            for k, v in (getattr(backend, "stats", {}) or {}).items()
            if "time" not in k and "seconds" not in k
        },
    }
    grid = backend.grid()
    out["grid"] = None if grid is None else np.asarray(grid.logodds)
    if hasattr(backend, "closures"):
        out["closures"] = [r.as_dict() for r in backend.closures]
        out["edges"] = list(backend.edges)
        out["nodes"] = backend.node_poses()
        out["judge"] = backend.closure_judge.name
    return out


@pytest.mark.parametrize("backend", ["graph", "gmapping", "frontend"])
def test_instances_in_a_worker_process_give_what_they_give_here(room, wheels, backend):
    from scanguard.slam.backend import FinishedBackend
    from scanguard.slam.detached import DetachedBackend

    got = {}
    # in the worker: its instances one after the other (1), and side by side on threads (2)
    for where, threads in (("off", 0), ("on", 1), ("on", 2)):
        cfg = RunConfig(backend=backend, instance_processes=where, instance_threads=threads)
        cfg.graph.minimum_travel_distance = 0.0  # a node on every scan: work on each one
        cfg.gmapping.particles = 3
        instances, pairs = _parts(room, cfg, ("none", "cnn", "baseline"), len(room))
        detached = isinstance(instances["none"].backend, DetachedBackend)
        assert detached == (where == "on")
        assert not isinstance(instances["cnn"].backend, DetachedBackend)  # the guarded stays
        loop = RunLoop(instances, pairs, cfg, odometry=wheels, start=np.zeros(3))
        res = loop.run(room.scans)
        if detached:
            assert isinstance(loop.instances["none"].backend, FinishedBackend)
        got[threads] = res, {g: _finished_view(i.backend) for g, i in loop.instances.items()}
    here, views_here = got[0]
    for threads in (1, 2):
        there, views_there = got[threads]
        assert [s.accepted for s in here.steps] == [s.accepted for s in there.steps]
        for g in ("none", "cnn", "baseline"):
            np.testing.assert_array_equal(here.wanted[g], there.wanted[g])
            assert there.backend_seconds[g].shape == (len(room),)
            a, b = views_here[g], views_there[g]
            assert a.keys() == b.keys()
            for key in a:
                if isinstance(a[key], np.ndarray):
                    np.testing.assert_array_equal(a[key], b[key])  # bit for bit
                else:
                    assert a[key] == b[key], key
        assert here.motion == there.motion


def _note_fed(loop: RunLoop, waits: list[int]) -> None:
    waits.append(len(loop.result.steps))


def test_the_guarded_instance_alone_in_a_worker_gives_what_it_gives_here(room, wheels):
    """``--no-compare``: the guarded graph (its learned closure judge read from the file) in a
    worker process, against the same run in this process: the same verdicts, bit for bit the
    same trajectory, map, nodes, closures and judge."""
    from scanguard.slam.backend import FinishedBackend
    from scanguard.slam.detached import DetachedBackend

    got = {}
    for where in ("off", "on"):
        cfg = RunConfig(backend="graph", compare=False, instance_processes=where)
        cfg.graph.minimum_travel_distance = 0.0  # a node on every scan: work on each one
        instances, pairs = _parts(room, cfg, ("cnn",), len(room))
        assert isinstance(instances["cnn"].backend, DetachedBackend) == (where == "on")
        waits: list[int] = []
        loop = RunLoop(instances, pairs, cfg, odometry=wheels, start=np.zeros(3))
        loop.on_wait = functools.partial(_note_fed, loop, waits)
        res = loop.run(room.scans)
        if where == "on":
            assert isinstance(loop.instances["cnn"].backend, FinishedBackend)
            assert waits == [len(room)]  # once, when every scan was fed, before the wait
        got[where] = res, _finished_view(loop.instances["cnn"].backend)
    (here, a), (there, b) = got["off"], got["on"]
    assert [s.accepted for s in here.steps] == [s.accepted for s in there.steps]
    np.testing.assert_array_equal(here.wanted["cnn"], there.wanted["cnn"])
    assert a.keys() == b.keys() and a["judge"] == b["judge"] == "learned"
    for key in a:
        if isinstance(a[key], np.ndarray):
            np.testing.assert_array_equal(a[key], b[key])
        else:
            assert a[key] == b[key], key


def test_the_worker_threads_follow_the_instance_threads():
    from scanguard.slam.detached import InstancesSpec

    for threads, backend, expected in ((2, "graph", 2), (1, "graph", 1), (0, "gmapping", 1)):
        cfg = RunConfig(backend=backend, instance_threads=threads)
        spec = InstancesSpec(cfg, ("none", "baseline"), np.zeros(3), np.zeros(3), 30.0)
        assert spec.build().threads == expected


def test_an_instance_alone_in_a_worker_splits_its_wide_searches():
    """Beside the guard's process, one instance's searches take the second core (if any)."""
    import os

    from scanguard.matching.lanes import search_lanes, set_search_lanes
    from scanguard.slam.detached import InstancesSpec

    try:
        spec = InstancesSpec(RunConfig(), ("none", "baseline"), np.zeros(3), np.zeros(3), 30.0)
        spec.build()
        assert search_lanes() == 1  # two instances share the worker's cores already
        spec = InstancesSpec(RunConfig(), ("none",), np.zeros(3), np.zeros(3), 30.0)
        spec.build()
        assert search_lanes() == (2 if (os.cpu_count() or 1) > 1 else 1)
    finally:
        set_search_lanes(1)


def test_the_worker_processes_resolve_per_run():
    import os

    cores = os.cpu_count() or 1
    auto = RunConfig()  # graph, fused, compare
    assert auto.worker_processes(5000, 2) == (min(2, cores - 1) if cores > 1 else 0)
    assert auto.worker_processes(999, 2) == 0  # a short run: starting a worker costs more
    assert RunConfig(backend="gmapping").worker_processes(5000, 2) == 0
    assert RunConfig(instance_processes="on").worker_processes(10, 2) == max(1, min(2, cores - 1))
    assert RunConfig(instance_processes="on", motion="odometry").worker_processes(10, 2) == 0
    assert RunConfig(instance_processes="on", compare=False).worker_processes(10, 1) == 1
    assert RunConfig(instance_processes="off").worker_processes(5000, 2) == 0
    assert RunConfig(instance_processes="on").worker_processes(10, 0) == 0


def test_the_guarded_instance_leaves_only_alone_and_without_a_cnn(
    room, tmp_path, monkeypatch: pytest.MonkeyPatch
):
    """With no comparison the guarded instance goes to a worker, unless its closure judge
    reads the CNN (no learned judge file); with comparisons only they go."""
    import scanguard.slam.graph.judges as judges
    from scanguard.slam.detached import DetachedBackend
    from scanguard.slam.registry import needs_detector

    def layout(cfg: RunConfig, gates) -> dict[str, bool]:
        instances, _ = _parts(room, cfg, gates, n_scans=5000)
        out = {g: isinstance(i.backend, DetachedBackend) for g, i in instances.items()}
        for i in instances.values():
            if isinstance(i.backend, DetachedBackend):
                i.backend.abort()
        return out

    alone = RunConfig(instance_processes="on", compare=False)
    assert not needs_detector(alone, "cnn") and not needs_detector(alone, "none")
    assert layout(alone, ("cnn",)) == {"cnn": True}
    both = RunConfig(instance_processes="on")
    assert layout(both, ("cnn", "none")) == {"cnn": False, "none": True}
    assert not needs_detector(RunConfig(backend="frontend"), "cnn")  # no closure judge at all
    monkeypatch.setattr(judges, "default_judge_path", lambda: tmp_path / "absent.json")
    assert needs_detector(alone, "cnn")  # the fallback judge reads the CNN: it stays here
    assert layout(alone, ("cnn",)) == {"cnn": False}


def test_the_worker_started_ahead_serves_a_long_run_and_dies_with_a_short_one(room):
    import os

    from scanguard.apps.loop_setup import prestart_instance_worker
    from scanguard.runtime import streaming
    from scanguard.slam.detached import DetachedBackend

    if (os.cpu_count() or 1) < 2:
        pytest.skip("no worker process on one core")
    streaming.discard_spare()  # one an earlier test (a run that failed early) left behind
    prestart_instance_worker(RunConfig(max_scans=500))  # too short a run for a worker
    prestart_instance_worker(RunConfig(backend="gmapping"))  # whose instances stay here
    assert streaming._spare is None
    prestart_instance_worker(RunConfig())
    spare = streaming._spare
    assert spare is not None
    instances, _ = _parts(room, RunConfig(), ("cnn", "none"), n_scans=500)  # it was short
    assert not any(isinstance(i.backend, DetachedBackend) for i in instances.values())
    assert streaming._spare is None and spare.wait(timeout=10) is not None  # killed
    prestart_instance_worker(RunConfig())
    spare = streaming._spare
    instances, _ = _parts(room, RunConfig(), ("cnn", "none"), n_scans=5000)
    worker = instances["none"].backend
    assert isinstance(worker, DetachedBackend)
    assert streaming._spare is spare  # adopted with the first batch, not before
    worker.abort()
    streaming.discard_spare()


def test_a_loop_refuses_workers_it_cannot_feed(room, wheels):
    from scanguard.slam.detached import DetachedBackend

    cfg = RunConfig(backend="frontend", instance_processes="on", motion="fused")
    instances, pairs = _parts(room, cfg, n_scans=len(room))
    assert isinstance(instances["none"].backend, DetachedBackend)

    class Watcher:
        def begin(self, *a): ...
        def step(self, view): ...
        def end(self, *a): ...

    with pytest.raises(ConfigError, match="worker processes"):
        RunLoop(instances, pairs, cfg, odometry=wheels, start=np.zeros(3), observer=Watcher())
    with pytest.raises(ConfigError, match="worker processes"):
        RunLoop(
            instances,
            pairs,
            cfg.model_copy(update={"motion": "odometry"}),
            odometry=wheels,
            start=np.zeros(3),
        )
    instances["none"].backend.abort()  # never started: nothing to stop


def test_a_detached_or_finished_instance_refuses_what_it_cannot_do(room):
    from scanguard.errors import BackendError
    from scanguard.slam.backend import FinishedBackend
    from scanguard.slam.detached import DetachedBackend, DetachedGroup, InstancesSpec

    cfg = RunConfig(backend="frontend")
    with pytest.raises(ConfigError, match="cannot run in a worker"):
        InstancesSpec(cfg, ("none", "both"), np.zeros(3), np.zeros(3), None)
    group = DetachedGroup(InstancesSpec(cfg, ("none",), np.zeros(3), np.zeros(3), None))
    proxy = DetachedBackend(group, "none")
    assert proxy.name == "frontend"
    for call in (lambda: proxy.wants_scan(0.0, None), proxy.trajectory, lambda: proxy.pose):
        with pytest.raises(BackendError, match="worker process"):
            call()
    proxy.abort()  # never started
    done = FinishedBackend("frontend", np.zeros(3), np.zeros((1, 3)), np.ones(1, bool), None)
    assert not done.wants_scan(1.0, None) and done.grid() is None
    with pytest.raises(ConfigError, match="no more scans"):
        done.update(room.scans[0], None)


@pytest.mark.parametrize("backend", ["graph", "gmapping", "frontend"])
def test_instances_on_a_thread_of_their_own_give_what_they_give_in_the_loop(room, wheels, backend):
    got = {}
    for pipeline, threads in (("off", 1), ("on", 1), ("on", 2)):
        cfg = RunConfig(backend=backend, pipeline=pipeline, instance_threads=threads)
        cfg.graph.minimum_travel_distance = 0.0  # a node on every scan: work on each one
        cfg.gmapping.particles = 3
        instances, pairs = _parts(room, cfg, ("none", "cnn", "baseline"))
        built = {g: i.backend for g, i in instances.items()}
        loop = RunLoop(instances, pairs, cfg, odometry=wheels, start=np.zeros(3))
        res = loop.run(room.scans)
        assert loop._lane is None and not loop._detached  # the thread is done and gone
        # the very objects stay in their place (not a snapshot, as from a worker)
        assert all(loop.instances[g].backend is b for g, b in built.items())
        got[(pipeline, threads)] = (
            res,
            {g: _finished_view(i.backend) for g, i in loop.instances.items()},
        )
    here, views_here = got[("off", 1)]
    for key in (("on", 1), ("on", 2)):
        there, views_there = got[key]
        assert [s.accepted for s in here.steps] == [s.accepted for s in there.steps]
        assert [s.reason for s in here.steps] == [s.reason for s in there.steps]
        for g in ("none", "cnn", "baseline"):
            np.testing.assert_array_equal(here.wanted[g], there.wanted[g])
            assert there.backend_seconds[g].shape == (len(room),)
            assert np.all(there.backend_seconds[g] > 0)  # timed on the thread, per scan
            a, b = views_here[g], views_there[g]
            assert a.keys() == b.keys()
            for name in a:
                if isinstance(a[name], np.ndarray):
                    np.testing.assert_array_equal(a[name], b[name])  # bit for bit
                else:
                    assert a[name] == b[name], name
        assert here.motion == there.motion and here.counts == there.counts


def test_an_error_of_an_instance_on_its_thread_is_raised_by_the_run(room, wheels):
    from scanguard.errors import BackendError

    cfg = RunConfig(backend="frontend", pipeline="on")
    instances, pairs = _parts(room, cfg)
    backend = instances["none"].backend
    real = backend.update

    def failing(scan, *args, **kwargs):
        if scan is room.scans[6]:
            raise BackendError("scan 6 broke the unguarded instance")
        return real(scan, *args, **kwargs)

    backend.update = failing
    loop = RunLoop(instances, pairs, cfg, odometry=wheels, start=np.zeros(3))
    with pytest.raises(BackendError, match=r"^scan 6 broke the unguarded instance$"):
        loop.run(room.scans)
    assert loop._lane is not None and not loop._lane._stream.alive  # stopped, not left running


def test_the_pipeline_resolves_per_run(room, wheels):
    import os

    two = (os.cpu_count() or 1) >= 2
    assert RunConfig().pipelines() == two
    assert RunConfig(backend="gmapping").pipelines() == two
    assert RunConfig(pipeline="on").pipelines()
    assert not RunConfig(pipeline="off").pipelines()
    assert not RunConfig(pipeline="on", motion="odometry").pipelines()  # inputs read back ends

    # an observer reads every instance's pose after each scan: the loop keeps them in step
    class Watcher:
        def __init__(self) -> None:
            self.poses: list = []

        def begin(self, *a): ...
        def step(self, view):
            self.poses.append(view.poses["cnn"].copy())

        def end(self, *a): ...

    cfg = RunConfig(backend="frontend", pipeline="on")
    instances, pairs = _parts(room, cfg)
    watcher = Watcher()
    loop = RunLoop(instances, pairs, cfg, odometry=wheels, start=np.zeros(3), observer=watcher)
    loop.run(room.scans)
    assert len(watcher.poses) == len(room)
    np.testing.assert_array_equal(watcher.poses[-1], loop.instances["cnn"].backend.pose)


class _Counter:
    """A back end that counts its scans (and fails on one, when told)."""

    name = "counter"

    def __init__(self, fail_at: int | None = None) -> None:
        self.stamps: list[float] = []
        self.fail_at = fail_at

    def wants_scan(self, stamp, odometry) -> bool:
        return len(self.stamps) % 2 == 0

    def update(self, scan, odometry, *, usable=True, match=None) -> None:
        if len(self.stamps) == self.fail_at:
            raise ValueError(f"scan {self.fail_at} failed")
        self.stamps.append(float(scan.stamp))


def test_the_instances_lanes_take_their_own_steps_in_order(room):
    from scanguard.slam.detached import DetachedStep, InstancesHandler

    def steps(gates):
        return [
            DetachedStep(g, scan, np.zeros(3), True, None, None)
            for scan in room.scans
            for g in gates
        ]

    backends = {g: _Counter() for g in ("a", "b", "c")}
    handler = InstancesHandler(backends, threads=2, snapshot=False)
    items = steps(backends)
    for start in range(0, len(items), 5):  # batches that cut through scans
        handler.feed(items[start : start + 5])
    out = handler.finish()
    stamps = [float(s.stamp) for s in room.scans]
    for g, b in backends.items():
        assert b.stamps == stamps  # every scan, in order, on whichever lane
        assert out[g].wanted.tolist() == [k % 2 == 0 for k in range(len(room))]
        assert out[g].seconds.shape == (len(room),) and out[g].finished is None
    assert handler._lanes is None  # the lanes' threads ended

    failing = InstancesHandler({"a": _Counter(), "b": _Counter(fail_at=3)}, threads=2)
    with pytest.raises(ValueError, match="scan 3 failed"):
        failing.feed(steps(("a", "b")))
        failing.finish()
    failing.abort()
    assert failing._lanes is None


class _EveryThirdGate:
    """Rejects every third judged pair: by the wheel-support test, else by the CNN."""

    def __init__(self, reason: str) -> None:
        self.reason, self.n = reason, 0

    def decide(self, verdict):  # type: ignore[no-untyped-def]
        from scanguard.slam.gate import GateDecision

        self.n += 1
        return (
            GateDecision(False, self.reason) if self.n % 3 == 0 else GateDecision(True, "accepted")
        )


class _Recording:
    """A back end that records the ``usable`` flag of every scan it is given."""

    def __init__(self, inner) -> None:  # type: ignore[no-untyped-def]
        self.inner, self.usable, self.scans = inner, [], []

    def update(self, scan, odometry, *, usable=True, match=None):  # type: ignore[no-untyped-def]
        self.usable.append(usable)
        self.scans.append(scan)
        self.inner.update(scan, odometry, usable=usable, match=match)

    def __getattr__(self, name):  # type: ignore[no-untyped-def]
        return getattr(self.inner, name)


def _every_third_rejected(room, wheels, cfg, instances, pairs, reason):  # type: ignore[no-untyped-def]
    """Run the loop with every third judged pair rejected for ``reason``: what the back end
    was given, and which scans were rejected."""
    from scanguard.slam.loop import Instance

    rec = _Recording(instances["cnn"].backend)
    loop = RunLoop(
        {"cnn": Instance(rec, _EveryThirdGate(reason))},
        pairs,
        cfg,
        odometry=wheels,
        start=np.zeros(3),  # type: ignore[arg-type]
    )
    res = loop.run(room.scans)
    rejected = [not s.accepted for s in res.steps]
    assert sum(rejected) == (len(room) - 1) // 3
    return rec, rejected


@pytest.mark.parametrize("reason", ["rejected_cnn", "rejected_wheels"])
def test_a_wheel_supported_scan_is_dropped_by_the_back_end_a_cnn_reject_is_not(
    room, wheels, reason
):
    """With ``motion: fused`` a rejected scan still reaches the back end (its own matching
    weighs it), unless the wheel-support test rejected it: the back end's match would follow
    the same moving thing."""

    cfg = RunConfig(backend="frontend", motion="fused", instance_processes="off")
    assert cfg.maps_rejected_scans()
    instances, pairs = _parts(room, cfg, ("cnn",))
    rec, rejected = _every_third_rejected(room, wheels, cfg, instances, pairs, reason)
    if reason == "rejected_wheels":
        assert rec.usable == [not r for r in rejected]
    else:
        assert all(rec.usable)


def test_a_wheel_supported_scan_reaches_the_back_end_without_the_follower_when_asked(room, wheels):
    """``wheel_support_remedy: mask``: the scan reaches the back end (as usable) with the
    beams of what the matches followed taken out, and the other scans whole."""
    from scanguard.slam.guard import GuardConfig

    cfg = RunConfig(
        backend="frontend",
        motion="fused",
        instance_processes="off",
        guard=GuardConfig(wheel_support_remedy="mask"),
    )
    instances, pairs = _parts(room, cfg, ("cnn",))
    follower = np.array([3, 4, 5])

    def mark(pair):  # type: ignore[no-untyped-def]
        pair.follower_beams = follower  # as the test sets it on a pair it fires on

    pairs._wheel_support = mark  # type: ignore[method-assign]
    rec, rejected = _every_third_rejected(room, wheels, cfg, instances, pairs, "rejected_wheels")
    assert all(rec.usable)
    for given, scan, r in zip(rec.scans, room.scans, rejected, strict=True):
        if r:
            assert np.isnan(given.ranges[follower]).all()
            others = np.setdiff1d(np.arange(scan.n_beams), follower)
            np.testing.assert_array_equal(given.ranges[others], scan.ranges[others])
        else:
            assert given is scan
