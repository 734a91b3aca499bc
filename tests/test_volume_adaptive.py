"""``adaptive_alpha`` and the per-tree interval: analytic solids, one-sided and sparse crowns,
the interval on simulated crown forms, real single-tree clouds, and the per-tree table."""

from __future__ import annotations

import numpy as np
import pytest

from canopy_kit.volume import estimate_volume

STEP = 0.1  # the pipeline's voxel grid


def jittered_grid(inside, lo: float, hi: float, seed: int = 0) -> np.ndarray:
    """One point per 0.1 m cell (jittered by ±0.03 m) of the cells whose point is ``inside``."""
    rng = np.random.default_rng(seed)
    g = np.arange(lo, hi, STEP)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    pts = pts + rng.uniform(-0.03, 0.03, pts.shape)
    return pts[inside(pts)]


def ball(r: float = 1.5):
    return jittered_grid(
        lambda p: np.linalg.norm(p, axis=1) <= r, -r - 0.1, r + 0.1
    ), 4 / 3 * np.pi * r**3


def cube(a: float = 2.0):
    return jittered_grid(
        lambda p: (np.abs(p) <= a / 2).all(axis=1), -a / 2 - 0.1, a / 2 + 0.1
    ), a**3


def hollow_ball(r_in: float = 1.0, r_out: float = 2.0):
    """A thick spherical shell with a closed cavity: the hollow-crown case."""
    d = lambda p: np.linalg.norm(p, axis=1)  # noqa: E731
    pts = jittered_grid(lambda p: (d(p) <= r_out) & (d(p) >= r_in), -r_out - 0.1, r_out + 0.1)
    return pts, 4 / 3 * np.pi * (r_out**3 - r_in**3)


def l_shape():
    """Two 3 × 1 × 1 m boxes in an L (a concave solid of 5 m³)."""

    def inside(p: np.ndarray) -> np.ndarray:
        in_l = ((p[:, 0] <= 3) & (p[:, 1] <= 1)) | ((p[:, 0] <= 1) & (p[:, 1] <= 3))
        return in_l & (p[:, :2] >= 0).all(axis=1) & (p[:, 2] >= 0) & (p[:, 2] <= 1)

    return jittered_grid(inside, -0.05, 3.05), 5.0


SHAPES = {"ball": ball, "cube": cube, "hollow ball": hollow_ball, "L": l_shape}


@pytest.mark.parametrize("name", SHAPES)
def test_adaptive_alpha_on_solids_of_known_volume(name: str) -> None:
    """Solids sampled on the 0.1 m grid up to their surface (measured: hull -3 %…+27 %).
    The α-hull alone (no offset) is 5-15 % below the truth (the thinned points lie up to half
    a cell inside; the 1 m thick L loses most) and never above the hull; the calibrated
    outward offset (0.425 of a spacing, for LiDAR returns that lie inside the crown) lands at
    +6 %…+10 %: on solids sampled up to their surface it over-counts by design."""
    pts, true = SHAPES[name]()
    hull = estimate_volume(pts, "convex_hull").volume_m3
    shell = {"fill_voids": False}  # the shell's own volume: its closed cavity left empty
    solid = estimate_volume(pts, "adaptive_alpha", offset_factor=0.0, **shell)
    default = estimate_volume(pts, "adaptive_alpha", **shell)
    assert solid.valid and default.valid
    assert 0.6 * STEP < solid.extra["alpha"] < 1.0  # a few spacings, not the paper's 0.9 m
    assert -0.16 < solid.volume_m3 / true - 1 < 0.0, (name, solid.volume_m3, true)
    assert solid.volume_m3 <= hull + 1e-9
    assert 0.0 < default.volume_m3 / true - 1 < 0.15, (name, default.volume_m3, true)
    if name in ("hollow ball", "L"):  # the hollow and the concave edge are not filled
        assert hull / true - 1 > 0.10
        assert default.volume_m3 < hull


def test_closed_voids_are_filled_and_open_hollows_are_not() -> None:
    """A crown's leafless inside is still crown: by default the closed cavity of the thick
    shell (r 1-2 m) is counted, giving the outer ball (33.5 m³; over it by the offset as the
    solid ball is). Cut open at the top (z ≥ 0.3 m removed: a bowl, like a vase's open centre),
    the hollow is reachable from outside and stays empty."""
    pts, shell_volume = hollow_ball()
    ball_volume = 4 / 3 * np.pi * 2.0**3
    filled = estimate_volume(pts, "adaptive_alpha")
    assert filled.extra["void_m3"] > 0
    assert 0.0 < filled.volume_m3 / ball_volume - 1 < 0.15
    kept = estimate_volume(pts, "adaptive_alpha", fill_voids=False)
    assert 0.0 < kept.volume_m3 / shell_volume - 1 < 0.15
    bowl = pts[pts[:, 2] < 0.3]
    open_hollow = estimate_volume(bowl, "adaptive_alpha")
    assert open_hollow.extra["void_m3"] == 0.0
    assert open_hollow.volume_m3 == pytest.approx(
        estimate_volume(bowl, "adaptive_alpha", fill_voids=False).volume_m3
    )


def test_alpha_follows_the_point_spacing() -> None:
    pts, _ = ball()
    dense = estimate_volume(pts, "adaptive_alpha").extra
    sparse = estimate_volume(pts[::8], "adaptive_alpha").extra
    assert sparse["spacing"] > 1.5 * dense["spacing"]
    assert sparse["alpha"] > 1.5 * dense["alpha"]
    assert sparse["alpha"] == pytest.approx(4.0 * sparse["spacing"])
    clipped = estimate_volume(pts, "adaptive_alpha", alpha_max=0.4).extra
    assert clipped["alpha"] == 0.4


def test_one_sided_and_sparse_crowns_widen_the_interval() -> None:
    from canopy_kit.volume.uncertainty import CALIBRATIONS, volume_interval

    pts, true = ball()
    full = volume_interval(pts, true, "adaptive_alpha")
    lo, hi = CALIBRATIONS["adaptive_alpha"].kinds["dense"]
    assert full.coverage == 1.0 and full.flags == ()
    assert (full.low_m3, full.high_m3) == pytest.approx((lo * true, hi * true))
    half = pts[pts[:, 0] > 0.3]  # seen from one side only
    one = volume_interval(half, true / 2, "adaptive_alpha")
    assert one.coverage < 0.75 and "one-sided" in one.flags[0]
    assert one.high_m3 > 1.3 * hi * true / 2
    rng = np.random.default_rng(1)
    # 25 clusters of 10 leaves: a few leaves that do not outline the crown
    centres = pts[rng.choice(len(pts), 25, replace=False)]
    few = (centres[:, None, :] + rng.normal(0, 0.05, (25, 10, 3))).reshape(-1, 3)
    sparse = volume_interval(few, true, "adaptive_alpha")
    assert any("sparse crown" in f for f in sparse.flags)
    lo_sparse, hi_sparse = CALIBRATIONS["adaptive_alpha"].kinds["sparse"]
    assert sparse.low_m3 == pytest.approx(lo_sparse * true)
    assert sparse.high_m3 >= hi_sparse * true * (1 - 1e-9)  # (25 clusters leave sectors empty)
    assert hi_sparse / lo_sparse > 1.5 * hi / lo  # a sparse crown's interval is wider
    assert volume_interval(pts, true, "slices") is None  # no calibration: no interval


def test_a_sparse_crown_gets_the_sample_corrected_hull() -> None:
    """40 leaf clusters (10 returns each) drawn uniformly in a 1.5 m ball, 30 such crowns: the
    points do not outline the ball (surface fill below 1.2), so ``adaptive_alpha`` takes the
    sample-corrected hull, whose mean is near the ball's volume (measured 0.89), where
    the α-hull of the same points is a fifth of it and the plain hull about half."""
    rng = np.random.default_rng(2)
    true = 4 / 3 * np.pi * 1.5**3
    corrected, alpha_only, hull = [], [], []
    for _ in range(30):
        centres = rng.uniform(-1.5, 1.5, (800, 3))
        centres = centres[np.linalg.norm(centres, axis=1) <= 1.5][:40]
        few = (centres[:, None, :] + rng.normal(0, 0.05, (40, 10, 3))).reshape(-1, 3)
        result = estimate_volume(few, "adaptive_alpha")
        assert result.extra["estimate"] == "sample_corrected_hull"
        assert result.extra["surface_fill"] < 1.2
        corrected.append(result.volume_m3 / true)
        alpha_only.append(estimate_volume(few, "adaptive_alpha", sparse_fill=None).volume_m3 / true)
        hull.append(estimate_volume(few, "convex_hull").volume_m3 / true)
    assert 0.8 < np.mean(corrected) < 1.1
    assert np.mean(alpha_only) < 0.4 and np.mean(hull) < 0.65


FORM_SESSION = {
    "orchard": {"rows": 1, "trees_per_row": 3},
    "lidar": {"columns": 512, "rings": 16},
    "imu": {"enabled": False},
    "gnss": {"enabled": False},
}


@pytest.mark.slow
def test_interval_covers_the_true_volume_on_every_dense_crown_form(sim_factory) -> None:
    """A 1 × 3 session per dense crown form (seed 431: neither a calibration nor a held-out
    seed of the benchmark), trees cut by the true tree_id, 16 rings × 512 columns, 0.1 m
    voxels, complete scans and one-sided ones (the map of one alley's sweeps): the interval
    holds the simulator's exact envelope volume for ≥ 90 % of the 36 scans, and the
    estimates meet issue 25's goal, mean signed error within ±5 % and mean |error| under 8 %,
    with none off by 10 %. This coarse, truth-labelled scan is the estimator's low side: the
    offset was set on the trees the pipeline segments, where it is −0.2 % (docs/history/VOLUMES_LOG.md,
    "The offset recalibrated"). Until 2026-12-05 this test took the lobed and vase crowns
    only (18 scans, one miss allowed); see docs/history/VOLUMES_LOG.md "One-sided scans from the alley
    maps" for what it measured."""
    from canopy_kit.config import merge
    from canopy_kit.evaluate.truth_map import truth_map
    from canopy_kit.evaluate.volume_errors import simulated_trees
    from canopy_kit.volume.uncertainty import volume_interval

    inside, errors = [], []
    for form in ("ellipsoid", "lobed", "vase", "hedged"):
        session = sim_factory(
            "pistachio",
            fmt="ros1",
            seed=431,
            overrides=merge(FORM_SESSION, {"orchard": {"crown_form": form}}),
        )
        trees = simulated_trees(
            session.root, reference_map=truth_map(session.root, voxel_size=0.05)
        )
        assert len(trees) == 3
        for tree in trees:
            for xyz in (tree.complete, *tree.sides.values()):
                result = estimate_volume(xyz, "adaptive_alpha")
                interval = volume_interval(xyz, result.volume_m3, "adaptive_alpha")
                inside.append(interval.low_m3 <= tree.true_volume_m3 <= interval.high_m3)
                errors.append(result.volume_m3 / tree.true_volume_m3 - 1)
    print(f"inside {np.mean(inside):.0%}; errors {np.round(errors, 3)}")
    assert len(inside) == 36 and np.mean(inside) >= 0.9
    assert abs(np.mean(errors)) <= 0.05 and np.abs(errors).mean() < 0.08
    assert np.abs(errors).max() < 0.10


REAL_TREES = ["archi_tree_1.las", "archi_tree_2.las", "pointcloudset_test_tree.las"]


@pytest.mark.parametrize("name", REAL_TREES)
def test_real_trees_are_ordered_hull_alpha_shell(shared_data, name: str) -> None:
    """Real single trees on 0.1 m voxels: hull ≥ the paper's alpha shape ≥ the filled voxel
    shell, and hull ≥ adaptive_alpha ≥ the shell, except where adaptive_alpha calls the crown
    sparse (the large leafless broadleaf archi_tree_1, surface fill 0.44): then it is the
    hull corrected for its thin sample, between the hull and 1.1 × it (measured 1.008 ×:
    1 600 points 0.2 m apart, 41 of them on the hull). The interval is ordered and holds the
    estimate."""
    from canopy_kit.core.voxel import voxel_downsample
    from canopy_kit.io.clouds import read_cloud
    from canopy_kit.volume.uncertainty import volume_interval

    xyz = voxel_downsample(read_cloud(shared_data / "real_trees" / name), 0.1).xyz
    vol = {
        m: estimate_volume(xyz, m)
        for m in ("convex_hull", "alpha_shape", "adaptive_alpha", "voxel")
    }
    assert all(r.valid for r in vol.values()), {m: r.reason for m, r in vol.items()}
    v = {m: r.volume_m3 for m, r in vol.items()}
    assert v["convex_hull"] >= v["alpha_shape"] >= v["voxel"] > 0, v
    sparse = vol["adaptive_alpha"].extra["estimate"] == "sample_corrected_hull"
    if sparse:
        assert v["convex_hull"] <= v["adaptive_alpha"] <= 1.1 * v["convex_hull"], v
    else:
        assert v["convex_hull"] >= v["adaptive_alpha"] >= v["voxel"], v
    assert sparse == (name == "archi_tree_1.las")  # 15 × 15 × 22 m of branches: fill 0.44
    interval = volume_interval(xyz, v["adaptive_alpha"], "adaptive_alpha")
    assert 0 < interval.low_m3 <= v["adaptive_alpha"] <= interval.high_m3
    assert sparse == any("sparse crown" in f for f in interval.flags)


def test_the_table_bounds_the_recommended_estimator() -> None:
    from canopy_kit.config import VolumeConfig, load_preset
    from canopy_kit.core.cloud import PointCloud
    from canopy_kit.errors import ConfigError
    from canopy_kit.volume.uncertainty import INTERVAL_COLUMNS
    from canopy_kit.volume.verb import measure_trees

    pts, true = ball()
    half = pts[pts[:, 0] > 0.3] + [6.0, 0.0, 0.0]
    cloud = PointCloud(np.vstack([pts, half]))
    labels = np.r_[np.zeros(len(pts), int), np.ones(len(half), int)]
    table = measure_trees(cloud, labels, VolumeConfig(workers=1, recommended="adaptive_alpha"))
    assert set(INTERVAL_COLUMNS.values()) <= set(table.columns)
    assert "volume_adaptive_alpha_m3" in table  # run although not in methods
    assert (table["volume_method"] == "adaptive_alpha").all()
    v = table["volume_adaptive_alpha_m3"]
    assert ((table["volume_low_m3"] < v) & (v < table["volume_high_m3"])).all()
    assert table.loc[0, "scan_coverage"] == 1.0 and table.loc[1, "scan_coverage"] < 0.75
    assert "one-sided" in table.loc[1, "volume_interval_flags"]
    default = measure_trees(cloud, labels, VolumeConfig(workers=1))  # the paper's alpha shape
    assert (default["volume_method"] == "alpha_shape").all()
    assert default["volume_low_m3"].notna().all()
    assert load_preset("adaptive").volume.recommended == "foliage_envelope"
    assert load_preset("pistachio").volume.recommended == "alpha_shape"
    with pytest.raises(ConfigError, match="volume.recommended"):
        VolumeConfig(recommended="")


def test_calibration_ratios_per_kind_of_crown() -> None:
    """Each kind (by surface fill) gets its own 2-98 % quantiles of true/estimate ∓ MARGIN."""
    from canopy_kit.volume.uncertainty import MARGIN, calibrate_ratios, crown_kind

    assert [crown_kind(f) for f in (3.0, 2.0, 1.99, 1.2, 1.19)] == [
        "dense",
        "dense",
        "mixed",
        "mixed",
        "sparse",
    ]
    rng = np.random.default_rng(3)
    dense, sparse = rng.uniform(0.95, 1.05, 200), rng.uniform(1.4, 2.6, 50)
    ratios = np.concatenate([dense, sparse])
    fill = np.concatenate([np.full(200, 3.0), np.full(50, 1.0)])
    out = calibrate_ratios(ratios, fill)
    assert set(out) == {"dense", "sparse"}  # no mixed crowns, no mixed ratios
    assert out["dense"][0] == pytest.approx(np.quantile(dense, 0.02) - MARGIN, abs=5e-4)
    assert out["sparse"][1] == pytest.approx(np.quantile(sparse, 0.98) + MARGIN, abs=5e-4)
    # the interval's own kind overrides the fill's (a thinly scanned lobed crown is mixed);
    # a missing kind falls back on the fill's
    kinds = ["dense"] * 200 + ["mixed"] * 10 + [""] * 40
    out = calibrate_ratios(ratios, fill, kinds)
    assert set(out) == {"dense", "mixed", "sparse"}
    assert out["mixed"][1] == pytest.approx(np.quantile(sparse[:10], 0.98) + MARGIN, abs=5e-4)
    assert out["sparse"][0] == pytest.approx(np.quantile(sparse[10:], 0.02) - MARGIN, abs=5e-4)
