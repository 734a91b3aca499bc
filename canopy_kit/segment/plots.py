"""Figures of a segmentation: the map from above, and a gallery of the failures."""

from __future__ import annotations

from typing import Any

import numpy as np

from canopy_kit.core.cloud import PointCloud, column_max, column_min
from canopy_kit.core.voxel import first_minimum
from canopy_kit.segment.result import Segmentation

NOISE_RGBA = (0.75, 0.75, 0.75, 0.35)


def segment_colours(labels: np.ndarray) -> np.ndarray:
    """RGBA per label: tab20 without its two greys (they read as the grey of unlabelled
    points), stepping 7 colours from one label to the next so neighbours differ."""
    import matplotlib

    palette = np.delete(np.asarray(matplotlib.colormaps["tab20"].colors), [14, 15], axis=0)
    rgba = np.ones((len(labels), 4))
    rgba[:, :3] = palette[np.maximum(labels, 0) * 7 % len(palette)]
    rgba[labels < 0] = NOISE_RGBA
    return rgba


def _sample(n: int, max_points: int, seed: int = 0) -> np.ndarray:
    if n <= max_points:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False))


def top_view_image(
    xy: np.ndarray, labels: np.ndarray, height: np.ndarray, pixel: float = 0.1
) -> tuple[np.ndarray, list[float]]:
    """RGBA image of points seen from above (the highest point of each pixel gives its
    colour, as a scatter plot of every point would look) and its ``imshow`` extent."""
    lo = column_min(xy)
    ij = np.floor((xy - lo) / pixel).astype(np.int64)
    shape = column_max(ij) + 1
    flat = ij[:, 1] * shape[0] + ij[:, 0]
    top = first_minimum(flat, -np.asarray(height, float))  # the highest point of each pixel
    image = np.zeros((shape[1] * shape[0], 4))  # transparent where no point fell
    image[flat[top]] = segment_colours(labels[top])
    hi = lo + shape * pixel
    return image.reshape(shape[1], shape[0], 4), [lo[0], hi[0], lo[1], hi[1]]


def plot_top_view(
    cloud: PointCloud, seg: Segmentation, ax: Any = None, pixel: float = 0.1, show_rows: bool = True
) -> Any:
    """Top view of the map (``pixel`` m): each tree in its colour, labelled by its
    ``tree_id`` (the id of trees.csv, ``r0-L0``); returns the Figure."""
    import matplotlib.pyplot as plt

    if ax is None:
        fig, ax = plt.subplots(figsize=(8, 8))
    else:
        fig = ax.figure
    keep = np.flatnonzero(seg.height >= 0.3)
    if len(keep):
        image, extent = top_view_image(
            cloud.xyz[keep, :2], seg.labels[keep], seg.height[keep], pixel
        )
        ax.imshow(image, extent=extent, origin="lower", interpolation="nearest")
    if show_rows:
        for line in seg.rows.lines:
            p = line.polyline()
            ax.plot(p[:, 0], p[:, 1], "k--", lw=0.6, alpha=0.6)
    for t in seg.trees:
        ax.annotate(t.tree_id, (t.x, t.y), fontsize=7, ha="center", va="center", weight="bold")
    d = seg.rows.direction
    lo = column_min(cloud.xyz[keep, :2]) if len(keep) else np.zeros(2)
    ax.annotate("", lo + 3 * d, lo, arrowprops={"arrowstyle": "->", "lw": 1.5})
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(
        f"{seg.n_trees} trees, {len(seg.rows.lines)} rows ({seg.method}); arrow: driving direction"
    )
    return fig


def plot_failure_gallery(
    cloud: PointCloud,
    seg: Segmentation,
    score: Any,
    truth: np.ndarray,
    max_panels: int = 6,
    margin: float = 2.0,
    max_points: int = 40_000,
) -> Any:
    """Side-by-side truth and segmentation around each tree that was not segmented correctly.

    ``score`` is a point-mode :class:`canopy_kit.evaluate.segmentation_score.SegmentationScore` of ``seg``
    against the per-point true tree ids ``truth``. Returns the Figure (``None`` if every
    tree was correct).
    """
    import matplotlib.pyplot as plt

    failed = score.trees[score.trees["status"] != "correct"].head(max_panels)
    if failed.empty:
        return None
    fig, axes = plt.subplots(len(failed), 2, figsize=(9, 3.2 * len(failed)), squeeze=False)
    for (ax_t, ax_p), (_, row) in zip(axes, failed.iterrows()):
        members = truth == row["truth_id"]
        lo = cloud.xyz[members, :2].min(axis=0) - margin
        hi = cloud.xyz[members, :2].max(axis=0) + margin
        near = np.flatnonzero(
            np.all((cloud.xyz[:, :2] >= lo) & (cloud.xyz[:, :2] <= hi), axis=1)
            & (seg.height >= 0.3)
        )
        near = near[_sample(len(near), max_points)]
        # Side view along the longer side of the window.
        axis = 0 if hi[0] - lo[0] >= hi[1] - lo[1] else 1
        for ax, labels, title in ((ax_t, truth, "truth"), (ax_p, seg.labels, "segmentation")):
            ax.scatter(
                cloud.xyz[near, axis],
                seg.height[near],
                s=0.4,
                c=segment_colours(labels[near]),
                linewidths=0,
                rasterized=True,
            )
            ax.set_aspect("equal")
            ax.set_title(
                f"{title}: tree {row['truth_id']}"
                + (f" ({row.get('truth_label', '')})" if "truth_label" in row else ""),
                fontsize=9,
            )
        ax_p.set_title(f"segmentation: {row['status']}, best IoU {row['iou']:.2f}", fontsize=9)
        ax_t.set_ylabel("height above ground (m)")
    fig.tight_layout()
    return fig
