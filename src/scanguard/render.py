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

In every style image rows go down and the x axis goes right, with +y pointing up (row 0 is the
largest y), like a matplotlib plot. Points are drawn as small discs of ``point_radius`` pixels
(all integer offsets within that radius), not single pixels.

Everything is plain vectorised numpy (no matplotlib, no torch) and deterministic; the batch
path `render_pairs` scatters and dilates all images at once.
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

# Half-side (m) used when all points coincide, so that the extent never collapses to zero.
_MIN_HALF_SIDE = 0.5


class RenderStyle(YamlModel):
    """How a scan pair becomes an image.

    Attributes:
        kind: ``"paper"`` (RGB, red/blue on white), ``"occupancy"`` (2 channels, auto-fitted
            extent) or ``"metric"`` (2 channels, fixed m/px centred on the previous sensor).
        size: Image side in pixels (images are square).
        resolution: Metres per pixel, used by ``"metric"`` only.
        margin: Extra border of the auto-fitted extent, as a fraction of the half-side (ignored
            by ``"metric"``).
        point_radius: Marker radius in pixels; every pixel whose offset from the point's pixel
            has length <= radius is set (0 = single pixel, 1 = plus of 5 px, 1.5 = 3x3 square).
        overlap: Colour of pixels hit by both scans in ``"paper"``: ``"mix"`` = magenta (both
            visible), ``"current"`` = blue (matplotlib painter's order, current on top).
    """

    kind: Literal["paper", "occupancy", "metric"] = "paper"
    size: int = Field(default=256, ge=8, le=4096)
    resolution: float = Field(default=0.05, gt=0.0)
    margin: float = Field(default=0.05, ge=0.0, le=1.0)
    point_radius: float = Field(default=1.0, ge=0.0, le=8.0)
    overlap: Literal["mix", "current"] = "mix"

    @model_validator(mode="after")
    def _check(self) -> RenderStyle:
        if self.kind != "paper" and self.overlap != "mix":
            raise ValueError("overlap applies to kind 'paper' only")
        return self

    @property
    def channels(self) -> int:
        """Number of image channels: 3 for ``"paper"``, 2 otherwise."""
        return 3 if self.kind == "paper" else 2

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


_XY = tuple[NDArray[np.float64], NDArray[np.float64]]


def _as_xy(points: PointsLike | ArrayLike, what: str) -> _XY:
    """Finite points as two contiguous coordinate arrays (column reductions are much faster)."""
    if isinstance(points, LaserScan):
        pts = points.points(np.float64)
    else:
        pts = np.asarray(points, dtype=np.float64)
        if pts.size == 0:
            return np.empty(0), np.empty(0)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ScanError(f"{what}: points must have shape (N, 2), got {pts.shape}")
    x = np.ascontiguousarray(pts[:, 0])
    y = np.ascontiguousarray(pts[:, 1])
    finite = np.isfinite(x) & np.isfinite(y)
    if not finite.all():
        return x[finite], y[finite]
    return x, y


def _as_pose(pose: ArrayLike, what: str) -> NDArray[np.float64]:
    p = np.asarray(pose, dtype=np.float64)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise ScanError(f"{what}: pose must be 3 finite numbers (x, y, theta), got {p!r}")
    return p


def _transform(pose: NDArray[np.float64], xy: _XY) -> _XY:
    c, s = float(np.cos(pose[2])), float(np.sin(pose[2]))
    x, y = xy
    return c * x - s * y + pose[0], s * x + c * y + pose[1]


def _extent(prev: _XY, cur: _XY, style: RenderStyle) -> tuple[float, float, float]:
    """Lower-left corner and side (m) of the square drawn area."""
    if style.kind == "metric":
        side = style.size * style.resolution
        return -side / 2.0, -side / 2.0, side
    sets = [p for p in (prev, cur) if len(p[0])]
    if not sets:
        h = _MIN_HALF_SIDE * (1.0 + style.margin)
        return -h, -h, 2.0 * h
    xlo = min(float(p[0].min()) for p in sets)
    xhi = max(float(p[0].max()) for p in sets)
    ylo = min(float(p[1].min()) for p in sets)
    yhi = max(float(p[1].max()) for p in sets)
    half = max(xhi - xlo, yhi - ylo) / 2.0
    if half < 1e-6:
        # All points coincide: any fixed extent will do, but it must not collapse to zero.
        half = _MIN_HALF_SIDE
    half *= 1.0 + style.margin
    return (xlo + xhi) / 2.0 - half, (ylo + yhi) / 2.0 - half, 2.0 * half


@cache
def _disc_offsets(radius: float) -> tuple[tuple[int, int], ...]:
    r = int(np.floor(radius))
    return tuple(
        (dy, dx)
        for dy in range(-r, r + 1)
        for dx in range(-r, r + 1)
        if dy * dy + dx * dx <= radius * radius + 1e-9
    )


def _pixel_index(
    xy: _XY, x0: float, y0: float, side: float, size: int, clip: bool
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Rows and columns of points: the nearest pixel centre, centres at ``x0 + j * side / size``.

    Rounding (not flooring) matches where matplotlib's Agg backend snaps markers, and puts the
    metric style's sensor origin exactly on the centre of pixel ``(size/2, size/2)``.
    """
    scale = size / side
    col = np.floor((xy[0] - x0) * scale + 0.5)
    row = np.floor((y0 + side - xy[1]) * scale + 0.5)
    if clip:
        # Auto-fitted extents contain every point; clipping only catches points within half a
        # pixel of the border (possible with a small margin).
        np.clip(col, 0, size - 1, out=col)
        np.clip(row, 0, size - 1, out=row)
        return row.astype(np.intp), col.astype(np.intp)
    keep = (col >= 0) & (col < size) & (row >= 0) & (row < size)
    return row[keep].astype(np.intp), col[keep].astype(np.intp)


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
        ``(x_min, y_min, side)`` in metres: the image spans ``[x_min, x_min + side]`` left to
        right and ``[y_min, y_min + side]`` bottom to top.
    """
    prev = _as_xy(previous, "previous")
    cur = _transform(_as_pose(pose, "pose"), _as_xy(current, "current"))
    return _extent(prev, cur, style)


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
    pose_arr = np.asarray(poses, dtype=np.float64)
    if n == 0 and pose_arr.size == 0:
        pose_arr = pose_arr.reshape(0, 3)
    if pose_arr.ndim != 2 or pose_arr.shape[1] != 3:
        raise ScanError(f"render_pairs: poses must have shape (B, 3), got {pose_arr.shape}")
    if len(current_list) != n or len(pose_arr) != n:
        raise ScanError(
            f"render_pairs: got {n} previous scans, {len(current_list)} current scans and "
            f"{len(pose_arr)} poses; they must match"
        )
    size = style.size
    offsets = _disc_offsets(style.point_radius)
    pad = int(np.floor(style.point_radius))
    full = size + 2 * pad
    # One flat index space over (B, full, full) so that one scatter per scan kind fills every
    # image; the canvas holds a 2-bit code per pixel: bit 0 = previous, bit 1 = current.
    flat: tuple[list[NDArray[np.intp]], list[NDArray[np.intp]]] = ([], [])
    clip = style.kind != "metric"
    for i in range(n):
        where = f"pair {i}"
        prev = _as_xy(previous_list[i], f"{where} previous")
        cur = _transform(_as_pose(pose_arr[i], f"{where} pose"), _as_xy(current_list[i], where))
        x0, y0, side = _extent(prev, cur, style)
        for ch, pts in enumerate((prev, cur)):
            if len(pts[0]):
                row, col = _pixel_index(pts, x0, y0, side, size, clip)
                flat[ch].append((i * full + row + pad) * full + col + pad)
    canvas = np.zeros((n, full, full), dtype=np.uint8)
    lin = canvas.reshape(-1)
    if flat[0]:
        lin[np.concatenate(flat[0])] = 1
    if flat[1]:
        # Duplicated indices all write the same value, so the buffered |= is still exact.
        lin[np.concatenate(flat[1])] |= 2
    if len(offsets) == 1:
        code = canvas[:, pad : pad + size, pad : pad + size]
    else:
        code = np.zeros((n, size, size), dtype=np.uint8)
        for dy, dx in offsets:
            code |= canvas[:, pad + dy : pad + dy + size, pad + dx : pad + dx + size]
    return _colourise(code, style)


def _colourise(code: NDArray[np.uint8], style: RenderStyle) -> NDArray[np.uint8]:
    """``(B, H, W)`` 2-bit codes (bit 0 previous, bit 1 current) to ``(B, H, W, C)`` uint8."""
    # Channel-by-channel strided writes of 0/1 and one in-place multiply are several times
    # faster than a lookup-table gather into the interleaved layout.
    out = np.empty((*code.shape, style.channels), dtype=np.uint8)
    if style.kind != "paper":
        np.bitwise_and(code, 1, out=out[..., 0])
        np.right_shift(code, 1, out=out[..., 1])
    else:
        red = code != 2 if style.overlap == "mix" else code < 2
        out[..., 0] = red.view(np.uint8)
        out[..., 1] = (code == 0).view(np.uint8)
        out[..., 2] = (code != 1).view(np.uint8)
    # 0/1 -> 0/255 by uint8 wrap-around (-1 == 255), cheaper than a multiply.
    np.negative(out, out=out)
    return out


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
