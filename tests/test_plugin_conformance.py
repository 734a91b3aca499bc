"""One contract for every plugin (issue 28): the conformance suite of ``canopy_kit.testing``
over every registered segmenter and volume estimator, a third-party pair registered through
a test entry point, broken plugins failing with the rule they break, ``plugins.create`` and
``plugins.parameters``, preset parameters checked before a run, and ``plugins --params``."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import pytest
from annotated_types import Ge

from canopy_kit import plugins
from canopy_kit.errors import ConfigError, InputError
from canopy_kit.plugins.params import NonNegative, Positive, check_positive
from canopy_kit.segment.base import Segmenter, check_points
from canopy_kit.testing import (
    check_segmenter,
    check_volume_estimator,
    parametrize_with_checks,
    unit_cube,
)
from canopy_kit.volume.base import VolumeEstimator, VolumeResult

BUILT_IN = [
    plugins.load(kind, name) for kind in ("segmenters", "volumes") for name in plugins.names(kind)
]


# -- a third-party segmenter and volume estimator -------------------------------------------
class GapSegmenter(Segmenter):
    """Trees are runs of points along x separated by gaps wider than ``gap``.

    Parameters
    ----------
    gap : float, default 1.0
        Gap (m) along x that separates two trees.
    min_points : int, default 5
        Runs with fewer points are noise (-1).
    """

    def __init__(self, gap: float = 1.0, min_points: int = 5) -> None:
        self.gap = gap
        self.min_points = min_points

    def validate_params(self) -> None:
        check_positive(self.gap, "gap", "GapSegmenter")
        check_positive(self.min_points, "min_points", "GapSegmenter")
        super().validate_params()

    def fit(self, X: np.ndarray, y: None = None) -> GapSegmenter:
        self.validate_params()
        xyz = check_points(X)
        order = np.argsort(xyz[:, 0], kind="stable")
        run = np.concatenate([[0], np.cumsum(np.diff(xyz[order, 0]) > self.gap)]).astype(np.int64)
        sizes = np.bincount(run) if len(run) else np.zeros(0, np.int64)
        keep = np.flatnonzero(sizes >= self.min_points)
        new = np.full(len(sizes), -1, np.int64)
        new[keep] = np.arange(len(keep))
        self.labels_ = np.empty(len(xyz), np.int64)
        self.labels_[order] = new[run]
        self.n_clusters_ = len(keep)
        return self


class BoxVolume(VolumeEstimator):
    """Volume of the axis-aligned bounding box, grown by ``margin`` on every side.

    Parameters
    ----------
    margin : float, default 0.0
        Added to every side of the box (m), >= 0.
    """

    name = "toy_box"
    measures = "the axis-aligned bounding box of the points, grown by the margin"
    convex_rtol = 1e-9  # exact on an axis-aligned box

    def __init__(self, margin: float = 0.0) -> None:
        self.margin = margin

    def validate_params(self) -> None:
        super().validate_params()  # types first: "x" is named before it is compared
        if self.margin < 0:
            raise ConfigError(f"{self.name}: margin must be >= 0, got {self.margin!r}")

    def _volume(self, xyz: np.ndarray) -> float:
        return float(np.prod(np.ptp(xyz, axis=0) + 2 * self.margin))


# -- broken plugins, one broken rule each -----------------------------------------------------
class WorkInInitSegmenter(GapSegmenter):
    """Converts its parameter and prepares state in ``__init__``."""

    def __init__(self, gap: float = 1.0, min_points: int = 5) -> None:
        self.gap = float(gap)
        self.min_points = min_points
        self.history_: list[int] = []


class ShortLabelsSegmenter(GapSegmenter):
    """Drops the last point's label."""

    def fit(self, X: np.ndarray, y: None = None) -> ShortLabelsSegmenter:
        super().fit(X)
        self.labels_ = self.labels_[:-1]
        return self


class FloatVolume(BoxVolume):
    """Returns a bare float instead of a VolumeResult."""

    def __call__(self, xyz: object) -> float:  # type: ignore[override]
        return super().__call__(xyz).volume_m3


class UnstatedVolume(BoxVolume):
    """Does not say what volume it measures."""

    measures = ""


class UncheckedVolume(BoxVolume):
    """Never checks its parameter."""

    def validate_params(self) -> None:
        pass


@pytest.fixture
def toy_plugins(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Register GapSegmenter and BoxVolume like an installed package would: a dist-info
    folder with entry_points.txt on sys.path."""
    dist = tmp_path / "canopy_toy_plugins-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: canopy-toy-plugins\nVersion: 0.1\n"
    )
    (dist / "entry_points.txt").write_text(
        f"[canopy_kit.segmenters]\ntoy_gap = {__name__}:GapSegmenter\n\n"
        f"[canopy_kit.volumes]\ntoy_box = {__name__}:BoxVolume\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))  # also invalidates importlib's caches
    clear = getattr(plugins.entry_points, "cache_clear", None)
    if clear is not None:
        clear()


# -- the suite over every registered plugin ---------------------------------------------------
def test_every_registered_plugin_is_in_the_suite() -> None:
    names = {cls.__name__ for cls in BUILT_IN}
    assert {"DBSCANSegmenter", "AdaptiveSegmenter", "AlphaShapeVolume", "ConvexHullVolume"} <= names
    assert len(BUILT_IN) == len(plugins.names("segmenters")) + len(plugins.names("volumes"))


@parametrize_with_checks(BUILT_IN)
def test_registered_plugins_conform(estimator: object, check) -> None:
    check(estimator)


def test_parametrize_ids_name_plugin_and_rule() -> None:
    mark = parametrize_with_checks([plugins.load("volumes", "alpha_shape"), BoxVolume(margin=0.5)])
    ids = mark.kwargs["ids"]
    assert "AlphaShapeVolume-unit_cube" in ids
    assert "BoxVolume(margin=0.5)-coplanar_is_invalid" in ids
    assert len(ids) == len(set(ids)) == len(mark.args[1])


# -- a third-party package ---------------------------------------------------------------------
def test_third_party_plugins_are_reachable_and_conform(toy_plugins: None) -> None:
    assert "toy_gap" in plugins.names("segmenters") and "toy_box" in plugins.names("volumes")
    seg = plugins.create("segmenters", "toy_gap", {"gap": 0.5})
    assert type(seg) is GapSegmenter and seg.gap == 0.5
    check_segmenter(seg)
    check_segmenter(plugins.load("segmenters", "toy_gap"))
    box = plugins.create("volumes", "toy_box", {"margin": 0.0})
    check_volume_estimator(box)
    # the truth by hand: a 2 x 1 x 0.5 m box, grown by 0.25 m on every side
    result = plugins.create("volumes", "toy_box", {"margin": 0.25})(unit_cube() * [2.0, 1.0, 0.5])
    assert isinstance(result, VolumeResult) and result.volume_m3 == pytest.approx(2.5 * 1.5 * 1.0)
    assert result.method == "toy_box" and result.params == {"margin": 0.25}


def test_create_checks_keys_types_and_values(toy_plugins: None) -> None:
    with pytest.raises(
        ConfigError,
        match=r"segmenter 'toy_gap' has no parameter 'gapp' "
        r"\(parameters: gap, min_points\)",
    ):
        plugins.create("segmenters", "toy_gap", {"gapp": 1.0})
    with pytest.raises(ConfigError, match=r"toy_gap.gap: expected a number, got 'wide'"):
        plugins.create("segmenters", "toy_gap", {"gap": "wide"})
    with pytest.raises(ConfigError, match=r"min_points: expected an integer, got 2.5"):
        plugins.create("segmenters", "toy_gap", {"min_points": 2.5})
    with pytest.raises(ConfigError, match=r"GapSegmenter: gap must be a positive number, got -1"):
        plugins.create("segmenters", "toy_gap", {"gap": -1})
    with pytest.raises(ConfigError, match=r"toy_box: margin must be >= 0"):
        plugins.create("volumes", "toy_box", {"margin": -0.1})
    # the old factories are thin wrappers; volume.estimator still defers value checks
    from canopy_kit.segment.verb import make_segmenter
    from canopy_kit.volume import estimator

    assert type(make_segmenter("toy_gap", {"min_points": 3})) is GapSegmenter
    lazy = estimator("toy_box", margin=-1.0)
    with pytest.raises(ConfigError, match="margin"):
        lazy(unit_cube())


def test_parameters_come_from_signature_and_docstring(toy_plugins: None) -> None:
    gap, min_points = plugins.parameters("segmenters", "toy_gap")
    assert (gap.name, gap.type, gap.default) == ("gap", float, 1.0)
    assert gap.doc == "Gap (m) along x that separates two trees."
    assert (min_points.type_name, min_points.default) == ("int", 5)
    (alpha,) = plugins.parameters("volumes", "alpha_shape")
    assert alpha.type is float and alpha.default == 0.9 and "circumradius" in alpha.doc
    for kind in ("segmenters", "volumes"):
        for name in plugins.names(kind):
            for p in plugins.parameters(kind, name):
                assert p.doc, f"{kind} {name}: parameter {p.name} has no Parameters entry"


def test_preset_plugin_params_fail_before_mapping(toy_plugins: None) -> None:
    from canopy_kit.config import SegmentConfig, load_preset
    from canopy_kit.pipeline import check_settings

    with pytest.raises(ConfigError, match=r"segment\.params\.gap: expected a number, got 'wide'"):
        load_preset("pistachio", {"segment": {"method": "toy_gap", "params": {"gap": "wide"}}})
    with pytest.raises(ConfigError, match=r"volume\.params\.alpha_shape\.alpha: expected a number"):
        load_preset("pistachio", {"volume": {"params": {"alpha_shape": {"alpha": "big"}}}})
    config = load_preset("pistachio", {"volume": {"methods": ["toy_box"]}})
    config.segment = SegmentConfig("toy_gap", {"gapp": 1.0})
    with pytest.raises(
        ConfigError,
        match=r"segment.params: segmenter 'toy_gap' has no parameter "
        r"'gapp'",
    ):
        check_settings(config)
    config.segment = SegmentConfig("toy_gap", {"gap": 0})
    with pytest.raises(ConfigError, match="gap must be a positive number"):
        check_settings(config)
    config.segment = SegmentConfig("toy_gap", {"gap": 2})
    check_settings(config)
    config.volume.params["toy_box"] = {"margin": "wide"}
    with pytest.raises(ConfigError, match=r"volume.params.toy_box.margin: expected a number"):
        check_settings(config)


# -- broken plugins fail with the rule they break ---------------------------------------------
@pytest.mark.parametrize(
    ("broken", "rule", "check"),
    [
        (WorkInInitSegmenter, "init_stores_params", check_segmenter),
        (ShortLabelsSegmenter, "labels_one_per_point", check_segmenter),
        (FloatVolume, "result_is_volume_result", check_volume_estimator),
        (UncheckedVolume, "validate_params_rejects_wrong_type", check_volume_estimator),
        (UnstatedVolume, "says_what_it_measures", check_volume_estimator),
    ],
)
def test_broken_plugin_fails_naming_the_rule(broken: type, rule: str, check) -> None:
    with pytest.raises(AssertionError) as err:
        check(broken)
    message = str(err.value)
    assert f"rule {rule!r} broken by {broken.__name__}" in message
    assert "init_stores_params" not in message or rule == "init_stores_params"


def test_one_check_positive_for_every_plugin() -> None:
    from canopy_kit.segment import base as segment_base
    from canopy_kit.volume import base as volume_base

    assert segment_base.check_positive is volume_base.check_positive is check_positive
    with pytest.raises(ConfigError, match=r"^dbscan: eps must be a positive number, got 0"):
        check_positive(0, "eps", "dbscan")
    with pytest.raises(ConfigError, match="eps must be a positive number, got True"):
        check_positive(True, "eps")
    check_positive(None, "grid_step", allow_none=True)
    assert issubclass(ConfigError, InputError)


def test_cli_prints_each_parameter() -> None:
    from typer.testing import CliRunner

    from canopy_kit.cli import app

    out = CliRunner().invoke(app, ["plugins", "--params", "alpha_shape"])
    assert out.exit_code == 0, out.output
    (row,) = [line for line in out.output.splitlines() if line.startswith("alpha")]
    name, type_, default, meaning = row.split("\t")
    assert (name, type_, default) == ("alpha", "float, a positive number", "0.9")
    assert meaning.startswith("Radius (m): the solid is the union of the Delaunay tetrahedra")
    hull = CliRunner().invoke(app, ["plugins", "--params", "convex_hull"])
    assert hull.exit_code == 0 and "0 parameter(s)" in hull.output


def test_annotation_checks_and_docstring_sections() -> None:
    from collections.abc import Sequence
    from typing import Literal

    from canopy_kit.plugins.params import docstring_parameters, matches

    assert matches(3, float) and matches(np.float32(1.5), float) and matches(np.int64(3), int)
    assert not matches(True, float) and not matches(3.0, int) and not matches("0.9", float)
    assert matches(None, float | None) and not matches("x", float | None)
    assert matches([1, 2.5], tuple[float, float]) and not matches([1.0], tuple[float, float])
    assert matches(np.array([1.0, 2.0]), tuple[float, float]) and not matches("ab", Sequence[str])
    assert matches("grid", Literal["grid", "exact"]) and not matches("kd", Literal["grid"])
    doc = """Summary.

    Parameters
    ----------
    a, b : float
        First line
        second line.
    c : int

    Returns
    -------
    x : float
        Not a parameter.
    """
    assert docstring_parameters(doc) == {
        "a": "First line second line.",
        "b": "First line second line.",
        "c": "",
    }
    assert docstring_parameters("No sections.") == {}


def test_every_shipped_preset_passes_the_checks() -> None:
    from canopy_kit.config import load_preset, preset_names
    from canopy_kit.pipeline import check_settings

    for name in preset_names():
        check_settings(load_preset(name))


# -- ranges declared once, in the annotation ----------------------------------------------
@pytest.mark.parametrize(
    "kind, name", [(k, n) for k in ("segmenters", "volumes") for n in plugins.names(k)]
)
def test_every_declared_range_is_enforced_by_create(kind, name):
    """Each parameter whose annotation declares a range (Positive, NonNegative, ...) is
    refused by plugins.create just outside it, with a ConfigError naming the parameter."""
    from canopy_kit.plugins.params import constraints

    cls = plugins.load(kind, name)
    for param, found in constraints(cls).items():
        lows = [getattr(c, a) for c in found for a in ("gt", "ge") if hasattr(c, a)]
        outside = (lows[0] - 1.0) if lows else float("nan")
        with pytest.raises(ConfigError, match=param):
            plugins.create(kind, name, {param: outside})


class Ranged:
    """A plugin-like class whose ranges are declared in its annotations (module level, so
    that its string annotations resolve)."""

    def __init__(
        self,
        size: Positive = 1.0,
        margin: NonNegative | None = None,
        factor: Annotated[float, Ge(1)] = 1.0,
        mode: Literal["a", "b"] = "a",
    ) -> None:
        self.size, self.margin, self.factor, self.mode = size, margin, factor, mode


def test_constraints_read_from_the_annotation_and_shown_in_params():
    from canopy_kit.plugins.params import parameters_of, validate_types

    validate_types(Ranged(margin=0.0))  # 0 is allowed where >= 0, None where Optional
    cases = {
        "size": (0, "size must be a positive number, got 0"),
        "margin": (-0.1, "margin must be a number >= 0, got -0.1"),
        "factor": (0.5, "factor must be a number >= 1, got 0.5"),
        "mode": ("c", "mode must be one of ['a', 'b'], got 'c'"),
    }
    for param, (value, message) in cases.items():
        with pytest.raises(ConfigError, match=f"^ranged: {re.escape(message)}$"):
            validate_types(Ranged(**{param: value}), "ranged")
    with pytest.raises(ConfigError, match="size must be a positive number, got inf"):
        validate_types(Ranged(size=float("inf")))
    shown = {p.name: p.type_name for p in parameters_of(Ranged)}
    assert shown["size"] == "float, a positive number"
    assert shown["margin"] == "Optional[float], a number >= 0"


def test_a_run_builds_its_segmenter_once_and_segments_with_that_instance(tmp_path, monkeypatch):
    """pipeline.check_settings builds and validates the segmenter; the segment stage uses
    that instance (it is fitted), and no other is built (docs/ARCHITECTURE.md)."""
    from fixtures_sim import synthetic_orchard

    from canopy_kit.config import load_preset
    from canopy_kit.io.clouds import write_cloud
    from canopy_kit.pipeline import compute

    built: list[str] = []
    real = plugins.create

    def counting(kind, name, *args, **kwargs):
        if kind == "segmenters":
            built.append(name)
        return real(kind, name, *args, **kwargs)

    monkeypatch.setattr(plugins, "create", counting)
    orchard = synthetic_orchard(rows=1, trees_per_row=3)
    map_file = write_cloud(tmp_path / "map.laz", orchard.cloud)
    ctx, _ = compute(load_preset("adaptive"), map_file, tmp_path / "run", use_cache=False)
    assert built == ["adaptive"]
    assert hasattr(ctx.segmenter, "labels_")  # the instance the stage fitted
    assert ctx.segmentation.n_trees == 3  # the synthetic orchard's trees
