"""The orchard store: every session's trees in one DuckDB file, each tree tracked over time.

``OrchardStore(path).ingest(SessionRecord(...), trees)`` adds a session's per-tree table
(``canopy_kit.pipeline.run(...).trees``) in one transaction, matching its trees to the
orchard's known ones by position after aligning the session (``store.identity``). The
queries (``growth``, ``row_growth``, ``changes``) return DataFrames; ``export`` writes them
to Parquet or CSV.
"""

from __future__ import annotations

from canopy_kit.store.db import IngestReport, OrchardStore, SessionRecord, volume_methods
from canopy_kit.store.identity import Alignment, MatchSettings, TreeMatch, match_trees
from canopy_kit.store.queries import (
    changes,
    consistency_problems,
    export,
    growth,
    interval_method,
    orchard_trees,
    row_growth,
    sessions,
    stored_methods,
)

__all__ = [
    "Alignment",
    "IngestReport",
    "MatchSettings",
    "OrchardStore",
    "SessionRecord",
    "TreeMatch",
    "changes",
    "consistency_problems",
    "export",
    "growth",
    "interval_method",
    "match_trees",
    "orchard_trees",
    "row_growth",
    "sessions",
    "stored_methods",
    "volume_methods",
]
