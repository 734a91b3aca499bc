"""Every ``[ground_truth]`` key acts: changed, it changes what the drone pipeline produces.

The keys come from the dataclass (:class:`canopy_kit.config.GroundTruthConfig`): a new key
without a case in ``CASES`` fails ``test_every_key_has_a_case``. Each case runs the cheap part
of the pipeline the key steers (feature extraction on a tiny simulated flight, the crowns
stage and the matching on a synthetic orchard, the surface search on two synthetic photos)
with the default and with a changed value.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from fixtures_aerial import NADIR, aerial_result, synthetic_hedgerows, two_photos_of_a_block

from canopy_kit.config import GroundTruthConfig, PipelineConfig, load_preset
from canopy_kit.core.geo import LocalFrame
from canopy_kit.errors import ConfigError, ProcessingError

FIELDS = [f.name for f in dataclasses.fields(GroundTruthConfig)]


@pytest.fixture(scope="module")
def flight_dir(tmp_path_factory) -> Path:
    """A 1 x 2 pistachio flight of 400 x 300 px photos (about 4 s to simulate)."""
    from canopy_kit.sim import load_sim_config
    from canopy_kit.sim.drone import simulate_drone_session

    root = tmp_path_factory.mktemp("gt_config")
    cfg = load_sim_config(
        "pistachio",
        {
            "seed": 4,
            "orchard": {"rows": 1, "trees_per_row": 2},
            "drone": {"enabled": True, "image_width": 400, "image_height": 300},
        },
    )
    simulate_drone_session(root / "sim", cfg)
    return root / "sim" / "drone"


# -- what each key steers, measured --------------------------------------------------------
def _keypoints(config: GroundTruthConfig, flight_dir: Path, tmp_path: Path) -> float:
    """SIFT keypoints pycolmap extracts from the flight (the pipeline's SfM settings)."""
    from ground_truth.exif import read_flight
    from ground_truth.pipeline import sfm_options
    from ground_truth.sfm import _extract, _quiet_colmap

    flight = read_flight(flight_dir)
    database = tmp_path / f"db_{config.max_image_size}.db"
    pycolmap, previous = _quiet_colmap()
    try:
        opts = dataclasses.replace(sfm_options(config), num_threads=1)
        _extract(pycolmap, flight, database, opts)
        db = pycolmap.Database.open(str(database))
        try:
            return float(db.num_keypoints())
        finally:
            db.close()
    finally:
        pycolmap.logging.minloglevel = previous


def _work_pixels(config: GroundTruthConfig, flight_dir: Path, tmp_path: Path) -> float:
    """Pixels of the photos the surface and the mosaic are made from."""
    from ground_truth.camera import camera_from_pose
    from ground_truth.exif import read_flight
    from ground_truth.pipeline import load_work_images

    flight = read_flight(flight_dir)
    w, h = flight.size
    cams = [
        camera_from_pose(
            n, "SIMPLE_PINHOLE", (300.0, w / 2, h / 2), w, h, np.array([0.0, 0.0, 30.0]), NADIR
        )
        for n in flight.names[:2]
    ]
    scaled, rgbs = load_work_images(flight, cams, config.work_image_size)
    assert [c.width for c in scaled] == [rgb.shape[1] for rgb in rgbs]
    return float(sum(rgb.shape[0] * rgb.shape[1] for rgb in rgbs))


def _canopy_search_height(config: GroundTruthConfig, *_) -> float:
    """The height above ground the fine surface matching searches up to."""
    from ground_truth.dsm import SurfaceOptions, canopy_top, search_height
    from ground_truth.raster import Grid

    cams, images = two_photos_of_a_block(3.0)
    grid = Grid(-6.0, 6.0, 0.1, 120, 120)
    ground = np.zeros(grid.shape)
    limit = config.max_canopy_height
    if limit is None:  # unset: from sparse points, here on the ground and the 3 m block's top
        xy = np.random.default_rng(0).uniform(-5, 5, (400, 2))
        top = np.abs(xy).max(axis=1) < 3.0
        limit, _ = search_height(np.column_stack([xy, np.where(top, 3.0, 0.0)]), grid, ground)
    return canopy_top(cams, images, grid, ground, limit, SurfaceOptions())


def _mosaic_pixels(config: GroundTruthConfig, *_) -> float:
    """Cells of the orthomosaic of the two synthetic photos (resolution from the config)."""
    from ground_truth.ortho import orthomosaic
    from ground_truth.pipeline import ortho_resolution
    from ground_truth.raster import Grid

    cams, images = two_photos_of_a_block(3.0)
    rgbs = [
        np.repeat((255 * np.clip(g, 0, 1)).astype(np.uint8)[..., None], 3, axis=2) for g in images
    ]
    grid = Grid(-6.0, 6.0, 0.1, 120, 120)
    gsd = 30.0 / cams[0].focal
    mosaic = orthomosaic(cams, rgbs, grid, np.zeros(grid.shape), ortho_resolution(gsd, config))
    return float(mosaic.grid.rows * mosaic.grid.cols)


def _orchard_with_offset_seeds():
    """The synthetic orchard of test_ground_truth_units, seeds 0.54 m off their crowns."""
    from ground_truth.dsm import SurfaceModel
    from ground_truth.match import tree_positions
    from ground_truth.ortho import Orthomosaic
    from tests.test_ground_truth_units import _synthetic_orchard

    grid, rgb, chm, crowns = _synthetic_orchard()
    rgba = np.dstack([rgb, np.full(grid.shape, 255, np.uint8)])
    mosaic = Orthomosaic(grid, rgba, np.zeros(grid.shape, np.int32), ["a"])
    surface = SurfaceModel(
        grid, chm, np.zeros(grid.shape), np.ones(grid.shape), np.zeros(grid.shape + (0,), int), []
    )
    truth = np.array([(cx, cy) for cx, cy, _, _ in crowns])
    trees = tree_positions(
        pd.DataFrame({"tree_id": list("abcd"), "x": truth[:, 0] + 0.45, "y": truth[:, 1] - 0.3}),
        None,
    )
    return mosaic, surface, trees, truth


def _crowns_stage(config: GroundTruthConfig):
    from ground_truth.pipeline import crowns_stage

    mosaic, surface, trees, truth = _orchard_with_offset_seeds()
    seg, _, matched, _ = crowns_stage(
        mosaic, surface, trees, LocalFrame.at(37.281, -120.42, 50.0), config
    )
    return seg, matched, truth


def _matched_trees(config: GroundTruthConfig, *_) -> float:
    """Trees given a crown by the crowns stage."""
    _, matched, _ = _crowns_stage(config)
    return float(matched["matched"].sum())


def _seed_error(config: GroundTruthConfig, *_) -> float:
    """Mean distance of the watershed's seed markers from the true crown centres."""
    seg, _, truth = _crowns_stage(config)
    return float(np.linalg.norm(seg.markers - truth, axis=1).mean())


def _seeded_markers(config: GroundTruthConfig, *_) -> float:
    """Share of the crowns' markers that are seed trees (the others come from the imagery)."""
    seg, _, _ = _crowns_stage(config)
    return float((seg.marker_seed_ids >= 0).mean()) if len(seg.marker_seed_ids) else 0.0


def _flagged_crowns(config: GroundTruthConfig, *_) -> float:
    """Aerial crowns flagged as fragments or merges in the per-tree table."""
    from canopy_kit.results.tree_table import join_aerial

    d = np.array([2.0, 2.6, 3.2, 4.0, 4.8, 5.6, 6.4, 8.0])
    aerial = aerial_result(d)
    lidar = pd.DataFrame(
        {"segment": np.arange(len(d)), "crown_diameter_m": 4.0, "volume_alpha_m3": 20.0}
    )
    return float((join_aerial(lidar, aerial, config)["aerial_flag"] != "").sum())


def _hedgerow_crowns(config: GroundTruthConfig):
    """Crowns the crowns stage finds, without seed trees, on synthetic touching hedgerows."""
    from ground_truth.dsm import SurfaceModel
    from ground_truth.match import assign
    from ground_truth.ortho import Orthomosaic
    from ground_truth.pipeline import crowns_stage

    grid, rgb, chm, centres, _ = synthetic_hedgerows()
    rgba = np.dstack([rgb, np.full(grid.shape, 255, np.uint8)])
    mosaic = Orthomosaic(grid, rgba, np.zeros(grid.shape, np.int32), ["a"])
    surface = SurfaceModel(
        grid, chm, np.zeros(grid.shape), np.ones(grid.shape), np.zeros(grid.shape + (0,), int), []
    )
    _, crowns, _, _ = crowns_stage(
        mosaic, surface, None, LocalFrame.at(37.281, -120.42, 50.0), config
    )
    ia, _, _ = assign(centres, crowns[["x", "y"]].to_numpy(), 1.5)
    return crowns, len(ia)


def _hedgerow_one_to_one(config: GroundTruthConfig, *_) -> float:
    """Hedgerow trees with a crown of their own within 1.5 m, found from the imagery alone."""
    return float(_hedgerow_crowns(config)[1])


def _hedgerow_crown_count(config: GroundTruthConfig, *_) -> float:
    """Crowns found on the hedgerows from the imagery alone."""
    return float(len(_hedgerow_crowns(config)[0]))


def _hull_crowns(config: GroundTruthConfig, flight_dir: Path, _) -> float:
    """Crowns given a visual-hull volume on the tiny flight (true camera poses)."""
    from tests.test_multiview_hull import _stage

    _, crowns, _, _, _ = _stage(flight_dir.parent, config)
    return float(crowns["hull_volume_m3"].notna().sum()) if "hull_volume_m3" in crowns else 0.0


def _hull_of_a_narrow_outline(config: GroundTruthConfig, *_) -> float:
    """The hull of an exact sphere seen from bearings every 30°, its outline 0.7 of its
    radius (tests/test_visual_hull.py), carved with the settings' hull options."""
    from ground_truth.multiview import hull_options
    from ground_truth.raster import Grid
    from ground_truth.visual_hull import crown_hull_volumes
    from tests.test_visual_hull import _ring, _silhouette

    cameras = _ring(30)
    grid = Grid.covering(np.array([-3.0, -3.0]), np.array([3.0, 3.0]), 0.1)
    x, y = grid.centers()
    labels = np.where(np.hypot(x, y) <= 1.05, 1, 0)
    crowns = pd.DataFrame({"crown_id": [1], "height_m": [4.0]})
    masks = [_silhouette(c) for c in cameras]
    ground = np.zeros(grid.shape)
    volume = crown_hull_volumes(
        cameras, masks, labels, grid, crowns, ground, grid, hull_options(config)
    )
    return float(volume[0])


Measure = Callable[[GroundTruthConfig, Path, Path], float]
# key -> (changed value, what it changes, expected sign of changed minus default: -1, +1, 0 any)
CASES: dict[str, tuple[object, Measure, int]] = {
    "max_image_size": (128, _keypoints, -1),
    "work_image_size": (200, _work_pixels, -1),
    "ortho_resolution": (0.2, _mosaic_pixels, -1),
    "max_canopy_height": (2.5, _canopy_search_height, -1),
    "match_distance_m": (0.3, _matched_trees, -1),
    "crowns_from_seeds": (False, _seeded_markers, -1),
    "crown_seeds": ("chm_maxima", _hedgerow_one_to_one, -1),
    "tree_spacing_m": (2.4, _hedgerow_crown_count, +1),
    # the fixture's rows run at 20°: given across them, the rows seeding finds fewer trees
    "row_bearing_deg": (110.0, _hedgerow_one_to_one, -1),
    "register_seeds": (False, _seed_error, +1),
    "min_diameter_ratio": (0.9, _flagged_crowns, +1),
    "max_diameter_ratio": (1.1, _flagged_crowns, +1),
    "hull_volume": (False, _hull_crowns, -1),
    "hull_outline_margin_m": (0.0, _hull_of_a_narrow_outline, -1),
}


def test_every_key_has_a_case() -> None:
    assert sorted(CASES) == sorted(FIELDS), "a [ground_truth] key needs a case in CASES"


@pytest.mark.parametrize("key", FIELDS)
def test_changing_the_key_changes_the_result(key: str, flight_dir: Path, tmp_path: Path) -> None:
    value, measure, sign = CASES[key]
    default = GroundTruthConfig()
    changed = dataclasses.replace(default, **{key: value})
    before, after = measure(default, flight_dir, tmp_path), measure(changed, flight_dir, tmp_path)
    assert after != before, f"ground_truth.{key} = {value!r} changed nothing ({before})"
    if sign:
        assert np.sign(after - before) == sign, (key, before, after)


@pytest.mark.parametrize("key", FIELDS)
def test_a_preset_sets_the_key(key: str, tmp_path: Path) -> None:
    """Each key can be set from a preset file's [ground_truth] table."""
    import tomlkit

    value = CASES[key][0]
    path = tmp_path / "p.toml"
    path.write_text(tomlkit.dumps({"name": "p", "ground_truth": {key: value}}))
    config = load_preset(path)
    assert getattr(config.ground_truth, key) == value
    assert (
        getattr(load_preset(path.as_posix(), {"ground_truth": {key: value}}).ground_truth, key)
        == value
    )


def test_an_unknown_key_fails_naming_it(tmp_path: Path) -> None:
    path = tmp_path / "old.toml"
    path.write_text('name = "old"\n[ground_truth]\nmatch_distance_m = 1.0\nmax_image_sise = 800\n')
    with pytest.raises(ConfigError, match=r"ground_truth.*'max_image_sise'"):
        load_preset(path)


@pytest.mark.parametrize(
    "table",
    [
        {"max_image_size": 10},
        {"work_image_size": 0},
        {"match_distance_m": 0.0},
        {"max_canopy_height": -1.0},
        {"ortho_resolution": 0.0},
        {"crown_seeds": "watershed"},
        {"tree_spacing_m": -4.0},
        {"hull_volume": "no"},
        {"hull_outline_margin_m": -0.3},
        {"hull_outline_margin_m": "0.6"},
    ],
)
def test_impossible_values_are_named(table: dict) -> None:
    from canopy_kit.config import from_dict

    with pytest.raises(ConfigError, match=f"ground_truth.{next(iter(table))}"):
        from_dict(PipelineConfig, {"ground_truth": table})


def test_process_flight_hands_the_config_to_sfm(
    flight_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The config given to ``process_flight`` reaches pycolmap's feature extraction."""
    import ground_truth.pipeline as gp

    seen = {}

    def fake_sfm(flight, work, frame, options, report):
        seen.update(
            max_image_size=options.max_image_size, seed=options.seed, threads=options.num_threads
        )
        raise ProcessingError("stop after SfM")

    monkeypatch.setattr(gp, "run_sfm", fake_sfm)
    config = GroundTruthConfig(max_image_size=640)
    with pytest.raises(ProcessingError, match="stop after SfM"):
        gp.process_flight(flight_dir, tmp_path / "out", config=config, seed=7, threads=1)
    assert seen == {"max_image_size": 640, "seed": 7, "threads": 1}
    with pytest.raises(ProcessingError, match="stop after SfM"):
        gp.process_flight(flight_dir, tmp_path / "out2", config=config)
    assert seen["threads"] == -1  # COLMAP's "every core"


@pytest.mark.parametrize("threads", [-1, 1.5, True])
def test_impossible_thread_counts_are_named_before_any_work(
    threads: object, flight_dir: Path, tmp_path: Path
) -> None:
    import ground_truth.pipeline as gp

    with pytest.raises(ConfigError, match="threads"):
        gp.process_flight(flight_dir, tmp_path / "out", threads=threads)  # type: ignore[arg-type]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("threads", [-1, 2.0, False])
def test_a_runs_impossible_sfm_threads_are_named_before_the_mapping(
    threads: object, tiny_pistachio, flight_dir: Path, tmp_path: Path
) -> None:
    """``run``/``compute`` with drone photos check ``sfm_threads`` before any stage: nothing
    is mapped, no output folder is made."""
    from canopy_kit.pipeline import compute

    with pytest.raises(ConfigError, match="sfm_threads: expected an integer >= 0"):
        compute(
            load_preset("adaptive"),
            tiny_pistachio.bag,
            tmp_path / "out",
            drone_images=flight_dir,
            sfm_threads=threads,  # type: ignore[arg-type]
        )
    assert not (tmp_path / "out").exists()


def test_reuse_refuses_other_reconstruction_settings(flight_dir: Path, tmp_path: Path) -> None:
    """A reused reconstruction cannot honour new SfM, surface or mosaic settings: an error."""
    from ground_truth.exif import read_flight
    from ground_truth.pipeline import process_flight

    flight = read_flight(flight_dir)
    frame = flight.default_frame()
    model = SimpleNamespace(cameras={n: None for n in flight.names}, unregistered=[])
    reuse = SimpleNamespace(model=model, frame=frame, config=GroundTruthConfig())
    with pytest.raises(ProcessingError, match="ground_truth.work_image_size"):
        process_flight(
            flight_dir, tmp_path / "out", config=GroundTruthConfig(work_image_size=500), reuse=reuse
        )
    reuse.report = {"sfm_seed": 0}  # SfM's random sampling was seeded otherwise: an error too
    with pytest.raises(ProcessingError, match="reconstructed with seed 0, not 3"):
        process_flight(
            flight_dir, tmp_path / "out", config=GroundTruthConfig(), reuse=reuse, seed=3
        )


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--set", "ground_truth.match_distanse_m=1.0"], "'match_distanse_m'"),
        (["--set", "volume.voxel_size=0.2"], "ground_truth.key=value"),
        (["--work-size", "10"], "ground_truth.work_image_size"),
    ],
)
def test_ground_truth_cli_settings_are_checked_before_any_work(
    args: list[str], fragment: str, tmp_path: Path
) -> None:
    """``canopy-kit ground-truth`` builds its [ground_truth] config with the preset loader."""
    from typer.testing import CliRunner

    from canopy_kit.cli import app

    res = CliRunner().invoke(
        app, ["ground-truth", str(tmp_path / "photos"), "--out", str(tmp_path / "out"), *args]
    )
    assert isinstance(res.exception, ConfigError) and fragment in str(res.exception), res.output
    assert not (tmp_path / "out").exists()


def test_a_given_row_bearing_is_used_and_reported() -> None:
    """The rows' true bearing, given, finds the trees the imagery finds; the crowns are
    measured along it and say so."""
    from ground_truth.rows import RowDirection

    found = _hedgerow_crowns(GroundTruthConfig())
    given = _hedgerow_crowns(GroundTruthConfig(row_bearing_deg=20.0))
    assert given[1] >= found[1] - 1
    direction = given[0].attrs["row_direction"]
    assert direction.source == "given" and direction.bearing_deg == pytest.approx(20.0)
    assert RowDirection.from_bearing(200.0).bearing_deg == pytest.approx(20.0)
    for bad in (-5.0, 360.0, "north", True):
        with pytest.raises(ConfigError, match="ground_truth.row_bearing_deg"):
            GroundTruthConfig(row_bearing_deg=bad)


def test_the_search_height_follows_the_trees_in_the_sparse_points() -> None:
    """Unset max_canopy_height: the sparse points' canopy top (14 m walnut-like crowns here,
    above the old fixed 8 m) plus 2 m, a stray point 60 m up left out; too few points above
    the ground: the 8 m default, said to be one."""
    from ground_truth.dsm import SEARCH_HEIGHT_WITHOUT_DATA_M, search_height
    from ground_truth.raster import Grid

    rng = np.random.default_rng(1)
    grid = Grid(-10.0, 10.0, 0.5, 40, 40)
    ground = np.full(grid.shape, 100.0)  # heights are above this ground, not above zero
    xy = rng.uniform(-9, 9, (3000, 2))
    crown = np.hypot(xy[:, 0], xy[:, 1]) < 5
    z = 100.0 + np.where(crown, rng.uniform(2.0, 14.0, len(xy)), rng.normal(0, 0.05, len(xy)))
    points = np.vstack([np.column_stack([xy, z]), [[0.0, 0.0, 160.0]]])
    height, source = search_height(points, grid, ground)
    assert 15.8 < height <= 16.0 and source == "the flight's sparse points"
    flat = np.column_stack([xy, np.full(len(xy), 100.0)])
    assert search_height(flat, grid, ground) == (
        SEARCH_HEIGHT_WITHOUT_DATA_M,
        "too few sparse points above the ground: a default",
    )
