"""The foliage envelope: a crown volume defined by the foliage alone, at a stated scale.

What it measures (the measurand), for a crown whose foliage forms a closed crown:

    the volume enclosed by the tree's foliage (leaves and branches) closed by a ball of
    radius α = 0.75 m: the α-hull of the foliage (the complement of every empty open ball
    of radius α), with the empty space it encloses counted as crown.

So a gap or crease narrower than about 2α between leaves is crown; a hollow a ball of radius
α can enter from outside (a vase's open centre, the space between two lobes more than 1.5 m
apart) is not; a leafless space the foliage closes round (the shaded inside of a crown
whose leaves form a shell) is, and its share is reported (``extra["void_m3"]``, the volume
without it ``extra["volume_without_voids_m3"]``) because a user may want the other choice.
The measurand is a property of the tree, not of a scan: on the complete foliage (every leaf
and branch, seen or not) it is what the estimate from a drive aims at, so the two can be
compared (docs/VOLUMES.md, "Tree families").

A sparse young crown whose few leaves do not form a closed crown (surface fill
``n · s² / A`` below ``sparse_fill``, :func:`canopy_kit.volume.uncertainty.surface_fill`, and a
convex hull of at most ``young_max_m3``) is measured as young trees are in the field: the
**enclosing ellipsoid of its foliage** (:func:`canopy_kit.volume.ellipsoid.enclosing_ellipsoid`).
``extra["measurand"]`` says which of the two a tree's volume is. A large crown that sparse
(a leafless tree, a tall tree seen only at its foot) keeps the envelope: its ellipsoid would
be a model of a crown the points do not show.

The estimate from a scan is the same construction on the scanned points. Where the scan is
too thin to resolve α (median 8th-neighbour spacing s above α / ``spacing_factor``), the
closing ball must grow to ``spacing_factor · s`` to keep the solid whole: the estimate then
bridges wider gaps than the measurand does, and ``extra["alpha_used"]`` and
``extra["thin_scan"]`` say so (the interval widens, :mod:`canopy_kit.volume.uncertainty`).
``extra["crown_kind"]`` names the interval's calibration: ``dense``, ``small`` (a young or
small crown, on which the sensor's range noise weighs more), ``tall`` (a crown over 4.5 m
high, whose top a sensor with a narrow field of view may not have seen), ``thin`` or
``sparse`` (the ellipsoid).
"""

from __future__ import annotations

from typing import Any, Literal, get_args

import numpy as np

from canopy_kit.plugins.params import Positive
from canopy_kit.volume.alpha_hull import alpha_hull_volume, grid_step
from canopy_kit.volume.base import VolumeEstimator

ENVELOPE_ALPHA = 0.75  # m: the measurand's scale
SPACING_FACTOR = 5.0  # the closing ball is at least this many point spacings
SPARSE_FILL = 1.2  # below: a sparse crown, measured as its enclosing ellipsoid when young
TALL_HEIGHT_M = 4.5  # a crown higher than this (lowest to top point) is of the tall kind
YOUNG_MAX_M3 = 15.0  # convex hull of a young crown at most (a full pistachio crown: 12-38 m³)
Measurand = Literal["auto", "envelope", "ellipsoid"]
MEASURANDS = get_args(Measurand)
VOID_EXACT_SHARE = 0.01  # enclosed voids above this share are measured exactly (a second closing)


def envelope_measurand(alpha: float) -> str:
    """The envelope's measurand in words (trees.csv ``volume_measurand``)."""
    return f"foliage envelope: alpha-hull of the foliage at {alpha:g} m, enclosed voids counted"


ELLIPSOID_MEASURAND = "enclosing ellipsoid of the foliage (sparse young crown)"


def envelope_kind(thin: bool, small: bool, height_m: float = 0.0) -> str:
    """The interval's kind of an envelope: ``tall`` (a crown more than ``TALL_HEIGHT_M``
    high: a sensor with a narrow field of view may not have seen its top), ``thin`` (the
    ball had to grow), ``small`` (a hull of at most ``young_max_m3``: the sensor's range noise
    is a larger share of a small crown), else ``dense``."""
    if height_m > TALL_HEIGHT_M:
        return "tall"
    return "thin" if thin else ("small" if small else "dense")


class FoliageEnvelopeVolume(VolumeEstimator):
    """The foliage envelope at scale α (module docstring), or the enclosing ellipsoid of a
    sparse young crown's foliage.

    Parameters
    ----------
    alpha : float, default 0.75
        Radius (m) of the ball that closes the foliage: the measurand's scale.
    spacing_factor : float, default 5.0
        On a scan whose point spacing s exceeds α / spacing_factor the ball grows to
        spacing_factor · s (reported as a thin scan).
    fill_voids : bool, default True
        Count the empty space the foliage closes round as crown (the measurand does).
    sparse_fill : float or None, default 1.2
        Below this surface fill the crown is sparse; if young (``young_max_m3``) its volume
        is the enclosing ellipsoid of its foliage. None: never.
    young_max_m3 : float, default 15.0
        The largest convex hull (m³) of a sparse crown measured as young.
    measurand : {"auto", "envelope", "ellipsoid"}, default "auto"
        Which measurand to estimate; "auto" chooses by the surface fill (to measure complete
        foliage as a scan chose, force it).
    grid_step : float or None, default None
        Edge (m) of the closing grid; None picks one from α and the extent.
    """

    name = "foliage_envelope"
    measures = (
        "the foliage envelope at alpha (default 0.75 m): the alpha-hull of the foliage, gaps "
        "narrower than about 2 alpha and enclosed leafless space counted as crown; a sparse "
        "young crown: the enclosing ellipsoid of its foliage"
    )
    convex_rtol = 0.03  # the closing on a grid (as alpha_hull)

    def __init__(
        self,
        alpha: Positive = ENVELOPE_ALPHA,
        spacing_factor: Positive = SPACING_FACTOR,
        fill_voids: bool = True,
        sparse_fill: Positive | None = SPARSE_FILL,
        young_max_m3: Positive = YOUNG_MAX_M3,
        measurand: Measurand = "auto",
        grid_step: Positive | None = None,
    ) -> None:
        self.alpha = alpha
        self.spacing_factor = spacing_factor
        self.fill_voids = fill_voids
        self.sparse_fill = sparse_fill
        self.young_max_m3 = young_max_m3
        self.measurand = measurand
        self.grid_step = grid_step

    def _volume(self, xyz: np.ndarray) -> tuple[float, dict[str, Any]]:
        from scipy.spatial import QhullError, cKDTree

        from canopy_kit.volume.adaptive import point_spacing
        from canopy_kit.volume.hull import hull_volume
        from canopy_kit.volume.uncertainty import surface_fill

        tree = cKDTree(xyz, balanced_tree=False, compact_nodes=False)
        s = point_spacing(xyz, tree=tree)
        fill = surface_fill(xyz, spacing=s)
        small = hull_volume(xyz) <= self.young_max_m3
        chosen = self.measurand
        if chosen == "auto":
            sparse = self.sparse_fill is not None and fill < self.sparse_fill
            chosen = "ellipsoid" if sparse and small else "envelope"
        extra: dict[str, Any] = {"spacing": s, "surface_fill": fill, "estimate": chosen}
        if chosen == "ellipsoid":
            from canopy_kit.volume.ellipsoid import enclosing_ellipsoid

            try:
                ell = enclosing_ellipsoid(xyz)
            except QhullError as exc:
                return 0.0, {**extra, "reason": f"no enclosing ellipsoid: {exc}"}
            extra.update(measurand=ELLIPSOID_MEASURAND, crown_kind="sparse")
            return ell.volume, extra
        alpha = max(float(self.alpha), float(self.spacing_factor) * s)
        h = grid_step(xyz, alpha, self.grid_step)
        volume, info = alpha_hull_volume(xyz, alpha, h, tree=tree, fill_voids=self.fill_voids)
        void = float(info.get("void_m3", 0.0))
        if void > VOID_EXACT_SHARE * volume:  # the grid's estimate is coarse: measure it
            without = alpha_hull_volume(xyz, alpha, h, tree=tree, fill_voids=False)[0]
            void = max(volume - without, 0.0)
        extra.update(
            measurand=envelope_measurand(float(self.alpha)),
            alpha_used=alpha,
            thin_scan=alpha > float(self.alpha) * (1 + 1e-9),
            void_m3=void,
            volume_without_voids_m3=max(volume - void, 0.0),
            grid_step=h,
            crown_kind=envelope_kind(
                alpha > float(self.alpha) * (1 + 1e-9), small, float(np.ptp(xyz[:, 2]))
            ),
        )
        if volume <= 0.0:
            extra["reason"] = f"the foliage envelope is empty (alpha = {alpha:.2f} m)"
        return volume, extra
