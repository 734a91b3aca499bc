"""Figures of simulated orchards and scans (matplotlib; used by docs and notebooks)."""

from __future__ import annotations

from typing import Any

import numpy as np

from canopy_kit.sim.orchard import Orchard


def plot_orchard_top_view(
    orchard: Orchard,
    ax: Any = None,
    trajectory_xy: np.ndarray | None = None,
    title: str | None = None,
) -> Any:
    """Crown footprints coloured by tree, trunks, labels and optionally the drive path."""
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    if ax is None:
        _, ax = plt.subplots(figsize=(7, 7))
    cmap = plt.get_cmap("tab20")
    for tree in orchard.trees:
        colour = cmap(tree.tree_id % 20)
        ax.add_patch(
            Polygon(
                tree.crown.footprint(),
                closed=True,
                facecolor=(*colour[:3], 0.45),
                edgecolor=colour,
                lw=1.0,
            )
        )
        ax.plot(tree.base[0], tree.base[1], "k.", ms=3)
        ax.annotate(
            f"{tree.row}:{tree.label}", tree.crown.center[:2], ha="center", va="center", fontsize=7
        )
    if trajectory_xy is not None:
        ax.plot(trajectory_xy[:, 0], trajectory_xy[:, 1], "-", color="0.3", lw=0.8, label="drive")
        ax.plot(*trajectory_xy[0, :2], "g^", ms=8, label="start")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.set_title(title or f"{orchard.spec.kind}: {len(orchard.trees)} trees (row:label)")
    return ax


def plot_scan_by_time(
    xyz: np.ndarray, times: np.ndarray, ax: Any = None, radius: float = 20.0
) -> Any:
    """One sweep seen from above, coloured by per-point time within the sweep."""
    import matplotlib.pyplot as plt

    if ax is None:
        _, ax = plt.subplots(figsize=(6, 6))
    keep = np.linalg.norm(xyz[:, :2], axis=1) < radius
    sc = ax.scatter(
        xyz[keep, 0], xyz[keep, 1], c=(times[keep] - times.min()) * 1e3, s=0.5, cmap="viridis"
    )
    plt.colorbar(sc, ax=ax, label="time in sweep (ms)")
    ax.set_aspect("equal")
    ax.set_xlabel("x sensor (m)")
    ax.set_ylabel("y sensor (m)")
    ax.set_title("one LiDAR sweep, coloured by point time")
    return ax
