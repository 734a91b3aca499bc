"""Which drone reference the report sets beside the LiDAR volumes: the flight's views and its
recommended aerial model, as ``ground_truth.multiview`` wrote them in the aerial report."""

from __future__ import annotations

from typing import Any

from canopy_kit.results.aerial_reference import MODEL_NAMES, recommended_model


def crown_flags_text(report: dict[str, Any]) -> str:
    """One sentence on the crowns flagged from the imagery alone (``report.json`` →
    ``crown_flags``), "" when the report has no such count (made before the flags)."""
    flags = report.get("crown_flags")
    if not flags:
        return ""
    merged, fragments = int(flags.get("merged", 0)), int(flags.get("fragment", 0))
    if merged + fragments == 0:
        return " No drone crown is flagged as two trees or a fragment."
    spacing = flags.get("tree_spacing_m")
    against = f" (tree spacing {spacing:.2f} m from the photos)" if spacing else ""
    return (
        f" {merged} drone crown(s) probably hold two trees and {fragments} look like "
        f"fragments{against}, from the imagery alone: their trees stay out of the agreement "
        "statistics."
    )


def aerial_reference_text(report: dict[str, Any]) -> str:
    """One paragraph: the flight's pattern (oblique or nadir photos), the recommended aerial
    model and why, that the paper's sphere stays beside it, and the crowns flagged from the
    imagery (:func:`crown_flags_text`)."""
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
        "(docs/GROUND_TRUTH.md gives every model's measured bias)." + crown_flags_text(report)
    )
