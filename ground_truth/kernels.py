"""Compiled per-cell loops (numba) of the dense surface matching, the orthomosaic's line
of sight and the visual hull's carving.

The plane sweep (``ground_truth.dsm``) looks every cell up in its photos at each trial
height: a projection, the lens distortion and a bilinear lookup. Through numpy and
``scipy.ndimage.map_coordinates`` that is a dozen passes over memory with temporaries per
photo and height (15,535 calls, 14 s of a 2 × 5 flight's 29 s surface stage); here it is one
loop. The kernel keeps ``map_coordinates(order=1, mode="constant", cval=nan)``'s values
(tested against it), is compiled on first use and cached on disk.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, inline="always")
def bilinear_at(image: np.ndarray, r: float, c: float) -> float:
    """``image`` at the fractional (row, column) ``r, c`` (cell centres at integers), bilinear;
    NaN outside the span of the cell centres (``map_coordinates(order=1, mode="constant",
    cval=nan)``), also for a NaN coordinate (no comparison holds)."""
    rows, cols = image.shape
    if not (r >= 0.0 and r <= rows - 1 and c >= 0.0 and c <= cols - 1):
        return np.nan
    r0 = min(int(r), max(rows - 2, 0))
    c0 = min(int(c), max(cols - 2, 0))
    r1, c1 = min(r0 + 1, rows - 1), min(c0 + 1, cols - 1)
    fr, fc = r - r0, c - c0
    top = (1.0 - fc) * image[r0, c0] + fc * image[r0, c1]
    bottom = (1.0 - fc) * image[r1, c0] + fc * image[r1, c1]
    return (1.0 - fr) * top + fr * bottom


@numba.njit(cache=True, nogil=True)
def project_bilinear(
    base: np.ndarray,
    axis: np.ndarray,
    height: float,
    intrinsics: np.ndarray,
    image: np.ndarray,
    index: np.ndarray,
    out: np.ndarray,
    second: np.ndarray,
    second_out: np.ndarray,
) -> None:
    """``out[index[n]]`` = ``image`` bilinearly sampled where camera point
    ``base[n] + height · axis`` projects (pinhole ``intrinsics`` = fx, fy, cx, cy, k1, k2, pixel
    centres at integers + 0.5); NaN where it falls outside the pixel centres' span. A
    ``second`` image of the same size (none: an empty one) is sampled at the same pixels into
    ``second_out``: one projection for both."""
    fx, fy, cx, cy, k1, k2 = (
        intrinsics[0],
        intrinsics[1],
        intrinsics[2],
        intrinsics[3],
        intrinsics[4],
        intrinsics[5],
    )
    distorted = k1 != 0.0 or k2 != 0.0
    both = second.size > 0
    for n in range(base.shape[0]):
        z = base[n, 2] + height * axis[2]
        x = (base[n, 0] + height * axis[0]) / z
        y = (base[n, 1] + height * axis[1]) / z
        if distorted:
            r2 = x * x + y * y
            d = 1.0 + k1 * r2 + k2 * r2 * r2
            x, y = x * d, y * d
        r, c = fy * y + (cy - 0.5), fx * x + (cx - 0.5)
        out[index[n]] = bilinear_at(image, r, c)
        if both:
            second_out[index[n]] = bilinear_at(second, r, c)


@numba.njit(cache=True, nogil=True, inline="always")
def _reflected(i: int, n: int) -> int:
    """Index ``i`` of a line of ``n`` cells mirrored at its ends (scipy.ndimage's "reflect":
    d c b a | a b c d | d c b a)."""
    while i < 0 or i >= n:
        i = -i - 1 if i < 0 else 2 * n - i - 1
    return i


@numba.njit(cache=True, nogil=True)
def pair_score(
    a: np.ndarray,
    b: np.ndarray,
    class_a: np.ndarray,
    class_b: np.ndarray,
    size: int,
    min_fraction: float,
    class_weight: float,
) -> np.ndarray:
    """Per cell, the windowed (``size`` × ``size``, mirrored at the edges) normalised
    cross-correlation of rasters ``a`` and ``b`` over the cells both have (NaN where either is
    NaN or fewer than ``min_fraction`` of the window counts), minus ``class_weight`` times the
    window's mean class difference of ``class_a`` and ``class_b`` over the cells both have
    (``class_weight`` 0: the correlation alone, the classes not read)."""
    rows, cols = a.shape
    out = np.empty((rows, cols), np.float32)
    first = size // 2
    need = min_fraction * size * size
    for i in range(rows):
        for j in range(cols):
            if not (np.isfinite(a[i, j]) and np.isfinite(b[i, j])):
                out[i, j] = np.nan
                continue
            n = 0.0
            sa = sb = saa = sbb = sab = 0.0
            nc = 0.0
            sc = 0.0
            for di in range(size):
                r = _reflected(i - first + di, rows)
                for dj in range(size):
                    c = _reflected(j - first + dj, cols)
                    va, vb = a[r, c], b[r, c]
                    if np.isfinite(va) and np.isfinite(vb):
                        n += 1.0
                        sa += va
                        sb += vb
                        saa += va * va
                        sbb += vb * vb
                        sab += va * vb
                    if class_weight != 0.0:
                        ca, cb = class_a[r, c], class_b[r, c]
                        if np.isfinite(ca) and np.isfinite(cb):
                            nc += 1.0
                            sc += abs(ca - cb)
            if n < need:
                out[i, j] = np.nan
                continue
            ma, mb = sa / n, sb / n
            var_a = max(saa / n - ma * ma, 1e-6)
            var_b = max(sbb / n - mb * mb, 1e-6)
            score = (sab / n - ma * mb) / np.sqrt(var_a * var_b)
            if class_weight != 0.0:
                score -= class_weight * (sc / nc if nc > 0 else np.nan)
            out[i, j] = score
    return out


@numba.njit(cache=True, nogil=True)
def rays_clear(
    points: np.ndarray,
    center: np.ndarray,
    reach: np.ndarray,
    step: float,
    surface: np.ndarray,
    x0: float,
    y0: float,
    resolution: float,
    clearance: float,
) -> np.ndarray:
    """Per point, whether the ray towards ``center`` stays no more than ``clearance`` below
    the ``surface`` raster (north-up, top-left corner ``x0, y0``) at every ``step`` metres of
    horizontal travel up to the point's ``reach``; outside the raster it is clear."""
    clear = np.ones(points.shape[0], np.bool_)
    for n in range(points.shape[0]):
        dx, dy, dz = center[0] - points[n, 0], center[1] - points[n, 1], center[2] - points[n, 2]
        horizontal = max(np.hypot(dx, dy), 1e-9)
        s = 1
        while s * step <= reach[n]:
            dist = s * step
            x = points[n, 0] + dx / horizontal * dist
            y = points[n, 1] + dy / horizontal * dist
            z = points[n, 2] + dz / horizontal * dist
            height = bilinear_at(surface, (y0 - y) / resolution - 0.5, (x - x0) / resolution - 0.5)
            if height > z + clearance:
                clear[n] = False
                break
            s += 1
    return clear


@numba.njit(cache=True, nogil=True)
def carve_count(
    pts: np.ndarray,
    rotations: np.ndarray,
    translations: np.ndarray,
    intrinsics: np.ndarray,
    vegetation: np.ndarray,
    offsets: np.ndarray,
    widths: np.ndarray,
    heights: np.ndarray,
    limit: float,
    min_views: int,
    min_fraction: float,
) -> int:
    """How many points ``pts`` (N, 3) stay in a visual hull: seen (in front of the camera,
    inside the image) by at least ``min_views`` of the views and shown as vegetation by at
    least ``min_fraction`` of those. View k: world-to-camera ``rotations[k]``,
    ``translations[k]``, pinhole ``intrinsics[k]`` = fx, fy, cx, cy, k1, k2 (pixel (row,
    col) = floor of the projection), its vegetation mask (1: vegetation) flattened row by
    row at ``vegetation[offsets[k]:]``, ``widths[k]`` x ``heights[k]`` pixels. A point
    leaves as soon as more than ``limit`` views showed no vegetation there."""
    count = 0
    for n in range(pts.shape[0]):
        px, py, pz = pts[n, 0], pts[n, 1], pts[n, 2]
        seen = 0
        bare = 0
        for k in range(rotations.shape[0]):
            r = rotations[k]
            depth = r[2, 0] * px + r[2, 1] * py + r[2, 2] * pz + translations[k, 2]
            if not depth > 0.0:
                continue
            x = (r[0, 0] * px + r[0, 1] * py + r[0, 2] * pz + translations[k, 0]) / depth
            y = (r[1, 0] * px + r[1, 1] * py + r[1, 2] * pz + translations[k, 1]) / depth
            k1, k2 = intrinsics[k, 4], intrinsics[k, 5]
            if k1 != 0.0 or k2 != 0.0:
                r2 = x * x + y * y
                d = 1.0 + k1 * r2 + k2 * r2 * r2
                x, y = x * d, y * d
            col = np.floor(intrinsics[k, 0] * x + intrinsics[k, 2])
            row = np.floor(intrinsics[k, 1] * y + intrinsics[k, 3])
            if col >= 0.0 and row >= 0.0 and col < widths[k] and row < heights[k]:
                seen += 1
                if vegetation[offsets[k] + int(row) * widths[k] + int(col)] == 0:
                    bare += 1
                    if bare > limit:
                        break
        if bare <= limit and seen >= min_views and seen - bare >= min_fraction * seen:
            count += 1
    return count
