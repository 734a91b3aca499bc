"""Aerial ground truth: drone photos → georeferenced orthomosaic → per-tree crowns.

``process_flight(images_dir, out_dir, frame, seeds)`` runs the whole chain:
``exif`` (read and check geotagged JPEGs) → ``sfm`` (pycolmap structure from motion,
georeferenced to the camera GPS positions) → ``dsm`` (surface and ground models from
multi-view height matching) → ``ortho`` (orthomosaic, GeoTIFF) → ``crowns`` (crown
masks, watershed, diameters and volumes; ``rows``: the row direction and the extents along
and across it; ``envelope``: the 2.5-D envelope volume) → ``match`` (one row per LiDAR tree)
→ ``multiview`` (the visual hull of each crown from its ``silhouettes`` in every photo, and
the flight's recommended aerial volume).
"""

from __future__ import annotations

from typing import Any

__all__ = ["GroundTruthResult", "process_flight"]


def __getattr__(name: str) -> Any:
    # Lazy: ``import ground_truth.exif`` stays light.
    if name in __all__:
        from ground_truth import pipeline

        return getattr(pipeline, name)
    raise AttributeError(f"module 'ground_truth' has no attribute {name!r}")
