"""The files of a run: ``decisions.csv``, ``summary.md``, ``metrics.json``, maps and figures."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.apps.batch import md_cell
from scanguard.apps.run_headline import (
    guard_change_lines,
    learned_lines,
    motion_lines,
    operating_point_lines,
    relations_used_lines,
    self_calibration_lines,
)
from scanguard.apps.run_result import (
    ResolvedRun,
    RunResult,
    environment,
    gate_cells,
    judged_text,
)
from scanguard.config import save_config
from scanguard.fsutil import atomic_write_text
from scanguard.slam.grid import build_map, save_maps_figure
from scanguard.slam.loop import Instance, LoopResult, LoopStep, trajectory_name
from scanguard.slam.metrics import save_centroid_figure, save_trajectories_figure

SETUP_COLUMNS = ["odometry", "matcher", "back end", "gate"]


#: File-name suffix of each instance's outputs: the guarded default is the main result
#: (``trajectory.tum``, ``map.pgm``); the comparisons say what they are.
OUTPUT_SUFFIX = {
    "cnn": "",
    "none": "_unguarded",
    "baseline": "_classical_gate",
    "oracle": "_oracle_gate",
}


def trajectory_file(gate: str) -> str:
    """File name of an instance's trajectory: ``trajectory.tum`` for the main result."""
    return f"trajectory{OUTPUT_SUFFIX[gate]}.tum"


def map_stem(gate: str) -> str:
    """File stem of an instance's map (``map`` + ``.pgm`` / ``.yaml`` / ``.png``)."""
    return f"map{OUTPUT_SUFFIX[gate]}"


def _graph_outputs(
    instances: dict[str, Any],
    names: dict[str, str],
    grids: dict[str, Any],
    out: Path,
    title: str,
) -> list[Path]:
    """closures_<instance>.csv for every graph instance, and graph.png over the maps."""
    from scanguard.slam.graph.plot import save_graph_figure

    files: list[Path] = []
    graph_panels: dict[str, Any] = {}
    for g, inst in instances.items():
        rows = [r.as_dict() for r in inst.closures]
        tag = names[g].replace("+", "_")
        buf = io.StringIO()
        fields = list(rows[0]) if rows else ["node", "target_node", "accepted"]
        w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
        atomic_write_text(out / f"closures_{tag}.csv", buf.getvalue())
        files.append(out / f"closures_{tag}.csv")
        grid = grids.get(g)
        graph_panels[f"{names[g]} (closures: {inst.closure_judge.name})"] = (
            grid,
            inst.node_poses(),
            inst.edges,
            inst.closures,
        )
    files.append(save_graph_figure(graph_panels, out / "graph.png", title=f"{title}: pose graphs"))
    return files


def _decisions_csv(
    decisions: list[LoopStep],
    labels: dict[int, int],
    backend_ms: NDArray[np.float64],
) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(
        [
            "index",
            "stamp",
            "judged",
            "accepted",
            "reason",
            "fault_probability",
            "baseline_score",
            "label",
            "match_x",
            "match_y",
            "match_theta",
            "centroid_match",
            "t_match_ms",
            "t_detect_ms",
            "t_baseline_ms",
            "t_guard_ms",
            "t_backend_ms",
            "motion_sources",
            "wheels_flagged",
            "wheel_mahalanobis2",
        ]
    )
    for d in decisions:
        lab = labels.get(d.index, "")
        w.writerow(
            [
                d.index,
                f"{d.stamp:.6f}",
                int(d.reason != "skipped"),
                int(d.accepted),
                d.reason,
                f"{d.fault_probability:.6g}",
                f"{d.baseline_score:.6g}",
                lab,
                *(f"{v:.6g}" for v in d.match_increment),
                f"{d.centroid_match:.6g}",
                *(
                    f"{1e3 * d.timings.get(k, 0.0):.3f}"
                    for k in ("match", "detect", "baseline", "total")
                ),
                f"{backend_ms[d.index]:.3f}",
                *_motion_cells(d),
            ]
        )
    return buf.getvalue()


def _trajectory_markers(
    run: ResolvedRun, loop: LoopResult, main: NDArray[np.float64] | None
) -> dict[str, NDArray[np.float64]]:
    """Markers of the trajectory figure: where the wheels slipped, and where they were flagged.

    The first comes from a simulated recording's ``wheel_slip`` windows (on the reference),
    the second from the main instance's fused motion: the two should coincide.
    """
    marks: dict[str, NDArray[np.float64]] = {}
    slips = run.seq.metadata.get("wheel_slip")
    if slips and run.reference is not None:
        from scanguard.sim.robot import slipping  # the simulator only where it simulated

        marks["wheels slipping (simulator)"] = run.reference[slipping(run.seq.stamps, slips), :2]
    if main is not None:
        idx = [s.index for s in loop.steps if s.motion is not None and s.motion.wheels_flagged]
        marks["wheels flagged (guarded)"] = main[np.asarray(idx, dtype=np.int64), :2]
    return marks


def _motion_cells(step: LoopStep) -> list[str]:
    """Which sources moved the main instance at this step (``motion: fused``), and why."""
    m = step.motion
    if m is None:
        return ["", "", ""]
    return [m.sources, str(int(m.wheels_flagged)), f"{m.mahalanobis2:.6g}"]


def _md_row(cells: list[str]) -> str:
    return "| " + " | ".join(md_cell(c) for c in cells) + " |"


def _errors_table(res: RunResult) -> list[str]:
    """ATE / RPE / centroid table (with a reference)."""
    if not res.errors:
        return []
    lines: list[str] = []
    setup_cols = SETUP_COLUMNS
    lines += [
        _md_row(
            [
                "trajectory",
                *setup_cols,
                "ATE RMSE (m)",
                "RPE trans RMSE (m)",
                "RPE rot RMSE (deg)",
                f"RPE vs {res.unguarded}",
                "centroid dist. (m)",
            ]
        ),
        "|" + "---|" * 10,
    ]
    for name, e in res.errors.items():
        red = res.rpe_reduction(name) if name != res.unguarded else 0.0
        s = res.setup(name)
        lines.append(
            _md_row(
                [
                    name,
                    *(s[k] for k in setup_cols),
                    f"{e['ate_rmse']:.3f}",
                    f"{e['rpe_trans_rmse']:.4f}",
                    f"{e['rpe_rot_rmse_deg']:.3f}",
                    f"{-100 * red:+.1f} %",
                    f"{res.centroid.get(name, float('nan')):.4f}",
                ]
            )
        )
    lines.append("")
    return lines


def _relations_tables(res: RunResult) -> list[str]:
    """Relation error tables and the published results (with relations)."""
    if not res.relations:
        return []
    lines: list[str] = []
    setup_cols = SETUP_COLUMNS
    lines += [f"Relations: `{res.relations_file}` (Kümmerle et al. 2009); mean ± std.", ""]
    for scope, table in res.relations.items():
        lines += [
            f"Relations ({scope}):",
            "",
            _md_row(
                [
                    "trajectory",
                    *setup_cols,
                    "relations used",
                    "trans. abs. (m)",
                    "trans. sq. (m²)",
                    "rot. abs. (deg)",
                    "rot. sq. (deg²)",
                ]
            ),
            "|" + "---|" * 10,
        ]
        for name, r in table.items():
            s = res.setup(name)
            lines.append(
                _md_row(
                    [
                        name,
                        *(s[k] for k in setup_cols),
                        r.used_text()
                        + ("" if r.n_selected == r.n_relations else f" (file: {r.n_relations})"),
                        f"{r.trans_mean:.3f} ± {r.trans_std:.3f}",
                        f"{r.trans_sq_mean:.3f} ± {r.trans_sq_std:.3f}",
                        f"{r.rot_mean_deg:.2f} ± {r.rot_std_deg:.2f}",
                        f"{r.rot_sq_mean:.2f} ± {r.rot_sq_std:.2f}",
                    ]
                )
            )
        lines.append("")
    if res.published:
        lines += [
            "Published on this recording (Kümmerle et al. 2009, Table 1):",
            "",
            _md_row(["method", "trans. abs. (m)"]),
            "|---|---|",
            *(
                _md_row([f"{k} (published)", f"{m:.3f} ± {sd:.3f}"])
                for k, (m, sd) in res.published.items()
            ),
            "",
        ]
    return lines


def _closures_table(res: RunResult) -> list[str]:
    """Loop-closure decisions per graph instance."""
    if not res.closures:
        return []
    lines: list[str] = []
    lines += [
        "Loop closures (candidates the search proposed, and what each instance's judge did; "
        "labels from the reference when there is one):",
        "",
        _md_row(
            [
                "instance",
                "judge",
                "candidates",
                "accepted",
                "rejected",
                "refused by the consistency gate",
                "entered by agreement",
                "withdrawn / dropped by final check",
                "accepted but fault",
                "rejected but normal",
            ]
        ),
        "|" + "---|" * 10,
    ]
    judges = {"": "none", "cnn": "cnn", "baseline": "classical", "oracle": "oracle"}
    for name, c in res.closures.items():
        gate = name.split("+", 1)[1] if "+" in name else ""
        lines.append(
            _md_row(
                [
                    name,
                    judges.get(gate, gate),
                    str(c["candidates"]),
                    str(c["accepted"]),
                    str(c["rejected"]),
                    str(c["inconsistent"]),
                    str(c.get("agreed", 0)),
                    f"{c.get('withdrawn', 0)} / {c['dropped_final']}",
                    str(c["accepted_fault"]),
                    str(c["rejected_normal"]),
                ]
            )
        )
    lines.append("")
    return lines


def _gates_table(res: RunResult) -> list[str]:
    """Agreement of each gate with the reference labels."""
    if not res.gates:
        return []
    lines: list[str] = []
    lines += [
        _md_row(
            [
                "gate",
                "odometry",
                "matcher",
                "back end",
                "judged pairs",
                "accuracy",
                "precision",
                "recall",
                "TP",
                "FP",
                "TN",
                "FN",
            ]
        ),
        "|" + "---|" * 12,
    ]
    for g in res.gates.values():
        lines.append(_md_row([*gate_cells(res, g), *(str(v) for v in (g.tp, g.fp, g.tn, g.fn))]))
    lines.append("")
    return lines


def _latency_table(res: RunResult) -> list[str]:
    """Per-scan latency of each stage."""
    if not res.latency_ms:
        return []
    lines: list[str] = []
    lines += [
        _md_row(["stage", "odometry", "matcher", "back end", "median (ms)", "p95 (ms)"]),
        "|" + "---|" * 6,
    ]
    for k, (m, p) in res.latency_ms.items():
        lines.append(
            _md_row([k, res.odometry_source, res.matcher, res.backend, f"{m:.2f}", f"{p:.2f}"])
        )
    lines.append("")
    return lines


def summary_markdown(res: RunResult) -> str:
    """A markdown report of a run (what `scanguard run` prints, as text)."""
    lines = [
        f"# scanguard run: {res.name}",
        "",
        *guard_change_lines(res),
        f"- scans: {res.n_scans}; odometry: {res.odometry_source}; matcher: {res.matcher}; "
        f"back end: {res.backend}; reference: {res.reference_kind or 'none'}",
        f"- guard: {judged_text(res.counts)}",
        f"- baseline gate ({trajectory_name(res.backend, 'baseline')}): {res.baseline or 'none'}",
        *(f"- gate of {k}: {v}" for k, v in res.gate_names.items()),
        *relations_used_lines(res),
        *learned_lines(res),
        *self_calibration_lines(res),
        *operating_point_lines(res),
        *motion_lines(res),
        "",
    ]
    for section in (
        _errors_table,
        _relations_tables,
        _closures_table,
        _gates_table,
        _latency_table,
    ):
        lines += section(res)
    return "\n".join(lines)


def _json_safe(obj: Any) -> Any:
    """``obj`` with numpy values made plain and non-finite floats made None (JSON null)."""
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _json_safe(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def strict_json(obj: Any) -> str:
    """Standard JSON of ``obj`` (NaN and infinities become null: never bare ``NaN``)."""
    return json.dumps(_json_safe(obj), indent=2, allow_nan=False, default=str) + "\n"


def _grid_config(run: ResolvedRun, backend_name: str) -> Any:
    """The settings of the maps built from a trajectory (GMapping's resolution for GMapping)."""
    if backend_name == "gmapping":
        return run.cfg.guard.grid.model_copy(update={"resolution": run.cfg.gmapping.delta})
    return run.cfg.guard.grid


def instance_grid(run: ResolvedRun, backend: Any, trajectory: NDArray[np.float64]) -> Any:
    """The final map of one instance: its own, else built from its trajectory and used scans.

    What ``map_<instance>.pgm`` holds (and the last map frame of ``result.mcap``).
    """
    grid = backend.grid()
    if grid is None:
        seq = run.seq
        grid = build_map(
            seq.scans,
            trajectory,
            seq.laser_offset,
            include=backend.used(),
            config=_grid_config(run, backend.name),
        )
    return grid


def final_maps(
    run: ResolvedRun,
    instances: dict[str, Instance],
    names: dict[str, str],
    trajs: dict[str, NDArray[np.float64]],
) -> tuple[dict[str, NDArray[np.float64]], dict[str, Any]]:
    """Gate -> final trajectory and gate -> final map of every instance (a sink's last frame)."""
    by_gate = {g: trajs[names[g]] for g in instances}
    return by_gate, {g: instance_grid(run, i.backend, by_gate[g]) for g, i in instances.items()}


def _write_maps(
    out: Path,
    run: ResolvedRun,
    instances: dict[str, Instance],
    names: dict[str, str],
    trajs: dict[str, NDArray[np.float64]],
) -> list[Path]:
    """The maps of the guarded (main) and the unguarded instance, graph outputs, maps figure."""
    seq, ref = run.seq, run.reference
    bname = instances["cnn"].backend.name
    grid_cfg = _grid_config(run, bname)
    files: list[Path] = []
    panels: dict[str, Any] = {}
    panel_trajs: dict[str, NDArray[np.float64]] = {}
    gate_grids: dict[str, Any] = {}
    shown = (("none", f"{bname} (unguarded)"), ("cnn", f"{bname} + CNN gate (main result)"))
    for g, title in ((g, t) for g, t in shown if g in instances):
        grid = instance_grid(run, instances[g].backend, trajs[names[g]])
        stem = map_stem(g)
        files.extend(grid.save_map_server(out / stem))
        files.append(grid.save_png(out / f"{stem}.png"))
        panels[title] = grid
        gate_grids[g] = grid
        panel_trajs[title] = trajs[names[g]]
    if bname == "graph":
        graphs = {g: inst.backend for g, inst in instances.items()}
        files.extend(_graph_outputs(graphs, names, gate_grids, out, seq.name))
    if ref is not None:
        panels["reference poses"] = build_map(seq.scans, ref, seq.laser_offset, config=grid_cfg)
        panel_trajs["reference poses"] = ref
    files.append(
        save_maps_figure(
            panels,
            out / "maps_side_by_side.png",
            trajectories=panel_trajs,
            title=f"{seq.name}: maps of {bname}, odometry {run.odometry_source}",
        )
    )
    return files


def _metrics(
    res: RunResult, run: ResolvedRun, instances: dict[str, Instance], names: dict[str, str]
) -> dict[str, Any]:
    """The content of ``metrics.json``."""
    policy = instances["cnn"].gate
    return {
        "name": res.name,
        "n_scans": res.n_scans,
        "odometry_source": res.odometry_source,
        "matcher": res.matcher,
        "backend": res.backend,
        "reference_kind": res.reference_kind,
        "trajectories": {k: res.setup(k) for k in res.trajectories},
        "baseline": res.baseline,
        "baseline_threshold": policy.baseline_threshold if "baseline" in instances else None,
        "counts": res.counts,
        "errors": res.errors,
        "unguarded": res.unguarded,
        "rpe_reduction_vs_unguarded": {
            k: res.rpe_reduction(k) for k in res.errors if k != res.unguarded
        },
        "gates": {k: g.as_dict() for k, g in res.gates.items()},
        "centroid_distance_mean": res.centroid,
        "latency_ms": {k: {"median": m, "p95": p} for k, (m, p) in res.latency_ms.items()},
        "cnn_threshold": policy.cnn_threshold,
        "relations_file": res.relations_file,
        "relations_note": res.relations_note,
        "relations": {
            scope: {k: r.as_dict() for k, r in table.items()}
            for scope, table in res.relations.items()
        },
        "relations_published": res.published,
        "backend_stats": {
            names[g]: dict(getattr(inst.backend, "stats", {}) or {})
            for g, inst in instances.items()
        },
        "closures": res.closures,
        "learned": res.learned,
        "operating_point": res.operating_point,
        "self_calibration": res.self_calibration,
        "motion_wheel_scale": res.motion_scale,
        "environment": environment(),
    }


def write_run(
    out: Path,
    run: ResolvedRun,
    res: RunResult,
    loop: LoopResult,
    instances: dict[str, Instance],
    names: dict[str, str],
    centroids: dict[str, NDArray[np.float64]],
) -> list[Path]:
    """Phase 4: write every output of a run into ``out``; the files written.

    Only called after the run succeeded, so that a failed run leaves no folder holding a
    config alone.
    """
    from scanguard.io.tum import write_tum

    seq, stamps, trajs = run.seq, run.seq.stamps, res.trajectories
    out.mkdir(parents=True, exist_ok=True)
    files: list[Path] = [save_config(run.cfg, out)]
    csv_text = _decisions_csv(loop.steps, loop.labels, 1e3 * loop.backend_seconds["cnn"])
    atomic_write_text(out / "decisions.csv", csv_text)
    files.append(out / "decisions.csv")
    gate_of = {name: g for g, name in names.items()}
    for name, t in trajs.items():
        p = out / (trajectory_file(gate_of[name]) if name in gate_of else f"trajectory_{name}.tum")
        write_tum(p, stamps, t)
        files.append(p)
    if run.reference is not None:
        write_tum(out / "trajectory_reference.tum", stamps, run.reference)
        files.append(out / "trajectory_reference.tum")
    files.extend(_write_maps(out, run, instances, names, trajs))
    files.append(
        save_trajectories_figure(
            trajs,
            out / "trajectories.png",
            reference=run.reference,
            title=f"{seq.name} ({res.backend}, odometry {run.odometry_source})",
            markers=_trajectory_markers(run, loop, trajs.get(names.get("cnn", ""))),
        )
    )
    files.append(
        save_centroid_figure(
            {k: v for k, v in centroids.items() if k != "odometry"}, out / "centroid_distance.png"
        )
    )
    atomic_write_text(out / "metrics.json", strict_json(_metrics(res, run, instances, names)))
    atomic_write_text(out / "summary.md", summary_markdown(res))
    return [*files, out / "metrics.json", out / "summary.md"]
