"""End-to-end per-scan latency of the guarded loop vs a paper-style chain, same run.

ours:   ScanGuard.step = icp-paper matcher + render (model's style) + CNN (onnxruntime, 1 thread,
        no spinning) + map update (numba), with the map update in the loop and on the guard's
        map worker thread (``GuardConfig.map_in_background``); wall and thread-CPU time.
        Also: the shipped metrics-model baseline scored on every pair (``scanguard demo``),
        `FaultDetector.fault_probability` (onnx vs torch) and the GMapping feature (compiled
        kernel vs the numpy reference) on the same pairs.
paper:  cKDTree point-to-point ICP (20 iterations, SVD) + matplotlib 256x256 scatter image +
        the paper-preset CNN in eager PyTorch (contiguous NCHW), no map.

Uses the shipped model when it exists, else an untrained ``compact`` model with the same
architecture (latency does not depend on the weights). Scans: simulated lobby, 1440 beams.

    python benchmarks/bench_pipeline.py [--scans 150]
"""

from __future__ import annotations

import argparse
import io
import os
import time

import numpy as np
import torch
from scipy.spatial import cKDTree

from scanguard.detect.baselines.registry import load_detector
from scanguard.detect.detector import FaultDetector, default_model_path
from scanguard.detect.model import build_model
from scanguard.detect.render import RenderStyle
from scanguard.matching import get_matcher
from scanguard.matching.quality import _gmapping_features_numpy, gmapping_features
from scanguard.sim import simulate
from scanguard.slam.guard import GuardConfig
from scanguard.slam.judge import BaselineJudge
from scanguard.slam.stream import ScanGuard

SHIPPED_BASELINE = default_model_path().parent / "baseline.json"


def paper_icp(src: np.ndarray, dst: np.ndarray, iters: int = 20) -> np.ndarray:
    tree = cKDTree(dst)
    R, t = np.eye(2), np.zeros(2)
    for _ in range(iters):
        p = src @ R.T + t
        _, idx = tree.query(p)
        q = dst[idx]
        mp, mq = p.mean(0), q.mean(0)
        K = (p - mp).T @ (q - mq)
        U, _, Vt = np.linalg.svd(K)
        dR = (U @ Vt).T
        if np.linalg.det(dR) < 0:
            Vt[1] *= -1
            dR = (U @ Vt).T
        dt = mq - dR @ mp
        R, t = dR @ R, dR @ t + dt
        if np.hypot(*dt) < 0.01:
            break
    return np.array([t[0], t[1], np.arctan2(R[1, 0], R[0, 0])])


def paper_image(prev: np.ndarray, cur: np.ndarray, pose: np.ndarray, fig, ax) -> np.ndarray:
    c, s = np.cos(pose[2]), np.sin(pose[2])
    moved = cur @ np.array([[c, -s], [s, c]]).T + pose[:2]
    ax.cla()
    ax.set_axis_off()
    ax.scatter(prev[:, 0], prev[:, 1], s=0.5, c="red")
    ax.scatter(moved[:, 0], moved[:, 1], s=0.5, c="blue")
    buf = io.BytesIO()
    fig.savefig(buf, format="raw", dpi=64)
    img = np.frombuffer(buf.getvalue(), dtype=np.uint8).reshape(256, 256, 4)[..., :3]
    return img


def stats(v: list[float]) -> tuple[float, float]:
    a = 1e3 * np.asarray(v)
    return float(np.median(a)), float(np.percentile(a, 95))


def run_guard(
    det, scans, odometry, background: bool, baseline=None, update_map: bool = True
) -> dict[str, list[float]]:
    """Per-scan wall timings of `ScanGuard.step` (plus the thread CPU time of each step).

    With a ``baseline`` judge it is scored too (as ``scanguard demo`` does); ``total`` then
    excludes it (the CNN policy's latency) and ``baseline`` holds its time.
    """
    cfg = GuardConfig(
        policy="none", score_all=True, map_in_background=background, update_map=update_map
    )
    keys = ("match", "detect", "baseline", "map", "total", "cpu")
    rows: dict[str, list[float]] = {k: [] for k in keys}
    with ScanGuard(det, get_matcher("icp-paper"), cfg, baseline=baseline) as guard:
        guard.step(scans[0])
        guard.step(scans[1])  # warm-up (numba, onnxruntime)
        guard.reset()
        for i, sc in enumerate(scans):
            c0 = time.thread_time()
            d = guard.step(sc, odometry[i])
            cpu = time.thread_time() - c0
            if i == 0:
                continue
            for k in ("match", "detect", "baseline", "map"):
                rows[k].append(d.timings[k])
            rows["total"].append(d.timings["total"] - d.timings["baseline"])
            rows["cpu"].append(cpu)
        guard.flush()
        rows["map_worker"] = list(guard.background_map_seconds[1:])
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scans", type=int, default=150)
    args = ap.parse_args()
    torch.set_num_threads(1)
    load0 = os.getloadavg()[0]
    seq = simulate("lobby", seed=11, duration=args.scans / 10.0 + 0.1)
    scans = seq.scans[: args.scans]
    print(f"{len(scans)} scans x {scans[0].n_beams} beams, torch threads 1, onnxruntime 1 thread")

    if default_model_path().exists():
        det = FaultDetector.load(backend="onnx")
        det_torch = FaultDetector.load(backend="torch")
        which = f"shipped model ({det.style.kind} {det.style.size}px)"
    else:
        net = build_model("compact")
        det = FaultDetector(net, RenderStyle.occupancy(size=64), 0.5, backend="onnx")
        det_torch = FaultDetector(net, RenderStyle.occupancy(size=64), 0.5, backend="torch")
        which = "untrained compact model (occupancy 64px; no shipped model yet)"
    print("detector:", which)

    # every scan scored by the CNN and inserted into the map (worst case: an untrained model
    # would otherwise reject everything and skip the map update)
    rows = run_guard(det, scans, seq.odometry, background=False)
    bg = run_guard(det, scans, seq.odometry, background=True)
    # the guard alone, as when the detector is dropped into another SLAM system (no scanguard map)
    nomap = run_guard(det, scans, seq.odometry, background=False, update_map=False)
    judge = None
    if SHIPPED_BASELINE.exists():
        judge = BaselineJudge(load_detector(SHIPPED_BASELINE), str(SHIPPED_BASELINE))
        rows_b = run_guard(det, scans, seq.odometry, background=False, baseline=judge)

    # stages of one hybrid-model call on the same pairs: GMapping feature (compiled kernel vs
    # the numpy reference), render, model forward (onnxruntime vs eager PyTorch)
    matcher = get_matcher("icp-paper")
    n_pairs = min(len(scans) - 1, 60)
    pairs = []
    for i in range(1, n_pairs + 1):
        prev_pts, cur_pts = scans[i - 1].points(), scans[i].points()
        pairs.append((scans[i - 1], scans[i], matcher(cur_pts, prev_pts, None)))
    gm_rows: dict[str, list[float]] = {"kernel": [], "numpy": []}
    for name, fn in (("kernel", gmapping_features), ("numpy", _gmapping_features_numpy)):
        fn(pairs[0][0], pairs[0][1], pairs[0][2].pose)
        for a, b, m in pairs:
            t0 = time.perf_counter()
            fn(a, b, m.pose)
            gm_rows[name].append(time.perf_counter() - t0)
    fp_rows: dict[str, list[float]] = {"onnx": [], "torch": []}
    for name, d in (("onnx", det), ("torch", det_torch)):
        d.fault_probability(pairs[0][0], pairs[0][1], pairs[0][2].pose, pairs[0][2])
        for a, b, m in pairs:
            t0 = time.perf_counter()
            d.fault_probability(a, b, m.pose, m)
            fp_rows[name].append(time.perf_counter() - t0)

    # CNN alone, same images: onnxruntime (used above) vs eager PyTorch channels-last
    images = [det.render(a, b, m.pose) for a, b, m in pairs]
    feats = [det.match_features(a, b, m) if det.metric_names else None for a, b, m in pairs]
    cnn_rows: dict[str, list[float]] = {"onnx": [], "torch": []}
    for name, d in (("onnx", det), ("torch", det_torch)):
        d.predict_images(images[0][None], features=feats[0])
        for img, f in zip(images, feats, strict=True):
            t0 = time.perf_counter()
            d.predict_images(img[None], features=f)
            cnn_rows[name].append(time.perf_counter() - t0)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(4, 4), dpi=64)
    ax = fig.add_axes((0, 0, 1, 1))
    paper_net = build_model("paper").eval()
    pts = [s.points(np.float64) for s in scans]
    p_rows: dict[str, list[float]] = {k: [] for k in ("icp", "image", "cnn", "total")}
    n_paper = min(len(scans) - 1, 60)
    for i in range(1, n_paper + 1):
        t0 = time.perf_counter()
        pose = paper_icp(pts[i], pts[i - 1])
        t1 = time.perf_counter()
        img = paper_image(pts[i - 1], pts[i], pose, fig, ax)
        t2 = time.perf_counter()
        with torch.inference_mode():
            x = torch.from_numpy(img.astype(np.float32) / 255.0).permute(2, 0, 1)[None]
            paper_net(x.contiguous())
        t3 = time.perf_counter()
        for k, v in zip(p_rows, (t1 - t0, t2 - t1, t3 - t2, t3 - t0), strict=True):
            p_rows[k].append(v)
    plt.close(fig)
    load1 = os.getloadavg()[0]

    ours_med, ours_p95 = stats(rows["total"])
    bg_med, bg_p95 = stats(bg["total"])
    pap_med, pap_p95 = stats(p_rows["total"])
    print(
        f"\nload average (1 min) {load0:.1f} at start, {load1:.1f} at end, "
        f"on {os.cpu_count()} cores"
    )
    print("| chain | stage | median (ms) | p95 (ms) |")
    print("|---|---|---|---|")
    for k in ("match", "detect"):
        m, p = stats(rows[k])
        print(f"| scanguard | {k} | {m:.2f} | {p:.2f} |")
    m, p = stats(rows["map"])
    print(f"| scanguard | map update (in the loop) | {m:.2f} | {p:.2f} |")
    m, p = stats([a - b for a, b in zip(rows["total"], rows["map"], strict=True)])
    print(f"| scanguard | **total without map** | {m:.2f} | {p:.2f} |")
    nm_med, nm_p95 = stats(nomap["total"])
    print(
        "| scanguard | **total, guard without a map (update_map=False)** | "
        f"{nm_med:.2f} | {nm_p95:.2f} |"
    )
    print(f"| scanguard | **total, map in the loop** | {ours_med:.2f} | {ours_p95:.2f} |")
    m, p = stats(rows["cpu"])
    print(f"| scanguard | total, map in the loop, thread CPU time | {m:.2f} | {p:.2f} |")
    print(f"| scanguard | **total, map on the worker thread** | {bg_med:.2f} | {bg_p95:.2f} |")
    m, p = stats(bg["map_worker"])
    print(f"| scanguard | map update on the worker thread | {m:.2f} | {p:.2f} |")
    for name, v in cnn_rows.items():
        m, p = stats(v)
        print(f"| CNN forward alone | {name} | {m:.2f} | {p:.2f} |")
    for name, v in fp_rows.items():
        m, p = stats(v)
        print(f"| FaultDetector.fault_probability | {name} | {m:.2f} | {p:.2f} |")
    for name, v in gm_rows.items():
        m, p = stats(v)
        print(f"| gmapping_features ({n_pairs} pairs) | {name} | {m:.3f} | {p:.3f} |")
    if judge is not None:
        for k, label in (("baseline", f"baseline stage ({judge.name})"), ("total", "total")):
            m, p = stats(rows_b[k])
            print(f"| scanguard + baseline scored | {label} | {m:.2f} | {p:.2f} |")
        m, p = stats([a + b for a, b in zip(rows_b["total"], rows_b["baseline"], strict=True)])
        print(f"| scanguard + baseline scored | total incl. baseline | {m:.2f} | {p:.2f} |")
    for k in p_rows:
        m, p = stats(p_rows[k])
        print(f"| paper-style ({n_paper} pairs) | {k} | {m:.2f} | {p:.2f} |")
    print(
        f"\nspeed-up of the median end-to-end latency (map in the loop): "
        f"{pap_med / ours_med:.1f}x (p95 {pap_p95 / ours_p95:.1f}x); with the map thread "
        f"{pap_med / bg_med:.1f}x. Target median <= 5 ms: map in the loop "
        f"{'met' if ours_med <= 5.0 else 'NOT met'} ({ours_med:.2f} ms), map thread "
        f"{'met' if bg_med <= 5.0 else 'NOT met'} ({bg_med:.2f} ms), guard without a map "
        f"{'met' if nm_med <= 5.0 else 'NOT met'} ({nm_med:.2f} ms; paper chain / guard "
        f"{pap_med / nm_med:.1f}x)"
    )
    m_k, _ = stats(gm_rows["kernel"])
    m_n, _ = stats(gm_rows["numpy"])
    print(f"gmapping_features: compiled kernel {m_n / m_k:.1f}x faster than the numpy reference")


if __name__ == "__main__":
    main()
