"""Signs that a point cloud given as one tree holds more: several labelled trees, or ground.

``canopy-kit volume`` measures every point of its file as one crown; a whole plot or a map
with its ground gives a volume that is valid as geometry and meaningless as a tree's
(issue 48: 1,055 m³ "(valid)" for a plot carrying ``segment_id`` and ground classes).
"""

from __future__ import annotations

import numpy as np

from canopy_kit.core.cloud import PointCloud

# per-point tree labels written by canopy-kit (segment_id), lidR (treeID) and others (tree_id)
TREE_LABEL_FIELDS = ("segment_id", "treeID", "tree_id")
GROUND_CLASS = 2  # ASPRS LAS classification: ground
MAX_GROUND_SHARE = 0.01  # ground returns a cut-out tree may keep under its trunk


def not_one_tree(cloud: PointCloud) -> list[str]:
    """Why ``cloud`` looks like more than one tree: each per-point tree label field with more
    than one tree in it (``segment_id`` -1 and ``treeID``/``tree_id`` 0 or below are "no
    tree"), and ground points
    (LAS class 2) over 1 % of the points; empty when nothing says so."""
    reasons = []
    for name in TREE_LABEL_FIELDS:
        if name not in cloud.fields:
            continue
        labels = np.asarray(cloud.fields[name])
        first_tree = 0 if name == "segment_id" else 1  # canopy-kit: -1 none; lidR: 0 none
        trees = np.unique(labels[labels >= first_tree])
        if len(trees) > 1:
            reasons.append(f"its {name} field labels {len(trees)} trees")
    if "classification" in cloud.fields and len(cloud):
        ground = int(np.count_nonzero(np.asarray(cloud.fields["classification"]) == GROUND_CLASS))
        if ground > MAX_GROUND_SHARE * len(cloud):
            reasons.append(
                f"{ground:,} of its {len(cloud):,} points ({100 * ground / len(cloud):.0f} %) "
                "are classified ground (LAS class 2)"
            )
    return reasons
