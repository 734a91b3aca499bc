"""``canopy-kit demo``: simulate a pistachio and an almond session and run everything on both."""

from __future__ import annotations

from pathlib import Path

import typer

DEMO_SESSIONS = {
    "pistachio": {"orchard": {"rows": 2, "trees_per_row": 5}},
    "almond": {"orchard": {"rows": 2, "trees_per_row": 6}},
}


def demo(
    out: Path = typer.Option(Path("out/demo"), "--out", help="Output folder"),
    seed: int = typer.Option(7, help="Simulation seed"),
    preset: str = typer.Option("adaptive", help="Pipeline preset for both orchards"),
    drone: bool = typer.Option(
        True, "--drone/--no-drone", help="Simulate and process drone photos"
    ),
) -> None:
    """The end-to-end demo: simulated sessions → pipeline → validated HTML reports."""
    from canopy_kit.cli.common import console, output_folder, progress_bar
    from canopy_kit.cli.run import print_results
    from canopy_kit.config import load_preset
    from canopy_kit.io.session_layout import drone_dir as drone_folder
    from canopy_kit.io.session_layout import find_bag, truth_dir
    from canopy_kit.pipeline import run as run_pipeline
    from canopy_kit.sim import load_sim_config, simulate_session

    reports = []
    with output_folder(out):
        for orchard, overrides in DEMO_SESSIONS.items():
            sim_dir = out / f"{orchard}_session"
            run_dir = out / f"{orchard}_run"
            console.rule(f"{orchard}")
            if not (truth_dir(sim_dir) / "trees.csv").exists() or not _has_bag(sim_dir):
                cfg = load_sim_config(
                    orchard, {**overrides, "seed": seed, "drone": {"enabled": drone}}
                )
                with progress_bar(transient=True) as progress:
                    simulate_session(sim_dir, cfg, overwrite=True, progress=progress)
                console.print(f"simulated {sim_dir}")
            else:
                console.print(f"reusing simulated session {sim_dir}")
            drone_dir = drone_folder(sim_dir) if drone and drone_folder(sim_dir).is_dir() else None
            with progress_bar(transient=True) as progress:
                results = run_pipeline(
                    load_preset(preset),
                    find_bag(sim_dir),
                    run_dir,
                    drone_images=drone_dir,
                    truth=sim_dir,
                    progress=progress,
                    orchard=f"simulated {orchard} orchard (seed {seed})",
                )
            print_results(results)
            reports.append(results.files["report.html"])
    console.rule("reports")
    for r in reports:
        console.print(f"[bold]{r.resolve()}")


def _has_bag(sim_dir: Path) -> bool:
    from canopy_kit.errors import InputError
    from canopy_kit.io.session_layout import find_bag

    try:
        find_bag(sim_dir)
        return True
    except InputError:
        return False
