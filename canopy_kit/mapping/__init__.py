"""LiDAR(-inertial) odometry and mapping: a bag becomes a deskewed, gravity-aligned,
georeferenced, voxel-thinned map and a trajectory (Abedi et al. 2025, §II.A).

Entry points: :func:`build_map` (whole bag, pose-graph smoothed) and :func:`stream_map`
(causal, sweep by sweep). See docs/MAPPING.md for the design and the measured figures.
The names are imported on first use, so reading a finished map (``mapping.map_source``)
does not load the odometry and its compiled kernels.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from canopy_kit.mapping.pipeline import (
        TIME_FIELD,
        MappingResult,
        RegisteredScan,
        build_map,
        stream_map,
    )

__all__ = ["TIME_FIELD", "MappingResult", "RegisteredScan", "build_map", "stream_map"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        return getattr(import_module("canopy_kit.mapping.pipeline"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
