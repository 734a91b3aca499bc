"""The paper's pistachio segmenter (§II.C.1): DBSCAN on the canopy points."""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np

from canopy_kit.errors import InputError
from canopy_kit.plugins.params import Positive
from canopy_kit.segment.base import Segmenter, check_points, check_weight
from canopy_kit.segment.density import grid_dbscan, weighted_dbscan


def lattice_is_cheaper(xyz: np.ndarray, eps: float) -> bool:
    """Whether the ``eps / 8`` lattice is cheaper than point neighbourhoods for ``xyz``.

    The lattice costs about one operation per cell of the bounding box, the exact method
    one per neighbour pair: dense canopy favours the lattice, sparse or tall scenes
    (airborne forest) the exact method.
    """
    if len(xyz) == 0:
        return True
    cells = np.prod(np.maximum(np.ptp(xyz, axis=0), eps) / (eps / 8.0))
    return bool(cells <= 200.0 * len(xyz))


def run_dbscan(
    xyz: np.ndarray, eps: float, min_samples: float, weight: np.ndarray, algorithm: str
) -> tuple[np.ndarray, np.ndarray]:
    """DBSCAN labels and core mask: ``grid``, ``exact`` or ``auto`` (the cheaper one)."""
    if algorithm == "auto":
        algorithm = "grid" if lattice_is_cheaper(xyz, eps) else "exact"
    if algorithm == "grid":
        return grid_dbscan(xyz, eps, min_samples, weight)
    if algorithm == "exact":
        return weighted_dbscan(xyz, eps, min_samples, weight)
    raise InputError(f"algorithm must be 'auto', 'grid' or 'exact', got {algorithm!r}")


Algorithm = Literal["auto", "grid", "exact"]
ALGORITHMS = get_args(Algorithm)


class DBSCANSegmenter(Segmenter):
    """DBSCAN with ``eps`` (m) and ``min_samples`` (map points within ``eps``).

    The paper used eps = 0.8 m and N_min = 1300. ``min_samples`` counts map points: on a
    voxel grid each voxel weighs the map points it holds (``sample_weight``), so the
    paper's number keeps its meaning at any voxel size.

    Parameters
    ----------
    eps : float, default 0.8
        Neighbourhood radius in metres.
    min_samples : float, default 1300
        Map points (sum of ``sample_weight``) within ``eps`` that make a core point.
    algorithm : str, default "auto"
        ``grid`` (DBSCAN on an ``eps / 8`` lattice, tile by tile: fast on dense canopy,
        memory linear in the map), ``exact`` (point neighbourhoods, tile by tile;
        scikit-learn's result) or ``auto`` (the cheaper one for the data).
    """

    def __init__(
        self, eps: Positive = 0.8, min_samples: Positive = 1300, algorithm: Algorithm = "auto"
    ) -> None:
        self.eps = eps
        self.min_samples = min_samples
        self.algorithm = algorithm

    def fit(
        self,
        X: np.ndarray,
        y: None = None,
        sample_weight: np.ndarray | None = None,
    ) -> DBSCANSegmenter:
        """Cluster points ``X`` (N, 3); sets ``labels_``, ``core_sample_mask_``, ``n_clusters_``."""
        self.validate_params()
        xyz = check_points(X)
        w = check_weight(sample_weight, len(xyz))
        self.labels_, self.core_sample_mask_ = run_dbscan(
            xyz, self.eps, self.min_samples, w, self.algorithm
        )
        self.n_clusters_ = int(self.labels_.max()) + 1 if len(self.labels_) else 0
        return self
