"""The report's static figures: one tree name everywhere, labels a person can read."""

from __future__ import annotations

import matplotlib
import pandas as pd

matplotlib.use("Agg")


def test_the_volume_chart_names_trees_by_their_tree_id() -> None:
    """The bar chart labels r0-L0 (as every other output), not row:label, at 9 pt."""
    from canopy_kit.report.plots import plot_volumes

    trees = pd.DataFrame(
        {
            "tree_id": ["r0-L0", "r0-L1", "r1-R0"],
            "row": [0, 0, 1],
            "label": ["L0", "L1", "R0"],
            "volume_alpha_m3": [20.0, 22.0, 19.0],
        }
    )
    fig = plot_volumes(trees, {"alpha shape": "volume_alpha_m3", "absent": "nope_m3"})
    ticks = fig.axes[0].get_xticklabels()
    assert [t.get_text() for t in ticks] == ["r0-L0", "r0-L1", "r1-R0"]
    assert min(t.get_fontsize() for t in ticks) >= 9
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == ["alpha shape"]
