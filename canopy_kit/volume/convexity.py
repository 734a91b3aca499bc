"""Is a thin sample of a crown a sample of a convex body?

Efron's correction of the convex hull (:func:`canopy_kit.volume.hull.sample_corrected_hull`)
estimates the volume of the convex hull of the body the points were drawn from. That is the
crown for a sparse young tree, whose few leaf clusters lie scattered through a rounded
envelope; it is not for a small crown with deep hollows between its lobes, whose points can
fill their hull's surface as thinly as a sparse tree's (docs/history/VOLUMES_LOG.md, "A small lobed
crown taken for a sparse one") and whose hull is 60 % more than the crown.

The test compares the sample with what a convex body would give. The α-solid of the points
(their α-hull with α = 4 × their own spacing) fills a share of their convex hull below 1 even
for a convex body, because a thin sample leaves gaps; how much below depends on the number of
points and the hull's shape, so the same share is measured on ``draws`` samples of as many
points drawn uniformly inside the same hull. ``z`` is how many of those samples' standard
deviations the crown's share lies below their mean: a strongly negative ``z`` says the body
has hollows a sample of this size resolves (simulated sparse crowns: z ≥ −2.6; a small
deep-lobed crown: −10 to −15; with 10 uniform samples instead of 40 their spread came out
too small now and then, and one sparse crown reached −6).

A skeleton of bare branches is as far from convex, and its corrected hull is what a user
means by its crown; but the α-hull of all its points (adaptive_alpha's α, a few point
spacings) is a set of thin tubes: 2-3 % of the convex hull on the real leafless broadleaf
``archi_tree_1`` and on a synthetic one, against 48-78 % on simulated lobed crowns and 80 %
and more on sparse ones. :func:`is_hollowed_body` asks for both: not convex, and solid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NULL_DRAWS = 40  # uniform samples of the hull that set the convex body's share (10 left z noisy)
HOLLOW_Z = -4.5  # at or below: not a sample of a convex body
SOLID_SHARE = 0.25  # α-hull / convex hull at or above: a body, not a skeleton of branches
ALPHA_SPACINGS = 4.0  # α of the share, in point spacings (as adaptive_alpha's)
GRID_CELLS = 24  # the share's grid: at least the largest extent / this, at most α / 4


@dataclass(frozen=True)
class SampleConvexity:
    """The sample's α-solid share of its hull against uniform samples of that hull."""

    share: float
    null_share: float
    null_sd: float
    n_points: int

    @property
    def z(self) -> float:
        """Standard deviations of the uniform samples' shares by which ``share`` lies below
        their mean (negative: less convex than a convex body's sample)."""
        if self.null_sd <= 0:
            return 0.0 if self.share >= self.null_share else -np.inf
        return (self.share - self.null_share) / self.null_sd


def alpha_share(points: np.ndarray) -> float:
    """Volume of the α-hull of ``points`` (α = ``ALPHA_SPACINGS`` × their spacing) over their
    convex hull's; raises scipy's QhullError when the points are degenerate."""
    from canopy_kit.volume.adaptive import point_spacing
    from canopy_kit.volume.alpha_hull import alpha_hull_volume
    from canopy_kit.volume.hull import hull_volume

    alpha = ALPHA_SPACINGS * point_spacing(points)
    step = max(alpha / 4.0, float(np.ptp(points, axis=0).max()) / GRID_CELLS)
    solid = alpha_hull_volume(points, alpha, step)[0]
    return solid / hull_volume(points)


def uniform_in_hull(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points drawn uniformly inside the convex hull of ``points`` (by rejection from
    their bounding box: a point is inside when it lies below every facet's plane; 100x faster
    than locating it in a Delaunay triangulation of the hull's corners, which scipy searches
    point by point, and the same points)."""
    from scipy.spatial import ConvexHull

    facets = ConvexHull(points).equations  # outward normal n, offset d: inside n.x + d <= 0
    lo, hi = points.min(axis=0), points.max(axis=0)
    drawn = np.empty((0, 3))
    while len(drawn) < n:
        batch = rng.uniform(lo, hi, (4 * n, 3))
        inside = np.all(batch @ facets[:, :3].T + facets[:, 3] <= 0.0, axis=1)
        drawn = np.vstack([drawn, batch[inside]])
    return drawn[:n]


def sample_convexity(points: np.ndarray, draws: int = NULL_DRAWS, seed: int = 0) -> SampleConvexity:
    """:class:`SampleConvexity` of already thinned ``points`` (module docstring); the same
    ``seed`` gives the same answer. Raises scipy's QhullError when the points are flat."""
    rng = np.random.default_rng(seed)
    null = [alpha_share(uniform_in_hull(points, len(points), rng)) for _ in range(draws)]
    return SampleConvexity(
        alpha_share(points), float(np.mean(null)), float(np.std(null, ddof=1)), len(points)
    )


def is_hollowed_body(test: SampleConvexity, alpha_hull_m3: float, hull_m3: float) -> bool:
    """A solid body with hollows: its thinned sample far from convex (``test``) and the
    α-hull of all its points at least ``SOLID_SHARE`` of their convex hull (not a skeleton).
    The α-hull, not the sample-corrected hull, measures such a crown."""
    return test.z <= HOLLOW_Z and alpha_hull_m3 >= SOLID_SHARE * hull_m3
