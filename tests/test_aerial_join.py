"""The per-tree join of aerial crowns: errors against the sphere, implausible crowns flagged."""

from __future__ import annotations

import numpy as np
import pandas as pd
from fixtures_aerial import aerial_result

from canopy_kit.config import GroundTruthConfig
from canopy_kit.results.tree_table import join_aerial


def test_errors_against_the_sphere_and_flags_for_fragments_and_merges() -> None:
    lidar = pd.DataFrame(
        {
            "segment": [0, 1, 2],
            "crown_diameter_m": [4.0, 4.0, 4.0],
            "volume_convex_hull_m3": [30.0, 30.0, 30.0],
            "volume_alpha_m3": [20.0, 20.0, 20.0],
        }
    )
    out = join_aerial(lidar, aerial_result([4.0, 0.4, 8.0]), GroundTruthConfig())
    sphere = np.pi * 4.0**3 / 6  # hand-computed: 33.51 m³
    assert np.isclose(out.loc[0, "aerial_sphere_volume_m3"], sphere)
    assert np.isclose(out.loc[0, "error_alpha_vs_aerial_pct"], 100 * (20 - sphere) / sphere)
    assert out.loc[0, "aerial_flag"] == ""
    assert "fragment" in out.loc[1, "aerial_flag"] and "merged" in out.loc[2, "aerial_flag"]
    # flagged crowns keep their aerial numbers but get no error
    assert out.loc[[1, 2], "aerial_diameter_m"].notna().all()
    assert out.loc[[1, 2], "error_alpha_vs_aerial_pct"].isna().all()
    assert out.loc[[1, 2], "error_convex_hull_vs_aerial_pct"].isna().all()


def test_ratio_bounds_come_from_the_config() -> None:
    lidar = pd.DataFrame(
        {
            "segment": [0],
            "crown_diameter_m": [4.0],
            "volume_convex_hull_m3": [30.0],
            "volume_alpha_m3": [20.0],
        }
    )
    loose = GroundTruthConfig(min_diameter_ratio=0.05, max_diameter_ratio=3.0)
    assert join_aerial(lidar, aerial_result([0.4]), loose).loc[0, "aerial_flag"] == ""
    assert join_aerial(lidar, aerial_result([0.4])).loc[0, "aerial_flag"] != ""


def test_inverted_ratio_bounds_are_a_config_error() -> None:
    import pytest

    from canopy_kit.errors import ConfigError

    with pytest.raises(ConfigError, match="min_diameter_ratio"):
        GroundTruthConfig(min_diameter_ratio=2.0, max_diameter_ratio=1.0)


def test_row_extents_and_envelope_reach_the_per_tree_table() -> None:
    """The aerial crowns' along/across-row extents and envelope volume reach trees.csv; an
    aerial result made before those columns existed still joins (without them)."""
    lidar = pd.DataFrame(
        {
            "segment": [0],
            "crown_diameter_m": [4.0],
            "volume_convex_hull_m3": [30.0],
            "volume_alpha_m3": [20.0],
        }
    )
    aerial = aerial_result([4.0])
    aerial.trees["aerial_diameter_across_row_m"] = 3.1
    aerial.trees["aerial_diameter_along_row_m"] = 4.0
    aerial.trees["aerial_envelope_volume_m3"] = 21.0
    out = join_aerial(lidar, aerial)
    assert out.loc[
        0,
        [
            "aerial_diameter_across_row_m",
            "aerial_diameter_along_row_m",
            "aerial_envelope_volume_m3",
        ],
    ].tolist() == [3.1, 4.0, 21.0]
    old = join_aerial(lidar, aerial_result([4.0]))
    assert "aerial_diameter_across_row_m" not in old and old.loc[0, "aerial_flag"] == ""


def test_new_aerial_columns_have_labels() -> None:
    from canopy_kit.report.columns import COLUMN_LABELS

    assert COLUMN_LABELS["aerial_diameter_across_row_m"] == "Drone crown extent across the row [m]"
    assert COLUMN_LABELS["aerial_diameter_along_row_m"] == "Drone crown extent along the row [m]"
    assert "envelope" in COLUMN_LABELS["aerial_envelope_volume_m3"]
    assert "imagery" in COLUMN_LABELS["aerial_crown_flag"]


def test_crowns_flagged_from_the_imagery_leave_the_agreement() -> None:
    """A crown the drone side flagged (``aerial_crown_flag``) keeps its numbers, but its tree gets
    ``aerial_flag`` and no error, even where the diameters agree; read back from a CSV, an
    empty flag is NaN and stays no flag."""
    lidar = pd.DataFrame(
        {
            "segment": [0, 1, 2],
            "crown_diameter_m": [4.0, 4.0, 4.0],
            "volume_convex_hull_m3": [30.0, 30.0, 30.0],
            "volume_alpha_m3": [20.0, 20.0, 20.0],
        }
    )
    aerial = aerial_result([4.0, 4.0, 0.4])
    aerial.trees["aerial_crown_flag"] = [np.nan, "merged", "fragment"]
    out = join_aerial(lidar, aerial, GroundTruthConfig())
    sphere = np.pi * 4.0**3 / 6  # hand-computed: 33.51 m³
    assert out.loc[0, "aerial_flag"] == ""
    assert np.isclose(out.loc[0, "error_alpha_vs_aerial_pct"], 100 * (20 - sphere) / sphere)
    assert out.loc[1, "aerial_flag"] == "aerial crown flagged from the drone imagery (merged)"
    assert "fragment (diameter below" in out.loc[2, "aerial_flag"]  # the LiDAR's reason first
    assert out.loc[1, "aerial_sphere_volume_m3"] > 0
    assert out.loc[[1, 2], "error_alpha_vs_aerial_pct"].isna().all()
