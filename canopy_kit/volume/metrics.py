"""Per-tree size metrics beside the volume, and the sphere volume the aerial truth uses.

Definitions (metres; the same as the simulator's truth table):

- ``height_m``: highest point minus the ground height (``ground_z``, default the lowest point);
- ``crown_base_height_m``: lowest horizontal slice (``slice_thickness`` thick) whose
  horizontal extent reaches ``crown_fraction`` of the widest slice's, minus the ground
  height: trunk slices are narrow and are skipped;
- ``crown_diameter_max_m``: the widest horizontal extent (largest distance between two
  points of the horizontal convex hull);
- ``crown_diameter_mean_m``: the mean of that widest extent and the extent perpendicular
  to it;
- ``projected_area_m2``: area of the horizontal convex hull;
- ``density_per_m3``: points per m³ of ``volume_m3`` (given, else the convex hull);
- ``sphere_volume_m3``: π d³/6 with d the widest extent, the paper's aerial ground-truth
  model (§III.A), so LiDAR and aerial numbers can be compared like with like.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from canopy_kit.errors import ConfigError, InputError
from canopy_kit.volume.base import as_points

# A tree's position and size in every per-tree table (run, segment, stream, report), in order.
POSITION_AND_SIZE = ["x", "y", "lat", "lon", "n_points", "height_m", "crown_diameter_m"]


@dataclass(frozen=True)
class TreeMetrics:
    """Size metrics of one tree's points (see the module docstring for definitions)."""

    n_points: int
    height_m: float
    crown_base_height_m: float
    crown_diameter_max_m: float
    crown_diameter_mean_m: float
    projected_area_m2: float
    density_per_m3: float
    sphere_volume_m3: float

    def as_dict(self) -> dict[str, Any]:
        """Plain dict (for JSON and tables)."""
        return asdict(self)


def sphere_volume(diameter: float) -> float:
    """Volume of a sphere of the given diameter, π d³/6."""
    return float(np.pi * diameter**3 / 6.0)


def horizontal_hull(xy: np.ndarray) -> np.ndarray:
    """Vertices of the 2-D convex hull of (N, 2) points, counter-clockwise.

    Degenerate sets give their extreme points: the two ends of points on one line (a tree
    seen edge-on, a wall), the one point of points that coincide."""
    from scipy.spatial import ConvexHull, QhullError

    xy = np.asarray(xy, dtype=float)
    if len(xy) >= 3:
        try:
            return xy[ConvexHull(xy - xy.mean(axis=0)).vertices]
        except QhullError:
            pass
    if len(xy) == 0:
        return xy.reshape(0, 2)
    centred = xy - xy.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    along = centred @ axes[0]
    ends = xy[[int(np.argmin(along)), int(np.argmax(along))]]
    return ends[:1] if np.array_equal(ends[0], ends[1]) else ends


def _farthest_pair(hull: np.ndarray) -> tuple[int, int]:
    """Indices of the two vertices of a convex polygon (counter-clockwise) farthest apart.

    Rotating calipers: O(h) time and memory in the h vertices, where all pairs would take
    h² (a hull of 30,000 vertices asks 13 GiB for the pair distances)."""
    n = len(hull)
    if n <= 3:
        d2 = ((hull[:, None, :] - hull[None, :, :]) ** 2).sum(axis=2)
        i, j = np.unravel_index(np.argmax(d2), d2.shape)
        return int(i), int(j)

    def height(a: int, b: int, c: int) -> float:  # twice the area of triangle a b c
        (ax, ay), (bx, by), (cx, cy) = hull[a], hull[b], hull[c]
        return abs((bx - ax) * (cy - ay) - (by - ay) * (cx - ax))

    best, pair, j = -1.0, (0, 1), 1
    for i in range(n):
        k = (i + 1) % n
        for _ in range(n):  # the vertex farthest from edge i-k (advances at most once around)
            if height(i, k, (j + 1) % n) <= height(i, k, j):
                break
            j = (j + 1) % n
        for a in (i, k):
            d = float(((hull[a] - hull[j]) ** 2).sum())
            if d > best:
                best, pair = d, (a, j)
    return pair


def widest_axis(xy: np.ndarray, hull: np.ndarray | None = None) -> tuple[float, float, np.ndarray]:
    """(widest extent, extent perpendicular to it, unit vector along the widest) of (N, 2)
    points; ``hull``: their :func:`horizontal_hull`, when already made."""
    hull = horizontal_hull(xy) if hull is None else hull
    if len(hull) < 2:
        return 0.0, 0.0, np.array([1.0, 0.0])
    i, j = _farthest_pair(hull)
    widest = float(np.linalg.norm(hull[j] - hull[i]))
    if widest == 0.0:
        return 0.0, 0.0, np.array([1.0, 0.0])
    axis = (hull[j] - hull[i]) / widest
    across = hull @ np.array([-axis[1], axis[0]])
    return widest, float(np.ptp(across)), axis


def widest_extents(xy: np.ndarray, hull: np.ndarray | None = None) -> tuple[float, float]:
    """(widest horizontal extent, extent perpendicular to it) of (N, 2) points; ``hull``:
    their :func:`horizontal_hull`, when already made."""
    widest, across, _ = widest_axis(xy, hull)
    return widest, across


def polygon_area(vertices: np.ndarray) -> float:
    """Area of a simple polygon given by its vertices in order (shoelace)."""
    if len(vertices) < 3:
        return 0.0
    x, y = vertices[:, 0], vertices[:, 1]
    return float(0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def crown_base_z(
    xyz: np.ndarray, slice_thickness: float = 0.1, crown_fraction: float = 0.25
) -> float:
    """Height of the lowest slice whose horizontal extent reaches ``crown_fraction`` of the widest."""
    z0 = xyz[:, 2].min()
    k = np.floor((xyz[:, 2] - z0) / slice_thickness).astype(np.intp)
    order = np.argsort(k, kind="stable")
    ks, xy = k[order], xyz[order, :2]
    starts = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    spread = np.maximum.reduceat(xy, starts) - np.minimum.reduceat(xy, starts)
    widths = np.zeros(int(ks[-1]) + 1)
    widths[ks[starts]] = spread.max(axis=1)
    first = int(np.argmax(widths >= crown_fraction * widths.max()))
    return float(z0 + first * slice_thickness)


def tree_metrics(
    xyz: Any,
    ground_z: float | None = None,
    volume_m3: float | None = None,
    slice_thickness: float = 0.1,
    crown_fraction: float = 0.25,
) -> TreeMetrics:
    """Height, crown base, diameters, projected area, count, density and sphere volume of a tree."""
    pts = as_points(xyz)
    if len(pts) == 0:
        raise InputError("xyz: a tree needs at least one point for its metrics")
    if not slice_thickness > 0:
        raise ConfigError(f"slice_thickness must be positive, got {slice_thickness!r}")
    if not 0 < crown_fraction <= 1:
        raise ConfigError(f"crown_fraction must be in (0, 1], got {crown_fraction!r}")
    ground = float(pts[:, 2].min()) if ground_z is None else float(ground_z)
    outline = horizontal_hull(pts[:, :2])
    widest, across = widest_extents(pts[:, :2], outline)
    area = polygon_area(outline)
    if volume_m3 is None:
        from canopy_kit.volume.hull import ConvexHullVolume

        volume_m3 = ConvexHullVolume()(pts).volume_m3
    density = len(pts) / volume_m3 if volume_m3 > 0 else float("nan")
    return TreeMetrics(
        n_points=len(pts),
        height_m=float(pts[:, 2].max() - ground),
        crown_base_height_m=crown_base_z(pts, slice_thickness, crown_fraction) - ground,
        crown_diameter_max_m=widest,
        crown_diameter_mean_m=0.5 * (widest + across),
        projected_area_m2=area,
        density_per_m3=float(density),
        sphere_volume_m3=sphere_volume(widest),
    )


def crown_columns(xyz: Any, ground_height: Any = None) -> dict[str, Any]:
    """One tree's position and size as the per-tree table's columns (``x``, ``y``: the median
    of its points; heights above ``ground_height(xy)`` at that position, e.g. the
    segmentation's ground model; else above its lowest point): what ``run`` and ``segment``
    both write for a tree."""
    pts = as_points(xyz)
    centre = np.median(pts[:, :2], axis=0)
    ground = float(ground_height(centre[None, :])[0]) if ground_height is not None else None
    # The metrics' density is not in the table: no second hull of every point for it.
    metrics = tree_metrics(pts, ground_z=ground, volume_m3=float("nan"))
    return {
        "x": float(centre[0]),
        "y": float(centre[1]),
        "n_points": metrics.n_points,
        "height_m": metrics.height_m,
        "crown_base_height_m": metrics.crown_base_height_m,
        "crown_diameter_m": metrics.crown_diameter_max_m,
        "crown_diameter_mean_m": metrics.crown_diameter_mean_m,
        "projected_area_m2": metrics.projected_area_m2,
        "sphere_volume_m3": metrics.sphere_volume_m3,
    }
