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


def test_the_trajectory_figure_is_drawn_in_the_maps_frame() -> None:
    """The true trajectory is brought onto the estimate's (the map's) frame by the inverse of
    the estimate-to-truth alignment: an estimate that is the truth moved by a rigid motion
    is drawn on top of it, at the estimate's coordinates."""
    import numpy as np

    from canopy_kit.mapping.plots import plot_trajectories

    t = np.linspace(0, 1, 50)
    estimate = pd.DataFrame({"x": 20 * t, "y": 3 * np.sin(4 * t), "z": 0.1 * t})
    c, s = np.cos(0.5), np.sin(0.5)
    align = np.eye(4)
    align[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    align[:3, 3] = [700.0, -40.0, 2.0]
    xyz = estimate.to_numpy() @ align[:3, :3].T + align[:3, 3]
    truth = pd.DataFrame(xyz, columns=["x", "y", "z"])
    fig = plot_trajectories(estimate, truth, align)
    true_line, estimated_line = fig.axes[0].get_lines()[:2]
    assert np.allclose(true_line.get_xydata(), estimate[["x", "y"]].to_numpy())
    assert np.allclose(estimated_line.get_xydata(), estimate[["x", "y"]].to_numpy())
