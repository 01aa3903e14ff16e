"""Scan-pair images: the CNN's input (paper Section 3.2) and compact variants.

A *pair* is the previous scan (ICP target) and the current scan (ICP source) moved into the
previous sensor frame by the match estimate, ``transform_points(pose, current)``. A good match
draws the two scans on top of each other; a faulty one shows them displaced.

Styles (`RenderStyle.kind`):

* ``"paper"`` — 3-channel RGB on white, previous scan red, current scan blue, the square plotted
  extent auto-fitted to the points (plus a margin), no axes. Pixels hit by both scans are
  magenta ``(255, 0, 255)`` by default (``overlap="mix"``), so the image encodes both
  occupancy masks losslessly: R = 255 unless only the current scan is there, B = 255 unless only
  the previous scan is there, G = 255 only on background. ``overlap="current"`` reproduces
  matplotlib's painter's order instead (current drawn last, blue hides red), which is what the
  paper's plots looked like.
* ``"occupancy"`` — 2 channels (previous, current), 255 = hit, 0 = empty, same auto-fitted
  extent as ``"paper"``.
* ``"metric"`` — 2 channels like ``"occupancy"`` but at a fixed scale (``resolution`` m/px)
  centred on the previous sensor origin, so a given misalignment is always the same number of
  pixels (auto-fitting a 25 m scan into 256 px makes 10 cm less than one pixel).
* ``"multiscale"`` — several views of the same pair stacked as channels, all ``size`` px:
  the ``"occupancy"`` view (auto-fitted extent; channels 0-1) followed by one ``"metric"`` view
  per entry of ``scales`` (m/px; channels 2-3, 4-5, ...). A fine crop shows small translation
  faults, a coarse one shows rotational misalignment at long range, and the global view
  keeps the whole scene. Each view is exactly what its single-view style draws.

In every style image rows go down and the x axis goes right, with +y pointing up (row 0 is the
largest y), like a matplotlib plot. Points are drawn as small discs of ``point_radius`` pixels
(all integer offsets within that radius), not single pixels.

Rendering is a numba kernel (no matplotlib, no torch) that fills each image with its background
once and stamps every point's marker straight into the uint8 image; it is deterministic and
byte-identical to the pure-numpy reference
`scanguard.detect.render_reference.render_pairs_numpy` (kept for the tests). The kernels
themselves are in `scanguard.detect._render_kernels`.
"""

from __future__ import annotations

import logging
import struct
import zlib
from collections.abc import Sequence
from functools import cache
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field, model_validator

from scanguard.config import YamlModel
from scanguard.detect._render_kernels import (
    MODE_CURRENT,
    MODE_MIX,
    MODE_OCC,
    extents_kernel,
    render_kernel,
)
from scanguard.errors import ConfigError, ScanError
from scanguard.fsutil import atomic_write_bytes
from scanguard.scan import LaserScan

log = logging.getLogger(__name__)

__all__ = [
    "PointsLike",
    "RenderStyle",
    "render_extent",
    "render_pair",
    "render_pairs",
    "save_png",
    "to_model_input",
    "to_rgb",
]

PointsLike = NDArray[np.floating[Any]] | LaserScan
"""Points ``(N, 2)`` in a sensor frame, or a `LaserScan` (its valid beams are used)."""


class RenderStyle(YamlModel):
    """How a scan pair becomes an image.

    Attributes:
        kind: ``"paper"`` (RGB, red/blue on white), ``"occupancy"`` (2 channels, auto-fitted
            extent), ``"metric"`` (2 channels, fixed m/px centred on the previous sensor) or
            ``"multiscale"`` (occupancy view + one metric view per ``scales`` entry).
        size: Image side in pixels (images are square).
        resolution: Metres per pixel, used by ``"metric"`` only.
        margin: Extra border of the auto-fitted extent, as a fraction of the half-side (ignored
            by ``"metric"``).
        point_radius: Marker radius in pixels; every pixel whose offset from the point's pixel
            has length <= radius is set (0 = single pixel, 1 = plus of 5 px, 1.5 = 3x3 square).
        overlap: Colour of pixels hit by both scans in ``"paper"``: ``"mix"`` = magenta (both
            visible), ``"current"`` = blue (matplotlib painter's order, current on top).
        scales: Metres per pixel of the metric views of ``"multiscale"`` (ignored otherwise).
    """

    kind: Literal["paper", "occupancy", "metric", "multiscale"] = "paper"
    size: int = Field(default=256, ge=8, le=4096)
    resolution: float = Field(default=0.05, gt=0.0)
    margin: float = Field(default=0.05, ge=0.0, le=1.0)
    point_radius: float = Field(default=1.0, ge=0.0, le=8.0)
    overlap: Literal["mix", "current"] = "mix"
    scales: list[float] = Field(default_factory=lambda: [0.05, 0.2], min_length=1, max_length=3)

    @model_validator(mode="after")
    def _check(self) -> RenderStyle:
        if self.kind != "paper" and self.overlap != "mix":
            raise ValueError("overlap applies to kind 'paper' only")
        if any(not s > 0 for s in self.scales):
            raise ValueError(f"scales must be positive m/px, got {self.scales}")
        return self

    @property
    def channels(self) -> int:
        """Image channels: 3 for ``"paper"``, 2 per view for ``"multiscale"``, 2 otherwise."""
        if self.kind == "multiscale":
            return 2 + 2 * len(self.scales)
        return 3 if self.kind == "paper" else 2

    def views(self) -> list[RenderStyle]:
        """The single-view styles a ``"multiscale"`` image stacks (``[self]`` otherwise)."""
        if self.kind != "multiscale":
            return [self]
        size, radius = self.size, self.point_radius
        return [
            RenderStyle(kind="occupancy", size=size, margin=self.margin, point_radius=radius)
        ] + [
            RenderStyle(kind="metric", size=size, resolution=r, point_radius=radius)
            for r in self.scales
        ]

    @property
    def shape(self) -> tuple[int, int, int]:
        """Image shape ``(H, W, C)``."""
        return (self.size, self.size, self.channels)

    @classmethod
    def paper(cls, size: int = 256, **kw: Any) -> RenderStyle:
        """The paper's red/blue RGB style (256x256 by default)."""
        return cls(kind="paper", size=size, **kw)

    @classmethod
    def occupancy(cls, size: int = 128, **kw: Any) -> RenderStyle:
        """Two-channel occupancy with the auto-fitted extent."""
        return cls(kind="occupancy", size=size, **kw)

    @classmethod
    def metric(cls, size: int = 256, resolution: float = 0.05, **kw: Any) -> RenderStyle:
        """Two-channel occupancy at ``resolution`` m/px centred on the previous sensor."""
        return cls(kind="metric", size=size, resolution=resolution, **kw)

    @classmethod
    def multiscale(
        cls, size: int = 64, scales: Sequence[float] = (0.05, 0.2), **kw: Any
    ) -> RenderStyle:
        """Occupancy view plus metric views at ``scales`` m/px, stacked as channels."""
        return cls(kind="multiscale", size=size, scales=list(scales), **kw)


def _as_array(points: PointsLike | ArrayLike, what: str) -> NDArray[np.floating[Any]]:
    """``(N, 2)`` floating points, without a copy when possible."""
    raw = points.points() if isinstance(points, LaserScan) else points
    pts = np.asarray(raw)
    if not np.issubdtype(pts.dtype, np.floating):
        pts = pts.astype(np.float64)
    if pts.size == 0:
        return np.empty((0, 2))
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ScanError(f"{what}: points must have shape (N, 2), got {pts.shape}")
    return pts


def _as_pose(pose: ArrayLike, what: str) -> NDArray[np.float64]:
    p = np.asarray(pose, dtype=np.float64)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise ScanError(f"{what}: pose must be 3 finite numbers (x, y, theta), got {p!r}")
    return p


def _check_poses(poses: ArrayLike, n: int, n_current: int) -> NDArray[np.float64]:
    pose_arr = np.asarray(poses, dtype=np.float64)
    if n == 0 and pose_arr.size == 0:
        pose_arr = pose_arr.reshape(0, 3)
    if pose_arr.ndim != 2 or pose_arr.shape[1] != 3:
        raise ScanError(f"render_pairs: poses must have shape (B, 3), got {pose_arr.shape}")
    if n_current != n or len(pose_arr) != n:
        raise ScanError(
            f"render_pairs: got {n} previous scans, {n_current} current scans and "
            f"{len(pose_arr)} poses; they must match"
        )
    if np.isfinite(pose_arr).all():
        return pose_arr
    bad = ~np.isfinite(pose_arr).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ScanError(f"pair {i} pose: must be 3 finite numbers, got {pose_arr[i]!r}")
    return pose_arr


@cache
def _disc_offsets(radius: float) -> tuple[tuple[int, int], ...]:
    r = int(np.floor(radius))
    return tuple(
        (dy, dx)
        for dy in range(-r, r + 1)
        for dx in range(-r, r + 1)
        if dy * dy + dx * dx <= radius * radius + 1e-9
    )


@cache
def _disc_arrays(radius: float) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    offs = np.array(_disc_offsets(radius), dtype=np.intp).reshape(-1, 2)
    return np.ascontiguousarray(offs[:, 0]), np.ascontiguousarray(offs[:, 1])


# Pairs packed per kernel call: bounds the temporary concatenated point array (a 1440+1440-beam
# pair is ~23 kB as float32) without measurable per-call overhead.
_KERNEL_CHUNK = 64


def _pack(
    previous_list: Sequence[PointsLike | ArrayLike],
    current_list: Sequence[PointsLike | ArrayLike],
    offset: int,
) -> tuple[NDArray[np.floating[Any]], NDArray[np.intp]]:
    """All points of a run of pairs in one ``(K, 2)`` array (prev_0, cur_0, prev_1, ...)."""
    arrays = []
    counts = [0]
    for i, (p, c) in enumerate(zip(previous_list, current_list, strict=True)):
        a = _as_array(p, f"pair {offset + i} previous")
        b = _as_array(c, f"pair {offset + i} current")
        counts += [counts[-1] + len(a), counts[-1] + len(a) + len(b)]
        # Empty arrays are left out: their float64 dtype would upcast float32 scans.
        if len(a):
            arrays.append(a)
        if len(b):
            arrays.append(b)
    starts = np.array(counts, dtype=np.intp)
    if not arrays:
        return np.empty((0, 2)), starts
    pts = arrays[0] if len(arrays) == 1 else np.concatenate(arrays)
    if pts.dtype != np.float32 and pts.dtype != np.float64:
        pts = pts.astype(np.float64)  # the kernel is compiled for these two only
    return np.ascontiguousarray(pts), starts


def _trig(poses: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    # numpy's cos/sin, as in the reference path (libm's may differ in the last bit).
    return np.cos(poses[:, 2]), np.sin(poses[:, 2])


def _run_kernel(
    previous_list: Sequence[PointsLike | ArrayLike],
    current_list: Sequence[PointsLike | ArrayLike],
    poses: NDArray[np.float64],
    style: RenderStyle,
    out: NDArray[np.uint8],
    extents: NDArray[np.float64],
) -> None:
    mode = (
        MODE_OCC
        if style.kind != "paper"
        else (MODE_MIX if style.overlap == "mix" else MODE_CURRENT)
    )
    # An auto-fitted extent with a margin of at least half a pixel keeps every point inside;
    # only a thinner margin can push a border point just past the last pixel.
    clip = style.kind != "metric" and (
        style.margin * style.size / (2.0 + 2.0 * style.margin) <= 0.5 + 1e-9
    )
    dys, dxs = _disc_arrays(style.point_radius)
    cos, sin = _trig(poses)
    poses = np.ascontiguousarray(poses)
    for start in range(0, len(previous_list), _KERNEL_CHUNK):
        stop = min(start + _KERNEL_CHUNK, len(previous_list))
        pts, starts = _pack(previous_list[start:stop], current_list[start:stop], start)
        render_kernel(
            pts, starts, cos[start:stop], sin[start:stop], poses[start:stop], mode,
            style.kind == "metric", clip, style.margin, style.resolution, dys, dxs,
            out[start:stop], extents[start:stop],
        )  # fmt: skip


def render_extent(
    previous: PointsLike | ArrayLike,
    current: PointsLike | ArrayLike,
    pose: ArrayLike,
    style: RenderStyle,
) -> tuple[float, float, float]:
    """The square area an image covers, in the previous sensor frame.

    Args:
        previous: Previous scan points ``(N, 2)`` (or a `LaserScan`).
        current: Current scan points ``(M, 2)`` in the current sensor frame (or a `LaserScan`).
        pose: Match estimate (pose of the current sensor in the previous sensor frame).
        style: Render style.

    Returns:
        ``(x_min, y_min, side)`` in metres: pixel centres are at ``x_min + j * side / size``
        (column ``j``, left to right) and ``y_min + side - i * side / size`` (row ``i``).
    """
    poses = _check_poses(np.asarray(pose, dtype=np.float64).reshape(1, -1), 1, 1)
    pts, starts = _pack([previous], [current], 0)
    e = np.empty((1, 3))
    extents_kernel(
        pts, starts, *_trig(poses), poses, style.kind == "metric", style.size, style.margin,
        style.resolution, e,
    )  # fmt: skip
    return float(e[0, 0]), float(e[0, 1]), float(e[0, 2])


def render_pairs(
    previous_list: Sequence[PointsLike | ArrayLike],
    current_list: Sequence[PointsLike | ArrayLike],
    poses: ArrayLike,
    style: RenderStyle,
) -> NDArray[np.uint8]:
    """Render a batch of scan pairs.

    Args:
        previous_list: ``B`` previous scans, each points ``(N_i, 2)`` or a `LaserScan`.
        current_list: ``B`` current scans in their own sensor frame.
        poses: ``(B, 3)`` match estimates; current points are drawn at
            ``transform_points(poses[i], current_list[i])``.
        style: Render style.

    Returns:
        ``(B, H, W, C)`` uint8 images (see the module docstring for the colour rules). Pairs
        without any point give a blank image.

    Raises:
        ScanError: Inconsistent batch lengths or malformed points/poses.
    """
    n = len(previous_list)
    pose_arr = _check_poses(poses, n, len(current_list))
    out = np.empty((n, *style.shape), dtype=np.uint8)
    extents = np.empty((n, 3))
    if style.kind != "multiscale":
        _run_kernel(previous_list, current_list, pose_arr, style, out, extents)
        return out
    # One kernel pass per view into a scratch buffer; the copy into the interleaved channels
    # costs far less than the point stamping.
    view_out = np.empty((n, style.size, style.size, 2), dtype=np.uint8)
    for v, view in enumerate(style.views()):
        _run_kernel(previous_list, current_list, pose_arr, view, view_out, extents)
        out[..., 2 * v : 2 * v + 2] = view_out
    return out


# Colour of each 2-bit code (0 none, 1 previous, 2 current, 3 both) per (kind, overlap).
_RGB_MIX = np.array([[255, 255, 255], [255, 0, 0], [0, 0, 255], [255, 0, 255]], dtype=np.uint8)
_RGB_CURRENT = np.array([[255, 255, 255], [255, 0, 0], [0, 0, 255], [0, 0, 255]], dtype=np.uint8)
_OCC = np.array([[0, 0], [255, 0], [0, 255], [255, 255]], dtype=np.uint8)
_LUTS = {
    ("paper", "mix"): _RGB_MIX,
    ("paper", "current"): _RGB_CURRENT,
    ("occupancy", "mix"): _OCC,
    ("metric", "mix"): _OCC,
}


def _colourise(
    code: NDArray[np.uint8], style: RenderStyle, out: NDArray[np.uint8] | None = None
) -> NDArray[np.uint8]:
    """``(..., H, W)`` 2-bit codes (bit 0 previous, bit 1 current) to ``(..., H, W, C)`` uint8."""
    if out is None:
        out = np.empty((*code.shape, style.channels), dtype=np.uint8)
    background, plan = _colour_plan(style.kind, style.overlap)
    # Scan images are mostly background: fill it at memset speed, then write only the drawn
    # pixels, channel by channel on the flat buffer (far cheaper than strided whole-image
    # writes or a row gather into the interleaved layout).
    flat_out = out.reshape(-1)
    flat_out.fill(background)
    flat_code = code.reshape(-1)
    drawn = np.flatnonzero(flat_code != 0)  # bool nonzero is several times faster than uint8
    codes = flat_code[drawn]
    drawn *= out.shape[-1]
    for k, value in plan:
        flat_out[drawn + k] = value if isinstance(value, int) else value[codes]
    return out


@cache
def _colour_plan(
    kind: str, overlap: str
) -> tuple[int, tuple[tuple[int, int | NDArray[np.uint8]], ...]]:
    """Background value and, per channel that drawn pixels change, a constant or a lookup."""
    lut = _LUTS[kind, overlap]
    plan: list[tuple[int, int | NDArray[np.uint8]]] = []
    for k in range(lut.shape[1]):
        values = lut[:, k]
        if (values[1:] == values[0]).all():
            continue
        plan.append((k, int(values[1]) if (values[1:] == values[1]).all() else values))
    return int(lut[0, 0]), tuple(plan)


def render_pair(
    previous: PointsLike | ArrayLike,
    current: PointsLike | ArrayLike,
    pose: ArrayLike,
    style: RenderStyle | None = None,
) -> NDArray[np.uint8]:
    """Render one scan pair.

    Args:
        previous: Previous scan points ``(N, 2)`` (ICP target) or a `LaserScan`.
        current: Current scan points ``(M, 2)`` in the current sensor frame, or a `LaserScan`.
        pose: Match estimate: pose of the current sensor frame in the previous sensor frame.
        style: Render style (default: the paper's 256x256 RGB).

    Returns:
        ``(H, W, C)`` uint8 image.
    """
    return render_pairs([previous], [current], np.asarray(pose)[None], style or RenderStyle())[0]


def to_model_input(images: ArrayLike) -> NDArray[np.float32]:
    """Convert uint8 images to the model's input layout.

    Args:
        images: ``(B, H, W, C)`` or a single ``(H, W, C)`` uint8 image.

    Returns:
        ``(B, C, H, W)`` float32 in ``[0, 1]`` (pixel / 255).
    """
    arr = np.asarray(images)
    if arr.ndim == 3:
        arr = arr[None]
    if arr.ndim != 4:
        raise ScanError(f"to_model_input: expected (B, H, W, C) images, got shape {arr.shape}")
    out = np.empty((arr.shape[0], arr.shape[3], arr.shape[1], arr.shape[2]), dtype=np.float32)
    np.multiply(arr.transpose(0, 3, 1, 2), np.float32(1.0 / 255.0), out=out)
    return out


def to_rgb(image: ArrayLike) -> NDArray[np.uint8]:
    """A viewable RGB version of any style's image (paper colours for 2-channel images).

    Args:
        image: ``(H, W)``, ``(H, W, 2)`` (previous, current) or ``(H, W, 3)``, or batched with a
            leading ``B``.

    Returns:
        uint8 RGB with the same leading shape and a last dimension of 3.
    """
    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        raise ScanError(f"to_rgb: expected a uint8 image, got {arr.dtype}")
    if arr.shape[-1] == 3 and arr.ndim >= 3:
        return arr
    if arr.shape[-1] == 2 and arr.ndim >= 3:
        code = (arr[..., 0] > 127).astype(np.uint8)
        code |= (arr[..., 1] > 127).astype(np.uint8) * np.uint8(2)
        flat_code = code.reshape(-1, *code.shape[-2:])
        return _colourise(flat_code, RenderStyle(kind="paper")).reshape(*arr.shape[:-1], 3)
    if arr.ndim == 2:
        return np.repeat(arr[..., None], 3, axis=-1)
    raise ScanError(f"to_rgb: unsupported image shape {arr.shape}")


def _png_bytes(image: NDArray[np.uint8]) -> bytes:
    h, w = image.shape[:2]
    channels = 1 if image.ndim == 2 else image.shape[2]
    colour_type = {1: 0, 3: 2, 4: 6}[channels]
    raw = np.empty((h, 1 + w * channels), dtype=np.uint8)
    raw[:, 0] = 0  # filter type "None" on every row: simple and deterministic
    raw[:, 1:] = image.reshape(h, w * channels)

    def chunk(tag: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + tag
            + data
            + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)
        )

    header = struct.pack(">IIBBBBB", w, h, 8, colour_type, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6))
        + chunk(b"IEND", b"")
    )


def save_png(path: str | Path, image: ArrayLike) -> Path:
    """Write an image as PNG, atomically (temporary file, then rename).

    Args:
        path: Destination file.
        image: uint8 ``(H, W)`` grey, ``(H, W, 3)`` RGB, ``(H, W, 4)`` RGBA, or ``(H, W, 2)``
            (previous, current) which is saved in paper colours (see `to_rgb`).

    Returns:
        The path written.

    Raises:
        ConfigError: The array is not a uint8 image of a supported shape.
    """
    arr = np.asarray(image)
    if arr.dtype != np.uint8 or arr.ndim not in (2, 3) or min(arr.shape[:2]) < 1:
        raise ConfigError(f"{path}: cannot save a {arr.dtype} array of shape {arr.shape} as PNG")
    if arr.ndim == 3 and arr.shape[2] == 2:
        arr = to_rgb(arr)
    if arr.ndim == 3 and arr.shape[2] not in (1, 3, 4):
        raise ConfigError(f"{path}: cannot save an image with {arr.shape[2]} channels as PNG")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    p = Path(path)
    atomic_write_bytes(p, _png_bytes(np.ascontiguousarray(arr)))
    log.debug("wrote %s (%dx%d)", p, arr.shape[1], arr.shape[0])
    return p
