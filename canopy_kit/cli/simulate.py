"""``canopy-kit simulate``: write a simulated orchard field session."""

from __future__ import annotations

from pathlib import Path

import typer


def simulate(
    out: Path = typer.Argument(..., help="Output folder for the session"),
    orchard: str = typer.Option(
        "pistachio",
        help="Orchard preset (pistachio, almond, almond-paper, fruiting-wall) or a TOML file",
    ),
    rows: int = typer.Option(None, help="Number of tree rows"),
    trees_per_row: int = typer.Option(None, "--trees-per-row", help="Trees per row"),
    seed: int = typer.Option(0, help="Random seed (same seed, same session)"),
    fmt: str = typer.Option("ros2-mcap", "--format", help="ros1, ros2-sqlite3 or ros2-mcap"),
    sensor: str = typer.Option(
        None, help="Sensor model: vlp16, hdl32, os0-32, os1-64, os1-128, livox-mid360, livox-avia"
    ),
    drone: bool = typer.Option(False, "--drone", help="Also render a drone photo flight"),
    no_truth_field: bool = typer.Option(
        False, "--no-truth-field", help="Do not add the per-point tree_id field"
    ),
    gnss_mode: str = typer.Option(None, "--gnss", help="standard or rtk"),
    rig: str = typer.Option(
        None,
        "--rig",
        help="Sensor rig: identity (one frame, the default), tower, "
        "imu-flipped, yawed-lever, side-tilt, or a rig file (TOML)",
    ),
    no_tf_static: bool = typer.Option(
        False, "--no-tf-static", help="Leave the rig's /tf_static out of the bag"
    ),
    pcap: bool = typer.Option(
        False,
        "--pcap",
        help="VLP-16 raw packets, also written as capture/drive.pcap with GNSS tracks "
        "(MTLS text, CSV, NMEA, GPX) for: run DRIVE.pcap --gnss TRACK",
    ),
    set_: list[str] = typer.Option([], "--set", help="Override any parameter: section.key=value"),
    overwrite: bool = typer.Option(False, help="Replace a non-empty output folder"),
) -> None:
    """Simulate an orchard drive (LiDAR, IMU, GNSS bag) with per-tree truth."""
    from canopy_kit.cli.common import console, output_folder, parse_overrides, progress_bar
    from canopy_kit.sim import load_sim_config, simulate_session

    overrides = parse_overrides(set_)
    overrides["seed"] = seed
    o = overrides.setdefault("orchard", {})
    if rows is not None:
        o["rows"] = rows
    if trees_per_row is not None:
        o["trees_per_row"] = trees_per_row
    if drone:
        overrides.setdefault("drone", {})["enabled"] = True
    if gnss_mode:
        overrides.setdefault("gnss", {})["mode"] = gnss_mode
    if rig:
        from canopy_kit.config.rig import rig_preset_names

        known = rig in rig_preset_names() or rig == "identity"
        overrides.setdefault("rig", {})["name"] = rig if known else str(Path(rig).resolve())
    if no_tf_static:
        overrides.setdefault("rig", {})["write_tf_static"] = False
    if pcap:  # a capture holds raw packets; the track comes in the LiDAR's frame
        overrides.setdefault("lidar", {}).update(output="velodyne_packets", frame_id="velodyne")
        overrides.setdefault("gnss", {})["frame_id"] = "velodyne"
        sensor = sensor or "vlp16"
    config = load_sim_config(orchard, overrides, sensor=sensor)
    with output_folder(out, option=None), progress_bar() as progress:
        session = simulate_session(
            out,
            config,
            fmt=fmt,
            truth_field=not no_truth_field,
            overwrite=overwrite,
            progress=progress,
        )
    if pcap:
        from canopy_kit.sim.pcap_drive import TRACK_FORMATS, export_pcap_drive

        files = export_pcap_drive(session.bag, Path(out) / "capture", TRACK_FORMATS)
        console.print(f"  capture: {files['pcap']} (tracks: {', '.join(TRACK_FORMATS)})")
    console.print(
        f"[green]simulated[/] {len(session.orchard.trees)} trees, {session.n_scans} scans, "
        f"{session.n_points:,} points, {session.trajectory.duration:.0f} s of driving\n"
        f"  bag:   {session.bag}\n  truth: {session.truth_dir}"
        + (f"\n  drone: {session.drone_dir}" if session.drone_dir else "")
    )
