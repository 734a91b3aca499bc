"""Conformance suite for segmenter and volume-estimator plugins, shipped with the library.

Modelled on scikit-learn's ``utils.estimator_checks``: every rule of the plugin contract is a
named check. :func:`check_segmenter` and :func:`check_volume_estimator` run them all on a
plugin (a class, built with its defaults, or a configured instance) and raise one
AssertionError naming each broken rule; :func:`parametrize_with_checks` makes one pytest
test per (plugin, rule)::

    from canopy_kit.testing import parametrize_with_checks

    @parametrize_with_checks([MySegmenter, MyVolume(margin=0.1)])
    def test_my_plugins(estimator, check):
        check(estimator)

The truths the rules measure against are independent of the plugin: the volume of a unit
cube is 1 m³ (to ``convex_rtol`` for estimators that promise it), coplanar points enclose
nothing, labels are one per point.
"""

from __future__ import annotations

import json
import types
import typing
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from canopy_kit.errors import ConfigError, InputError
from canopy_kit.plugins.params import annotations, init_parameters

__all__ = [
    "Check",
    "check_segmenter",
    "check_volume_estimator",
    "checks_for",
    "parametrize_with_checks",
    "segmenter_checks",
    "volume_checks",
]

WRONG_TYPE = "not-a-number"
TRANSLATION_RTOL = 0.01


@dataclass(frozen=True)
class Check:
    """One named rule of the contract; calling it on a plugin raises AssertionError naming
    the rule when the plugin breaks it."""

    name: str
    func: Callable[[Any], None]

    def __call__(self, estimator: Any) -> None:
        try:
            self.func(_instance(estimator))
        except AssertionError as exc:
            message = f"rule {self.name!r} broken by {_label(estimator)}: {exc}"
            raise AssertionError(message) from exc
        except Exception as exc:  # a crash breaks the rule too
            raise AssertionError(
                f"rule {self.name!r} broken by {_label(estimator)}: raised "
                f"{type(exc).__name__}: {exc}"
            ) from exc

    def __repr__(self) -> str:
        return self.name


# -- data with known answers -----------------------------------------------------------------
def unit_cube(n: int = 9) -> np.ndarray:
    """A lattice of n³ points filling the unit cube, corners and faces included (1 m³)."""
    g = np.linspace(0.0, 1.0, n)
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)


def crown(n: int = 1500, seed: int = 0) -> np.ndarray:
    """Points filling an ellipsoid of semi-axes 2 x 1.8 x 1.5 m around (0, 0, 2.5)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * rng.uniform(0, 1, (n, 1)) ** (1 / 3) * [2.0, 1.8, 1.5] + [0, 0, 2.5]


def coplanar(n: int = 50, seed: int = 1) -> np.ndarray:
    """Points of a horizontal plane at 1.7 m (no volume)."""
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(0, 3, (n, 2)), np.full(n, 1.7)])


def blobs(n: int = 200, seed: int = 0) -> np.ndarray:
    """Three round blobs of ``n`` points each, 5 m apart along x (canopy-like points)."""
    rng = np.random.default_rng(seed)
    return np.concatenate([rng.normal([x, 0.0, 2.0], 0.4, (n, 3)) for x in (0.0, 5.0, 10.0)])


# -- helpers ------------------------------------------------------------------------------------
def _instance(estimator: Any) -> Any:
    """A fresh instance: the class built with its defaults, or a copy of the instance's params."""
    if isinstance(estimator, type):
        return estimator()
    if not hasattr(estimator, "get_params"):  # a reader: no parameters, used as it is
        return estimator
    return type(estimator)(**estimator.get_params())


def _label(estimator: Any) -> str:
    if isinstance(estimator, type):
        return estimator.__name__
    try:
        text = repr(estimator)
    except Exception:  # a broken repr must not hide the rule
        text = type(estimator).__name__
    if len(text) > 60 or " object at 0x" in text:  # long, or the default repr's address
        return type(estimator).__name__  # (stable ids: pytest-xdist workers must agree)
    return text


def _param_names(est: Any) -> list[str]:
    return [p.name for p in init_parameters(type(est))]


def _numeric_params(est: Any) -> list[str]:
    """Parameters annotated as a number (or an optional number)."""
    out = []
    for name, tp in annotations(type(est)).items():
        args = (
            typing.get_args(tp)
            if typing.get_origin(tp) in (typing.Union, types.UnionType)
            else (tp,)
        )
        args = tuple(a for a in args if a is not type(None))
        if name in _param_names(est) and args and all(a in (float, int) for a in args):
            out.append(name)
    return out


def _same(a: Any, b: Any) -> bool:
    try:
        return bool(np.all(a == b)) if isinstance(a, np.ndarray) else a == b or a is b
    except Exception:
        return a is b


# -- rules shared by every plugin ---------------------------------------------------------------
def check_init_stores_params(est: Any) -> None:
    """``__init__`` stores each keyword argument unchanged, as is, and nothing else."""
    params = {p: getattr(est, p, None) for p in _param_names(est)}
    sentinels = {p: object() for p in params}
    try:
        built = type(est)(**sentinels)
    except Exception as exc:
        raise AssertionError(
            f"__init__ works on its parameters (placeholder values raised "
            f"{type(exc).__name__}: {exc}); store them unchanged and check "
            f"them in validate_params"
        ) from exc
    for p, sentinel in sentinels.items():
        assert getattr(built, p, None) is sentinel, (
            f"__init__ must store parameter {p!r} unchanged as self.{p} (no conversion)"
        )
    extra = sorted(set(vars(built)) - set(params))
    assert not extra, f"__init__ sets attributes that are not parameters: {extra} (do work in fit)"


def check_get_params_round_trip(est: Any) -> None:
    """``get_params()`` names every ``__init__`` parameter; building from it gives the same."""
    params = est.get_params()
    assert set(params) == set(_param_names(est)), (
        f"get_params() keys {sorted(params)} differ from __init__'s {sorted(_param_names(est))}"
    )
    again = type(est)(**params).get_params()
    assert all(_same(again[k], v) for k, v in params.items()), "rebuilding changed the params"
    est.set_params(**params)
    assert all(_same(est.get_params()[k], v) for k, v in params.items()), "set_params failed"


def check_clone(est: Any) -> None:
    """``sklearn.base.clone`` gives a new, unfitted object with equal parameters."""
    from sklearn.base import clone

    copy = clone(est)
    assert copy is not est and type(copy) is type(est)
    assert all(_same(copy.get_params()[k], v) for k, v in est.get_params().items())


def check_repr(est: Any) -> None:
    """``repr`` starts with the class name and an opening parenthesis."""
    text = repr(est)
    assert text.startswith(type(est).__name__ + "("), f"repr {text!r}"


def check_validate_params_accepts_defaults(est: Any) -> None:
    """A public ``validate_params()`` accepts the parameters the plugin was built with."""
    assert callable(getattr(est, "validate_params", None)), "no public validate_params()"
    est.validate_params()


def _rejects(est: Any, run: Callable[[Any], Any], where: str) -> None:
    for p in _numeric_params(est):
        bad = type(est)(**{**est.get_params(), p: WRONG_TYPE})  # building never validates
        for action, call in (("validate_params()", lambda e: e.validate_params()), (where, run)):
            try:
                call(bad)
            except ConfigError as exc:
                assert p in str(exc), (
                    f"{action} with {p}={WRONG_TYPE!r}: message {exc} misses {p!r}"
                )
            else:
                raise AssertionError(f"{action} accepted {p}={WRONG_TYPE!r} (expected ConfigError)")


# -- segmenters ---------------------------------------------------------------------------------
def check_seg_validates_params(est: Any) -> None:
    """A string for a numeric parameter: ConfigError naming it, from validate_params and fit."""
    _rejects(est, lambda e: e.fit(blobs(20)), "fit")


def check_fit_returns_self(est: Any) -> None:
    """``fit(X)`` returns the segmenter itself."""
    assert est.fit(blobs()) is est, "fit must return self"


def check_labels(est: Any) -> None:
    """``labels_``: one integer per point, -1 for noise, ``n_clusters_`` trees."""
    xyz = blobs()
    labels = np.asarray(est.fit(xyz).labels_)
    assert labels.shape == (len(xyz),), f"labels_ has shape {labels.shape} for {len(xyz)} points"
    assert labels.dtype.kind in "iu", f"labels_ has dtype {labels.dtype}, not integer"
    assert labels.min() >= -1, f"labels_ below -1: {labels.min()} (noise is -1)"
    n = len(np.unique(labels[labels >= 0]))
    assert getattr(est, "n_clusters_", None) == n, (
        f"n_clusters_ = {getattr(est, 'n_clusters_', None)!r}, labels_ hold {n} trees"
    )


def check_fit_predict(est: Any) -> None:
    """``fit_predict(X)`` returns ``fit(X).labels_``."""
    xyz = blobs()
    got = np.asarray(est.fit_predict(xyz))
    assert np.array_equal(got, est.labels_), "fit_predict differs from labels_"


def check_seg_deterministic(est: Any) -> None:
    """Two fits on the same points give the same labels, and leave the points as they were."""
    xyz = blobs()
    copy = xyz.copy()
    first = np.asarray(_instance(est).fit(xyz).labels_).copy()
    assert np.array_equal(xyz, copy), "fit modified its input"
    assert np.array_equal(first, _instance(est).fit(xyz).labels_), "labels differ between fits"


def check_seg_rejects_nan(est: Any) -> None:
    """NaN or infinite coordinates: InputError."""
    xyz = blobs(50)
    xyz[7, 1] = np.nan
    try:
        est.fit(xyz)
    except InputError:
        return
    raise AssertionError("fit accepted NaN coordinates (expected InputError)")


def check_seg_rejects_wrong_shape(est: Any) -> None:
    """Points that are not (N, 3): InputError."""
    try:
        est.fit(np.zeros((10, 2)))
    except InputError:
        return
    raise AssertionError("fit accepted (10, 2) points (expected InputError)")


def check_seg_empty(est: Any) -> None:
    """No points: no labels and no trees."""
    labels = np.asarray(est.fit(np.zeros((0, 3))).labels_)
    assert labels.shape == (0,), f"labels_ has shape {labels.shape} for 0 points"


def check_unit_sample_weight(est: Any) -> None:
    """``sample_weight`` of ones (if ``fit`` takes it) gives the labels of no weight."""
    import inspect

    if "sample_weight" not in inspect.signature(est.fit).parameters:
        return
    xyz = blobs()
    plain = np.asarray(_instance(est).fit(xyz).labels_)
    weighted = np.asarray(_instance(est).fit(xyz, sample_weight=np.ones(len(xyz))).labels_)
    assert np.array_equal(plain, weighted), "unit weights changed the labels"


# -- volume estimators --------------------------------------------------------------------------
def check_vol_validates_params(est: Any) -> None:
    """A string for a numeric parameter: ConfigError naming it, from validate_params and call."""
    _rejects(est, lambda e: e(crown(100)), "__call__")


def check_says_what_it_measures(est: Any) -> None:
    """``measures``: a sentence saying what volume the estimator measures (its measurand), for
    the docs, the report and ``canopy-kit plugins volumes --params``."""
    what = getattr(est, "measures", None)
    assert isinstance(what, str) and len(what.split()) >= 4, (
        f"measures must say in a sentence what volume {type(est).__name__} measures, got {what!r}"
    )


def check_result(est: Any) -> None:
    """``est(xyz)`` is a :class:`VolumeResult` naming the method and its parameters, JSON-able."""
    from canopy_kit.volume.base import VolumeResult

    xyz = crown()
    result = est(xyz)
    assert isinstance(result, VolumeResult), f"returned {type(result).__name__}, not VolumeResult"
    name = getattr(est, "name", None)
    assert result.method == name, f"result.method {result.method!r} is not the name {name!r}"
    assert result.params == est.get_params(), "result.params differ from get_params()"
    assert result.n_points == len(xyz), f"n_points {result.n_points} for {len(xyz)} points"
    assert isinstance(result.valid, bool) and isinstance(result.volume_m3, float)
    json.dumps(result.as_dict())


def check_unit_cube(est: Any) -> None:
    """A unit cube's points: 1 m³ within ``convex_rtol``, or at least a positive finite volume."""
    result = est(unit_cube())
    v = result.volume_m3
    assert result.valid and np.isfinite(v) and v > 0, f"unit cube: {v!r} m³, reason {result.reason}"
    rtol = getattr(est, "convex_rtol", None)
    if rtol is not None:
        assert abs(v - 1.0) <= rtol, f"unit cube: {v!r} m³, expected 1 within {rtol}"


def check_coplanar(est: Any) -> None:
    """Coplanar points enclose nothing: ``valid=False``, 0 m³ and a reason."""
    result = est(coplanar())
    assert result.valid is False and result.volume_m3 == 0.0, (
        f"coplanar points: valid={result.valid}, {result.volume_m3} m³"
    )
    assert result.reason, "no reason for an invalid result"


def check_too_few_points(est: Any) -> None:
    """Three points enclose nothing: ``valid=False`` and 0 m³."""
    result = est(np.eye(3))
    assert result.valid is False and result.volume_m3 == 0.0, (
        f"3 points: valid={result.valid}, {result.volume_m3} m³"
    )


def check_vol_rejects_nan(est: Any) -> None:
    """NaN or infinite coordinates: InputError."""
    xyz = crown(200)
    xyz[17, 1] = np.nan
    try:
        est(xyz)
    except InputError:
        return
    raise AssertionError("accepted NaN coordinates (expected InputError)")


def check_vol_rejects_wrong_shape(est: Any) -> None:
    """Points that are not (N, 3): InputError."""
    try:
        est(np.zeros((10, 2)))
    except InputError:
        return
    raise AssertionError("accepted (10, 2) points (expected InputError)")


def check_vol_deterministic(est: Any) -> None:
    """The same points give the same volume twice, and are left as they were."""
    xyz = crown()
    copy = xyz.copy()
    first = est(xyz).volume_m3
    assert np.array_equal(xyz, copy), "the estimator modified its input"
    assert est(xyz).volume_m3 == first, "volumes differ between calls"


def check_translation(est: Any) -> None:
    """Moving the points to projected coordinates (600 km, 4100 km) keeps the volume (1 %)."""
    xyz = crown()
    here, there = est(xyz).volume_m3, est(xyz + [631_000.0, 4_127_000.0, 85.0]).volume_m3
    assert abs(there - here) <= TRANSLATION_RTOL * here, f"{here} m³ here, {there} m³ moved"


def check_surface(est: Any) -> None:
    """``with_surface(xyz)`` (when the estimator has it) gives the call's result and, if it
    draws one, a mesh of the points' coordinates whose volume is the result's; invalid
    results draw nothing."""
    if not hasattr(est, "with_surface"):
        return
    xyz = crown()
    result, surface = est.with_surface(xyz)
    assert result == est(xyz), "with_surface's result differs from the call's"
    if surface is not None:
        assert result.valid, "a surface drawn for an invalid result"
        assert surface.volume_m3 == result.volume_m3, "the surface's volume is not the result's"
        faces = np.asarray(surface.faces)
        assert faces.ndim == 2 and faces.shape[1] == 3 and len(faces), "faces are not triangles"
        assert 0 <= faces.min() and faces.max() < len(surface.vertices), "faces index no vertex"
        on_points = {tuple(p) for p in np.asarray(xyz)}
        assert all(tuple(v) in on_points for v in surface.vertices), "a vertex is no input point"
    assert est.with_surface(xyz[:3])[1] is None, "a surface drawn for three points"


SHARED: tuple[tuple[str, Callable[[Any], None]], ...] = (
    ("init_stores_params", check_init_stores_params),
    ("get_params_round_trip", check_get_params_round_trip),
    ("clone", check_clone),
    ("repr", check_repr),
    ("validate_params_accepts_defaults", check_validate_params_accepts_defaults),
)
SEGMENTER_RULES = SHARED + (
    ("validate_params_rejects_wrong_type", check_seg_validates_params),
    ("fit_returns_self", check_fit_returns_self),
    ("labels_one_per_point", check_labels),
    ("fit_predict_is_labels", check_fit_predict),
    ("deterministic", check_seg_deterministic),
    ("rejects_nan", check_seg_rejects_nan),
    ("rejects_wrong_shape", check_seg_rejects_wrong_shape),
    ("empty_input", check_seg_empty),
    ("unit_sample_weight", check_unit_sample_weight),
)
VOLUME_RULES = SHARED + (
    ("validate_params_rejects_wrong_type", check_vol_validates_params),
    ("result_is_volume_result", check_result),
    ("says_what_it_measures", check_says_what_it_measures),
    ("unit_cube", check_unit_cube),
    ("coplanar_is_invalid", check_coplanar),
    ("too_few_points", check_too_few_points),
    ("rejects_nan", check_vol_rejects_nan),
    ("rejects_wrong_shape", check_vol_rejects_wrong_shape),
    ("deterministic", check_vol_deterministic),
    ("translation_invariant", check_translation),
    ("surface_is_the_measured_solid", check_surface),
)


def segmenter_checks() -> list[Check]:
    """Every rule of the segmenter contract."""
    return [Check(name, func) for name, func in SEGMENTER_RULES]


def volume_checks() -> list[Check]:
    """Every rule of the volume-estimator contract."""
    return [Check(name, func) for name, func in VOLUME_RULES]


def checks_for(estimator: Any) -> list[Check]:
    """The rules for a reader (has ``sniff``), a segmenter (has ``fit``) or a volume
    estimator (callable)."""
    cls = estimator if isinstance(estimator, type) else type(estimator)
    if hasattr(cls, "sniff"):
        from canopy_kit.testing.readers import reader_checks

        return reader_checks()
    if hasattr(cls, "fit"):
        return segmenter_checks()
    if any("__call__" in vars(k) for k in cls.__mro__[:-1]):
        return volume_checks()
    raise TypeError(
        f"{cls.__name__} is not a reader (sniff), a segmenter (fit) or a volume estimator"
    )


def _run(estimator: Any, checks: Iterable[Check]) -> None:
    broken = []
    for check in checks:
        try:
            check(estimator)
        except AssertionError as exc:
            broken.append(str(exc))
    if broken:
        raise AssertionError(f"{len(broken)} rule(s) broken:\n" + "\n".join(broken))


def check_segmenter(estimator: Any) -> None:
    """Run every segmenter rule on a class or instance; AssertionError naming each broken one."""
    _run(estimator, segmenter_checks())


def check_volume_estimator(estimator: Any) -> None:
    """Run every volume rule on a class or instance; AssertionError naming each broken one."""
    _run(estimator, volume_checks())


def _pairs(estimators: Iterable[Any]) -> Iterator[tuple[Any, Check, str]]:
    for est in estimators:
        for check in checks_for(est):
            yield est, check, f"{_label(est)}-{check.name}"


def parametrize_with_checks(estimators: Iterable[Any]) -> Any:
    """A ``pytest.mark.parametrize("estimator, check", ...)`` over every (plugin, rule) pair,
    with ids such as ``AlphaShapeVolume()-unit_cube``."""
    import pytest

    pairs = list(_pairs(estimators))
    return pytest.mark.parametrize(
        "estimator, check", [(e, c) for e, c, _ in pairs], ids=[i for _, _, i in pairs]
    )
