"""The first lines of a run's summary: what the guard changed, and what the run learned.

They come before every table of ``summary.md`` (and the CLI prints them first): scans
rejected, the error with and without the guard, how many relations each figure uses, and what
self-calibration learned from the recording.
"""

from __future__ import annotations

from scanguard.apps.run_result import RunResult
from scanguard.slam.loop import trajectory_name


def relations_used_lines(res: RunResult) -> list[str]:
    """One line per trajectory: how many of the relations its figure uses, of how many."""
    table = res.relations.get("all") or {}
    tol = next(iter(table.values())).tolerance if table else 0.0
    note = [f"- relations: {res.relations_note}"] if res.relations_note else []
    return note + [
        f"- relations used by {name}: {r.used_text()} (nearest scan stamp within {tol:g} s)"
        for name, r in table.items()
    ]


def partial_relation_figures(res: RunResult) -> list[str]:
    """``"<scope>: <trajectory>"`` of every relation figure on too few relations."""
    return [
        f"{scope}: {name}"
        for scope, table in res.relations.items()
        for name, r in table.items()
        if r.partial
    ]


def guard_change_lines(res: RunResult) -> list[str]:
    """What the guard changed: scans rejected, and the error with and without it."""
    main = trajectory_name(res.backend, "cnn")
    c = res.counts
    judged = c.get("judged", 0)
    share = f" ({100 * c.get('rejected', 0) / judged:.1f} %)" if judged else ""
    fate = (
        ": each lost its match's motion term, the scan still reached the back end"
        if res.rejected_mapped
        else ""
    )
    lines = [
        f"- main result `trajectory.tum` ({main}): the guard rejected {c.get('rejected', 0)} "
        f"of {judged} judged scans{share}{fate}"
    ]
    if res.unguarded in res.trajectories:
        lines.append(f"- comparison `trajectory_unguarded.tum` ({res.unguarded}): every scan used")
    rel = res.relations.get("all") or {}
    figures = {
        "ATE": {n: float(e["ate_rmse"]) for n, e in res.errors.items()},
        "relation error (all)": {n: float(r.trans_mean) for n, r in rel.items()},
    }
    for what, by_name in figures.items():
        if main not in by_name or res.unguarded not in by_name:
            continue
        guarded, unguarded = by_name[main], by_name[res.unguarded]
        change = f" ({100 * (guarded / unguarded - 1):+.0f} %)" if unguarded > 0 else ""
        lines.append(f"- {what}: guarded {guarded:.3f} m, unguarded {unguarded:.3f} m{change}")
    return lines


def motion_lines(res: RunResult) -> list[str]:
    """Which sources moved the main instance (``motion: fused``), and the wheel noise fitted."""
    c = res.counts
    if "motion match" not in c:
        return []
    steps = max(res.n_scans - 1, 1)
    sc = res.motion_scale
    return [
        f"- motion (fused, main result): judged match in {c['motion match']} of {steps} steps, "
        + (
            f"a rejected match the wheels vouched for in {c['motion vouched_match']}, "
            if c.get("motion vouched_match")
            else ""
        )
        + (
            f"a rejected match weighted by its fault probability in {c['motion doubted_match']}, "
            if c.get("motion doubted_match")
            else ""
        )
        + f"wheels in {c['motion wheels']}, wheels flagged by a normal match "
        f"{c['motion flagged']} times, prediction alone {c['motion prediction_only']}; "
        f"wheel noise fitted on this recording: x{sc.get('wheel_scale_x', 1.0):.2f} "
        f"x{sc.get('wheel_scale_y', 1.0):.2f} x{sc.get('wheel_scale_theta', 1.0):.2f} "
        "(x, y, theta; times GMapping's odometry model)"
        + (
            f"; match variance fitted (three-cornered): x{sc['match_scale_x']:.2f} "
            f"x{sc['match_scale_y']:.2f} x{sc['match_scale_theta']:.2f}"
            if "match_scale_x" in sc
            else ""
        )
    ]


def learned_lines(res: RunResult) -> list[str]:
    """What the run learned from the recording itself (self-calibration)."""
    if not res.learned:
        return []
    k = res.learned
    return [
        f"- learned from this recording ({int(k['odometry_noise_pairs'])} matched pairs, no "
        f"reference): odometry noise x{k['odometry_noise_trans_scale']:.2f} (translation: "
        f"{k['odometry_noise_trans_floor']:.3f} m + {k['odometry_noise_trans_per_m']:.3f}/m), "
        f"x{k['odometry_noise_rot_scale']:.2f} (rotation: floor "
        f"{k['odometry_noise_rot_floor_deg']:.2f} deg)"
    ]


def self_calibration_lines(res: RunResult) -> list[str]:
    """What ``run --self-calibrate`` changed (the model it ran with is in ``self_calibration/``)."""
    k = res.self_calibration
    if not k:
        return []
    params = ", ".join(f"{n} {k[n]:.3g}" for n in ("temperature", "a", "b") if n in k)
    agree = k.get("agreement_zero_shot")
    agreed = "" if agree is None else f"; the zero-shot model agreed with {100 * agree:.1f} %"
    return [
        f"- self-calibrated on this recording ({k['method']}: {params}): CNN threshold "
        f"{k['threshold_before']:.3g} -> {k['threshold_after']:.3g}, from "
        f"{k['pairs_normal']} normal and {k['pairs_fault']} faulty {k['labels']}{agreed} "
        "(model and report in self_calibration/)"
    ]


def operating_point_lines(res: RunResult) -> list[str]:
    """Where the adaptive operating point ended (``guard.operating_point: adaptive``)."""
    k = res.operating_point
    if not k:
        return []
    state = "still warming up" if k.get("warming_up") else "adapted"
    return [
        f"- adaptive operating point ({int(k['n_scores'])} judged pairs, {state}, no "
        f"reference): CNN threshold {k['threshold']:.3g} at the end (calibrated "
        f"{k['calibrated_threshold']:.3g}); reported probabilities are shifted to decide "
        f"against the calibrated one"
    ]
