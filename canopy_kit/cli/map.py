"""``canopy-kit map BAG --out DIR``: LiDAR(-inertial) odometry and mapping of one bag."""

from __future__ import annotations

from pathlib import Path

import typer

from canopy_kit.cli.common import ASSUME_IDENTITY_OPTION, CALIBRATE_OPTION, RIG_OPTION


def map_bag(
    bag: Path = typer.Argument(..., help="ROS1 .bag file or ROS2 bag folder"),
    out: Path = typer.Option(
        ..., "--out", help="Output folder (map.laz, trajectory.csv/.tum, mapping.json)"
    ),
    evaluate: bool = typer.Option(
        False,
        "--evaluate",
        help="Compare with the bag's ground-truth odometry (and, for a "
        "simulated session, the true scene)",
    ),
    truth: Path = typer.Option(
        None, "--truth", help="Simulated session folder (default: the bag's folder)"
    ),
    preset: str = typer.Option(
        None, help="Use the mapping section of a preset (name or TOML file)"
    ),
    set_: list[str] = typer.Option([], "--set", help="Override a mapping setting: key=value"),
    plots: bool = typer.Option(
        True, "--plots/--no-plots", help="Write trajectory and top-view PNGs"
    ),
    rig: Path = RIG_OPTION,
    assume_identity: bool = ASSUME_IDENTITY_OPTION,
    calibrate: bool = CALIBRATE_OPTION,
) -> None:
    """Map a bag: deskewed, gravity-aligned, georeferenced, voxel-thinned LAZ plus trajectory."""
    from canopy_kit.cli.common import (
        check_output_folder,
        console,
        output_folder,
        parse_overrides,
        progress_bar,
    )
    from canopy_kit.config import MappingConfig, from_dict, load_preset, merge, to_dict
    from canopy_kit.config.rig import extrinsics_mode, rig_overrides
    from canopy_kit.mapping import build_map
    from canopy_kit.mapping.outputs import write_mapping_outputs

    overrides = merge(
        parse_overrides(set_), rig_overrides(rig, extrinsics_mode(assume_identity, calibrate))
    )
    overrides = merge(
        {k: v for k, v in overrides.items() if k != "mapping"}, overrides.get("mapping", {})
    )
    base = to_dict(load_preset(preset).mapping) if preset else {}
    config = from_dict(MappingConfig, merge(base, overrides), "mapping")
    check_output_folder(out)  # before the mapping, not after it
    with progress_bar(transient=True) as progress:
        result = build_map(bag, config, progress=progress)
        evaluation, reference = (
            _evaluate(result, bag, truth, progress) if evaluate else (None, None)
        )
    with output_folder(out):
        paths = write_mapping_outputs(result, out, evaluation)
        if plots:
            paths.update(_write_plots(result, out, reference, evaluation))
    _print_summary(console, result, evaluation, paths)


def _evaluate(result, bag: Path, truth: Path | None, progress):
    from canopy_kit.evaluate.trajectory_error import (
        estimate_in_frame,
        evaluate_against_simulation,
        reference_from_bag,
        trajectory_errors,
    )
    from canopy_kit.io.session_layout import truth_dir

    reference = reference_from_bag(bag)
    sim_dir = truth
    if sim_dir is None:  # a simulated session keeps truth/ next to its bag
        sim_dir = next(
            (p for p in (bag.parent, bag.parent.parent) if (truth_dir(p) / "frame.json").exists()),
            None,
        )
    if sim_dir is not None:
        if progress:
            progress("evaluation: map vs true scene", 0, 1)
        return evaluate_against_simulation(result, sim_dir, reference), reference
    return trajectory_errors(
        estimate_in_frame(result, reference.attrs.get("frame")), reference
    ), reference


def _write_plots(result, out: Path, reference, evaluation) -> dict[str, Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from canopy_kit.core.atomic import atomic_path
    from canopy_kit.mapping.plots import mapping_figures

    paths = {}
    for name, fig in mapping_figures(result, reference, evaluation).items():
        path = out / f"{name}.png"
        with atomic_path(path) as tmp:  # an interrupt leaves no half-written PNG
            fig.savefig(tmp, dpi=110, format="png")
        plt.close(fig)
        paths[f"{name}_png"] = path
    return paths


def _print_summary(console, result, evaluation, paths) -> None:
    d = result.diagnostics
    t = d["timing"]
    console.print(
        f"[green]mapped[/] {d['sweeps_mapped']}/{d['scans']} sweeps ({d['sweeps_registered']} registered), "
        f"{d['path_length_m']:.0f} m in {d['duration_s']:.0f} s of driving, "
        f"{d['map_points']:,} map points "
        f"({result.map.crs or 'local frame, not georeferenced'})"
    )
    console.print(
        f"  compute {t['total_wall_s']:.1f} s wall, {t['total_cpu_s']:.1f} s CPU "
        f"({d['duration_s'] / max(t['total_wall_s'], 1e-9):.1f}x real time)"
    )
    skipped = d.get("odometry_map_skipped")
    if skipped:
        setting = skipped["setting"]
        setting = str(setting).lower() if isinstance(setting, bool) else setting
        console.print(
            "  unregistered sweeps in the odometry's local map: "
            f"{'on' if skipped['on'] else 'off'} ({setting}: {skipped['reason']})"
        )
    if evaluation is not None:
        e = evaluation
        console.print(
            f"  ATE {100 * e['ate_rmse_m']:.1f} cm (SE(3)-aligned), drift "
            f"{e['drift_percent']:.2f} % of segment length, end drift "
            f"{e['end_drift_percent']:.2f} % of path"
        )
        if "map_aligned" in e:
            m = e["map_aligned"]
            console.print(
                f"  map vs true surfaces: median {100 * m['median_m']:.1f} cm, "
                f"90 % within {100 * m['p90_m']:.1f} cm"
            )
        if "georeferenced" in e:
            console.print(
                f"  georeferencing error (no alignment): {e['georeferenced']['rmse_m']:.2f} m RMS"
            )
    for w in result.warnings:
        console.print(f"  [yellow]warning[/]: {w}")
    for name, path in paths.items():
        console.print(f"  {name}: {path}")
