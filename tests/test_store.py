"""The orchard store on synthetic plantings: identity over visits, changes, transactions, queries."""

from __future__ import annotations

import datetime as dt
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from canopy_kit.core.geo import LocalFrame
from canopy_kit.errors import InputError
from canopy_kit.store import (
    MatchSettings,
    OrchardStore,
    SessionRecord,
    changes,
    consistency_problems,
    export,
    growth,
    interval_method,
    match_trees,
    row_growth,
)

FRAME = LocalFrame.at(37.281, -120.42)
ROWS, PER_ROW = 4, 6
LAYOUT = np.array([[r * 6.0, i * 5.0] for r in range(ROWS) for i in range(PER_ROW)])
VOLUME = np.random.default_rng(1).uniform(20.0, 40.0, len(LAYOUT))


def visit(shift=(0.0, 0.0), rotation_deg=0.0, absent=(), young=(), growth_factor=1.0, seed=0):
    """A session's per-tree table: the layout seen through a GNSS shift and rotation."""
    rng = np.random.default_rng(seed)
    a = np.radians(rotation_deg)
    r = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    centre = LAYOUT.mean(axis=0)
    xy = (LAYOUT - centre) @ r.T + centre + shift + rng.normal(0, 0.1, LAYOUT.shape)
    volume = VOLUME * growth_factor
    volume[list(young)] = 2.0
    lat, lon, _ = FRAME.to_wgs84(np.column_stack([xy, np.zeros(len(xy))]))
    table = pd.DataFrame(
        {
            "segment": np.arange(len(xy)),
            "label": [f"L{i}" for i in range(len(xy))],
            "row": np.repeat(np.arange(ROWS), PER_ROW),
            "lat": lat,
            "lon": lon,
            "n_points": 1000,
            "height_m": 3.0,
            "crown_diameter_m": 3.5,
            "volume_convex_hull_m3": 1.05 * volume,
            "volume_alpha_m3": volume,
            "volume_flags": "",
            "truth": np.arange(len(xy)),
        }
    )
    return table.drop(index=list(absent)).reset_index(drop=True)


def record(sid, month):
    return SessionRecord(sid, "block-a", dt.date(2025, month, 1), bag=f"{sid}.bag")


@pytest.fixture()
def three_visits(tmp_path):
    """Spring (first), summer (tree 7 gone, GNSS off by 1.4 m and 0.6°), autumn (replanted)."""
    store = OrchardStore(tmp_path / "orchard.duckdb")
    tables = {
        "spring": visit(seed=1),
        "summer": visit((1.2, -0.8), 0.6, absent=(7,), growth_factor=1.2, seed=2),
        "autumn": visit((-0.9, 1.4), -0.5, young=(7,), growth_factor=1.4, seed=3),
    }
    reports = {
        sid: store.ingest(record(sid, m), tables[sid])
        for sid, m in (("spring", 4), ("summer", 6), ("autumn", 9))
    }
    yield store, tables, reports
    store.close()


def test_trees_keep_their_ids_across_shifted_visits(three_visits):
    store, tables, reports = three_visits
    obs = store.query("SELECT session_id, tree_id, segment FROM observations")
    ids = {}
    for sid, table in tables.items():
        got = obs[obs.session_id == sid].set_index("segment")["tree_id"]
        for seg, truth in zip(table["segment"], table["truth"]):
            ids.setdefault(int(truth), {})[sid] = int(got[seg])
    persistent = [t for t in ids if t != 7]
    assert all(len(set(ids[t].values())) == 1 for t in persistent)
    assert reports["summer"].alignment["rms_m"] < 0.25  # the residual is the 0.1 m jitter
    assert abs(reports["summer"].alignment["rotation_deg"] + 0.6) < 0.3


def test_removed_tree_is_missing_then_replaced(three_visits):
    store, _, reports = three_visits
    old = store.one("SELECT tree_id FROM observations WHERE session_id = 'spring' AND segment = 7")[
        0
    ]
    assert reports["summer"].missing == [old] and reports["summer"].new == []
    assert len(reports["autumn"].replanted) == 1 and reports["autumn"].replanted[0][1] == old
    new = reports["autumn"].replanted[0][0]
    status = dict(store.run("SELECT tree_id, status FROM trees"))
    assert status[old] == "removed" and status[new] == "present"
    kinds = changes(store).groupby("session_id")["kind"].apply(set).to_dict()
    assert kinds["summer"] == {"missing"} and kinds["autumn"] == {"replanted"}
    assert consistency_problems(store) == []


def test_growth_per_tree_and_row(three_visits, tmp_path):
    store, _, _ = three_visits
    g = growth(store)
    kept = g[(g.status == "present") & (g.session_id == "autumn") & (g.kind == "matched")]
    assert np.allclose(kept["growth_since_first"], 0.4)  # volumes x1.4 since spring
    summer = g[(g.session_id == "summer")]
    assert np.allclose(summer["growth_since_previous"], 0.2)
    rows = row_growth(store, method="convex_hull")
    assert set(rows["tree_row"]) == set(range(ROWS))
    assert (rows.groupby("tree_row")["n_trees"].max() == PER_ROW).all()
    for suffix in ("parquet", "csv"):
        path = export(store, "growth", tmp_path / f"growth.{suffix}")
        back = pd.read_parquet(path) if suffix == "parquet" else pd.read_csv(path)
        assert len(back) == len(g)
    with pytest.raises(InputError, match=r"growth\.xlsx: export format must be \.parquet or \.csv"):
        export(store, "growth", tmp_path / "growth.xlsx")


def test_a_failed_ingest_leaves_the_store_as_it_was(three_visits, monkeypatch):
    import canopy_kit.store.db as db

    store, _, _ = three_visits
    before = {
        t: store.query(f"SELECT * FROM {t} ORDER BY ALL")
        for t in ("sessions", "trees", "observations", "volumes")
    }

    def fail(stage):
        if stage == "volumes":
            raise RuntimeError("disk full")

    monkeypatch.setattr(db, "_FAULT", fail)
    with pytest.raises(RuntimeError, match="disk full"):
        store.ingest(record("winter", 12), visit(growth_factor=1.5, seed=4))
    for table, frame in before.items():
        pd.testing.assert_frame_equal(store.query(f"SELECT * FROM {table} ORDER BY ALL"), frame)
    assert not store.has_session("winter")


def test_a_crash_mid_ingest_leaves_the_previous_state(tmp_path):
    path = tmp_path / "orchard.duckdb"
    with OrchardStore(path) as store:
        store.ingest(record("spring", 4), visit(seed=1))
    tests = str(Path(__file__).parent)
    script = f"""
import os, sys
sys.path.insert(0, {tests!r})
import canopy_kit.store.db as db
from canopy_kit.store import OrchardStore
from test_store import record, visit
db._FAULT = lambda stage: os._exit(9) if stage == "volumes" else None
OrchardStore({str(path)!r}).ingest(record("summer", 6), visit(seed=2))
"""
    proc = subprocess.run(
        [sys.executable, "-c", script], check=False, capture_output=True, text=True
    )
    assert proc.returncode == 9, proc.stderr
    with OrchardStore(path, read_only=True) as store:
        assert store.query("SELECT session_id FROM sessions")["session_id"].tolist() == ["spring"]
        assert store.one("SELECT count(*) FROM observations")[0] == len(LAYOUT)
        assert consistency_problems(store) == []


def test_errors_name_the_store_and_session(tmp_path):
    with OrchardStore(tmp_path / "o.duckdb") as store:
        store.ingest(record("spring", 4), visit())
        with pytest.raises(
            InputError, match=r"o\.duckdb: session 'spring' is already in the store"
        ):
            store.ingest(record("spring", 4), visit())
        no_gnss = visit().assign(lat=np.nan)
        with pytest.raises(InputError, match=r"session 'summer': trees without latitude/longitude"):
            store.ingest(record("summer", 6), no_gnss)
    with pytest.raises(InputError, match=r"nothing\.duckdb: store does not exist"):
        OrchardStore(tmp_path / "nothing.duckdb", read_only=True)


def test_a_store_cut_short_is_bad_input_naming_it(tmp_path):
    """A copy interrupted half-way: every read or write that reaches past the end is an
    InputError naming the file (exit 2 from the CLI), never DuckDB's raw IOException."""
    from test_cli_foundation import run_cli

    with OrchardStore(tmp_path / "full.duckdb") as store:
        for sid, month in (("spring", 4), ("summer", 6)):
            store.ingest(record(sid, month), visit(seed=month))
    data = (tmp_path / "full.duckdb").read_bytes()
    cut = tmp_path / "cut.duckdb"
    cut.write_bytes(data[: int(0.4 * len(data))])
    with pytest.raises(InputError, match=r"cut\.duckdb: the store is damaged or cut short"):
        with OrchardStore(cut, read_only=True) as store:
            growth(store)
    with pytest.raises(InputError, match=r"cut\.duckdb: the store is damaged or cut short"):
        with OrchardStore(cut) as store:
            store.ingest(record("autumn", 9), visit(seed=9))
    result = run_cli("store", "growth", str(cut))
    assert result.returncode == 2 and result.stderr.startswith(
        f"error: {cut}: the store is damaged"
    ), result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_regular_grid_offset_is_not_taken_for_the_neighbour():
    # A 2.3 m shift along rows of trees 5 m apart: the neighbour is 2.7 m the other way.
    session = LAYOUT + [0.0, 2.3]
    m = match_trees(session, LAYOUT, MatchSettings(refine="translation"))
    assert len(m.pairs) == len(LAYOUT)
    assert np.array_equal(m.pairs[:, 0], m.pairs[:, 1])
    assert abs(m.alignment.dy + 2.3) < 1e-6


def test_trees_outside_the_visited_area_are_not_missing():
    half = LAYOUT[LAYOUT[:, 0] < 7]  # only the first two rows driven this time
    m = match_trees(half, LAYOUT, MatchSettings())
    assert len(m.pairs) == len(half) and len(m.missing) == 0
    gone = np.delete(half, 3, axis=0)
    m = match_trees(gone, LAYOUT, MatchSettings())
    assert m.missing.tolist() == [3]


def _with_interval(table: pd.DataFrame, contact: float = 0.1) -> pd.DataFrame:
    """A visit's table with what a run adds: the alpha shape's interval, the void-free
    volume, crown contact, trunk flags and the aerial check with its crown flag."""
    v = table["volume_alpha_m3"].to_numpy()
    n = len(table)
    return table.assign(
        volume_method="alpha_shape",
        volume_low_m3=0.9 * v,
        volume_high_m3=1.2 * v,
        volume_without_voids_m3=0.8 * v,
        volume_interval_flags=["interwoven crown" if i % 2 else "" for i in range(n)],
        crown_contact=np.linspace(0.0, contact, n),
        trunk_flags="",
        aerial_diameter_m=3.4,
        aerial_sphere_volume_m3=20.6,
        aerial_crown_flag=["merged" if i == 0 else "" for i in range(n)],
    )


def test_intervals_contact_and_crown_flags_are_stored_and_bounds_are_no_method(tmp_path):
    spring = _with_interval(visit(seed=1))
    with OrchardStore(tmp_path / "o.duckdb") as store:
        store.ingest(record("spring", 4), spring)
        methods = set(store.query("SELECT DISTINCT method FROM volumes")["method"])
        assert methods == {"alpha_shape", "convex_hull"}  # not 'low', 'high', 'without_voids'
        g = growth(store).sort_values("tree_id").reset_index(drop=True)
        # tree ids are given in the table's order on a first session
        assert np.allclose(g["low_m3"], spring["volume_low_m3"])
        assert np.allclose(g["high_m3"], spring["volume_high_m3"])
        assert g["interval_flags"].tolist() == spring["volume_interval_flags"].tolist()
        assert np.allclose(g["crown_contact"], spring["crown_contact"])
        hull = growth(store, method="convex_hull")
        assert hull["low_m3"].isna().all() and hull["high_m3"].isna().all()
        flags = store.query("SELECT crown_flag FROM aerial ORDER BY tree_id")["crown_flag"]
        assert flags.tolist() == spring["aerial_crown_flag"].tolist()


def test_a_version_1_store_is_upgraded_when_written_and_refused_when_read(tmp_path):
    """Two sessions as version 1 stored them (no interval columns; the interval's bounds and
    the void-free volume stored as methods 'low', 'high', 'without_voids'), one whose run
    folder still holds its trees.parquet, one whose folder is gone. Read only, the store is
    refused with the command that upgrades it; `canopy-kit store upgrade` adds the columns,
    drops the pseudo-methods, refills the first session's columns from its run (equal to the
    table's) and says which session stays empty."""
    from test_cli_foundation import run_cli

    from canopy_kit.store.schema import V1_PSEUDO_METHODS

    path = tmp_path / "old.duckdb"
    tables = {"spring": _with_interval(visit(seed=1)), "summer": _with_interval(visit(seed=2))}
    runs = {sid: tmp_path / f"run_{sid}" for sid in tables}
    runs["spring"].mkdir()
    tables["spring"].to_parquet(runs["spring"] / "trees.parquet")
    with OrchardStore(path) as store:
        for sid, month in (("spring", 4), ("summer", 6)):
            rec = SessionRecord(sid, "block-a", dt.date(2025, month, 1), run_dir=str(runs[sid]))
            store.ingest(rec, tables[sid])
        n_volumes = store.one("SELECT count(*) FROM volumes")[0]
        for table, column in (
            ("observations", "crown_contact"),
            ("observations", "trunk_flags"),
            ("volumes", "low_m3"),
            ("volumes", "high_m3"),
            ("volumes", "interval_flags"),
            ("aerial", "crown_flag"),
        ):
            store.run(f"ALTER TABLE {table} DROP COLUMN {column}")
        store.run(
            "INSERT INTO volumes SELECT session_id, tree_id, m.method, 1.0 FROM "
            "(SELECT DISTINCT session_id, tree_id FROM volumes), "
            "(SELECT unnest(?) AS method) m",
            [list(V1_PSEUDO_METHODS)],
        )
        store.run("UPDATE meta SET value = '1' WHERE key = 'schema_version'")
    with pytest.raises(InputError, match=r"old\.duckdb: store schema version 1; upgrade it with "):
        OrchardStore(path, read_only=True)
    copy = tmp_path / "copy.duckdb"  # the library's account of the same upgrade
    copy.write_bytes(path.read_bytes())
    with OrchardStore(copy) as store:
        assert store.upgrade is not None and store.upgrade.as_dict() == {
            "from_version": "1",
            "to_version": "2",
            "dropped_rows": 3 * 2 * len(LAYOUT),
            "refilled_sessions": ["spring"],
            "sessions_left_empty": ["summer"],
        }
    result = run_cli("store", "upgrade", str(path))
    assert result.returncode == 0, result.stderr
    assert "schema version 1 -> 2" in result.stdout
    assert f"removed {3 * 2 * len(LAYOUT)} volume rows" in result.stdout
    assert "filled from the runs of 1 session" in result.stdout
    assert "left empty for 1 session whose run folder is gone: summer" in result.stdout
    with OrchardStore(path, read_only=True) as store:
        assert store.one("SELECT count(*) FROM volumes")[0] == n_volumes
        g = growth(store).set_index("session_id")
        spring = g.loc["spring"].sort_values("tree_id")
        assert np.allclose(spring["low_m3"], tables["spring"]["volume_low_m3"])
        assert np.allclose(spring["high_m3"], tables["spring"]["volume_high_m3"])
        assert np.allclose(spring["crown_contact"], tables["spring"]["crown_contact"])
        assert g.loc["summer", "low_m3"].isna().all()
        flags = store.query("SELECT session_id, crown_flag FROM aerial ORDER BY tree_id")
        assert (flags[flags.session_id == "spring"]["crown_flag"] == "merged").sum() == 1
        assert flags[flags.session_id == "summer"]["crown_flag"].isna().all()
    with OrchardStore(path) as store:  # the upgraded store takes new sessions with intervals
        store.ingest(record("autumn", 9), _with_interval(visit(seed=3)))
        assert store.upgrade is None
        assert growth(store)["low_m3"].notna().sum() == 2 * len(LAYOUT)
    again = run_cli("store", "upgrade", str(path))
    assert again.returncode == 0 and "already schema version 2" in again.stdout


def test_a_duckdb_file_of_another_program_is_not_taken_for_a_store(tmp_path):
    """Opened for writing, a DuckDB file with tables but no store 'meta' table is refused and
    left as it was (no store tables added); read only, it is refused too."""
    import duckdb

    path = tmp_path / "other.duckdb"
    with duckdb.connect(str(path)) as con:
        con.execute("CREATE TABLE foo (x INTEGER)")
    for read_only in (False, True):
        with pytest.raises(InputError, match=r"other\.duckdb: not an orchard store"):
            OrchardStore(path, read_only=read_only)
    with duckdb.connect(str(path), read_only=True) as con:
        names = {
            r[0] for r in con.execute("SELECT table_name FROM information_schema.tables").fetchall()
        }
    assert names == {"foo"}


def test_a_real_runs_table_stores_its_estimators_and_its_interval(tiny_pistachio_run, tmp_path):
    """The pipeline's own per-tree table: every configured estimator is a method, nothing
    else is, and the interval lands on the recommended estimator's rows."""
    from canopy_kit.config import load_preset
    from canopy_kit.volume.verb import volume_methods as configured

    trees = tiny_pistachio_run.trees
    recommended = load_preset("adaptive").volume.recommended
    with OrchardStore(tmp_path / "o.duckdb") as store:
        store.ingest(record("spring", 4), trees)
        stored = store.query("SELECT method, low_m3, high_m3, volume_m3 FROM volumes")
    assert set(stored["method"]) == set(configured(load_preset("adaptive").volume))
    bounded = stored[stored["low_m3"].notna()]
    assert set(bounded["method"]) == {recommended}
    assert len(bounded) == trees["volume_low_m3"].notna().sum() > 0
    assert (bounded["low_m3"] <= bounded["volume_m3"]).all()
    assert (bounded["volume_m3"] <= bounded["high_m3"]).all()
    # the growth CLI defaults to that method (not the paper's alpha_shape) and shows the bounds
    with OrchardStore(tmp_path / "o.duckdb", read_only=True) as store:
        assert interval_method(store) == recommended != "alpha_shape"
    from test_cli_foundation import run_cli

    shown = run_cli("store", "growth", str(tmp_path / "o.duckdb"))
    assert shown.returncode == 0 and "low_m3" in shown.stdout, shown.stderr


def test_growth_says_when_the_intervals_tell_it_from_the_measurement(tmp_path):
    """Intervals 0.9-1.2 x the volume: a visit 1.2 x larger overlaps the first (not told
    apart), 1.4 x larger lies wholly above it (grew); the first visit and a method without
    intervals say nothing; the CLI shows the bounds and the verdict for that method."""
    from test_cli_foundation import run_cli

    path = tmp_path / "o.duckdb"
    with OrchardStore(path) as store:
        for sid, month, factor in (("spring", 4, 1.0), ("summer", 6, 1.2), ("autumn", 9, 1.4)):
            table = _with_interval(visit(growth_factor=factor, seed=month))
            store.ingest(record(sid, month), table)
        g = growth(store)
        verdict = g.groupby("session_id")["change_since_first"].agg(lambda c: set(c.dropna()))
        assert verdict.to_dict() == {
            "spring": set(),
            "summer": {"within the intervals"},
            "autumn": {"grew"},
        }
        assert growth(store, method="convex_hull")["change_since_first"].isna().all()
    shown = run_cli("store", "growth", str(path), "--tree", "1")  # the intervals' method
    assert shown.returncode == 0 and "change_since_first" in shown.stdout, shown.stdout
    assert "grew" in shown.stdout and "low_m3" in shown.stdout
    plain = run_cli("store", "growth", str(path), "--method", "convex_hull", "--tree", "1")
    assert plain.returncode == 0 and "change_since_first" not in plain.stdout


def test_change_is_told_against_the_first_visit_that_had_an_interval(tmp_path):
    """A first visit without an interval (as an upgraded store keeps it): the verdicts start
    from the next visit with one; that visit itself says nothing."""
    with OrchardStore(tmp_path / "o.duckdb") as store:
        store.ingest(record("spring", 4), visit(seed=4))
        store.ingest(record("summer", 6), _with_interval(visit(growth_factor=1.2, seed=6)))
        store.ingest(record("autumn", 9), _with_interval(visit(growth_factor=1.8, seed=9)))
        g = growth(store)
    verdict = g.groupby("session_id")["change_since_first"].agg(lambda c: set(c.dropna()))
    # autumn / summer = 1.5: 0.9 x 1.5 > 1.2, wholly above summer's interval
    assert verdict.to_dict() == {"spring": set(), "summer": set(), "autumn": {"grew"}}
