"""Every registered volume plugin honours one contract; bad input is flagged or refused
with a message that names what is wrong; the verb, the metrics and the CLI."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from cli_server import CliServer

from canopy_kit import plugins
from canopy_kit.errors import ConfigError, InputError, PluginError
from canopy_kit.volume import VolumeResult, estimate_volume, estimator, sphere_volume, tree_metrics
from canopy_kit.volume.base import VolumeEstimator

BUILT_IN = {
    "convex_hull",
    "alpha_shape",
    "alpha_hull",
    "alpha_auto",
    "adaptive_alpha",
    "voxel",
    "slices",
    "mirror",
}


def blob(n: int = 3000, seed: int = 0) -> np.ndarray:
    """A crown-like cloud: points in an ellipsoid of 2 x 1.8 x 1.5 m around (0, 0, 2.5)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * rng.uniform(0, 1, (n, 1)) ** (1 / 3) * [2.0, 1.8, 1.5] + [0, 0, 2.5]


DEGENERATE = {
    "empty": (np.zeros((0, 3)), "too few points: 0"),
    "three points": (np.eye(3), "too few points: 3"),
    "identical": (np.ones((10, 3)), "all 10 points are identical"),
    "collinear": (np.outer(np.arange(20.0), [1.0, 2.0, 0.5]), "all 20 points are collinear"),
    "coplanar": (
        np.column_stack([np.random.default_rng(1).uniform(0, 3, (50, 2)), np.full(50, 1.7)]),
        "all 50 points are coplanar",
    ),
    "tilted plane": (
        np.random.default_rng(2).uniform(0, 3, (60, 2)) @ [[1.0, 0, 0.3], [0, 1, -0.2]]
        + [5e5, 4e6, 90.0],
        "all 60 points are coplanar",
    ),
}


def test_built_in_volume_plugins_are_registered() -> None:
    assert BUILT_IN <= set(plugins.names("volumes"))


@pytest.mark.parametrize("name", plugins.names("volumes"))
def test_every_volume_plugin_honours_the_contract(name: str) -> None:
    target = plugins.load("volumes", name)
    est = target()
    assert isinstance(est, VolumeEstimator) and est.name == name
    assert repr(est).startswith(type(est).__name__ + "(")
    pts = blob()
    result = est(pts)
    assert isinstance(result, VolumeResult)
    assert result.method == name and result.params == est.get_params()
    assert result.valid and result.reason is None and result.n_points == len(pts)
    assert np.isfinite(result.volume_m3) and 0 < result.volume_m3 < 30
    json.dumps(result.as_dict())
    # deterministic, and the input is not modified
    copy = pts.copy()
    assert est(pts).volume_m3 == result.volume_m3
    np.testing.assert_array_equal(pts, copy)
    # translation invariance (large projected coordinates included), within 1 %
    shifted = est(pts + [631_000.0, 4_127_000.0, 85.0])
    assert shifted.volume_m3 == pytest.approx(result.volume_m3, rel=0.01)
    # a PointCloud is accepted as well as an array
    from canopy_kit.core.cloud import PointCloud

    assert est(PointCloud(pts)).volume_m3 == result.volume_m3


@pytest.mark.parametrize("name", plugins.names("volumes"))
@pytest.mark.parametrize("case", DEGENERATE)
def test_degenerate_input_is_flagged_not_measured(name: str, case: str) -> None:
    pts, reason = DEGENERATE[case]
    result = plugins.load("volumes", name)()(pts)
    assert result.valid is False
    assert result.volume_m3 == 0.0
    assert reason in result.reason


@pytest.mark.parametrize("name", plugins.names("volumes"))
def test_non_finite_coordinates_are_refused_by_name(name: str) -> None:
    pts = blob(200)
    pts[17, 1] = np.nan
    pts[150, 2] = np.inf
    with pytest.raises(
        InputError,
        match=r"xyz: 2 of 200 points have NaN or infinite "
        r"coordinates \(first at row 17\)",
    ):
        plugins.load("volumes", name)()(pts)


@pytest.mark.parametrize("bad", [np.zeros((10, 2)), np.zeros(12), [[1, 2, "x"]], "points"])
def test_wrong_shapes_are_refused(bad: object) -> None:
    with pytest.raises(InputError, match=r"^xyz: expected an \(N, 3\) array"):
        estimate_volume(bad, "convex_hull")


def test_init_does_no_work_and_bad_parameters_name_themselves() -> None:
    est = estimator("alpha_shape", alpha=-1.0)  # constructing never fails...
    with pytest.raises(
        ConfigError, match=r"^alpha_shape: alpha must be a positive number, got -1.0"
    ):
        est(blob())  # ...calling checks
    with pytest.raises(ConfigError, match=r"^slices: area must be one of \['hull', 'alpha'\]"):
        estimate_volume(blob(), "slices", area="circle")
    with pytest.raises(ConfigError, match=r"^alpha_hull: grid_step must be a positive number"):
        estimate_volume(blob(), "alpha_hull", grid_step=0)
    with pytest.raises(ConfigError, match=r"^mirror: plane_point must be two finite numbers"):
        estimate_volume(blob(), "mirror", plane_point=(1.0, np.nan))
    with pytest.raises(
        ConfigError, match=r"^voxel: voxel_size must be a positive number, got True"
    ):
        estimate_volume(blob(), "voxel", voxel_size=True)
    with pytest.raises(ConfigError, match=r"^adaptive_alpha: offset_factor must be a number >= 0"):
        estimate_volume(blob(), "adaptive_alpha", offset_factor=-0.1)
    with pytest.raises(ConfigError, match=r"^adaptive_alpha: alpha_min \(2.0\) must not exceed"):
        estimate_volume(blob(), "adaptive_alpha", alpha_min=2.0, alpha_max=1.0)


def test_the_verb_loads_plugins_by_name() -> None:
    pts = blob()
    assert estimate_volume(pts).method == "alpha_shape"
    assert estimate_volume(pts, "alpha_shape").params == {"alpha": 0.9}
    assert estimate_volume(pts, "alpha_shape", alpha=1.5).params == {"alpha": 1.5}
    with pytest.raises(PluginError, match=r"no volumes plugin named 'sphere' \(registered: "):
        estimate_volume(pts, "sphere")
    with pytest.raises(
        ConfigError,
        match=r"volume method 'voxel' has no parameter 'alpha' "
        r"\(parameters: voxel_size, fill_holes\)",
    ):
        estimate_volume(pts, "voxel", alpha=0.9)


def test_alpha_methods_order_between_nothing_and_the_hull() -> None:
    pts = blob(5000)
    hull = estimate_volume(pts, "convex_hull").volume_m3
    for alpha in (0.3, 0.9, 3.0):
        assert 0 < estimate_volume(pts, "alpha_shape", alpha=alpha).volume_m3 <= hull * (1 + 1e-9)
    # a huge α keeps every tetrahedron but flat hull slivers: the convex hull
    assert estimate_volume(pts, "alpha_shape", alpha=100.0).volume_m3 == pytest.approx(
        hull, rel=1e-5
    )
    assert estimate_volume(pts, "alpha_hull", alpha=8.0).volume_m3 == pytest.approx(hull, rel=0.02)


def test_voxel_hole_filling_fills_closed_rings_only() -> None:
    # a closed cylindrical shell, 2 m tall, radius 1 m, sampled densely
    t = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    z = np.arange(0.05, 2.0, 0.05)
    tt, zz = np.meshgrid(t, z)
    shell = np.column_stack([np.cos(tt.ravel()), np.sin(tt.ravel()), zz.ravel()])
    filled = estimate_volume(shell, "voxel", voxel_size=0.05, fill_holes=True)
    empty = estimate_volume(shell, "voxel", voxel_size=0.05, fill_holes=False)
    assert filled.volume_m3 == pytest.approx(np.pi * 1.0**2 * 1.95, rel=0.05)
    assert empty.volume_m3 < 0.2 * filled.volume_m3
    assert filled.extra["filled_voxels"] > 0 == empty.extra["filled_voxels"]
    # open rings (half the cylinder) are not filled
    half = shell[shell[:, 0] > 0]
    assert estimate_volume(half, "voxel", voxel_size=0.05).extra["filled_voxels"] == 0


def test_slices_of_a_cylinder() -> None:
    rng = np.random.default_rng(3)
    n = 20000
    r = np.sqrt(rng.uniform(0, 1, n))
    t = rng.uniform(0, 2 * np.pi, n)
    pts = np.column_stack([r * np.cos(t), r * np.sin(t), rng.uniform(0, 2, n)])
    hull_slices = estimate_volume(pts, "slices", thickness=0.25)
    assert hull_slices.volume_m3 == pytest.approx(2 * np.pi, rel=0.03)
    assert hull_slices.extra["n_slices"] == 8
    alpha_slices = estimate_volume(pts, "slices", thickness=0.25, area="alpha", alpha=0.5)
    assert alpha_slices.volume_m3 == pytest.approx(hull_slices.volume_m3, rel=0.03)


def test_tree_metrics_of_a_cylinder_crown_on_a_trunk() -> None:
    rng = np.random.default_rng(4)
    # trunk: radius 0.1 m from ground (z = 10) to 11 m; crown: cylinder radius 1.5 m, 11-13 m
    n = 20000
    r = 1.5 * np.sqrt(rng.uniform(0, 1, n))
    t = rng.uniform(0, 2 * np.pi, n)
    crown = np.column_stack([r * np.cos(t), r * np.sin(t), rng.uniform(11, 13, n)])
    t2 = rng.uniform(0, 2 * np.pi, 2000)
    trunk = np.column_stack([0.1 * np.cos(t2), 0.1 * np.sin(t2), rng.uniform(10.2, 11, 2000)])
    pts = np.concatenate([trunk, crown])
    m = tree_metrics(pts, ground_z=10.0)
    assert m.n_points == 22000
    assert m.height_m == pytest.approx(3.0, abs=0.01)
    assert m.crown_base_height_m == pytest.approx(1.0, abs=0.1)
    assert m.crown_diameter_max_m == pytest.approx(3.0, abs=0.02)
    assert m.crown_diameter_mean_m == pytest.approx(3.0, abs=0.03)
    assert m.projected_area_m2 == pytest.approx(np.pi * 1.5**2, rel=0.01)
    assert m.sphere_volume_m3 == pytest.approx(sphere_volume(m.crown_diameter_max_m))
    assert m.density_per_m3 == pytest.approx(22000 / estimate_volume(pts, "convex_hull").volume_m3)
    # without a ground height the lowest point is the ground
    assert tree_metrics(pts).height_m == pytest.approx(np.ptp(pts[:, 2]))
    # an elongated crown: mean of the widest extent and the one perpendicular to it
    box = rng.uniform([-2, -1, 0], [2, 1, 1], (5000, 3))
    mb = tree_metrics(box)
    assert mb.crown_diameter_max_m == pytest.approx(np.hypot(4, 2), abs=0.05)
    widest = mb.crown_diameter_max_m
    across = 2 * 4 * 2 / np.hypot(4, 2)  # the box's extent perpendicular to its diagonal
    assert mb.crown_diameter_mean_m == pytest.approx(0.5 * (widest + across), abs=0.05)


def test_sphere_volume() -> None:
    assert sphere_volume(2.0) == pytest.approx(4 / 3 * np.pi)


def _cli(cli: CliServer, *args: str) -> subprocess.CompletedProcess[str]:
    """``canopy-kit args`` on the module's command server (conftest.py ``cli_server``)."""
    return cli.run(list(args), timeout=120)


def test_cli_volume_json_and_errors(cli_server, tmp_path: Path) -> None:
    from canopy_kit.core.cloud import PointCloud
    from canopy_kit.io.clouds import write_cloud

    pts = blob(2000)
    path = write_cloud(tmp_path / "tree.ply", PointCloud(pts))
    out = _cli(
        cli_server, "volume", str(path), "--method", "alpha_shape", "--alpha", "1.2", "--json"
    )
    assert out.returncode == 0, out.stderr
    data = json.loads(out.stdout)
    expected = estimate_volume(pts, "alpha_shape", alpha=1.2).volume_m3
    assert data["method"] == "alpha_shape" and data["params"] == {"alpha": 1.2}
    assert data["volume_m3"] == pytest.approx(expected, rel=1e-6) and data["valid"] is True
    assert data["metrics"]["n_points"] == 2000 and data["warnings"] == []
    human = _cli(cli_server, "volume", str(path), "-m", "convex_hull")
    assert human.returncode == 0 and "m³ by convex_hull" in human.stdout
    bad = _cli(cli_server, "volume", str(path), "-m", "voxel", "--alpha", "0.9")
    assert bad.returncode == 2
    assert "volume method 'voxel' has no parameter 'alpha'" in bad.stderr
    missing = _cli(cli_server, "volume", str(tmp_path / "nope.las"))
    assert missing.returncode == 2 and "file does not exist" in missing.stderr
    unknown = _cli(cli_server, "volume", str(path), "-m", "sphere")
    assert unknown.returncode == 2 and "no volumes plugin named 'sphere'" in unknown.stderr


def test_alpha_hull_flags_clouds_too_sparse_for_the_grid_formulation() -> None:
    sparse = blob(150)
    result = estimate_volume(sparse, "alpha_hull")
    assert not result.valid and result.volume_m3 > 0
    assert result.reason.startswith("points too sparse for the alpha hull: median spacing")
    assert "use alpha_shape" in result.reason and result.extra["spacing_ratio"] > 0.2
    assert estimate_volume(blob(20000), "alpha_hull").extra["spacing_ratio"] < 0.2


def test_tree_metrics_refuse_empty_input_and_bad_parameters() -> None:
    with pytest.raises(InputError, match="xyz: a tree needs at least one point"):
        tree_metrics(np.zeros((0, 3)))
    with pytest.raises(ConfigError, match="crown_fraction must be in"):
        tree_metrics(blob(100), crown_fraction=1.5)
    one = tree_metrics(np.array([[1.0, 2.0, 3.0]]))
    assert one.height_m == 0 and one.crown_diameter_max_m == 0 and np.isnan(one.density_per_m3)


def test_alpha_hull_gap_to_the_complex_grows_with_the_spacing() -> None:
    from scipy.spatial import cKDTree

    gaps = {}
    for n in (200, 3000):
        rng = np.random.default_rng(5)
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        pts = d * 2.0 * rng.uniform(0, 1, (n, 1)) ** 0.25
        ratio = np.median(cKDTree(pts).query(pts, k=2)[0][:, 1]) / 0.9
        gap = estimate_volume(pts, "alpha_hull").volume_m3 / estimate_volume(pts).volume_m3 - 1
        gaps[n] = (ratio, gap)
    assert gaps[3000][0] < 0.16 and -0.03 < gaps[3000][1] < 0
    assert gaps[200][0] > 0.3 and gaps[200][1] < -0.1


def test_cli_volume_warns_when_the_file_holds_several_trees_or_ground(
    cli_server, tmp_path: Path
) -> None:
    """Two labelled crowns over a ground plane (class 2) in one LAS file: the volume is still
    computed, and the user is told the file is not one tree, naming the field and the ground."""
    from canopy_kit.core.cloud import PointCloud
    from canopy_kit.io.las_write import write_las

    rng = np.random.default_rng(3)
    crowns = np.vstack([blob(1500), blob(1500) + [6.0, 0.0, 0.0]])
    ground = np.column_stack([rng.uniform(-3, 9, (600, 2)), np.full(600, -3.0)])
    xyz = np.vstack([crowns, ground])
    fields = {
        "segment_id": np.r_[np.zeros(1500), np.ones(1500), -np.ones(600)].astype(np.int32),
        "classification": np.r_[np.ones(3000), np.full(600, 2)].astype(np.uint8),
    }
    path = write_las(tmp_path / "plot.las", PointCloud(xyz, fields))
    out = _cli(cli_server, "volume", str(path), "--json")
    assert out.returncode == 0, out.stderr
    (warning,) = [w for w in json.loads(out.stdout)["warnings"] if "may not be one tree" in w]
    assert "its segment_id field labels 2 trees" in warning
    assert "600 of its 3,600 points (17 %) are classified ground" in warning
    human = _cli(cli_server, "volume", str(path))
    assert "warning:" in human.stdout and "cut one tree out first" in human.stdout
