"""``OrchardStore``: sessions, trees, observations, volumes and aerial checks in one DuckDB file.

Each session is written in one transaction: a failure or a crash half-way leaves the
store as it was before (DuckDB discards an uncommitted transaction on recovery).
"""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.core.extras import needs_extra
from canopy_kit.errors import InputError
from canopy_kit.store.identity import MatchSettings, TreeMatch, match_trees
from canopy_kit.store.schema import (
    AERIAL_COLUMNS,
    AERIAL_TEXT_COLUMNS,
    SCHEMA_VERSION,
    TABLES,
    UPGRADES,
)
from canopy_kit.store.upgrade import UpgradeReport, upgrade_store

_FAULT: Callable[[str], None] | None = None  # tests: called between the writes of an ingest


@dataclass
class SessionRecord:
    """What the store needs to know about a session besides its trees."""

    session_id: str
    orchard: str
    date: dt.date
    bag: str = ""
    preset: str = ""
    run_dir: str = ""
    metrics: dict[str, Any] = field(default_factory=dict)


@dataclass
class IngestReport:
    """What one ingest found: matches, new, missing and replanted trees, the alignment."""

    session_id: str
    orchard: str
    n_trees: int
    matched: dict[int, int]  # session row -> tree_id
    new: list[int]  # tree ids created for trees not known before
    missing: list[int]  # known tree ids not found where the session looked
    replanted: list[tuple[int, int]]  # (new tree_id, tree_id it replaces)
    found_again: list[int]
    alignment: dict[str, Any]

    def summary(self) -> dict[str, Any]:
        """Counts and the alignment as plain data."""
        return {
            "session_id": self.session_id,
            "orchard": self.orchard,
            "n_trees": self.n_trees,
            "n_matched": len(self.matched),
            "n_new": len(self.new),
            "n_missing": len(self.missing),
            "n_replanted": len(self.replanted),
            "missing": self.missing,
            "replanted": self.replanted,
            "alignment": self.alignment,
        }


def volume_methods(trees: pd.DataFrame) -> dict[str, str]:
    """Volume column -> method name of a per-tree table (``volume_alpha_m3`` is alpha_shape);
    the interval's bounds and the void-free volume are not methods."""
    from canopy_kit.volume.verb import DERIVED_VOLUME_COLUMNS, VOLUME_COLUMN

    reverse = {v: k for k, v in VOLUME_COLUMN.items()}
    return {
        c: reverse.get(c, c[len("volume_") : -len("_m3")])
        for c in trees.columns
        if c.startswith("volume_") and c.endswith("_m3") and c not in DERIVED_VOLUME_COLUMNS
    }


def interval_frame(trees: pd.DataFrame, methods: dict[str, str]) -> pd.DataFrame:
    """Per tree: the method its interval bounds (``volume_method``), ``low_m3``, ``high_m3``
    and ``interval_flags``; no rows when the table has no interval columns."""
    from canopy_kit.volume.uncertainty import INTERVAL_COLUMNS as IC

    if not {IC["method"], IC["low"], IC["high"]} <= set(trees.columns):
        return pd.DataFrame(columns=["row", "method", "low_m3", "high_m3", "interval_flags"])
    flags = trees[IC["flags"]] if IC["flags"] in trees else pd.Series("", index=trees.index)
    frame = pd.DataFrame(
        {
            "row": np.arange(len(trees)),
            "method": trees[IC["method"]].astype(str).to_numpy(),
            "low_m3": trees[IC["low"]].to_numpy(float),
            "high_m3": trees[IC["high"]].to_numpy(float),
            "interval_flags": flags.fillna("").astype(str).to_numpy(),
        }
    )
    return frame[frame["method"].isin(set(methods.values()))]


class OrchardStore:
    """A DuckDB file (``orchard.duckdb``) holding every session of one or more orchards."""

    def __init__(
        self,
        path: str | Path = "orchard.duckdb",
        read_only: bool = False,
        volume_method: str = "alpha_shape",
    ) -> None:
        with needs_extra("batch"):
            import duckdb

        self.path = Path(path)
        if read_only and not self.path.exists():
            raise InputError(f"{self.path}: store does not exist")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self.con = duckdb.connect(str(self.path), read_only=read_only)
        except duckdb.Error as exc:
            raise InputError(f"{self.path}: cannot open the store ({exc})") from None
        self.volume_method = volume_method
        self.upgrade: UpgradeReport | None = None  # what opening it for writing upgraded
        if read_only:
            try:
                self._check_version()
            except Exception as exc:
                self.__exit__(type(exc), exc, None)
                raise
        else:
            try:
                self._create()
            except Exception as exc:
                self.__exit__(type(exc), exc, None)  # closes; a damaged file is bad input
                raise

    def _create(self) -> None:
        with self.transaction():
            tables = {r[0] for r in self.run("SELECT table_name FROM information_schema.tables")}
            if tables and "meta" not in tables:  # another program's DuckDB file: leave it be
                raise InputError(
                    f"{self.path}: not an orchard store (it holds tables but no 'meta' table)"
                )
            for name, columns in TABLES.items():
                self.run(f"CREATE TABLE IF NOT EXISTS {name} ({columns})")
            found = self.one("SELECT value FROM meta WHERE key = 'schema_version'")
            if found is None:
                self.run("INSERT INTO meta VALUES ('schema_version', ?)", [SCHEMA_VERSION])
            elif found[0] in UPGRADES:
                self.upgrade = upgrade_store(self, found[0])
            elif found[0] != SCHEMA_VERSION:
                raise InputError(
                    f"{self.path}: store schema version {found[0]}, this canopy-kit "
                    f"reads version {SCHEMA_VERSION}"
                )

    def _check_version(self) -> None:
        """Opened read only: an InputError unless the store is of this version."""
        has_meta = self.one(
            "SELECT count(*) FROM information_schema.tables WHERE table_name = 'meta'"
        )
        if not has_meta or not has_meta[0]:
            raise InputError(f"{self.path}: not an orchard store (it has no 'meta' table)")
        found = self.one("SELECT value FROM meta WHERE key = 'schema_version'")
        if found is None or found[0] == SCHEMA_VERSION:
            return
        how = (
            f"upgrade it with 'canopy-kit store upgrade {self.path}'"
            if found[0] in UPGRADES
            else f"this canopy-kit reads version {SCHEMA_VERSION}"
        )
        raise InputError(f"{self.path}: store schema version {found[0]}; {how}")

    def close(self) -> None:
        """Close the file (committed data is already on disk)."""
        self.con.close()

    def __enter__(self) -> OrchardStore:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object
    ) -> None:
        self.close()
        damaged = damaged_store_error(self.path, exc) if exc is not None else None
        if damaged is not None:
            raise damaged from None

    @contextmanager
    def transaction(self) -> Iterator[None]:
        """Everything inside is written together or not at all."""
        self.run("BEGIN TRANSACTION")
        try:
            yield
        except BaseException as exc:
            damaged = damaged_store_error(self.path, exc)
            try:
                self.run("ROLLBACK")
            except Exception:
                if damaged is None:
                    raise exc from None
            if damaged is not None:
                raise damaged from None
            raise
        self.run("COMMIT")

    def run(self, sql: str, params: Any = None) -> list[tuple]:
        """Execute one statement and fetch its result (DuckDB wants results consumed)."""
        return self.con.execute(sql, params or []).fetchall()

    def one(self, sql: str, params: Any = None) -> tuple | None:
        """The first row of a query's result (None when empty)."""
        rows = self.run(sql, params)
        return rows[0] if rows else None

    def query(self, sql: str, params: list[Any] | None = None) -> pd.DataFrame:
        """Run SQL on the store and return a DataFrame."""
        return self.con.execute(sql, params or []).df()

    def has_session(self, session_id: str) -> bool:
        """Whether ``session_id`` is already stored."""
        return self.one("SELECT count(*) FROM sessions WHERE session_id = ?", [session_id])[0] > 0

    # -- ingest ------------------------------------------------------------------------------
    def ingest(
        self, record: SessionRecord, trees: pd.DataFrame, settings: MatchSettings | None = None
    ) -> IngestReport:
        """Add one session's per-tree table: match its trees to the orchard's, write it all."""
        settings = settings or MatchSettings()
        settings.check()
        where = f"{self.path}: session {record.session_id!r}"
        if self.has_session(record.session_id):
            raise InputError(f"{where} is already in the store")
        missing_cols = {"lat", "lon", "n_points"} - set(trees.columns)
        if missing_cols:
            raise InputError(f"{where}: per-tree table has no {sorted(missing_cols)[0]!r} column")
        trees = trees.reset_index(drop=True)
        if len(trees) and not np.isfinite(trees[["lat", "lon"]].to_numpy(float)).all():
            raise InputError(
                f"{where}: trees without latitude/longitude (a map without GNSS) "
                "cannot be placed in the orchard"
            )
        with self.transaction():
            frame = self._orchard_frame(record.orchard, trees)
            xy = (
                frame.to_local(trees["lat"].to_numpy(float), trees["lon"].to_numpy(float))[:, :2]
                if len(trees)
                else np.zeros((0, 2))
            )
            known = self.con.execute(
                "SELECT tree_id, x, y, status FROM trees WHERE orchard = ? AND status <> 'removed' "
                "ORDER BY tree_id",
                [record.orchard],
            ).df()
            match = match_trees(xy, known[["x", "y"]].to_numpy(float), settings)
            report = self._write(record, trees, xy, known, match)
        return report

    def _orchard_frame(self, orchard: str, trees: pd.DataFrame) -> Any:
        from canopy_kit.core.geo import LocalFrame

        row = self.one(
            "SELECT epsg, origin_easting, origin_northing FROM orchards WHERE orchard = ?",
            [orchard],
        )
        if row is not None:
            return LocalFrame(int(row[0]), float(row[1]), float(row[2]))
        if len(trees) == 0:
            raise InputError(
                f"{self.path}: orchard {orchard!r} is new and its first session has "
                "no trees to place it"
            )
        exact = LocalFrame.at(float(trees["lat"].mean()), float(trees["lon"].mean()))
        frame = LocalFrame(
            exact.epsg,
            float(np.round(exact.origin_easting)),
            float(np.round(exact.origin_northing)),
        )
        self.run(
            "INSERT INTO orchards VALUES (?, ?, ?, ?, now())",
            [orchard, frame.epsg, frame.origin_easting, frame.origin_northing],
        )
        return frame

    def _write(
        self,
        record: SessionRecord,
        trees: pd.DataFrame,
        xy: np.ndarray,
        known: pd.DataFrame,
        match: TreeMatch,
    ) -> IngestReport:
        sid = record.session_id
        methods = volume_methods(trees)
        ids, kind, dist, report = self._identify(record, trees, known, match, methods)
        obs = observations_frame(sid, trees, ids, kind, dist, xy, match.aligned)
        self._insert("observations", obs)
        _fault("observations")
        vols = [
            pd.DataFrame(
                {
                    "session_id": sid,
                    "tree_id": ids,
                    "method": m,
                    "volume_m3": trees[c].to_numpy(float),
                    "row": np.arange(len(trees)),
                }
            )
            for c, m in methods.items()
        ]
        if vols:
            table = pd.concat(vols, ignore_index=True).merge(
                interval_frame(trees, methods), on=["row", "method"], how="left"
            )
            self._insert("volumes", table.drop(columns="row"))
        self._write_aerial(sid, trees, ids)
        _fault("volumes")
        self._update_trees(record, obs, report)
        self._write_events(report)
        self._write_session_row(record, report, match)
        _fault("sessions")
        return report

    def _identify(
        self,
        record: SessionRecord,
        trees: pd.DataFrame,
        known: pd.DataFrame,
        match: TreeMatch,
        methods: dict[str, str],
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, IngestReport]:
        """Each session tree's tree_id, kind (matched, found_again, replanted, new) and match
        distance, and the ingest report listing them. A missing tree found again with less
        than half its last volume is a replant: a new tree that replaces it."""
        primary = self._primary_column(methods)
        next_id = int(self.one("SELECT coalesce(max(tree_id), 0) + 1 FROM trees")[0])
        ids = np.full(len(trees), -1, dtype=np.int64)
        kind = np.full(len(trees), "new", dtype=object)
        dist = np.full(len(trees), np.nan)
        report = IngestReport(
            record.session_id,
            record.orchard,
            len(trees),
            {},
            [],
            [],
            [],
            [],
            asdict(match.alignment),
        )
        last_volume = self._last_volumes(known["tree_id"].tolist(), primary, methods)
        for (si, kj), d in zip(match.pairs, match.distances):
            tid, status = int(known["tree_id"].iat[kj]), known["status"].iat[kj]
            dist[si] = d
            if status == "missing":
                old, now = last_volume.get(tid), trees[primary].iat[si] if primary else np.nan
                if old is not None and np.isfinite(now) and now < 0.5 * old:
                    ids[si], kind[si] = next_id, "replanted"
                    report.replanted.append((next_id, tid))
                    next_id += 1
                    continue
                report.found_again.append(tid)
                kind[si] = "found_again"
            else:
                kind[si] = "matched"
            ids[si] = tid
            report.matched[int(si)] = tid
        for si in match.new:
            ids[si] = next_id
            report.new.append(next_id)
            next_id += 1
        report.missing = [int(known["tree_id"].iat[k]) for k in match.missing]
        return ids, kind, dist, report

    def _write_events(self, report: IngestReport) -> None:
        """The session's events: trees new, missing, replanted and found again."""
        sid = report.session_id
        events = (
            [(sid, t, "new", "") for t in report.new]
            + [(sid, t, "missing", "") for t in report.missing]
            + [(sid, new, "replanted", f"replaces tree {old}") for new, old in report.replanted]
            + [(sid, t, "found_again", "") for t in report.found_again]
        )
        if events:
            self._insert(
                "events", pd.DataFrame(events, columns=["session_id", "tree_id", "kind", "detail"])
            )

    def _write_session_row(
        self, record: SessionRecord, report: IngestReport, match: TreeMatch
    ) -> None:
        """The session's row: its record, the counts of the report and the alignment."""
        a = match.alignment
        self.run(
            "INSERT INTO sessions VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, now(), ?)",
            [
                record.session_id,
                record.orchard,
                record.date,
                record.bag,
                record.preset,
                record.run_dir,
                report.n_trees,
                len(report.matched),
                len(report.new),
                len(report.missing),
                len(report.replanted),
                a.method,
                a.dx,
                a.dy,
                a.rotation_deg,
                None if not np.isfinite(a.rms_m) else a.rms_m,
                json.dumps(record.metrics, default=str),
            ],
        )

    def _primary_column(self, methods: dict[str, str]) -> str | None:
        by_method = {m: c for c, m in methods.items()}
        return by_method.get(self.volume_method) or next(iter(methods), None)

    def _last_volumes(
        self, tree_ids: list[int], column: str | None, methods: dict[str, str]
    ) -> dict[int, float]:
        if column is None or not tree_ids:
            return {}
        rows = self.con.execute(
            "SELECT v.tree_id, v.volume_m3 FROM volumes v JOIN sessions s USING (session_id) "
            "WHERE v.method = ? AND v.tree_id IN (SELECT unnest(?)) "
            "QUALIFY row_number() OVER (PARTITION BY v.tree_id ORDER BY s.date DESC) = 1",
            [methods[column], tree_ids],
        ).fetchall()
        return {int(t): float(v) for t, v in rows if v is not None}

    def _write_aerial(self, sid: str, trees: pd.DataFrame, ids: np.ndarray) -> None:
        present = [c for c in AERIAL_COLUMNS if c in trees.columns]
        if "aerial_sphere_volume_m3" not in present:
            return
        ok = trees["aerial_sphere_volume_m3"].notna().to_numpy()
        if not ok.any():
            return
        table = pd.DataFrame({"session_id": sid, "tree_id": ids[ok]})
        for col, name in AERIAL_COLUMNS.items():
            table[name] = trees.loc[ok, col].to_numpy(float) if col in trees else np.nan
        for col, name in AERIAL_TEXT_COLUMNS.items():
            table[name] = (
                trees.loc[ok, col].fillna("").astype(str).to_numpy() if col in trees else ""
            )
        self._insert("aerial", table)

    def _update_trees(self, record: SessionRecord, obs: pd.DataFrame, report: IngestReport) -> None:
        sid = record.session_id
        fresh = obs[obs["kind"].isin(["new", "replanted"])]
        if len(fresh):
            replaces = dict(report.replanted)
            table = pd.DataFrame(
                {
                    "tree_id": fresh["tree_id"].to_numpy(),
                    "orchard": record.orchard,
                    "x": fresh["x"].to_numpy(),
                    "y": fresh["y"].to_numpy(),
                    "lat": fresh["lat"].to_numpy(),
                    "lon": fresh["lon"].to_numpy(),
                    "row": fresh["row"].to_numpy(),
                    "label": fresh["label"].to_numpy(),
                    "first_session": sid,
                    "last_seen": sid,
                    "status": "present",
                    "replaces": [replaces.get(int(t)) for t in fresh["tree_id"]],
                }
            )
            self._insert("trees", table)
        seen = obs[obs["kind"].isin(["matched", "found_again"])]["tree_id"].tolist()
        if seen:
            # A known tree's position: the mean of its aligned observations.
            self.run(
                "UPDATE trees SET status = 'present', last_seen = ?, x = o.mx, y = o.my "
                "FROM (SELECT tree_id, avg(x) AS mx, avg(y) AS my FROM observations "
                "      WHERE tree_id IN (SELECT unnest(?)) GROUP BY tree_id) o "
                "WHERE trees.tree_id = o.tree_id",
                [sid, seen],
            )
        if report.missing:
            self.run(
                "UPDATE trees SET status = 'missing' WHERE tree_id IN (SELECT unnest(?))",
                [report.missing],
            )
        if report.replanted:
            self.run(
                "UPDATE trees SET status = 'removed' WHERE tree_id IN (SELECT unnest(?))",
                [[old for _, old in report.replanted]],
            )

    def _insert(self, table: str, frame: pd.DataFrame) -> None:
        self.con.register("_incoming", frame)
        try:
            cols = ", ".join(frame.columns)
            self.run(f"INSERT INTO {table} ({cols}) SELECT {cols} FROM _incoming")
        finally:
            self.con.unregister("_incoming")


def observations_frame(
    sid: str,
    trees: pd.DataFrame,
    ids: np.ndarray,
    kind: np.ndarray,
    dist: np.ndarray,
    xy: np.ndarray,
    aligned: np.ndarray,
) -> pd.DataFrame:
    """One observation row per session tree: its tree_id and kind, position in the orchard's
    frame (``aligned``) and the session's (``xy``), match distance, size and flags."""
    n = len(trees)
    return pd.DataFrame(
        {
            "session_id": sid,
            "tree_id": ids,
            "kind": kind,
            "segment": trees.get("segment", pd.Series(np.arange(n))).to_numpy(),
            "label": trees.get("label", pd.Series([""] * n)).astype(str).to_numpy(),
            "row": trees.get("row", pd.Series(np.full(n, -1))).to_numpy(),
            "x": aligned[:, 0],
            "y": aligned[:, 1],
            "x_session": xy[:, 0],
            "y_session": xy[:, 1],
            "lat": trees["lat"].to_numpy(float),
            "lon": trees["lon"].to_numpy(float),
            "match_distance_m": dist,
            "n_points": trees["n_points"].to_numpy(),
            "height_m": trees.get("height_m", pd.Series(np.full(n, np.nan))).to_numpy(),
            "crown_diameter_m": trees.get(
                "crown_diameter_m", pd.Series(np.full(n, np.nan))
            ).to_numpy(),
            "flags": _text(trees, "volume_flags"),
            **observation_extras(trees),
        }
    )


def observation_extras(trees: pd.DataFrame) -> pd.DataFrame:
    """Per tree of a per-tree table: ``crown_contact`` (NaN where absent) and ``trunk_flags``
    (empty where absent), as the store's observations keep them."""
    contact = trees["crown_contact"] if "crown_contact" in trees else np.nan
    return pd.DataFrame(
        {
            "crown_contact": pd.Series(contact, index=trees.index, dtype=float).to_numpy(),
            "trunk_flags": _text(trees, "trunk_flags"),
        }
    )


def _text(trees: pd.DataFrame, column: str) -> np.ndarray:
    """A text column of the per-tree table, empty strings where absent or missing."""
    if column not in trees:
        return np.full(len(trees), "", dtype=object)
    return trees[column].fillna("").astype(str).to_numpy()


def damaged_store_error(path: Path, exc: BaseException) -> InputError | None:
    """An ``InputError`` naming the store when DuckDB failed on the file itself, else None.

    A store cut short (a copy interrupted, a full disk) opens, and fails at the first read
    of a block past its end; that is bad input, not a fault of canopy-kit."""
    with needs_extra("batch"):
        import duckdb

    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    if (
        isinstance(exc, (duckdb.IOException, duckdb.SerializationException))
        or "corrupt" in text.lower()
    ):
        return InputError(f"{path}: the store is damaged or cut short ({text})")
    return None


def _fault(stage: str) -> None:
    if _FAULT is not None:
        _FAULT(stage)
