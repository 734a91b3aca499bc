"""Bringing a store written by an older canopy-kit to this version's schema.

The steps (``schema.UPGRADES``) add columns and drop what an older version stored wrongly;
the new columns are then filled again from each session's own run, where its folder
(``sessions.run_dir``) still holds the per-tree table (``trees.parquet``): the interval of the
recommended estimator, the crown contact, the trunk flags and the aerial crown flag, joined to
the store's rows by the session's ``segment``. Sessions whose run folder is gone keep them
empty. Runs inside the caller's transaction: an upgrade that fails leaves the store as it was.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.store.schema import SCHEMA_VERSION, UPGRADES, V1_PSEUDO_METHODS


@dataclass
class UpgradeReport:
    """What an upgrade did: from which version, the rows it dropped, the sessions refilled."""

    from_version: str
    dropped_rows: int = 0
    refilled: list[str] = field(default_factory=list)  # sessions whose run gave the columns
    not_refilled: list[str] = field(default_factory=list)  # their run folder is gone

    def as_dict(self) -> dict[str, Any]:
        """Plain data (batch.json, the CLI)."""
        return {
            "from_version": self.from_version,
            "to_version": SCHEMA_VERSION,
            "dropped_rows": self.dropped_rows,
            "refilled_sessions": list(self.refilled),
            "sessions_left_empty": list(self.not_refilled),
        }


def upgrade_store(store: Any, version: str) -> UpgradeReport:
    """Upgrade ``store`` (an open, writable ``OrchardStore`` inside a transaction) from
    ``version`` to ``SCHEMA_VERSION``, step by step, and refill the new columns from the
    sessions' runs; the meta table then says the new version."""
    report = UpgradeReport(version)
    report.dropped_rows = store.one(
        "SELECT count(*) FROM volumes WHERE method IN (SELECT unnest(?))",
        [list(V1_PSEUDO_METHODS)],
    )[0]
    while version in UPGRADES:
        version, statements = UPGRADES[version]
        for statement in statements:
            store.run(statement)
    for session_id, run_dir in store.run("SELECT session_id, run_dir FROM sessions"):
        table = Path(run_dir or "") / "trees.parquet"
        if run_dir and table.is_file():
            _refill_session(store, session_id, pd.read_parquet(table))
            report.refilled.append(session_id)
        else:
            report.not_refilled.append(session_id)
    store.run("UPDATE meta SET value = ? WHERE key = 'schema_version'", [SCHEMA_VERSION])
    return report


def _refill_session(store: Any, session_id: str, trees: pd.DataFrame) -> None:
    """The new columns of one stored session from its run's per-tree table, by segment."""
    from canopy_kit.store.db import interval_frame, observation_extras, volume_methods

    ids = store.query(
        "SELECT segment, tree_id FROM observations WHERE session_id = ?", [session_id]
    )
    if "segment" not in trees or ids.empty:
        return
    tree_of = dict(zip(ids["segment"].astype(int), ids["tree_id"].astype(int), strict=True))
    segment = trees["segment"].to_numpy(int)
    known = np.array([s in tree_of for s in segment], bool)
    tree_id = np.array([tree_of.get(int(s), -1) for s in segment], np.int64)
    bounds = interval_frame(trees, volume_methods(trees))
    bounds = bounds.assign(tree_id=tree_id[bounds["row"].to_numpy(int)])[known[bounds["row"]]]
    _update(
        store,
        "volumes",
        bounds.drop(columns="row"),
        ["low_m3", "high_m3", "interval_flags"],
        ["tree_id", "method"],
        session_id,
    )
    extra = observation_extras(trees).assign(tree_id=tree_id)[known]
    _update(store, "observations", extra, ["crown_contact", "trunk_flags"], ["tree_id"], session_id)
    if "aerial_crown_flag" in trees:
        flags = pd.DataFrame(
            {"tree_id": tree_id, "crown_flag": trees["aerial_crown_flag"].fillna("").astype(str)}
        )[known]
        _update(store, "aerial", flags, ["crown_flag"], ["tree_id"], session_id)


def _update(
    store: Any, table: str, frame: pd.DataFrame, columns: list[str], keys: list[str], sid: str
) -> None:
    """``UPDATE table SET columns`` from ``frame``, matched on ``keys`` within session ``sid``."""
    if frame.empty:
        return
    store.con.register("_refill", frame[keys + columns])
    try:
        assign = ", ".join(f"{c} = r.{c}" for c in columns)
        match = " AND ".join(f"{table}.{k} = r.{k}" for k in keys)
        store.run(
            f"UPDATE {table} SET {assign} FROM _refill r WHERE {table}.session_id = ? AND {match}",
            [sid],
        )
    finally:
        store.con.unregister("_refill")
