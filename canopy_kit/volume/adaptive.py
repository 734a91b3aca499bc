"""Adaptive alpha: an α-hull whose α and outward offset follow each tree's point spacing.

The paper's alpha shape uses one α (0.9 m) for every tree. What α should be depends on the
scan: it must bridge the gaps between neighbouring returns (or the solid falls apart into
shells) but no more, or it fills the hollows between lobes and the open centre of a vase.
Both are a multiple of the tree's own point spacing ``s``: the median distance from a point
to its ``k``-th nearest neighbour (k = 8, on the 0.1 m voxel-thinned points the pipeline
measures). The estimator is

- ``α = clip(alpha_factor · s, alpha_min, alpha_max)``;
- the solid: the α-hull of the points (closing by a ball of radius α,
  :func:`~canopy_kit.volume.alpha_hull.alpha_hull_volume`), grown outwards by
  ``offset = offset_factor · s``: LiDAR returns lie inside the crown envelope, the outermost
  leaves are sparse, and the closing's boundary bites between boundary points by an amount
  that also scales with ``s``;
- closed voids (empty space inside the crown no α-ball from outside reaches, e.g. the
  leafless inside of a crown whose leaves form a shell) count as crown (``fill_voids``): the
  volume is the outer envelope's. An open hollow, such as a vase's centre, stays empty;
- a sparse crown, whose few returns do not outline its envelope (surface fill
  ``n · s² / A`` below ``sparse_fill``, :func:`canopy_kit.volume.uncertainty.surface_fill`:
  young trees with few leaves), gets the convex hull corrected for its thin sampling
  (:func:`~canopy_kit.volume.hull.sample_corrected_hull`) instead: every hull or α-solid of
  such points is about half the envelope, and no α can close what was never hit. Unless the
  thinned points are far from a sample of a convex body yet form a solid
  (:func:`~canopy_kit.volume.convexity.is_hollowed_body`: a small lobed crown scanned
  thinly, whose convex hull would be 60 % too much): then the α-hull, and
  ``extra["crown_kind"] = "mixed"`` gives it the interval of sparse-or-lobed crowns. A
  skeleton of bare branches is as far from convex, but its α-hull is thin tubes: it keeps
  the corrected hull.

The two factors were calibrated on simulated crowns of every form (docs/history/VOLUMES_LOG.md,
"`adaptive_alpha` and the per-tree interval" and "The offset recalibrated on harsher
crowns"). One k-d tree query, two distance transforms: about 0.1-0.2 s for a 50k-point
tree, where the exact alpha complex needs a Delaunay triangulation (1-2 s).
"""

from __future__ import annotations

from contextlib import suppress

import numpy as np

from canopy_kit.errors import ConfigError
from canopy_kit.plugins.params import NonNegative, Positive
from canopy_kit.volume.alpha_hull import alpha_hull_volume, grid_step
from canopy_kit.volume.base import VolumeEstimator
from canopy_kit.volume.convexity import HOLLOW_Z, is_hollowed_body, sample_convexity
from canopy_kit.volume.hull import efron_corrected_hull, hull_volume, thin_to_distance

SPACING_K = 8  # neighbour whose distance is the point spacing
SPACING_SAMPLE = 5000  # points sampled for the spacing (evenly through the array)
# Calibrated on seeds 401-402 of every crown form (benchmarks/bench_adaptive_volume.py). The
# offset was 0.5 until the harsher crowns (deep lobe hollows, leaves in a 0.3 m shell) and the
# matrix's denser sensors joined the tuning set: 0.5 left them 5-6 % high, 0.4 and 0.45 bracket
# every sensor and form within ±3.4 % (docs/history/VOLUMES_LOG.md, "The offset recalibrated").
ALPHA_FACTOR = 4.0
OFFSET_FACTOR = 0.425
SPARSE_FILL = 1.2  # below: a sparse crown (canopy_kit.volume.uncertainty.SPARSE_FILL)
SAMPLE_CELL = 0.2  # thinning before the sampling correction of a sparse crown's hull


def point_spacing(xyz: np.ndarray, k: int = SPACING_K, tree: object = None) -> float:
    """Median distance from a point to its ``k``-th nearest neighbour (metres); ``tree``: a
    ``cKDTree`` of ``xyz`` if the caller has one."""
    from scipy.spatial import cKDTree

    k = min(k, len(xyz) - 1)
    sample = xyz[:: max(1, len(xyz) // SPACING_SAMPLE)]
    if tree is None:
        tree = cKDTree(xyz, balanced_tree=False, compact_nodes=False)
    dist = tree.query(sample, k=k + 1)[0][:, k]
    return float(np.median(dist))


class AdaptiveAlphaVolume(VolumeEstimator):
    """α-hull volume with α and an outward offset proportional to the tree's point spacing.

    ``alpha = clip(alpha_factor · s, alpha_min, alpha_max)``, ``offset = offset_factor · s``
    (capped at α/2), with ``s`` the median 8th-neighbour distance; both, and ``s``, are
    reported in ``result.extra``.

    Parameters
    ----------
    alpha_factor : float, default 4.0
        α as a multiple of the point spacing, before clipping.
    offset_factor : float, default 0.425
        Outward offset of the hull as a multiple of the point spacing (0: none).
    alpha_min : float, default 0.3
        Smallest α (m).
    alpha_max : float, default 1.5
        Largest α (m).
    grid_step : float or None, default None
        Edge (m) of the closing grid; None picks one from α and the extent.
    fill_voids : bool, default True
        Count closed cavities inside the crown (no leaves there, but enclosed by the crown's
        outer surface) as crown: the volume of the outer envelope, as the crown volume is
        defined. An open hollow (a vase's centre) is never filled.
    sparse_fill : float or None, default 1.2
        Below this surface fill (``n · s² / A``) the crown is sparse and its volume is the
        sample-corrected convex hull (``result.extra["estimate"]`` says which); None: never.
    sample_cell : float, default 0.2
        Smallest distance (m) between the points kept for that correction.
    """

    name = "adaptive_alpha"
    measures = (
        "the alpha-hull at alpha = 4 point spacings, grown outwards by 0.425 spacings: fitted"
        " to the envelopes the simulator draws round its leaves, so its scale follows the "
        "scan's density (recommended for a wall's trunk-midpoint cuts; for free crowns "
        "foliage_envelope replaced it on 2026-12-06)"
    )

    def __init__(
        self,
        alpha_factor: Positive = ALPHA_FACTOR,
        offset_factor: NonNegative = OFFSET_FACTOR,
        alpha_min: Positive = 0.3,
        alpha_max: Positive = 1.5,
        grid_step: Positive | None = None,
        fill_voids: bool = True,
        sparse_fill: Positive | None = SPARSE_FILL,
        sample_cell: Positive = SAMPLE_CELL,
    ) -> None:
        self.alpha_factor = alpha_factor
        self.offset_factor = offset_factor
        self.alpha_min = alpha_min
        self.alpha_max = alpha_max
        self.grid_step = grid_step
        self.fill_voids = fill_voids
        self.sparse_fill = sparse_fill
        self.sample_cell = sample_cell

    def validate_params(self) -> None:
        """ConfigError naming the first unusable parameter."""
        super().validate_params()  # each value's type and range first
        if self.alpha_min > self.alpha_max:
            raise ConfigError(
                f"{self.name}: alpha_min ({self.alpha_min}) must not exceed "
                f"alpha_max ({self.alpha_max})"
            )

    def choose(self, xyz: np.ndarray, tree: object = None) -> tuple[float, float, float]:
        """(α, offset, spacing) for these points."""
        s = point_spacing(xyz, tree=tree)
        alpha = float(np.clip(self.alpha_factor * s, self.alpha_min, self.alpha_max))
        offset = float(min(self.offset_factor * s, 0.5 * alpha))
        return alpha, offset, s

    def _volume(self, xyz: np.ndarray) -> tuple[float, dict]:
        from scipy.spatial import QhullError, cKDTree

        from canopy_kit.volume.uncertainty import surface_fill

        tree = cKDTree(xyz, balanced_tree=False, compact_nodes=False)
        alpha, offset, s = self.choose(xyz, tree)
        fill = surface_fill(xyz, spacing=s)
        corrected, test = None, None
        if self.sparse_fill is not None and fill < self.sparse_fill:
            # Too few points a sample cell apart for a solid hull: the sample decides.
            with suppress(QhullError):
                sample = xyz[thin_to_distance(xyz, self.sample_cell)]
                test = sample_convexity(sample)
                corrected = efron_corrected_hull(sample)
        if corrected is not None:
            corrected_extra = {
                "estimate": "sample_corrected_hull",
                "surface_fill": fill,
                "spacing": s,
                "sample_factor": corrected.factor,
                "thinned_points": corrected.n_points,
                "sample_convexity_z": test.z,
            }
            if test.z > HOLLOW_Z:  # a sample of a convex body: no α-hull needed
                return corrected.volume_m3, corrected_extra
        h = grid_step(xyz, alpha, self.grid_step)
        volume, extra = alpha_hull_volume(
            xyz, alpha, h, offset=offset, tree=tree, fill_voids=self.fill_voids
        )
        extra.update(
            estimate="alpha_hull", surface_fill=fill, alpha=alpha, offset=offset, spacing=s
        )
        if corrected is not None:
            if not is_hollowed_body(test, volume, hull_volume(xyz)):  # bare branches
                return corrected.volume_m3, corrected_extra
            # a lobed crown scanned thinly, not a sparse one: the α-hull holds
            extra.update(crown_kind="mixed", sample_convexity_z=test.z)
        if volume <= 0.0:
            extra["reason"] = f"the adaptive alpha hull is empty (alpha = {alpha:.2f} m)"
        return volume, extra
