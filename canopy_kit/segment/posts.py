"""Trellis posts among trunk detections: a post stands as a narrow column above the canopy.

In the stem band a post (about 0.1 m thick) is a column like a trunk. What tells them apart
is the top: a post stands on through the wall and out above it, while a crown's top is far
wider than a post for more than a few millimetres below its apex. So a detection is a post
when the canopy points above it hold a column whose top ``POLE_MIN_HEIGHT_M`` is narrower
than ``TRELLIS_MAX_WIDTH_M`` (nothing that high in the ring around it): the trellis rule of
the row profile (``segment.trellis_filter``), asked at the foot of each detection. A post
that does not reach above the wall is not told from a trunk here.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from canopy_kit.segment.stems import StemDetections
from canopy_kit.segment.trellis_filter import POLE_MIN_HEIGHT_M, TRELLIS_MAX_WIDTH_M

MIN_TOP_RETURNS = 3  # returns of the column's top that show it is there


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


def without_posts(stems: StemDetections, canopy_xyz: np.ndarray) -> StemDetections:
    """The detections that are not posts (:func:`is_post`)."""
    return stems.select(~is_post(stems, canopy_xyz))
