"""Volume methods on real single-tree clouds from ../shared/data (lidR's MixedConifer
airborne tiles with reference tree IDs, TreeLS terrestrial pine and spruce)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from canopy_kit import plugins
from canopy_kit.volume import estimate_volume


def test_convex_hull_matches_the_shipped_per_tree_hulls(shared_data) -> None:
    from canopy_kit.io.clouds import read_cloud

    cloud = read_cloud(shared_data / "lidr" / "MixedConifer.laz")
    stats = pd.read_csv(shared_data / "lidr" / "MixedConifer_tree_stats.csv")
    ids = cloud.fields["treeID"]
    checked = flagged = 0
    for row in stats.itertuples():
        result = estimate_volume(cloud.xyz[ids == row.treeID], "convex_hull")
        if np.isnan(row.hull_volume_3d_all_m3):
            # too few or coplanar points: no hull in the reference, flagged here
            assert not result.valid and result.volume_m3 == 0.0 and result.reason
            flagged += 1
        else:
            assert result.valid
            # the reference rounds to 1 dm³
            assert result.volume_m3 == pytest.approx(row.hull_volume_3d_all_m3, abs=6e-4)
            checked += 1
    assert checked == 200 and flagged == 5


@pytest.mark.parametrize("name", ["pine", "spruce"])
def test_every_method_measures_a_real_terrestrial_tree(shared_data, name: str) -> None:
    from canopy_kit.core.voxel import voxel_downsample
    from canopy_kit.io.clouds import read_cloud

    cloud = voxel_downsample(read_cloud(shared_data / "treels" / f"{name}.laz"), 0.1)
    hull = estimate_volume(cloud.xyz, "convex_hull").volume_m3
    for method in plugins.names("volumes"):
        result = estimate_volume(cloud.xyz, method)
        assert result.valid, (method, result.reason)
        if method == "enclosing_ellipsoid":
            # around the hull, and inside the smallest ellipsoid round the 2.5 × 2.5 × 21 m
            # column box (semi-axes √3 times the box's half sides) that holds the cloud
            assert hull <= result.volume_m3 <= 4 / 3 * np.pi * 3**1.5 * 1.25 * 1.25 * 10.5
            continue
        # the clouds are clipped to a 2.5 m column: every method stays inside the column
        assert 0 < result.volume_m3 < 2.5 * 2.5 * 21, method
        if method != "mirror":  # the mirror completes an unseen side that is not there
            assert result.volume_m3 <= hull * 1.05, method


def test_a_real_tree_whose_estimators_disagree_does_not_pass_silently(
    shared_data, cli_server
) -> None:
    """aRchi's tree 1 is a leafless skeleton 22 m tall: the foliage envelope follows its
    branches (tens of m³), its convex hull is over a thousand. The command says what the
    volume measures and warns that the estimators disagree beyond every tree family; the
    small leafy tree 2 gets no warning."""
    import json

    from test_volume_contract import _cli

    skeleton = _cli(
        cli_server,
        "volume",
        str(shared_data / "real_trees" / "archi_tree_1.las"),
        "--voxel-size",
        "0.1",
        "--json",
    )
    assert skeleton.returncode == 0, skeleton.stderr
    out = json.loads(skeleton.stdout)
    assert out["method"] == "foliage_envelope" and "alpha-hull of the foliage" in out["measures"]
    assert out["disagreement"] and "convex_hull" in out["disagreement"]
    human = _cli(
        cli_server,
        "volume",
        str(shared_data / "real_trees" / "archi_tree_1.las"),
        "--voxel-size",
        "0.1",
    )
    assert "warning: estimators disagree beyond every tree family" in human.stdout
    leafy = json.loads(
        _cli(
            cli_server,
            "volume",
            str(shared_data / "real_trees" / "archi_tree_2.las"),
            "--voxel-size",
            "0.1",
            "--json",
        ).stdout
    )
    assert leafy["disagreement"] is None and leafy["valid"]
