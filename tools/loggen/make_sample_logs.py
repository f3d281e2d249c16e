"""Procedural camera logs with ground truth: a camera drives a street route and revisits places.

The world is a 2.5D street: walls are polylines offset from the route's centre line, cut into
facades (each with its own procedural texture: value noise plus windows, stripes, panels,
bricks or posters, random parameters per facade) and opened by a few alleys. A pinhole camera
ray-casts one ray per image column (distance-dependent wall height), with a textured ground
and a cloudy sky. The light direction, diffuse strength, exposure gain and gamma drift slowly,
so revisits are lit differently; the camera's speed varies along the route and between laps,
it wobbles a little sideways and in heading, and the images get Gaussian noise and JPEG.

Routes (all revisits happen in the same direction except where said):
* loops      - several laps of a closed street loop (a rounded, slightly wavy block);
* figure8    - laps of a figure eight; the two passes through the crossing are about 90 degrees
               apart, so they are not loops under the heading threshold;
* outandback - a winding dead-end street driven out, turned in place (180 degrees, 6 s), driven
               back, and again. The back leg sees the same walls in the opposite direction:
               the ground truth does NOT count it (heading differs by 180 degrees). Same-direction
               legs of later cycles (out vs out, back vs back) are loops.

Ground truth (computed from the true camera poses as written to the poses .csv, rounded as
written): GT[i, j] = 1 for j < i when
* the positions are within GT_DISTANCE_M = 2.0 m,
* the headings are within GT_HEADING_DEG = 20 degrees,
* frame j is at least GT_MIN_AGE_S = 40 s older (the detector's default kappa), and
* the camera travelled at least GT_MIN_TRAVEL_M = 20 m between them (sum of the distances
  between consecutive frames), so that a parked camera does not "revisit" its own place.
Saved as .npz key "gt" (uint8, dense) up to DENSE_GT_MAX_FRAMES frames, above that as a
scipy.sparse CSR .npz (scipy.sparse.load_npz). Poses (frame, stamp_ns, t, x, y, yaw) go to a
.csv, the run's parameters and facts (parked span, dropped frames, counts) to a .json.

With --depth, every log also carries an aligned depth image per camera frame, as an RGB-D
camera's ROS driver writes it (REP 118): `/camera/depth/image` (sensor_msgs/Image, Foxglove:
RawImage; same stamp, size and pinhole model as the camera image) with its own
`/camera/depth/camera_info`. Encoding 32FC1: metres along the optical axis (z, not the ray
length), NaN where a ray hits nothing (the sky); or, with --depth-encoding 16UC1, millimetres
with 0 for nothing hit or farther than 65.535 m. The depth is the ray-cast geometry itself: no
noise, no blur, no quantisation but the encoding's.

With --season-change, the frames from the lap boundary nearest the middle of the drive on show
the same streets in another season (snow on the ground, ledges and plinths, frosted and
flattened facades, an overcast sky, another exposure): the poses and the ground truth are
those of the same drive without it, and the .json names the first frame of the new season.

Every output is byte-deterministic per seed and parameters (also with --jobs > 1): frame i's
noise comes from its own generator seeded by (seed, i). See camera_log_writers for the
containers. Run `PYTHONPATH=tools python -m loggen.make_sample_logs --samples` (from the
repository root) to regenerate sample_logs/.
"""

from __future__ import annotations

import argparse
import ctypes
import io
import json
import math
import multiprocessing
import sys
import time
import zipfile
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from multiprocessing.pool import AsyncResult
from pathlib import Path
from typing import Any, Final, Literal

import cv2
import numpy as np
import numpy.typing as npt
from scipy import sparse
from scipy.spatial import cKDTree

from loggen import camera_log_writers as clw

# Array aliases name the intended dtype; they are NDArray[Any] because numpy's stubs lose the
# dtype through most arithmetic, and casts everywhere would hide the code.
F32 = npt.NDArray[Any]  # float32
F64 = npt.NDArray[Any]  # float64
I64 = npt.NDArray[Any]  # int64
U8 = npt.NDArray[Any]  # uint8
Route = Literal["loops", "figure8", "outandback"]
DepthEncoding = Literal["32FC1", "16UC1"]
DEPTH_ENCODINGS: Final[tuple[DepthEncoding, ...]] = ("32FC1", "16UC1")
ROUTES: Final[tuple[Route, ...]] = ("loops", "figure8", "outandback")

# -- documented constants --------------------------------------------------------------------------

GT_DISTANCE_M: Final = 2.0
GT_HEADING_DEG: Final = 20.0
GT_MIN_AGE_S: Final = 40.0
GT_MIN_TRAVEL_M: Final = 20.0
DENSE_GT_MAX_FRAMES: Final = 6000

START_NS: Final = 1_700_000_000 * 1_000_000_000  # first frame stamp: 2023-11-14T22:13:20Z
HFOV_DEG: Final = 70.0
CAMERA_HEIGHT_M: Final = 1.6
HALF_WIDTH_M: Final = 4.0  # street: walls 4 m either side of the centre line
SPEED_MPS: Final = 1.4  # mean driving speed before curve slow-down and variation
TURN_S: Final = 6.0  # out-and-back: time of a 180-degree turn in place
TEXELS_PER_M: Final = 40  # facade texture resolution, independent of the image size
SIM_HZ: Final = 100.0  # the true trajectory and the odometry are integrated at this rate
VIEW_RANGE_M: Final = 70.0  # walls farther than this are not ray-cast (they are in the haze)


# -- smooth random functions ---------------------------------------------------------------------


class SmoothNoise:
    """A random sum of sinusoids: smooth, deterministic, zero-mean, roughly unit amplitude."""

    def __init__(self, rng: np.random.Generator, min_period: float, max_period: float, n: int = 6):
        self.freq = 2 * np.pi / rng.uniform(min_period, max_period, n)
        self.phase = rng.uniform(0, 2 * np.pi, n)
        self.amp = rng.uniform(0.5, 1.0, n)
        self.amp *= math.sqrt(2.0) / np.sqrt(np.sum(self.amp**2))

    def __call__(self, x: npt.ArrayLike) -> F64:
        xs = np.asarray(x, dtype=np.float64)
        out = np.zeros(xs.shape)
        for f, p, a in zip(self.freq, self.phase, self.amp, strict=True):
            out += a * np.sin(f * xs + p)
        return out


def value_noise(rng: np.random.Generator, shape: tuple[int, int], cell: float) -> F32:
    """Smooth noise in [-1, 1] with features about `cell` texels wide (bicubic upsampling)."""
    h, w = shape
    cell = max(cell, 1.0)
    small = rng.uniform(-1, 1, (int(h / cell) + 3, int(w / cell) + 3)).astype(np.float32)
    big = cv2.resize(small, None, fx=cell, fy=cell, interpolation=cv2.INTER_CUBIC)
    return np.clip(big[:h, :w], -1.0, 1.0)


# -- routes -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Path2D:
    """A centre line sampled every `ds` metres; closed paths do not repeat the first point."""

    points: F64  # (M, 2)
    closed: bool
    ds: float

    @property
    def length(self) -> float:
        return self.ds * (len(self.points) if self.closed else len(self.points) - 1)

    def _index(self, s: F64) -> tuple[I64, I64, F64]:
        m = len(self.points)
        x = np.mod(s, self.length) if self.closed else np.clip(s, 0.0, self.length)
        i = np.minimum((x / self.ds).astype(np.int64), m - 1 if self.closed else m - 2)
        w = x / self.ds - i
        j = (i + 1) % m if self.closed else i + 1
        return i, j, w

    def position(self, s: npt.ArrayLike) -> F64:
        i, j, w = self._index(np.asarray(s, dtype=np.float64))
        pos: F64 = self.points[i] * (1 - w)[..., None] + self.points[j] * w[..., None]
        return pos

    def tangent(self, s: npt.ArrayLike) -> F64:
        """Unit tangents (central differences over one metre)."""
        s = np.asarray(s, dtype=np.float64)
        d = self.position(s + 0.5) - self.position(s - 0.5)
        unit: F64 = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-9)
        return unit

    def curvature(self, s: npt.ArrayLike) -> F64:
        s = np.asarray(s, dtype=np.float64)
        t0, t1 = self.tangent(s - 1.0), self.tangent(s + 1.0)
        cross = t0[..., 0] * t1[..., 1] - t0[..., 1] * t1[..., 0]
        dot = np.sum(t0 * t1, axis=-1)
        kappa: F64 = np.arctan2(cross, dot) / 2.0  # turn over 2 m, per metre
        return kappa


def resample(points: F64, closed: bool, ds: float) -> Path2D:
    """Resample a dense polyline at equal arc-length steps."""
    pts = np.vstack([points, points[:1]]) if closed else points
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    n = round(cum[-1] / ds)
    step = cum[-1] / n
    s = np.arange(n if closed else n + 1) * step
    out = np.column_stack([np.interp(s, cum, pts[:, 0]), np.interp(s, cum, pts[:, 1])])
    return Path2D(out, closed, step)


def _wavy(points: F64, closed: bool, rng: np.random.Generator, amplitude: float) -> F64:
    """Bend a polyline sideways by a smooth random offset (long wavelengths: gentle curves)."""
    path = resample(points, closed, 0.25)
    s = np.arange(len(path.points)) * path.ds
    if closed:  # periodic: integer numbers of waves per lap
        k = rng.integers(2, 6, 3)
        off = sum(
            rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * kk * s / path.length + rng.uniform(0, 6.3))
            for kk in k
        )
    else:
        off = SmoothNoise(rng, 25.0, 60.0, 3)(s)
    off = amplitude * off / max(float(np.max(np.abs(off))), 1e-9)
    t = path.tangent(s)
    normal = np.column_stack([-t[:, 1], t[:, 0]])
    bent: F64 = path.points + normal * off[:, None]
    return bent


def loop_centerline(lap_length: float, rng: np.random.Generator) -> Path2D:
    """A rounded rectangle (a city block) with slightly wavy sides, driven counter-clockwise."""
    aspect = rng.uniform(1.3, 2.2)
    radius = rng.uniform(HALF_WIDTH_M + 2.5, HALF_WIDTH_M + 5.0)
    # perimeter = 2 (w + h) - (8 - 2 pi) r, with h = w / aspect
    width = (lap_length + (8 - 2 * np.pi) * radius) / (2 * (1 + 1 / aspect))
    height = width / aspect
    radius = min(radius, height / 2)
    a = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
    # A superellipse-free construction: clamp a rectangle's corners onto circles.
    hx, hy = width / 2 - radius, height / 2 - radius
    x = np.cos(a) * radius + np.sign(np.cos(a)) * hx
    y = np.sin(a) * radius + np.sign(np.sin(a)) * hy
    pts = _wavy(np.column_stack([x, y]), True, rng, 0.6)
    return resample(pts, True, 0.25)


def figure8_centerline(lap_length: float, rng: np.random.Generator) -> Path2D:
    """A lemniscate of Gerono, lobes taller than wide (the passes cross at 60 to 70 degrees)."""
    ratio = rng.uniform(1.4, 1.8)
    a = np.linspace(0, 2 * np.pi, 4000, endpoint=False)
    unit = np.column_stack([np.sin(a), ratio * np.sin(a) * np.cos(a)])
    perimeter = float(np.sum(np.linalg.norm(np.diff(np.vstack([unit, unit[:1]]), axis=0), axis=1)))
    pts = _wavy(unit * (lap_length / perimeter), True, rng, 0.5)
    return resample(pts, True, 0.25)


def outandback_centerline(lap_length: float, rng: np.random.Generator) -> Path2D:
    """A winding open street of half the lap length (curvature is a smooth random function)."""
    length = lap_length / 2
    s = np.arange(0.0, length + 0.125, 0.25)
    curvature = SmoothNoise(rng, 20.0, 50.0, 4)(s) / (HALF_WIDTH_M + 10.0)
    heading = rng.uniform(0, 2 * np.pi) + np.cumsum(curvature) * 0.25
    pts = np.cumsum(np.column_stack([np.cos(heading), np.sin(heading)]) * 0.25, axis=0)
    return resample(pts, False, 0.25)


CENTERLINES: Final[dict[Route, Callable[[float, np.random.Generator], Path2D]]] = {
    "loops": loop_centerline,
    "figure8": figure8_centerline,
    "outandback": outandback_centerline,
}


# -- facade textures ------------------------------------------------------------------------------


def _windows(rng: np.random.Generator, u: F32, h: F32, height: float) -> tuple[F32, F32]:
    """(mask, albedo) of a grid of windows: floors, columns, per-window glass brightness."""
    floor_h = rng.uniform(2.7, 3.6)
    pitch = rng.uniform(1.3, 3.2)
    win_w = pitch * rng.uniform(0.35, 0.7)
    win_h = floor_h * rng.uniform(0.35, 0.6)
    sill = rng.uniform(0.7, 1.0)
    shifted = u - rng.uniform(0, pitch)
    col = np.floor(shifted / pitch)
    across = np.abs(shifted - col * pitch - pitch / 2)  # distance from the window's axis
    row = np.floor(h / floor_h)
    hv = h - row * floor_h
    ground_floor = rng.random() < 0.5  # shop windows on the ground floor, or a blank one
    mask = (across < win_w / 2) & (hv > sill) & (hv < sill + win_h)
    mask &= (row >= 1) | ground_floor
    mask &= h < height - 0.6
    glass = rng.uniform(0.03, 0.35, (64, 256)).astype(np.float32)
    glass[rng.random((64, 256)) < rng.uniform(0.0, 0.25)] = rng.uniform(0.75, 0.95)  # lit
    value: F32 = glass[row.astype(np.int64) % 64, col.astype(np.int64) % 256]
    value = value + 0.12 * (hv - sill) / win_h  # a reflection gradient
    frame = (across < win_w / 2 + 0.08) & (hv > sill - 0.1)
    frame &= (hv < sill + win_h + 0.08) & ~mask & ((row >= 1) | ground_floor) & (h < height - 0.6)
    return (mask | frame).astype(np.float32), np.where(frame, rng.uniform(0.6, 0.95), value)


def _bands(rng: np.random.Generator, coord: F32, extent: float, lo: float, hi: float) -> F32:
    """Albedo of random bands along one coordinate (stripes across or panels along a wall)."""
    widths = rng.uniform(lo, hi, int(extent / lo) + 2)
    edges = np.cumsum(widths)
    albedo = rng.uniform(0.15, 0.85, len(widths) + 1).astype(np.float32)
    return albedo[np.searchsorted(edges, coord)]


def _bricks(rng: np.random.Generator, u: F32, h: F32) -> F32:
    bw, bh = rng.uniform(0.2, 0.32), rng.uniform(0.06, 0.1)
    row = np.floor(h / bh)
    shifted = u + (row % 2) * bw / 2
    col = np.floor(shifted / bw)
    jitter = rng.uniform(-0.12, 0.12, (512, 128)).astype(np.float32)
    value = jitter[row.astype(np.int64) % 512, col.astype(np.int64) % 128]
    mortar = (np.mod(h, bh) < 0.015) | (np.mod(shifted, bw) < 0.015)
    return np.where(mortar, rng.uniform(-0.3, 0.3), value).astype(np.float32)


def _posters(rng: np.random.Generator, tex: F32, u: F32, h: F32, length: float) -> None:
    """Paste a few high-contrast posters near the ground (the most distinctive cue)."""
    for _ in range(rng.integers(0, 4)):
        pw, ph = rng.uniform(0.6, 2.2), rng.uniform(0.8, 2.4)
        u0, h0 = rng.uniform(0, max(length - pw, 0.1)), rng.uniform(0.3, 1.6)
        inside = (u >= u0) & (u < u0 + pw) & (h >= h0) & (h < h0 + ph)
        if not inside.any():
            continue
        rows, cols = np.nonzero(inside)
        r0, c0 = rows.min(), cols.min()
        shape = (rows.max() - r0 + 1, cols.max() - c0 + 1)
        cell = rng.uniform(0.06, 0.3) * TEXELS_PER_M
        art = value_noise(rng, shape, cell) * rng.uniform(1.0, 3.0) + rng.uniform(-0.5, 0.5)
        art = np.clip(0.5 + 0.5 * art, 0.02, 0.98)
        border = np.zeros(shape, dtype=bool)
        border[:2, :], border[-2:, :], border[:, :2], border[:, -2:] = True, True, True, True
        tex[r0 : r0 + shape[0], c0 : c0 + shape[1]] = np.where(border, 0.9, art)


def facade_texture(rng: np.random.Generator, length: float, height: float) -> U8:
    """Albedo (0..255) of one facade, row 0 at the top, TEXELS_PER_M texels per metre."""
    cols, rows = max(2, round(length * TEXELS_PER_M)), max(2, round(height * TEXELS_PER_M))
    u = ((np.arange(cols, dtype=np.float32) + 0.5) / TEXELS_PER_M)[None, :]
    h = (height - (np.arange(rows, dtype=np.float32) + 0.5) / TEXELS_PER_M)[:, None]
    u, h = np.broadcast_arrays(u, h)
    tex: F32 = np.full((rows, cols), rng.uniform(0.2, 0.75), dtype=np.float32)
    style = rng.choice(
        ["windows", "stripes", "panels", "bricks", "plain"], p=[0.4, 0.15, 0.15, 0.15, 0.15]
    )
    if style == "stripes":
        tex = 0.5 * tex + 0.5 * _bands(rng, h, height, 0.15, 1.2)
    elif style == "panels":
        tex = 0.4 * tex + 0.6 * _bands(rng, u, length, 0.4, 2.0)
        tex[np.mod(u, rng.uniform(0.8, 2.0)) < 0.04] *= 0.4
    elif style == "bricks":
        tex += _bricks(rng, u, h)
    if style == "windows" or rng.random() < 0.25:
        mask, value = _windows(rng, u, h, height)
        tex = tex * (1 - mask) + value * mask
    tex += value_noise(rng, (rows, cols), rng.uniform(1.0, 3.0) * TEXELS_PER_M) * rng.uniform(
        0.04, 0.15
    )
    streaks = value_noise(rng, (rows // 8 + 1, cols), rng.uniform(0.3, 1.0) * TEXELS_PER_M)
    tex += cv2.resize(streaks, (cols, rows), interpolation=cv2.INTER_LINEAR) * rng.uniform(0, 0.1)
    tex += value_noise(rng, (rows, cols), 2.0) * rng.uniform(0.02, 0.06)  # grain
    tex[h > height - rng.uniform(0.2, 0.6)] = rng.uniform(0.1, 0.9)  # cornice
    tex[h < rng.uniform(0.2, 0.8)] *= rng.uniform(0.5, 0.9)  # plinth
    if rng.random() < 0.7:
        _posters(rng, tex, u, h, length)
    return (np.clip(tex, 0.02, 0.98) * 255).astype(np.uint8)


# -- the world --------------------------------------------------------------------------------


@dataclass
class World:
    """Wall edges with their facades, a mip-mapped facade atlas, a ground tile and a sky."""

    a: F32  # (S, 2) edge start
    b: F32  # (S, 2) edge end
    normal_angle: F32  # (S,) direction the wall faces (into the street)
    edge_facade: I64  # (S,)
    edge_s0: F32  # (S,) metres along the facade where the edge starts
    facade_height: F32  # (F,)
    facade_tint: F32  # (F, 3) RGB
    atlas: U8  # every facade and mip level, flattened
    mip_offset: I64  # (F, L)
    mip_width: I64  # (F, L)
    mip_height: I64  # (F, L)
    ground: U8  # (G, G) tile, GROUND_TPM texels per metre, repeating
    sky: U8  # (SKY_ROWS, SKY_COLS): elevation 0..90 degrees x azimuth 0..360 degrees
    centerline: Path2D
    wall_length: float = 0.0
    n_facades: int = field(default=0)
    ground_far: float = 0.35  # what the ground fades to in the distance (haze on asphalt)


MIP_LEVELS: Final = 4
GROUND_TPM: Final = 16
GROUND_SIZE: Final = 1024
SKY_ROWS: Final = 256
SKY_COLS: Final = 2048


def _offset_polyline(path: Path2D, side: float, extend: float) -> F64:
    """The wall line `side` metres left of the centre line (negative: right), 1 m spacing."""
    if path.closed:
        s = np.arange(0.0, path.length, path.length / round(path.length))
    else:
        n = round(path.length + 2 * extend)
        s = np.linspace(-extend, path.length + extend, n + 1)
    t = path.tangent(np.clip(s, 0, path.length) if not path.closed else s)
    base = path.position(s)
    if not path.closed:  # straight extensions past the ends (to the end walls)
        before, after = s < 0, s > path.length
        base[before] = path.points[0] + t[before] * s[before, None]
        base[after] = path.points[-1] + t[after] * (s[after, None] - path.length)
    pts = base + np.column_stack([-t[:, 1], t[:, 0]]) * side
    return np.vstack([pts, pts[:1]]) if path.closed else pts


def _clear_runs(points: F64, tree: cKDTree, keep_out: float) -> list[F64]:
    """Split a polyline where it comes within `keep_out` of the centre line (crossings)."""
    dist, _ = tree.query(points)
    ok = dist >= keep_out
    runs: list[F64] = []
    start = None
    for i, good in enumerate(ok):
        if good and start is None:
            start = i
        if (not good or i == len(ok) - 1) and start is not None:
            stop = i + 1 if good else i
            if stop - start >= 2:
                runs.append(points[start:stop])
            start = None
    return runs


def _alley(rng: np.random.Generator, p0: F64, p1: F64, outward: F64) -> list[F64]:
    """Three walls of a dead-end alley opening between p0 and p1 of a wall line."""
    depth = rng.uniform(5.0, 10.0)
    q0, q1 = p0 + outward * depth, p1 + outward * depth
    return [np.array([p0, q0]), np.array([q0, q1]), np.array([q1, p1])]


def _wall_pieces(path: Path2D, rng: np.random.Generator) -> list[F64]:
    """Every wall polyline: both street sides (with alleys), end walls of an open street."""
    tree = cKDTree(path.points)
    pieces: list[F64] = []
    for side in (HALF_WIDTH_M, -HALF_WIDTH_M):
        line = _offset_polyline(path, side, extend=4.0)
        for run in _clear_runs(line, tree, HALF_WIDTH_M - 0.3):
            pieces.extend(_cut_alleys(run, side, tree, rng))
    if not path.closed:
        ends = [_offset_polyline(path, s, 4.0)[[0, -1]] for s in (HALF_WIDTH_M, -HALF_WIDTH_M)]
        pieces.append(np.array([ends[1][0], ends[0][0]]))
        pieces.append(np.array([ends[0][1], ends[1][1]]))
    # Alley walls may run into another street: clear them too.
    cleared: list[F64] = []
    for piece in pieces:
        dense = resample(piece, False, 0.5).points if len(piece) == 2 else piece
        cleared.extend(_clear_runs(dense, tree, HALF_WIDTH_M - 0.3))
    return cleared


def _clear_of(points: F64, tree: cKDTree) -> bool:
    """True when a wall segment stays well away from every street (sampled every 0.5 m)."""
    dense = resample(points, False, 0.5).points
    dist, _ = tree.query(dense)
    return bool(np.min(dist) > HALF_WIDTH_M + 1.5)


def _cut_alleys(run: F64, side: float, tree: cKDTree, rng: np.random.Generator) -> list[F64]:
    """Split a wall line at random alley openings (3 to 5 m wide, every 15 to 60 m)."""
    out: list[F64] = []
    start = 0
    i = int(rng.integers(8, 40))
    while i < len(run) - 10:
        width = int(rng.integers(3, 6))
        along = run[i + width] - run[i]
        # The wall is `side` metres left of the centre line: outward is left for side > 0.
        outward = np.array([-along[1], along[0]]) * np.sign(side) / np.linalg.norm(along)
        alley = _alley(rng, run[i], run[i + width], outward)
        if _clear_of(np.vstack(alley[1:2]), tree):  # no alley through a block into a street
            out.append(run[start : i + 1])
            out.extend(alley)
            start = i + width
        i += width + int(rng.integers(15, 60))
    out.append(run[start:])
    return [p for p in out if len(p) >= 2]


def _mip_chain(tex: U8) -> list[U8]:
    chain = [tex]
    for _ in range(MIP_LEVELS - 1):
        prev = chain[-1]
        size = (max(1, prev.shape[1] // 2), max(1, prev.shape[0] // 2))
        chain.append(cv2.resize(prev, size, interpolation=cv2.INTER_AREA))
    return chain


@dataclass
class _FacadeBuilder:
    """Collects facades and their edges, then packs the atlas."""

    rng: np.random.Generator
    edges_a: list[F64] = field(default_factory=list)
    edges_b: list[F64] = field(default_factory=list)
    edge_facade: list[int] = field(default_factory=list)
    edge_s0: list[float] = field(default_factory=list)
    heights: list[float] = field(default_factory=list)
    tints: list[F64] = field(default_factory=list)
    textures: list[list[U8]] = field(default_factory=list)

    def add(self, points: F64) -> None:
        """One facade along a polyline."""
        seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        height = float(self.rng.choice([self.rng.uniform(3.5, 7), self.rng.uniform(7, 18)]))
        fid = len(self.heights)
        self.heights.append(height)
        warm = self.rng.uniform(-0.15, 0.15)
        self.tints.append(np.array([1 + warm, 1.0, 1 - warm]) * self.rng.uniform(0.9, 1.1, 3))
        self.textures.append(_mip_chain(facade_texture(self.rng, float(cum[-1]), height)))
        for k in range(len(points) - 1):
            self.edges_a.append(points[k])
            self.edges_b.append(points[k + 1])
            self.edge_facade.append(fid)
            self.edge_s0.append(float(cum[k]))

    def add_wall(self, points: F64) -> None:
        """A wall polyline cut into facades 4 to 14 m long."""
        seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        start = 0
        while start < len(points) - 1:
            stop = int(np.searchsorted(cum, cum[start] + self.rng.uniform(4.0, 14.0)))
            stop = min(max(stop, start + 1), len(points) - 1)
            if len(points) - 1 - stop < 3:  # no sliver at the end
                stop = len(points) - 1
            self.add(points[start : stop + 1])
            start = stop

    def pack(self) -> tuple[U8, I64, I64, I64]:
        n = len(self.textures)
        offset = np.zeros((n, MIP_LEVELS), np.int64)
        width = np.zeros((n, MIP_LEVELS), np.int64)
        height = np.zeros((n, MIP_LEVELS), np.int64)
        flat: list[U8] = []
        pos = 0
        for f, chain in enumerate(self.textures):
            for level, tex in enumerate(chain):
                offset[f, level], width[f, level], height[f, level] = (
                    pos,
                    tex.shape[1],
                    tex.shape[0],
                )
                flat.append(tex.ravel())
                pos += tex.size
        return np.concatenate(flat), offset, width, height


def _ground_tile(rng: np.random.Generator) -> U8:
    """Asphalt: grain, patches and a few dark stains, repeating every 64 m."""
    g = np.full((GROUND_SIZE, GROUND_SIZE), 0.35, np.float32)
    g += 0.08 * _tileable_noise(rng, 64)
    g += 0.05 * _tileable_noise(rng, 16)
    g += 0.05 * _tileable_noise(rng, 2)
    return (np.clip(g, 0, 1) * 255).astype(np.uint8)


def _tileable_noise(rng: np.random.Generator, cell: int) -> F32:
    n = GROUND_SIZE // cell
    small = rng.uniform(-1, 1, (n, n)).astype(np.float32)
    wrapped = np.pad(small, 2, mode="wrap")
    big = cv2.resize(wrapped, None, fx=cell, fy=cell, interpolation=cv2.INTER_CUBIC)
    return big[2 * cell : 2 * cell + GROUND_SIZE, 2 * cell : 2 * cell + GROUND_SIZE]


def _sky(rng: np.random.Generator) -> U8:
    """Sky brightness by elevation (rows, 0 = horizon) and azimuth (columns), with clouds."""
    el = np.linspace(0, 1, SKY_ROWS, dtype=np.float32)[:, None]
    clouds = value_noise(rng, (SKY_ROWS, SKY_COLS + 64), 24.0)[:, :SKY_COLS]
    # Make azimuth periodic: blend the seam.
    ramp = np.linspace(0, 1, 64, dtype=np.float32)
    clouds[:, -64:] = clouds[:, -64:] * (1 - ramp) + clouds[:, :64] * ramp
    sky = 0.9 - 0.35 * el + 0.12 * np.maximum(clouds, 0) * (1 - el)
    return (np.clip(sky, 0, 1) * 255).astype(np.uint8)


def build_world(route: Route, lap_length: float, seed: int) -> World:
    """The street along a route; deterministic per (route, lap_length, seed)."""
    rng = np.random.default_rng([seed, 1])
    path = CENTERLINES[route](lap_length, rng)
    builder = _FacadeBuilder(rng)
    for piece in _wall_pieces(path, rng):
        builder.add_wall(piece)
    atlas, offset, width, height = builder.pack()
    a, b = np.array(builder.edges_a), np.array(builder.edges_b)
    d = b - a
    # Walls face the centre line: flip a normal that points away from it.
    mid = (a + b) / 2
    _, nearest = cKDTree(path.points).query(mid)
    normal = np.column_stack([-d[:, 1], d[:, 0]])
    flip = np.sum(normal * (path.points[nearest] - mid), axis=1) < 0
    normal[flip] *= -1
    return World(
        a=a.astype(np.float32),
        b=b.astype(np.float32),
        normal_angle=np.arctan2(normal[:, 1], normal[:, 0]).astype(np.float32),
        edge_facade=np.array(builder.edge_facade, np.int64),
        edge_s0=np.array(builder.edge_s0, np.float32),
        facade_height=np.array(builder.heights, np.float32),
        facade_tint=np.array(builder.tints, np.float32),
        atlas=atlas,
        mip_offset=offset,
        mip_width=width,
        mip_height=height,
        ground=_ground_tile(rng),
        sky=_sky(rng),
        centerline=path,
        wall_length=float(np.sum(np.linalg.norm(d, axis=1))),
        n_facades=len(builder.heights),
    )


# -- the drive ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DriveSpec:
    """What the camera does: route timing, stops and the frame clock."""

    duration: float
    rate: float
    parked: float = 0.0  # seconds parked in the middle of the drive (each stop's, with `stops`)
    variable_rate: bool = False
    drop_frames: int = 0
    stops: int = 1  # parking stops of `parked` seconds each, evenly spread over the drive
    lighting: float = 1.0  # strength of the exposure and gamma drift (1: the samples')


@dataclass
class Drive:
    """True poses, odometry and lighting at every emitted frame."""

    stamps_ns: I64
    x: F64
    y: F64
    yaw: F64
    odom: F64  # (N, 5): x, y, yaw, linear velocity, angular velocity
    light: F64  # (N, 4): gain, gamma, sun azimuth, diffuse
    parked_span_s: tuple[float, float] | None
    dropped: list[int]  # indices in the nominal frame sequence that were not emitted
    nominal_frames: int
    distance_m: float
    odom_drift_m: float
    odom_heading_drift_deg: float
    lap: F64  # laps (or out-and-back cycles) driven at each frame


class _Leg:
    """Maps driven distance sigma to (arc length s on the centre line, direction +-1)."""

    def __init__(self, path: Path2D) -> None:
        self.path = path
        self.cycle = path.length if path.closed else 2 * path.length

    def __call__(self, sigma: F64) -> tuple[F64, F64]:
        if self.path.closed:
            return np.mod(sigma, self.path.length), np.ones_like(sigma)
        c = np.mod(sigma, self.cycle)
        forward = c < self.path.length
        return np.where(forward, c, self.cycle - c), np.where(forward, 1.0, -1.0)

    def turn_points(self, sigma_max: float) -> list[float]:
        """Where an open street's dead ends are reached (turn in place there)."""
        if self.path.closed:
            return []
        return [k * self.path.length for k in range(1, int(sigma_max / self.path.length) + 1)]


def _speed(path: Path2D, leg: _Leg, sigma: F64, rng: np.random.Generator) -> F64:
    """Speed along the drive: slower in curves, a smooth wander, a different pace each lap."""
    s, _ = leg(sigma)
    laps = np.arange(int(sigma[-1] / leg.cycle) + 2)
    pace = np.interp(sigma / leg.cycle, laps, rng.uniform(0.88, 1.12, len(laps)))
    wander = 1 + 0.15 * SmoothNoise(rng, 8.0, 40.0)(sigma)
    speed: F64 = SPEED_MPS * pace * wander / (1 + 3 * np.abs(path.curvature(s)))
    return speed


def _brake(v: F64, sigma: F64, stops: Sequence[_Stop]) -> F64:
    """Decelerate into and accelerate out of each stop (0.4 m/s^2)."""
    for stop in stops:
        v = np.minimum(v, 0.1 + np.sqrt(0.8 * np.abs(sigma - stop.sigma)))
    return v


@dataclass(frozen=True)
class _Stop:
    """A halt at driven distance `sigma`: a turn in place or parking."""

    sigma: float
    seconds: float
    parking: bool = False


def _time_knots(
    sigma: F64, v: F64, stops: Sequence[_Stop]
) -> tuple[F64, F64, list[tuple[float, float, _Stop]]]:
    """(t, sigma) knots of the drive with each stop inserted, and each stop's time span."""
    t = np.concatenate([[0.0], np.cumsum(np.diff(sigma) / ((v[1:] + v[:-1]) / 2))])
    knots_t, knots_s = t, sigma
    spans: list[tuple[float, float, _Stop]] = []
    for stop in sorted(stops, key=lambda s: s.sigma):
        i = int(np.searchsorted(knots_s, stop.sigma))
        if i >= len(knots_s):
            break
        t0 = float(knots_t[i])
        # Repeat the knot: sigma stays put while time runs on.
        knots_t = np.concatenate([knots_t[: i + 1], knots_t[i:] + stop.seconds])
        knots_s = np.concatenate([knots_s[: i + 1], knots_s[i:]])
        spans.append((t0, t0 + stop.seconds, stop))
    return knots_t, knots_s, spans


def _plan(
    path: Path2D, spec: DriveSpec, rng: np.random.Generator
) -> tuple[F64, F64, list[tuple[float, float, _Stop]]]:
    """Knots of driven distance over time and the time spans of the stops."""
    leg = _Leg(path)
    sigma = np.arange(0.0, spec.duration * SPEED_MPS * 2 + 20, 0.05)
    base_v = _speed(path, leg, sigma, rng)
    stops = [_Stop(p, TURN_S) for p in leg.turn_points(float(sigma[-1]))]
    knots_t, knots_s, spans = _time_knots(sigma, _brake(base_v, sigma, stops), stops)
    if spec.parked > 0:
        # Stop k of n where the drive would be at (k + 1) / (n + 1) of its moving time: one
        # stop is centred.
        moving = spec.duration - spec.stops * spec.parked
        for k in range(spec.stops):
            at = moving / 2 if spec.stops == 1 else moving * (k + 1) / (spec.stops + 1)
            where = float(np.interp(at, knots_t, knots_s))
            stops.append(_Stop(where, spec.parked, parking=True))
        knots_t, knots_s, spans = _time_knots(sigma, _brake(base_v, sigma, stops), stops)
    return knots_t, knots_s, spans


@dataclass
class _Fine:
    """The true trajectory at SIM_HZ."""

    t: F64
    x: F64
    y: F64
    yaw: F64  # unwrapped
    lap: F64  # laps (of a closed route) or out-and-back cycles driven


def _true_path(
    path: Path2D, spec: DriveSpec, rng: np.random.Generator
) -> tuple[_Fine, tuple[float, float] | None]:
    knots_t, knots_s, spans = _plan(path, spec, rng)
    parked = next(((t0, t1) for t0, t1, stop in spans if stop.parking), None)
    t = np.arange(0.0, spec.duration + 1.0, 1.0 / SIM_HZ)
    sigma = np.interp(t, knots_t, knots_s)
    s, direction = _Leg(path)(sigma)
    # Sideways wobble and heading jitter are functions of driven distance: frozen while parked.
    wobble = SmoothNoise(rng, 6.0, 30.0)
    jitter = SmoothNoise(rng, 3.0, 15.0)
    tangent = path.tangent(s)
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    pos = path.position(s) + normal * (0.3 * wobble(sigma))[:, None]
    slope = 0.3 * (wobble(sigma + 0.05) - wobble(sigma - 0.05)) / 0.1
    heading = direction[:, None] * tangent + normal * slope[:, None]
    yaw = np.arctan2(heading[:, 1], heading[:, 0]) + np.radians(1.5) * jitter(sigma)
    for t0, t1, stop in spans:  # turn in place, to the left
        inside = (t >= t0) & (t <= t1)
        if not stop.parking and inside.any():
            before = yaw[max(int(np.argmax(inside)) - 1, 0)]
            after_i = min(len(t) - 1, int(len(t) - np.argmax(inside[::-1])))
            turn = np.mod(yaw[after_i] - before, 2 * np.pi)
            u = (t[inside] - t0) / (t1 - t0)
            yaw[inside] = before + turn * u * u * (3 - 2 * u)
    lap = sigma / _Leg(path).cycle
    return _Fine(t, pos[:, 0], pos[:, 1], np.unwrap(yaw), lap), parked


def _odometry(fine: _Fine, rng: np.random.Generator) -> F64:
    """Wheel odometry at SIM_HZ: noisy, mis-scaled and biased velocities, integrated.

    Returns (M, 5): x, y, yaw in the odom frame (origin = start pose), v, omega.
    """
    dt = 1.0 / SIM_HZ
    v = np.hypot(np.diff(fine.x), np.diff(fine.y)) / dt
    w = np.diff(fine.yaw) / dt
    moving = (v > 1e-6) | (np.abs(w) > 1e-6)  # wheels that do not turn report nothing
    v_hat = v * (1 + rng.normal(0, 0.02)) + rng.normal(0, 0.02, len(v)) * moving
    w_bias = np.radians(rng.uniform(0.03, 0.08)) * rng.choice([-1, 1])
    w_hat = w * (1 + rng.normal(0, 0.01)) + (w_bias + rng.normal(0, 0.01, len(w))) * moving
    yaw = np.concatenate([[0.0], np.cumsum(w_hat * dt)])
    x = np.concatenate([[0.0], np.cumsum(v_hat * np.cos(yaw[:-1]) * dt)])
    y = np.concatenate([[0.0], np.cumsum(v_hat * np.sin(yaw[:-1]) * dt)])
    return np.column_stack([x, y, yaw, np.append(v_hat, 0.0), np.append(w_hat, 0.0)])


def _frame_times(spec: DriveSpec, rng: np.random.Generator) -> tuple[F64, list[int], int]:
    """Frame times (s), the dropped nominal indices and the nominal frame count."""
    if spec.variable_rate:  # the rate wanders by about +-40 %, plus jitter
        wander = SmoothNoise(rng, 10.0, 40.0)
        times = [0.0]
        while True:
            dt = np.exp(0.3 * wander(times[-1]) + 0.1 * rng.normal()) / spec.rate
            if times[-1] + dt >= spec.duration:
                break
            times.append(times[-1] + float(dt))
        nominal = np.array(times)
    else:
        nominal = np.arange(math.ceil(spec.duration * spec.rate - 1e-9)) / spec.rate
    dropped: list[int] = []
    candidates = np.arange(5, len(nominal) - 5)
    while len(dropped) < spec.drop_frames and len(candidates):
        k = int(rng.choice(candidates))
        dropped.append(k)
        candidates = candidates[np.abs(candidates - k) > 2]  # drops stay single frames
    dropped.sort()
    return np.delete(nominal, dropped), dropped, len(nominal)


def _lighting(t: F64, rng: np.random.Generator, strength: float = 1.0) -> F64:
    """Per-frame (gain, gamma, sun azimuth, diffuse): exposure and a wandering sun; `strength`
    scales the exposure and gamma drift."""
    gain = np.exp((0.25 * strength) * SmoothNoise(rng, 20.0, 120.0)(t))
    gamma = (1 / 1.8) * np.exp((0.12 * strength) * SmoothNoise(rng, 30.0, 150.0)(t))
    sun = rng.uniform(0, 2 * np.pi) + np.radians(0.6) * t + 0.3 * SmoothNoise(rng, 40.0, 200.0)(t)
    diffuse = 0.35 + 0.18 * SmoothNoise(rng, 15.0, 90.0)(t)
    return np.column_stack([gain, gamma, sun, diffuse])


def simulate_drive(path: Path2D, spec: DriveSpec, seed: int) -> Drive:
    """The true trajectory, odometry, frame clock and lighting; deterministic per seed."""
    rng = np.random.default_rng([seed, 2])
    fine, parked = _true_path(path, spec, rng)
    odom_fine = _odometry(fine, rng)
    times, dropped, nominal = _frame_times(spec, rng)

    def at(values: F64) -> F64:
        return np.interp(times, fine.t, values)

    x, y, yaw = at(fine.x), at(fine.y), at(fine.yaw)
    odom = np.column_stack([at(odom_fine[:, k]) for k in range(5)])
    end = round(times[-1] * SIM_HZ)
    true_rel = _relative(fine, end)
    distance = float(np.sum(np.hypot(np.diff(fine.x[: end + 1]), np.diff(fine.y[: end + 1]))))
    return Drive(
        stamps_ns=START_NS + np.round(times * 1e9).astype(np.int64),
        x=x,
        y=y,
        yaw=_wrap(yaw),
        odom=np.column_stack([odom[:, :2], _wrap(odom[:, 2]), odom[:, 3:]]),
        light=_lighting(times, rng, spec.lighting),
        parked_span_s=parked,
        dropped=dropped,
        nominal_frames=nominal,
        distance_m=distance,
        odom_drift_m=float(np.hypot(*(odom_fine[end, :2] - true_rel[:2]))),
        odom_heading_drift_deg=float(np.degrees(abs(_wrap(odom_fine[end, 2] - true_rel[2])))),
        lap=at(fine.lap),
    )


def _relative(fine: _Fine, k: int) -> F64:
    """The true pose at fine step k expressed in the start pose's frame (= the odom frame)."""
    c, s = math.cos(fine.yaw[0]), math.sin(fine.yaw[0])
    dx, dy = fine.x[k] - fine.x[0], fine.y[k] - fine.y[0]
    return np.array([c * dx + s * dy, -s * dx + c * dy, fine.yaw[k] - fine.yaw[0]])


def _wrap(angle: Any) -> Any:
    return np.mod(np.asarray(angle) + np.pi, 2 * np.pi) - np.pi


# -- rendering ------------------------------------------------------------------------------------

SKY_TINT: Final = np.array([0.78, 0.88, 1.08], np.float32)
GROUND_TINT: Final = np.array([0.97, 0.97, 1.0], np.float32)
AMBIENT: Final = 0.55


@dataclass(frozen=True)
class RenderSpec:
    width: int
    height: int
    color: bool = True
    noise_sigma: float = 2.0  # Gaussian sensor noise, grey levels


class Renderer:
    """Ray-casts the world for one camera: one ray per column, textures looked up per pixel."""

    def __init__(self, world: World, spec: RenderSpec, seed: int) -> None:
        self.world = world
        self.spec = spec
        self.camera = clw.CameraIntrinsics.from_hfov(spec.width, spec.height, HFOV_DEG)
        cam = self.camera
        self.x_cam = ((np.arange(spec.width) + 0.5 - cam.cx) / cam.fx).astype(np.float32)
        self.y_cam = ((cam.cy - np.arange(spec.height) - 0.5) / cam.fy).astype(np.float32)
        self.below = self.y_cam < 0
        self.ground_z = (CAMERA_HEIGHT_M / -self.y_cam[self.below]).astype(np.float32)
        elevation = np.arctan(np.maximum(self.y_cam[~self.below], 0)) / (np.pi / 2)
        self.sky_row = np.minimum((elevation * SKY_ROWS).astype(np.int64), SKY_ROWS - 1)
        self.col_angle = np.arctan(-self.x_cam).astype(np.float32)
        r = np.hypot(self.x_cam[None, :], self.y_cam[:, None]) * cam.fx / max(cam.cx, cam.cy)
        self.vignette = (1 - 0.25 * np.clip(r, 0, 1.5) ** 2).astype(np.float32)
        d = world.b - world.a
        self.edge_len = np.hypot(d[:, 0], d[:, 1])
        self.mid = (world.a + world.b) / 2
        channels = 3 if spec.color else 1
        bank_rng = np.random.default_rng([seed, 3])
        # A bank of noise, cropped at a random offset per frame: fresh Gaussian noise per frame
        # would cost more than the whole rendering.
        shape = (spec.height + 37, spec.width + 41, channels)
        self.noise = bank_rng.standard_normal(shape, dtype=np.float32) * spec.noise_sigma
        self.seed = seed

    def _cast(self, px: float, py: float, yaw: float) -> tuple[F32, I64, F32]:
        """Per column: depth along the optical axis (inf: no wall), edge index, position u."""
        w = self.world
        fx, fy = math.cos(yaw), math.sin(yaw)
        dx = fx + self.x_cam * fy  # ray = forward + x * right, right = (sin, -cos)
        dy = fy - self.x_cam * fx
        rel_a = w.a - np.array([px, py], np.float32)
        rel_m = self.mid - np.array([px, py], np.float32)
        ahead = np.maximum(rel_a @ [fx, fy], (rel_a + w.b - w.a) @ [fx, fy]) > 0.05
        near = np.hypot(rel_m[:, 0], rel_m[:, 1]) < VIEW_RANGE_M + self.edge_len / 2
        cand = np.flatnonzero(ahead & near)
        if cand.size == 0:
            inf = np.full(self.spec.width, np.inf, np.float32)
            return inf, np.zeros(self.spec.width, np.int64), np.zeros_like(inf)
        qx, qy = rel_a[cand, 0], rel_a[cand, 1]
        ex, ey = (w.b - w.a)[cand, 0], (w.b - w.a)[cand, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / (dx[:, None] * ey - dy[:, None] * ex)
            t = (qx * ey - qy * ex) * inv
            u = (qx * dy[:, None] - qy * dx[:, None]) * inv
            t = np.where((u >= 0) & (u <= 1) & (t > 0.05), t, np.inf)
        k = np.argmin(t, axis=1)
        cols = np.arange(self.spec.width)
        return t[cols, k].astype(np.float32), cand[k], u[cols, k].astype(np.float32)

    def _walls(self, z: F32, edge: I64, u: F32, light: F64) -> tuple[Any, F32, F32]:
        """(wall mask, wall brightness, per-column facade tint) for every pixel."""
        w = self.world
        hit = np.isfinite(z)
        z = np.where(hit, z, 1e4).astype(np.float32)
        facade = w.edge_facade[edge]
        fy = self.camera.fy
        level = np.clip(np.log2(np.maximum(z * TEXELS_PER_M / fy, 1.0)), 0, MIP_LEVELS - 1)
        level = level.astype(np.int64)
        tpm = (TEXELS_PER_M / 2.0**level).astype(np.float32)
        width, rows = w.mip_width[facade, level], w.mip_height[facade, level]
        along = w.edge_s0[edge] + u * self.edge_len[edge]
        col = np.clip((along * tpm).astype(np.int64), 0, width - 1)
        top = w.facade_height[facade]
        h = CAMERA_HEIGHT_M + self.y_cam[:, None] * z[None, :]
        mask = (h >= 0) & (h < top) & hit
        v = np.clip(((top - h) * tpm).astype(np.int64), 0, rows - 1)
        tex = w.atlas[w.mip_offset[facade, level] + v * width + col].astype(np.float32)
        sun = np.maximum(np.cos(w.normal_angle[edge] - light[2]), 0)
        haze = np.exp(-z / 90.0)
        shade = (AMBIENT + light[3] * sun) * haze / 255.0
        value = tex * shade + (1 - haze) * 0.75
        return mask, value.astype(np.float32), w.facade_tint[facade]

    def _background(self, px: float, py: float, yaw: float, light: F64) -> F32:
        """Sky above the horizon, ground below it (haze fades the ground texture)."""
        spec, w = self.spec, self.world
        out = np.empty((spec.height, spec.width), np.float32)
        dx = np.cos(yaw) + self.x_cam * np.sin(yaw)
        dy = np.sin(yaw) - self.x_cam * np.cos(yaw)
        gx = px + self.ground_z[:, None] * dx[None, :]
        gy = py + self.ground_z[:, None] * dy[None, :]
        mask = GROUND_SIZE - 1
        ix = (gx * GROUND_TPM + 1e6).astype(np.int64) & mask
        iy = (gy * GROUND_TPM + 1e6).astype(np.int64) & mask
        fade = np.exp(-self.ground_z / 12.0)[:, None]
        tex = w.ground[iy, ix].astype(np.float32) / 255.0
        far = w.ground_far
        ground = (far + (tex - far) * fade) * (AMBIENT + 0.5 * light[3])
        out[self.below] = ground + (1 - fade) * 0.1
        azimuth = np.mod(yaw + self.col_angle, 2 * np.pi) / (2 * np.pi)
        sky_col = np.minimum((azimuth * SKY_COLS).astype(np.int64), SKY_COLS - 1)
        out[~self.below] = w.sky[self.sky_row[:, None], sky_col[None, :]] / 255.0
        return out

    def render(self, px: float, py: float, yaw: float, light: F64, index: int) -> U8:
        """One frame (H x W x 3 RGB or H x W grey, uint8); `index` seeds its noise."""
        return self._render(px, py, yaw, light, index)[0]

    def render_with_depth(
        self, px: float, py: float, yaw: float, light: F64, index: int
    ) -> tuple[U8, F32]:
        """The frame of `render` and its depth (H x W float32, metres along the optical axis,
        NaN where the pixel shows the sky)."""
        frame, z, wall = self._render(px, py, yaw, light, index)
        return frame, self._depth(z, wall)

    def _depth(self, z: F32, wall: Any) -> F32:
        """Walls at their column's depth, the ground plane below the horizon, NaN above."""
        depth = np.full((self.spec.height, self.spec.width), np.nan, np.float32)
        depth[self.below] = self.ground_z[:, None]
        out: F32 = np.where(wall, z[None, :], depth).astype(np.float32)
        return out

    def _render(
        self, px: float, py: float, yaw: float, light: F64, index: int
    ) -> tuple[U8, F32, Any]:
        """(frame, per-column wall depth, wall mask)."""
        z, edge, u = self._cast(px, py, yaw)
        mask, wall, tint = self._walls(z, edge, u, light)
        lum = np.where(mask, wall, self._background(px, py, yaw, light))
        if self.spec.color:
            # One 2-D plane per channel: several times cheaper than 3-D selects and products,
            # and the same arithmetic per pixel, so the same bytes as the 3-D form.
            region = np.where(self.below[None, :], GROUND_TINT[:, None], SKY_TINT[:, None])
            planes = [lum * np.where(mask, tint[None, :, c], region[c][:, None]) for c in range(3)]
        else:
            planes = [lum]
        exposure = self.vignette * light[0]  # float64, as is the product below
        out = [
            self._expose(
                cv2.GaussianBlur((p * exposure).astype(np.float32), (0, 0), 0.6), c, light[1], index
            )
            for c, p in enumerate(planes)
        ]
        frame: U8 = cv2.merge(out) if self.spec.color else out[0]
        return frame, z, mask

    def _expose(self, plane: F32, channel: int, gamma: float, index: int) -> U8:
        """Gamma curve through a look-up table, then sensor noise and 8-bit quantisation."""
        lut = (255.0 * np.linspace(0, 1, 1024) ** gamma).astype(np.float32)
        out = np.take(lut, (np.clip(plane, 0, 1) * 1023).astype(np.int64))
        rng = np.random.default_rng([self.seed, 4, index])
        oy, ox = rng.integers(0, 37), rng.integers(0, 41)
        out += self.noise[oy : oy + self.spec.height, ox : ox + self.spec.width, channel]
        quantised: U8 = np.clip(out + 0.5, 0, 255).astype(np.uint8)
        return quantised


# -- the second season ---------------------------------------------------------------------------
# With --season-change the drive is seen in another season from the lap boundary nearest its
# middle on: snow and an overcast sky over the same streets. The geometry, the poses and so the
# ground truth stay; what changes is what a feature detector sees. Brightness changes alone would
# not do (BRIEF's pixel comparisons survive any monotonic tone curve): the facades' fine detail is
# damped and partly covered (snow on ledges and the plinth, frost), so that across the change few
# of a place's corners are the same corners, while its layout (walls, sky, ground, the large
# light and dark parts of a facade) stays for a whole-image method such as SeqSLAM.

WINTER_DETAIL: Final = 0.35  # share of a facade's fine detail (under ~0.3 m) that stays
WINTER_GAIN: Final = 1.4  # exposure, times the drive's: snow light
WINTER_GAMMA: Final = 1.3  # gamma exponent, times the drive's (a harder tone curve)
WINTER_DIFFUSE: Final = 0.05  # overcast: hardly any sun-facing shading


def season_start(drive: Drive) -> int:
    """The first frame of the second season: the first frame of the lap (or out-and-back cycle)
    that begins nearest the middle of the drive in time.

    Raises:
        ValueError: the drive completes no lap.
    """
    starts = np.flatnonzero(np.diff(np.floor(drive.lap)) > 0) + 1
    if not starts.size:
        raise ValueError("--season-change needs a drive of more than one lap")
    t = drive.stamps_ns.astype(np.float64)
    middle = (t[0] + t[-1]) / 2
    return int(starts[np.argmin(np.abs(t[starts] - middle))])


def winter_light(light: F64) -> F64:
    """A frame's (gain, gamma, sun azimuth, diffuse) under the other season's sky."""
    gain, gamma, sun, _ = light
    return np.array([gain * WINTER_GAIN, gamma * WINTER_GAMMA, sun, WINTER_DIFFUSE])


def winter_facade(tex: U8, rng: np.random.Generator) -> U8:
    """One facade's albedo in winter: large parts brightened and flattened, fine detail damped
    and overlaid with frost, snow on the upper side of horizontal edges, a drift on the plinth."""
    albedo = tex.astype(np.float32) / 255.0
    rows, cols = albedo.shape
    coarse = cv2.GaussianBlur(albedo, (0, 0), 0.3 * TEXELS_PER_M)
    out = 0.45 + 0.55 * coarse + WINTER_DETAIL * (albedo - coarse)
    out += 0.08 * value_noise(rng, (rows, cols), rng.uniform(0.1, 0.3) * TEXELS_PER_M)
    out += 0.04 * value_noise(rng, (rows, cols), 2.0)
    # Snow along horizontal edges (sills, lintels, cornices), in patches.
    step = np.zeros_like(albedo)
    step[:-3] = np.abs(albedo[3:] - albedo[:-3])
    ledge = cv2.dilate((step > 0.15).astype(np.uint8), np.ones((5, 1), np.uint8), anchor=(0, 4))
    patchy = value_noise(rng, (rows, cols), 0.2 * TEXELS_PER_M) > -0.3
    out = np.where((ledge > 0) & patchy, 0.93, out)
    drift = rng.uniform(0.2, 0.7) * TEXELS_PER_M
    edge = drift * (1 + 0.4 * value_noise(rng, (1, cols), 0.5 * TEXELS_PER_M))
    out = np.where(np.arange(rows)[:, None] >= rows - edge, 0.9, out)
    winter: U8 = (np.clip(out, 0.02, 0.98) * 255).astype(np.uint8)
    return winter


def _winter_atlas(world: World, rng: np.random.Generator) -> U8:
    """The facade atlas with every facade in winter (mip levels rebuilt from level 0)."""
    atlas: U8 = world.atlas.copy()
    for f in range(world.n_facades):
        offset, width, height = (
            int(a[f, 0]) for a in (world.mip_offset, world.mip_width, world.mip_height)
        )
        level0 = world.atlas[offset : offset + width * height].reshape(height, width)
        for level, tex in enumerate(_mip_chain(winter_facade(level0, rng))):
            start = int(world.mip_offset[f, level])
            atlas[start : start + tex.size] = tex.ravel()
    return atlas


def _snow_tile(rng: np.random.Generator) -> U8:
    """Snow on the street: bright, faint drifts, no asphalt grain."""
    g = np.full((GROUND_SIZE, GROUND_SIZE), 0.85, np.float32)
    g += 0.05 * _tileable_noise(rng, 64) + 0.03 * _tileable_noise(rng, 8)
    return (np.clip(g, 0, 1) * 255).astype(np.uint8)


def _overcast_sky(rng: np.random.Generator) -> U8:
    """A flat grey sky, a little darker towards the zenith, faint cloud."""
    el = np.linspace(0, 1, SKY_ROWS, dtype=np.float32)[:, None]
    clouds = value_noise(rng, (SKY_ROWS, SKY_COLS + 64), 48.0)[:, :SKY_COLS]
    ramp = np.linspace(0, 1, 64, dtype=np.float32)
    clouds[:, -64:] = clouds[:, -64:] * (1 - ramp) + clouds[:, :64] * ramp
    sky = 0.55 - 0.1 * el + 0.03 * clouds
    return (np.clip(sky, 0, 1) * 255).astype(np.uint8)


def winter_world(world: World, seed: int) -> World:
    """The same streets in the other season (its own random stream: [seed, 5])."""
    rng = np.random.default_rng([seed, 5])
    return replace(
        world,
        atlas=_winter_atlas(world, rng),
        ground=_snow_tile(rng),
        sky=_overcast_sky(rng),
        ground_far=0.8,
    )


# -- ground truth and side files -------------------------------------------------------------------


def poses_csv(drive: Drive) -> str:
    """frame, stamp_ns, t (s since the first frame), x, y (m), yaw (rad): the true camera poses."""
    lines = ["frame,stamp_ns,t,x,y,yaw"]
    t = (drive.stamps_ns - drive.stamps_ns[0]) / 1e9
    for i, (stamp, ti, x, y, yaw) in enumerate(
        zip(drive.stamps_ns, t, drive.x, drive.y, drive.yaw, strict=True)
    ):
        lines.append(f"{i},{stamp},{ti:.6f},{x:.4f},{y:.4f},{yaw:.6f}")
    return "\n".join(lines) + "\n"


def read_poses_csv(text: str) -> dict[str, F64 | I64]:
    """The columns of a poses .csv (stamps and frame numbers as int64)."""
    rows = [line.split(",") for line in text.strip().splitlines()[1:]]
    cols = list(zip(*rows, strict=True)) if rows else [()] * 6
    names = ["frame", "stamp_ns", "t", "x", "y", "yaw"]
    out: dict[str, F64 | I64] = {}
    for name, col in zip(names, cols, strict=True):
        dtype = np.int64 if name in ("frame", "stamp_ns") else np.float64
        out[name] = np.array([dtype(v) for v in col], dtype=dtype)
    return out


def ground_truth_pairs(stamps_ns: I64, x: F64, y: F64, yaw: F64) -> tuple[I64, I64]:
    """(rows, cols) of the loop cells, sorted, from poses as written to the .csv (see top)."""
    if len(x) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    xy = np.column_stack([x, y])
    pairs = cKDTree(xy).query_pairs(GT_DISTANCE_M * 1.001, output_type="ndarray")
    i, j = np.maximum(pairs[:, 0], pairs[:, 1]), np.minimum(pairs[:, 0], pairs[:, 1])
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    keep = np.hypot(x[i] - x[j], y[i] - y[j]) <= GT_DISTANCE_M
    keep &= np.abs(_wrap(yaw[i] - yaw[j])) <= math.radians(GT_HEADING_DEG)
    keep &= stamps_ns[i] - stamps_ns[j] >= round(GT_MIN_AGE_S * 1e9)
    keep &= travelled[i] - travelled[j] >= GT_MIN_TRAVEL_M
    i, j = i[keep].astype(np.int64), j[keep].astype(np.int64)
    order = np.lexsort((j, i))
    return i[order], j[order]


def _npz_bytes(arrays: dict[str, Any]) -> bytes:
    """An .npz like numpy.savez_compressed, but with fixed zip timestamps (byte-deterministic)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, value in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            archive.writestr(info, member.getvalue())
    return buffer.getvalue()


def gt_npz_bytes(n: int, rows: I64, cols: I64, dense: bool) -> bytes:
    """Dense: key "gt", uint8 N x N. Sparse: the keys scipy.sparse.save_npz writes (CSR)."""
    if dense:
        gt = np.zeros((n, n), np.uint8)
        gt[rows, cols] = 1
        return _npz_bytes({"gt": gt})
    matrix = sparse.csr_array((np.ones(len(rows), np.uint8), (rows, cols)), shape=(n, n))
    matrix.sort_indices()
    return _npz_bytes(
        {
            "indices": matrix.indices,
            "indptr": matrix.indptr,
            "format": np.array(b"csr"),
            "shape": np.array(matrix.shape),
            "data": matrix.data,
            "_is_array": np.array(True),
        }
    )


def write_atomic(path: Path, data: bytes) -> None:
    """Write beside the target, then rename: readers never see a partial file."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    tmp.replace(path)


# -- the generation pipeline ---------------------------------------------------------------------


@dataclass(frozen=True)
class Config:
    """Everything that determines a generated log (and so its bytes)."""

    name: str = "drive"
    seed: int = 0
    route: Route = "loops"
    duration: float = 180.0
    rate: float = 3.0
    width: int = 256
    height: int = 192
    formats: tuple[clw.Format, ...] = clw.FORMATS
    image: Literal["jpeg", "raw"] = "jpeg"
    quality: int = 75
    color: bool = True
    noise_sigma: float = 2.0
    parked: float = 0.0
    variable_rate: bool = False
    drop_frames: int = 0
    lap_length: float | None = None  # None: about three laps (at least MIN_LAP_M[route])
    latency_ms: float = 0.0  # image receive latency: log time = stamp + latency
    bag_compression: clw.BagCompression = "none"
    mcap_compression: clw.McapCompression = "zstd"
    depth: bool = False  # an aligned depth topic (see the module docstring)
    depth_encoding: DepthEncoding = "32FC1"
    stops: int = 1  # with parked > 0: this many stops of `parked` seconds
    lighting: float = 1.0  # strength of the exposure and gamma drift
    season_change: bool = False  # the other season from the lap boundary nearest the middle

    def lap(self) -> float:
        if self.lap_length is not None:
            return max(self.lap_length, MIN_LAP_M[self.route])
        moving = max(self.duration - self.stops * self.parked, 1.0)
        return float(np.clip(SPEED_MPS * moving / 3.0, MIN_LAP_M[self.route], 600.0))

    def drive_spec(self) -> DriveSpec:
        return DriveSpec(
            self.duration,
            self.rate,
            self.parked,
            self.variable_rate,
            self.drop_frames,
            self.stops,
            self.lighting,
        )

    def render_spec(self) -> RenderSpec:
        return RenderSpec(self.width, self.height, self.color, self.noise_sigma)

    def recorded(self) -> dict[str, Any]:
        """The fields a log's metadata and .json record. The depth fields only when depth is
        on, so that logs without it keep the bytes they had before the option existed."""
        values = asdict(self)
        if not self.depth:
            del values["depth"], values["depth_encoding"]
        for name, default in (("stops", 1), ("lighting", 1.0), ("season_change", False)):
            if values[name] == default:
                del values[name]
        return values


# Shorter routes would not leave room for blocks between the street's passes.
MIN_LAP_M: Final[dict[Route, float]] = {"loops": 60.0, "figure8": 140.0, "outandback": 60.0}


@dataclass
class Result:
    """What a generation produced (for the summary and the sample README)."""

    config: Config
    files: dict[str, Path]
    n_frames: int
    gt_cells: int
    gt_events: int
    render_fps: float
    seconds: float
    drive: Drive
    world: World


def depth_bytes(depth: F32, encoding: DepthEncoding) -> bytes:
    """A depth image as a little-endian message body: 32FC1 metres (NaN kept) or 16UC1
    millimetres (0 where nothing was hit or the depth does not fit in 16 bits)."""
    if encoding == "32FC1":
        return depth.astype("<f4").tobytes()
    with np.errstate(invalid="ignore"):
        mm = np.rint(depth.astype(np.float64) * 1000.0)
        valid = np.isfinite(mm) & (mm >= 1) & (mm <= 65535)
    return np.where(valid, mm, 0).astype("<u2").tobytes()


# One frame's message bodies: the encoded image and, with --depth, the depth image.
FrameData = tuple[bytes, bytes | None]


def encode(img: U8, config: Config) -> tuple[bytes, str]:
    """(data, encoding) of one rendered frame as the log stores it."""
    if config.image == "raw":
        return img.tobytes(), "rgb8" if config.color else "mono8"
    bgr = cv2.cvtColor(img, cv2.COLOR_RGB2BGR) if config.color else img
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, config.quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes(), "jpeg"


class _FrameMaker:
    """Renders and encodes frames by index (one per worker process)."""

    def __init__(self, world: World, drive: Drive, config: Config) -> None:
        self.renderer = Renderer(world, config.render_spec(), config.seed)
        self.drive = drive
        self.config = config
        self.winter: Renderer | None = None
        self.season_start = len(drive.x)
        if config.season_change:
            self.winter = Renderer(
                winter_world(world, config.seed), config.render_spec(), config.seed
            )
            self.season_start = season_start(drive)

    def make(self, i: int) -> FrameData:
        d = self.drive
        pose = (float(d.x[i]), float(d.y[i]), float(d.yaw[i]))
        renderer, light = self.renderer, d.light[i]
        if self.winter is not None and i >= self.season_start:
            renderer, light = self.winter, winter_light(light)
        if not self.config.depth:
            return encode(renderer.render(*pose, light, i), self.config)[0], None
        img, depth = renderer.render_with_depth(*pose, light, i)
        return encode(img, self.config)[0], depth_bytes(depth, self.config.depth_encoding)

    def block(self, start: int, stop: int) -> list[FrameData]:
        return [self.make(i) for i in range(start, stop)]


_WORKER: _FrameMaker | None = None


def _keep_heap() -> None:
    """Ask glibc to keep freed memory instead of unmapping it.

    Every frame allocates and frees a few dozen image-sized temporaries; with glibc's defaults
    each is a fresh mmap that page-faults in, which costs more system time than the rendering
    itself (about 40 % more wall time at 640x480). Elsewhere this does nothing.
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    m_trim_threshold, m_top_pad, m_mmap_threshold = -1, -2, -3
    libc.mallopt(m_mmap_threshold, 1 << 30)
    libc.mallopt(m_trim_threshold, 1 << 30)
    libc.mallopt(m_top_pad, 64 << 20)


def _init_worker(world: World, drive: Drive, config: Config) -> None:
    global _WORKER
    cv2.setNumThreads(1)  # the pool is the parallelism; OpenCV's own threads would compete
    _keep_heap()  # again: a spawned worker does not inherit it
    _WORKER = _FrameMaker(world, drive, config)


def _work(start: int, stop: int) -> list[FrameData]:
    assert _WORKER is not None
    return _WORKER.block(start, stop)


def render_frames(world: World, drive: Drive, config: Config, jobs: int) -> Iterator[FrameData]:
    """Encoded frames (and depth) in order; with jobs > 1, blocks render in worker processes."""
    n = len(drive.x)
    _keep_heap()
    if jobs <= 1:
        maker = _FrameMaker(world, drive, config)
        yield from (maker.make(i) for i in range(n))
        return
    # spawn, not fork: the parent has used OpenCV, whose thread pool does not survive a fork
    # (forked workers deadlocked rendering 640x480 frames).
    ctx = multiprocessing.get_context("spawn")
    block = 8
    with ctx.Pool(jobs, _init_worker, (world, drive, config)) as pool:
        pending: deque[AsyncResult[list[FrameData]]] = deque()
        for start in range(0, n, block):  # keep a bounded number of blocks in flight
            pending.append(pool.apply_async(_work, (start, min(start + block, n))))
            if len(pending) >= 3 * jobs:
                yield from pending.popleft().get()
        while pending:
            yield from pending.popleft().get()


def _open_writers(config: Config, out: Path) -> dict[str, clw.CameraLogWriter]:
    writers: dict[str, clw.CameraLogWriter] = {}
    try:
        for fmt in config.formats:
            path = clw.output_path(out, config.name, fmt)
            writers[fmt] = clw.open_writer(
                fmt,
                path,
                mcap_compression=config.mcap_compression,
                bag_compression=config.bag_compression,
            )
            writers[fmt].add_metadata("generator", _metadata(config))
    except BaseException:
        for writer in writers.values():
            writer.abort()
        raise
    return writers


def _metadata(config: Config) -> dict[str, str]:
    values = config.recorded()
    values["formats"] = ",".join(config.formats)
    # The generator's path when the committed logs were made, kept so that they regenerate
    # byte for byte (every log carries this metadata record).
    values["tool"] = "tools/make_sample_logs.py"
    return {k: str(v) for k, v in sorted(values.items())}


def _write_frame(
    writers: Sequence[clw.CameraLogWriter],
    drive: Drive,
    i: int,
    data: FrameData,
    config: Config,
    camera: clw.CameraIntrinsics,
) -> None:
    stamp = int(drive.stamps_ns[i])
    ox, oy, oyaw, ov, ow = (float(v) for v in drive.odom[i])
    odom = clw.OdometrySample(clw.PlanarPose(stamp, ox, oy, oyaw), ov, ow)
    truth = clw.PlanarPose(stamp, float(drive.x[i]), float(drive.y[i]), float(drive.yaw[i]))
    truth = replace(truth, z=CAMERA_HEIGHT_M)
    encoding = "jpeg" if config.image == "jpeg" else ("rgb8" if config.color else "mono8")
    image, depth = data
    frame = clw.ImageFrame(stamp, image, encoding, config.width, config.height)
    latency = round(config.latency_ms * 1e6)
    for writer in writers:
        writer.write_camera_info(camera, stamp)
        if depth is not None:
            writer.write_camera_info(camera, stamp, topic=writer.topics.depth_camera_info)
        writer.write_odometry(odom)
        writer.write_ground_truth(truth)
        writer.write_image(frame, stamp + latency)
        if depth is not None:
            depth_frame = clw.ImageFrame(
                stamp, depth, config.depth_encoding, config.width, config.height
            )
            writer.write_image(depth_frame, stamp + latency)


def _side_files(config: Config, out: Path, drive: Drive) -> tuple[dict[str, Path], int, int]:
    """poses .csv, GT .npz, run .json; returns them and the GT cell and event counts."""
    text = poses_csv(drive)
    poses = read_poses_csv(text)  # the GT uses the poses exactly as written
    rows, cols = ground_truth_pairs(poses["stamp_ns"], poses["x"], poses["y"], poses["yaw"])
    n = len(drive.x)
    events = len(np.unique(rows))
    files = {
        "poses": out / f"{config.name}.poses.csv",
        "gt": out / f"{config.name}.gt.npz",
        "info": out / f"{config.name}.json",
    }
    write_atomic(files["poses"], text.encode())
    write_atomic(files["gt"], gt_npz_bytes(n, rows, cols, dense=n <= DENSE_GT_MAX_FRAMES))
    info = _info(config, drive, len(rows), events)
    write_atomic(files["info"], (json.dumps(info, indent=2, sort_keys=True) + "\n").encode())
    return files, len(rows), events


def _info(config: Config, drive: Drive, cells: int, events: int) -> dict[str, Any]:
    """The machine-readable facts of a run (parameters, thresholds, spans, counts)."""
    stamps = drive.stamps_ns
    parked = None
    if drive.parked_span_s is not None:
        t0, t1 = drive.parked_span_s
        inside = np.flatnonzero((stamps >= START_NS + t0 * 1e9) & (stamps <= START_NS + t1 * 1e9))
        parked = {
            "start_s": round(t0, 3),
            "end_s": round(t1, 3),
            "frames": [int(inside[0]), int(inside[-1])],
        }
    info: dict[str, Any] = {
        "config": {
            k: (list(v) if isinstance(v, tuple) else v) for k, v in config.recorded().items()
        },
        "lap_length_m": round(config.lap(), 3),
        "frames": len(stamps),
        "nominal_frames": drive.nominal_frames,
        "dropped_nominal_frames": drive.dropped,
        "first_stamp_ns": int(stamps[0]),
        "last_stamp_ns": int(stamps[-1]),
        "parked": parked,
        "distance_m": round(drive.distance_m, 2),
        "odometry_end_error_m": round(drive.odom_drift_m, 2),
        "odometry_end_heading_error_deg": round(drive.odom_heading_drift_deg, 2),
        "ground_truth": {
            "distance_m": GT_DISTANCE_M,
            "heading_deg": GT_HEADING_DEG,
            "min_age_s": GT_MIN_AGE_S,
            "min_travel_m": GT_MIN_TRAVEL_M,
            "loop_cells": cells,
            "loop_events": events,
        },
        "camera": {"hfov_deg": HFOV_DEG, "height_m": CAMERA_HEIGHT_M},
    }
    if config.season_change:  # only then, so that other runs keep their bytes
        first = season_start(drive)
        info["season_change"] = {"first_frame": first, "start_s": _seconds(stamps, first)}
    return info


def _seconds(stamps: I64, frame: int) -> float:
    return round((int(stamps[frame]) - int(stamps[0])) / 1e9, 3)


def generate(config: Config, out: Path, jobs: int = 1, progress: bool = True) -> Result:
    """Make one log in every requested format, plus its poses, GT and run description."""
    began = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    world = build_world(config.route, config.lap(), config.seed)
    drive = simulate_drive(world.centerline, config.drive_spec(), config.seed)
    if config.season_change:
        season_start(drive)  # a drive of one lap fails here, before a file is written
    files, cells, events = _side_files(config, out, drive)
    camera = clw.CameraIntrinsics.from_hfov(config.width, config.height, HFOV_DEG)
    n = len(drive.x)
    _say(progress, f"{config.name}: {n} frames, {world.n_facades} facades, GT {events} events")
    writers = _open_writers(config, out)
    started = time.perf_counter()
    try:
        for i, data in enumerate(render_frames(world, drive, config, jobs)):
            _write_frame(list(writers.values()), drive, i, data, config, camera)
            if progress and (i + 1) % max(1, n // 10) == 0:
                rate = (i + 1) / (time.perf_counter() - started)
                _say(progress, f"  {i + 1}/{n} frames ({rate:.1f} frames/s)")
    except BaseException:
        for writer in writers.values():
            writer.abort()
        raise
    for writer in writers.values():
        writer.close()
    fps = n / max(time.perf_counter() - started, 1e-9)
    for fmt, writer in writers.items():
        files[fmt] = writer.final_path
    return Result(config, files, n, cells, events, fps, time.perf_counter() - began, drive, world)


def _say(enabled: bool, text: str) -> None:
    if enabled:
        print(text, flush=True)


# -- the committed samples -------------------------------------------------------------------------

REPO: Final = Path(__file__).resolve().parents[2]
_SAMPLE_IMAGE: Final[dict[str, Any]] = {"rate": 2.0, "quality": 70, "noise_sigma": 1.5}
SAMPLES: Final[tuple[Config, ...]] = (
    Config(name="drive_loops", seed=11, route="loops", duration=120.0, **_SAMPLE_IMAGE),
    Config(
        name="drive_parked",
        seed=12,
        route="loops",
        duration=150.0,
        parked=60.0,
        formats=("ros2mcap",),
        **_SAMPLE_IMAGE,
    ),
    Config(
        name="drive_varrate",
        seed=13,
        route="outandback",
        duration=120.0,
        variable_rate=True,
        drop_frames=4,
        latency_ms=25.0,
        formats=("bag",),
        bag_compression="lz4",
        **_SAMPLE_IMAGE,
    ),
)
# How to run this module (from the repository root), as the samples' README shows it.
COMMAND: Final = "PYTHONPATH=tools python -m loggen.make_sample_logs"
SAMPLES_COMMAND: Final = f"{COMMAND} --samples"

_FORMAT_NAMES: Final[dict[str, str]] = {
    "ros2mcap": "ROS 2 MCAP (profile ros2, CDR, sensor_msgs/msg/CompressedImage)",
    "foxglove": "Foxglove protobuf MCAP (foxglove.CompressedImage, foxglove.PoseInFrame)",
    "bag": "ROS 1 bag (sensor_msgs/CompressedImage)",
    "db3": "ROS 2 bag directory (sqlite3 .db3 + metadata.yaml)",
    "poses": "true camera poses: frame, stamp_ns, t, x, y, yaw",
    "gt": 'ground-truth loop matrix, key "gt", uint8 N x N',
    "info": "generator parameters, parked span, dropped frames, counts",
}


def command_line(config: Config, out: str = "sample_logs") -> str:
    """The command (COMMAND and its options) that generates `config` into `out`."""
    args = [
        f"--out {out} --name {config.name} --seed {config.seed} --route {config.route}",
        f"--duration {config.duration:g} --rate {config.rate:g}",
        f"--width {config.width} --height {config.height} --formats {','.join(config.formats)}",
        f"--quality {config.quality} --noise {config.noise_sigma:g}",
    ]
    optional = [
        (config.image != "jpeg", f"--image {config.image}"),
        (not config.color, "--mono"),
        (config.parked > 0, f"--parked {config.parked:g}"),
        (config.variable_rate, "--variable-rate"),
        (config.drop_frames > 0, f"--drop-frames {config.drop_frames}"),
        (config.lap_length is not None, f"--lap-length {config.lap_length}"),
        (config.latency_ms > 0, f"--latency-ms {config.latency_ms:g}"),
        (config.bag_compression != "none", f"--bag-compression {config.bag_compression}"),
        (config.mcap_compression != "zstd", f"--mcap-compression {config.mcap_compression}"),
        (config.depth, "--depth"),
        (config.depth and config.depth_encoding != "32FC1", "--depth-encoding 16UC1"),
        (config.season_change, "--season-change"),
    ]
    args += [flag for wanted, flag in optional if wanted]
    return f"{COMMAND} " + " ".join(args)


def make_samples(out: Path, jobs: int) -> list[Result]:
    results = [generate(config, out, jobs) for config in SAMPLES]
    write_atomic(out / "README.md", sample_readme(results, out).encode())
    return results


def _route_text(result: Result) -> str:
    c, d = result.config, result.drive
    lap = c.lap()
    text = {
        "loops": f"laps of a closed street loop ({lap:.0f} m centre line)",
        "figure8": f"laps of a figure eight ({lap:.0f} m centre line)",
        "outandback": (
            f"out-and-back along a {lap / 2:.0f} m dead-end street, turning in place at each end;"
            " back legs see the same walls in the opposite direction and are not GT loops"
        ),
    }[c.route]
    extras = []
    if d.parked_span_s is not None:
        t0, t1 = d.parked_span_s
        extras.append(f"parked from t = {t0:.1f} s to {t1:.1f} s")
    if c.variable_rate:
        intervals = np.diff(d.stamps_ns) / 1e9
        extras.append(
            f"variable frame interval {intervals.min():.3f} to {intervals.max():.3f} s"
            f" around {1 / c.rate:.2f} s, nominal frames {d.dropped} dropped,"
            f" images logged {c.latency_ms:.0f} ms after their stamps"
        )
    return text + "".join(f"; {e}" for e in extras)


def _sample_section(result: Result, out: Path) -> list[str]:
    c, d = result.config, result.drive
    duration = (d.stamps_ns[-1] - d.stamps_ns[0]) / 1e9
    lines = [
        f"### {c.name}",
        "",
        f"Route: {_route_text(result)}.",
        f"Seed {c.seed}; {duration:.1f} s from first to last frame; {result.n_frames} frames"
        f" at {'about ' if c.variable_rate else ''}{c.rate:g} Hz; {c.width}x{c.height} colour"
        f" JPEG, quality {c.quality}; {d.distance_m:.0f} m driven; odometry ends"
        f" {d.odom_drift_m:.1f} m and {d.odom_heading_drift_deg:.1f} deg off.",
        f"Ground truth: {result.gt_events} query frames with a loop"
        f" ({result.gt_cells} loop cells).",
        "",
        "Regenerate alone with:",
        "",
        "```",
        command_line(c),
        "```",
        "",
        "| file | what | bytes |",
        "|---|---|---:|",
    ]
    for key, path in result.files.items():
        name = path.name + ("/" if path.is_dir() else "")
        lines.append(f"| `{name}` | {_FORMAT_NAMES[key]} | {clw.path_size(path):,} |")
    lines.append("")
    return lines


def _depth_rows(results: Sequence[Result]) -> list[str]:
    """The depth topics' rows of the README's topic table, when some log carries them."""
    encodings = sorted({r.config.depth_encoding for r in results if r.config.depth})
    if not encodings:
        return []
    return [
        "| `/camera/depth/image` | sensor_msgs/Image, encoding "
        + " or ".join(f"`{e}`" for e in encodings)
        + ": aligned depth along the optical axis (32FC1 metres, NaN = sky; 16UC1 mm, 0 ="
        " invalid) |",
        "| `/camera/depth/camera_info` | sensor_msgs/CameraInfo: the same as the camera's |",
    ]


def sample_readme(results: Sequence[Result], out: Path) -> str:
    total = sum(clw.path_size(p) for r in results for p in r.files.values())
    head = [
        "# Sample logs",
        "",
        "Procedural street drives made by `tools/loggen/make_sample_logs.py`, rewritten by",
        f"`{SAMPLES_COMMAND}` (run from the repository root).",
        "",
        "## What is byte for byte",
        "",
        "- **On one machine**, every generation of a sample is byte-identical, with any number",
        "  of worker processes (`--jobs`). That is the promise for reproducible fixtures.",
        "- **On another processor**, the same package versions give the same side files",
        "  (`*.json`, `*.poses.csv`, `*.gt.npz`, `metadata.yaml`) byte for byte, but the logs",
        "  may differ by a few bytes: the rendering and the poses go through NumPy and OpenCV",
        "  floating-point kernels whose SIMD paths (AVX2, AVX-512, NEON) round differently in",
        "  the last bit. What stays the same there, and is tested",
        "  (`tests/test_sample_logs.py`, with `tools/loggen/compare_sample_logs.py`):",
        "  - the container facts (MCAP profile, schemas, channels, metadata; bag connections),",
        "    the messages in the same order with the same topics, types, log and publish times,",
        "    and every decoded field exactly (stamps, frame ids, CameraInfo, image formats);",
        "  - pose and velocity floats (`pose.*`, `twist.*`) to 1e-9 (they differ by an ulp);",
        "  - decoded image values: in every frame at least 99 % within one grey level, over a",
        "    log at least 99.9 %, none more than 32 levels off. Measured with every SIMD",
        "    extension of NumPy and OpenCV switched off (`tools/loggen/other_processor.py`):",
        "    a few frames per log differ, on at most 4.4e-5 of the values, by at most 3 levels",
        "    (a pixel on a rounding boundary moves one level, and JPEG spreads it over its",
        "    block);",
        "  - the detector's decisions on the logs: the same sequences, matches and verdicts,",
        "    scores within 1 %.",
        "- The committed files were written on x86-64 with NumPy's AVX2 kernels. On an AVX-512",
        "  machine, `PYTHONPATH=tools python -m loggen.other_processor -- python -m",
        "  loggen.make_sample_logs --samples` does not reproduce them (it switches off more",
        "  than AVX-512); setting",
        "  `NPY_DISABLE_CPU_FEATURES='X86_V4 AVX512_ICL'` does, byte for byte.",
        "",
        "## The drives",
        "",
        f"A pinhole camera ({HFOV_DEG:g} deg horizontal field of view, {CAMERA_HEIGHT_M:g} m"
        " above the ground)",
        "drives a street with procedurally textured facades (windows, stripes, panels, bricks,",
        "posters; random per facade) and a few alleys. Lighting direction, exposure gain and",
        "gamma drift between visits; speed varies along the route and between laps; the camera",
        "wobbles a little sideways and in heading; images carry sensor noise and JPEG artefacts.",
        "",
        "Every log has these topics (the Foxglove MCAP uses Foxglove schemas on the same topics):",
        "",
        "| topic | type |",
        "|---|---|",
        "| `/camera/image/compressed` | sensor_msgs/CompressedImage, format `jpeg` |",
        "| `/camera/camera_info` | sensor_msgs/CameraInfo: fx = fy = (W/2)/tan(hfov/2),"
        " cx = W/2, cy = H/2, no distortion |",
        "| `/odom` | nav_msgs/Odometry: wheel odometry from noisy velocities (drifts) |",
        "| `/ground_truth/pose` | geometry_msgs/PoseStamped: the true camera pose, frame `map` |",
        *_depth_rows(results),
        "",
        "Header stamps are the frame times (first frame at 1700000000 s); log time equals the",
        "stamp unless a receive latency is noted.",
        "",
        "## Ground truth",
        "",
        "`*.gt.npz` holds `gt`, an N x N uint8 matrix over the images in log order:",
        "`gt[i, j] = 1` (only for j < i) when the true camera positions are within"
        f" {GT_DISTANCE_M:g} m,",
        f"the headings within {GT_HEADING_DEG:g} degrees, frame j is at least"
        f" {GT_MIN_AGE_S:g} s older than frame i",
        "(the detector's default kappa) and the camera drove at least"
        f" {GT_MIN_TRAVEL_M:g} m in between (so a",
        "parked camera does not revisit itself). It is computed from `*.poses.csv` exactly as",
        "written. A query frame with at least one 1 is a loop event. Revisits in the opposite",
        "direction are not loops.",
        "",
        "## Files",
        "",
    ]
    body = [line for r in results for line in _sample_section(r, out)]
    tail = [f"Total: {total:,} bytes (plus this README).", ""]
    return "\n".join(head + body + tail)


# -- command line ---------------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, help="output folder (default with --samples: sample_logs/)")
    p.add_argument("--samples", action="store_true", help="regenerate the committed sample set")
    p.add_argument("--name", help="file name stem (default: the route and seed)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--route", choices=ROUTES, default="loops")
    p.add_argument("--duration", type=float, default=180.0, help="seconds")
    p.add_argument("--rate", type=float, default=3.0, help="frames per second")
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--height", type=int, default=192)
    p.add_argument("--formats", default=",".join(clw.FORMATS), help="comma-separated")
    p.add_argument("--image", choices=("jpeg", "raw"), default="jpeg")
    p.add_argument("--quality", type=int, default=75, help="JPEG quality")
    p.add_argument("--mono", action="store_true", help="grey images (mono8 / grey JPEG)")
    p.add_argument("--noise", type=float, default=2.0, help="sensor noise sigma, grey levels")
    p.add_argument("--parked", type=float, default=0.0, help="seconds parked mid-drive")
    p.add_argument("--stops", type=int, default=1, help="with --parked: stops of that length")
    p.add_argument(
        "--lighting", type=float, default=1.0, help="exposure and gamma drift (1: the samples')"
    )
    p.add_argument("--variable-rate", action="store_true")
    p.add_argument("--drop-frames", type=int, default=0, metavar="K")
    p.add_argument("--lap-length", type=float, help="metres of route per lap")
    p.add_argument("--latency-ms", type=float, default=0.0, help="image log time - stamp")
    p.add_argument("--bag-compression", choices=("none", "bz2", "lz4"), default="none")
    p.add_argument("--mcap-compression", choices=("none", "lz4", "zstd"), default="zstd")
    p.add_argument("--depth", action="store_true", help="also write an aligned depth topic")
    p.add_argument(
        "--depth-encoding",
        choices=DEPTH_ENCODINGS,
        help="with --depth: 32FC1 (metres, the default) or 16UC1 (millimetres)",
    )
    p.add_argument(
        "--season-change",
        action="store_true",
        help="snow and an overcast sky from the lap boundary nearest the middle on",
    )
    p.add_argument("--jobs", type=int, default=1, help="rendering worker processes")
    return p


def _config(args: argparse.Namespace) -> Config:
    return Config(
        name=args.name or f"{args.route}_seed{args.seed}",
        seed=args.seed,
        route=args.route,
        duration=args.duration,
        rate=args.rate,
        width=args.width,
        height=args.height,
        formats=tuple(clw.parse_formats(args.formats)),
        image=args.image,
        quality=args.quality,
        color=not args.mono,
        noise_sigma=args.noise,
        parked=args.parked,
        stops=args.stops,
        lighting=args.lighting,
        variable_rate=args.variable_rate,
        drop_frames=args.drop_frames,
        lap_length=args.lap_length,
        latency_ms=args.latency_ms,
        bag_compression=args.bag_compression,
        mcap_compression=args.mcap_compression,
        depth=args.depth,
        depth_encoding=args.depth_encoding or "32FC1",
        season_change=args.season_change,
    )


def _report(results: Sequence[Result]) -> None:
    for r in results:
        print(
            f"{r.config.name}: {r.n_frames} frames {r.config.width}x{r.config.height},"
            f" rendered+encoded at {r.render_fps:.1f} frames/s, {r.seconds:.1f} s in all;"
            f" GT {r.gt_events} loop events ({r.gt_cells} cells)"
        )
        for path in r.files.values():
            print(f"  {clw.path_size(path):>12,d}  {path}")
    total = sum(clw.path_size(p) for r in results for p in r.files.values())
    print(f"total {total:,} bytes")


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if args.samples:
            results = make_samples(args.out or REPO / "sample_logs", args.jobs)
        elif args.out is None:
            _parser().error("--out is required (or use --samples)")
        elif args.depth_encoding and not args.depth:
            _parser().error("--depth-encoding needs --depth")
        else:
            results = [generate(_config(args), args.out, args.jobs)]
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    _report(results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
