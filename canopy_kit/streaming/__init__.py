"""Streaming mode: each tree is emitted once the robot has passed it, with bounded memory.

``run_stream(config, bag, out)`` writes the per-tree table like the batch pipeline;
``TreeStream(config, bag)`` is the generator underneath (iterate it to get the trees as
they are finished). See ``streaming.layout`` for when a stretch of a row is finished.
"""

from __future__ import annotations

from canopy_kit.streaming.engine import StreamedTree, StreamSettings, TreeStream
from canopy_kit.streaming.run import final_table, run_stream

__all__ = ["StreamSettings", "StreamedTree", "TreeStream", "final_table", "run_stream"]
