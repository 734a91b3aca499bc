"""Which drone volume a run holds the LiDAR to: the flight's recommended aerial model, as
``ground_truth.multiview`` wrote it in the aerial report (``aerial_volume_model``)."""

from __future__ import annotations

from typing import Any

HULL_MODEL = "hull_volume_m3"  # an oblique flight's recommendation (ground_truth.multiview)
DEFAULT_MODEL = "ellipsoid_volume_m3"  # a nadir flight's, and results made before flights
# recommended a model

#: The aerial models a flight can recommend, by crowns-table column: the name runs use.
MODEL_NAMES = {HULL_MODEL: "visual hull", DEFAULT_MODEL: "height-aware ellipsoid"}


def recommended_model(report: dict[str, Any]) -> str:
    """The crowns-table column of the flight's recommended aerial volume."""
    return (report.get("aerial_volume_model") or {}).get("recommended", DEFAULT_MODEL)


def recommended_aerial_column(report: dict[str, Any]) -> str:
    """The per-tree table's column of the flight's recommended aerial volume."""
    return "aerial_" + recommended_model(report)
