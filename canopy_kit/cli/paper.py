"""``canopy-kit paper``: reproduce the paper's results.

A command group: ``table1`` checks and summarises the paper's Table I; ``experiments``
re-runs the paper's segmentation and volume experiments on simulated orchards and prints
them beside the paper's figures.
"""

from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer(
    name="paper",
    help="Reproduce the results of Abedi et al. 2025 (Table I; experiments on simulated orchards).",
    no_args_is_help=True,
    add_completion=False,
)


@app.command("table1")
def table1(
    json_output: bool = typer.Option(
        False, "--json", help="Print one JSON document instead of tables."
    ),
    corrected: bool = typer.Option(
        True,
        "--corrected/--as-printed",
        help="Statistics on the table with columns put back where the numbers say "
        "(default), or read under the printed header.",
    ),
    path: Path | None = typer.Option(
        None, "--path", help="Table I CSV (default: data/paper/table1.csv)."
    ),
    flat_tolerance: float | None = typer.Option(
        None,
        "--flat-tolerance",
        min=0.0,
        help="Ignore the rounding of the printed values and accept an order when "
        "|recomputed - printed error| <= this many percentage points.",
    ),
) -> None:
    """Check Table I row by row; print the corrected table, its inconsistencies and statistics.

    The statistics are those the paper does not give: MAPE, bias, RMSE, R², Bland-Altman,
    the alpha-vs-hull claim and the crown diameters implied by the sphere volumes.
    """
    from canopy_kit.cli.common import print_json
    from canopy_kit.cli.table1_report import print_table1_report
    from canopy_kit.paper import check_table1, summarise_table1
    from canopy_kit.paper.summary import table1_result

    if flat_tolerance is None:
        check = check_table1(path)
    else:
        check = check_table1(path, rounding=False, tolerance_pp=flat_tolerance)
    summary = summarise_table1(check, "corrected" if corrected else "as_printed")
    result = table1_result(check, summary)
    if json_output:
        print_json(result)
        return
    print_table1_report(check, summary, result)


@app.command("experiments")
def experiments(
    # Defaults = the committed results' settings (canopy_kit.paper.experiments.COMMITTED_*,
    # not imported: it pulls in pandas; a test holds them equal).
    seeds: int = typer.Option(3, "--seeds", min=1, help="Simulated sessions per orchard."),
    first_seed: int = typer.Option(301, "--first-seed", help="Seed of the first session."),
    rows: int = typer.Option(2, "--rows", min=1, help="Rows per simulated orchard."),
    trees_per_row: int = typer.Option(6, "--trees-per-row", min=2, help="Trees per row."),
    orchard: list[str] = typer.Option(
        ["pistachio", "almond"],
        "--orchard",
        help="Orchard (repeat for several): pistachio, almond, "
        "almond-paper (calibrated on the paper's DBSCAN).",
    ),
    # = canopy_kit.paper.experiments.DEFAULT_METHODS (not imported: it pulls in pandas)
    method: list[str] = typer.Option(
        ["dbscan", "dbscan_spectral", "adaptive"],
        "--method",
        help="Segmenter (repeat): dbscan = the pistachio preset, "
        "dbscan_spectral = the almond preset, adaptive, "
        "dbscan_spectral_scaled = almond-scaled.",
    ),
    true_poses: bool = typer.Option(
        False,
        "--true-poses",
        help="Also run every method on a map from the true poses "
        "(separates mapping error from the rest).",
    ),
    drone: bool = typer.Option(
        False,
        "--drone",
        help="Also simulate a drone flight and compare with the "
        "photogrammetry stage's sphere volumes (slow).",
    ),
    set_: list[str] = typer.Option(
        [], "--set", help="Simulator override section.key=value, e.g. lidar.columns=512."
    ),
    sensor: str | None = typer.Option(None, "--sensor", help="Simulated sensor model."),
    work: Path | None = typer.Option(
        None, "--work", help="Folder for the simulated sessions (default: a temporary folder)."
    ),
    keep_sessions: bool = typer.Option(
        False, "--keep-sessions", help="Keep the simulated sessions and runs."
    ),
    out: Path | None = typer.Option(
        None,
        "--out",
        help="Where the results go (default: a new folder "
        "out/paper-YYYYmmdd-HHMMSS, UTC); with --show-saved, where they are "
        "read from (default: the committed data/paper).",
    ),
    overwrite: bool = typer.Option(
        False,
        "--overwrite",
        help="Allow --out to be the committed data/paper or a folder "
        "holding results (they are replaced).",
    ),
    show_saved: bool = typer.Option(
        False, "--show-saved", help="Print the results saved in --out; run nothing."
    ),
    saved_only: bool = typer.Option(
        False,
        "--saved-only",
        help="Run nothing: collect the sessions already finished in "
        "--work (e.g. by several processes sharing it), leave out "
        "the others, write the results.",
    ),
    json_output: bool = typer.Option(False, "--json", help="Print one JSON document."),
) -> None:
    """Re-run the paper's experiments on simulated pistachio and almond sessions.

    Segmentation success of DBSCAN, DBSCAN + spectral (and canopy-kit's adaptive segmenter),
    and convex hull vs alpha-shape errors against the aerial sphere ground truth and the true
    crown volume, beside the paper's figures. Writes experiments_*.csv and experiments.json
    into a new folder; the defaults are the settings of the committed results (seeds
    301-303, 2 rows x 6 trees: docs/REPRODUCTION.md).
    """
    import tempfile
    from contextlib import nullcontext

    from canopy_kit.cli.common import (
        check_output_folder,
        console,
        output_folder,
        parse_overrides,
        print_json,
        progress_bar,
    )
    from canopy_kit.cli.experiments_report import print_experiments
    from canopy_kit.errors import InputError
    from canopy_kit.paper.experiments import (
        ExperimentConfig,
        check_results_dir,
        load_results,
        new_results_dir,
        run_experiments,
        write_results,
    )

    if show_saved:
        results = load_results(out)
    else:
        out = out or new_results_dir()
        check_output_folder(out)  # before hours of runs
        out = check_results_dir(out, overwrite)
        if work is not None:
            check_output_folder(work, "--work")
        config = ExperimentConfig(
            seeds=tuple(range(first_seed, first_seed + seeds)),
            rows=rows,
            trees_per_row=trees_per_row,
            orchards=tuple(orchard),
            methods=tuple(method),
            mappings=("pipeline", "true_poses") if true_poses else ("pipeline",),
            sim_overrides=parse_overrides(set_),
            sensor=sensor,
            drone=drone,
        )
        config.validate()
        if saved_only and work is None:
            raise InputError("--saved-only needs --work (the folder the sessions ran in)")
        with (
            tempfile.TemporaryDirectory(prefix="canopy-kit-experiments-") as tmp,
            output_folder(work, "--work") if work is not None else nullcontext(),
            progress_bar(transient=True) as progress,
        ):
            results = run_experiments(
                config,
                work or tmp,
                progress=progress,
                keep_sessions=keep_sessions,
                saved_only=saved_only,
            )
        with output_folder(out):
            files = write_results(results, out, overwrite)
    if json_output:
        print_json(results.to_dict())
        return
    print_experiments(results)
    if not show_saved:
        console.print("results: " + ", ".join(str(p) for p in files.values()))
