"""``canopy-kit ground-truth``: drone photos → orthomosaic, crowns and per-tree aerial estimates."""

from __future__ import annotations

from pathlib import Path

import typer

from canopy_kit.cli.common import preset_help


def ground_truth(
    images_dir: Path = typer.Argument(..., help="Folder of geotagged drone JPEGs"),
    out: Path = typer.Option(..., "--out", help="Output folder"),
    seeds: Path = typer.Option(
        None, "--seeds", help="CSV of tree positions (lat/lon or x/y), e.g. the LiDAR trees.csv"
    ),
    frame: Path = typer.Option(
        None,
        "--frame",
        help="frame.json of the LiDAR map or simulated session (local frame "
        "and CRS); default: UTM at the flight",
    ),
    preset: str = typer.Option("adaptive", help=preset_help(": its [ground_truth] table is used")),
    set_: list[str] = typer.Option(
        [], "--set", help="Override a setting: ground_truth.key=value, or seed=N (SfM's sampling)"
    ),
    work_size: int = typer.Option(
        None,
        "--work-size",
        help="Longest image side (px) for the surface and mosaic (ground_truth.work_image_size)",
    ),
    tree_spacing: float = typer.Option(
        None,
        "--tree-spacing",
        help="Planting distance along the rows (m), for crowns found without --seeds "
        "(ground_truth.tree_spacing_m); default: the crowns' width across the row",
    ),
    threads: int = typer.Option(
        0,
        "--threads",
        help="Threads of structure from motion (0: every core); 1 repeats a result bit for bit",
    ),
    json_out: bool = typer.Option(False, "--json", help="Print the report as JSON"),
) -> None:
    """Structure from motion, orthomosaic, DSM/CHM and crown diameters from drone photos."""
    import json

    from canopy_kit.cli.common import (
        console,
        output_folder,
        parse_overrides,
        print_json,
        progress_bar,
    )
    from canopy_kit.config import load_preset
    from canopy_kit.core.geo import LocalFrame
    from canopy_kit.errors import ConfigError, InputError
    from ground_truth.pipeline import process_flight

    local = None
    if frame is not None:
        try:
            data = json.loads(frame.read_text())
        except (OSError, ValueError) as exc:
            raise InputError(f"{frame}: not a readable frame JSON ({exc})") from None
        local = LocalFrame.from_dict(data.get("frame", data) if isinstance(data, dict) else {})
    overrides = parse_overrides(set_)
    other = sorted(set(overrides) - {"ground_truth", "seed"})
    if other:  # the other sections do nothing here
        raise ConfigError(
            f"--set {other[0]}...: ground-truth takes only ground_truth.key=value and seed=N"
        )
    if work_size is not None:
        overrides.setdefault("ground_truth", {})["work_image_size"] = work_size
    if tree_spacing is not None:
        overrides.setdefault("ground_truth", {})["tree_spacing_m"] = tree_spacing
    pipeline = load_preset(preset, overrides)
    with output_folder(out), progress_bar(transient=True) as progress:
        result = process_flight(
            images_dir,
            out,
            frame=local,
            seeds=seeds,
            progress=progress,
            config=pipeline.ground_truth,
            seed=pipeline.seed,
            threads=threads,
        )
    if json_out:
        print_json(result.report)
        return
    sfm = result.report["sfm"]
    console.print(
        f"[green]registered[/] {sfm['registered_images']}/{sfm['total_images']} photos, "
        f"reprojection error {sfm['mean_reprojection_error_px']:.2f} px, GPS residual RMS "
        f"{sfm['gps_residual_rms_horizontal_m']:.3f} m horizontal / "
        f"{sfm['gps_residual_rms_vertical_m']:.3f} m vertical"
    )
    level = sfm.get("alignment", {})
    if level.get("vertical_from") == "camera_axes":
        console.print(
            f"[yellow]levelled by the photos' optical axes[/]: the GPS heights would tilt the "
            f"model {level['gps_tilt_vs_camera_axes_deg']:.1f}° (GPS tilt sigma "
            f"{level['gps_tilt_sigma_deg']:.1f}°)"
        )
    line = f"[green]crowns[/] {len(result.crowns)}"
    if result.trees is not None:
        line += f", matched to {int(result.trees['matched'].sum())} of {len(result.trees)} trees"
    rows = result.report.get("crown_rows")
    if rows:
        line += (
            f", seeded along {rows['rows']} rows at {rows['tree_spacing_m']:.2f} m "
            f"({rows['tree_spacing_source']})"
        )
    else:
        line += f", seeded by {result.report.get('crown_seeding', 'tree positions')}"
    console.print(line)
    flags = result.report.get("crown_flags") or {}
    if flags.get("merged") or flags.get("fragment"):
        spacing = flags.get("tree_spacing_m")
        console.print(
            f"[yellow]crowns flagged[/] from the imagery (crown_flag): {flags['merged']} "
            f"probably two trees, {flags['fragment']} fragments"
            + (
                f", against a tree spacing of {spacing:.2f} m ({flags['tree_spacing_source']})"
                if spacing
                else ""
            )
        )
    model, views = result.report.get("aerial_volume_model"), result.report.get("flight_views")
    if model and views:
        console.print(
            f"[green]aerial volume[/] {model['recommended']} recommended: {views['views']} "
            f"flight ({views['oblique_photos']} of {views['photos']} photos oblique)"
        )
    offset = result.report.get("seed_offset") or {}
    if offset.get("significant"):
        console.print(
            f"[yellow]crowns sit {offset['east_m']:+.2f} m east, {offset['north_m']:+.2f} m north "
            f"of their seed trees[/] (± {offset['standard_error_m']:.2f} m, {offset['pairs']} "
            "trees): the seeds' georeferencing differs from the photos'"
            + ("; seeds moved by it" if offset.get("seeds_shifted") else "")
        )
    for name, path in result.paths.items():
        console.print(f"  {name:18s} {path}")
