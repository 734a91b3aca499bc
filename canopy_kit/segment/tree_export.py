"""One LAZ per tree: ``trees/<tree_id>.laz``, the tree's map points in map.laz's coordinates.

Each file holds the points the segmentation gave the tree (every attribute, the LAS class
and ``segment_id`` as in map.laz), with map.laz's CRS, origin and 1 mm scale, so
``canopy-kit volume trees/<tree_id>.laz`` reads it. trees.csv measures its volumes on these
points thinned to ``volume.voxel_size`` (0.1 m by default): ``canopy-kit volume
--voxel-size`` does the same thinning.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from canopy_kit.core.cloud import PointCloud
from canopy_kit.segment.labelled import labelled_map
from canopy_kit.segment.result import Segmentation


def tree_file_name(tree_id: str) -> str:
    """``<tree_id>.laz``, any character unsafe in a file name replaced by ``_``."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", str(tree_id)) + ".laz"


def export_trees(folder: str | Path, cloud: PointCloud, seg: Segmentation) -> dict[str, Path]:
    """Write every tree's points of ``cloud`` (the segmented map) into ``folder``; returns
    ``{"trees/<name>.laz": path}``. LAZ files of trees an earlier run had are removed."""
    from canopy_kit.io.las import las_ready, write_las

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    labelled = las_ready(labelled_map(cloud, seg))
    order = np.argsort(seg.labels, kind="stable")
    bounds = np.searchsorted(
        seg.labels[order], [t.segment_id for t in seg.trees] + [t.segment_id + 1 for t in seg.trees]
    )
    n = len(seg.trees)
    paths = {}
    for k, tree in enumerate(seg.trees):
        members = np.sort(order[bounds[k] : bounds[n + k]])
        if len(members) == 0:
            continue
        path = folder / tree_file_name(tree.tree_id)
        paths[f"{folder.name}/{path.name}"] = write_las(path, labelled.select(members))
    for stale in set(folder.glob("*.laz")) - set(paths.values()):
        stale.unlink()
    return paths
