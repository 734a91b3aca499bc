"""canopy-kit: per-tree canopy volumes from mobile LiDAR drives through orchards.

The public API, in the order a session is processed (the notebooks use these names)::

    import canopy_kit as ck

    config = ck.load_preset("adaptive", {"volume": {"params": {"alpha_shape": {"alpha": 0.8}}}})
    results = ck.run(config, "drive.bag", "out/run")      # every stage and every output
    ctx = ck.load_context("out/demo/almond_session")       # a run's stages, to explore
    seg = ck.segment_trees(ck.read_cloud("map.laz"), ck.make_segmenter("dbscan", {"eps": 0.5}))
    ck.estimate_volume(xyz, "alpha_shape", alpha=0.9).volume_m3

Importing the package is cheap: each name is imported on first use, and heavy libraries
(open3d, pycolmap, pyvista) only inside the functions that need them.
"""

from __future__ import annotations

import importlib
from typing import Any

from canopy_kit.errors import (
    CanopyKitError,
    ConfigError,
    InputError,
    PluginError,
    ProcessingError,
)

__version__ = "0.1.0"

# public name -> "module:attribute" (a bare module path: the module itself)
_PUBLIC = {
    # settings
    "load_preset": "canopy_kit.config:load_preset",
    "preset_names": "canopy_kit.config:preset_names",
    "PipelineConfig": "canopy_kit.config:PipelineConfig",
    # the whole chain
    "run": "canopy_kit.pipeline:run",
    "compute": "canopy_kit.pipeline:compute",
    "load_context": "canopy_kit.pipeline.explore:load_context",
    # inputs
    "open_bag": "canopy_kit.io.bag:open_bag",
    "read_scan": "canopy_kit.io.bag:read_scan",
    "read_cloud": "canopy_kit.io.clouds:read_cloud",
    "write_cloud": "canopy_kit.io.clouds:write_cloud",
    "describe_path": "canopy_kit.io.info:describe_path",
    "PointCloud": "canopy_kit.core.cloud:PointCloud",
    "LocalFrame": "canopy_kit.core.geo:LocalFrame",
    "local_frame_for": "canopy_kit.mapping.gnss:local_frame_for",
    # segmentation
    "make_segmenter": "canopy_kit.segment.verb:make_segmenter",
    "segment_trees": "canopy_kit.segment.verb:segment",  # canopy_kit.segment is the subpackage
    "score_point_labels": "canopy_kit.evaluate.segmentation_score:score_point_labels",
    # volumes
    "estimate_volume": "canopy_kit.volume:estimate_volume",
    "estimator": "canopy_kit.volume:estimator",
    "tree_metrics": "canopy_kit.volume:tree_metrics",
    "alpha_curve": "canopy_kit.volume:alpha_curve",
    "auto_alpha": "canopy_kit.volume:auto_alpha",
    "measure_tree": "canopy_kit.volume.verb:measure_tree",
    "measured_points": "canopy_kit.volume.verb:measured_points",
    "tree_points": "canopy_kit.volume.verb:tree_points",
    "volume_column": "canopy_kit.volume.verb:volume_column",
    "volume_methods": "canopy_kit.volume.verb:volume_methods",
    "hull_mesh": "canopy_kit.volume.hull:hull_mesh",
    "PAPER_ALPHA_M": "canopy_kit.plugins.params:PAPER_ALPHA_M",
    "ALPHA_COLUMN": "canopy_kit.volume.verb:ALPHA_COLUMN",
    "CONVEX_HULL_COLUMN": "canopy_kit.volume.verb:CONVEX_HULL_COLUMN",
    # accuracy and truth
    "accuracy_table": "canopy_kit.volume.accuracy:accuracy_table",
    "family_accuracy_table": "canopy_kit.volume.accuracy:family_accuracy_table",
    "load_truth": "canopy_kit.evaluate.truth:load_truth",
    # plugins and the orchard store
    "plugins": "canopy_kit.plugins",
    "store": "canopy_kit.store",
}

__all__ = [
    "CanopyKitError",
    "ConfigError",
    "InputError",
    "PluginError",
    "ProcessingError",
    "__version__",
    *sorted(_PUBLIC),
]


def __getattr__(name: str) -> Any:
    """Import a public name on first use (PEP 562), so ``import canopy_kit`` stays cheap."""
    target = _PUBLIC.get(name)
    if target is None:
        raise AttributeError(f"module 'canopy_kit' has no attribute {name!r}")
    module, _, attribute = target.partition(":")
    value = importlib.import_module(module)
    if attribute:
        value = getattr(value, attribute)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
