"""The volume-estimator contract: a result type, the shared input check and a base class.

Every estimator is a scikit-learn ``BaseEstimator`` (``get_params``, ``set_params``,
``repr`` and ``clone`` come with it) whose ``__init__`` only stores keyword parameters,
whose ``validate_params()`` raises ConfigError naming a bad one and whose ``__call__(xyz)``
returns a :class:`VolumeResult`. ``canopy_kit.testing.check_volume_estimator`` checks an
estimator against this contract.

Input policy (the same for every estimator):

- ``xyz`` that is not an ``(N, 3)`` array of numbers, or that holds NaN/Inf, raises
  :class:`~canopy_kit.errors.InputError`. Non-finite coordinates mean an upstream stage is
  broken; dropping them here would hide that, so the caller decides (a batch run can catch
  the error per tree).
- Fewer than 4 points, or points that are all identical, collinear or coplanar, enclose no
  volume: the result is ``volume_m3 = 0.0`` with ``valid = False`` and the reason, never a
  silent number from a degenerate hull.
- Bad parameter values raise :class:`~canopy_kit.errors.ConfigError` naming the parameter.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from sklearn.base import BaseEstimator

from canopy_kit.errors import InputError
from canopy_kit.plugins.params import check_choice, check_positive, validate_types
from canopy_kit.volume.surface import Surface

__all__ = [
    "MIN_POINTS",
    "VolumeEstimator",
    "VolumeResult",
    "as_points",
    "check_choice",
    "check_positive",
    "degeneracy",
]

MIN_POINTS = 4
# Relative singular-value threshold below which the cloud is treated as flat or a line.
FLATNESS_TOL = 1e-9


@dataclass(frozen=True)
class VolumeResult:
    """A per-tree volume with how it was made and whether it can be trusted."""

    volume_m3: float
    method: str
    params: dict[str, Any]
    valid: bool
    reason: str | None = None
    n_points: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """Plain dict (for JSON and tables)."""
        return {
            "volume_m3": self.volume_m3,
            "method": self.method,
            "params": dict(self.params),
            "valid": self.valid,
            "reason": self.reason,
            "n_points": self.n_points,
            **({"extra": dict(self.extra)} if self.extra else {}),
        }


def as_points(xyz: Any, name: str = "xyz") -> np.ndarray:
    """``xyz`` (or a PointCloud's ``.xyz``) as a float64 (N, 3) array; InputError if unusable."""
    if hasattr(xyz, "xyz") and not isinstance(xyz, np.ndarray):
        xyz = xyz.xyz
    try:
        arr = np.asarray(xyz, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(
            f"{name}: expected an (N, 3) array of coordinates, got {type(xyz).__name__} ({exc})"
        ) from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name}: expected an (N, 3) array of coordinates, got shape {arr.shape}")
    finite = np.isfinite(arr).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise InputError(
            f"{name}: {len(bad)} of {len(arr)} points have NaN or infinite "
            f"coordinates (first at row {bad[0]}); remove them before estimating a "
            f"volume"
        )
    return arr


def degeneracy(xyz: np.ndarray) -> str | None:
    """Why ``xyz`` encloses no volume (too few, identical, collinear, coplanar), else None."""
    n = len(xyz)
    if n < MIN_POINTS:
        return f"too few points: {n} (a volume needs at least {MIN_POINTS})"
    s = np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False)
    # Rounding of the coordinates themselves (1e-9 m at UTM northings) is no extent: points
    # 1e-7 m apart in a plane at UTM coordinates gave s[2] = 2e-14, not 0.
    noise = 4.0 * np.finfo(np.float64).eps * float(np.abs(xyz).max()) * np.sqrt(n)
    if s[0] <= noise:
        return f"all {n} points are identical"
    if s[1] <= max(FLATNESS_TOL * s[0], noise):
        return f"all {n} points are collinear"
    if s[2] <= max(FLATNESS_TOL * s[0], noise):
        return f"all {n} points are coplanar"
    return None


class VolumeEstimator(BaseEstimator):
    """Base class: validates input and parameters, then calls :meth:`_volume`.

    Subclasses set ``name`` and ``measures`` (what volume the estimator measures, its
    measurand, in a sentence for the docs and the report), store their keyword arguments in ``__init__`` unchanged,
    document them in a numpydoc ``Parameters`` section and implement
    ``_volume(xyz) -> float`` (or ``-> (float, extra_dict)``) on checked, non-degenerate
    points (and ``_volume_and_surface`` when they can draw the solid they measured);
    ``validate_params`` adds their range checks (ConfigError naming the parameter) and
    calls ``super().validate_params()``, which checks values against the annotations.
    ``convex_rtol``: the relative error promised on a densely sampled convex solid (the
    conformance suite measures a unit cube); None promises only a positive volume.
    """

    name: ClassVar[str] = "volume"
    measures: ClassVar[str] = ""  # what volume it measures, in a sentence (docs, report)
    convex_rtol: ClassVar[float | None] = None

    def validate_params(self) -> None:
        """ConfigError naming the first parameter whose value misfits its annotation."""
        validate_types(self, self.name)

    def _volume(self, xyz: np.ndarray) -> float | tuple[float, dict[str, Any]]:
        raise NotImplementedError

    def _volume_and_surface(
        self, xyz: np.ndarray
    ) -> tuple[float | tuple[float, dict[str, Any]], Surface | None]:
        """:meth:`_volume` and the surface of the solid measured; estimators that can draw
        it override this (from the same triangulation), the others draw nothing."""
        return self._volume(xyz), None

    def __call__(self, xyz: Any) -> VolumeResult:
        """Estimate the volume enclosed by the points ``xyz`` (N, 3) in metres."""
        return self._measure(xyz, surface=False)[0]

    def with_surface(self, xyz: Any) -> tuple[VolumeResult, Surface | None]:
        """The volume of ``xyz`` (as calling the estimator gives it) and the surface of the
        solid it measured, from the same triangulation; None when the estimator draws no
        surface or the result is not valid."""
        return self._measure(xyz, surface=True)

    def _measure(self, xyz: Any, surface: bool) -> tuple[VolumeResult, Surface | None]:
        self.validate_params()
        pts = as_points(xyz)
        params = self.get_params()
        reason = degeneracy(pts)
        if reason is not None:
            return VolumeResult(0.0, self.name, params, False, reason, len(pts)), None
        out, drawn = self._volume_and_surface(pts) if surface else (self._volume(pts), None)
        volume, extra = out if isinstance(out, tuple) else (out, {})
        if not np.isfinite(volume) or volume < 0:
            reason = f"estimator produced an unusable volume ({volume!r})"
            return VolumeResult(0.0, self.name, params, False, reason, len(pts), extra), None
        reason = extra.pop("reason", None)
        result = VolumeResult(
            float(volume), self.name, params, reason is None, reason, len(pts), extra
        )
        return result, drawn if result.valid else None
