"""LAS classification codes per map point, as the segmentation decided them.

ASPRS LAS 1.4 codes: 2 ground (within the ground RANSAC threshold of the ground model),
5 high vegetation (a point of a segmented tree crown), 4 medium vegetation (the trunk and
low-vegetation band: above the ground, below the canopy, not in a crown), 1 unclassified
(everything else: canopy-height points no tree took, points above ``max_canopy_height`` or
below the ground).
"""

from __future__ import annotations

import numpy as np

UNCLASSIFIED, GROUND, MEDIUM_VEGETATION, HIGH_VEGETATION = 1, 2, 4, 5


def classify_points(
    labels: np.ndarray, height: np.ndarray, ground_threshold: float, min_canopy_height: float
) -> np.ndarray:
    """LAS class per point from its segment label and height above the ground model."""
    labels = np.asarray(labels)
    height = np.asarray(height, dtype=np.float64)
    classes = np.full(len(labels), UNCLASSIFIED, dtype=np.uint8)
    classes[np.abs(height) <= ground_threshold] = GROUND
    classes[(height > ground_threshold) & (height < min_canopy_height)] = MEDIUM_VEGETATION
    classes[labels >= 0] = HIGH_VEGETATION
    return classes
