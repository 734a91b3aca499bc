"""ground_truth building blocks on synthetic inputs with known answers (fast)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from fixtures_aerial import NADIR, two_photos_of_a_block

from canopy_kit.core.geo import LocalFrame
from canopy_kit.sim.drone_render import PinholeView
from ground_truth.camera import PosedCamera, camera_from_pose
from ground_truth.crowns import CrownOptions, delineate_crowns, feret_extents, measure_crowns
from ground_truth.dsm import SurfaceOptions, dense_surface, ground_model, reliable_points
from ground_truth.match import assign, match_crowns, tree_positions
from ground_truth.raster import Grid, read_geotiff, write_geotiff


def test_projection_inverts_the_renderer_rays():
    rot = NADIR @ np.array(
        [[np.cos(0.02), 0, np.sin(0.02)], [0, 1, 0], [-np.sin(0.02), 0, np.cos(0.02)]]
    )
    view = PinholeView(np.array([3.0, -2.0, 35.0]), rot, 800.0, 120, 90)
    cam = camera_from_pose("a", "SIMPLE_PINHOLE", (800.0, 60.0, 45.0), 120, 90, view.position, rot)
    d = view.ray_directions()
    pts = view.position + d.reshape(-1, 3) * 30.0
    uv, depth = cam.project(pts)
    jj, ii = np.meshgrid(np.arange(120) + 0.5, np.arange(90) + 0.5)
    assert np.allclose(uv[:, 0], jj.ravel(), atol=1e-6) and np.allclose(
        uv[:, 1], ii.ravel(), atol=1e-6
    )
    assert (depth > 0).all()
    assert np.allclose(cam.center, view.position)
    half = cam.scaled(0.5)
    assert np.allclose(half.project(pts)[0], uv * 0.5)


def test_geotiff_round_trip(tmp_path):
    frame = LocalFrame.at(37.281, -120.42, 50.0)
    grid = Grid.covering(np.array([-3.0, -2.0]), np.array([4.0, 5.0]), 0.5)
    data = np.arange(grid.rows * grid.cols, dtype=np.float32).reshape(grid.shape)
    write_geotiff(tmp_path / "a.tif", data, grid, frame, nodata=float("nan"))
    back, geo = read_geotiff(tmp_path / "a.tif")
    assert np.array_equal(back, data)
    assert geo["epsg"] == frame.epsg == 32610
    assert geo["pixel_scale"][:2] == (0.5, 0.5)
    assert geo["tiepoint"][3] == pytest.approx(frame.origin_easting - 3.0)
    assert geo["tiepoint"][4] == pytest.approx(frame.origin_northing + 5.0)


def test_feret_extents_of_an_ellipse():
    res = 0.02
    yy, xx = np.mgrid[-150:151, -150:151] * res
    a, b, t = 2.5, 1.5, np.radians(30)
    u = xx * np.cos(t) + yy * np.sin(t)
    v = -xx * np.sin(t) + yy * np.cos(t)
    rows, cols = np.nonzero((u / a) ** 2 + (v / b) ** 2 <= 1)
    widest, perp, _ = feret_extents(rows, cols, res)
    assert widest == pytest.approx(2 * a, abs=2 * res)
    assert perp == pytest.approx(2 * b, abs=2 * res)


def _synthetic_orchard(res: float = 0.05):
    """An 'orthomosaic' with green crowns (domes in the CHM), a flat green weed patch."""
    grid = Grid(0.0, 20.0, res, int(20 / res), int(30 / res))
    x, y = grid.centers()
    rng = np.random.default_rng(0)
    rgb = np.empty(grid.shape + (3,), np.uint8)
    rgb[...] = (150, 120, 90)
    rgb = np.clip(rgb + rng.normal(0, 8, rgb.shape), 0, 255).astype(np.uint8)
    chm = np.zeros(grid.shape)
    crowns = [
        (5.0, 10.0, 3.0, 4.0),
        (12.0, 10.0, 4.0, 5.0),
        (15.7, 10.0, 3.4, 4.5),
        (24.0, 6.0, 2.6, 3.5),
    ]
    for cx, cy, d, h in crowns:
        r2 = ((x - cx) ** 2 + (y - cy) ** 2) / (d / 2) ** 2
        inside = r2 <= 1
        chm[inside] = np.maximum(chm[inside], h * np.sqrt(1 - r2[inside]) * 0.6 + 0.4 * h)
        rgb[inside] = (60, 110, 40)
    weeds = (np.abs(x - 24.0) < 1.5) & (np.abs(y - 15.0) < 1.0)
    rgb[weeds] = (70, 120, 45)
    return grid, rgb, chm, crowns


def test_crowns_found_measured_and_weeds_ignored():
    grid, rgb, chm, crowns = _synthetic_orchard()
    seg = delineate_crowns(
        rgb,
        np.ones(grid.shape, bool),
        chm,
        grid,
        options=CrownOptions(min_tree_spacing_m=2.0, unseeded="chm_maxima"),
    )
    table = measure_crowns(seg, chm)
    truth = np.array([(cx, cy) for cx, cy, _, _ in crowns])
    ia, ib, dist = assign(truth, table[["x", "y"]].to_numpy(), 1.0)
    assert len(ia) == 4 and len(table) == 4  # the two touching crowns are split, weeds dropped
    d_true = np.array([crowns[i][2] for i in ia])
    d_est = table["diameter_max_m"].to_numpy()[ib]
    # The touching pair is cut at the CHM saddle, so their widest extents shrink a little.
    lone = [k for k, i in enumerate(ia) if i in (0, 3)]
    assert np.abs(d_est[lone] - d_true[lone]).max() < 0.1
    assert np.abs(d_est - d_true).max() < 0.6
    assert table.loc[ib[lone], "height_m"].to_numpy() == pytest.approx(
        [crowns[i][3] for i in ia[lone]], abs=0.3
    )
    sphere = table["sphere_volume_m3"].to_numpy()
    assert sphere == pytest.approx(np.pi * table["diameter_max_m"].to_numpy() ** 3 / 6)


def test_crowns_seeded_by_tree_positions():
    grid, rgb, chm, crowns = _synthetic_orchard()
    seeds = np.array([(cx, cy) for cx, cy, _, _ in crowns] + [(28.0, 18.0)])  # last: no crown there
    seg = delineate_crowns(rgb, np.ones(grid.shape, bool), chm, grid, seeds_xy=seeds)
    table = measure_crowns(seg, chm)
    assert sorted(table["seed_id"].tolist()) == [0, 1, 2, 3]


def test_match_crowns_to_trees_with_gate():
    trees = pd.DataFrame({"tree_id": [1, 2, 3], "x": [0.0, 5.0, 10.0], "y": [0.0, 0.0, 0.0]})
    trees = tree_positions(trees, None)
    crowns = pd.DataFrame(
        {
            "crown_id": [7, 8, 9],
            "x": [5.3, 0.2, 30.0],
            "y": [0.1, -0.2, 0.0],
            "seed_id": [-1, -1, -1],
            "diameter_max_m": [3.0, 4.0, 5.0],
        }
    )
    out = match_crowns(trees, crowns, max_distance_m=1.5)
    assert out["matched"].tolist() == [True, True, False]
    assert out["aerial_crown_id"].tolist()[:2] == [8, 7]
    assert np.isnan(out["aerial_diameter_max_m"].iloc[2])
    assert out["aerial_distance_m"].iloc[0] == pytest.approx(np.hypot(0.2, 0.2))


def test_tree_positions_from_lat_lon_follow_the_frame():
    frame = LocalFrame.at(37.281, -120.42, 50.0)
    lat, lon, _ = frame.to_wgs84(np.array([[12.0, -7.0, 0.0]]))
    trees = tree_positions(pd.DataFrame({"lat": lat, "lon": lon}), frame)
    assert trees[["tree_x", "tree_y"]].to_numpy()[0] == pytest.approx([12.0, -7.0], abs=1e-6)


def test_ground_model_ignores_crowns_and_outliers():
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 30, (4000, 2))
    z = 0.05 * xy[:, 0] + rng.normal(0, 0.02, len(xy))
    on_crown = np.hypot(xy[:, 0] - 15, xy[:, 1] - 15) < 2.0
    z[on_crown] += 3.0
    z[0] = -200.0  # a two-view outlier
    tracks = np.full(len(z), 4)
    tracks[0] = 2
    pts = reliable_points(np.column_stack([xy, z]), tracks, np.full(len(z), 0.5))
    grid = Grid(0.0, 30.0, 0.5, 60, 60)
    ground = ground_model(pts, grid, window_m=8.0)
    x, _ = grid.centers()
    inner = (slice(10, 50), slice(10, 50))
    assert np.abs(ground - 0.05 * x)[inner].max() < 0.25


def test_dense_surface_recovers_a_raised_block():
    """Two nadir photos of a textured ground with a 2 m block: the matched height is right."""
    res = 0.1
    cams, images = two_photos_of_a_block(2.0)
    grid = Grid(-6.0, 6.0, res, 120, 120)
    surface = dense_surface(
        cams,
        images,
        grid,
        np.zeros(grid.shape),
        3.0,
        SurfaceOptions(resolution=res, views_per_cell=2, window_cells=5),
    )
    x, y = grid.centers()
    top = (np.abs(x) < 2.5) & (np.abs(y) < 2.5)
    ground = (np.abs(x) > 3.5) & (np.abs(x) < 5.5) & (np.abs(y) < 5)
    assert np.nanmedian(np.abs(surface.dsm[top] - 2.0)) < 0.08
    assert np.nanmedian(np.abs(surface.dsm[ground])) < 0.08


def test_posed_camera_rejects_unknown_model():
    from canopy_kit.errors import InputError

    with pytest.raises(InputError, match="model OPENCV_FISHEYE is not one of"):
        PosedCamera("x", "OPENCV_FISHEYE", (1.0,), 10, 10, np.eye(3), np.zeros(3))


def _survey(rng: np.random.Generator, attitude_deg: float = 0.8):
    """A 3-strip nadir survey (true centres, optical axes) and a random similarity of it (the model)."""
    from scipy.spatial.transform import Rotation

    xs, ys = np.meshgrid(np.arange(5) * 8.0, np.arange(3) * 10.0)
    true = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, 35.0)])
    tilts = Rotation.from_rotvec(
        np.column_stack([rng.normal(0, np.radians(attitude_deg), (xs.size, 2)), np.zeros(xs.size)])
    )
    axes_true = tilts.apply([0.0, 0.0, -1.0])
    g = Rotation.from_rotvec([0.4, -0.7, 1.1]).as_matrix()
    model = 0.13 * true @ g.T + np.array([3.0, -1.0, 2.0])
    return true, axes_true, model, axes_true @ g.T, g


def test_georeference_trusts_precise_gps():
    from ground_truth.sfm import georeference

    rng = np.random.default_rng(1)
    true, _, model, axes, _ = _survey(rng)
    gps = true + rng.normal(0, [0.02, 0.02, 0.05], true.shape)
    s, r, t, info = georeference(model, axes, gps)
    assert info["vertical_from"] == "gps" and info["gps_weight"] > 0.9
    assert np.abs(s * model @ r.T + t - true).max() < 0.1


def test_georeference_levels_by_the_photos_when_gps_altitude_drifts():
    """Camera GPS: metre-level horizontal noise, altitude climbing 26 m over level flight."""
    from ground_truth.sfm import georeference

    rng = np.random.default_rng(2)
    true, _, model, axes, g = _survey(rng)
    gps = true + rng.normal(0, [3.0, 3.0, 1.0], true.shape)
    gps[:, 2] += np.linspace(0.0, 26.0, len(gps)).reshape(5, 3).T.ravel()  # climbs strip by strip
    s, r, t, info = georeference(model, axes, gps)
    assert info["vertical_from"] == "camera_axes" and info["gps_tilt_vs_camera_axes_deg"] > 10
    up = r @ (g @ np.array([0.0, 0.0, 1.0]))  # the true vertical, through the recovered transform
    assert np.degrees(np.arccos(up[2])) < 1.5
    horizontal = s * model @ r.T + t - true
    assert np.sqrt(np.mean(np.sum(horizontal[:, :2] ** 2, axis=1))) < 4.0


def test_georeference_needs_three_spread_photos():
    from canopy_kit.errors import ProcessingError
    from ground_truth.sfm import georeference

    with pytest.raises(ProcessingError, match="fewer than 3"):
        georeference(np.zeros((2, 3)), np.tile([0.0, 0.0, -1.0], (2, 1)), np.zeros((2, 3)))


def test_shared_outline_of_a_crown_cut_by_its_neighbours():
    """A round crown cut on both sides by overlapping neighbours: its visible extents give the
    widest chord and a short one (mean 4.0 m for a 5 m crown); the shared outline says so."""
    from ground_truth.crowns import shared_outline_fraction

    res = 0.05
    yy, xx = np.mgrid[-80:81, -120:121] * res
    disc = xx**2 + yy**2 <= 2.5**2
    cut = disc & (np.abs(xx) < 1.5)  # neighbours take everything beyond 1.5 m either side
    rows, cols = np.nonzero(cut)
    widest, perp, _ = feret_extents(rows, cols, res)
    assert widest == pytest.approx(5.0, abs=0.1) and (widest + perp) / 2 < 4.2
    assert 0.4 < shared_outline_fraction(cut, disc & ~cut) < 0.7
    assert shared_outline_fraction(disc, np.zeros_like(disc)) == 0.0


def test_seed_off_its_crown_top_still_gets_its_crown():
    """Overlapping crowns; the middle tree's position lies 1.9 m off its crown top, on the slope
    of a taller neighbour. A one-cell marker there lost the watershed race (the neighbour came
    out 9.7 m wide); seed discs keep both crowns near their true 6 m and 5 m."""
    res = 0.05
    grid = Grid(0.0, 10.0, res, int(10 / res), int(24 / res))
    x, y = grid.centers()
    rgb = np.empty(grid.shape + (3,), np.uint8)
    rgb[...] = (150, 120, 90)
    chm = np.zeros(grid.shape)
    for cx, d, h in ((8.0, 6.0, 5.0), (12.5, 5.0, 3.5), (17.0, 5.0, 4.0)):
        r2 = ((x - cx) ** 2 + (y - 5.0) ** 2) / (d / 2) ** 2
        inside = r2 <= 1
        chm[inside] = np.maximum(chm[inside], h * np.sqrt(1 - r2[inside]) * 0.6 + 0.4 * h)
        rgb[inside] = (60, 110, 40)
    seeds = np.array([(8.0, 5.0), (10.6, 5.0), (17.0, 5.0)])
    widths = {}
    for fraction in (0.0, CrownOptions().seed_disc_fraction):
        seg = delineate_crowns(
            rgb,
            np.ones(grid.shape, bool),
            chm,
            grid,
            seeds,
            CrownOptions(seed_disc_fraction=fraction),
        )
        widths[fraction] = (
            measure_crowns(seg, chm).sort_values("seed_id")["diameter_max_m"].to_numpy()
        )
    assert widths[0.0][0] > 9.0  # the failure the discs fix
    assert widths[CrownOptions().seed_disc_fraction] == pytest.approx([6.0, 5.0, 5.0], abs=0.45)


def test_seed_offset_is_measured_and_the_seeds_registered():
    """Seeds from a map georeferenced by standalone GNSS sit off the photos' crowns by one
    translation (simulated: 0.3-0.9 m). The crowns stage measures it as the median crown-from-
    seed offset, moves the seeds by it and delineates again; the crowns stay where they are."""
    from canopy_kit.config import GroundTruthConfig
    from ground_truth.dsm import SurfaceModel
    from ground_truth.ortho import Orthomosaic
    from ground_truth.pipeline import crowns_stage

    grid, rgb, chm, crowns = _synthetic_orchard()
    rgba = np.dstack([rgb, np.full(grid.shape, 255, np.uint8)])
    mosaic = Orthomosaic(grid, rgba, np.zeros(grid.shape, np.int32), ["a"])
    surface = SurfaceModel(
        grid, chm, np.zeros(grid.shape), np.ones(grid.shape), np.zeros(grid.shape + (0,), int), []
    )
    frame = LocalFrame.at(37.281, -120.42, 50.0)
    truth = np.array([(cx, cy) for cx, cy, _, _ in crowns])
    gnss_error = np.array([0.45, -0.3])
    trees = tree_positions(
        pd.DataFrame(
            {
                "tree_id": list("abcd"),
                "x": truth[:, 0] + gnss_error[0],
                "y": truth[:, 1] + gnss_error[1],
            }
        ),
        None,
    )
    for register in (False, True):
        seg, _, matched, offset = crowns_stage(
            mosaic, surface, trees, frame, GroundTruthConfig(register_seeds=register)
        )
        assert matched["matched"].all() and offset["pairs"] == 4
        assert [offset["east_m"], offset["north_m"]] == pytest.approx(-gnss_error, abs=0.05)
        assert offset["significant"] and offset["seeds_shifted"] == register
        # The crowns' centres come from the photos whatever the seeds: unbiased either way.
        centres = matched[["aerial_x", "aerial_y"]].to_numpy()
        assert np.abs((centres - truth).mean(axis=0)).max() < 0.05
        assert matched["aerial_distance_m"].to_numpy() == pytest.approx(
            np.hypot(*gnss_error), abs=0.1
        )
        if register:
            assert seg.markers == pytest.approx(truth, abs=0.15)  # seeds moved onto the crowns
            assert [offset["east_after_m"], offset["north_after_m"]] == pytest.approx(
                -gnss_error, abs=0.05
            )
    exact = tree_positions(pd.DataFrame({"x": truth[:, 0], "y": truth[:, 1]}), None)
    _, _, _, offset = crowns_stage(mosaic, surface, exact, frame, GroundTruthConfig())
    assert not offset["significant"] and not offset["seeds_shifted"]


def test_crown_agreement_scores_hand_made_crowns_and_an_empty_match():
    """Two true trees, one crown 0.3 m from the first (its extents 0.5 m too long along the
    row and 0.2 m too narrow across) and one 5 m from anything: one matched, one extra,
    along/across errors as built; with no crown in the gate the row metrics are NaN."""
    from ground_truth.crowns import CROWN_COLUMNS
    from ground_truth.flight_accuracy import crown_agreement

    truth = pd.DataFrame(
        {
            "tree_id": [1, 2],
            "label": ["L0", "L1"],
            "row": [0, 0],
            "crown_x": [0.0, 5.0],
            "crown_y": [0.0, 0.0],
            "crown_diameter_m": [4.0, 4.0],
            "crown_diameter_mean_m": [3.8, 3.8],
            "tree_height_m": [3.0, 3.0],
            "crown_volume_m3": [20.0, 20.0],
            "sphere_volume_m3": [33.5, 33.5],
            "extent_along_row_m": [4.0, 4.0],
            "extent_across_row_m": [3.6, 3.6],
        }
    )
    crowns = pd.DataFrame(0.0, index=range(2), columns=CROWN_COLUMNS)
    crowns["x"], crowns["y"] = [0.3, 0.0], [0.0, 5.0]
    crowns["touches_border"] = False
    crowns["diameter_along_row_m"] = [4.5, 3.0]
    crowns["diameter_across_row_m"] = [3.4, 3.0]
    table, m = crown_agreement(crowns, truth)
    assert (m["matched"], m["unmatched_crowns"], m["trees"]) == (1, 1, 2)
    assert table["tree_id"].tolist() == [1] and table["distance_m"][0] == pytest.approx(0.3)
    assert m["along_row_bias_m"] == pytest.approx(0.5)
    assert m["across_row_bias_m"] == pytest.approx(-0.2)
    assert m["free_standing"] == 1  # shared_outline_fraction 0
    far = crowns.assign(x=[20.0, 30.0])
    table, m = crown_agreement(far, truth)
    assert m["matched"] == 0 and len(table) == 0
    assert np.isnan(m["along_row_mae_m"]) and np.isnan(m["across_row_bias_m"])


@pytest.mark.parametrize("k1, k2", [(0.0, 0.0), (-0.12, 0.03)])
def test_projected_bilinear_lookup_agrees_with_scipy(k1, k2):
    """The compiled lookup of the surface matching against the projection written out in
    numpy and ``scipy.ndimage.map_coordinates(order=1, mode="constant", cval=nan)``, on
    points inside, on and beyond the image's edge, behind the camera too; a second image is
    read at the same pixels (bilinear is linear: 1 - 2 x the first's values)."""
    from scipy.ndimage import map_coordinates

    from ground_truth.kernels import project_bilinear

    rng = np.random.default_rng(3)
    image = rng.random((40, 60)).astype(np.float32)
    fx, fy, cx, cy = 50.0, 52.0, 30.0, 20.0
    base = np.column_stack(
        [rng.uniform(-0.9, 0.9, 500), rng.uniform(-0.7, 0.7, 500), rng.uniform(0.5, 2.0, 500)]
    ).astype(np.float32)
    base[:4, :2] = [[-0.59, 0.0], [0.0, -0.385], [0.59, 0.0], [0.0, 0.375]]  # near the edges
    base[:4, 2] = 1.0
    base[4, 2] = -1.0  # behind the camera: projects through the centre, mirrored
    axis = np.array([0.05, -0.02, 0.3], np.float32)
    height = 0.7
    index = rng.permutation(600)[:500]  # the cells these points stand for, scattered
    out = np.full(600, -1.0, np.float32)
    second, second_out = 1.0 - 2.0 * image, np.full(600, -1.0, np.float32)
    intrinsics = np.array([fx, fy, cx, cy, k1, k2])
    project_bilinear(base, axis, height, intrinsics, image, index, out, second, second_out)
    alone = np.full(600, -1.0, np.float32)  # without a second image: the same first one
    no_image = np.empty((0, 0), np.float32)
    project_bilinear(base, axis, height, intrinsics, image, index, alone, no_image, out[:0])
    np.testing.assert_array_equal(alone, out)
    np.testing.assert_allclose(second_out[index], 1.0 - 2.0 * out[index], rtol=1e-5, atol=1e-5)

    cam = base.astype(np.float64) + height * axis.astype(np.float64)
    x, y = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
    d = 1.0 + k1 * (x * x + y * y) + k2 * (x * x + y * y) ** 2
    rows, cols = fy * y * d + (cy - 0.5), fx * x * d + (cx - 0.5)
    expected = map_coordinates(image, [rows, cols], order=1, mode="constant", cval=np.nan)
    inside = (rows >= 0) & (rows <= 39) & (cols >= 0) & (cols <= 59)
    assert 50 < inside.sum() < 490  # both kinds are tried
    np.testing.assert_allclose(out[index], expected, rtol=1e-5, atol=1e-6)
    assert np.isnan(out[index][~inside]).all()
    untouched = np.setdiff1d(np.arange(600), index)
    assert (out[untouched] == -1.0).all()


def _windowed_score_reference(a, b, ca, cb, size, min_fraction, class_weight):
    """The matching score written out with scipy's box filter (mirrored edges): windowed
    NCC over the cells both rasters have, minus the weighted mean class difference."""
    from scipy.ndimage import uniform_filter

    a, b = a.astype(np.float64), b.astype(np.float64)
    valid = np.isfinite(a) & np.isfinite(b)
    a0, b0 = np.where(valid, a, 0.0), np.where(valid, b, 0.0)
    w = uniform_filter(valid.astype(float), size)
    with np.errstate(invalid="ignore", divide="ignore"):
        ma, mb = uniform_filter(a0, size) / w, uniform_filter(b0, size) / w
        va = uniform_filter(a0 * a0, size) / w - ma * ma
        vb = uniform_filter(b0 * b0, size) / w - mb * mb
        cov = uniform_filter(a0 * b0, size) / w - ma * mb
        ncc = cov / np.sqrt(np.maximum(va, 1e-6) * np.maximum(vb, 1e-6))
        ncc[(w < min_fraction - 1e-9) | ~valid] = np.nan
        both = np.isfinite(ca) & np.isfinite(cb)
        diff = np.where(both, np.abs(ca - cb), 0.0)
        disagreement = uniform_filter(diff, size) / uniform_filter(both.astype(float), size)
    return ncc - class_weight * disagreement if class_weight else ncc


@pytest.mark.parametrize("size, class_weight", [(3, 1.0), (3, 0.0), (4, 0.5), (5, 1.0)])
def test_pair_score_agrees_with_the_box_filter_formula(size, class_weight):
    """The compiled matching score of two views against the same score from scipy's
    ``uniform_filter``: textured and flat patches, NaN holes, the raster's edges."""
    from ground_truth.kernels import pair_score

    rng = np.random.default_rng(size)
    a = rng.random((23, 31)).astype(np.float32)
    b = (0.6 * a + 0.4 * rng.random(a.shape)).astype(np.float32)
    b[5:9, 20:26] = 0.25 + 1e-4 * a[5:9, 20:26]  # nearly flat: the variance floor decides
    a[rng.random(a.shape) < 0.05] = np.nan
    b[10:12, :3] = np.nan  # a hole at the edge
    ca = (rng.random(a.shape) < 0.5).astype(np.float32)
    cb = np.where(rng.random(a.shape) < 0.8, ca, 1 - ca).astype(np.float32)
    cb[0, :] = np.nan
    got = pair_score(a, b, ca, cb, size, 0.8, class_weight)
    want = _windowed_score_reference(a, b, ca, cb, size, 0.8, class_weight)
    assert np.isfinite(want).sum() > 0.6 * a.size and np.isnan(want).sum() > 20
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


def test_line_of_sight_over_a_wall_against_hand_geometry():
    """A 2 m wall along x = 5 m on flat ground (DSM at 0.1 m cells) and a camera 20 m up at
    x = 15 m: ground points west of the wall see the camera only where the ray from them to
    the camera clears the wall's top, i.e. where z_ray(x = 5) = 20 (5 - x) / (15 - x) > 2
    + 0.15 m; points east of it and outside the raster always see it."""
    from ground_truth.ortho import _line_of_sight_clear

    grid = Grid(0.0, 10.0, 0.1, 100, 100)
    dsm = np.zeros(grid.shape)
    x, _ = grid.centers()
    dsm[(x > 4.9) & (x < 5.1)] = 2.0  # the wall: two cell columns around x = 5
    camera = camera_from_pose(
        "above",
        "PINHOLE",
        (300.0, 300.0, 200.0, 150.0),
        400,
        300,
        np.array([15.0, 5.0, 20.0]),
        NADIR,
    )
    px = np.array([0.5, 2.0, 3.0, 3.5, 4.0, 4.2, 4.4, 4.6, 4.8, 6.0, 8.0, -3.0])
    points = np.column_stack([px, np.full(len(px), 5.0), np.zeros(len(px))])
    clear = _line_of_sight_clear(points, camera, grid, dsm, top=2.0, step=0.05)
    ray_at_wall = 20.0 * (5.0 - px) / (15.0 - px)  # height of each ray above x = 5
    expected = (px > 5.1) | (px < 0) | (ray_at_wall > 2.15 + 0.2)  # 0.2: a margin
    assert (clear == expected)[np.abs(ray_at_wall - 2.15) > 0.2].all(), (clear, ray_at_wall)
    assert clear.sum() >= 3 and (~clear).sum() >= 3
