"""Preprocessing: ground model, height above ground, canopy and stem bands, voxel grid.

Points are split by their height above the fitted ground: ground and low vegetation below
the stem band, stems (trunks) inside it, canopy from ``min_canopy_height`` up to
``max_canopy_height`` or, unset, up to the top the data shows (:func:`canopy_ceiling`).
Segmenters see canopy points height-normalised, ``(x, y, height above ground)``, so sloped
and bumpy ground looks flat to them.

With ``voxelize = "before_clustering"`` (the paper's text) the segmenter sees one point per
occupied voxel; with ``weight_by_density`` each voxel then weighs as many map points as it
holds, so point-count parameters (DBSCAN's N_min, the spectral split threshold) keep the
meaning they have on the map, whatever the voxel size. With ``"after_clustering"`` (the
paper's Fig. 3) the segmenter sees every canopy point of the map.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from canopy_kit.config import PreprocessConfig
from canopy_kit.core.cloud import PointCloud
from canopy_kit.core.voxel import voxel_representatives
from canopy_kit.errors import ConfigError, InputError
from canopy_kit.segment.ground import GroundModel, fit_ground

Progress = Callable[[str, float, float], None]


@dataclass
class PreparedMap:
    """A map split into ground, stems and canopy, with the points a segmenter sees."""

    ground: GroundModel
    height: np.ndarray  # per map point: height above the ground model (m)
    canopy_index: np.ndarray  # map indices of canopy points
    stem_index: np.ndarray  # map indices of stem-band points
    seen_index: np.ndarray  # map indices of the points handed to the segmenter
    seen_weight: np.ndarray  # map points each of them stands for
    canopy_to_seen: np.ndarray  # per canopy point: index into seen_index
    ceiling: float  # top of the canopy band (m above ground): set, or from the data

    def normalized(self, cloud: PointCloud, index: np.ndarray) -> np.ndarray:
        """``(x, y, height above ground)`` of map points ``index``."""
        out = cloud.xyz[index].copy()
        out[:, 2] = self.height[index]
        return out


def check_preprocess_config(config: PreprocessConfig) -> None:
    """Reject impossible preprocessing settings with an error naming the setting."""
    if not config.voxel_size > 0:
        raise ConfigError(f"preprocess.voxel_size must be positive, got {config.voxel_size}")
    top = config.max_canopy_height
    if not (0 <= config.min_canopy_height and (top is None or config.min_canopy_height < top)):
        raise ConfigError(
            "preprocess.min_canopy_height must be >= 0 and below max_canopy_height, got "
            f"{config.min_canopy_height} and {top}"
        )
    lo, hi = config.stem_band
    if not 0 <= lo < hi:
        raise ConfigError(
            f"preprocess.stem_band must be [low, high] with 0 <= low < high, got {config.stem_band}"
        )


def prepare(
    cloud: PointCloud, config: PreprocessConfig, seed: int = 0, progress: Progress | None = None
) -> PreparedMap:
    """Fit the ground, band the points by height and build the voxel grid the segmenter sees."""
    check_preprocess_config(config)
    if len(cloud) == 0:
        raise InputError("map has no points: nothing to segment")
    if not np.all(np.isfinite(cloud.xyz)):
        raise InputError("map has points with NaN or infinite coordinates")
    report = progress or (lambda *_: None)
    report("ground", 0, 2)
    ground = fit_ground(
        cloud.xyz,
        config.ground_cell_size,
        config.ground_ransac_threshold,
        config.ground_candidate_cell,
        seed=seed,
    )
    height = ground.above(cloud.xyz)
    report("ground", 1, 2)
    ceiling = config.max_canopy_height
    if ceiling is None:
        ceiling = canopy_ceiling(height, config.min_canopy_height)
    canopy = (height >= config.min_canopy_height) & (height <= ceiling)
    canopy_index = np.flatnonzero(canopy)
    stem_index = np.flatnonzero((height >= config.stem_band[0]) & (height < config.stem_band[1]))
    if config.voxelize == "before_clustering" and len(canopy_index):
        reps, inverse = voxel_representatives(cloud.xyz[canopy_index], config.voxel_size)
        weight = np.bincount(inverse, minlength=len(reps)).astype(np.float64)
        if not config.weight_by_density:
            weight = np.ones(len(reps))
        seen_index, canopy_to_seen = canopy_index[reps], inverse
    else:
        seen_index = canopy_index
        weight = np.ones(len(canopy_index))
        canopy_to_seen = np.arange(len(canopy_index))
    report("ground", 2, 2)
    return PreparedMap(
        ground, height, canopy_index, stem_index, seen_index, weight, canopy_to_seen, ceiling
    )


CEILING_BIN_M = 0.25  # height bins the canopy's top is looked for in
CEILING_GAP_M = 2.0  # an empty band this deep ends the canopy: what floats above is not tree
CEILING_MIN_SHARE = 1e-5  # a bin holding fewer of the points above the floor counts as empty
TALLEST_TREE_M = 150.0  # heights above this are never canopy


def canopy_ceiling(height: np.ndarray, floor: float) -> float:
    """The top of the canopy band (m above ground) from the data, with no fixed limit.

    Going up from ``floor`` in ``CEILING_BIN_M`` bins, the canopy ends at the first band
    ``CEILING_GAP_M`` deep that holds (next to) no points: crowns of any height are kept
    whole, while what floats clear above them (overhead wires, birds, multipath echoes,
    stray returns) is left out. A bin is empty below ``CEILING_MIN_SHARE`` of the points
    (and at least 3); the ceiling is the highest point below the gap.
    """
    above = height[np.isfinite(height) & (height >= floor)] - floor
    # No tree stands higher (the tallest known, 116 m): a wild point cannot size the bins.
    above = above[above < TALLEST_TREE_M]
    if not len(above):
        return float(floor)
    counts = np.bincount((above / CEILING_BIN_M).astype(np.int64))
    occupied = np.flatnonzero(counts >= max(3.0, CEILING_MIN_SHARE * len(above)))
    if not len(occupied):
        return float(floor + above.max())
    gap_bins = int(round(CEILING_GAP_M / CEILING_BIN_M))
    jumps = np.flatnonzero(np.diff(occupied) > gap_bins)
    last = occupied[jumps[0]] if len(jumps) else occupied[-1]
    # Sparse points just above the last full bin (a spire's tip) still belong to the crown.
    limit = (last + 1 + gap_bins) * CEILING_BIN_M
    return float(floor + above[above < limit].max())
