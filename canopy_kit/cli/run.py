"""``canopy-kit run``: the whole pipeline on one bag, or on a map made elsewhere."""

from __future__ import annotations

from pathlib import Path

import typer

from canopy_kit.cli.common import ASSUME_IDENTITY_OPTION, CALIBRATE_OPTION, RIG_OPTION, preset_help

CHECKS_FAILED_EXIT = 4  # run --strict: every output written, but a check failed


def run(
    bag: Path = typer.Argument(
        ...,
        help="ROS1 .bag file, ROS2 bag folder, Velodyne VLP-16 .pcap capture, or a finished "
        "map (LAS/LAZ/PCD/PLY)",
    ),
    out: Path = typer.Option(..., "--out", help="Output folder"),
    preset: str = typer.Option("adaptive", help=preset_help()),
    drone_images: Path = typer.Option(
        None, "--drone-images", help="Folder of geotagged drone JPEGs"
    ),
    sfm_threads: int = typer.Option(
        0,
        "--sfm-threads",
        min=0,
        help="Threads for the drone photos' structure from motion: 0 every core; 1 repeats "
        "the reconstruction bit for bit (slower)",
    ),
    truth: Path = typer.Option(
        None, "--truth", help="Simulated session folder to evaluate against"
    ),
    set_: list[str] = typer.Option([], "--set", help="Override a setting: section.key=value"),
    no_cache: bool = typer.Option(False, "--no-cache", help="Recompute every stage"),
    stream: bool = typer.Option(
        False,
        "--stream",
        help="Emit each tree once the robot has passed "
        "it, keeping only a window of the map (no map or report)",
    ),
    rig: Path = RIG_OPTION,
    assume_identity: bool = ASSUME_IDENTITY_OPTION,
    calibrate: bool = CALIBRATE_OPTION,
    orchard: str = typer.Option(
        None,
        "--orchard",
        help="Orchard or block name for the "
        "provenance (metrics.json, tables, GeoJSON); default: the bag's name",
    ),
    export_trees: bool = typer.Option(
        False,
        "--export-trees",
        help="Also write each tree's points as trees/<tree_id>.laz (for canopy-kit volume)",
    ),
    gnss: Path = typer.Option(
        None, "--gnss", help="GNSS track of a pcap drive (MTLS text, CSV, NMEA or GPX)"
    ),
    gnss_crs: str = typer.Option(
        None, "--gnss-crs", help="EPSG code of the track's easting/northing (e.g. 25831)"
    ),
    gnss_time: str = typer.Option(
        "utc", "--gnss-time", help="Time scale of the track's times of day: utc or gps"
    ),
    trajectory: Path = typer.Option(
        None,
        "--trajectory",
        help="Map file only: the drive, CSV t,x,y[,z] or x,y, or TUM "
        "'t x y z qx qy qz qw' lines, in the map's coordinates",
    ),
    crs: str = typer.Option(
        None, "--crs", help="Map file only: its CRS (EPSG code) when the file names none"
    ),
    strict: bool = typer.Option(
        False,
        "--strict",
        help="Exit with code 4 when any check fails "
        "(after writing every output: they should not be trusted)",
    ),
) -> None:
    """Map, segment, measure and (optionally) validate one field session; write the report.

    BAG may also be a finished map (LAS/LAZ/PCD/PLY): mapping is skipped
    (docs/DATASETS.md, "Maps made elsewhere").

    Exit codes: 0 done (also when checks failed, unless --strict), 2 bad input, 3 processing
    failed, 4 with --strict: done, but a check failed (docs/RELIABILITY.md).
    """
    from canopy_kit.cli.common import output_folder, parse_overrides, progress_bar
    from canopy_kit.config import load_preset, merge
    from canopy_kit.config.rig import extrinsics_mode, rig_overrides
    from canopy_kit.errors import InputError
    from canopy_kit.mapping.map_source import MapFile, run_input

    if stream and strict:  # a streamed run has no checks: --strict would pass it unchecked
        raise InputError(
            "--strict: a --stream run has no checks to hold it to; run without "
            "--stream for the checks and the report"
        )
    source = run_input(bag, trajectory, crs)  # a map file skips the mapping (map_source)
    if stream and isinstance(source, MapFile):
        raise InputError(f"--stream: {bag} is a finished map, not a drive; run without --stream")
    if stream and export_trees:  # a streamed run keeps no map to cut the trees from
        raise InputError("--export-trees: a --stream run keeps no map; run without --stream")
    overrides = merge(
        parse_overrides(set_), rig_overrides(rig, extrinsics_mode(assume_identity, calibrate))
    )
    config = load_preset(preset, overrides)
    if stream:
        from canopy_kit.cli.stream import run_streaming
        from canopy_kit.io.pcap_drive import is_pcap

        if is_pcap(bag):
            raise InputError(f"{bag}: --stream takes a bag; run a pcap capture without --stream")

        with output_folder(out):
            run_streaming(config, bag, out, extra_inputs=drone_images or truth, orchard=orchard)
        return
    # Imported once the inputs are checked: the pipeline loads scikit-learn and SciPy (1-2 s)
    from canopy_kit.io.pcap_drive import GnssTrackOption
    from canopy_kit.pipeline import run as run_pipeline

    with output_folder(out), progress_bar(transient=True) as progress:
        results = run_pipeline(
            config,
            source,
            out,
            drone_images=drone_images,
            truth=truth,
            use_cache=not no_cache,
            progress=progress,
            orchard=orchard,
            export_trees=export_trees,
            gnss=GnssTrackOption(gnss, gnss_crs, gnss_time),
            sfm_threads=sfm_threads,
        )
    print_results(results)
    if strict and results.metrics.get("checks_summary", {}).get("fail", 0):
        raise typer.Exit(CHECKS_FAILED_EXIT)


def print_results(results) -> None:
    """One screen of what a run found and where its files are."""
    from canopy_kit.cli.common import console
    from canopy_kit.results.checks import true_volume_name

    m = results.metrics
    console.print(
        f"[green]done[/]: {m['n_trees']} trees ({m['segmenter']}, preset {m.get('preset', '?')})"
    )
    ev = m.get("evaluation", {})
    mapping = ev.get("mapping", {})
    if "ate_rmse_m" in mapping:
        console.print(
            f"  trajectory vs truth: ATE {mapping['ate_rmse_m']:.3f} m, "
            f"drift {mapping.get('drift_percent', float('nan')):.2f} % of the path"
        )
    if "segmentation" in ev:
        s = ev["segmentation"]
        console.print(
            f"  segmentation vs truth: {s['n_correct']}/{s['n_truth']} "
            f"({100 * s['success_rate']:.0f} %), labels {100 * s['label_accuracy']:.0f} %"
        )
    for method, a in ev.get("volumes", {}).items():
        if isinstance(a, dict) and "mape_pct" in a:
            against = true_volume_name(ev)
            if method == "recommended_vs_measurand":
                method, against = ev.get("recommended_volume", method), "its measurand"
            console.print(
                f"  {method} vs {against}: MAPE {a['mape_pct']:.1f} %, bias {a['bias_pct']:+.1f} %"
            )
    held = ev.get("volumes", {}).get("recommended_interval")
    if isinstance(held, dict) and held.get("n"):
        console.print(
            f"  {ev.get('recommended_volume', 'recommended')} interval held its measurand for "
            f"{held['held']}/{held['n']} trees"
            + (f" (misses' IoU {held['missed_iou']})" if held.get("missed_iou") else "")
        )
    aerial = m.get("aerial") or {}
    for column, a in aerial.items():
        if isinstance(a, dict) and "mape_pct" in a:
            console.print(
                f"  {column} vs aerial sphere volume ({a['n']} trees compared): "
                f"MAPE {a['mape_pct']:.1f} %, bias {a['bias_pct']:+.1f} %"
            )
    if m.get("flagged_segments"):
        console.print(
            f"  [yellow]{m['flagged_segments']} crowns unlike the others[/] (merged trees or "
            "fragments?): see segment_flags in trees.csv"
        )
    if results.cache_hits:
        console.print(f"  reused cached stages: {', '.join(results.cache_hits)}")
    for w in results.warnings:
        console.print(f"  [yellow]warning[/]: {w}")
    console.print(f"  report: {results.files['report.html']}")
    bad = [c for c in m.get("checks", []) if c["status"] == "fail"]
    warned = sum(1 for c in m.get("checks", []) if c["status"] == "warn")
    if bad:
        names = "; ".join(f"{c['name']} ({c['value']})" for c in bad)
        console.print(
            f"[bold red]{len(bad)} check{'s' if len(bad) > 1 else ''} failed: do not trust "
            f"this run[/]: {names}"
        )
    elif warned:
        console.print(f"[yellow]{warned} check{'s' if warned > 1 else ''} warned[/], none failed")
