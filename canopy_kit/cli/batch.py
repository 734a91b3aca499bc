"""``canopy-kit batch``: many sessions on a Dask cluster, stored in the orchard store."""

from __future__ import annotations

from contextlib import nullcontext
from pathlib import Path

import typer


def batch(
    manifest: Path = typer.Argument(
        ..., help="Sessions to process: TOML ([[session]] tables) or CSV"
    ),
    out: Path = typer.Option(..., "--out", help="Output folder (sessions/<id>/, orchard.duckdb)"),
    scheduler: str = typer.Option(
        None,
        "--scheduler",
        help="Address of a running Dask scheduler, e.g. tcp://host:8786 "
        "(default: a LocalCluster on this machine)",
    ),
    workers: int = typer.Option(
        None,
        "--workers",
        help="LocalCluster worker processes (default: one per core, at most one per session)",
    ),
    retries: int = typer.Option(2, "--retries", help="Retries of a task whose worker failed"),
    store: Path = typer.Option(None, "--store", help="Orchard store (default: OUT/orchard.duckdb)"),
    gate: float = typer.Option(
        1.5,
        "--gate",
        help="Largest distance (m) between a tree and its match in an earlier session",
    ),
    rerun: bool = typer.Option(False, "--rerun", help="Also process sessions already stored"),
    rig: Path = typer.Option(
        None,
        "--rig",
        help="Rig file for every session that names none in the "
        "manifest (docs/MAPPING.md, 'Sensor rigs')",
    ),
) -> None:
    """Process every session of a manifest on Dask and track each tree in the store."""
    from canopy_kit.cli.common import (
        check_output_file,
        check_output_folder,
        console,
        err_console,
        output_file,
        output_folder,
        progress_bar,
    )
    from canopy_kit.pipeline.batch import load_manifest, run_batch
    from canopy_kit.store import MatchSettings

    specs = load_manifest(manifest, default_rig=rig)
    check_output_folder(out)  # a file in the way: said before the cluster starts
    if store is not None:
        check_output_file(store, "--store")
    console.print(f"{len(specs)} sessions from {manifest} on {scheduler or 'a LocalCluster'}")

    def show(outcome) -> None:
        if outcome.ok:
            console.print(
                f"  [green]done[/] {outcome.session_id}: {outcome.summary.get('n_trees')} "
                f"trees in {outcome.wall_s:.0f} s ({outcome.worker})"
            )
        else:
            console.print(f"  [red]failed[/] {outcome.session_id}: {outcome.error}")

    with (
        output_folder(out),
        output_file(store, "--store") if store is not None else nullcontext(),
        progress_bar() as progress,
    ):
        result = run_batch(
            specs,
            out,
            scheduler=scheduler,
            n_workers=workers,
            retries=retries,
            store=store,
            match=MatchSettings(gate_m=gate),
            skip_stored=not rerun,
            progress=progress,
            on_session=show,
        )
    if result.store_upgrade:
        u = result.store_upgrade
        console.print(
            f"  upgraded the store from schema version {u['from_version']} to "
            f"{u['to_version']}; columns left empty for sessions whose run folder is gone: "
            f"{', '.join(u['sessions_left_empty']) or 'none'}"
        )
    for sid in result.skipped:
        console.print(f"  skipped {sid}: already in the store")
    for sid, ing in result.ingests.items():
        a = ing["alignment"]
        console.print(
            f"  stored {sid}: {ing['n_matched']} known trees, {ing['n_new']} new, "
            f"{ing['n_missing']} missing, {ing['n_replanted']} replanted "
            f"(aligned by {a['dx']:+.2f}, {a['dy']:+.2f} m, {a['rotation_deg']:+.2f}°)"
        )
    done = sum(o.ok for o in result.outcomes.values())
    console.print(
        f"[bold]{done}/{len(result.outcomes)} sessions done[/] in {result.wall_s:.0f} s on "
        f"{result.n_workers} workers; store: {result.store}; summary: {out / 'batch.json'}"
    )
    if result.failures:
        for sid, msg in result.failures.items():
            err_console.print(f"[red]failed[/] {sid}: {msg}")
        raise typer.Exit(3)
