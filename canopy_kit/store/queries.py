"""Questions asked of the store: growth per tree and per row, changes, consistency; exports."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd

from canopy_kit.errors import InputError

# Per tree and session: the volume (with its interval where the run gave one for this method,
# and the crown's contact with its neighbours') and how it changed since the tree's first and
# previous observation (dates in session order). change_since_first: 'grew' / 'shrank' when
# this visit's interval lies wholly above / below that of the first visit that had one (a
# store upgraded from version 1 may hold early visits without), 'within the intervals' when
# they overlap (the change is not told from the measurement's error), NULL on a visit without
# an interval and on the first one with.
GROWTH_SQL = """
SELECT t.orchard, v.tree_id, t."row" AS tree_row, t.label AS tree_label, t.status,
       s.session_id, s.date, o.x, o.y, o.height_m, o.crown_diameter_m, o.kind,
       v.method, v.volume_m3, v.low_m3, v.high_m3, v.interval_flags, o.crown_contact,
       first_value(v.volume_m3) OVER w AS first_volume_m3,
       v.volume_m3 / nullif(first_value(v.volume_m3) OVER w, 0) - 1 AS growth_since_first,
       v.volume_m3 / nullif(lag(v.volume_m3) OVER w, 0) - 1 AS growth_since_previous,
       date_diff('day', first_value(s.date) OVER w, s.date) AS days_since_first,
       CASE WHEN v.low_m3 IS NULL OR v.high_m3 IS NULL OR count(v.low_m3) OVER w < 2 THEN NULL
            WHEN v.low_m3 > first_value(v.high_m3 IGNORE NULLS) OVER w THEN 'grew'
            WHEN v.high_m3 < first_value(v.low_m3 IGNORE NULLS) OVER w THEN 'shrank'
            ELSE 'within the intervals' END AS change_since_first
FROM volumes v
JOIN sessions s USING (session_id)
JOIN trees t USING (tree_id)
JOIN observations o ON o.session_id = v.session_id AND o.tree_id = v.tree_id
WHERE v.method = $method AND ($orchard IS NULL OR t.orchard = $orchard)
WINDOW w AS (PARTITION BY v.tree_id ORDER BY s.date, s.session_id)
ORDER BY t.orchard, v.tree_id, s.date
"""

ROW_GROWTH_SQL = f"""
SELECT orchard, tree_row, session_id, date, count(*) AS n_trees,
       sum(volume_m3) AS total_volume_m3, avg(volume_m3) AS mean_volume_m3,
       median(growth_since_first) AS median_growth_since_first
FROM ({GROWTH_SQL})
GROUP BY orchard, tree_row, session_id, date
ORDER BY orchard, tree_row, date
"""

CHANGES_SQL = """
SELECT s.orchard, s.date, e.session_id, e.kind, e.tree_id, e.detail, t.x, t.y, t.label AS tree_label
FROM events e JOIN sessions s USING (session_id) LEFT JOIN trees t USING (tree_id)
WHERE ($orchard IS NULL OR s.orchard = $orchard)
ORDER BY s.date, e.kind, e.tree_id
"""


def growth(store: Any, method: str | None = None, orchard: str | None = None) -> pd.DataFrame:
    """Volume per tree and session with growth since the first and the previous visit."""
    return store.con.execute(
        GROWTH_SQL, {"method": method or store.volume_method, "orchard": orchard}
    ).df()


def row_growth(store: Any, method: str | None = None, orchard: str | None = None) -> pd.DataFrame:
    """Per row (the row a tree had when first seen) and session: count, total, median growth."""
    return store.con.execute(
        ROW_GROWTH_SQL, {"method": method or store.volume_method, "orchard": orchard}
    ).df()


def changes(store: Any, orchard: str | None = None) -> pd.DataFrame:
    """New, missing, replanted and found-again trees, session by session."""
    return store.con.execute(CHANGES_SQL, {"orchard": orchard}).df()


SESSIONS_SQL = """
SELECT session_id, orchard, date, n_trees, n_matched, n_new, n_missing, n_replanted,
       round(align_dx, 2) AS dx, round(align_dy, 2) AS dy, round(align_rms_m, 3) AS rms_m
FROM sessions ORDER BY orchard, date
"""


def sessions(store: Any) -> pd.DataFrame:
    """One row per ingested session: its trees, matches, changes and alignment to the orchard."""
    return store.con.execute(SESSIONS_SQL).df()


def stored_methods(store: Any) -> list[str]:
    """The volume methods the store holds, sorted."""
    rows = store.con.execute("SELECT DISTINCT method FROM volumes ORDER BY method").fetchall()
    return [r[0] for r in rows]


def interval_method(store: Any) -> str | None:
    """The volume method whose rows carry the runs' intervals (the runs' recommended
    estimator; the most common one if the runs differ), None when no row has one."""
    row = store.one(
        "SELECT method FROM volumes WHERE low_m3 IS NOT NULL "
        "GROUP BY method ORDER BY count(*) DESC, method LIMIT 1"
    )
    return row[0] if row else None


def orchard_trees(store: Any, orchard: str) -> pd.DataFrame:
    """The orchard's known trees: id, position (orchard frame) and status."""
    return store.con.execute(
        "SELECT tree_id, x, y, status FROM trees WHERE orchard = ? ORDER BY tree_id", [orchard]
    ).df()


def export(
    store: Any, what: str, path: str | Path, method: str | None = None, orchard: str | None = None
) -> Path:
    """Write ``growth``, ``row_growth``, ``changes``, ``trees`` or ``sessions`` to Parquet or CSV.

    The format follows the suffix (``.parquet`` or ``.csv``); written under a temporary
    name and renamed.
    """
    from canopy_kit.core.atomic import atomic_path

    path = Path(path)
    fmt = {".parquet": "PARQUET", ".csv": "CSV"}.get(path.suffix.lower())
    if fmt is None:
        raise InputError(f"{path}: export format must be .parquet or .csv")
    params: dict[str, Any] = {}
    if what in ("growth", "row_growth"):
        sql = GROWTH_SQL if what == "growth" else ROW_GROWTH_SQL
        params = {"method": method or store.volume_method, "orchard": orchard}
    elif what == "changes":
        sql, params = CHANGES_SQL, {"orchard": orchard}
    elif what in ("trees", "sessions"):
        sql = f"SELECT * FROM {what} ORDER BY 1"
    else:
        raise InputError(
            f"export: {what!r} is not one of growth, row_growth, changes, trees, sessions"
        )
    with atomic_path(path) as tmp:
        literal = str(tmp).replace("'", "''")
        options = "FORMAT PARQUET" if fmt == "PARQUET" else "FORMAT CSV, HEADER"
        store.run(f"COPY ({sql}) TO '{literal}' ({options})", params)
    return path


def consistency_problems(store: Any) -> list[str]:
    """What is wrong in the store's references and counts (empty when consistent)."""
    checks = {
        "observations of unknown sessions": "SELECT count(*) FROM observations "
        "WHERE session_id NOT IN (SELECT session_id FROM sessions)",
        "observations of unknown trees": "SELECT count(*) FROM observations "
        "WHERE tree_id NOT IN (SELECT tree_id FROM trees)",
        "volumes without an observation": "SELECT count(*) FROM volumes v "
        "ANTI JOIN observations o USING (session_id, tree_id)",
        "events of unknown sessions": "SELECT count(*) FROM events "
        "WHERE session_id NOT IN (SELECT session_id FROM sessions)",
        "trees never observed": "SELECT count(*) FROM trees "
        "WHERE tree_id NOT IN (SELECT tree_id FROM observations)",
        "sessions whose tree count differs from their observations": "SELECT count(*) "
        "FROM sessions s LEFT JOIN (SELECT session_id, count(*) AS n "
        "FROM observations GROUP BY session_id) o USING (session_id) "
        "WHERE s.n_trees <> coalesce(o.n, 0)",
        "trees seen twice in one session": "SELECT count(*) FROM (SELECT session_id, tree_id FROM observations "
        "GROUP BY ALL HAVING count(*) > 1)",
    }
    out = []
    for name, sql in checks.items():
        n = store.one(sql)[0]
        if n:
            out.append(f"{n} {name}")
    return out
