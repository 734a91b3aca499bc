"""Volume methods on simulated trees against the simulator's exact crown volume (loose
bounds; the full table is benchmarks/bench_volume_accuracy.py, quoted in docs/history/VOLUMES_LOG.md)."""

from __future__ import annotations

import numpy as np
import pytest

from canopy_kit.evaluate.volume_errors import (
    MethodSpec,
    error_table,
    simulated_trees,
    volume_errors,
)

SPECS = [
    MethodSpec("hull", "convex_hull"),
    MethodSpec("alpha", "alpha_shape", {"alpha": 0.9}),
    MethodSpec("alpha_hull", "alpha_hull", {"alpha": 0.9}),
    MethodSpec("slices", "slices"),
    MethodSpec("mirror", "mirror", trunk_plane=True),
]


@pytest.fixture(scope="module")
def errors(tiny_pistachio):
    trees = simulated_trees(tiny_pistachio.root, voxel_size=0.1)
    assert len(trees) == 6
    assert all(len(t.complete) > 500 and len(t.sides["left"]) > 100 for t in trees)
    return volume_errors(trees, SPECS)


def summary(errors, scan: str) -> dict[str, tuple[float, float]]:
    table = error_table(errors)
    rows = table[table["scan"] == scan]
    return {r.method: (r.mape, r.bias) for r in rows.itertuples()}


def test_every_method_gives_a_valid_volume_on_every_scan(errors) -> None:
    assert errors["valid"].all()
    assert set(errors["scan"]) == {"complete", "left", "right"}


def test_complete_trees_are_within_a_few_percent(errors) -> None:
    s = summary(errors, "complete")
    assert -0.15 < s["hull"][1] < 0.05, s  # points lie inside the envelope: a little low
    assert min(s[m][0] for m in ("hull", "slices", "mirror")) < 0.08, s
    assert s["alpha"][1] < s["hull"][1]  # the alpha shape carves more than the hull


def test_mirror_beats_alpha_on_one_sided_scans(errors) -> None:
    s = summary(errors, "one-sided")
    assert s["mirror"][0] < s["alpha"][0], s
    assert s["mirror"][0] < s["hull"][0], s
    assert s["mirror"][0] < 0.1, s


def test_fast_alpha_hull_tracks_the_exact_alpha_on_simulated_crowns(errors) -> None:
    wide = errors.pivot_table(index=["tree", "scan"], columns="method", values="volume_m3")
    ratio = wide["alpha_hull"] / wide["alpha"] - 1
    # the α-hull is bitten between sparse boundary points: slightly smaller, never larger
    assert ratio.max() < 0.01 and ratio.min() > -0.06, ratio.describe()
    assert np.isfinite(ratio).all()


def test_alley_maps_hold_what_one_alley_alone_saw(tiny_pistachio) -> None:
    """Each row's side map is built from the sweeps driven in the alley on that side only:
    the points were measured with the sensor on that side of the row line (all but the ends of
    sweeps that cross it in a headland turn) and nearer to it than the row spacing (true
    poses); the two sides of a row share no point time; and each
    side of a row sees every tree of that row."""
    from canopy_kit.evaluate.truth import load_truth, true_pose_interpolator
    from canopy_kit.evaluate.truth_map import alley_maps, row_lines

    trees = load_truth(tiny_pistachio.root).trees
    lines = row_lines(trees)
    maps = alley_maps(tiny_pistachio.root)
    assert set(maps) == {(r, s) for r in lines for s in (1, -1)}
    pose_at = true_pose_interpolator(tiny_pistachio.root)
    spacing = abs((lines[1][0] - lines[0][0]) @ np.array([-lines[0][1][1], lines[0][1][0]]))
    for (row, side), cloud in maps.items():
        centre, along = lines[row]
        across = np.array([-along[1], along[0]])
        times = np.asarray(cloud.fields["time"])
        offset = (pose_at(times[::50])[0][:, :2] - centre) @ across
        # a sweep joins by where it began: its last points may lie a few dm past a headland turn
        assert (offset * side > -0.5).all() and (np.abs(offset) < spacing + 0.5).all()
        assert np.mean(offset * side > 0) > 0.99
        ids = set(np.unique(np.asarray(cloud.fields["tree_id"])))
        assert set(trees.loc[trees["row"] == row, "tree_id"]) <= ids
    for row in lines:
        left = np.asarray(maps[(row, 1)].fields["time"])
        right = np.asarray(maps[(row, -1)].fields["time"])
        assert not np.intersect1d(left, right).size
