"""canopy_kit.evaluate.row_truth cutting points into a run's row sections, by hand."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from canopy_kit.evaluate.row_truth import sections_of_points
from canopy_kit.segment.rows import RowLine


def test_points_are_cut_into_the_sections_of_their_row_line() -> None:
    # row 0 runs north along x = 0, row 1 along x = 6 (right of the driving direction: +x)
    north = np.array([0.0, 1.0])
    lines = [
        RowLine(0, north, (0.0, 0.0, 0.0), (0.0, 10.0), 3),
        RowLine(1, north, (6.0, 0.0, 0.0), (0.0, 10.0), 3),
    ]
    sections = pd.DataFrame(
        {"row": [0, 0, 1], "section": [0, 1, 0], "x": [0.0, 0.0, 6.0], "y": [0.5, 1.5, 0.5]}
    )
    points = np.array(
        [
            [-1.2, 0.2, 2.0],  # row 0, section 0: 1.2 m left
            [0.7, 0.9, 3.1],  # row 0, section 0: 0.7 m right, the top
            [0.3, 1.0, 1.0],  # y = 1.0 belongs to section 1 (1.0 <= y < 2.0): 0.3 m right
            [-2.9, 1.4, 2.5],  # within half the 6 m spacing of row 0: section 1, 2.9 m left
            # 3.2 m right of row 0: beyond half the spacing; 2.8 m left of row 1, but outside
            # its only section (y in [0, 1)): in no section
            [3.2, 1.4, 9.0],
            [6.4, 0.5, 1.5],  # row 1, section 0: 0.4 m right
            [0.1, 5.0, 7.0],  # row 0 but beyond every measured section
        ]
    )
    got = sections_of_points(points, lines, sections, row_spacing_m=6.0).set_index(
        ["row", "section"]
    )
    assert got.loc[(0, 0)].to_dict() == pytest.approx(
        {
            "true_height_m": 3.1,
            "true_width_left_m": 1.2,
            "true_width_right_m": 0.7,
            "true_width_m": 1.9,
        }
    )
    assert got.loc[(0, 1)].to_dict() == pytest.approx(
        {
            "true_height_m": 2.5,
            "true_width_left_m": 2.9,
            "true_width_right_m": 0.3,
            "true_width_m": 3.2,
        }
    )
    assert got.loc[(1, 0), "true_height_m"] == pytest.approx(1.5)
    assert got.loc[(1, 0), "true_width_right_m"] == pytest.approx(0.4)


def test_a_section_without_points_is_a_gap() -> None:
    lines = [RowLine(0, np.array([1.0, 0.0]), (0.0, 0.0, 0.0), (0.0, 5.0), 2)]
    sections = pd.DataFrame({"row": [0], "section": [3], "x": [3.5], "y": [0.0]})
    got = sections_of_points(np.array([[0.2, 0.5, 2.0]]), lines, sections, 5.0)
    assert got.iloc[0][["true_height_m", "true_width_m"]].tolist() == [0.0, 0.0]
