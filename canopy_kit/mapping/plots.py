"""Figures of a mapping run, for notebooks, the CLI and the docs (matplotlib, no display needed)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.core.cloud import PointCloud


def _figure(ax: Any, size: tuple[float, float]) -> tuple[Any, Any]:
    import matplotlib.pyplot as plt

    if ax is not None:
        return ax.figure, ax
    fig, ax = plt.subplots(figsize=size, constrained_layout=True)
    return fig, ax


def plot_trajectories(
    estimated: pd.DataFrame,
    reference: pd.DataFrame | None = None,
    alignment: np.ndarray | None = None,
    title: str = "",
    ax: Any = None,
) -> Any:
    """Top view of the estimated trajectory and, when given, the reference, in the estimate's
    (the map's) frame: the frame of every other map figure.

    ``alignment`` (4x4, e.g. from :func:`canopy_kit.evaluate.trajectory_error.trajectory_errors`)
    maps the estimate onto the reference frame; its inverse brings the reference onto the
    map. Without it both are drawn as they are. Returns the matplotlib Figure.
    """
    fig, ax = _figure(ax, (7, 6))
    xyz = estimated[["x", "y", "z"]].to_numpy()
    if reference is not None:
        ref = reference[["x", "y", "z"]].to_numpy()
        if alignment is not None:
            a = np.asarray(alignment)
            ref = (ref - a[:3, 3]) @ a[:3, :3]  # the inverse of x -> R x + t
        ax.plot(ref[:, 0], ref[:, 1], color="0.3", lw=2.5, alpha=0.6, label="true")
    ax.plot(xyz[:, 0], xyz[:, 1], color="tab:red", lw=1.0, label="estimated")
    ax.plot(xyz[0, 0], xyz[0, 1], "o", color="tab:green", ms=6, label="start")
    ax.set_aspect("equal")
    ax.set_xlabel("x (east) [m]")
    ax.set_ylabel("y (north) [m]")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title or "trajectory, top view")
    return fig


def plot_trajectory_errors(
    estimated: pd.DataFrame, reference: pd.DataFrame, alignment: np.ndarray, ax: Any = None
) -> Any:
    """Position error (x, y, z and norm) over time after the SE(3) alignment; the Figure."""
    from canopy_kit.evaluate.trajectory_error import interpolate_reference

    fig, ax = _figure(ax, (8, 3))
    t = estimated["time"].to_numpy()
    ref, inside = interpolate_reference(reference, t)
    xyz = estimated[["x", "y", "z"]].to_numpy()[inside]
    a = np.asarray(alignment)
    err = xyz @ a[:3, :3].T + a[:3, 3] - ref[:, :3, 3]
    tt = t[inside] - t[inside][0]
    for k, name in enumerate("xyz"):
        ax.plot(tt, err[:, k] * 100, lw=0.8, label=name)
    ax.plot(tt, np.linalg.norm(err, axis=1) * 100, color="k", lw=1.0, label="|e|")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("error [cm]")
    ax.legend(loc="upper right", fontsize=8, ncol=4)
    ax.set_title("position error after SE(3) alignment")
    return fig


def height_raster(
    cloud: PointCloud, cell: float = 0.1
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Highest point per ``cell`` (NaN where empty) and its extent (xmin, xmax, ymin, ymax)."""
    xyz = cloud.xyz
    lo = xyz[:, :2].min(axis=0)
    ij = np.floor((xyz[:, :2] - lo) / cell).astype(np.int64)
    shape = ij.max(axis=0) + 1
    flat = ij[:, 1] * shape[0] + ij[:, 0]
    top = np.full(int(shape[0] * shape[1]), -np.inf)
    np.maximum.at(top, flat, xyz[:, 2])
    top[~np.isfinite(top)] = np.nan
    extent = (lo[0], lo[0] + shape[0] * cell, lo[1], lo[1] + shape[1] * cell)
    return top.reshape(shape[1], shape[0]), extent


def above_ground(
    raster: np.ndarray,
    extent: tuple[float, float, float, float],
    cell: float,
    ground_height: Callable[[np.ndarray], np.ndarray],
) -> np.ndarray:
    """A :func:`height_raster` less the ground height ``ground_height(xy)`` at each cell centre."""
    rows, cols = np.nonzero(np.isfinite(raster))
    xy = np.column_stack([extent[0] + (cols + 0.5) * cell, extent[2] + (rows + 0.5) * cell])
    out = np.full_like(raster, np.nan)
    out[rows, cols] = raster[rows, cols] - ground_height(xy)
    return out


def plot_map_top_view(
    cloud: PointCloud,
    trajectory: pd.DataFrame | None = None,
    cell: float = 0.1,
    title: str = "",
    ax: Any = None,
    ground_height: Callable[[np.ndarray], np.ndarray] | None = None,
) -> Any:
    """Top view of a map: highest point per cell coloured by its height above the ground
    (``ground_height(xy) -> z``, e.g. a segmentation's ground model) or, without one, by the
    map's z, labelled so; trajectory on top."""
    fig, ax = _figure(ax, (7, 7))
    raster, extent = height_raster(cloud, cell)
    if ground_height is not None:
        raster = above_ground(raster, extent, cell, ground_height)
    z0 = np.nanpercentile(raster, 2)
    z1 = np.nanpercentile(raster, 99.5)
    im = ax.imshow(
        raster,
        origin="lower",
        extent=extent,
        cmap="viridis",
        vmin=z0,
        vmax=z1,
        interpolation="nearest",
    )
    label = (
        "height above ground [m]" if ground_height is not None else "map z (not above ground) [m]"
    )
    fig.colorbar(im, ax=ax, shrink=0.7, label=label)
    if trajectory is not None:
        ax.plot(trajectory["x"], trajectory["y"], color="w", lw=0.8, alpha=0.9)
    ax.set_aspect("equal")
    ax.set_xlabel("x (east) [m]")
    ax.set_ylabel("y (north) [m]")
    ax.set_title(title or f"map top view ({len(cloud):,} points, {cell} m cells)")
    return fig


def mapping_figures(
    result: Any,
    reference: pd.DataFrame | None = None,
    evaluation: dict | None = None,
    ground_height: Callable[[np.ndarray], np.ndarray] | None = None,
) -> dict[str, Any]:
    """The standard figures of a run: ``trajectory`` (with errors when a reference is given) and
    ``map`` (coloured by height above ``ground_height`` when given, else by map z)."""
    import matplotlib.pyplot as plt

    figs: dict[str, Any] = {}
    if reference is not None and evaluation is not None:
        fig, (a1, a2) = plt.subplots(
            2, 1, figsize=(8, 9), height_ratios=[3, 1], constrained_layout=True
        )
        align = np.asarray(evaluation["alignment"])
        plot_trajectories(
            result.trajectory,
            reference,
            align,
            title=f"estimated vs true (ATE {100 * evaluation['ate_rmse_m']:.1f} cm, "
            f"drift {evaluation['drift_percent']:.2f} %)",
            ax=a1,
        )
        plot_trajectory_errors(result.trajectory, reference, align, ax=a2)
        figs["trajectory"] = fig
    else:
        figs["trajectory"] = plot_trajectories(result.trajectory)
    figs["map"] = plot_map_top_view(result.map, result.trajectory, ground_height=ground_height)
    return figs
