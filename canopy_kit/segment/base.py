"""What every segmenter shares: the scikit-learn contract and input checks.

A segmenter takes its parameters as keyword arguments in ``__init__`` (no work there),
``validate_params()`` raises ConfigError naming a bad one, ``fit(xyz)`` does the work and
stores ``labels_`` (one per point, -1 for noise) and ``n_clusters_``, ``fit_predict(xyz)``
returns ``labels_``. Optional fit parameters that
the ``segment`` verb passes when a segmenter's ``fit`` accepts them:

- ``sample_weight``: map points each input point stands for (voxel grid, see
  ``segment.preprocess``),
- ``stem_xyz``: height-normalised points of the stem band under the canopy (trunks).

``canopy_kit.testing.check_segmenter`` checks a segmenter against this contract.
"""

from __future__ import annotations

import numpy as np
from sklearn.base import BaseEstimator, ClusterMixin

from canopy_kit.errors import InputError
from canopy_kit.plugins.params import check_positive, validate_types

__all__ = ["Segmenter", "check_points", "check_positive", "check_weight"]


class Segmenter(ClusterMixin, BaseEstimator):
    """Base class: ``fit_predict`` forwards the optional fit parameters to ``fit``."""

    def validate_params(self) -> None:
        """ConfigError naming the first parameter whose value misfits its annotation.

        Subclasses add their range checks and call ``super().validate_params()``.
        """
        validate_types(self, type(self).__name__)

    def fit_predict(self, X: np.ndarray, y: None = None, **fit_params: object) -> np.ndarray:
        """Fit and return one label per point (-1 for noise)."""
        return self.fit(X, **fit_params).labels_


def check_points(xyz: np.ndarray, name: str = "xyz") -> np.ndarray:
    """Points as a float64 (N, 3) array; InputError naming ``name`` otherwise."""
    arr = np.asarray(xyz, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} has NaN or infinite coordinates")
    return arr


def check_weight(sample_weight: np.ndarray | None, n: int) -> np.ndarray:
    """Per-point weights (ones when ``None``); InputError on a length mismatch."""
    if sample_weight is None:
        return np.ones(n)
    w = np.asarray(sample_weight, dtype=np.float64).ravel()
    if len(w) != n:
        raise InputError(f"sample_weight has {len(w)} values for {n} points")
    if np.any(w < 0):
        raise InputError("sample_weight has negative values")
    return w
