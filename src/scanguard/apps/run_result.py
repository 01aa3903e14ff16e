"""A run of `scanguard.apps.run.run_recording`: resolved (`ResolvedRun`), computed (`RunResult`)."""

from __future__ import annotations

import platform
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanguard.scan import ScanSequence
from scanguard.slam.config import RunConfig


@dataclass
class GateQuality:
    """Agreement of a gate with the reference labels (ambiguous pairs excluded)."""

    name: str
    tp: int
    fp: int
    tn: int
    fn: int

    @property
    def n(self) -> int:
        """Labelled pairs compared."""
        return self.tp + self.fp + self.tn + self.fn

    @property
    def accuracy(self) -> float:
        """(TP + TN) / all."""
        return (self.tp + self.tn) / self.n if self.n else float("nan")

    @property
    def precision(self) -> float:
        """TP / (TP + FP) of the fault class."""
        d = self.tp + self.fp
        return self.tp / d if d else float("nan")

    @property
    def recall(self) -> float:
        """TP / (TP + FN) of the fault class."""
        d = self.tp + self.fn
        return self.tp / d if d else float("nan")

    def as_dict(self) -> dict[str, Any]:
        """Plain dict."""
        return {
            "name": self.name,
            "tp": self.tp,
            "fp": self.fp,
            "tn": self.tn,
            "fn": self.fn,
            "accuracy": self.accuracy,
            "precision": self.precision,
            "recall": self.recall,
        }


@dataclass
class RunResult:
    """Everything `run_recording` computed (also written to the output folder).

    Attributes:
        name: Sequence name.
        n_scans: Scans processed.
        odometry_source: ``recorded``, ``simulated_from_reference``,
            ``none (zero-motion prior)`` or ``none (constant-velocity prior)``.
        reference_kind: Reference kind of the sequence (None without a reference).
        trajectories: Name -> robot poses ``(N, 3)`` (see `trajectory_names`).
        backend: The SLAM back end (``gmapping`` or ``frontend``).
        matcher: The scan matcher of the guard.
        gate_names: Back-end trajectory name -> description of the gate that guarded it.
        errors: Name -> ATE/RPE dict (empty without a reference).
        gates: ``cnn``, ``baseline``, ``none`` (accept all) -> `GateQuality` over the judged
            pairs (empty without a reference).
        centroid: Name -> mean Fig. 19 centroid distance (m).
        counts: Guard counts (``judged``, ``accepted``, ``rejected``, ``failed``,
            ``skipped``), labels, and per instance ``used <name>`` (scans in its map).
        latency_ms: Stage -> (median, p95) per-scan latency (ms).
        baseline: What gated the ``+baseline`` instance (None without one).
        relations: Scope (``all``, ``dt <= 10 s``) -> trajectory -> `RelationErrors`
            (empty without relations).
        relations_file: The relations file used (None without).
        relations_note: Why relation figures are missing or incomplete (no relation inside
            a recording cut short, a figure that could not be computed), else None.
        published: Published relation errors of that recording (method -> (mean, std) m).
        closures: ``graph`` only: instance name -> counts of its loop-closure decisions
            (`closure_counts`).
        learned: What the run learned from the recording itself (self-calibration: the
            odometry noise scales), empty when it learned nothing.
        self_calibration: ``run --self-calibrate``: what the self-calibration changed
            (`scanguard.apps.self_calibrate.self_calibration_summary`), else empty.
        operating_point: ``guard.operating_point: adaptive``: where the CNN's adaptive
            threshold ended (`scanguard.detect.adaptive.AdaptiveOperatingPoint.summary`),
            empty with the fixed one.
        motion_scale: ``motion: fused``: the main instance's fitted wheel noise scales
            (``wheel_scale_x|y|theta``, times GMapping's odometry model), else empty.
        rejected_mapped: A scan whose match the gate rejected still reached the back end
            (``RunConfig.maps_rejected_scans``: the fused default), else it was discarded.
        files: Written files.
    """

    name: str
    n_scans: int
    odometry_source: str
    reference_kind: str | None
    trajectories: dict[str, NDArray[np.float64]]
    backend: str = "frontend"
    matcher: str = "icp-paper"
    gate_names: dict[str, str] = field(default_factory=dict)
    errors: dict[str, dict[str, Any]] = field(default_factory=dict)
    gates: dict[str, GateQuality] = field(default_factory=dict)
    centroid: dict[str, float] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    latency_ms: dict[str, tuple[float, float]] = field(default_factory=dict)
    baseline: str | None = None
    relations: dict[str, dict[str, Any]] = field(default_factory=dict)
    relations_file: str | None = None
    relations_note: str | None = None
    published: dict[str, tuple[float, float]] | None = None
    closures: dict[str, dict[str, int]] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)
    learned: dict[str, float] = field(default_factory=dict)
    motion_scale: dict[str, float] = field(default_factory=dict)
    operating_point: dict[str, Any] = field(default_factory=dict)
    self_calibration: dict[str, Any] = field(default_factory=dict)
    rejected_mapped: bool = False

    @property
    def unguarded(self) -> str:
        """Name of the unguarded back-end trajectory (the reference of `rpe_reduction`)."""
        return self.backend

    def setup(self, name: str) -> dict[str, str]:
        """What produced trajectory ``name``: odometry source, matcher, back end and gate.

        The gate is ``none`` (unguarded), ``cnn``, ``baseline`` or ``oracle`` (described in
        `gate_names`), ``-`` for the odometry trajectory.
        """
        if name == "odometry":
            return {"odometry": self.odometry_source, "matcher": "-", "back end": "-", "gate": "-"}
        gate = name.split("+", 1)[1] if "+" in name else "none"
        return {
            "odometry": self.odometry_source,
            "matcher": self.matcher,
            "back end": self.backend,
            "gate": gate,
        }

    def rpe_reduction(self, name: str) -> float:
        """Relative RPE (translation) reduction of ``name`` against the unguarded back end."""
        base_name = self.unguarded
        if base_name not in self.errors or name not in self.errors:
            return float("nan")
        base = self.errors[base_name]["rpe_trans_rmse"]
        return float(1.0 - self.errors[name]["rpe_trans_rmse"] / base) if base > 0 else 0.0


def gate_cells(res: RunResult, gate: GateQuality) -> list[str]:
    """One gate's row (gate, setup, pairs, accuracy, precision, recall), for every report."""
    return [
        gate.name,
        res.odometry_source,
        res.matcher,
        res.backend,
        str(gate.n),
        f"{gate.accuracy:.3f}",
        f"{gate.precision:.3f}",
        f"{gate.recall:.3f}",
    ]


def judged_text(counts: dict[str, int]) -> str:
    """One sentence on what the guard judged (from `RunResult.counts`)."""
    text = f"{counts.get('judged', 0)} pairs judged"
    if counts.get("skipped", 0):
        text += f" ({counts['skipped']} scans skipped: no back end wanted them)"
    return (
        f"{text}; {counts.get('accepted', 0)} accepted, {counts.get('rejected', 0)} rejected "
        f"({counts.get('failed', 0)} failed matches)"
    )


@dataclass
class ResolvedRun:
    """A run after the resolve phase: what the loop, the scoring and the writers share.

    Attributes:
        seq: The recording (cut to ``max_scans``).
        cfg: The settings, resolved (labels, no-odometry adjustments).
        odometry: Robot odometry poses ``(N, 3)``, or None.
        odometry_source: Where they come from (`resolve_odometry`).
        matcher: The match function.
        matcher_name: Its name (reports).
        start: Robot pose of the first scan.
        reference: Reference robot poses ``(N, 3)``, or None.
        relations: Kümmerle relations (None without, or when none lies inside the recording).
        relations_note: Why the relations given are not scored (see `RunResult`), or None.
        published: Published relation errors of the recording (None without).
        baseline_name: Name of the classical detector of the ``+baseline`` instance (or None).
    """

    seq: ScanSequence
    cfg: RunConfig
    odometry: NDArray[np.float64] | None
    odometry_source: str
    matcher: Any
    matcher_name: str
    start: NDArray[np.float64]
    reference: NDArray[np.float64] | None
    relations: Any = None
    relations_note: str | None = None
    published: Any = None
    baseline_name: str | None = None


#: Distributions whose releases move a run's last digits (iSAM2, the ONNX runtime, numpy's
#: reductions): a run names them so that two runs' figures can be told apart.
_NUMERIC_DISTS = ("scanguard", "numpy", "scipy", "numba", "gtsam", "onnxruntime", "torch")


def environment() -> dict[str, str]:
    """Python and the versions of the numeric packages a run's results depend on.

    Read from the installed distributions' metadata (nothing is imported); ``none`` for one
    that is not installed.
    """
    out = {"python": platform.python_version()}
    for dist in _NUMERIC_DISTS:
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "none"
    return out
