"""Which drone reference the report sets beside the LiDAR volumes: the flight's views and its
recommended aerial model, as ``ground_truth.multiview`` wrote them in the aerial report."""

from __future__ import annotations

from typing import Any

from canopy_kit.results.aerial_reference import MODEL_NAMES, recommended_model


def aerial_reference_text(report: dict[str, Any]) -> str:
    """One paragraph: the flight's pattern (oblique or nadir photos), the recommended aerial
    model and why, and that the paper's sphere stays beside it."""
    model = recommended_model(report)
    name = MODEL_NAMES.get(model, model)
    views = report.get("flight_views") or {}
    if views:
        pattern = (
            f"{views['views']} photos ({views['oblique_photos']} of {views['photos']} "
            f"registered photos oblique, median pitch {views['median_pitch_deg']:.0f}°)"
        )
    else:
        pattern = "photos of unknown pattern (processed before flights were told apart)"
    why = (report.get("aerial_volume_model") or {}).get("why")
    return (
        f"Drone flight: {pattern}. Recommended aerial reference: the {name} "
        f"({model})" + (f", because {why}" if why else "") + ". The paper's sphere of the "
        "widest crown extent stays beside it for the paper's comparison "
        "(docs/GROUND_TRUTH.md gives every model's measured bias)."
    )
