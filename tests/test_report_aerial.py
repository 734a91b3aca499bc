"""The report names the drone flight's pattern and its recommended aerial model next to the
LiDAR-vs-drone comparison, with the paper's sphere kept beside it (issue 51)."""

from __future__ import annotations

from types import SimpleNamespace

import matplotlib
import numpy as np
import pandas as pd
import pytest
from fixtures_aerial import aerial_result

from canopy_kit.report.aerial import aerial_reference_text
from canopy_kit.results.aerial_reference import recommended_aerial_column
from canopy_kit.results.tree_table import join_aerial
from canopy_kit.volume.verb import ALPHA_COLUMN

matplotlib.use("Agg")

OBLIQUE = {
    "flight_views": {
        "views": "oblique",
        "photos": 66,
        "oblique_photos": 66,
        "median_pitch_deg": -60.2,
    },
    "aerial_volume_model": {
        "recommended": "hull_volume_m3",
        "flight_views": "oblique",
        "why": "oblique photos see below the crowns' widest level",
    },
}
NADIR = {
    "flight_views": {"views": "nadir", "photos": 36, "oblique_photos": 0, "median_pitch_deg": -90},
    "aerial_volume_model": {"recommended": "ellipsoid_volume_m3", "flight_views": "nadir"},
}


def test_the_text_names_pattern_model_and_the_sphere() -> None:
    text = aerial_reference_text(OBLIQUE)
    assert "oblique photos (66 of 66" in text and "-60°" in text
    assert "visual hull (hull_volume_m3)" in text and "sphere" in text
    assert "height-aware ellipsoid (ellipsoid_volume_m3)" in aerial_reference_text(NADIR)
    assert recommended_aerial_column(OBLIQUE) == "aerial_hull_volume_m3"
    # a result processed before flights recommended a model: the ellipsoid, said to be unknown
    assert recommended_aerial_column({}) == "aerial_ellipsoid_volume_m3"
    assert "unknown pattern" in aerial_reference_text({})


def test_the_hull_reaches_the_per_tree_table() -> None:
    aerial = aerial_result([4.0, 4.2])
    aerial.trees["aerial_hull_volume_m3"] = [20.0, 22.0]
    lidar = pd.DataFrame({"segment": [0, 1], "crown_diameter_m": [4.0, 4.1]})
    assert join_aerial(lidar, aerial)["aerial_hull_volume_m3"].tolist() == [20.0, 22.0]


@pytest.mark.parametrize("report, marked", [(OBLIQUE, "visual hull"), (NADIR, "ellipsoid")])
def test_the_drone_section_marks_the_flights_reference(
    report: dict, marked: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    import matplotlib.pyplot as plt

    from canopy_kit.report import session

    monkeypatch.setattr(session, "plot_crowns", lambda *a: plt.figure().add_subplot())
    monkeypatch.setattr(session, "describe_seeding", lambda *a: "")
    rng = np.random.default_rng(0)
    trees = pd.DataFrame(
        {
            "tree_id": ["L0", "L1", "L2"],
            ALPHA_COLUMN: rng.uniform(15, 25, 3),
            "aerial_sphere_volume_m3": rng.uniform(20, 30, 3),
            "aerial_ellipsoid_volume_m3": rng.uniform(15, 25, 3),
            "aerial_hull_volume_m3": rng.uniform(15, 25, 3),
            "aerial_flag": "",
        }
    )
    ctx = SimpleNamespace(aerial=SimpleNamespace(report=report, ortho=None, segmentation=None))
    ctx.aerial.crowns = None
    section = session.aerial_section(ctx, trees)
    assert section.text == aerial_reference_text(report)
    captions = [c for c, _ in section.figures]
    assert captions[0].startswith("Alpha-shape volume against the aerial sphere")  # the paper's
    recommended = [c for c in captions if "Recommended aerial reference" in c]
    assert len(recommended) == 1 and marked in recommended[0]
    plt.close("all")


def test_the_text_counts_the_crowns_flagged_from_the_imagery() -> None:
    flagged = {
        **OBLIQUE,
        "crown_flags": {
            "merged": 2,
            "fragment": 1,
            "tree_spacing_m": 4.72,
            "tree_spacing_source": "crown_rows (hedge_width)",
        },
    }
    text = aerial_reference_text(flagged)
    assert "2 drone crown(s) probably hold two trees and 1 look like fragments" in text
    assert "4.72 m" in text and "agreement statistics" in text
    none = {**OBLIQUE, "crown_flags": {**flagged["crown_flags"], "merged": 0, "fragment": 0}}
    assert "No drone crown is flagged" in aerial_reference_text(none)
    assert "flagged" not in aerial_reference_text(OBLIQUE)  # made before the flags
