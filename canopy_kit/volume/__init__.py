"""Per-tree canopy volume: estimators as plugins, a verb to run one, and tree metrics.

``estimate_volume(xyz, "alpha_shape", alpha=0.9)`` loads the estimator registered under
that name in the ``canopy_kit.volumes`` entry-point group and returns a
:class:`VolumeResult`. Built-ins: ``convex_hull``, ``alpha_shape`` (exact alpha complex),
``alpha_hull`` (fast closing formulation), ``voxel``, ``slices`` and ``mirror`` (for
one-sided scans). See docs/VOLUMES.md.
"""

from __future__ import annotations

import inspect
from typing import Any

from canopy_kit.errors import ConfigError
from canopy_kit.volume.base import VolumeEstimator, VolumeResult
from canopy_kit.volume.metrics import TreeMetrics, sphere_volume, tree_metrics
from canopy_kit.volume.sensitivity import AlphaCurve, AutoAlpha, alpha_curve, auto_alpha

__all__ = ["AlphaCurve", "AutoAlpha", "TreeMetrics", "VolumeEstimator", "VolumeResult", "alpha_curve",
           "auto_alpha", "estimate_volume", "estimator", "sphere_volume", "tree_metrics"]


def estimator(method: str = "alpha_shape", **params: Any) -> Any:
    """An instance of the volume plugin ``method`` configured with ``params``."""
    from canopy_kit import plugins

    target = plugins.load("volumes", method)
    if not isinstance(target, type):
        if params:
            raise ConfigError(f"volume method {method!r} takes no parameters, got {sorted(params)}")
        return target
    accepted = [p for p in inspect.signature(target.__init__).parameters if p != "self"]
    unknown = sorted(set(params) - set(accepted))
    if unknown:
        raise ConfigError(f"volume method {method!r} has no parameter {unknown[0]!r} "
                          f"(parameters: {', '.join(accepted) or 'none'})")
    return target(**params)


def estimate_volume(xyz: Any, method: str = "alpha_shape", **params: Any) -> VolumeResult:
    """Volume of one tree's points (N, 3) with the named estimator plugin and its parameters."""
    return estimator(method, **params)(xyz)
