"""Figures for notebooks and docs: orthomosaic with crown outlines and labels, DSM/CHM."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from ground_truth.crowns import CrownSegmentation
from ground_truth.dsm import SurfaceModel
from ground_truth.ortho import Orthomosaic


def overlay_crowns_rgb(
    mosaic: Orthomosaic, seg: CrownSegmentation, color: tuple[int, int, int] = (255, 40, 40)
) -> np.ndarray:
    """The orthomosaic (RGBA uint8) with crown boundaries painted in ``color``."""
    from skimage.segmentation import find_boundaries

    out = mosaic.rgba.copy()
    edges = find_boundaries(seg.labels, mode="inner")
    out[edges, :3] = color
    return out


def crown_labels(crowns: pd.DataFrame) -> list[str]:
    """Per crown: its matched LiDAR ``tree_id``, or ``aerial <crown_id>`` when unmatched."""
    ids = crowns["tree_id"].fillna("").astype(str) if "tree_id" in crowns else [""] * len(crowns)
    return [tid if tid else f"aerial {int(cid)}" for tid, cid in zip(ids, crowns["crown_id"])]


def plot_crowns(
    mosaic: Orthomosaic,
    seg: CrownSegmentation,
    crowns: pd.DataFrame,
    label_column: str | None = None,
    truth: pd.DataFrame | None = None,
    ax: Any = None,
    window: tuple[float, float, float, float] | None = None,
) -> Any:
    """Orthomosaic with crown outlines and labels; ``truth`` (x, y, diameter) adds circles.

    Crowns are labelled by ``label_column``; by default a crown matched to a LiDAR tree by
    that tree's ``tree_id`` (the id of trees.csv), any other ``aerial <crown_id>``.
    ``window`` is (xmin, xmax, ymin, ymax) in the local frame (default: around the crowns).
    Returns the axes.
    """
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    if ax is None:
        _, ax = plt.subplots(figsize=(10, 8))
    ax.imshow(mosaic.rgba, extent=mosaic.grid.extent, interpolation="nearest")
    x, y = mosaic.grid.centers()
    ax.contour(
        x, y, seg.labels, levels=np.unique(seg.labels)[1:] - 0.5, colors="red", linewidths=0.8
    ) if seg.labels.max() > 0 else None
    labels = crown_labels(crowns) if label_column is None else crowns[label_column].astype(str)
    for row, label in zip(crowns.itertuples(), labels):
        ax.annotate(
            label,
            (row.x, row.y),
            color="white",
            fontsize=8,
            ha="center",
            va="center",
            weight="bold",
        )
    if truth is not None:
        for row in truth.itertuples():
            ax.add_patch(
                Circle((row.x, row.y), row.diameter / 2, fill=False, color="cyan", lw=0.7, ls="--")
            )
    if window is None and len(crowns):  # the trees, not the whole surveyed area
        window = (
            crowns["x"].min() - 4,
            crowns["x"].max() + 4,
            crowns["y"].min() - 4,
            crowns["y"].max() + 4,
        )
    if window is not None:
        ax.set_xlim(window[0], window[1])
        ax.set_ylim(window[2], window[3])
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.set_aspect("equal")
    return ax


def plot_surface(surface: SurfaceModel, axes: Any = None, chm_max: float | None = None) -> Any:
    """DSM (relative to the lowest ground) and CHM side by side. Returns the two axes."""
    import matplotlib.pyplot as plt

    if axes is None:
        _, axes = plt.subplots(1, 2, figsize=(14, 6))
    base = float(np.nanmin(surface.dtm))
    im0 = axes[0].imshow(surface.dsm - base, extent=surface.grid.extent, cmap="terrain")
    axes[0].set_title(f"DSM (m above {base:.1f} m)")
    plt.colorbar(im0, ax=axes[0], shrink=0.8)
    top = chm_max if chm_max is not None else float(np.nanpercentile(surface.chm, 99.5))
    im1 = axes[1].imshow(
        np.clip(surface.chm, 0, None), extent=surface.grid.extent, cmap="viridis", vmin=0, vmax=top
    )
    axes[1].set_title("canopy height model (m)")
    plt.colorbar(im1, ax=axes[1], shrink=0.8)
    for a in axes:
        a.set_xlabel("x east (m)")
        a.set_ylabel("y north (m)")
    return axes


def plot_agreement(
    measured: np.ndarray, truth: np.ndarray, ax: Any = None, label: str = "diameter (m)"
) -> Any:
    """Measured against true values with the 1:1 line."""
    import matplotlib.pyplot as plt

    if ax is None:
        _, ax = plt.subplots(figsize=(5, 5))
    ax.scatter(truth, measured, s=14)
    lo = float(np.nanmin([np.nanmin(truth), np.nanmin(measured)]))
    hi = float(np.nanmax([np.nanmax(truth), np.nanmax(measured)]))
    ax.plot([lo, hi], [lo, hi], "k--", lw=0.8)
    ax.set_xlabel(f"true {label}")
    ax.set_ylabel(f"aerial {label}")
    ax.set_aspect("equal")
    return ax
