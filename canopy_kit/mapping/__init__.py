"""LiDAR(-inertial) odometry and mapping: a bag becomes a deskewed, gravity-aligned,
georeferenced, voxel-thinned map and a trajectory (Abedi et al. 2025, §II.A).

Entry points: :func:`build_map` (whole bag, pose-graph smoothed) and :func:`stream_map`
(causal, sweep by sweep). See docs/MAPPING.md for the design and the measured figures.
"""

from __future__ import annotations

from canopy_kit.mapping.pipeline import (
    TIME_FIELD,
    MappingResult,
    RegisteredScan,
    build_map,
    stream_map,
)

__all__ = ["TIME_FIELD", "MappingResult", "RegisteredScan", "build_map", "stream_map"]
