"""Trellis posts among trunk detections: a post stands as a straight column through the canopy.

In the stem band a post (about 0.1 m thick) is a column like a trunk. What tells them apart
is what stands above the foot. Three rules, any makes a post:

- **Above the wall**: the canopy points above the detection hold a column whose top
  ``POLE_MIN_HEIGHT_M`` is narrower than ``TRELLIS_MAX_WIDTH_M`` (nothing that high in the
  ring around it): the trellis rule of the row profile (``segment.trellis_filter``), asked
  at the foot of each detection. A crown's top is far wider than a post for more than a few
  millimetres below its apex.
- **Through the wall** (:func:`stands_through_canopy`): a post is one straight vertical
  cylinder from the ground to its top, so in nearly every ``COLUMN_LAYER_M`` layer of the
  canopy above its foot the narrow cylinder around the foot holds several times the point
  density of the ring around it; a trunk divides into branches at the crown's base, and the
  foliage above it is as dense on its axis as beside it. This finds the posts that do not
  stand out of the wall (an end post as tall as the trees beside it). It is asked on
  trellised walls only (the ``trunk-midpoints`` cut): a trunk that goes on up through a
  sparse crown reads the same (2 of the 18 trunks of a pistachio session), and so would a
  wall tree's straight central leader seen through thin foliage (the simulator's wall trees
  have none: untested).
- **Leaning out of a row's end** (:func:`leans_out_of_row_end`, trellised walls only): an
  anchor post at a row's end is often set leaning outward along the row, against the wires'
  pull. Its foot is a row's last detection, and the same column test runs along lines
  leaning outward from the foot (``LEAN_MIN_DEG`` to ``LEAN_MAX_DEG``); above the wall's end
  the post stands in the open, and a layer where only the cylinder holds returns shows the
  column too. A trunk's foliage above it shows no slanted column either way.

The posts found keep their line (:class:`Posts`: an upright one on its detection, a leaning
one fitted to its returns), and the segmentation takes the returns along it out of the trees
(:meth:`Posts.on_post`, ``segment.verb``): a post is no canopy, also where it stands inside
the wall's foliage.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from canopy_kit.segment.rows import row_axis
from canopy_kit.segment.stems import StemDetections
from canopy_kit.segment.trellis_filter import POLE_MIN_HEIGHT_M, TRELLIS_MAX_WIDTH_M

MIN_TOP_RETURNS = 3  # returns of the column's top that show it is there
# Through the wall: the cylinder around the foot (a post 0.1-0.15 m thick, the foot's
# position a few cm off), the ring it is compared with, the layers, and how many of the
# occupied layers must show the column. Chosen on walls whose posts stand no higher than
# their trees (fruiting-wall seeds 0-2 with 3.4 m posts): posts showed the column in 79-100 %
# of 13-14 layers, trunks in 8-67 % (docs/SEGMENTATION.md, "Fruiting walls").
COLUMN_RADIUS_M = 0.08
COLUMN_RING_M = 0.4
COLUMN_LAYER_M = 0.2
COLUMN_DENSITY_RATIO = 3.0
COLUMN_MIN_LAYERS = 8
COLUMN_MIN_SHARE = 0.7
# Leaning out of a row's end: the leans tried (the trellis filter follows posts up to 35 deg)
# and the turns of the lean's direction about the row's axis, what makes a detection a row's
# end (:func:`row_end_outward`), and the returns a layer in the open needs in the cylinder.
# Chosen on fruiting-wall seeds 0-2 with end posts at 20 deg, then on seeds 707-720 (leans of
# 15-30 deg, posts 0.4-1.0 m past the end tree, a row starting with a gap): leaning posts showed
# the column in 79-100 % of their layers, row-end trunks (walls without posts) in at most 60 %
# (docs/SEGMENTATION.md, "Leaning end posts").
LEAN_MIN_DEG = 6.0
LEAN_MAX_DEG = 36.0
LEAN_STEP_DEG = 1.5
TURN_DEG = (-3.0, 0.0, 3.0)  # the lean's direction: the row's axis and a little either side
ROW_END_NEIGHBOUR_M = 4.0
ROW_END_ANGLE_DEG = 20.0
OPEN_LAYER_RETURNS = 2
_COLUMN_AREA = np.pi * COLUMN_RADIUS_M**2
_RING_AREA = np.pi * (COLUMN_RING_M**2 - (2.0 * COLUMN_RADIUS_M) ** 2)


def is_post(stems: StemDetections, canopy_xyz: np.ndarray) -> np.ndarray:
    """Per detection: whether a narrow column stands above it (a post, not a trunk).

    ``canopy_xyz`` are the canopy points ``(x, y, height above ground)``. The column is the
    points within half ``TRELLIS_MAX_WIDTH_M`` of the detection; its top
    ``POLE_MIN_HEIGHT_M`` holds at least ``MIN_TOP_RETURNS`` returns and nothing in the ring
    out to twice that width reaches as high.
    """
    out = np.zeros(len(stems), bool)
    if len(stems) == 0 or len(canopy_xyz) == 0:
        return out
    xyz = np.asarray(canopy_xyz, float)
    tree = cKDTree(xyz[:, :2])
    inner, outer = 0.5 * TRELLIS_MAX_WIDTH_M, 2.0 * TRELLIS_MAX_WIDTH_M
    for i, (near, around) in enumerate(
        zip(tree.query_ball_point(stems.xy, inner), tree.query_ball_point(stems.xy, outer))
    ):
        if len(near) < MIN_TOP_RETURNS:
            continue
        top = xyz[near, 2].max()
        level = top - POLE_MIN_HEIGHT_M
        in_column = int((xyz[near, 2] >= level).sum())
        in_ring = int((xyz[around, 2] >= level).sum()) - in_column
        out[i] = in_column >= MIN_TOP_RETURNS and in_ring == 0
    return out


def _layers(height: np.ndarray) -> tuple[np.ndarray, int]:
    """Each point's ``COLUMN_LAYER_M`` layer from the lowest of them up, and how many layers."""
    layer = np.floor((height - height.min()) / COLUMN_LAYER_M).astype(np.int64)
    return layer, int(layer.max()) + 1


def _column_and_ring(
    layer: np.ndarray, r: np.ndarray, n_layers: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per layer, from the points' distances ``r`` to a column's axis: the returns in the
    cylinder of ``COLUMN_RADIUS_M``, those in the ring from twice that out to ``COLUMN_RING_M``,
    and whether the cylinder holds more than ``COLUMN_DENSITY_RATIO`` times the ring's point
    density (per m² of plan)."""
    in_column = np.bincount(layer[r <= COLUMN_RADIUS_M], minlength=n_layers)
    in_ring = np.bincount(
        layer[(r > 2.0 * COLUMN_RADIUS_M) & (r <= COLUMN_RING_M)], minlength=n_layers
    )
    dense = in_column / _COLUMN_AREA > COLUMN_DENSITY_RATIO * (in_ring / _RING_AREA)
    return in_column, in_ring, dense


def stands_through_canopy(stems: StemDetections, canopy_xyz: np.ndarray) -> np.ndarray:
    """Per detection: whether a straight vertical column stands on it through the canopy.

    The canopy points within ``COLUMN_RING_M`` of the foot are cut into ``COLUMN_LAYER_M``
    layers (from the lowest to the highest of them); a layer with canopy in the ring from
    twice ``COLUMN_RADIUS_M`` out shows the column when the cylinder of ``COLUMN_RADIUS_M``
    around the foot holds returns at more than ``COLUMN_DENSITY_RATIO`` times the ring's
    point density (per m² of plan). Layers with nothing in the ring (a bare stem under a
    crown, a post's top above the wall) are not counted. A post: at least
    ``COLUMN_MIN_LAYERS`` layers hold canopy in the ring and at least ``COLUMN_MIN_SHARE`` of
    them show the column.
    """
    out = np.zeros(len(stems), bool)
    if len(stems) == 0 or len(canopy_xyz) == 0:
        return out
    xyz = np.asarray(canopy_xyz, float)
    tree = cKDTree(xyz[:, :2])
    for i, (foot, near) in enumerate(zip(stems.xy, tree.query_ball_point(stems.xy, COLUMN_RING_M))):
        if len(near) < MIN_TOP_RETURNS:
            continue
        pts = xyz[near]
        layer, n_layers = _layers(pts[:, 2])
        r = np.hypot(pts[:, 0] - foot[0], pts[:, 1] - foot[1])
        _, in_ring, dense = _column_and_ring(layer, r, n_layers)
        occupied = in_ring > 0  # layers of canopy beside it: not a bare stem under a crown
        shows = dense & occupied
        out[i] = (
            occupied.sum() >= COLUMN_MIN_LAYERS and shows.sum() >= COLUMN_MIN_SHARE * occupied.sum()
        )
    return out


def row_end_outward(xy: np.ndarray) -> np.ndarray:
    """Per detection: the unit vector pointing out of its row when it is a row's last
    detection, else NaN. Along the rows' axis (:func:`~canopy_kit.segment.rows.row_axis`) a last detection
    has at least two detections within ``ROW_END_ANGLE_DEG`` of it on one side (the nearest
    within ``ROW_END_NEIGHBOUR_M``, the others within twice that) and none on the other; the
    vector is the principal axis through it and those (two trunks a few cm off the row line
    would turn it by several degrees)."""
    xy = np.asarray(xy, float)
    out = np.full((len(xy), 2), np.nan)
    if len(xy) < 3:
        return out
    row = row_axis(xy)
    cos_max = np.cos(np.radians(ROW_END_ANGLE_DEG))
    for i, near in enumerate(cKDTree(xy).query_ball_point(xy, 2.0 * ROW_END_NEIGHBOUR_M)):
        near = np.array([j for j in near if j != i], int)
        step = xy[near] - xy[i]
        dist = np.hypot(*step.T)
        along = step @ row / np.maximum(dist, 1e-9)
        ahead, behind = along >= cos_max, along <= -cos_max
        if ahead.any() == behind.any():
            continue
        line = ahead if ahead.any() else behind
        if line.sum() < 2 or dist[line].min() > ROW_END_NEIGHBOUR_M:
            continue
        pts = np.vstack([xy[i], xy[near[line]]])
        axis = np.linalg.svd(pts - pts.mean(0), full_matrices=False)[2][0]
        out[i] = -axis if axis @ step[line].mean(0) > 0 else axis
    return out


def _slanted_column_share(
    pts: np.ndarray, foot: np.ndarray, outward: np.ndarray
) -> tuple[float, np.ndarray]:
    """The best share of layers showing a column along a line leaning out of ``foot`` by
    ``outward`` (a unit vector), over the leans tried (0 with fewer than ``COLUMN_MIN_LAYERS``
    layers occupied), and that line's tilt (horizontal metres per metre of height)."""
    layer, n_layers = _layers(pts[:, 2])
    best, best_tilt = 0.0, np.zeros(2)
    turns = np.radians(TURN_DEG)
    directions = [
        np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ outward for a in turns
    ]
    for lean, direction in itertools.product(
        np.arange(LEAN_MIN_DEG, LEAN_MAX_DEG, LEAN_STEP_DEG), directions
    ):
        tilt = np.tan(np.radians(lean)) * direction
        centre = foot + pts[:, 2:3] * tilt
        r = np.hypot(*(pts[:, :2] - centre).T)
        in_column, in_ring, dense = _column_and_ring(layer, r, n_layers)
        in_open = (in_ring == 0) & (in_column >= OPEN_LAYER_RETURNS)
        occupied = (in_ring > 0) | in_open
        shows = in_open | dense
        share = float((shows & occupied).sum() / max(occupied.sum(), 1))
        if occupied.sum() >= COLUMN_MIN_LAYERS and share > best:
            best, best_tilt = share, tilt
    return best, best_tilt


def _fitted_line(
    pts: np.ndarray, foot: np.ndarray, tilt: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The post's line refined on its returns: within twice ``COLUMN_RADIUS_M`` of the line
    tried (``foot``, ``tilt``), x and y fitted against the height by least squares, once more
    without the returns farther than ``COLUMN_RADIUS_M`` (a leaf, a wire). The lean steps and
    turns tried leave a line some cm off the post at its top."""
    for reach in (2.0 * COLUMN_RADIUS_M, COLUMN_RADIUS_M):
        near = np.hypot(*(pts[:, :2] - foot - pts[:, 2:3] * tilt).T) <= reach
        if near.sum() < 2 * COLUMN_MIN_LAYERS:
            break
        design = np.column_stack([np.ones(int(near.sum())), pts[near, 2]])
        (foot, tilt), *_ = np.linalg.lstsq(design, pts[near, :2], rcond=None)
    return foot, tilt


def leaning_posts(stems: StemDetections, canopy_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per detection: the foot (x, y at the ground) and tilt (horizontal metres per metre of
    height) of the straight column leaning out of it, away from its row, when it is the row's
    last detection (:func:`row_end_outward`) and the column shows in at least
    ``COLUMN_MIN_SHARE`` of at least ``COLUMN_MIN_LAYERS`` layers for one lean between
    ``LEAN_MIN_DEG`` and ``LEAN_MAX_DEG`` (the layer test of :func:`stands_through_canopy`,
    along the slanted line; a layer with returns in the cylinder and none in the ring counts
    as showing it); NaN otherwise."""
    feet, tilts = np.full((len(stems), 2), np.nan), np.full((len(stems), 2), np.nan)
    if len(stems) == 0 or len(canopy_xyz) == 0:
        return feet, tilts
    xyz = np.asarray(canopy_xyz, float)
    tree = cKDTree(xyz[:, :2])
    outward = row_end_outward(stems.xy)
    reach = np.tan(np.radians(LEAN_MAX_DEG)) * float(xyz[:, 2].max())
    for i in np.flatnonzero(np.isfinite(outward[:, 0])):
        foot, u = stems.xy[i], outward[i]
        near = tree.query_ball_point(foot + 0.5 * reach * u, 0.5 * reach + COLUMN_RING_M)
        if len(near) < MIN_TOP_RETURNS:
            continue
        share, tilt = _slanted_column_share(xyz[near], foot, u)
        if share >= COLUMN_MIN_SHARE:
            feet[i], tilts[i] = _fitted_line(xyz[near], foot, tilt)
    return feet, tilts


def leans_out_of_row_end(stems: StemDetections, canopy_xyz: np.ndarray) -> np.ndarray:
    """Per detection: whether a post leans out of it, away from its row (:func:`leaning_posts`)."""
    return np.isfinite(leaning_posts(stems, canopy_xyz)[1][:, 0])


@dataclass(frozen=True)
class Posts:
    """Posts found among the trunk detections: the foot (x, y) and the tilt of each (horizontal
    metres per metre of height along the post; zero for an upright one)."""

    xy: np.ndarray
    tilt: np.ndarray

    def __len__(self) -> int:
        return len(self.xy)

    def on_post(
        self, xy: np.ndarray, height: np.ndarray, radius: float = COLUMN_RADIUS_M
    ) -> np.ndarray:
        """Which points (``xy``, ``height`` above the ground) lie within ``radius`` of a post's
        axis at their height (a post's own returns, and the few leaves touching it)."""
        xy = np.asarray(xy, float)
        height = np.asarray(height, float)
        hit = np.zeros(len(xy), bool)
        if len(self) == 0 or len(xy) == 0:
            return hit
        top = float(height.max())
        tree = cKDTree(xy)
        for foot, tilt in zip(self.xy, self.tilt):
            # the ball round the axis's middle, from the ground to the highest point
            reach = radius + 0.5 * float(np.hypot(*tilt)) * top
            near = np.asarray(tree.query_ball_point(foot + 0.5 * tilt * top, reach), int)
            if len(near) == 0:
                continue
            axis = foot + height[near, None] * tilt
            hit[near[np.hypot(*(xy[near] - axis).T) <= radius]] = True
        return hit


def no_posts() -> Posts:
    """No post found."""
    return Posts(np.zeros((0, 2)), np.zeros((0, 2)))


def split_posts(
    stems: StemDetections, canopy_xyz: np.ndarray, through_canopy: bool = False
) -> tuple[StemDetections, Posts]:
    """The detections that are not posts, and the posts: :func:`is_post`, and with
    ``through_canopy`` (a trellised wall) :func:`stands_through_canopy` (upright, at the
    detection, as the first) and :func:`leaning_posts` (along their fitted lines)."""
    post = is_post(stems, canopy_xyz)
    feet, tilt = stems.xy.copy(), np.zeros((len(stems), 2))
    if through_canopy:
        post |= stands_through_canopy(stems, canopy_xyz)
        lean_feet, lean_tilt = leaning_posts(stems, canopy_xyz)
        lean = np.isfinite(lean_tilt[:, 0]) & ~post
        feet[lean], tilt[lean] = lean_feet[lean], lean_tilt[lean]
        post |= lean
    return stems.select(~post), Posts(feet[post], tilt[post])


def without_posts(
    stems: StemDetections, canopy_xyz: np.ndarray, through_canopy: bool = False
) -> StemDetections:
    """The detections that are not posts (:func:`split_posts`)."""
    return split_posts(stems, canopy_xyz, through_canopy)[0]
