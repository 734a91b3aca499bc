"""Volume-versus-α curves and the automatic α rule."""

from __future__ import annotations

import numpy as np
import pytest

from canopy_kit.errors import ConfigError, InputError
from canopy_kit.volume import alpha_curve, auto_alpha, estimate_volume


def ball(n: int, radius: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * radius * rng.uniform(0, 1, (n, 1)) ** (1 / 3)


def sphere_surface(n: int, radius: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * radius + rng.normal(
        scale=1e-3, size=(n, 3)
    )


def test_curve_is_the_exact_alpha_volume_at_every_alpha() -> None:
    pts = ball(4000, 1.5)
    alphas = [0.1, 0.2, 0.4, 0.9, 2.0, 10.0]
    curve = alpha_curve(pts, alphas)
    assert np.all(np.diff(curve.volumes) >= 0)
    for a, v in zip(alphas, curve.volumes):
        assert v == pytest.approx(estimate_volume(pts, "alpha_shape", alpha=a).volume_m3, rel=1e-12)
    assert curve.hull_volume == pytest.approx(
        estimate_volume(pts, "convex_hull").volume_m3, rel=1e-9
    )
    assert curve.as_dict()["alphas"] == alphas


def test_curve_refuses_bad_alphas_and_degenerate_points() -> None:
    with pytest.raises(ConfigError, match="alphas: expected positive finite values"):
        alpha_curve(ball(100, 1.0), [0.5, -1.0])
    with pytest.raises(ConfigError, match="alphas: expected positive finite values"):
        alpha_curve(ball(100, 1.0), [])
    with pytest.raises(InputError, match="xyz: no alpha curve: all 30 points are coplanar"):
        alpha_curve(
            np.column_stack([np.random.default_rng(0).uniform(size=(30, 2)), np.zeros(30)]), [1.0]
        )


def test_auto_alpha_on_a_solid_crown_is_a_few_spacings() -> None:
    pts = ball(20000, 2.0)
    truth = 4 / 3 * np.pi * 8
    choice = auto_alpha(pts)
    assert 0.1 < choice.alpha < 0.9
    assert choice.volume_m3 == pytest.approx(truth, rel=0.07)
    assert choice.volume_m3 == pytest.approx(estimate_volume(pts, alpha=choice.alpha).volume_m3)


def test_auto_alpha_fills_a_hollow_surface_crown() -> None:
    # α = 0.9 m finds almost nothing inside a 2 m surface-only sphere; the rule waits for
    # the interior to fill (α near the radius)
    pts = sphere_surface(3000, 2.0)
    truth = 4 / 3 * np.pi * 8
    assert estimate_volume(pts, alpha=0.9).volume_m3 < 0.05 * truth
    choice = auto_alpha(pts)
    assert choice.alpha > 1.6
    assert choice.volume_m3 == pytest.approx(truth, rel=0.03)


def test_auto_alpha_parameters_are_checked() -> None:
    with pytest.raises(ConfigError, match="tolerance must be in"):
        auto_alpha(ball(100, 1.0), tolerance=0)
    with pytest.raises(ConfigError, match="n must be an integer of at least 8"):
        auto_alpha(ball(100, 1.0), n=3)
