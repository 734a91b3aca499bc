"""Per-tree canopy volume: estimators as plugins, a verb to run one, and tree metrics.

``estimate_volume(xyz, "alpha_shape", alpha=0.9)`` loads the estimator registered under
that name in the ``canopy_kit.volumes`` entry-point group and returns a
:class:`VolumeResult`. Built-ins: ``convex_hull``, ``sample_corrected_hull`` (the hull
corrected for a thin sample), ``alpha_shape`` (exact alpha complex), ``alpha_hull`` (fast
closing formulation), ``alpha_auto``, ``adaptive_alpha`` (α from the point spacing),
``voxel``, ``slices`` and ``mirror`` (for one-sided scans). See docs/VOLUMES.md.
"""

from __future__ import annotations

from typing import Any

from canopy_kit.volume.base import VolumeEstimator, VolumeResult
from canopy_kit.volume.metrics import TreeMetrics, sphere_volume, tree_metrics
from canopy_kit.volume.sensitivity import AlphaCurve, AutoAlpha, alpha_curve, auto_alpha

__all__ = [
    "AlphaCurve",
    "AutoAlpha",
    "TreeMetrics",
    "VolumeEstimator",
    "VolumeResult",
    "alpha_curve",
    "auto_alpha",
    "estimate_volume",
    "estimator",
    "sphere_volume",
    "tree_metrics",
]


def estimator(method: str = "alpha_shape", **params: Any) -> Any:
    """An instance of the volume plugin ``method`` configured with ``params``.

    Parameter values are checked when it is called (``validate_params``), so building one
    never fails on a value; :func:`canopy_kit.plugins.create` checks them at once.
    """
    from canopy_kit import plugins

    return plugins.create("volumes", method, params, validate=False)


def estimate_volume(xyz: Any, method: str = "alpha_shape", **params: Any) -> VolumeResult:
    """Volume of one tree's points (N, 3) with the named estimator plugin and its parameters."""
    return estimator(method, **params)(xyz)
