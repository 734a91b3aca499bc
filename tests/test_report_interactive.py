"""The interactive report: map, searchable and sortable table, drill-down and downloads, offline.

The browser test opens a real run's report in headless Chromium with every request recorded
(only data:, blob: and about: may load besides the page itself) and checks what it shows
against the run's trees.csv.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

ARTIFACTS = Path(__file__).resolve().parents[1] / "test-artifacts"
ALLOWED = ("data:", "blob:", "about:")


def test_columns_get_human_names_with_units() -> None:
    from canopy_kit.report.columns import column_label

    assert column_label("volume_alpha_m3") == "Alpha-shape volume [m³]"
    assert column_label("tree_id") == "Tree ID"
    # Columns without an entry get words and the unit their suffix names.
    assert column_label("error_alpha_vs_aerial_pct") == "Alpha shape vs drone sphere: error [%]"
    assert (
        column_label("error_voxel_vs_true_pct") == "Voxel vs true crown (drawn envelope): error [%]"
    )
    assert column_label("error_foliage_envelope_vs_measurand_pct") == (
        "Foliage envelope vs its measurand on the complete foliage: error [%]"
    )
    assert column_label("aerial_gap_m") == "Aerial gap [m]"
    assert column_label("projected_gap_m2") == "Projected gap [m²]"
    assert column_label("volume_flags") == "Volume flags"


def test_report_title_names_the_orchard_when_the_provenance_does() -> None:
    from canopy_kit.report.session import report_title

    assert (
        report_title({"orchard": "Block 7 pistachio"}, "adaptive")[0]
        == "canopy-kit report: Block 7 pistachio"
    )
    assert "adaptive" in report_title({"orchard": "Block 7 pistachio"}, "adaptive")[1]
    assert report_title({}, "adaptive")[0] == "canopy-kit report: adaptive"


def test_scale_bar_lengths_are_round() -> None:
    from canopy_kit.report.mapdecor import nice_length

    assert nice_length(14.0) == 2.0
    assert nice_length(60.0) == 10.0
    assert nice_length(260.0) == 50.0
    assert nice_length(1.2) == pytest.approx(0.2)


def test_map_figures_get_a_north_arrow_and_a_scale_bar() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    from canopy_kit.report.mapdecor import add_north_arrow_and_scale

    _, ax = plt.subplots()
    ax.set_xlim(0, 40)
    add_north_arrow_and_scale(ax)
    bars = [a for a in ax.artists if isinstance(a, AnchoredSizeBar)]
    assert len(bars) == 1 and bars[0].txt_label.get_text() == "5 m"
    assert [t.get_text() for t in ax.texts] == ["N"]
    plt.close("all")


def test_mapping_map_is_coloured_by_height_above_the_ground() -> None:
    """On sloping ground a 3 m tree at the top of the slope and one at the bottom have the
    same colour once the ground is subtracted; the colour bar says which it is."""
    import matplotlib

    matplotlib.use("Agg")
    from canopy_kit.core.cloud import PointCloud
    from canopy_kit.mapping.plots import plot_map_top_view

    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 20, (4000, 2))
    ground = 0.5 * xy[:, 0]  # 10 m of slope
    cloud = PointCloud(np.column_stack([xy, ground + 3.0]))
    fig = plot_map_top_view(cloud, ground_height=lambda p: 0.5 * p[:, 0])
    image = fig.axes[0].images[0].get_array()
    assert np.nanmax(image) - np.nanmin(image) < 0.1  # 3 m everywhere
    assert fig.axes[1].get_ylabel() == "height above ground [m]"
    plain = plot_map_top_view(cloud)
    assert "not above ground" in plain.axes[1].get_ylabel()


def _ball(n: int = 600, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    return (
        2.0
        * v
        / np.linalg.norm(v, axis=1, keepdims=True)
        * rng.uniform(0.6, 1.0, (n, 1)) ** (1 / 3)
    )


def _closed(faces: np.ndarray) -> bool:
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [0, 2]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(counts % 2 == 0))


def test_surfaces_are_the_estimators_solids() -> None:
    """The drawn surfaces bound what the estimators measure: same volumes, closed meshes."""
    from canopy_kit.volume.alpha import AlphaShapeVolume
    from canopy_kit.volume.hull import ConvexHullVolume, hull_volume

    xyz = _ball()
    result, hull = ConvexHullVolume().with_surface(xyz)
    assert hull is not None and hull.volume_m3 == pytest.approx(hull_volume(xyz))
    assert result.volume_m3 == hull.volume_m3 == ConvexHullVolume()(xyz).volume_m3
    assert _closed(hull.faces) and hull.faces.max() < len(hull.vertices)
    result, alpha = AlphaShapeVolume(alpha=0.9).with_surface(xyz)
    assert alpha is not None and alpha.name == "alpha shape (α = 0.9 m)"
    assert alpha.volume_m3 == result.volume_m3 == AlphaShapeVolume(alpha=0.9)(xyz).volume_m3
    assert _closed(alpha.faces)
    # α below the point spacing, or points that enclose nothing: no solid to draw
    assert AlphaShapeVolume(alpha=1e-4).with_surface(xyz)[1] is None
    assert ConvexHullVolume().with_surface(np.zeros((5, 3)))[1] is None


def test_boundary_triangles_are_the_faces_of_one_tetrahedron_only() -> None:
    """Two tetrahedra glued on a face: the six outer faces, not the shared one; on a
    Delaunay triangulation of many points, the same set as counting faces row by row."""
    from scipy.spatial import Delaunay

    from canopy_kit.volume.surface import boundary_triangles

    glued = np.array([[0, 1, 2, 3], [4, 2, 1, 3]])
    faces = {tuple(f) for f in boundary_triangles(glued, 5)}
    assert faces == {(0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 4), (1, 3, 4), (2, 3, 4)}
    simplices = Delaunay(_ball()).simplices[::2]  # every other one: holes inside too
    rows = np.sort(
        np.concatenate(
            [
                simplices[:, [0, 1, 2]],
                simplices[:, [0, 1, 3]],
                simplices[:, [0, 2, 3]],
                simplices[:, [1, 2, 3]],
            ]
        ),
        axis=1,
    )
    unique, counts = np.unique(rows, axis=0, return_counts=True)
    expected = {tuple(f) for f in unique[counts == 1]}
    assert {tuple(f) for f in boundary_triangles(simplices, len(_ball()))} == expected
    # indices too large for one int64 key per triangle take the row-wise way, same answer
    assert {tuple(f) for f in boundary_triangles(glued + 3_000_000, 3_000_005)} == {
        tuple(np.array(f) + 3_000_000) for f in faces
    }
    # just below the cut-off the int64 keys of the largest indices do not overflow
    near = glued + 1_999_990
    assert {tuple(f) for f in boundary_triangles(near, 1_999_999)} == {
        tuple(np.array(f) + 1_999_990) for f in faces
    }
    assert boundary_triangles(np.empty((0, 4), np.int64), 10).shape == (0, 3)


def test_encoded_points_round_trip_to_the_centimetre() -> None:
    import base64

    from canopy_kit.report.explorer import downsample, encode_xyz

    xyz = _ball() + [500.0, 300.0, 20.0]
    centre = np.array([500.0, 300.0, 18.0])
    back = (
        np.frombuffer(base64.b64decode(encode_xyz(xyz, centre)), "<i2").reshape(-1, 3) / 100
        + centre
    )
    assert np.abs(back - xyz).max() <= 0.005 + 1e-9
    idx = downsample(10_000, 2000, seed=3)
    assert len(idx) == 2000 and len(np.unique(idx)) == 2000 and np.all(np.diff(idx) > 0)
    assert np.array_equal(idx, downsample(10_000, 2000, seed=3))
    assert np.array_equal(downsample(50, 2000), np.arange(50))


def test_ortho_crop_is_around_the_tree() -> None:
    from canopy_kit.report.explorer import ortho_crop
    from ground_truth.ortho import Orthomosaic
    from ground_truth.raster import Grid

    grid = Grid(x0=0.0, y0=50.0, resolution=0.05, rows=1000, cols=1000)  # 50 m x 50 m
    rgba = np.zeros((1000, 1000, 4), np.uint8)
    rgba[..., 3] = 255
    x, y = grid.centers()
    rgba[((x - 20) ** 2 + (y - 30) ** 2) < 4, 1] = 200  # a green crown of 2 m radius at (20, 30)
    crop = ortho_crop(Orthomosaic(grid, rgba, np.zeros((1000, 1000), int), ["a"]), 20.0, 30.0, 3.0)
    assert crop is not None and crop["uri"].startswith("data:image/jpeg;base64,")
    assert crop["x0"] == pytest.approx(17.0, abs=0.1) and crop["x1"] == pytest.approx(23.0, abs=0.1)
    assert crop["y0"] == pytest.approx(27.0, abs=0.1) and crop["y1"] == pytest.approx(33.0, abs=0.1)
    assert (
        ortho_crop(Orthomosaic(grid, rgba, np.zeros((1000, 1000), int), ["a"]), 200.0, 30.0, 3.0)
        is None
    )


def test_script_json_cannot_close_its_script_element() -> None:
    from canopy_kit.report.html import script_json

    text = script_json({"flag": "</script><script>alert(1)</script>", "a&b": 1})
    assert "</" not in text and "<" not in text
    assert json.loads(text) == {"flag": "</script><script>alert(1)</script>", "a&b": 1}


def test_the_vendored_files_are_those_of_the_pinned_tarball() -> None:
    """scripts/vendor_js.py records each file's hash as unpacked from the integrity-checked
    tarball: an edited or truncated vendored file fails here."""
    import hashlib
    from importlib.resources import files

    from canopy_kit.report.assets import plotly_js, vendored

    record = vendored()["plotly.js-dist-min"]
    assert record["integrity"].startswith("sha512-") and record["version"] in record["tarball"]
    vendor = files("canopy_kit.report").joinpath("vendor")  # as installed: package data
    for name, digest in record["files"].items():
        assert hashlib.sha256(vendor.joinpath(name).read_bytes()).hexdigest() == digest, name
    assert "MIT License" in vendor.joinpath("plotly.LICENSE.txt").read_text()
    assert "</script" not in plotly_js()


def _marker_position(page, tree_id: str) -> tuple[float, float]:
    """Where the map draws ``tree_id``'s marker, in page pixels (from plotly's own axes)."""
    return tuple(
        page.evaluate(
            """id => {
        const gd = document.getElementById('map'), fl = gd._fullLayout, r = gd.getBoundingClientRect();
        const tr = gd.data.find(t => t.meta && t.meta.markers);
        const k = tr.customdata.indexOf(id);
        return [r.left + fl._size.l + fl.xaxis.l2p(tr.x[k]), r.top + fl._size.t + fl.yaxis.l2p(tr.y[k])];
    }""",
            tree_id,
        )
    )


@pytest.mark.browser
def test_interactive_report_works_offline_and_matches_trees_csv(tiny_pistachio_run) -> None:
    from playwright.sync_api import sync_playwright

    from canopy_kit.report.browser import CHROMIUM_ARGS, find_chromium

    run = tiny_pistachio_run
    path = Path(run.files["report.html"])
    # The run's table at full precision (trees.csv holds it rounded to its meaning).
    trees = pd.read_parquet(run.out_dir / "trees.parquet")
    page_url = path.resolve().as_uri()
    requests: list[str] = []
    blocked: list[str] = []
    errors: list[str] = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=find_chromium(), args=CHROMIUM_ARGS, headless=True
        )
        page = browser.new_page(viewport={"width": 1400, "height": 1000})

        def route(r):
            url = r.request.url
            requests.append(url)
            if url == page_url or url.startswith(ALLOWED):
                return r.continue_()
            blocked.append(url)
            return r.abort()

        page.route("**/*", route)
        page.on("request", lambda r: requests.append(r.url))
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(page_url, wait_until="load")
        page.wait_for_function("window.canopyReport !== undefined")

        # The header: named after the orchard, every provenance key of metrics.json shown.
        provenance = json.loads((run.out_dir / "metrics.json").read_text())["provenance"]
        assert page.title() == f"canopy-kit report: {provenance['orchard']}"
        shown = dict(
            zip(
                page.locator("#provenance dt").all_inner_texts(),
                page.locator("#provenance dd").all_inner_texts(),
                strict=True,
            )
        )
        assert shown["bag sha256"] == provenance["bag_sha256"]
        assert len(shown) == len(provenance) and shown["drone images"] == "none"

        # The map: one crown polygon and one marker per tree, named by trees.csv's tree_id.
        crowns = page.evaluate(
            "document.getElementById('map').data.filter(t => t.meta && t.meta.crown)"
            ".map(t => t.meta.crown)"
        )
        markers = page.evaluate(
            "document.getElementById('map').data.find(t => t.meta && t.meta.markers).customdata"
        )
        assert sorted(crowns) == sorted(trees["tree_id"]) and sorted(markers) == sorted(
            trees["tree_id"]
        )
        page.locator("#explore").scroll_into_view_if_needed()
        page.screenshot(path=str(ARTIFACTS / "report_interactive_map.png"))

        # Clicking a tree on the map opens its drill-down, whose numbers are trees.csv's.
        tree = trees.iloc[len(trees) // 2]
        page.locator("#map").scroll_into_view_if_needed()
        x, y = _marker_position(page, tree["tree_id"])
        page.mouse.move(x, y)  # as a hand would: plotly reports the click on what it hovers
        page.mouse.click(x, y)
        summary = page.locator("#drill-summary")
        assert summary.get_attribute("data-tree") == tree["tree_id"]
        assert int(summary.get_attribute("data-points")) == int(tree["n_points"])
        shown = float(
            page.locator("#drill-values td[data-key='volume_alpha_m3']").get_attribute("data-v")
        )
        assert shown == pytest.approx(tree["volume_alpha_m3"], rel=1e-9)
        surfaces = page.evaluate(
            f"window.canopyReport.data.details['{tree['tree_id']}'].surfaces"
            ".map(s => [s.name, s.volume_m3])"
        )
        volumes = {name.split(" (")[0]: v for name, v in surfaces}
        assert volumes["alpha shape"] == pytest.approx(tree["volume_alpha_m3"], rel=1e-9)
        assert volumes["convex hull"] == pytest.approx(tree["volume_convex_hull_m3"], rel=1e-9)
        n_drawn = page.evaluate("document.getElementById('drill-3d').data[0].x.length")
        assert 0 < n_drawn <= min(2000, int(tree["n_points"]))
        page.wait_for_timeout(300)
        page.locator("#drill").screenshot(path=str(ARTIFACTS / "report_interactive_drilldown.png"))

        # Search: typing a tree_id leaves that tree's row only.
        target = trees["tree_id"].iloc[-1]
        page.fill("#tree-search", target)
        visible = page.eval_on_selector_all(
            "#trees tbody tr",
            "rs => rs.filter(r => r.style.display !== 'none').map(r => r.dataset.id)",
        )
        assert visible == [target]
        assert page.locator("#tree-count").inner_text() == f"1 of {len(trees)} trees shown"
        page.fill("#tree-search", "")
        assert page.locator("#trees tbody tr:visible").count() == len(trees)

        # Sorting a numeric column orders it by value; a click on a row opens that tree.
        page.locator("#trees th[data-key='volume_alpha_m3']").click()
        col = int(page.locator("#trees th[data-key='volume_alpha_m3']").get_attribute("data-col"))
        values = page.eval_on_selector_all(
            f"#trees tbody tr td:nth-child({col + 1})",
            "els => els.map(e => parseFloat(e.dataset.v))",
        )
        assert values == pytest.approx(sorted(trees["volume_alpha_m3"]))
        smallest = trees.loc[trees["volume_alpha_m3"].idxmin(), "tree_id"]
        page.locator("#trees tbody tr").first.click()
        assert summary.get_attribute("data-tree") == smallest
        page.evaluate("document.getElementById('tree-search').scrollIntoView()")
        page.screenshot(path=str(ARTIFACTS / "report_interactive_table.png"))

        # Downloads are Blobs of the embedded files, each byte for byte the file the run wrote.
        names = page.eval_on_selector_all(
            "#downloads a", "as => as.map(a => [a.dataset.name, a.href])"
        )
        assert [n for n, _ in names] == [
            "trees.csv",
            "trees.geojson",
            "crowns.geojson",
            "rows.geojson",
        ]
        assert all(href.startswith("blob:") for _, href in names)
        for name, href in names:
            embedded = page.evaluate("href => fetch(href).then(r => r.text())", href)
            assert embedded == (run.out_dir / name).read_text(), name

        # The recommended estimator's volume leads: the map's colours and the histogram.
        from canopy_kit.config import load_preset
        from canopy_kit.report.columns import COLUMN_LABELS
        from canopy_kit.volume.verb import volume_column

        lead = COLUMN_LABELS[
            volume_column(load_preset(run.out_dir / "config.toml").volume.recommended)
        ]
        assert page.locator("#map-colour option").first.text_content() == lead.replace(" [m³]", "")
        assert page.evaluate("document.getElementById('hist').data[0].name") == lead

        # Colouring by flag redraws the map with the same trees.
        page.select_option("#map-colour", "flag")
        again = page.evaluate(
            "document.getElementById('map').data.filter(t => t.meta && t.meta.crown).length"
        )
        assert again == len(trees)
        browser.close()
    assert blocked == []
    assert all(u == page_url or u.startswith(ALLOWED) for u in requests), requests
    assert errors == []


def test_header_shows_every_provenance_key_present() -> None:
    from canopy_kit.report import render_report

    trees = pd.DataFrame({"tree_id": ["r0-L0"], "volume_alpha_m3": [12.5]})
    provenance = {"orchard": "Block 7", "bag_sha256": "9f" * 32, "run_seconds": 81.5}
    page = render_report("t", {}, trees, [], [], "", provenance=provenance)
    for key, value in provenance.items():
        assert f"<dt>{key.replace('_', ' ')}</dt><dd>{value}</dd>" in page
    assert 'id="provenance"' not in render_report("t", {}, trees, [], [], "")
    assert ">Alpha-shape volume [m³]</th>" in page  # human headers, trees.csv's name in the tooltip
    assert 'title="volume_alpha_m3"' in page and 'data-id="r0-L0"' in page


def test_row_summary_counts_sums_and_flags_per_row() -> None:
    from canopy_kit.report.explorer import row_summary

    trees = pd.DataFrame(
        {
            "row": [0, 0, 0, 1],
            "volume_alpha_m3": [1.0, 3.0, 8.0, np.nan],
            "volume_flags": ["", "alpha_shape: too few points", None, ""],
            "aerial_flag": ["", "", "", "aerial crown merged with neighbours"],
        }
    )
    rows = row_summary(trees)
    assert rows["row"].tolist() == [0, 1] and rows["trees"].tolist() == [3, 1]
    assert rows["median_m3"].iloc[0] == 3.0 and rows["total_m3"].iloc[0] == 12.0
    assert np.isnan(rows["median_m3"].iloc[1]) and np.isnan(rows["total_m3"].iloc[1])
    assert rows["flagged"].tolist() == [1, 1]
    assert row_summary(trees.drop(columns="row")).empty


@pytest.fixture(scope="module")
def tiny_drone_run(tiny_drone_session, tmp_path_factory):
    """A 2-row x 3-tree pistachio session with a drone flight (seed 4), run with its photos
    (the session and the run's stages shared with the other files that use them)."""
    return tiny_drone_session.run_into(tmp_path_factory.mktemp("drone_run"))


@pytest.mark.slow
@pytest.mark.browser
def test_drill_down_shows_the_drone_crop_around_the_tree(tiny_drone_run) -> None:
    from playwright.sync_api import sync_playwright

    from canopy_kit.report.browser import CHROMIUM_ARGS, find_chromium

    run = tiny_drone_run
    trees = pd.read_parquet(run.out_dir / "trees.parquet")  # trees.csv: rounded
    assert trees["aerial_sphere_volume_m3"].notna().any()
    url = Path(run.files["report.html"]).resolve().as_uri()
    errors: list[str] = []
    outside: list[str] = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=find_chromium(), args=CHROMIUM_ARGS, headless=True
        )
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        page.on(
            "request",
            lambda r: (
                outside.append(r.url) if not (r.url == url or r.url.startswith(ALLOWED)) else None
            ),
        )
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(url, wait_until="load")
        page.wait_for_function("window.canopyReport !== undefined")
        for tree in trees.itertuples():
            page.evaluate("id => window.canopyReport.showTree(id)", tree.tree_id)
            image = page.evaluate("document.getElementById('drill-ortho').layout.images[0]")
            assert image["source"].startswith("data:image/jpeg;base64,")
            # The crop is centred on the tree (in the map's frame) and holds its crown.
            half = max(tree.crown_diameter_m / 2, 1.0) + 1.5
            assert image["x"] == pytest.approx(tree.x - half, abs=0.2)
            assert image["x"] + image["sizex"] == pytest.approx(tree.x + half, abs=0.2)
            assert image["y"] == pytest.approx(tree.y + half, abs=0.2)
            shown = page.locator("#drill-values td[data-key='aerial_sphere_volume_m3']")
            if not np.isnan(tree.aerial_sphere_volume_m3):
                assert float(shown.get_attribute("data-v")) == pytest.approx(
                    tree.aerial_sphere_volume_m3
                )
        assert page.locator("#drill-ortho image").count() == 1  # drawn, not only configured
        page.locator("#drill").screenshot(
            path=str(ARTIFACTS / "report_interactive_drilldown_drone.png")
        )
        browser.close()
    assert outside == [] and errors == []


def _explorer(trees: pd.DataFrame) -> dict:
    """Explorer data for ``trees`` without a run: square crowns, no points or surfaces."""
    from canopy_kit.report.explorer import _flagged, column_specs, json_records

    square = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    return {
        "trees": json_records(trees),
        "columns": column_specs(trees),
        "flagged": [bool(f) for f in _flagged(trees)],
        "map": {
            "footprints": {t.tree_id: (square + [t.x, t.y]).tolist() for t in trees.itertuples()},
            "rows": [],
            "drive": [],
        },
        "details": {},
        "downloads": [{"name": "trees.csv", "mime": "text/csv", "text": trees.to_csv()}],
    }


@pytest.mark.browser
@pytest.mark.parametrize("n_trees", [0, 2])
def test_a_run_with_no_or_unmeasured_trees_still_renders_without_errors(tmp_path, n_trees) -> None:
    """A failed run is the one that must still be read: no trees at all, or a tree whose
    volumes are missing (NaN) and flagged."""
    from playwright.sync_api import sync_playwright

    from canopy_kit.report import render_report
    from canopy_kit.report.browser import CHROMIUM_ARGS, find_chromium

    trees = pd.DataFrame(
        {
            "tree_id": ["r0-L0", "r0-L1"],
            "row": [0, 0],
            "x": [0.0, 5.0],
            "y": [0.0, 0.0],
            "crown_diameter_m": [2.0, np.nan],
            "volume_alpha_m3": [12.0, np.nan],
            "volume_flags": ["", "alpha_shape: qhull could not triangulate the points"],
            "segment_flags": ["", ""],
        }
    ).head(n_trees)
    path = tmp_path / "report.html"
    path.write_text(render_report("t", {}, trees, [], [], "", explorer=_explorer(trees)))
    errors: list[str] = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=find_chromium(), args=CHROMIUM_ARGS, headless=True
        )
        page = browser.new_page()
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(path.as_uri(), wait_until="load")
        page.wait_for_function("window.canopyReport !== undefined")
        page.select_option("#map-colour", "flag")
        crowns = page.evaluate(
            "document.getElementById('map').data.filter(t => t.meta && t.meta.crown).length"
        )
        title = page.locator("#drill-title").inner_text()
        browser.close()
    assert errors == []
    assert crowns == n_trees
    # The drill-down opens on the flagged tree, even with nothing measured.
    assert title == ("Tree r0-L1" if n_trees else "Tree drill-down")
