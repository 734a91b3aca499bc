"""The map as every run folder writes it: one tree identity and LAS classes per point.

``segment_id`` is the ``segment`` (``segment_id``) of the tree table, -1 off the trees;
``classification`` the LAS code the segmentation decided (``segment.classes``). The
simulator's per-point truth id, ``tree_id`` in memory, is written as ``truth_tree_id``, the
name trees.csv gives the matched true tree: the tables' ``tree_id`` is the ``r0-L0`` label,
and one name must not mean two things in a folder.
"""

from __future__ import annotations

import numpy as np

from canopy_kit.core.cloud import PointCloud
from canopy_kit.segment.result import Segmentation

TRUE_TREE_ID = "truth_tree_id"  # the simulator's truth id, as written
SIM_TREE_ID = "tree_id"  # ... and as the simulator and the mapping keep it in memory


def labelled_map(cloud: PointCloud, seg: Segmentation, with_height: bool = False) -> PointCloud:
    """``cloud`` with ``segment_id``, ``classification`` (and ``height_above_ground``), the
    truth id renamed ``truth_tree_id``."""
    fields = {(TRUE_TREE_ID if k == SIM_TREE_ID else k): v for k, v in cloud.fields.items()}
    fields["segment_id"] = np.asarray(seg.labels).astype(np.int32)
    if seg.classification is not None:
        fields["classification"] = np.asarray(seg.classification, dtype=np.uint8)
    if with_height:
        fields["height_above_ground"] = np.asarray(seg.height).astype(np.float32)
    return PointCloud(cloud.xyz, fields, cloud.crs, cloud.origin.copy())


def truth_ids(cloud: PointCloud) -> np.ndarray | None:
    """The per-point simulator truth id of a cloud read back (or in memory), None without one."""
    for name in (TRUE_TREE_ID, SIM_TREE_ID):
        if name in cloud.fields:
            return np.asarray(cloud.fields[name])
    return None
