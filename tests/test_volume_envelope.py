"""The foliage envelope (issue 46): a crown volume whose measurand is stated and does not
depend on the scan; its interval's rules (calibration parameters, enclosed voids, estimators
that disagree).

Truths: closed-form volumes of balls and of their hollow shells, the enclosing ellipsoid
computed on its own, and the definition of the α-hull (gaps wider than 2α stay open).
"""

from __future__ import annotations

import numpy as np
import pytest

from canopy_kit.errors import ConfigError
from canopy_kit.volume import estimate_volume
from canopy_kit.volume.envelope import ELLIPSOID_MEASURAND, FoliageEnvelopeVolume


def ball(n: int, radius: float, centre=(0.0, 0.0, 0.0), seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(centre) + d * radius * rng.random((n, 1)) ** (1 / 3)


def sphere(n: int, radius: float, seed: int = 0) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def test_a_dense_ball_is_its_own_envelope() -> None:
    """On a convex crown the envelope is the points' hull, less the small bites of the ball
    between boundary points; both sit just inside the ball the points were drawn from."""
    xyz = ball(40_000, 2.0)
    r = estimate_volume(xyz, "foliage_envelope")
    assert r.valid and r.extra["crown_kind"] == "dense" and not r.extra["thin_scan"]
    hull = estimate_volume(xyz, "convex_hull").volume_m3
    assert hull * 0.98 < r.volume_m3 <= hull
    assert r.volume_m3 == pytest.approx(4 / 3 * np.pi * 8, rel=0.05)
    assert "0.75 m" in r.extra["measurand"]


def test_the_leafless_inside_of_a_shell_is_crown_and_reported() -> None:
    """Leaves only in a shell: the space they close round counts, and its volume is given."""
    shell = sphere(30_000, 2.0)
    full = 4 / 3 * np.pi * 8
    r = estimate_volume(shell, "foliage_envelope")
    assert r.volume_m3 == pytest.approx(full, rel=0.04)
    assert r.extra["void_m3"] > 0.6 * full
    assert r.extra["volume_without_voids_m3"] < 0.4 * full
    empty = estimate_volume(shell, "foliage_envelope", fill_voids=False)
    assert empty.volume_m3 == pytest.approx(r.extra["volume_without_voids_m3"], rel=0.1)


def test_a_gap_wider_than_two_alpha_stays_open_and_a_narrower_one_closes() -> None:
    one = 4 / 3 * np.pi * 1.0
    for gap, bridged in ((2.0, False), (0.4, True)):
        centre = 2.0 + gap
        xyz = np.vstack([ball(20_000, 1.0), ball(20_000, 1.0, (centre, 0, 0), seed=1)])
        v = estimate_volume(xyz, "foliage_envelope").volume_m3
        if bridged:
            assert v > 2 * one * 1.03
        else:
            assert v == pytest.approx(2 * one, rel=0.04)


def test_a_scan_too_thin_for_alpha_grows_the_ball_and_says_so() -> None:
    xyz = ball(600, 2.0)  # spacing about 0.5 m: far above alpha / 5
    r = estimate_volume(xyz, "foliage_envelope", sparse_fill=None)
    assert r.extra["thin_scan"] and r.extra["crown_kind"] == "thin"
    assert r.extra["alpha_used"] == pytest.approx(5 * r.extra["spacing"])


def test_a_sparse_crown_is_measured_as_its_enclosing_ellipsoid() -> None:
    rng = np.random.default_rng(3)  # 30 leaf clusters spread through a young crown
    clusters = rng.normal(size=(30, 3)) * [0.6, 0.55, 0.45] + [0, 0, 1.5]
    xyz = np.concatenate([c + rng.normal(0, 0.03, (9, 3)) for c in clusters])
    assert estimate_volume(xyz, "convex_hull").volume_m3 < 15.0
    r = estimate_volume(xyz, "foliage_envelope")
    assert r.extra["surface_fill"] < 1.2 and r.extra["crown_kind"] == "sparse"
    assert r.extra["measurand"] == ELLIPSOID_MEASURAND
    assert r.volume_m3 == pytest.approx(estimate_volume(xyz, "enclosing_ellipsoid").volume_m3)
    forced = estimate_volume(xyz, "foliage_envelope", measurand="envelope")
    assert forced.extra["estimate"] == "envelope" and forced.volume_m3 < r.volume_m3


def test_a_large_sparse_crown_keeps_the_envelope() -> None:
    """A leafless or barely seen big crown is not a young tree: no ellipsoid of a crown its
    points do not show."""
    rng = np.random.default_rng(4)
    clusters = rng.normal(size=(60, 3)) * [2.5, 2.5, 2.0] + [0, 0, 5.0]
    xyz = np.concatenate([c + rng.normal(0, 0.03, (9, 3)) for c in clusters])
    assert estimate_volume(xyz, "convex_hull").volume_m3 > 15.0
    r = estimate_volume(xyz, "foliage_envelope")
    assert r.extra["surface_fill"] < 1.2 and r.extra["estimate"] == "envelope"


@pytest.mark.parametrize(
    ("params", "name"),
    [
        ({"alpha": -1}, "alpha"),
        ({"spacing_factor": 0}, "spacing_factor"),
        ({"measurand": "hull"}, "measurand"),
        ({"sparse_fill": "x"}, "sparse_fill"),
    ],
)
def test_bad_parameters_are_named(params: dict, name: str) -> None:
    with pytest.raises(ConfigError, match=name):
        FoliageEnvelopeVolume(**params)(ball(100, 1.0))


def test_an_estimator_run_with_other_parameters_gets_no_interval() -> None:
    from canopy_kit.volume.uncertainty import volume_interval

    xyz = ball(5000, 2.0)
    ok = volume_interval(xyz, 30.0, "alpha_shape", params={"alpha": 0.9})
    assert ok is not None and np.isfinite(ok.low_m3)
    other = volume_interval(xyz, 30.0, "alpha_shape", params={"alpha": 0.5})
    assert np.isnan(other.low_m3) and np.isnan(other.high_m3)
    assert "alpha = 0.5" in other.flags[0] and "0.9" in other.flags[0]


def test_enclosed_empty_space_is_flagged_and_spanned() -> None:
    from canopy_kit.volume.uncertainty import CALIBRATIONS, volume_interval

    xyz = sphere(20_000, 2.0)
    r = estimate_volume(xyz, "foliage_envelope")
    interval = volume_interval(
        xyz, r.volume_m3, "foliage_envelope", kind="dense", params=r.params, extra=r.extra
    )
    lo = CALIBRATIONS["foliage_envelope"].kinds["dense"][0]
    assert any("enclosed empty space" in f for f in interval.flags)
    assert interval.low_m3 == pytest.approx(r.extra["volume_without_voids_m3"] * lo)


def test_estimators_that_disagree_beyond_the_families_are_flagged_and_spanned() -> None:
    from canopy_kit.volume.uncertainty import AGREEMENT, volume_interval

    xyz = ball(5000, 2.0)
    lo, _ = AGREEMENT[("foliage_envelope", "convex_hull", "envelope")]
    hull = 30.0 / (0.5 * lo)  # the envelope far below the hull
    interval = volume_interval(
        xyz, 30.0, "foliage_envelope", kind="dense", others={"convex_hull": hull}
    )
    assert any("disagree" in f for f in interval.flags)
    assert interval.high_m3 == pytest.approx(hull) and interval.low_m3 <= 30.0
    agree = volume_interval(
        xyz, 30.0, "foliage_envelope", kind="dense", others={"convex_hull": 32.0}
    )
    assert not any("disagree" in f for f in agree.flags)


def test_sides_seen_counts_the_alleys_the_drive_passed_along() -> None:
    from canopy_kit.volume.uncertainty import sides_seen

    x = np.linspace(-20, 20, 200)
    alley = lambda y: np.column_stack([x, np.full_like(x, y)])  # noqa: E731
    tree = np.array([1.0, 0.2])
    assert sides_seen(tree, np.vstack([alley(3.0), alley(-3.0)])) == 2
    assert sides_seen(tree, alley(3.0)) == 1
    assert sides_seen(tree, alley(-3.2)) == 1
    assert sides_seen(tree, alley(40.0)) == 0
    # the alley beyond the next row (9 m off) is not the far side of this tree's row
    assert sides_seen(tree, np.vstack([alley(3.0), alley(9.0)])) == 1
    # a rotated, bowed drive: the principal axis follows the alleys
    turn = np.array([[np.cos(0.7), -np.sin(0.7)], [np.sin(0.7), np.cos(0.7)]])
    both = np.vstack([alley(3.0), alley(-3.0)]) @ turn.T
    assert sides_seen(tree @ turn.T, both) == 2


def test_a_tree_seen_from_one_side_takes_the_one_sided_calibration() -> None:
    from canopy_kit.volume.uncertainty import CALIBRATIONS, ONE_SIDED, volume_interval

    kinds = CALIBRATIONS["foliage_envelope"].kinds
    xyz = ball(5000, 2.0)
    both = volume_interval(xyz, 30.0, "foliage_envelope", kind="dense", sides=2)
    one = volume_interval(xyz, 30.0, "foliage_envelope", kind="dense", sides=1)
    assert both.high_m3 == pytest.approx(30.0 * kinds["dense"][1])
    assert one.high_m3 == pytest.approx(30.0 * kinds["dense" + ONE_SIDED][1])
    assert one.flags[0].startswith("seen from one side of its row only")


def test_a_crown_taller_than_every_calibration_tree_reaches_the_hull() -> None:
    from canopy_kit.volume.uncertainty import CALIBRATED_HEIGHT_M, volume_interval

    tall = ball(8000, 1.0) * [1.0, 1.0, 1.5 * CALIBRATED_HEIGHT_M / 2] + [0, 0, 8.0]
    hull = estimate_volume(tall, "convex_hull").volume_m3
    interval = volume_interval(tall, 0.5 * hull, "foliage_envelope", kind="dense")
    assert any("taller than every tree" in f for f in interval.flags)
    assert interval.high_m3 == pytest.approx(hull)
    short = volume_interval(ball(8000, 1.0), 3.0, "foliage_envelope", kind="dense")
    assert not any("taller" in f for f in short.flags)
