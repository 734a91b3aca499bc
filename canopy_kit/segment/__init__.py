"""Tree segmentation: ground and trunk removal, segmenter plugins, rows and per-tree labels.

``segment(cloud, make_segmenter("adaptive"))`` (``canopy_kit.segment.verb``) returns a
:class:`~canopy_kit.segment.result.Segmentation`. Segmenters are plugins of the
``canopy_kit.segmenters`` entry-point group (built-ins: ``dbscan``, ``dbscan_spectral``,
``adaptive``). See docs/SEGMENTATION.md.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

#: Public names, loaded on first use: importing a submodule (a plugin) loads nothing more.
_EXPORTS = {
    "segment": "canopy_kit.segment.verb",
    "make_segmenter": "canopy_kit.segment.verb",
    "Segmentation": "canopy_kit.segment.result",
    "TreeRecord": "canopy_kit.segment.result",
}
__all__ = ["Segmentation", "TreeRecord", "make_segmenter", "segment"]


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'canopy_kit.segment' has no attribute {name!r}")
    return getattr(import_module(_EXPORTS[name]), name)


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])
