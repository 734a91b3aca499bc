"""Crowns that touch, separated from the imagery alone: rows in the canopy, trees along them.

The truth is the synthetic hedgerows' crown centres (``fixtures_aerial.synthetic_hedgerows``:
neighbouring crowns overlap by 0.5-2 m, the CHM hardly dips between them) and hand-made
profiles whose segmentation is known.
"""

from __future__ import annotations

import numpy as np
import pytest
from fixtures_aerial import synthetic_hedgerows

from ground_truth.crowns import CrownOptions, delineate_crowns, measure_crowns
from ground_truth.match import assign
from ground_truth.row_seeds import (
    canopy_runs,
    cut_row,
    row_direction_from_canopy,
)


def _one_to_one(options: CrownOptions, **orchard) -> tuple[int, int, int, object]:
    """(trees, crowns, trees with their own crown within 1.5 m, segmentation)."""
    grid, rgb, chm, centres, _ = synthetic_hedgerows(**orchard)
    seg = delineate_crowns(rgb, np.ones(grid.shape, bool), chm, grid, options=options)
    table = measure_crowns(seg, chm)
    ia, _, _ = assign(centres, table[["x", "y"]].to_numpy(), 1.5)
    return len(centres), len(table), len(ia), seg


@pytest.mark.parametrize(
    "orchard",
    [{}, {"bearing_deg": 75.0, "bow_m": 1.5, "seed": 1}, {"bearing_deg": 140.0, "seed": 3}],
    ids=["straight", "bowed", "north-west"],
)
def test_touching_crowns_are_found_one_to_one_from_the_rows(orchard: dict) -> None:
    trees, crowns, matched, seg = _one_to_one(CrownOptions(), **orchard)
    assert seg.seeding == "rows"
    assert (seg.marker_seed_ids == -1).all()  # nothing but the imagery seeded them
    assert [r.trees for r in seg.row_layout.rows] == [7, 7, 7]
    assert matched >= trees - 1 and crowns <= trees + 1, (trees, crowns, matched)
    expected = orchard.get("bearing_deg", 20.0) % 180.0
    assert abs(seg.row_layout.bearing_deg - expected) < 1.0
    # drawn 4.2-5.2 m apart, crowns 4.4-5.0 m across the row: the spacing is taken as the width
    assert seg.row_layout.spacing_source == "hedge_width"
    assert 4.2 <= seg.row_layout.spacing_m <= 5.2
    # The CHM maxima (today's mode without seeds) merge or split some of the same crowns.
    _, _, maxima, seg_max = _one_to_one(CrownOptions(unseeded="chm_maxima"), **orchard)
    assert seg_max.seeding == "chm_maxima" and maxima <= matched


def test_a_given_planting_distance_is_used() -> None:
    trees, crowns, matched, seg = _one_to_one(CrownOptions(tree_spacing_m=4.7))
    assert seg.row_layout.spacing_source == "given" and seg.row_layout.spacing_m == 4.7
    assert matched >= trees - 1
    # Half the planting distance cuts every crown in two.
    _, crowns_half, _, _ = _one_to_one(CrownOptions(tree_spacing_m=2.35))
    assert crowns_half >= 1.8 * trees


@pytest.mark.parametrize("bearing", [0.0, 33.0, 90.0, 121.0])
def test_row_direction_from_the_canopy_alone(bearing: float) -> None:
    from ground_truth.row_seeds import _canopy_points

    grid, _, chm, _, _ = synthetic_hedgerows(bearing_deg=bearing, rows=2, trees_per_row=5)
    points, _ = _canopy_points(chm > 0.3, grid)
    angle = row_direction_from_canopy(points)  # radians from east
    found = np.degrees(np.pi / 2 - angle) % 180.0
    assert min(abs(found - bearing), 180.0 - abs(found - bearing)) < 1.0


def test_cut_row_follows_the_saddles() -> None:
    # 20 m of hedge, saddles 5, 10 and 15 m in, spacing and crown width 5 m: every segment
    # has its expected length and every cut sits on a saddle, so this is the only zero-cost cut.
    evidence = np.zeros(100)
    evidence[[25, 50, 75]] = 0.5
    assert cut_row(evidence, 5.0, 5.0) == [(0, 25), (25, 50), (50, 75), (75, 100)]
    # Saddles off the spacing win over the prior when they are clear: 6.4 m and 3.6 m trees.
    evidence = np.zeros(100)
    evidence[[32, 50, 68]] = 0.5
    assert cut_row(evidence, 5.0, 5.0) == [(0, 32), (32, 50), (50, 68), (68, 100)]


def test_a_lone_crown_is_one_tree_and_two_touching_ones_two() -> None:
    # pistachio-like: crowns 4 m wide on a 5 m planting distance
    assert cut_row(np.zeros(20), 5.0, 4.0) == [(0, 20)]
    evidence = np.zeros(40)
    evidence[20] = 0.4
    assert cut_row(evidence, 5.0, 4.0) == [(0, 20), (20, 40)]


def test_canopy_runs_split_at_gaps() -> None:
    empty = np.array([1, 0, 0, 1, 0, 0, 1, 1, 0, 0, 0, 1, 1, 1], bool)
    # one empty bin does not split; two do
    assert canopy_runs(empty) == [(1, 6), (8, 11)]
    assert canopy_runs(np.ones(5, bool)) == []
