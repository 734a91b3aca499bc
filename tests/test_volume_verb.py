"""The volume stage (``canopy_kit.volume.verb``): one tree measured as trees.csv measures it,
estimators built once per run, and the volumes notebook showing trees.csv's numbers."""

from __future__ import annotations

import sys

import numpy as np
import pandas as pd
import pytest
from conftest import REPO

from canopy_kit.config import VolumeConfig
from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import ConfigError
from canopy_kit.volume import verb
from canopy_kit.volume.verb import (
    build_estimators,
    measure_tree,
    measure_trees,
    tree_points,
    volume_column,
    volume_methods,
)

MEASURED = [
    "x",
    "y",
    "n_points",
    "height_m",
    "crown_diameter_m",
    "projected_area_m2",
    "sphere_volume_m3",
    "volume_low_m3",
    "volume_high_m3",
]


def _blobs(n_trees: int, seed: int = 0) -> tuple[PointCloud, np.ndarray]:
    """Noisy ellipsoidal crowns 5 m apart, one label each (points off the 1 mm grid)."""
    rng = np.random.default_rng(seed)
    parts, labels = [], []
    for k in range(n_trees):
        pts = rng.normal(0.0, 1.0, (3000, 3)) * np.array([1.2, 1.0, 0.8])
        parts.append(pts + np.array([5.0 * k, 0.0, 2.5]))
        labels.append(np.full(len(pts), k))
    return PointCloud(np.vstack(parts)), np.concatenate(labels)


def _assert_same(row: dict, expected: pd.Series, columns: list[str]) -> None:
    for col in columns:
        got, want = float(row[col]), float(expected[col])
        assert (np.isnan(got) and np.isnan(want)) or got == pytest.approx(
            want, rel=1e-9, abs=1e-12
        ), col


def test_volume_column_names_the_paper_estimators_and_any_plugin() -> None:
    assert volume_column("alpha_shape") == verb.ALPHA_COLUMN == "volume_alpha_m3"
    assert volume_column("convex_hull") == verb.CONVEX_HULL_COLUMN == "volume_convex_hull_m3"
    assert volume_column("slices") == "volume_slices_m3"
    assert volume_methods(VolumeConfig(recommended="adaptive_alpha")) == [
        "convex_hull",
        "alpha_shape",
        "adaptive_alpha",
    ]


def test_measure_tree_gives_the_table_row_of_that_tree() -> None:
    cloud, labels = _blobs(3)
    config = VolumeConfig(voxel_size=0.1, workers=1)
    table = measure_trees(cloud, labels, config)
    columns = MEASURED + [volume_column(m) for m in volume_methods(config)]
    for seg in range(3):
        row = measure_tree(cloud.xyz[labels == seg], config)
        _assert_same(row, table.set_index("segment").loc[seg], columns)
        assert row["volume_flags"] == table.loc[seg, "volume_flags"]


def test_the_kept_surfaces_are_the_solids_the_table_measured() -> None:
    """The volume stage's surfaces (from forked workers) are those drawn afresh for each
    tree, their volumes the table's hull and alpha columns; the table is measure_trees'."""
    from canopy_kit.volume.verb import measure_trees_and_surfaces, tree_surfaces

    cloud, labels = _blobs(8, seed=5)
    labels[labels == 3] = -1  # unlabelled points are no tree
    config = VolumeConfig(voxel_size=0.1, workers=2)
    kept = measure_trees_and_surfaces(cloud, labels, config)
    pd.testing.assert_frame_equal(kept.table, measure_trees(cloud, labels, config))
    assert sorted(kept.surfaces) == [0, 1, 2, 4, 5, 6, 7]
    table = kept.table.set_index("segment")
    for seg, surfaces in kept.surfaces.items():
        fresh = tree_surfaces(cloud.xyz[labels == seg], config)
        assert [s.name for s in surfaces] == ["convex hull", "alpha shape (α = 0.9 m)"]
        for got, want in zip(surfaces, fresh, strict=True):
            np.testing.assert_array_equal(got.vertices, want.vertices)
            np.testing.assert_array_equal(got.faces, want.faces)
        hull, alpha = (s.volume_m3 for s in surfaces)
        assert hull == table.loc[seg, verb.CONVEX_HULL_COLUMN]
        assert alpha == table.loc[seg, verb.ALPHA_COLUMN]
    only_hull = VolumeConfig(voxel_size=0.1, workers=1, methods=["convex_hull", "slices"])
    drawn = measure_trees_and_surfaces(cloud, labels, only_hull).surfaces
    assert [s.name for s in drawn[0]] == ["convex hull"]


def test_no_tree_gives_an_empty_table_that_still_joins() -> None:
    """A segmentation without trees: an empty table with its ``segment`` key, no surfaces."""
    from canopy_kit.volume.verb import measure_trees_and_surfaces

    cloud, labels = _blobs(2)
    kept = measure_trees_and_surfaces(cloud, np.full(len(labels), -1), VolumeConfig(workers=1))
    assert kept.table.empty and kept.surfaces == {}
    names = pd.DataFrame({"tree_id": pd.Series(dtype=str)}, index=pd.Index([], name="segment_id"))
    assert kept.table.join(names, on="segment").empty


def test_the_report_draws_only_the_trees_it_was_not_given() -> None:
    """Kept surfaces are used as they are; the trees without an entry are drawn afresh,
    exactly as the volume stage would have kept them; with no drawn estimator, none is."""
    from types import SimpleNamespace

    from canopy_kit.report.explorer import _encoded_surfaces, encode_surface
    from canopy_kit.volume.verb import measure_trees_and_surfaces

    cloud, labels = _blobs(3, seed=2)
    config = VolumeConfig(voxel_size=0.1, workers=1)
    kept = measure_trees_and_surfaces(cloud, labels, config).surfaces
    items = [(SimpleNamespace(segment=s, x=0.0, y=0.0), cloud.xyz[labels == s]) for s in range(3)]
    partly = {0: kept[0], 2: []}  # tree 1 missing; tree 2 measured with nothing to draw
    encoded = _encoded_surfaces(items, config, partly)
    centre = np.array([0.0, 0.0, cloud.xyz[labels == 1][:, 2].min()])
    assert encoded[1] == [encode_surface(s, centre) for s in kept[1]] and len(encoded[1]) == 2
    assert len(encoded[0]) == 2 and encoded[2] == []
    no_drawing = VolumeConfig(voxel_size=0.1, workers=1, methods=["slices"])
    assert _encoded_surfaces(items, no_drawing, {}) == [[], [], []]


def test_the_interval_takes_the_recommended_estimators_fill_unchanged() -> None:
    """adaptive_alpha's surface fill, handed to the interval, is the fill measured afresh."""
    from canopy_kit.volume.uncertainty import INTERVAL_COLUMNS, surface_fill
    from canopy_kit.volume.verb import interval_columns, measured_points

    cloud, labels = _blobs(2, seed=3)
    config = VolumeConfig(voxel_size=0.1, workers=1, recommended="adaptive_alpha")
    for seg in range(2):
        xyz = cloud.xyz[labels == seg]
        row = measure_tree(xyz, config)
        measured = measured_points(xyz, config)
        others = {
            "convex_hull": row["volume_convex_hull_m3"],
            "alpha_shape": row["volume_alpha_m3"],
        }
        fresh = interval_columns(
            measured, row["volume_adaptive_alpha_m3"], "adaptive_alpha", others=others
        )
        assert row[INTERVAL_COLUMNS["fill"]] == pytest.approx(surface_fill(measured), rel=1e-12)
        for key in ("low", "high", "fill", "flags"):
            assert row[INTERVAL_COLUMNS[key]] == fresh[INTERVAL_COLUMNS[key]]


def test_tree_points_are_on_the_map_laz_grid() -> None:
    from canopy_kit.io.las_write import on_las_grid

    cloud, labels = _blobs(2)
    np.testing.assert_array_equal(
        tree_points(cloud, labels, 1), on_las_grid(cloud).xyz[labels == 1]
    )


def test_estimators_are_built_once_per_table(monkeypatch: pytest.MonkeyPatch) -> None:
    from canopy_kit import plugins

    built: list[str] = []
    real = plugins.create

    def counting(kind: str, name: str, *args, **kwargs):
        if kind == "volumes":
            built.append(name)
        return real(kind, name, *args, **kwargs)

    monkeypatch.setattr(plugins, "create", counting)
    cloud, labels = _blobs(3)
    config = VolumeConfig(workers=1)
    estimators = build_estimators(config)
    assert built == volume_methods(config)
    measure_trees(cloud, labels, config, estimators=estimators)
    assert built == volume_methods(config)  # none built again for the trees


def test_build_estimators_names_a_bad_parameter() -> None:
    with pytest.raises(ConfigError, match="alpha"):
        build_estimators(VolumeConfig(params={"alpha_shape": {"alpha": -1.0}}))


@pytest.fixture(scope="module")
def run_context(tiny_pistachio, tiny_pistachio_run):
    """The stages of ``tiny_pistachio_run`` as a notebook loads them (from the run's cache)."""
    from canopy_kit.pipeline.explore import load_context

    return load_context(tiny_pistachio.root, run_dir=tiny_pistachio_run.out_dir, use_drone=False)


@pytest.mark.slow
def test_the_notebook_code_path_gives_trees_csv_numbers(run_context, tiny_pistachio_run) -> None:
    ctx = run_context
    # trees.parquet: the run's table at full precision (trees.csv is rounded to its meaning)
    csv = pd.read_parquet(tiny_pistachio_run.out_dir / "trees.parquet").set_index("segment")
    assert len(csv) > 0
    columns = MEASURED + [volume_column(m) for m in volume_methods(ctx.config.volume)]
    for seg in csv.index:
        xyz = tree_points(ctx.mapping.map, ctx.segmentation.labels, int(seg))
        row = measure_tree(xyz, ctx.config.volume, ctx.segmentation.ground.height, ctx.estimators)
        _assert_same(row, csv.loc[seg], columns)


@pytest.mark.slow
def test_the_volumes_notebook_shows_trees_csv_numbers(
    monkeypatch, tiny_pistachio, tiny_pistachio_run
) -> None:
    """The notebook run in this process (marimo's ``app.run``): its first tree's volumes."""
    import importlib.util

    import matplotlib

    matplotlib.use("Agg")
    monkeypatch.setattr(
        sys,
        "argv",
        [
            "volumes.py",
            "--session",
            str(tiny_pistachio.root),
            "--run",
            str(tiny_pistachio_run.out_dir),
        ],
    )
    spec = importlib.util.spec_from_file_location(
        "volumes_notebook", REPO / "notebooks" / "volumes.py"
    )
    notebook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(notebook)
    _, defs = notebook.app.run()
    ctx = defs["ctx"]
    # trees.parquet: the run's table at full precision (trees.csv is rounded to its meaning)
    csv = pd.read_parquet(tiny_pistachio_run.out_dir / "trees.parquet").set_index("segment")
    columns = [volume_column(m) for m in volume_methods(ctx.config.volume)]
    _assert_same(defs["measured"], csv.loc[defs["tree"].value], MEASURED + columns)


@pytest.mark.slow
def test_the_drill_down_draws_what_the_volume_stage_kept(run_context, tiny_pistachio_run) -> None:
    """The report's surfaces come from the volume stage; drawn afresh (a context without
    them) they are the same, byte for byte."""
    from dataclasses import replace

    from canopy_kit.report.explorer import tree_details

    ctx = run_context
    trees = ctx.table
    assert set(ctx.surfaces) == set(trees["segment"])
    kept = tree_details(ctx, trees)
    fresh = tree_details(replace(ctx, surfaces={}), trees)
    assert kept == fresh and all(len(d["surfaces"]) == 2 for d in kept.values())


@pytest.mark.parametrize("largest", [40, 70_000])
def test_points_grouped_by_label_as_a_stable_sort_groups_them(largest) -> None:
    from canopy_kit.volume.verb import grouped_by_label

    rng = np.random.default_rng(3)
    labels = rng.integers(-1, 6, 50_000) * (largest // 5)  # labels -largest/5 .. largest
    order, sorted_labels = grouped_by_label(labels)
    kept = np.flatnonzero(labels >= 0)
    want = kept[np.argsort(labels[kept], kind="mergesort")]
    np.testing.assert_array_equal(order, want)
    np.testing.assert_array_equal(sorted_labels, labels[want])
    assert sorted_labels.dtype == labels.dtype
