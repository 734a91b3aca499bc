"""``canopy-kit segment MAP --preset NAME --out DIR``: trees, rows and labels of a map."""

from __future__ import annotations

from pathlib import Path

import typer

from canopy_kit.cli.common import preset_help


def segment(
    map_path: Path = typer.Argument(..., metavar="MAP", help="Map point cloud (LAS/LAZ/PLY/PCD)"),
    preset: str = typer.Option(
        "adaptive", help=preset_help("; the default is the same as canopy-kit run's")
    ),
    out: Path = typer.Option(..., "--out", help="Output folder"),
    method: str = typer.Option(None, help="Segmenter plugin, overriding the preset's"),
    trajectory: Path = typer.Option(
        None,
        help="The drive (CSV t,x,y[,z] or x,y, or TUM lines), in the map file's coordinates; "
        "its first pass orders and labels the trees",
    ),
    set_: list[str] = typer.Option([], "--set", help="Override any setting: section.key=value"),
    no_cloud: bool = typer.Option(False, "--no-cloud", help="Do not write segmented.laz"),
    export_trees: bool = typer.Option(
        False,
        "--export-trees",
        help="Also write each tree's points as trees/<tree_id>.laz (for canopy-kit volume)",
    ),
) -> None:
    """Remove ground and trunks, segment the trees, find rows and label the trees."""
    import numpy as np

    from canopy_kit.cli.common import (
        check_output_folder,
        console,
        output_folder,
        parse_overrides,
        progress_bar,
    )
    from canopy_kit.config import load_preset, write_config
    from canopy_kit.io.clouds import read_cloud
    from canopy_kit.segment.export import write_segmentation
    from canopy_kit.segment.rows import driving_direction_from_trajectory
    from canopy_kit.segment.verb import make_segmenter
    from canopy_kit.segment.verb import segment as run_segment

    overrides = parse_overrides(set_)
    if method:  # another method than the preset's starts from its own defaults (apply_overrides)
        overrides.setdefault("segment", {})["method"] = method
    config = load_preset(preset, overrides)
    check_output_folder(out)  # before reading and segmenting the map
    cloud = read_cloud(map_path)
    direction, source = None, None
    if trajectory is not None:
        from canopy_kit.mapping.map_source import read_trajectory  # CSV or TUM, as run reads it

        traj = read_trajectory(trajectory, cloud.origin)
        direction = driving_direction_from_trajectory(traj[["x", "y"]].to_numpy())
        source = f"trajectory {trajectory.name}"
    segmenter = make_segmenter(config.segment.method, config.segment.params)
    with output_folder(out), progress_bar(transient=True) as progress:
        seg = run_segment(
            cloud,
            segmenter,
            config.preprocess,
            config.rows,
            driving_direction=direction,
            direction_source=source,
            seed=config.seed,
            progress=progress,
        )
        write_segmentation(out, seg, cloud, with_cloud=not no_cloud)
        if export_trees:
            from canopy_kit.segment.tree_export import export_trees as write_tree_clouds

            write_tree_clouds(out / "trees", cloud, seg)
        write_config(config, out / "config.toml")
    for w in seg.warnings:
        console.print(f"[yellow]warning:[/] {w}")
    n_rows = len(seg.rows.lines)
    console.print(
        f"[green]segmented[/] {seg.n_trees} trees in {n_rows} rows "
        f"({config.segment.method}, {np.sum(seg.labels >= 0):,} of {len(cloud):,} points)"
        f"\n  output: {out}"
    )
