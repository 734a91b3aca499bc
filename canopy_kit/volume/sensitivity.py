"""Alpha sensitivity: the exact volume-versus-α curve of a tree and an automatic α.

One Delaunay triangulation gives the alpha-complex volume for every α at once: the
tetrahedra sorted by circumradius, their volumes summed cumulatively.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np
from annotated_types import Gt, Lt

from canopy_kit.errors import ConfigError, InputError
from canopy_kit.volume.alpha import Tetrahedra, delaunay_tetrahedra, qhull_failure
from canopy_kit.volume.base import VolumeEstimator, as_points, degeneracy


@dataclass(frozen=True)
class AlphaCurve:
    """Alpha-complex volume (m³) at each α (m), with the convex-hull volume it tends to."""

    alphas: np.ndarray
    volumes: np.ndarray
    hull_volume: float

    def as_dict(self) -> dict[str, Any]:
        """Plain dict (for JSON and tables)."""
        return {
            "alphas": self.alphas.tolist(),
            "volumes": self.volumes.tolist(),
            "hull_volume": self.hull_volume,
        }


class _Cumulative:
    """Alpha-complex volume as a step function of α from sorted tetrahedra."""

    def __init__(self, tetra: Tetrahedra) -> None:
        order = np.argsort(tetra.circumradius, kind="stable")
        self.radius = tetra.circumradius[order]
        self.cumulative = np.concatenate([[0.0], np.cumsum(tetra.volume[order])])

    def __call__(self, alphas: np.ndarray) -> np.ndarray:
        return self.cumulative[np.searchsorted(self.radius, alphas, side="left")]


def _tetrahedra(xyz: Any) -> Tetrahedra:
    pts = as_points(xyz)
    reason = degeneracy(pts)
    if reason is not None:
        raise InputError(f"xyz: no alpha curve: {reason}")
    return delaunay_tetrahedra(pts)


def alpha_curve(xyz: Any, alphas: Any) -> AlphaCurve:
    """Exact alpha-complex volume of the points at each α in ``alphas`` (metres, > 0)."""
    a = np.asarray(alphas, dtype=np.float64).ravel()
    if len(a) == 0 or not np.isfinite(a).all() or (a <= 0).any():
        raise ConfigError(f"alphas: expected positive finite values in metres, got {alphas!r}")
    tetra = _tetrahedra(xyz)
    step = _Cumulative(tetra)
    return AlphaCurve(a, step(a), float(step.cumulative[-1]))


@dataclass(frozen=True)
class AutoAlpha:
    """The automatically chosen α, its volume and the curve it was read from."""

    alpha: float
    volume_m3: float
    curve: AlphaCurve


def auto_alpha(xyz: Any, tolerance: float = 0.02, n: int = 64) -> AutoAlpha:
    """Smallest α after which doubling α adds less than ``tolerance`` of the volume.

    Rule (docs/VOLUME_METHODS.md): sample α at ``n`` log-spaced values from the median
    nearest-neighbour spacing of the points to half the diagonal of their bounding box
    (beyond which the alpha shape is the convex hull), and return the first α with a
    non-zero volume V(α) and V(2α) <= (1 + tolerance) V(α): the start of the plateau
    where the interior is filled and a larger α only bridges concavities. On a hollow,
    surface-only crown that is where the interior fills at once (α near the crown radius);
    on a dense solid crown it is a few point spacings. Returns the largest α sampled when
    no plateau is found.
    """
    from scipy.spatial import cKDTree

    if not isinstance(n, int) or n < 8:
        raise ConfigError(f"n must be an integer of at least 8, got {n!r}")
    if not 0 < tolerance < 1:
        raise ConfigError(f"tolerance must be in (0, 1), got {tolerance!r}")
    pts = as_points(xyz)
    tetra = _tetrahedra(pts)
    spacing = float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1]))
    top = 0.5 * float(np.linalg.norm(np.ptp(pts, axis=0)))
    low = spacing if spacing > 0 else top * 1e-3
    alphas = np.geomspace(low, max(top, 2 * low), n)
    step = _Cumulative(tetra)
    volumes = step(alphas)
    plateau = (volumes > 0) & (step(2 * alphas) <= (1 + tolerance) * volumes)
    k = int(np.argmax(plateau)) if plateau.any() else n - 1
    curve = AlphaCurve(alphas, volumes, float(step.cumulative[-1]))
    return AutoAlpha(float(alphas[k]), float(volumes[k]), curve)


class AutoAlphaVolume(VolumeEstimator):
    """Alpha-shape volume at the α the plateau rule picks per tree (:func:`auto_alpha`);
    the α used is reported in ``result.extra["alpha"]``.

    Parameters
    ----------
    tolerance : float, default 0.02
        Plateau rule: the smallest α whose doubling grows the volume by at most this
        fraction, in (0, 1).
    """

    name = "alpha_auto"
    measures = "the alpha shape at the start of its volume plateau, alpha chosen per tree"
    convex_rtol = 1e-3  # a filled convex solid is a plateau from the first α that fills it

    def __init__(self, tolerance: Annotated[float, Gt(0), Lt(1)] = 0.02) -> None:
        self.tolerance = tolerance

    def _volume(self, xyz: np.ndarray) -> tuple[float, dict]:
        from scipy.spatial import QhullError

        try:
            choice = auto_alpha(xyz, tolerance=float(self.tolerance))
        except QhullError as exc:  # points qhull finds flat although they pass degeneracy()
            return 0.0, {"reason": qhull_failure(exc)}
        return choice.volume_m3, {"alpha": choice.alpha}
