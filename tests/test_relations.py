"""Kümmerle et al. 2009 relation metric: reading ``*.relations`` files and scoring trajectories."""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np
import pytest

from scanguard.errors import InputError
from scanguard.geometry import compose, relative
from scanguard.io.relations import Relations, read_relations
from scanguard.slam.relations import (
    PUBLISHED_RELATION_ERRORS,
    RelationErrors,
    published_for,
    relation_errors,
    relation_table_markdown,
)

BENCHMARK = Path(__file__).resolve().parents[1].parent / "shared/data/benchmark"

# Intel-sized stamps (~1e9 s): integer microseconds must still be exact there.
T0 = 976052857.337530
DT = 0.2


def _stamps(n: int, t0: float = T0) -> np.ndarray:
    """Stamps as a log stores them: ``%.6f`` text read back as float."""
    return np.array([float(f"{t0 + DT * i:.6f}") for i in range(n)])


def _trajectory(n: int, seed: int = 0) -> np.ndarray:
    """A random but fixed planar robot path of ``n`` poses."""
    rng = np.random.default_rng(seed)
    steps = np.column_stack(
        [rng.uniform(0.0, 0.5, n), rng.normal(0.0, 0.05, n), rng.normal(0.0, 0.2, n)]
    )
    poses = np.zeros((n, 3))
    for i in range(1, n):
        poses[i] = compose(poses[i - 1], steps[i])
    return poses


def _relations(
    stamps: np.ndarray, reference: np.ndarray, pairs: list[tuple[int, int]], path: str = "x.rel"
) -> Relations:
    """Reference relations between the scans ``pairs`` of ``reference``."""
    i = np.array([a for a, _ in pairs])
    j = np.array([b for _, b in pairs])
    return Relations(
        t1=stamps[i].copy(),
        t2=stamps[j].copy(),
        delta=relative(reference[i], reference[j]),
        path=path,
    )


PAIRS = [(0, 1), (3, 4), (2, 9), (10, 40), (39, 5), (0, 49), (20, 21)]


# --- (a) estimate == reference ----------------------------------------------------------------


def test_reference_trajectory_has_zero_error() -> None:
    stamps, ref = _stamps(50), _trajectory(50)
    rel = _relations(stamps, ref, PAIRS)
    r = relation_errors(stamps, ref, rel)
    assert (r.n_relations, r.n_matched, r.n_unmatched, r.n_ambiguous_stamps) == (7, 7, 0, 0)
    for value in (r.trans_mean, r.trans_std, r.rot_mean_deg, r.rot_std_deg, r.rot_sq_mean):
        assert value == pytest.approx(0.0, abs=1e-9)
    assert r.max_dt is None


# --- (b) known errors -------------------------------------------------------------------------


def test_heading_drift_gives_known_rotational_error() -> None:
    # Straight path along x; the estimate's heading drifts by w per step, positions exact.
    n, w = 6, 0.01
    stamps = _stamps(n)
    ref = np.column_stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)])
    est = ref.copy()
    est[:, 2] = w * np.arange(n)
    ks = np.arange(1, n)
    rel = _relations(stamps, ref, [(0, int(k)) for k in ks])
    r = relation_errors(stamps, est, rel)
    # From scan 0 (heading exact), scan k is seen at its true place, rotated by k w.
    rot = np.degrees(w * ks)
    assert r.n_matched == n - 1
    assert r.trans_mean == pytest.approx(0.0, abs=1e-12)
    assert r.rot_mean_deg == pytest.approx(rot.mean(), rel=1e-12)
    assert r.rot_std_deg == pytest.approx(rot.std(), rel=1e-12)
    assert r.rot_sq_mean == pytest.approx((rot**2).mean(), rel=1e-12)
    assert r.rot_sq_std == pytest.approx((rot**2).std(), rel=1e-12)

    # From scan i (heading off by i w) to i + 1 the chord is seen rotated by -i w:
    # translational error 2 sin(i w / 2), rotational error w.
    rel = _relations(stamps, ref, [(i, i + 1) for i in range(n - 1)])
    r = relation_errors(stamps, est, rel)
    trans = 2.0 * np.sin(w * np.arange(n - 1) / 2.0)
    assert r.trans_mean == pytest.approx(trans.mean(), rel=1e-9)
    assert r.trans_std == pytest.approx(trans.std(), rel=1e-9)
    assert r.rot_mean_deg == pytest.approx(math.degrees(w), rel=1e-9)
    assert r.rot_std_deg == pytest.approx(0.0, abs=1e-9)


def test_translation_offset_of_one_pose_gives_its_length() -> None:
    stamps, ref = _stamps(10), _trajectory(10, seed=3)
    est = ref.copy()
    est[5, :2] += (0.3, 0.4)  # 0.5 m off, in the world frame
    rel = _relations(stamps, ref, [(0, 1), (4, 5), (5, 6), (7, 8)])
    r = relation_errors(stamps, est, rel)
    # errors 0, 0.5, 0.5, 0 whatever the headings
    assert r.trans_mean == pytest.approx(0.25, abs=1e-12)
    assert r.trans_std == pytest.approx(0.25, abs=1e-12)
    assert r.trans_sq_mean == pytest.approx(0.125, abs=1e-12)
    assert r.trans_sq_std == pytest.approx(0.125, abs=1e-12)
    assert r.rot_mean_deg == pytest.approx(0.0, abs=1e-12)


# --- (c) frame independence -------------------------------------------------------------------


def test_global_rigid_transform_leaves_errors_unchanged() -> None:
    stamps, ref = _stamps(50), _trajectory(50)
    rel = _relations(stamps, ref, PAIRS)
    moved = compose(np.array([12.5, -7.0, 2.1]), ref)
    r = relation_errors(stamps, moved, rel)
    assert r.trans_mean == pytest.approx(0.0, abs=1e-9)
    assert r.rot_mean_deg == pytest.approx(0.0, abs=1e-9)

    noisy = ref + np.random.default_rng(7).normal(0.0, [0.05, 0.05, 0.02], ref.shape)
    a = relation_errors(stamps, noisy, rel)
    b = relation_errors(stamps, compose(np.array([-3.0, 40.0, -1.3]), noisy), rel)
    assert a.trans_mean > 0.01
    assert b.n_matched == a.n_matched == len(PAIRS)
    for key in ("trans_mean", "trans_std", "trans_sq_mean", "rot_mean_deg", "rot_sq_std"):
        assert getattr(b, key) == pytest.approx(getattr(a, key), rel=1e-9), key


# --- (d) nearest-stamp matching ---------------------------------------------------------------


def test_stamps_a_microsecond_off_match_and_exact_matching_is_still_available(
    caplog: pytest.LogCaptureFixture,
) -> None:
    stamps, ref = _stamps(50), _trajectory(50)
    rel = _relations(stamps, ref, PAIRS)
    shifted = stamps.copy()
    shifted[4] = float(f"{stamps[4] + 1e-6:.6f}")  # touches (3, 4)
    shifted[40] = float(f"{stamps[40] - 1e-6:.6f}")  # touches (10, 40)
    r = relation_errors(shifted, ref, rel)  # default: nearest scan stamp within 1 ms
    assert (r.n_relations, r.n_matched, r.n_unmatched) == (7, 7, 0)
    assert r.coverage == 1.0 and not r.partial and r.tolerance == 1e-3
    assert r.trans_mean == pytest.approx(0.0, abs=1e-9)
    exact = relation_errors(shifted, ref, rel, tolerance=0.0)
    assert (exact.n_matched, exact.n_unmatched) == (5, 2)
    assert exact.partial and "PARTIAL (71 %)" in exact.used_text()
    assert "2 of 7 relations have a stamp with no scan stamp within 0 s" in caplog.text
    with pytest.raises(ValueError, match="tolerance"):
        relation_errors(shifted, ref, rel, tolerance=-1.0)


@pytest.mark.parametrize("decimals", [3, 5, 6, 9])
def test_relations_printed_with_any_decimals_score_alike(tmp_path: Path, decimals: int) -> None:
    """A log with 6-decimal stamps, its relations written with 3, 5, 6 or 9 decimals."""
    stamps, ref = _stamps(50), _trajectory(50)
    est = ref + np.random.default_rng(3).normal(0.0, 0.02, ref.shape)
    delta = relative(ref[[i for i, _ in PAIRS]], ref[[j for _, j in PAIRS]])
    lines = [
        f"{stamps[i]:.{decimals}f} {stamps[j]:.{decimals}f} {d[0]:.9f} {d[1]:.9f} 0 0 0 {d[2]:.9f}"
        for (i, j), d in zip(PAIRS, delta, strict=True)
    ]
    path = tmp_path / f"d{decimals}.relations"
    path.write_text("\n".join(lines) + "\n")
    r = relation_errors(stamps, est, read_relations(path))
    want = relation_errors(stamps, est, _relations(stamps, ref, PAIRS))
    assert (r.n_matched, r.n_unmatched, r.n_collapsed_stamps) == (7, 0, 0)
    assert r.trans_mean == pytest.approx(want.trans_mean, abs=1e-8)
    assert r.rot_mean_deg == pytest.approx(want.rot_mean_deg, abs=1e-6)
    assert r.used_text() == "7 of 7"


def test_stamps_that_fall_on_one_scan_are_reported(caplog: pytest.LogCaptureFixture) -> None:
    stamps, ref = _stamps(10), _trajectory(10)
    rel = _relations(stamps, ref, [(0, 3), (5, 8)])
    # relation stamps 0.05 s apart around scan 3: both within a 0.15 s tolerance of scan 3
    rel = Relations(
        t1=np.array([stamps[3] - 0.05, stamps[5]]),
        t2=np.array([stamps[3] + 0.05, stamps[8]]),
        delta=rel.delta,
        path="x.rel",
    )
    r = relation_errors(stamps, ref, rel, tolerance=0.15)
    assert r.n_collapsed_stamps == 2
    assert "2 distinct relation stamps fall on a scan shared" in caplog.text
    assert relation_errors(stamps, ref, rel, tolerance=0.06).n_collapsed_stamps == 2
    assert relation_errors(stamps, ref, rel, tolerance=0.01).n_matched == 1


def test_relations_outside_a_cut_recording_do_not_make_it_partial() -> None:
    stamps, ref = _stamps(50), _trajectory(50)
    rel = _relations(stamps, ref, PAIRS)
    r = relation_errors(stamps[:30], ref[:30], rel)  # --max-scans 30
    # (10, 40), (39, 5) and (0, 49) reach past scan 29
    assert (r.n_matched, r.n_unmatched, r.n_outside) == (4, 3, 3)
    assert r.coverage == 1.0 and not r.partial
    assert r.used_text() == "4 of 7 (3 outside the recording)"


def test_no_matching_stamp_raises_naming_the_relations_file() -> None:
    stamps, ref = _stamps(20), _trajectory(20)
    rel = _relations(stamps, ref, [(0, 1), (2, 3)], path="/data/intel.relations")
    with pytest.raises(InputError, match="no relation stamps match the scan stamps") as err:
        relation_errors(stamps + 1000.0, ref, rel)
    assert "intel.relations" in str(err.value)
    assert f"{stamps[0]:.6f}" in str(err.value)


def test_duplicated_stamps_use_the_first_scan_and_are_counted() -> None:
    stamps, ref = _stamps(12), _trajectory(12)
    rel = _relations(stamps, ref, [(0, 1), (4, 5), (5, 6), (8, 9)])
    # a second scan carries stamp 5 (the log's clock stepped back); its pose is far off
    dup_stamps = np.insert(stamps, 7, stamps[5])
    dup_poses = np.insert(ref, 7, [100.0, 100.0, 3.0], axis=0)
    r = relation_errors(dup_stamps, dup_poses, rel)
    assert (r.n_matched, r.n_unmatched, r.n_ambiguous_stamps) == (4, 0, 2)
    assert r.trans_mean == pytest.approx(0.0, abs=1e-9)


def test_nan_poses_count_as_unmatched(caplog: pytest.LogCaptureFixture) -> None:
    stamps, ref = _stamps(12), _trajectory(12)
    rel = _relations(stamps, ref, [(0, 1), (4, 5), (5, 6), (8, 9)])
    est = ref.copy()
    est[5] = np.nan
    r = relation_errors(stamps, est, rel)
    assert (r.n_matched, r.n_unmatched) == (2, 2)
    assert r.trans_mean == pytest.approx(0.0, abs=1e-9)
    assert caplog.text.count("non-finite estimated pose") == 1
    est[:] = np.nan
    with pytest.raises(InputError, match="non-finite pose"):
        relation_errors(stamps, est, rel)


def test_mismatched_lengths_are_rejected() -> None:
    stamps, ref = _stamps(5), _trajectory(5)
    with pytest.raises(ValueError, match="5 stamps but 4 poses"):
        relation_errors(stamps, ref[:4], _relations(stamps, ref, [(0, 1)]))


# --- (e) max_dt -------------------------------------------------------------------------------


def test_max_dt_keeps_only_short_relations() -> None:
    stamps, ref = _stamps(60), _trajectory(60)
    # spans 0.2 s, 5 s, exactly 10 s, 10.2 s
    rel = _relations(stamps, ref, [(0, 1), (10, 35), (50, 0), (1, 52)])
    est = ref.copy()
    est[52, :2] += (0.0, 2.0)  # only the 10.2 s relation sees this
    everything = relation_errors(stamps, est, rel)
    assert everything.n_matched == 4
    assert everything.trans_mean == pytest.approx(0.5, abs=1e-12)
    short = relation_errors(stamps, est, rel, max_dt=10.0)
    assert (short.n_relations, short.n_matched, short.n_unmatched) == (4, 3, 0)
    assert short.n_selected == 3
    assert short.trans_mean == pytest.approx(0.0, abs=1e-9)
    assert short.max_dt == 10.0
    assert relation_errors(stamps, est, rel, max_dt=0.2).n_matched == 1
    with pytest.raises(InputError, match=r"spans at most 0\.1 s"):
        relation_errors(stamps, est, rel, max_dt=0.1)
    with pytest.raises(ValueError, match="max_dt"):
        relation_errors(stamps, est, rel, max_dt=-1.0)


# --- (f) reading relations files --------------------------------------------------------------


def _write_relations(path: Path, rows: np.ndarray, compress: bool = False) -> Path:
    lines = ["# t1 t2 x y z roll pitch yaw", ""]
    lines += [" ".join(f"{v:.6f}" for v in row) for row in rows]
    text = "\n".join(lines) + "\n"
    if compress:
        path.write_bytes(gzip.compress(text.encode()))
    else:
        path.write_text(text)
    return path


ROWS = np.array(
    [
        [1216.630413, 1217.490267, 0.407950, -0.016330, 0.0, 0.0, 0.0, -0.069620],
        [1217.490267, 1218.340166, 0.461150, 0.029270, 0.0, 0.0, 0.0, -0.001960],
        [976052905.125000, 976052912.000001, -1.5, 2.25, 0.1, 0.2, 0.3, 3.1],
    ]
)


@pytest.mark.parametrize("compress", [False, True])
def test_read_relations_round_trip(tmp_path: Path, compress: bool) -> None:
    name = "a.relations.gz" if compress else "a.relations"
    path = _write_relations(tmp_path / name, ROWS, compress)
    rel = read_relations(path)
    assert len(rel) == 3
    assert rel.path == str(path)
    np.testing.assert_array_equal(rel.t1, ROWS[:, 0])
    np.testing.assert_array_equal(rel.t2, ROWS[:, 1])
    np.testing.assert_array_equal(rel.delta, ROWS[:, [2, 3, 7]])
    assert rel.delta.shape == (3, 3) and rel.delta.dtype == np.float64
    # the stamps come back exactly as %.6f text
    assert [f"{t:.6f}" for t in rel.t2] == ["1217.490267", "1218.340166", "976052912.000001"]


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ("1.0 2.0 0.1 0.2 0 0 0", "expected 8 values"),
        ("1.0 2.0 0.1 0.2 0 0 0 0.3 9", "expected 8 values"),
        ("1.0 2.0 nan 0.2 0 0 0 0.3", "non-finite value for x"),
        ("1.0 inf 0.1 0.2 0 0 0 0.3", "non-finite value for t2"),
        ("1.0 2.0 0.1 abc 0 0 0 0.3", "not a number"),
    ],
)
def test_read_relations_rejects_bad_lines(tmp_path: Path, line: str, expected: str) -> None:
    path = tmp_path / "bad.relations"
    path.write_text("# header\n1.0 2.0 0.1 0.2 0 0 0 0.3\n\n" + line + "\n5 6 0 0 0 0 0 0\n")
    with pytest.raises(InputError, match=expected) as err:
        read_relations(path)
    message = str(err.value)
    assert "bad.relations, line 4:" in message
    assert "\n" not in message


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n"])
def test_read_relations_rejects_empty_files(tmp_path: Path, text: str) -> None:
    path = tmp_path / "empty.relations"
    path.write_text(text)
    with pytest.raises(InputError, match=r"empty\.relations: no relations"):
        read_relations(path)


def test_read_relations_missing_and_corrupt_files(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        read_relations(tmp_path / "missing.relations")
    truncated = tmp_path / "t.relations.gz"
    truncated.write_bytes(gzip.compress(b"1 2 0 0 0 0 0 0\n" * 50)[:30])
    with pytest.raises(InputError, match=r"t\.relations\.gz: truncated gzip"):
        read_relations(truncated)


# --- table and published figures --------------------------------------------------------------


def test_published_figures_and_lookup() -> None:
    assert PUBLISHED_RELATION_ERRORS["intel"]["scan matching"] == (0.220, 0.296)
    assert PUBLISHED_RELATION_ERRORS["fr079"]["graph mapping"] == (0.056, 0.042)
    assert PUBLISHED_RELATION_ERRORS["aces"]["RBPF (GMapping, 50 particles)"] == (0.060, 0.049)
    intel = published_for("/x/intel.clf.gz")
    assert intel == PUBLISHED_RELATION_ERRORS["intel"]
    assert intel is not PUBLISHED_RELATION_ERRORS["intel"]
    assert published_for("FR079.relations") == PUBLISHED_RELATION_ERRORS["fr079"]
    assert published_for(Path("aces-run2.log")) == PUBLISHED_RELATION_ERRORS["aces"]
    assert published_for("mit-csail.clf") is None


def test_relation_table_markdown() -> None:
    r = RelationErrors(
        n_relations=10,
        n_matched=8,
        n_unmatched=1,
        n_ambiguous_stamps=0,
        trans_mean=0.1234,
        trans_std=0.05,
        trans_sq_mean=0.02,
        trans_sq_std=0.01,
        rot_mean_deg=1.5,
        rot_std_deg=0.25,
        rot_sq_mean=3.0,
        rot_sq_std=2.0,
        max_dt=10.0,
    )
    assert r.as_dict()["n_matched"] == 8
    table = relation_table_markdown({"odometry": r}, {"graph mapping": (0.056, 0.042)})
    assert table.splitlines() == [
        "| trajectory | relations used | trans. abs. (m) | trans. sq. (m²) "
        "| rot. abs. (deg) | rot. sq. (deg²) |",
        "|---|---|---|---|---|---|",
        "| odometry | 8 of 9 PARTIAL (89 %) (Δt ≤ 10 s, of 10) | 0.123 ± 0.050 | 0.020 ± 0.010 "
        "| 1.50 ± 0.25 | 3.00 ± 2.00 |",
        "| graph mapping (published) |  | 0.056 ± 0.042 |  |  |  |",
    ]
    assert table.endswith("\n")


# --- (g) the real fr079 recording -------------------------------------------------------------


@pytest.mark.skipif(
    not (BENCHMARK / "fr079.relations").exists() or not (BENCHMARK / "fr079.clf.gz").exists(),
    reason="benchmark data not present",
)
def test_fr079_relations_match_the_log_and_score_raw_odometry() -> None:
    from scanguard.io import read_sequence

    rel = read_relations(BENCHMARK / "fr079.relations")
    # 1685 lines, 4 of them repeats of another line: each relation counted once (issue 24)
    assert len(rel) == 1681
    seq = read_sequence(BENCHMARK / "fr079.clf.gz")
    scan_us = set(np.rint(seq.stamps * 1e6).astype(np.int64).tolist())
    for t in (rel.t1, rel.t2):
        assert set(np.rint(t * 1e6).astype(np.int64).tolist()) <= scan_us
    assert seq.odometry is not None
    r = relation_errors(seq.stamps, seq.odometry, rel)
    assert (r.n_matched, r.n_unmatched, r.n_ambiguous_stamps) == (1681, 0, 0)
    # README: raw odometry scores 6.5 ± 13.7 m on all relations
    assert r.trans_mean == pytest.approx(6.5, rel=0.10)
    assert r.trans_std == pytest.approx(13.7, rel=0.10)
    short = relation_errors(seq.stamps, seq.odometry, rel, max_dt=10.0)
    assert short.n_matched < r.n_matched
    assert short.trans_mean < r.trans_mean


def test_a_partial_figure_is_marked_and_sets_the_exit_status() -> None:
    import typer

    from scanguard.cli.render import EXIT_PARTIAL_RELATIONS, exit_on_partial_relations

    stamps, ref = _stamps(50), _trajectory(50)
    rel = _relations(stamps, ref, PAIRS)
    est = ref.copy()
    est[[3, 10]] = np.nan  # two relations touch a non-finite pose: 5 of 7 used
    full, partial = relation_errors(stamps, ref, rel), relation_errors(stamps, est, rel)
    assert partial.partial and not full.partial
    res = type("R", (), {"relations": {"all": {"gmapping": full, "gmapping+cnn": partial}}})()
    exit_on_partial_relations(type("R", (), {"relations": {"all": {"gmapping": full}}})())
    with pytest.raises(typer.Exit) as err:
        exit_on_partial_relations(res)
    assert err.value.exit_code == EXIT_PARTIAL_RELATIONS == 3


# --- (h) an independent scorer on every shared log --------------------------------------------


def _independent_scorer(
    scan_stamps: np.ndarray, poses: np.ndarray, lines: list[list[float]], tol: float = 1e-3
) -> tuple[float, int]:
    """Kümmerle's metric written out plainly, sharing no code with scanguard: each relation
    stamp takes the nearest scan stamp within ``tol``; error = |translation of rel⁻¹ ⊕ est|."""

    def inv_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # a⁻¹ ⊕ b
        c, s = math.cos(a[2]), math.sin(a[2])
        dx, dy = b[0] - a[0], b[1] - a[1]
        return np.array([c * dx + s * dy, -s * dx + c * dy, b[2] - a[2]])

    errors = []
    for t1, t2, x, y, _z, _roll, _pitch, yaw in lines:
        i = int(np.argmin(np.abs(scan_stamps - t1)))
        j = int(np.argmin(np.abs(scan_stamps - t2)))
        if abs(scan_stamps[i] - t1) > tol or abs(scan_stamps[j] - t2) > tol:
            continue
        est = inv_compose(poses[i], poses[j])
        err = inv_compose(np.array([x, y, yaw]), est)
        errors.append(math.hypot(err[0], err[1]))
    return float(np.mean(errors)), len(errors)


@pytest.mark.parametrize("log", ["intel", "fr079", "aces"])
@pytest.mark.parametrize("decimals", [None, 5])
def test_relation_figures_agree_with_an_independent_scorer(
    tmp_path: Path, log: str, decimals: int | None
) -> None:
    if not (BENCHMARK / f"{log}.relations").exists():
        pytest.skip("benchmark data not present")
    from scanguard.io import read_sequence

    seq = read_sequence(BENCHMARK / f"{log}.clf.gz")
    text = (BENCHMARK / f"{log}.relations").read_text()
    lines = sorted({tuple(float(v) for v in ln.split()) for ln in text.splitlines() if ln.strip()})
    path = BENCHMARK / f"{log}.relations"
    if decimals is not None:  # the same relations with stamps printed with 5 decimals
        path = tmp_path / f"{log}-{decimals}.relations"
        path.write_text(
            "".join(
                f"{t1:.{decimals}f} {t2:.{decimals}f} " + " ".join(f"{v:.9f}" for v in rest) + "\n"
                for t1, t2, *rest in lines
            )
        )
        lines = [
            [float(f"{ln[0]:.{decimals}f}"), float(f"{ln[1]:.{decimals}f}"), *ln[2:]]
            for ln in lines
        ]
    ours = relation_errors(seq.stamps, seq.odometry, read_relations(path))
    theirs, n = _independent_scorer(seq.stamps, seq.odometry, [list(ln) for ln in lines])
    assert ours.n_matched == n == len(lines)
    assert ours.trans_mean == pytest.approx(theirs, abs=1e-3)
