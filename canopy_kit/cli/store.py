"""``canopy-kit store``: look into an orchard store, add a run to it, export growth tables."""

from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer(
    help="The orchard store (DuckDB): sessions, trees over time, growth exports.",
    no_args_is_help=True,
)


@app.command("sessions")
def sessions(store: Path = typer.Argument(..., help="Store file (orchard.duckdb)")) -> None:
    """List the stored sessions with their matched, new and missing trees."""
    from canopy_kit.cli.tables import frame_grid, print_grid
    from canopy_kit.store import OrchardStore

    with OrchardStore(store, read_only=True) as db:
        table = db.query(
            "SELECT session_id, orchard, date, n_trees, n_matched, n_new, n_missing, "
            "n_replanted, round(align_rms_m, 3) AS align_rms_m FROM sessions "
            "ORDER BY orchard, date"
        )
    print_grid(frame_grid(table, keys=1))


@app.command("changes")
def changes(
    store: Path = typer.Argument(..., help="Store file"),
    orchard: str = typer.Option(None, help="Only this orchard"),
) -> None:
    """New, missing and replanted trees, session by session."""
    from canopy_kit.cli.common import console
    from canopy_kit.cli.tables import frame_grid, print_grid
    from canopy_kit.store import OrchardStore
    from canopy_kit.store import changes as changes_of

    with OrchardStore(store, read_only=True) as db:
        table = changes_of(db, orchard)
    if len(table):
        print_grid(frame_grid(table, keys=2))
    else:
        console.print("no changes")


@app.command("growth")
def growth(
    store: Path = typer.Argument(..., help="Store file"),
    orchard: str = typer.Option(None, help="Only this orchard"),
    method: str = typer.Option(
        None,
        help="Volume method (default: the one the runs' intervals bound, else alpha_shape)",
    ),
    tree: int = typer.Option(None, "--tree", help="Only this tree_id"),
    rows: bool = typer.Option(False, "--rows", help="Per row instead of per tree"),
) -> None:
    """Volume and growth per tree (or per row) over the sessions of a store."""
    from canopy_kit.cli.common import console
    from canopy_kit.cli.tables import frame_grid, print_grid
    from canopy_kit.store import OrchardStore, interval_method, row_growth
    from canopy_kit.store import growth as growth_of

    with OrchardStore(store, read_only=True) as db:
        method = method or interval_method(db)
        table = (row_growth if rows else growth_of)(db, method=method, orchard=orchard)
    if len(table):  # a session's date, not a midnight timestamp
        table["date"] = table["date"].astype(str).str.slice(0, 10)
    if rows:
        cols = [
            "orchard",
            "tree_row",
            "date",
            "n_trees",
            "total_volume_m3",
            "mean_volume_m3",
            "median_growth_since_first",
        ]
    else:
        if tree is not None:
            table = table[table["tree_id"] == tree]
        cols = [
            "orchard",
            "tree_id",
            "tree_label",
            "status",
            "date",
            "kind",
            "volume_m3",
            "growth_since_first",
            "growth_since_previous",
        ]
        if table["low_m3"].notna().any():  # the method the runs' intervals bound
            cols[cols.index("volume_m3") + 1 : cols.index("volume_m3") + 1] = ["low_m3", "high_m3"]
            cols.append("change_since_first")
    if len(table):
        print_grid(frame_grid(table[cols], keys=2))
    else:
        console.print("no observations")


@app.command("export")
def export(
    store: Path = typer.Argument(..., help="Store file"),
    out: Path = typer.Argument(..., help="Output .parquet or .csv"),
    what: str = typer.Option("growth", help="growth, row_growth, changes, trees or sessions"),
    method: str = typer.Option(None, help="Volume method (default: alpha_shape)"),
    orchard: str = typer.Option(None, help="Only this orchard"),
) -> None:
    """Export a growth table (per tree or per row) or a store table to Parquet or CSV."""
    from canopy_kit.cli.common import console, output_file
    from canopy_kit.store import OrchardStore
    from canopy_kit.store import export as export_table

    with output_file(out, None), OrchardStore(store, read_only=True) as db:
        path = export_table(db, what, out, method=method, orchard=orchard)
    console.print(f"[green]wrote[/] {path}")


@app.command("add")
def add(
    store: Path = typer.Argument(..., help="Store file (created when absent)"),
    run_dir: Path = typer.Argument(..., help="Output folder of 'canopy-kit run'"),
    orchard: str = typer.Option(..., help="Orchard name"),
    date: str = typer.Option(..., help="Session date, YYYY-MM-DD"),
    session_id: str = typer.Option(None, "--id", help="Session id (default: ORCHARD-DATE)"),
    gate: float = typer.Option(1.5, help="Largest distance (m) to a tree's earlier position"),
) -> None:
    """Add one run's trees (RUN_DIR/trees.parquet) to the store."""
    import datetime as dt

    import pandas as pd

    from canopy_kit.cli.common import console, output_file
    from canopy_kit.errors import InputError
    from canopy_kit.store import MatchSettings, OrchardStore, SessionRecord

    table = run_dir / "trees.parquet"
    if not table.exists():
        raise InputError(f"{table}: no per-tree table (is {run_dir} a 'canopy-kit run' output?)")
    try:
        day = dt.date.fromisoformat(date)
    except ValueError:
        raise InputError(f"--date {date!r}: expected YYYY-MM-DD") from None
    record = SessionRecord(
        session_id or f"{orchard}-{day.isoformat()}", orchard, day, run_dir=str(run_dir)
    )
    with output_file(store, None), OrchardStore(store) as db:
        _say_upgraded(store, db)
        rep = db.ingest(record, pd.read_parquet(table), MatchSettings(gate_m=gate)).summary()
    console.print(
        f"[green]stored[/] {rep['session_id']}: {rep['n_matched']} known trees, "
        f"{rep['n_new']} new, {rep['n_missing']} missing, {rep['n_replanted']} replanted"
    )


@app.command("upgrade")
def upgrade(store: Path = typer.Argument(..., help="Store file")) -> None:
    """Bring a store written by an older canopy-kit to this version's schema."""
    from canopy_kit.cli.common import console
    from canopy_kit.errors import InputError
    from canopy_kit.store import OrchardStore
    from canopy_kit.store.schema import SCHEMA_VERSION

    if not store.exists():
        raise InputError(f"{store}: store does not exist")
    with OrchardStore(store) as db:
        if not _say_upgraded(store, db):
            console.print(f"{store}: already schema version {SCHEMA_VERSION}")


def _say_upgraded(store: Path, db: object) -> bool:
    """Print what opening ``db`` for writing upgraded, if anything; whether it did."""
    from canopy_kit.cli.common import console
    from canopy_kit.store.schema import SCHEMA_VERSION

    done = getattr(db, "upgrade", None)
    if done is None:
        return False
    old = done.from_version
    console.print(f"[green]upgraded[/] {store}: schema version {old} -> {SCHEMA_VERSION}")
    if done.dropped_rows:
        console.print(
            f"removed {done.dropped_rows} volume rows that version {old} stored as methods "
            "'low', 'high' and 'without_voids' (the interval's bounds and the void-free volume)"
        )
    if done.refilled:
        console.print(
            f"new columns (intervals, crown contact, trunk and crown flags) filled from the runs "
            f"of {_sessions(len(done.refilled))}"
        )
    if done.not_refilled:
        console.print(
            f"[yellow]left empty[/] for {_sessions(len(done.not_refilled))} whose run folder is "
            f"gone: {', '.join(done.not_refilled)} (to have them, ingest their runs into a new "
            "store)"
        )
    return True


def _sessions(n: int) -> str:
    return f"{n} session" if n == 1 else f"{n} sessions"


@app.command("check")
def check(store: Path = typer.Argument(..., help="Store file")) -> None:
    """Check the store's references and counts; exit code 3 when something is wrong."""
    from canopy_kit.cli.common import console
    from canopy_kit.store import OrchardStore, consistency_problems

    with OrchardStore(store, read_only=True) as db:
        problems = consistency_problems(db)
    for p in problems:
        console.print(f"[red]problem[/]: {p}")
    if problems:
        raise typer.Exit(3)
    console.print("[green]consistent[/]")
