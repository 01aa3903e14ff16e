"""`scanguard.apps.run_headline`: the summary's line on which sources moved the main instance."""

from __future__ import annotations

from types import SimpleNamespace

from scanguard.apps.run_headline import motion_lines


def _res(**extra: int) -> SimpleNamespace:
    base = {"match": 575, "wheels": 581, "flagged": 19, "prediction_only": 0} | extra
    counts = {f"motion {k}": v for k, v in base.items()}
    return SimpleNamespace(counts=counts, n_scans=601, motion_scale={"wheel_scale_x": 0.3})


def test_the_motion_line_says_which_sources_moved_the_robot() -> None:
    (line,) = motion_lines(_res())
    assert line.startswith("- motion (fused, main result): judged match in 575 of 600 steps, ")
    assert "wheels in 581, wheels flagged by a normal match 19 times, prediction alone 0" in line
    assert "x0.30 x1.00 x1.00" in line and "rejected" not in line
    (line,) = motion_lines(_res(doubted_match=25, vouched_match=0))
    assert "a rejected match weighted by its fault probability in 25, wheels in 581" in line
    assert "vouched" not in line  # a count of 0 says nothing
    (line,) = motion_lines(_res(vouched_match=3))
    assert "a rejected match the wheels vouched for in 3, " in line
    assert motion_lines(SimpleNamespace(counts={}, n_scans=5, motion_scale={})) == []
