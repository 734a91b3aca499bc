"""Volumes from one-sided scans: complete the unseen side by mirror symmetry.

A robot driving one alley sees the crown side that faces it; the alpha shape of those
points is a cup and the convex hull about half a crown. Orchard trees are planted on the
row line and their crowns are close to mirror-symmetric about the vertical plane through
the trunk along the row, so the unseen half is estimated as the mirror image of the seen
half across that plane.

The plane (a point and a horizontal normal, the across-row direction) should come from
the pipeline: the trunk position or the fitted row line. When it is not given, it is
estimated from the points with this rule (documented in docs/history/VOLUMES_LOG.md):

- normal: the minor principal axis of the horizontal coordinates (a one-sided scan, like a
  row of crowns, is narrower across the row than along it);
- position: the crown is assumed ``across_ratio`` times as wide across the row as along
  it, so the plane lies half that width behind the face nearest the sensor. Which face that
  is, is decided by mirroring about both candidate planes and keeping the more compact
  result (smaller convex hull): mirroring a cup about its rim closes it, mirroring it about
  its tip makes a waisted double cup with a larger hull.

On a complete scan both candidate planes pass near the crown centre and the mirror
changes little.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from canopy_kit.errors import ConfigError
from canopy_kit.plugins.params import Positive
from canopy_kit.volume.alpha import PAPER_ALPHA_M
from canopy_kit.volume.base import VolumeEstimator
from canopy_kit.volume.hull import hull_volume

MirrorBase = Literal["convex_hull", "alpha_hull", "alpha_shape"]
MIRROR_BASES = get_args(MirrorBase)


@dataclass(frozen=True)
class MirrorPlane:
    """A vertical plane: a horizontal point on it and its horizontal unit normal."""

    point: np.ndarray  # (2,)
    normal: np.ndarray  # (2,)

    def reflect(self, xyz: np.ndarray) -> np.ndarray:
        """Mirror images of (N, 3) points across the plane (z unchanged)."""
        s = (xyz[:, :2] - self.point) @ self.normal
        out = xyz.copy()
        out[:, :2] -= 2.0 * s[:, None] * self.normal
        return out


def horizontal_axes(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Major and minor principal axes (unit 2-vectors) of the horizontal coordinates."""
    xy = xyz[:, :2] - xyz[:, :2].mean(axis=0)
    _, v = np.linalg.eigh(xy.T @ xy)
    return v[:, 1], v[:, 0]


def estimate_mirror_plane(
    xyz: np.ndarray, across_ratio: float = 1.0, normal: np.ndarray | None = None
) -> MirrorPlane:
    """The mirror plane by the round-crown rule (module docstring); ``normal`` if known."""
    major, minor = horizontal_axes(xyz)
    if normal is not None:
        minor = np.asarray(normal, float) / np.linalg.norm(normal)
        major = np.array([-minor[1], minor[0]])
    t = xyz[:, :2] @ major
    s = xyz[:, :2] @ minor
    half = 0.5 * across_ratio * float(np.ptp(t))
    best: tuple[float, MirrorPlane] | None = None
    for s_plane in (s.max() - half, s.min() + half):
        plane = MirrorPlane(s_plane * minor, minor)
        v = hull_volume(np.concatenate([xyz, plane.reflect(xyz)]))
        if best is None or v < best[0]:
            best = (v, plane)
    assert best is not None
    return best[1]


def mirrored(xyz: np.ndarray, plane: MirrorPlane) -> np.ndarray:
    """The points together with their mirror images."""
    return np.concatenate([xyz, plane.reflect(xyz)])


def _as_pair(value: object, name: str, method: str) -> np.ndarray | None:
    if value is None:
        return None
    arr = np.asarray(value, dtype=float).ravel()
    if arr.shape != (2,) or not np.isfinite(arr).all():
        raise ConfigError(f"{method}: {name} must be two finite numbers (x, y), got {value!r}")
    return arr


class MirrorVolume(VolumeEstimator):
    """Volume of the points plus their mirror image across a vertical plane (one-sided scans).

    ``plane_point`` (x, y) and ``plane_normal`` (across-row direction) place the plane, e.g.
    through the trunk along the row; either may be omitted and is then estimated (module
    docstring). ``base`` is the estimator applied to the completed cloud.

    Parameters
    ----------
    plane_point : tuple of two floats or None, default None
        A point (x, y) of the vertical mirror plane; None estimates it from the points.
    plane_normal : tuple of two floats or None, default None
        Horizontal normal (x, y) of the plane (the across-row direction); None estimates it.
    base : str, default "convex_hull"
        Estimator applied to the points and their mirror image.
    alpha : float, default 0.9
        α (m) of the base estimator when it is an alpha method.
    across_ratio : float, default 1.0
        The crown is assumed this many times as wide across the row as along it; places an
        estimated plane half that width behind the face nearest the sensor.
    """

    name = "mirror"
    measures = (
        "the base estimator on the points and their mirror image across a vertical plane "
        "(one-sided scans): assumes a crown symmetric about the row"
    )

    def __init__(
        self,
        plane_point: tuple[float, float] | None = None,
        plane_normal: tuple[float, float] | None = None,
        base: MirrorBase = "convex_hull",
        alpha: Positive = PAPER_ALPHA_M,
        across_ratio: Positive = 1.0,
    ) -> None:
        self.plane_point = plane_point
        self.plane_normal = plane_normal
        self.base = base
        self.alpha = alpha
        self.across_ratio = across_ratio

    def validate_params(self) -> None:
        """ConfigError naming the first unusable parameter."""
        super().validate_params()  # each value's type and range first
        _as_pair(self.plane_point, "plane_point", self.name)
        normal = _as_pair(self.plane_normal, "plane_normal", self.name)
        if normal is not None and np.linalg.norm(normal) == 0:
            raise ConfigError(f"{self.name}: plane_normal must not be (0, 0)")

    def plane(self, xyz: np.ndarray) -> MirrorPlane:
        """The plane used for ``xyz``: as given, or estimated."""
        point = _as_pair(self.plane_point, "plane_point", self.name)
        normal = _as_pair(self.plane_normal, "plane_normal", self.name)
        if normal is not None:
            normal = normal / np.linalg.norm(normal)
        if point is not None:
            if normal is None:
                normal = horizontal_axes(xyz)[1]
            return MirrorPlane(point, normal)
        return estimate_mirror_plane(xyz, float(self.across_ratio), normal)

    def _volume(self, xyz: np.ndarray) -> tuple[float, dict]:
        plane = self.plane(xyz)
        both = mirrored(xyz, plane)
        if self.base == "convex_hull":
            from canopy_kit.volume.hull import ConvexHullVolume

            result = ConvexHullVolume()(both)
        elif self.base == "alpha_hull":
            from canopy_kit.volume.alpha_hull import AlphaHullVolume

            result = AlphaHullVolume(alpha=self.alpha)(both)
        else:
            from canopy_kit.volume.alpha import AlphaShapeVolume

            result = AlphaShapeVolume(alpha=self.alpha)(both)
        extra = {"plane_point": plane.point.tolist(), "plane_normal": plane.normal.tolist()}
        if not result.valid:
            extra["reason"] = f"{self.base} of the mirrored points: {result.reason}"
        return result.volume_m3, extra
