"""Row metrics on a fruiting wall (issue 52): TRV and LWA per row within 5 % of the simulator's
exact crowns, and no post, wire or drip-line return in the canopy.

One small session: 2 rows of 10 trees (about 10 m), every alley driven (a wall's far face is
seen only from the next alley), the adaptive pipeline with its own odometry. Seed 0 was
looked at while writing the trellis filter and the third-outermost reach of
``segment.row_profile``; the preset names the held-out seeds.
"""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.slow  # simulating and running the session: about 90 s on 2 cores

WALL = {"orchard": {"rows": 2, "trees_per_row": 10}, "lidar": {"columns": 512}}


@pytest.fixture(scope="module")
def wall_run(sim_factory, tmp_path_factory):
    """The session, the run's context (cached stages) and the truth of the row metrics."""
    from canopy_kit.config import load_preset
    from canopy_kit.evaluate.row_truth import true_row_sections
    from canopy_kit.pipeline import compute, run

    session = sim_factory("fruiting-wall", overrides=WALL)
    out = tmp_path_factory.mktemp("wall_run")
    run(load_preset("adaptive"), session.bag, out, truth=session.root)
    ctx, _ = compute(load_preset("adaptive"), session.bag, out, truth=session.root)
    band = ctx.segmentation.canopy_band_m
    truth = true_row_sections(ctx.row_profiles, ctx, session.root, band[0], surface=True)
    return session, out, ctx, truth


def test_trv_and_lwa_per_row_are_within_5_percent_of_the_walls_truth(wall_run) -> None:
    """Per row against the exact crowns cut into the same sections, with the layout's row
    spacing. Measured when written (seed 0): TRV +2.0 and +2.0 %, LWA -0.2 and +0.1 %;
    per section median |error| height 0.03 m, width 0.04 m."""
    import pandas as pd

    session, out, ctx, d = wall_run
    spacing = session.orchard.spec.row_spacing
    profiles = ctx.row_profiles
    assert len(ctx.segmentation.rows.lines) == 2
    assert profiles.row_spacing_m == pytest.approx(spacing, rel=0.02)
    written = pd.read_csv(out / "rows_summary.csv").set_index("row")
    for row, sec in d.groupby("row"):
        true_trv = (sec["true_height_m"] * sec["true_width_m"]).mean() * 1e4 / spacing
        true_lwa = 2 * sec["true_height_m"].mean() * 1e4 / spacing
        assert written.loc[row, "trv_m3_per_ha"] == pytest.approx(true_trv, rel=0.05), row
        assert written.loc[row, "lwa_m2_per_ha"] == pytest.approx(true_lwa, rel=0.05), row
    both = (d["true_height_m"] > 0) & (d["height_m"] > 0)
    assert both.all()  # a continuous wall: every section holds canopy, in truth and measured
    assert np.median(np.abs(d["height_m"] - d["true_height_m"])) <= 0.08
    assert np.median(np.abs(d["width_m"] - d["true_width_m"])) <= 0.08


def test_posts_wires_and_the_drip_line_are_no_canopy(wall_run) -> None:
    """The LiDAR saw the trellis (posts standing above the wall, the drip line below it),
    yet no section is higher than the true wall by more than 0.15 m, the rows end with their
    trees, and the trellis returns alone make no canopy: the row metrics are those of the
    map without them."""
    from canopy_kit.segment.row_profile import row_profiles

    session, _, ctx, d = wall_run
    seg, profiles = ctx.segmentation, ctx.row_profiles
    cloud = ctx.mapping.map
    trellis = cloud.fields["tree_id"] == -2  # canopy_kit.sim.trellis.TRELLIS_ID
    wall_top = max(t.height for t in session.orchard.trees)
    assert (seg.height[trellis] > wall_top + 0.2).sum() >= 50  # post tops above the wall
    assert (seg.height[trellis] < 0.6).sum() >= 50  # the drip line and the posts' feet
    assert (d["height_m"] - d["true_height_m"]).max() <= 0.15
    length = profiles.summary.set_index("row")["length_m"]
    for row in (0, 1):
        trees = [t for t in session.orchard.trees if t.row == row]
        along = [np.dot(t.base[:2], session.orchard.row_direction) for t in trees]
        # the crowns reach about 1 m past the end trunks; the end posts 0.6 m
        assert length[row] <= np.ptp(along) + 2 * 1.3 + 1.0, row

    band = tuple(seg.canopy_band_m)
    alone = row_profiles(cloud.xyz[trellis], seg.height[trellis], seg.rows, 3.2, band)
    assert len(alone.sections) == 0
    without = row_profiles(cloud.xyz[~trellis], seg.height[~trellis], seg.rows, 3.2, band)
    with_all = row_profiles(cloud.xyz, seg.height, seg.rows, 3.2, band)
    for column in ("trv_m3_per_ha", "lwa_m2_per_ha"):
        assert with_all.summary[column].to_numpy() == pytest.approx(
            without.summary[column].to_numpy(), rel=0.01
        )
