"""Trellis posts among trunk detections: a post stands as a straight column through the canopy.

In the stem band a post (about 0.1 m thick) is a column like a trunk. What tells them apart
is what stands above the foot. Two rules, either makes a post:

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
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

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
    inner_area = np.pi * COLUMN_RADIUS_M**2
    ring_area = np.pi * (COLUMN_RING_M**2 - (2.0 * COLUMN_RADIUS_M) ** 2)
    for i, (foot, near) in enumerate(zip(stems.xy, tree.query_ball_point(stems.xy, COLUMN_RING_M))):
        if len(near) < MIN_TOP_RETURNS:
            continue
        pts = xyz[near]
        r = np.hypot(pts[:, 0] - foot[0], pts[:, 1] - foot[1])
        layer = np.floor((pts[:, 2] - pts[:, 2].min()) / COLUMN_LAYER_M).astype(np.int64)
        n_layers = int(layer.max()) + 1
        in_column = np.bincount(layer[r <= COLUMN_RADIUS_M], minlength=n_layers) / inner_area
        in_ring = np.bincount(layer[r > 2.0 * COLUMN_RADIUS_M], minlength=n_layers) / ring_area
        occupied = in_ring > 0  # layers of canopy beside it: not a bare stem under a crown
        shows = (in_column > COLUMN_DENSITY_RATIO * in_ring) & occupied
        out[i] = (
            occupied.sum() >= COLUMN_MIN_LAYERS and shows.sum() >= COLUMN_MIN_SHARE * occupied.sum()
        )
    return out


def without_posts(
    stems: StemDetections, canopy_xyz: np.ndarray, through_canopy: bool = False
) -> StemDetections:
    """The detections that are not posts: not :func:`is_post`, and with ``through_canopy``
    (a trellised wall) not :func:`stands_through_canopy` either."""
    post = is_post(stems, canopy_xyz)
    if through_canopy:
        post |= stands_through_canopy(stems, canopy_xyz)
    return stems.select(~post)
